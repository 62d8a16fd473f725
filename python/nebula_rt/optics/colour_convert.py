"""Colour of a reflection nebula: per-band radiative-transfer results to 8-bit sRGB.

The transport runs at a handful of wavelength bands (e.g. 677/550/439 nm, or 8
bands).  A voxel's scattered light is described per band by the *ratio* of the
nebula quantity to the star's luminosity in that band.  That ratio varies
slowly with wavelength (dust albedo and optical depth), whereas the stellar
spectrum does not, so we

1. interpolate the ratio across wavelength with piecewise-linear "hat"
   functions (:func:`hat_basis`),
2. multiply by the full stellar spectrum at 1 nm (:func:`star_spectrum`),
3. integrate against the CIE 1931 2 degree colour matching functions at 1 nm.

All three steps are linear in the ratios, so they collapse into one
``(3, nb)`` matrix (:func:`band_to_xyz_matrix`) computed once per band set and
star.  Pushing coarse band arrays through ``colour.msds_to_XYZ`` instead would
resample the CMFs to the band grid and cost about 0.004 in xy.

Colour pipeline after XYZ (:func:`bands_to_srgb8`): XYZ -> linear sRGB
(D65 white, no chromatic adaptation) -> gamut mapping by desaturation towards
the pixel's luminance -> one global exposure -> hue-preserving clip of
over-exposed colours -> sRGB transfer curve -> uint8.

This module is part of the library core and never imports VTK.
"""

from __future__ import annotations

import functools
import math
from typing import Union

import numpy as np

from ..array_api import array_module
from .blackbody import planck_lambda

__all__ = [
    "auto_exposure",
    "band_edges",
    "band_luminosity_fractions",
    "band_to_xyz_matrix",
    "bands_to_srgb8",
    "encode_asinh",
    "encode_picture",
    "encode_srgb",
    "gamut_map",
    "hat_basis",
    "star_spectrum",
    "xyz_to_linear_srgb",
]

#: Wavelength range (nm) of the colour integrals; matches the CIE 1931 2 degree
#: CMF table so no extrapolation of the CMFs is ever needed.
CMF_RANGE_NM = (360, 830)
#: Visible range (nm) over which band luminosity fractions are computed.
LUMINOSITY_RANGE_NM = (380, 780)
#: Rec. 709 / sRGB luminance coefficients (row Y of the sRGB RGB->XYZ matrix).
SRGB_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])

_CMFS_NAME = "CIE 1931 2 Degree Standard Observer"

def _colour():
    """colour-science, imported where first needed: ``import colour`` also imports its plotting
    and with it matplotlib (1.5-2.7 s on 2 cores), which every process importing NebulaRT paid
    before it did anything (ParaView's start with the plugin, each command line run, a
    transport without a colour stage)."""
    import colour

    return colour


@functools.lru_cache(maxsize=None)
def xyz_to_srgb_matrix() -> np.ndarray:
    """CIE XYZ -> linear sRGB (Rec. 709 primaries, D65 white), from colour-science (read-only)."""
    m = np.asarray(_colour().RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB, dtype=np.float64).copy()
    m.flags.writeable = False
    return m


def __getattr__(name: str):
    # XYZ_TO_LINEAR_SRGB, the module constant it was, made when first asked for
    if name == "XYZ_TO_LINEAR_SRGB":
        return xyz_to_srgb_matrix()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _wavelength_grid(lo: int, hi: int) -> np.ndarray:
    """1 nm grid from ``lo`` to ``hi`` inclusive, in nm."""
    return np.arange(lo, hi + 1, dtype=np.float64)


