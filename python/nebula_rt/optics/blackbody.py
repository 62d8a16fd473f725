"""The blackbody: one Planck law for the stars' colours and their luminosities.

Both uses evaluate colour-science's ``planck_law`` (CIE 015), with two sets of constants:

- colorimetry (:func:`nebula_rt.optics.colour_convert.star_spectrum`, the stars' relative
  spectra behind the band luminosity fractions and the sRGB colours) uses CIE 015's
  ``c2 = 1.4388e-2 m K``, the value of the International Temperature Scale on which a
  colour temperature is defined, as colour-science's illuminants do;
- photometry (:mod:`nebula_rt.scene.units`: a star's luminosity inside the bands, its
  absolute magnitude, the calibrated sky's spectra) uses the exact 2019 SI constants, so that
  the law integrates to sigma T^4 / pi with :func:`stefan_boltzmann` (the rounded c2 moves the
  total by 6e-5); ratios of one star's light, which is all colorimetry takes, differ by 1e-5.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.constants import Boltzmann, Stefan_Boltzmann, c, h

#: the exact 2019 SI radiation constants: c1 = 2 pi h c^2 (W m^2), c2 = h c / k (m K)
SI_C1 = 2.0 * math.pi * h * c * c
SI_C2 = h * c / Boltzmann


def planck_lambda(wavelength_m, temperature: float, *, colorimetry: bool = False) -> np.ndarray:
    """Planck's B_lambda = 2 h c^2 / lambda^5 / (exp(h c / (lambda k T)) - 1).

    Parameters
    ----------
    wavelength_m : array_like
        Wavelengths (m, > 0), any shape.
    temperature : float
        Temperature (K).
    colorimetry : bool
        CIE 015's constants (c2 = 1.4388e-2 m K) instead of the exact SI ones.

    Returns
    -------
    ndarray, the shape of ``wavelength_m``
        Spectral radiance, W m^-2 sr^-1 m^-1 (0 where exp overflows: far Wien tail).
    """
    # imported here: colour-science's package import takes about 1.5 s (it loads matplotlib
    # for its plotting), which every command's start-up and every scene would pay
    import colour

    wl = np.asarray(wavelength_m, np.float64)
    constants = {} if colorimetry else {"c1": SI_C1, "c2": SI_C2}
    with np.errstate(over="ignore"):  # (the Wien tail: exp overflows, B -> 0)
        b = colour.colorimetry.planck_law(wl, float(temperature), **constants)
    return np.asarray(b, np.float64).reshape(wl.shape)  # (planck_law ravels and squeezes)


def stefan_boltzmann() -> float:
    """sigma, W m^-2 K^-4 (``scipy.constants``: exact in the 2019 SI)."""
    return float(Stefan_Boltzmann)
