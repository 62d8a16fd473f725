"""The device post-processing (kernels/postprocess.cl) against the NumPy reference.

The kernel repeats the reference's double-precision operations one by one, so J, the
relative error and the emissivity must come out bit for bit; the colour bytes may differ only
where the band sum of the colour matrix rounds differently (at most one step, rarely); the
exposure comes from float32 brightness keys instead of float64 ones (relative 2^-24).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nebula_rt.transport import finish as postprocess
from nebula_rt.pipeline.stages import Pipeline, compute_light, finish_light_field
from nebula_rt.scene import Scene

ROOT = Path(__file__).resolve().parents[2]


def _scene(extra):
    return Scene.load(ROOT / "examples/scenes/thesis-default.toml").with_overrides(
        ["grid.shape=[20,16,12]", "transport.photons=20000"] + list(extra))


@pytest.mark.parametrize("estimator", ["track-length", "collision-filter"])
@pytest.mark.parametrize("extra", [[], ['colour.white_point="star"', "colour.exposure=3.0"],
                                   ['colour.white_point="E"', "colour.opacity_scale=4.0"]])
def test_device_finish_matches_reference(backend, estimator, extra):
    scene = _scene([f'transport.estimator="{estimator}"'] + extra)
    rho = Pipeline(backend).density(scene)
    r_ref, J_ref, rel_ref = compute_light(scene, rho, backend)
    ref = finish_light_field(scene, rho, r_ref, J_ref, rel_ref)
    r_dev, J_dev, rel_dev = compute_light(scene, rho, backend, on_device=True)
    assert r_dev.device_sums is not None and r_dev.J is None
    dev = finish_light_field(scene, rho, r_dev, J_dev, rel_dev)
    np.testing.assert_array_equal(dev.J, ref.J)
    np.testing.assert_array_equal(dev.rel_error, ref.rel_error)
    np.testing.assert_array_equal(dev.emissivity, ref.emissivity)
    assert dev.J.shape == ref.J.shape and dev.rgba.shape == ref.rgba.shape
    diff = np.abs(dev.rgba.astype(int) - ref.rgba.astype(int))
    assert diff.max() <= 1 and (diff > 0).mean() < 1e-3
    np.testing.assert_array_equal(dev.rgba[..., 3], ref.rgba[..., 3])
    assert dev.exposure == pytest.approx(ref.exposure, rel=1e-6)


def test_finish_without_colour(backend):
    scene = _scene([])
    rho = Pipeline(backend).density(scene)
    res, J, rel = compute_light(scene, rho, backend, on_device=True)
    light = finish_light_field(scene, rho, res, J, rel, colour=False)
    assert light.rgba is None and np.isnan(light.exposure)
    assert np.all(np.isfinite(light.J)) and light.J.dtype == np.float32


def _reference_percentile(keys: np.ndarray, q: float) -> float:
    visible = ~np.signbit(keys)
    sample = keys[visible] if visible.any() else np.abs(keys)
    pos = sample[np.isfinite(sample) & (sample > 0)].astype(np.float64)
    return float(np.percentile(pos, q)) if pos.size else None


@pytest.mark.parametrize("case", ["spread", "duplicates", "specials", "invisible", "tiny", "one"])
@pytest.mark.parametrize("q", [0.0, 50.0, 95.0, 100.0])
def test_exposure_radix_select_is_exact(backend, case, q):
    rng = np.random.default_rng(7)
    n = 5000
    if case == "spread":  # six decades, like J falling off from a star
        keys = 10.0 ** rng.uniform(-6, 0, n)
        keys[rng.random(n) < 0.3] *= -1  # invisible voxels: sign bit set
    elif case == "duplicates":
        keys = rng.choice([0.5, 0.25, 3.0], n)
    elif case == "specials":
        keys = rng.uniform(0, 1, n)
        keys[:50] = 0.0
        keys[50:60] = np.inf
        keys[60:70] = np.nan
        keys[70:80] = -0.0
    elif case == "invisible":  # nothing visible: every voxel counts
        keys = -rng.uniform(0, 2, n)
    elif case == "tiny":  # denormal float32 values share one high-bits bin
        keys = rng.integers(1, 1 << 16, n).astype(np.uint32).view(np.float32).astype(np.float64)
    else:
        keys = np.array([0.0, 0.0, 2.5, -7.0])
    keys = keys.astype(np.float32)
    expect = _reference_percentile(keys, q)
    got = postprocess.auto_exposure_on_device(backend, backend.to_device(keys), keys.size, q)
    assert expect is not None
    assert 1.0 / got == pytest.approx(expect, rel=1e-12, abs=0)


@pytest.mark.parametrize("group", [8, 64, 256])
def test_exposure_select_with_any_group_size(backend, monkeypatch, group):
    """The one-group select kernels split the 2^16 bins into chunks, one per work item of the
    group, and then walk the chunks: the same order statistics for every group size (the
    backends launch one item on OpenCL and 256 on CUDA; here the OpenCL launch is given the
    group explicitly). Keys with many ranks in one chunk and ranks at chunk edges."""
    if backend.name != "opencl":
        pytest.skip("the group size is set through pyopencl's launch (CUDA launches 256 items: tests-cuda)")
    import pyopencl as cl

    launch = backend.launch

    def grouped(prog, name, n, *args, defines=None):
        if name not in ("select_rank_bins", "select_level"):
            return launch(prog, name, n, *args, defines=defines)
        k = backend.kernel(prog, name, defines)
        local = min(group, k.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, backend.device))
        args = [a.data if hasattr(a, "data") and not isinstance(a, np.generic) else a for a in args]
        k(backend.queue, (local,), (local,), *args)

    monkeypatch.setattr(backend, "launch", grouped)
    rng = np.random.default_rng(3)
    keys = np.concatenate([10.0 ** rng.uniform(-8, 3, 3000), rng.choice([1.0, 2.0, 0.75], 2000)])
    keys[rng.random(keys.size) < 0.2] *= -1
    keys = keys.astype(np.float32)
    for q in (0.0, 7.5, 50.0, 95.0, 100.0):
        got = postprocess.percentile_of_keys(backend, backend.to_device(keys), keys.size, q)
        assert got == pytest.approx(_reference_percentile(keys, q), rel=1e-12, abs=0)


def test_exposure_without_positive_keys(backend):
    keys = np.array([0.0, -0.0, np.nan, -np.inf], np.float32)
    assert postprocess.auto_exposure_on_device(backend, backend.to_device(keys), keys.size, 95.0) == 1.0


def test_collision_filter_on_the_opencl_device(backend):
    """With pyvkfft, an OpenCL run filters the collisions on the device (VkFFT); the result is
    the host filter's up to FFT round-off (~1e-15 relative, here allowed 1e-9)."""
    from nebula_rt.transport import filtering_opencl
    from nebula_rt.pipeline.stages import _opencl_fft

    if backend.name != "opencl" or not filtering_opencl.available():
        pytest.skip("needs the OpenCL backend and pyvkfft (optional: no wheels on PyPI)")
    assert _opencl_fft(backend)
    scene = _scene(['transport.estimator="collision-filter"', "transport.filter_radius=0.15"])
    rho = Pipeline(backend).density(scene)
    r_ref, J_ref, rel_ref = compute_light(scene, rho, backend)
    ref = finish_light_field(scene, rho, r_ref, J_ref, rel_ref)
    r_dev, J_dev, rel_dev = compute_light(scene, rho, backend, on_device=True)
    assert J_dev.ndim == 1  # device layout: filtered on the device
    dev = finish_light_field(scene, rho, r_dev, J_dev, rel_dev)
    np.testing.assert_allclose(dev.J, ref.J, rtol=1e-9, atol=1e-9 * float(ref.J.max()))
    # FFT round-off is ~1e-16 of a field's largest value, so a filtered variance is meaningful
    # only where it is well above 1e-16 of the band's largest variance (the variance spans
    # twice the decades of J; the local linear fit near the faces adds terms that cancel by up
    # to ~100x): compare the errors where the variance is above 1e-10 of its maximum (so the
    # round-off is under ~1e-4 relative; an error estimate needs no more than 3 digits)
    var = (ref.J.astype(np.float64) * ref.rel_error) ** 2
    lit = var > 1e-10 * var.max(axis=(1, 2, 3), keepdims=True)
    assert lit.mean() > 0.8  # most voxels (the rest are hardly reached by light in this dense dust)
    np.testing.assert_allclose(dev.rel_error[lit], ref.rel_error[lit], rtol=1e-3)
    assert np.abs(dev.rgba.astype(int) - ref.rgba.astype(int)).max() <= 1


