#!/usr/bin/env python
"""Fit benchmark: the thesis scene with 3 free parameters (albedo, g, tau); prints and saves JSON.

    python benchmarks/bench_fit.py                          # 64^3, 1M packets per band per trial
    python benchmarks/bench_fit.py --shape 128 --photons 2.1e6
    python benchmarks/bench_fit.py --uncertainty both       # profile and MCMC on one problem
    python benchmarks/bench_fit.py --quick                  # a smoke run on the CPU (16^3)
    python benchmarks/bench_fit.py --device NVIDIA --out benchmarks/results/fit-gpu.json

The problem: examples/scenes/thesis-default.toml (turbulence, the star at the centre inside its
dust bump, thesis-rgb bands) with albedo 0.6, g 0.6, tau 128 is observed along -z by a run of
``--truth-photons`` packets per band (seed 99): Delta(B-V) in 4 annuli (error ``--colour-err``
mag) and the absolute nebula/star ratio at 3 wavelengths in 3 annuli (relative error
``--ratio-err``), plus Gaussian noise of those errors. The fit starts at albedo 0.5, g 0.45,
tau 90 with bounds albedo [0.02, 0.98], g [0, 0.95], tau [32, 512] (log) and traces
``--photons`` packets per band per trial, seed 1 for every trial (common random numbers).

Reported: traces per stage, wall time of the fit, seconds per trace, the best fit with its
errors, the pulls (best - truth) / error, chi^2 and dof, and the largest model/data error ratio
(the fit wants it well below 1: raise --photons otherwise).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "python"))
SCENE = ROOT / "examples" / "scenes" / "thesis-default.toml"
TRUTH = {"albedo": 0.6, "g": 0.6, "tau": 128.0}
START = {"albedo": 0.5, "g": 0.45, "tau": 90.0}
FREE = ["albedo=0.02:0.98", "g=0:0.95", "tau=32:512:log"]


def tables(scene, args, backend):
    from nebula_rt.observe import comparison
    from nebula_rt.observe.observed_tables import ObservedTable, _annuli_from_offsets

    truth = scene.with_overrides([f"bands.albedo={TRUTH['albedo']}", f"bands.g={TRUTH['g']}",
                                  f"dust.tau={TRUTH['tau']}", f"transport.photons={int(args.truth_photons)}",
                                  "transport.seed=99"])
    offs = np.array([0.05, 0.15, 0.25, 0.35])
    col = ObservedTable("colour", "synthetic colour", offs, np.zeros(4), np.full(4, args.colour_err),
                        *_annuli_from_offsets(offs, "offset"))
    wl = np.array([450.0, 550.0, 650.0])
    ann = [(0.0, 0.1), (0.1, 0.25), (0.25, 0.4)]
    x = np.tile(wl, len(ann))
    lo, hi = np.repeat([a[0] for a in ann], 3), np.repeat([a[1] for a in ann], 3)
    rat = ObservedTable("ratio", "synthetic ratio", x, np.ones(9), np.ones(9), lo, hi, normalisation="absolute")
    t0 = time.perf_counter()
    comp = comparison.compare(truth, [col, rat], size=args.size, backend=backend)
    truth_s = time.perf_counter() - t0
    rng = np.random.default_rng(4)
    col.value = comp.results[0].model + col.error * rng.standard_normal(4)
    rat.error = args.ratio_err * comp.results[1].model
    rat.value = comp.results[1].model + rat.error * rng.standard_normal(9)
    return [col, rat], truth_s


def run(method, scene, obs, args, backend):
    from nebula_rt.observe import fit

    t0 = time.perf_counter()
    res = fit.fit_observations(scene, obs, FREE, size=args.size, uncertainty=method, backend=backend,
                               start=[START[n] for n in ("albedo", "g", "tau")], mcmc_steps=args.mcmc_steps)
    wall = time.perf_counter() - t0
    n = sum(res.traces.values())
    out = {"uncertainty": method, "wall_s": round(wall, 2), "traces": res.traces, "traces_total": n,
           "s_per_trace": round(wall / n, 4), "chi2": round(res.chi2, 3), "dof": res.dof,
           "max_model_to_data_error": round(res.comparison.model_error_ratio(), 3), "parameters": {}}
    for i, p in enumerate(res.parameters):
        v, want = float(res.best[i]), TRUTH[p.name]
        err = res.err_minus[i] if v > want else res.err_plus[i]
        out["parameters"][p.name] = {"best": v, "err_minus": float(res.err_minus[i]),
                                     "err_plus": float(res.err_plus[i]), "truth": want,
                                     "pull": float((v - want) / err) if err > 0 else None}
    if res.mcmc:
        out["mcmc"] = res.mcmc
    if res.profile_check:
        out["profile_check_rise"] = res.profile_check
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shape", type=int, default=64, help="grid voxels per side (default 64; the thesis: 128)")
    ap.add_argument("--photons", type=float, default=1e6, help="packets per band per trial (default 1e6)")
    ap.add_argument("--truth-photons", type=float, default=2e7, help="packets per band of the observation (2e7)")
    ap.add_argument("--colour-err", type=float, default=0.03, help="Delta(B-V) error, mag (default 0.03)")
    ap.add_argument("--ratio-err", type=float, default=0.05, help="relative ratio error (default 0.05)")
    ap.add_argument("--size", type=int, default=64, help="peel-off image pixels per side (default 64)")
    ap.add_argument("--uncertainty", default="profile", choices=["profile", "mcmc", "both"])
    ap.add_argument("--mcmc-steps", type=int, default=200)
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--device", default="")
    ap.add_argument("--quick", action="store_true", help="16^3, 10k packets: a smoke run on the CPU")
    ap.add_argument("--out", default=None, help="JSON output (default benchmarks/results/fit-<device>.json)")
    args = ap.parse_args()
    if args.quick:
        args.shape, args.photons, args.truth_photons, args.size = 16, 1e4, 2e5, 24
        args.colour_err, args.ratio_err, args.mcmc_steps = 0.12, 0.15, 60

    from nebula_rt.backends import get_backend
    from nebula_rt.scene import Scene

    backend = get_backend(args.backend, args.device)
    scene = Scene.load(SCENE).with_overrides([
        f"grid.shape=[{args.shape},{args.shape},{args.shape}]", f"transport.photons={int(args.photons)}",
        "transport.seed=1", f'transport.backend="{args.backend}"', f'transport.device="{args.device}"'])
    obs, truth_s = tables(scene, args, backend)
    methods = ["profile", "mcmc"] if args.uncertainty == "both" else [args.uncertainty]
    report = {"benchmark": "fit", "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
              "host": platform.node(), "device": getattr(backend, "device_name", str(backend)),
              "scene": str(SCENE.relative_to(ROOT)), "shape": [args.shape] * 3, "bands": "thesis-rgb",
              "photons_per_band_per_trial": int(args.photons), "truth_photons": int(args.truth_photons),
              "truth_trace_s": round(truth_s, 2), "free": FREE, "truth": TRUTH, "start": START,
              "colour_err_mag": args.colour_err, "ratio_rel_err": args.ratio_err, "runs": []}
    for m in methods:
        r = run(m, scene, obs, args, backend)
        report["runs"].append(r)
        print(f"{m}: {r['traces_total']} traces in {r['wall_s']} s ({r['s_per_trace']} s/trace), "
              f"chi2 {r['chi2']} / {r['dof']} dof, model/data error {r['max_model_to_data_error']}", flush=True)
        for name, p in r["parameters"].items():
            print(f"  {name:7s} {p['best']:.5g} -{p['err_minus']:.3g} +{p['err_plus']:.3g}  (truth {p['truth']}, "
                  f"pull {p['pull']:+.2f})", flush=True)
    tag = "".join(c if c.isalnum() else "-" for c in str(report["device"]).lower()).strip("-")[:40] or "device"
    out = Path(args.out) if args.out else ROOT / "benchmarks" / "results" / f"fit-{tag}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
