"""The GUI test's reference: the default pipeline shown with the pvpython helpers.

    pvpython reference_render.py VIEW.json OUT.png

Nebula Dust Density and Nebula Light Field with their default properties (the thesis's
nebula; only the Device pinned to the test device, as the GUI test's user settings do),
shown with show_rgba_volume and show_stars in a render view of the size, camera and
background that VIEW.json (one view of gui_probe.py's record) gives. With the plugin loaded,
its display behaviour is installed too; the helpers set everything it would.
RESULT: the PNG and the light field's last error.
"""

import json
import sys

import _common
from paraview import simple
from nebula_rt_paraview.view import load_plugin, show_rgba_volume, show_stars

spec = json.load(open(sys.argv[1]))
png = sys.argv[2]
load_plugin()
dust = simple.NebulaDustDensity(Device=_common.TEST_DEVICE)
light = simple.NebulaLightField(dust, Device=_common.TEST_DEVICE)
light.DensityArray = ["POINTS", "density"]
view = simple.CreateView("RenderView")
view.ViewSize = spec["size"]
view.UseColorPaletteForBackground = 0
view.Background = spec["Background"]
show_rgba_volume(light, view)
show_stars(light, view)
simple.Render(view)  # (the first render resets the camera: set it after)
view.CameraPosition = spec["CameraPosition"]
view.CameraFocalPoint = spec["CameraFocalPoint"]
view.CameraViewUp = spec["CameraViewUp"]
view.CameraViewAngle = spec["CameraViewAngle"]
view.CameraParallelProjection = int(spec["CameraParallelProjection"])
view.CameraParallelScale = spec["CameraParallelScale"]
simple.Render(view)
simple.SaveScreenshot(png, view, ImageResolution=spec["size"])
_common.result(png=png, error=light.GetClientSideObject().last_error)
