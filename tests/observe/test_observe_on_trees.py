"""Calibrated sky images, colour profiles, ring comparisons and fits on an octree, against the
uniform grid, which they did not use:

- a tree whose leaves are the 16^3 grid's voxels (``dust.octree`` refined wherever the density
  varies, the deepest leaves the grid's bits): the same packets give the grid's peel-off image
  to float32 rounding, the stars' optical depth to the observer is the grid's exact march to
  1e-12 (the sum over the leaves the ray crosses), and so the calibrated image, the colour
  profile and the ring sums are the grid's;
- the column through a random tree against the grid of its finest cells, along the axes (rays
  on faces and edges) and obliquely.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import TEST_BACKEND, TEST_DEVICE

from nebula_rt.density.generate import scene_density
from nebula_rt.density.octree import Octree, coarsen
from nebula_rt.observe import calibrate, comparison
from nebula_rt.observe import colours as observe
from nebula_rt.scene import Scene
from nebula_rt.transport.line_of_sight import density_column, line_of_sight_tau


def scene(octree: bool, **transport):
    return Scene.from_dict({
        "grid": {"shape": [16, 16, 16], "length": "0.2 pc"},
        "dust": {"model": "turbulence", "tau": 12.0, "octree": octree, "tree_depth": 4, "cell_tau": 1e-6,
                 "cell_tau_spread": 0.0},
        "stars": [{"position": [0.5, 0.47, 0.52], "luminosity_lsun": 100.0, "temperature": 9000.0, "bump_radius": 0.0}],
        "transport": {"photons": 20000, "seed": 3, "method": "analog", "backend": TEST_BACKEND, "device": TEST_DEVICE,
                      **transport},
        "observer": {"distance": "50 pc", "psf_fwhm": 30.0},
    })


def test_the_tree_is_the_grid_here(backend):
    tree = scene_density(scene(True), backend)
    assert isinstance(tree, Octree) and tree.n_leaves == 16**3 and tree.depth() == 4


@pytest.mark.parametrize("direction", [(0.0, 0.0, -1.0), (0.3, -0.5, -0.8)])
def test_a_calibrated_sky_image_on_a_tree_is_the_grids(backend, direction):
    cam = calibrate.camera_for(scene(False), direction=direction, size=24)
    cal_t, res_t = calibrate.peel_off_sky(scene(True), cam, backend)
    cal_g, res_g = calibrate.peel_off_sky(scene(False), cam, backend)
    np.testing.assert_array_equal(res_t.counts, res_g.counts)
    np.testing.assert_allclose(cal_t.star_flux_jy, cal_g.star_flux_jy, rtol=1e-12)
    np.testing.assert_allclose(cal_t.scattered, cal_g.scattered, rtol=2e-5, atol=1e-6 * cal_g.scattered.max())
    np.testing.assert_allclose(cal_t.surface_brightness, cal_g.surface_brightness, rtol=2e-5,
                               atol=1e-6 * cal_g.surface_brightness.max())


def test_colour_profiles_and_ring_sums_on_a_tree_are_the_grids(backend):
    edges = np.array([0.0, 0.1, 0.2, 0.35])
    prof_t, _ = observe.observe_scene(scene(True), size=24, edges=edges, backend=backend)
    prof_g, _ = observe.observe_scene(scene(False), size=24, edges=edges, backend=backend)
    np.testing.assert_allclose(prof_t.star_ebv, prof_g.star_ebv, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(prof_t.delta_bv, prof_g.delta_bv, rtol=0, atol=1e-5)
    rings_t = comparison.trace_rings(scene(True), edges, size=24, backend=backend)
    rings_g = comparison.trace_rings(scene(False), edges, size=24, backend=backend)
    np.testing.assert_allclose(rings_t.star_tau, rings_g.star_tau, rtol=1e-12)
    np.testing.assert_allclose(rings_t.sums, rings_g.sums, rtol=2e-5)


def test_the_column_through_a_random_tree_is_its_finest_grids():
    rng = np.random.default_rng(11)
    rho = rng.random((16, 16, 16)) + 0.05
    rho[:8, :8, :8] = 0.4  # merged into coarse leaves
    rho[8:, 8:, :8] = 1.3
    tree = coarsen(rho.astype(np.float32), (2, 2, 2))
    assert tree.n_leaves < 16**3
    grid = np.asarray(rho.astype(np.float32), np.float64)[None]
    for start, toward in [((0.5, 0.5, 0.5), (0, 0, 1)), ((0.5, 0.5, 0.5), (-1, 0, 0)), ((0.25, 0.5, 0.75), (0, 1, 0)),
                          ((0.31, 0.52, 0.47), (0.3, -0.2, 0.9)), ((0.3, 0.3, 0.3), (-1, -1, -1)),
                          ((0.5, 0.5, 1.0), (0, 1, 0)), ((-0.2, 0.4, 0.6), (1, 0.1, 0))]:
        np.testing.assert_allclose(density_column(tree, start, toward),
                                   line_of_sight_tau(grid, start, toward)[0], rtol=1e-12, err_msg=str((start, toward)))


@pytest.mark.filterwarnings("ignore:the model's Monte Carlo error")  # 5,000 packets: a small fit
def test_a_fit_on_a_tree_finds_the_grids_answer(backend):
    """The fit's traces on the tree are the grid's (to float32 rounding), so its best albedo,
    errors and chi^2 are the grid's."""
    from nebula_rt.observe import fit
    from nebula_rt.observe.observed_tables import ObservedTable

    table = ObservedTable("colour", "c", np.array([0.1, 0.2, 0.3]), np.array([-0.3, -0.28, -0.25]), np.full(3, 0.05),
                          np.array([0.05, 0.15, 0.25]), np.array([0.15, 0.25, 0.35]))
    runs = [fit.fit_observations(scene(octree, photons=5000), [table], ["albedo"], size=24, backend=backend)
            for octree in (True, False)]
    t, g = runs
    np.testing.assert_allclose(t.best, g.best, rtol=1e-4)
    np.testing.assert_allclose(t.chi2, g.chi2, rtol=1e-4)
    np.testing.assert_allclose([t.err_minus, t.err_plus], [g.err_minus, g.err_plus], rtol=1e-3)
