"""Fit a scene's dust to the user's observations: albedo, g, optical depth, the star's depth.

The objective is the chi^2 of :mod:`nebula_rt.observe.comparison` (data errors and the run's Monte
Carlo error in quadrature) over all tables. Every trial traces the same number of packets with
the same seed: **common random numbers**. The packets' random numbers are counter-based
(Philox, keyed by packet and scattering), so two trials differ only through the parameters:
a change of g or of tau moves every packet's path continuously, and a change of the albedo
flips the absorption of the few packets whose uniform lies between the old and the new albedo
(analog absorption), a step of one packet's light. The objective is thus a fine staircase
about a smooth curve, not differentiable at the scale of one packet. Measured on a 16^3
uniform cube, 4 bands, 20,000 packets (``tests/observe/test_fit.py``, steps of 0.01 in albedo and g,
0.02 in tau): the second differences of the model's Delta(B-V) and absolute flux ratio are 11
to 160 times smaller with common random numbers than with a new seed per trial. What is left
is a fine roughness: chi^2 scatters by about 1 about a parabola at the fits' Monte Carlo
errors, as much as the rise that defines a 1-sigma error. Hence a derivative-free optimiser
and a fitted surface rather than point-by-point derivatives: a small grid, Nelder-Mead
(``scipy.optimize.minimize``) in the unit cube of the bounds, then a quadratic response
surface fitted by least squares to designs about the minimum (:func:`_refine`).

Parameters (``free``, :class:`FreeParameter`, parsed from ``name=lo:hi[:log]``):

- ``albedo``, ``g``: every band's value (as ``bands.albedo`` / ``bands.g``);
- ``albedo_slope``, ``g_slope``: a linear function of wavelength with the above as its value
  at 550 nm, the slope per 100 nm (clipped to [0, 1] and [-1, 1] per band);
- ``albedo.NAME``, ``g.NAME``: one band's value (band ``NAME``);
- ``tau``: ``dust.tau`` (default bounds a factor 10 either side of the scene's, log scale);
- ``depth``: the most luminous star's coordinate along the line of sight, p . d (box units;
  d the unit viewing direction, so larger is farther from the observer), moving the star
  along d so that its projected position stays put;
- any other scalar scene key (``dust.scale``, ``stars.0.luminosity``): bounds required.

Uncertainties (``uncertainty``):

- ``"profile"`` (default): the profile likelihood, for each parameter the values where the
  chi^2 minimised over the other parameters is chi^2_min + 1 (68.3 % for one parameter):
  started from the refined quadratic, traced there (the others re-minimised where chi^2 rose
  by more than 1.5), corrected by one secant step; asymmetric errors, and the rises traced
  (``profile_check``: near 1 where the quadratic holds, far from it in a curved valley);
- ``"mcmc"``: emcee's affine-invariant ensemble sampler (``pip install emcee``) on
  exp(-chi^2 / 2) with a flat prior inside the bounds (flat in log for log parameters); the
  16th and 84th percentiles;
- ``"none"``.

The measurement behind the default (docs/observations.md, the test problem of
``tests/observe/test_fit.py`` on the CPU): the profile took 311 traces, MCMC (12 walkers x 150 steps)
1894; both held the truth within 2 of their errors; MCMC's marginal intervals were up to 2x
wider along the albedo-tau valley, which the profile's quadratic start underestimates. The
profile is the default for its cost; ``mcmc`` is the choice when the profile check's rises
are far from 1 (``benchmarks/bench_fit.py --uncertainty both`` measures both on a GPU).

Progress and cancel as for a render: ``progress(done, total, best_chi2)`` after every trace
(``total`` the planned number of traces, an estimate), ``cancel()`` polled before every trace
and before every launch within it (:class:`~nebula_rt.errors.CancelledError`).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from .comparison import (
    Comparison, DEFAULT_SIZE, check_tables_against_scene, compare_tables, ring_edges, trace_rings)
from ..density.generate import generate_density
from ..errors import CancelledError, NebulaWarning, SceneError
from .colours import _check_reference
from .observed_tables import ObservedTable, _annuli_from_offsets, finite_or_none
from ..scene.model import Scene
from ..transport.request import scene_backend

UNCERTAINTIES = ("profile", "mcmc", "none")
SPECIAL = ("albedo", "g", "albedo_slope", "g_slope", "tau", "depth")
#: Default bounds of the parameters that have them.
#: g >= 0: interstellar dust scatters forwards in the optical (Draine 2003: g 0.4-0.7 from 380 to
#: 780 nm); allowing g < 0 opens a second minimum (back-scattering from the dust behind the star
#: can mimic forward scattering from the dust in front), so ask for it explicitly (g=-0.5:0.95).
DEFAULT_BOUNDS = {"albedo": (0.02, 0.98), "g": (0.0, 0.95), "albedo_slope": (-0.2, 0.2), "g_slope": (-0.2, 0.2)}
#: Wavelength (nm) at which a linear albedo(lambda) or g(lambda) takes its base value, and the
#: span (nm) its slope is given per.
PIVOT_NM, SLOPE_NM = 550.0, 100.0
#: Largest model/data error ratio a fit accepts without a warning (at 0.5 the combined error is
#: 12 % above the data's).
MAX_MODEL_ERROR = 0.5
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
    name, _, rng = spec.partition("=")
    name = name.strip()
    log = False
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


@dataclass
class FitResult:
    """What :func:`fit_observations` found.

    Attributes
    ----------
    parameters : list of FreeParameter
    best : ndarray (k,)
        Best-fit values.
    err_minus, err_plus : ndarray (k,)
        1-sigma errors below and above (profile: where the profile chi^2 rises by 1; MCMC:
        the 16th / 84th percentiles about the median). NaN without uncertainties; a bound
        reached before chi^2 rose by 1 gives the distance to that bound (``at_bound``).
    chi2, dof : float, int
        At the best fit; dof = rows - free parameters - fitted ratio scales.
    comparison : Comparison
        The best fit against the tables.
    scene : Scene
        The best-fit scene (``scene.to_toml()`` writes it).
    traces : dict
        Traces per stage (grid, optimiser, uncertainties).
    history : list of (values, chi2)
    """

    parameters: list
    best: np.ndarray
    err_minus: np.ndarray
    err_plus: np.ndarray
    chi2: float
    dof: int
    comparison: Comparison
    scene: object
    uncertainty: str = "profile"
    at_bound: list = field(default_factory=list)
    traces: dict = field(default_factory=dict)
    wall_s: float = 0.0
    history: list = field(default_factory=list)
    mcmc: dict = field(default_factory=dict)
    chi2_surface: float = math.nan
    profile_check: dict = field(default_factory=dict)
    covariance: Optional[np.ndarray] = None

    def to_dict(self) -> dict:
        out = {"parameters": {}, "chi2": finite_or_none(self.chi2), "dof": self.dof,
               "reduced_chi2": finite_or_none(self.chi2 / self.dof) if self.dof > 0 else None,
               "uncertainty": self.uncertainty, "traces": self.traces,
               "traces_total": int(sum(self.traces.values())), "wall_s": round(self.wall_s, 3),
               "photons_per_band": self.comparison.rings.photons if self.comparison.rings else None,
               "max_model_to_data_error": finite_or_none(self.comparison.model_error_ratio()),
               "comparison": self.comparison.to_dict()}
        for i, p in enumerate(self.parameters):
            out["parameters"][p.name] = {"value": finite_or_none(self.best[i]),
                                         "err_minus": finite_or_none(self.err_minus[i]),
                                         "err_plus": finite_or_none(self.err_plus[i]),
                                         "bounds": [p.lo, p.hi], "log": p.log, "at_bound": self.at_bound[i]}
        if self.mcmc:
            out["mcmc"] = self.mcmc
        return out

    def summary(self) -> str:
        lines = [f"chi2 = {self.chi2:.3f} for {self.dof} degrees of freedom ({sum(self.traces.values())} traces)"]
        for i, p in enumerate(self.parameters):
            lines.append(f"  {p.name} = {self.best[i]:.5g}  -{self.err_minus[i]:.3g} +{self.err_plus[i]:.3g}"
                         + ("  (interval reaches a bound)" if any(self.at_bound[i]) else ""))
        return "\n".join(lines)


class _Objective:
    """chi^2 of a parameter vector in the unit cube; counts traces, keeps every trace's ring sums
    (a change of the fixed Monte Carlo errors re-scores them without tracing again), reports
    progress, polls the cancel."""

    def __init__(self, base, params, tables, direction, size, reference, backend, progress, cancel, total):
        self.base, self.params, self.tables = base, params, tables
        self.direction, self.size, self.reference = direction, size, reference
        self.backend, self.progress, self.cancel = backend, progress, cancel
        self.edges = ring_edges(tables)
        self.total = total
        self.done = 0
        self.stage = "grid"
        self.traces: dict = {}
        self.rings: dict = {}  # unit-cube point -> RingSums
        self.scores: dict = {}  # unit-cube point -> chi^2 with the present errors
        self.density_cache: dict = {}
        self.model_errors = None  # the Monte Carlo errors held fixed (see freeze)
        self.history: list = []  # (values, chi^2 when traced)

    def values(self, z) -> np.ndarray:
        return np.array([p.from_unit(zi) for p, zi in zip(self.params, z)])

    def _density(self, scene):

        d = scene.to_dict()
        key = json.dumps([d["grid"], {k: v for k, v in d["dust"].items() if k != "tau"},
                          [(s.get("position"), s.get("bump_radius")) for s in d["stars"]]], sort_keys=True)
        if key not in self.density_cache:
            self.density_cache.clear()  # keep one: a free dust key makes a new one per trial
            self.density_cache[key] = generate_density(scene, self.backend)
        return self.density_cache[key]

    def _trace(self, values):
        scene = scene_with(self.base, self.params, values, self.direction)
        return trace_rings(scene, self.edges, direction=self.direction, size=self.size, backend=self.backend,
                           cancel=self.cancel, density=self._density(scene))

    def comparison(self, z, own_errors: bool = False) -> Comparison:
        """The comparison at unit-cube point z (traced if new), with the fixed or its own errors."""
        rings = self._rings(np.clip(np.asarray(z, np.float64), 0.0, 1.0))
        return compare_tables(rings, self.tables, self.reference, None if own_errors else self.model_errors)

    def freeze(self, z) -> None:
        """Hold the Monte Carlo errors of the run at z fixed from now on, and re-score every trace.
        A run's own error depends on the parameters; left free in chi^2 (without the log
        determinant of a likelihood) it pulls the fit towards where the model is noisiest.
        Measured on the test problem (16^3, 4 bands, 20,000 packets): with each trial's own
        errors the best fit's chi^2 was 8 below the truth's, by a noisier model, at 5-8 sigma
        from it; with frozen errors it is within the stated errors."""
        self.model_errors = [r.raw_model_err for r in self.comparison(z, own_errors=True).results]
        self.scores = {key: compare_tables(r, self.tables, self.reference, self.model_errors).chi2
                       for key, r in self.rings.items()}

    def _rings(self, z):
        key = tuple(np.round(z, 12))
        if key not in self.rings:
            if self.cancel is not None and self.cancel():
                raise CancelledError(f"fit cancelled after {self.done} traces")
            values = self.values(z)
            try:
                self.rings[key] = self._trace(values)
            except CancelledError as exc:  # say where the fit was, not only the trace
                raise CancelledError(f"fit cancelled after {self.done} traces ({exc})") from None
            self.done += 1
            self.traces[self.stage] = self.traces.get(self.stage, 0) + 1
            chi2 = compare_tables(self.rings[key], self.tables, self.reference, self.model_errors).chi2
            self.scores[key] = chi2
            self.history.append((values.tolist(), chi2))
            if self.progress is not None:
                self.progress(self.done, max(self.total, self.done), self.best[0])
        return self.rings[key]

    def __call__(self, z) -> float:
        z = np.clip(np.asarray(z, np.float64), 0.0, 1.0)
        self._rings(z)
        return self.scores[tuple(np.round(z, 12))]

    @property
    def best(self):
        """(chi^2, unit-cube point) of the lowest score so far."""
        if not self.scores:
            return (math.inf, None)
        key = min(self.scores, key=self.scores.get)
        return (self.scores[key], np.array(key))

    def points(self):
        """(unit-cube point, chi^2 with the present errors) of every trace so far."""
        return [(np.array(k), c) for k, c in self.scores.items()]


def _minimise(obj: _Objective, z0, step: float, free_idx, fixed_z, fatol: float, maxfev: int):
    """Nelder-Mead over the coordinates ``free_idx`` of the unit cube, the others at ``fixed_z``."""
    from scipy.optimize import minimize

    z0 = np.asarray(z0, np.float64)
    k = len(free_idx)

    def full(y):
        z = np.array(fixed_z, np.float64)
        z[free_idx] = y
        return z

    y0 = z0[free_idx]
    # the initial simplex: a step along each axis, turned inwards at the cube's faces
    simplex = [y0]
    for j in range(k):
        y = y0.copy()
        y[j] = y0[j] + step if y0[j] + step <= 1.0 else y0[j] - step
        simplex.append(y)
    res = minimize(lambda y: obj(full(y)), y0, method="Nelder-Mead", bounds=[(0.0, 1.0)] * k,
                   options={"initial_simplex": np.array(simplex), "xatol": 1e-3, "fatol": fatol, "maxfev": maxfev})
    return full(res.x), float(res.fun)


def _quadratic(zs, fs):
    """Least-squares quadratic f = c + b.z + z.A.z / 2 through points (n, k); returns (c, b, A)
    or None when there are too few points."""
    zs = np.asarray(zs, np.float64)
    fs = np.asarray(fs, np.float64)
    n, k = zs.shape
    pairs = [(i, j) for i in range(k) for j in range(i, k)]
    if n < 1 + k + len(pairs) + 2:
        return None
    cols = [np.ones(n)] + [zs[:, i] for i in range(k)] + [zs[:, i] * zs[:, j] * (0.5 if i == j else 1.0)
                                                         for i, j in pairs]
    coef, *_ = np.linalg.lstsq(np.stack(cols, 1), fs, rcond=None)
    A = np.zeros((k, k))
    for (i, j), c in zip(pairs, coef[1 + k:]):
        A[i, j] = A[j, i] = c
    return coef[0], coef[1:1 + k], A


#: Refinement: design points at this many (quadratic) standard deviations from the centre,
#: where chi^2 has risen by about 4, well above its roughness (about 1 at the fits'
#: Monte Carlo errors: docs/observations.md); the quadratic is fitted to the traced points
#: within REGION standard deviations and DCHI2 of the lowest.
DESIGN_SIGMA, REGION, DCHI2 = 2.0, 3.5, 25.0


#: Largest variance of the design along any direction (a standard deviation of a quarter of the
#: cube): a flat direction would otherwise ask for points far outside.
MAX_VAR = 0.0625


def _capped(V, var) -> np.ndarray:
    """The covariance V diag(var) V^T with each variance in [1e-10, MAX_VAR]."""
    return V @ np.diag(np.clip(var, 1e-10, MAX_VAR)) @ V.T


def _design(k: int) -> np.ndarray:
    """Unit directions of a refinement round: +-e_i and (e_i +- e_j) / sqrt 2 for i < j."""
    out = []
    for i in range(k):
        for s in (-1.0, 1.0):
            e = np.zeros(k)
            e[i] = s
            out.append(e)
    for i in range(k):
        for j in range(i + 1, k):
            for s in (-1.0, 1.0):
                e = np.zeros(k)
                e[i], e[j] = 1.0 / math.sqrt(2.0), s / math.sqrt(2.0)
                out.append(e)
                out.append(-e)
    return np.array(out)


def _refine(obj, z0, cov0, rounds: int = 5):
    """A trust-region quadratic response surface about the minimum: each round traces a design
    of points DESIGN_SIGMA standard deviations out along the axes and diagonals of the present
    covariance, fits chi^2 = c + b.z + z.A.z / 2 by least squares to the traced points near the
    centre, and moves the centre to the quadratic's minimum (at most REGION standard deviations,
    inside the cube), with covariance 2 A^-1. Fitting many points smooths the fine staircase
    that common random numbers leave in chi^2 (Nelder-Mead and a point-by-point profile would
    follow its steps). Stops when the centre moves less than 0.3 standard deviations.
    Returns (centre, covariance or None, chi^2 of the quadratic at the centre)."""
    k = len(z0)
    zc, cov = np.asarray(z0, np.float64), np.asarray(cov0, np.float64)
    f_c = None
    dirs = _design(k)
    for _ in range(rounds):
        L = np.linalg.cholesky(cov)
        for u in dirs:
            obj(np.clip(zc + DESIGN_SIGMA * L @ u, 0.0, 1.0))
        pts = obj.points()
        fmin = min(c for _, c in pts)
        Li = np.linalg.inv(L)
        near = [(z, c) for z, c in pts if c < fmin + DCHI2 and np.linalg.norm(Li @ (z - zc)) < REGION]
        fit = _quadratic([z for z, _ in near], [c for _, c in near]) if len(near) > 0 else None
        if fit is None:
            cov = cov * 0.5  # too few points near: a tighter design (more points fall inside)
            continue
        c0, b, A = fit
        w, V = np.linalg.eigh(A)
        if not np.all(w > 0):
            # not a minimum yet (or flat in some direction): widen the design there, recentre on
            # the lowest trace
            cov = _capped(V, np.where(w > 0, 2.0 / np.maximum(w, 1e-300), MAX_VAR))
            zc = np.asarray(min(pts, key=lambda p: p[1])[0], np.float64)
            continue
        cov_new = _capped(V, 2.0 / w)
        z_new = -np.linalg.solve(A, b)
        step = z_new - zc
        r = np.linalg.norm(Li @ step)
        if r > REGION:
            z_new = zc + step * (REGION / r)
        z_new = np.clip(z_new, 0.0, 1.0)
        moved = np.linalg.norm(np.linalg.solve(np.linalg.cholesky(cov_new), z_new - zc))
        zc, cov = z_new, cov_new
        f_c = float(c0 + b @ zc + 0.5 * zc @ A @ zc)
        if moved < 0.3:
            break
    return zc, cov, f_c


def _local_start(obj, z, grid: int) -> np.ndarray:
    """A first covariance for the refinement: a quadratic through the traced points near ``z``
    when it is a minimum, else a grid cell (or 0.1) wide."""
    pts = [(p, c) for p, c in obj.points() if np.max(np.abs(np.asarray(p) - z)) < 0.25]
    fit = _quadratic([p for p, _ in pts], [c for _, c in pts]) if pts else None
    k = len(z)
    width = 0.25 / grid if grid > 0 else 0.05
    if fit is not None:
        w, V = np.linalg.eigh(fit[2])
        if np.all(w > 0):
            cov = 2.0 * V @ np.diag(1.0 / w) @ V.T
            return cov * min(1.0, 0.0625 / float(np.max(np.diag(cov))))
    return np.eye(k) * width ** 2


def _covariance(params, z, cov):
    """The unit-cube covariance as one of the parameters (through d value / dz; log parameters
    linearised)."""
    if cov is None:
        return None
    jac = np.array([(p.from_unit(min(zi + 1e-6, 1.0)) - p.from_unit(max(zi - 1e-6, 0.0))) /
                    (min(zi + 1e-6, 1.0) - max(zi - 1e-6, 0.0)) for p, zi in zip(params, z)])
    return cov * jac[:, None] * jac[None, :]


def fit_observations(scene, tables: Sequence[ObservedTable], free: Sequence, *, direction=(0.0, 0.0, -1.0),
                     size: int = DEFAULT_SIZE, reference: str = "observed", uncertainty: str = "profile",
                     grid: Optional[int] = None, start: Optional[Sequence[float]] = None, starts: int = 2,
                     maxfev: Optional[int] = None,
                     fatol: float = 0.05, mcmc_walkers: int = 0, mcmc_steps: int = 200, backend=None,
                     progress: Optional[Callable] = None, cancel: Optional[Callable[[], bool]] = None) -> FitResult:
    """Find the parameters ``free`` of ``scene`` that best match ``tables`` (minimum chi^2).

    Parameters
    ----------
    scene : Scene
        The model; its seed and ``transport.photons`` are used for every trial (common random
        numbers). An error target, quality preset or time limit is refused.
    tables : sequence of ObservedTable
        From :func:`nebula_rt.observe.observed_tables.read_table`.
    free : sequence of FreeParameter or str
        The parameters (strings as ``parse_free`` takes them).
    direction : (3,)
        Viewing direction, from the observer into the scene.
    size : int
        Peel-off image pixels per side (over twice the largest offset of the tables).
    reference : {"observed", "intrinsic"}
        The star the colours and ratios are taken against.
    uncertainty : {"profile", "mcmc", "none"}
    grid : int, optional
        Points per parameter of the starting grid (default 3 for up to 3 parameters, else 0:
        start at ``start``, default the scene's values).
    starts : int
        Nelder-Mead runs, from the best ``starts`` points of the grid (and the start); 0: none,
        the refinement starts from the grid's best.
    maxfev : int, optional
        Traces per optimiser run (default 40 + 30 per parameter).
    fatol : float
        The optimiser stops when the simplex's chi^2 values agree to this.
    mcmc_walkers, mcmc_steps : int
        For ``uncertainty="mcmc"`` (walkers default 4 x parameters, at least 8); the first
        half of the steps is discarded as burn-in.
    progress : callable(done, total, best_chi2), optional
    cancel : callable() -> bool, optional

    Returns
    -------
    FitResult
    """

    t0 = time.perf_counter()
    _check_reference(reference)
    if uncertainty not in UNCERTAINTIES:
        raise SceneError("uncertainty", uncertainty, f"must be one of {', '.join(UNCERTAINTIES)}")
    tr = scene.transport
    for key, v in (("transport.target_error", tr.target_error), ("transport.quality", tr.quality),
                   ("transport.time_limit", tr.time_limit)):
        if v:
            raise SceneError(key, v, "must be unset for a fit: every trial traces transport.photons packets with one "
                                     "seed (common random numbers), so the objective is smooth in the parameters")
    check_tables_against_scene(scene, tables)
    params = [p if isinstance(p, FreeParameter) else parse_free(p, scene, direction) for p in free]
    if not params:
        raise SceneError("--free", [], "name at least one parameter to fit")
    names = [p.name for p in params]
    if len(set(names)) != len(names):
        raise SceneError("--free", names, "each parameter once")
    for vals in ([p.lo for p in params], [p.hi for p in params]):  # both corners must be valid scenes
        scene_with(scene, params, vals, direction)
    k = len(params)
    if start is None:
        start = [min(max(current_value(scene, p.name, direction), p.lo), p.hi) for p in params]
    z_start = np.array([p.to_unit(v) for p, v in zip(params, start)])
    grid = (3 if k <= 3 else 0) if grid is None else int(grid)
    maxfev = 20 + 15 * k if maxfev is None else int(maxfev)
    backend = backend or scene_backend(scene)
    if uncertainty == "mcmc":
        try:
            import emcee  # noqa: F401
        except ImportError:
            raise SceneError("uncertainty", "mcmc", "needs emcee: pip install 'nebula-rt[fit]' (or emcee)") from None
    walkers = max(8, 4 * k) if not mcmc_walkers else int(mcmc_walkers)
    # MCMC: emcee evaluates the starting ensemble too
    unc_budget = {"profile": 2 * k, "mcmc": walkers * (mcmc_steps + 1), "none": 0}[uncertainty]
    total = grid ** k + 1 + max(0, int(starts)) * maxfev + 3 * len(_design(k)) + 1 + unc_budget
    obj = _Objective(scene, params, list(tables), direction, size, reference, backend, progress, cancel, total)

    # 1. a coarse grid (cell centres) and the start
    candidates = [z_start]
    if grid > 0:
        axes = [(np.arange(grid) + 0.5) / grid] * k
        candidates += [np.array(c) for c in np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, k)]
    obj(z_start)
    obj.freeze(z_start)  # the Monte Carlo errors of the start, fixed while searching
    scores = [obj(z) for z in candidates]
    # 2. Nelder-Mead from the best ``starts`` of them (a valley that the grid cuts into separate
    # cells, or two minima, e.g. g > 0 and g < 0, can trap one start), the simplex a grid cell wide
    obj.stage = "optimiser"
    step = 0.5 / grid if grid > 0 else 0.1
    for j in np.argsort(scores)[:max(0, int(starts))]:
        _minimise(obj, candidates[j], step, list(range(k)), candidates[j], fatol, maxfev)
    # 3. refinement: a quadratic response surface about the minimum (see _refine), with the
    # Monte Carlo errors of the optimiser's best
    obj.stage = "refine"
    z_nm = np.asarray(obj.best[1])
    obj.freeze(z_nm)
    cov = _local_start(obj, z_nm, grid)
    z_best, cov, f_best = _refine(obj, z_nm, cov)
    if f_best is None:  # no quadratic: report the lowest trace
        f_best, z_best = obj.best[0], np.asarray(obj.best[1])
    obj.freeze(z_best)  # the errors of the best fit for the uncertainties (one more trace)
    if obj(z_best) > obj.best[0] + 1.0:
        # the quadratic's minimum is worse than a trace: the surface misled (too few or too rough
        # points); keep the lowest trace, with its errors
        z_best = np.asarray(obj.best[1])
        obj.freeze(z_best)
    comp = obj.comparison(z_best)
    chi2_best = comp.chi2
    profile_check = {}
    best = obj.values(z_best)
    err_m = np.full(k, np.nan)
    err_p = np.full(k, np.nan)
    at_bound = [[False, False] for _ in range(k)]
    mcmc_info = {}
    if uncertainty == "profile":
        obj.stage = "profile"
        # the profile: start from the refined quadratic (sigma_i = sqrt(cov_ii), reached with the
        # others at their conditional optimum cov[:, i] / sigma_i), trace chi^2 there, minimise the
        # others from there when it rose by more than 1.5 (a curved valley leaves the quadratic's
        # line), and correct the distance by the secant of a parabola through the minimum,
        # sigma / sqrt(rise), kept within [0.5, 2] sigma
        checks = {}
        for i in range(k):
            sd = math.sqrt(cov[i, i])
            others = [j for j in range(k) if j != i]
            for s, arr in ((-1, err_m), (1, err_p)):
                zi = np.clip(z_best + s * cov[:, i] / sd, 0.0, 1.0)
                q = obj(zi) - chi2_best
                if q > 1.5 and others:
                    so = float(np.sqrt(np.max(np.diag(cov)[others])))
                    _, chi2_p = _minimise(obj, zi, max(0.5 * so, 0.005), others, zi, fatol, 8 * len(others) + 4)
                    q = chi2_p - chi2_best
                d = sd / math.sqrt(q) if q > 0.25 else 2.0 * sd
                d = min(max(d, 0.5 * sd), 2.0 * sd)
                zc = min(max(z_best[i] + s * d, 0.0), 1.0)
                at_bound[i][0 if s < 0 else 1] = bool(zc != z_best[i] + s * d)
                arr[i] = abs(params[i].from_unit(zc) - best[i])
                checks[params[i].name + ("+" if s > 0 else "-")] = round(q, 3)
        profile_check = checks
    elif uncertainty == "mcmc":
        import emcee

        obj.stage = "mcmc"
        rng = np.random.default_rng(int(scene.transport.seed))
        L = np.linalg.cholesky(cov) if cov is not None else 0.02 * np.eye(k)

        def log_prob(z):
            if np.any(z < 0) or np.any(z > 1):
                return -np.inf
            return -0.5 * obj(z)

        # walkers start in a ball of half the refined quadratic's width about the best fit
        p0 = np.clip(z_best[None] + 0.5 * rng.standard_normal((walkers, k)) @ L.T, 0.0, 1.0)
        sampler = emcee.EnsembleSampler(walkers, k, log_prob)
        sampler.run_mcmc(p0, mcmc_steps, progress=False)
        chain = sampler.get_chain(discard=mcmc_steps // 2, flat=True)
        vals = np.array([obj.values(z) for z in chain])
        q16, q50, q84 = np.percentile(vals, [16, 50, 84], axis=0)
        err_m, err_p = q50 - q16, q84 - q50
        try:
            tau_ac = sampler.get_autocorr_time(discard=mcmc_steps // 2, quiet=True).tolist()
        except Exception:  # too short a chain for an estimate
            tau_ac = None
        mcmc_info = {"walkers": walkers, "steps": mcmc_steps, "median": q50.tolist(),
                     "acceptance": float(np.mean(sampler.acceptance_fraction)), "autocorr_steps": tau_ac}
    ratio = comp.model_error_ratio()
    if ratio > MAX_MODEL_ERROR:
        import warnings


        warnings.warn(NebulaWarning(
            f"the model's Monte Carlo error is up to {ratio:.2f} of the data's at the best fit: one seed's noise "
            "then moves the fit by about as much as the data's (chi^2 takes the errors as independent, the model's "
            "are correlated across rows); raise transport.photons (the error falls as 1/sqrt(photons))"))
    n_scales = sum(len(r.scale) for r in comp.results if r.scale is not None)
    dof = comp.n - k - n_scales
    return FitResult(parameters=params, best=best, err_minus=err_m, err_plus=err_p, chi2=float(chi2_best), dof=dof,
                     chi2_surface=float(f_best), profile_check=profile_check,
                     covariance=_covariance(params, z_best, cov),
                     comparison=comp, scene=scene_with(scene, params, best, direction), uncertainty=uncertainty,
                     at_bound=at_bound, traces=dict(obj.traces), wall_s=time.perf_counter() - t0,
                     history=obj.history, mcmc=mcmc_info)


def synthetic_tables(scene, *, offsets, wavelengths, annulus=(0.05, 0.45), colour_err: float = 0.02,
                     ratio_rel_err: float = 0.03, noise_seed: int = 0, direction=(0.0, 0.0, -1.0),
                     size: int = DEFAULT_SIZE, reference: str = "observed", backend=None, cancel=None):
    """A synthetic observation of ``scene``: a colour table at ``offsets`` (box units, annuli
    halfway to the neighbours) and an absolute ratio table at ``wavelengths`` (nm) in
    ``annulus``, each the model's value plus Gaussian noise of the stated error (the tables'
    errors: ``colour_err`` mag; ``ratio_rel_err`` times the value). The model's own Monte Carlo
    error adds to the scatter: trace it with many more packets than the fit uses."""

    offsets = np.asarray(offsets, np.float64)
    wavelengths = np.asarray(wavelengths, np.float64)
    lo, hi = _annuli_from_offsets(offsets, "offsets")
    col = ObservedTable("colour", "synthetic colour", offsets, np.zeros_like(offsets),
                        np.full(offsets.shape, float(colour_err)), lo, hi, x_display=offsets, x_unit="box units")
    rat = ObservedTable("ratio", "synthetic ratio", wavelengths, np.ones_like(wavelengths), np.ones_like(wavelengths),
                        np.full(wavelengths.shape, float(annulus[0])), np.full(wavelengths.shape, float(annulus[1])),
                        x_display=wavelengths, x_unit="nm", normalisation="absolute")
    comp = compare_tables(trace_rings(scene, ring_edges([col, rat]), direction=direction, size=size, backend=backend,
                                      cancel=cancel), [col, rat], reference)
    rng = np.random.default_rng(noise_seed)
    m_col, m_rat = comp.results[0].model, comp.results[1].model
    col.value = m_col + col.error * rng.standard_normal(len(offsets))
    rat.error = ratio_rel_err * m_rat
    rat.value = m_rat + rat.error * rng.standard_normal(len(wavelengths))
    return col, rat
