"""Colours as an observer measures them, against observed reflection nebulae.

Expected behaviour (REFERENCES.md, data/observations.toml):
- optically thin dust scatters blue light more (extinction and albedo both rise to the blue),
  so Delta(B-V) lies inside the single-scattering range -0.34 .. -0.17 mag;
- more dust reddens the scattered light: Delta(B-V) rises monotonically with optical depth.
MC tolerance: each annulus sums thousands of pixels of 8 bands x 60k packets; the run-to-run
scatter of an annulus's Delta(B-V) is below 0.01 mag here (checked by the seed test), so the
monotonic steps (0.1 mag and more) are far outside the noise.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import TEST_BACKEND, TEST_DEVICE
from nebula_rt import observe
from nebula_rt.colour_convert import band_luminosity_fractions
from nebula_rt.pipeline import Pipeline
from nebula_rt.scene import Scene


def uniform_scene(tau, seed=1, photons=60_000):
    return Scene.from_dict({
        "grid": {"shape": [24, 24, 24]},
        "dust": {"model": "uniform", "density": 1.0, "tau": tau},
        "stars": [{"position": [0.5, 0.5, 0.5], "temperature": 14000.0}],
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
    means = []
    for tau in (0.1, 1.0, 3.0, 10.0):
        prof = observe.profiles(Pipeline(backend).run(uniform_scene(tau), colour=False), size=48)
        means.append(float(np.nanmean(prof.delta_bv)))
    assert np.all(np.diff(means) > 0.05), means
    assert means[0] < -0.17 and means[-1] > 0.0  # from bluer than the star to redder


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
    bad = subprocess.run([sys.executable, "-m", "nebula_rt.cli", "compare", str(scene), "--direction", "0,0"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "--direction" in bad.stderr


def test_band_luminosities_add_up_for_spectral_bands():
    wl = [b.wavelength for b in Scene.from_dict({"bands": {"preset": "spectral-16"}}).bands.resolve()]
    assert band_luminosity_fractions(wl, 17000.0).sum() == pytest.approx(1.0, abs=1e-12)
