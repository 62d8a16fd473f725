"""Milky Way dust optical properties per band, from Draine's (2003) tables.

Data: the carbonaceous-silicate grain models of Weingartner & Draine (2001, ApJ 548, 296) with
the abundances renormalised by Draine (2003, ARA&A 41, 241; ApJ 598, 1017) -- tables computed
by B. T. Draine (Princeton University, 2003) of albedo, <cos theta> (= the Henyey-Greenstein g)
and the extinction cross-section per H nucleon versus wavelength, for R_V = 3.1 (diffuse
interstellar medium), 4.0 and 5.5 (dense clouds, larger grains). They are read from the copies
shipped in the ``dust_extinction`` package (K. Gordon, JOSS 9, 7023, 2024; BSD-3-Clause),
``dust_extinction/data/kext_albedo_WD_MW_*_D03.dat``; its classes expose only the extinction,
so the files are parsed here.

Band averages (never point samples): on a 1 nm grid over the band [lo, hi], with the table
interpolated linearly,

    C_ext,b = mean C_ext,     albedo_b = mean(a C_ext) / mean(C_ext),
    g_b = mean(g a C_ext) / mean(a C_ext),

i.e. the band's extinction, its scattering over its extinction, and the scattering-weighted
mean cosine, for light spread evenly over the band.
"""

from __future__ import annotations

import functools
import importlib.util
from pathlib import Path

import numpy as np

from ..errors import SceneError

#: R_V -> file name in dust_extinction/data
DRAINE_FILES = {
    "3.1": "kext_albedo_WD_MW_3.1_60_D03.dat",
    "4.0": "kext_albedo_WD_MW_4.0A_40_D03.dat",
    "5.5": "kext_albedo_WD_MW_5.5A_30_D03.dat",
}

CITATION = (
    "Draine (2003, ARA&A 41, 241; ApJ 598, 1017) Milky Way dust, Weingartner & Draine (2001, "
    "ApJ 548, 296) grain models, tables kext_albedo_WD_MW_*_D03.dat as shipped in the "
    "dust_extinction package (Gordon 2024, JOSS 9, 7023)"
)


def _data_dir() -> Path:
    spec = importlib.util.find_spec("dust_extinction")  # locate without importing astropy
    if spec is None or not spec.submodule_search_locations:
        raise SceneError("bands.preset", "spectral", "needs the dust_extinction package "
                         "(pip install dust_extinction), which ships Draine's dust tables")
    return Path(list(spec.submodule_search_locations)[0]) / "data"


def _lines(rv: str) -> list[str]:
    if rv not in DRAINE_FILES:
        raise ValueError(f"rv must be one of {sorted(DRAINE_FILES)}, got {rv!r}")
    return (_data_dir() / DRAINE_FILES[rv]).read_text().splitlines()


@functools.lru_cache(maxsize=None)
def dust_mass_per_h(rv: str = "3.1") -> float:
    """Dust mass per H nucleon (g per H) of Draine's model ``rv``, as its table's header states
    it ("1.870E-26 = M_dust per H nucleon (gram/H) for this dust model" for R_V = 3.1; 1.969e-26
    for 4.0, 2.199e-26 for 5.5)."""
    for line in _lines(rv):
        if "M_dust per H nucleon" in line:
            return float(line.split("=")[0])
    raise ValueError(f"{DRAINE_FILES[rv]}: no 'M_dust per H nucleon' line in the header")


@functools.lru_cache(maxsize=None)
def v_filter_cext(rv: str = "3.1") -> float:
    """Extinction cross-section per H nucleon (cm^2 per H) of the row Draine's table marks
    "V filter" (0.547 um): 4.896e-22 cm^2 per H for R_V = 3.1, i.e. A_V / N_H = 1.0857 x that
    = 5.32e-22 mag cm^2 (Draine 2003, ARA&A 41, 241)."""
    for line in _lines(rv):
        if line.rstrip().endswith("V filter"):
            return float(line.split()[3])
    raise ValueError(f"{DRAINE_FILES[rv]}: no row marked 'V filter'")


@functools.lru_cache(maxsize=None)
def draine_table(rv: str = "3.1") -> dict:
    """Draine's table for ``rv`` ("3.1", "4.0" or "5.5") as arrays in ascending wavelength.

    Returns
    -------
    dict with ``wavelength_nm``, ``albedo``, ``g`` (<cos theta>), ``cext`` (cm^2 per H
    nucleon), float64 arrays.
    """
    lines = _lines(rv)
    start = next(i for i, line in enumerate(lines) if line.startswith("-----------")) + 1
    rows = []
    for line in lines[start:]:
        parts = line.split()
        if len(parts) < 4:
            if rows:
                break
            continue
        rows.append([float(x) for x in parts[:4]])
    a = np.array(rows)[::-1]  # the file runs from long to short wavelengths
    return {"wavelength_nm": a[:, 0] * 1e3, "albedo": a[:, 1], "g": a[:, 2], "cext": a[:, 3]}


def band_average(rv: str, lo_nm: float, hi_nm: float) -> tuple[float, float, float]:
    """(C_ext, albedo, g) of the dust averaged over the band [lo_nm, hi_nm] (module docstring)."""
    t = draine_table(rv)
    wl = np.arange(float(lo_nm), float(hi_nm) + 0.5, 1.0)
    cext = np.interp(wl, t["wavelength_nm"], t["cext"])
    alb = np.interp(wl, t["wavelength_nm"], t["albedo"])
    g = np.interp(wl, t["wavelength_nm"], t["g"])
    sca = alb * cext
    return float(cext.mean()), float(sca.mean() / cext.mean()), float((g * sca).mean() / sca.mean())


def cext_at(rv: str, wavelength_nm: float) -> float:
    """Extinction cross-section per H nucleon (cm^2 per H) at one wavelength, the table
    interpolated linearly in wavelength (as :func:`band_average` does)."""
    t = draine_table(rv)
    return float(np.interp(float(wavelength_nm), t["wavelength_nm"], t["cext"]))


def spectral_reference_cext(n: int, rv: str = "3.1", lo_nm: float = 380.0, hi_nm: float = 780.0) -> float:
    """The band-averaged extinction cross-section per H (cm^2 per H) of the reference band of
    :func:`spectral_band_properties` (the band holding 550 nm), the scale its relative
    extinctions are divided by: a band's extinction x this = its own band-averaged C_ext / H."""
    edges = np.linspace(lo_nm, hi_nm, n + 1)
    ref = int(np.searchsorted(edges, 550.0, side="right")) - 1
    return band_average(rv, edges[ref], edges[ref + 1])[0]


def spectral_band_properties(n: int, rv: str = "3.1", lo_nm: float = 380.0,
                             hi_nm: float = 780.0) -> list[tuple[float, float, float, float]]:
    """``n`` equal bands across [lo_nm, hi_nm] with Draine dust of ``rv``.

    Returns
    -------
    list of (centre nm, extinction, albedo, g), one per band from blue to red: the
    extinction is relative to the band holding 550 nm (V), which then has 1.0 and is the
    reference band. :mod:`nebula_rt.optics.bands` makes its ``Band`` records from these (this module
    knows nothing of bands, so the two do not import each other).
    """
    edges = np.linspace(lo_nm, hi_nm, n + 1)
    props = [band_average(rv, a, b) for a, b in zip(edges[:-1], edges[1:])]
    ref = int(np.searchsorted(edges, 550.0, side="right")) - 1
    c_ref = props[ref][0]
    return [(float(0.5 * (a + b)), cext / c_ref, alb, g)
            for (a, b), (cext, alb, g) in zip(zip(edges[:-1], edges[1:]), props)]
