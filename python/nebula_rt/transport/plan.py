"""How a run is planned: the method and error estimate chosen per run (auto), the batches
(the unit of the error estimate), the launches, and the transport plan with its tallies."""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from collections.abc import Sequence
from typing import Optional

import numpy as np

from ..optics import colour_convert
from ..optics.mie import mie_bands
from ..optics.polarization import OWN_OPTICS
from .. import limits
from ..backends import Backend, TransportSetup
from ..backends.binned import enabled as binned_deposits
from ..backends.capacity import region_bytes
from ..backends.regions import region_capacity
from ..density.octree import Octree
from . import tree as tree_run
from ..errors import NebulaWarning, SceneError, user_stacklevel
from .importance import depth_map, observer_depth_map, resolve_importance, window_rates
from .line_of_sight import density_column, peel_axis, peel_columns
from ..scene.sections import AUTO_THICK, AUTO_THIN, ERROR_ESTIMATES, METHODS as _scene_methods
from .tails import (
    DEPTH_CLASS_NAMES, class_edges)

from .estimate import TARGET_BATCHES, _max_deposit, _no_wrap, _peel_camera, _peel_scale


#: Default largest batch (packets per band): larger batches fold less often; launches last at
#: most LAUNCH_SECONDS whatever the batch. 16 batches at least, for the error estimate. On
#: grids of more than 8 MAX_AUTO_BATCH voxels a batch may hold up to a packet per
#: AUTO_VOXELS_PER_PACKET voxels: each fold reads and writes every cell (about 40 bytes), which
#: a batch of fewer packets would not pay for (512^3: 1.5 ms per fold on an H200), and by
#: regions each batch ends in a dwindling tail of passes (512^3: about 10 ms of an H200 lost
#: per batch), which a batch of more packets spreads thinner.
MAX_AUTO_BATCH = 1 << 20
AUTO_VOXELS_PER_PACKET = 2
MIN_BATCHES = 16
#: Fixed-point units per voxel edge (the smallest edge): 2^32, so one crossing of the smallest
#: voxel is 2^32 units; a cell holds 2^63 units = 2^31 full crossings per batch before the
#: headroom check trips (then the batch is re-traced in halves).
FIXED_POINT_BITS = 32

TALLY_NAMES = ("emitted", "absorbed", "escaped", "terminated")
#: Weighted packets add a fifth tally: the weight the biasing game (composite biasing, Russian
#: roulette) removed, signed (negative where it added weight), zero in expectation; then
#: emitted = absorbed + escaped + terminated + biasing, bit for bit.
BIASED_TALLY_NAMES = TALLY_NAMES + ("biasing",)

#: How packets are traced (``transport.method``, declared in the scene schema): analog (every
#: packet one unit, absorbed or scattered with probability albedo), biased (weighted packets,
#: kernels/transport.cl), or auto (:func:`resolve_method`).
METHODS = _scene_methods


def scene_optical_depth(density, tau: float, stars) -> float:
    """The scene's optical depth in the reference band: the median, over the stars and the six
    axis directions, of the optical depth from the star to the box's edge (an exact voxel
    march, :func:`nebula_rt.transport.line_of_sight.line_of_sight_tau`)."""

    depths = [float(tau) * density_column(density, s.position, d) for s in stars
              for d in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))]
    return float(np.median(depths)) if depths else 0.0


