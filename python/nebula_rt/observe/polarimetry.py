"""Polarization maps of a calibrated sky image (a scene with ``bands.polarization``).

The transport's peel-off gives Stokes Q and U of the scattered light in the camera's frame
(:func:`nebula_rt.transport.trace`: reference the image's up axis, angles towards the image's
left). A calibrated image's up axis lies at ``observer.position_angle`` east of north, so its
Q and U turn by twice that angle into the IAU convention (Hamaker & Bregman 1996, A&A 117,
161; IAU 1974): the polarization angle chi counted from celestial north through east,
Q = P I cos 2chi, U = P I sin 2chi. They are PSF-convolved and calibrated as the intensity
(MJy/sr); their batch-means errors go through the PSF as variances (the squared kernel), the
pixels' errors taken as independent.

The degree of linear polarization of the scattered light, P = sqrt(Q^2 + U^2) / I, and the angle
chi = atan2(U, Q) / 2 come with first-order errors. P is a positive quantity made of two noisy
ones, so where it is below a few of its errors it is biased high (the Ricean bias: 0.27 of the
error at a signal-to-noise of 2, half the error at 1). ``debias="mas"`` gives instead the
modified asymptotic estimator of Plaszczynski et al. (2014, MNRAS 439, 4048; the estimator
Montier et al. 2015, A&A 574, A136, recommend for maps), which is unbiased to about 0.05 of
the error from a signal-to-noise of 2 on and never negative; its error is the same first-order one
(the paper: its variance reaches the components' from a signal-to-noise of 2).
"""

from __future__ import annotations

import math

import numpy as np

#: the FITS card of the Stokes extensions' convention (as CASA, astropy and the Planck maps use it)
POLCONV = "IAU"
POLCONV_COMMENT = "angle from north through east (IAU 1974)"


def to_celestial(stokes, position_angle_deg: float) -> np.ndarray:
    """Q and U (..., 2, W, H) from the camera's frame (its up axis as north) to the sky's: the
    up axis lies at ``position_angle_deg`` east of north, so chi_sky = chi + PA. A third
    component, V (..., 3, W, H), does not depend on the frame and is kept."""
    s = np.asarray(stokes, np.float64)
    a = 2.0 * math.radians(position_angle_deg)
    c, sn = math.cos(a), math.sin(a)
    out = s.copy()
    out[..., 0, :, :] = c * s[..., 0, :, :] - sn * s[..., 1, :, :]
    out[..., 1, :, :] = sn * s[..., 0, :, :] + c * s[..., 1, :, :]
    return out


def errors_to_celestial(errors, position_angle_deg: float) -> np.ndarray:
    """The errors of :func:`to_celestial`'s Q and U (independent errors of Q and U propagated;
    V's kept)."""
    e2 = np.asarray(errors, np.float64) ** 2
    a = 2.0 * math.radians(position_angle_deg)
    c2, s2 = math.cos(a) ** 2, math.sin(a) ** 2
    out = e2.copy()
    out[..., 0, :, :] = c2 * e2[..., 0, :, :] + s2 * e2[..., 1, :, :]
    out[..., 1, :, :] = s2 * e2[..., 0, :, :] + c2 * e2[..., 1, :, :]
    return np.sqrt(out)


#: the estimators of the degree of polarization ``polarization_maps`` takes
DEBIAS = ("none", "mas")


