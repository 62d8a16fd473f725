"""A tabulated Mueller matrix: the dust's scattering matrix read from a file
(``bands.polarization = "matrix"``, ``bands.grain_matrix``).

For grains whose matrix comes from elsewhere: a benchmark's published table (Pinte et al.
2009, A&A 498, 967, whose grains' matrix at 1 micron is a table of 180 angles), a T-matrix or
DDA code, or a laboratory measurement. The matrix is that of spheres or of a mirror-symmetric,
randomly oriented ensemble, four independent elements (Bohren & Huffman 1983, ch. 4 and 13):

    | S11 S12  0    0  |
    | S12 S11  0    0  |
    |  0   0  S33  S34 |
    |  0   0 -S34  S33 |

The file is text: comment lines start with ``#``, then one row per scattering angle, five
numbers: theta (degrees, increasing, from at most MAX_END_GAP_DEG to at least 180 minus it),
S11, S12, S33, S34. S11's unit is free (only its shape is used); S12 < 0 where scattered
unpolarized light is polarized perpendicular to the scattering plane (Bohren & Huffman's
sign: -S12 / S11 is the degree of linear polarization, positive for dipole scattering);
S34 with Bohren & Huffman's sign. The sign of S34 changes only the sign of circular
polarization (V): linear polarization takes S34 in pairs (S34 V and V itself made from S34 U),
so Q and U do not depend on it.

The kernel reads the table the Mie grains use (:func:`nebula_rt.optics.mie.kernel_table`),
on MIE's equal steps of a quarter degree: the file's elements are interpolated linearly in
theta between its rows, and where the file stops short of 0 or 180 degrees the ends are the
exact forward and backward matrices of such grains (S12 = S34 = 0, S33 = +-S11) with S11 flat
(an even function of theta has no slope there). The albedo and the extinction are the bands'
own; the asymmetry g is the table's (its piecewise-linear phase function's mean cosine).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Tuple

import numpy as np

from ..errors import SceneError
from ..input_files import MAX_TABLE_BYTES, read_input_text
from .mie import N_ANGLES, kernel_table, table_asymmetry

#: what bands.grain_matrix must be, for the refusals
MATRIX_FILE = "a text table of rows 'theta_deg S11 S12 S33 S34'"
#: the largest gap (degrees) between the file's first angle and 0, or its last and 180, that
#: the exact end matrices fill
MAX_END_GAP_DEG = 2.0
#: rows a file needs at least
MIN_ROWS = 10
#: rounding allowed in S12^2 + S33^2 + S34^2 <= S11^2 (a matrix that would polarize light
#: beyond 100 % is refused)
POLARIZATION_ROUNDING = 1e-3


@dataclass(frozen=True)
class MuellerTable:
    """The matrix elements of a file (see the module's doc), as read (tuples: hashable).

    Attributes
    ----------
    source : str
        Where it came from (the file's path), for messages.
    theta_deg : tuple of float
        Scattering angles, degrees, increasing.
    s11, s12, s33, s34 : tuple of float
        The elements at those angles.
    """

    source: str
    theta_deg: Tuple[float, ...]
    s11: Tuple[float, ...]
    s12: Tuple[float, ...]
    s33: Tuple[float, ...]
    s34: Tuple[float, ...]

    def __post_init__(self):
        t = np.asarray(self.theta_deg, np.float64)
        els = [np.asarray(getattr(self, k), np.float64) for k in ("s11", "s12", "s33", "s34")]

        def refuse(why):
            return SceneError("bands.grain_matrix", self.source, f"must be {MATRIX_FILE}: {why}")

        if t.ndim != 1 or any(e.shape != t.shape for e in els):
            raise refuse("every row needs five numbers")
        if t.size < MIN_ROWS:
            raise refuse(f"{t.size} rows, at least {MIN_ROWS} needed")
        if not (np.all(np.isfinite(t)) and all(np.all(np.isfinite(e)) for e in els)):
            row = int(np.flatnonzero(~np.isfinite(np.stack([t] + els)).all(axis=0))[0])
            raise refuse(f"row {row + 1} holds a value that is not a finite number")
        if np.any(np.diff(t) <= 0.0):
            row = int(np.flatnonzero(np.diff(t) <= 0.0)[0]) + 2
            raise refuse(f"the angles must increase (row {row}: {t[row - 1]:g} after {t[row - 2]:g} degrees)")
        if t[0] < 0.0 or t[0] > MAX_END_GAP_DEG or t[-1] > 180.0 or t[-1] < 180.0 - MAX_END_GAP_DEG:
            raise refuse(f"the angles run from {t[0]:g} to {t[-1]:g} degrees; they must start within "
                         f"[0, {MAX_END_GAP_DEG:g}] and end within [{180 - MAX_END_GAP_DEG:g}, 180] degrees")
        s11, s12, s33, s34 = els
        if np.any(s11 <= 0.0):
            row = int(np.flatnonzero(s11 <= 0.0)[0])
            raise refuse(f"S11 must be positive (row {row + 1}, {t[row]:g} degrees: {s11[row]:g})")
        excess = (s12 ** 2 + s33 ** 2 + s34 ** 2) / s11 ** 2 - 1.0
        if np.any(excess > POLARIZATION_ROUNDING):
            row = int(np.argmax(excess))
            raise refuse(f"S12^2 + S33^2 + S34^2 must not exceed S11^2 (row {row + 1}, {t[row]:g} degrees: "
                         f"{math.sqrt(1.0 + excess[row]):.4g} S11; the light would be polarized beyond 100 %)")

    def kernel_table(self, n_angles: int = N_ANGLES) -> np.ndarray:
        """(TABLE_ROWS, n_angles) float64: the kernel's table (:func:`nebula_rt.optics.mie.kernel_table`)
        on ``n_angles`` angles equal in theta from 0 to 180 degrees."""
        return _kernel_table(self, int(n_angles))

    @property
    def g(self) -> float:
        """The asymmetry parameter: the mean cosine of the phase function the kernel samples."""
        return table_asymmetry(self.kernel_table())

    @property
    def phase_max(self) -> float:
        """The largest S11 per steradian (normalised: its integral over the sphere is 1)."""
        return float(np.max(self.kernel_table()[2])) / (2.0 * math.pi)


@functools.lru_cache(maxsize=16)
def _kernel_table(m: MuellerTable, n_angles: int) -> np.ndarray:
    t = np.asarray(m.theta_deg, np.float64)
    s11, s12, s33, s34 = (np.asarray(getattr(m, k), np.float64) for k in ("s11", "s12", "s33", "s34"))
    if t[0] > 0.0:  # the exact forward matrix, S11 flat
        t, s11, s12, s33, s34 = (np.concatenate([[v], a]) for v, a in
                                 ((0.0, t), (s11[0], s11), (0.0, s12), (s11[0], s33), (0.0, s34)))
    if t[-1] < 180.0:  # the exact backward matrix
        t, s11, s12, s33, s34 = (np.concatenate([a, [v]]) for v, a in
                                 ((180.0, t), (s11[-1], s11), (0.0, s12), (-s11[-1], s33), (0.0, s34)))
    theta = np.linspace(0.0, 180.0, n_angles)
    mu = np.cos(np.radians(theta))
    mu[0], mu[-1] = 1.0, -1.0
    e11, e12, e33, e34 = (np.interp(theta, t, a) for a in (s11, s12, s33, s34))
    table = kernel_table(mu, e11, e12 / e11, e33 / e11, e34 / e11)
    table.setflags(write=False)
    return table


def parse_matrix(text: str, source: str) -> MuellerTable:
    """A :class:`MuellerTable` from a file's text (``source``: its name, for messages)."""
    rows = []
    for k, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        try:
            values = [float(x) for x in parts]
        except ValueError:
            raise SceneError("bands.grain_matrix", source, f"must be {MATRIX_FILE}: line {k} is not numbers "
                                                           f"({line[:60]!r})") from None
        if len(values) != 5:
            raise SceneError("bands.grain_matrix", source, f"must be {MATRIX_FILE}: line {k} holds {len(values)} "
                                                           "numbers, 5 needed")
        rows.append(values)
    a = np.asarray(rows, np.float64).reshape(-1, 5)
    return MuellerTable(source, *(tuple(float(x) for x in a[:, j]) for j in range(5)))


def read_matrix(path) -> MuellerTable:
    """The :class:`MuellerTable` of the file ``path`` (``bands.grain_matrix``)."""
    path = Path(path)
    return parse_matrix(read_input_text("bands.grain_matrix", path, MATRIX_FILE, max_bytes=MAX_TABLE_BYTES),
                        str(path))
