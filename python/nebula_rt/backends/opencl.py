"""OpenCL backend (pyopencl): GPUs through their vendors' drivers, CPUs through PoCL."""

from __future__ import annotations

import contextlib
import math
import os
import sys
import tempfile

import numpy as np

from ..errors import BackendUnavailableError, KernelCacheError
from .kernel_cache import (build_log_blames_files, cache_failure, folder_problem, pocl_cache_folder,
                           pyopencl_cache_folder)
from .kernel_source import kernel_source
from .base import Backend
from .transport_setup import NVIDIA_TRACE_REGISTERS

try:  # pyopencl is a hard dependency, but give a clear message if the ICD loader is broken
    import pyopencl as cl
except Exception as exc:  # pragma: no cover - depends on the machine
    cl = None
    _IMPORT_ERROR = exc
else:
    _IMPORT_ERROR = None


def _cl_array():
    """pyopencl.array (device arrays for the post-processing), imported on first use."""
    import pyopencl.array as cl_array

    return cl_array


@contextlib.contextmanager
def _mapped(queue, dev, n: int):
    """The first ``n`` elements of the pyopencl array ``dev`` mapped for reading and writing,
    unmapped (and the queue finished) when the block ends."""
    arr, ev = cl.enqueue_map_buffer(queue, dev.data, cl.map_flags.READ | cl.map_flags.WRITE, 0, (n,), dev.dtype)
    ev.wait()
    try:
        yield arr
    finally:
        arr.base.release(queue)
        queue.finish()


def list_devices() -> list[tuple[int, int, str, bool]]:
    """All OpenCL devices as (platform index, device index, "platform: device", is_gpu)."""
    if cl is None:
        return []
    if os.environ.get("POCL_CACHE_DIR") == "":
        # an empty one stands for none: PoCL 3.1 takes it for a folder and aborts the process
        # (an assertion) at its first device query
        del os.environ["POCL_CACHE_DIR"]
    out = []
    try:
        platforms = cl.get_platforms()
    except cl.Error:
        return []
    for pi, plat in enumerate(platforms):
        try:
            devices = plat.get_devices()
        except cl.Error:
            continue
        for di, dev in enumerate(devices):
            is_gpu = bool(dev.type & cl.device_type.GPU)
            out.append((pi, di, f"{plat.name.strip()}: {dev.name.strip()}", is_gpu))
    return out


#: the platform name of PoCL (OpenCL on the CPU), which keeps a kernel cache of its own
POCL_PLATFORM = "Portable Computing Language"

#: what to do about a PoCL cache folder that cannot be used
POCL_CACHE_REMEDY = "set POCL_CACHE_DIR to a writable folder"


def pocl_cache_refusal():
    """A :class:`~nebula_rt.errors.KernelCacheError` naming PoCL's cache folder where a PoCL
    platform has no devices because that folder cannot be made or written (PoCL then reports
    only "no devices"), else None."""
    if cl is None:
        return None
    try:
        platforms = cl.get_platforms()
    except cl.Error:
        return None
    for plat in platforms:
        if POCL_PLATFORM not in plat.name:
            continue
        try:
            if plat.get_devices():
                continue
        except cl.Error:
            pass
        folder = pocl_cache_folder()
        why = folder_problem(folder)
        if why is not None:
            return KernelCacheError("PoCL", folder, why, POCL_CACHE_REMEDY)
    return None


def _usable(dev) -> bool:
    """The transport kernel needs 64-bit integer atomics and doubles for the batch sums."""
    ext = dev.extensions
    return "cl_khr_int64_base_atomics" in ext and "cl_khr_fp64" in ext


def select_device(selector: str = ""):
    """Pick an OpenCL device.

    Parameters
    ----------
    selector : str
        ``""``: the first usable GPU, else the first usable device;
        ``"P:D"``: platform P, device D (indices as in ``nebula-rt devices``);
        anything else: the first usable device whose "platform: device" name contains the
        text (case-insensitive), e.g. ``"Portable Computing Language"`` or ``"NVIDIA"``.
    """
    if cl is None:
        raise BackendUnavailableError(f"transport.backend = 'opencl': pyopencl cannot be imported ({_IMPORT_ERROR})")
    found = list_devices()
    if not found:
        refusal = pocl_cache_refusal()
        if refusal is not None:
            raise refusal
        raise BackendUnavailableError(
            "transport.backend = 'opencl': no OpenCL platform found; install an OpenCL driver "
            "(for CPUs: pip install pocl-binary-distribution, or Debian's pocl-opencl-icd)"
        )
    platforms = cl.get_platforms()
    candidates = []
    sel = selector.strip()
    if sel and ":" in sel and all(part.strip().isdigit() for part in sel.split(":", 1)):
        pi, di = (int(part) for part in sel.split(":", 1))
        candidates = [(p, d, n, g) for p, d, n, g in found if p == pi and d == di]
    elif sel:
        candidates = [(p, d, n, g) for p, d, n, g in found if sel.lower() in n.lower()]
    else:
        candidates = sorted(found, key=lambda t: (not t[3], t[0], t[1]))
    names = "; ".join(f"{p}:{d} {n}" for p, d, n, _ in found)
    for p, d, name, _ in candidates:
        dev = platforms[p].get_devices()[d]
        if _usable(dev):
            return dev, name
    refusal = pocl_cache_refusal()  # PoCL's devices missing from the list for its cache
    if refusal is not None:
        raise refusal
    raise BackendUnavailableError(
        f"transport.device = {selector!r}: no matching OpenCL device with 64-bit atomics and "
        f"doubles; available: {names}"
    )


