"""The degree of polarization against projected offset as an observable of ``compare`` and
``fit`` (observe.comparison, observe.observed_tables): tables of P in annuli.

- The model's P of every annulus is the tangential Stokes over the intensity of the annulus's
  pixels, computed here from the run's full I, Q and U images with each pixel's own position
  angle (the same packets: the same deposits), to rounding; its Monte Carlo error is honest:
  over 8 seeds the pulls against a run of 16 times the packets spread as chi^2 says.
- A table of P made from the model with another seed compares with chi^2 per dof near 1, and a
  table of another p_l is rejected; a fit of ``bands.peak_polarization`` finds it.
- Tables are read with their units (a fraction or %), and refused by name where they cannot be
  compared (|P| > 1, a missing column, a scene without polarization, wavelengths beyond the bands).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import TEST_BACKEND, TEST_DEVICE

from nebula_rt.errors import NebulaWarning, SceneError
from nebula_rt.observe.comparison import (
    _position_angles, compare_tables, model_values, ring_edges, ring_pixels, trace_rings)
from nebula_rt.observe.observed_tables import ObservedTable, read_table
from nebula_rt.scene import Scene
from nebula_rt.transport.request import TransportRequest

EDGES = np.array([0.04, 0.08, 0.12, 0.18, 0.26, 0.36])


def scene(photons=40_000, seed=1, peak=0.5, polarization="white"):
    return Scene.from_dict({
        "grid": {"shape": [16, 16, 16]},
        "dust": {"model": "uniform", "density": 1.0, "floor": 0.0, "tau": 2.0},
        "stars": [{"position": [0.5, 0.5, 0.5], "luminosity": 1.0, "temperature": 12000.0, "bump_radius": 0.0}],
        "bands": {"preset": "thesis-rgb", "polarization": polarization, "peak_polarization": peak},
        "transport": {"photons": photons, "seed": seed, "backend": TEST_BACKEND, "device": TEST_DEVICE}})


def table(values, errors, wavelength=550.0, path="p.ecsv"):
    lo, hi = EDGES[:-1], EDGES[1:]
    return ObservedTable(kind="polarization", path=path, x=0.5 * (lo + hi), value=np.asarray(values, float),
                         error=np.asarray(errors, float), lo=lo, hi=hi, wavelength=np.full(len(lo), wavelength))


def test_ring_polarization_is_the_images_tangential_stokes(backend):
    s = scene()
    rings = trace_rings(s, EDGES, size=48, backend=backend, stokes=True)
    cam, labels, _ = ring_pixels(s.stars[0].position, (0.0, 0.0, -1.0), 48, EDGES)
    res = TransportRequest.from_scene(s, peel=cam, light_field=False).trace(
        np.ones((16, 16, 16), np.float32), backend)
    psi = _position_angles(cam, s.stars[0].position)
    t = res.peel_stokes[:, 0] * np.cos(2 * psi) + res.peel_stokes[:, 1] * np.sin(2 * psi)
    for k in range(len(EDGES) - 1):
        sel = labels == k
        np.testing.assert_allclose(rings.sums[:, k], res.peel_image[:, sel].sum(axis=1), rtol=1e-9)
        np.testing.assert_allclose(rings.tangential[:, k], t[:, sel].sum(axis=1), rtol=1e-9, atol=1e-12)
    # band G (550 nm): the model's P is its ring's T / I
    m, err = model_values(rings, table(np.zeros(5), np.ones(5)))
    np.testing.assert_allclose(m, rings.tangential[1] / rings.sums[1], rtol=1e-12)
    assert np.all(m > 0.05) and np.all(err > 0)  # tangential, as about a star


def test_the_model_error_of_p_is_honest(backend):
    ref = trace_rings(scene(photons=640_000, seed=99), EDGES, size=48, backend=backend, stokes=True)
    truth, _ = model_values(ref, table(np.zeros(5), np.ones(5)))
    pulls = []
    for seed in range(1, 9):
        m, err = model_values(trace_rings(scene(seed=seed), EDGES, size=48, backend=backend, stokes=True),
                              table(np.zeros(5), np.ones(5)))
        pulls.append((m - truth) / np.sqrt(err**2 + (err / 4.0) ** 2))  # (the reference's own error: 1/4)
    z = np.concatenate(pulls)
    from scipy.stats import chi2

    lo, hi = chi2.ppf([0.0005, 0.9995], z.size)
    assert lo < np.sum(z**2) < hi, (np.sum(z**2), z.size)


def test_compare_and_fit_the_peak_polarization(backend):
    from nebula_rt.observe.fit import fit_observations

    truth = trace_rings(scene(photons=160_000, seed=7, peak=0.6), EDGES, size=48, backend=backend, stokes=True)
    p, perr = model_values(truth, table(np.zeros(5), np.ones(5)))
    obs = table(p, np.maximum(2.0 * perr, 0.01))
    same = compare_tables(trace_rings(scene(photons=80_000, seed=3, peak=0.6), EDGES, size=48, backend=backend,
                                      stokes=True), [obs])
    other = compare_tables(trace_rings(scene(photons=80_000, seed=3, peak=0.2), EDGES, size=48, backend=backend,
                                       stokes=True), [obs])
    assert same.chi2 < 25.0 and other.chi2 > 100.0, (same.chi2, other.chi2)
    d = same.to_dict()["tables"][0]
    assert d["kind"] == "polarization" and d["wavelength_nm"] == [550.0] * 5
    fit = fit_observations(scene(photons=80_000, seed=3), [obs], ["bands.peak_polarization=0.1:0.9"], size=48,
                           backend=backend)
    best, err = float(fit.best[0]), float(max(fit.err_minus[0], fit.err_plus[0]))
    assert abs(best - 0.6) < max(4.0 * err, 0.05), (best, err)
    # bounds that hold the truth out: the best fit sits on the upper bound, and says so
    held = fit_observations(scene(photons=80_000, seed=3), [obs], ["bands.peak_polarization=0.1:0.4"], size=48,
                            backend=backend)
    assert float(held.best[0]) == pytest.approx(0.4) and held.at_bound[0][1] and held.err_plus[0] == 0.0


def test_tables_are_read_with_units_and_refused_by_name(tmp_path, backend):
    f = tmp_path / "pol.csv"
    f.write_text("offset,wavelength [nm],polarization [%],polarization_err [%]\n0.05,550,12,1.5\n0.10,550,20,2\n"
                 "0.15,550,26,2\n")
    t = read_table(f)
    assert t.kind == "polarization" and np.allclose(t.value, [0.12, 0.20, 0.26]) and np.allclose(t.error[0], 0.015)
    assert np.allclose(t.wavelength, 550.0) and t.lo[0] == pytest.approx(0.025)
    bad = tmp_path / "bad.csv"
    bad.write_text("offset,wavelength [nm],polarization,polarization_err\n0.05,550,1.5,0.1\n0.1,550,0.2,0.1\n")
    with pytest.raises(SceneError, match="column 'polarization', row 1"):
        read_table(bad)
    bad.write_text("offset,polarization,polarization_err\n0.05,0.1,0.1\n0.1,0.2,0.1\n")
    with pytest.raises(SceneError, match="column 'wavelength'"):
        read_table(bad)
    from nebula_rt.observe.comparison import check_tables_against_scene

    with pytest.raises(SceneError, match="bands.polarization"):
        check_tables_against_scene(scene(polarization="none"), [t])
    far = table(np.zeros(5), np.ones(5), wavelength=900.0)
    with pytest.raises(SceneError, match="within the scene's bands"):
        check_tables_against_scene(scene(), [far])
    with pytest.raises(SceneError, match="bands.polarization"):
        trace_rings(scene(polarization="none"), ring_edges([far]), size=16, backend=backend, stokes=True)
    assert math.isfinite(t.value.sum())


def test_observed_stokes_images_become_a_table_the_model_fits(tmp_path, backend):
    """A polarized scene's own sky FITS (``nebula-rt sky``: SB_G, Q_G, U_G in MJy/sr, IAU, at
    position angle 30 degrees, so the sky's north is not the image's up) read back as an
    observation (observe.observed_stokes: annuli in arcsec about the star, the star's pixel
    masked): the tangential degree of polarization is positive and rises outwards, and the
    model (another seed) compares with it within chi^2 bounds; a scene without polarization
    would compare nothing (refused)."""
    from nebula_rt.cli import commands as cli
    from nebula_rt.observe.comparison import compare
    from nebula_rt.observe.observed_stokes import stokes_table
    from scipy.stats import chi2 as chi2_dist

    d = scene(photons=160_000, seed=11).to_dict()
    d["grid"]["length"] = "0.2 pc"
    d["stars"][0] = {"position": [0.5, 0.5, 0.5], "luminosity_lsun": 100.0, "temperature": 12000.0,
                     "bump_radius": 0.0}
    d["dust"].pop("tau")
    d["dust"]["visual_extinction"] = 2.2
    d["observer"] = {"distance": "50 pc", "psf_fwhm": 0.0, "position_angle": 30.0}
    s = Scene.from_dict(d)
    (tmp_path / "s.toml").write_text(s.to_toml())
    assert cli.main(["sky", str(tmp_path / "s.toml"), "--fits", str(tmp_path / "obs.fits"), "--size", "64",
                     "-q"]) == 0
    pixel_arcsec = math.degrees(math.sqrt(3.0) / 64 * 0.2 / 50.0) * 3600.0  # camera_for's default extent
    edges = np.array([3, 6, 10, 15, 21, 28]) * pixel_arcsec
    obs = stokes_table(s, tmp_path / "obs.fits", intensity="SB_G", q="Q_G", u="U_G",
                       errors=["0.02 MJy/sr"], wavelength_nm=550.0, annuli_arcsec=edges,
                       mask_arcsec=1.5 * pixel_arcsec)
    assert np.all(obs.value > 0.05) and obs.value[-1] > obs.value[0], obs.value
    model = scene(photons=160_000, seed=12).to_dict()
    model.update(grid=d["grid"], stars=d["stars"], dust=d["dust"], observer=d["observer"])
    comp = compare(Scene.from_dict(model), [obs], size=64, backend=backend)
    r = comp.results[0]
    assert comp.chi2 < chi2_dist.ppf(0.999, r.dof), (comp.chi2, r.model, obs.value, obs.error)
    # the same table against a scene whose p_l is a third of it: rejected
    model["bands"]["peak_polarization"] = 0.5 / 3
    low = compare(Scene.from_dict(model), [obs], size=64, backend=backend)
    assert low.chi2 > 10 * comp.chi2 + 50, (low.chi2, comp.chi2)
    # the command line: nebula-rt compare --stokes (the same table), and its refusals by option
    import json

    (tmp_path / "m.toml").write_text(Scene.from_dict(dict(model, bands=d["bands"])).to_toml())
    args = ["compare", str(tmp_path / "m.toml"), "--stokes", str(tmp_path / "obs.fits"), "--stokes-hdus",
            "SB_G,Q_G,U_G", "--stokes-wavelength", "550", "--stokes-annuli", ",".join(f"{e:.6f}" for e in edges),
            "--stokes-error", "0.02 MJy/sr", "--stokes-mask", f"{1.5 * pixel_arcsec:.6f}", "--size", "64",
            "--png", str(tmp_path / "c.png"), "--json", str(tmp_path / "c.json")]
    assert cli.main(args) == 0
    summary = json.loads((tmp_path / "c.json").read_text())
    np.testing.assert_allclose(summary["tables"][0]["data"], obs.value, rtol=1e-12)
    assert summary["chi2"] == pytest.approx(comp.chi2, rel=1e-9)
    for option, bad in (("--stokes-hdus", "SB_G,Q_G"), ("--stokes-annuli", "5,3"), ("--stokes-error", None)):
        argv = list(args)
        if bad is None:
            i = argv.index(option)
            del argv[i:i + 2]
        else:
            argv[argv.index(option) + 1] = bad
        assert cli.main(argv) == 2


def test_fit_the_largest_grains_of_mie_dust(backend):
    """The degree of polarization against offset constrains the grains: with Mie grains (MRN
    astronomical silicate) P falls from about 0.3-0.4 at a largest radius of 0.1 micron to about
    0.01 at 0.5 micron, and a fit of ``bands.grain_radius_max`` (in log) recovers the radius that
    made the observations (another seed, twice the packets) within its errors."""
    from nebula_rt.observe.fit import fit_observations

    def mie(photons, seed, radius):
        s = scene(photons=photons, seed=seed).to_dict()
        s["bands"].update({"polarization": "mie", "grain_radius_max": radius})
        s["bands"].pop("peak_polarization", None)
        return Scene.from_dict(s)

    truth = trace_rings(mie(160_000, 7, 0.15), EDGES, size=48, backend=backend, stokes=True)
    p, perr = model_values(truth, table(np.zeros(5), np.ones(5)))
    assert np.all(p > 0.1)
    obs = table(p, np.maximum(2.0 * perr, 0.01))
    with pytest.warns(NebulaWarning, match="Monte Carlo error"):
        fit = fit_observations(mie(80_000, 3, 0.25), [obs], ["bands.grain_radius_max=0.05:0.5:log"], size=48,
                               backend=backend)
    best, err = float(fit.best[0]), float(max(fit.err_minus[0], fit.err_plus[0]))
    assert abs(best - 0.15) < max(4.0 * err, 0.01), (best, err)
    assert not any(fit.at_bound[0])