def mas_estimate(p, q, u, q_err, u_err):
    """The modified asymptotic estimator (MAS) of a degree of polarization (Plaszczynski et
    al. 2014, MNRAS 439, 4048): p - b^2 (1 - exp(-p^2 / b^2)) / (2 p), 0 where p = 0.

    b^2 is the noise variance across the measured (q, u) vector,
    (q^2 sigma_u^2 + u^2 sigma_q^2) / (q^2 + u^2), the paper's form for independent errors of q
    and u (for equal errors, their common variance). q, u and their errors are in any one unit
    with p = sqrt(q^2 + u^2) (normalised Stokes parameters and P, or Q, U and the polarized
    intensity). Where b = 0 (no noise) p is returned unchanged.
    """
    p, q, u = (np.asarray(a, np.float64) for a in (p, q, u))
    sq, su = (np.broadcast_to(np.asarray(e, np.float64), p.shape) for e in (q_err, u_err))
    lin2 = q * q + u * u
    with np.errstate(divide="ignore", invalid="ignore"):
        b2 = np.where(lin2 > 0, (q * q * su * su + u * u * sq * sq) / lin2, 0.0)
        # -expm1(-x) = 1 - exp(-x) without cancellation where p is far below b
        shift = np.where((b2 > 0) & (p > 0), -0.5 * b2 * np.expm1(-(p * p) / b2) / p, 0.0)
    return np.where(np.isnan(p), np.nan, p - shift)


def polarization_maps(i, q, u, i_err=None, q_err=None, u_err=None, debias: str = "none"):
    """Degree and angle of linear polarization with first-order errors.

    Parameters
    ----------
    i, q, u : ndarray (..., W, H)
        Intensity and Stokes Q, U (any one unit).
    i_err, q_err, u_err : ndarray or None
        Their standard errors (None: 0).
    debias : {"none", "mas"}
        The estimator of P: the raw ratio, or the modified asymptotic estimator
        (:func:`mas_estimate` of Q / I and U / I with the errors of Q and U over I), which
        removes the Ricean bias where P is within a few of its errors.

    Returns
    -------
    p, p_err : ndarray
        sqrt(Q^2 + U^2) / I (or its MAS estimate; NaN where I <= 0) and its first-order error.
    chi_deg, chi_err_deg : ndarray
        The angle atan2(U, Q) / 2 in degrees, in [0, 180) (east of north for IAU Q and U), and
        its error (NaN where Q = U = 0).
    """
    if debias not in DEBIAS:
        raise ValueError(f"debias = {debias!r}: one of {', '.join(map(repr, DEBIAS))}")
    i, q, u = (np.asarray(a, np.float64) for a in (i, q, u))
    zero = np.zeros_like(i)
    si, sq, su = (zero if e is None else np.asarray(e, np.float64) for e in (i_err, q_err, u_err))
    lin2 = q * q + u * u
    lin = np.sqrt(lin2)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(i > 0, lin / i, np.nan)
        lin_err = np.sqrt(q * q * sq * sq + u * u * su * su) / lin
        p_err = np.where(i > 0, np.sqrt((lin_err / i) ** 2 + (p * si / i) ** 2), np.nan)
        chi = np.mod(0.5 * np.degrees(np.arctan2(u, q)), 180.0)
        chi_err = np.degrees(0.5 * np.sqrt(q * q * su * su + u * u * sq * sq) / lin2)
    chi = np.where(lin2 > 0, chi, np.nan)
    if debias == "mas":
        with np.errstate(divide="ignore", invalid="ignore"):
            p = np.where(i > 0, mas_estimate(p, q / i, u / i, sq / i, su / i), np.nan)
    return p, p_err, chi, np.where(lin2 > 0, chi_err, np.nan)


