"""Particle snapshots on an octree (nebula_rt.density.particles): the kernel's normalisation and
shape against the formula, the tree refined by count, the deposit keeping the mass exactly and
giving a smooth field back where the particles sample one; bad particles refused by name."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from nebula_rt.density.particles import cubic_spline, deposit, refine_by_count


def test_the_kernel_integrates_to_one_and_is_the_cubic_spline():
    norm, _ = integrate.quad(lambda q: 4 * math.pi * q * q * cubic_spline(q), 0.0, 1.0, points=[0.5])
    assert abs(norm - 1.0) < 1e-12
    assert cubic_spline(0.0) == pytest.approx(8 / math.pi)
    assert cubic_spline(0.5) == pytest.approx(8 / math.pi * 0.25)  # 1 - 6/4 + 6/8 = 2 (1/2)^3 = 1/4
    assert cubic_spline(1.0) == 0.0 and cubic_spline(1.3) == 0.0


def test_the_tree_holds_at_most_so_many_particles_a_leaf():
    rng = np.random.default_rng(1)
    pts = np.concatenate([rng.random((500, 3)), 0.3 + 0.02 * rng.standard_normal((1500, 3))])
    pts = np.clip(pts, 0.0, 1.0)
    tree = refine_by_count(pts, (2, 2, 2), max_per_leaf=16, max_depth=6)
    counts = np.bincount(tree.locate(pts), minlength=tree.n_leaves)
    lo, hi, _ = tree.leaves()
    deepest = np.isclose(hi[:, 0] - lo[:, 0], 1 / (2 * 2 ** 6))
    assert counts[~deepest].max() <= 16 and counts.sum() == len(pts)
    assert tree.depth() >= 4  # the clump is refined, the background is not
    assert abs(np.prod(hi - lo, axis=1).sum() - 1.0) < 1e-12


def test_the_deposit_keeps_the_mass_and_the_smooth_field():
    """A lattice of equal particles, h two lattice spacings: the deposited density is the mean
    density (sum of masses, the box's volume 1) within 2 % away from the faces, whatever leaf
    sizes the tree chose; the leaves' masses sum to the particles' to 1e-12, faces included."""
    n = 24
    g = (np.arange(n) + 0.5) / n
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    m = np.full(len(pts), 1.0 / len(pts))
    tree = refine_by_count(pts, (1, 1, 1), max_per_leaf=64, max_depth=5)
    mass, rho = deposit(tree, pts, m, 2.0 / n, samples=8)
    assert abs(mass.sum() - 1.0) < 1e-12
    lo, hi, _ = tree.leaves()
    inner = np.all((lo > 0.15) & (hi < 0.85), axis=1)
    assert inner.sum() > 8
    np.testing.assert_allclose(rho[inner], 1.0, rtol=0.02)


def test_a_small_particle_puts_all_its_mass_in_its_leaf():
    tree = refine_by_count(np.array([[0.1, 0.1, 0.1], [0.9, 0.9, 0.9]]), (2, 2, 2), max_per_leaf=1, max_depth=0)
    mass, rho = deposit(tree, [[0.3, 0.2, 0.2], [0.999, 0.5, 0.5]], [2.0, 3.0], [1e-3, 0.2])
    leaf = tree.locate(np.array([[0.3, 0.2, 0.2]]))[0]
    assert mass[leaf] == pytest.approx(2.0, rel=1e-14)
    assert abs(mass.sum() - 5.0) < 1e-12  # the second one's kernel crosses the face: folded back
    assert rho[leaf] == pytest.approx(2.0 / 0.125)


@pytest.mark.parametrize("pos,mass,h,needle", [
    ([[0.5, 0.5, 1.2]], [1.0], 0.1, "particle 0 at .* outside the box"),
    ([[0.5, 0.5, np.nan]], [1.0], 0.1, "particle 0: position .* not finite"),
    ([[0.5, 0.5, 0.5]], [-1.0], 0.1, "particle 0: mass -1.0 must be >= 0"),
    ([[0.5, 0.5, 0.5]], [1.0], 0.0, "particle 0: smoothing length 0.0 must be > 0"),
    ([[0.5, 0.5, 0.5]], [1.0, 2.0], 0.1, "one of each per particle"),
])
def test_bad_particles_are_refused(pos, mass, h, needle):
    tree = refine_by_count(np.array([[0.5, 0.5, 0.5]]), (1, 1, 1))
    with pytest.raises(ValueError, match=needle):
        deposit(tree, pos, mass, h)
