"""The OpenCL/VkFFT collision filter against the host (SciPy) one, on PoCL.

``normalised_convolution_cl`` must reproduce ``filtering.normalised_convolution`` to FFT
round-off (1e-12 relative in float64) for a 1-voxel-radius and a larger kernel, one wider than
the grid and one flat along an axis, with and without variance, and keep a uniform field
uniform up to the faces (the local linear fit there).
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip(
    "pyvkfft.opencl",
    reason="pyvkfft (VkFFT) is optional and has no wheels on PyPI: scripts/setup.sh builds it "
    "from source (VKFFT_BACKEND=opencl pip install pyvkfft; needs opencl-headers, "
    "ocl-icd-opencl-dev and g++) to test the OpenCL FFT filter",
)

import pyopencl as cl  # noqa: E402
import pyopencl.array as cla  # noqa: E402

from nebula_rt.transport.filtering import cubic_kernel, normalised_convolution  # noqa: E402
from nebula_rt.transport.filtering_opencl import _plan, available, normalised_convolution_cl, padded_shape

PLATFORM = "Portable Computing Language"
RTOL = 1e-12
SHAPES = [(16, 12, 10), (33, 20, 17)]
# 0.1 box units is a 1-voxel radius on the (16, 12, 10) grid (a 3x3x3 kernel); 0.25 is larger
RADII = [0.1, 0.25]
# and the local linear fit's special cases: a kernel wider than the grid along an axis, one flat
# along an axis (1 voxel: no slope fitted there)
EXTRA = [((9, 30, 4), 0.3), ((2, 12, 12), 0.2)]
CASES = [(s, r) for s in SHAPES for r in RADII] + EXTRA


@pytest.fixture(scope="module")
def queue():
    """A queue on the first PoCL device with doubles (the project pins tests to PoCL by name)."""
    for platform in cl.get_platforms():
        if PLATFORM.lower() not in platform.name.lower():
            continue
        for dev in platform.get_devices():
            if "cl_khr_fp64" in dev.extensions:
                return cl.CommandQueue(cl.Context([dev]))
    pytest.skip(f"no OpenCL platform named {PLATFORM!r} with a double-precision device")


def _fields(shape, seed=0):
    rng = np.random.default_rng(seed)
    # strictly positive so that an element-wise relative comparison is meaningful
    field = rng.random(shape) + 0.05
    variance = rng.random(shape) * 0.3 + 0.01
    return field, variance


def _max_rel(a, b):
    return float(np.max(np.abs(a - b) / np.abs(b)))


def test_available():
    assert available()


@pytest.mark.parametrize("shape, radius", CASES)
@pytest.mark.parametrize("with_variance", [False, True])
def test_matches_host(queue, shape, radius, with_variance):
    kernel = cubic_kernel(shape, radius)
    assert kernel.size > 1
    field, variance = _fields(shape)
    var_in = variance if with_variance else None
    ref_out, ref_var = normalised_convolution(field, kernel, var_in)

    d_field = cla.to_device(queue, field)
    d_var = cla.to_device(queue, variance) if with_variance else None
    out, var = normalised_convolution_cl(queue, d_field, kernel, d_var)

    assert isinstance(out, cla.Array) and out.shape == shape and out.dtype == np.float64
    assert _max_rel(out.get(), ref_out) < RTOL
    if with_variance:
        assert isinstance(var, cla.Array) and var.shape == shape
        assert _max_rel(var.get(), ref_var) < RTOL
        np.testing.assert_array_equal(d_var.get(), variance)  # inputs are left alone
    else:
        assert var is None
    np.testing.assert_array_equal(d_field.get(), field)


@pytest.mark.parametrize("shape, radius", CASES)
def test_uniform_field_stays_uniform(queue, shape, radius):
    """The fit inside the box: no darkening at the faces."""
    kernel = cubic_kernel(shape, radius)
    out, _ = normalised_convolution_cl(queue, np.full(shape, 3.7), kernel)
    np.testing.assert_allclose(out.get(), 3.7, rtol=1e-12, atol=0.0)


def test_numpy_input_is_uploaded(queue):
    shape = SHAPES[1]
    kernel = cubic_kernel(shape, 0.25)
    field, variance = _fields(shape, seed=3)
    ref_out, ref_var = normalised_convolution(field, kernel, variance)
    out, var = normalised_convolution_cl(queue, np.asfortranarray(field), kernel, variance)
    assert _max_rel(out.get(), ref_out) < RTOL
    assert _max_rel(var.get(), ref_var) < RTOL


def test_identity_kernel_copies(queue):
    shape = SHAPES[0]
    kernel = cubic_kernel(shape, 0.01)  # under half a voxel: the identity
    assert kernel.size == 1
    field, variance = _fields(shape, seed=5)
    d_field, d_var = cla.to_device(queue, field), cla.to_device(queue, variance)
    out, var = normalised_convolution_cl(queue, d_field, kernel, d_var)
    assert out is not d_field and var is not d_var
    np.testing.assert_array_equal(out.get(), field)
    np.testing.assert_array_equal(var.get(), variance)


def test_plan_is_reused(queue):
    shape = SHAPES[0]
    kernel = cubic_kernel(shape, 0.25)
    field, _ = _fields(shape, seed=7)
    normalised_convolution_cl(queue, field, kernel)
    before = _plan.cache_info()
    normalised_convolution_cl(queue, field * 2.0, kernel)
    after = _plan.cache_info()
    assert after.misses == before.misses and after.hits > before.hits


def test_padded_shape_is_linear_and_smooth():
    for n, k in [(16, 3), (33, 17), (64, 7), (97, 31)]:
        p = padded_shape((n, n, n), (k, k, k))
        for m in p:
            assert m >= n + k // 2 and m >= k
            r = m
            for f in (2, 3, 5, 7, 11, 13):
                while r % f == 0:
                    r //= f
            assert r == 1
        assert p[-1] % 2 == 0
