"""Collision-filter smoothing on an OpenCL device: ``normalised_convolution`` with VkFFT.

``filtering.normalised_convolution`` runs its FFTs on the array's device: NumPy/SciPy on the
host or CuPy on a CUDA GPU. An OpenCL run had to copy every band's deposit and variance to the
host, convolve there and copy the result back. This module does the same computation on the
OpenCL device, with pyvkfft (VkFFT) for the FFTs and a few small pyopencl kernels for the
zero padding, the spectrum products and the cropping/weighting, so nothing but the small
kernel terms and the fit's coefficient table cross the bus.

The arithmetic is that of ``filtering.normalised_convolution`` (the kernel-weighted mean in
the interior, a local linear fit within the kernel's radius of a face; see
``nebula_rt.transport.filtering``), with the same terms, coefficients and padded box, so the results
agree to FFT round-off (1e-12 relative in float64, tests/transport/test_filtering_opencl.py):

    out = max(sum_t c_t conv(field, K u^t), 0)            t over the fit's field terms
    var = max(sum_t d_t conv(variance, K^2 u^t), 0)       t over its variance terms

with c_t, d_t from ``filtering.boundary_fit`` (a small per-class table, looked up per voxel).

pyvkfft is an optional dependency (it has no wheels on PyPI; it is built from source against
an OpenCL ICD loader: scripts/setup.sh does so with ``VKFFT_BACKEND=opencl``). ``available()``
says whether it can be imported.

Layout of the padded problem (why it is linear, not circular): the field is placed at the
origin of a zero-filled box of shape P = ``filtering.padded_shape`` and each term kernel is
placed *centred on the origin* with its negative offsets wrapped to the far end of the box. A
circular convolution of size P then equals the "same"-cropped linear convolution at the voxels
0..n-1 of every axis, provided that P >= n + k//2 (and P >= k): the wrapped contributions land
in the zero padding, never in the kept window. The "same" crop is a plain copy of the first n
voxels of every axis (no offset).
"""

from __future__ import annotations

import functools

import numpy as np

from .filtering import boundary_fit, padded_shape

try:  # pyopencl is a hard dependency of the project, but keep the import error readable
    import pyopencl as cl
    import pyopencl.array as cla
except Exception as _exc:  # pragma: no cover - exercised only without pyopencl
    cl = None
    cla = None
    _CL_IMPORT_ERROR = _exc
else:
    _CL_IMPORT_ERROR = None

__all__ = ["available", "normalised_convolution_cl", "padded_shape"]

def available() -> bool:
    """Whether the OpenCL FFT path can be used: pyopencl and ``pyvkfft.opencl`` import."""
    if cl is None:
        return False
    try:
        import pyvkfft.opencl  # noqa: F401
    except Exception:  # ImportError, or OSError when the VkFFT shared library cannot load
        return False
    return True


# ---------------------------------------------------------------------------------------------
# device kernels

