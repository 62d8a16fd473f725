#!/usr/bin/env python
"""Where the host time of one end-to-end run goes (cProfile of ``Pipeline.run``), after a
warm-up on the same grid: the Python-side checks and bookkeeping around the kernels.

    python benchmarks/profile_host.py [--backend cuda] [--device SEL] [--photons 2.1e6] [--top 25]

A development aid, not a benchmark (the profiler slows Python code down).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--backend", default="cuda")
    ap.add_argument("--device", default="")
    ap.add_argument("--photons", type=float, default=2.1e6)
    ap.add_argument("--top", type=int, default=25)
    args = ap.parse_args()
    from bench_neb128 import nebula_scene

    from nebula_rt.backends import get_backend
    from nebula_rt.pipeline import Pipeline

    backend = get_backend(args.backend, args.device)
    Pipeline(backend).run(nebula_scene(10_000, args.backend, args.device), colour=False)
    scene = nebula_scene(int(args.photons), args.backend, args.device)
    t0 = time.perf_counter()
    Pipeline(backend).run(scene, colour=False)
    plain = time.perf_counter() - t0
    prof = cProfile.Profile()
    prof.enable()
    light = Pipeline(backend).run(scene, colour=False)
    prof.disable()
    print(f"end to end {plain * 1e3:.1f} ms unprofiled; stages {light.timings}")
    pstats.Stats(prof).sort_stats("tottime").print_stats(args.top)


if __name__ == "__main__":
    main()