def _cmfs_1nm() -> tuple[np.ndarray, np.ndarray]:
    """CIE 1931 2 degree CMFs on the 360..830 nm, 1 nm grid.

    Returns
    -------
    wavelengths : ndarray, shape (471,)
        Wavelengths in nm.
    cmf : ndarray, shape (471, 3)
        xbar, ybar, zbar (dimensionless).
    """
    colour = _colour()
    shape = colour.SpectralShape(CMF_RANGE_NM[0], CMF_RANGE_NM[1], 1)
    cmfs = colour.MSDS_CMFS[_CMFS_NAME].copy().align(shape)
    return np.asarray(cmfs.wavelengths, dtype=np.float64), np.asarray(cmfs.values, dtype=np.float64)


def _check_temperature(temperature: float | None) -> float | None:
    if temperature is None:
        return None
    t = float(temperature)
    if not np.isfinite(t) or t <= 0.0:
        raise ValueError(f"temperature must be a positive finite number of kelvin, got {temperature!r}")
    return t


def _check_bands(band_wavelengths_nm) -> np.ndarray:
    bands = np.asarray(band_wavelengths_nm, dtype=np.float64).reshape(-1)
    if bands.size == 0:
        raise ValueError("at least one band wavelength is required")
    if not np.all(np.isfinite(bands)) or np.any(bands <= 0.0):
        raise ValueError(f"band wavelengths must be positive finite nm, got {bands.tolist()}")
    if np.unique(bands).size != bands.size:
        # Two hat functions with the same centre are not defined (zero-width segment).
        raise ValueError(f"band wavelengths must be distinct, got {bands.tolist()}")
    return bands


def star_spectrum(source, wavelengths_nm: np.ndarray) -> np.ndarray:
    """Relative spectral power of the star.

    Parameters
    ----------
    source : float, None, or array_like (n, 2)
        A number: effective temperature in K, Planck blackbody with CIE 015's constants
        (:func:`nebula_rt.optics.blackbody.planck_lambda`, the law behind ``colour.sd_blackbody``).
        ``None``: flat, equal-energy spectrum (CIE illuminant E).
        (n, 2) pairs: a measured spectrum, wavelength in nm (increasing) and relative power
        per unit wavelength, interpolated linearly and 0 outside its range.
    wavelengths_nm : array_like
        Wavelengths in nm, any shape.

    Returns
    -------
    ndarray, same shape as ``wavelengths_nm``
        Spectral power per unit wavelength, relative (dimensionless): the
        blackbody is scaled to 1 at 560 nm (a fixed reference, so the scale does
        not depend on the sampling grid); the flat spectrum is 1 everywhere, a
        measured one 1 at its peak. Only ratios matter downstream, all consumers
        renormalise.
    """
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    if source is not None and not np.isscalar(source):
        table = np.asarray(source, dtype=np.float64).reshape(-1, 2)
        power = np.interp(wl, table[:, 0], table[:, 1], left=0.0, right=0.0)
        return power / table[:, 1].max()
    t = _check_temperature(source)
    if t is None:
        return np.ones_like(wl)
    # the absolute value (W sr^-1 m^-2 m^-1) is irrelevant, and ~1e13 numbers are awkward,
    # hence the 560 nm reference
    spd = planck_lambda(wl * 1e-9, t, colorimetry=True)
    ref = planck_lambda(560e-9, t, colorimetry=True)
    return spd / ref


def hat_basis(band_wavelengths_nm, wavelengths_nm) -> np.ndarray:
    """Piecewise-linear interpolation weights from band centres to wavelengths.

    A per-band quantity ``r_b`` becomes ``r(lambda) = sum_b r_b h_b(lambda)``:
    linear between neighbouring band centres and constant beyond the outermost
    centres (no extrapolation, which could turn negative).  Hence
    ``sum_b h_b(lambda) = 1`` for every ``lambda`` and a constant ratio is
    reproduced exactly.

    Parameters
    ----------
    band_wavelengths_nm : array_like, shape (nb,)
        Band centre wavelengths in nm, distinct, in any order.
    wavelengths_nm : array_like, shape (nw,)
        Wavelengths in nm at which to evaluate the basis.

    Returns
    -------
    ndarray, shape (nb, nw)
        ``h[b, i] = h_b(wavelengths_nm[i])``; rows follow the input band order.
    """
    bands = _check_bands(band_wavelengths_nm)
    wl = np.asarray(wavelengths_nm, dtype=np.float64).reshape(-1)
    nb = bands.size
    if nb == 1:
        return np.ones((1, wl.size))
    order = np.argsort(bands)
    sorted_bands = bands[order]
    h = np.empty((nb, wl.size))
    eye = np.eye(nb)
    for rank, b in enumerate(order):
        # np.interp holds the end values beyond the range: exactly the
        # "constant beyond the outermost bands" rule.
        h[b] = np.interp(wl, sorted_bands, eye[rank])
    return h


