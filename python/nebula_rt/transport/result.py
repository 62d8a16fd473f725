"""What a run returns (:class:`TransportResult`) and the warnings about its trust: packets
terminated at the scattering cap, heavy tails."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..errors import NebulaWarning, user_stacklevel
from .finish import DeviceSums
from .tails import (
    DEPTH_CLASS_NAMES, failures)



@dataclass
class TransportResult:
    """Mean intensity per band and the run's bookkeeping.

    Attributes
    ----------
    J : ndarray, float64, (n_bands, nx, ny, nz)
        Mean intensity (luminosity per box-unit area per steradian), unfiltered estimate
        (None with ``on_device`` or ``light_field=False``).
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
        :mod:`nebula_rt.transport.finish`; J, rel_error and the raw sums are then None.
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
    #: polarized runs with a peel-off image (``trace(polarization=...)``): Stokes Q and U (and V
    #: for Mie grains), (n_bands, 2 or 3, W, H) in the units of ``peel_image`` (IAU convention in the camera's frame:
    #: its up axis north, east to the image's left), their batch-means standard errors, and with
    #: ``peel_bins`` every batch's Stokes images summed over each group, (batches, n_bands, 2 or 3, n_groups)
    peel_stokes: Optional[np.ndarray] = None
    peel_stokes_error: Optional[np.ndarray] = None
    peel_stokes_bin_batches: Optional[np.ndarray] = None
    device: str = ""
    ranks: int = 1  # processes that traced it together (nebula_rt.backends.parallel)
    reduce_path: str = ""  # how the ranks' slots were added (Tallies.reduce_path)
    timings: dict = field(default_factory=dict)
    method: str = "analog"
    #: the weighted packets' windows: "stars" or "observer" (nebula_rt.transport.importance); "" for analog
    importance: str = ""
    #: how the error was estimated: "batches" (batch means) or "packets" (batches of one packet)
    error_estimate: str = "batches"
    weight_unit: float = 1.0  # count units per packet (WEIGHT_UNIT for biased runs)
    #: the heavy-tail diagnostic (nebula_rt.transport.tails): per band, the peel-off image's TailCheck
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
    J at a depth from the stars) whose heavy-tail check failed (:mod:`nebula_rt.transport.tails`): its
    stated error is not to be trusted."""
    lines = failures(None if result.tail_image is None else [[c] for c in result.tail_image], band_names, [image])
    lines += failures(result.tail_j, band_names, [f"J at optical {n} from the stars" for n in DEPTH_CLASS_NAMES])
    if lines:
        warnings.warn(NebulaWarning(
            "the stated error is not reliable (a few packets carry much of the light, or none reached; "
            "nebula_rt.transport.tails): " + "; ".join(lines) + ". Trace more packets"
            + ("" if result.method == "biased" else ', or use transport.method = "biased" (weighted packets) '
               "where the dust is optically thick")), stacklevel=user_stacklevel())


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
        + "); raise transport.max_scatterings"), stacklevel=user_stacklevel())


def exact_packet_energy(luminosity: float, photons: int) -> float:
    """L / N rounded so that (count <= N) * q and sums of such products are exact in float64."""
    bits = max(1, 53 - int(photons).bit_length())
    m, e = math.frexp(luminosity / photons)
    return math.ldexp(math.floor(m * 2.0**bits) / 2.0**bits, e)
