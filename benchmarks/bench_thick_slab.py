"""Light through thick dust: accuracy against the exact answer beside precision and speed.

The scene of tests/transport/test_thick_slab.py (tests/slab_scene.py): a slab of 4 voxel layers of
vertical optical depth tau, lit by a star just above it, seen from below; the transmitted
T(mu = 1) of every run is held against the adding-doubling solution of the infinite slab
(tests/oracles/plane_parallel.py); with ``--sides above`` the camera is on the star's side and
the run's R(mu = 1) is held against it. For each case (side, albedo, g, tau, method and, for
weighted packets, the windows' importance: ``--importance stars observer``), ``--seeds`` runs
give:

- accuracy: the mean of run / exact, its standard error from the scatter of the runs, and the
  worst run in its own stated errors (the pull);
- honesty: the fractions of runs within 1 and 2 stated sigma of the exact value; every run's
  pull (run - exact) / stated error and whether the heavy-tail checks flagged its image; and,
  pooled over albedo and g per side, depth and method (16 seeds of one case give a fraction
  with a binomial spread of 12 %), the coverage of all runs and of the runs the checks passed,
  with their binomial standard errors (``pooled`` in the JSON);
- precision and speed: the median stated relative error, the mean wall time of a run (kernels
  built beforehand) and the figure of merit FOM = 1 / (sigma^2 t) (larger is better). A FOM
  of a method that misses the exact value by more than 5 of its standard errors is printed
  but flagged ``biased``: precision without accuracy.

The library measured is whichever ``nebula_rt`` Python imports: to measure another commit's
method on the same scenes, put its ``python/`` first on PYTHONPATH (``--label`` names it; the
recorded commit and sources digest are then this checkout's, ``library`` says which ran).

    python benchmarks/bench_thick_slab.py --backend opencl --out results.json
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from oracles.plane_parallel import PointSourceSlab, Slab  # noqa: E402
from slab_scene import image_power, peel_bins, slab  # noqa: E402

import nebula_rt  # noqa: E402
from provenance import provenance  # noqa: E402  (benchmarks/provenance.py)
from nebula_rt.backends import get_backend  # noqa: E402
from nebula_rt.errors import NebulaWarning  # noqa: E402
from nebula_rt.transport import trace  # noqa: E402


def measure(backend, albedo, g, tau, method, photons, seeds, side="below", importance="auto"):
    rho, bands, stars, kappa, cam = slab(tau, albedo=albedo, g=g, side=side)
    oracle = PointSourceSlab(Slab(tau, albedo, g))
    exact = oracle.transmitted(1.0) if side == "below" else oracle.reflected(1.0)
    kw = dict(tau=kappa, backend=backend, method=method, peel=cam, peel_bins=peel_bins(cam), importance=importance)
    vals, errs, times, flagged = [], [], [], []
    ran = ""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NebulaWarning)
        trace(rho, bands, stars, photons=min(photons, 10_000), **kw)  # builds this option set's kernels
        for seed in range(1, seeds + 1):
            t0 = time.perf_counter()
            r = trace(rho, bands, stars, photons=photons, seed=seed, **kw)
            times.append(time.perf_counter() - t0)
            ran = r.importance
            v, se = image_power(r, cam)
            vals.append(v / exact)
            errs.append(se / exact)
            flagged.append(not r.tail_image[0].reliable)  # the heavy-tail checks (nebula_rt.transport.tails)
    vals, errs = np.array(vals), np.array(errs)
    rel = np.where(vals > 0, errs / np.where(vals > 0, vals, 1.0), np.inf)
    pulls = np.where(errs > 0, (vals - 1.0) / np.where(errs > 0, errs, 1.0), np.inf)
    mean = float(vals.mean())
    se_mean = float(vals.std(ddof=1) / math.sqrt(seeds)) if seeds > 1 else math.inf
    sigma, t = float(np.median(rel)), float(np.mean(times))
    return {"albedo": albedo, "g": g, "tau": tau, "side": side, "method": method, "importance": ran,
            "photons": photons, "seeds": seeds,
            "exact": exact, "mean_ratio": mean, "se_mean": se_mean,
            "biased": bool(abs(mean - 1.0) > 5 * se_mean + 1e-12),
            "within_1_sigma": float(np.mean(np.abs(pulls) < 1)), "within_2_sigma": float(np.mean(np.abs(pulls) < 2)),
            "pulls": pulls.tolist(), "flagged": flagged,
            "worst_pull": float(pulls[np.argmax(np.abs(pulls))]), "median_rel_error": sigma, "time_s": t,
            "fom": 1.0 / (sigma**2 * t) if np.isfinite(sigma) and sigma > 0 else 0.0}


def pooled(rows) -> list[dict]:
    """Coverage of the stated errors pooled over albedo and g: per (side, depth, method,
    importance), the fraction of runs within 1 and 2 sigma of the exact value, of all runs and
    of those the heavy-tail checks passed, each with its binomial standard error."""
    def frac(x):
        n = len(x)
        p = float(np.mean(x)) if n else math.nan
        return p, math.sqrt(p * (1 - p) / n) if n else math.nan

    groups = {}
    for r in rows:
        groups.setdefault((r["side"], r["tau"], r["method"], r["importance"]), []).append(r)
    out = []
    for (side, tau, method, imp), rs in groups.items():
        pulls = np.abs(np.concatenate([r["pulls"] for r in rs]))
        ok = ~np.concatenate([r["flagged"] for r in rs]).astype(bool)
        row = {"side": side, "tau": tau, "method": method, "importance": imp, "runs": int(pulls.size),
               "passed_checks": int(ok.sum())}
        for name, sel in (("all", np.ones_like(ok)), ("passed", ok)):
            for k in (1, 2):
                row[f"within_{k}_sigma_{name}"], row[f"within_{k}_sigma_{name}_se"] = frac(pulls[sel] < k)
        out.append(row)
        print(f"pooled {'T' if side == 'below' else 'R'} tau {tau:5.1f} {method:7s} {imp or '-':8s} "
              f"{pulls.size} runs: within 1 / 2 sigma {row['within_1_sigma_all']:.3f} +- "
              f"{row['within_1_sigma_all_se']:.3f} / {row['within_2_sigma_all']:.3f} +- {row['within_2_sigma_all_se']:.3f};"
              f" the {ok.sum()} the checks passed: {row['within_1_sigma_passed']:.3f} / {row['within_2_sigma_passed']:.3f}",
              flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="opencl")
    ap.add_argument("--device", default="")
    ap.add_argument("--photons", type=float, default=1e5)
    ap.add_argument("--seeds", type=int, default=16)
    ap.add_argument("--taus", type=float, nargs="+", default=[10, 20, 30, 60])
    ap.add_argument("--albedos", type=float, nargs="+", default=[0.3, 0.6, 0.9])
    ap.add_argument("--gs", type=float, nargs="+", default=[0.0, 0.6])
    ap.add_argument("--methods", nargs="+", default=["auto", "analog", "biased"])
    ap.add_argument("--sides", nargs="+", default=["below"], choices=["below", "above"],
                    help="where the camera is: below the slab (T) or above, on the star's side (R)")
    ap.add_argument("--importance", nargs="+", default=["auto"], choices=["auto", "stars", "observer"],
                    help="the weighted packets' windows (trace(importance=...)); analog runs take one")
    ap.add_argument("--label", default="", help="a name for the library measured (e.g. a commit)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    backend = get_backend(a.backend, a.device)
    rows = []
    cases = [(side, albedo, g, tau, method, imp) for side in a.sides for albedo in a.albedos for g in a.gs
             for tau in a.taus for method in a.methods for imp in (a.importance if method != "analog" else ["auto"])]
    for side, albedo, g, tau, method, imp in cases:
        row = measure(backend, albedo, g, tau, method, int(a.photons), a.seeds, side, imp)
        rows.append(row)
        print(f"{'T' if side == 'below' else 'R'} a {albedo:4.2f} g {g:4.2f} tau {tau:5.1f} {method:7s} "
              f"{row['importance'] or '-':8s} ratio {row['mean_ratio']:.4f} "
              f"+- {row['se_mean']:.4f}  in 1/2 sigma {row['within_1_sigma']:.2f}/"
              f"{row['within_2_sigma']:.2f}  worst {row['worst_pull']:+.1f}  err "
              f"{row['median_rel_error']:.3e}  t {row['time_s']:.3f} s  FOM {row['fom']:.3e}"
              f"{'  BIASED' if row['biased'] else ''}", flush=True)
    result = {"benchmark": "bench_thick_slab", "label": a.label, "library": str(Path(nebula_rt.__file__).parent),
              "device": backend.device_name, "backend": a.backend, "python": platform.python_version(),
              "command": " ".join(sys.argv), **provenance(), "rows": rows, "pooled": pooled(rows)}
    if a.out:
        with open(a.out, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
