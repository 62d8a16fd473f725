#!/usr/bin/env python
"""Scaling on a GPU: time and peak device memory over grid size and photon count.

    python benchmarks/bench_scaling.py [--backend cuda] [--out FILE]

Scene: the neb128 medium (uniform dust, optical depth 1 from the centre to a face, albedo 0.6,
g 0.6, one band, source at the centre) on grids 64^3 .. 1024^3 and 1e6 .. 1e9 packets.
Each configuration runs in its own process after a warm-up (compile excluded). Peak device
memory is CuPy's memory-pool high-water mark (all device arrays of the run: density, batch
slots, sums, post-processing). The largest grids are tried until one does not fit.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

GRIDS = [(64, [1e6, 1e7, 1e8]), (128, [1e6, 1e7, 1e8, 1e9]), (256, [1e6, 1e7, 1e8]),
         (512, [1e6, 1e7, 1e8]), (768, [1e6]), (1024, [1e6])]


def single(n: int, photons: int, backend_name: str) -> dict:
    import cupy as cp

    from nebula_rt.backends import get_backend
    from nebula_rt.pipeline import Pipeline
    from nebula_rt.scene import Scene

    def scene(nn, p):
        return Scene.from_dict({
            "grid": {"shape": [nn, nn, nn]},
            "dust": {"model": "uniform", "density": 1.0, "floor": 0.0, "tau": 2.0},
            "bands": {"list": [{"name": "V", "wavelength": 550.0, "extinction": 1.0, "albedo": 0.6, "g": 0.6}]},
            "transport": {"photons": int(p), "backend": backend_name},
        })

    backend = get_backend(backend_name, "")
    Pipeline(backend).run(scene(16, 10_000), colour=False)
    pool = cp.get_default_memory_pool()
    pool.free_all_blocks()
    t0 = time.perf_counter()
    light = Pipeline(backend).run(scene(n, photons), colour=False)
    wall = time.perf_counter() - t0
    peak = pool.total_bytes()
    k = light.timings["kernel_s"]
    return {"grid": n, "photons": int(photons), "kernel_s": round(k, 4), "end_to_end_s": round(wall, 4),
            "photons_per_ms": round(photons / (k * 1e3)), "peak_device_mib": round(peak / 2**20, 1),
            "absorbed_fraction": float(light.transport.counts[0, 1] / photons), "device": backend.device_name}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="cuda")
    ap.add_argument("--out", default=None)
    ap.add_argument("--single", nargs=2, type=float, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.single:
        print("ROW" + json.dumps(single(int(args.single[0]), int(args.single[1]), args.backend)))
        return 0
    rows, largest = [], None
    for n, counts in GRIDS:
        for p in counts:
            proc = subprocess.run([sys.executable, __file__, "--backend", args.backend, "--single", str(n), str(p)],
                                  capture_output=True, text=True)
            line = next((l for l in proc.stdout.splitlines() if l.startswith("ROW")), None)
            if line is None:
                err = (proc.stderr.strip().splitlines() or ["?"])[-1]
                print(f"{n:5d}^3 {int(p):>14,d} photons  FAILED: {err[:160]}", flush=True)
                rows.append({"grid": n, "photons": int(p), "error": err[:400]})
                break
            row = json.loads(line[3:])
            rows.append(row)
            largest = n
            print(f"{n:5d}^3 {int(p):>14,d} photons  kernel {row['kernel_s']:9.3f} s  end to end {row['end_to_end_s']:9.3f} s  "
                  f"{row['photons_per_ms']:>9,d} photons/ms  peak device {row['peak_device_mib']:9.1f} MiB  "
                  f"absorbed {row['absorbed_fraction']:.5f}", flush=True)
    result = {"benchmark": "scaling", "backend": args.backend, "rows": rows, "largest_grid_that_ran": largest}
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
