"""Bands are independent: each band's light depends on its own dust properties only.

Random numbers are keyed by (seed, band index, packet) (docs/physics.md), so a band gives the
same bits in any set of bands in which it has the same index, whatever its companions:
- a band traced alone (index 0) and first in a set: identical sums, counts, J / L_b;
- a band at index 1 or 2 of the set and at the same index among other companions: identical.
Traced alone, a band at index 1 or 2 draws other random numbers: compared statistically,
its escape and absorption fractions (binomial, 5 sigma of the difference of two independent
runs) and its J / L_b summed over a sparse lattice of voxels (every other voxel along each
axis in the lit shell 0.1 < r < 0.45, whose batch-means errors are close to independent: few
packets cross two of them; tests/transport/test_estimators.py measures this), within 5 standard errors
of the ratio of the sums, which is under 0.2 % at 10^6 packets (a 1 % error in a band's
normalisation is more than 5 sigma).
The bands' albedos, g and extinctions all differ, so exchanging any two bands' properties
changes a band's result.

The emissivity the pipeline writes is each band's own albedo x extinction x J.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import centre_star, voxel_centres
from nebula_rt.optics.bands import Band
from nebula_rt.pipeline import Pipeline
from nebula_rt.scene import Scene
from nebula_rt.transport import trace

SHAPE = (16, 16, 16)
TAU = 2.0
PHOTONS = 100_000  # the bit-for-bit comparisons
PHOTONS_STAT = 1_000_000  # the statistical ones: a standard error of 0.2 % on J / L_b
SEED = 3
BANDS = [
    Band(name="B", wavelength=440.0, extinction=1.3, albedo=0.45, g=0.55),
    Band(name="V", wavelength=550.0, extinction=1.0, albedo=0.60, g=0.45),
    Band(name="R", wavelength=650.0, extinction=0.8, albedo=0.75, g=0.35),
]


def run(bands, photons=PHOTONS, backend=None):
    rho = np.ones(SHAPE, np.float32)
    return trace(rho, bands, centre_star(), tau=TAU, photons=photons, seed=SEED, backend=backend)


@pytest.fixture(scope="module")
def together(backend):
    return run(BANDS, backend=backend)


@pytest.fixture(scope="module")
def together_long(backend):
    return run(BANDS, PHOTONS_STAT, backend=backend)


def same_bits(res_a, a, res_b, b):
    np.testing.assert_array_equal(res_a.raw_sum[a], res_b.raw_sum[b])
    np.testing.assert_array_equal(res_a.raw_m2[a], res_b.raw_m2[b])
    np.testing.assert_array_equal(res_a.counts[a], res_b.counts[b])
    # J per unit luminosity: the same up to the rounding of the packet energy L_b / N to
    # 53 - bit_length(N) bits (transport.exact_packet_energy), twice
    rtol = 2.0 * 2.0 ** -(52 - PHOTONS.bit_length())
    np.testing.assert_allclose(res_a.J[a] / res_a.band_luminosity[a], res_b.J[b] / res_b.band_luminosity[b],
                               rtol=rtol)


def test_same_index_same_bits_whatever_the_companions(backend, together):
    same_bits(together, 0, run(BANDS[:1], backend=backend), 0)  # B alone
    same_bits(together, 1, run([BANDS[2], BANDS[1]], backend=backend), 1)  # V after R
    same_bits(together, 2, run([BANDS[1], BANDS[0], BANDS[2]], backend=backend), 2)  # R after V, B


def sparse_lit_voxels():
    X, Y, Z = voxel_centres(SHAPE)
    r = np.sqrt((X - 0.5) ** 2 + (Y - 0.5) ** 2 + (Z - 0.5) ** 2)
    i, j, k = np.meshgrid(*[np.arange(n) for n in SHAPE], indexing="ij")
    return (r > 0.1) & (r < 0.45) & (i % 2 == 0) & (j % 2 == 0) & (k % 2 == 0)


@pytest.mark.parametrize("b", [1, 2])
def test_band_alone_matches_the_band_in_a_set(backend, together_long, b):
    together = together_long
    alone = run(BANDS[b:b + 1], PHOTONS_STAT, backend=backend)
    n = PHOTONS_STAT
    for tally in (1, 2):  # absorbed, escaped
        p1, p2 = together.counts[b, tally] / n, alone.counts[0, tally] / n
        p = 0.5 * (p1 + p2)
        sigma = math.sqrt(2 * p * (1 - p) / n)
        assert abs(p1 - p2) < 5 * sigma, (tally, p1, p2, sigma)
    mask = sparse_lit_voxels()
    j1 = together.J[b][mask] / together.band_luminosity[b]
    j2 = alone.J[0][mask] / alone.band_luminosity[0]
    s1, s2 = j1 * together.rel_error[b][mask], j2 * alone.rel_error[0][mask]
    # the ratio of the sums over the lattice and its standard error (independent voxels and runs)
    d = j1.sum() / j2.sum() - 1
    se = math.sqrt(np.sum(s1**2) + np.sum(s2**2) * (1 + d) ** 2) / j2.sum()
    assert abs(d) < 5 * se, (d, se)
    assert se < 0.002, se


def test_swapped_properties_would_show(backend, together):
    """The teeth of the statistical comparison: V traced alone with R's albedo differs from
    the set's V by far more than 5 sigma in its absorbed fraction."""
    wrong = Band(name="V", wavelength=550.0, extinction=1.0, albedo=BANDS[2].albedo, g=BANDS[1].g)
    alone = run([wrong], backend=backend)
    p1, p2 = together.counts[1, 1] / PHOTONS, alone.counts[0, 1] / PHOTONS
    sigma = math.sqrt(2 * 0.25 / PHOTONS)  # p (1 - p) <= 1/4
    assert abs(p1 - p2) > 20 * sigma


def test_emissivity_is_each_bands_own_albedo_times_extinction_times_j(backend):
    scene = Scene.from_dict({
        "grid": {"shape": [10, 10, 10]},
        "dust": {"model": "uniform", "density": 1.0, "tau": TAU},
        "stars": [{"position": [0.5, 0.5, 0.5], "luminosity": 1.0}],
        "bands": {"list": [{"name": b.name, "wavelength": b.wavelength, "extinction": b.extinction,
                            "albedo": b.albedo, "g": b.g} for b in BANDS]},
        "transport": {"photons": 20_000},
    })
    light = Pipeline(backend).run(scene, colour=False)
    J = light.J.astype(np.float64)
    for k, band in enumerate(BANDS):
        want = band.albedo * TAU * band.extinction * light.density.astype(np.float64) * J[k]
        # float32 outputs of float64 arithmetic: the ratio is 1 to float32 rounding
        np.testing.assert_allclose(light.emissivity[k], want, rtol=3e-7, atol=0.0)
