"""CUDA backend: the same kernel sources compiled at run time by NVRTC through CuPy.

The ``.cl`` files are written against ``nebula_common.h``, whose macros map OpenCL C onto
CUDA C (``__kernel`` -> ``extern "C" __global__``, address spaces, 64-bit atomics, math
functions), so one source serves both backends. CuPy caches compiled modules on disk
(``~/.cupy/kernel_cache``, keyed by source and options), so only the first run compiles.
"""

from __future__ import annotations

import numpy as np

from ..errors import BackendUnavailableError
from ..kernel_source import kernel_source
from .base import Backend, TransportSession, TransportSetup, transport_defines

BLOCK = 256
#: threads per block of the transport kernel: smaller blocks retire sooner after their slowest
#: packet (H100, thesis 128^3 3 x 2.1M: 11.8 ms at 128 against 14.0 ms at 256)
TRACE_BLOCK = 128


def _cupy():
    try:
        import cupy as cp
    except Exception as exc:  # ImportError, or a CUDA runtime that fails to load
        raise BackendUnavailableError(
            f"transport.backend = 'cuda': CuPy is not importable here ({exc}); install cupy-cudaXXx "
            "for your CUDA version, or use backend 'opencl'"
        ) from None
    try:
        n = cp.cuda.runtime.getDeviceCount()
    except Exception as exc:
        raise BackendUnavailableError(f"transport.backend = 'cuda': no usable CUDA driver ({exc})") from None
    if n < 1:
        raise BackendUnavailableError("transport.backend = 'cuda': no CUDA device found")
    return cp


def cuda_available() -> bool:
    """True when CuPy imports and sees at least one CUDA device."""
    try:
        _cupy()
        return True
    except BackendUnavailableError:
        return False


