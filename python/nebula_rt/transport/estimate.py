"""Estimates from the tallies: the mean intensity from the exact sums, batch-means errors,
the lit region and its error, peel-off image sums."""

from __future__ import annotations

import math

import numpy as np

from ..array_api import array_module
from ..errors import AccumulatorOverflowError
from .finish import lit_region_error_on_device

from .result import exact_packet_energy


def _peel_camera(camera) -> np.ndarray:
    """The 15 floats the kernel's peel-off reads: direction to the observer, image axes u and
    v, centre of pixel (0, 0), pixel size, W, H (box units)."""
    d, u, v = camera.basis()
    w, h = camera.size
    return np.concatenate([-d, u, v, camera.origin(), [camera.pixel_size, w, h]]).astype(np.float32)


def _peel_scale(gs, polarization=None, wavelengths=None) -> float:
    """Fixed-point units per 1/sr of a peel-off deposit: 2^24 at the largest phase function
    value of the bands (forward, |g| clamped as the sampling does; Rayleigh's 3 / (8 pi); the
    largest S11 of Mie's tables at the bands' ``wavelengths``, nm), so one
    deposit is at most 2^24 + 1 units and a launch of 2^23 packets scattering up to 2^15 times
    each cannot reach 2^63. Polarized light's intensity towards the observer, S11 (1 + s12 q),
    is at most twice the phase function, so the scale halves. Deposits are rounded
    stochastically (kernels/transport.cl, nrt_fixed_stochastic), so weights far below one unit
    still add their expectation."""
    g = min(max(abs(float(x)) for x in gs), 1.0 - 1.0e-4)
    phi_max = (1.0 + g) / (4.0 * math.pi * (1.0 - g) ** 2)
    if polarization is not None and polarization.enabled:
        own = polarization.phase_max(wavelengths)
        phi_max = 2.0 * (phi_max if own is None else own)
    return float(2.0**24 / phi_max)


def batch_standard_error(s1, m2, m):
    """Standard error of a total of ``m`` batch totals from their sum ``s1`` and centred sum
    of squares ``m2`` = sum (x - mean)^2; ``m`` an int or, per band, an array (n_bands,)
    (then ``s1`` is (n_bands, ...))."""
    xp = array_module(s1)
    mm = np.asarray(m, dtype=np.float64)
    if mm.ndim:
        # band by band, in place: one temporary of a band (the whole-array expression made six
        # of every band at once, 1.5 s for 3 x 5.6M leaves on 2 CPU cores)
        out = xp.empty(s1.shape, dtype=xp.result_type(s1, m2, np.float64))
        for b, k in enumerate(mm.reshape(-1)):
            out[b] = batch_standard_error(s1[b], m2[b], int(k))
        return out
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
        self._row_labels = None  # add_batches: the labels of its rows, offset row by row
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
        self.add_batches(np.asarray(image)[None], band0)

    def add_batches(self, images, band0: int = 0) -> None:
        """Fold several batches' images (batches, bands, W, H) in order: the same bits as
        :meth:`add` of each, with the pixel groups summed for all of them at once (a fit's
        trial folds 16 batches; one at a time it took 3 ms of an H200 trial's host time)."""
        x = np.asarray(images).astype(np.float64)
        m, nb = x.shape[0], x.shape[1]
        sl = slice(band0, band0 + nb)
        for j in range(m):
            welford_fold(self.s1[sl], self.s2[sl], x[j], int(self.band_batches[band0]))
            self.band_batches[sl] += 1
        self.batches = int(self.band_batches.min())
        if self.labels is not None and m:
            idx, lab, n = self.labels
            flat = x.reshape(m * nb, -1)[:, idx]  # rows (batch, band)
            # one bincount over every row, each row's groups offset by n: a row's sums add its
            # pixels in the same order as a bincount of that row alone
            rows = m * nb
            if self._row_labels is None or self._row_labels.size != rows * lab.size:
                self._row_labels = (lab[None, :] + n * np.arange(rows)[:, None]).ravel()
            sums = np.bincount(self._row_labels, weights=flat.ravel(), minlength=rows * n).reshape(m, nb, n)
            for b in range(nb):
                self.groups[band0 + b].extend(sums[:, b])

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
    (:func:`nebula_rt.transport.finish.lit_region_error_on_device`): ``sums`` the (sum, centred
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
