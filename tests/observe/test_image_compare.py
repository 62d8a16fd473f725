"""The user's observed FITS image against the calibrated model image (nebula_rt.observe.image_compare,
``nebula-rt compare --image``): reprojection with ``reproject`` against analytic skies, flux
conservation, the errors through the reprojection, chi^2 against its distribution with the
run's own Monte Carlo error in quadrature, bad input, and the command end to end.

The observed images here are made independently of the code under test: a smooth sky brightness
defined in RA/Dec (an elliptical Gaussian about a point off the image centre, so that a wrong
rotation, flip or shift of either grid shows) evaluated at each grid's pixel centres with
astropy.wcs, on a grid of its own (another position angle, pixel scale and centre), built here
by hand. The model image's WCS is the calibrated image's own (nebula_rt.observe.calibrate.celestial_wcs,
tested against hand calculations in tests/observe/test_calibrate.py).
"""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest

from conftest import TEST_BACKEND, TEST_DEVICE
from nebula_rt.observe import calibrate
from nebula_rt.observe import image_compare as ic
from nebula_rt.errors import SceneError
from nebula_rt.scene import Scene

RA0, DEC0, PA0 = 83.8, -5.4, 20.0
#: 1 MJy/sr in Jy/arcsec^2: 1e6 Jy over (180 x 3600 / pi)^2 arcsec^2
MJY_SR_IN_JY_ARCSEC2 = 1e6 / (180.0 * 3600.0 / math.pi) ** 2


def sky_scene(seed=1, photons=4000, shape=16, psf=60.0, **over):
    """A small scene in physical units: a 0.2 pc box of uniform dust (tau about 1 across) at 50 pc,
    a 100 L_sun star off the centre; 24 pixels across the box's projection are 59.5 arcsec."""
    d = {"grid": {"shape": [shape] * 3, "length": "0.2 pc"},
         "dust": {"model": "uniform", "hydrogen_density": 3000.0, "floor": 0.0},
         "stars": [{"position": [0.55, 0.45, 0.5], "luminosity_lsun": 100.0, "temperature": 9000.0}],
         "transport": {"photons": photons, "backend": TEST_BACKEND, "device": TEST_DEVICE, "seed": seed},
         "observer": {"distance": "50 pc", "ra": RA0, "dec": DEC0, "position_angle": PA0, "psf_fwhm": psf}}
    for k, v in over.items():
        d[k] = {**d.get(k, {}), **v}
    return Scene.from_dict(d)


def model_grid(scene, size):
    cam = calibrate.camera_for(scene, size=size)
    return cam, calibrate.celestial_wcs(scene, cam), (size, size)


def tan_wcs(centre, scale_arcsec, pa_deg, shape, crpix_offset=(0.3, -0.2)):
    """A TAN WCS by hand: reference point ``centre`` (SkyCoord) near the middle of ``shape`` (ny, nx),
    square pixels of ``scale_arcsec``, image up ``pa_deg`` east of north, east to the left."""
    from astropy.wcs import WCS

    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [centre.ra.deg, centre.dec.deg]
    w.wcs.crpix = [(shape[1] + 1) / 2 + crpix_offset[0], (shape[0] + 1) / 2 + crpix_offset[1]]
    p = math.radians(pa_deg)
    w.wcs.cd = scale_arcsec / 3600.0 * np.array([[-math.cos(p), math.sin(p)], [math.sin(p), math.cos(p)]])
    w.wcs.set()
    return w


def centre(offset_arcmin=0.0, towards_deg=0.0):
    import astropy.units as u
    from astropy.coordinates import SkyCoord

    return SkyCoord(RA0 * u.deg, DEC0 * u.deg).directional_offset_by(towards_deg * u.deg, offset_arcmin * u.arcmin)


#: the analytic sky: peak A (MJy/sr), widths along and across the major axis (arcmin), its position angle
GAUSS_A, GAUSS_SA, GAUSS_SB, GAUSS_PA = 5.0, 4.0, 2.5, 30.0
GAUSS_CENTRE = centre(3.5, 70.0)


