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
tolerance of 0 merges only blocks of equal values. :func:`from_boxes` makes one from its
leaves' boxes (a hyper tree grid's or an AMR hierarchy's, refused where they are not the cells
of a forest of octrees that tile the box). :meth:`Octree.leaves` gives each leaf's box and
density, for :func:`nebula_rt.density.resample.box_averages` and for tests.
"""

from __future__ import annotations

import functools

from dataclasses import dataclass

import numpy as np

__all__ = ["Octree", "coarsen", "from_boxes"]


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

    The arrays are not to be changed in place: the leaves' boxes are found once per tree
    (a walk of every node) and kept.
    """

    roots: tuple
    child: np.ndarray
    density: np.ndarray

    @property
    def n_leaves(self) -> int:
        return int(self.density.size)

    def depth(self) -> int:
        """Levels below the roots of the deepest leaf (0: the root grid itself)."""
        return int(self._boxes[2].max(initial=0))

    @functools.cached_property
    def _boxes(self):
        """(lo (n, 3), hi (n, 3), level (n,)) of every leaf in leaf-index order (a run on the
        tree asks for them several times: its plan, its J per leaf)."""
        nodes, corner, level = self._walk()
        ids = -1 - self.child[nodes].astype(np.int64)
        size = 1.0 / (np.asarray(self.roots, np.float64)[None, :] * (2.0 ** level)[:, None])
        order = np.argsort(ids)
        lo, hi = corner * size, (corner + 1) * size
        out = lo[order], hi[order], level[order]
        for a in out:  # shared by every caller: read-only
            a.setflags(write=False)
        return out

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

    def locate(self, points) -> np.ndarray:
        """The leaf index of each point (n, 3) of the unit box (a point on a face belongs to
        the cell above it; the box's high faces to the last cell). Vectorised descent: one
        step per level for all points together."""
        p = np.clip(np.asarray(points, np.float64).reshape(-1, 3), 0.0, 1.0)
        r = np.asarray(self.roots, np.int64)
        cell = np.minimum(np.floor(p * r).astype(np.int64), r - 1)
        node = cell[:, 0] + r[0] * (cell[:, 1] + r[1] * cell[:, 2])
        scale = r.astype(np.float64)
        c = self.child[node].astype(np.int64)
        inner = c >= 0
        while inner.any():
            scale = scale * 2.0
            sub = np.minimum(np.floor(p[inner] * scale).astype(np.int64), (scale - 1).astype(np.int64)) & 1
            node[inner] = c[inner] + sub[:, 0] + 2 * sub[:, 1] + 4 * sub[:, 2]
            c[inner] = self.child[node[inner]]
            inner = c >= 0
        return -1 - c

    def leaves(self):
        """(lo (n, 3), hi (n, 3), density (n,)) of every leaf, in leaf-index order (box units)."""
        lo, hi, _ = self._boxes
        return lo, hi, self.density


