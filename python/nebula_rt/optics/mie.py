"""Mie scattering by spherical grains with a size distribution: the dust's Mueller matrix,
albedo, asymmetry and extinction per band (``bands.polarization = "mie"``).

The Mie coefficients a_n, b_n come from miepython (S. Prahl; MIT; validated against Wiscombe's
MIEV0 and Bohren & Huffman's BHMIE test cases), in its pure-NumPy form (no JIT compiler
needed); the series over the angles is summed here as one matrix product per grain size
(tests/optics/test_mie.py holds it to miepython's own S1_S2). It was
chosen over PyMieScatt (unmaintained since 2018) and scattnlay (compiled, for layered spheres)
as the well-kept library that does exactly homogeneous spheres.

Grains: homogeneous spheres of one material, radii a from ``radius_min`` to ``radius_max``
(micron) with n(a) da proportional to a^-q da (``size_slope`` q; Mathis, Rumpl & Nordsieck
1977: q = 3.5 between 0.005 and 0.25 micron, the defaults), or one radius where the two are
equal. The refractive index m = n + i k is the material's (``"astronomical-silicate"``: Draine
2003, ApJ 598, 1017, as shipped in ``data/astrosilicate_draine2003.csv``; n and k interpolated
linearly in log wavelength), or the scene's own ``n`` and ``k`` (one value, or one per band).

Per band, at the band's wavelength lambda (vacuum; the grains in vacuum), with k = 2 pi / lambda
and the amplitudes S1, S2 of Bohren & Huffman (1983, ch. 3 and 4; m = n + i k):

    C_ext = < pi a^2 Q_ext >,     C_sca = < pi a^2 Q_sca >,     albedo = C_sca / C_ext,
    g = < pi a^2 Q_sca g_a > / C_sca,
    S11 = < |S1|^2 + |S2|^2 > / (2 k^2 C_sca),   S12 = < |S2|^2 - |S1|^2 > / (2 k^2 C_sca),
    S33 = < Re S1 S2* > / (k^2 C_sca),         S34 = < Im S2 S1* > / (k^2 C_sca),

the brackets the average over the size distribution (per grain), S11 per steradian (its
integral over the sphere is 1). miepython's amplitudes are those of m = n - i k (Wiscombe's
convention), the complex conjugates of Bohren & Huffman's, so S34 is formed from its S1 S2*.

The kernel's table (kernels/polarization.cl, NRT_POLAR_MIE) holds, on :func:`angles` scattering
angles 0-180 degrees in equal steps (a quarter degree, finer for grains beyond size parameter 50): mu = cos theta, the cumulative probability from mu = 1,
the probability density p(mu) = 2 pi S11, and S12 / S11, S33 / S11, S34 / S11. Between the
nodes everything is linear in mu; the phase function the kernel samples and peels off is that
piecewise-linear p, normalised to 1 exactly (its cumulative sums are exact trapezoids), so the
sampling, the peel-off and the energy agree to float32 rounding; the table's own error against
the exact Mie S11 is checked (tests/optics/test_mie.py).
"""

from __future__ import annotations

import functools
import math
import numbers
from dataclasses import dataclass
from importlib import resources
from typing import Optional, Sequence, Tuple, Union

import numpy as np

from ..errors import SceneError

#: scattering angles of the kernel's table: 0 to 180 degrees in steps of 0.25 degree, for grains
#: up to ANGLES_SIZE_PARAMETER; larger ones (a forward peak about 1 / x radian wide) get steps
#: that many times finer (angles(x_max))
N_ANGLES = 721
ANGLES_SIZE_PARAMETER = 50.0
#: rows of a band's table: mu, cumulative probability, p(mu) = 2 pi S11, S12/S11, S33/S11, S34/S11
TABLE_ROWS = 6
#: cells of a band's guide table after its rows (kernels/polarization.cl, NRT_MIE_GUIDE): entry
#: j is the last interval whose cumulative probability is at most j / GUIDE_CELLS, so a scattering
#: angle's binary search starts within a few intervals of its answer
GUIDE_CELLS = 64


def kernel_table(mu: np.ndarray, s11: np.ndarray, r12: np.ndarray, r33: np.ndarray, r34: np.ndarray) -> np.ndarray:
    """One band's kernel table (TABLE_ROWS, n) from a matrix on ``mu`` = cos theta (1 down to
    -1, nodes equal in theta): mu, the cumulative probability from mu = 1, p(mu) = 2 pi S11
    normalised so that the piecewise-linear p between the nodes integrates to 1 exactly (its
    cumulative sums are exact trapezoids), and S12 / S11, S33 / S11, S34 / S11. ``s11`` may be
    in any unit: only its shape is kept."""
    p = 2.0 * math.pi * np.asarray(s11, np.float64)
    steps = 0.5 * (p[1:] + p[:-1]) * (mu[:-1] - mu[1:])
    total = steps.sum()
    cdf = np.concatenate([[0.0], np.cumsum(steps) / total])
    cdf[-1] = 1.0
    return np.stack([mu, cdf, p / total, r12, r33, r34])


