"""Transport through an adaptive density on the device: analog packets walking from leaf to
leaf of a :class:`nebula_rt.density.octree.Octree` (``kernels/tree.cl``), the track-length
estimate of J per leaf.

The first piece of the transport on trees (docs/adaptive_grids.md): one launch, one batch, a
peel-off image on request, no error estimate, no progress or cancel yet. The packets draw their random numbers
as the uniform grid's analog packets do, so on a tree whose leaves are a grid's voxels they fly
the same paths (``tests/transport/test_tree_transport.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..density.octree import Octree
from .plan import FIXED_POINT_BITS, star_band_luminosities
from .estimate import _peel_camera, _peel_scale
from .result import exact_packet_energy

__all__ = ["TreeLight", "trace_tree"]


@dataclass
class TreeLight:
    """J per leaf of a tree trace.

    Attributes
    ----------
    J : ndarray float64 (n_bands, n_leaves)
        Mean intensity per leaf (luminosity per box-unit area per steradian), as the uniform
        grid's ``TransportResult.J`` per voxel.
    counts : ndarray int64 (n_bands, 4)
        Packets emitted, absorbed, escaped, terminated.
    packet_energy : ndarray (n_bands,)
    track_scale : float
        Fixed-point units per box unit of path.
    peel_image : ndarray (n_bands, W, H) or None
        With ``trace_tree(peel=camera)``: luminosity per box-unit area per steradian.
    """

    J: np.ndarray
    counts: np.ndarray
    packet_energy: np.ndarray
    track_scale: float
    peel_image: Optional[np.ndarray] = None


def trace_tree(tree: Octree, bands, stars, *, tau: float, photons: int, backend, seed: int = 1,
               max_scatterings: int = 1000, peel=None) -> TreeLight:
    """Trace ``photons`` analog packets per band through ``tree`` (densities per leaf; the
    extinction per box unit is tau x extinction_b x density) from ``stars``; returns
    :class:`TreeLight`. The fixed-point scale keeps every leaf's sum below 2^63 whatever the
    packets do (a packet crosses a leaf at most max_scatterings + 1 times, each at most its
    diagonal, sqrt(3) box units). ``peel`` (a :class:`nebula_rt.observe.sky.Camera`): also the
    peel-off image (``TreeLight.peel_image``, as ``TransportResult.peel_image``), its optical
    depths marched leaf by leaf."""
    n = int(photons)
    if n < 1 or int(max_scatterings) < 0:
        raise ValueError(f"photons must be >= 1 and max_scatterings >= 0, got {photons!r}, {max_scatterings!r}")
    wl = np.array([b.wavelength for b in bands], np.float64)
    slum = star_band_luminosities(stars, wl)
    band_lum = slum.sum(axis=0)
    cdf = np.cumsum(slum, axis=0) / band_lum[None, :]
    cdf[-1, :] = 1.0
    nb = len(bands)
    optics = np.zeros((nb, 4), np.float32)
    optics[:, 0] = [tau * b.extinction for b in bands]
    optics[:, 1] = [b.albedo for b in bands]
    optics[:, 2] = [b.g for b in bands]
    stars4 = np.zeros((len(stars), 4), np.float32)
    stars4[:, :3] = [s.position for s in stars]
    cells = max(tree.roots) * 2 ** tree.depth()
    scale = min(2.0 ** FIXED_POINT_BITS * cells, 2.0 ** 62 / (n * (int(max_scatterings) + 1) * math.sqrt(3.0)))
    scale = float(2.0 ** math.floor(math.log2(scale)))  # a power of 2: x scale is exact in float32
    be = backend
    d_acc = be.device_zeros(nb * tree.n_leaves, np.uint64)
    d_tally = be.device_zeros(nb * 4, np.uint64)
    rx, ry, rz = tree.roots
    if peel is not None:
        cam = _peel_camera(peel)
        peel_scale = _peel_scale([b.g for b in bands])
        w, hgt = peel.size
        d_image = be.device_zeros(nb * w * hgt, np.uint64)
    else:
        cam, peel_scale, d_image = np.zeros(15, np.float32), 0.0, be.device_zeros(1, np.uint64)
    be.launch("tree.cl", "trace_tree", n * nb,
              be.to_device(np.ascontiguousarray(tree.child, np.int32)), be.to_device(np.ascontiguousarray(tree.density, np.float32)),
              np.int32(rx), np.int32(ry), np.int32(rz), be.to_device(optics), be.to_device(stars4),
              be.to_device(np.ascontiguousarray(cdf.T, np.float32)), np.int32(len(stars)), np.uint64(seed),
              np.uint64(0), np.uint64(n), np.int32(nb), np.int32(max_scatterings), np.float32(scale),
              np.uint64(tree.n_leaves), d_acc, d_tally, be.to_device(cam), np.float32(peel_scale), d_image,
              defines={"NRT_PEEL": int(peel is not None)})
    sums = be.to_host(d_acc).reshape(nb, tree.n_leaves).astype(np.float64)
    counts = be.to_host(d_tally).reshape(nb, 4).astype(np.int64)
    q = np.array([exact_packet_energy(L, n) for L in band_lum])
    lo, hi, _ = tree.leaves()
    vol = np.prod(hi - lo, axis=1)
    J = sums * (q / (scale * 4.0 * math.pi))[:, None] / vol[None, :]
    image = None
    if peel is not None:  # packet energy x (phase x attenuation) per pixel area, as estimate_light
        units = be.to_host(d_image).reshape(nb, w, hgt).astype(np.float64)
        image = units * (q / (peel_scale * peel.pixel_size ** 2))[:, None, None]
    return TreeLight(J=J, counts=counts, packet_energy=q, track_scale=scale, peel_image=image)