def band_edges(band_wavelengths_nm) -> np.ndarray:
    """Edges (nm) of the bands, in increasing wavelength: each band holds the wavelengths
    nearer its centre than any other's, over 380-780 nm (widened to the outermost centres when
    they lie outside). Returns nb + 1 edges for the bands sorted by wavelength."""
    bands = np.sort(_check_bands(band_wavelengths_nm))
    lo = min(float(LUMINOSITY_RANGE_NM[0]), float(bands[0]))
    hi = max(float(LUMINOSITY_RANGE_NM[1]), float(bands[-1]))
    return np.concatenate([[lo], 0.5 * (bands[1:] + bands[:-1]), [hi]])


def band_luminosity_fractions(band_wavelengths_nm, source) -> np.ndarray:
    """Fraction of the star's luminosity carried by each band.

    ``f_b = int_{band b} S(lambda) dlambda / int S(lambda) dlambda``: the spectrum integrated
    over each band (:func:`band_edges`: the wavelengths nearest the band's centre, over
    380-780 nm), with the trapezoid rule on a 1 nm grid; the fractions sum to 1, i.e. the
    bands share the star's luminosity over the covered range.

    Parameters
    ----------
    band_wavelengths_nm : array_like, shape (nb,)
        Band centres in nm, any order.
    source : float, None or (n, 2) array
        The star's spectrum (see :func:`star_spectrum`).

    Returns
    -------
    ndarray, shape (nb,)
        Dimensionless fractions in input band order; they sum to 1.
    """
    bands = _check_bands(band_wavelengths_nm)
    # kept for the last few (bands, spectrum): every scene check and run plan asks again, and
    # a fit's trials all ask the same (about 1 ms a trial)
    try:
        src = np.asarray(source, np.float64) if source is not None else None
        key = (bands.tobytes(), None if src is None else (src.shape, src.tobytes()))
    except (TypeError, ValueError):  # not a spectrum: star_spectrum below says why
        key = None
    hit = _FRACTIONS.get(key)
    if hit is not None:
        return hit.copy()
    edges = band_edges(bands)
    wl = np.arange(np.floor(edges[0]), np.ceil(edges[-1]) + 1.0)
    s = star_spectrum(source, wl)
    # cumulative trapezoid integral on the grid, continued to each edge inside its 1 nm cell
    # (exact for the piecewise-linear S of the grid)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (s[1:] + s[:-1]) * np.diff(wl))])
    s_edges = np.interp(edges, wl, s)
    k = np.clip(np.searchsorted(wl, edges, side="right") - 1, 0, wl.size - 1)
    x = edges - wl[k]
    at = cum[k] + 0.5 * (s[k] + s_edges) * x
    per_band = np.diff(at)
    total = per_band.sum()
    if not total > 0:
        raise ValueError("the star's spectrum has no power in the bands' range")
    out = np.empty(bands.size)
    out[np.argsort(bands)] = per_band / total
    if key is not None:
        if len(_FRACTIONS) >= 32:
            _FRACTIONS.pop(next(iter(_FRACTIONS)))
        _FRACTIONS[key] = out.copy()
    return out


_FRACTIONS: dict = {}