def table_asymmetry(table: np.ndarray) -> float:
    """The mean scattering cosine of a kernel table's piecewise-linear phase function (the one
    the kernel samples): per interval the exact integral of mu p(mu), p linear in mu."""
    mu, p = np.asarray(table[0], np.float64), np.asarray(table[2], np.float64)
    a, b, pa, pb = mu[1:], mu[:-1], p[1:], p[:-1]  # each interval from a up to b
    h = b - a
    # integral over [a, b] of mu (pa + (pb - pa)(mu - a) / h): h (a (pa + pb) / 2 + h (pa + 2 pb) / 6)
    return float(np.sum(h * (a * (pa + pb) / 2.0 + h * (pa + 2.0 * pb) / 6.0)))


def guide_table(cdf32: np.ndarray) -> np.ndarray:
    """(GUIDE_CELLS + 1,) float32: for j = 0..GUIDE_CELLS the largest interval i (0 .. n - 2)
    with cdf[i] <= j / GUIDE_CELLS, from the cumulative probabilities as the kernel reads them
    (float32)."""
    c = np.asarray(cdf32, np.float32).astype(np.float64)
    j = np.arange(GUIDE_CELLS + 1, dtype=np.float64) / GUIDE_CELLS
    i = np.searchsorted(c, j, side="right") - 1
    return np.clip(i, 0, c.size - 2).astype(np.float32)
#: the grain materials with shipped optical constants (name -> data file)
MATERIALS = {"astronomical-silicate": "astrosilicate_draine2003.csv"}
#: Mathis, Rumpl & Nordsieck (1977): radii 0.005-0.25 micron, n(a) ~ a^-3.5
DEFAULT_RADIUS_MIN_UM = 0.005
DEFAULT_RADIUS_MAX_UM = 0.25
DEFAULT_SIZE_SLOPE = 3.5
#: the radii allowed (micron): from molecules' size to millimetre grains
RADIUS_RANGE_UM = (1.0e-4, 1.0e3)
#: the largest size parameter 2 pi a / lambda traced: the table then resolves the forward peak
#: with steps of 0.0625 degree (2881 angles), about 9 across its 1 / x radian
MAX_SIZE_PARAMETER = 200.0
#: the size distribution's exponents allowed
SIZE_SLOPE_RANGE = (-10.0, 10.0)
#: the refractive index's allowed parts
N_RANGE = (0.01, 100.0)
K_RANGE = (0.0, 100.0)
#: size-distribution nodes per unit of ln a: enough for the resonances of the largest grains
NODES_PER_E_FOLD = 32
NODES_PER_SIZE_PARAMETER = 12
MAX_SIZE_NODES = 4000

Number = Union[float, Sequence[float]]


