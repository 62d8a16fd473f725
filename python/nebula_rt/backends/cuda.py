"""CUDA backend: the same kernel sources compiled at run time by NVRTC through CuPy.

The ``.cl`` files are written against ``nebula_common.h``, whose macros map OpenCL C onto
CUDA C (``__kernel`` -> ``extern "C" __global__``, address spaces, 64-bit atomics, math
functions), so one source serves both backends. CuPy caches compiled modules on disk
(``~/.cupy/kernel_cache``, keyed by source and options), so only the first run compiles.
"""

from __future__ import annotations

import numpy as np

from .. import exact_sum
from ..errors import BackendUnavailableError
from .kernel_source import kernel_source
from .base import Backend
from .transport_setup import NVIDIA_TRACE_REGISTERS

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


def _resident_empty(shape, dtype) -> np.ndarray:
    """An ordinary array whose pages are made resident by several threads (NumPy's fill
    releases the GIL), so that a device-to-host copy into it does not fault its pages in one
    at a time."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    out = np.empty(shape, dtype)
    flat = out.reshape(-1).view(np.uint8)
    workers = max(1, min(16, os.cpu_count() or 1))
    step = -(-flat.size // workers)
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(lambda i: flat[i:i + step].fill(0), range(0, flat.size, step)))
    return out


def _grid(n: int) -> tuple[int]:
    return ((int(n) + BLOCK - 1) // BLOCK,)


class CUDABackend(Backend):
    """Kernels compiled with NVRTC (CuPy RawModule) for one CUDA device."""

    name = "cuda"
    #: packets sorted by first direction from 256^3 on (H200, neb medium, 1e8 photons, kernel
    #: photons/ms unsorted -> sorted: 128^3 493k -> 479k, 512^3 30.9k -> 32.7k, 1024^3
    #: 17.9k -> 26.0k, benchmarks/results/h200-2026-12-01-sorted/; by regions, 256^3 165k ->
    #: 187k, benchmarks/results/h200-2026-12-02e/)
    sort_min_voxels = 256**3
    #: transport by regions (kernels/transport.cl, NRT_REGIONS) from 256^3 on, regions of 64
    #: voxels a side (H200, neb medium, 1e8 photons, kernel packets/ms without -> 64 / 128:
    #: 256^3 144k -> 182k / 154k, 512^3 54.9k -> 73.4k / 74.2k, 1024^3 27.2k -> 32.3k / 33.7k,
    #: benchmarks/results/h200-2026-12-02c/; 1024^3 has 4096 regions, whose sorts counted per
    #: work group only once the local bins held 8192: 64 / 128 then gave 41.3k / 40.8k at 1e8
    #: and, with the error estimate by packets, whose squares' slot shares the L2, 27.8k /
    #: 25.0k at 1e7, benchmarks/results/h200-2026-12-02f/)
    region_shifts = ((256**3, 6),)
    #: the analog transport kernel's register cap (NVRTC --maxrregcount; a --maxrregcount among
    #: ``compile_options`` wins)
    trace_registers = NVIDIA_TRACE_REGISTERS

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
        # a launch fills the GPU 32 times over (so its slowest packets leave little idle time):
        # 2^23 on an H100 or H200 (132 SMs x 2048 threads)
        self.launch_packets = self.sm_count * int(props["maxThreadsPerMultiProcessor"]) * 32
        # a GPU traces a full launch in milliseconds: the first needs no shortening
        self.first_launch_packets = self.launch_packets
        # transport by regions (kernels/transport.cl, NRT_REGIONS) on grids past the L2 cache:
        # regions of 2^region_shift voxels a side; a launch's last pass runs its packets to the
        # end once fewer than half the GPU's resident threads are left
        self.region_tail = self.sm_count * int(props["maxThreadsPerMultiProcessor"]) // 2

    def _compile(self, name, defines):
        # --fmad=false: no contraction of a * b + c into one rounding (as OpenCL's FP_CONTRACT
        # OFF in nebula_common.h), so the float arithmetic is the same whatever the compiler
        # makes of the surrounding code: every kernel option and both GPU backends give the
        # same bits, and CUDA, NVIDIA OpenCL and PoCL differ only in their math functions
        options = ("--std=c++14", f"--fmad={'true' if self.fmad else 'false'}") + self.compile_options + tuple(f"-D{k}={v}" for k, v in sorted(defines.items()))
        cap = self.register_cap(name, defines)
        if cap and not any(o.startswith("--maxrregcount") for o in self.compile_options):
            options += (f"--maxrregcount={cap}",)
        return self.cp.RawModule(code=kernel_source(name), options=options)

    def _get_kernel(self, module, kernel_name):
        return module.get_function(kernel_name)

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

    #: largest result array placed in page-locked memory: allocating pinned memory costs
    #: about 0.5 s per GiB (cudaHostAlloc), so larger arrays go to ordinary memory made
    #: resident by several threads first (the copy then runs at the staging rate instead of
    #: faulting pages one by one)
    PINNED_MAX_BYTES = 256 << 20

    def host_empty(self, shape, dtype):
        """Page-locked host memory (from CuPy's pinned pool) for arrays up to
        ``PINNED_MAX_BYTES``: device-to-host copies run at the bus's full rate instead of
        through a staging buffer. Larger arrays: ordinary memory, touched in parallel."""
        nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
        if nbytes > self.PINNED_MAX_BYTES:
            return _resident_empty(shape, dtype)
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

    def upload(self, dev, host):
        dev[:host.size].set(np.ascontiguousarray(host, dev.dtype).reshape(-1))

    def fill_zero(self, dev):
        dev.fill(0)

    def device_extremes(self, dev):
        # two reductions on the device (NaN propagates through both): on the host they took
        # about 80 ms at 512^3 and 0.6 s at 1024^3
        cp = self.cp
        return float(cp.min(dev)), float(cp.max(dev))

    def device_density_stats(self, dev, n):
        # the extremes' bits after the significand sums: one read-back instead of three
        cp = self.cp
        nb = exact_sum.SIGNIFICAND_BINS
        out = cp.zeros(nb + 2, cp.uint64)
        self._sum_significands(dev, n, out)
        out[nb:] = cp.stack([cp.min(dev[:n]), cp.max(dev[:n])]).view(cp.uint32).astype(cp.uint64)
        host = out.get()
        low, high = host[nb:].astype(np.uint32).view(np.float32)
        return (float(low), float(high)), host[:nb]

    def launch(self, prog_name, kernel_name, n, *args, defines=None):
        self.kernel(prog_name, kernel_name, defines)(_grid(max(int(n), 1)), (BLOCK,), args)

    def trace_local_size(self, prog_name, kernel_name, defines=None) -> int:
        """Threads per block ``launch_trace`` gives kernel ``kernel_name``."""
        return int(self.trace_block)

    def launch_trace(self, prog_name, kernel_name, n, *args, defines=None):
        tb = self.trace_block
        k = self.kernel(prog_name, kernel_name, defines)
        k(((self.work_items(max(int(n), 1), k) + tb - 1) // tb,), (tb,), args)
