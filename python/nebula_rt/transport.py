"""Photon transport stage: batches of packets on a backend -> mean intensity per band.

Normalisation
-------------
Each band b of total luminosity L_b is traced with N packets of equal energy q_b ~= L_b / N
(analog transport: a packet is scattered with probability albedo, else absorbed, so every
packet keeps its energy). The track-length estimator of the mean intensity of voxel v is

    J_v = q_b * (sum of path lengths in v) / (4 pi V_v)

(box units: J is luminosity per box-unit area per steradian), so a point source in vacuum
gives J = L / (16 pi^2 r^2). The collision estimator replaces the path length by
(number of interactions in v) / sigma_v, sigma_v the extinction per box unit.

Exact energy bookkeeping
------------------------
Packet counts are exact integers. q_b is L_b / N rounded to 53 - bit_length(N) significant
bits, so every energy count * q_b and every sum of them is exact in float64:
emitted = absorbed + escaped + terminated holds bit for bit. The rounding changes q_b by
less than 2^-(52 - bit_length(N)) relative (2^-31 for 2.1M packets).

Error estimate
--------------
Packets are traced in M batches of (nearly) equal size; for each cell (voxel and band) the
device keeps the sum of the batch totals X_k (float64) and their centred sum of squares
Q = sum (X_k - mean)^2 (Welford's update as each batch is folded, float32), and the standard
error of the total is sqrt(M / (M - 1) * Q) (batch means). ``rel_error`` = SE / total, and
1.0 where nothing was tallied. The batch slots are folded as soon as a launch is done, so the
memory is the sums and at most a launch's slots, never one slot per batch.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field
from collections.abc import Sequence
from typing import Callable, Optional

import numpy as np

from . import colour_convert, limits
from .array_api import array_module
from .backends import Backend, TransportSetup
from .backends.session import region_capacity
from .errors import AccumulatorOverflowError, CancelledError, NebulaWarning, SceneError, TimeLimitError
from .importance import depth_map, observer_depth_map, resolve_importance, window_rates
from .line_of_sight import line_of_sight_tau
from .parallel import Serial, device_reducer, share
from .postprocess import DeviceSums, lit_region_error_on_device
from .scene import (  # noqa: F401  (auto's thresholds, declared with the method)
    AUTO_THICK, AUTO_THIN, ERROR_ESTIMATES, METHODS as _scene_methods)
from .tails import (
    DEPTH_CLASS_NAMES, IMAGE_ERROR_LIMIT, J_ERROR_LIMIT, TAIL_BINS, check_histograms, class_cells, class_edges, failures)

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
    march, :func:`nebula_rt.line_of_sight.line_of_sight_tau`)."""

    sigma = float(tau) * np.asarray(density, np.float64)
    depths = [float(line_of_sight_tau(sigma, s.position, d)[0]) for s in stars
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


def packet_scales(photons: int, max_scatterings: int, shape, estimator: str):
    """(track bits k, square shift j) of the error estimate by packets, or None where k would
    fall below MIN_PACKET_TRACK_BITS.

    The run is one batch, its deposits added unchecked, so no cell may reach 2^63 whatever the
    packets do: a flight crosses a (convex) voxel at most once, so a packet deposits into a
    cell at most max_scatterings + 1 times, each at most a voxel diagonal of track (or one
    collision); k, the fixed-point bits per crossing of the smallest voxel (at most
    FIXED_POINT_BITS), is the largest that keeps N such packets below 2^63. A packet's
    squares per cell add up to at most the square of its total there, so the squares, in
    units of 2^j, stay below 2^63 too (with one unit of rounding per visit)."""
    n, ms = int(photons), int(max_scatterings) + 1

    def per_deposit(bits):
        return _max_deposit(estimator, float(2.0**bits * max(shape)), shape)

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
                NebulaWarning, stacklevel=3)
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


@dataclass
class TransportResult:
    """Mean intensity per band and the run's bookkeeping.

    Attributes
    ----------
    J : ndarray, float64, (n_bands, nx, ny, nz)
        Mean intensity (luminosity per box-unit area per steradian), unfiltered estimate.
    rel_error : ndarray, float64, (n_bands, nx, ny, nz)
        Batch-means relative standard error of J (1.0 where nothing was tallied).
    counts : ndarray, int64, (n_bands, 4)
        Packets emitted, absorbed, escaped, terminated. Biased runs: exact Python integers,
        (n_bands, 5), weight sums in units of 1 / ``weight_unit`` packet with the signed
        biasing tally last (:data:`BIASED_TALLY_NAMES`).
    packet_energy : ndarray, float64, (n_bands,)
        Energy q_b of one packet.
    band_luminosity : ndarray, float64, (n_bands,)
        L_b summed over the stars.
    star_band_luminosity : ndarray, float64, (n_stars, n_bands)
    photons : int
        Packets per band.
    batches : int
        Number of batches folded (for the error estimate): the fewest of any band.
    band_batches : ndarray, int64, (n_bands,)
        Batches folded per band (more than ``batches`` in a band whose batch was re-traced in
        halves after a fixed-point overflow).
    estimator : str
    raw_sum, raw_m2 : ndarray
        The sum (fixed-point track units or collision counts) of the batch totals and their
        centred sum of squares sum (X_k - mean)^2, float64, kept for the collision-filter
        stage and for diagnostics.
    j_scale : ndarray (n_bands,)
        J per unit of raw_sum (track-length), or per unit of raw_sum / sigma (collision).
    sigma_scale : ndarray (n_bands,)
        Extinction per box unit at density 1, tau k_b.
    achieved_error : float
        Error-targeted runs: the :func:`lit_region_error` reached, combined in quadrature with
        the largest :func:`terminated_bias` (NaN otherwise).
    peel_image : ndarray or None
        With ``trace(peel=camera)``: the peel-off image of the scattered light, (n_bands, W, H),
        luminosity per box-unit area per steradian.
    peel_error : ndarray or None
        Batch-means standard error of ``peel_image`` per pixel (same units and shape).
    peel_bin_batches : ndarray or None
        With ``trace(peel_bins=labels)``: per folded batch, the peel-off image summed over each
        pixel group, (batches, n_bands, n_groups), in the units of ``peel_image``: the batch
        totals from which :mod:`nebula_rt.observe` takes the errors of its annulus profiles.
    device_bytes : int
        Device memory the transport held (see ``TransportSession.device_bytes``).
    photons_budget : int
        The packets per band asked for (``photons`` is what was traced; they differ when an
        error-targeted run stopped early).
    device_sums : DeviceSums or None
        With ``trace(on_device=True)``: the sums left on the device for
        :mod:`nebula_rt.postprocess`; J, rel_error and the raw sums are then None.
    timings : dict
        Seconds spent in the kernel launches and in total.
    """

    J: np.ndarray
    rel_error: np.ndarray
    counts: np.ndarray
    packet_energy: np.ndarray
    band_luminosity: np.ndarray
    star_band_luminosity: np.ndarray
    photons: int
    batches: int
    estimator: str
    raw_sum: Optional[np.ndarray]
    raw_m2: Optional[np.ndarray]
    band_batches: Optional[np.ndarray] = None
    j_scale: Optional[np.ndarray] = None
    sigma_scale: Optional[np.ndarray] = None
    device_sums: Optional[DeviceSums] = None
    achieved_error: float = float("nan")
    photons_budget: int = 0
    device_bytes: int = 0
    peel_image: Optional[np.ndarray] = None
    peel_error: Optional[np.ndarray] = None
    peel_bin_batches: Optional[np.ndarray] = None
    device: str = ""
    ranks: int = 1  # processes that traced it together (nebula_rt.parallel)
    reduce_path: str = ""  # how the ranks' slots were added (Tallies.reduce_path)
    timings: dict = field(default_factory=dict)
    method: str = "analog"
    #: the weighted packets' windows: "stars" or "observer" (nebula_rt.importance); "" for analog
    importance: str = ""
    #: how the error was estimated: "batches" (batch means) or "packets" (batches of one packet)
    error_estimate: str = "batches"
    weight_unit: float = 1.0  # count units per packet (WEIGHT_UNIT for biased runs)
    #: the heavy-tail diagnostic (nebula_rt.tails): per band, the peel-off image's TailCheck
    #: (None without an image) and J's per depth class (DEPTH_CLASS_NAMES; None unless weighted
    #: packets with the track-length estimator: an analog packet's deposits into a voxel are
    #: bounded by its path there, so J's batch errors are counting statistics)
    tail_image: Optional[list] = None
    tail_j: Optional[list] = None
    #: the histograms behind them, uint64 (n_bands, histograms, TAIL_BINS)
    tail_hist: Optional[np.ndarray] = None

    @property
    def energy(self) -> np.ndarray:
        """Energies (n_bands, 4, or 5 when biased) = counts * packet energy (exact in float64
        for analog runs)."""
        return self.counts.astype(np.float64) / self.weight_unit * self.packet_energy[:, None]

    @property
    def terminated_fraction(self) -> np.ndarray:
        """(n_bands,) fraction of the packets stopped at ``max_scatterings`` (their light is
        missing from J)."""
        return terminated_fraction(self.counts)

    @property
    def terminated_bias(self) -> np.ndarray:
        """(n_bands,) bound on the relative bias of J from the terminated packets
        (:func:`terminated_bias`)."""
        return terminated_bias(self.counts)


