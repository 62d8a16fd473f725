"""The user's observed image read from FITS: data in MJy/sr, a celestial WCS, 1-sigma errors.

:func:`read_image` takes one 2-D image HDU of a FITS file (leading axes of length 1 dropped)
with a celestial WCS in its header (any frame and projection astropy knows), in a surface
brightness per unit frequency (BUNIT, or the unit given, convertible to MJy/sr), and its
1-sigma errors: an error HDU of the same shape, a relative error (``"5%"``), a constant surface
brightness (``"0.2 MJy/sr"``), or several of these added in quadrature. Every problem is a
:class:`nebula_rt.errors.SceneError` naming the file and HDU and what is allowed, raised before
anything is traced. :mod:`nebula_rt.observe.image_compare` holds the image against the model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..backends.capacity import host_available_bytes
from ..errors import SceneError
from ..input_files import check_input_file
from .observed_tables import MAX_VALUE, MIN_ERROR

_UNITS_ALLOWED = ("must be a surface brightness per unit frequency, convertible to MJy/sr (e.g. MJy/sr, Jy/arcsec2, "
                  "erg/s/cm2/Hz/sr); convert counts, magnitudes or per-wavelength units first (docs/observations.md)")
_ERROR_ALLOWED = ("must be an error HDU of the file (1 sigma, the image's shape, e.g. ERR), a relative error such as "
                  "'5%', or a surface brightness such as '0.2 MJy/sr' (repeatable: they add in quadrature)")


def _sb_unit():
    import astropy.units as u

    return u.MJy / u.sr


def _parse_unit(text, where: str):
    import astropy.units as u

    try:
        try:
            unit = u.Unit(str(text), format="fits")
        except ValueError:
            unit = u.Unit(str(text))
    except (ValueError, TypeError):
        raise SceneError(where, text, _UNITS_ALLOWED) from None
    if not unit.is_equivalent(_sb_unit()):
        raise SceneError(where, text, _UNITS_ALLOWED)
    return unit


@dataclass
class ObservedImage:
    """An observed image read from FITS, in MJy/sr.

    Attributes
    ----------
    path : str
    label : str
        ``path[HDU]``, for messages.
    data : ndarray (ny, nx)
        Surface brightness, MJy/sr (FITS order: [row, column] = [y, x]); NaN where not observed.
    sigma : ndarray (ny, nx)
        1-sigma error, MJy/sr: the error terms in quadrature.
    wcs : astropy.wcs.WCS
        The image's celestial WCS (2 pixel axes).
    unit : str
        The image's unit as read (BUNIT or the one given).
    header_band : str or None
        The header's BAND or FILTER keyword, to name the model image when none is given.
    error_terms : list of str
        What the errors are made of, as given.
    """

    path: str
    label: str
    data: np.ndarray
    sigma: np.ndarray
    wcs: object
    unit: str
    header_band: Optional[str] = None
    error_terms: list = field(default_factory=list)


def _image_hdus(hdul):
    from astropy.io import fits

    kinds = (fits.PrimaryHDU, fits.ImageHDU, fits.CompImageHDU)
    # from the headers (h.shape): reading every HDU's data to see its shape would allocate
    # what a crafted header claims before anything is checked
    return [(i, h) for i, h in enumerate(hdul) if isinstance(h, kinds) and len(getattr(h, "shape", ()) or ()) >= 2]


def _hdu_name(i, h) -> str:
    return h.name if h.name and not (i == 0 and h.name == "PRIMARY") else str(i)


def _find_hdu(hdul, key, path, option: str):
    """The image HDU named (case-blind) or numbered ``key``."""
    images = _image_hdus(hdul)
    names = [_hdu_name(i, h) for i, h in images]
    text = str(key).strip()
    for i, h in images:
        if text.isdigit() and int(text) == i or text.upper() == (h.name or "").upper():
            return i, h
    raise SceneError(option, key, f"must be an image HDU of {path}: it has {names or 'none'} (name or number)")


def _hdu_data(h, path: str, label: str):
    """The data of HDU ``h``, once its header's claim is checked: a header may not declare
    more bytes than the file holds after it (a crafted or truncated file would make astropy
    allocate the claim, e.g. 600 GB for a 6 kB file), nor an image larger than the memory
    there is (as float64)."""
    from astropy.io import fits

    shape = tuple(int(n) for n in (getattr(h, "shape", None) or ()))
    values = math.prod(shape) if shape else 0
    if not isinstance(h, fits.CompImageHDU):  # (tile-compressed HDUs decompress beyond their bytes)
        offset = getattr(h, "_data_offset", None)
        size = int(getattr(h, "size", 0) or 0)
        file_bytes = Path(path).stat().st_size
        if offset is not None and int(offset) + size > file_bytes:
            raise SceneError(f"image {label}", f"shape {shape}",
                             f"the header declares {size} bytes of data, the file holds {max(file_bytes - int(offset), 0)} "
                             "after the header: a truncated or damaged FITS file")
    available = host_available_bytes()
    if values * 8 > available:
        raise SceneError(f"image {label}", f"shape {shape}",
                         f"needs {values * 8} bytes as float64, more than the {available} bytes of memory available")
    return h.data


def _squeeze(data, label: str) -> np.ndarray:
    a = np.asarray(data)
    while a.ndim > 2 and a.shape[0] == 1:
        a = a[0]
    if a.ndim != 2:
        raise SceneError(f"image {label}", f"shape {tuple(np.shape(data))}",
                         "must be a 2-D image (leading axes of length 1 are dropped)")
    return a.astype(np.float64)


def _celestial_wcs(header, label: str):
    import warnings

    from astropy.wcs import WCS, FITSFixedWarning

    allowed = ("needs a celestial WCS in its header (CTYPE1 and CTYPE2 such as RA---TAN and DEC--TAN, CRVAL, CRPIX, "
               "and CD or CDELT with PC) on the image's two axes: the sky position of every pixel")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FITSFixedWarning)
            w = WCS(header)
    except Exception as exc:  # astropy raises several kinds for a header it cannot read
        raise SceneError(f"image {label}", f"WCS: {exc}", allowed) from None
    if not w.has_celestial or sorted((w.wcs.lng, w.wcs.lat)) != [0, 1]:
        raise SceneError(f"image {label}", "no celestial WCS", allowed)
    wc = w.celestial
    try:
        wc.wcs.set()
        sky = wc.pixel_to_world_values(0.0, 0.0)
    except Exception as exc:
        raise SceneError(f"image {label}", f"WCS: {exc}", allowed) from None
    if not np.all(np.isfinite(sky)):
        raise SceneError(f"image {label}", "WCS gives no sky position for pixel (1, 1)", allowed)
    return wc


def _error_term(spec, hdul, path, data, unit):
    """(sigma (ny, nx) MJy/sr, description) of one error spec."""
    import astropy.units as u

    if isinstance(spec, u.Quantity):
        q = spec
    else:
        text = str(spec).strip()
        if text.endswith("%"):
            try:
                frac = float(text[:-1]) / 100.0
            except ValueError:
                raise SceneError("--image-error", spec, _ERROR_ALLOWED) from None
            if not (math.isfinite(frac) and frac > 0):
                raise SceneError("--image-error", spec, "a relative error must be a positive percentage, e.g. '5%'")
            if frac < MIN_ERROR:  # its square underflows: the data's error would be left out
                raise SceneError("--image-error", spec, f"a relative error must be at least {MIN_ERROR * 100:.0e} % "
                                                        "(its square is formed in float64)")
            return frac * np.abs(data), f"{text} of the image"
        q = None
        try:
            q = u.Quantity(text)
        except (TypeError, ValueError):
            pass
        if q is None or q.unit == u.dimensionless_unscaled:  # an HDU's name or number
            i, h = _find_hdu(hdul, text, path, "--image-error")
            err = _squeeze(_hdu_data(h, path, f"{path}[{_hdu_name(i, h)}]"), f"{path}[{_hdu_name(i, h)}]")
            if err.shape != data.shape:
                raise SceneError("--image-error", spec, f"the error HDU of {path} must have the image's shape "
                                 f"{data.shape}, not {err.shape}")
            eunit = str(h.header.get("BUNIT") or "").strip() or unit  # without BUNIT: the image's unit
            err = err * float(_parse_unit(eunit, f"image {path}[{_hdu_name(i, h)}] BUNIT").to(_sb_unit()))
            if np.any(err[np.isfinite(err)] < 0):
                raise SceneError("--image-error", spec, f"the error HDU of {path} must hold 1-sigma errors >= 0")
            return err, f"HDU {_hdu_name(i, h)} of {path}"
    if not q.unit.is_equivalent(_sb_unit()):
        raise SceneError("--image-error", spec, _ERROR_ALLOWED)
    val = float(q.to_value(_sb_unit()))
    if not (math.isfinite(val) and val > 0):
        raise SceneError("--image-error", spec, "a constant error must be a positive surface brightness")
    return np.full(data.shape, val), f"{q} per pixel"


def _check_sigma(sigma, data, spec, floor: bool = True) -> None:
    """An error term's values on the observed pixels within what chi^2 can square and sum: at
    most MAX_VALUE MJy/sr, and (``floor``) 0 or at least MIN_ERROR (the tables' bounds,
    :mod:`nebula_rt.observe.observed_tables`). Checked per term, before the terms are squared:
    an error of 1e308 MJy/sr (or 1e308 %) squared to infinity and left the comparison without a
    pixel, refused as the image's fault; one of 1e-320 MJy/sr squared to 0 and left the data's
    error out. A relative error has no floor per pixel (5 % of a pixel of nearly nothing is
    nearly nothing): its percentage is bounded instead (:func:`_error_term`)."""
    s = np.abs(sigma[np.isfinite(data)])
    bad = ~np.isfinite(s) | (s > MAX_VALUE)
    if floor:
        bad |= (s > 0) & (s < MIN_ERROR)
    if bad.any():
        span = f"0 or in [{MIN_ERROR:.0e}, {MAX_VALUE:.0e}]" if floor else f"at most {MAX_VALUE:.0e}"
        raise SceneError("--image-error", spec, f"gives a 1-sigma error of {float(s[bad][0]):.4g} MJy/sr on an "
                         f"observed pixel; errors must be {span} MJy/sr (chi^2 squares (data - model) / error in "
                         "float64)".replace("e+", "e"))


def read_image(path, hdu=None, *, unit=None, errors: Sequence = (), option: str = "image") -> ObservedImage:
    """Read an observed image and its errors from FITS (module docstring).

    Parameters
    ----------
    path : str or Path
    hdu : str or int, optional
        The image HDU, by name (EXTNAME, case-blind) or number; default the first HDU holding an
        image (2-D, or with leading axes of length 1).
    unit : str, optional
        The image's unit when its header has no BUNIT (or to override it); a surface brightness
        per unit frequency (MJy/sr, Jy/arcsec2, erg/s/cm2/Hz/sr, ...).
    errors : sequence
        1-sigma error terms, added in quadrature: an HDU's name or number (the image's shape;
        its BUNIT, else the image's), a relative error ``"5%"``, or a surface brightness
        (``"0.2 MJy/sr"`` or an astropy Quantity). At least one.
    option : str
        What names the file in messages (the command line's ``--image``).

    Raises
    ------
    SceneError
        Naming the file and HDU: not FITS, no image HDU, not 2-D, no celestial WCS, a unit that
        is not a surface brightness, errors missing, of the wrong shape or negative.
    """
    from astropy.io import fits

    import warnings

    path = str(path)
    check_input_file(option, path, "a readable FITS file")
    with warnings.catch_warnings():
        # a header declaring more data than the file holds: astropy's warning was a line of its
        # own beside the refusal (_hdu_data), which names the file, the HDU and the sizes
        warnings.filterwarnings("ignore", message="File may have been truncated")
        return _read_image(fits, path, hdu, unit, errors, option)


def _read_image(fits, path: str, hdu, unit, errors, option) -> ObservedImage:
    try:
        hdul = fits.open(path, memmap=False)
    except (OSError, ValueError) as exc:
        raise SceneError(option, path, f"must be a FITS file (astropy.io.fits: {exc})") from None
    with hdul:
        if hdu is None:
            images = _image_hdus(hdul)
            if not images:
                raise SceneError(option, path, "holds no image HDU: it needs a 2-D image with a celestial WCS")
            i, h = images[0]
        else:
            i, h = _find_hdu(hdul, hdu, path, "--image-hdu")
        label = f"{path}[{_hdu_name(i, h)}]"
        data = _squeeze(_hdu_data(h, path, label), label)
        wcs = _celestial_wcs(h.header, label)
        if unit is not None and not str(unit).strip():  # (was: reported as the header's BUNIT missing)
            raise SceneError("--image-unit", unit, _UNITS_ALLOWED)
        text = unit if unit is not None else h.header.get("BUNIT")
        if text is None or not str(text).strip():
            raise SceneError(f"image {label} BUNIT", None, _UNITS_ALLOWED + ": give it in BUNIT or with --image-unit")
        bunit = _parse_unit(text, f"image {label} BUNIT" if unit is None else "--image-unit")
        data = data * float(bunit.to(_sb_unit()))
        if not np.isfinite(data).any():
            raise SceneError(f"image {label}", "no finite pixel", "must hold at least one finite surface brightness")
        if not errors:
            raise SceneError("--image-error", None, "the observation's 1-sigma error is needed: " + _ERROR_ALLOWED[8:])
        terms = [_error_term(e, hdul, path, data, str(text)) for e in errors]
        for e, (term, _) in zip(errors, terms):
            _check_sigma(term, data, e, floor=not (isinstance(e, str) and e.strip().endswith("%")))
        sigma = np.sqrt(sum(t[0] ** 2 for t in terms))
        band = h.header.get("BAND") or h.header.get("FILTER")
    return ObservedImage(path=path, label=label, data=data, sigma=sigma, wcs=wcs, unit=str(text),
                         header_band=None if band is None else str(band).strip(), error_terms=[t[1] for t in terms])