def gaussian_sky(world):
    """The sky brightness (MJy/sr) at ``world`` (SkyCoord): offsets from GAUSS_CENTRE along and
    across the major axis from the separation and position angle on the sphere."""
    sep = GAUSS_CENTRE.separation(world).arcmin
    pa = np.radians(GAUSS_CENTRE.position_angle(world).deg - GAUSS_PA)
    along, across = sep * np.cos(pa), sep * np.sin(pa)
    return GAUSS_A * np.exp(-0.5 * (along ** 2 / GAUSS_SA ** 2 + across ** 2 / GAUSS_SB ** 2))


def on_grid(f, wcs, shape, sub=1):
    """f at the pixel centres of ``wcs`` (sub = 1), or its mean over each pixel by the midpoint
    rule on sub x sub points (sub > 1)."""
    yy, xx = np.indices(shape, dtype=np.float64)
    offs = (np.arange(sub) + 0.5) / sub - 0.5 if sub > 1 else np.zeros(1)
    return sum(f(wcs.pixel_to_world(xx + a, yy + b)) for a in offs for b in offs) / len(offs) ** 2


def write_fits(path, data, wcs, bunit="MJy/sr", err=None, err_bunit=None, name="SCI", extra=None):
    from astropy.io import fits

    h = wcs.to_header() if wcs is not None else fits.Header()
    if bunit is not None:
        h["BUNIT"] = bunit
    for k, v in (extra or {}).items():
        h[k] = v
    hdus = [fits.PrimaryHDU(), fits.ImageHDU(np.asarray(data, np.float64), header=h, name=name)]
    if err is not None:
        eh = wcs.to_header() if wcs is not None else fits.Header()
        if err_bunit is not None:
            eh["BUNIT"] = err_bunit
        hdus.append(fits.ImageHDU(np.asarray(err, np.float64), header=eh, name="ERR"))
    fits.HDUList(hdus).writeto(path, overwrite=True)
    return path


# --- reprojection ---------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["interp", "exact"])
def test_a_sky_on_another_grid_reprojects_onto_the_function_on_the_model_grid(tmp_path, mode):
    """The Gaussian sky sampled on a grid turned 35 degrees from the model's, with 20 arcsec
    pixels (the model's are 44.7), centred 1.5 arcmin away, written in Jy/arcsec^2 (converted
    back by the reader) and reprojected onto the model grid, is the same function on the model
    grid within the interpolation error:

    - interp (bilinear, at the model pixels' centres): |e| <= h^2 / 8 (max|f_uu| + max|f_vv|)
      along the observed grid's axes (pixel side h); a Gaussian's second derivative along any
      direction is at most A / sigma_min^2, so |e| <= A h^2 / (4 sigma_b^2) = 4.4e-3 A;
    - exact (area means): against f's mean over each model pixel (16 x 16 midpoint rule, error
      H^2/(24 x 256) |lap f| ~ 2e-5 A); the leading error is each observed pixel's centre sample
      against its mean, (h^2 / 24) max|lap f| = (h^2 / 24) A (1/sigma_a^2 + 1/sigma_b^2) = 1.0e-3 A,
      plus the observed pixels split by the model pixel's edges, measured at under 25 % more
      (1.22e-3 A at h = 20", 3.5e-4 A at 10": second order). Tolerance twice the leading term.
    """
    s = sky_scene()
    _, wm, shape = model_grid(s, 32)
    h = 20.0
    n_obs = (114, 120)  # 38 x 40 arcmin: the model field (24 arcmin, turned) inside it
    wo = tan_wcs(centre(1.5, 200.0), h, PA0 + 35.0, n_obs)
    sky = on_grid(gaussian_sky, wo, n_obs)
    path = write_fits(tmp_path / "obs.fits", sky * MJY_SR_IN_JY_ARCSEC2, wo, bunit="Jy/arcsec2",
                      err=np.full(n_obs, 0.01 * MJY_SR_IN_JY_ARCSEC2))
    obs = ic.read_image(path, errors=["ERR"])
    assert obs.label.endswith("[SCI]") and np.allclose(obs.data, sky, rtol=1e-12, atol=0)
    assert np.allclose(obs.sigma, 0.01, rtol=1e-12)  # the error HDU's BUNIT is the image's when it has none
    rep = ic.reproject_to_model(obs, wm, shape, mode)
    ok = rep.usable
    assert ok.sum() >= 0.99 * ok.size  # the model grid lies inside the observation
    h_arcmin = h / 60.0
    if mode == "interp":
        want, tol = on_grid(gaussian_sky, wm, shape), GAUSS_A * h_arcmin ** 2 / (4 * GAUSS_SB ** 2)
    else:
        lap_max = GAUSS_A * (1 / GAUSS_SA ** 2 + 1 / GAUSS_SB ** 2)
        want, tol = on_grid(gaussian_sky, wm, shape, sub=16), 2 * h_arcmin ** 2 / 24 * lap_max
    err = np.abs(rep.data - want)[ok]
    assert err.max() <= tol, (err.max(), tol)
    # the comparison is sharp: the sky off by one model pixel (44.7") would differ by 0.2 A
    shifted = on_grid(lambda w: gaussian_sky(w.directional_offset_by(0.0 * w.ra.unit, 44.7 / 3600 * w.ra.unit)),
                      wm, shape)
    assert np.abs(shifted - want)[ok].max() > 20 * tol


