"""Collision-filter smoothing: normalised convolution with the thesis's cubic kernel.

The thesis deposits packets at their interaction points and smooths the deposit with the
kernel (1 - d^2/r^2)^3 by FFT convolution (thesis section 3.2.3, listing A.2). We do the same
with two corrections: the kernel is normalised on the voxel lattice (sum = 1, so the total is
conserved exactly; the thesis divided by 4/3 pi r^3, which is not the kernel's integral), and
the convolution is normalised by the kernel weight inside the box (a uniform field stays
uniform up to the faces instead of darkening there). The filter trades noise for a bias that
grows with r: features narrower than r are smeared.
"""

from __future__ import annotations

import math

import numpy as np

from .array_api import array_module, fftconvolve_same


def kernel_half_widths(shape: tuple[int, int, int], radius: float) -> tuple[int, int, int]:
    """Voxels the kernel reaches on each side along x, y, z: floor(r / h), at most n - 1.

    A same-size convolution never pairs voxels further apart than n - 1, so the kernel beyond
    that is never used: cutting it there changes nothing in the normalised convolution (which
    divides by the same kernel's in-box weight) and bounds its memory whatever the radius.
    """
    h = 1.0 / np.asarray(shape, dtype=np.float64)
    return tuple(int(min(math.floor(radius / hh), n - 1)) for hh, n in zip(h, shape))


def cubic_kernel(shape: tuple[int, int, int], radius: float) -> np.ndarray:
    """The normalised kernel (1 - d^2/r^2)^3 on the voxel lattice of a grid of ``shape``.

    Parameters
    ----------
    shape : (nx, ny, nz)
        Grid shape; voxel edges are 1/nx, 1/ny, 1/nz box units.
    radius : float
        Kernel radius in box units. A radius under half a voxel gives the identity kernel.
    """
    h = 1.0 / np.asarray(shape, dtype=np.float64)
    half = kernel_half_widths(shape, radius)
    axes = [np.arange(-m, m + 1) * hh for m, hh in zip(half, h)]
    dx, dy, dz = np.meshgrid(*axes, indexing="ij")
    d2 = (dx * dx + dy * dy + dz * dz) / (radius * radius)
    k = np.where(d2 < 1.0, (1.0 - d2) ** 3, 0.0)
    return k / k.sum()


def normalised_convolution(field, kernel: np.ndarray, variance=None):
    """Convolve ``field`` with ``kernel`` inside the box, renormalised by the kernel weight there.

    Returns the filtered field and, if ``variance`` (per-voxel, independent voxels) is given,
    the variance of the filtered field: sum K^2 var / W^2. NumPy or CuPy arrays (the FFTs run
    on the array's device).
    """
    xp = array_module(field)
    if kernel.size == 1:
        return field.copy(), (None if variance is None else variance.copy())
    w = fftconvolve_same(xp, xp.ones_like(field), kernel)
    w = xp.maximum(w, 1e-300)
    out = xp.maximum(fftconvolve_same(xp, field, kernel), 0.0) / w
    var = None
    if variance is not None:
        var = xp.maximum(fftconvolve_same(xp, variance, kernel * kernel), 0.0) / (w * w)
    return out, var