def band_to_xyz_matrix(band_wavelengths_nm, source) -> np.ndarray:
    """Matrix taking per-band nebula/star ratios to CIE XYZ.

    ``M[:, b] = sum_lambda h_b(lambda) S(lambda) cmf(lambda)`` over 360..830 nm
    at 1 nm with the CIE 1931 2 degree CMFs, where ``S`` is the star spectrum
    scaled so that the star itself (``r_b = 1`` for all ``b``) has ``Y = 1``.

    XYZ of a voxel is ``M @ r`` with ``r_b = nebula_b / star_luminosity_b``:
    the ratio is interpolated across wavelength and multiplied by the full
    stellar spectrum, so the star's own colour is reproduced exactly and only
    the (slowly varying) dust ratio is approximated.

    Parameters
    ----------
    band_wavelengths_nm : array_like, shape (nb,)
        Band centres in nm, any order.
    source : float, None or (n, 2) array
        The star's spectrum: temperature in K, None (flat) or measured pairs
        (see :func:`star_spectrum`).

    Returns
    -------
    ndarray, shape (3, nb)
        Columns in input band order; XYZ relative to the star (star Y = 1).
    """
    # the same bands and star every run: the matrix is cached (forming it took 1.4 ms, a tenth
    # of the thesis headline's finishing)
    wavelengths = tuple(float(w) for w in np.atleast_1d(np.asarray(band_wavelengths_nm, np.float64)))
    if source is None or np.ndim(source) == 0:
        key = None if source is None else float(source)
    else:
        pairs = np.ascontiguousarray(source, np.float64)
        key = (pairs.shape, pairs.tobytes())
    return _band_to_xyz_cached(wavelengths, key).copy()


@functools.lru_cache(maxsize=64)
def _band_to_xyz_cached(wavelengths: tuple, source_key) -> np.ndarray:
    """:func:`band_to_xyz_matrix` of hashable arguments (``source_key``: a temperature, None, or
    the measured pairs' (shape, bytes))."""
    if isinstance(source_key, tuple):
        shape, raw = source_key
        source = np.frombuffer(raw, np.float64).reshape(shape)
    else:
        source = source_key
    wl, cmf = _cmfs_1nm()
    h = hat_basis(np.array(wavelengths), wl)  # (nb, nw)
    s = star_spectrum(source, wl)  # (nw,)
    weighted = cmf * s[:, None]  # (nw, 3)
    m = (h @ weighted).T  # (3, nb)
    y_star = float(s @ cmf[:, 1])  # = m[1].sum() since sum_b h_b = 1
    return m / y_star


def xyz_to_linear_srgb(xyz) -> np.ndarray:
    """CIE XYZ to linear sRGB (Rec. 709 primaries), no chromatic adaptation.

    The sRGB white point is D65: a source with D65's chromaticity comes out
    neutral (R = G = B).  No adaptation to the star is applied, so stars keep
    their own colour, as a camera balanced for daylight would see them: a
    5800 K star looks slightly warm, a 20000 K star blue.

    Parameters
    ----------
    xyz : array_like, shape (..., 3)
        Tristimulus values (any consistent scale, Y = relative luminance).

    Returns
    -------
    ndarray, shape (..., 3)
        Linear R, G, B; components may be negative for colours outside the
        sRGB gamut (see :func:`gamut_map`).
    """
    xp = array_module(xyz)
    xyz = xp.asarray(xyz, dtype=xp.float64)
    # Same result as colour.XYZ_to_RGB(..., chromatic_adaptation_transform=None,
    # apply_cctf_encoding=False) but a plain matmul, which is faster for 1e6 voxels.
    return xyz @ xp.asarray(xyz_to_srgb_matrix()).T


