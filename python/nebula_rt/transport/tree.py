"""What a run on an adaptive density needs besides the grid's machinery: the tree's layout on
the device, its leaves' volumes and the cell sizes its bounds take.

A :class:`nebula_rt.density.octree.Octree` is traced by the same plan, session, batches,
folds and estimates as a uniform grid (:func:`nebula_rt.transport.trace` takes one in place
of the density array); the cells of a run are then the tree's leaves. The packets walk from
leaf to leaf (``kernels/tree.cl``, in place of the grid's walk) and draw their random numbers
as the grid's analog packets do, so on a tree whose leaves are a grid's voxels they fly the
same paths (``tests/transport/test_tree_transport.py``); weighted packets walk the leaves too,
their windows' maps made on :func:`map_grid`. docs/adaptive_grids.md.
"""

from __future__ import annotations

import numpy as np

from ..density.octree import Octree

__all__ = ["device_layout", "leaf_volumes", "leaf_edges", "finest_shape", "coarsest_shape", "map_grid"]


def device_layout(tree: Octree) -> np.ndarray:
    """The density buffer of a run on ``tree`` (float32): the leaves' densities, then each
    node's child entry (int32 bits; kernels/tree.cl)."""
    return np.concatenate([np.asarray(tree.density, np.float32),
                           np.asarray(tree.child, np.int32).view(np.float32)])


def leaf_volumes(tree: Octree) -> np.ndarray:
    """Each leaf's volume (box units^3, float64, leaf-index order): what divides its track
    sum into J, as the voxel volume does on a grid."""
    r = np.asarray(tree.roots, np.float64)
    return np.ldexp(1.0 / float(np.prod(r)), -3 * _leaf_levels(tree))  # 1 / (prod(r) 8^level), exactly


def leaf_edges(tree: Octree) -> np.ndarray:
    """Each leaf's longest edge (box units, float64, leaf-index order)."""
    r = np.asarray(tree.roots, np.float64)
    return np.ldexp(1.0 / float(r.min()), -_leaf_levels(tree))


def _leaf_levels(tree: Octree) -> np.ndarray:
    """Each leaf's level below the roots (int, leaf-index order), from the boxes the tree keeps
    (one int a leaf rather than (n, 3) floats of box corners: 39M leaves took seconds)."""
    return tree._boxes[2].astype(np.int64)


def finest_shape(tree: Octree) -> tuple[int, int, int]:
    """Cells per axis at the tree's deepest level: the grid of its smallest leaves, whose
    size sets the fixed-point resolution of the track lengths and the largest J a leaf can
    hold."""
    scale = 2 ** tree.depth()
    return tuple(int(r) * scale for r in tree.roots)


def coarsest_shape(tree: Octree) -> tuple[int, int, int]:
    """Cells per axis of the root grid: no leaf is larger than a root cell, so its diagonal
    bounds a flight's deposit into one leaf."""
    return tuple(int(r) for r in tree.roots)


def map_grid(tree: Octree) -> np.ndarray:
    """The tree's density on a uniform grid for the weighted packets' window maps
    (:mod:`nebula_rt.transport.importance`): the leaves' exact-overlap averages
    (:func:`~nebula_rt.density.resample.box_averages`) on the grid of the tree's deepest level,
    at most ``importance.MAX_CELLS`` cells a side (the maps' own resolution: a finer grid would
    be averaged down to it there)."""
    from ..density.resample import box_averages
    from .importance import MAX_CELLS

    lo, hi, rho = tree.leaves()
    shape = tuple(min(int(n), MAX_CELLS) for n in finest_shape(tree))
    return box_averages(lo, hi, np.asarray(rho, np.float64), shape)
