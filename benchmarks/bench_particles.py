#!/usr/bin/env python
"""A particle snapshot on a tree, end to end: deposit, transport, the light on a grid.

    python benchmarks/bench_particles.py [--backend opencl] [--device ""] [--particles 200000]
        [--depth 8] [--leaf-particles 8] [--photons 1e6] [--grid 128] [--out FILE.json]

Clumps of SPH particles (a lognormal-ish mix of Gaussian clumps on a thin background, positions
in a unit box, smoothing lengths from the local spacing) are deposited on an octree refined
by count down to ``--depth`` levels (256^3 effective at depth 8), traced with the thesis's bands
and written on a ``--grid``^3 output grid, through the scene path (``dust.file`` a .vtp). Prints
and saves the leaves, the effective resolution and the seconds of each stage.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def snapshot(n: int, seed: int = 3):
    rng = np.random.default_rng(seed)
    k = max(1, n // 20)
    parts = [rng.uniform(0.0, 1.0, (k, 3))]
    centres = rng.uniform(0.2, 0.8, (12, 3))
    widths = rng.uniform(0.01, 0.06, 12)
    counts = rng.multinomial(n - k, np.full(12, 1 / 12))
    for c, w, m in zip(centres, widths, counts):
        parts.append(rng.normal(c, w, (m, 3)))
    pos = np.clip(np.concatenate(parts), 1e-6, 1 - 1e-6)
    mass = np.full(len(pos), 1.0 / len(pos))
    h = np.full(len(pos), 0.01)
    return pos, mass, h


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="opencl")
    ap.add_argument("--device", default="")
    ap.add_argument("--particles", type=int, default=200_000)
    ap.add_argument("--depth", type=int, default=8)
    ap.add_argument("--leaf-particles", type=int, default=8)
    ap.add_argument("--photons", type=float, default=1e6)
    ap.add_argument("--grid", type=int, default=128)
    ap.add_argument("--tau", type=float, default=10.0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "filters"))
    from test_adaptive import _write_particles  # the suite's .vtp writer (VTK's XML poly data)

    from nebula_rt.pipeline import Pipeline
    from nebula_rt.scene import Scene

    folder = Path(tempfile.mkdtemp(prefix="nebula-particles-"))
    pos, mass, h = snapshot(args.particles)
    path = _write_particles(folder / "snap.vtp", pos, mass, h)
    scene = Scene.from_dict({
        "grid": {"shape": [args.grid] * 3},
        "dust": {"model": "file", "file": str(path), "tau": args.tau, "floor": 0.0,
                 "leaf_particles": args.leaf_particles, "tree_depth": args.depth},
        "stars": [{"position": [0.5, 0.5, 0.5], "temperature": 15000.0, "bump_radius": 0.0}],
        "transport": {"photons": int(args.photons), "backend": args.backend, "device": args.device,
                      "method": "analog"},
    })
    pipe = Pipeline()
    t0 = time.perf_counter()
    tree = pipe.density(scene)
    t1 = time.perf_counter()
    light = pipe.run(scene)
    t2 = time.perf_counter()
    res = light.transport
    rec = {"particles": len(pos), "leaves": tree.n_leaves, "depth": tree.depth(),
           "effective": 2 ** tree.depth(), "photons_per_band": int(args.photons), "bands": len(light.bands),
           "deposit_s": t1 - t0, "run_s": t2 - t1, "transport_s": light.timings["transport_s"],
           "kernel_s": float(res.timings["kernel_s"]), "finish_s": light.timings["finish_s"],
           "packets_per_ms": float(res.counts[:, 0].sum() / (res.timings["kernel_s"] * 1e3)),
           "device": res.device, "device_bytes": int(res.device_bytes)}
    for k, v in rec.items():
        print(f"{k:>18}: {v:,.3f}" if isinstance(v, float) else f"{k:>18}: {v}")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"benchmark": "bench_particles", "date": time.strftime("%Y-%m-%d %H:%M:%S"),
                                              "command": " ".join(["benchmarks/bench_particles.py"] + (argv or sys.argv[1:])),
                                              "record": rec}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