def from_boxes(lo, hi, values, roots) -> Octree:
    """The octree whose leaves are the boxes [lo, hi) (box units) with densities ``values``,
    over ``roots`` root cells per axis: what a hyper tree grid's or an AMR hierarchy's leaves
    (refinement ratio 2) give. The leaves are numbered as the boxes are given.

    Every box must be a cell of the forest (a root cell halved L times on every axis, at its
    place), the boxes must tile the unit box (none inside another, their volumes summing to 1:
    no hole) and the densities must be finite and >= 0. Raises ValueError naming what is wrong
    and the first box it concerns."""
    lo = np.asarray(lo, np.float64).reshape(-1, 3)
    hi = np.asarray(hi, np.float64).reshape(-1, 3)
    v = np.asarray(values, np.float64).reshape(-1)
    r = np.array([int(x) for x in roots], np.int64)
    if r.size != 3 or r.min() < 1:
        raise ValueError(f"roots must be 3 positive counts, got {roots}")
    if not (lo.shape == hi.shape and len(v) == len(lo) and len(v)):
        raise ValueError(f"lo {lo.shape}, hi {hi.shape} and values {v.shape} must describe the same boxes (at least one)")
    bad = np.flatnonzero(~np.isfinite(v) | (v < 0.0))
    if bad.size:
        raise ValueError(f"box {bad[0]}: density {v[bad[0]]!r} must be finite and >= 0")
    # level per axis: root size / box size = 2^L, the same L on every axis
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = 1.0 / (r[None, :] * (hi - lo))
        level = np.rint(np.log2(ratio))
    ok = np.isfinite(level).all(axis=1) & (np.abs(ratio / 2.0 ** level - 1.0) < 1e-9).all(axis=1) & (level >= 0).all(axis=1)
    ok &= (level == level[:, :1]).all(axis=1)
    corner = lo * r[None, :] * 2.0 ** np.where(np.isfinite(level), level, 0)
    ok &= (np.abs(corner - np.rint(corner)) < 1e-6).all(axis=1)
    if not ok.all():
        i = int(np.flatnonzero(~ok)[0])
        raise ValueError(f"box {i} [{lo[i].tolist()}, {hi[i].tolist()}) is not a cell of an octree over "
                         f"{tuple(r.tolist())} roots (a root cell halved the same number of times on every axis, in place)")
    lev = level[:, 0].astype(np.int64)
    corner = np.rint(corner).astype(np.int64)
    depth = int(lev.max())
    if depth > 20:
        raise ValueError(f"a box {depth} levels below the roots: at most 20")
    vol = np.prod(hi - lo, axis=1)
    if abs(vol.sum() - 1.0) > 1e-9:
        raise ValueError(f"the boxes cover {vol.sum():.12g} of the unit box, not all of it: "
                         "a tree with holes (or overlapping boxes)")

    def key(level_, c):  # an integer per cell of a level: its corner, x fastest
        w = r * (1 << int(level_))
        return c[:, 0] + w[0] * (c[:, 1] + w[1] * c[:, 2])

    leaves = {}  # level -> (sorted keys, box indices)
    for L in range(depth + 1):
        at = np.flatnonzero(lev == L)
        k = key(L, corner[at])
        order = np.argsort(k)
        if len(k) and (np.diff(k[order]) == 0).any():
            dup = at[order][np.flatnonzero(np.diff(k[order]) == 0)[0]]
            raise ValueError(f"box {dup} is given twice")
        leaves[L] = (k[order], at[order])
    # no leaf inside another: a leaf's ancestors are not leaves (with the volumes summing to 1,
    # the boxes then tile the unit box exactly)
    for L in range(1, depth + 1):
        at = np.flatnonzero(lev == L)
        for up in range(1, L + 1):
            ks, _ = leaves[L - up]
            anc = key(L - up, corner[at] >> up)
            hit = np.isin(anc, ks)
            if hit.any():
                raise ValueError(f"box {at[np.flatnonzero(hit)[0]]} lies inside another box")
    octants = np.array(list(np.ndindex(2, 2, 2)))[:, ::-1]  # c = ix + 2 iy + 4 iz
    cells = np.stack(np.unravel_index(np.arange(int(r.prod())), tuple(r), order="F"), axis=1)
    child, next_node = [], int(r.prod())
    for L in range(depth + 1):
        ks, ids = leaves[L]
        k = key(L, cells)
        pos = np.searchsorted(ks, k)
        is_leaf = (pos < len(ks)) & (ks[np.minimum(pos, len(ks) - 1)] == k) if len(ks) else np.zeros(len(k), bool)
        c = np.empty(len(cells), np.int64)
        c[is_leaf] = -1 - ids[pos[is_leaf]]
        inner = np.flatnonzero(~is_leaf)
        if L == depth and inner.size:  # (cannot happen once the tiling is checked)
            raise ValueError("a cell at the deepest level is neither a box nor refined")
        c[inner] = next_node + 8 * np.arange(inner.size)
        next_node += 8 * inner.size
        child.append(c)
        cells = (2 * cells[inner][:, None, :] + octants[None, :, :]).reshape(-1, 3)
    return Octree(roots=tuple(int(x) for x in r), child=np.concatenate(child).astype(np.int32),
                  density=v.astype(np.float32))


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
