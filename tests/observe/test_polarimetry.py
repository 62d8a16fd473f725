"""Polarization maps of calibrated sky images (nebula_rt.observe.polarimetry) and their FITS.

- The errors of P and chi against the scatter of P and chi over simulated Gaussian noise of
  I, Q and U (the formulas are first order; the simulation is not).
- The IAU convention on the sky: the same packets seen with the image's up axis at position
  angle 0 and 90 degrees give Q and U of opposite signs (an angle turned by 90 degrees doubles
  to 180), and a pixel east of a central star in a Rayleigh nebula is polarized north-south
  (Q > 0), one north of it east-west (Q < 0).
- ``nebula-rt sky`` writes ``Q_<band>`` and ``U_<band>`` with the intensity's WCS and units and
  ``POLCONV = 'IAU'``; the vectors need a polarized scene and the ray march refuses one.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import TEST_BACKEND, TEST_DEVICE

from nebula_rt.observe import calibrate
from nebula_rt.observe.polarimetry import polarization_maps, vector_field, overlay_vectors
from nebula_rt.scene import Scene


def test_polarization_errors_follow_the_scatter_of_simulated_noise():
    rng = np.random.default_rng(1)
    n = 200_000
    i0, p0, chi0 = 100.0, 0.3, np.radians(35.0)
    q0, u0 = i0 * p0 * np.cos(2 * chi0), i0 * p0 * np.sin(2 * chi0)
    si, sq, su = 1.0, 0.6, 0.9
    i = i0 + si * rng.normal(size=n)
    q = q0 + sq * rng.normal(size=n)
    u = u0 + su * rng.normal(size=n)
    p, p_err, chi, chi_err = polarization_maps(np.full(1, i0), np.full(1, q0), np.full(1, u0),
                                               np.full(1, si), np.full(1, sq), np.full(1, su))
    p_sim, _, chi_sim, _ = polarization_maps(i, q, u)
    assert p[0] == pytest.approx(p0, rel=1e-12) and chi[0] == pytest.approx(35.0, abs=1e-9)
    assert p_err[0] == pytest.approx(np.std(p_sim), rel=0.03)
    assert chi_err[0] == pytest.approx(np.std(chi_sim), rel=0.03)
    # angles in [0, 180) east of north
    _, _, a, _ = polarization_maps(np.ones(4), np.array([1.0, 0.0, -1.0, 0.0]), np.array([0.0, 1.0, 0.0, -1.0]))
    np.testing.assert_allclose(a, [0.0, 45.0, 90.0, 135.0])


@pytest.mark.parametrize("snr", [1.0, 2.0, 3.0, 5.0])
def test_mas_estimator_removes_the_ricean_bias(snr):
    """The expectation of the raw P and of its MAS estimate over the Rice distribution of the
    measured P (scipy.stats.rice: equal Gaussian errors sigma on q and u, true P0 = snr sigma),
    by quadrature. Plaszczynski et al. (2014) state the MAS estimate unbiased from a
    signal-to-noise of 2 on: within 0.06 sigma at 2 (their Fig. 4: about 0.05), 0.01 sigma from
    3; the raw ratio's bias, sqrt(pi/2) L_1/2(-snr^2/2) - snr, is 0.27 sigma at 2."""
    from scipy import integrate, stats

    from nebula_rt.observe.polarimetry import mas_estimate

    sigma = 0.02
    p0 = snr * sigma
    pdf = stats.rice(p0 / sigma, scale=sigma).pdf

    def mas(p):  # a measured p whose (q, u) lies along q (the estimate depends on |p| alone here)
        return float(mas_estimate(p, p, 0.0, sigma, sigma))

    top = p0 + 12 * sigma
    raw = integrate.quad(lambda p: p * pdf(p), 0, top, limit=200)[0] - p0
    debiased = integrate.quad(lambda p: mas(p) * pdf(p), 0, top, limit=200)[0] - p0
    assert raw > 0.09 * sigma  # the bias to remove (0.10 sigma at snr 5)
    if snr >= 3:
        assert abs(debiased) < 0.01 * sigma
    elif snr >= 2:
        assert abs(debiased) < 0.06 * sigma
    assert abs(debiased) < 0.6 * raw  # better at every signal-to-noise
    assert mas(0.0) == 0.0 and mas(1e-9) >= 0.0 and mas(10 * sigma) < 10 * sigma


