"""Error-targeted runs and quality presets.

The honesty test compares the reported error with the true error of a pure absorber, whose
J is analytic (L exp(-kappa r) / (16 pi^2 r^2), averaged over each voxel by quadrature):
- the reported error is the brightness-weighted RMS over the lit region of the per-voxel
  1-sigma batch-means errors, so the same weighted RMS of the true relative errors over the
  same voxels must match it; with thousands of voxels both are known to a few per cent, hence
  the +-15 % band;
- per voxel, |true error| <= 2 x reported holds with probability P(|t_15| <= 2) = 0.936 for a
  batch-means error from 16 batches (Student t, 15 degrees of freedom); over ~1000 voxels the
  observed fraction is known to about +-1 % (binomial), so 0.90..0.97 is a 3-sigma band that
  also fails if the errors are overstated.
"""

from __future__ import annotations

import numpy as np
import pytest

from conftest import centre_star, one_band, voxel_centres
from nebula_rt.errors import SceneError
from nebula_rt.scene import QUALITY_PRESETS, Transport
from nebula_rt.scene import Scene
from nebula_rt.transport.estimate import lit_region
from nebula_rt.transport import trace
from nebula_rt.transport.analytic import voxel_average_point_source

SHAPE = (16, 16, 16)
KAPPA = 3.0


def absorber_run(backend, **kw):
    rho = np.ones(SHAPE, np.float32)
    args = dict(tau=KAPPA, photons=2_000_000, seed=5, backend=backend, target_error=0.1)
    args.update(kw)
    return trace(rho, one_band(albedo=0.0), centre_star(1.0), **args)


def test_reported_error_is_honest(backend):
    res = absorber_run(backend)
    assert res.photons < res.photons_budget  # stopped on the target, not the budget
    assert res.achieved_error <= 0.1
    sigma = np.full((1,) + SHAPE, KAPPA)
    lit = lit_region(res.J, sigma)[0]
    X, Y, Z = voxel_centres(SHAPE)
    r = np.sqrt((X - 0.5) ** 2 + (Y - 0.5) ** 2 + (Z - 0.5) ** 2)
    mask = lit & (r > 1.5 / SHAPE[0])  # the star's voxels: quadrature of a 1/r^2 singularity
    assert mask.sum() > 500
    truth = voxel_average_point_source(SHAPE, (0.5, 0.5, 0.5), KAPPA, 1.0, mask, order=6)
    true_rel = res.J[0][mask] / truth - 1.0
    reported = res.rel_error[0][mask]
    w = res.J[0][mask] * KAPPA  # brightness weights sigma J, as the reported error uses
    ratio = np.sqrt(np.sum(w * true_rel**2) / np.sum(w * reported**2))
    print(f"photons {res.photons}, error {res.achieved_error:.4f}, true/reported RMS {ratio:.3f}")
    assert 0.85 < ratio < 1.15, ratio
    coverage = np.mean(np.abs(true_rel) <= 2.0 * reported)
    print(f"coverage at 2 sigma {coverage:.3f} over {mask.sum()} voxels")
    assert 0.90 < coverage < 0.97, coverage


def test_targeted_runs_are_deterministic(backend):
    a = absorber_run(backend, target_error=0.15)
    b = absorber_run(backend, target_error=0.15)
    assert a.photons == b.photons and a.batches == b.batches
    assert a.J.tobytes() == b.J.tobytes()
    # energies stay exact with the photons actually used
    e = a.energy[0]
    assert e[0] == e[1] + e[2] + e[3]
    assert a.counts[0, 0] == a.photons


def test_budget_ends_a_run_that_cannot_reach_its_target(backend):
    res = absorber_run(backend, target_error=1e-4, photons=40_000)
    assert res.photons == res.photons_budget == 40_000
    assert res.achieved_error > 1e-4


def test_time_limit_ends_a_run(backend):
    res = absorber_run(backend, target_error=1e-4, time_limit=1e-9)
    # stopped after the first launch: its finished batches are the result, the error is theirs
    assert 1 <= res.batches < 256 and res.photons < res.photons_budget
    assert res.counts[0, 0] == res.photons and 0 < res.achieved_error < 1