def _build_log(program, device) -> str:
    """The build log of a program whose build failed ("" where the driver keeps none)."""
    try:
        return str(program.get_build_info(device, cl.program_build_info.LOG) or "")
    except cl.Error:
        return ""


def _failed_in_cache(exc, program, device) -> bool:
    """Whether a failed build (``exc`` raised by ``program.build``) may have failed in a
    kernel cache rather than in the source."""
    if not isinstance(exc, cl.Error):
        return cache_failure(exc)
    return build_log_blames_files(_build_log(program, device) or str(exc))


def _refuse_unusable_cache(exc, pocl_folder) -> None:
    """Raise a :class:`~nebula_rt.errors.KernelCacheError` where the cache that a build failed
    in (pyopencl's, or PoCL's folder ``pocl_folder``) cannot be written; a folder that went
    away is made again (PoCL does not)."""
    if cache_failure(exc):
        compiler, folder = "pyopencl", pyopencl_cache_folder()
        remedy = "set XDG_CACHE_HOME to a writable folder, or PYOPENCL_NO_CACHE=1"
    elif pocl_folder is not None:
        compiler, folder, remedy = "PoCL", pocl_folder, POCL_CACHE_REMEDY
    else:
        return
    why = folder_problem(folder)
    if why is not None:
        raise KernelCacheError(compiler, folder, why, remedy) from None


def build_program(context, source: str, options=()):
    """Build ``source`` for the device of ``context``; returns the built pyopencl Program.

    Parameters
    ----------
    context : pyopencl.Context
    source : str
        OpenCL C source.
    options : sequence of str
        Compiler options.

    Notes
    -----
    A build can fail in a compiler's kernel cache rather than in the source: PoCL's folder
    removed while the process runs, a file in it that lost a race with another process using
    the same folder (clang: "unable to rename temporary ... No such file or directory"),
    pyopencl's binary cache failing. Such a failure is tried once more with a private cache:
    pyopencl's in a temporary folder (``cache_dir``); PoCL's folder cannot be moved once PoCL
    has initialised (:mod:`~nebula_rt.backends.kernel_cache`), so it is made again where it
    went away, and the build is given an entry of its own in it (an extra define changes
    PoCL's key of the build). A cache folder that cannot be written is reported as such
    (:class:`~nebula_rt.errors.KernelCacheError`, naming it); any other failure is the
    compiler's verdict on the source and raised as it came.
    """
    device = context.devices[0]
    # PoCL's folder as the environment gives it now (PoCL read it at the process's first
    # device query; the environment seldom changes after)
    pocl_folder = pocl_cache_folder() if POCL_PLATFORM in device.platform.name else None
    options = list(options)
    program = cl.Program(context, source)
    try:
        return program.build(options=options)
    except (cl.Error, OSError, KeyError) as exc:
        failure = exc
    if not _failed_in_cache(failure, program, device):
        raise failure
    _refuse_unusable_cache(failure, pocl_folder)
    with tempfile.TemporaryDirectory(prefix="nebula-rt-kernels-") as private:
        program = cl.Program(context, source)
        try:
            return program.build(options=[*options, f"-DNRT_PRIVATE_BUILD={os.getpid()}"], cache_dir=private)
        except (cl.Error, OSError, KeyError) as exc:
            failure = exc
    if _failed_in_cache(failure, program, device):
        _refuse_unusable_cache(failure, pocl_folder)
    raise failure


def probe_device(selector: str):
    """None if the device ``selector`` can build and run the NebulaRT kernels, else why not
    (one line)."""
    try:
        OpenCLBackend(selector).check_build()
    except BackendUnavailableError as exc:
        return str(exc)
    except Exception as exc:  # a driver that fails in its own way
        return f"{type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc).strip() else ''}"
    return None