def test_mas_estimator_takes_unequal_errors_of_q_and_u():
    """With sigma_U = sigma_Q / 2, Gaussian noise draws of Q and U around P0 = 2 sigma_Q / I at
    angles from 0 to 90 degrees: the raw ratio is biased high by 0.09-0.23 sigma_Q / I (by the
    noise across the vector, which turns with the angle), the mean MAS estimate from
    polarization_maps holds P0 within the paper's 0.05 sigma at a signal-to-noise of 2 (plus 4
    standard errors of the mean) at every angle, and a third of the raw bias at most."""
    rng = np.random.default_rng(7)
    n = 200_000
    i0, sq, su = 100.0, 1.0, 0.5
    p0 = 2 * sq / i0
    i, eq, eu = np.full(n, i0), np.full(n, sq), np.full(n, su)
    for chi in (0.0, 22.5, 45.0, 67.5, 90.0):
        a = np.radians(2 * chi)
        q = i0 * p0 * np.cos(a) + sq * rng.normal(size=n)
        u = i0 * p0 * np.sin(a) + su * rng.normal(size=n)
        raw = polarization_maps(i, q, u, None, eq, eu)[0].mean() - p0
        mas = polarization_maps(i, q, u, None, eq, eu, debias="mas")[0]
        bias = mas.mean() - p0
        assert raw > 0.09 * sq / i0
        assert abs(bias) < 4 * mas.std() / np.sqrt(n) + 0.05 * sq / i0, (chi, bias * i0 / sq)
        assert abs(bias) < raw / 3 and np.all(mas >= 0)
    with pytest.raises(ValueError, match="debias = 'rice'"):
        polarization_maps(np.ones(1), np.ones(1), np.ones(1), debias="rice")


def test_circular_polarization_error_follows_the_scatter_of_simulated_noise():
    """V / I's first-order error against the spread of V / I over Gaussian noise of I and V."""
    from nebula_rt.observe.polarimetry import circular_polarization

    rng = np.random.default_rng(12)
    i, v, si, sv = np.array([10.0, 5.0, 50.0]), np.array([0.3, -0.4, 2.0]), np.array([0.3, 0.2, 2.0]), \
        np.array([0.05, 0.08, 0.5])
    ratio, err = circular_polarization(i, v, si, sv)
    draws = circular_polarization(i + si * rng.standard_normal((40_000, 3)), v + sv * rng.standard_normal((40_000, 3)))[0]
    np.testing.assert_allclose(ratio, v / i)
    np.testing.assert_allclose(draws.std(axis=0), err, rtol=0.03)


def test_vectors_are_block_sums_and_lines_along_their_angle():
    i = np.ones((8, 8))
    q = np.zeros((8, 8))
    u = np.zeros((8, 8))
    q[:4, :4] = 0.5            # block (0, 0): north-south, P = 0.5
    u[4:, 4:] = -0.5           # block (1, 1): chi = 135 degrees east of north
    centres, p, p_err, chi, keep = vector_field(i, q, u, 0.01 * i, 0.01 * i, 0.01 * i, step=4)
    np.testing.assert_allclose(centres, [[1.5, 1.5], [1.5, 5.5], [5.5, 1.5], [5.5, 5.5]])
    np.testing.assert_allclose(p, [0.5, 0.0, 0.0, 0.5], atol=1e-12)
    assert keep.tolist() == [True, False, False, True]
    assert chi[0] == pytest.approx(0.0) and chi[3] == pytest.approx(135.0)
    rgb = overlay_vectors(np.zeros((8, 8, 3), np.uint8), centres, p, chi, keep, length=4.0)
    lit = np.argwhere(rgb[..., 0] == 255)
    # the north-south one: one column (p), rows (q) around its centre
    first = lit[(lit[:, 0] < 4) & (lit[:, 1] < 4)]
    assert len(set(first[:, 0])) == 1 and len(set(first[:, 1])) >= 2
    # 135 degrees east of north: the south-east, -p and -q (east is -p): a line of slope +1
    last = lit[(lit[:, 0] >= 4) & (lit[:, 1] >= 4)]
    d = np.polyfit(last[:, 0], last[:, 1], 1)[0]
    assert d == pytest.approx(1.0, abs=0.3)


