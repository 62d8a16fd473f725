"""What a transport run asks of a device: its inputs (:class:`TransportSetup`), the kernel's
compile-time options (:func:`transport_defines`), and the interface of its device-resident
state (:class:`TransportSession`; one implementation for every backend:
:class:`~.session.DeviceTransport`).

Below both the backends (:mod:`.base`) and the session (:mod:`.session`), so that neither
imports the other's module to name these.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np

from .kernel_params import CONSTANT

@dataclass(frozen=True)
class TransportSetup:
    """Everything the transport kernel needs besides the photon range.

    Attributes
    ----------
    density : ndarray, float32, shape (nx, ny, nz)
        Dust density per voxel (index [i, j, k] = x, y, z); on a tree (``tree``), per leaf,
        shape (n_leaves, 1, 1): the cells of a run are then the leaves.
    sigma_scale, albedo, g : ndarray, float32, shape (n_bands,)
        Extinction per box unit at density 1 (tau * k_b), albedo, HG asymmetry per band.
    stars : ndarray, float32, shape (n_stars, 3)
        Star positions in box units.
    star_cdf : ndarray, float32, shape (n_bands, n_stars)
        Cumulative probability of choosing each star, per band.
    estimator : str
        ``"track-length"`` or ``"collision-filter"``; ``"none"``: no J (a peel-off image
        alone, ``trace(light_field=False)``), no batch slots.
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
        (:mod:`nebula_rt.transport.importance`).
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
    #: peel-off towards an observer along a grid axis: (axis, up) and each voxel's density
    #: column beyond it along that axis (float32, the density's shape), which the kernel reads
    #: after the densities instead of marching to the edge (kernels/transport.cl, NRT_PEEL_AXIS)
    peel_axis: object = None
    peel_columns: object = None
    #: no fixed-point cell can wrap past 2^64 within one launch (see ``trace``), so deposits may
    #: be added without reading the old value back and checked by the fold instead
    unchecked_adds: bool = False
    biased: bool = False
    collision_scale: float = 1.0
    window: object = None
    window_rate: object = None
    #: ``biased``: what the windows follow, "stars" or "observer" (nebula_rt.transport.importance)
    importance: str = "stars"
    #: the error estimate by packets (``transport.error_estimate``): the kernel also adds the
    #: square of each packet's deposits per voxel visit, in units of 2^sq_shift square track
    #: units, to a second slot; one batch, all bands in one launch
    packet_sq: bool = False
    sq_shift: int = 0
    #: ``biased`` with the track-length estimator: J's heavy-tail histograms per class of depth
    #: from the stars (nebula_rt.transport.tails), and the classes' edges per band in the depth map's
    #: units (float32, (n_bands, tail_classes - 1)), uploaded after the map
    tail_classes: int = 0
    tail_edges: object = None
    #: an adaptive density (nebula_rt.density.octree.Octree): the packets walk its leaves
    #: (kernels/tree.cl, NRT_TREE), whose densities ``density`` holds; ``tree_buffer`` is its
    #: device layout (float32: the leaves' densities, then the nodes' child entries as int32
    #: bits; nebula_rt.transport.tree.device_layout)
    tree: object = None
    tree_buffer: object = None
    #: polarized packets (kernels/polarization.cl, NRT_POLAR: 1 Rayleigh, 2 White's
    #: approximation, 3 Mie; 0 intensity alone) and their parameters (flat float32: 4 per band,
    #: then Mie's tables; nebula_rt.optics.polarization.Polarization.kernel_params), uploaded
    #: after the bands' optics
    polar: int = 0
    polar_params: object = None

    @property
    def light_field(self) -> bool:
        """Whether the run estimates J (deposits into batch slots, folded into statistics)."""
        return self.estimator != "none"

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
        """Heavy-tail histograms per band (nebula_rt.transport.tails): the image's, then J's depth classes."""
        return (self.peel is not None) + self.tail_classes

    @property
    def tally_words(self) -> int:
        """64-bit words of one (batch, band) tally block: the energy tallies, then the heavy-tail
        histograms' counts."""
        return self.tally_base + self.tail_hists * CONSTANT["NRT_TAIL_BINS"]

    @property
    def stokes_images(self) -> int:
        """Peel-off images per band: I, or (polarized) I, Q and U, and V where the matrix gives
        it (Mie) (kernels/transport.cl, NRT_STOKES_IMAGES)."""
        from ..optics.polarization import KERNEL_KIND, Polarization

        kind = next(k for k, v in KERNEL_KIND.items() if v == self.polar)
        return 1 + Polarization(kind).stokes

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

#: Tuning keys that are sizes, not switches: 0 is a value to pass (NRT_HOT_HALF 0: a star block
#: of its voxel alone), not "off".
SIZE_TUNING = frozenset({"NRT_HOT_HALF"})

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
    defines = {"track-length": {"NRT_TRACK_LENGTH": 1}, "collision-filter": {"NRT_COLLISION": 1},
               "none": {}}[setup.estimator]
    defines = dict(defines)
    if setup.acc_limit_bits != 63:
        defines["NRT_ACC_LIMIT_BITS"] = int(setup.acc_limit_bits)
    if setup.tree is not None:
        defines["NRT_TREE"] = 1
    if setup.polar:
        defines["NRT_POLAR"] = int(setup.polar)
    if setup.peel is not None:
        defines["NRT_PEEL"] = 1
        if setup.peel_columns is not None:
            defines["NRT_PEEL_AXIS"], defines["NRT_PEEL_UP"] = int(setup.peel_axis[0]), int(setup.peel_axis[1])
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
    defines.update({k: int(v) for k, v in opts.items() if k.startswith("NRT_") and (v or k in SIZE_TUNING)})
    return defines


class TransportSession(abc.ABC):
    """Device-resident state of one transport run: batch slots and the running statistics of
    the batch totals (one implementation for every backend: :class:`~.session.DeviceTransport`).

    ``bands`` arguments are (first band, number of bands) of one launch group (default: all
    bands), when the slots hold fewer bands than the run has."""

    slots: int = 1
    bands_per_launch: int = 1
    #: a callable the next :meth:`run_group` calls once its launch is queued, before it waits for
    #: the device: host work that overlaps the trace (then reset to None)
    while_tracing = None

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
    def fold(self, n_slots: int, bands: tuple[int, int] | None = None, folded_before: int = 0,
             packets: int = 0, clear: bool = True) -> None:
        """Fold slots 0..n_slots-1 (in order, except those that overflowed) of the group's
        bands into their running sums and centred sums of squares (``folded_before`` batches
        are in them already) and clear the slots (``clear`` False: only those that overflowed,
        for the run's last fold, after which no launch traces into them; ``packets``: the
        run's packets per band, for the error estimate by packets)."""

    @abc.abstractmethod
    def overflow_seen(self) -> bool:
        """Whether a fold found a cell at or past the headroom limit (only adds that were not
        checked as they happened, ``TransportSetup.unchecked_adds``, leave this to the fold);
        from the read :meth:`read_overflow_seen` started, if it did."""

    @abc.abstractmethod
    def read_overflow_seen(self) -> None:
        """Start reading the flag of :meth:`overflow_seen` back now, after the last fold: a
        read-back issued later would wait behind the outputs' copies to the host, which share
        the bus (measured on an H100: 1.5 ms)."""

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
        bands, W, H); polarized: (n_slots, group bands, 1 + Stokes, W, H), I, then Q, U (and V)
        as 64-bit two's complement), clearing them; an empty array without a peel-off camera."""

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