def terminated_fraction(counts) -> np.ndarray:
    """Fraction f_b of the emitted packets that were terminated, from tallies (n_bands, 4)."""
    c = np.asarray(counts, np.float64)
    return np.where(c[:, 0] > 0, c[:, 3] / np.maximum(c[:, 0], 1.0), 0.0)


def terminated_bias(counts) -> np.ndarray:
    """Bound on the relative (low) bias that terminated packets leave in the light the dust
    intercepts, sum over voxels of sigma_b J_b V (what the lit-region error weighs by):
    f_b / (A_b + f_b), A_b the absorbed and f_b the terminated fraction of the packets.

    Why: every interaction absorbs with probability 1 - albedo_b (uniform per band), so the
    expected absorbed fraction is (1 - albedo_b) times the expected interactions per packet,
    and sum sigma J V is proportional to those interactions (the collision estimator's
    expectation). Completing the terminated packets would add at most f_b to the absorbed
    fraction (each packet at most once), so the true sum exceeds the truncated one by the
    factor (A_b + x) / A_b with x <= f_b: a relative bias x / (A_b + x) <= f_b / (A_b + f_b).
    With albedo 1 nothing is absorbed and energy bounds nothing: the bound is then 1 wherever
    a packet was terminated. 0 where none was.
    """
    c = np.asarray(counts, np.float64)
    emitted = np.maximum(c[:, 0], 1.0)
    f = c[:, 3] / emitted
    a = c[:, 1] / emitted
    return np.where(c[:, 3] > 0, f / np.where(c[:, 3] > 0, a + f, 1.0), 0.0)


#: Warn (:class:`~nebula_rt.errors.NebulaWarning`) when the terminated packets may bias J by
#: more than this (:func:`terminated_bias`): a tenth of the finest quality preset's target
#: (1 %), so that below it the bias changes no targeted error by more than 0.5 %
#: (sqrt(0.01^2 + 0.001^2) = 1.005 %).
TERMINATED_WARN_BIAS = 1.0e-3


def warn_if_heavy_tailed(result: "TransportResult", band_names, image: str = "the peel-off image") -> None:
    """Warn (:class:`~nebula_rt.errors.NebulaWarning`) naming every band and tally (``image``, or
    J at a depth from the stars) whose heavy-tail check failed (:mod:`nebula_rt.tails`): its
    stated error is not to be trusted."""
    lines = failures(None if result.tail_image is None else [[c] for c in result.tail_image], band_names, [image])
    lines += failures(result.tail_j, band_names, [f"J at optical {n} from the stars" for n in DEPTH_CLASS_NAMES])
    if lines:
        warnings.warn(NebulaWarning(
            "the stated error is not reliable (a few packets carry much of the light, or none reached; "
            "nebula_rt.tails): " + "; ".join(lines) + ". Trace more packets"
            + ("" if result.method == "biased" else ', or use transport.method = "biased" (weighted packets) '
               "where the dust is optically thick")), stacklevel=3)


def warn_if_terminated(counts, band_names, max_scatterings: int) -> None:
    """Warn when the terminated packets may bias J by more than ``TERMINATED_WARN_BIAS``."""
    bias = terminated_bias(counts)
    if not np.any(bias > TERMINATED_WARN_BIAS):
        return
    f = terminated_fraction(counts)
    worst = int(np.argmax(bias))
    warnings.warn(NebulaWarning(
        f"{f[worst]:.3g} of the packets of band {band_names[worst]} stopped at transport.max_scatterings = "
        f"{max_scatterings} (terminated_fraction per band: "
        + ", ".join(f"{n} {x:.3g}" for n, x in zip(band_names, f))
        + f"); their light is missing, so J may be low by up to {bias[worst]:.3g} (sum of sigma J over "
        + ("the grid; with albedo 1 no energy balance bounds it" if bias[worst] >= 1.0 else "the grid")
        + "); raise transport.max_scatterings"), stacklevel=3)


