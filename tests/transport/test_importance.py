"""The weight windows' maps (nebula_rt.transport.importance) against answers worked out by hand.

- The decay rate k of thick dust: 1 for a pure absorber; for isotropic scattering the root of
  Case's dispersion relation (a / 2k) ln((1 + k) / (1 - k)) = 1 (Case & Zweifel 1967), solved
  here with SciPy; for HG scattering the plane-parallel oracle's own eigenvalue solver
  (tests/oracles/plane_parallel.py, written apart from the library).
- The stars' map: below a star above a uniform slab, the vertical optical depth.
- The observer's map: for a slab, the optical depth to the face the observer sees, so that seen
  from the side away from the star it is the stars' map up to a constant (the same windows),
  and seen from the star's side the star's cell is its maximum (no window below W0); light
  behind a dense core goes round it; the line of sight in uniform dust is the distance to the
  box's edge times the extinction.
- The choice: by the run's product, every wrong value refused by name.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from scipy.optimize import brentq

from nebula_rt.transport import importance
from nebula_rt.errors import NebulaWarning, SceneError
from nebula_rt.observe.sky import Camera
from nebula_rt.transport import trace
from oracles.plane_parallel import decay_rate as oracle_decay_rate
from slab_scene import peel_bins, slab


@pytest.mark.parametrize("albedo", (0.2, 0.6, 0.9, 0.99))
def test_decay_rate_of_isotropic_scattering_solves_case_dispersion_relation(albedo):
    """(Towards k = 1, at small albedo, the eigenfunction peaks at mu = 1 and the 48 nodes
    resolve k to 6e-5: 0.4 % of a window at optical depth 60.)"""
    k = brentq(lambda k: albedo / (2 * k) * math.log((1 + k) / (1 - k)) - 1.0, 1e-9, 1 - 1e-12)
    assert importance.decay_rate(albedo, 0.0) == pytest.approx(k, rel=1e-4 if albedo < 0.5 else 1e-6)


@pytest.mark.parametrize("albedo,g", [(0.3, 0.6), (0.6, 0.6), (0.9, 0.3), (0.9, 0.8)])
def test_decay_rate_of_hg_scattering_matches_the_oracle(albedo, g):
    assert importance.decay_rate(albedo, g) == pytest.approx(oracle_decay_rate(albedo, g), rel=1e-5)


def test_decay_rate_limits():
    assert importance.decay_rate(0.0, 0.6) == 1.0
    assert importance.decay_rate(1.0, 0.6) == 0.0


def _slab(n=16, top=12, bottom=4, sigma=40.0):
    """Extinction per box unit of a uniform slab between z layers ``bottom`` and ``top``."""
    s = np.zeros((n, n, n))
    s[:, :, bottom:top] = sigma
    return s, (top - bottom) / n * sigma


def test_stars_map_is_the_vertical_depth_below_the_star():
    sigma, tau = _slab()
    d = importance.depth_map(sigma, [(0.53, 0.53, 0.97)])
    column = d[8, 8].astype(np.float64)
    # cell centres z = (k + 0.5) / 16; the edge from k to k + 1 costs the mean of the two
    # cells times 1/16; the slab's cells 4..11 each 40/16 = 2.5
    expected = np.zeros(16)
    for k in range(14, -1, -1):
        expected[k] = expected[k + 1] + 0.5 * (sigma[8, 8, k] + sigma[8, 8, k + 1]) / 16
    assert np.allclose(column[:15], expected[:15], rtol=1e-6, atol=1e-6)
    assert column[0] == pytest.approx(tau, rel=1e-6)


def test_observer_map_seen_through_the_slab_is_the_stars_map_shifted():
    """Seen from below (the star above), the observer's importance and the light field fall
    together: the two maps differ by a constant where the light goes (the column below the
    star), so the windows W0 e^-k (D - D_star) are the same."""
    sigma, _ = _slab()
    stars = importance.depth_map(sigma, [(0.53, 0.53, 0.97)])[8, 8].astype(np.float64)
    obs = importance.observer_depth_map(sigma, (0.0, 0.0, -1.0))[8, 8].astype(np.float64)
    assert np.allclose((obs - obs[-2]) - (stars - stars[-2]), 0.0, atol=1e-5)


def test_observer_map_on_the_star_side_has_its_maximum_at_the_star():
    """Seen from the star's side, the deep layers matter least: D falls with depth, so no
    window below the star's (the kernel's windows never rise above W0: packets going down are
    not split)."""
    sigma, tau = _slab()
    obs = importance.observer_depth_map(sigma, (0.0, 0.0, 1.0))
    column = obs[8, 8].astype(np.float64)
    assert column[15] == pytest.approx(obs.max())
    assert np.all(np.diff(column[4:13]) > 0)
    # tau_obs at the slab's lowest cell centre: 7.5 cells of 2.5, or less by a path round the
    # slab's edge, which its width (16 cells of 2.5) forbids
    assert column[15] - column[4] == pytest.approx(7.5 * 2.5, rel=1e-5)
    assert column[15] - column[0] == pytest.approx(tau, rel=1e-5)


def test_observer_map_goes_round_a_dense_core():
    """Behind a core of optical depth 200 (along the view), light reaches the observer round
    it: the line of sight is blocked, the map's way out is clear."""
    sigma = np.zeros((16, 16, 16))
    sigma[6:10, 6:10, 6:10] = 800.0
    h = np.full(3, 1.0 / 16)
    los = importance.line_of_sight_depth(sigma, h, (1.0, 0.0, 0.0))
    assert los[2, 8, 8] == pytest.approx(4 / 16 * 800.0, rel=1e-6)
    obs = importance.observer_depth_map(sigma, (1.0, 0.0, 0.0))
    assert obs.max() - obs[2, 8, 8] < 1e-3


