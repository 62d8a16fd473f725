"""Polarized scattering: which Mueller matrix the dust has, per band.

A scene that asks for polarization (``bands.polarization``) has its packets carry a Stokes
vector and scatter by the matrix of the kind chosen (kernels/polarization.cl):

- ``"rayleigh"``: dipole scattering, the phase function 3 (1 + cos^2 theta) / (16 pi) and the
  polarization sin^2 theta / (1 + cos^2 theta) of unpolarized light (the bands' g plays no
  part);
- ``"white"``: the bands' Henyey-Greenstein phase function with White's (1979, ApJ 229, 954)
  approximation of the linear polarization, -S12 / S11 = p_l sin^2 theta / (1 + cos^2 theta),
  p_l (``bands.peak_polarization``) the polarization at 90 degrees.

``"none"`` (the default) traces intensity alone, exactly as without this module.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence, Union

import numpy as np

from ..errors import SceneError

#: bands.polarization: the kinds of polarized scattering, and the kernel's number of each
#: (kernels/polarization.cl, NRT_POLAR)
KINDS = ("none", "rayleigh", "white")
KERNEL_KIND = {"none": 0, "rayleigh": 1, "white": 2}
#: the peak linear polarization p_l (White's approximation) where the scene gives none
DEFAULT_PEAK = 0.5
#: kinds whose phase function is not the bands' Henyey-Greenstein one
OWN_PHASE_FUNCTION = ("rayleigh",)
#: 4 floats per band of the kernel's polarization parameters (after the bands' optics)
PARAMS_PER_BAND = 4


@dataclass(frozen=True)
class Polarization:
    """The dust's polarized scattering.

    Parameters
    ----------
    kind : str
        One of :data:`KINDS`.
    peak : float or sequence of float
        ``"white"``: p_l, the linear polarization of unpolarized light scattered through 90
        degrees, in [0, 1]: one value for every band or one per band.
    """

    kind: str = "none"
    peak: Union[float, Sequence[float]] = DEFAULT_PEAK

    def __post_init__(self):
        if self.kind not in KINDS:
            raise SceneError("bands.polarization", self.kind, f"must be one of {', '.join(map(repr, KINDS))}")
        peaks = np.atleast_1d(np.asarray(self.peak, dtype=object))
        for p in peaks:
            ok = isinstance(p, (int, float, np.floating, np.integer)) and not isinstance(p, bool) \
                and math.isfinite(float(p)) and 0.0 <= float(p) <= 1.0
            if not ok:
                raise SceneError("bands.peak_polarization", self.peak,
                                 "must be a number in [0, 1] or a list of them, one per band")
        if not isinstance(self.peak, (int, float)):
            object.__setattr__(self, "peak", tuple(float(p) for p in peaks))

    @property
    def enabled(self) -> bool:
        """Whether packets carry a Stokes vector."""
        return self.kind != "none"

    @property
    def kernel_kind(self) -> int:
        """The transport kernel's NRT_POLAR."""
        return KERNEL_KIND[self.kind]

    def peaks(self, n_bands: int) -> np.ndarray:
        """(n_bands,) p_l per band; a list of another length is refused by name."""
        if isinstance(self.peak, tuple):
            if len(self.peak) != n_bands:
                raise SceneError("bands.peak_polarization", list(self.peak),
                                 f"must hold one value per band ({n_bands}), or be one number")
            return np.asarray(self.peak, np.float64)
        return np.full(n_bands, float(self.peak))

    def kernel_params(self, n_bands: int) -> np.ndarray:
        """(n_bands, PARAMS_PER_BAND) float32: what kernels/polarization.cl reads per band."""
        out = np.zeros((n_bands, PARAMS_PER_BAND), np.float32)
        if self.kind == "white":
            out[:, 0] = self.peaks(n_bands)
        return out


NONE = Polarization()


def polarization_of(scene) -> Polarization:
    """The scene's :class:`Polarization` (``bands.polarization``, ``bands.peak_polarization``)."""
    b = scene.bands
    return Polarization(kind=getattr(b, "polarization", "none") or "none",
                        peak=DEFAULT_PEAK if getattr(b, "peak_polarization", None) is None else b.peak_polarization)