def test_exact_reprojection_conserves_flux_and_surface_brightness():
    """Flux: an image of random surface brightness on a turned grid of 13" pixels lying wholly
    inside the model field: the sum of reprojected surface brightness x footprint x model pixel
    solid angle equals the sum over the observed pixels x their solid angle. Pixel solid angles
    are the projection-plane areas at the reference points; a TAN pixel's true solid angle falls
    as cos^3 of its distance theta from the tangent point, and the two grids' tangent points are
    1.5' apart, with the field within 7' of both, so the planar areas err by less than
    1.5 x (7'/3438')^2 = 6e-6 in relative terms: tolerance 2e-5. Surface brightness: a constant
    image reprojects onto that constant (both modes), to rounding."""
    s = sky_scene()
    _, wm, shape = model_grid(s, 32)
    rng = np.random.default_rng(5)
    for h, n, pa in ((13.0, (50, 60), 55.0), (70.0, (8, 9), 10.0)):  # finer and coarser than the model's pixels
        wo = tan_wcs(centre(1.5, 200.0), h, pa, n)
        x = rng.uniform(0.1, 2.0, n)
        obs = ic.ObservedImage(path="x", label="x", data=x, sigma=np.ones(n), wcs=wo, unit="MJy/sr")
        rep = ic.reproject_to_model(obs, wm, shape, "exact")
        flux_out = np.nansum(rep.data * rep.footprint) * ic._pixel_area_sr(wm)
        flux_in = x.sum() * ic._pixel_area_sr(wo)
        assert flux_out == pytest.approx(flux_in, rel=2e-5)
        assert 0 < rep.usable.sum() < rep.usable.size  # the observation is smaller than the model field
        const = ic.ObservedImage(path="x", label="x", data=np.full(n, 3.7), sigma=np.ones(n), wcs=wo, unit="MJy/sr")
        for mode in ic.REPROJECT_MODES:
            r = ic.reproject_to_model(const, wm, shape, mode)
            assert np.allclose(r.data[r.footprint > 0], 3.7, rtol=1e-12, atol=0)


