"""Published numbers about real reflection nebulae: their dust's albedo and g against
wavelength, and their illuminating stars; package data with their provenance.

Two tables ship with the package (``nebula_rt/data/``; each file's header names its sources,
commits, licences and how the numbers were copied, and every row names its paper):

- ``published_dust.csv``: the dust albedo and Henyey-Greenstein g derived for NGC 7023,
  NGC 2023, IC 435, the Pleiades, Upper Sco and the Orion reflection component, as compiled
  in Karl Gordon's DGFit repository (BSD-3-Clause; Gordon 2004, ASP Conf. Ser. 309, 77).
  These are **model fits with their own geometry**: each paper fitted its own radiative
  transfer model to its observations, so the values are plausibility bounds for a scene's
  dust, not truth. Most lie in the ultraviolet; only NGC 7023 (Witt et al. 1982) and IC 435
  (Calzetti et al. 1995) reach the visible.
- ``illuminating_stars.csv``: the illuminating stars' spectral type, V, E(B-V), R_V, T_eff
  and distance where a cited table gives them (Fitzpatrick & Massa 2007, ApJ 663, 320;
  Gordon et al. 2009, ApJ 705, 1320, through Karl Gordon's extinction_ensemble_props
  repository, BSD-3-Clause).

:func:`scene_star` turns a star's row into a scene's ``[[stars]]`` keys (the example scenes
``examples/scenes/ngc2023.toml`` and ``ngc7023.toml`` take their stars from it), and
:func:`beside` puts a scene's band albedo and g beside the published values (``nebula-rt
compare`` and ``fit`` print it and plot it).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from importlib import resources
from typing import Optional, Sequence

#: the package data files
DUST_FILE, STARS_FILE = "data/published_dust.csv", "data/illuminating_stars.csv"


@dataclass(frozen=True)
class PublishedDust:
    """One published determination: the dust's albedo and g of ``nebula`` at one wavelength
    (either may be None: not determined there), with their 1-sigma uncertainties."""

    nebula: str
    wavelength_nm: float
    albedo: Optional[float]
    albedo_unc: Optional[float]
    g: Optional[float]
    g_unc: Optional[float]
    reference: str
    note: str = ""


@dataclass(frozen=True)
class PublishedStar:
    """An illuminating star's published parameters (None where no cited table gives one).

    Attributes
    ----------
    star, nebula : str
        The star (HD number) and the nebula it lights.
    spectral_type : str
        As the table writes it (e.g. ``"B2Ve"``).
    v_mag : float
        Apparent Johnson V (mag, Vega system).
    e_bv, e_bv_unc, r_v, r_v_unc : float
        Colour excess E(B-V) (mag) and R_V = A_V / E(B-V) towards the star, with their
        1-sigma uncertainties.
    t_eff, t_eff_unc : float
        Effective temperature (K) of the star's model atmosphere fit.
    distance_pc : float
        Distance (pc).
    sources : dict
        The table each quantity was copied from, by quantity.
    """

    star: str
    nebula: str
    spectral_type: str
    v_mag: Optional[float]
    e_bv: Optional[float]
    e_bv_unc: Optional[float]
    r_v: Optional[float]
    r_v_unc: Optional[float]
    t_eff: Optional[float]
    t_eff_unc: Optional[float]
    distance_pc: Optional[float]
    sources: dict

    @property
    def a_v(self) -> Optional[float]:
        """A_V = R_V E(B-V) (mag), from the same table's R_V and E(B-V)."""
        return None if self.r_v is None or self.e_bv is None else self.r_v * self.e_bv


def _rows(name: str) -> list[dict]:
    text = resources.files("nebula_rt").joinpath(name).read_text(encoding="utf-8")
    body = "\n".join(line for line in text.splitlines() if not line.startswith("#"))
    return list(csv.DictReader(io.StringIO(body)))


def _number(text: str) -> Optional[float]:
    return float(text) if text.strip() else None


def dust(nebulae: Optional[Sequence[str]] = None) -> list[PublishedDust]:
    """The published albedo and g determinations (of ``nebulae`` only, if given), in the
    file's order."""
    out = []
    for r in _rows(DUST_FILE):
        if nebulae is not None and r["object"] not in nebulae:
            continue
        out.append(PublishedDust(r["object"], float(r["wavelength_nm"]), _number(r["albedo"]), _number(r["albedo_unc"]),
                                 _number(r["g"]), _number(r["g_unc"]), r["reference"], r.get("note") or ""))
    return out