_SOURCE = r"""
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

/* Zero-pad a C-ordered (nx, ny, nz) field into the first corner of a (px, py, pz) box.
   One work-item per box voxel, so the box is written completely (no separate zero fill).
   Global size (pz, py, px): dimension 0 runs along the contiguous axis. */
__kernel void pad_real(__global const double *src, __global double *dst,
                       const int nx, const int ny, const int nz, const int py, const int pz)
{
    const int l = get_global_id(0), j = get_global_id(1), i = get_global_id(2);
    const size_t d = ((size_t)i * py + j) * pz + l;
    dst[d] = (i < nx && j < ny && l < nz) ? src[((size_t)i * ny + j) * nz + l] : 0.0;
}

/* Scatter a C-ordered (kx, ky, kz) kernel into a zero-filled (px, py, pz) box with its "same"
   centre (sx, sy, sz) = ((kx-1)/2, ...) at the origin; negative offsets wrap to the far end. */
__kernel void scatter_kernel(__global const double *k, __global double *dst,
                             const int kx, const int ky, const int kz,
                             const int sx, const int sy, const int sz,
                             const int px, const int py, const int pz)
{
    const int c = get_global_id(0), b = get_global_id(1), a = get_global_id(2);
    int i = a - sx, j = b - sy, l = c - sz;
    if (i < 0) i += px;
    if (j < 0) j += py;
    if (l < 0) l += pz;
    dst[((size_t)i * py + j) * pz + l] = k[((size_t)a * ky + b) * kz + c];
}

/* out = a * b for two half-spectra (complex128 stored as double2); a and b are kept. */
__kernel void cmul_to(__global const double2 *a, __global const double2 *b, __global double2 *out)
{
    const size_t g = get_global_id(0);
    const double2 x = a[g], y = b[g];
    out[g] = (double2)(x.x * y.x - x.y * y.y, x.x * y.y + x.y * y.x);
}

/* out += coef * conv on the (nx, ny, nz) crop of a (px, py, pz) convolution (out = when first):
   coef is term `term` of the fit's class table (ncx, ncy, ncz, n_terms), looked up through
   the per-axis class index of each voxel (filtering.BoundaryFit). With last != 0 the sum is
   clamped below at 0 (written so that a NaN stays a NaN, as with numpy.maximum). */
__kernel void crop_accumulate(__global const double *conv, __global const double *coef,
                              __global const int *cls_x, __global const int *cls_y,
                              __global const int *cls_z, __global double *out,
                              const int ny, const int nz, const int py, const int pz,
                              const int ncy, const int ncz, const int n_terms, const int term,
                              const int first, const int last)
{
    const int l = get_global_id(0), j = get_global_id(1), i = get_global_id(2);
    const size_t o = ((size_t)i * ny + j) * nz + l;
    const size_t cls = ((size_t)cls_x[i] * ncy + cls_y[j]) * ncz + cls_z[l];
    const double v = coef[cls * n_terms + term] * conv[((size_t)i * py + j) * pz + l];
    double s = first ? v : out[o] + v;
    if (last)
        s = (s < 0.0) ? 0.0 : s;
    out[o] = s;
}
"""

_KERNEL_NAMES = ("pad_real", "scatter_kernel", "cmul_to", "crop_accumulate")


def _require_fp64(device) -> None:
    if "cl_khr_fp64" not in device.extensions or not device.double_fp_config:
        raise RuntimeError(
            f"normalised_convolution_cl: the OpenCL device {device.name!r} has no double "
            "precision (cl_khr_fp64); the collision filter needs float64 FFTs. Use the host path "
            "filtering.normalised_convolution instead."
        )


class _Kernels:
    """The compiled helper kernels of one context (Kernel objects are made once: pyopencl
    creates a new, independent Kernel on every ``program.name`` access)."""

    def __init__(self, context):
        from ..backends.opencl import build_program

        prog = build_program(context, _SOURCE)
        for name in _KERNEL_NAMES:
            setattr(self, name, cl.Kernel(prog, name))


@functools.lru_cache(maxsize=8)
def _kernels(context) -> _Kernels:
    return _Kernels(context)


@functools.lru_cache(maxsize=16)
def _plan(queue, pshape: tuple[int, int, int]):
    """The out-of-place float64 R2C/C2R VkFFT plan for a real box of ``pshape``.

    Cached because creating a VkFFTApp generates and compiles OpenCL code (~1 s on PoCL).
    Keyed by the queue (hence context and device): VkFFT binds the plan to the device of the
    queue it was made with, and pyvkfft warns when a plan runs on another queue.
    norm=1: the inverse transform divides by the box size, like numpy.fft.irfftn.
    """
    from pyvkfft.opencl import VkFFTApp

    try:
        return VkFFTApp(pshape, np.float64, queue, ndim=3, r2c=True, inplace=False, norm=1)
    except Exception as exc:  # e.g. a driver where VkFFT cannot build double-precision code
        raise RuntimeError(
            f"normalised_convolution_cl: VkFFT could not create a float64 R2C plan of shape "
            f"{pshape} on {queue.device.name!r}: {exc}"
        ) from exc


