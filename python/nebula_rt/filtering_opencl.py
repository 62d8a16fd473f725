"""Collision-filter smoothing on an OpenCL device: ``normalised_convolution`` with VkFFT.

``filtering.normalised_convolution`` runs its FFTs on the array's device: NumPy/SciPy on the
host or CuPy on a CUDA GPU. An OpenCL run had to copy every band's deposit and variance to the
host, convolve there and copy the result back. This module does the same computation on the
OpenCL device, with pyvkfft (VkFFT) for the FFTs and a few small pyopencl kernels for the
zero padding, the spectrum product and the cropping/normalisation, so nothing but the small
kernel crosses the bus.

The result matches ``filtering.normalised_convolution`` (which is
``scipy.signal.fftconvolve(..., mode="same")`` renormalised by the kernel weight inside the
box) to FFT round-off, ~1e-15 relative in float64:

    w   = conv(1, K)                       (clamped below at 1e-300)
    out = max(conv(field, K), 0) / w
    var = max(conv(variance, K*K), 0) / w^2

pyvkfft is an optional dependency (it has no wheels on PyPI; it is built from source against
an OpenCL ICD loader). ``available()`` says whether it can be imported.

Layout of the padded problem (why it is linear, not circular): the field is placed at the
origin of a zero-filled box of shape P = (px, py, pz) and the kernel is placed *centred on the
origin* with its negative offsets wrapped to the far end of the box. A circular convolution of
size P then equals the "same"-cropped linear convolution at the voxels 0..n-1 of every axis,
provided that P >= n + k//2 (and P >= k): the wrapped contributions land in the zero padding,
never in the kept window. This needs a little less padding than the full linear length
n + k - 1, and the "same" crop is a plain copy of the first n voxels of every axis (no offset).
"""

from __future__ import annotations

import functools

import numpy as np

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

# Radices VkFFT handles with its fast (non-Bluestein) code paths; a size with a larger prime
# factor falls back to Bluestein's algorithm, which is slower and loses a few bits.
_RADICES = (2, 3, 5, 7, 11, 13)


def available() -> bool:
    """Whether the OpenCL FFT path can be used: pyopencl and ``pyvkfft.opencl`` import."""
    if cl is None:
        return False
    try:
        import pyvkfft.opencl  # noqa: F401
    except Exception:  # ImportError, or OSError when the VkFFT shared library cannot load
        return False
    return True


def _is_smooth(n: int) -> bool:
    for p in _RADICES:
        while n % p == 0:
            n //= p
    return n == 1


def _next_smooth(n: int, even: bool = False) -> int:
    """The smallest m >= n whose prime factors are all <= 13 (and even, if asked)."""
    m = max(int(n), 1)
    while not (_is_smooth(m) and (not even or m % 2 == 0)):
        m += 1
    return m


