"""What the device's number formats can carry, checked before any work starts.

The kernels compute in float32 (density, extinction, albedo, g, positions, path lengths) and
store J and the emissivity as float32; counts, indices and the seed are 32- or 64-bit integers.
A value beyond what these formats hold does not fail on the device: it turns into infinity,
zero, a denormal or a wrapped integer and is traced as nonsense. This module holds those
limits in one place; the scene validation (:mod:`nebula_rt.scene`, :mod:`nebula_rt.optics.bands`), the
density loader (:mod:`nebula_rt.density`), the transport (:func:`check_transport`, called by
:func:`nebula_rt.transport.trace` before the first launch) and the VTK filters use it, and every
check raises :class:`~nebula_rt.errors.SceneError` naming the parameter, the value and the
allowed range.

The float32 rule: a value that reaches the device as float32 is 0 or has a magnitude in the
*normal* range [FLOAT32_TINY, FLOAT32_MAX] = [1.1754944e-38, 3.4028235e38]. (A smaller
magnitude is a denormal, which GPUs flush to 0, or is 0 itself: the value would be traced as
something else than what was asked.) Products formed on the device (tau x extinction x
density) and outputs stored as float32 (J, emissivity) are bounded from the inputs before the
transport starts: see :func:`check_transport` and docs/physics.md, "Numerical limits".

No NumPy at import time (the scene module imports this one and stays light).
"""

from __future__ import annotations

import math
from typing import Sequence

from .errors import SceneError

#: Largest finite float32 (numpy.finfo(numpy.float32).max).
FLOAT32_MAX = 3.4028234663852886e38
#: Smallest normal float32 (numpy.finfo(numpy.float32).tiny); below it float32 is denormal.
FLOAT32_TINY = 1.1754943508222875e-38
#: Largest value of the int32 kernel arguments (max_scatterings, grid dimensions).
INT32_MAX = 2**31 - 1
#: The seed is a 64-bit unsigned key of the counter-based RNG.
SEED_LIMIT = 2**64

#: Largest |dust.offset| component (box units). The turbulence is evaluated in float32 at
#: voxel centre + offset, so its coordinates lose precision as the offset grows: measured
#: against the float64 oracle (tests/oracles/reference_density.py) on 32^3-128^3 grids, the rms
#: density error is 4e-5 of the density's standard deviation at offset 0.5, 0.5-0.75 % at 1e4,
#: 1-1.7 % at 2e4, 6 % at 1e5, 40-50 % at 1e6 (76 % of neighbouring voxels equal: blocky), and
#: above 1e7 the structure is gone. The noise has no common period to wrap the offset by (the
#: first octave's frequency is 2^0.05), so offsets beyond this are refused.
MAX_OFFSET = 1.0e4

#: Largest optical depth one flight can have: tau = -ln(1 - xi), xi at most 1 - 2^-24
#: (kernels/nebula_common.h nrt_tau_of_xi), i.e. 24 ln 2 = 16.64; rounded up.
MAX_FLIGHT_TAU = 17.0

#: Track-length estimator: the mean free path in the densest voxel must span at least this
#: many fixed-point track units (1 / track_scale box units each). A flight's deposit is its
#: length rounded to whole units, so much shorter flights deposit nothing (tau = 1e30 on a
#: 64^3 grid gave J = 0 everywhere); at 16 units the rounding of exponential path lengths is
#: below 0.1 % on average.
MIN_TRACK_UNITS_PER_FREE_PATH = 16.0

#: Effective temperatures a star may have (K). Below 1000 K a blackbody puts almost no light
#: into the blue (and below ~40 K its visible spectrum underflows float64 altogether); above
#: 1e7 K its visible spectrum is Rayleigh-Jeans (the colour no longer changes; far above, the
#: Planck law overflows float64).
TEMPERATURE_RANGE = (1.0e3, 1.0e7)


def fmt(x: float) -> str:
    """A number as messages write it: 8 significant digits (float32 needs at most 9)."""
    return f"{x:.8g}"


#: The float32 range in words, for messages.
FLOAT32_RANGE_TEXT = f"[{fmt(FLOAT32_TINY)}, {fmt(FLOAT32_MAX)}]"


def in_float32_range(v: float, zero: bool = True) -> bool:
    """True when ``v`` is 0 (if allowed) or has a magnitude in the normal float32 range (False
    for NaN and infinities)."""
    if v == 0:
        return zero
    return FLOAT32_TINY <= abs(v) <= FLOAT32_MAX


def float32_allowed(what: str = "a number", zero: bool = True) -> str:
    """The 'allowed' text of a float32 parameter, e.g. 'must be 0 or a number in [...]'."""
    head = f"must be 0 or {what}" if zero else f"must be {what}"
    return f"{head} in {FLOAT32_RANGE_TEXT} (the float32 range the device computes in)"