# --- errors and chi^2 -----------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["interp", "exact"])
def test_errors_through_a_turned_finer_grid_give_chi2_its_distribution(mode):
    """Independent Gaussian noise of known sigma (0.25 MJy/sr times 1 to 2 across the image) on
    the analytic sky sampled on a turned grid of 20" pixels (about 5 per model pixel), reprojected
    onto the model grid: chi^2 of the result against the sky's own value on the model grid (the
    pixel means for exact, the centres for interp; their interpolation error is at most 0.0125 MJy/sr
    (the test above), under 1/8 of the propagated sigma of 0.11 to 0.5, so it adds at most about 1 %
    to chi^2) lies within
    5 sqrt(2 n) of n: the propagated variances sum W_jk^2 sigma_k^2 are right. Neighbouring model
    pixels share only the observed pixels split by their common edge, so chi^2 is near a sum of n
    independent squares. The error image reprojected as it stands (sum W_jk sigma_k) would make
    chi^2 several times too small. The area bound of the exact mode is at least the lattice's
    everywhere and too large by less than 1 / r (r = observed pixels across a model pixel)."""
    s = sky_scene()
    _, wm, shape = model_grid(s, 32)
    n_obs = (114, 120)
    wo = tan_wcs(centre(1.5, 200.0), 20.0, PA0 + 35.0, n_obs)
    rng = np.random.default_rng(11)
    sig = 0.25 * (1.0 + np.indices(n_obs)[1] / n_obs[1])
    noisy = on_grid(gaussian_sky, wo, n_obs) + sig * rng.standard_normal(n_obs)
    obs = ic.ObservedImage(path="x", label="x", data=noisy, sigma=sig, wcs=wo, unit="MJy/sr")
    rep = ic.reproject_to_model(obs, wm, shape, mode)
    assert rep.variance == "lattice" and rep.passes == (4 if mode == "interp" else 25)
    truth = on_grid(gaussian_sky, wm, shape, sub=1 if mode == "interp" else 16)
    c = ic.compare_image(truth, np.zeros(shape), rep.data, rep.error, mask=rep.usable)
    assert c.n >= 1000 and abs(c.chi2 - c.n) < 5 * math.sqrt(2 * c.n), (c.chi2, c.n)
    naive = ic.compare_image(truth, np.zeros(shape), rep.data,
                             ic.reproject_to_model(ic.ObservedImage("x", "x", sig, sig, wo, "MJy/sr"), wm, shape,
                                                   mode).data, mask=rep.usable)
    assert naive.chi2 < 0.7 * c.n
    if mode == "exact":
        bound = ic.reproject_to_model(obs, wm, shape, mode, variance="bound")
        ok = rep.usable
        excess = bound.error[ok] ** 2 / rep.error[ok] ** 2 - 1
        r = math.sqrt(rep.pixel_ratio)
        assert excess.min() >= -1e-9 and excess.mean() < 1 / r, (excess.mean(), r)


def test_chi2_of_an_independent_run_plus_noise_follows_its_distribution(tmp_path, backend):
    """The observation: the calibrated image (band G, PSF 60") of the scene traced with another
    seed (run B), plus Gaussian noise of known sigma_d (run B's own Monte Carlo error map, so that
    the three noises are alike in size), written on the model's grid with its error HDU
    sqrt(sigma_d^2 + sigma_B^2). Held against run A through the API (read, reproject onto the
    same grid: the identity, then trace, calibrate, chi^2): d - m has variance sigma_d^2 +
    sigma_B^2 + sigma_A^2, which is what chi^2 divides by with the run's own error in quadrature,
    so chi^2 lies within 5 sqrt(2 n) of n. The batch-means variance estimate of 16 batches is
    itself noisy (and heavy-tailed with few packets a pixel), which raises E[chi^2] by a few per
    cent at these packet counts (measured: 9-18 % with the Monte Carlo error alone at 80,000
    packets, a third of that here). Without the run's error chi^2 would be about 1.5 n: far
    outside."""
    from astropy.wcs import WCS

    size = 24
    kind = ic.resolve_band(sky_scene(), "G")
    sb = sky_scene(seed=2, photons=80_000)
    cam, wm, shape = model_grid(sb, size)
    b = ic.model_image(sb, kind, cam, backend)
    assert b.batches >= 16 and np.isfinite(b.error).all()
    rng = np.random.default_rng(7)
    sig_d = b.error
    obs_data = b.image + sig_d * rng.standard_normal(shape)
    path = write_fits(tmp_path / "obs.fits", obs_data, wm, err=np.sqrt(sig_d ** 2 + b.error ** 2),
                      extra={"BAND": "G"})
    obs = ic.read_image(path, "SCI", errors=["ERR"])
    assert obs.header_band == "G" and isinstance(obs.wcs, WCS)
    res = ic.compare_observed_image(sky_scene(seed=1, photons=80_000), obs, direction=(0, 0, -1), size=size,
                                    backend=backend)
    rep, a = res.observed, res.model
    ok = rep.usable
    assert np.allclose(rep.data[ok], obs_data[ok], rtol=1e-9, atol=1e-12 * np.abs(obs_data).max())  # identity
    assert np.allclose(rep.error[ok], obs.sigma[ok], rtol=1e-9, atol=1e-12 * obs.sigma.max())
    c = res.comparison
    assert a.band == "G" and c.n >= 400
    assert abs(c.chi2 - c.n) < 5 * math.sqrt(2 * c.n), (c.chi2, c.n)
    without = ic.compare_image(a.image, np.zeros(shape), rep.data, rep.error, mask=c.mask)
    assert without.chi2 > c.n + 5 * math.sqrt(2 * c.n), (without.chi2, c.n)
    d = res.to_dict()
    assert d["pixels"] == c.n and d["chi2"] == pytest.approx(np.nansum(c.pull ** 2), rel=1e-12)
    assert 0.0 < d["p_value"] < 1.0 and d["error_propagation"] == "lattice"


