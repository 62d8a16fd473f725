"""The Gaussian point-spread function of calibrated sky images (observer.psf_fwhm): its
pixel-integrated weights, an image convolved with it, and the errors of a convolved image."""

from __future__ import annotations

import math

import numpy as np


def _ndtr(x):
    from scipy.special import ndtr

    return ndtr(x)


def psf_weights(n: int, centre: float, sigma: float) -> np.ndarray:
    """The 1D Gaussian of ``sigma`` (pixels) centred at ``centre`` (pixel coordinates, pixel k
    spans [k - 1/2, k + 1/2)) integrated over each of n pixels; sigma 0: 1 in the pixel
    holding the centre."""
    k = np.arange(n, dtype=np.float64)
    if sigma == 0.0:
        w = np.zeros(n)
        j = int(math.floor(centre + 0.5))
        if 0 <= j < n:
            w[j] = 1.0
        return w
    return _ndtr((k + 0.5 - centre) / sigma) - _ndtr((k - 0.5 - centre) / sigma)


def convolve_psf(image, sigma: float) -> np.ndarray:
    """``image`` (..., W, H) convolved with the pixel-integrated Gaussian of ``sigma`` pixels;
    light carried beyond the image is lost (the kernel reaches 8 sigma, where the Gaussian's
    tail is 1e-15, and is not renormalised)."""
    from scipy.ndimage import convolve1d

    img = np.asarray(image, np.float64)
    if sigma == 0.0:
        return img.copy()
    w, h = img.shape[-2:]
    radius = int(min(math.ceil(8.0 * sigma) + 1, max(w, h)))
    kernel = psf_weights(2 * radius + 1, float(radius), sigma)
    out = convolve1d(img, kernel, axis=-2, mode="constant", cval=0.0)
    return convolve1d(out, kernel, axis=-1, mode="constant", cval=0.0)


def convolve_psf_error(error, sigma: float) -> np.ndarray:
    """Standard errors (..., W, H) of an image convolved with the PSF of ``sigma`` pixels
    (:func:`convolve_psf`): the variances convolved with the squared
    kernel, the pixels' errors independent."""
    from scipy.ndimage import convolve1d

    var = np.asarray(error, np.float64) ** 2
    if sigma == 0.0:
        return np.sqrt(var)
    w, h = var.shape[-2:]
    radius = int(min(math.ceil(8.0 * sigma) + 1, max(w, h)))
    k2 = psf_weights(2 * radius + 1, float(radius), sigma) ** 2
    out = convolve1d(var, k2, axis=-2, mode="constant", cval=0.0)
    return np.sqrt(convolve1d(out, k2, axis=-1, mode="constant", cval=0.0))