def circular_polarization(i, v, i_err=None, v_err=None):
    """The degree of circular polarization V / I and its first-order error (NaN where I <= 0).

    Parameters
    ----------
    i, v : ndarray (..., W, H)
        Intensity and Stokes V (any one unit).
    i_err, v_err : ndarray or None
        Their standard errors (None: 0).
    """
    i, v = np.asarray(i, np.float64), np.asarray(v, np.float64)
    si = np.zeros_like(i) if i_err is None else np.asarray(i_err, np.float64)
    sv = np.zeros_like(v) if v_err is None else np.asarray(v_err, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(i > 0, v / i, np.nan)
        err = np.where(i > 0, np.sqrt((sv / i) ** 2 + (ratio * si / i) ** 2), np.nan)
    return ratio, err


def stokes_hdus(wcs_header, names, stokes):
    """FITS image HDUs ``Q_<band>`` and ``U_<band>`` (and ``V_<band>`` where ``stokes`` holds V)
    (MJy/sr, the intensity's WCS) of ``stokes`` (n_bands, 2 or 3, W, H) in the IAU convention
    (V > 0: the electric vector turning counterclockwise, from north through east, as the
    observer sees it; IAU 1974)."""
    from astropy.io import fits

    hdus = []
    for b, name in enumerate(names):
        for k, which in enumerate("QUV"[:np.shape(stokes)[1]]):
            hh = wcs_header.copy()
            hh["BUNIT"] = "MJy/sr"
            hh["BAND"] = name
            hh["STOKES"] = (which, "Stokes parameter of the scattered light")
            hh["POLCONV"] = (POLCONV, POLCONV_COMMENT)
            hdus.append(fits.ImageHDU(np.ascontiguousarray(np.asarray(stokes[b, k]).T, np.float32), header=hh,
                                      name=f"{which}_{name}"))
    return hdus


def vector_field(i, q, u, i_err=None, q_err=None, u_err=None, step: int = 8, snr: float = 3.0):
    """Polarization vectors over blocks of ``step`` x ``step`` pixels: I, Q and U summed over
    each block (their errors in quadrature, the pixels' taken as independent), the block's P and
    chi, and whether P is at least ``snr`` of its error.

    Returns
    -------
    centres : ndarray (n, 2)
        Each block's centre in pixel coordinates (p, q).
    p, p_err, chi_deg : ndarray (n,)
        Degree of polarization, its error and angle (east of north for IAU Q and U) of each block.
    keep : ndarray bool (n,)
        P >= snr x its error (and I > 0).
    """
    i, q, u = (np.asarray(a, np.float64) for a in (i, q, u))
    w, h = i.shape
    nw, nh = w // step, h // step

    def blocks(a, square=False):
        if a is None:
            return np.zeros((nw, nh))
        a = np.asarray(a, np.float64)[:nw * step, :nh * step]
        a = a * a if square else a
        return a.reshape(nw, step, nh, step).sum(axis=(1, 3))

    bi, bq, bu = blocks(i), blocks(q), blocks(u)
    ei, eq, eu = (np.sqrt(blocks(e, square=True)) for e in (i_err, q_err, u_err))
    p, p_err, chi, _ = polarization_maps(bi, bq, bu, ei, eq, eu)
    pc, qc = np.meshgrid((np.arange(nw) + 0.5) * step - 0.5, (np.arange(nh) + 0.5) * step - 0.5, indexing="ij")
    keep = (bi > 0) & np.isfinite(p) & np.isfinite(chi) & (p >= snr * p_err)
    return np.stack([pc.ravel(), qc.ravel()], axis=1), p.ravel(), p_err.ravel(), chi.ravel(), keep.ravel()


def overlay_vectors(rgb8, centres, p, chi_deg, keep, length: float, colour=(255, 255, 255)):
    """The picture ``rgb8`` (W, H, 3; q = 0 the bottom row, north up) with a polarization vector
    at each kept centre (:func:`vector_field`): a headless line of ``length`` pixels at P = 1,
    proportionally shorter, along chi east of north (east is to the left)."""
    out = np.array(rgb8, copy=True)
    w, h = out.shape[:2]
    for (pc, qc), pv, a, k in zip(centres, p, chi_deg, keep):
        if not k:
            continue
        half = 0.5 * length * min(float(pv), 1.0)
        dp, dq = -math.sin(math.radians(a)), math.cos(math.radians(a))  # north = +q, east = -p
        t = np.linspace(-half, half, max(2, int(math.ceil(2.0 * half)) + 1))
        pp, qq = np.rint(pc + t * dp).astype(int), np.rint(qc + t * dq).astype(int)
        ok = (pp >= 0) & (pp < w) & (qq >= 0) & (qq < h)
        out[pp[ok], qq[ok]] = colour
    return out
