"""Tests of nebula_rt.optics.colour_convert (band results -> sRGB)."""

from __future__ import annotations

import colour
import numpy as np
import pytest

from nebula_rt.optics.colour_convert import (
    auto_exposure, band_luminosity_fractions, band_to_xyz_matrix, bands_to_srgb8, encode_srgb, gamut_map, hat_basis, star_spectrum, xyz_to_linear_srgb)

THESIS_BANDS = np.array([677.0, 550.0, 439.0])  # thesis-rgb order: R, G, B
EIGHT_BANDS = np.array([400.0, 440.0, 480.0, 520.0, 560.0, 600.0, 650.0, 700.0])
LUM = np.array([0.2126, 0.7152, 0.0722])


def blackbody_xy(temperature: float) -> np.ndarray:
    """Chromaticity of a blackbody by colour-science at full 1 nm resolution.

    The shape is passed explicitly: by default colour-science 0.4 trims the
    integral to 360..780 nm, which moves a 3000 K star by ~2e-6 in xy.
    """
    shape = colour.SpectralShape(360, 830, 1)
    sd = colour.sd_blackbody(temperature, shape)
    xyz = colour.sd_to_XYZ(
        sd,
        cmfs=colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"],
        illuminant=colour.sd_ones(shape),  # equal energy: emission, not reflectance
        method="Integration",
        shape=shape,
    )
    return colour.XYZ_to_xy(xyz)


# --- hat basis ---------------------------------------------------------------

def test_hat_basis_partition_of_unity_and_nodes():
    wl = np.arange(300.0, 901.0, 0.5)
    h = hat_basis(EIGHT_BANDS, wl)
    assert h.shape == (8, wl.size)
    np.testing.assert_allclose(h.sum(axis=0), 1.0, atol=1e-12)
    assert np.all(h >= 0.0)
    at_centres = hat_basis(EIGHT_BANDS, EIGHT_BANDS)
    np.testing.assert_allclose(at_centres, np.eye(8), atol=1e-12)


def test_hat_basis_unsorted_and_constant_ends():
    wl = np.arange(360.0, 831.0)
    h = hat_basis(THESIS_BANDS, wl)  # descending input
    np.testing.assert_allclose(hat_basis(THESIS_BANDS, THESIS_BANDS), np.eye(3), atol=1e-12)
    np.testing.assert_allclose(h.sum(axis=0), 1.0, atol=1e-12)
    # Rows follow input order: row 2 is the 439 nm band, 1 below 439 nm.
    assert np.all(h[2, wl <= 439] == 1.0)
    assert np.all(h[0, wl >= 677] == 1.0)
    # Midway between 439 and 550 both neighbours weigh 1/2.
    np.testing.assert_allclose(hat_basis(THESIS_BANDS, [494.5])[:, 0], [0.0, 0.5, 0.5])
    # Same result as the sorted input with permuted rows.
    order = np.argsort(THESIS_BANDS)
    np.testing.assert_allclose(hat_basis(THESIS_BANDS[order], wl), h[order])


def test_hat_basis_single_band():
    h = hat_basis([550.0], np.arange(360.0, 831.0))
    assert h.shape == (1, 471)
    assert np.all(h == 1.0)


def test_hat_basis_rejects_duplicates():
    with pytest.raises(ValueError):
        hat_basis([550.0, 550.0], [500.0])


# --- spectra and band fractions ----------------------------------------------

def test_star_spectrum_shape():
    wl = np.arange(360.0, 831.0)
    assert np.all(star_spectrum(None, wl) == 1.0)
    s = star_spectrum(5800.0, wl)
    ref = colour.sd_blackbody(5800.0, colour.SpectralShape(360, 830, 1)).values
    np.testing.assert_allclose(s / s[200], ref / ref[200], rtol=1e-10)
    with pytest.raises(ValueError):
        star_spectrum(-1.0, wl)


@pytest.mark.parametrize("temperature", [None, 3000.0, 5800.0, 20000.0])
def test_band_luminosity_fractions_sum_to_one(temperature):
    f = band_luminosity_fractions(EIGHT_BANDS, temperature)
    assert f.shape == (8,)
    assert np.all(f > 0)
    assert abs(f.sum() - 1.0) < 1e-12


def test_band_luminosity_fractions_flat_analytic():
    f = band_luminosity_fractions(THESIS_BANDS, None)
    total = 780.0 - 380.0
    f439 = (439 - 380) + (550 - 439) / 2  # 114.5 nm
    f550 = (550 - 439) / 2 + (677 - 550) / 2  # 119 nm
    f677 = (677 - 550) / 2 + (780 - 677)  # 166.5 nm
    np.testing.assert_allclose(f, np.array([f677, f550, f439]) / total, rtol=1e-12)


def test_hot_star_puts_more_light_in_blue_band():
    cool = band_luminosity_fractions(THESIS_BANDS, 3000.0)
    hot = band_luminosity_fractions(THESIS_BANDS, 20000.0)
    assert hot[2] > cool[2] and hot[0] < cool[0]