def exact_packet_energy(luminosity: float, photons: int) -> float:
    """L / N rounded so that (count <= N) * q and sums of such products are exact in float64."""
    bits = max(1, 53 - int(photons).bit_length())
    m, e = math.frexp(luminosity / photons)
    return math.ldexp(math.floor(m * 2.0**bits) / 2.0**bits, e)


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
                  scatter_depth: float = 0.0) -> LaunchPlan:
    """The :class:`LaunchPlan` of a run of ``photons`` packets per band on a grid of ``shape``
    (checks the batch count against the limits first); ``error_estimate`` and the arguments
    after it as :func:`resolve_error_estimate` takes them (``cell_bytes`` 16: weighted
    packets)."""
    nvox = int(np.prod([int(n) for n in shape]))
    size = planned_batch_size(photons, batch_size, targeted, nvox)
    limits.check_batch_count(batch_count(photons, size, nvox), size)
    plan = batch_plan(photons, size, nvox)
    per_launch, slots = backend.launch_plan(nvox, n_bands, plan.base + 1, len(plan), cell_bytes)
    launches = LaunchPlan(plan, size, per_launch, slots, int(n_bands))
    scales = packet_scales(photons, max_scatterings, shape, estimator)

    if resolve_error_estimate(error_estimate, biased=cell_bytes == 16, peel=peel, targeted=targeted,
                              time_limit=time_limit, batch_size=batch_size, launches=launches, scales=scales,
                              nvox=nvox, in_flight=region_capacity(backend, nvox, cell_bytes == 16),
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


def _peel_camera(camera) -> np.ndarray:
    """The 15 floats the kernel's peel-off reads: direction to the observer, image axes u and
    v, centre of pixel (0, 0), pixel size, W, H (box units)."""
    d, u, v = camera.basis()
    w, h = camera.size
    return np.concatenate([-d, u, v, camera.origin(), [camera.pixel_size, w, h]]).astype(np.float32)


def _peel_scale(gs) -> float:
    """Fixed-point units per 1/sr of a peel-off deposit: 2^24 at the largest phase function
    value of the bands (forward, |g| clamped as the sampling does), so one deposit is at most
    2^24 + 1 units and a launch of 2^23 packets scattering up to 2^15 times each cannot reach
    2^63. Deposits are rounded stochastically (kernels/transport.cl, nrt_fixed_stochastic), so
    weights far below one unit still add their expectation."""
    g = min(max(abs(float(x)) for x in gs), 1.0 - 1.0e-4)
    phi_max = (1.0 + g) / (4.0 * math.pi * (1.0 - g) ** 2)
    return float(2.0**24 / phi_max)


def batch_standard_error(s1, m2, m):
    """Standard error of a total of ``m`` batch totals from their sum ``s1`` and centred sum
    of squares ``m2`` = sum (x - mean)^2; ``m`` an int or, per band, an array (n_bands,)
    (then ``s1`` is (n_bands, ...))."""
    xp = array_module(s1)
    mm = np.asarray(m, dtype=np.float64)
    if mm.ndim:
        mm = xp.asarray(mm.reshape((-1,) + (1,) * (s1.ndim - 1)))
        return xp.where(mm < 2, xp.abs(s1), xp.sqrt(xp.maximum(m2 * (mm / xp.maximum(mm - 1.0, 1.0)), 0.0)))
    if mm < 2:
        return xp.abs(s1)  # one batch: no spread to measure, report 100 %
    return xp.sqrt(xp.maximum(m2 * (float(mm) / (float(mm) - 1.0)), 0.0))


def welford_fold(s1, m2, x, k: int):
    """Fold batch total ``x`` into the sum ``s1`` and centred sum of squares ``m2`` of ``k``
    earlier batches (in place), as the device's fold does (kernels/transport.cl)."""
    if k == 0:
        s1 += x
        return
    mean_old = s1 / k
    s1 += x
    m2 += (x - mean_old) * (x - s1 / (k + 1))


class _PeelSums:
    """Per-batch peel-off images folded on the host: the sum and the centred sum of squares of
    the batch images per pixel (batch means, as for the voxel tallies) and, with pixel groups
    (``labels``: group of each pixel, (W, H), -1 for none), every batch's group sums."""

    def __init__(self, n_bands: int, size, labels=None):
        self.s1 = np.zeros((n_bands,) + tuple(size), np.float64)
        self.s2 = np.zeros_like(self.s1)
        self.batches = 0
        self.band_batches = np.zeros(n_bands, np.int64)
        self.groups = [[] for _ in range(n_bands)]  # per band: every batch's group sums
        self.labels = None
        if labels is not None:
            lab = np.asarray(labels)
            if lab.shape != tuple(size) or not np.issubdtype(lab.dtype, np.integer):
                raise ValueError(f"peel_bins must be an integer array of the image's shape {tuple(size)}, "
                                 f"got {lab.dtype} {lab.shape}")
            keep = lab.reshape(-1) >= 0
            self.labels = (np.flatnonzero(keep), lab.reshape(-1)[keep], int(lab.max(initial=-1)) + 1)

    def add(self, image, band0: int = 0) -> None:
        """Fold one batch's image of bands ``band0 ..`` (uint64 fixed point, (bands, W, H));
        the units are exact integers, and their float64 sum stays exact while a pixel holds
        fewer than 2^29 full-weight deposits over the run. The error uses the batches of the
        first band (the bands of one batch are folded together or one after another)."""
        x = image.astype(np.float64)
        sl = slice(band0, band0 + x.shape[0])
        k = self.band_batches[band0]
        welford_fold(self.s1[sl], self.s2[sl], x, int(k))
        self.band_batches[sl] += 1
        self.batches = int(self.band_batches.min())
        if self.labels is not None:
            idx, lab, n = self.labels
            flat = x.reshape(x.shape[0], -1)[:, idx]
            for b, row in enumerate(flat, start=band0):
                self.groups[b].append(np.bincount(lab, weights=row, minlength=n))

    def finish(self, scale):
        """(image, standard error, group sums per batch) in units of ``scale`` per fixed-point
        unit (per band)."""
        sc = np.asarray(scale, np.float64)[:, None, None]
        err = batch_standard_error(self.s1, self.s2, self.band_batches) * sc
        groups = None
        if self.labels is not None:
            m = min(len(g) for g in self.groups)
            if any(len(g) != m for g in self.groups):
                # only a band whose batch overflowed (and was re-traced in halves) has more
                raise AccumulatorOverflowError(
                    "peel_bins: a batch of one band was re-traced in halves after a fixed-point "
                    "overflow, so the bands' batch sums no longer pair up; lower transport.batch_size")
            groups = (np.stack([np.stack(g) for g in self.groups], axis=1) if m else
                      np.zeros((0, self.s1.shape[0], self.labels[2])))
            groups = groups * np.asarray(scale, np.float64)[None, :, None]
        return self.s1 * sc, err, groups


#: Error-targeted runs: batches planned for the photon budget, so that the error can be checked
#: (and the run stopped) after every launch once MIN_BATCHES batches are in.
TARGET_BATCHES = 256
#: Lit region: voxels whose intercepted light sigma_b J_b is at least LIT_FRACTION of the
#: LIT_PERCENTILE-th percentile of the positive values (the brightness the colour's auto
#: exposure maps to full scale), i.e. what a rendering shows above about 1 % of full scale.
LIT_FRACTION = 0.01
LIT_PERCENTILE = 95.0


def lit_region(J, sigma):
    """Boolean mask (n_bands, nx, ny, nz) of the lit region of each band.

    ``sigma``: extinction per box unit (n_bands, nx, ny, nz) or broadcastable. Where a band has
    no dust at all the light itself (J) decides. NumPy or CuPy arrays.
    """
    xp = array_module(J)
    masks = []
    for b in range(J.shape[0]):
        x = J[b] * sigma[b] if sigma is not None else J[b]
        if not bool(xp.any(x > 0)):
            x = J[b]
        pos = x[x > 0]
        if pos.size == 0:
            masks.append(xp.zeros(J.shape[1:], dtype=bool))
            continue
        level = LIT_FRACTION * float(xp.percentile(pos, LIT_PERCENTILE))
        masks.append(x >= level)
    return xp.stack(masks)


def lit_region_error(J, rel, sigma) -> float:
    """The run's relative error: over each band's lit region, the brightness-weighted RMS of the
    per-voxel batch-means relative standard errors (1 sigma), the largest over the bands; 1.0
    where nothing is lit.

    Weights w = sigma_b J_b (the light the dust intercepts, which a rendering shows): a dim
    voxel's large relative error counts for what the eye sees of it, so the figure tracks the
    graininess of an image rather than the noise of its faintest corner.
    """
    xp = array_module(J)
    mask = lit_region(J, sigma)
    worst = 0.0
    for b in range(J.shape[0]):
        m = mask[b]
        if not bool(xp.any(m)):
            return 1.0
        w = _weights(J[b], None if sigma is None else sigma[b])[m]
        err = float(xp.sqrt(xp.sum(w * rel[b][m] ** 2) / xp.sum(w)))
        worst = max(worst, err)
    return worst


def _weights(J_b, sigma_b):
    """Brightness weights sigma J (J alone where there is no dust at all)."""
    xp = array_module(J_b)
    x = J_b * sigma_b if sigma_b is not None else J_b
    return x if bool(xp.any(x > 0)) else J_b


def light_from_sums(s1, s2, batches, estimator: str, j_scale, sigma_scale, density):
    """J and its batch-means relative error from the sum ``s1`` of the batch totals and their
    centred sum of squares ``s2``; ``batches`` an int or per band (n_bands,).

    NumPy or CuPy arrays (n_bands, nx, ny, nz); the reference for the device kernel
    ``finish_voxels`` (kernels/postprocess.cl).
    """
    xp = array_module(s1)
    se = batch_standard_error(s1, s2, batches)
    rel = xp.where(s1 > 0, se / xp.where(s1 > 0, s1, 1.0), 1.0)
    if estimator == "track-length":
        J = s1 * xp.asarray(j_scale)[:, None, None, None]
    else:
        rho = xp.asarray(density, dtype=xp.float64)
        sigma = xp.asarray(sigma_scale)[:, None, None, None] * rho[None]
        J = xp.where(sigma > 0, s1 / xp.where(sigma > 0, sigma, 1.0), 0.0)
        J *= xp.asarray(j_scale)[:, None, None, None]
    return J, rel


def _current_error(backend, sums, shape, folded, estimator, band_lum, photons, track_scale, nvox_inv,
                   sigma_scale, albedo, collision_scale=1.0) -> float:
    """The lit-region error of the batches folded so far, on the device
    (:func:`nebula_rt.postprocess.lit_region_error_on_device`): ``sums`` the (sum, centred
    squares, density) device arrays of the session or of the DeviceSums."""

    q = np.array([exact_packet_energy(L, photons) for L in band_lum])
    params = np.stack([_j_scale(q, estimator, track_scale, nvox_inv, collision_scale), sigma_scale, albedo], axis=1)
    s1, m2, rho = sums
    return lit_region_error_on_device(backend, s1, m2, rho, shape, params, folded,
                                      estimator != "track-length", LIT_FRACTION, LIT_PERCENTILE)


def _no_wrap(packets_per_batch: int, max_scatterings: int, estimator: str, track_scale: float,
             shape) -> bool:
    """Whether no fixed-point cell of a batch slot can pass 2^64 within one launch, so that
    deposits may be added unchecked and the headroom checked afterwards.

    A flight is a straight segment: it crosses a (convex) voxel at most once and ends once, so
    a packet makes at most max_scatterings + 1 deposits into one cell, each at most one voxel
    diagonal of track (or 1 collision).
    """
    return packets_per_batch * (max_scatterings + 1) * _max_deposit(estimator, track_scale, shape) < 2.0**64


def _max_deposit(estimator: str, track_scale: float, shape) -> float:
    """Largest fixed-point deposit of one flight into one cell: a voxel diagonal of track at
    ``track_scale`` units per box unit (float32 segment rounding and the rounding to an
    integer included), or one collision."""
    if estimator == "track-length":
        diagonal = math.sqrt(sum((1.0 / n) ** 2 for n in shape))
        return track_scale * diagonal * 1.001 + 1.0
    return 1.0


def _j_scale(q, estimator: str, track_scale: float, nvox_inv: float, collision_scale: float = 1.0):
    """J per unit of the sums: per fixed-point track unit, or per collision unit / sigma."""
    if estimator == "track-length":
        return q / (track_scale * 4.0 * np.pi * nvox_inv)
    return q / (collision_scale * 4.0 * np.pi * nvox_inv)


#: A launch lasts at most about this long (sized by the speed measured on the run's earlier
#: launches), so that a cancel (Ctrl-C) or a time limit is honoured within it; a group of
#: batches is then traced in several launches, which gives the same bits (absolute packet
#: indices, integer deposits).
LAUNCH_SECONDS = 0.25


class _Launcher:
    """Traces a group of batches in launches of at most about ``LAUNCH_SECONDS``, polling the
    cancel callback before each and the deadline between them."""

    def __init__(self, session, backend, cancel, deadline: float, progress_of=None):
        self.session, self.cancel, self.deadline = session, cancel, deadline
        self.progress_of = progress_of  # () -> (packets per band done, total), for messages
        self.first = max(1, int(getattr(backend, "first_launch_packets", 1 << 21)))
        self.rate = None  # packets (all bands) per second of the latest launch
        self.kernel_s = 0.0

    def poll(self) -> None:
        if self.cancel is not None and self.cancel():
            if self.progress_of is None:
                raise CancelledError("transport cancelled")
            done, total = self.progress_of()
            raise CancelledError(f"transport cancelled after {done:,} of {total:,} packets per band")

    def run(self, start: int, count: int, base: int, extra: int, first_batch: int, n_slots: int,
            bands: tuple[int, int], on_progress=None):
        """Trace packets [start, start + count) of ``bands`` (first band, number) into slots
        0..n_slots-1; ``on_progress(traced)`` after each launch but the last (a group traced in
        several launches reports as it goes).

        Returns (tallies, overflow, traced): the group's tallies and overflow flags so far and
        the packets per band traced from ``start`` (less than ``count`` only when the deadline
        passed between two launches).
        """
        nb = bands[1]
        traced = 0
        tallies = overflow = None
        while traced < count:
            self.poll()
            if traced and time.perf_counter() >= self.deadline:
                # finish the packets still in flight (transport by regions), adding none
                tallies, overflow = self._launch(start + traced, 0, base, extra, first_batch, n_slots,
                                                 False, bands)
                break
            chunk = max(1, min(count - traced, self._budget(nb) // nb))
            tallies, overflow = self._launch(start + traced, chunk, base, extra, first_batch, n_slots,
                                             traced == 0, bands, drain=traced + chunk >= count)
            traced += chunk
            if on_progress is not None and traced < count:
                on_progress(traced)
        self.poll()  # a cancel that came during the last launch
        return tallies, overflow, traced

    def _budget(self, nb: int) -> int:
        """Packets (all bands) of the next launch: the first launch's, then what the measured
        speed traces in ``LAUNCH_SECONDS``."""
        return self.first if self.rate is None else max(nb, int(self.rate * LAUNCH_SECONDS))

    def _launch(self, start, chunk, base, extra, first_batch, n_slots, fresh, bands, drain=True):
        """One launch, timed (its speed sizes the next); ``drain`` False: not the group's last
        (:meth:`TransportSession.run_group`)."""
        tk = time.perf_counter()
        out = self.session.run_group(start, chunk, base, extra, first_batch, n_slots, fresh=fresh, bands=bands,
                                     drain=drain)
        dt = time.perf_counter() - tk
        self.kernel_s += dt
        if chunk:
            self.rate = chunk * bands[1] / max(dt, 1e-6)
        return out

    def run_together(self, comm, start: int, count: int, base: int, extra: int, first_batch: int,
                     n_slots: int, bands: tuple[int, int], cancel, on_progress=None):
        """With several ranks: trace this rank's ``count`` packets of a group in as many
        launches as rank 0 needs for its share (each about ``LAUNCH_SECONDS``), every rank the
        same number, and check after each launch whether any rank was cancelled (then all
        raise :class:`CancelledError`). Returns (tallies, overflow): ``count`` may be 0."""
        nb = bands[1]
        launches = max(1, -(-count * nb // max(self._budget(nb), 1))) if comm.rank == 0 else None
        launches = int(comm.bcast(launches))
        tallies = overflow = None
        traced = 0
        for i in range(launches):
            chunk = count * (i + 1) // launches - count * i // launches
            if chunk:
                tallies, overflow = self._launch(start + traced, chunk, base, extra, first_batch, n_slots,
                                                 traced == 0, bands, drain=i + 1 == launches)
                traced += chunk
                if on_progress is not None and i + 1 < launches:
                    on_progress(traced * comm.size)
            if comm.allreduce_max(1.0 if cancel is not None and cancel() else 0.0) > 0:
                raise CancelledError("transport cancelled")
        if tallies is None:
            tallies, overflow = self.session.empty_group(n_slots, bands)
        return tallies, overflow



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
    achieved_error: float = float("nan")
    device_bytes: int = 0
    setup_s: float = 0.0
    kernel_s: float = 0.0
    reduce_s: float = 0.0  # several ranks: time spent adding the ranks' slots and tallies
    #: several ranks: how the slots were added ("nccl", "host" through a host buffer, "mapped"
    #: in the device memory a CPU shares, "copied"); "" for one rank
    reduce_path: str = ""
    #: the heavy-tail histograms' counts summed over the folded batches, uint64 (n_bands,
    #: histograms, TAIL_BINS): the image's, then J's depth classes (nebula_rt.tails)
    tail_hist: Optional[np.ndarray] = None

    @property
    def photons(self) -> int:
        """Packets per band folded in every band."""
        return int(self.band_done.min())


def plan_transport(density, bands, stars, *, tau: float, photons: int, estimator: str = "track-length",
                   max_scatterings: int = 1000, seed: int = 1, batch_size: int = 0, backend: Backend,
                   target_error: float = 0.0, time_limit: float = 0.0, peel=None, peel_bins=None,
                   checked_adds: bool = False, _acc_limit_bits: int = 63, method: str = "analog",
                   error_estimate: str = "batches", importance: str = "auto") -> TransportPlan:
    """The first stage: check every input against what the device can represent, then resolve
    the run (see :func:`trace` for the parameters; ``checked_adds`` checks every deposit for
    the headroom as it is added)."""
    density = np.asarray(density, dtype=np.float32)
    shape = density.shape
    wl = np.array([b.wavelength for b in bands], dtype=np.float64)
    slum = star_band_luminosities(stars, wl)
    band_lum = slum.sum(axis=0)
    biased = resolve_method(method, density, tau, stars, peel) == "biased"
    importance = resolve_importance(importance, peel)
    track_scale = float(2.0**FIXED_POINT_BITS * max(shape))
    # what the device forms from these inputs must fit float32/int32: checked before any work
    rho_max = limits.check_transport(density, bands, stars, slum, tau=tau, photons=photons, max_scatterings=max_scatterings,
                                     estimator=estimator, track_scale=track_scale, seed=seed,
                                     extremes=backend.density_extremes(density))
    backend.check_grid_fits(shape, len(bands))
    cdf = np.cumsum(slum, axis=0) / band_lum[None, :]
    cdf[-1, :] = 1.0
    sigma_scale = np.array([tau * b.extinction for b in bands], dtype=np.float64)
    albedo = np.array([b.albedo for b in bands], dtype=np.float64)
    # albedo x optical depth of the longest voxel edge at the densest voxel, the largest over the bands
    scatter_depth = float(np.max(sigma_scale * albedo)) * rho_max / min(shape)
    launches = plan_launches(photons, batch_size, target_error > 0.0, shape, len(bands), backend,
                             16 if biased else 8, error_estimate=error_estimate, peel=peel, time_limit=time_limit,
                             max_scatterings=max_scatterings, estimator=estimator, scatter_depth=scatter_depth)
    packets = launches.packet_scales is not None
    if packets:  # the fixed point the one batch's bound allows (packet_scales)
        track_scale = float(2.0**launches.packet_scales[0] * max(shape))
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
        acc_limit_bits=int(_acc_limit_bits),
        unchecked_adds=(not biased and not checked_adds
                        and (packets or _no_wrap(base + 1, max_scatterings, estimator, track_scale, shape))),
        biased=biased,
        collision_scale=float(2.0**FIXED_POINT_BITS * WIDE_SCALE) if biased else 1.0,
        packet_sq=packets,
        sq_shift=launches.packet_scales[1] if packets else 0,
    )
    if biased:
        extinction = [b.extinction for b in bands]
        if importance == "observer":  # the image's windows; J is not this run's product
            window = observer_depth_map(tau * density, -np.asarray(peel.basis()[0], np.float64))
        else:
            window = depth_map(tau * density, setup.stars)
        setup = dataclasses.replace(setup, window=window, window_rate=window_rates(albedo, setup.g, extinction),
                                    importance=importance)
        if estimator == "track-length" and importance == "stars":  # J's heavy-tail histograms by depth
            setup = dataclasses.replace(setup, tail_classes=len(DEPTH_CLASS_NAMES), tail_edges=class_edges(extinction))
    if peel is not None:
        setup = dataclasses.replace(setup, peel=_peel_camera(peel),
                                    peel_scale=_peel_scale([b.g for b in bands]) * (WIDE_SCALE if biased else 1.0))
    return TransportPlan(setup=setup, launches=launches, photons=int(photons),
                         band_names=tuple(b.name for b in bands), band_luminosity=band_lum,
                         star_band_luminosity=slum, sigma_scale=sigma_scale, albedo=albedo,
                         nvox_inv=1.0 / float(np.prod(shape)), target_error=float(target_error),
                         time_limit=float(time_limit), peel=peel, peel_bins=peel_bins)


def run_transport(plan: TransportPlan, backend: Backend, *, progress=None, cancel=None,
                  started: Optional[float] = None, comm=None) -> Tallies:
    """The tracing stage: trace the plan's batches, folding each launch's slots into the
    device sums, until every batch is in, the error target is met or the time limit
    (counted from ``started``) comes. Returns the :class:`Tallies`; its session stays open.

    ``comm`` (:mod:`nebula_rt.parallel`) with several ranks: each rank traces its share of
    every group's packets, the ranks' slots and tallies are added before each fold, and the
    decisions to stop (time limit, cancel: any rank's) are made together between groups, so
    every rank folds the one-rank run's sums."""

    comm = comm if comm is not None else Serial()
    distributed = comm.size > 1
    if comm.rank != 0:
        progress = None
    t0 = time.perf_counter() if started is None else started
    setup, launches = plan.setup, plan.launches
    shape, nb, photons = plan.shape, plan.n_bands, plan.photons
    batches = launches.batches
    base, extra = batches.base, batches.extra
    slots, groups = launches.slots, launches.band_groups  # groups: bands traced together
    targeted = plan.target_error > 0.0
    track_scale = setup.track_scale
    peel_sums = None if plan.peel is None else _PeelSums(nb, plan.peel.size, plan.peel_bins)
    # python ints: exact whatever the photon count (and 128-bit weight sums)
    counts = np.zeros((nb, len(BIASED_TALLY_NAMES) if setup.biased else 4), dtype=object)
    session = backend.transport_session(setup, slots, launches.bands_per_launch)
    out = Tallies(session=session, counts=np.zeros((nb, 4), np.int64), folded=np.zeros(nb, np.int64),
                  band_done=np.zeros(nb, np.int64), peel_sums=peel_sums, device_bytes=session.device_bytes(),
                  setup_s=time.perf_counter() - t0,
                  tail_hist=np.zeros((nb, setup.tail_hists, TAIL_BINS), np.uint64))
    folded, band_done = out.folded, out.band_done
    # several ranks on GPUs: the slots are added on the device (collective: every rank)
    reducer = device_reducer(comm, backend) if distributed else None
    if distributed:
        mapped = reducer is None and backend.map_host(session.d_acc, 1) is not None
        out.reduce_path = reducer.kind if reducer is not None else ("mapped" if mapped else "copied")
    deadline = t0 + plan.time_limit if plan.time_limit > 0 else math.inf
    done = 0  # packets per band traced (all bands)
    # several ranks: no rank stops on its own within a group (the others would wait for it)
    launcher = _Launcher(session, backend, None if distributed else cancel,
                         math.inf if distributed else deadline, lambda: (done, photons))

    def trace_group(start, count, first_batch, n, group, on_progress=None, base_=None, extra_=None):
        """Trace a group (this rank's share of it) and, with several ranks, add the ranks'."""
        b_, e_ = (base, extra) if base_ is None else (base_, extra_)
        if not distributed:
            return launcher.run(start, count, b_, e_, first_batch, n, group, on_progress)
        lo, mine = share(start, count, comm)
        tallies, overflow = launcher.run_together(comm, lo, mine, b_, e_, first_batch, n, group, cancel,
                                                  on_progress)
        tr = time.perf_counter()
        tallies, overflow = session.reduce_group(comm, n, group, tallies, overflow, reducer)
        out.reduce_s += time.perf_counter() - tr
        return tallies, overflow, count

    def stop_together() -> bool:
        """With several ranks: whether any rank was cancelled (all raise) or rank 0's clock
        passed the time limit (all stop), decided between groups."""
        if not distributed:
            return time.perf_counter() >= deadline
        if comm.allreduce_max(1.0 if cancel is not None and cancel() else 0.0) > 0:
            raise CancelledError(f"transport cancelled after {done:,} of {photons:,} packets per band")
        return bool(comm.bcast(time.perf_counter() >= deadline))
    next_check = 0  # packets per band after which the error is checked next (targeted runs)
    redo: list[tuple[int, int, tuple[int, int]]] = []

    def take(tallies, overflow, images, ranges, group):
        """Fold the finished batches ``ranges`` [(start, count)] of a launch's slots (bands
        ``group``) into the counts."""
        b0, nlb = group
        for k, (b_start, b_count) in enumerate(ranges):
            if overflow[k]:
                redo.append((b_start, b_count, group))
                continue
            if images is not None:
                peel_sums.add(images[k], b0)
            folded[b0:b0 + nlb] += 1
            counts[b0:b0 + nlb] += session.counts_of(tallies[k])
            if setup.tail_hists:
                out.tail_hist[b0:b0 + nlb] += tallies[k][:, setup.tally_base:].reshape(nlb, setup.tail_hists, TAIL_BINS)
            band_done[b0:b0 + nlb] += b_count

    def fold_group(group, n, tallies, overflow, ranges):
        """Fold a group's first ``n`` slots on the device and its tallies on the host."""
        session.fold(n, group, int(folded[group[0]]), packets=sum(c for _, c in ranges))
        images = session.take_images(n, group)[:len(ranges)] if plan.peel is not None else None
        take(tallies, overflow, images, ranges, group)

    try:
        # batches in groups of consecutive ones, each group's bands traced in one or more
        # launches and folded before the next group's
        first = 0
        while first < len(batches):
            n = min(slots, len(batches) - first)
            start = batches.start(first)
            count = batches.start(first + n) - start
            cut = None  # packets of the group every band finished, when the time limit came
            for gi, group in enumerate(groups):
                tallies, overflow, traced = trace_group(
                    start, count, first, n, group,
                    None if progress is None else (lambda k, gi=gi: progress(done + (gi * count + k) // len(groups), photons)))
                if traced < count:  # the time limit came: keep the batches every band finished
                    # earlier band groups traced all n; they must end where this one does
                    finished = batches.batches_within(first, start + traced) if gi == 0 else 0
                    fold_group(group, finished, tallies, overflow, batches[first:first + finished])
                    cut = batches.start(first + finished) - start
                    break
                fold_group(group, n, tallies, overflow, batches[first:first + n])
            if cut is not None:
                if cut == 0 and len(groups) > 1:
                    raise TimeLimitError(
                        f"transport.time_limit = {plan.time_limit!r}: the bands are traced one group after "
                        "another on this grid, and the time limit came before every band had finished a "
                        "batch; raise it or lower transport.batch_size")
                redo.clear()  # no time left to re-trace
                break
            done += count
            if progress is not None:
                progress(done, photons)
            first += n
            if first >= len(batches) or stop_together():
                break
            if targeted and int(folded.min()) >= MIN_BATCHES and done >= next_check:
                out.achieved_error = _current_error(backend, session.device_arrays(), shape, folded,
                                                    plan.estimator, plan.band_luminosity, done,
                                                    track_scale * setup.fold_scale, plan.nvox_inv,
                                                    plan.sigma_scale, plan.albedo,
                                                    setup.collision_scale * setup.fold_scale)
                if out.achieved_error <= plan.target_error:
                    break
                # the error falls as 1/sqrt(N): check again near where it should reach the
                # target (never before 10 % more packets), so the checks cost O(log N)
                predicted = done * (out.achieved_error / plan.target_error) ** 2
                next_check = max(int(done * 1.1), int(0.9 * predicted))
        # A batch whose fixed-point cell would have passed 2^63 was not folded. Same packets,
        # same random numbers: tracing it in two halves gives the same integer deposits with
        # more headroom each (each half then counts as a batch of the error estimate).
        if redo and setup.packet_sq:  # packet_scales keeps every cell below the limit
            raise AccumulatorOverflowError("a voxel tally of the error estimate by packets reached 2^63; "
                                           'set transport.error_estimate = "batches"')
        while redo:
            b_start, b_count, group = redo.pop()
            if b_count == 1:
                raise AccumulatorOverflowError(
                    "a single packet overflowed a 64-bit fixed-point voxel tally; "
                    "reduce dust.tau or transport.max_scatterings"
                )
            half = b_count // 2
            for h_start, h_count in ((b_start, half), (b_start + half, b_count - half)):
                # one batch covering the whole range: base 2^62 puts every packet in batch 0
                tallies, overflow, traced = trace_group(h_start, h_count, 0, 1, group, None, 1 << 62, 0)
                if traced < h_count:  # the time limit came: what is folded is the result
                    redo.clear()
                    break
                fold_group(group, 1, tallies, overflow, [(h_start, h_count)])
        if out.photons == 0:
            raise TimeLimitError(
                f"transport.time_limit = {plan.time_limit!r}: no batch of {base} packets per band "
                "finished within the time limit; raise it or lower transport.batch_size"
            )
    except BaseException:
        session.close()
        raise
    out.counts = counts if setup.biased else np.array(counts.tolist(), dtype=np.int64)
    out.kernel_s = launcher.kernel_s
    return out


def estimate_light(plan: TransportPlan, tallies: Tallies, backend: Backend, *, on_device: bool = False) -> TransportResult:
    """The estimate stage: J and its error (or the device sums, ``on_device``), the packet
    energies from the packets folded, the peel-off image and the error reached, from a
    plan's tallies (whose session must still be open)."""
    session, folded, band_done = tallies.session, tallies.folded, tallies.band_done
    shape, nb, estimator = plan.shape, plan.n_bands, plan.estimator
    photons = tallies.photons
    # per band: a band whose overflowed batch the time limit left unfinished has fewer
    q = np.array([exact_packet_energy(L, int(n)) for L, n in zip(plan.band_luminosity, band_done)])
    fs = plan.setup.fold_scale  # statistics units per cell unit
    if plan.setup.packet_sq:  # the error estimate by packets: batches of one packet
        folded = band_done.copy()
    j_scale = _j_scale(q, estimator, plan.setup.track_scale * fs, plan.nvox_inv, plan.setup.collision_scale * fs)
    peel_image = peel_error = peel_groups = None
    if plan.peel is not None:  # packet energy x (phase x attenuation) per pixel area
        peel_image, peel_error, peel_groups = tallies.peel_sums.finish(
            q / (plan.setup.peel_scale * plan.peel.pixel_size**2))
    achieved = float("nan")
    if plan.target_error > 0.0:
        achieved = _current_error(backend, session.device_arrays(), shape, folded, estimator, plan.band_luminosity,
                                  photons, plan.setup.track_scale * fs, plan.nvox_inv, plan.sigma_scale,
                                  plan.albedo, plan.setup.collision_scale * fs)
        # the stopping rule uses the statistical error alone (more packets do not shrink the
        # bias); the error reported adds the terminated packets' bias bound
        achieved = math.hypot(achieved, float(np.max(terminated_bias(tallies.counts))))
    has_image = plan.setup.peel is not None
    present = np.ones((nb, plan.setup.tail_hists), bool)
    if plan.setup.tail_classes:  # a depth class the grid does not reach has nothing to check
        present[:, int(has_image):] = class_cells(plan.setup.window, plan.setup.tail_edges) > 0
    limits = [IMAGE_ERROR_LIMIT] * int(has_image) + [J_ERROR_LIMIT] * plan.setup.tail_classes
    checks = check_histograms(tallies.tail_hist, band_done, limits, present) if tallies.tail_hist is not None else None
    tail_image = [row[0] for row in checks] if checks is not None and has_image else None
    tail_j = ([row[int(has_image):] for row in checks] if checks is not None and plan.setup.tail_classes
              else None)
    if on_device:
        s1, s2, d_rho = session.release_sums()
        device_sums = DeviceSums(backend, shape, nb, s1, s2, d_rho)
        J = rel = None
    else:
        device_sums = None
        s1, s2 = session.sums()
        J, rel = light_from_sums(s1, s2, folded, estimator, j_scale, plan.sigma_scale, plan.setup.density)
    return TransportResult(
        J=J,
        rel_error=rel,
        counts=tallies.counts,
        packet_energy=q,
        band_luminosity=plan.band_luminosity,
        star_band_luminosity=plan.star_band_luminosity,
        photons=photons,
        batches=int(folded.min()),
        band_batches=folded,
        estimator=estimator,
        raw_sum=None if on_device else s1,
        raw_m2=None if on_device else s2,
        j_scale=j_scale,
        sigma_scale=plan.sigma_scale,
        device_sums=device_sums,
        achieved_error=achieved,
        photons_budget=plan.photons,
        device_bytes=tallies.device_bytes,
        peel_image=peel_image,
        peel_error=peel_error,
        peel_bin_batches=peel_groups,
        device=backend.device_name,
        timings={"setup_s": tallies.setup_s, "kernel_s": tallies.kernel_s, "reduce_s": tallies.reduce_s},
        reduce_path=tallies.reduce_path,
        method="biased" if plan.setup.biased else "analog",
        importance=plan.setup.importance if plan.setup.biased else "",
        error_estimate="packets" if plan.setup.packet_sq else "batches",
        weight_unit=WEIGHT_UNIT if plan.setup.biased else 1.0,
        tail_image=tail_image,
        tail_j=tail_j,
        tail_hist=tallies.tail_hist,
    )


def trace(
    density: np.ndarray,
    bands,
    stars,
    *,
    tau: float,
    photons: int,
    estimator: str = "track-length",
    max_scatterings: int = 1000,
    seed: int = 1,
    batch_size: int = 0,
    backend: Backend,
    progress: Optional[Callable[[int, int], None]] = None,
    cancel: Optional[Callable[[], bool]] = None,
    _acc_limit_bits: int = 63,
    on_device: bool = False,
    target_error: float = 0.0,
    time_limit: float = 0.0,
    peel=None,
    peel_bins=None,
    comm=None,
    _checked_adds: bool = False,
    method: str = "analog",
    error_estimate: str = "batches",
    importance: str = "auto",
) -> TransportResult:
    """Trace ``photons`` packets per band through ``density`` and estimate J.

    Parameters
    ----------
    density : ndarray (nx, ny, nz)
        Dust density per voxel (>= 0).
    bands : sequence of nebula_rt.bands.Band
        Band optical properties (extinction relative to the reference band, albedo, g).
    stars : sequence of nebula_rt.scene.Star
        Positions (box units), luminosities, optional temperatures.
    tau : float
        Optical depth across one box edge at density 1 in the reference band.
    photons : int
        Packets per band.
    estimator : {"track-length", "collision-filter"}
        Which tally the kernel accumulates (the collision estimate is unfiltered here).
    progress : callable(done, total), optional
        Called after every group of batches (and after each launch of a group traced in
        several) with the packets per band done so far.
    cancel : callable() -> bool, optional
        Polled before every launch (launches last at most ``LAUNCH_SECONDS``) and after the
        last; True raises :class:`~nebula_rt.errors.CancelledError`.
    target_error : float
        0: trace ``photons`` packets. In (0, 1): trace batch after batch (the plan is made for
        ``photons``, now a budget) until :func:`lit_region_error` is at most this, checked once
        ``MIN_BATCHES`` batches are in and then where the 1/sqrt(N) fall of the error predicts
        the target (O(log N) checks); ``result.photons`` is what was used
        and ``result.achieved_error`` the error reached, sqrt(statistical^2 + bias^2) with the
        bias bound of terminated packets (:func:`terminated_bias`), which more packets do not
        shrink and so does not enter the stopping rule.
    time_limit : float
        Seconds; > 0 stops any run within one launch of this long, keeping the finished
        batches (the photon count then depends on the machine's speed).
    peel : nebula_rt.sky.Camera, optional
        Also make a peel-off image of the scattered light seen by this camera (the phase
        function at every scattering towards the observer, attenuated to the box's edge):
        ``result.peel_image``, luminosity per box-unit area per steradian, (n_bands, W, H),
        the layout of :class:`nebula_rt.sky.SkyImage`; ``result.peel_error`` its batch-means
        standard error per pixel.
    peel_bins : int ndarray (W, H), optional
        With ``peel``: a pixel group per pixel (-1: none); ``result.peel_bin_batches`` then
        holds every batch's image summed over each group, for the errors of statistics of
        several pixels (an annulus's sum: the pixels of a batch are correlated, one packet
        peeling off into many of them).
    on_device : bool
        Leave the sums on the device (``result.device_sums``, for
        :func:`nebula_rt.postprocess.finish`) instead of computing J and rel_error on the host.
    comm : communicator, optional
        Trace with several processes (:func:`nebula_rt.parallel.world` under ``mpiexec``):
        every rank calls ``trace`` with the same arguments, traces a share of the packets, and
        gets the one-rank result, bit for bit.
    method : {"analog", "biased", "auto"}
        Analog packets, or weighted ones for optically thick dust (forced scattering,
        composite path-length biasing, Russian roulette; kernels/transport.cl, docs/physics.md),
        or the one measured best for this run (:func:`resolve_method`); ``result.method`` says
        which ran.
    error_estimate : {"batches", "packets", "auto"}
        How the error of J is estimated (:func:`resolve_error_estimate`): the spread of batch
        totals, or every packet's contribution per voxel and its square (then
        ``result.batches`` is the packet count: batches of one packet).
    importance : {"auto", "stars", "observer"}
        What steers the weighted packets' windows (:mod:`nebula_rt.importance`): the light
        field from the stars, or the peel-off image's observer (``peel`` needed); ``"auto"``
        takes the observer's when there is a peel-off image, the stars' otherwise.
        ``result.importance`` says which ran ("" for analog packets). J's heavy-tail classes
        (``result.tail_j``) are checked under the stars' windows only.
    """
    t0 = time.perf_counter()
    kw = dict(tau=tau, photons=photons, estimator=estimator, max_scatterings=max_scatterings, seed=seed,
              batch_size=batch_size, backend=backend, target_error=target_error, time_limit=time_limit,
              peel=peel, peel_bins=peel_bins, _acc_limit_bits=_acc_limit_bits, method=method,
              error_estimate=error_estimate, importance=importance)
    plan = plan_transport(density, bands, stars, checked_adds=_checked_adds, **kw)
    tallies = run_transport(plan, backend, progress=progress, cancel=cancel, started=t0, comm=comm)
    try:
        if plan.setup.unchecked_adds and tallies.session.overflow_seen():
            # a cell reached the headroom limit unnoticed during a launch: trace again with
            # every add checked (same packets, same bits as a checked run)
            tallies.session.close()
            plan = plan_transport(density, bands, stars, checked_adds=True, **kw)
            tallies = run_transport(plan, backend, progress=progress, cancel=cancel, started=t0, comm=comm)
        result = estimate_light(plan, tallies, backend, on_device=on_device)
    finally:
        tallies.session.close()
    warn_if_terminated(result.counts, list(plan.band_names), plan.setup.max_scatterings)
    warn_if_heavy_tailed(result, list(plan.band_names))
    result.ranks = 1 if comm is None else int(comm.size)
    result.timings["total_s"] = time.perf_counter() - t0
    return result