def padded_shape(shape: tuple[int, int, int], kshape: tuple[int, int, int]) -> tuple[int, int, int]:
    """The FFT box for a field of ``shape`` (voxels) and a kernel of ``kshape`` (voxels).

    Each axis gets at least ``n + k//2`` voxels (enough for the "same" window to be free of
    circular wrap-around with a kernel centred on the origin, see the module docstring) and at
    least ``k`` (so the wrapped kernel does not overlap itself), rounded up to a 13-smooth size
    for VkFFT's fast radices. The last axis, the one the real-to-complex transform halves, is
    also made even: VkFFT's R2C/C2R paths are the best tested for even sizes.
    """
    out = []
    for axis, (n, k) in enumerate(zip(shape, kshape)):
        need = max(n + k // 2, k)
        out.append(_next_smooth(need, even=(axis == len(shape) - 1)))
    return tuple(out)


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

/* The indicator of the (nx, ny, nz) box inside the (px, py, pz) box: the field "ones" whose
   convolution with the kernel is the weight w. */
__kernel void pad_ones(__global double *dst, const int nx, const int ny, const int nz,
                       const int py, const int pz)
{
    const int l = get_global_id(0), j = get_global_id(1), i = get_global_id(2);
    dst[((size_t)i * py + j) * pz + l] = (i < nx && j < ny && l < nz) ? 1.0 : 0.0;
}

/* Scatter a C-ordered (kx, ky, kz) kernel into a zero-filled (px, py, pz) box with its "same"
   centre (sx, sy, sz) = ((kx-1)/2, ...) at the origin; negative offsets wrap to the far end.
   When square != 0 the kernel is squared on the way (the variance kernel K*K). */
__kernel void scatter_kernel(__global const double *k, __global double *dst,
                             const int kx, const int ky, const int kz,
                             const int sx, const int sy, const int sz,
                             const int px, const int py, const int pz, const int square)
{
    const int c = get_global_id(0), b = get_global_id(1), a = get_global_id(2);
    int i = a - sx, j = b - sy, l = c - sz;
    if (i < 0) i += px;
    if (j < 0) j += py;
    if (l < 0) l += pz;
    const double v = k[((size_t)a * ky + b) * kz + c];
    dst[((size_t)i * py + j) * pz + l] = square ? v * v : v;
}

/* In-place complex product a *= b of two half-spectra (complex128 stored as double2). */
__kernel void cmul(__global double2 *a, __global const double2 *b)
{
    const size_t g = get_global_id(0);
    const double2 x = a[g], y = b[g];
    a[g] = (double2)(x.x * y.x - x.y * y.y, x.x * y.y + x.y * y.x);
}

/* Crop the convolution of the box indicator to (nx, ny, nz): the weight w, clamped below at
   1e-300 like filtering.normalised_convolution (written so that a NaN stays a NaN, as with
   numpy.maximum). */
__kernel void crop_weight(__global const double *conv, __global double *w,
                          const int ny, const int nz, const int py, const int pz)
{
    const int l = get_global_id(0), j = get_global_id(1), i = get_global_id(2);
    const double c = conv[((size_t)i * py + j) * pz + l];
    w[((size_t)i * ny + j) * nz + l] = (c < 1e-300) ? 1e-300 : c;
}

/* Crop a convolution to (nx, ny, nz), clamp it at 0 and divide by w (square == 0, the field)
   or by w^2 (square != 0, the variance). */
__kernel void crop_normalise(__global const double *conv, __global const double *w,
                             __global double *out, const int ny, const int nz,
                             const int py, const int pz, const int square)
{
    const int l = get_global_id(0), j = get_global_id(1), i = get_global_id(2);
    const size_t o = ((size_t)i * ny + j) * nz + l;
    const double c = conv[((size_t)i * py + j) * pz + l];
    const double v = (c < 0.0) ? 0.0 : c;
    const double ww = w[o];
    out[o] = square ? v / (ww * ww) : v / ww;
}
"""

_KERNEL_NAMES = ("pad_real", "pad_ones", "scatter_kernel", "cmul", "crop_weight", "crop_normalise")


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
        prog = cl.Program(context, _SOURCE).build()
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


@functools.lru_cache(maxsize=8)
def _kernel_terms(queue, shape, pshape, kshape, kbytes):
    """Device data that depends only on the grid and the kernel, computed once per pair.

    Returns (K_hat, K2_hat, w): the half-spectra (complex128, shape ``_half(pshape)``) of the
    origin-centred kernel and of its square, and the weight w = max(conv(1, K), 1e-300) of
    shape ``shape`` (float64). The kernel is uploaded (a few kB) and padded on the device, so
    no box-sized array is transformed or copied on the host.
    """
    knl = _kernels(queue.context)
    app = _plan(queue, pshape)
    kernel = np.frombuffer(kbytes, dtype=np.float64).reshape(kshape)
    d_k = cla.to_device(queue, kernel)
    real = cla.empty(queue, pshape, np.float64)
    centre = [(k - 1) // 2 for k in kshape]  # scipy's "same" crop starts at (k-1)//2
    kgrid = (kshape[2], kshape[1], kshape[0])
    spectra = []
    for square in (0, 1):
        real.fill(0.0)
        knl.scatter_kernel(queue, kgrid, None, d_k.data, real.data,
                           *_i32(*kshape, *centre, *pshape, square))
        spec = cla.empty(queue, _half(pshape), np.complex128)
        app.fft(real, spec, queue=queue)
        spectra.append(spec)
    k_hat, k2_hat = spectra

    # w = conv(box indicator, K), cropped and clamped
    pgrid = (pshape[2], pshape[1], pshape[0])
    knl.pad_ones(queue, pgrid, None, real.data, *_i32(*shape, pshape[1], pshape[2]))
    tmp = cla.empty(queue, _half(pshape), np.complex128)
    app.fft(real, tmp, queue=queue)
    knl.cmul(queue, (tmp.size,), None, tmp.data, k_hat.data)
    app.ifft(tmp, real, queue=queue)
    w = cla.empty(queue, shape, np.float64)
    knl.crop_weight(queue, (shape[2], shape[1], shape[0]), None, real.data, w.data,
                    *_i32(shape[1], shape[2], pshape[1], pshape[2]))
    return k_hat, k2_hat, w


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
        max(conv(field, K), 0) / w, w = conv(1, K) the kernel weight inside the box.
    var : pyopencl.array.Array, float64, shape (nx, ny, nz), or None
        max(conv(variance, K*K), 0) / w^2; None when ``variance`` is None.

    Raises
    ------
    ImportError
        pyvkfft is not installed (see ``available()``).
    RuntimeError
        The device has no double precision, or VkFFT cannot make the float64 plan.

    Notes
    -----
    A kernel of one voxel is the identity: copies are returned, as on the host. The FFT box is
    ``padded_shape(field.shape, kernel.shape)``; plans, compiled helper kernels and the kernel
    spectra and weight are cached (functools.lru_cache), so repeated calls on one grid pay
    two R2C and two C2R transforms (one of each without variance). The caches keep device
    memory alive: about 3 half-spectra plus one grid per cached (grid, kernel) pair. The
    helper Kernel objects are shared, so do not call this from several host threads at once
    on the same context.
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
    pshape = padded_shape(shape, kshape)
    knl = _kernels(queue.context)
    app = _plan(queue, pshape)
    k_hat, k2_hat, w = _kernel_terms(queue, shape, pshape, kshape, kernel.tobytes())

    pgrid = (pshape[2], pshape[1], pshape[0])
    ngrid = (shape[2], shape[1], shape[0])
    real = cla.empty(queue, pshape, np.float64)
    spec = cla.empty(queue, _half(pshape), np.complex128)

    def convolve(src, k_spec, square):
        knl.pad_real(queue, pgrid, None, src.data, real.data, *_i32(*shape, pshape[1], pshape[2]))
        app.fft(real, spec, queue=queue)
        knl.cmul(queue, (spec.size,), None, spec.data, k_spec.data)
        # C2R of a multi-dimensional transform overwrites its complex input: spec is scratch
        app.ifft(spec, real, queue=queue)
        res = cla.empty(queue, shape, np.float64)
        knl.crop_normalise(queue, ngrid, None, real.data, w.data, res.data,
                           *_i32(shape[1], shape[2], pshape[1], pshape[2], square))
        return res

    out = convolve(d_field, k_hat, 0)
    var = None if d_var is None else convolve(d_var, k2_hat, 1)
    return out, var