# --- band -> XYZ --------------------------------------------------------------

@pytest.mark.parametrize("temperature", [3000.0, 5800.0, 20000.0])
@pytest.mark.parametrize("bands", [THESIS_BANDS, EIGHT_BANDS], ids=["3band", "8band"])
def test_star_seen_directly_is_exact(temperature, bands):
    m = band_to_xyz_matrix(bands, temperature)
    assert m.shape == (3, bands.size)
    xyz = m @ np.ones(bands.size)
    assert abs(xyz[1] - 1.0) < 1e-12
    # A constant ratio is interpolated exactly by the hat basis, so this is
    # the same sum as colour-science's: exact up to rounding.
    np.testing.assert_allclose(colour.XYZ_to_xy(xyz), blackbody_xy(temperature), atol=1e-9)


def test_flat_star_is_equal_energy_white():
    xyz = band_to_xyz_matrix(THESIS_BANDS, None) @ np.ones(3)
    np.testing.assert_allclose(colour.XYZ_to_xy(xyz), [1 / 3, 1 / 3], atol=1e-4)


@pytest.mark.parametrize(
    "temperature, expected", [(5800.0, (255, 241, 235)), (20000.0, (171, 193, 255))]
)
def test_blackbody_srgb_reference(temperature, expected):
    xyz = band_to_xyz_matrix(THESIS_BANDS, temperature) @ np.ones(3)
    rgb = gamut_map(xyz_to_linear_srgb(xyz))
    rgb8 = encode_srgb(rgb, 1.0 / rgb.max())
    assert rgb8.dtype == np.uint8
    assert np.all(np.abs(rgb8.astype(int) - np.array(expected)) <= 3), rgb8
    # Same through the full pipeline with the star's own band luminosities.
    star = band_luminosity_fractions(THESIS_BANDS, temperature)
    out, e = bands_to_srgb8(star[:, None], THESIS_BANDS, star, temperature, exposure=1.0 / rgb.max())
    np.testing.assert_array_equal(out[0], rgb8)


def test_xyz_to_linear_srgb_matches_colour_science():
    xyz = np.array([[0.3, 0.4, 0.2], [0.95047, 1.0, 1.08883]])
    ref = colour.XYZ_to_RGB(
        xyz,
        colour.RGB_COLOURSPACES["sRGB"],
        apply_cctf_encoding=False,
        chromatic_adaptation_transform=None,
    )
    np.testing.assert_allclose(xyz_to_linear_srgb(xyz), ref, rtol=1e-10)
    # D65 is white.
    white = xyz_to_linear_srgb(xyz[1])
    np.testing.assert_allclose(white, white[1], rtol=1e-3)


def test_bluer_nebula_than_star():
    temperature = 5800.0
    star = band_luminosity_fractions(THESIS_BANDS, temperature)
    ratio = np.array([0.2, 0.4, 0.8])  # rises towards 439 nm (Rayleigh-like dust)
    m = band_to_xyz_matrix(THESIS_BANDS, temperature)
    rgb_star = xyz_to_linear_srgb(m @ np.ones(3))
    rgb_neb = xyz_to_linear_srgb(m @ ratio)
    assert rgb_neb[2] / rgb_neb[0] > rgb_star[2] / rgb_star[0]
    xy_star = colour.XYZ_to_xy(m @ np.ones(3))
    xy_neb = colour.XYZ_to_xy(m @ ratio)
    assert xy_neb[0] < xy_star[0] and xy_neb[1] < xy_star[1]


# --- gamut mapping, exposure, encoding ---------------------------------------

def test_gamut_map_in_gamut_unchanged():
    rgb = np.array([[0.2, 0.5, 0.9], [0.0, 0.0, 0.0], [3.0, 1.0, 0.0]])
    np.testing.assert_array_equal(gamut_map(rgb), rgb)


def test_gamut_map_negative_component():
    rgb = np.array([[-0.1, 0.5, 0.9], [0.8, -0.05, 0.1], [0.1, 0.2, -3.0]])
    out = gamut_map(rgb)
    y_in = rgb @ LUM
    for i in range(2):  # rows with positive luminance
        assert y_in[i] > 0
        assert abs(out[i].min()) < 1e-12
        np.testing.assert_allclose(out[i] @ LUM, y_in[i], rtol=1e-12)
    assert y_in[2] < 0
    np.testing.assert_array_equal(out[2], 0.0)
    # Desaturation keeps the direction from grey (hue).
    d_in = rgb[0] - y_in[0]
    d_out = out[0] - y_in[0]
    np.testing.assert_allclose(d_out / np.linalg.norm(d_out), d_in / np.linalg.norm(d_in), atol=1e-12)


