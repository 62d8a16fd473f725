"""A NebulaRT pipeline in the ParaView GUI, to start from:

    source scripts/pv-env.sh
    paraview --script=plugin/examples/gui_demo.py

Makes Nebula Dust Density -> Nebula Light Field -> Nebula Colour, shows the colour as an rgba
volume (show_rgba_volume) with the camera of `nebula-rt render`, and selects the light field
so its properties are in the panel. (docs/images/paraview-gui.png is this, on Xvfb with
`-geometry 1280x1024+0+0`, grabbed with PIL.ImageGrab.grab(xdisplay=...).)
"""

import os
import sys

if "__file__" in globals():  # (the GUI's --script runs without __file__: the plugin, loaded
    # from PV_PLUGIN_PATH, has put plugin/ on sys.path already)
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from paraview import simple  # noqa: E402
from nebula_rt_paraview.view import set_orbit_camera, show_rgba_volume  # noqa: E402

dust = simple.NebulaDustDensity(registrationName="Nebula Dust Density1", GridShape=[48, 48, 48])
light = simple.NebulaLightField(dust, registrationName="Nebula Light Field1", Photons=300000)
light.DensityArray = ["POINTS", "density"]
colour = simple.NebulaColour(light, registrationName="Nebula Colour1")
view = simple.GetActiveViewOrCreate("RenderView")
view.OrientationAxesVisibility = 0
if "UseColorPaletteForBackground" in view.ListProperties():
    view.UseColorPaletteForBackground = 0
view.Background = [0.0, 0.0, 0.0]
show_rgba_volume(colour, view)
simple.Render(view)
set_orbit_camera(view)
simple.SetActiveSource(light)
simple.Render(view)
