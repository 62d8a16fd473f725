"""The procedural density on an octree (nebula_rt.density.procedural_tree) against the uniform
grid's density kernel, which the tree builder does not use for its voxels:

- a leaf at the deepest level has the bits of the 2^depth grid's voxel there, and a leaf one
  level up the float64 mean of the grid's 8 voxels it covers (both made with the floor);
- every leaf above the deepest level passed the refinement tests it was declared with (optical
  depth per cell, its octants' spread in optical depth, the stars' bumps, the top levels);
- a uniform density stops at the top levels; the leaves tile the box;
- a tree refined wherever the density varies traces as the grid: the packets' fates agree to a
  few packets (the two walks form their faces with different float32 rounding);
- refusals name the key.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import TEST_BACKEND, TEST_DEVICE

from nebula_rt import limits
from nebula_rt.density.procedural_tree import MIN_LEVEL
from nebula_rt.density.generate import generate_density, scene_density
from nebula_rt.errors import SceneError
from nebula_rt.scene import Scene

BASE = f"""
[grid]
shape = [16, 16, 16]
[dust]
model = "turbulence"
octree = true
tree_depth = 5
tau = 40.0
[transport]
photons = 20000
backend = "{TEST_BACKEND}"
device = "{TEST_DEVICE}"
[[stars]]
position = [0.5, 0.5, 0.5]
luminosity = 1.0
temperature = 20000.0
bump_radius = 0.0
"""


def scene(*overrides):
    return Scene.loads(BASE).with_overrides(list(overrides))


def grid_of(sc, n):
    return generate_density(sc.with_overrides(["dust.octree=false", f"grid.shape=[{n},{n},{n}]"]), _backend())


def _backend():
    from nebula_rt.backends import get_backend

    return get_backend(TEST_BACKEND, TEST_DEVICE)


def leaf_levels(tree):
    lo, hi, d = tree.leaves()
    return lo, np.rint(-np.log2(hi[:, 0] - lo[:, 0])).astype(int), np.asarray(d)


def test_deepest_leaves_are_the_grid_and_the_next_level_its_means(backend):
    sc = scene("dust.cell_tau_spread=0.05")
    tree = scene_density(sc, backend)
    lo, level, d = leaf_levels(tree)
    g = grid_of(sc, 32)
    fine = level == 5
    assert 1000 < fine.sum() < tree.n_leaves  # both kinds of leaves are there
    i = np.rint(lo[fine] * 32).astype(int)
    np.testing.assert_array_equal(d[fine], g[i[:, 0], i[:, 1], i[:, 2]])
    up = level == 4
    assert up.sum() > 100
    i = np.rint(lo[up] * 32).astype(int)
    blocks = np.stack([g[i[:, 0] + a, i[:, 1] + b, i[:, 2] + c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])
    np.testing.assert_array_equal(d[up], blocks.astype(np.float64).mean(axis=0).astype(np.float32))


def test_every_coarse_leaf_passed_the_refinement_tests(backend):
    sc = scene("dust.cell_tau=0.2", "dust.cell_tau_spread=0.1")
    tree = scene_density(sc, backend)
    lo, level, d = leaf_levels(tree)
    assert level.min() >= MIN_LEVEL
    coarse = level < 5
    assert coarse.any() and (~coarse).any()
    edge = 0.5 ** level[coarse]
    # the reference band's extinction is 1: a cell's optical depth is tau x density x edge
    assert np.all(40.0 * d[coarse].astype(np.float64) * edge <= 0.2 * (1 + 1e-6))
    # and its octants' values (the grid's voxels one level down, when that level is the
    # deepest) spread in optical depth across the cell by at most cell_tau_spread
    g = grid_of(sc, 32)
    at4 = level == 4
    i = np.rint(lo[at4] * 32).astype(int)
    blocks = np.stack([g[i[:, 0] + a, i[:, 1] + b, i[:, 2] + c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])
    spread = blocks.max(0).astype(np.float64) - blocks.min(0)
    assert np.all(40.0 * spread / 16 <= 0.1 * (1 + 1e-6))
    # the leaves tile the box
    np.testing.assert_allclose(np.sum(0.125 ** level), 1.0, rtol=1e-12)


def test_a_uniform_density_stops_at_the_top_levels(backend):
    tree = scene_density(scene('dust.model="uniform"', "dust.density=2.0", "dust.tau=0.2"), backend)
    assert tree.n_leaves == 8 ** MIN_LEVEL
    np.testing.assert_array_equal(tree.density, np.float32(2.0))
    # (0.2 x 2 / 8 = 0.05 per cell at level 3); at tau 40, 40 x 1 / 16 = 2.5 > 0.1: split to the deepest level
    deep = scene_density(scene('dust.model="uniform"', "dust.tree_depth=4"), backend)
    assert deep.n_leaves == 8 ** 4


def test_a_star_bump_is_refined_to_its_radius(backend):
    sc = scene('dust.model="uniform"', "dust.tau=0.5", "stars.0.bump_radius=0.05", "stars.0.position=[0.3,0.6,0.5]")
    tree = scene_density(sc, backend)
    lo, level, d = leaf_levels(tree)
    edge = 0.5 ** level
    s = np.array([0.3, 0.6, 0.5])
    # (strictly inside: a cell whose face is the bump's reach gets none of it)
    near = np.sum((np.clip(s, lo, lo + edge[:, None]) - s) ** 2, axis=1) < (0.05 * (1 - 1e-6)) ** 2
    assert near.any() and np.all(edge[near] <= 0.05)
    # the bump is there: leaves at the star are denser than the uniform 1
    assert d[tree.locate(s[None, :])[0]] > 1.3


def test_a_tree_refined_wherever_the_density_varies_traces_as_the_grid(backend):
    from nebula_rt.pipeline import Pipeline

    sc = scene("dust.cell_tau_spread=0.0", "dust.cell_tau=1e-6", "dust.tree_depth=4", "grid.shape=[16,16,16]",
               "transport.estimator=\"track-length\"", 'transport.method="analog"', "transport.batch_size=10000")
    tree = scene_density(sc, backend)
    lo, level, d = leaf_levels(tree)
    assert np.all(level == 4)  # nothing merged: every cell varies
    light_tree = Pipeline(backend).run(sc, colour=False)
    light_grid = Pipeline(backend).run(sc.with_overrides(["dust.octree=false"]), colour=False)
    ct, cg = light_tree.transport.counts, light_grid.transport.counts
    assert np.all(ct[:, 0] == 20_000) and np.all(cg[:, 0] == 20_000)
    assert np.abs(ct[:, 1:] - cg[:, 1:]).max() <= 5, (ct, cg)
    np.testing.assert_allclose(light_tree.density, light_grid.density, rtol=1e-6)
    # the light per voxel within the two runs' stated errors (independent only in rounding:
    # the same packets, so far closer than that)
    J_t, J_g = light_tree.J[0], light_grid.J[0]
    lit = J_g > 0
    assert np.median(np.abs(J_t[lit] - J_g[lit]) / (J_g[lit] * light_grid.rel_error[0][lit] + 1e-300)) < 0.1


def test_refusals_name_the_key(backend, monkeypatch):
    with pytest.raises(SceneError) as e:
        generate_density(scene(), backend)
    assert e.value.parameter == "dust.octree"
    with pytest.raises(SceneError) as e:
        scene_density(scene('dust.model="file"', 'dust.file="x.npy"'), backend)
    assert e.value.parameter == "dust.octree" and '"file"' in str(e.value)
    monkeypatch.setattr(limits, "INT32_MAX", 1000)
    with pytest.raises(SceneError) as e:
        scene_density(scene(), backend)
    assert e.value.parameter == "dust.cell_tau" and "1000 nodes" in str(e.value)
    for bad in ("dust.octree=2", 'dust.octree="yes"', "dust.cell_tau=0.0", "dust.cell_tau_spread=-1.0"):
        with pytest.raises(SceneError) as e:
            scene(bad)
        assert e.value.parameter == bad.split("=")[0]


def test_a_central_stars_bump_is_resolved_as_on_the_finest_grid(backend):
    """The refinement sees the bump's own density: the light a central star's bump absorbs on
    the tree is the 2^depth grid's, within the two runs' binomial errors (other seeds). With the
    bump left out of the tests (cells split only down to its radius), the tree absorbed 0.08-0.13
    less of the light than the grid here (binomial sigma 0.003)."""
    from nebula_rt.pipeline import Pipeline

    sc = scene('dust.model="uniform"', "dust.density=0.01", "dust.tau=20.0", "stars.0.bump_radius=0.1",
               "dust.cell_tau=0.05", "dust.tree_depth=5", "transport.photons=40000", 'transport.method="analog"')
    tree = scene_density(sc, backend)
    assert tree.n_leaves < 0.2 * 32**3  # adaptive: fine at the bump only
    t = Pipeline(backend).run(sc, colour=False).transport.counts
    g = Pipeline(backend).run(sc.with_overrides(["dust.octree=false", "grid.shape=[32,32,32]", "transport.seed=7"]),
                              colour=False).transport.counts
    n = 40000
    pt, pg = t[:, 1] / n, g[:, 1] / n
    sigma = np.sqrt(pt * (1 - pt) / n + pg * (1 - pg) / n)
    assert np.all(np.abs(pt - pg) < 4 * sigma), (pt, pg, sigma)