def gamut_map(rgb) -> np.ndarray:
    """Bring out-of-gamut linear sRGB into gamut by desaturating towards grey.

    For a colour with a negative component, ``rgb' = Y + t (rgb - Y)`` with
    ``Y = 0.2126 R + 0.7152 G + 0.0722 B`` and the largest ``t`` in [0, 1]
    making ``min(rgb') >= 0``, i.e. ``t = Y / (Y - min(rgb))``.  Because the
    luminance weights sum to 1 this keeps the luminance and the hue angle and
    only lowers saturation (unlike per-channel clipping, which shifts hue and
    brightness).  Colours with ``Y <= 0`` become black.  In-gamut colours are
    returned unchanged.

    Parameters
    ----------
    rgb : array_like, shape (..., 3)
        Linear sRGB.

    Returns
    -------
    ndarray, shape (..., 3)
        Linear sRGB with all components >= 0 (float64, new array).
    """
    xp = array_module(rgb)
    rgb = xp.array(rgb, dtype=xp.float64, copy=True)
    y = rgb @ xp.asarray(SRGB_LUMINANCE)  # (...)
    mn = rgb.min(axis=-1)
    out_of_gamut = mn < 0.0
    if not bool(xp.any(out_of_gamut)):
        return rgb
    y_pos = y > 0.0
    fix = out_of_gamut & y_pos
    # Denominator Y - min > 0 wherever fix holds; elsewhere use 1 to avoid 0/0.
    denom = xp.where(fix, y - mn, 1.0)
    t = xp.where(fix, y / denom, 1.0)
    yy = y[..., None]
    mapped = yy + t[..., None] * (rgb - yy)
    # t is exact only up to rounding: clamp the tiny negative residue at min.
    mapped = xp.where(fix[..., None], xp.maximum(mapped, 0.0), mapped)
    black = out_of_gamut & ~y_pos
    mapped[black] = 0.0
    return mapped


def _check_exposure(exposure) -> float:
    e = float(exposure)
    if not np.isfinite(e) or e <= 0.0:
        raise ValueError(f"exposure must be a positive finite number, got {exposure!r}")
    return e


def encode_srgb(linear, exposure: float) -> np.ndarray:
    """Expose, clip and encode linear sRGB to 8-bit sRGB.

    The colour is multiplied by ``exposure``; where its largest component then
    exceeds 1 the whole colour is divided by that maximum.  This keeps the hue
    and saturation of over-exposed regions (bright nebula near the star stays
    blue instead of bleaching to white or turning cyan as with per-channel
    clipping), at the cost of compressing their brightness.  Negative values
    (which :func:`gamut_map` should already have removed) are clipped to 0.
    Then the sRGB transfer curve (IEC 61966-2-1, as ``colour.cctf_encoding(x,
    function="sRGB")``, written out so it also runs on CuPy arrays) is applied and
    values are rounded to 0..255.

    Parameters
    ----------
    linear : array_like, shape (..., 3)
        Linear sRGB, relative units.
    exposure : float
        Positive multiplier applied before clipping (1 / linear value that maps
        to full scale).

    Returns
    -------
    ndarray of uint8, shape (..., 3)
        Encoded sRGB.
    """
    e = _check_exposure(exposure)
    xp = array_module(linear)
    x = xp.clip(xp.asarray(linear, dtype=xp.float64) * e, 0.0, None)
    mx = x.max(axis=-1, keepdims=True)
    x = x / xp.maximum(mx, 1.0)
    encoded = xp.where(x <= 0.0031308, 12.92 * x, 1.055 * xp.power(x, 1.0 / 2.4) - 0.055)
    return xp.clip(xp.rint(encoded * 255.0), 0, 255).astype(xp.uint8)