def _grid(n: int) -> tuple[int]:
    return ((int(n) + BLOCK - 1) // BLOCK,)


class CUDATransport(TransportSession):
    def __init__(self, backend: "CUDABackend", setup: TransportSetup, slots: int):
        cp = backend.cp
        self.backend = backend
        self.setup = setup
        self.shape = tuple(int(n) for n in setup.density.shape)
        nb = setup.n_bands
        self.nvox = int(np.prod(self.shape))
        self.ncell = nb * self.nvox
        self.slots = int(slots)
        resident = backend.resident_density(setup.density)
        self.d_density = (resident if resident is not None else
                          cp.asarray(np.ravel(np.asarray(setup.density, np.float32), order="F")))
        self.d_sigma = cp.asarray(np.asarray(setup.sigma_scale, np.float32))
        self.d_albedo = cp.asarray(np.asarray(setup.albedo, np.float32))
        self.d_g = cp.asarray(np.asarray(setup.g, np.float32))
        stars4 = np.zeros((setup.stars.shape[0], 4), np.float32)
        stars4[:, :3] = setup.stars
        self.d_stars = cp.asarray(stars4.ravel())
        self.d_cdf = cp.asarray(np.ascontiguousarray(setup.star_cdf, np.float32).ravel())
        self.d_acc = cp.zeros(self.ncell * self.slots, cp.uint64)
        self.d_sum1 = cp.zeros(self.ncell, cp.float64)
        self.d_sum2 = cp.zeros(self.ncell, cp.float64)
        self.d_tallies = cp.zeros(self.slots * nb * 4, cp.uint64)
        self.d_overflow = cp.zeros(self.slots, cp.uint32)
        self.d_seen = cp.zeros(1, cp.uint32)
        self.d_peel = cp.asarray(np.zeros(15, np.float32) if setup.peel is None else np.asarray(setup.peel, np.float32))
        self.d_image = cp.zeros(max(1, self.slots * nb * setup.peel_pixels), cp.uint64)
        defines = transport_defines(setup, backend.transport_tuning)
        self.k_trace = backend.kernel(backend.transport_program, "trace_photons", defines)
        self.k_fold = backend.kernel(backend.transport_program, "fold_batches", defines)

    def run_group(self, photon_start, count, batch_base, batch_extra, first_batch, n_slots, fresh=True):
        s = self.setup
        nx, ny, nz = self.shape
        if fresh:
            self.d_tallies.fill(0)
            self.d_overflow.fill(0)
        total = int(count) * s.n_bands
        tb = self.backend.trace_block
        self.k_trace(((self.backend.work_items(total, self.k_trace) + tb - 1) // tb,), (tb,), (
            self.d_density, self.d_sigma, self.d_albedo, self.d_g, self.d_stars, self.d_cdf,
            np.int32(nx), np.int32(ny), np.int32(nz), np.int32(s.n_bands), np.int32(s.stars.shape[0]),
            np.uint64(s.seed), np.uint64(photon_start), np.uint64(count),
            np.uint64(batch_base), np.uint64(batch_extra), np.uint64(first_batch),
            np.int32(s.max_scatterings), np.float32(s.track_scale),
            self.d_acc, self.d_tallies, self.d_overflow, self.d_peel, np.float32(s.peel_scale), self.d_image,
        ))
        tallies = self.d_tallies.get().reshape(self.slots, s.n_bands, 4)  # synchronises
        return tallies[:n_slots], self.d_overflow.get()[:n_slots].astype(bool)

    def fold(self, n_slots):
        self.k_fold(_grid(self.ncell), (BLOCK,), (self.d_acc, self.d_sum1, self.d_sum2, self.d_overflow,
                                                 np.int32(n_slots), np.uint64(self.ncell), self.d_seen))

    def overflow_seen(self):
        return bool(self.d_seen.get()[0])

    def sums_on_device(self):
        nb = self.setup.n_bands
        # device layout: band-major, x fastest; as (nb, nx, ny, nz) views
        return tuple(buf.reshape((nb,) + self.shape[::-1]).transpose(0, 3, 2, 1) for buf in (self.d_sum1, self.d_sum2))

    def sums(self):
        return tuple(a.get() for a in self.sums_on_device())

    def take_images(self, n_slots):
        s = self.setup
        if s.peel is None:
            return np.zeros((n_slots, s.n_bands, 0, 0), np.uint64)
        w, h = int(s.peel[13]), int(s.peel[14])
        out = self.d_image.get().reshape(self.slots, s.n_bands, w, h)[:n_slots]
        self.d_image.fill(0)
        return out

    def release_sums(self):
        out = (self.d_sum1, self.d_sum2, self.d_density)
        self.d_sum1 = self.d_sum2 = self.d_density = None
        return out

    def close(self):
        for name in ("d_acc", "d_sum1", "d_sum2", "d_density"):
            setattr(self, name, None)


class CUDABackend(Backend):
    """Kernels compiled with NVRTC (CuPy RawModule) for one CUDA device."""

    name = "cuda"

    def __init__(self, selector: str = "", *, compile_options: tuple = (), trace_block: int = TRACE_BLOCK,
                 transport_tuning: dict | None = None, fmad: bool = False):
        """``compile_options``: extra NVRTC options (e.g. ``("--maxrregcount=40",)``),
        ``trace_block``: threads per block of the transport kernel and ``transport_tuning``:
        overrides of the kernel's performance options (``base.TRANSPORT_TUNING``) -- tuning
        knobs measured by ``benchmarks/tune_cuda.py``; ``fmad``: let NVRTC contract a * b + c
        (off by default, see ``_compile``)."""
        cp = _cupy()
        self.fmad = bool(fmad)
        self.transport_tuning = dict(transport_tuning or {})
        self.compile_options = tuple(compile_options)
        self.trace_block = int(trace_block)
        self.cp = cp
        self.array_module = cp
        index = 0
        sel = selector.strip()
        if sel:
            if sel.isdigit():
                index = int(sel)
            else:
                names = [cp.cuda.runtime.getDeviceProperties(i)["name"].decode() for i in range(cp.cuda.runtime.getDeviceCount())]
                hits = [i for i, n in enumerate(names) if sel.lower() in n.lower()]
                if not hits:
                    raise BackendUnavailableError(f"transport.device = {selector!r}: no matching CUDA device; available: {names}")
                index = hits[0]
        self.device = cp.cuda.Device(index)
        self.device.use()
        props = cp.cuda.runtime.getDeviceProperties(index)
        self._device_name = f"CUDA: {props['name'].decode()}"
        self.sm_count = int(props["multiProcessorCount"])
        self.launch_packets = 1 << 23
        # a GPU traces a full launch in milliseconds: the first needs no shortening
        self.first_launch_packets = self.launch_packets
        free, _total = cp.cuda.runtime.memGetInfo()
        self.slot_memory_budget = int(free) // 4

    def _compile(self, name, defines):
        # --fmad=false: no contraction of a * b + c into one rounding (as OpenCL's FP_CONTRACT
        # OFF in nebula_common.h), so the float arithmetic is the same whatever the compiler
        # makes of the surrounding code: every kernel option and both GPU backends give the
        # same bits, and CUDA, NVIDIA OpenCL and PoCL differ only in their math functions
        options = ("--std=c++14", f"--fmad={'true' if self.fmad else 'false'}") + self.compile_options + tuple(f"-D{k}={v}" for k, v in sorted(defines.items()))
        return self.cp.RawModule(code=kernel_source(name), options=options)

    def _get_kernel(self, module, kernel_name):
        return module.get_function(kernel_name)

    def generate_density(self, shape, model, offset, scale, uniform_density, floor, stars, subsamples=8):
        cp = self.cp
        nx, ny, nz = (int(v) for v in shape)
        n = nx * ny * nz
        out = cp.empty(n, cp.float32)
        stars = np.asarray(stars, np.float32).reshape(-1, 4)
        d_stars = cp.asarray(stars.ravel() if len(stars) else np.zeros(4, np.float32))
        self.kernel("density.cl", "generate_density")(_grid(n), (BLOCK,), (
            out, np.int32(nx), np.int32(ny), np.int32(nz), np.int32(model),
            np.float32(offset[0]), np.float32(offset[1]), np.float32(offset[2]),
            np.float32(scale), np.float32(uniform_density), np.float32(floor),
            d_stars, np.int32(len(stars)), np.int32(subsamples)))
        # into page-locked memory (4x faster than pageable); the device copy stays for the transport
        host = self.host_empty((nz, ny, nx), np.float32)
        out.get(out=host.reshape(-1))
        return self._keep_resident(host.transpose(2, 1, 0), out)

    def transport_session(self, setup, slots):
        return CUDATransport(self, setup, slots)

    def memory_limits(self):
        cp = self.cp
        # free memory plus what CuPy's pool holds for reuse
        free, _total = cp.cuda.runtime.memGetInfo()
        avail = int(free) + int(cp.get_default_memory_pool().free_bytes())
        return avail, avail

    def work_items(self, packets: int, kernel=None) -> int:
        """One thread per packet. Blocks start roughly in packet order, so the packets in flight
        are consecutive and touch one or two batch slots: the atomics' working set stays in L2.
        (Persistent threads looping over packets were measured slower on an H100: 151k vs 288k
        packets/ms on neb128, as threads drifted apart over several slots.)"""
        return int(packets)

    # --- device arrays ------------------------------------------------------------------------
    def to_device(self, host):
        return self.cp.asarray(np.ascontiguousarray(host).reshape(-1))

    def device_zeros(self, n, dtype):
        return self.cp.zeros(int(n), dtype)

    def host_empty(self, shape, dtype):
        """Page-locked host memory (from CuPy's pinned pool): device-to-host copies run at the
        bus's full rate instead of through a staging buffer."""
        import cupyx

        return cupyx.empty_pinned(shape, dtype)

    def to_host(self, dev, out=None):
        if out is None:
            return dev.get()
        dev.get(out=out.reshape(dev.shape))
        return out

    def to_host_async(self, dev, out):
        """On a second stream, after an event on the current one: copies of the finished
        arrays overlap the exposure and colour kernels."""
        cp = self.cp
        if getattr(self, "_copy_stream", None) is None:
            self._copy_stream = cp.cuda.Stream(non_blocking=True)
        ready = cp.cuda.Event(disable_timing=True)
        ready.record()
        self._copy_stream.wait_event(ready)
        assert out.flags.c_contiguous and out.nbytes == dev.nbytes
        cp.cuda.runtime.memcpyAsync(out.ctypes.data, dev.data.ptr, dev.nbytes,
                                    cp.cuda.runtime.memcpyDeviceToHost, self._copy_stream.ptr)
        done = cp.cuda.Event(disable_timing=True)
        done.record(self._copy_stream)
        return done, dev  # the device array must live until the copy is done

    def wait_copy(self, handle):
        if handle is not None:
            handle[0].synchronize()

    def launch(self, prog_name, kernel_name, n, *args, defines=None):
        self.kernel(prog_name, kernel_name, defines)(_grid(max(int(n), 1)), (BLOCK,), args)
