"""Polarized scattering: which Mueller matrix the dust has, per band.

A scene that asks for polarization (``bands.polarization``) has its packets carry a Stokes
vector and scatter by the matrix of the kind chosen (kernels/polarization.cl):

- ``"rayleigh"``: dipole scattering, the phase function 3 (1 + cos^2 theta) / (16 pi) and the
  polarization sin^2 theta / (1 + cos^2 theta) of unpolarized light (the bands' g plays no
  part);
- ``"white"``: the bands' Henyey-Greenstein phase function with White's (1979, ApJ 229, 954)
  approximation of the linear polarization, -S12 / S11 = p_l sin^2 theta / (1 + cos^2 theta),
  p_l (``bands.peak_polarization``) the polarization at 90 degrees;
- ``"mie"``: spherical grains (``bands.grain_*``: :class:`nebula_rt.optics.mie.Grains`), their
  full matrix from Mie theory per band, circular polarization (V) included; the bands' albedo,
  g and extinction are then the grains' (:func:`nebula_rt.optics.mie.mie_bands`);
- ``"matrix"``: a tabulated matrix (``bands.grain_matrix``:
  :class:`nebula_rt.optics.mueller_table.MuellerTable`) in every band, traced as Mie's tables
  are; the bands' albedo and extinction are their own, g the table's.

``"none"`` (the default) traces intensity alone, exactly as without this module.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Union

import numpy as np

from ..errors import SceneError
from .mie import GUIDE_CELLS, Grains, TABLE_ROWS, guide_table, mie_optics
from .mueller_table import MuellerTable

#: bands.polarization: the kinds of polarized scattering, and the kernel's number of each
#: (kernels/polarization.cl, NRT_POLAR)
KINDS = ("none", "rayleigh", "white", "mie", "matrix")
#: (a tabulated matrix is traced by the Mie tables' code)
KERNEL_KIND = {"none": 0, "rayleigh": 1, "white": 2, "mie": 3, "matrix": 3}
#: the peak linear polarization p_l (White's approximation) where the scene gives none
DEFAULT_PEAK = 0.5
#: kinds whose phase function is not the bands' Henyey-Greenstein one
OWN_PHASE_FUNCTION = ("rayleigh", "mie", "matrix")
#: kinds whose albedo, g and extinction are the grains' (not the bands' own)
OWN_OPTICS = ("mie",)
#: kinds whose matrix has S34 != 0, so that light becomes circularly polarized (Stokes V)
CIRCULAR = ("mie", "matrix")
#: kinds whose kernel parameters are a table per band (kernels/polarization.cl, NRT_POLAR_MIE)
TABULATED = ("mie", "matrix")
#: 4 floats per band of the kernel's polarization parameters (after the bands' optics); the
#: Mie tables follow them
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
    grains : nebula_rt.optics.mie.Grains, optional
        ``"mie"``: the grains (default: astronomical silicate with the MRN size distribution).
    matrix : nebula_rt.optics.mueller_table.MuellerTable, optional
        ``"matrix"``: the tabulated matrix (required).
    """

    kind: str = "none"
    peak: Union[float, Sequence[float]] = DEFAULT_PEAK
    grains: Optional[Grains] = None
    matrix: Optional[MuellerTable] = None

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
        if self.kind == "mie" and self.grains is None:
            object.__setattr__(self, "grains", Grains())
        if (self.kind == "matrix") != (self.matrix is not None):
            raise SceneError("bands.grain_matrix", None if self.matrix is None else self.matrix.source,
                             "is needed with bands.polarization = 'matrix', and taken with it alone")

    @property
    def enabled(self) -> bool:
        """Whether packets carry a Stokes vector."""
        return self.kind != "none"

    @property
    def stokes(self) -> int:
        """Stokes components the peel-off images carry besides I: Q and U, and V where the
        matrix makes light circularly polarized (:data:`CIRCULAR`); 0 without polarization."""
        return 0 if not self.enabled else 3 if self.kind in CIRCULAR else 2

    def phase_max(self, wavelengths_nm: Optional[Sequence[float]] = None) -> Optional[float]:
        """The largest S11 (per sr) of a kind with its own phase function (:data:`OWN_PHASE_FUNCTION`:
        Rayleigh's 3 / (8 pi), the largest of Mie's tables at the bands' wavelengths, nm); None
        for the bands' Henyey-Greenstein one."""
        if self.kind == "rayleigh":
            return 3.0 / (8.0 * math.pi)
        if self.kind == "mie":
            table = mie_optics(self.grains, wavelengths_nm).table
            return float(np.max(table[:, 2])) / (2.0 * math.pi)
        if self.kind == "matrix":
            return self.matrix.phase_max
        return None

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

    def kernel_params(self, n_bands: int, wavelengths_nm: Optional[Sequence[float]] = None) -> np.ndarray:
        """Flat float32: what kernels/polarization.cl reads, PARAMS_PER_BAND floats per band,
        then (``"mie"``: the bands' wavelengths in nm needed) each band's table of
        TABLE_ROWS x angles floats and its guide table (GUIDE_CELLS + 1 floats). A Mie band's pol[0] is the distance in floats from its
        parameters to its table, pol[1] the table's angles. ``"matrix"``: the same, every band
        the file's table."""
        params = np.zeros((n_bands, PARAMS_PER_BAND), np.float32)
        if self.kind == "white":
            params[:, 0] = self.peaks(n_bands)
        if self.kind not in TABULATED:
            return params.reshape(-1)
        if self.kind == "matrix":
            table = np.repeat(np.asarray(self.matrix.kernel_table(), np.float32)[None], n_bands, axis=0)
        elif wavelengths_nm is None or len(wavelengths_nm) != n_bands:
            raise ValueError("polarization 'mie' needs the bands' wavelengths")
        else:
            table = np.asarray(mie_optics(self.grains, wavelengths_nm).table, np.float32)
        n_angles = table.shape[-1]
        size = TABLE_ROWS * n_angles + GUIDE_CELLS + 1
        b = np.arange(n_bands)
        params[:, 0] = PARAMS_PER_BAND * n_bands + size * b - PARAMS_PER_BAND * b
        params[:, 1] = n_angles
        tables = [np.concatenate([band.reshape(-1), guide_table(band[1])]) for band in table]
        return np.concatenate([params.reshape(-1)] + tables)

NONE = Polarization()


def grains_of(bands_config) -> Grains:
    """The grains of a scene's ``[bands]`` (``bands.grain_*``)."""
    b = bands_config
    return Grains(material=b.grain_material, n=b.grain_n, k=b.grain_k, radius_min=b.grain_radius_min,
                  radius_max=b.grain_radius_max, size_slope=b.grain_size_slope)


def polarization_of(scene) -> Polarization:
    """The scene's :class:`Polarization` (``bands.polarization``, ``bands.peak_polarization``,
    ``bands.grain_*``, ``bands.grain_matrix``)."""
    b = scene.bands
    kind = getattr(b, "polarization", "none") or "none"
    return Polarization(kind=kind,
                        peak=DEFAULT_PEAK if getattr(b, "peak_polarization", None) is None else b.peak_polarization,
                        grains=grains_of(b) if kind == "mie" else None,
                        matrix=b.mueller_table() if kind == "matrix" else None)
