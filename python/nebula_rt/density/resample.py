"""Voxel averages of a piecewise-constant field given on axis-aligned boxes, by exact overlap.

An adaptive grid (an octree's leaves, the visible cells of AMR blocks, a particle deposit on a
tree) is a set of disjoint axis-aligned boxes, each with a constant density. Its average over
a voxel of a uniform grid is

    rho_v = sum over boxes b of rho_b |b ∩ v| / |v|,

exact for the piecewise-constant field: the mass sum_v rho_v |v| equals sum_b rho_b |b| (to
float64 rounding) whatever the two resolutions, a box finer than a voxel adds its share to
the one or few voxels it overlaps, and a coarser one spreads its value over the voxels it
covers. This is how the uniform light field for the volume mapper and the colour stage is to
be made from an adaptive one, and how an adaptive density compares with a uniform one.

The overlap of a box with a voxel is the product of three 1-D overlaps, so each box's
contributions are an outer product of per-axis overlap lengths; boxes are handled in groups
of equal per-axis voxel spans (an octree level makes a few such groups), each group in one
vectorised scatter-add.
"""

from __future__ import annotations

import numpy as np

__all__ = ["box_averages"]


def _axis_overlaps(lo, hi, n: int):
    """Per box, the first voxel index along one axis and the overlap lengths (box units) with
    that voxel and the following ones: (first (k,), lengths (k, span)), span the largest
    number of voxels a box of the group meets."""
    h = 1.0 / n
    first = np.clip(np.floor(lo * n).astype(np.int64), 0, n - 1)
    last = np.clip(np.ceil(hi * n).astype(np.int64) - 1, 0, n - 1)
    last = np.maximum(last, first)
    span = int((last - first).max(initial=0)) + 1
    idx = first[:, None] + np.arange(span)[None, :]
    # voxel faces as multiples of h (not sums of h): the same faces for every box
    lengths = np.minimum(hi[:, None], (idx + 1) * h) - np.maximum(lo[:, None], idx * h)
    lengths = np.where(idx <= last[:, None], np.maximum(lengths, 0.0), 0.0)
    return first, lengths


def box_averages(lo, hi, values, shape) -> np.ndarray:
    """The voxel averages on a uniform grid of ``shape`` over the unit box of a field that is
    ``values[b]`` on box b = [lo[b], hi[b]) (box units) and 0 elsewhere.

    Parameters
    ----------
    lo, hi : array_like (n, 3)
        The boxes' low and high corners, box units, inside [0, 1]^3, lo < hi; the boxes must
        not overlap (not checked: overlapping boxes add).
    values : array_like (n,)
        The field on each box (any unit; the averages are in the same unit).
    shape : (nx, ny, nz)

    Returns
    -------
    ndarray float64 (nx, ny, nz)
        Index [i, j, k] is the voxel [i/nx, (i+1)/nx) x ...; sum(avg) / (nx ny nz) equals
        sum(values x box volumes) to rounding.
    """
    lo = np.asarray(lo, np.float64).reshape(-1, 3)
    hi = np.asarray(hi, np.float64).reshape(-1, 3)
    v = np.asarray(values, np.float64).reshape(-1)
    shape = tuple(int(s) for s in shape)
    if not (lo.shape == hi.shape and len(v) == len(lo)):
        raise ValueError(f"lo {lo.shape}, hi {hi.shape} and values {v.shape} must describe the same boxes")
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"shape must be 3 positive sizes, got {shape}")
    if len(v) and not (np.all(lo >= 0.0) and np.all(hi <= 1.0) and np.all(lo < hi)):
        raise ValueError("every box must lie inside the unit box with lo < hi")
    out = np.zeros(int(np.prod(shape)), np.float64)
    if not len(v):
        return out.reshape(shape)
    n = np.array(shape)
    # group the boxes by their extent in voxels per axis (a tree level gives one or two)
    spans = np.stack([np.ceil(hi[:, a] * n[a]) - np.floor(lo[:, a] * n[a]) for a in range(3)], axis=1).astype(np.int64)
    keys, group = np.unique(spans, axis=0, return_inverse=True)
    voxel = 1.0 / float(np.prod(n))
    for g in range(len(keys)):
        sel = np.flatnonzero(group.reshape(-1) == g)
        (fx, ox), (fy, oy), (fz, oz) = (_axis_overlaps(lo[sel, a], hi[sel, a], shape[a]) for a in range(3))
        w = (v[sel, None, None, None] * ox[:, :, None, None] * oy[:, None, :, None] * oz[:, None, None, :]) / voxel
        ix = np.minimum(fx[:, None] + np.arange(ox.shape[1]), shape[0] - 1)
        iy = np.minimum(fy[:, None] + np.arange(oy.shape[1]), shape[1] - 1)
        iz = np.minimum(fz[:, None] + np.arange(oz.shape[1]), shape[2] - 1)
        # flat index of voxel [i, j, k] in C order of shape (nx, ny, nz)
        flat = (ix[:, :, None, None] * shape[1] + iy[:, None, :, None]) * shape[2] + iz[:, None, None, :]
        out += np.bincount(flat.reshape(-1), weights=w.reshape(-1), minlength=out.size)
    return out.reshape(shape)
