"""Trace a nebula with the NebulaRT ParaView plugin and save two pictures (pvpython/pvbatch).

    source scripts/pv-env.sh
    pvpython plugin/examples/render_nebula.py --out out/           # needs an X display
    xvfb-run -a pvpython plugin/examples/render_nebula.py --out out/

Writes <out>/paraview-nebula-volume.png (the rgba volume with its star, the camera of
`nebula-rt render`) and <out>/paraview-sky-image.png (Nebula Sky Image: what a telescope sees
along -z). With the plugin loaded, ``Show`` alone gives these displays (the plugin's default
display); the helpers used here set the same explicitly.
The images in docs/images were made with: --out docs/images (64^3 voxels, 10^6 packets).
"""

import argparse
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))  # plugin/

from paraview import simple  # noqa: E402
from nebula_rt_paraview.view import (load_plugin, set_orbit_camera, show_rgba_volume, show_sky_image,  # noqa: E402
                                     show_stars)

ap = argparse.ArgumentParser()
ap.add_argument("--out", default=".")
ap.add_argument("--grid", type=int, default=64)
ap.add_argument("--photons", type=int, default=1_000_000)
ap.add_argument("--device", default="", help='e.g. "NVIDIA" or "Portable Computing Language" (default: automatic)')
args = ap.parse_args()
os.makedirs(args.out, exist_ok=True)

load_plugin()  # a no-op when PV_PLUGIN_PATH already loaded it

# one star (x, y, z, luminosity, temperature K, bump radius) at the centre of the box
star = [0.5, 0.5, 0.5, 1.0, 20000.0, 0.01]
dust = simple.NebulaDustDensity(GridShape=[args.grid] * 3, Model="turbulence", Scale=0.15,
                                Offset=[0.5, 0.5, 0.5], Stars=star, Device=args.device)
# pass the input positionally: paraview.simple then picks the density array from it
light = simple.NebulaLightField(dust, Stars=star, Tau=128.0, Photons=args.photons,
                                BandPreset="thesis-rgb", OverrideOptics=1, Albedo=0.6, G=0.6, Device=args.device)
light.DensityArray = ["POINTS", "density"]  # explicit is better (and what states store)
colour = simple.NebulaColour(light, WhitePoint="D65")

view = simple.CreateView("RenderView")
view.ViewSize = [800, 800]
view.OrientationAxesVisibility = 0
if "UseColorPaletteForBackground" in view.ListProperties():  # ParaView >= 5.10
    view.UseColorPaletteForBackground = 0
view.Background = [0.0, 0.0, 0.0]
show_rgba_volume(colour, view)
show_stars(light, view)  # the light field's second output: a point per star, drawn over the volume
simple.Render(view)  # paraview.simple resets the camera on the first render
set_orbit_camera(view, azimuth=30.0, elevation=20.0)
simple.SaveScreenshot(os.path.join(args.out, "paraview-nebula-volume.png"), view, ImageResolution=[800, 800])

sky = simple.NebulaSkyImage(light, ViewDirection=[0.0, 0.0, -1.0], ViewUp=[0.0, 1.0, 0.0], ImageSize=[320, 320],
                         Extent=1.1)
sky_view = simple.CreateView("NebulaSkyView")  # the plugin's 2D view: black, parallel projection
sky_view.ViewSize = [600, 600]
show_sky_image(sky, sky_view)
simple.Render(sky_view)
simple.SaveScreenshot(os.path.join(args.out, "paraview-sky-image.png"), sky_view, ImageResolution=[600, 600])

for p in (light, colour, sky):
    err = p.GetClientSideObject().last_error  # errors do not raise in pvpython: check
    if err:
        raise SystemExit(err)
print("wrote", os.path.join(args.out, "paraview-nebula-volume.png"), "and paraview-sky-image.png")
