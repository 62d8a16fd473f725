"""The parameters a fit may free (``free``, parsed from ``name=lo:hi[:log]``; see
:mod:`nebula_rt.observe.fit`): their bounds, their values in a scene, and the scene with new
values; each maps its bounds onto [0, 1] (linearly or in log) for the optimiser."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..errors import SceneError
from ..optics.bands import ALBEDO_RANGE, G_RANGE
from ..scene.model import Scene
from ..scene.units import DUST_KEYS

SPECIAL = ("albedo", "g", "albedo_slope", "g_slope", "tau", "depth")
#: Default bounds of the parameters that have them.
#: g >= 0: interstellar dust scatters forwards in the optical (Draine 2003: g 0.4-0.7 from 380 to
#: 780 nm); allowing g < 0 opens a second minimum (back-scattering from the dust behind the star
#: can mimic forward scattering from the dust in front), so ask for it explicitly (g=-0.5:0.95).
DEFAULT_BOUNDS = {"albedo": (0.02, 0.98), "g": (0.0, 0.95), "albedo_slope": (-0.2, 0.2), "g_slope": (-0.2, 0.2)}
#: Wavelength (nm) at which a linear albedo(lambda) or g(lambda) takes its base value, and the
#: span (nm) its slope is given per.
PIVOT_NM, SLOPE_NM = 550.0, 100.0
#: The values the bounds of a band parameter may take: a band's albedo and g (their declared
#: ranges, nebula_rt.optics.bands), and their slopes per SLOPE_NM at most the whole range of the
#: value (a steeper slope takes it from one end to the other within 100 nm of the pivot, and
#: every band farther out is clipped to an end: a slope that fits nothing).
RANGES = {"albedo": ALBEDO_RANGE, "g": G_RANGE,
          "albedo_slope": (ALBEDO_RANGE[0] - ALBEDO_RANGE[1], ALBEDO_RANGE[1] - ALBEDO_RANGE[0]),
          "g_slope": (G_RANGE[0] - G_RANGE[1], G_RANGE[1] - G_RANGE[0])}

#: The star keeps at least this far from the box's faces when its depth is free (box units).
DEPTH_MARGIN = 0.01


@dataclass(frozen=True)
class FreeParameter:
    """A parameter of the fit.

    Parameters
    ----------
    name : str
        See the module's doc (``albedo``, ``g``, ``tau``, ``depth``, ``albedo.NAME``, a scene key).
    lo, hi : float
        Bounds (the optimiser stays inside).
    log : bool
        Search (and, for MCMC, a flat prior) in log(value); needs lo > 0.
    """

    name: str
    lo: float
    hi: float
    log: bool = False

    def to_unit(self, value: float) -> float:
        if self.log:
            return (math.log(value) - math.log(self.lo)) / (math.log(self.hi) - math.log(self.lo))
        return (value - self.lo) / (self.hi - self.lo)

    def from_unit(self, z: float) -> float:
        z = min(max(float(z), 0.0), 1.0)
        if self.log:
            return math.exp(math.log(self.lo) + z * (math.log(self.hi) - math.log(self.lo)))
        return self.lo + z * (self.hi - self.lo)


def _star_index(scene) -> int:
    return max(range(len(scene.stars)), key=lambda i: scene.stars[i].luminosity)


def _unit(direction) -> np.ndarray:
    d = np.asarray(direction, np.float64)
    return d / np.linalg.norm(d)


def depth_range(scene, direction) -> tuple[float, float]:
    """The depths p . d the most luminous star can take inside the box (DEPTH_MARGIN from the faces)."""
    d = _unit(direction)
    p = np.asarray(scene.stars[_star_index(scene)].position, np.float64)
    lo, hi = -math.inf, math.inf  # range of t with p + t d inside [m, 1 - m]^3
    for a in range(3):
        if d[a] != 0.0:
            t0, t1 = (DEPTH_MARGIN - p[a]) / d[a], (1.0 - DEPTH_MARGIN - p[a]) / d[a]
            lo, hi = max(lo, min(t0, t1)), min(hi, max(t0, t1))
    base = float(p @ d)
    return base + lo, base + hi


def current_value(scene, name: str, direction) -> float:
    """The scene's present value of a parameter (the fit's default start)."""
    bands = scene.bands.resolve()
    if name in ("albedo", "g"):
        vals = [getattr(b, name) for b in bands]
        ref = min(bands, key=lambda b: abs(b.wavelength - PIVOT_NM))
        return float(getattr(ref, name)) if len(set(vals)) > 1 else float(vals[0])
    if name in ("albedo_slope", "g_slope"):
        return 0.0
    if name.startswith(("albedo.", "g.")):
        attr, band = name.split(".", 1)
        return float(getattr(next(b for b in bands if b.name == band), attr))
    if name == "tau":
        return float(scene.dust.tau)
    if name == "depth":
        return float(np.asarray(scene.stars[_star_index(scene)].position) @ _unit(direction))
    return float(_get_key(scene.to_dict(), name))


def _get_key(d, key: str):
    import re

    cur = d
    for tok in re.sub(r"\[(\d+)\]", r".\1", key).split("."):
        cur = cur[int(tok)] if isinstance(cur, list) else cur[tok]
    return cur


def parse_free(spec: str, scene, direction=(0.0, 0.0, -1.0)) -> FreeParameter:
    """``name``, ``name=lo:hi`` or ``name=lo:hi:log`` -> :class:`FreeParameter` (default bounds
    where the parameter has them). Raises SceneError("--free", spec, ...) if malformed."""
    name, eq, rng = spec.partition("=")
    name = name.strip()
    log = False
    if eq and not rng.strip():  # "albedo=": bounds meant but not given (was: the default bounds, silently)
        raise SceneError("--free", spec, "must be NAME, NAME=LO:HI or NAME=LO:HI:log (numbers LO < HI)")
    if rng:
        parts = [p.strip() for p in rng.split(":")]
        if len(parts) == 3 and parts[2] == "log":
            log = True
            parts = parts[:2]
        try:
            lo, hi = (float(p) for p in parts)
        except ValueError:
            raise SceneError("--free", spec, "must be NAME, NAME=LO:HI or NAME=LO:HI:log (numbers LO < HI)") from None
    else:
        lo = hi = None
    return make_parameter(name, scene, lo, hi, log, direction)


def make_parameter(name: str, scene, lo=None, hi=None, log: bool = False, direction=(0.0, 0.0, -1.0)):
    """A :class:`FreeParameter` with default bounds filled in and the name checked against the scene."""
    band_names = [b.name for b in scene.bands.resolve()]
    where = f"--free {name}"
    if name.startswith(("albedo.", "g.")):
        attr, band = name.split(".", 1)
        if band not in band_names:
            raise SceneError(where, band, f"names no band; the scene's bands: {', '.join(band_names)}")
        default = DEFAULT_BOUNDS[attr]
    elif name in DEFAULT_BOUNDS:
        default = DEFAULT_BOUNDS[name]
    elif name == "tau":
        t = float(scene.dust.tau)
        if lo is None and not t > 0:
            raise SceneError(where, t, "dust.tau is 0: give bounds, tau=LO:HI")
        default, log = ((t / 10.0, t * 10.0), True) if lo is None else ((lo, hi), log)
    elif name == "depth":
        default = depth_range(scene, direction)
    else:
        try:
            v = _get_key(scene.to_dict(), name)
        except (KeyError, IndexError, ValueError, TypeError):
            raise SceneError(where, name, "must be albedo, g, albedo_slope, g_slope, albedo.BAND, g.BAND, tau, depth "
                                          "or a scalar scene key (e.g. dust.scale, stars.0.luminosity)") from None
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise SceneError(where, v, "a scene key to fit must hold a number")
        if lo is None:
            raise SceneError(where, name, f"give bounds: {name}=LO:HI")
        default = (lo, hi)
    lo, hi = default if lo is None else (lo, hi)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise SceneError(where, (lo, hi), "bounds must be finite with LO < HI")
    if log and lo <= 0:
        raise SceneError(where, (lo, hi), "a log parameter needs LO > 0")
    kind = name.split(".", 1)[0] if name.startswith(("albedo.", "g.")) else name
    if kind in RANGES:
        rlo, rhi = RANGES[kind]
        if lo < rlo or hi > rhi:
            raise SceneError(where, (lo, hi), f"bounds must lie within [{rlo:g}, {rhi:g}]"
                             + (f" (per {SLOPE_NM:g} nm)" if kind.endswith("_slope") else f" (a band's {kind})"))
    if name == "depth":
        dlo, dhi = depth_range(scene, direction)
        if lo < dlo - 1e-12 or hi > dhi + 1e-12:
            raise SceneError(where, (lo, hi), f"the star must stay inside the box: depth within [{dlo:.4g}, {dhi:.4g}] "
                                              "along this line of sight")
    return FreeParameter(name, float(lo), float(hi), bool(log))


def scene_with(base, params: Sequence[FreeParameter], values: Sequence[float], direction=(0.0, 0.0, -1.0)):
    """``base`` with the parameters set to ``values`` (a new, validated scene)."""

    vals = {p.name: float(v) for p, v in zip(params, values)}
    d = base.to_dict()
    bands = base.bands.resolve()
    if any(n in vals for n in ("albedo", "g", "albedo_slope", "g_slope")) or \
            any(n.startswith(("albedo.", "g.")) for n in vals):
        rows = []
        for b in bands:
            row = {"name": b.name, "wavelength": b.wavelength, "extinction": b.extinction}
            for attr, lim in (("albedo", (0.0, 1.0)), ("g", (-1.0, 1.0))):
                v = vals.get(attr, getattr(b, attr))
                v += vals.get(f"{attr}_slope", 0.0) * (b.wavelength - PIVOT_NM) / SLOPE_NM
                v = vals.get(f"{attr}.{b.name}", v)
                row[attr] = min(max(v, lim[0]), lim[1])
            rows.append(row)
        d["bands"] = {"list": rows}
        # the optical depth stays the base scene's: a physical dust key (n_H, the dust's mass
        # density, A_V) gives dust.tau through the preset's reference band, which a list of
        # bands defines otherwise (0.1 % apart for spectral-8), and the two then disagreed
        for key in DUST_KEYS:
            d["dust"].pop(key, None)
    if "tau" in vals:
        d["dust"]["tau"] = vals["tau"]
    if "depth" in vals:
        i = _star_index(base)
        u = _unit(direction)
        p = np.asarray(base.stars[i].position, np.float64)
        p = p + (vals["depth"] - float(p @ u)) * u
        d["stars"][i]["position"] = [float(x) for x in np.clip(p, 0.0, 1.0)]
    scene = Scene.from_dict(d, base_dir=base.base_dir)
    others = [f"{n}={v!r}" for n, v in vals.items() if n not in SPECIAL and not n.startswith(("albedo.", "g."))]
    return scene.with_overrides(others) if others else scene