def test_the_model_error_is_the_transports_batch_error_calibrated(backend):
    """Without a PSF a band's calibrated pixel is its peel-off pixel times the band's constant
    (L_sun / L^2 / dnu in MJy/sr), so the model's Monte Carlo error, computed from each batch's
    calibrated deviation, is the transport's own batch-means error of the pixel (folded on the
    host by Welford's update, another path) times that constant, to rounding. A passband's image
    is the calibrated image's, with a positive error wherever light was scattered."""
    s = sky_scene(photons=4000, psf=0.0)
    cam, _, _ = model_grid(s, 16)
    cal, res = calibrate.peel_off_sky(s, cam, backend)
    b = 1
    m = ic.model_image(s, ic.resolve_band(s, "G"), cam, backend)
    lit = res.peel_image[b] > 0
    factor = (cal.scattered[b][lit] / res.peel_image[b][lit]).mean()
    np.testing.assert_allclose(cal.scattered[b][lit], factor * res.peel_image[b][lit], rtol=1e-12)
    np.testing.assert_allclose(m.error.T, factor * res.peel_error[b], rtol=1e-9, atol=1e-12 * m.error.max())
    np.testing.assert_allclose(m.image.T, cal.surface_brightness[b], rtol=1e-12)
    v = ic.model_image(s, ic.resolve_band(s, "bessell-V"), cam, backend)
    np.testing.assert_allclose(v.image.T, cal.passband_sb[cal.passbands.index("V")], rtol=1e-12)
    assert (v.error.T[lit] > 0).all() and v.batches == m.batches >= 16


def test_same_grid_chi2_is_the_sum_of_squared_pulls():
    """compare_image against an independent sum: chi^2 = sum (o - m)^2 / (sigma_o^2 + sigma_m^2)
    over the pixels with a positive combined error; images of another shape are refused."""
    rng = np.random.default_rng(1)
    m, me = rng.uniform(1, 2, (5, 6)), np.full((5, 6), 0.1)
    o, oe = m + 0.2 * rng.standard_normal((5, 6)), np.full((5, 6), 0.2)
    me[0, 0] = oe[0, 0] = 0.0  # no error at all: not used
    o[1, 1] = np.nan  # not observed: not used
    r = ic.compare_image(m, me, o, oe)
    ok = (oe ** 2 + me ** 2 > 0) & np.isfinite(o)
    want = sum((o[i] - m[i]) ** 2 / (oe[i] ** 2 + me[i] ** 2) for i in zip(*np.nonzero(ok)))
    assert r.n == 28 and r.chi2 == pytest.approx(want, rel=1e-12)
    with pytest.raises(SceneError, match="shape"):
        ic.compare_image(m, me, o[:4], oe[:4])