def test_gamut_map_zero_and_shapes():
    z = np.zeros((4, 5, 3))
    out = gamut_map(z)
    assert out.shape == z.shape and np.all(out == 0.0) and not np.any(np.isnan(out))
    single = gamut_map(np.array([-0.1, 0.5, 0.9]))
    assert single.shape == (3,) and abs(single.min()) < 1e-12


def test_encode_srgb_exposure_and_hue():
    lin = np.array([[0.1, 0.2, 0.05], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    out = encode_srgb(lin, 2.0)
    assert out.dtype == np.uint8 and out.shape == (3, 3)
    expected = np.rint(255 * colour.cctf_encoding(lin[0] * 2.0, function="sRGB"))
    np.testing.assert_array_equal(out[0], expected)
    np.testing.assert_array_equal(out[1], 0)
    np.testing.assert_array_equal(out[2], 255)
    # Over-exposed colour: scaled by its max, ratios kept.
    hot = np.array([4.0, 2.0, 1.0])
    out_hot = encode_srgb(hot, 1.0)
    expected_hot = np.rint(255 * colour.cctf_encoding(hot / 4.0, function="sRGB"))
    np.testing.assert_array_equal(out_hot, expected_hot)
    assert out_hot[0] == 255 and out_hot[1] < 255 and out_hot[2] < out_hot[1]
    with pytest.raises(ValueError):
        encode_srgb(lin, 0.0)


def test_auto_exposure():
    rng = np.random.default_rng(1)
    rgb = rng.uniform(0.0, 2.0, size=(1000, 3))
    rgb[:500] = 0.0  # empty space is ignored
    e = auto_exposure(rgb, percentile=100.0)
    assert e == pytest.approx(1.0 / rgb.max())
    e995 = auto_exposure(rgb)
    mx = rgb[500:].max(axis=1)
    assert e995 == pytest.approx(1.0 / np.percentile(mx, 99.5))
    assert auto_exposure(np.zeros((10, 3))) == 1.0


def test_bands_to_srgb8_volume_and_auto():
    rng = np.random.default_rng(2)
    temperature = 20000.0
    star = 5.0 * band_luminosity_fractions(EIGHT_BANDS, temperature)
    vals = rng.uniform(0.0, 1.0, size=(8, 6, 5, 4)) * star[:, None, None, None]
    vals[:, 0, 0, 0] = 0.0
    out, e = bands_to_srgb8(vals, EIGHT_BANDS, star, temperature)
    assert out.shape == (6, 5, 4, 3) and out.dtype == np.uint8
    assert e > 0
    np.testing.assert_array_equal(out[0, 0, 0], 0)
    # Vectorised result equals the per-voxel composition of the public steps.
    m = band_to_xyz_matrix(EIGHT_BANDS, temperature)
    v = vals[:, 2, 3, 1] / star
    rgb = gamut_map(xyz_to_linear_srgb(m @ v))
    np.testing.assert_array_equal(out[2, 3, 1], encode_srgb(rgb, e))
    with pytest.raises(ValueError):
        bands_to_srgb8(vals[:3], EIGHT_BANDS, star, temperature)
    with pytest.raises(ValueError):
        bands_to_srgb8(vals, EIGHT_BANDS, star, temperature, exposure="bright")


def test_sky_picture_is_the_one_composition_of_sky_pictures():
    """colour_convert.sky_picture makes every sky picture (nebula-rt sky's and Nebula Sky
    Image's): its auto exposure brings the given percentile of the scattered light's largest
    displayed component to full scale (1.0 before the transfer curve), a star brighter than
    that saturates, a given exposure is used as it is, and the tone curve is the scene's."""
    from nebula_rt.optics.colour_convert import band_to_xyz_matrix, gamut_map, sky_picture, xyz_to_linear_srgb

    rng = np.random.default_rng(7)
    wl = np.array([450.0, 550.0, 650.0])
    lum = np.array([1.2, 1.0, 0.8])
    scattered = rng.uniform(0.0, 1e-3, (3, 16, 12))
    intensity = scattered.copy()
    intensity[:, 5, 7] += 1.0  # a star, far brighter than the nebula
    m = band_to_xyz_matrix(wl, 20000.0)
    rgb8, exposure = sky_picture(intensity, scattered, lum, m, "auto", 90.0)
    displayed = gamut_map(xyz_to_linear_srgb(np.tensordot(scattered / lum[:, None, None], m, axes=([0], [1]))))
    assert np.percentile(displayed.max(axis=-1), 90.0) * exposure == pytest.approx(1.0, rel=1e-12)
    assert rgb8.shape == (16, 12, 3) and rgb8.dtype == np.uint8 and rgb8[5, 7].max() == 255
    fixed, used = sky_picture(intensity, scattered, lum, m, 2.5)
    assert used == 2.5 and not np.array_equal(fixed, rgb8)
    asinh, used_asinh = sky_picture(intensity, scattered, lum, m, "auto", 90.0, "asinh", 8.0)
    assert used_asinh == exposure and not np.array_equal(asinh, rgb8)
