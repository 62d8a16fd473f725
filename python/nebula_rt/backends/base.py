"""The interface every compute backend implements.

A backend owns one device and compiles the shared kernel sources for it. The
pipeline stages (density, transport) talk only to this interface, so the
OpenCL and CUDA paths are interchangeable.
"""

from __future__ import annotations

import abc
import weakref

import numpy as np

from .. import exact_sum
from .capacity import check_grid, region_bytes
from .session import DeviceTransport
# re-exported: what a transport run asks of a device (its module is below this one and the session)
from .transport_setup import (NVIDIA_TRACE_REGISTERS, TRANSPORT_TUNING, TransportSession,  # noqa: F401
                              TransportSetup, transport_defines)

MODEL_TURBULENCE = 0
MODEL_UNIFORM = 1


class Backend(abc.ABC):
    """A compute device with the NebulaRT kernels compiled for it."""

    name: str = "abstract"
    #: array module the post-processing runs with on this backend (numpy or cupy)
    array_module = np

    @property
    def device_name(self) -> str:
        """Human-readable platform and device name."""
        return self._device_name

    # --- compiled programs, cached per backend ------------------------------------------------
    @abc.abstractmethod
    def _compile(self, name: str, defines: dict):
        """Compile kernel file ``name`` with ``-D`` ``defines`` (the backend's program object)."""

    @abc.abstractmethod
    def _get_kernel(self, program, kernel_name: str):
        """One kernel of a compiled program."""

    def program(self, name: str, defines: dict | None = None):
        """The compiled kernel file ``name``, built once per backend and option set (the
        OpenCL and CUDA toolchains also cache binaries on disk across processes)."""
        programs = self.__dict__.setdefault("_programs", {})
        key = (name, tuple(sorted((defines or {}).items())))
        if key not in programs:
            programs[key] = self._compile(name, dict(defines or {}))
        return programs[key]

    def kernel(self, prog_name: str, kernel_name: str, defines: dict | None = None):
        """A kernel object, created once per backend (retrieving one is not free)."""
        kernels = self.__dict__.setdefault("_kernels", {})
        key = (prog_name, kernel_name, tuple(sorted((defines or {}).items())))
        if key not in kernels:
            kernels[key] = self._get_kernel(self.program(prog_name, defines), kernel_name)
        return kernels[key]

    def generate_density(
        self,
        shape: tuple[int, int, int],
        model: int,
        offset: tuple[float, float, float],
        scale: float,
        uniform_density: float,
        floor: float,
        stars: np.ndarray,
        subsamples: int = 8,
    ) -> np.ndarray:
        """Dust density on the grid (float32, (nx, ny, nz)); ``stars`` is (n, 4): x, y, z, bump
        radius. The device copy stays resident for a transport through the returned array."""
        nx, ny, nz = (int(v) for v in shape)
        n = nx * ny * nz
        out = self.device_zeros(n, np.float32)
        stars = np.asarray(stars, np.float32).reshape(-1, 4)
        d_stars = self.to_device(stars if len(stars) else np.zeros(4, np.float32))
        self.launch("density.cl", "generate_density", n, out,
                    np.int32(nx), np.int32(ny), np.int32(nz), np.int32(model),
                    np.float32(offset[0]), np.float32(offset[1]), np.float32(offset[2]),
                    np.float32(scale), np.float32(uniform_density), np.float32(floor),
                    d_stars, np.int32(len(stars)), np.int32(subsamples))
        # into the backend's result memory (page-locked where that pays); x fastest on the device
        host = self.host_empty((nz, ny, nx), np.float32)
        self.to_host(out, host.reshape(-1))
        return self._keep_resident(host.transpose(2, 1, 0), out)

    def density_cells(self, cells: np.ndarray, n: int, model: int, offset, scale: float,
                      uniform_density: float) -> np.ndarray:
        """The base density (no bumps, no floor; float32) at the centres of ``cells`` (m, 3)
        int32 (i, j, k) of the n x n x n grid of one octree level, with the arithmetic of
        :meth:`generate_density`'s voxels (``kernels/density.cl``: ``nrt_base_density``)."""
        cells = np.ascontiguousarray(cells, np.int32).reshape(-1, 3)
        m = len(cells)
        if m == 0:
            return np.zeros(0, np.float32)
        out = self.device_zeros(m, np.float32)
        self.launch("density.cl", "density_cells", m, self.to_device(cells.reshape(-1)), np.uint64(m),
                    np.int32(n), np.int32(model), np.float32(offset[0]), np.float32(offset[1]),
                    np.float32(offset[2]), np.float32(scale), np.float32(uniform_density), out)
        return self.to_host(out)

    def transport_session(self, setup: TransportSetup, slots: int, bands_per_launch: int = 0) -> TransportSession:
        """Allocate the device state for a transport run with ``slots`` batch slots of
        ``bands_per_launch`` bands each (0: all)."""
        return DeviceTransport(self, setup, slots, bands_per_launch)

    def launch_plan(self, nvox: int, n_bands: int, packets_per_batch: int, n_batches: int,
                    cell_bytes: int = 8) -> tuple[int, int]:
        """(bands per launch, batches per launch) of a transport run: enough packets to fill
        the device (``launch_packets``) and to keep launches few, with batch slots
        (``cell_bytes`` per voxel and band each: 8, or 16 for the 128-bit cells of weighted
        packets) within ``slot_memory_budget`` and at most 32 batches (the fold kernel's
        order). Where one slot of every band exceeds the budget, the bands are traced in groups
        of as many as fit it (at least one), one batch at a time."""
        nvox, n_bands = max(int(nvox), 1), max(int(n_bands), 1)
        budget, cb = int(self.slot_memory_budget), int(cell_bytes)
        # the transport by regions' stopped packets share the budget (within the memory target)
        budget = max(budget - region_bytes(self, nvox, cb == 16), 0)
        if cb * nvox * n_bands > budget:
            return int(max(1, min(n_bands, budget // (cb * nvox)))), 1
        by_work = max(1, -(-int(self.launch_packets) // max(int(packets_per_batch) * n_bands, 1)))
        by_memory = max(1, budget // (cb * nvox * n_bands))
        return n_bands, int(max(1, min(32, n_batches, by_work, by_memory)))

    def memory_limits(self) -> tuple[int, int]:
        """(device memory, largest single allocation) in bytes, for the estimates of
        :mod:`nebula_rt.transport.resources`."""
        return 1 << 62, 1 << 62

    def check_grid_fits(self, shape, n_bands: int = 0) -> None:
        """Raise a ResourceError (a SceneError) for ``grid.shape`` unless the grid fits this
        device: the density alone (``n_bands`` 0), or a transport of ``n_bands`` bands (see
        :func:`nebula_rt.backends.capacity.check_grid`). Checked before the first allocation, which
        would otherwise fail with the runtime's own error (OpenCL's INVALID_BUFFER_SIZE)."""
        check_grid(shape, self, n_bands)

    #: transport.error_estimate "auto": packets where a launch's group of batches holds fewer
    #: packets than this fraction of the packets in flight (transport.AUTO_PACKETS_BATCH_FRACTION)
    auto_packets_fraction: float = 0.25
    #: transport by regions: ((least voxels, region shift), ...) ascending; none: never
    #: (backends/session.py, region_shift_of)
    region_shifts: tuple = ()
    #: a launch's last region pass once fewer packets than this are left
    region_tail: int = 0

    #: registers per thread the analog transport kernel is built with, without and with
    #: regions, where the compiler takes a cap (NVIDIA_TRACE_REGISTERS); None: its own choice
    trace_registers: dict | None = None

    def register_cap(self, name: str, defines: dict) -> int:
        """Register cap of program ``name`` built with ``defines`` (0: none): the analog
        transport kernel's, from ``trace_registers`` or the tuning key ``max_registers``."""
        if self.trace_registers is None or name != self.transport_program or int(defines.get("NRT_BIASED", 0)):
            return 0
        regions = bool(int(defines.get("NRT_REGIONS", 0)))
        return int(self.transport_tuning.get("max_registers", self.trace_registers[regions]))

    #: kernel file of the transport (benchmarks swap in variants to compare them)
    transport_program: str = "transport.cl"
    #: packets (all bands) worth one launch, and bytes the batch slots may take beyond one
    #: slot of one band (the transport's memory stays within twice the minimum plus this)
    launch_packets: int = 1 << 21
    slot_memory_budget: int = 1 << 30
    #: packets (all bands) of a run's first launch, before its speed is measured; later
    #: launches are sized by the measured speed to last at most ``LAUNCH_SECONDS``
    first_launch_packets: int = 1 << 21
    #: overrides of ``TRANSPORT_TUNING`` for this backend (benchmarks)
    transport_tuning: dict = {}
    #: a run finished on the device makes its light as its last fold ends where
    #: it may (nebula_rt.transport.plan.light_while_folding); False: after the transport, all
    #: bands at once (the same bits; benchmarks compare the two)
    light_while_folding: bool = True
    #: grids of at least this many voxels trace their packets sorted by first direction
    #: (NRT_SORTED) unless ``transport_tuning`` says otherwise; 0: never
    sort_min_voxels: int = 0

    # --- the density stays on the device ------------------------------------------------------
    def _keep_resident(self, host: np.ndarray, dev) -> np.ndarray:
        """Remember ``dev`` as the device copy of the (now read-only) host density ``host``, so
        that a transport through the same array uses it instead of uploading it again."""
        host.flags.writeable = False  # the device copy must stay a copy of it
        self._resident_density = (weakref.ref(host), dev)
        return host

    def resident_density(self, host: np.ndarray):
        """The device copy of ``host`` made by :meth:`generate_density`, or None."""
        entry = getattr(self, "_resident_density", None)
        if entry is not None and entry[0]() is host and not host.flags.writeable:
            return entry[1]
        return None

    def density_with_columns(self, host: np.ndarray, columns: np.ndarray):
        """A device buffer of the densities ``host`` then their peel-off ``columns`` (x fastest
        each; kernels/transport.cl, NRT_PEEL_AXIS), kept for the next run with the same
        read-only arrays (a fit traces one density many times)."""
        import weakref

        entry = getattr(self, "_density_with_columns", None)
        if entry is not None and entry[0]() is host and entry[1]() is columns:
            return entry[2]
        dev = self.to_device(np.concatenate([np.ravel(np.asarray(host, np.float32), order="F"),
                                             np.ravel(np.asarray(columns, np.float32), order="F")]))
        if all(isinstance(a, np.ndarray) and not a.flags.writeable for a in (host, columns)):
            self._density_with_columns = (weakref.ref(host), weakref.ref(columns), dev)
        return dev

    def density_extremes(self, host: np.ndarray) -> tuple[float, float] | None:
        """(min, max) of ``host`` reduced on the device where it has a resident copy there and
        the backend reduces on the device (:meth:`device_extremes`), once per density: the
        density stage's finiteness check and the transport's limits share it (on the host, the
        two reductions took 0.54 s at 1024^3). None otherwise."""
        stats = self._density_stats(host)
        return None if stats is None else stats[0]

    def density_mean(self, host: np.ndarray) -> float | None:
        """The mean of ``host``, correctly rounded (:mod:`nebula_rt.exact_sum`: the same
        bits as :func:`~nebula_rt.exact_sum.mean_float32` on the host), summed on the
        device where it has a resident copy, once per density; None otherwise. (The thesis
        headline's host sum took 3 ms and, on a worker thread while the device traced, held the
        interpreter from the transport's set-up.)"""
        stats = self._density_stats(host)
        return None if stats is None else stats[1]

    def _density_stats(self, host: np.ndarray):
        """((min, max) or None, mean) of the resident density ``host``, reduced once per density
        (:meth:`device_density_stats`), or None without a resident copy."""
        dev = self.resident_density(host)
        if dev is None:
            return None
        cached = getattr(self, "_density_stats_of", None)
        if cached is not None and cached[0] is dev:
            return cached[1]
        extremes, bins = self.device_density_stats(dev, int(host.size))
        stats = (extremes, exact_sum.exact_mean(bins, host.size))
        self._density_stats_of = (dev, stats)
        return stats

    def device_density_stats(self, dev, n: int):
        """((min, max) or None, the 512 significand sums) of the first ``n`` values of a float32
        device array: :meth:`device_extremes` and :meth:`significand_sums`. A backend may read
        both back at once."""
        return self.device_extremes(dev), self.significand_sums(dev, n)

    def significand_sums(self, dev, n: int) -> np.ndarray:
        """The 512 bins (uint64) of :func:`nebula_rt.exact_sum.significand_sums` of the
        first ``n`` values of a float32 device array, summed on the device
        (``kernels/density.cl``: ``significand_sums``)."""
        out = self.device_zeros(exact_sum.SIGNIFICAND_BINS, np.uint64)
        self._sum_significands(dev, n, out)
        bins = np.empty(exact_sum.SIGNIFICAND_BINS, np.uint64)
        self.to_host(out, bins)
        return bins

    def _sum_significands(self, dev, n: int, out) -> None:
        """Add the significand sums of the first ``n`` values of ``dev`` into ``out[:512]``
        (zeroed by the caller), queued."""
        self.launch("density.cl", "significand_sums", max(1, -(-int(n) // exact_sum.SIGNIFICAND_RUN)), dev,
                    np.uint64(n), out)

    # --- device arrays, for the post-processing on the device -------------------------------
    # Device arrays are CuPy arrays (CUDA) or pyopencl.array.Array (OpenCL), always flat.
    @abc.abstractmethod
    def to_device(self, host: np.ndarray):
        """Copy a host array to a new flat device array."""

    @abc.abstractmethod
    def device_zeros(self, n: int, dtype):
        """A zeroed flat device array of ``n`` elements."""

    def host_empty(self, shape, dtype) -> np.ndarray:
        """A host array for results coming back from the device (page-locked where the
        backend benefits from it)."""
        return np.empty(shape, dtype)

    @abc.abstractmethod
    def to_host(self, dev, out: np.ndarray | None = None) -> np.ndarray:
        """Copy a device array to the host (into ``out``, contiguous, if given)."""

    def to_host_async(self, dev, out: np.ndarray):
        """Start copying a device array into the host array ``out`` (page-locked, from
        :meth:`host_empty`) once the work queued so far is done, without waiting for it; work
        queued afterwards may overlap the copy. Returns a handle for :meth:`wait_copy`.
        Default: a synchronous copy."""
        self.to_host(dev, out)
        return None

    def wait_copy(self, handle) -> None:
        """Wait until the copy started by :meth:`to_host_async` has arrived."""

    def device_extremes(self, dev) -> tuple[float, float] | None:
        """(min, max) of a float device array, reduced on the device (NaN propagates), or None
        where the host copy is as cheap to reduce (the default)."""
        return None

    def map_host(self, dev, n: int):
        """A context manager giving a writeable host array over the first ``n`` elements of
        the device array ``dev`` without a copy, where the device's memory is the host's
        (what the block writes is the device's afterwards; no kernel may run meanwhile), or
        None where it is not: the caller then copies (:meth:`to_host`, :meth:`upload`)."""
        return None

    @abc.abstractmethod
    def upload(self, dev, host: np.ndarray) -> None:
        """Copy a host array into the first ``host.size`` elements of a device array."""

    @abc.abstractmethod
    def fill_zero(self, dev) -> None:
        """Set every element of a device array to zero (queued, not waited for)."""

    @abc.abstractmethod
    def launch(self, prog_name: str, kernel_name: str, n: int, *args, defines: dict | None = None) -> None:
        """Run a kernel over ``n`` work items; device arrays and NumPy scalars as arguments.
        (The kernels exposed for tests and diagnostics run through this:
        :mod:`nebula_rt.backends.probes`.)"""

    def trace_local_size(self, prog_name: str, kernel_name: str, defines: dict | None = None) -> int:
        """Work items per group that :meth:`launch_trace` gives ``kernel_name`` (the binned
        deposits size their per-group buffers by it)."""
        raise NotImplementedError(f"{type(self).__name__} launches with the runtime's group size")

    def launch_trace(self, prog_name: str, kernel_name: str, n: int, *args, defines: dict | None = None) -> None:
        """Run the transport kernel over ``n`` packets, in the work-group size and grid the
        backend traces best with. Default: :meth:`launch`."""
        self.launch(prog_name, kernel_name, n, *args, defines=defines)
