"""OpenCL backend (pyopencl): GPUs through their vendors' drivers, CPUs through PoCL."""

from __future__ import annotations

import sys

import numpy as np

from ..errors import BackendUnavailableError
from ..kernel_source import kernel_source
from .base import Backend, TransportSession, TransportSetup, transport_defines

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


def list_devices() -> list[tuple[int, int, str, bool]]:
    """All OpenCL devices as (platform index, device index, "platform: device", is_gpu)."""
    if cl is None:
        return []
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
    raise BackendUnavailableError(
        f"transport.device = {selector!r}: no matching OpenCL device with 64-bit atomics and "
        f"doubles; available: {names}"
    )


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


class OpenCLTransport(TransportSession):
    """Device buffers of one transport run."""

    def __init__(self, backend: "OpenCLBackend", setup: TransportSetup, slots: int):
        self.backend = backend
        self.setup = setup
        ctx, q = backend.context, backend.queue
        mf = cl.mem_flags
        nx, ny, nz = setup.density.shape
        self.shape = (nx, ny, nz)
        self.nvox = nx * ny * nz
        nb = setup.n_bands
        self.ncell = nb * self.nvox
        self.slots = int(slots)

        def ro(a, dtype):
            return cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(a, dtype=dtype))

        resident = backend.resident_density(setup.density)
        self.own_density = resident is None
        self.d_density = (resident if resident is not None else
                          ro(np.asfortranarray(setup.density, dtype=np.float32).ravel(order="F"), np.float32))
        self.d_sigma = ro(setup.sigma_scale, np.float32)
        self.d_albedo = ro(setup.albedo, np.float32)
        self.d_g = ro(setup.g, np.float32)
        stars4 = np.zeros((setup.stars.shape[0], 4), np.float32)
        stars4[:, :3] = setup.stars
        self.d_stars = ro(stars4.ravel(), np.float32)
        self.d_cdf = ro(setup.star_cdf.ravel(), np.float32)
        self.d_acc = cl.Buffer(ctx, mf.READ_WRITE, size=8 * self.ncell * self.slots)
        self.d_sum1 = cl.Buffer(ctx, mf.READ_WRITE, size=8 * self.ncell)
        self.d_sum2 = cl.Buffer(ctx, mf.READ_WRITE, size=8 * self.ncell)
        cl.enqueue_fill_buffer(q, self.d_acc, np.uint64(0), 0, 8 * self.ncell * self.slots)
        for buf in (self.d_sum1, self.d_sum2):
            cl.enqueue_fill_buffer(q, buf, np.uint64(0), 0, 8 * self.ncell)
        self.h_tallies = np.zeros((self.slots, nb, 4), np.uint64)
        self.d_tallies = cl.Buffer(ctx, mf.READ_WRITE, size=self.h_tallies.nbytes)
        self.h_overflow = np.zeros(self.slots, np.uint32)
        self.d_overflow = cl.Buffer(ctx, mf.READ_WRITE, size=self.h_overflow.nbytes)
        self.d_peel = ro(np.zeros(15, np.float32) if setup.peel is None else setup.peel, np.float32)
        self.image_cells = max(1, self.slots * nb * setup.peel_pixels)
        self.d_image = cl.Buffer(ctx, mf.READ_WRITE, size=8 * self.image_cells)
        cl.enqueue_fill_buffer(q, self.d_image, np.uint64(0), 0, 8 * self.image_cells)
        self.d_seen = cl.Buffer(ctx, mf.READ_WRITE, size=4)
        cl.enqueue_fill_buffer(q, self.d_seen, np.uint32(0), 0, 4)
        defines = transport_defines(setup, backend.transport_tuning)
        self.k_trace = backend.kernel(backend.transport_program, "trace_photons", defines)
        self.k_fold = backend.kernel(backend.transport_program, "fold_batches", defines)
        most = self.k_trace.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, backend.device)
        self.local_size = (int(min(backend.TRACE_LOCAL_SIZE, most)),)

    def run_group(self, photon_start, count, batch_base, batch_extra, first_batch, n_slots, fresh=True):
        q = self.backend.queue
        s = self.setup
        nx, ny, nz = self.shape
        if fresh:
            cl.enqueue_fill_buffer(q, self.d_tallies, np.uint64(0), 0, self.h_tallies.nbytes)
            cl.enqueue_fill_buffer(q, self.d_overflow, np.uint32(0), 0, self.h_overflow.nbytes)
        total = int(count) * s.n_bands
        self.k_trace(
            q, (self.backend.work_items(total, self.local_size[0]),), self.local_size,
            self.d_density, self.d_sigma, self.d_albedo, self.d_g, self.d_stars, self.d_cdf,
            np.int32(nx), np.int32(ny), np.int32(nz), np.int32(s.n_bands), np.int32(s.stars.shape[0]),
            np.uint64(s.seed), np.uint64(photon_start), np.uint64(count),
            np.uint64(batch_base), np.uint64(batch_extra), np.uint64(first_batch),
            np.int32(s.max_scatterings), np.float32(s.track_scale),
            self.d_acc, self.d_tallies, self.d_overflow, self.d_peel, np.float32(s.peel_scale), self.d_image,
        )
        cl.enqueue_copy(q, self.h_tallies, self.d_tallies)
        cl.enqueue_copy(q, self.h_overflow, self.d_overflow)
        q.finish()
        return self.h_tallies[:n_slots].copy(), self.h_overflow[:n_slots].astype(bool)

    def fold(self, n_slots):
        self.k_fold(self.backend.queue, (self.ncell,), None, self.d_acc, self.d_sum1, self.d_sum2,
                    self.d_overflow, np.int32(n_slots), np.uint64(self.ncell), self.d_seen)

    def overflow_seen(self):
        h = np.zeros(1, np.uint32)
        cl.enqueue_copy(self.backend.queue, h, self.d_seen)
        self.backend.queue.finish()
        return bool(h[0])

    def sums(self):
        q = self.backend.queue
        nb = self.setup.n_bands
        out = []
        for buf in (self.d_sum1, self.d_sum2):
            h = np.empty(self.ncell, np.float64)
            cl.enqueue_copy(q, h, buf)
            # device layout: band-major, x fastest within a band
            out.append(h.reshape((nb,) + self.shape[::-1]).transpose(0, 3, 2, 1))
        q.finish()
        return out[0], out[1]

    def take_images(self, n_slots):
        s = self.setup
        if s.peel is None:
            return np.zeros((n_slots, s.n_bands, 0, 0), np.uint64)
        w, h = int(s.peel[13]), int(s.peel[14])
        out = np.empty(self.image_cells, np.uint64)
        q = self.backend.queue
        cl.enqueue_copy(q, out, self.d_image)
        cl.enqueue_fill_buffer(q, self.d_image, np.uint64(0), 0, 8 * self.image_cells)
        q.finish()
        return out.reshape(self.slots, s.n_bands, w, h)[:n_slots]

    def release_sums(self):
        cl_array = _cl_array()
        q = self.backend.queue
        out = (cl_array.Array(q, (self.ncell,), np.float64, data=self.d_sum1),
               cl_array.Array(q, (self.ncell,), np.float64, data=self.d_sum2),
               cl_array.Array(q, (self.nvox,), np.float32, data=self.d_density))
        self.d_sum1 = self.d_sum2 = self.d_density = None
        return out

    def close(self):
        for name in ("d_acc", "d_sum1", "d_sum2", "d_density"):
            buf = getattr(self, name, None)
            if buf is not None:
                if name != "d_density" or self.own_density:  # not the backend's resident copy
                    buf.release()
                setattr(self, name, None)


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
        # On a CPU the work-group tallies cost more (barriers split PoCL's work-item loops) than
        # the contention they save: neb128 2e5 packets, 2-core PoCL, 665 vs 567 ms.
        self.transport_tuning = {} if self.is_gpu else {"NRT_GROUP_TALLY": 0}
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
        self.slot_memory_budget = mem // 4 if self.is_gpu else min(mem // 4, 1 << 30)

    def _compile(self, name, defines):
        options = [f"-D{k}={v}" for k, v in sorted(defines.items())]
        return cl.Program(self.context, kernel_source(name)).build(options=options)

    def _get_kernel(self, program, kernel_name):
        return cl.Kernel(program, kernel_name)

    # --- stages ------------------------------------------------------------------------------
    def generate_density(self, shape, model, offset, scale, uniform_density, floor, stars, subsamples=8):
        nx, ny, nz = (int(v) for v in shape)
        n = nx * ny * nz
        mf = cl.mem_flags
        out = cl.Buffer(self.context, mf.WRITE_ONLY, size=4 * n)
        stars = np.zeros((0, 4), np.float32) if len(stars) == 0 else np.asarray(stars, np.float32).reshape(-1, 4)
        d_stars = cl.Buffer(
            self.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(stars if len(stars) else np.zeros(4, np.float32))
        )
        self.kernel("density.cl", "generate_density")(
            self.queue, (n,), None, out,
            np.int32(nx), np.int32(ny), np.int32(nz), np.int32(model),
            np.float32(offset[0]), np.float32(offset[1]), np.float32(offset[2]),
            np.float32(scale), np.float32(uniform_density), np.float32(floor),
            d_stars, np.int32(len(stars)), np.int32(subsamples),
        )
        h = self.host_empty((nz, ny, nx), np.float32)
        cl.enqueue_copy(self.queue, h, out)
        self.queue.finish()
        # the device copy stays for the transport
        return self._keep_resident(h.transpose(2, 1, 0), out)

    def transport_session(self, setup, slots):
        return OpenCLTransport(self, setup, slots)

    def memory_limits(self):
        return int(self.device.global_mem_size), int(self.device.max_mem_alloc_size)

    def check_build(self) -> None:
        """Build the density kernel (it includes the shared header the others use) and run it
        on a 2^3 grid, so that a device that cannot build the kernels is refused before a run
        starts, not in the middle of it."""
        try:
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
        cl.enqueue_copy(self.queue, out.reshape(-1), dev.data)
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
        return cl.enqueue_copy(self._copy_queue, out.reshape(-1), dev.data, is_blocking=False,
                               wait_for=[ready]), dev

    def wait_copy(self, handle):
        if handle is not None:
            handle[0].wait()

    def launch(self, prog_name, kernel_name, n, *args, defines=None):
        array_type = _cl_array().Array
        args = [a.data if isinstance(a, array_type) else a for a in args]
        self.kernel(prog_name, kernel_name, defines)(self.queue, (max(int(n), 1),), None, *args)