def stars() -> dict[str, PublishedStar]:
    """The illuminating stars, by name (``"HD037903"``)."""
    out = {}
    for r in _rows(STARS_FILE):
        sources = {k[:-len("_source")]: v for k, v in r.items() if k.endswith("_source") and v}
        out[r["star"]] = PublishedStar(r["star"], r["nebula"], r["spectral_type"], _number(r["V"]), _number(r["E_BV"]),
                                       _number(r["E_BV_unc"]), _number(r["R_V"]), _number(r["R_V_unc"]),
                                       _number(r["T_eff_K"]), _number(r["T_eff_unc_K"]), _number(r["distance_pc"]),
                                       sources)
    return out


def scene_star(star: PublishedStar, ab_minus_vega_v: float) -> dict:
    """A scene's ``[[stars]]`` keys from a published star: ``temperature`` (its T_eff) and,
    where the distance, V, E(B-V) and R_V are known, ``absolute_magnitude``, the AB magnitude
    through Bessell V at 10 pc:

        M_V = V - R_V E(B-V) - 5 log10(d / 10 pc) + (m_AB - m_Vega)_V

    (``ab_minus_vega_v``: the V passband's AB - Vega offset; the published V is a Vega
    magnitude). Raises ValueError if the star has no T_eff."""
    if star.t_eff is None:
        raise ValueError(f"{star.star} has no published T_eff: give its temperature or spectral type")
    keys = {"temperature": star.t_eff}
    if None not in (star.v_mag, star.a_v, star.distance_pc):
        keys["absolute_magnitude"] = (star.v_mag - star.a_v - 5.0 * math.log10(star.distance_pc / 10.0)
                                      + ab_minus_vega_v)
    return keys


@dataclass(frozen=True)
class DustBeside:
    """A scene's band albedo and g beside the published values (:func:`beside`)."""

    bands: list  # [(name, wavelength_nm, albedo, g)]
    published: list  # [PublishedDust]

    def in_range(self) -> list[PublishedDust]:
        """The published values inside the scene's bands' wavelength range."""
        lo, hi = min(b[1] for b in self.bands), max(b[1] for b in self.bands)
        return [p for p in self.published if lo <= p.wavelength_nm <= hi]

    def to_dict(self) -> dict:
        return {"scene_bands": [{"band": n, "wavelength_nm": w, "albedo": a, "g": g} for n, w, a, g in self.bands],
                "published_in_band_range": [
                    {"nebula": p.nebula, "wavelength_nm": p.wavelength_nm, "albedo": p.albedo,
                     "albedo_unc": p.albedo_unc, "g": p.g, "g_unc": p.g_unc, "reference": p.reference}
                    for p in self.in_range()],
                "note": "published values are model fits with their own geometry: plausibility bounds, not truth "
                        "(nebula_rt.observe.published)"}


def beside(scene, nebulae: Optional[Sequence[str]] = None) -> DustBeside:
    """The scene's bands (name, wavelength nm, albedo, g) beside the published values (of
    ``nebulae`` only, if given)."""
    bands = [(b.name, float(b.wavelength), float(b.albedo), float(b.g)) for b in scene.bands.resolve()]
    return DustBeside(bands=bands, published=dust(nebulae))


def plot_beside(axes, dust_beside: DustBeside) -> None:
    """Draw albedo (``axes[0]``) and g (``axes[1]``) against wavelength: the scene's bands as
    a line, each nebula's published values with their 1-sigma errors."""
    import numpy as np
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    wl = np.array([b[1] for b in dust_beside.bands])
    order = np.argsort(wl)
    nebulae = list(dict.fromkeys(p.nebula for p in dust_beside.published))
    markers = "osD^v<>p*h"
    for ax, attr, label in ((axes[0], "albedo", "albedo"), (axes[1], "g", "g (Henyey-Greenstein)")):
        scene_values = np.array([b[2] if attr == "albedo" else b[3] for b in dust_beside.bands])
        ax.plot(wl[order], scene_values[order], "-", color="k", lw=2, label="this scene's bands", zorder=5)
        for j, name in enumerate(nebulae):
            rows = [p for p in dust_beside.published if p.nebula == name and getattr(p, attr) is not None]
            if not rows:
                continue
            ax.errorbar([p.wavelength_nm for p in rows], [getattr(p, attr) for p in rows],
                        yerr=[getattr(p, attr + "_unc") or 0.0 for p in rows], fmt=markers[j % len(markers)],
                        color=f"C{j}", ms=4, capsize=2, lw=0.8, label=name)
        ax.set_xscale("log")
        ax.set_xticks([100, 150, 200, 300, 400, 550, 750])
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("wavelength (nm)")
        ax.set_ylabel(label)
        ax.set_title(f"dust {attr}: published values are model fits (plausibility bounds, not truth)", fontsize=8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, ncol=2)