def check_float32_array(parameter: str, value: object, data, what: str = "values",
                        underflow: bool = True) -> None:
    """Raise SceneError unless every value of ``data`` (any float dtype, finite) survives the
    conversion to float32: magnitudes at most FLOAT32_MAX, and (with ``underflow``) non-zero
    ones at least FLOAT32_TINY.

    Parameters
    ----------
    parameter : str
        Name of the parameter in the message (``dust.file``).
    value : object
        What the message shows as the value (the file's path).
    data : ndarray
        The values (checked in float64).
    what : str
        What the values are, for the message ("density values").
    """
    import numpy as np

    a = np.abs(np.asarray(data, dtype=np.float64))
    if a.size == 0:
        return
    big = float(a.max())
    if not big <= FLOAT32_MAX:  # also NaN
        raise SceneError(parameter, value, f"{what} must be at most {fmt(FLOAT32_MAX)} in magnitude "
                                           f"(float32; found {fmt(big)})")
    small = a[(a > 0) & (a < FLOAT32_TINY)] if underflow else a[:0]
    if small.size:
        raise SceneError(parameter, value, f"non-zero {what} must be at least {fmt(FLOAT32_TINY)} in "
                                           f"magnitude (float32 normal range; found {fmt(float(small.min()))}): "
                                           "set them to 0 or scale the data")


#: packets per band at most (transport.photons): an exact integer in float64, the photon
#: numbers the kernels take as 64-bit integers
MAX_PHOTONS = 2**53
#: levels of an octree below its roots at most (a particle snapshot's dust.tree_depth; the
#: tree walk's NRT_TREE_MAX_DEPTH, kernels/tree.cl)
MAX_TREE_DEPTH = 20
#: a particle snapshot's coordinates (dust.particle_origin, grid.unit): finite float64 values
#: whose box-unit positions keep float64's precision
PARTICLE_COORDINATE_MAX = 1e30


def check_int_range(parameter: str, value: int, lo: int, hi: int, what: str = "an integer") -> None:
    """Raise SceneError unless lo <= value <= hi."""
    if not lo <= value <= hi:
        raise SceneError(parameter, value, f"must be {what} in [{lo}, {hi}]")


def check_batch_count(batches: int, batch_size: int) -> None:
    """The batch count is an int32 of the finishing kernels (the batch-means error estimate)."""
    if batches > INT32_MAX:
        raise SceneError("transport.batch_size", batch_size,
                         f"gives {batches} batches, more than the {INT32_MAX} (int32) the device counts: "
                         f"choose a batch size of at least photons / {INT32_MAX}")


# ---------------------------------------------------------------------------------------------
# products and outputs of the transport
# ---------------------------------------------------------------------------------------------


def _voxel_geometry(shape) -> tuple[float, float]:
    """(voxel volume, voxel diagonal) in box units."""
    volume = 1.0 / float(math.prod(int(n) for n in shape))
    diagonal = math.sqrt(sum((1.0 / int(n)) ** 2 for n in shape))
    return volume, diagonal


def _spectral_key(star) -> str:
    return "spectrum" if getattr(star, "spectrum", None) else "temperature"


def _spectral_source(star):
    """What sets a star's spectrum (measured pairs, temperature K, or None: flat)."""
    return getattr(star, "spectrum", None) or getattr(star, "temperature", None)


