"""The slab Monte Carlo oracle (tests/oracles/slab_mc.py) against exact answers.

- Made laterally infinite, a star just above it: the transmitted and reflected power per
  steradian straight down and up against the adding-doubling solution
  (tests/oracles/plane_parallel.py), at optical depths 10 to 35 and albedos 0.3 to 0.9, where
  light that crossed depth 35 has scattered dozens of times; the stated errors over seeds.
- Finite and optically thin: the single-scattering integral over the slab's volume (a midpoint
  rule on a fine lattice), which checks its lateral geometry and its peel-off towards oblique
  observers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from oracles.plane_parallel import PointSourceSlab, Slab
from oracles.slab_mc import BoxSlab, _hg, scattered

WIDE = 1.0e4


@pytest.mark.parametrize("tau,albedo,g", [(10.0, 0.6, 0.6), (20.0, 0.9, 0.6), (30.0, 0.3, 0.6), (35.0, 0.45, 0.0),
                                          (35.0, 0.6, 0.6)])
def test_infinite_slab_is_exact(tau, albedo, g):
    s = BoxSlab(kappa=tau / 0.3, albedo=albedo, g=g, h=0.3, star=(0.0, 0.0, 0.3 + 1e-4), x0=-WIDE, x1=WIDE,
                y0=-WIDE, y1=WIDE)
    exact = PointSourceSlab(Slab(tau, albedo, g))
    want = np.array([exact.transmitted(1.0), exact.reflected(1.0)])
    pulls = []
    for seed in range(1, 5):
        v, e = scattered(s, [(0.0, 0.0, -1.0), (0.0, 0.0, 1.0)], 10_000, seed=seed)
        pulls.append((v - want) / e)
    pulls = np.array(pulls)
    # each run within 4 of its own sigma, and the stated errors not too small over the 8
    assert np.all(np.abs(pulls) < 4.0), pulls
    assert np.mean(pulls**2) < 2.5, pulls


def test_thin_finite_slab_is_the_single_scattering_integral():
    tau, albedo, g = 0.01, 0.6, 0.6
    s = BoxSlab(kappa=tau / 0.3, albedo=albedo, g=g, h=0.3, star=(0.5, 0.5, 0.9))
    dirs = np.array([[0.0, math.sin(t), math.cos(t)] for t in np.radians([0.0, 60.0, 90.0, 150.0, 180.0])])
    v, e = scattered(s, dirs, 200_000, seed=3)
    # midpoint rule: scattered power per sr = int kappa albedo e^-tau_in / (4 pi r^2) p(mu) e^-tau_out dV
    n = (100, 100, 30)
    axes = [(np.arange(k) + 0.5) / k * ext for k, ext in zip(n, (1.0, 1.0, 0.3))]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    p = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    r = p - np.array(s.star)
    dist = np.linalg.norm(r, axis=1)
    d = r / dist[:, None]
    tau_in = s.kappa * (s.h - p[:, 2]) / -d[:, 2]
    dv = 0.3 / np.prod(n)
    for j, o in enumerate(dirs):
        with np.errstate(divide="ignore"):
            t = np.where(o > 0, (np.array([1.0, 1.0, 0.3]) - p) / o,
                         np.where(o < 0, -p / np.where(o < 0, o, 1.0), np.inf)).min(axis=1)
        f = s.kappa * albedo * np.exp(-tau_in) / (4 * math.pi * dist**2) * _hg(g, d @ o) * np.exp(-s.kappa * t)
        want = f.sum() * dv
        assert abs(v[j] - want) < 4 * e[j] + 0.01 * want, (j, v[j], want, e[j])
