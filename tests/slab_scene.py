"""The thick-slab scene of the plane-parallel tests and benchmark, and what a run of it measures.

A uniform slab of ``layers`` voxel layers (of ``nz`` along z; the box is [0, 1]^3, so the slab
is layers / nz thick and 1 wide: a thin sheet, whose lateral edges are far in optical depth),
a star of luminosity 1 just above its top face (the slab is lit over all downward directions,
as an infinite slab by a point source), a peel-off camera below it looking up (the light the
slab transmits) or above it looking down (the light it reflects). The image's total times the
pixel area is the scattered power per steradian towards the camera, which the oracle
(tests/oracles/plane_parallel.py, :class:`PointSourceSlab`) gives for an infinite slab.
Laterally the grid is coarse: the slab is uniform there, and voxel crossings cost time.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from nebula_rt.optics.bands import Band
from nebula_rt.errors import NebulaWarning
from nebula_rt.scene import Star
from nebula_rt.observe.sky import Camera
from nebula_rt.transport import trace
from oracles.plane_parallel import PointSourceSlab, Slab

#: the slab's top face and the star's height above it (box units): light below mu0 = 2e-4
#: (0.02 % of the downward light) misses the 1-wide slab, and is left out of the oracle's
#: absorbed fraction by the same geometry
GAP = 1.0e-4


def slab(tau: float, *, nxy: int = 4, nz: int = 64, layers: int = 4, albedo: float = 0.6, g: float = 0.6,
         side: str = "below", image: int = 4):
    """(density, bands, stars, extinction per box unit, camera) of the slab of vertical
    optical depth ``tau``; ``side``: where the camera is ("below": transmission)."""
    rho = np.zeros((nxy, nxy, nz), np.float32)
    z0 = nz // 2 - layers
    rho[:, :, z0:z0 + layers] = 1.0
    kappa = tau * nz / layers
    top = (z0 + layers) / nz
    bands = [Band(name="V", wavelength=550.0, extinction=1.0, albedo=albedo, g=g)]
    stars = [Star(position=(0.5, 0.5, top + GAP), luminosity=1.0, temperature=None, bump_radius=0.0)]
    direction = (0.0, 0.0, 1.0) if side == "below" else (0.0, 0.0, -1.0)
    cam = Camera(direction=direction, size=(image, image), extent=1.5)
    return rho, bands, stars, kappa, cam


def image_power(result, camera) -> tuple[float, float]:
    """(power per steradian towards the camera, its batch-means standard error) of a run: the
    image total times the pixel area, and the error from the batch totals of the whole image
    (``trace(peel_bins=zeros)``)."""
    area = (camera.extent / camera.size[0]) ** 2
    total = float(result.peel_image[0].sum()) * area
    batches = result.peel_bin_batches[:, 0, 0] * area
    m = batches.size
    se = math.sqrt(batches.var(ddof=1) * m) if m > 1 else math.inf
    return total, se


def peel_bins(camera):
    return np.zeros(camera.size, np.int64)


def seeded_runs(backend, tau: float, albedo: float, g: float, *, seeds: int, photons: int, method: str = "auto",
                side: str = "below"):
    """Runs of the slab with seeds 1..``seeds`` (NebulaWarnings silenced: the callers judge the
    results against the exact answer): yields (result, image power, its standard error, the
    exact value, the oracle)."""
    rho, bands, stars, kappa, cam = slab(tau, albedo=albedo, g=g, side=side)
    oracle = PointSourceSlab(Slab(tau, albedo, g))
    exact = oracle.transmitted(1.0) if side == "below" else oracle.reflected(1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NebulaWarning)
        for seed in range(1, seeds + 1):
            r = trace(rho, bands, stars, tau=kappa, photons=photons, seed=seed, backend=backend, method=method,
                      peel=cam, peel_bins=peel_bins(cam), light_field=False)
            v, se = image_power(r, cam)
            yield r, v, se, exact, oracle
