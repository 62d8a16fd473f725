"""The interface every compute backend implements.

A backend owns one device and compiles the shared kernel sources for it. The
pipeline stages (density, transport) talk only to this interface, so the
OpenCL and CUDA paths are interchangeable.
"""

from __future__ import annotations

import abc
import weakref
from dataclasses import dataclass

import numpy as np

from ..kernel_params import CONSTANT

MODEL_TURBULENCE = 0
MODEL_UNIFORM = 1


@dataclass(frozen=True)
class TransportSetup:
    """Everything the transport kernel needs besides the photon range.

    Attributes
    ----------
    density : ndarray, float32, shape (nx, ny, nz)
        Dust density per voxel (index [i, j, k] = x, y, z).
    sigma_scale, albedo, g : ndarray, float32, shape (n_bands,)
        Extinction per box unit at density 1 (tau * k_b), albedo, HG asymmetry per band.
    stars : ndarray, float32, shape (n_stars, 3)
        Star positions in box units.
    star_cdf : ndarray, float32, shape (n_bands, n_stars)
        Cumulative probability of choosing each star, per band.
    estimator : str
        ``"track-length"`` or ``"collision-filter"``.
    max_scatterings : int
        Packets are terminated when they would scatter more often than this.
    seed : int
        Philox key word 0.
    track_scale : float
        Fixed-point units per box unit of path length.
    acc_limit_bits : int
        A fixed-point cell may hold up to 2^bits before the overflow flag is raised (63; lower
        only to test the overflow handling); with ``biased`` the 128-bit cells hold up to
        2^(64 + bits).
    biased : bool
        Weighted packets (``transport.method = "biased"``: forced scattering, composite
        biasing, Russian roulette; kernels/transport.cl): cells, images and tallies are
        128-bit, and the tallies are five weight sums (:data:`TALLY_NAMES`) in units of
        2^-96 of a packet.
    collision_scale : float
        Fixed-point units per collision of a packet of weight 1 (1 for analog packets).
    window, window_rate : ndarray float32 or None
        ``biased``: the weight windows' depth map (optical depth at cell centres of a grid
        over the box, at most the density's) and decay rate per band
        (:mod:`nebula_rt.importance`).
    """

    density: np.ndarray
    sigma_scale: np.ndarray
    albedo: np.ndarray
    g: np.ndarray
    stars: np.ndarray
    star_cdf: np.ndarray
    estimator: str
    max_scatterings: int
    seed: int
    track_scale: float
    acc_limit_bits: int = 63
    #: peel-off image: camera (15 float32: direction to the observer, u, v, centre of pixel
    #: (0, 0), pixel size, W, H), fixed-point units per 1/sr, or None for no image
    peel: object = None
    peel_scale: float = 0.0
    #: no fixed-point cell can wrap past 2^64 within one launch (see ``trace``), so deposits may
    #: be added without reading the old value back and checked by the fold instead
    unchecked_adds: bool = False
    biased: bool = False
    collision_scale: float = 1.0
    window: object = None
    window_rate: object = None
    #: ``biased``: what the windows follow, "stars" or "observer" (nebula_rt.importance)
    importance: str = "stars"
    #: the error estimate by packets (``transport.error_estimate``): the kernel also adds the
    #: square of each packet's deposits per voxel visit, in units of 2^sq_shift square track
    #: units, to a second slot; one batch, all bands in one launch
    packet_sq: bool = False
    sq_shift: int = 0
    #: ``biased`` with the track-length estimator: J's heavy-tail histograms per class of depth
    #: from the stars (nebula_rt.tails), and the classes' edges per band in the depth map's
    #: units (float32, (n_bands, tail_classes - 1)), uploaded after the map
    tail_classes: int = 0
    tail_edges: object = None

    @property
    def cell_words(self) -> int:
        """64-bit words per accumulator cell and image pixel (2: 128-bit cells when biased)."""
        return 2 if self.biased else 1

    @property
    def fold_scale(self) -> float:
        """The fold's factor from cell units to the units of the statistics (2^-32 for
        128-bit cells, kernels/transport.cl NRT_FOLD_SCALE)."""
        return 2.0**-32 if self.biased else 1.0

    @property
    def tally_base(self) -> int:
        """64-bit words of a tally block's energy tallies: 4 counts, or 5 128-bit weight sums."""
        return CONSTANT["NRT_TALLY_WEIGHTED" if self.biased else "NRT_TALLY_ANALOG"]

    @property
    def tail_hists(self) -> int:
        """Heavy-tail histograms per band (nebula_rt.tails): the image's, then J's depth classes."""
        return (self.peel is not None) + self.tail_classes

    @property
    def tally_words(self) -> int:
        """64-bit words of one (batch, band) tally block: the energy tallies, then the heavy-tail
        histograms' counts."""
        return self.tally_base + self.tail_hists * CONSTANT["NRT_TAIL_BINS"]

    @property
    def peel_pixels(self) -> int:
        """W x H of the peel-off image (0 without one)."""
        return 0 if self.peel is None else int(self.peel[13]) * int(self.peel[14])

    @property
    def n_bands(self) -> int:
        return int(self.sigma_scale.shape[0])