#: ``transport.error_estimate = "auto"`` takes the estimate by packets for the transport by
#: regions where a group of batches (the batches and bands one launch's slots hold) has fewer
#: packets than a fraction of the packets in flight (``Backend.auto_packets_fraction``, by
#: default this): such groups are traced one after another, each in poorly filled passes that
#: end in a dwindling tail, where packets are one full stream into one slot.
#: Measured, kernel packets/ms, batches -> packets (group / packets in flight): H200 (neb
#: medium) 512^3 1e7 photons (0.10) 55.4k -> 68.3k, 1024^3 1e7 (0.10) 15.4k -> 21.2k; 512^3 1e8
#: (1.0) 101k -> 69.6k, 1024^3 1e8 (1.0) 42.0k -> 23.3k; 256^3 1e7 (5 slots, 0.68) 160k -> 129k;
#: 256^3 1e7 three bands (0.41) packets 128k against 175k for one band by batches; the squares'
#: adds cost about 40 % of the kernel there (without them 110.7k and 37.0k at 1e7;
#: benchmarks/results/h200-2026-12-02e/). PoCL (2 cores, same medium): 128^3 2e5 (16 slots,
#: 200k) 298-331 -> 479-552, 256^3 4e5 (5 slots, 125k) 92-96 -> 119-157: on a CPU the squares
#: cost little, and one slot instead of several keeps a region's cells in the cache, so the
#: OpenCL backend on a CPU takes packets whenever it traces by regions (fraction infinite).
AUTO_PACKETS_BATCH_FRACTION = 0.25
#: The estimate by packets squares each visit of a voxel apart: a packet that scatters back
#: into a voxel it left adds the visits' covariance to the true variance but not to the
#: estimate. Measured (PoCL, pure scatterer-absorber around a point source on 20^3, 16 runs x
#: 3 sets; R = variance between runs / stated variance, batch means give 1.00 +- 0.02): R - 1
#: = 0.04 / 0.08 / 0.37 at albedo x optical depth of one voxel edge 0.1 / 0.3 / 1, about
#: 0.4 x that depth. "auto" takes packets only up to this depth (stated errors at most about
#: 0.5 % low); a run that asks for packets beyond it is warned.
AUTO_PACKETS_MAX_SCATTER_DEPTH = 0.025
#: the estimate by packets keeps at least this many fixed-point bits per voxel crossing
MIN_PACKET_TRACK_BITS = 12


def packet_scales(photons: int, max_scatterings: int, shape, estimator: str, cell_shapes=None):
    """(track bits k, square shift j) of the error estimate by packets, or None where k would
    fall below MIN_PACKET_TRACK_BITS.

    The run is one batch, its deposits added unchecked, so no cell may reach 2^63 whatever the
    packets do: a flight crosses a (convex) voxel at most once, so a packet deposits into a
    cell at most max_scatterings + 1 times, each at most a voxel diagonal of track (or one
    collision); k, the fixed-point bits per crossing of the smallest voxel (at most
    FIXED_POINT_BITS), is the largest that keeps N such packets below 2^63. A packet's
    squares per cell add up to at most the square of its total there, so the squares, in
    units of 2^j, stay below 2^63 too (with one unit of rounding per visit). ``cell_shapes``
    (finest, coarsest): cells of several sizes (a tree's leaves): k counts crossings of the
    finest, the bound takes the coarsest's diagonal."""
    n, ms = int(photons), int(max_scatterings) + 1
    fine, bound = cell_shapes if cell_shapes is not None else (shape, shape)

    def per_deposit(bits):
        return _max_deposit(estimator, float(2.0**bits * max(fine)), bound)

    k = FIXED_POINT_BITS
    while estimator == "track-length" and k >= MIN_PACKET_TRACK_BITS and n * ms * per_deposit(k) >= 2.0**63:
        k -= 1
    if k < MIN_PACKET_TRACK_BITS or n * ms * per_deposit(k) >= 2.0**63:
        return None
    x_max = ms * per_deposit(k)
    j = 0
    while n * (x_max * x_max / 2.0**j + ms) >= 2.0**62:
        j += 1
    return (k, j) if j < 64 else None  # the kernel shifts a 128-bit square by at most 63