@pytest.mark.parametrize("target", [0.0, 1e-3])
def test_time_limit_holds_whatever_the_budget(backend, target):
    """A budget of 10^12 packets per band with a 2 s limit ends after about 2 s (launches are
    sized to LAUNCH_SECONDS by the measured speed; the batch plan costs O(1) memory), with or
    without a target error, and keeps only finished batches (exact energies)."""
    import time

    from nebula_rt.transport.run import LAUNCH_SECONDS

    t0 = time.perf_counter()
    res = absorber_run(backend, photons=10**12, target_error=target, time_limit=2.0)
    wall = time.perf_counter() - t0
    # the limit plus one launch, plus the finishing of a 16^3 grid (generous for a loaded CPU)
    assert wall < 2.0 + 2 * LAUNCH_SECONDS + 1.5, wall
    assert 1 <= res.batches and res.photons < res.photons_budget == 10**12
    e = res.energy[0]
    assert res.counts[0, 0] == res.photons and e[0] == e[1] + e[2] + e[3]


def test_quality_presets():
    for name, preset in QUALITY_PRESETS.items():
        t = Transport(quality=name, photons=123, target_error=0.5)
        assert t.effective() == (preset["photons"], preset["target_error"])
    assert Transport(photons=123, target_error=0.2).effective() == (123, 0.2)
    base = Scene()
    with pytest.raises(SceneError) as err:
        base.with_overrides(['transport.quality="fast"'])
    assert err.value.parameter == "transport.quality" and "preview" in str(err.value)
    with pytest.raises(SceneError) as err:
        base.with_overrides(["transport.target_error=1.5"])
    assert err.value.parameter == "transport.target_error"


def test_pipeline_reports_the_error_and_photons_used(backend):
    from pathlib import Path

    from nebula_rt.pipeline import Pipeline

    root = Path(__file__).resolve().parents[2]
    scene = Scene.load(root / "examples/scenes/thesis-default.toml").with_overrides(
        ["grid.shape=[12,12,12]", "transport.photons=400000", "transport.target_error=0.2"])
    light = Pipeline(backend).run(scene, colour=False)
    fd = light.field_data()
    assert fd["photons"] < fd["photons_budget"] == 400_000
    assert 0 < fd["achieved_error"] <= 0.2


@pytest.mark.parametrize("estimator,medium", [("track-length", "dust"), ("collision-filter", "dust"),
                                             ("track-length", "vacuum")])
def test_device_lit_region_error_matches_the_reference(backend, estimator, medium):
    """The error the stopping rule uses, formed on the device with one float of work memory per
    voxel (float32 keys, radix-selected percentile, partial sums in a fixed order), against the
    float64 NumPy reference on the same sums: equal to float32 rounding of the weights (1e-5),
    in dust and in vacuum (no dust anywhere: the light alone decides), and the same value twice
    (deterministic)."""
    from nebula_rt.optics.bands import Band
    from nebula_rt.transport.finish import lit_region_error_on_device
    from nebula_rt.transport.estimate import LIT_FRACTION, LIT_PERCENTILE, light_from_sums, lit_region_error

    rng = np.random.default_rng(3)
    rho = (rng.random(SHAPE) ** 2).astype(np.float32) * (medium == "dust")
    bands = [Band(name="B", wavelength=450.0, extinction=1.2, albedo=0.6, g=0.4),
             Band(name="R", wavelength=650.0, extinction=0.7, albedo=0.5, g=-0.2)]
    res = trace(rho, bands, centre_star(1.0), tau=2.0, photons=40_000, seed=2, backend=backend,
                estimator=estimator, on_device=True)
    ds = res.device_sums
    # the float64 reference runs on host copies (the sums are CuPy arrays on CUDA)
    s1, m2 = (a.get() if hasattr(a, "get") else a for a in ds.host_sums())
    J, rel = light_from_sums(s1, m2, res.band_batches, estimator, res.j_scale, res.sigma_scale, rho)
    sigma = res.sigma_scale[:, None, None, None] * rho.astype(np.float64)[None]
    ref = lit_region_error(J, rel, sigma)
    params = np.stack([res.j_scale, res.sigma_scale, [b.albedo for b in bands]], axis=1)
    args = (backend, ds.sum1, ds.m2, ds.density, SHAPE, params, res.band_batches,
            estimator != "track-length", LIT_FRACTION, LIT_PERCENTILE)
    dev = lit_region_error_on_device(*args)
    assert 0.0 < ref < 1.0
    assert dev == pytest.approx(ref, rel=1e-5)
    assert lit_region_error_on_device(*args) == dev