def test_page_locked_result_buffers_are_reused(backend, monkeypatch):
    """The OpenCL backend hands out mapped page-locked buffers on GPUs and reuses one only when
    no array refers to it; the results are the ordinary ones (forced on here for any device)."""
    if backend.name != "opencl":
        pytest.skip("OpenCL page-locked buffers")
    monkeypatch.setattr(backend, "pinned_host", True)
    monkeypatch.setattr(backend, "_pinned_pool", [], raising=False)
    scene = _scene([])
    rho = Pipeline(backend).density(scene)
    res, J, rel = compute_light(scene, rho, backend)
    ref = finish_light_field(scene, rho, res, J, rel)
    n0 = len(backend._pinned_pool)  # rho and ref hold theirs
    first = Pipeline(backend).run(scene)
    per_run = len(backend._pinned_pool) - n0  # density, J, rel_error, emissivity, rgba
    assert per_run == 5
    second = Pipeline(backend).run(scene)  # the first run's arrays are alive: new buffers
    assert len(backend._pinned_pool) == n0 + 2 * per_run
    np.testing.assert_array_equal(first.J, ref.J)
    np.testing.assert_array_equal(second.rgba, first.rgba)
    del first
    Pipeline(backend).run(scene)  # reuses the freed ones
    assert len(backend._pinned_pool) == n0 + 2 * per_run