def _scene(pa=0.0, **bands):
    return Scene.from_dict({
        "grid": {"shape": [16, 16, 16], "length": "0.2 pc"},
        "dust": {"model": "uniform", "hydrogen_density": 400.0, "floor": 0.0},
        "stars": [{"position": [0.5, 0.5, 0.5], "luminosity_lsun": 100.0, "temperature": 9000.0}],
        "bands": {"preset": "thesis-rgb", "polarization": "rayleigh", **bands},
        "transport": {"photons": 60_000, "seed": 4, "backend": TEST_BACKEND, "device": TEST_DEVICE},
        "observer": {"distance": "50 pc", "psf_fwhm": 0.0, "position_angle": pa}})


def test_stokes_images_on_the_sky_follow_the_iau_convention(backend):
    cals = []
    for pa in (0.0, 90.0):
        s = _scene(pa)
        cam = calibrate.camera_for(s, (0.0, 0.0, -1.0), 12, extent=1.0)
        cal, res = calibrate.peel_off_sky(s, cam, backend)
        cals.append(cal)
    a, b = cals
    assert a.stokes.shape == (3, 2, 12, 12)
    np.testing.assert_array_equal(a.scattered, b.scattered)
    np.testing.assert_allclose(b.stokes, -a.stokes, atol=1e-12 * np.abs(a.stokes).max())
    # position angle 0: north up, east to the left (image p decreasing); a Rayleigh nebula about
    # a central star is polarized tangentially
    g = 1  # band G
    east, west = a.stokes[g, 0, 1:4, 4:8].sum(), a.stokes[g, 0, 8:11, 4:8].sum()
    north, south = a.stokes[g, 0, 4:8, 8:11].sum(), a.stokes[g, 0, 4:8, 1:4].sum()
    assert east > 0 and west > 0 and north < 0 and south < 0
    p, p_err, chi, chi_err = a.polarization()
    assert np.nanmax(p) < 1.0 and np.all(p_err[np.isfinite(p)] > 0)
    assert chi[g, 2, 6] == pytest.approx(0.0, abs=20.0) or chi[g, 2, 6] == pytest.approx(180.0, abs=20.0)
    assert chi[g, 6, 9] == pytest.approx(90.0, abs=20.0)


def test_cli_sky_writes_stokes_extensions_and_vectors(tmp_path, capsys):
    from astropy.io import fits
    from astropy.wcs import WCS

    from nebula_rt.cli import commands as cli

    s = _scene()
    (tmp_path / "s.toml").write_text(s.to_toml())
    out = tmp_path / "out"
    out.mkdir()
    status = cli.main(["sky", str(tmp_path / "s.toml"), "--fits", str(out / "sky.fits"), "--png", str(out / "sky.png"),
                       "--json", str(out / "sky.json"), "--size", "24", "--vectors", "-q"])
    assert status == 0, capsys.readouterr().err
    with fits.open(out / "sky.fits") as hdul:
        names = [h.name for h in hdul]
        for band in ("R", "G", "B"):
            q, u, sb = hdul[f"Q_{band}"], hdul[f"U_{band}"], hdul[f"SB_{band}"]
            assert q.header["POLCONV"] == "IAU" and q.header["BUNIT"] == "MJy/sr" and q.header["STOKES"] == "Q"
            assert u.header["STOKES"] == "U" and q.data.shape == sb.data.shape
            assert WCS(q.header).to_header() == WCS(sb.header).to_header()
            assert np.all(np.hypot(q.data, u.data) <= sb.data * (1 + 1e-5) + 1e-30)
        assert names.index("Q_R") > names.index("SB_B")
    summary = json.loads((out / "sky.json").read_text())
    assert set(summary["net_polarization"]) == {"R", "G", "B"}
    # refused before tracing, naming the option
    status = cli.main(["sky", str(tmp_path / "s.toml"), "--fits", str(out / "rm.fits"), "--method", "ray-march", "-q"])
    assert status == 2 and "--method" in capsys.readouterr().err
    plain = _scene(polarization="none")
    (tmp_path / "p.toml").write_text(plain.to_toml())
    status = cli.main(["sky", str(tmp_path / "p.toml"), "--fits", str(out / "p.fits"), "--vectors", "-q"])
    assert status == 2 and "--vectors" in capsys.readouterr().err
    assert not (out / "rm.fits").exists() and not (out / "p.fits").exists()