def encode_asinh(linear, exposure: float, q: float = 8.0) -> np.ndarray:
    """Lupton et al. (2004, PASP 116, 133) asinh stretch of linear sRGB to 8 bits.

    With I = (R + G + B) / 3 the pixel's intensity (their eq. 2's I), every channel is scaled
    by f(I) / I, ``f(I) = asinh(Q alpha I) / asinh(Q)`` with alpha = ``exposure``: the colour
    (the ratios of the channels) is kept whatever the brightness, faint light is lifted by up to
    Q / asinh(Q) (2.9 for Q = 8) over the linear curve, and bright light compressed
    logarithmically. The asinh(Q) normalisation (Lupton et al. write f = asinh(alpha Q I) / Q)
    keeps the exposure's meaning: an intensity of 1 / exposure maps to full scale, as with
    :func:`encode_srgb`. A colour whose largest channel then exceeds 1 is divided by it (their
    section 3.2), and the values are rounded to 0..255; the stretch is the display curve, no
    sRGB transfer curve follows. ``q`` -> 0 gives the linear curve alpha x.

    Parameters
    ----------
    linear : array_like, shape (..., 3)
        Linear sRGB, relative units (>= 0 after :func:`gamut_map`; negatives are clipped).
    exposure : float
        alpha, > 0.
    q : float
        Softening Q, > 0.

    Returns
    -------
    ndarray of uint8, shape (..., 3)
    """
    e = _check_exposure(exposure)
    q = float(q)
    if not (np.isfinite(q) and q > 0.0):
        raise ValueError(f"q must be a positive finite number, got {q!r}")
    xp = array_module(linear)
    x = xp.clip(xp.asarray(linear, dtype=xp.float64), 0.0, None)
    i = x.mean(axis=-1, keepdims=True)
    # asinh(q e i) / asinh(q) / i: its limit e for i -> 0, and e also where q e i underflows
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        scale = xp.where(i > 0.0, xp.arcsinh(q * e * i) / (math.asinh(q) * xp.where(i > 0.0, i, 1.0)),
                         e * q / math.asinh(q))
    y = x * scale
    y = y / xp.maximum(y.max(axis=-1, keepdims=True), 1.0)
    return xp.clip(xp.rint(y * 255.0), 0, 255).astype(xp.uint8)


def encode_picture(linear, exposure: float, stretch: str = "linear", q: float = 8.0) -> np.ndarray:
    """8-bit colours of linear sRGB with the scene's tone curve ``colour.stretch``:
    "linear" (:func:`encode_srgb`) or "asinh" (:func:`encode_asinh` with softening ``q``)."""
    if stretch == "linear":
        return encode_srgb(linear, exposure)
    if stretch == "asinh":
        return encode_asinh(linear, exposure, q)
    raise ValueError(f'stretch must be "linear" or "asinh", got {stretch!r}')


def sky_picture(intensity, scattered, band_luminosity, matrix, exposure="auto", percentile: float = 99.0,
                stretch: str = "linear", q: float = 8.0):
    """The true-colour picture of a sky image: (uint8 (W, H, 3) sRGB, exposure used).

    Every sky picture is made here (the calibrated image's, ``nebula-rt sky``; Nebula Sky
    Image's): per band the image over the stars' band luminosity (the colour relative to the
    stars' light), to XYZ by ``matrix`` (:func:`band_to_xyz_matrix` of the dominant star),
    linear sRGB, :func:`gamut_map`, the exposure and the tone curve (:func:`encode_picture`).

    Parameters
    ----------
    intensity, scattered : ndarray (n_bands, W, H)
        The image with the stars, and its scattered light alone (box-unit intensities).
    band_luminosity : ndarray (n_bands,)
        The stars' luminosity per band (scene units).
    matrix : ndarray (3, n_bands)
        Bands -> XYZ.
    exposure : "auto" or float
        "auto": ``percentile`` of the scattered light's largest displayed component maps to
        full scale (the stars saturate).
    stretch, q : str, float
        ``colour.stretch`` and ``colour.asinh_q``.
    """
    lum = np.asarray(band_luminosity, np.float64)[:, None, None]

    def displayed(img):
        return gamut_map(xyz_to_linear_srgb(np.tensordot(np.asarray(img) / lum, matrix, axes=([0], [1]))))

    rgb = displayed(intensity)
    if exposure == "auto":
        exposure = auto_exposure(displayed(scattered), percentile=percentile)
    exposure = float(exposure)
    return encode_picture(rgb, exposure, stretch, q), exposure


