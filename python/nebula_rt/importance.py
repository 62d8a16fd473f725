"""Weight windows of the weighted packets: where the light will be, before it is traced.

The biased transport (``transport.method = "biased"``, kernels/transport.cl) keeps each
packet's weight near a window W_c(x) = exp(-rate_b depth(x)): above it the packet is split,
below it Russian roulette decides. For as many packets to reach every depth as leave the star,
W_c must fall as the light field falls, and in thick dust that is e^-k tau, with tau the optical
depth the light has crossed and k the slowest decay rate of the transport equation for the
band's albedo and phase function (the diffusion eigenvalue: 1 for a pure absorber, 0 for
conservative scattering; Case & Zweifel 1967). So:

- ``depth``: per voxel, the least optical depth of the reference band from any star, along
  paths through the grid (Dijkstra's shortest paths on the voxel graph, 26 neighbours, each
  edge the mean extinction of its two voxels times its length; light reaches the far side of a
  dense core around it, not through it). Grids finer than ``MAX_CELLS`` a side are first
  averaged in blocks. The kernel interpolates the map linearly between cell centres, so the
  window falls smoothly through a voxel of large optical depth.
- ``rate_b = k(albedo_b, g_b) x k_b`` (k_b the band's extinction relative to the reference).

A window only steers where the packets go, never what they carry: any window gives the same
expectation (every split and roulette keeps the weight in expectation, the bookkeeping keeps it
exactly). A window that falls too slowly lets the packets thin out with depth, one that falls
too fast multiplies them (the kernel caps both, see NRT_SPLIT_MAX and NRT_SPLIT_DEPTH).
"""

from __future__ import annotations

import functools
import itertools

import numpy as np
from numpy.polynomial.legendre import leggauss

#: the depth map's grid at most this many cells a side (Dijkstra on 64^3 takes about 1 s)
MAX_CELLS = 64
#: Gauss nodes per hemisphere of the decay rate's discrete ordinates (converged to 1e-6 for
#: |g| <= 0.9)
_ORDINATES = 48


def _hg_azimuth_mean(g: float, mu: np.ndarray) -> np.ndarray:
    """The Henyey-Greenstein phase function averaged over azimuth, p0(mu_i, mu_j) =
    sum_l (2l + 1) g^l P_l(mu_i) P_l(mu_j) (normalised: (1/2) int p0 dmu = 1), truncated
    where g^l < 1e-16 and at 2 x nodes terms (what the quadrature resolves)."""
    lmax = 1 if g == 0 else min(2 * mu.size, int(np.ceil(np.log(1e-16) / np.log(abs(g)))))
    p = np.zeros((mu.size, mu.size))
    p_prev, p_cur = np.ones_like(mu), mu.copy()
    p += 1.0
    for el in range(1, lmax + 1):
        p += (2 * el + 1) * g**el * np.outer(p_cur, p_cur)
        p_prev, p_cur = p_cur, ((2 * el + 1) * mu * p_cur - el * p_prev) / (el + 1)
    return p


@functools.lru_cache(maxsize=256)
def decay_rate(albedo: float, g: float) -> float:
    """The slowest decay rate k (per unit optical depth) of the homogeneous transport equation
    for HG scattering, I ~ e^-k tau: the smallest positive eigenvalue of the discrete
    ordinates, (1 - (a/2) P W) phi = k M phi. 1 for albedo 0, 0 for albedo 1."""
    a = float(albedo)
    if a <= 0.0:
        return 1.0
    if a >= 1.0:
        return 0.0
    x, w = leggauss(2 * _ORDINATES)
    p = _hg_azimuth_mean(float(np.clip(g, -0.99, 0.99)), x)
    ev = np.linalg.eigvals((np.eye(x.size) - 0.5 * a * p * w[None, :]) / x[:, None])
    ev = ev.real[(np.abs(ev.imag) < 1e-9) & (ev.real > 1e-12)]
    return float(min(1.0, ev.min())) if ev.size else 1.0


def window_rates(albedo, g, extinction) -> np.ndarray:
    """rate_b = k(albedo_b, g_b) x extinction_b per band (float32): the windows' decay per
    unit optical depth of the reference band."""
    return np.array([decay_rate(float(a), float(gg)) * float(k) for a, gg, k in zip(albedo, g, extinction)],
                    np.float32)


def _block_mean(sigma: np.ndarray, factor: tuple) -> np.ndarray:
    """Mean of sigma over blocks of ``factor`` voxels (the last block of an axis may be
    shorter)."""
    out = sigma
    for ax, f in enumerate(factor):
        if f == 1:
            continue
        n = out.shape[ax]
        edges = np.arange(0, n, f)
        sums = np.add.reduceat(out, edges, axis=ax)
        counts = np.diff(np.append(edges, n)).reshape([-1 if i == ax else 1 for i in range(3)])
        out = sums / counts
    return out


def depth_map(sigma: np.ndarray, star_positions) -> np.ndarray:
    """Least optical depth from any star to the centre of every cell of a grid over the box
    (float32): the density's grid, or blocks of it at most ``MAX_CELLS`` a side (the kernel
    interpolates between the cell centres, as if the cells were equal: a last, shorter block
    of an axis shifts the map by less than a voxel, which only a window's efficiency feels).

    sigma : ndarray (nx, ny, nz)
        Extinction per box unit of the reference band.
    star_positions : array (n_stars, 3)
        Box units.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    shape = tuple(int(n) for n in sigma.shape)
    factor = tuple(max(1, -(-n // MAX_CELLS)) for n in shape)
    coarse = _block_mean(np.asarray(sigma, np.float64), factor)
    cshape = coarse.shape
    h = np.array([f / n for f, n in zip(factor, shape)])  # the coarse cells' edges (box units)
    idx = np.arange(coarse.size).reshape(cshape)
    rows, cols, weights = [], [], []
    for step in itertools.product((-1, 0, 1), repeat=3):
        if step <= (0, 0, 0):
            continue  # each undirected edge once
        a = tuple(slice(max(0, -k), n - max(0, k)) for k, n in zip(step, cshape))
        b = tuple(slice(max(0, k), n - max(0, -k)) for k, n in zip(step, cshape))
        length = float(np.sqrt(np.sum((np.array(step) * h) ** 2)))
        rows.append(idx[a].ravel())
        cols.append(idx[b].ravel())
        # an edge of zero weight would vanish from the sparse graph: vacuum costs 1e-30
        weights.append(0.5 * length * (coarse[a] + coarse[b]).ravel() + 1e-30)
    graph = coo_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))),
                       shape=(coarse.size, coarse.size)).tocsr()
    sources = []
    for pos in np.asarray(star_positions, np.float64).reshape(-1, 3):
        cell = [min(int(pos[k] * cshape[k]), cshape[k] - 1) for k in range(3)]
        sources.append(int(idx[tuple(cell)]))
    dist = dijkstra(graph, directed=False, indices=sorted(set(sources)), min_only=True)
    return np.asarray(dist.reshape(cshape), np.float32)