def _mie_scene(n, photons, pa=0.0):
    """Mie grains of one size (0.2 micron) in a uniform box, its star off the centre (so V does
    not cancel), in physical units for the calibrated sky."""
    return Scene.from_dict({
        "grid": {"shape": [n, n, n], "length": "0.2 pc"},
        "dust": {"model": "uniform", "tau": 3.0, "floor": 0.0},
        "stars": [{"position": [0.35, 0.5, 0.45], "luminosity_lsun": 100.0, "temperature": 9000.0}],
        "bands": {"preset": "thesis-rgb", "polarization": "mie", "grain_radius_min": 0.2, "grain_radius_max": 0.2},
        "transport": {"photons": photons, "seed": 4, "backend": TEST_BACKEND, "device": TEST_DEVICE},
        "observer": {"distance": "50 pc", "psf_fwhm": 0.0, "position_angle": pa}})


def test_cli_sky_writes_circular_polarization_of_mie_grains(tmp_path, capsys):
    """Mie grains: ``V_<band>`` after Q and U, the same units and WCS, |V| within the intensity;
    V does not turn with the position angle (only Q and U do)."""
    from astropy.io import fits

    from nebula_rt.cli import commands as cli

    heads = {}
    for pa in (0.0, 90.0):
        s = _mie_scene(16, 40_000, pa)
        (tmp_path / "s.toml").write_text(s.to_toml())
        fits_path = tmp_path / f"sky{int(pa)}.fits"
        status = cli.main(["sky", str(tmp_path / "s.toml"), "--fits", str(fits_path), "--size", "16", "-q",
                           "--json", str(tmp_path / "s.json")])
        assert status == 0, capsys.readouterr().err
        with fits.open(fits_path) as hdul:
            names = [h.name for h in hdul]
            assert names.index("V_R") == names.index("U_R") + 1
            v, sb = hdul["V_G"], hdul["SB_G"]
            assert v.header["STOKES"] == "V" and v.header["BUNIT"] == "MJy/sr"
            assert np.all(np.abs(v.data) <= sb.data * (1 + 1e-5) + 1e-30) and np.any(v.data != 0)
            heads[pa] = (hdul["Q_G"].data.copy(), v.data.copy())
            net = json.loads((tmp_path / "s.json").read_text())["net_polarization"]["G"]
            assert set(net) == {"p", "angle_deg_east_of_north", "v_over_i"} and abs(net["v_over_i"]) < net["p"]
    np.testing.assert_allclose(heads[90.0][0], -heads[0.0][0], atol=1e-12 * np.abs(heads[0.0][0]).max())
    np.testing.assert_array_equal(heads[90.0][1], heads[0.0][1])


def test_circular_polarization_maps_of_mie_grains(backend):
    """CalibratedSky.circular_polarization: V / I of the scattered light pixel by pixel, its
    first-order error from V's and I's; None where the grains give no V."""
    s = _mie_scene(12, 30_000)
    cal, _ = calibrate.peel_off_sky(s, calibrate.camera_for(s, (0.0, 0.0, -1.0), 12, extent=1.0), backend)
    ratio, err = cal.circular_polarization()
    lit = cal.scattered > 0
    np.testing.assert_allclose(ratio[lit], cal.stokes[:, 2][lit] / cal.scattered[lit], rtol=1e-12)
    assert np.all(err[lit] > 0)
    assert np.all(np.abs(ratio[lit]) <= 1 + 1e-9) and np.any(ratio[lit] != 0) and np.all(np.isnan(ratio[~lit]))
    assert cal.polarization() is not None
    assert calibrate.peel_off_sky(_scene(), calibrate.camera_for(_scene(), (0.0, 0.0, -1.0), 8, extent=1.0),
                                  backend)[0].circular_polarization() is None  # Rayleigh: no V