# --- bad input ------------------------------------------------------------------------------


def test_bad_images_are_refused_naming_the_file_and_what_is_allowed(tmp_path, monkeypatch):
    """Each bad observation is a SceneError naming the file (and HDU) and what is allowed: no
    celestial WCS, no overlap with the model image (checked before tracing), a unit that is not
    a surface brightness, no unit, no error, an error HDU of another shape, an unknown HDU, a file
    that is not FITS; and without the reproject package, a SceneError naming it and the extra."""
    s = sky_scene()
    _, wm, shape = model_grid(s, 24)
    n = (30, 30)
    wo = tan_wcs(centre(1.0, 45.0), 40.0, 10.0, n)
    good = np.ones(n)

    def refused(match, path, **kw):
        with pytest.raises(SceneError, match=match) as e:
            obs = ic.read_image(path, kw.pop("hdu", None), errors=kw.pop("errors", ["5%"]), **kw)
            ic.check_overlap(obs, wm, shape)
        return str(e.value)

    from astropy.wcs import WCS

    lin = WCS(naxis=2)  # pixel coordinates only
    lin.wcs.ctype = ["LINEAR", "LINEAR"]
    msg = refused("celestial WCS", write_fits(tmp_path / "nowcs.fits", good, lin))
    assert "nowcs.fits[SCI]" in msg and "RA---TAN" in msg
    far = tan_wcs(centre(600.0, 0.0), 40.0, 10.0, n)  # 10 degrees north
    msg = refused("no overlap", write_fits(tmp_path / "far.fits", good, far))
    assert "far.fits[SCI]" in msg and "must overlap the model image" in msg and f"{RA0:.5f}" in msg
    msg = refused("BUNIT", write_fits(tmp_path / "adu.fits", good, wo, bunit="adu"))
    assert "adu.fits[SCI]" in msg and "MJy/sr" in msg
    msg = refused("BUNIT", write_fits(tmp_path / "flam.fits", good, wo, bunit="erg/(s cm2 Angstrom sr)"))
    assert "per unit frequency" in msg
    msg = refused("BUNIT", write_fits(tmp_path / "nounit.fits", good, wo, bunit=None))
    assert "nounit.fits[SCI]" in msg and "--image-unit" in msg
    assert ic.read_image(tmp_path / "nounit.fits", unit="MJy/sr", errors=["5%"]).unit == "MJy/sr"
    msg = refused("--image-error", write_fits(tmp_path / "ok.fits", good, wo), errors=[])
    assert "1-sigma" in msg
    write_fits(tmp_path / "err.fits", good, wo, err=np.ones((3, 3)))
    assert "shape" in refused("--image-error", tmp_path / "err.fits", errors=["ERR"])
    assert "'5%'" in refused("--image-error", tmp_path / "ok.fits", errors=["0.2 km"])
    assert "SCI" in refused("--image-hdu", tmp_path / "ok.fits", hdu="NOPE")
    (tmp_path / "text.fits").write_text("not a FITS file\n")
    assert "text.fits" in refused("FITS", tmp_path / "text.fits")
    obs = ic.read_image(tmp_path / "ok.fits", errors=["5%", "0.02 MJy/sr"])  # in quadrature
    assert np.allclose(obs.sigma, math.hypot(0.05, 0.02), rtol=1e-12)
    with pytest.raises(SceneError, match="--image-band"):
        ic.resolve_band(s, "bessell-U")
    assert ic.resolve_band(s, "bessell-V") == ("passband", "V", "bessell-V")
    monkeypatch.setitem(sys.modules, "reproject", None)  # as if not installed
    with pytest.raises(SceneError, match=r"reproject.*nebula-rt\[observe\]"):
        ic.reproject_to_model(obs, wm, shape)


# --- the command ----------------------------------------------------------------------------


