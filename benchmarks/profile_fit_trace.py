#!/usr/bin/env python
"""Where a fit's trace spends its time: cProfile of the comparison trace that a fit makes for
every trial (``nebula_rt.observe.comparison.trace_rings``), on the thesis scene; prints and
saves JSON.

    python benchmarks/profile_fit_trace.py --backend cuda --shape 128 --photons 2.1e6
    python benchmarks/profile_fit_trace.py --shape 32 --photons 2e4          # CPU (PoCL)

The scene is examples/scenes/thesis-default.toml at ``--shape``^3, the rings of the fit benchmark's
tables (bench_fit.py), a peel-off image of ``--size`` pixels; one warm-up trace, then
``--traces`` traces with the albedo changed each time (as a fit's trials). Reported: wall time
per trace, the kernels' time per trace (the transport's own ``kernel_s``), and the functions
with the largest cumulative time per trace.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "python"))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--shape", type=int, default=128)
    ap.add_argument("--photons", type=float, default=2.1e6)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--traces", type=int, default=10)
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--device", default="")
    ap.add_argument("--out", default="benchmarks/results/fit-trace-profile.json")
    args = ap.parse_args()
    from nebula_rt.backends import get_backend
    from nebula_rt.density.generate import generate_density
    from nebula_rt.observe.comparison import trace_rings
    from nebula_rt.scene import Scene

    backend = get_backend(args.backend, args.device)
    scene = Scene.load(ROOT / "examples/scenes/thesis-default.toml").with_overrides([
        f"grid.shape=[{args.shape},{args.shape},{args.shape}]", f"transport.photons={int(args.photons)}",
        f'transport.backend="{args.backend}"', f'transport.device="{args.device}"'])
    edges = np.array([0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4])
    rho = generate_density(scene, backend)
    trace_rings(scene, edges, size=args.size, backend=backend, density=rho)  # warm-up: kernels built
    kernel_s = []
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    for i in range(args.traces):
        s = scene.with_overrides([f"bands.albedo={0.5 + 0.01 * i}"])
        trace_rings(s, edges, size=args.size, backend=backend, density=rho)
    prof.disable()
    wall = (time.perf_counter() - t0) / args.traces
    stats = pstats.Stats(prof)
    rows = []
    for (file, line, name), (cc, nc, tt, ct, _) in stats.stats.items():
        rows.append({"function": f"{Path(file).name}:{line}({name})", "calls_per_trace": nc / args.traces,
                     "cumulative_ms_per_trace": round(1e3 * ct / args.traces, 3),
                     "own_ms_per_trace": round(1e3 * tt / args.traces, 3)})
    rows.sort(key=lambda r: -r["cumulative_ms_per_trace"])
    text = io.StringIO()
    pstats.Stats(prof, stream=text).sort_stats("cumulative").print_stats(25)
    print(text.getvalue())
    out = {"benchmark": "fit trace profile", "shape": args.shape, "photons": int(args.photons), "size": args.size,
           "backend": args.backend, "device": args.device, "traces": args.traces,
           "wall_ms_per_trace": round(1e3 * wall, 3), "top_cumulative": rows[:40],
           "command": "python benchmarks/profile_fit_trace.py " + " ".join(sys.argv[1:])}
    print(json.dumps({k: v for k, v in out.items() if k != "top_cumulative"}, indent=2))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
