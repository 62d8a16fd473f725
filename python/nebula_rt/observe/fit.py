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

- ``albedo``, ``g``: every band's value (as ``bands.albedo`` / ``bands.g``; bounds within
  [0, 1] and [-1, 1]);
- ``albedo_slope``, ``g_slope``: a linear function of wavelength with the above as its value
  at 550 nm, the slope per 100 nm (bounds within +-1 and +-2; the value clipped to [0, 1] and
  [-1, 1] per band where value and slope together leave it);
- ``albedo.NAME``, ``g.NAME``: one band's value (band ``NAME``; bounds as ``albedo``, ``g``);
- ``tau``: ``dust.tau`` (default bounds a factor 10 either side of the scene's, log scale);
- ``depth``: the most luminous star's coordinate along the line of sight, p . d (box units;
  d the unit viewing direction, so larger is farther from the observer), moving the star
  along d so that its projected position stays put;
- any other scalar scene key (``dust.scale``, ``stars.0.luminosity``): bounds required.

Uncertainties (``uncertainty``):

- ``"profile"`` (default): the profile likelihood, for each parameter the values where the
  chi^2 minimised over the other parameters is chi^2_min + 1 (68.3 % for one parameter),
  from the profile itself: the others re-minimised at 1 and 2 of the quadratic's standard
  deviations on each side, a parabola through the best fit fitted to each side's rises, the
  error where it reaches 1 (asymmetric errors; ``profile_check``: each side's curvature
  against the quadratic's, near 1 where the quadratic holds, far from it in a curved valley);
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
import numbers
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from .comparison import (
    Comparison, DEFAULT_SIZE, check_tables_against_scene, compare_tables, needs_stokes, ring_edges, trace_rings)
from ..density.generate import scene_density
from ..errors import CancelledError, NebulaWarning, SceneError
from .colours import _check_reference
from .fit_parameters import FreeParameter, current_value, parse_free, scene_with
from .fit_surface import _covariance, _design, _local_start, _minimise, _refine
from .observed_tables import ObservedTable, _annuli_from_offsets, finite_or_none
from ..scene.model import Scene
from ..scene.sky_schema import DIRECTION_ALLOWED, valid_direction
from ..backends.parallel import any_rank
from ..transport.request import scene_backend

UNCERTAINTIES = ("profile", "mcmc", "none")
#: The profile's steps on each side of the best fit, in the quadratic surface's standard
#: deviations: where chi^2 rises by about 1 and 4, each well inside the bounds of a fit
#: whose errors are small against them (FitRequest._profile_errors)
PROFILE_STEPS = (1.0, 2.0)
#: Nelder-Mead traces per other parameter at each profile step (plus 4): the start is the
#: quadratic's conditional optimum, continued from the last step's optimum, so it is near
PROFILE_MAXFEV_PER_PARAMETER = 6
#: Most points of the starting grid (``grid`` per parameter, to the power of the parameters):
#: each is held in memory and traced, so that 100,000 are a day at a trace a second; a grid
#: larger than this is a mistake, not a search (3 parameters at 100 points made 1e6 traces).
MAX_GRID_POINTS = 100_000
#: Largest model/data error ratio a fit accepts without a warning (at 0.5 the combined error is
#: 12 % above the data's).
MAX_MODEL_ERROR = 0.5


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
            lo, hi = self.err_minus[i], self.err_plus[i]
            # no interval (--uncertainty none, or none found): said in words, not "-nan +nan"
            interval = f"-{lo:.3g} +{hi:.3g}" if math.isfinite(lo) and math.isfinite(hi) else "(no interval)"
            lines.append(f"  {p.name} = {self.best[i]:.5g}  {interval}"
                         + ("  (interval reaches a bound)" if any(self.at_bound[i]) else ""))
        return "\n".join(lines)


class _Objective:
    """chi^2 of a parameter vector in the unit cube; counts traces, keeps every trace's ring sums
    (a change of the fixed Monte Carlo errors re-scores them without tracing again), reports
    progress, polls the cancel."""

    def __init__(self, base, params, tables, direction, size, reference, backend, progress, cancel, total,
                 comm=None):
        self.base, self.params, self.tables = base, params, tables
        self.direction, self.size, self.reference = direction, size, reference
        self.backend, self.progress, self.cancel = backend, progress, cancel
        self.comm = comm  # the ranks sharing every trace: each takes the same steps after it
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
            self.density_cache[key] = scene_density(scene, self.backend)  # a grid or an octree
        return self.density_cache[key]

    def _trace(self, values):
        scene = scene_with(self.base, self.params, values, self.direction)
        return trace_rings(scene, self.edges, direction=self.direction, size=self.size, backend=self.backend,
                           cancel=self.cancel, density=self._density(scene), comm=self.comm,
                           stokes=needs_stokes(self.tables))

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
            if any_rank(self.comm, self.cancel is not None and self.cancel()):
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



@dataclass
class FitRequest:
    """What a fit is asked: the scene, the observations, the free parameters and how to search
    and estimate errors (:func:`fit_observations` runs it; ``nebula-rt fit`` builds it).

    Attributes
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
        start at ``start``, default the scene's values); >= 0, at most
        :data:`MAX_GRID_POINTS` points in all.
    start : sequence of float, optional
        The starting values, each within its parameter's bounds (default the scene's, moved
        into the bounds).
    starts : int, optional
        Nelder-Mead runs, from the best ``starts`` points of the grid (and the start); 0: none,
        the refinement starts from the grid's best. At most the grid's points and the start;
        default 2, or 1 where there is only the start.
    maxfev : int, optional
        Traces per optimiser run (default 20 + 15 per parameter), >= 1.
    fatol : float
        The optimiser stops when the simplex's chi^2 values agree to this (> 0).
    mcmc_walkers, mcmc_steps : int
        For ``uncertainty="mcmc"`` (walkers default 4 x parameters, at least 8; given, at least
        2 x parameters); the first half of the steps (at least 2) is discarded as burn-in.

    Every field is checked by :meth:`parameters` before any trace: a value out of range is
    refused (SceneError naming it), never clipped into range.
    """

    scene: Scene
    tables: Sequence[ObservedTable]
    free: Sequence
    direction: Sequence[float] = (0.0, 0.0, -1.0)
    size: int = DEFAULT_SIZE
    reference: str = "observed"
    uncertainty: str = "profile"
    grid: Optional[int] = None
    start: Optional[Sequence[float]] = None
    starts: Optional[int] = None
    maxfev: Optional[int] = None
    fatol: float = 0.05
    mcmc_walkers: int = 0
    mcmc_steps: int = 200

    def parameters(self) -> list:
        """The free parameters, checked (before any trace): refusals name the key."""
        scene = self.scene
        _check_reference(self.reference)
        if self.uncertainty not in UNCERTAINTIES:
            raise SceneError("uncertainty", self.uncertainty, f"must be one of {', '.join(UNCERTAINTIES)}")
        tr = scene.transport
        for key, v in (("transport.target_error", tr.target_error), ("transport.quality", tr.quality),
                       ("transport.time_limit", tr.time_limit)):
            if v:
                raise SceneError(key, v, "must be unset for a fit: every trial traces transport.photons packets with "
                                         "one seed (common random numbers), so the objective is smooth in the "
                                         "parameters")
        if not valid_direction(self.direction):
            raise SceneError("direction", self.direction, DIRECTION_ALLOWED)
        check_tables_against_scene(scene, self.tables, direction=self.direction, size=self.size)
        params = [p if isinstance(p, FreeParameter) else parse_free(p, scene, self.direction) for p in self.free]
        if not params:
            raise SceneError("--free", [], "name at least one parameter to fit")
        names = [p.name for p in params]
        if len(set(names)) != len(names):
            raise SceneError("--free", names, "each parameter once")
        for p in params:  # each bound a valid scene, named by its parameter
            for v in (p.lo, p.hi):
                try:
                    scene_with(scene, [p], [v], self.direction)
                except SceneError as exc:
                    raise SceneError(f"--free {p.name}", (p.lo, p.hi), f"the bound {v:g} gives {exc}") from None
        for vals in ([p.lo for p in params], [p.hi for p in params]):  # both corners must be valid scenes
            scene_with(scene, params, vals, self.direction)
        self._check_search(params)
        if self.uncertainty == "mcmc":
            try:
                import emcee  # noqa: F401  (optional: the fit extra)
            except ImportError:
                raise SceneError("uncertainty", "mcmc", "needs emcee: pip install 'nebula-rt[fit]' (or emcee)") from None
        return params

    def _check_search(self, params) -> None:
        """The search's options: counts that are whole and in range, a start within the bounds
        (each refused rather than clipped into range)."""
        k = len(params)

        def count(name, value, lo, what):
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < lo:
                raise SceneError(name, value, f"must be an integer >= {lo} ({what})")

        if self.grid is not None:
            count("--grid", self.grid, 0, "points per parameter of the starting grid; 0: none")
            if int(self.grid) ** k > MAX_GRID_POINTS:
                raise SceneError("--grid", self.grid, f"gives {int(self.grid)}^{k} = {int(self.grid) ** k:,} starting "
                                                      f"traces ({k} free parameter{'s' if k > 1 else ''}); at most "
                                                      f"{MAX_GRID_POINTS:,} "
                                                      f"(--grid <= {math.floor(MAX_GRID_POINTS ** (1.0 / k) + 1e-9)})")
        if self.starts is not None:
            count("--starts", self.starts, 0, "Nelder-Mead runs from the grid's best points; 0: none")
            points = self._grid(k) ** k + 1
            if self.starts > points:  # (was: as many as there are, silently)
                raise SceneError("--starts", self.starts, f"must be at most {points}: a run starts from one of the "
                                                          f"grid's {self._grid(k)}^{k} points or the start")
        if self.maxfev is not None:
            count("maxfev", self.maxfev, 1, "traces per optimiser run")
        count("mcmc_steps", self.mcmc_steps, 2, "steps of the MCMC chain, half of them burn-in")
        if self.mcmc_walkers:
            count("mcmc_walkers", self.mcmc_walkers, 2 * k, "walkers of the ensemble sampler, at least twice the "
                                                            "free parameters; 0: 4 per parameter")
        if not (isinstance(self.fatol, numbers.Real) and math.isfinite(self.fatol) and self.fatol > 0):
            raise SceneError("fatol", self.fatol, "must be a finite number > 0 (the chi^2 tolerance of the optimiser)")
        if self.start is not None:
            start = list(self.start)
            if len(start) != k or not all(isinstance(v, numbers.Real) and p.lo <= v <= p.hi
                                          for p, v in zip(params, start)):
                raise SceneError("start", start, "must hold one value per free parameter, each within its bounds "
                                 + ", ".join(f"{p.name} [{p.lo:g}, {p.hi:g}]" for p in params))

    def _grid(self, k: int) -> int:
        """Points per parameter of the starting grid, for ``k`` free parameters."""
        return (3 if k <= 3 else 0) if self.grid is None else int(self.grid)

    def _starts(self, k: int) -> int:
        """Nelder-Mead runs: as given, else 2 where the grid and the start offer 2 points."""
        return min(2, self._grid(k) ** k + 1) if self.starts is None else int(self.starts)

    def run(self, backend=None, progress: Optional[Callable] = None,
            cancel: Optional[Callable[[], bool]] = None, comm=None) -> FitResult:
        """Fit: a coarse grid, Nelder-Mead from its best points, a quadratic surface about the
        minimum, then the errors (``progress(done, total, best_chi2)`` after every trace,
        ``cancel()`` before every trace and launch). ``comm``: the ranks that share every
        trace (:mod:`nebula_rt.backends.parallel`); each trace ends with the same bits on every
        rank and the search is deterministic, so every rank takes the same steps and returns
        the same result."""
        t0 = time.perf_counter()
        scene, direction = self.scene, self.direction
        params = self.parameters()
        k = len(params)
        start = self.start
        if start is None:
            start = [min(max(current_value(scene, p.name, direction), p.lo), p.hi) for p in params]
        z_start = np.array([p.to_unit(v) for p, v in zip(params, start)])
        grid = self._grid(k)
        starts = self._starts(k)
        maxfev = 20 + 15 * k if self.maxfev is None else int(self.maxfev)
        backend = backend or scene_backend(scene)
        walkers = max(8, 4 * k) if not self.mcmc_walkers else int(self.mcmc_walkers)
        # MCMC: emcee evaluates the starting ensemble too
        profile_traces = 2 * k * len(PROFILE_STEPS) * (PROFILE_MAXFEV_PER_PARAMETER * (k - 1) + 4 if k > 1 else 1)
        unc_budget = {"profile": profile_traces, "mcmc": walkers * (self.mcmc_steps + 1), "none": 0}[self.uncertainty]
        total = grid ** k + 1 + starts * maxfev + 3 * len(_design(k)) + 1 + unc_budget
        obj = _Objective(scene, params, list(self.tables), direction, self.size, self.reference, backend, progress,
                         cancel, total, comm)
        z_best, cov, f_best = self._search(obj, z_start, grid, maxfev)
        comp = obj.comparison(z_best)
        best = obj.values(z_best)
        at_bound = [[False, False] for _ in range(k)]
        profile_check, mcmc_info = {}, {}
        if self.uncertainty == "profile":
            err_m, err_p, profile_check = self._profile_errors(obj, params, z_best, cov, comp.chi2, best, at_bound)
        elif self.uncertainty == "mcmc":
            err_m, err_p, mcmc_info = self._mcmc_errors(obj, z_best, cov, walkers)
        else:
            err_m, err_p = np.full(k, np.nan), np.full(k, np.nan)
        ratio = comp.model_error_ratio()
        if ratio > MAX_MODEL_ERROR:
            warnings.warn(NebulaWarning(
                f"the model's Monte Carlo error is up to {ratio:.2f} of the data's at the best fit: one seed's noise "
                "then moves the fit by about as much as the data's (chi^2 takes the errors as independent, the "
                "model's are correlated across rows); raise transport.photons (the error falls as 1/sqrt(photons))"))
        n_scales = sum(len(r.scale) for r in comp.results if r.scale is not None)
        return FitResult(parameters=params, best=best, err_minus=err_m, err_plus=err_p, chi2=float(comp.chi2),
                         dof=comp.n - k - n_scales, chi2_surface=float(f_best), profile_check=profile_check,
                         covariance=_covariance(params, z_best, cov), comparison=comp,
                         scene=scene_with(scene, params, best, direction), uncertainty=self.uncertainty,
                         at_bound=at_bound, traces=dict(obj.traces), wall_s=time.perf_counter() - t0,
                         history=obj.history, mcmc=mcmc_info)

    def _search(self, obj: _Objective, z_start, grid: int, maxfev: int):
        """The best fit (unit cube), its covariance and the surface's chi^2 there."""
        k = len(z_start)
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
        for j in np.argsort(scores)[:self._starts(k)]:
            _minimise(obj, candidates[j], step, list(range(k)), candidates[j], self.fatol, maxfev)
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
        return z_best, cov, f_best

    def _profile_errors(self, obj: _Objective, params, z_best, cov, chi2_best: float, best, at_bound):
        """The profile likelihood's errors (minus, plus), from the profile itself, and its
        curvature against the quadratic's (``profile_check``).

        For each parameter i and side, chi^2 is minimised over the other parameters at
        :data:`PROFILE_STEPS` quadratic standard deviations sigma_i = sqrt(cov_ii) from the best
        fit (Nelder-Mead over the others, started where the quadratic puts their conditional
        optimum and continued outwards from the last step's optimum; parameter i alone: traced
        there). Each side's profile rises Delta chi^2_j at offsets d_j are fitted by least
        squares with a parabola through the best fit, Delta chi^2 = a d^2, and the error is
        where it reaches 1, 1 / sqrt(a). The fit averages the roughness of chi^2 (about 1 at a
        fit's Monte Carlo errors, as much as the rise that defines the error) over the steps,
        where one point's rise, or a secant through it, takes it whole. The chi^2 holds the
        run's frozen Monte Carlo errors beside the data's. A side whose rises do not grow (a
        <= 0: flat or too rough) gets the farthest step as its error, and its check is 0.
        ``profile_check``: a sigma_i^2 per side, 1 where the quadratic surface holds, above 1
        where the profile is narrower (the nuisance parameters cannot follow), below where it
        is wider. ``at_bound`` is filled in (the error reaches the parameter's bound)."""
        k = len(params)
        err_m, err_p = np.full(k, np.nan), np.full(k, np.nan)
        obj.stage = "profile"
        checks = {}
        maxfev = PROFILE_MAXFEV_PER_PARAMETER * (k - 1) + 4
        for i in range(k):
            sd = math.sqrt(cov[i, i])
            others = [j for j in range(k) if j != i]
            so = float(np.sqrt(np.max(np.diag(cov)[others]))) if others else 0.0
            for s, arr in ((-1, err_m), (1, err_p)):
                d, q = [], []
                z_prev = z_best.copy()
                for m in PROFILE_STEPS:
                    target = z_best[i] + s * m * sd
                    zi = min(max(target, 0.0), 1.0)
                    # the quadratic's conditional optimum of the others, moved from the last step
                    z0 = np.clip(z_prev + (zi - z_prev[i]) * cov[:, i] / cov[i, i], 0.0, 1.0)
                    z0[i] = zi
                    if others:
                        z_prev, chi2_p = _minimise(obj, z0, max(0.5 * so, 0.005), others, z0, self.fatol, maxfev)
                    else:
                        chi2_p = obj(z0)
                    if zi == z_best[i]:
                        break  # (at a bound already: no step out)
                    d.append(zi - z_best[i])
                    q.append(chi2_p - chi2_best)
                    if zi != target:
                        break  # the bound: no farther step
                d, q = np.abs(np.array(d)), np.array(q)
                a = float((d * d * q).sum() / (d ** 4).sum()) if d.size else 0.0
                err_z = 1.0 / math.sqrt(a) if a > 0 else (float(d.max()) if d.size else 0.0)
                zc = z_best[i] + s * err_z
                # past the bound, or on it with no room for a step (the best fit sits on it)
                on_it = not d.size and (z_best[i] >= 1.0 if s > 0 else z_best[i] <= 0.0)
                at_bound[i][0 if s < 0 else 1] = bool(zc < 0.0 or zc > 1.0 or on_it)
                zc = min(max(zc, 0.0), 1.0)
                arr[i] = abs(params[i].from_unit(zc) - best[i])
                checks[params[i].name + ("+" if s > 0 else "-")] = round(max(a, 0.0) * sd * sd, 3)
        return err_m, err_p, checks

    def _mcmc_errors(self, obj: _Objective, z_best, cov, walkers: int):
        """emcee's 16th-84th percentiles about the median, and the chain's summary."""
        import emcee  # optional: the fit extra, checked by parameters()

        k = len(z_best)
        steps = self.mcmc_steps
        obj.stage = "mcmc"
        rng = np.random.default_rng(int(self.scene.transport.seed))
        L = np.linalg.cholesky(cov) if cov is not None else 0.02 * np.eye(k)

        def log_prob(z):
            if np.any(z < 0) or np.any(z > 1):
                return -np.inf
            return -0.5 * obj(z)

        # walkers start in a ball of half the refined quadratic's width about the best fit
        p0 = np.clip(z_best[None] + 0.5 * rng.standard_normal((walkers, k)) @ L.T, 0.0, 1.0)
        sampler = emcee.EnsembleSampler(walkers, k, log_prob)
        # emcee starts its moves from numpy's global random state: seeded here, the chain is
        # the scene's (the same on every run and every rank of an MPI job)
        sampler.random_state = np.random.RandomState(int(self.scene.transport.seed) & 0xFFFFFFFF).get_state()
        sampler.run_mcmc(p0, steps, progress=False)
        chain = sampler.get_chain(discard=steps // 2, flat=True)
        vals = np.array([obj.values(z) for z in chain])
        q16, q50, q84 = np.percentile(vals, [16, 50, 84], axis=0)
        try:
            tau_ac = sampler.get_autocorr_time(discard=steps // 2, quiet=True).tolist()
        except Exception:  # too short a chain for an estimate
            tau_ac = None
        info = {"walkers": walkers, "steps": steps, "median": q50.tolist(),
                "acceptance": float(np.mean(sampler.acceptance_fraction)), "autocorr_steps": tau_ac}
        return q50 - q16, q84 - q50, info


def fit_observations(request, tables: Optional[Sequence[ObservedTable]] = None, free: Optional[Sequence] = None, *,
                     backend=None, progress: Optional[Callable] = None, cancel: Optional[Callable[[], bool]] = None,
                     **options) -> FitResult:
    """Find the parameters of a scene that best match observed tables (minimum chi^2).

    Parameters
    ----------
    request : FitRequest or Scene
        What to fit; or, as earlier, the scene, with ``tables``, ``free`` and the other
        :class:`FitRequest` fields as keywords (``options``).
    backend : Backend, optional
        Default: the scene's (``transport.backend``, ``transport.device``).
    progress : callable(done, total, best_chi2), optional
    cancel : callable() -> bool, optional

    Returns
    -------
    FitResult
    """
    if not isinstance(request, FitRequest):
        request = FitRequest(request, tables, free, **options)
    elif tables is not None or free is not None or options:
        raise TypeError("fit_observations: give a FitRequest alone, or a scene with tables, free and options")
    return request.run(backend=backend, progress=progress, cancel=cancel)


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
