"""The volume's opacity chosen from the data (colour.opacity_scale = "auto", the default).

The rgba alpha of a voxel is 1 - exp(-k sigma_ref h); "auto" picks k so that the reference
band's mean optical depth across the box is nebula_rt.pipeline.AUTO_OPACITY_MEAN_TAU (3), a
number is k itself (1: the dust's own opacity). Checked on real traces (PoCL), from the alpha
bytes the light field writes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from nebula_rt.pipeline.rgba import AUTO_OPACITY_MEAN_TAU, mean_optical_depth
from nebula_rt.pipeline import Pipeline
from nebula_rt.scene import Scene

SHAPE = (24, 20, 16)


def run(backend, **colour_and_dust):
    dust = {k: v for k, v in colour_and_dust.items() if k in ("tau", "model", "density")}
    colour = {k: v for k, v in colour_and_dust.items() if k in ("opacity_scale", "stretch")}
    scene = Scene.from_dict({"grid": {"shape": list(SHAPE)}, "dust": dust, "colour": colour,
                             "transport": {"photons": 4000}})
    return Pipeline(backend).run(scene)


def voxel_optical_depth(alpha8):
    """-ln(1 - a/255): the optical depth of one voxel that an alpha byte stands for."""
    return -np.log1p(-alpha8.astype(np.float64) / 255.0)


def rounding_bound(alpha8, n_column):
    """The largest error of a column's optical depth from uint8 alpha: half a level per
    voxel, d tau = (0.5/255) / (1 - a/255 - 0.5/255), over the column's voxels."""
    a = min(float(alpha8.max()), 254.0) / 255.0
    return n_column * (0.5 / 255.0) / (1.0 - a - 0.5 / 255.0)


@pytest.mark.parametrize("tau", [1.0, 128.0])
def test_auto_gives_the_box_a_mean_optical_depth_of_3(backend, tau):
    """Whatever tau, the alpha bytes of the default colour sum, along a column of the box, to a
    mean optical depth of 3 (the mean over voxels times the voxels per edge; the grid is
    not cubic: h is the geometric mean of the spacing, so a column of n voxels is n h long
    in those units and the mean over columns is N^(1/3) voxels' worth), within the rounding
    of the bytes; the factor used is what the field data say."""
    light = run(backend, tau=tau)
    alpha = light.rgba[..., 3]
    n_edge = math.prod(SHAPE) ** (1.0 / 3.0)  # 1 / h
    mean_tau = voxel_optical_depth(alpha).mean() * n_edge
    assert abs(mean_tau - AUTO_OPACITY_MEAN_TAU) <= rounding_bound(alpha, n_edge), mean_tau
    fd = light.field_data()
    sigma_scale = tau * light.bands[light.reference_band].extinction
    assert fd["opacity_scale"] == AUTO_OPACITY_MEAN_TAU / mean_optical_depth(light.density, sigma_scale)


def test_auto_opacity_does_not_depend_on_tau(backend):
    """k sigma = 3 sigma / mean(sigma): tau cancels, so a thin and a thick nebula of the same
    density have the same alpha bytes (up to the rounding of k sigma h in float64, which may
    move a byte at a .5 boundary: at most 1 level, in under 0.1 % of the voxels), while their
    colours differ (the thick one's light is extinguished: tau changes J)."""
    thin, thick = run(backend, tau=1.0), run(backend, tau=50.0)
    d = np.abs(thin.rgba[..., 3].astype(int) - thick.rgba[..., 3].astype(int))
    assert d.max() <= 1 and (d > 0).mean() < 1e-3
    assert np.abs(thin.rgba[..., :3].astype(int) - thick.rgba[..., :3].astype(int)).max() > 10


def test_a_number_is_the_factor_on_the_dusts_own_opacity(backend):
    """opacity_scale = 1: alpha = 1 - exp(-sigma_ref h) of the dust itself (bit for bit the
    float64 formula, rounded to a byte); 4: the same with 4 sigma_ref."""
    for k in (1.0, 4.0):
        light = run(backend, tau=20.0, opacity_scale=k)
        sigma = 20.0 * light.bands[light.reference_band].extinction * light.density.astype(np.float64)
        h = math.prod(1.0 / n for n in SHAPE) ** (1.0 / 3.0)
        want = np.clip(np.rint((1.0 - np.exp(-(sigma * h * k))) * 255.0), 0, 255).astype(np.uint8)
        np.testing.assert_array_equal(light.rgba[..., 3], want)
        assert light.field_data()["opacity_scale"] == k


def test_the_asinh_stretch_keeps_the_auto_opacity(backend):
    """colour.stretch = "asinh" colours on the host (the device's colour pass has the linear
    curve only): the opacity is still the auto factor of the density, written to the field
    data, and the alpha bytes are the float64 formula with it, bit for bit (as a number's
    are above); the stretch changes the colour only."""
    light = run(backend, tau=20.0, stretch="asinh")
    sigma_scale = 20.0 * light.bands[light.reference_band].extinction
    k = light.field_data()["opacity_scale"]
    assert k == AUTO_OPACITY_MEAN_TAU / mean_optical_depth(light.density, sigma_scale)
    sigma = sigma_scale * light.density.astype(np.float64)
    h = math.prod(1.0 / n for n in SHAPE) ** (1.0 / 3.0)
    want = np.clip(np.rint((1.0 - np.exp(-(sigma * h * k))) * 255.0), 0, 255).astype(np.uint8)
    np.testing.assert_array_equal(light.rgba[..., 3], want)


def test_no_dust_keeps_a_transparent_volume(backend):
    """tau 0: nothing to scale (k = 1), every alpha 0, no error."""
    light = run(backend, tau=0.0)
    assert light.rgba[..., 3].max() == 0 and light.field_data()["opacity_scale"] == 1.0


@pytest.mark.parametrize("stretch", ["linear", "asinh"])
def test_a_density_file_has_its_mean_summed_on_the_device(backend, tmp_path, monkeypatch, stretch):
    """A density read from a file has no device copy made with it: the finishing sums the
    transport's copy on the device (not the host), and the factor is the host's exact mean's,
    bit for bit, as the output's density gives it to Nebula Colour."""
    from nebula_rt import exact_sum

    rng = np.random.default_rng(2)
    rho = rng.lognormal(-1.0, 1.5, SHAPE).astype(np.float32)
    np.save(tmp_path / "rho.npy", rho)
    scene = Scene.from_dict({"grid": {"shape": list(SHAPE)},
                             "dust": {"model": "file", "file": str(tmp_path / "rho.npy"), "tau": 5.0},
                             "colour": {"stretch": stretch}, "transport": {"photons": 4000}})
    def no_host_sums(values):
        raise AssertionError("the pipeline summed the density on the host")

    monkeypatch.setattr(exact_sum, "significand_sums", no_host_sums)
    light = Pipeline(backend).run(scene)
    monkeypatch.undo()
    sigma_scale = 5.0 * scene.bands.resolve()[light.reference_band].extinction
    want = AUTO_OPACITY_MEAN_TAU / mean_optical_depth(light.density, sigma_scale)  # (floored at dust.floor)
    assert light.field_data()["opacity_scale"] == light.opacity_scale == want

