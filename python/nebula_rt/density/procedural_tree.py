"""The procedural density (turbulence or uniform, thesis Eq. 3.2) on an adaptive octree.

A scene with ``dust.octree = true`` gets its density as a tree over the unit box, refined
top down where the dust needs it instead of on every voxel of a uniform grid: a cell is split
into its 8 octants while

- its optical depth across one edge in the reference band (``dust.tau`` x extinction x its
  mean density x its edge) exceeds ``dust.cell_tau`` (SKIRT's maximum optical depth per cell),
- or its octants' optical depths across that edge spread (max - min) by more than
  ``dust.cell_tau_spread`` (structure the cell would smear where it matters to the light: a
  relative contrast would split thin fluff down to the deepest level, since the turbulence has
  structure on every scale),
- or a star's bump (``bump_radius``) reaches into it and its edge is longer than the radius
  (the tests above take the bumps' values at the octants' centres into the density too),
- or it lies above level :data:`MIN_LEVEL`,

down to ``dust.tree_depth`` levels (2^tree_depth cells per edge at most).

A cell's octants are sampled at their centres with the uniform grid's arithmetic
(``kernels/density.cl``, ``nrt_base_density``, on the device): a leaf at the deepest level has
its own centre value, the very bits of the 2^depth uniform grid's voxel there; a coarser leaf
has the mean of its 8 octants' values, each at least the floor (a 2-point-per-axis midpoint
rule for its average). The
stars' bumps are then averaged over each leaf (:func:`~nebula_rt.density.bumps.leaf_bumps`)
and the floor applied, as for an adaptive file.

Cost: one device evaluation of 8 values per cell that is looked at, i.e. about 8/7 of the
leaves' count in total; host memory a few tens of bytes per leaf.
"""

from __future__ import annotations

import numpy as np

from .. import limits
from ..backends.base import MODEL_TURBULENCE, MODEL_UNIFORM
from ..errors import SceneError
from .bumps import leaf_bumps, stars_array
from .octree import Octree

__all__ = ["MIN_LEVEL", "procedural_tree"]

#: every cell above this level is split: the 8 samples of a cell larger than an eighth of the
#: box (level < 3) say little about the structure inside it (the thesis's turbulence has
#: features of about a tenth of the box)
MIN_LEVEL = 3

#: the octant c = ix + 2 iy + 4 iz of a cell (the octree's child order), as (ix, iy, iz)
_OCTANTS = np.array(list(np.ndindex(2, 2, 2)), np.int32)[:, ::-1]


