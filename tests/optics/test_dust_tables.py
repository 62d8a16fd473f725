"""Draine's Milky Way dust tables and the spectral band presets built from them.

Reference values: REFERENCES.md's table of the R_V = 3.1 curve (albedo, g and A/A(V) at
350-800 nm, three significant digits) and the thesis's extinction factors 0.748 / 1.324 at
677 / 439 nm relative to 550 nm. Tolerances: half a unit in the last quoted digit, plus the
difference between A(V) (V band, ~545 nm effective) and A(550 nm) for the A/A(V) column.
"""

from __future__ import annotations

import numpy as np
import pytest

from nebula_rt.optics.bands import PRESETS, reference_band_index, resolve_bands, spectral_bands
from nebula_rt.optics.dust_tables import CITATION, band_average, draine_table

WL = [350, 400, 450, 500, 550, 600, 650, 700, 750, 800]
ALBEDO = [.613, .638, .656, .668, .674, .676, .675, .671, .665, .658]
G = [.568, .570, .564, .553, .537, .519, .499, .479, .458, .439]
A_AV = [1.66, 1.46, 1.28, 1.12, 0.99, 0.88, 0.79, 0.71, 0.64, 0.58]


def sample(rv, key, wl):
    t = draine_table(rv)
    return np.interp(wl, t["wavelength_nm"], t[key])


def test_table_matches_the_published_curve():
    np.testing.assert_allclose(sample("3.1", "albedo", WL), ALBEDO, atol=0.0015)
    np.testing.assert_allclose(sample("3.1", "g", WL), G, atol=0.0015)
    cext = sample("3.1", "cext", WL)
    np.testing.assert_allclose(cext / cext[4] * 0.99, A_AV, atol=0.012)
    # the thesis's R and B extinction factors are this curve at 677 and 439 nm
    c = sample("3.1", "cext", [439.0, 550.0, 677.0])
    assert c[2] / c[1] == pytest.approx(0.748, rel=0.01)
    assert c[0] / c[1] == pytest.approx(1.324, rel=0.01)


def test_band_averages():
    # a narrow band is the table's value there; a wide one lies within the band's range
    cext, alb, g = band_average("3.1", 549.5, 550.5)
    assert alb == pytest.approx(sample("3.1", "albedo", 550.0), abs=1e-4)
    assert g == pytest.approx(sample("3.1", "g", 550.0), abs=1e-4)
    cext, alb, g = band_average("3.1", 380.0, 430.0)
    lo, hi = sorted(sample("3.1", "cext", [380.0, 430.0]))
    assert lo < cext < hi
    # a flat curve averages to itself: albedo weighting by extinction keeps [min, max]
    a = sample("3.1", "albedo", np.arange(380, 431))
    assert a.min() <= alb <= a.max()


@pytest.mark.parametrize("name,n,rv", [("spectral-8", 8, "3.1"), ("spectral-16", 16, "3.1"),
                                       ("spectral-8-dense", 8, "5.5")])
def test_spectral_presets(name, n, rv):
    bands = resolve_bands(name, None)
    assert len(bands) == n and bands == spectral_bands(n, rv)
    wl = np.array([b.wavelength for b in bands])
    ext = np.array([b.extinction for b in bands])
    assert wl[0] == pytest.approx(380 + 200 / n) and wl[-1] == pytest.approx(780 - 200 / n)
    assert np.all(np.diff(ext) < 0)  # blue is extinguished more
    ref = reference_band_index(bands)
    assert ext[ref] == 1.0 and abs(wl[ref] - 550) <= 200 / n
    assert all(0.6 < b.albedo < 0.8 and 0.4 < b.g < 0.65 for b in bands)
    assert len({b.name for b in bands}) == n


def test_dense_dust_has_a_flatter_curve_and_brighter_grains():
    diffuse, dense = PRESETS["spectral-8"], PRESETS["spectral-8-dense"]
    # R_V = 5.5: larger grains, less selective extinction, higher albedo and g in the optical
    assert dense[0].extinction / dense[-1].extinction < diffuse[0].extinction / diffuse[-1].extinction
    assert all(d.albedo > m.albedo for d, m in zip(dense, diffuse))


def test_presets_are_listed_without_reading_the_tables():
    assert set(PRESETS) == {"thesis-rgb", "spectral-8", "spectral-16", "spectral-8-dense"}
    assert "Draine" in CITATION and "dust_extinction" in CITATION
