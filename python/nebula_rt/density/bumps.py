"""The stars' dust bumps (thesis Eq. 3.3): what the density kernel averages over voxels,
averaged over a tree's leaves."""

from __future__ import annotations

import numpy as np

__all__ = ["BUMP_SUBSAMPLES", "leaf_bumps", "stars_array"]

#: Midpoint samples per axis used to average a star's bump over a voxel.
BUMP_SUBSAMPLES = 8


def stars_array(stars) -> np.ndarray:
    """(n, 4) float32: each star's x, y, z (box units) and bump radius, as the kernels take them."""
    return np.array([[*s.position, s.bump_radius] for s in stars], dtype=np.float32).reshape(-1, 4)



def leaf_bumps(lo, hi, stars, subsamples: int = BUMP_SUBSAMPLES) -> np.ndarray:
    """The stars' cubic bumps (1 - d^2 / r^2)^3 (thesis Eq. 3.3) averaged over boxes [lo, hi)
    (a tree's leaves) with ``subsamples``^3 midpoint samples, as ``kernels/density.cl``
    averages them over voxels (here in float64); boxes the bump cannot reach stay 0.
    ``stars``: (n, 4) x, y, z, radius."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    out = np.zeros(len(lo))
    t = (np.arange(subsamples) + 0.5) / subsamples
    for sx, sy, sz, r in np.asarray(stars, np.float64).reshape(-1, 4):
        if not r > 0:
            continue
        s = np.array([sx, sy, sz])
        near = np.sum((np.clip(s, lo, hi) - s) ** 2, axis=1) < r * r
        for i in np.flatnonzero(near):
            axes = [lo[i, a] + t * (hi[i, a] - lo[i, a]) - s[a] for a in range(3)]
            d2 = axes[0][:, None, None] ** 2 + axes[1][None, :, None] ** 2 + axes[2][None, None, :] ** 2
            out[i] += np.mean(np.where(d2 < r * r, (1.0 - d2 / (r * r)) ** 3, 0.0))
    return out
