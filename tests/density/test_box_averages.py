"""Voxel averages of boxes by exact overlap (nebula_rt.density.resample), against answers made
without the code under test: a random octree's leaves tile the box, so ones average to ones
and the mass is kept; a uniform grid given as boxes at its own resolution comes back; a coarse
aligned tree on a finer grid gives each voxel its leaf's value; and one unaligned box's
overlaps, worked out by hand."""

from __future__ import annotations

import numpy as np
import pytest

from nebula_rt.density.resample import box_averages


def random_octree(seed, roots=4, depth=3, p=0.45):
    """Leaves (lo, hi) of a forest of octrees over roots^3 cells, each cell split with
    probability p down to ``depth`` levels below the roots (a tree with holes in nothing: the
    leaves tile the unit box)."""
    rng = np.random.default_rng(seed)
    cells = [(np.array([i, j, k], float) / roots, 1.0 / roots, 0)
             for i in range(roots) for j in range(roots) for k in range(roots)]
    leaves = []
    while cells:
        lo, size, level = cells.pop()
        if level < depth and rng.random() < p:
            half = size / 2
            cells += [(lo + half * np.array(c, float), half, level + 1)
                      for c in np.ndindex(2, 2, 2)]
        else:
            leaves.append((lo, lo + size))
    lo = np.array([a for a, _ in leaves])
    hi = np.array([b for _, b in leaves])
    return lo, hi


@pytest.mark.parametrize("shape", [(8, 8, 8), (5, 7, 3), (64, 64, 64), (1, 1, 1)])
def test_the_leaves_of_a_random_tree_average_to_ones_and_keep_the_mass(shape):
    lo, hi = random_octree(3)
    vol = np.prod(hi - lo, axis=1)
    assert abs(vol.sum() - 1.0) < 1e-12 and len(lo) > 64  # the leaves tile the box, the tree is refined
    ones = box_averages(lo, hi, np.ones(len(lo)), shape)
    np.testing.assert_allclose(ones, 1.0, rtol=0, atol=1e-12)
    rho = np.random.default_rng(4).lognormal(0.0, 1.0, len(lo))
    avg = box_averages(lo, hi, rho, shape)
    mass = (rho * vol).sum()
    assert abs(avg.sum() / np.prod(shape) - mass) <= 1e-12 * mass
    assert avg.min() >= rho.min() * (1 - 1e-12) and avg.max() <= rho.max() * (1 + 1e-12)  # averages


def test_a_uniform_grid_given_as_boxes_comes_back():
    shape = (6, 5, 4)
    rho = np.random.default_rng(1).random(shape)
    idx = np.array(list(np.ndindex(*shape)), float)
    n = np.array(shape, float)
    got = box_averages(idx / n, (idx + 1) / n, rho.reshape(-1), shape)
    np.testing.assert_allclose(got, rho, rtol=1e-13, atol=0)


def test_coarse_aligned_leaves_fill_their_voxels():
    lo, hi = random_octree(7, roots=2, depth=2)
    values = np.arange(1.0, len(lo) + 1.0)
    got = box_averages(lo, hi, values, (16, 16, 16))  # finer than the finest leaf (1/8)
    centres = (np.array(list(np.ndindex(16, 16, 16))) + 0.5) / 16
    inside = np.all((centres[:, None, :] >= lo[None]) & (centres[:, None, :] < hi[None]), axis=2)
    assert (inside.sum(axis=1) == 1).all()
    np.testing.assert_allclose(got.reshape(-1), values[inside.argmax(axis=1)], rtol=1e-13)


def test_one_unaligned_box_by_hand():
    """Box [0.1, 0.6) x [0.25, 0.5) x [0, 1) of value 2 on a 2 x 2 x 1 grid: the x overlaps
    with the two voxel columns are 0.4 and 0.1, the y overlaps 0.25 and 0 (the box ends at the
    y face 0.5), so the averages are 2 x 0.4 x 0.25 / 0.25 = 0.8 and 2 x 0.1 x 0.25 / 0.25 = 0.2."""
    got = box_averages([[0.1, 0.25, 0.0]], [[0.6, 0.5, 1.0]], [2.0], (2, 2, 1))
    np.testing.assert_allclose(got[:, :, 0], [[0.8, 0.0], [0.2, 0.0]], rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("lo,hi,values,shape,needle", [
    ([[0, 0, 0]], [[1.2, 1, 1]], [1.0], (2, 2, 2), "inside the unit box"),
    ([[0.5, 0, 0]], [[0.5, 1, 1]], [1.0], (2, 2, 2), "lo < hi"),
    ([[0, 0, 0]], [[1, 1, 1]], [1.0, 2.0], (2, 2, 2), "same boxes"),
    ([[0, 0, 0]], [[1, 1, 1]], [1.0], (2, 0, 2), "3 positive sizes"),
])
def test_bad_boxes_are_refused(lo, hi, values, shape, needle):
    with pytest.raises(ValueError, match=needle):
        box_averages(lo, hi, values, shape)
