#!/usr/bin/env python
"""The transport on a tree against the uniform grid it was made from, side by side in one run.

    python benchmarks/bench_tree.py [--backend cuda] [--device ""] [--grid 128] [--photons 2.1e6]
        [--tolerances 0 0.05 0.2] [--roots 8] [--out FILE.json]

The thesis scene's turbulent density on n^3 voxels, traced as the grid and as octrees made
from it (``coarsen``: 2^3 blocks whose values differ by at most ``tolerance`` x their mean
merged, up to roots of n / roots voxels): leaves, device bytes, kernel time, packets per ms
and the absorbed fraction of the reference band. Tolerance 0 merges only equal voxels (the
bump around the star and the floor), so that tree is nearly the grid's voxels: it measures
the walk's own cost against the grid's. Each configuration is traced once untimed (kernel
builds) and then timed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from tuning import add_tuning_argument, apply_tuning  # noqa: E402  (benchmarks/tuning.py, beside this script)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="cuda")
    ap.add_argument("--device", default="")
    ap.add_argument("--grid", type=int, default=128)
    ap.add_argument("--photons", type=float, default=2.1e6)
    ap.add_argument("--tolerances", type=float, nargs="+", default=[0.0, 0.05, 0.2])
    ap.add_argument("--roots", type=int, default=8, help="root cells per axis")
    add_tuning_argument(ap)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    from nebula_rt.backends import get_backend
    from nebula_rt.density import generate_density
    from nebula_rt.density.octree import coarsen
    from nebula_rt.scene import Scene
    from nebula_rt.transport.request import TransportRequest

    be = get_backend(args.backend, args.device)
    apply_tuning(be, args.tuning)
    n = args.grid
    scene = Scene.load(ROOT / "examples/scenes/thesis-default.toml").with_overrides(
        [f"grid.shape=[{n},{n},{n}]", f"transport.photons={int(args.photons)}", 'transport.method="analog"'])
    rho = np.array(generate_density(scene, be), np.float32)
    request = TransportRequest.from_scene(scene)
    records = []

    def run(label, medium, leaves):
        request.trace(medium, be)  # builds
        t0 = time.perf_counter()
        res = request.trace(medium, be)
        wall = time.perf_counter() - t0
        packets = int(res.counts[:, 0].sum())
        rec = {"medium": label, "cells": int(leaves), "device_bytes": int(res.device_bytes),
               "kernel_s": float(res.timings["kernel_s"]), "wall_s": wall,
               "packets_per_ms": packets / (res.timings["kernel_s"] * 1e3),
               "absorbed_fraction": float(res.counts[0, 1] / res.counts[0, 0])}
        records.append(rec)
        print(f"{label:<26} cells {leaves:>10,}  kernel {rec['kernel_s'] * 1e3:8.2f} ms  "
              f"{rec['packets_per_ms']:>10,.0f} packets/ms  wall {wall * 1e3:8.1f} ms  "
              f"absorbed {rec['absorbed_fraction']:.6f}  device {rec['device_bytes'] / 2**20:.0f} MiB", flush=True)

    run(f"grid {n}^3", rho, rho.size)
    for tol in args.tolerances:
        t0 = time.perf_counter()
        tree = coarsen(rho, (args.roots,) * 3, tol)
        made = time.perf_counter() - t0
        run(f"tree tolerance {tol:g}", tree, tree.n_leaves)
        records[-1].update(tolerance=tol, depth=tree.depth(), nodes=int(tree.child.size), coarsen_s=made)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({
            "benchmark": "bench_tree", "date": time.strftime("%Y-%m-%d %H:%M:%S"), "device": be.device_name,
            "command": " ".join(["benchmarks/bench_tree.py"] + (argv or sys.argv[1:])), "records": records}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