class OpenCLBackend(Backend):
    """Kernels compiled with pyopencl for one OpenCL device."""

    name = "opencl"

    def __init__(self, selector: str = "", *, transport_tuning: dict | None = None):
        """``transport_tuning``: overrides of the transport kernel's performance options
        (``base.TRANSPORT_TUNING``), for benchmarks."""
        self._selector = selector
        self.device, self._device_name = select_device(selector)
        self.context = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.context)
        self.is_gpu = bool(self.device.type & cl.device_type.GPU)
        if self.is_gpu and "NVIDIA" in self.device.platform.name:
            self.trace_registers = NVIDIA_TRACE_REGISTERS
        # On a CPU the work-group tallies cost more (barriers split PoCL's work-item loops) than
        # the contention they save: neb128 2e5 packets, 2-core PoCL, 665 vs 567 ms.
        # on a CPU: no work-group sums; and a tree's walk finds the next leaf from the lowest
        # shared ancestor (PoCL, 2 cores: 1.3-1.55x the walk from the root grid; on an H200
        # 0.58-0.91x, so GPUs keep that: benchmarks/results/pocl-2026-12-04c/, h200-2026-12-04g/)
        self.transport_tuning = {} if self.is_gpu else {"NRT_GROUP_TALLY": 0, "NRT_TREE_ASCEND": 1}
        self.transport_tuning.update(transport_tuning or {})
        mem = int(self.device.global_mem_size)
        # a GPU launch should hold millions of packets; a CPU launch ~2M (a few seconds on PoCL,
        # so progress and cancellation stay responsive)
        self.launch_packets = (1 << 23) if self.is_gpu else (1 << 21)
        # the first launch of a run, before its speed is known, is kept short on a CPU (PoCL
        # traces about 1-3M packets/s on two cores) so that a cancel is honoured at once
        self.first_launch_packets = self.launch_packets if self.is_gpu else (1 << 16)
        # page-locked result buffers on GPUs (host_empty); on a CPU device memory is host memory
        self.pinned_host = self.is_gpu
        self.slot_memory_budget = min(mem // 4, 1 << 30)
        if self.is_gpu:
            # transport by regions on large grids, as on CUDA (backends/cuda.py); the last pass
            # of a launch once fewer packets are left than 2^17 (half an H200's resident threads)
            from .cuda import CUDABackend

            self.region_shifts = CUDABackend.region_shifts
            self.region_tail = 1 << 17
        else:
            # on a CPU the caches are MiBs: regions of 32 voxels from 128^3 on (PoCL, 2 cores,
            # neb medium, 4e5 packets, kernel packets/ms without -> with: 128^3 253 -> 316,
            # 256^3 78 -> 89; at 64^3 they cost more than they save: 957 -> 808;
            # benchmarks/results/pocl-2026-12-02b/regions-pocl.json)
            self.region_shifts = ((128**3, 5),)
            self.region_tail = 4096
            # error_estimate "auto": packets whenever by regions (transport.AUTO_PACKETS_BATCH_FRACTION)
            self.auto_packets_fraction = math.inf

    def _compile(self, name, defines):
        options = [f"-D{k}={v}" for k, v in sorted(defines.items())]
        cap = self.register_cap(name, defines)
        if cap:  # NVIDIA's OpenCL compiler takes a register cap (as NVRTC's --maxrregcount)
            options.append(f"-cl-nv-maxrregcount={cap}")
        return build_program(self.context, kernel_source(name), options)

    def _get_kernel(self, program, kernel_name):
        return cl.Kernel(program, kernel_name)

    # --- stages ------------------------------------------------------------------------------
    def memory_limits(self):
        return int(self.device.global_mem_size), int(self.device.max_mem_alloc_size)

    def check_build(self) -> None:
        """Build the density kernel (it includes the shared header the others use) and run it
        on a 2^3 grid, so that a device that cannot build the kernels is refused before a run
        starts, not in the middle of it."""
        try:
            self._compile("density.cl", {})  # a build, not the backend's cached program
            self.generate_density((2, 2, 2), 1, (0.0, 0.0, 0.0), 0.0, 1.0, 0.0, np.zeros((0, 4), np.float32))
        except cl.Error as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise BackendUnavailableError(
                f"transport.device = {self._selector!r} ({self.device_name}): this OpenCL device "
                f"cannot build the NebulaRT kernels ({first}); `nebula-rt devices` lists the usable ones"
            ) from None

    #: work-group size of the transport launches (at most what the compiled kernel allows).
    #: Fixed, not left to the runtime: for a global size with no small factor a runtime picks
    #: tiny groups (a prime count gives groups of one item), and PoCL compiles the kernel anew
    #: for every group size it picks (0.4-0.5 s each: launches sized by the measured speed have
    #: ever new global sizes). 64, 128 and 256 trace alike on PoCL (3.5-4M packets/s on a 32^3
    #: sphere); 128 is the CUDA backend's block size.
    TRACE_LOCAL_SIZE = 128

    def work_items(self, packets: int, multiple: int = 1) -> int:
        """One work item per packet (see the CUDA backend for why not persistent threads),
        padded to a multiple of the work-group size (the kernel's grid-stride loop skips the
        padding)."""
        return -(-int(packets) // multiple) * multiple

    # --- device arrays ------------------------------------------------------------------------
    def to_device(self, host):
        return _cl_array().to_device(self.queue, np.ascontiguousarray(host).reshape(-1))

    def device_zeros(self, n, dtype):
        return _cl_array().zeros(self.queue, int(n), dtype)

    #: most page-locked result buffers kept for reuse
    PINNED_POOL_MAX = 16

    def host_empty(self, shape, dtype):
        """On a GPU: host memory of a mapped ``ALLOC_HOST_PTR`` buffer (page-locked, so the
        device writes it at the bus's full rate), reused once no array refers to it any more
        (allocating page-locked memory is slow); elsewhere an ordinary array."""
        if not self.pinned_host:
            return np.empty(shape, dtype)
        nbytes = max(1, int(np.prod(shape)) * np.dtype(dtype).itemsize)
        pool = self.__dict__.setdefault("_pinned_pool", [])
        for i in range(len(pool)):
            # free: referred to only by the pool's tuple and getrefcount's own argument
            if pool[i][0] == nbytes and sys.getrefcount(pool[i][2]) <= 2:
                return pool[i][2].view(dtype).reshape(shape)
        if len(pool) >= self.PINNED_POOL_MAX:
            return np.empty(shape, dtype)
        mf = cl.mem_flags
        buf = cl.Buffer(self.context, mf.ALLOC_HOST_PTR | mf.READ_WRITE, size=nbytes)
        arr, _ = cl.enqueue_map_buffer(self.queue, buf, cl.map_flags.READ | cl.map_flags.WRITE, 0,
                                       (nbytes,), np.uint8)
        pool.append((nbytes, buf, arr))
        return arr.view(dtype).reshape(shape)

    def to_host(self, dev, out=None):
        if out is None:
            return dev.get()
        # (base_data and offset: a slice of an array as well as a whole one)
        cl.enqueue_copy(self.queue, out.reshape(-1), dev.base_data, src_offset=dev.offset)
        self.queue.finish()
        return out

    def to_host_async(self, dev, out):
        """On a second command queue, after a marker on the first: copies of the finished
        arrays overlap the exposure and colour kernels."""
        if getattr(self, "_copy_queue", None) is None:
            self._copy_queue = cl.CommandQueue(self.context)
        ready = cl.enqueue_marker(self.queue)
        self.queue.flush()
        assert out.flags.c_contiguous and out.nbytes == dev.nbytes
        return cl.enqueue_copy(self._copy_queue, out.reshape(-1), dev.base_data, src_offset=dev.offset,
                               is_blocking=False, wait_for=[ready]), dev

    def wait_copy(self, handle):
        if handle is not None:
            handle[0].wait()

    def map_host(self, dev, n):
        """On a CPU device (host-unified memory): the buffer mapped (PoCL maps it in place:
        0.1 ms for 256 MiB, where a copy into fresh host memory took 0.8 s of page faults)."""
        if self.is_gpu or not self.device.host_unified_memory:
            return None
        return _mapped(self.queue, dev, int(n))

    def upload(self, dev, host):
        cl.enqueue_copy(self.queue, dev.data, np.ascontiguousarray(host, dev.dtype).reshape(-1))

    def fill_zero(self, dev):
        cl.enqueue_fill_buffer(self.queue, dev.data, np.uint8(0), 0, dev.nbytes)

    def launch(self, prog_name, kernel_name, n, *args, defines=None):
        array_type = _cl_array().Array
        args = [a.data if isinstance(a, array_type) else a for a in args]
        self.kernel(prog_name, kernel_name, defines)(self.queue, (max(int(n), 1),), None, *args)

    def trace_local_size(self, prog_name, kernel_name, defines=None) -> int:
        """Work items per group ``launch_trace`` gives kernel ``kernel_name``."""
        k = self.kernel(prog_name, kernel_name, defines)
        most = k.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, self.device)
        return int(min(self.TRACE_LOCAL_SIZE, most))

    def launch_trace(self, prog_name, kernel_name, n, *args, defines=None):
        array_type = _cl_array().Array
        args = [a.data if isinstance(a, array_type) else a for a in args]
        k = self.kernel(prog_name, kernel_name, defines)
        local = self.trace_local_size(prog_name, kernel_name, defines)
        k(self.queue, (self.work_items(max(int(n), 1), local),), (local,), *args)
