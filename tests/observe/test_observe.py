"""Colours as an observer measures them, against observed reflection nebulae.

Expected behaviour (REFERENCES.md, data/observations.toml):
- optically thin dust scatters blue light more (extinction and albedo both rise to the blue),
  so Delta(B-V) lies inside the single-scattering range -0.34 .. -0.17 mag;
- more dust reddens the scattered light: Delta(B-V) against the star's intrinsic colour rises
  monotonically with optical depth;
- against the star as seen (the default reference), the star's own reddening by the dust in
  front of it, E(B-V), comes off: Delta(B-V)_observed = Delta(B-V)_intrinsic - E(B-V).
MC tolerance: each annulus sums thousands of pixels of 8 bands x 60k packets; the run-to-run
scatter of an annulus's Delta(B-V) is below 0.01 mag here (checked by the seed test), so the
monotonic steps (0.1 mag and more) are far outside the noise. The stated errors of the
peel-off profiles are checked against the scatter of 10 seeds (chi-square bounds).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from conftest import TEST_BACKEND, TEST_DEVICE
from nebula_rt.observe import colours as observe
from nebula_rt.optics.colour_convert import band_luminosity_fractions
from nebula_rt.pipeline import Pipeline
from nebula_rt.scene import Scene

ROOT = Path(__file__).resolve().parents[2]


def uniform_scene(tau, seed=1, photons=60_000):
    return Scene.from_dict({
        "grid": {"shape": [24, 24, 24]},
        "dust": {"model": "uniform", "density": 1.0, "tau": tau},
        "stars": [{"position": [0.5, 0.5, 0.5], "temperature": 14000.0, "bump_radius": 0.0}],
        "bands": {"preset": "spectral-8"},
        "transport": {"photons": photons, "seed": seed, "backend": TEST_BACKEND, "device": TEST_DEVICE},
    })


def test_star_colour_is_zero_and_passbands_are_bessell():
    wl = np.array([b.wavelength for b in Scene.from_dict({"bands": {"preset": "spectral-8"}}).bands.resolve()])
    # a nebula with the star's own spectrum (ratio 1 in every band) has Delta(B-V) = 0
    assert abs(observe.delta_b_minus_v(np.ones(8), wl, 14000.0)) < 1e-12
    # bluer ratios give negative Delta(B-V)
    assert observe.delta_b_minus_v(np.linspace(1.5, 0.7, 8), wl, 14000.0) < -0.1
    b, v = observe.passband("B"), observe.passband("V")
    assert 360 <= b[0][0] and b[0][-1] <= 560 and 470 <= v[0][0] and v[0][-1] <= 700
    assert abs(observe.passband_weights(wl, 14000.0, "B").sum() - 1) < 1e-12


def test_thin_dust_is_inside_the_single_scattering_range(backend):
    prof = observe.profiles(Pipeline(backend).run(uniform_scene(0.1), colour=False), size=48)
    lo, hi = observe.observations()["single_scattering_delta_bv"]["range"]
    ok = prof.pixels > 0
    assert ok.sum() >= 6
    assert np.all((prof.delta_bv[ok] > lo) & (prof.delta_bv[ok] < hi)), prof.delta_bv
    # the ratio falls with wavelength: blue scattered more
    assert np.all(np.diff(prof.ratio[:, 2]) < 0)


def test_reddening_grows_with_optical_depth(backend):
    means, seen = [], []
    for tau in (0.1, 1.0, 3.0, 10.0):
        light = Pipeline(backend).run(uniform_scene(tau), colour=False)
        prof = observe.profiles(light, size=48, reference="intrinsic")
        means.append(float(np.nanmean(prof.delta_bv)))
        obs = observe.profiles(light, size=48)
        assert obs.reference == "observed" and prof.reference == "intrinsic"
        np.testing.assert_allclose(obs.delta_bv, prof.delta_bv - obs.star_ebv, rtol=0, atol=1e-12)
        seen.append(float(np.nanmean(obs.delta_bv)))
    # against the intrinsic star: from bluer than the star to redder
    assert np.all(np.diff(means) > 0.05), means
    assert means[0] < -0.17 and means[-1] > 0.0
    # against the star as seen through tau 5 of the same dust the thick nebula stays bluer than
    # the star: its light leaves from shallower layers than the star's
    assert seen[-1] < -0.2, seen


def test_seed_scatter_is_small(backend):
    a = observe.profiles(Pipeline(backend).run(uniform_scene(1.0, seed=1), colour=False), size=48)
    b = observe.profiles(Pipeline(backend).run(uniform_scene(1.0, seed=2), colour=False), size=48)
    assert np.nanmax(np.abs(a.delta_bv - b.delta_bv)) < 0.02


def test_observation_table_loads_and_is_cited():
    obs = observe.observations()
    assert {"mean_delta_bv", "single_scattering_delta_bv", "single_scattering_ratio_90deg",
            "reddening_with_depth"} <= set(obs)
    for name, entry in obs.items():
        assert entry["source"] and entry["kind"] in ("observed", "model") and entry["description"], name
    assert obs["mean_delta_bv"]["value"] == pytest.approx(-0.2)
    assert obs["single_scattering_delta_bv"]["range"] == [-0.34, -0.17]


def test_peel_off_colours_depend_on_the_scattering_angle(backend):
    """With the phase function (peel-off image), thin dust is bluest where small scattering
    angles dominate -- near the star in projection, where the dust in front scatters forwards --
    and stays inside the single-scattering range on average (-0.34 at 20 deg .. -0.17 at 135)."""
    prof, res = observe.observe_scene(uniform_scene(0.1, photons=1_000_000), size=32, backend=backend)
    assert res.peel_image is not None and res.peel_image.shape == (8, 32, 32)
    lo, hi = observe.observations()["single_scattering_delta_bv"]["range"]
    assert lo < np.nanmean(prof.delta_bv) < hi, prof.delta_bv
    assert prof.delta_bv[0] < prof.delta_bv[-1] - 0.03, prof.delta_bv


def test_line_of_sight_tau_of_a_uniform_cube_is_sigma_times_distance():
    """Uniform cube: tau_b = sigma_b x distance from the start to the face the ray leaves by
    (analytic), for random starts and directions and a start outside the box."""
    rng = np.random.default_rng(5)
    sig = np.array([1.3, 2.0, 0.25])
    sigma = sig[:, None, None, None] * np.ones((3, 10, 7, 5))
    for _ in range(50):
        p = rng.uniform(0.0, 1.0, 3)
        o = rng.normal(size=3)
        o /= np.linalg.norm(o)
        dist = min(((1.0 if o[a] > 0 else 0.0) - p[a]) / o[a] for a in range(3))
        np.testing.assert_allclose(observe.line_of_sight_tau(sigma, p, o), sig * dist, rtol=1e-12)
    # along an axis, and from outside the box: the chord inside counts
    np.testing.assert_allclose(observe.line_of_sight_tau(sigma, (0.3, 0.4, 0.5), (0, 0, 1)), sig * 0.5, rtol=1e-12)
    np.testing.assert_allclose(observe.line_of_sight_tau(sigma, (0.3, 0.4, -2.0), (0, 0, 1)), sig * 1.0, rtol=1e-12)
    assert np.all(observe.line_of_sight_tau(sigma, (0.3, 0.4, -2.0), (0, 0, -1)) == 0.0)


def test_line_of_sight_tau_through_a_random_grid():
    """A random voxel grid, oblique ray: against an independent midpoint sum of 2e6 equal
    steps (each voxel-face crossing can give at most one step to the wrong voxel: error at
    most crossings x max sigma x step) and, along an axis, against the sky image's march
    (exact there)."""
    from nebula_rt.observe.sky import Camera, sky_image

    rng = np.random.default_rng(8)
    shape = (9, 11, 6)
    sigma = rng.uniform(0.0, 3.0, (2,) + shape)
    p, o = np.array([0.37, 0.52, 0.61]), np.array([0.3, -0.5, 0.8])
    o /= np.linalg.norm(o)
    got = observe.line_of_sight_tau(sigma, p, o)
    length = min(((1.0 if o[a] > 0 else 0.0) - p[a]) / o[a] for a in range(3))
    n = 2_000_000
    ds = length / n
    x = p[None] + ((np.arange(n) + 0.5) * ds)[:, None] * o[None]
    idx = np.minimum((x * np.array(shape)).astype(int), np.array(shape) - 1)
    want = sigma[:, idx[:, 0], idx[:, 1], idx[:, 2]].sum(axis=1) * ds
    bound = sum(shape) * sigma.max() * ds
    assert np.all(np.abs(got - want) <= bound), (got, want, bound)
    assert np.all(got > 0.3)
    # viewed along -z the star's light goes +z: the sky image's tau_star, a midpoint march of
    # steps step / 11 whose error is at most (faces crossed) x max sigma x step / 11
    step = 1e-3
    img = sky_image(np.zeros_like(sigma), sigma, Camera(size=(2, 2)), stars=[p],
                    star_band_luminosity=np.ones((1, 2)), step=step)
    got = observe.line_of_sight_tau(sigma, p, (0, 0, 1))
    assert np.all(np.abs(got - img.tau_star[0]) <= shape[2] * sigma.max() * step / max(shape)), (got, img.tau_star)


def _planck(wl_nm, t):
    """Blackbody spectral radiance per unit wavelength (arbitrary units)."""
    c2 = 1.4387769e7  # h c / k in nm K
    return wl_nm**-5.0 / np.expm1(c2 / (wl_nm * t))


def test_star_reddening_is_a_passband_integral():
    """E(B-V) of a 14,000 K star through tau_b = tau_V k_b of the spectral-8 dust, against a
    direct integral on a 0.05 nm grid of the transmission (tau interpolated linearly between
    band centres; below the bluest centre, 405 nm, Draine's R_V = 3.1 law scaled to that band,
    read point by point with dust_tables.cext_at), a Planck spectrum and the Bessell responses
    (linear between their 10 nm samples). Tolerance 2e-4 mag: the library integrates on 1 nm
    with the trapezoid rule; a trapezoid error h^2/12 f'' over kinks 10 nm apart stays below
    1e-5 of each integral (4e-5 mag for the four). Also R_V: E(B-V) = A_V / R_V within 10 % for
    R_V = 3.1 (broad passbands do not sample the curve at single wavelengths)."""
    from nebula_rt.optics.dust_tables import cext_at

    bands = Scene.from_dict({"bands": {"preset": "spectral-8"}}).bands.resolve()
    wl = np.array([b.wavelength for b in bands])
    k = np.array([b.extinction for b in bands])
    t = 14000.0
    for tau_v in (0.1, 0.52, 2.0):
        tau = tau_v * k
        got = observe.star_reddening(tau, wl, t)
        order = np.argsort(wl)
        mags = []
        for name in ("B", "V"):
            wx, rx = observe.passband(name)
            grid = np.arange(wx[0], wx[-1], 0.05)
            resp = np.interp(grid, wx, rx)
            tau_l = np.interp(grid, wl[order], tau[order])
            lo = grid < wl.min()
            tau_l[lo] = tau[order][0] * np.array([cext_at("3.1", x) for x in grid[lo]]) / cext_at("3.1", wl.min())
            trans = np.exp(-tau_l)
            s = _planck(grid, t) * resp
            mags.append(-2.5 * math.log10(np.trapezoid(trans * s, grid) / np.trapezoid(s, grid)))
        assert abs(got - (mags[0] - mags[1])) < 2e-4, (tau_v, got, mags)
        a_v = 2.5 * math.log10(math.e) * tau_v * k[int(np.argmin(np.abs(wl - 550)))]
        assert abs(got / (a_v / 3.1) - 1) < 0.10, (got, a_v / 3.1)


def test_observed_reference_is_the_intrinsic_less_the_star_reddening(backend):
    """Uniform cube of tau 1 about the star (tau 0.5 to the face, times k_b): the star's line of
    sight is analytic; Delta(B-V) against the star as seen is Delta(B-V) against its intrinsic
    colour minus the star's E(B-V), exactly; the per-band ratios divide by exp(-tau_b); the
    errors do not change (the star's transmission is no Monte Carlo quantity)."""
    scene = uniform_scene(1.0, photons=40_000)
    seen, _ = observe.observe_scene(scene, size=24, backend=backend)
    intr, _ = observe.observe_scene(scene, size=24, backend=backend, reference="intrinsic")
    k = np.array([b.extinction for b in scene.bands.resolve()])
    np.testing.assert_allclose(seen.star_tau, 0.5 * k, rtol=1e-6)  # float32 density
    assert seen.reference == "observed" and intr.reference == "intrinsic"
    assert seen.star_ebv == intr.star_ebv == observe.star_reddening(seen.star_tau, seen.wavelength_nm, 14000.0)
    assert 0.15 < seen.star_ebv < 0.2
    np.testing.assert_allclose(seen.delta_bv - intr.delta_bv, -seen.star_ebv, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(seen.delta_bv_err, intr.delta_bv_err)
    np.testing.assert_allclose(seen.delta_bv_intrinsic, intr.delta_bv, rtol=0, atol=1e-12)
    np.testing.assert_allclose(intr.delta_bv_observed, seen.delta_bv, rtol=0, atol=1e-12)
    t = np.exp(-seen.star_tau)
    vb = int(np.argmin(np.abs(seen.wavelength_nm - 550)))
    np.testing.assert_allclose(seen.ratio, intr.ratio * (t[vb] / t)[:, None], rtol=1e-12)
    with pytest.raises(ValueError, match="reference"):
        observe.observe_scene(scene, size=8, backend=backend, reference="apparent")


def test_ngc7023_star_is_reddened_towards_the_observer(backend):
    """The NGC 7023-like scene seen along (0, 0, -1): the README's figures for the star's line
    of sight (tau about 0.52 near 550 nm, E(B-V) about +0.10 mag)."""
    from nebula_rt.density import generate_density

    scene = Scene.load(ROOT / "examples/scenes/ngc7023-like.toml")
    bands = scene.bands.resolve()
    rho = generate_density(scene, backend).astype(np.float64)
    sigma = np.array([scene.dust.tau * b.extinction for b in bands])[:, None, None, None] * rho[None]
    tau = observe.line_of_sight_tau(sigma, scene.stars[0].position, (0.0, 0.0, 1.0))
    wl = np.array([b.wavelength for b in bands])
    tau_v = tau[int(np.argmin(np.abs(wl - 550)))]
    ebv = observe.star_reddening(tau, wl, 17000.0)
    assert 0.50 < tau_v < 0.54 and 0.09 < ebv < 0.11, (tau_v, ebv)


def test_profile_errors_match_the_seed_scatter(backend):
    """The stated batch-means errors of the peel-off profiles and image against the scatter
    of 10 independent seeds. For annulus k, (n - 1) s_k^2 / sigma_k^2 is chi-square with n - 1
    = 9 degrees of freedom; the mean of s_k^2 / sigma_k^2 over 8 annuli (72 degrees of freedom
    if independent) must lie within its 99.9 % two-sided chi-square bounds [0.54, 1.64], and
    every annulus within the 9-dof bounds [0.11, 3.30]; the stated error is the mean over the
    seeds (its own scatter, about 1 / sqrt(2 x 15 x 10) = 6 %, is inside the bounds' width).
    Per pixel (pooled over some 4600 pixels) the seed variance over the mean stated variance
    must be within 1 +- 0.15 (5 sigma of the pooled chi-square spread, about 2 %, plus
    the stated variances' low bias for the faintest pixels)."""
    profs, results = [], []
    for seed in range(1, 11):
        prof, res = observe.observe_scene(uniform_scene(1.0, seed=seed, photons=200_000), size=24, backend=backend)
        profs.append(prof)
        results.append(res)
    # the batches' annulus sums add up to the annuli of the image
    res, cam = results[0], observe._camera(uniform_scene(1.0).stars[0], (0.0, 0.0, -1.0), 24)
    _, u, v = cam.basis()
    labels = observe._labels(observe._offsets(cam.origin(), cam.pixel_size, u, v, cam.size, (0.5, 0.5, 0.5),
                                              (0.0, 0.0, -1.0)), observe._edges(None))
    assert profs[0].batches == res.batches >= 16 and res.peel_bin_batches.shape == (res.batches, 8, 8)
    np.testing.assert_allclose(res.peel_bin_batches.sum(axis=0),
                               [[im[labels == k].sum() for k in range(8)] for im in res.peel_image], rtol=1e-12)
    n = len(profs)
    lo72, hi72 = chi2.ppf(0.0005, 72) / 72, chi2.ppf(0.9995, 72) / 72
    lo9, hi9 = chi2.ppf(0.0005, n - 1) / (n - 1), chi2.ppf(0.9995, n - 1) / (n - 1)
    for values, errors in ((np.array([p.delta_bv for p in profs]), np.array([p.delta_bv_err for p in profs])),
                           (np.array([p.ratio[0] for p in profs]), np.array([p.ratio_err[0] for p in profs]))):
        q2 = values.var(axis=0, ddof=1) / errors.mean(axis=0) ** 2
        assert lo72 < q2.mean() < hi72, q2
        assert np.all((q2 > lo9) & (q2 < hi9)), q2
    img = np.array([r.peel_image for r in results])
    err = np.array([r.peel_error for r in results])
    lit = img.min(axis=0) > 0
    ratio = img.var(axis=0, ddof=1)[lit].sum() / (err**2).mean(axis=0)[lit].sum()
    assert lit.sum() > 4000 and abs(ratio - 1) < 0.15, (ratio, lit.sum())


def test_compare_command(tmp_path):
    scene = tmp_path / "thin.toml"
    scene.write_text(uniform_scene(0.1, photons=200_000).to_toml())
    png, js = tmp_path / "c.png", tmp_path / "c.json"
    proc = subprocess.run([sys.executable, "-m", "nebula_rt.cli", "compare", str(scene), "--png", str(png),
                           "--json", str(js), "--size", "32"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(js.read_text())
    assert png.stat().st_size > 10_000
    vals = [x for x in out["delta_bv_mag"] if x is not None]
    assert len(vals) == 8 and -0.34 < np.mean(vals) < -0.17
    # the reference is named, the errors are there, and the intrinsic values differ by E(B-V)
    assert out["reference"] == "observed" and out["star_ebv_mag"] > 0 and out["batches"] >= 16
    assert all(0 < e < 0.1 for e in out["delta_bv_err_mag"])  # about 0.03-0.06 mag here
    np.testing.assert_allclose(np.array(out["delta_bv_intrinsic_mag"]) - np.array(out["delta_bv_mag"]),
                               out["star_ebv_mag"], atol=2e-4)  # 4-decimal rounding
    assert len(out["ratio_err"]) == 8 and out["ratio_err"][3] == [0.0] * 8  # the 550 nm band
    bad = subprocess.run([sys.executable, "-m", "nebula_rt.cli", "compare", str(scene), "--direction", "0,0"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "--direction" in bad.stderr
    bad = subprocess.run([sys.executable, "-m", "nebula_rt.cli", "compare", str(scene), "--reference", "seen"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "--reference" in bad.stderr


def test_band_luminosities_add_up_for_spectral_bands():
    wl = [b.wavelength for b in Scene.from_dict({"bands": {"preset": "spectral-16"}}).bands.resolve()]
    assert band_luminosity_fractions(wl, 17000.0).sum() == pytest.approx(1.0, abs=1e-12)
