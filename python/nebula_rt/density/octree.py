"""An adaptive density: a forest of octrees over a uniform grid of root cells, in flat arrays.

The layout is the one a device walks: ``child`` holds one int32 per node; the first
``rx * ry * rz`` nodes are the root cells (x fastest), a node's value >= 0 is the index of the
first of its 8 children (stored together, child c = ix + 2 iy + 4 iz of the octants), and a
value < 0 marks a leaf whose index into ``density`` is ``-1 - value``. A point is located by
one index into the root grid and at most ``depth`` steps down; memory is 4 bytes a node and 4
a leaf (a tree with L leaves has at most L + L / 7 + roots nodes), so proportional to the
leaves, not to the finest resolution.

:func:`coarsen` makes a tree from a uniform density by merging every 2 x 2 x 2 block of
cells whose values agree within a tolerance into their mean (bottom up, so a merged block
may merge again): the mass is kept exactly (a parent is the mean of its children), and a
tolerance of 0 merges only blocks of equal values. :meth:`Octree.leaves` gives each leaf's
box and density, for :func:`nebula_rt.density.resample.box_averages` and for tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Octree", "coarsen"]


@dataclass(frozen=True)
class Octree:
    """A forest of octrees over the unit box (see the module's doc).

    Attributes
    ----------
    roots : (rx, ry, rz)
        The root grid.
    child : ndarray int32 (n_nodes,)
        Per node: the first child's index, or -1 - leaf index for a leaf.
    density : ndarray float32 (n_leaves,)
        Per leaf.
    """

    roots: tuple
    child: np.ndarray
    density: np.ndarray

    @property
    def n_leaves(self) -> int:
        return int(self.density.size)

    def depth(self) -> int:
        """Levels below the roots of the deepest leaf (0: the root grid itself)."""
        return int(self._walk()[2].max(initial=0))

    def _walk(self):
        """(node, integer corner at its level (n, 3), level) of every leaf, by levels."""
        rx, ry, rz = self.roots
        nodes = np.arange(rx * ry * rz)
        corner = np.stack(np.unravel_index(nodes, (rx, ry, rz), order="F"), axis=1).astype(np.int64)
        level = np.zeros(nodes.size, np.int64)
        out_n, out_c, out_l = [], [], []
        octants = np.array(list(np.ndindex(2, 2, 2)))[:, ::-1]  # c = ix + 2 iy + 4 iz
        while nodes.size:
            c = self.child[nodes]
            leaf = c < 0
            out_n.append(nodes[leaf])
            out_c.append(corner[leaf])
            out_l.append(level[leaf])
            inner = ~leaf
            first = c[inner].astype(np.int64)
            nodes = (first[:, None] + np.arange(8)[None, :]).reshape(-1)
            corner = (2 * corner[inner][:, None, :] + octants[None, :, :]).reshape(-1, 3)
            level = np.repeat(level[inner] + 1, 8)
        return np.concatenate(out_n), np.concatenate(out_c), np.concatenate(out_l)

    def leaves(self):
        """(lo (n, 3), hi (n, 3), density (n,)) of every leaf, in leaf-index order (box units)."""
        nodes, corner, level = self._walk()
        ids = -1 - self.child[nodes].astype(np.int64)
        size = 1.0 / (np.asarray(self.roots, np.float64)[None, :] * (2.0 ** level)[:, None])
        order = np.argsort(ids)
        lo, hi = corner * size, (corner + 1) * size
        return lo[order], hi[order], self.density[ids[order]]


def coarsen(density, roots, tolerance: float = 0.0) -> Octree:
    """The octree of a uniform ``density`` (nx, ny, nz) over ``roots`` root cells per axis,
    each root cell covering 2^L x 2^L x 2^L voxels (nx = rx 2^L, ...), with every 2 x 2 x 2
    block whose values v satisfy max(v) - min(v) <= tolerance x mean(v) merged into one leaf
    of their mean, repeatedly up to the roots. tolerance 0 merges only equal values.

    Raises ValueError for a shape that is not the roots times one power of 2, a negative or
    non-finite density or tolerance."""
    rho = np.asarray(density, np.float64)
    rx, ry, rz = (int(r) for r in roots)
    if rho.ndim != 3 or min(rx, ry, rz) < 1:
        raise ValueError(f"density must be 3-D and roots 3 positive counts, got {rho.shape} and {roots}")
    ratios = {rho.shape[0] // rx, rho.shape[1] // ry, rho.shape[2] // rz}
    f = ratios.pop() if len(ratios) == 1 else 0
    if f < 1 or (f & (f - 1)) or rho.shape != (rx * f, ry * f, rz * f):
        raise ValueError(f"the density's shape {rho.shape} must be the roots {tuple(roots)} times one power of 2")
    if not np.all(np.isfinite(rho)) or rho.min(initial=0.0) < 0.0:
        raise ValueError("the density must be finite and >= 0")
    if not (np.isfinite(tolerance) and tolerance >= 0.0):
        raise ValueError(f"tolerance must be finite and >= 0, got {tolerance!r}")
    levels = f.bit_length() - 1
    octants = np.array(list(np.ndindex(2, 2, 2)))[:, ::-1]  # c = ix + 2 iy + 4 iz
    # bottom up: per level the values and whether each cell is a leaf (merged or finest)
    values, merged = [rho], [np.ones(rho.shape, bool)]
    for _ in range(levels):
        v, m = values[-1], merged[-1]
        blocks = v.reshape(v.shape[0] // 2, 2, v.shape[1] // 2, 2, v.shape[2] // 2, 2)
        kids_leaf = m.reshape(blocks.shape).all(axis=(1, 3, 5))
        mean = blocks.mean(axis=(1, 3, 5))
        spread = blocks.max(axis=(1, 3, 5)) - blocks.min(axis=(1, 3, 5))
        values.append(mean)
        merged.append(kids_leaf & (spread <= tolerance * mean))
    # top down: number the nodes breadth first (roots first), children of a node together
    child, leaf_values = [], []
    top = values[levels]
    level_cells = [np.stack(np.unravel_index(np.arange(top.size), top.shape, order="F"), axis=1)]
    next_node, leaves_so_far = top.size, 0
    for lev in range(levels, -1, -1):
        cells = level_cells[-1]
        v, m = values[lev], merged[lev]
        is_leaf = m[cells[:, 0], cells[:, 1], cells[:, 2]]
        c = np.empty(len(cells), np.int64)
        n_leaf = int(is_leaf.sum())
        c[is_leaf] = -1 - (leaves_so_far + np.arange(n_leaf))
        leaves_so_far += n_leaf
        leaf_values.append(v[cells[is_leaf, 0], cells[is_leaf, 1], cells[is_leaf, 2]])
        inner = np.flatnonzero(~is_leaf)
        c[inner] = next_node + 8 * np.arange(inner.size)
        next_node += 8 * inner.size
        child.append(c)
        if lev == 0:
            break
        level_cells.append((2 * cells[inner][:, None, :] + octants[None, :, :]).reshape(-1, 3))
    return Octree(roots=(rx, ry, rz), child=np.concatenate(child).astype(np.int32),
                  density=np.concatenate(leaf_values).astype(np.float32))