def _half(pshape):
    return pshape[:-1] + (pshape[-1] // 2 + 1,)


def _i32(*values):
    return [np.int32(v) for v in values]


class _FitOnDevice:
    """Device data that depends only on the grid and the kernel, made once per pair: the
    half-spectra (complex128, shape ``_half(pshape)``) of the origin-centred term kernels of
    the field (K u^t) and of the variance (K^2 u^t), the coefficient tables and the per-axis
    class indices of ``filtering.boundary_fit``. The term kernels (a few kB each) are uploaded
    and padded on the device, so no box-sized array is transformed or copied on the host."""

    def __init__(self, queue, fit, kernel):
        knl = _kernels(queue.context)
        app = _plan(queue, fit.pshape)
        real = cla.empty(queue, fit.pshape, np.float64)
        kgrid = (fit.kshape[2], fit.kshape[1], fit.kshape[0])
        self.spectra = {}
        for which, terms in (("mean", fit.mean_terms), ("var", fit.var_terms)):
            spectra = []
            for exps in terms:
                d_k = cla.to_device(queue, np.ascontiguousarray(fit.term_kernel(kernel, exps, which == "var")))
                real.fill(0.0)
                knl.scatter_kernel(queue, kgrid, None, d_k.data, real.data,
                                   *_i32(*fit.kshape, *fit.centre, *fit.pshape))
                spec = cla.empty(queue, _half(fit.pshape), np.complex128)
                app.fft(real, spec, queue=queue)
                spectra.append(spec)
            self.spectra[which] = spectra
        self.coef = {"mean": cla.to_device(queue, np.ascontiguousarray(fit.mean_coef)),
                     "var": cla.to_device(queue, np.ascontiguousarray(fit.var_coef))}
        self.ncls = fit.mean_coef.shape[:3]
        self.classes = [cla.to_device(queue, c.astype(np.int32)) for c in fit.classes]


@functools.lru_cache(maxsize=4)
def _fit_on_device(queue, shape, kshape, kbytes) -> _FitOnDevice:
    kernel = np.frombuffer(kbytes, dtype=np.float64).reshape(kshape)
    return _FitOnDevice(queue, boundary_fit(shape, kernel), kernel)


def _as_device_array(queue, a, name: str):
    """A C-contiguous float64 pyopencl array of ``a`` on ``queue`` (uploads NumPy input)."""
    if isinstance(a, cla.Array):
        if a.ndim != 3:
            raise ValueError(f"{name}: expected a 3D array, got shape {a.shape}")
        if a.dtype != np.float64:
            a = a.astype(np.float64, queue=queue)  # device-side conversion
        if not a.flags.c_contiguous:
            raise ValueError(f"{name}: the pyopencl array must be C-contiguous")
        if a.context != queue.context:
            raise ValueError(f"{name}: the array lives in another OpenCL context than the queue")
        return a
    arr = np.ascontiguousarray(a, dtype=np.float64)
    if arr.ndim != 3:
        raise ValueError(f"{name}: expected a 3D array, got shape {arr.shape}")
    return cla.to_device(queue, arr)


def normalised_convolution_cl(queue, field, kernel: np.ndarray, variance=None):
    """``filtering.normalised_convolution`` on an OpenCL device (VkFFT float64 FFTs).

    Parameters
    ----------
    queue : pyopencl.CommandQueue
        The queue (and so context and device) to run on. The device needs ``cl_khr_fp64``.
        All work is enqueued on it; the returned arrays are ready once the queue is finished
        (``.get()`` waits).
    field : pyopencl.array.Array or numpy.ndarray, shape (nx, ny, nz)
        The deposited quantity per voxel (any unit; the output has the same unit). A
        pyopencl array must be C-contiguous and in the queue's context; it is converted on the
        device if not float64. A NumPy array (any layout/real dtype) is uploaded as a
        C-ordered float64 copy. The input is not modified.
    kernel : numpy.ndarray, shape (kx, ky, kz)
        The small smoothing kernel, e.g. ``filtering.cubic_kernel(shape, radius)``: sums to 1,
        odd sizes with the centre at index (k-1)//2 (any size works with scipy's "same"
        convention, but odd sizes are what the filter uses). Stays on the host; it is uploaded
        and transformed once per (queue, grid shape, kernel values) and cached.
    variance : pyopencl.array.Array or numpy.ndarray, shape (nx, ny, nz), optional
        Per-voxel variance of ``field`` (unit of ``field`` squared), voxels independent.

    Returns
    -------
    out : pyopencl.array.Array, float64, shape (nx, ny, nz)
        The smoothed field (the fit of ``filtering.normalised_convolution``), clamped at 0.
    var : pyopencl.array.Array, float64, shape (nx, ny, nz), or None
        Its variance (the fit's equivalent kernel squared, applied to ``variance``); None when
        ``variance`` is None.

    Raises
    ------
    ImportError
        pyvkfft is not installed (see ``available()``).
    RuntimeError
        The device has no double precision, or VkFFT cannot make the float64 plan.

    Notes
    -----
    A kernel of one voxel is the identity: copies are returned, as on the host. The FFT box is
    ``filtering.padded_shape(field.shape, kernel.shape)``; plans, compiled helper kernels, the
    term spectra and the coefficient tables are cached (functools.lru_cache), so repeated calls
    on one grid pay one R2C transform and one C2R per term: 1 + 4 for the field, 1 + 10 for
    the variance (fewer where the kernel is flat along an axis). The caches keep device memory
    alive: 14 half-spectra per cached (grid, kernel) pair. The helper Kernel objects are
    shared, so do not call this from several host threads at once on the same context.
    """
    if cl is None:
        raise ImportError(f"normalised_convolution_cl needs pyopencl ({_CL_IMPORT_ERROR})")
    _require_fp64(queue.device)
    if queue.properties & cl.command_queue_properties.OUT_OF_ORDER_EXEC_MODE_ENABLE:
        # the scratch buffers are reused between enqueued steps without events
        raise ValueError("normalised_convolution_cl needs an in-order command queue")
    d_field = _as_device_array(queue, field, "field")
    d_var = None if variance is None else _as_device_array(queue, variance, "variance")
    shape = tuple(int(n) for n in d_field.shape)
    if d_var is not None and tuple(d_var.shape) != shape:
        raise ValueError(f"variance shape {d_var.shape} differs from field shape {shape}")

    kernel = np.ascontiguousarray(kernel, dtype=np.float64)
    if kernel.ndim != 3:
        raise ValueError(f"kernel: expected a 3D array, got shape {kernel.shape}")
    if kernel.size == 1:  # same shortcut as the host path (the identity kernel of a tiny radius)
        out = d_field.copy(queue=queue) if d_field is field else d_field
        var = None
        if d_var is not None:
            var = d_var.copy(queue=queue) if d_var is variance else d_var
        return out, var

    import pyvkfft.opencl  # noqa: F401  (a clear ImportError here when pyvkfft is missing)

    kshape = tuple(int(k) for k in kernel.shape)
    fit = boundary_fit(shape, kernel)
    pshape = fit.pshape
    knl = _kernels(queue.context)
    app = _plan(queue, pshape)
    dev = _fit_on_device(queue, shape, kshape, kernel.tobytes())

    pgrid = (pshape[2], pshape[1], pshape[0])
    ngrid = (shape[2], shape[1], shape[0])
    real = cla.empty(queue, pshape, np.float64)
    spec = cla.empty(queue, _half(pshape), np.complex128)
    prod = cla.empty(queue, _half(pshape), np.complex128)
    cx, cy, cz = dev.classes

    def smooth(src, which):
        knl.pad_real(queue, pgrid, None, src.data, real.data, *_i32(*shape, pshape[1], pshape[2]))
        app.fft(real, spec, queue=queue)
        res = cla.empty(queue, shape, np.float64)
        spectra = dev.spectra[which]
        for t, k_spec in enumerate(spectra):
            knl.cmul_to(queue, (spec.size,), None, spec.data, k_spec.data, prod.data)
            # C2R of a multi-dimensional transform overwrites its complex input: prod is scratch
            app.ifft(prod, real, queue=queue)
            knl.crop_accumulate(queue, ngrid, None, real.data, dev.coef[which].data, cx.data, cy.data,
                                cz.data, res.data,
                                *_i32(shape[1], shape[2], pshape[1], pshape[2], dev.ncls[1], dev.ncls[2],
                                      len(spectra), t, t == 0, t == len(spectra) - 1))
        return res

    out = smooth(d_field, "mean")
    var = None if d_var is None else smooth(d_var, "var")
    return out, var