#: Performance options of the transport kernel (kernels/transport.cl; all give the same bits),
#: on by default where they were measured faster (benchmarks/tune_cuda.py). A backend's
#: ``transport_tuning`` overrides them (the tuning benchmark switches them one by one).
TRANSPORT_TUNING = {"NRT_ACC_RED": 1, "NRT_PREFETCH": 1, "NRT_GROUP_TALLY": 1, "NRT_SORTED": 0}

#: NVIDIA GPUs (CUDA, NVIDIA OpenCL): registers per thread of the analog transport kernel
#: without and with regions. The compiler's own choice (112; 120 by regions) allows 4 blocks
#: of 128 threads per SM (25 % occupancy), too few warps to hide the latency of the density
#: read at each voxel step; capped, more fit (CUDA on an H200, neb medium, kernel packets/ms,
#: no cap -> 96 / 80 / 72 / 64: 128^3 3e7 photons 584k -> 632k / 631k / 629k / 616k; 512^3 by
#: regions of 64, 1e8 photons 75.6k -> 85.5k / 90.3k / 93.6k / 95.1k; 56 and below lose again;
#: benchmarks/results/h200-2026-12-02d/). The weighted packets' kernel (128-bit arithmetic)
#: keeps the compiler's choice. Tuning key ``max_registers`` (0: no cap).
NVIDIA_TRACE_REGISTERS = {False: 80, True: 64}


def transport_defines(setup: TransportSetup, tuning: dict | None = None) -> dict:
    """Compile-time options of the transport kernel: only the estimator the scene asks for is
    built, the accumulator headroom (lowered only by tests) and the performance options."""
    defines = {"track-length": {"NRT_TRACK_LENGTH": 1}, "collision-filter": {"NRT_COLLISION": 1}}[setup.estimator]
    defines = dict(defines)
    if setup.acc_limit_bits != 63:
        defines["NRT_ACC_LIMIT_BITS"] = int(setup.acc_limit_bits)
    if setup.peel is not None:
        defines["NRT_PEEL"] = 1
    opts = dict(TRANSPORT_TUNING, **(tuning or {}))
    if not setup.unchecked_adds:
        opts["NRT_ACC_RED"] = 0
    if setup.biased:  # checked 128-bit adds into global memory only
        defines["NRT_BIASED"] = 1
        opts["NRT_ACC_RED"] = opts["NRT_GROUP_TALLY"] = 0
    if setup.packet_sq:
        defines["NRT_PACKET_SQ"] = 1
    if setup.tail_classes:
        defines["NRT_TAIL_CLASSES"] = int(setup.tail_classes)
    if int(np.prod(setup.density.shape)) < 2**32:
        opts.setdefault("NRT_IDX32", 1)
    defines.update({k: int(v) for k, v in opts.items() if v and k.startswith("NRT_")})
    return defines


