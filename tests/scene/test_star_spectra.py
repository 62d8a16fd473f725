"""Star spectra: blackbody or measured, several stars, band luminosities as band integrals."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate

from nebula_rt.optics.bands import PRESETS
from nebula_rt.optics.colour_convert import band_edges, band_luminosity_fractions, star_spectrum
from nebula_rt.errors import SceneError
from nebula_rt.scene import Scene
from nebula_rt.scene import Star
from nebula_rt.transport.plan import star_band_luminosities

EIGHT = np.array([b.wavelength for b in PRESETS["spectral-8"]])


def test_band_edges_split_the_range_at_midpoints():
    np.testing.assert_allclose(band_edges([677.0, 550.0, 439.0]), [380.0, 494.5, 613.5, 780.0])
    np.testing.assert_allclose(band_edges(EIGHT), np.arange(380.0, 781.0, 50.0))
    # centres outside 380-780 nm widen the range so every band keeps some light
    assert band_edges([350.0, 900.0])[[0, -1]].tolist() == [350.0, 900.0]


@pytest.mark.parametrize("source", [5800.0, 20000.0, ((380.0, 1.0), (500.0, 3.0), (620.0, 0.5), (780.0, 2.0))])
def test_band_luminosities_are_band_integrals(source):
    """f_b = int over band b of S / int over 380-780 nm of S, against adaptive quadrature."""
    f = band_luminosity_fractions(EIGHT, source)
    edges = band_edges(EIGHT)

    def S(x):
        return float(star_spectrum(source, np.array([x]))[0])

    total = integrate.quad(S, 380.0, 780.0, points=[500.0, 620.0], limit=200)[0]
    want = [integrate.quad(S, a, b, points=[p for p in (500.0, 620.0) if a < p < b], limit=200)[0] / total
            for a, b in zip(edges[:-1], edges[1:])]
    # trapezoid on a 1 nm grid: exact for the piecewise-linear measured spectrum, ~1e-6 for
    # the smooth blackbody
    np.testing.assert_allclose(f, want, rtol=1e-5)
    assert f.sum() == pytest.approx(1.0, abs=1e-12)


def test_measured_spectrum_of_a_blackbody_matches_the_blackbody():
    wl = np.arange(370.0, 791.0, 5.0)
    pairs = tuple(zip(wl, star_spectrum(14000.0, wl) * 3.7))  # any scale
    np.testing.assert_allclose(band_luminosity_fractions(EIGHT, pairs),
                               band_luminosity_fractions(EIGHT, 14000.0), rtol=2e-4)


def test_several_stars_share_out_their_own_luminosities():
    stars = [Star(position=(0.3, 0.5, 0.5), luminosity=2.0, temperature=20000.0),
             Star(position=(0.7, 0.5, 0.5), luminosity=0.5, temperature=4000.0),
             Star(position=(0.5, 0.2, 0.5), luminosity=1.0,
                  spectrum=((440.0, 0.0), (550.0, 1.0), (660.0, 0.0)))]
    lum = star_band_luminosities(stars, EIGHT)
    np.testing.assert_allclose(lum.sum(axis=1), [2.0, 0.5, 1.0], rtol=1e-12)
    assert lum[0, 0] / lum[0, -1] > 1 > lum[1, 0] / lum[1, -1]  # the hot star is bluer
    assert lum[2, 0] == 0.0 and lum[2, -1] == 0.0  # nothing outside 440-660 nm


def test_scene_spectrum_round_trip_and_errors():
    scene = Scene.from_dict({"stars": [{"position": [0.5, 0.5, 0.5], "spectrum": [[400, 1], [700, 2]]}]})
    assert scene.stars[0].spectrum == ((400.0, 1.0), (700.0, 2.0))
    again = Scene.from_toml(scene.to_toml()) if hasattr(Scene, "from_toml") else None
    if again is not None:
        assert again.stars[0].spectrum == scene.stars[0].spectrum
    for bad in ([[400, 1]], [[500, 1], [400, 1]], [[400, -1], [500, 1]], [[400, 0], [500, 0]],
                "sun.csv", [[400, 1, 2], [500, 1]]):
        with pytest.raises(SceneError) as err:
            Scene.from_dict({"stars": [{"position": [0.5, 0.5, 0.5], "spectrum": bad}]})
        assert err.value.parameter == "stars[0].spectrum", err.value.parameter
        assert "pairs" in str(err.value)


def test_light_field_colours_follow_a_measured_spectrum(backend):
    """The colour stage and the VTK colour/sky filters take the star's measured spectrum (from
    the scene TOML in the field data), not a blackbody."""
    from nebula_rt.pipeline import Pipeline
    from nebula_rt.pipeline.rgba import colour_source_from_field_data

    pairs = [[400.0, 0.2], [550.0, 1.0], [700.0, 1.6]]
    scene = Scene.from_dict({
        "grid": {"shape": [8, 8, 8]},
        "stars": [{"position": [0.5, 0.5, 0.5], "temperature": 20000.0, "spectrum": pairs}],
        "transport": {"photons": 5000},
    })
    light = Pipeline(backend).run(scene)
    source = colour_source_from_field_data(light.field_data())
    assert np.allclose(np.asarray(source), pairs)
    # a red measured spectrum gives the bands less blue light than the 20000 K blackbody
    assert light.transport.band_luminosity[2] < light.transport.band_luminosity[0]