def auto_exposure(linear_rgb, percentile: float = 99.5) -> float:
    """Exposure mapping a percentile of pixel brightness to full scale.

    Parameters
    ----------
    linear_rgb : array_like, shape (..., 3)
        Linear sRGB.
    percentile : float, optional
        Percentile (0..100) of the per-pixel maximum component, taken over the
        pixels whose maximum is positive (empty space would otherwise dominate).

    Returns
    -------
    float
        ``1 / value_at_percentile``; 1.0 if no pixel is positive.
    """
    if not 0.0 <= float(percentile) <= 100.0:
        raise ValueError(f"percentile must be in [0, 100], got {percentile!r}")
    xp = array_module(linear_rgb)
    mx = xp.asarray(linear_rgb, dtype=xp.float64).max(axis=-1).reshape(-1)
    pos = mx[xp.isfinite(mx) & (mx > 0.0)]
    if pos.size == 0:
        return 1.0
    level = float(xp.percentile(pos, percentile))
    return 1.0 / level if level > 0.0 else 1.0


def bands_to_srgb8(
    band_values,
    band_wavelengths_nm,
    star_band_luminosity,
    temperature: float | None = None,
    exposure: Union[float, str] = "auto",
) -> tuple[np.ndarray, float]:
    """Per-band nebula quantities to 8-bit sRGB colours.

    Parameters
    ----------
    band_values : array_like, shape (nb, ...)
        Nebula quantity per band (e.g. scattered luminosity per voxel), same
        units as ``star_band_luminosity``; band axis first.
    band_wavelengths_nm : array_like, shape (nb,)
        Band centres in nm, any order (matching the band axis).
    star_band_luminosity : array_like, shape (nb,)
        Star luminosity in each band (positive), e.g. from
        :func:`band_luminosity_fractions` times the total.
    temperature : float or None, optional
        Star temperature in K; ``None`` for a flat spectrum.
    exposure : float or "auto", optional
        Positive multiplier on linear sRGB (a voxel equal to the star has
        Y = 1), or ``"auto"`` for :func:`auto_exposure` (99.5th percentile).

    Returns
    -------
    rgb8 : ndarray of uint8, shape (..., 3)
        Encoded sRGB, band axis replaced by a trailing colour axis.
    exposure_used : float
        The exposure applied.
    """
    bands = _check_bands(band_wavelengths_nm)
    nb = bands.size
    values = np.asarray(band_values, dtype=np.float64)
    if values.ndim < 1 or values.shape[0] != nb:
        raise ValueError(
            f"band_values must have the band axis first with {nb} entries, got shape {values.shape}"
        )
    star = np.asarray(star_band_luminosity, dtype=np.float64).reshape(-1)
    if star.size != nb:
        raise ValueError(f"star_band_luminosity must have {nb} entries, got {star.size}")
    if not np.all(np.isfinite(star)) or np.any(star <= 0.0):
        raise ValueError(f"star_band_luminosity must be positive and finite, got {star.tolist()}")

    # Fold the per-band division by the star and XYZ -> RGB into one (3, nb)
    # matrix so the per-voxel work is a single small matrix product.
    m_xyz = band_to_xyz_matrix(bands, temperature) / star[None, :]
    m_rgb = xyz_to_srgb_matrix() @ m_xyz
    spatial = values.shape[1:]
    flat = values.reshape(nb, -1)  # (nb, N), a view when contiguous
    rgb = (m_rgb @ flat).T.reshape(spatial + (3,))
    rgb = gamut_map(rgb)

    if isinstance(exposure, str):
        if exposure != "auto":
            raise ValueError(f'exposure must be a positive float or "auto", got {exposure!r}')
        exposure_used = auto_exposure(rgb)
    else:
        exposure_used = _check_exposure(exposure)
    return encode_srgb(rgb, exposure_used), exposure_used