def resolve_error_estimate(choice: str, *, biased: bool, peel, targeted: bool, time_limit: float,
                           batch_size: int, launches: "LaunchPlan", scales, nvox: int, in_flight: int,
                           scatter_depth: float = 0.0, fraction: float = AUTO_PACKETS_BATCH_FRACTION) -> bool:
    """Whether the run estimates its error by packets (``transport.error_estimate``; "auto":
    see AUTO_PACKETS_BATCH_FRACTION and AUTO_PACKETS_MAX_SCATTER_DEPTH; ``in_flight``: the
    packets the transport by regions keeps in flight, 0 without regions; ``scatter_depth``:
    the largest albedo x optical depth of a voxel edge over the bands and voxels)."""
    if choice not in ERROR_ESTIMATES:
        raise SceneError("transport.error_estimate", choice, " or ".join(f'"{m}"' for m in ERROR_ESTIMATES))
    if choice == "batches":
        return False
    why = ("weighted packets (transport.method = \"biased\")" if biased else
           "a peel-off image" if peel is not None else
           "a target error" if targeted else
           "a time limit" if time_limit > 0 else
           "a transport.batch_size" if batch_size else
           "more packets than the 64-bit cells can hold with max_scatterings" if scales is None else None)
    if choice == "packets":
        if why is not None:
            raise SceneError("transport.error_estimate", choice,
                             f'"batches" or "auto" for a run with {why}: the estimate by packets is one batch '
                             "of analog packets without a stopping rule")
        if scatter_depth > AUTO_PACKETS_MAX_SCATTER_DEPTH:
            warnings.warn(
                f"transport.error_estimate = \"packets\": the densest voxels scatter back a share of the "
                f"packets that leave them (albedo x optical depth of a voxel edge {scatter_depth:.3g}), and "
                f"the estimate by packets misses those returns: the stated errors there are about "
                f"{20 * scatter_depth:.2g} % low (docs/physics.md); \"batches\" has no such bias",
                NebulaWarning, stacklevel=user_stacklevel())
        return True
    if (why is not None or not in_flight
            or launches.slots * launches.bands_per_launch * (launches.batches.base + 1) >= fraction * in_flight
            or scatter_depth > AUTO_PACKETS_MAX_SCATTER_DEPTH):
        return False
    # within the memory target, 2 x (density + one 64-bit cell per band) + 1 GiB, also while
    # finishing (density, the two slots turned statistics, J; 1 MiB for the small buffers)
    nb = launches.n_bands
    return (4 + 20 * nb) * nvox + 2**20 <= 2 * (4 + 8 * nb) * nvox + 2**30


def resolve_method(method: str, density, tau: float, stars, peel) -> str:
    """The method a run takes: ``method`` itself unless it is ``"auto"``, which gives analog
    for a light field alone and, for a run that makes a peel-off image, biased where the
    scene's optical depth (:func:`scene_optical_depth`) is below ``AUTO_THIN`` or above
    ``AUTO_THICK`` (see those for the measurement)."""
    if method not in METHODS:
        raise SceneError("transport.method", method, " or ".join(f'"{m}"' for m in METHODS))
    if method != "auto":
        return method
    if peel is None:
        return "analog"
    t = scene_optical_depth(density, tau, stars)
    return "biased" if (t < AUTO_THIN or t > AUTO_THICK) else "analog"
#: Weighted packets: weight units per packet (the tallies of a biased run are in these), and
#: the extra resolution of their 128-bit cells over the analog 64-bit ones (2^56: a packet of
#: weight 1 crossing one voxel deposits 2^88 units, so weights down to about 2^-80 of a
#: packet keep 8 bits, and a cell holds 2^31 full crossings per batch below 2^127).
WEIGHT_UNIT = 2.0**96
WIDE_SCALE = 2.0**56


