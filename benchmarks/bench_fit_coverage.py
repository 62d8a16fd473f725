#!/usr/bin/env python
"""Coverage of the fit's errors: the problem of tests/observe/test_fit_coverage.py with more
realisations; prints and saves JSON.

    python benchmarks/bench_fit_coverage.py                       # 100 realisations, PoCL
    python benchmarks/bench_fit_coverage.py --realisations 200 --out benchmarks/results/fit-coverage.json

Each realisation: the truth's ratios (8^3 cube, one band, albedo 0.6, g 0.5; 2,000,000 packets)
plus Gaussian noise of the 4 % errors (numpy seed r), fitted (albedo and g free, profile errors)
by runs with seed 1000 + r. Reported: how many of the 1-sigma and 2-sigma intervals hold the
truth against the nominal 68.3 % and 95.4 % with the binomial standard deviation, the pulls'
mean and standard deviation per parameter (best - truth over the error on the truth's side),
traces and seconds per fit.
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

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "python"), str(ROOT / "tests"), str(ROOT / "tests" / "observe")]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--realisations", type=int, default=100)
    ap.add_argument("--photons", type=int, default=20_000, help="packets per band of each fit's runs")
    ap.add_argument("--out", default="benchmarks/results/fit-coverage.json")
    args = ap.parse_args(argv)
    import test_fit_coverage as problem
    from conftest import TEST_BACKEND, TEST_DEVICE
    from nebula_rt.backends import get_backend

    backend = get_backend(TEST_BACKEND, TEST_DEVICE)
    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    results = problem.coverage_run(backend, args.realisations, args.photons)
    wall = time.perf_counter() - t0
    n = 2 * len(results)
    truth = np.array(list(problem.TRUTH.values()))
    pulls = np.array([(b - truth) / np.where(b > truth, em, ep) for b, em, ep, *_ in results])
    out = {"benchmark": "fit coverage", "device": backend.describe() if hasattr(backend, "describe") else str(backend),
           "host": platform.node(), "realisations": len(results), "intervals": n, "photons": args.photons,
           "coverage": {}, "pull_mean": dict(zip(problem.TRUTH, pulls.mean(axis=0).round(3).tolist())),
           "pull_sd": dict(zip(problem.TRUTH, pulls.std(axis=0, ddof=1).round(3).tolist())),
           "traces_per_fit": float(np.mean([r[3] for r in results])),
           "seconds_per_fit": round(float(np.mean([r[4] for r in results])), 3), "wall_s": round(wall, 1),
           "command": "python benchmarks/bench_fit_coverage.py " + " ".join(argv or sys.argv[1:])}
    for width, p in problem.NOMINAL.items():
        got = problem.covered(results, width)
        out["coverage"][f"{width}_sigma"] = {"held": got, "fraction": round(got / n, 4), "nominal": round(p, 4),
                                             "binomial_sd_fraction": round(math.sqrt(p * (1 - p) / n), 4)}
    print(json.dumps(out, indent=2))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
