"""A model image against an observed image (issue 17, 3b): the extension point.

What is here works on one pixel grid: :func:`compare_image` takes the model image, its Monte
Carlo error and an observed 2-D array with its errors on the same grid and gives the residuals
and chi^2 (the errors in quadrature, as :mod:`nebula_rt.comparison` explains).
:func:`model_wcs` builds the celestial WCS of a peel-off image (astropy.wcs, gnomonic) from its
pixel geometry, the distance, the box's physical edge and the pointing the user gives, and
:func:`reproject_to_model` resamples an observed FITS image with its own WCS onto it with the
``reproject`` package (not a dependency: ``pip install reproject``). Calibrated model images
(surface brightness, the star as a point source with a PSF) come from the sky-image output, so
this module compares what it is given; it converts no units.

Orientation: a peel-off image is (W, H) indexed [p, q], p along the camera's u (image right) and
q along v (image up); a FITS array is [row, column] = [y, x], so the model enters as its
transpose (H, W). With position angle 0, image up is north and image right is west (east to the
left, as on the sky seen from the Earth); the position angle turns image up from north through
east.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import SceneError


@dataclass
class ImageComparison:
    """Residual image, pulls and chi^2 of a model against an observed image on one grid."""

    residual: np.ndarray
    pull: np.ndarray
    chi2: float
    n: int


def compare_image(model, model_err, observed, observed_err, mask=None) -> ImageComparison:
    """chi^2 of ``observed`` (2-D) against ``model`` on the same grid, errors in quadrature.

    Parameters
    ----------
    model, model_err : array_like (H, W)
        The model image (FITS order) and its 1-sigma Monte Carlo error.
    observed, observed_err : array_like (H, W)
        The observation and its 1-sigma error (> 0 where used).
    mask : array_like of bool (H, W), optional
        Pixels to use (default: every pixel where all four are finite and observed_err > 0).
    """
    arrays = {"model": model, "model_err": model_err, "observed": observed, "observed_err": observed_err}
    a = {k: np.asarray(v, np.float64) for k, v in arrays.items()}
    shape = a["observed"].shape
    if a["observed"].ndim != 2:
        raise SceneError("observed", shape, "must be a 2-D image")
    for k, v in a.items():
        if v.shape != shape:
            raise SceneError(k, v.shape, f"must have the observed image's shape {shape} (reproject it first: "
                                         "reproject_to_model)")
    ok = np.isfinite(a["model"]) & np.isfinite(a["model_err"]) & np.isfinite(a["observed"]) & \
        np.isfinite(a["observed_err"]) & (a["observed_err"] > 0)
    if mask is not None:
        ok &= np.asarray(mask, bool)
    if not ok.any():
        raise SceneError("observed_err", "no usable pixel", "needs pixels with finite values and errors > 0")
    res = a["observed"] - a["model"]
    pull = np.where(ok, res / np.sqrt(a["observed_err"] ** 2 + a["model_err"] ** 2), np.nan)
    return ImageComparison(residual=np.where(ok, res, np.nan), pull=pull, chi2=float(np.nansum(pull ** 2)),
                           n=int(ok.sum()))


def model_wcs(size, pixel_size: float, box_length, distance, ra_deg: float, dec_deg: float,
              position_angle_deg: float = 0.0):
    """The celestial WCS (RA---TAN, DEC--TAN) of a model image centred on its star.

    Parameters
    ----------
    size : (W, H)
        Pixels of the image.
    pixel_size : float
        Pixel side, box units (``Camera.pixel_size``).
    box_length, distance : astropy Quantity (length)
        The box's physical edge and the distance to the nebula.
    ra_deg, dec_deg : float
        Where the image centre (the star) is on the sky.
    position_angle_deg : float
        Angle of image up from north through east.
    """
    import astropy.units as u
    from astropy.wcs import WCS

    w, h = (int(s) for s in size)
    scale_deg = math.degrees(pixel_size * (box_length / distance).to_value(u.dimensionless_unscaled))
    pa = math.radians(position_angle_deg)
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    wcs.wcs.crval = [float(ra_deg), float(dec_deg)]
    wcs.wcs.crpix = [(w + 1) / 2.0, (h + 1) / 2.0]  # FITS pixels count from 1
    # east to the left (RA falls with x), then the position angle's turn
    wcs.wcs.cd = np.array([[-math.cos(pa), math.sin(pa)], [math.sin(pa), math.cos(pa)]]) * scale_deg
    return wcs


def reproject_to_model(observed, observed_wcs, target_wcs, shape_out):
    """The observed image resampled onto the model's grid with ``reproject.reproject_interp``
    (flux-density images; use reproject_exact for surface integrals). Returns (array,
    footprint)."""
    try:
        from reproject import reproject_interp
    except ImportError:
        raise SceneError("observed image", "reproject", "resampling a FITS image onto the model's grid needs the "
                                                        "reproject package: pip install reproject") from None
    return reproject_interp((np.asarray(observed, np.float64), observed_wcs), target_wcs, shape_out=tuple(shape_out))