def check_transport(
    density,
    bands: Sequence,
    stars: Sequence,
    star_band_luminosity,
    *,
    tau: float,
    photons: int,
    max_scatterings: int,
    estimator: str,
    track_scale: float,
    seed: int = 0,
    extremes: tuple[float, float] | None = None,
    cell_shapes=None,
) -> float:
    """Check, before the first launch, that what the transport forms on the device fits float32.

    Bounds (box units; V the voxel volume, h its diagonal, N the packets per band, M =
    max_scatterings + 1 the flights of a packet at most, L_b the stars' luminosity in band b,
    k_b its relative extinction, a_b its albedo, rho the density):

    - extinction: tau k_b (a float32 kernel argument) and tau k_b rho over the voxels are 0 or
      in the normal float32 range; for the track-length estimator the mean free path in the
      densest voxel is at least MIN_TRACK_UNITS_PER_FREE_PATH fixed-point units;
    - J (float32 output): a packet's flights cross a voxel at most M times, so track-length J
      <= L_b M h / (4 pi V), collision J <= L_b M / (4 pi V sigma_min); the smallest non-zero
      J, one fixed-point unit (track-length) or one collision in the densest voxel, is at least
      FLOAT32_TINY;
    - emissivity a sigma J (float32 output): a flight spends at most MAX_FLIGHT_TAU of optical
      depth, and at most sigma h in one voxel, so e <= a_b L_b M min(MAX_FLIGHT_TAU, sigma_max
      h) / (4 pi V) (collision: a_b L_b M / (4 pi V)). The emissivity of nearly empty voxels may
      underflow: that is its value, rounded.

    Parameters
    ----------
    density : ndarray, float32 (nx, ny, nz)
    bands : sequence of Band
    stars : sequence of Star
    star_band_luminosity : ndarray (n_stars, n_bands)
    tau, photons, max_scatterings, estimator, track_scale, seed
        As :func:`nebula_rt.transport.trace` uses them (max_scatterings is an int32 and the
        seed a uint64 kernel argument).
    extremes : (float, float), optional
        The density's (min, max) where already reduced (on the device:
        ``Backend.density_extremes``); else reduced here.
    cell_shapes : (shape, shape), optional
        Cells of several sizes (a tree's leaves; ``density`` then holds one value per cell):
        the grids of the smallest and of the largest cells, each checked as V and h above.
        Default: the density's own shape for both.

    Returns
    -------
    float
        The density's maximum (the reduction made for the checks, for the caller's use).

    Raises
    ------
    SceneError
        Naming ``density``, ``dust.tau``, ``stars[i].luminosity``, ``stars[i].temperature`` /
        ``stars[i].spectrum``, with the value and the allowed range for this scene.
    """
    import numpy as np

    check_int_range("transport.photons", int(photons), 1, MAX_PHOTONS, "an integer (packets per band)")
    check_int_range("transport.max_scatterings", int(max_scatterings), 0, INT32_MAX, "an integer (int32)")
    check_int_range("transport.seed", int(seed), 0, SEED_LIMIT - 1, "an integer (uint64)")
    rho = np.asarray(density)
    # reductions without temporaries where possible (NaN propagates through max and min): on a
    # GPU the kernel of a thesis-sized run takes milliseconds, and so must these checks
    if extremes is not None:
        rho_low, rho_max = (float(v) for v in extremes)
    else:
        rho_max = float(rho.max()) if rho.size else 0.0
        rho_low = float(rho.min()) if rho.size else 0.0
    if not (math.isfinite(rho_max) and math.isfinite(rho_low)):
        raise SceneError("density", f"array of shape {tuple(rho.shape)}",
                         f"must be finite in float32 (magnitudes at most {fmt(FLOAT32_MAX)}; found NaN or infinity)")
    shape = rho.shape
    if rho_low >= FLOAT32_TINY:
        rho_min = rho_low
    else:  # vacuum or denormal voxels: the least normal density
        rho_min = float(np.min(rho, initial=np.inf, where=rho >= FLOAT32_TINY)) if rho_max >= FLOAT32_TINY else 0.0
    k = np.array([b.extinction for b in bands], np.float64)
    alb = np.array([b.albedo for b in bands], np.float64)
    slum = np.asarray(star_band_luminosity, np.float64).reshape(len(stars), len(bands))
    band_lum = slum.sum(axis=0)
    track = estimator == "track-length"
    dusty = tau > 0 and rho_max > 0

    if tau > 0:
        _check_extinction(tau, k, rho_max, rho_min, track_scale, track)
    sigma_max = tau * k * rho_max  # per band
    sigma_min = tau * k * rho_min
    for cells in (cell_shapes if cell_shapes is not None else (shape,)):
        _check_tallies(bands, stars, slum, band_lum, photons, max_scatterings, tau, sigma_max, sigma_min, alb,
                       track, dusty, track_scale, tuple(int(n) for n in cells))
    return rho_max


def _check_extinction(tau: float, k, rho_max: float, rho_min: float, track_scale: float, track: bool) -> None:
    """dust.tau against float32 (tau k_b and tau k_b rho) and, for the track-length estimator,
    against the fixed-point resolution of the densest voxel's mean free path."""
    lo, why_lo = FLOAT32_TINY / float(k.min()), "tau x extinction (float32)"
    hi, why_hi = FLOAT32_MAX / float(k.max()), "tau x extinction (float32)"
    if rho_max > 0:
        if FLOAT32_MAX / (k.max() * rho_max) < hi:
            hi, why_hi = FLOAT32_MAX / (k.max() * rho_max), "tau x extinction x density (float32)"
        resolved = track_scale / (MIN_TRACK_UNITS_PER_FREE_PATH * k.max() * rho_max)
        if track and resolved < hi:
            hi = resolved
            why_hi = ("the mean free path in the densest voxel, which the track-length estimator must "
                      f"resolve in {MIN_TRACK_UNITS_PER_FREE_PATH:g} fixed-point units of 1/{fmt(track_scale)} "
                      "box units (or use the collision-filter estimator)")
        if rho_min > 0 and FLOAT32_TINY / (k.min() * rho_min) > lo:
            lo, why_lo = FLOAT32_TINY / (k.min() * rho_min), "tau x extinction x density (float32)"
    if not lo <= tau <= hi:
        raise SceneError("dust.tau", tau, f"must be 0 or in [{fmt(lo)}, {fmt(hi)}] for this density "
                                          f"(max {fmt(rho_max)}, smallest non-zero {fmt(rho_min)}) and these "
                                          f"bands (extinction {fmt(k.min())} to {fmt(k.max())}): limited by "
                                          f"{why_lo if tau < lo else why_hi}")


