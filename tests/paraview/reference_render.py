"""The GUI test's reference: the default pipeline shown with the pvpython helpers.

    pvpython reference_render.py VIEW.json OUT.png [--defaults]

Nebula Dust Density and Nebula Light Field with their default properties (Device pinned to
the test device; Tau 128 and the thesis's 20 000 K star as the GUI test's user settings, or
nothing else with ``--defaults``), shown with show_rgba_volume and show_stars in a render view of the size,
camera and background that VIEW.json (one view of gui_probe.py's record) gives. With the
plugin loaded, its display behaviour is installed too; the helpers set everything it would.
With ``--defaults`` also OUT-own-opacity.png: the same data through a Nebula Colour with Auto
Opacity off (Opacity Scale 1, the dust's own opacity), shown instead of the light field.
RESULT: the PNG(s) and the light field's last error.
"""

import json
import sys

import _common
from paraview import simple
from nebula_rt_paraview.view import load_plugin, show_rgba_volume, show_stars

spec = json.load(open(sys.argv[1]))
png = sys.argv[2]
load_plugin()
if sys.argv[3:] == ["--defaults"]:
    dust = simple.NebulaDustDensity(Device=_common.TEST_DEVICE)
    light = simple.NebulaLightField(dust, Device=_common.TEST_DEVICE)
else:  # as the GUI test's settings
    dust = simple.NebulaDustDensity(Device=_common.TEST_DEVICE, Stars=[0.5, 0.5, 0.5, 1.0, 20000.0, 0.01])
    light = simple.NebulaLightField(dust, Device=_common.TEST_DEVICE, Tau=128.0)
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
own = own_error = own_alpha = None
if sys.argv[3:] == ["--defaults"]:
    colour = simple.NebulaColour(light, AutoOpacity=0, OpacityScale=1.0)
    simple.Hide(light, view)
    show_rgba_volume(colour, view)
    simple.Render(view)
    own = png.replace(".png", "-own-opacity.png")
    simple.SaveScreenshot(own, view, ImageResolution=spec["size"])
    own_error = colour.GetClientSideObject().last_error
    own_alpha = list(colour.PointData["rgba"].GetRange(3))
_common.result(png=png, own_opacity_png=own, own_opacity_error=own_error, own_opacity_alpha=own_alpha,
               error=light.GetClientSideObject().last_error)
