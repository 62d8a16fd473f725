"""The TRUST I slab (Gordon et al. 2017, A&A 603, A114) as a NebulaRT scene, and its oracle.

The benchmark: a box of 10 pc, a uniform slab filling its lower 3 pc (z from -5 to -2 pc), a
star at (0, 0, 4) pc, observers far away at polar angles 0, 30, ..., 180 degrees in the y-z
plane (phi = 90). Here the box is [0, 1]^3 (1 = 10 pc): the slab is z < 0.3, the star at
(0.5, 0.5, 0.9); the slab's faces fall on voxel faces, so the voxel grid holds it exactly. The
dust: Milky Way R_V = 3.1 (Draine 2003, NebulaRT's own tables) at single wavelengths, in place
of TRUST's BARE-GR-S mix (the question here is transport, not the dust model), with the slab's
vertical optical depth 10 at 550 nm; wavelengths whose vertical depth passes 35 are left out,
as the benchmark target asks.

The reference is tests/oracles/slab_mc.py: scattered power per steradian towards each observer.
NebulaRT's is its peel-off image's total times the pixel area over the band's luminosity.
"""

from __future__ import annotations

import math

import numpy as np

from nebula_rt.optics.bands import Band
from nebula_rt.optics.dust_tables import draine_table
from nebula_rt.scene import Star
from nebula_rt.observe.sky import Camera
from oracles.slab_mc import BoxSlab

#: slab top (box units: 3 pc of 10), star height, vertical optical depth at 550 nm
SLAB_TOP = 0.3
STAR = (0.5, 0.5, 0.9)
TAU_V = 10.0
#: the benchmark's observers: polar angles (degrees) in the y-z plane
ANGLES = (0.0, 30.0, 60.0, 90.0, 120.0, 150.0, 180.0)
#: wavelengths (nm): ultraviolet to near infrared, as TRUST's SED grid spans it
WAVELENGTHS = (150.0, 175.0, 217.5, 250.0, 300.0, 365.0, 440.0, 550.0, 700.0, 900.0, 1250.0, 1650.0, 2200.0)
#: the target's range: vertical optical depths up to 35
MAX_TAU_Z = 35.0
#: the voxel grid (the slab is its lowest 3 of 10 layers)
SHAPE = (8, 8, 10)


def dust(wavelength_nm: float) -> tuple[float, float, float]:
    """(extinction relative to 550 nm, albedo, g) of the Milky Way dust at one wavelength."""
    t = draine_table("3.1")
    wl = t["wavelength_nm"]
    c = np.interp(wavelength_nm, wl, t["cext"]) / np.interp(550.0, wl, t["cext"])
    return float(c), float(np.interp(wavelength_nm, wl, t["albedo"])), float(np.interp(wavelength_nm, wl, t["g"]))


def wavelengths(max_tau_z: float = MAX_TAU_Z) -> list[float]:
    """The benchmark's wavelengths whose vertical optical depth is at most ``max_tau_z``."""
    return [w for w in WAVELENGTHS if TAU_V * dust(w)[0] <= max_tau_z]


def scene(wls):
    """(density, bands, stars, tau) of the slab for the wavelengths ``wls`` (nm)."""
    rho = np.zeros(SHAPE, np.float32)
    rho[:, :, : round(SLAB_TOP * SHAPE[2])] = 1.0
    bands = []
    for w in wls:
        ext, alb, g = dust(w)
        bands.append(Band(name=f"{w:g}nm", wavelength=w, extinction=ext, albedo=alb, g=g))
    stars = [Star(position=STAR, luminosity=1.0, temperature=None, bump_radius=0.0)]
    return rho, bands, stars, TAU_V / SLAB_TOP


def observer(angle_deg: float) -> np.ndarray:
    """Unit vector from the slab towards the observer at polar angle ``angle_deg`` (phi = 90)."""
    t = math.radians(angle_deg)
    return np.array([0.0, math.sin(t), math.cos(t)])


def camera(angle_deg: float, pixels: int = 8) -> Camera:
    """A peel-off camera of the whole box seen from the observer (x is the image's up: it is
    perpendicular to every observer of the benchmark)."""
    return Camera(direction=tuple(-observer(angle_deg)), up=(1.0, 0.0, 0.0), size=(pixels, pixels), extent=1.8,
                  center=(0.5, 0.5, 0.5))


def oracle_slab(wavelength_nm: float) -> BoxSlab:
    ext, alb, g = dust(wavelength_nm)
    return BoxSlab(kappa=TAU_V * ext / SLAB_TOP, albedo=alb, g=g, h=SLAB_TOP, star=STAR)


def scattered_per_sr(result, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(scattered power per steradian over the band's luminosity, its batch-means error) per
    band of a run with ``peel=cam, peel_bins=zeros``."""
    area = (cam.extent / cam.size[0]) ** 2
    lum = np.asarray(result.band_luminosity, np.float64)
    total = result.peel_image.reshape(lum.size, -1).sum(axis=1) * area / lum
    batches = result.peel_bin_batches[:, :, 0] * area / lum[None, :]
    m = batches.shape[0]
    return total, np.sqrt(batches.var(axis=0, ddof=1) * m)