def procedural_tree(scene, backend):
    """The scene's turbulence or uniform density on an octree (see the module's doc).

    Returns
    -------
    Octree
        Over one root cell (the unit box), leaves numbered breadth first.

    Raises
    ------
    SceneError
        ``dust.model`` not procedural, a tree that would pass the int32 node indices of the
        device walk (``dust.cell_tau``, ``dust.cell_tau_spread`` or ``dust.tree_depth`` to
        change), or a density float32 cannot hold.
    """
    from ..optics.bands import reference_band_index

    dust = scene.dust
    if dust.model not in ("turbulence", "uniform"):
        raise SceneError("dust.octree", dust.octree,
                         f'true only with dust.model "turbulence" or "uniform", or a .vtp particle snapshot (an '
                         f'adaptive dust.file is a tree already; a uniform one is traced on its grid): dust.model '
                         f'is "{dust.model}"')
    bands = scene.bands.resolve()
    sigma = float(dust.tau) * float(bands[reference_band_index(bands)].extinction)
    model = MODEL_TURBULENCE if dust.model == "turbulence" else MODEL_UNIFORM
    stars = stars_array(scene.stars)
    stars = stars[stars[:, 3] > 0]
    depth = int(dust.tree_depth)

    def sample(cells, level):
        return backend.density_cells(cells, 1 << level, model, dust.offset, dust.scale, dust.density)

    cells = np.zeros((1, 3), np.int32)
    values = sample(cells, 0) if depth == 0 else None  # the cells' own values (deepest level only)
    child, leaf_vals, leaf_lo, leaf_edge = [], [], [], []
    next_node, n_leaves = 1, 0
    for level in range(depth + 1):
        n_cells = len(cells)
        edge = 1.0 / (1 << level)
        if level == depth:
            split = np.zeros(n_cells, bool)
            vals = np.asarray(values, np.float64)
        else:
            kids = (2 * cells[:, None, :] + _OCTANTS[None, :, :]).reshape(-1, 3)
            s = sample(kids, level + 1).reshape(n_cells, 8)
            # a coarse leaf averages its octants with the floor each voxel of a grid gets
            floored = np.maximum(s, np.float32(dust.floor))
            vals = floored.mean(axis=1, dtype=np.float64)
            # the tests see the whole density, the bumps' values at the octants' centres too: a
            # star's bump is the densest dust there is, and smeared over cells as wide as its
            # radius it let 16 % more of a central star's light out at 2^10 resolution
            dense = floored + _bump_values(cells, level + 1, stars)
            split = (level < MIN_LEVEL) | (sigma * dense.mean(axis=1) * edge > dust.cell_tau)
            split |= sigma * (dense.max(axis=1) - dense.min(axis=1)) * edge > dust.cell_tau_spread
            split |= _near_bumps(cells, edge, stars)
        c = np.empty(n_cells, np.int64)
        leaf = ~split
        k = int(leaf.sum())
        c[leaf] = -1 - (n_leaves + np.arange(k))
        n_leaves += k
        leaf_vals.append(vals[leaf])
        leaf_lo.append(cells[leaf].astype(np.float64) * edge)
        leaf_edge.append(np.full(k, edge))
        inner = np.flatnonzero(split)
        if next_node + 8 * inner.size > limits.INT32_MAX:
            raise SceneError("dust.cell_tau", dust.cell_tau,
                             f"the octree would pass {limits.INT32_MAX} nodes (the device walk's int32 indices) "
                             f"at level {level + 1}: raise dust.cell_tau or dust.cell_tau_spread, or lower "
                             f"dust.tree_depth ({depth})")
        c[inner] = next_node + 8 * np.arange(inner.size)
        next_node += 8 * inner.size
        child.append(c)
        if inner.size == 0:
            break
        cells = kids.reshape(n_cells, 8, 3)[inner].reshape(-1, 3)
        values = s[inner].reshape(-1)
    lo = np.concatenate(leaf_lo)
    hi = lo + np.concatenate(leaf_edge)[:, None]
    rho = np.maximum(np.concatenate(leaf_vals) + leaf_bumps(lo, hi, stars), dust.floor)
    if not np.all(np.isfinite(rho)) or not rho.max(initial=0.0) <= limits.FLOAT32_MAX:
        raise SceneError("dust.scale" if dust.model == "turbulence" else "dust.density",
                         dust.scale if dust.model == "turbulence" else dust.density,
                         f"the density plus the stars' bumps overflows float32 (at most {limits.fmt(limits.FLOAT32_MAX)})")
    return Octree(roots=(1, 1, 1), child=np.concatenate(child).astype(np.int32), density=rho.astype(np.float32))


def _bump_values(cells, kid_level: int, stars) -> np.ndarray:
    """(n, 8) float64: the stars' cubic bumps (1 - d^2 / r^2)^3 at the centres of the cells'
    octants (level ``kid_level``), 0 where none reaches."""
    out = np.zeros((len(cells), 8))
    if not len(stars):
        return out
    h = 1.0 / (1 << kid_level)
    for sx, sy, sz, r in stars:
        s = np.array([sx, sy, sz], np.float64)
        lo = cells.astype(np.float64) * (2 * h)
        near = np.flatnonzero(np.sum((np.clip(s, lo, lo + 2 * h) - s) ** 2, axis=1) < float(r) ** 2)
        if near.size == 0:
            continue
        centres = (2 * cells[near][:, None, :] + _OCTANTS[None, :, :] + 0.5) * h  # (m, 8, 3)
        d2 = np.sum((centres - s) ** 2, axis=2) / float(r) ** 2
        out[near] += np.where(d2 < 1.0, (1.0 - d2) ** 3, 0.0)
    return out


def _near_bumps(cells, edge: float, stars) -> np.ndarray:
    """Cells (level edge ``edge``) a star's bump reaches into while the edge is longer than
    its radius: there the bump's shape needs finer leaves than the dust around it."""
    out = np.zeros(len(cells), bool)
    for sx, sy, sz, r in stars:
        if not edge > r:
            continue
        lo = cells.astype(np.float64) * edge
        s = np.array([sx, sy, sz])
        out |= np.sum((np.clip(s, lo, lo + edge) - s) ** 2, axis=1) < r * r
    return out
