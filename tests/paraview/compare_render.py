"""Render the same light field in ParaView as ``nebula_rt.filters.render`` does with pyvista.

    pvpython compare_render.py OUT_DIR

Builds a small nebula (40^3 voxels, thesis-rgb, tau 128), writes the Nebula Colour output to
OUT_DIR/light.vti, reads that file back and renders its ``rgba`` with show_rgba_volume and the
orbit camera of nebula_rt.filters.render (azimuth 30, elevation 20, view angle 30, black background,
400 x 400) to OUT_DIR/paraview.png, and once more with the plain linear opacity ramp to
OUT_DIR/paraview-naive.png. The test renders light.vti with render_png_from_vti.
"""

import os
import sys

import _common
from paraview import simple
from nebula_rt_paraview.view import load_plugin, set_orbit_camera, show_rgba_volume

out = sys.argv[1]
size = [400, 400]
load_plugin()
dust = simple.NebulaDustDensity(GridShape=[40, 40, 40], Model="turbulence", Scale=0.15,
                                Offset=[0.5, 0.5, 0.5], Device=_common.TEST_DEVICE)
light = simple.NebulaLightField(dust, Photons=200000, Tau=128.0, Albedo=0.6, G=0.6,
                                Device=_common.TEST_DEVICE)
light.DensityArray = ["POINTS", "density"]
colour = simple.NebulaColour(light)
colour.UpdatePipeline()
vti = os.path.join(out, "light.vti")
simple.SaveData(vti, proxy=colour, PointDataArrays=["rgba", "density"])

reader = simple.XMLImageDataReader(FileName=[vti])
reader.PointArrayStatus = ["rgba", "density"]
view = simple.CreateView("RenderView")
view.ViewSize = size
view.OrientationAxesVisibility = 0
if "UseColorPaletteForBackground" in view.ListProperties():
    view.UseColorPaletteForBackground = 0
view.Background = [0.0, 0.0, 0.0]
show_rgba_volume(reader, view)
simple.Render(view)  # paraview.simple resets the camera on the first render: do it first
pos, focal, up = set_orbit_camera(view, azimuth=30.0, elevation=20.0)
simple.Render(view)
png = os.path.join(out, "paraview.png")
simple.SaveScreenshot(png, view, ImageResolution=size)

# the plain recipe for comparison (a fresh display: linear opacity ramp, ScalarOpacityUnitDistance = spacing):
# what one gets without the per-voxel opacity mapping
simple.Delete(simple.GetDisplayProperties(reader, view))
_common.plain_rgba_recipe(reader, view, 1.0 / 40)
simple.Render(view)
naive = os.path.join(out, "paraview-naive.png")
simple.SaveScreenshot(naive, view, ImageResolution=size)

_common.result(vti=vti, png=png, naive_png=naive, size=size, camera={"position": pos, "focal_point": focal, "view_up": up},
               error=colour.GetClientSideObject().last_error or light.GetClientSideObject().last_error)