def _check_tallies(bands, stars, slum, band_lum, photons: int, max_scatterings: int, tau: float, sigma_max, sigma_min,
                   alb, track: bool, dusty: bool, track_scale: float, shape) -> None:
    """Each band's J and emissivity against float32: the largest a voxel can reach below
    FLOAT32_MAX, the smallest tally above FLOAT32_TINY (the bounds of :func:`check_transport`)."""
    import numpy as np

    volume, diag = _voxel_geometry(shape)
    four_pi_v = 4.0 * math.pi * volume
    flights = float(max_scatterings) + 1.0
    brightest = int(np.argmax([s.luminosity for s in stars]))
    total_lum = float(sum(s.luminosity for s in stars))
    q = band_lum / float(photons)
    for b, band in enumerate(bands):
        if band_lum[b] <= 0:
            i = brightest
            raise SceneError(f"stars[{i}].{_spectral_key(stars[i])}", _spectral_source(stars[i]),
                             f"must give band {band.name!r} some light (no star does)")
        if track:
            j_hi = band_lum[b] * flights * diag / four_pi_v
            j_lo = q[b] / (track_scale * four_pi_v)
            e_hi = alb[b] * band_lum[b] * flights * min(MAX_FLIGHT_TAU, sigma_max[b] * diag) / four_pi_v
        elif dusty:
            j_hi = band_lum[b] * flights / (four_pi_v * sigma_min[b]) if sigma_min[b] > 0 else 0.0
            j_lo = q[b] / (four_pi_v * sigma_max[b])
            e_hi = alb[b] * band_lum[b] * flights / four_pi_v
        else:  # collision estimator without dust: nothing is tallied, J = 0
            continue
        hi = max(j_hi, e_hi)
        if hi > FLOAT32_MAX:
            if not track and j_hi >= e_hi:
                raise SceneError("dust.tau", tau, f"the collision estimate of J in the thinnest voxel "
                                                  f"(up to {fmt(j_hi)} in band {band.name!r}) would overflow float32 "
                                                  f"({fmt(FLOAT32_MAX)}): allowed tau >= {fmt(tau * j_hi / FLOAT32_MAX)} "
                                                  "for this scene (or the track-length estimator)")
            star = stars[brightest]
            what = "J" if j_hi >= e_hi else "emissivity"
            raise SceneError(f"stars[{brightest}].luminosity", star.luminosity,
                             f"the brightest voxel's {what} in band {band.name!r} could reach {fmt(hi)} (luminosity x "
                             f"(max_scatterings + 1) x voxel diagonal / (4 pi voxel volume)), beyond float32 "
                             f"({fmt(FLOAT32_MAX)}): allowed total luminosity of the stars <= "
                             f"{fmt(total_lum * FLOAT32_MAX / hi)} for this grid {tuple(shape)} and "
                             f"transport.max_scatterings = {max_scatterings}")
        if j_lo < FLOAT32_TINY:
            if not track and sigma_max[b] > 1.0:
                raise SceneError("dust.tau", tau, f"one collision in the densest voxel gives J = {fmt(j_lo)} in band "
                                                  f"{band.name!r}, which underflows float32 ({fmt(FLOAT32_TINY)}): "
                                                  f"allowed tau <= {fmt(tau * j_lo / FLOAT32_TINY)} for this scene")
            star = stars[brightest]
            share = slum[brightest, b] / star.luminosity
            if share < 1e-6 and _spectral_source(star) is not None:
                raise SceneError(f"stars[{brightest}].{_spectral_key(star)}", _spectral_source(star),
                                 f"gives band {band.name!r} only {fmt(share)} of the star's light, so its smallest "
                                 f"J tally ({fmt(j_lo)}) underflows float32 ({fmt(FLOAT32_TINY)}): allowed a spectrum "
                                 f"that gives every band at least {fmt(share * FLOAT32_TINY / j_lo)} of the light "
                                 "(a hotter star, or bands where it shines)")
            raise SceneError(f"stars[{brightest}].luminosity", star.luminosity,
                             f"the smallest J tally in band {band.name!r} ({fmt(j_lo)}: luminosity / photons / "
                             f"(4 pi voxel volume x fixed-point scale)) underflows float32 ({fmt(FLOAT32_TINY)}): "
                             f"allowed total luminosity of the stars >= {fmt(total_lum * FLOAT32_TINY / j_lo)} "
                             f"for {photons} photons on this grid {tuple(shape)}")
