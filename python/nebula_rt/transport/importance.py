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

That map serves the light field J. A run that makes a peel-off image wants the image's
importance instead, the adjoint: how much of a packet's light will reach the observer
(:func:`observer_depth_map`; :func:`resolve_importance` chooses by the run's product).

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

from ..errors import SceneError

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


def _coarse(sigma: np.ndarray):
    """(the grid of the depth maps: sigma averaged in blocks of at most ``MAX_CELLS`` cells a
    side, its cells' edges in box units)."""
    shape = tuple(int(n) for n in sigma.shape)
    factor = tuple(max(1, -(-n // MAX_CELLS)) for n in shape)
    coarse = _block_mean(np.asarray(sigma, np.float64), factor)
    return coarse, np.array([f / n for f, n in zip(factor, shape)])


def _voxel_graph(coarse: np.ndarray, h: np.ndarray, extra_nodes: int = 0):
    """(rows, cols, weights) of the 26-neighbour graph of the cells, each undirected edge once,
    its weight the mean extinction of its two cells times its length; node numbers leave
    ``extra_nodes`` free after the cells."""
    cshape = coarse.shape
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
    return rows, cols, weights


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

    coarse, h = _coarse(sigma)
    cshape = coarse.shape
    rows, cols, weights = _voxel_graph(coarse, h)
    graph = coo_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))),
                       shape=(coarse.size, coarse.size)).tocsr()
    idx = np.arange(coarse.size).reshape(cshape)
    sources = []
    for pos in np.asarray(star_positions, np.float64).reshape(-1, 3):
        cell = [min(int(pos[k] * cshape[k]), cshape[k] - 1) for k in range(3)]
        sources.append(int(idx[tuple(cell)]))
    dist = dijkstra(graph, directed=False, indices=sorted(set(sources)), min_only=True)
    return np.asarray(dist.reshape(cshape), np.float32)


def line_of_sight_depth(coarse: np.ndarray, h: np.ndarray, toward) -> np.ndarray:
    """Optical depth from every cell centre to the box's edge along the unit vector ``toward``
    (midpoint rule in steps of half the smallest cell edge: each step the extinction of the
    cell at its middle, counted while the middle is inside the box; float64, the coarse grid's
    shape). Exact along an axis; otherwise within half a step's extinction."""
    u = np.asarray(toward, np.float64)
    u = u / np.linalg.norm(u)
    cshape = np.array(coarse.shape)
    step = 0.5 * float(h.min())
    axes = [(np.arange(n) + 0.5) * hk for n, hk in zip(cshape, h)]
    mid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3) + 0.5 * step * u
    depth = np.zeros(len(mid))
    live = np.arange(len(mid))
    while True:
        p = mid[live]
        inside = np.all((p >= 0.0) & (p < 1.0), axis=1)
        live, p = live[inside], p[inside]
        if not live.size:
            break
        cell = np.minimum((p / h).astype(np.int64), cshape - 1)
        depth[live] += coarse[cell[:, 0], cell[:, 1], cell[:, 2]] * step
        mid[live] += step * u
    return depth.reshape(coarse.shape)


def observer_depth_map(sigma: np.ndarray, toward) -> np.ndarray:
    """The weight windows' map for a peel-off image: per cell, the optical depth *to the
    observer* turned round, D = max - tau_obs (float32, the grid of :func:`depth_map`).

    tau_obs is the least optical depth of a path from the cell through the grid to some cell
    and from there straight out of the box along ``toward`` (the unit vector to the observer):
    light scattered deep in a cloud reaches the observer by diffusing to where the way out is
    clear (Dijkstra from a node joined to every cell by its line-of-sight depth,
    :func:`line_of_sight_depth`). The image's importance of a cell falls as e^-(k tau_obs), so
    the window W_c(x) = e^-(k (D(x) - D(star))) is the adjoint's (Booth 1982): packets are split
    as they approach the observer, and where they move away from it the kernel keeps the window
    at the packet's start (it never raises a window above W0), which leaves them to the
    absorption and the path stretching towards the observer. For a slab seen from the side
    opposite its star the map is the stars' :func:`depth_map` up to a constant (the same
    windows); for the side of the star it stops the splitting that drove packets deep into
    dust whose light never comes out towards the observer.

    sigma : ndarray (nx, ny, nz)
        Extinction per box unit of the reference band.
    toward : 3 floats
        Direction to the observer (any length).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    coarse, h = _coarse(sigma)
    n = coarse.size
    rows, cols, weights = _voxel_graph(coarse, h)
    rows, cols = rows + cols, cols + rows  # both directions: the graph is directed (the node below)
    weights = weights + weights
    # node n: the observer, joined to every cell by the way straight out
    rows.append(np.full(n, n))
    cols.append(np.arange(n))
    weights.append(line_of_sight_depth(coarse, h, toward).ravel() + 1e-30)
    graph = coo_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))),
                       shape=(n + 1, n + 1)).tocsr()
    tau_obs = dijkstra(graph, directed=True, indices=n)[:n]
    return np.asarray((tau_obs.max() - tau_obs).reshape(coarse.shape), np.float32)


#: which map steers the weight windows (``trace(importance=...)``)
IMPORTANCES = ("auto", "stars", "observer")


def resolve_importance(importance: str, peel) -> str:
    """The windows a weighted run takes: ``importance`` itself unless it is ``"auto"``, which
    follows the run's product: the observer's when the run makes a peel-off image (the J of
    such a run is not its product), the stars' (the light field) otherwise."""
    if importance not in IMPORTANCES:
        raise SceneError("importance", importance, " or ".join(f'"{m}"' for m in IMPORTANCES))
    if importance == "observer" and peel is None:
        raise SceneError("importance", importance, '"stars" or "auto" (a run without a peel-off image '
                         'has no observer)')
    if importance != "auto":
        return importance
    return "stars" if peel is None else "observer"
