"""A calibrated sky image from the NebulaRT ParaView plugin, saved as FITS (pvpython/pvbatch).

    source scripts/pv-env.sh
    pvpython plugin/examples/sky_fits.py --out out/merope.fits

A Merope-like nebula (examples/scenes/merope-sky.toml in the panel's terms): a 14,000 K star of
718 L_sun (Luminosity Unit L_sun) in a 0.5 pc box (Box Length) of thin turbulent dust, seen from
136 pc at (RA, Dec) = (56.58, +23.95) deg through a 2 arcsec PSF. Nebula Sky Image with Units
"MJy/sr" adds ``sb_<band>`` (MJy/sr) and ``mag_<passband>`` (AB mag/arcsec^2) with the celestial
WCS; ``SaveData(".fits")`` writes them through the plugin's writer (one extension per band and
per passband). Prints the FITS file's extensions and the V surface brightness range.
"""

import argparse
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))  # plugin/

from paraview import simple  # noqa: E402
from nebula_rt_paraview.view import load_plugin  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--out", default="sky.fits")
ap.add_argument("--grid", type=int, default=64)
ap.add_argument("--photons", type=int, default=1_000_000)
ap.add_argument("--size", type=int, default=256)
ap.add_argument("--device", default="", help='e.g. "NVIDIA" or "Portable Computing Language" (default: automatic)')
args = ap.parse_args()

load_plugin()

star = [0.5, 0.5, 0.5, 718.0, 14000.0, 0.0]  # x, y, z, luminosity (L_sun: LuminosityUnit 1), T (K), bump
dust = simple.NebulaDustDensity(GridShape=[args.grid] * 3, Model="turbulence", Scale=0.15, Floor=0.002,
                                Stars=star, Device=args.device)
light = simple.NebulaLightField(dust, Stars=star, Tau=2.0, BandPreset="spectral-8", Photons=args.photons,
                                Device=args.device)
light.DensityArray = ["POINTS", "density"]
light.LuminosityUnit = "L_sun"
light.BoxLength = 0.5  # pc (grid.unit)
sky = simple.NebulaSkyImage(light, ViewDirection=[0.0, 0.0, -1.0], ImageSize=[args.size, args.size],
                            Units="MJy/sr", Distance="136 pc", RA=56.5815, Dec=23.9484, PositionAngle=0.0,
                            PSFFWHM=2.0, Stretch="asinh")
simple.SaveData(args.out, proxy=sky)

from astropy.io import fits  # noqa: E402  (in the .venv-pv of scripts/setup.sh)

with fits.open(args.out) as hdul:
    print([h.name for h in hdul])
    v = hdul["MAG_BESSELL_V"].data
    print(f"V: {float(v[v == v].min()):.2f} to {float(v[v == v].max()):.2f} mag/arcsec^2; "
          f"pixel {hdul[0].header['PIXSCALE']:.3f} arcsec")