def test_cli_compare_image_writes_the_plot_and_prints_chi2(tmp_path, capsys, backend):
    """``nebula-rt compare --image`` on a 16^3 scene with 4000 packets: the observation is the
    calibrated FITS of the same scene with another seed (as ``nebula-rt sky --fits`` writes it: its
    SB_G extension, BUNIT MJy/sr, the model's WCS) with a 20 % error; the command prints chi^2 in
    its JSON summary, writes the side-by-side plot and the comparison FITS, whose PULL image
    squared and summed is chi^2 and whose MODEL is the calibrated image with the command's seed;
    --mask-stars leaves out the pixels within the radius of the star (counted here by hand).
    A bad image exits 2 naming the file and writes nothing."""
    from astropy.io import fits

    from nebula_rt.cli import commands as cli

    s = sky_scene(photons=4000)
    (tmp_path / "s.toml").write_text(s.to_toml())
    cam = calibrate.camera_for(s, size=24)
    obs_cal, _ = calibrate.peel_off_sky(s.with_overrides(["transport.seed=2"]), cam, backend)
    calibrate.write_fits(tmp_path / "obs.fits", obs_cal, s)
    model_cal, _ = calibrate.peel_off_sky(s, cam, backend)
    out = tmp_path / "out"
    out.mkdir()
    args = ["compare", str(tmp_path / "s.toml"), "--image", str(tmp_path / "obs.fits"), "--image-hdu", "SB_G",
            "--image-error", "20%", "--size", "24", "--png", str(out / "c.png"), "--json", str(out / "c.json"),
            "--fits", str(out / "c.fits")]
    assert cli.main(args) == 0, capsys.readouterr().err
    printed = json.loads(capsys.readouterr().out)
    assert printed["chi2"] > 0 and printed["band"] == "G" and printed["reproject"] == "exact"
    assert json.loads((out / "c.json").read_text())["chi2"] == printed["chi2"]
    assert (out / "c.png").stat().st_size > 20_000
    with fits.open(out / "c.fits") as h:
        pull = h["PULL"].data.astype(np.float64)
        assert np.nansum(pull ** 2) == pytest.approx(printed["chi2"], rel=1e-5)  # float32 pulls
        assert np.isfinite(pull).sum() == printed["pixels"]
        want = model_cal.surface_brightness[1].T  # float32 in the file: its rounding, and its underflow below 1e-38
        np.testing.assert_allclose(h["MODEL"].data, want, rtol=1e-6, atol=1e-30 * want.max())
        assert h["MODEL"].header["CTYPE1"] == "RA---TAN" and h["MODEL"].header["BUNIT"] == "MJy/sr"
    radius = 150.0  # arcsec: 2.5 model pixels of 59.5"
    assert cli.main(args + ["--mask-stars", str(radius)]) == 0, capsys.readouterr().err
    masked = json.loads(capsys.readouterr().out)
    p, q = model_cal.star_pixel[0]
    yy, xx = np.indices((24, 24))
    inside = (xx - p) ** 2 + (yy - q) ** 2 <= (radius / masked["model_pixel_arcsec"]) ** 2
    assert masked["pixels"] == printed["pixels"] - int((inside & np.isfinite(pull)).sum()) < printed["pixels"]
    # a bad image: exit 2, named, nothing written
    write_fits(tmp_path / "adu.fits", np.ones((8, 8)), calibrate.celestial_wcs(s, cam), bunit="adu")
    bad = ["compare", str(tmp_path / "s.toml"), "--image", str(tmp_path / "adu.fits"), "--image-error", "5%",
           "--image-band", "G", "--png", str(out / "bad.png")]
    assert cli.main(bad) == 2
    err = capsys.readouterr().err
    assert "adu.fits[SCI]" in err and "MJy/sr" in err
    assert not (out / "bad.png").exists()
    # an image's option without --image is refused, not ignored
    lone = ["compare", str(tmp_path / "s.toml"), "--fits", str(out / "x.fits"), "--png", str(out / "x.png")]
    assert cli.main(lone) == 2
    assert "--fits" in capsys.readouterr().err and not (out / "x.png").exists()