def _check_number(param: str, value, lo: float, hi: float, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(float(value)) \
            or not lo <= float(value) <= hi:
        raise SceneError(param, value, f"must be {what} in [{lo:g}, {hi:g}]")
    return float(value)


@dataclass(frozen=True)
class Grains:
    """Spherical dust grains: their material and size distribution.

    Parameters
    ----------
    material : str
        A key of :data:`MATERIALS` whose optical constants give m = n + i k at each band's
        wavelength; unused where ``n`` and ``k`` are given.
    n, k : float or sequence of float, optional
        The real and imaginary parts of the refractive index (k >= 0: absorbing), one value for
        every band or one per band; both or neither.
    radius_min, radius_max : float
        The smallest and largest grain radius, micron; equal for grains of one size.
    size_slope : float
        q of the size distribution n(a) ~ a^-q.
    """

    material: str = "astronomical-silicate"
    n: Optional[Number] = None
    k: Optional[Number] = None
    radius_min: float = DEFAULT_RADIUS_MIN_UM
    radius_max: float = DEFAULT_RADIUS_MAX_UM
    size_slope: float = DEFAULT_SIZE_SLOPE

    def __post_init__(self):
        if self.material not in MATERIALS:
            raise SceneError("bands.grain_material", self.material,
                             f"must be one of {', '.join(map(repr, MATERIALS))}")
        if (self.n is None) != (self.k is None):
            given, missing = ("n", "k") if self.k is None else ("k", "n")
            raise SceneError(f"bands.grain_{given}", getattr(self, given), f"must be given with bands.grain_{missing} "
                             "(the refractive index n + i k), or neither (the material's optical constants)")
        for key, rng in (("n", N_RANGE), ("k", K_RANGE)):
            v = getattr(self, key)
            if v is None:
                continue
            one = isinstance(v, numbers.Real) and not isinstance(v, bool)
            vals = [v] if one else v
            if isinstance(vals, (str, bytes)) or not isinstance(vals, Sequence) or len(vals) == 0:
                raise SceneError(f"bands.grain_{key}", v, f"must be a number in [{rng[0]:g}, {rng[1]:g}] "
                                 "or a list of them, one per band")
            checked = tuple(_check_number(f"bands.grain_{key}", x, *rng, "a number (or a list of numbers)")
                            for x in vals)
            object.__setattr__(self, key, checked[0] if one else checked)
        lo = _check_number("bands.grain_radius_min", self.radius_min, *RADIUS_RANGE_UM, "a radius in micron")
        hi = _check_number("bands.grain_radius_max", self.radius_max, *RADIUS_RANGE_UM, "a radius in micron")
        if hi < lo:
            raise SceneError("bands.grain_radius_max", self.radius_max,
                             f"must be at least bands.grain_radius_min ({lo:g} micron)")
        _check_number("bands.grain_size_slope", self.size_slope, *SIZE_SLOPE_RANGE, "the exponent q of n(a) ~ a^-q")

    def refractive_index(self, wavelengths_nm: Sequence[float]) -> np.ndarray:
        """(n_bands,) complex m = n + i k at the bands' wavelengths (nm)."""
        wl = np.asarray(wavelengths_nm, np.float64)
        if self.n is not None:
            return _per_band("grain_n", self.n, wl.size) + 1j * _per_band("grain_k", self.k, wl.size)
        table = material_table(self.material)
        um = wl * 1e-3
        lo, hi = table[0, 0], table[-1, 0]
        bad = (um < lo) | (um > hi)
        if np.any(bad):
            raise SceneError("bands.grain_material", self.material,
                             f"has optical constants from {lo * 1e3:g} to {hi * 1e3:g} nm, not at "
                             f"{float(wl[bad][0]):g} nm (give bands.grain_n and bands.grain_k)")
        x = np.log(table[:, 0])
        return np.interp(np.log(um), x, table[:, 1]) + 1j * np.interp(np.log(um), x, table[:, 2])

    def radii(self, x_max: float) -> Tuple[np.ndarray, np.ndarray]:
        """The size distribution's quadrature: radii (micron) and weights summing to 1 (composite
        Gauss-Legendre in ln a, 8 nodes per panel, on n(a) a d ln a), fine enough for size
        parameters up to x_max."""
        lo, hi = float(self.radius_min), float(self.radius_max)
        if hi <= lo * (1.0 + 1e-12):
            return np.array([lo]), np.array([1.0])
        span = math.log(hi / lo)
        nodes = min(MAX_SIZE_NODES, max(32, math.ceil(span * max(NODES_PER_E_FOLD, NODES_PER_SIZE_PARAMETER * x_max))))
        panels = -(-nodes // 8)
        xg, wg = np.polynomial.legendre.leggauss(8)
        edges = np.linspace(math.log(lo), math.log(hi), panels + 1)
        half = 0.5 * np.diff(edges)
        ln_a = ((edges[:-1] + half)[:, None] + half[:, None] * xg[None, :]).ravel()
        a = np.exp(ln_a)
        w = (half[:, None] * wg[None, :]).ravel() * a ** (1.0 - float(self.size_slope))
        return a, w / w.sum()


def _per_band(key: str, value: Number, n_bands: int) -> np.ndarray:
    if isinstance(value, tuple):
        if len(value) != n_bands:
            raise SceneError(f"bands.{key}", list(value), f"must hold one value per band ({n_bands}), or be one number")
        return np.asarray(value, np.float64)
    return np.full(n_bands, float(value))


def _material_text(material: str) -> str:
    return resources.files("nebula_rt").joinpath("data", MATERIALS[material]).read_text()


@functools.lru_cache(maxsize=None)
def material_table(material: str) -> np.ndarray:
    """(rows, 3): wavelength (micron), n, k of a material of :data:`MATERIALS`."""
    text = _material_text(material)
    rows = [ln.split(",") for ln in text.splitlines() if ln and not ln.startswith("#")][1:]
    return np.asarray(rows, np.float64)


@functools.lru_cache(maxsize=None)
def material_density(material: str) -> float:
    """The bulk density of a material of :data:`MATERIALS`, g cm^-3 (its data file's
    ``bulk_density_g_cm3`` line)."""
    for line in _material_text(material).splitlines():
        if line.startswith("# bulk_density_g_cm3"):
            return float(line.split("=")[1])
    raise ValueError(f"{MATERIALS[material]}: no bulk_density_g_cm3 line")


#: the wavelength (nm) of A_V for dust.visual_extinction: the V filter row of Draine's tables
#: (0.547 micron), as the Draine-model conversion takes it
V_WAVELENGTH_NM = 547.0


def mie_cext_cm2(grains: Grains, wavelengths_nm: Sequence[float]) -> np.ndarray:
    """The grains' extinction cross-section per grain (cm^2) at the wavelengths (nm)."""
    return np.asarray(mie_optics(grains, wavelengths_nm).c_ext) * 1e-8


def grain_mass_g(grains: Grains, wavelengths_nm: Sequence[float]) -> float:
    """The mean mass of a grain (g): the material's bulk density times the mean volume."""
    return material_density(grains.material) * mie_optics(grains, wavelengths_nm).grain_volume * 1e-12


@dataclass(frozen=True)
class MieOptics:
    """The grains' optics per band (:func:`mie_optics`).

    Attributes
    ----------
    albedo, g : ndarray, shape (n_bands,)
        C_sca / C_ext and the mean scattering cosine.
    c_ext, c_sca : ndarray, shape (n_bands,)
        Cross-sections per grain, micron^2.
    grain_volume : float
        The mean volume of a grain, micron^3.
    table : ndarray, shape (n_bands, TABLE_ROWS, angles)
        The kernel's tables (module comment).
    """

    albedo: np.ndarray
    g: np.ndarray
    c_ext: np.ndarray
    c_sca: np.ndarray
    grain_volume: float
    table: np.ndarray


def _pi_tau(mu: np.ndarray, n_terms: int):
    """pi_n(mu) and tau_n(mu), n = 1..n_terms, (n_terms, mu.size): the angular functions of the
    Mie series by their upward recurrences (Bohren & Huffman 4.47), the same for every size."""
    pi = np.zeros((n_terms, mu.size))
    tau = np.zeros((n_terms, mu.size))
    pi[0] = 1.0
    before = np.zeros(mu.size)
    for n in range(1, n_terms):
        tau[n - 1] = n * mu * pi[n - 1] - (n + 1) * before
        pi[n] = ((2 * n + 1) * mu * pi[n - 1] - (n + 1) * before) / n
        before = pi[n - 1]
    tau[n_terms - 1] = n_terms * mu * pi[n_terms - 1] - (n_terms + 1) * before
    return pi, tau


def _amplitudes(an, bn, pi_n, tau_n):
    """S1 and S2 (miepython's convention and normalisation, as its S1_S2 with norm "wiscombe")
    from miepython's coefficients a_n, b_n: the series sum (2n+1)/(n(n+1)) (a_n pi_n + b_n tau_n)
    as one matrix product for all angles (miepython sums angle by angle in Python)."""
    n = np.arange(1, len(an) + 1)
    scale = (2 * n + 1) / (n * (n + 1.0))
    sa, sb = scale * an, scale * bn
    p, t = pi_n[:len(an)], tau_n[:len(an)]
    return np.conj(sa @ p + sb @ t), np.conj(sa @ t + sb @ p)


def angles(x_max: float) -> int:
    """The table's scattering angles for grains up to size parameter ``x_max``: N_ANGLES, with
    steps ceil(x_max / ANGLES_SIZE_PARAMETER) times finer beyond ANGLES_SIZE_PARAMETER."""
    return 1 + (N_ANGLES - 1) * max(1, math.ceil(x_max / ANGLES_SIZE_PARAMETER))


def _size_parameter(grains: Grains, wavelength_nm: float) -> float:
    x_max = 2.0 * math.pi * grains.radius_max / (wavelength_nm * 1e-3)
    if x_max > MAX_SIZE_PARAMETER:
        raise SceneError("bands.grain_radius_max", grains.radius_max,
                         f"gives the size parameter 2 pi a / lambda = {x_max:.4g} at {wavelength_nm:g} nm; "
                         f"at most {MAX_SIZE_PARAMETER:g} is traced (the table's angles resolve the forward "
                         "peak up to there)")
    return x_max


def _band_optics(m: complex, wavelength_nm: float, grains: Grains, mu: np.ndarray):
    import miepython

    lam = wavelength_nm * 1e-3  # micron
    k = 2.0 * math.pi / lam
    x_max = _size_parameter(grains, wavelength_nm)
    a, w = grains.radii(x_max)
    m_mp = complex(m.real, -m.imag)  # miepython: m = n - i k
    qext, qsca, _, g_a = (np.atleast_1d(np.asarray(v, np.float64)) for v in miepython.efficiencies_mx(m_mp, k * a))
    geo = math.pi * a * a
    c_ext = float(np.sum(w * geo * qext))
    c_sca = float(np.sum(w * geo * qsca))
    if not c_sca > 0.0 or not math.isfinite(c_ext):  # m = 1: the grains are the vacuum around them
        raise SceneError("bands.grain_n", grains.n if grains.n is not None else grains.material,
                         f"gives grains that scatter nothing at {wavelength_nm:g} nm (m = {m.real:g} + "
                         f"{m.imag:g} i): the refractive index must differ from 1")
    g = float(np.sum(w * geo * qsca * g_a)) / c_sca
    s11 = np.zeros(mu.size)
    s12 = np.zeros(mu.size)
    s33 = np.zeros(mu.size)
    s34 = np.zeros(mu.size)
    coefficients = [miepython.coefficients(m_mp, k * aj) for aj in a]
    pi_n, tau_n = _pi_tau(mu, max(len(c[0]) for c in coefficients))
    for (an, bn), wj in zip(coefficients, w):
        s1, s2 = _amplitudes(an, bn, pi_n, tau_n)
        a1, a2 = np.abs(s1) ** 2, np.abs(s2) ** 2
        c = s1 * np.conj(s2)
        s11 += wj * 0.5 * (a1 + a2)
        s12 += wj * 0.5 * (a2 - a1)
        s33 += wj * c.real
        s34 += wj * c.imag  # Im S1 S2* of m = n - i k is Im S2 S1* of Bohren & Huffman's amplitudes
    norm = 1.0 / (k * k * c_sca)
    return c_ext, c_sca, g, s11 * norm, s12 / s11, s33 / s11, s34 / s11


@functools.lru_cache(maxsize=64)
def _mie_optics(grains: Grains, wavelengths_nm: Tuple[float, ...]) -> MieOptics:
    m = grains.refractive_index(wavelengths_nm)
    n_angles = angles(max(_size_parameter(grains, wl) for wl in wavelengths_nm))
    theta = np.linspace(0.0, math.pi, n_angles)
    mu = np.cos(theta)
    mu[0], mu[-1] = 1.0, -1.0
    nb = len(wavelengths_nm)
    albedo, g, c_ext, c_sca = (np.zeros(nb) for _ in range(4))
    table = np.zeros((nb, TABLE_ROWS, n_angles))
    for b, (mb, wl) in enumerate(zip(m, wavelengths_nm)):
        c_ext[b], c_sca[b], g[b], s11, r12, r33, r34 = _band_optics(complex(mb), float(wl), grains, mu)
        albedo[b] = c_sca[b] / c_ext[b]
        table[b] = kernel_table(mu, s11, r12, r33, r34)
    a, w = grains.radii(2.0 * math.pi * grains.radius_max / (min(wavelengths_nm) * 1e-3))
    volume = float(np.sum(w * 4.0 / 3.0 * math.pi * a ** 3))
    for arr in (albedo, g, c_ext, c_sca, table):
        arr.setflags(write=False)
    return MieOptics(albedo, g, c_ext, c_sca, volume, table)


def mie_optics(grains: Grains, wavelengths_nm: Sequence[float]) -> MieOptics:
    """The grains' albedo, g, cross-sections and kernel tables at the bands' wavelengths (nm);
    computed once per grains and wavelengths in a process (cached)."""
    return _mie_optics(grains, tuple(float(w) for w in wavelengths_nm))


#: explicit bands of Mie grains take the band nearest this wavelength (nm) as the reference
#: band, as the presets do (the band holding 550 nm)
REFERENCE_WAVELENGTH_NM = 550.0


def mie_bands(bands, grains: Grains, reference: Optional[int] = None):
    """The bands with the grains' albedo, g and extinction: C_ext relative to the reference
    band's, which stays the reference (``reference``, else
    :func:`nebula_rt.optics.bands.reference_band_index` of the bands as given)."""
    from dataclasses import replace

    from .bands import reference_band_index

    optics = mie_optics(grains, [b.wavelength for b in bands])
    ref = reference_band_index(bands) if reference is None else int(reference)
    rel = optics.c_ext / optics.c_ext[ref]
    return [replace(b, albedo=float(optics.albedo[i]), g=float(optics.g[i]), extinction=float(rel[i]))
            for i, b in enumerate(bands)]
