"""The optical depth along a straight line through the voxel grid, exactly.

Pure NumPy, below every other module: the transport (``transport.method = "auto"`` measures
the scene's optical depth with it), the observation comparisons (:mod:`nebula_rt.observe`, the
star seen through the dust) and the calibrated sky images (:mod:`nebula_rt.observe.calibrate`) use it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["line_of_sight_tau", "density_column", "peel_axis", "peel_columns"]


def line_of_sight_tau(sigma, start, toward) -> np.ndarray:
    """Optical depth per band from ``start`` along ``toward`` to the edge of the box.

    Exact for the piecewise-constant medium: the ray's crossings of every voxel face are
    computed, and each piece between two consecutive crossings lies in one voxel (the one
    holding its midpoint) and adds sigma times its length.

    Parameters
    ----------
    sigma : array_like (n_bands, nx, ny, nz)
        Extinction per box unit of each voxel (voxel [i, j, k] spans [i/nx, (i+1)/nx) x ...).
    start : (3,) box units
        Where the ray starts (inside or outside the box).
    toward : (3,)
        Direction of the ray (any length); towards the observer is ``-camera direction``.

    Returns
    -------
    ndarray (n_bands,)
    """
    sig = np.asarray(sigma, np.float64)
    if sig.ndim == 3:
        sig = sig[None]
    shape = np.array(sig.shape[1:])
    p = np.asarray(start, np.float64)
    o = np.asarray(toward, np.float64)
    o = o / np.linalg.norm(o)
    t_lo, t_hi = 0.0, np.inf
    for a in range(3):
        if o[a] == 0.0:
            if not 0.0 <= p[a] <= 1.0:
                return np.zeros(sig.shape[0])
            continue
        t0, t1 = -p[a] / o[a], (1.0 - p[a]) / o[a]
        t_lo, t_hi = max(t_lo, min(t0, t1)), min(t_hi, max(t0, t1))
    if not t_hi > t_lo:
        return np.zeros(sig.shape[0])
    ts = [np.array([t_lo, t_hi])]
    for a in range(3):
        if o[a] != 0.0:
            t = (np.arange(shape[a] + 1) / shape[a] - p[a]) / o[a]
            ts.append(t[(t > t_lo) & (t < t_hi)])
    ts = np.unique(np.concatenate(ts))
    mid = p[None, :] + (0.5 * (ts[1:] + ts[:-1]))[:, None] * o[None, :]
    idx = np.clip(np.floor(mid * shape[None, :]).astype(np.int64), 0, shape - 1)
    return sig[:, idx[:, 0], idx[:, 1], idx[:, 2]] @ np.diff(ts)


#: the last density columns taken (:func:`density_column`), by density, start and direction
_COLUMNS: dict = {}
_MAX_COLUMNS = 32


def density_column(density, start, toward) -> float:
    """The density integrated along a ray from ``start`` towards ``toward`` to the box's edge
    (box units): :func:`line_of_sight_tau` of the density alone (a grid) or the exact sum over
    an octree's leaves (:func:`_leaves_column`), which is linear in sigma, so
    a band's optical depth is its extinction coefficient per unit density times this. Kept for
    the last few (density, start, direction): a fit or a run's method choice asks for the same
    ones at every trial (a read-only density array is known by its identity while it lives)."""
    import weakref

    key = (id(density), tuple(float(x) for x in start), tuple(float(x) for x in toward))
    hit = _COLUMNS.get(key)
    if hit is not None and hit[0]() is density:
        return hit[1]
    if hasattr(density, "leaves"):  # an octree (nebula_rt.density.octree.Octree: immutable)
        col = _leaves_column(*density.leaves(), start, toward)
        if len(_COLUMNS) >= _MAX_COLUMNS:
            _COLUMNS.pop(next(iter(_COLUMNS)))
        _COLUMNS[key] = (weakref.ref(density), col)
        return col
    col = float(line_of_sight_tau(np.asarray(density, np.float64)[None], start, toward)[0])
    if isinstance(density, np.ndarray) and not density.flags.writeable:
        if len(_COLUMNS) >= _MAX_COLUMNS:
            _COLUMNS.pop(next(iter(_COLUMNS)))
        _COLUMNS[key] = (weakref.ref(density), col)
    return col


def _leaves_column(lo, hi, values, start, toward, chunk: int = 1 << 22) -> float:
    """The column of a field given on boxes that tile the unit box (a tree's leaves: ``lo``,
    ``hi`` (n, 3), ``values`` (n,)) along the ray from ``start`` towards ``toward`` to the box's
    edge: each box adds its value times the length of the ray inside it (the slab test, exact).
    A ray along a face belongs to the boxes on its high side, [lo, hi) as the grid's march
    takes voxels (the top face of the box to the boxes below it). In chunks of boxes, so memory
    stays bounded for tens of millions of leaves."""
    p = np.asarray(start, np.float64)
    o = np.asarray(toward, np.float64)
    o = o / np.linalg.norm(o)
    moving = o != 0.0
    inv = np.where(moving, 1.0 / np.where(moving, o, 1.0), 0.0)
    total = 0.0
    for a in range(0, len(values), chunk):
        b0, b1 = np.asarray(lo[a:a + chunk], np.float64), np.asarray(hi[a:a + chunk], np.float64)
        t0, t1 = (b0 - p) * inv, (b1 - p) * inv
        tmin = np.where(moving, np.minimum(t0, t1), -np.inf).max(axis=1)
        tmax = np.where(moving, np.maximum(t0, t1), np.inf).min(axis=1)
        # on the axes the ray does not move along, the box must hold the start's coordinate
        holds = (b0 <= p) & ((p < b1) | ((b1 >= 1.0) & (p <= b1)))
        inside = np.all(holds | moving, axis=1)
        length = np.where(inside, np.maximum(tmax - np.maximum(tmin, 0.0), 0.0), 0.0)
        total += float(np.dot(np.asarray(values[a:a + chunk], np.float64), length))
    return total


def peel_axis(toward):
    """(axis, up) where ``toward`` points along a grid axis (up: to its high end), else None."""
    o = np.asarray(toward, np.float64)
    along = np.flatnonzero(o != 0.0)
    return (int(along[0]), bool(o[along[0]] > 0.0)) if len(along) == 1 else None


def peel_columns(density, axis: int, up: bool) -> np.ndarray:
    """Per voxel, the density column from its far face along ``axis`` (towards the high end
    where ``up``) to the box's edge: h times the sum of the densities of the voxels beyond it
    (box units x density; float64 sums, float32 result, read-only, shape of ``density``). A
    peel-off towards an observer along that axis has the optical depth sigma_b (column + rho
    x the rest of its own voxel) (kernels/transport.cl, NRT_PEEL_AXIS). Kept for the last few
    read-only densities, as :func:`density_column`: a fit traces one density many times."""
    import weakref

    key = (id(density), int(axis), bool(up))
    hit = _PEEL_COLUMNS.get(key)
    if hit is not None and hit[0]() is density:
        return hit[1]
    rho = np.moveaxis(np.asarray(density, np.float64), axis, -1)
    beyond = np.zeros_like(rho)
    if up:
        beyond[..., :-1] = np.cumsum(rho[..., :0:-1], axis=-1)[..., ::-1]
    else:
        beyond[..., 1:] = np.cumsum(rho[..., :-1], axis=-1)
    cols = np.moveaxis(beyond / rho.shape[-1], -1, axis).astype(np.float32)
    cols.flags.writeable = False
    if isinstance(density, np.ndarray) and not density.flags.writeable:
        if len(_PEEL_COLUMNS) >= 2:  # (a grid's worth each)
            _PEEL_COLUMNS.pop(next(iter(_PEEL_COLUMNS)))
        _PEEL_COLUMNS[key] = (weakref.ref(density), cols)
    return cols


_PEEL_COLUMNS: dict = {}