@pytest.mark.parametrize("toward", [(1.0, 2.0, -0.5), (-0.3, 0.0, 1.0), (0.0, -1.0, 0.0)])
def test_line_of_sight_in_uniform_dust_is_the_way_to_the_edge(toward):
    n, s = 12, 7.0
    sigma = np.full((n, n, n), s)
    h = np.full(3, 1.0 / n)
    los = importance.line_of_sight_depth(sigma, h, toward)
    u = np.asarray(toward) / np.linalg.norm(toward)
    c = (np.arange(n) + 0.5) / n
    x = np.stack(np.meshgrid(c, c, c, indexing="ij"), -1)
    with np.errstate(divide="ignore"):
        to_edge = np.where(u > 0, (1.0 - x) / u, np.where(u < 0, -x / u, np.inf)).min(axis=-1)
    # steps of half a cell, each counted by its middle: off by at most half a step
    step = 0.5 / n
    assert np.all(np.abs(los - s * to_edge) <= s * 0.5 * step + 1e-9)
    if np.count_nonzero(u) == 1:  # along an axis the steps end at the edge: exact
        assert np.allclose(los, s * to_edge, rtol=1e-12)


def test_the_choice_follows_the_product():
    cam = Camera(direction=(0.0, 0.0, 1.0))
    assert importance.resolve_importance("auto", cam) == "observer"
    assert importance.resolve_importance("auto", None) == "stars"
    assert importance.resolve_importance("stars", cam) == "stars"
    with pytest.raises(SceneError, match=r"importance = 'observer': .*no observer"):
        importance.resolve_importance("observer", None)
    with pytest.raises(SceneError, match=r"importance = 'adjoint': \"auto\" or \"stars\" or \"observer\""):
        importance.resolve_importance("adjoint", cam)


def test_a_run_says_which_windows_it_took(backend):
    rho, bands, stars, kappa, cam = slab(10.0, side="above")
    kw = dict(tau=kappa, photons=2000, seed=1, backend=backend, peel=cam, peel_bins=peel_bins(cam))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NebulaWarning)
        assert trace(rho, bands, stars, method="biased", **kw).importance == "observer"
        assert trace(rho, bands, stars, method="biased", importance="stars", **kw).importance == "stars"
        assert trace(rho, bands, stars, method="analog", **kw).importance == ""
        with pytest.raises(SceneError, match="importance"):
            trace(rho, bands, stars, method="biased", importance="camera", **kw)
