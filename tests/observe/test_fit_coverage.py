"""Fit errors to trust: over noisy realisations of a small scene, fitted with other seeds, the
profile errors' 1-sigma and 2-sigma intervals hold the truth at their nominal rates.

The problem (:func:`coverage_run`; ``benchmarks/bench_fit_coverage.py`` runs it with more
realisations and saves the figures): an 8^3 uniform cube of tau 1 across, one band at 555 nm
with albedo 0.6 and g 0.5, a 14,000 K star at (0.5, 0.5, 0.4), seen along -z; the observation
is the absolute nebula/star ratio in 4 annuli (0.03-0.4 box units) with 4 % errors. The truth's
ratios are traced once with 2,000,000 packets (seed 999; its Monte Carlo error, 0.3-0.7 % of
the values, is a tenth of the data's), and realisation r adds Gaussian noise of the errors
(numpy seed r) and is fitted (albedo in [0.2, 0.95], g in [0, 0.9]) by runs of
``photons`` packets with seed 1000 + r: every realisation has its own data noise and its own
Monte Carlo noise, as two observers with two runs would.
"""

from __future__ import annotations

import math

import numpy as np

from conftest import TEST_BACKEND, TEST_DEVICE
from nebula_rt.observe import fit
from nebula_rt.observe.comparison import compare_tables, ring_edges, trace_rings
from nebula_rt.observe.observed_tables import ObservedTable
from nebula_rt.scene import Scene

TRUTH = {"albedo": 0.6, "g": 0.5}
FREE = ["albedo=0.2:0.95", "g=0:0.9"]
ANNULI = [(0.03, 0.08), (0.08, 0.15), (0.15, 0.25), (0.25, 0.4)]
RATIO_ERR = 0.04
#: nominal coverage of +-1 and +-2 profile errors (Delta chi^2 = 1 and, for the second, 2x
#: the error, the quadratic's Delta chi^2 = 4)
NOMINAL = {1: math.erf(1 / math.sqrt(2)), 2: math.erf(2 / math.sqrt(2))}


def scene(albedo=0.6, g=0.5, photons=20_000, seed=1):
    return Scene.from_dict({
        "grid": {"shape": [8, 8, 8]},
        "dust": {"model": "uniform", "density": 1.0, "tau": 1.0},
        "stars": [{"position": [0.5, 0.5, 0.4], "temperature": 14000.0}],
        "bands": {"list": [{"name": "V", "wavelength": 555.0, "extinction": 1.0, "albedo": albedo, "g": g}]},
        "transport": {"photons": photons, "seed": seed, "backend": TEST_BACKEND, "device": TEST_DEVICE},
    })


def truth_table(backend, photons=2_000_000):
    """The ratio table with the truth's values (no noise yet) and the data's errors."""
    lo, hi = np.array([a[0] for a in ANNULI]), np.array([a[1] for a in ANNULI])
    x = np.full(len(ANNULI), 555.0)
    table = ObservedTable("ratio", "coverage ratio", x, np.ones_like(x), np.ones_like(x), lo, hi,
                          x_display=x, x_unit="nm", normalisation="absolute")
    rings = trace_rings(scene(photons=photons, seed=999, **TRUTH), ring_edges([table]), size=24, backend=backend)
    model = compare_tables(rings, [table]).results[0].model
    table.value, table.error = model.copy(), RATIO_ERR * model
    return table


def coverage_run(backend, realisations: int, photons: int = 20_000):
    """Fit ``realisations`` noisy observations; returns a list of (best, err_minus, err_plus,
    traces, seconds) per realisation, each array over the parameters in TRUTH's order."""
    import copy
    import time

    base = truth_table(backend)
    out = []
    for r in range(realisations):
        table = copy.deepcopy(base)
        table.value = base.value + base.error * np.random.default_rng(r).standard_normal(len(base.value))
        t0 = time.perf_counter()
        res = fit.fit_observations(scene(photons=photons, seed=1000 + r, albedo=0.5, g=0.4), [table], FREE, size=24,
                                   backend=backend, grid=2)
        out.append((np.asarray(res.best), np.asarray(res.err_minus), np.asarray(res.err_plus),
                    sum(res.traces.values()), time.perf_counter() - t0))
    return out


def covered(results, width: float) -> int:
    """Intervals [best - width err_minus, best + width err_plus] (every parameter of every
    realisation) that hold the truth."""
    truth = np.array(list(TRUTH.values()))
    return int(sum(((b - width * em <= truth) & (truth <= b + width * ep)).sum() for b, em, ep, *_ in results))


def test_profile_intervals_hold_the_truth_at_their_nominal_rates(backend):
    """20 realisations x 2 parameters = 40 intervals: the 1-sigma intervals hold the truth in
    27.3 +- 2.9 of them at the nominal 68.3 % (binomial standard deviation), the 2-sigma in
    38.2 +- 1.3 (95.4 %); each count must lie within 2.5 binomial standard deviations of its
    nominal value (a false alarm in about 1 % of problems). Errors half the right size would
    hold the truth in about 15 of 40 at 1 sigma, twice the right size in about 38: both fail."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (each fit's model-error note)
        results = coverage_run(backend, 20)
    n = 2 * len(results)
    for width, p in NOMINAL.items():
        got = covered(results, width)
        sd = math.sqrt(n * p * (1 - p))
        assert abs(got - n * p) <= 2.5 * sd, (width, got, n * p, sd)
