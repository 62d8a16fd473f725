"""The octree of a uniform density (nebula_rt.density.octree): its leaves tile the box, keep the
mass exactly, and give back the density where nothing merged; uniform blocks merge up to the
roots; the flat layout is what the module says (roots first, 8 children together, leaves
numbered by -1 - index)."""

from __future__ import annotations

import numpy as np
import pytest

from nebula_rt.density.octree import coarsen, from_boxes
from nebula_rt.density.resample import box_averages


def _volumes(lo, hi):
    return np.prod(hi - lo, axis=1)


def test_a_uniform_density_is_its_root_cells():
    tree = coarsen(np.full((16, 8, 8), 2.5), (4, 2, 2))
    assert tree.n_leaves == 16 and tree.depth() == 0 and (tree.child == -1 - np.arange(16)).all()
    lo, hi, rho = tree.leaves()
    np.testing.assert_allclose(hi - lo, np.broadcast_to([0.25, 0.5, 0.5], lo.shape))
    assert (rho == 2.5).all()


def test_nothing_merges_where_every_value_differs():
    rho = np.random.default_rng(2).random((8, 8, 8)) + 0.1
    tree = coarsen(rho, (1, 1, 1))
    assert tree.n_leaves == 512 and tree.depth() == 3
    assert len(tree.child) == 1 + 8 + 64 + 512  # every node refined down to the voxels
    lo, hi, dens = tree.leaves()
    np.testing.assert_array_equal(box_averages(lo, hi, dens, (8, 8, 8)), rho.astype(np.float32))