class BatchPlan(Sequence):
    """``photons`` packets split into ``m`` batches of (nearly) equal size, as a sequence of
    (start, count), computed on demand: O(1) memory whatever the photon count (2**53 packets
    are 2**33 batches).

    The first ``extra`` batches hold ``base + 1`` packets, the rest ``base``
    (``base, extra = divmod(photons, m)``), the layout the kernel's ``nrt_batch_of`` assumes.
    """

    __slots__ = ("photons", "m", "base", "extra")

    def __init__(self, photons: int, m: int):
        self.photons, self.m = int(photons), int(m)
        self.base, self.extra = divmod(self.photons, self.m)

    def __len__(self) -> int:
        return self.m

    def start(self, k: int) -> int:
        """First packet of batch ``k`` (``k == len(self)`` gives ``photons``)."""
        return k * self.base + min(k, self.extra)

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(self.m))]
        if k < 0:
            k += self.m
        if not 0 <= k < self.m:
            raise IndexError(k)
        return self.start(k), self.base + (1 if k < self.extra else 0)

    def batches_within(self, first: int, end_packet: int) -> int:
        """How many batches from ``first`` on end at or before packet ``end_packet``."""
        k = first
        # batches are at most base + 1 long: jump close, then step
        if self.base > 0:
            k = max(first, min(self.m, (end_packet - self.extra) // self.base) - 1)
        while k < self.m and self.start(k + 1) <= end_packet:
            k += 1
        while k > first and self.start(k) > end_packet:
            k -= 1
        return k - first

    def __eq__(self, other) -> bool:
        if isinstance(other, BatchPlan):
            return (self.photons, self.m) == (other.photons, other.m)
        return NotImplemented

    def __hash__(self) -> int:
        return hash((self.photons, self.m))

    def __repr__(self) -> str:
        return f"BatchPlan(photons={self.photons}, batches={self.m})"


#: Most batches an automatic plan makes (the finishing kernels count batches in an int32):
#: past MAX_AUTO_BATCH x MAX_AUTO_BATCHES packets the batches grow instead (a long batch is
#: traced in several launches anyway).
MAX_AUTO_BATCHES = 1 << 24


def auto_batch_limit(nvox: int = 0) -> int:
    """Largest automatic batch (packets per band) on a grid of ``nvox`` voxels."""
    return max(MAX_AUTO_BATCH, int(nvox) // AUTO_VOXELS_PER_PACKET)


def batch_count(photons: int, batch_size: int = 0, nvox: int = 0) -> int:
    """Number of batches :func:`batch_plan` makes."""
    photons = int(photons)
    if batch_size and batch_size > 0:
        m = max(1, -(-photons // int(batch_size)))
    else:
        m = min(max(MIN_BATCHES, -(-photons // auto_batch_limit(nvox))), MAX_AUTO_BATCHES)
    return min(m, photons)


def planned_batch_size(photons: int, batch_size: int, targeted: bool, nvox: int = 0) -> int:
    """The batch size a run uses: ``batch_size`` if given, else 0 (automatic) for a fixed run
    and, for an error-targeted run, batches small enough that the error is checked (and a time
    limit honoured) early whatever the budget: TARGET_BATCHES of the budget, at most
    :func:`auto_batch_limit` packets, unless that would make more than MAX_AUTO_BATCHES batches."""
    if batch_size or not targeted:
        return int(batch_size)
    return max(min(auto_batch_limit(nvox), -(-int(photons) // TARGET_BATCHES)),
               -(-int(photons) // MAX_AUTO_BATCHES), 1)


def batch_plan(photons: int, batch_size: int = 0, nvox: int = 0) -> BatchPlan:
    """Split ``photons`` packets into batches: a :class:`BatchPlan` of (start, count).

    ``batch_size`` 0 chooses at least ``MIN_BATCHES`` batches of at most
    :func:`auto_batch_limit` packets on a grid of ``nvox`` voxels (larger past that times
    ``MAX_AUTO_BATCHES``). Counts differ by at most one, so the batch totals are comparable
    for the error estimate. The plan depends only on the arguments (never on the device):
    same scene, same bits.
    """
    photons = int(photons)
    return BatchPlan(photons, batch_count(photons, batch_size, nvox))


@dataclass(frozen=True)
class LaunchPlan:
    """How a run's packets are split and traced: the batches (which fix the result) and how
    many batches and bands one launch holds (which the device's memory and speed fix; they
    change no bit). Resolved once, by :func:`plan_launches`, for the run and for the memory
    estimate alike.

    Attributes
    ----------
    batches : BatchPlan
    batch_size : int
        The batch size asked for after :func:`planned_batch_size` (0: automatic).
    bands_per_launch, slots : int
        Bands and batches one launch traces (``slots`` batch slots of ``bands_per_launch``
        bands each).
    n_bands : int
    packet_scales : (int, int) or None
        The error estimate by packets (``transport.error_estimate``): (track bits, square
        shift) of :func:`packet_scales`; then the run is one batch of every band in one slot.
    """

    batches: BatchPlan
    batch_size: int
    bands_per_launch: int
    slots: int
    n_bands: int
    packet_scales: Optional[tuple] = None

    @property
    def band_groups(self) -> list[tuple[int, int]]:
        """(first band, bands) of each group of bands traced together."""
        k = self.bands_per_launch
        return [(b, min(k, self.n_bands - b)) for b in range(0, self.n_bands, k)]


def plan_launches(photons: int, batch_size: int, targeted: bool, shape, n_bands: int, backend,
                  cell_bytes: int = 8, *, error_estimate: str = "batches", peel=None, time_limit: float = 0.0,
                  max_scatterings: int = 1000, estimator: str = "track-length",
                  scatter_depth: float = 0.0, cell_shapes=None, stokes: int = 1) -> LaunchPlan:
    """The :class:`LaunchPlan` of a run of ``photons`` packets per band on a grid of ``shape``
    (checks the batch count against the limits first); ``error_estimate`` and the arguments
    after it as :func:`resolve_error_estimate` takes them (``cell_bytes`` 16: weighted
    packets; ``cell_shapes``: (finest, coarsest) cells per axis where the cells differ in size,
    a tree's, else ``shape`` for both; ``stokes``: images per band, 3 for polarized packets,
    whose stopped states are larger)."""
    nvox = int(np.prod([int(n) for n in shape]))
    size = planned_batch_size(photons, batch_size, targeted, nvox)
    limits.check_batch_count(batch_count(photons, size, nvox), size)
    plan = batch_plan(photons, size, nvox)
    per_launch, slots = backend.launch_plan(nvox, n_bands, plan.base + 1, len(plan), cell_bytes)
    launches = LaunchPlan(plan, size, per_launch, slots, int(n_bands))
    if estimator == "none":  # no J: the slots hold only the images, so every band and up to
        # the fold's 32 batches go in one launch, within the slot budget (a peel-off image
        # refuses the estimate by packets as any other does)
        resolve_error_estimate(error_estimate, biased=cell_bytes == 16, peel=peel, targeted=targeted,
                               time_limit=time_limit, batch_size=batch_size, launches=launches, scales=None,
                               nvox=nvox, in_flight=0)
        per_image = max(1, cell_bytes * n_bands * stokes * (0 if peel is None else int(np.prod(peel.size))))
        return LaunchPlan(plan, size, int(n_bands), int(max(1, min(32, len(plan),
                                                                   backend.slot_memory_budget // per_image))),
                          int(n_bands))
    scales = packet_scales(photons, max_scatterings, shape, estimator, cell_shapes)

    if resolve_error_estimate(error_estimate, biased=cell_bytes == 16, peel=peel, targeted=targeted,
                              time_limit=time_limit, batch_size=batch_size, launches=launches, scales=scales,
                              # (binned deposits: no regions, so "auto" takes batches)
                              nvox=nvox, in_flight=0 if binned_deposits(backend) else
                              region_capacity(backend, nvox, cell_bytes == 16, stokes > 1),
                              scatter_depth=scatter_depth,
                              fraction=getattr(backend, "auto_packets_fraction", AUTO_PACKETS_BATCH_FRACTION)):
        return LaunchPlan(BatchPlan(int(photons), 1), 0, int(n_bands), 1, int(n_bands), scales)
    return launches


def star_band_luminosities(stars, wavelengths_nm) -> np.ndarray:
    """(n_stars, n_bands) luminosity of each star in each band: its spectrum (measured,
    blackbody or flat) integrated over each band; a star's bands add up to its luminosity."""
    out = np.empty((len(stars), len(wavelengths_nm)))
    for i, s in enumerate(stars):
        source = s.spectral_source() if hasattr(s, "spectral_source") else s.temperature
        out[i] = s.luminosity * colour_convert.band_luminosity_fractions(wavelengths_nm, source)
    return out


@dataclass(frozen=True)
class TransportPlan:
    """A transport run resolved from its inputs, once (the stage :func:`plan_transport`): what
    the device is given (``setup``), how the packets are split (``launches``) and the
    per-band constants the estimate needs. :func:`run_transport` traces it.

    Attributes
    ----------
    setup : TransportSetup
    launches : LaunchPlan
    photons : int
        Packets per band asked for (the budget of an error-targeted run).
    band_names : tuple of str
    band_luminosity : ndarray (n_bands,)
    star_band_luminosity : ndarray (n_stars, n_bands)
    sigma_scale, albedo : ndarray float64 (n_bands,)
        Extinction per box unit at density 1 (tau k_b) and albedo.
    nvox_inv : float
        Voxel volume (box units^3).
    target_error, time_limit : float
    peel, peel_bins : camera and pixel groups of a peel-off image, or None
    """

    setup: TransportSetup
    launches: LaunchPlan
    photons: int
    band_names: tuple
    band_luminosity: np.ndarray
    star_band_luminosity: np.ndarray
    sigma_scale: np.ndarray
    albedo: np.ndarray
    nvox_inv: float
    target_error: float = 0.0
    time_limit: float = 0.0
    peel: object = None
    peel_bins: object = None

    @property
    def shape(self) -> tuple:
        return tuple(int(n) for n in self.setup.density.shape)

    @property
    def estimator(self) -> str:
        return self.setup.estimator

    @property
    def n_bands(self) -> int:
        return len(self.band_names)


@dataclass
class Tallies:
    """What the tracing stage (:func:`run_transport`) leaves: the exact packet counts, the
    batches and packets folded per band, the device session holding the sums (open: the
    estimate reads them, the caller closes it), the peel-off sums and timings.

    Attributes
    ----------
    session : TransportSession
    counts : ndarray int64 (n_bands, 4)
        Emitted, absorbed, escaped, terminated.
    folded, band_done : ndarray int64 (n_bands,)
        Batches and packets folded per band.
    peel_sums : _PeelSums or None
    stokes_sums : _PeelSums or None
        A polarized run's Q and U images (as 2 n_bands images: band b's Q, then its U).
    achieved_error : float
        The last lit-region error checked (error-targeted runs; NaN otherwise).
    device_bytes : int
    setup_s, kernel_s : float
    """

    session: object
    counts: np.ndarray
    folded: np.ndarray
    band_done: np.ndarray
    peel_sums: object = None
    stokes_sums: object = None
    achieved_error: float = float("nan")
    device_bytes: int = 0
    setup_s: float = 0.0
    kernel_s: float = 0.0
    reduce_s: float = 0.0  # several ranks: time spent adding the ranks' slots and tallies
    #: several ranks: how the slots were added ("nccl", "host" through a host buffer, "mapped"
    #: in the device memory a CPU shares, "copied"); "" for one rank
    reduce_path: str = ""
    #: the heavy-tail histograms' counts summed over the folded batches, uint64 (n_bands,
    #: histograms, TAIL_BINS): the image's, then J's depth classes (nebula_rt.transport.tails)
    tail_hist: Optional[np.ndarray] = None
    #: the light made as the last fold ended (:func:`light_while_folding`), a
    #: :class:`~nebula_rt.transport.finish.LightOutputs`, or None
    light: object = None

    @property
    def photons(self) -> int:
        """Packets per band folded in every band."""
        return int(self.band_done.min())


def light_while_folding(estimator: str, n_cells: int, spare_bytes: int, *, light_field: bool = True,
                        packets: bool = False, peel: bool = False, tree: bool = False,
                        targeted: bool = False) -> bool:
    """Whether a run whose sums are finished on the device makes its light (J, error,
    emissivity: :class:`~nebula_rt.transport.finish.LightOutputs`) as soon as its last fold
    ends, in the transport, so that the copies to the host overlap the host's work up to the
    colour pass (the thesis headline's finishing started its copies about 1.3 ms after its
    trace ended, and they took 1.5 ms). Only where the light
    comes straight from the sums (the track-length estimator, without a filter), the run
    folds batches on the device (not the estimate by packets) and nothing reads the squares
    after the fold (no error target), without peel-off images or a tree, and where J and the
    emissivity (8 B per cell beside the slots and sums) fit the slot memory the run leaves
    unused (``spare_bytes``: :func:`spare_slot_bytes`), so the device peak stays within the
    memory target."""
    return (estimator == "track-length" and light_field and not (packets or peel or tree or targeted)
            and 8 * int(n_cells) <= int(spare_bytes))


def spare_slot_bytes(backend, nvox: int, launches: "LaunchPlan", cell_bytes: int = 8) -> int:
    """The part of the backend's slot memory budget a run of ``launches`` leaves unused: its
    batch slots and the transport by regions' state take the rest."""
    slots = int(cell_bytes) * launches.bands_per_launch * int(nvox) * launches.slots
    return int(backend.slot_memory_budget) - region_bytes(backend, int(nvox), cell_bytes == 16) - slots


def plan_transport(density, request, backend: Backend, *, checked_adds: bool = False,
                   acc_limit_bits: int = 63) -> TransportPlan:
    """The first stage: check every input of ``request`` (a
    :class:`~nebula_rt.transport.request.TransportRequest`) against what the device can
    represent, then resolve the run (see :func:`nebula_rt.transport.trace` for the
    parameters; ``checked_adds`` checks every deposit for the headroom as it is added,
    ``acc_limit_bits`` is the headroom limit, lower in tests)."""
    bands, stars, tau, photons = list(request.bands), list(request.stars), request.tau, request.photons
    estimator, method, max_scatterings = request.estimator, request.method, request.max_scatterings
    seed, batch_size, target_error, time_limit = request.seed, request.batch_size, request.target_error, request.time_limit
    peel, peel_bins, error_estimate = request.peel, request.peel_bins, request.error_estimate
    if not request.light_field:
        if peel is None:
            raise SceneError("light_field", False, "a run without the light field needs a peel-off image (peel)")
        if target_error > 0.0:
            raise SceneError("transport.target_error", target_error,
                             "must be 0 for a run without the light field (it is the error of J)")
    tree = density if isinstance(density, Octree) else None
    if tree is not None:
        # the cells are the leaves (shape (n_leaves, 1, 1)); the smallest leaf sets the track
        # resolution and the largest J, a root cell the largest deposit of a flight into one
        density = np.asarray(tree.density, dtype=np.float32).reshape(-1, 1, 1)
        fine, bound = tree_run.finest_shape(tree), tree_run.coarsest_shape(tree)
    else:
        density = np.asarray(density, dtype=np.float32)
        fine = bound = density.shape
    shape = density.shape
    wl = np.array([b.wavelength for b in bands], dtype=np.float64)
    slum = star_band_luminosities(stars, wl)
    band_lum = slum.sum(axis=0)
    polarization = request.polarization
    if polarization.kind in OWN_OPTICS:  # the bands must carry the grains' optics (as a scene's do)
        own = mie_bands(bands, polarization.grains)
        for b, m in zip(bands, own):
            if not np.allclose([b.albedo, b.g, b.extinction], [m.albedo, m.g, m.extinction], rtol=1e-6, atol=0):
                raise SceneError("bands", b.name, f"with polarization '{polarization.kind}' must carry the grains' "
                                 f"albedo {m.albedo:.6g}, g {m.g:.6g} and extinction {m.extinction:.6g} "
                                 f"(nebula_rt.optics.mie.mie_bands), not {b.albedo:.6g}, {b.g:.6g}, {b.extinction:.6g}")
    biased = resolve_method(method, density if tree is None else tree, tau, stars, peel) == "biased"
    importance = resolve_importance(request.importance, peel)
    track_scale = float(2.0**FIXED_POINT_BITS * max(fine))
    # what the device forms from these inputs must fit float32/int32: checked before any work
    rho_max = limits.check_transport(density, bands, stars, slum, tau=tau, photons=photons, max_scatterings=max_scatterings,
                                     estimator=estimator, track_scale=track_scale, seed=seed,
                                     extremes=None if tree is not None else backend.density_extremes(density),
                                     cell_shapes=(fine, bound))
    backend.check_grid_fits(shape, len(bands))
    cdf = np.cumsum(slum, axis=0) / band_lum[None, :]
    cdf[-1, :] = 1.0
    sigma_scale = np.array([tau * b.extinction for b in bands], dtype=np.float64)
    albedo = np.array([b.albedo for b in bands], dtype=np.float64)
    # albedo x optical depth of the longest voxel edge at the densest voxel, the largest over the bands
    dense_edge = (rho_max / min(shape) if tree is None else
                  float(np.max(np.asarray(tree.density, np.float64) * tree_run.leaf_edges(tree))))
    scatter_depth = float(np.max(sigma_scale * albedo)) * dense_edge
    if not request.light_field:
        estimator = "none"  # (checked above as the scene's, which the image does not use)
    launches = plan_launches(photons, batch_size, target_error > 0.0, shape, len(bands), backend,
                             16 if biased else 8, error_estimate=error_estimate, peel=peel, time_limit=time_limit,
                             max_scatterings=max_scatterings, estimator=estimator, scatter_depth=scatter_depth,
                             cell_shapes=(fine, bound), stokes=1 + polarization.stokes)
    packets = launches.packet_scales is not None
    if packets:  # the fixed point the one batch's bound allows (packet_scales)
        track_scale = float(2.0**launches.packet_scales[0] * max(fine))
    base = launches.batches.base
    setup = TransportSetup(
        density=density,
        sigma_scale=sigma_scale.astype(np.float32),
        albedo=albedo.astype(np.float32),
        g=np.array([b.g for b in bands], np.float32),
        stars=np.array([s.position for s in stars], np.float32).reshape(-1, 3),
        star_cdf=np.ascontiguousarray(cdf.T, dtype=np.float32),
        estimator=estimator,
        max_scatterings=int(max_scatterings),
        seed=int(seed),
        track_scale=track_scale * (WIDE_SCALE if biased else 1.0),
        acc_limit_bits=int(acc_limit_bits),
        unchecked_adds=(not biased and not checked_adds and request.light_field
                        and (packets or _no_wrap(base + 1, max_scatterings, estimator, track_scale, bound))),
        biased=biased,
        collision_scale=float(2.0**FIXED_POINT_BITS * WIDE_SCALE) if biased else 1.0,
        packet_sq=packets,
        sq_shift=launches.packet_scales[1] if packets else 0,
        tree=tree,
        tree_buffer=None if tree is None else tree_run.device_layout(tree),
        polar=polarization.kernel_kind,
        polar_params=(polarization.kernel_params(len(bands), [b.wavelength for b in bands])
                      if polarization.enabled else None),
    )
    if biased:
        extinction = [b.extinction for b in bands]
        # the windows' maps are made on a grid: a tree's, its leaves' exact-overlap averages
        # on the grid of its deepest level, at most the maps' own resolution
        medium = density if tree is None else tree_run.map_grid(tree)
        if importance == "observer":  # the image's windows; J is not this run's product
            window = observer_depth_map(tau * medium, -np.asarray(peel.basis()[0], np.float64))
        else:
            window = depth_map(tau * medium, setup.stars)
        setup = dataclasses.replace(setup, window=window, window_rate=window_rates(albedo, setup.g, extinction),
                                    importance=importance)
        if estimator == "track-length" and importance == "stars":  # J's heavy-tail histograms by depth
            setup = dataclasses.replace(setup, tail_classes=len(DEPTH_CLASS_NAMES), tail_edges=class_edges(extinction))
    if peel is not None:
        setup = dataclasses.replace(setup, peel=_peel_camera(peel),
                                    peel_scale=_peel_scale([b.g for b in bands], polarization, wl)
                                    * (WIDE_SCALE if biased else 1.0))
        # an observer along a grid axis: the peel-offs read the density columns (4 bytes a
        # voxel) instead of marching to the edge (tuning key "peel_columns" 0: always march)
        axis = peel_axis(setup.peel[:3]) if tree is None else None
        if axis is not None and getattr(backend, "transport_tuning", {}).get("peel_columns", 1):
            setup = dataclasses.replace(setup, peel_axis=axis, peel_columns=peel_columns(density, *axis))
    return TransportPlan(setup=setup, launches=launches, photons=int(photons),
                         band_names=tuple(b.name for b in bands), band_luminosity=band_lum,
                         star_band_luminosity=slum, sigma_scale=sigma_scale, albedo=albedo,
                         # (a tree's J per leaf is divided by each leaf's volume: estimate_light)
                         nvox_inv=1.0 / float(np.prod(shape)) if tree is None else 1.0,
                         target_error=float(target_error),
                         time_limit=float(time_limit), peel=peel, peel_bins=peel_bins)
