"""A NebulaRT pipeline in the ParaView GUI, to start from:

    source scripts/pv-env.sh
    paraview --script=plugin/examples/gui_demo.py

Makes Nebula Dust Density -> Nebula Light Field -> Nebula Colour, shows the colour (the
plugin's default display: the rgba volume with the light field's stars) with the camera of
`nebula-rt render`, and selects the light field so its properties are in the panel. The same
pipeline made from the menus with Apply shows the same (tests/paraview/test_paraview_gui.py; the
screenshot docs/images/paraview-gui.png is that test's).
"""

import os
import sys

if "__file__" in globals():  # (the GUI's --script runs without __file__: the plugin, loaded
    # from PV_PLUGIN_PATH, has put plugin/ on sys.path already)
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from paraview import simple  # noqa: E402
from nebula_rt_paraview.view import set_orbit_camera  # noqa: E402

dust = simple.NebulaDustDensity(registrationName="Nebula Dust Density1", GridShape=[48, 48, 48])
# the density made before the light field is: the light field's Density Array box lists the
# arrays its input has when the panel is made (made on an input not yet run, it stays empty)
dust.UpdatePipeline()
light = simple.NebulaLightField(dust, registrationName="Nebula Light Field1", Photons=300000)
light.DensityArray = ["POINTS", "density"]
colour = simple.NebulaColour(light, registrationName="Nebula Colour1")
view = simple.GetActiveViewOrCreate("RenderView")
view.OrientationAxesVisibility = 0
simple.Show(colour, view)  # the plugin sets up the volume (and a black background) at the render
simple.Show(simple.OutputPort(light, 1), view)  # the stars
simple.Render(view)
set_orbit_camera(view)
simple.SetActiveSource(light)
simple.Render(view)