def test_a_clumpy_density_merges_its_smooth_parts_and_keeps_the_mass():
    """A smooth background with a few dense clumps: tolerance 0.05 merges the background into
    large leaves, the clumps stay refined; the leaves tile the box, their mass is the grid's,
    and the voxel averages of the leaves are within the tolerance of the density."""
    n = 32
    x = (np.arange(n) + 0.5) / n
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    rho = 1.0 + 0.001 * X
    for c in ((0.3, 0.3, 0.3), (0.7, 0.6, 0.4)):
        rho = rho + 50.0 * np.exp(-((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2) / 0.002)
    tree = coarsen(rho, (2, 2, 2), tolerance=0.05)
    lo, hi, dens = tree.leaves()
    vol = _volumes(lo, hi)
    assert abs(vol.sum() - 1.0) < 1e-12
    assert tree.n_leaves < n ** 3 / 8 and tree.depth() == 4  # merged a lot, refined to the voxels somewhere
    assert abs((dens.astype(np.float64) * vol).sum() - rho.mean()) <= 1e-6 * rho.mean()  # float32 leaves
    back = box_averages(lo, hi, dens, rho.shape)
    assert np.max(np.abs(back - rho) / rho) <= 0.05 + 1e-6


def test_the_flat_layout():
    rho = np.ones((4, 4, 4))
    rho[:2, :2, :2] = np.arange(8).reshape(2, 2, 2, order="F") + 2.0  # only octant 0 of the root differs
    tree = coarsen(rho, (1, 1, 1))
    # root -> 8 children at 1..8; child 0 (x, y, z low) -> 8 leaves; the other 7 children are leaves
    assert tree.child[0] == 1
    inner = [i for i in range(1, 9) if tree.child[i] >= 0]
    assert inner == [1] and tree.child[1] == 9
    assert (tree.child[9:17] < 0).all() and len(tree.child) == 17
    lo, hi, dens = tree.leaves()
    fine = np.isclose(hi[:, 0] - lo[:, 0], 0.25)
    assert fine.sum() == 8 and (dens[~fine] == 1.0).all()
    # the fine leaves' values are octant order c = ix + 2 iy + 4 iz of voxels [0:2]^3
    ids = -1 - tree.child[9:17]
    corner = np.round(lo[ids] * 4).astype(int)
    np.testing.assert_array_equal(dens[ids], rho[corner[:, 0], corner[:, 1], corner[:, 2]])
    assert [tuple(c) for c in corner] == [(i, j, k) for k in range(2) for j in range(2) for i in range(2)]


@pytest.mark.parametrize("shape,roots,tol,needle", [
    ((12, 12, 12), (1, 1, 1), 0.0, "power of 2"),
    ((8, 8, 4), (1, 1, 1), 0.0, "power of 2"),
    ((8, 8, 8), (1, 0, 1), 0.0, "positive"),
    ((8, 8, 8), (1, 1, 1), -0.1, "tolerance"),
])
def test_bad_input_is_refused(shape, roots, tol, needle):
    with pytest.raises(ValueError, match=needle):
        coarsen(np.ones(shape), roots, tol)


def test_negative_or_nan_density_is_refused():
    for bad in (-1.0, np.nan):
        rho = np.ones((4, 4, 4))
        rho[1, 2, 3] = bad
        with pytest.raises(ValueError, match="finite and >= 0"):
            coarsen(rho, (1, 1, 1))


def _random_boxes(seed):
    from test_box_averages import random_octree  # (tests/density is on the test path)

    return random_octree(seed, roots=3, depth=3)


def test_the_leaves_of_a_tree_make_the_same_tree():
    n = 16
    rho = np.ones((n, n, n))
    rho[3:7, 2:9, 5:6] = 7.0
    rho[12, 12, 12] = 3.0
    tree = coarsen(rho, (2, 2, 2))
    lo, hi, dens = tree.leaves()
    again = from_boxes(lo, hi, dens, (2, 2, 2))
    np.testing.assert_array_equal(again.child, tree.child)
    np.testing.assert_array_equal(again.density, tree.density)


def test_boxes_in_any_order_keep_their_numbers():
    lo, hi = _random_boxes(5)
    vals = np.random.default_rng(6).random(len(lo))
    perm = np.random.default_rng(7).permutation(len(lo))
    tree = from_boxes(lo[perm], hi[perm], vals[perm], (3, 3, 3))
    tlo, thi, tval = tree.leaves()  # leaf i is box i as given
    np.testing.assert_allclose(tlo, lo[perm], atol=1e-15)
    np.testing.assert_allclose(thi, hi[perm], atol=1e-15)
    np.testing.assert_array_equal(tval, vals[perm].astype(np.float32))
    assert tree.depth() == int(np.rint(np.log2(1 / (3 * (hi - lo)[:, 0].min()))))


def test_boxes_that_are_not_a_tiling_are_refused():
    lo, hi = _random_boxes(8)
    vals = np.ones(len(lo))
    roots = (3, 3, 3)
    with pytest.raises(ValueError, match="holes"):
        from_boxes(lo[1:], hi[1:], vals[1:], roots)
    with pytest.raises(ValueError, match="inside another|holes|twice"):
        from_boxes(np.vstack([lo, [[0, 0, 0]]]), np.vstack([hi, [[1 / 3, 1 / 3, 1 / 3]]]), np.ones(len(lo) + 1), roots)
    shifted = lo.copy()
    shifted[0] += 1e-3
    with pytest.raises(ValueError, match="box 0 .* not a cell"):
        from_boxes(shifted, hi, vals, roots)
    flat = hi.copy()
    flat[2, 2] = lo[2, 2] + (hi[2, 2] - lo[2, 2]) / 2  # halved on one axis only
    with pytest.raises(ValueError, match="box 2 .* not a cell"):
        from_boxes(lo, flat, vals, roots)
    for bad in (np.nan, -1.0):
        v = vals.copy()
        v[4] = bad
        with pytest.raises(ValueError, match="box 4: density"):
            from_boxes(lo, hi, v, roots)


def test_every_point_is_found_in_the_leaf_that_holds_it():
    lo, hi = _random_boxes(11)
    tree = from_boxes(lo, hi, np.arange(len(lo), dtype=float), (3, 3, 3))
    pts = np.random.default_rng(12).random((5000, 3))
    pts[:3] = [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1 / 3, 0.5, 2 / 3]]  # corners and root faces
    got = tree.locate(pts)
    inside = np.all((pts[:, None, :] >= lo[None]) & (pts[:, None, :] < hi[None]), axis=2)
    inside[1, np.argmax(np.all(np.isclose(hi, 1.0), axis=1))] = True  # the high corner: the last cell
    want = inside.argmax(axis=1)
    assert (inside.sum(axis=1) >= 1).all()
    np.testing.assert_array_equal(got, want)
