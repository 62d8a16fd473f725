#!/usr/bin/env python
"""The density kernel alone on a GPU: the thesis's turbulence with its star's bump, with the
noise's tables where the backend reads them as built and in constant memory as before, the bits
of both compared. CUDA: global memory against ``NRT_TABLES_CONSTANT``; OpenCL: each work
group's local copy against ``NRT_NOISE_LOCAL=0``. A development aid for the headline's density
stage.

    python benchmarks/profile_density.py [--backend cuda|opencl] [--device SEL] [--grids 128 256]
                                         [--repeats 20] [--out d.json]

CUDA times the kernel with events; OpenCL with the host clock around each launch and a finish
of the queue (a few microseconds more).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))
from provenance import provenance, save


def _timed(be, launch) -> float:
    """Milliseconds of one launch on the device: CUDA events, else the host clock around the
    launch with the queue finished before and after."""
    if be.name == "cuda":
        import cupy as cp

        start, stop = cp.cuda.Event(), cp.cuda.Event()
        start.record()
        launch()
        stop.record()
        stop.synchronize()
        return cp.cuda.get_elapsed_time(start, stop)
    be.queue.finish()
    t = time.perf_counter()
    launch()
    be.queue.finish()
    return (time.perf_counter() - t) * 1e3


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="cuda")
    ap.add_argument("--device", default="")
    ap.add_argument("--grids", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--out", default="")
    args = ap.parse_args(argv)
    from nebula_rt.backends import get_backend
    from nebula_rt.backends.base import MODEL_TURBULENCE
    from nebula_rt.density.bumps import BUMP_SUBSAMPLES, stars_array
    from nebula_rt.scene import Scene

    be = get_backend(args.backend, args.device)
    variants = ({"constant tables": {"NRT_TABLES_CONSTANT": 1}, "global tables": None} if args.backend == "cuda"
                else {"constant tables": {"NRT_NOISE_LOCAL": 0}, "local tables": None})
    scene = Scene.load(ROOT / "examples/scenes/thesis-default.toml")
    dust = scene.dust
    stars = be.to_device(np.asarray(stars_array(scene.stars), np.float32).reshape(-1))
    out = {"benchmark": "profile_density", "date": time.strftime("%Y-%m-%d %H:%M:%S"), **provenance(),
           "device": be.device_name, "command": " ".join(sys.argv), "runs": []}
    for n in args.grids:
        arrays = {}
        for label, defines in variants.items():
            d = be.device_zeros(n**3, np.float32)
            kernel_args = (d, np.int32(n), np.int32(n), np.int32(n), np.int32(MODEL_TURBULENCE),
                           np.float32(dust.offset[0]), np.float32(dust.offset[1]), np.float32(dust.offset[2]),
                           np.float32(dust.scale), np.float32(0.0), np.float32(dust.floor), stars,
                           np.int32(len(scene.stars)), np.int32(BUMP_SUBSAMPLES))
            times = [_timed(be, lambda: be.launch("density.cl", "generate_density", n**3, *kernel_args,
                                                  defines=defines)) for _ in range(args.repeats + 1)]
            arrays[label] = be.to_host(d)
            ms = statistics.median(times[1:])
            print(f"{n}^3 {label:16s} {ms:7.3f} ms (median of {args.repeats})")
            out["runs"].append({"grid": n, "tables": label, "kernel_ms": ms, "times_ms": times[1:]})
        first, second = arrays.values()
        same = np.array_equal(first.view(np.uint32), second.view(np.uint32))
        print(f"{n}^3 same bits: {same}")
        out["runs"][-1]["same_bits"] = bool(same)
    save(out, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