class TransportSession(abc.ABC):
    """Device-resident state of one transport run: batch slots and the running statistics of
    the batch totals (one implementation for every backend: :class:`~.session.DeviceTransport`).

    ``bands`` arguments are (first band, number of bands) of one launch group (default: all
    bands), when the slots hold fewer bands than the run has."""

    slots: int = 1
    bands_per_launch: int = 1

    @abc.abstractmethod
    def run_group(self, photon_start: int, count: int, batch_base: int, batch_extra: int,
                  first_batch: int, n_slots: int, fresh: bool = True,
                  bands: tuple[int, int] | None = None, drain: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Trace packets ``[photon_start, photon_start + count)`` of the group's bands in one launch.

        They belong to batches ``first_batch .. first_batch + n_slots - 1`` of a plan whose
        first ``batch_extra`` batches hold ``batch_base + 1`` packets and the rest
        ``batch_base``; batch ``first_batch + k`` accumulates into slot ``k``.
        Returns the tallies (uint64, (n_slots, group bands, 4): emitted, absorbed, escaped,
        terminated) and the per-slot overflow flags (bool, (n_slots,)).

        ``fresh`` False continues the previous launch's group: tallies and overflow flags are
        not cleared, so a group may be traced in several shorter launches (packet indices are
        absolute and deposits integer: the same bits) and the results are the group's so far.
        ``drain`` False (the transport by regions; a launch that is not the group's last) may
        leave packets in flight for the next launch of the group to finish: its tallies then
        lack them until a launch with ``drain`` True.
        """

    @abc.abstractmethod
    def fold(self, n_slots: int, bands: tuple[int, int] | None = None, folded_before: int = 0) -> None:
        """Fold slots 0..n_slots-1 (in order, except those that overflowed) of the group's
        bands into their running sums and centred sums of squares (``folded_before`` batches
        are in them already) and clear the slots."""

    @abc.abstractmethod
    def overflow_seen(self) -> bool:
        """Whether a fold found a cell at or past the headroom limit (only adds that were not
        checked as they happened, ``TransportSetup.unchecked_adds``, leave this to the fold)."""

    @abc.abstractmethod
    def sums(self) -> tuple[np.ndarray, np.ndarray]:
        """Return (sum of the batch totals, centred sum of their squares sum (x - mean)^2),
        float64 host arrays (n_bands, nx, ny, nz)."""

    def sums_on_device(self):
        """The same sums as arrays of the backend's array module (CuPy arrays stay on the GPU).
        Default: the host arrays of :meth:`sums`."""
        return self.sums()

    @abc.abstractmethod
    def take_images(self, n_slots: int, bands: tuple[int, int] | None = None) -> np.ndarray:
        """The peel-off images of slots 0..n_slots-1 (uint64 fixed point, (n_slots, group
        bands, W, H)), clearing them; an empty array without a peel-off camera."""

    @abc.abstractmethod
    def release_sums(self) -> tuple:
        """Hand the sums (float64), the centred sums of squares (float32 x 2^-64) and the
        density over as flat device arrays (the sums band-major, x fastest) for the device
        post-processing, and free the batch slots; :meth:`close` then leaves them alone."""

    @abc.abstractmethod
    def device_bytes(self) -> int:
        """Device memory this run holds."""

    def close(self) -> None:  # pragma: no cover - default: nothing to release
        """Release device memory."""


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

    def transport_session(self, setup: TransportSetup, slots: int, bands_per_launch: int = 0) -> TransportSession:
        """Allocate the device state for a transport run with ``slots`` batch slots of
        ``bands_per_launch`` bands each (0: all)."""
        from .session import DeviceTransport

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
        from ..resources import region_bytes

        budget = max(budget - region_bytes(self, nvox, cb == 16), 0)
        if cb * nvox * n_bands > budget:
            return int(max(1, min(n_bands, budget // (cb * nvox)))), 1
        by_work = max(1, -(-int(self.launch_packets) // max(int(packets_per_batch) * n_bands, 1)))
        by_memory = max(1, budget // (cb * nvox * n_bands))
        return n_bands, int(max(1, min(32, n_batches, by_work, by_memory)))

    def memory_limits(self) -> tuple[int, int]:
        """(device memory, largest single allocation) in bytes, for the estimates of
        :mod:`nebula_rt.resources`."""
        return 1 << 62, 1 << 62

    def check_grid_fits(self, shape, n_bands: int = 0) -> None:
        """Raise a ResourceError (a SceneError) for ``grid.shape`` unless the grid fits this
        device: the density alone (``n_bands`` 0), or a transport of ``n_bands`` bands (see
        :func:`nebula_rt.resources.check_grid`). Checked before the first allocation, which
        would otherwise fail with the runtime's own error (OpenCL's INVALID_BUFFER_SIZE)."""
        from ..resources import check_grid

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

    def density_extremes(self, host: np.ndarray) -> tuple[float, float] | None:
        """(min, max) of ``host`` reduced on the device where it has a resident copy there and
        the backend reduces on the device (:meth:`device_extremes`), once per density: the
        density stage's finiteness check and the transport's limits share it (on the host, the
        two reductions took 0.54 s at 1024^3). None otherwise."""
        dev = self.resident_density(host)
        if dev is None:
            return None
        cached = getattr(self, "_density_extremes", None)
        if cached is not None and cached[0] is dev:
            return cached[1]
        extremes = self.device_extremes(dev)
        if extremes is not None:
            self._density_extremes = (dev, extremes)
        return extremes

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

    def launch_trace(self, prog_name: str, kernel_name: str, n: int, *args, defines: dict | None = None) -> None:
        """Run the transport kernel over ``n`` packets, in the work-group size and grid the
        backend traces best with. Default: :meth:`launch`."""
        self.launch(prog_name, kernel_name, n, *args, defines=defines)
