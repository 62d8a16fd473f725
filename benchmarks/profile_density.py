#!/usr/bin/env python
"""The density kernel alone on a GPU (CUDA): the thesis's turbulence with its star's bump, the
noise's tables in global memory (as built) and in constant memory (``NRT_TABLES_CONSTANT``,
as before), with the bits of both compared. A development aid for the headline's density stage.

    python benchmarks/profile_density.py [--grids 128 256] [--repeats 20] [--out d.json]
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--grids", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--out", default="")
    args = ap.parse_args(argv)
    import cupy as cp
    from nebula_rt.backends import get_backend
    from nebula_rt.backends.base import MODEL_TURBULENCE
    from nebula_rt.density.bumps import BUMP_SUBSAMPLES, stars_array
    from nebula_rt.scene import Scene

    be = get_backend("cuda", "")
    scene = Scene.load(ROOT / "examples/scenes/thesis-default.toml")
    dust = scene.dust
    stars = be.to_device(np.asarray(stars_array(scene.stars), np.float32).reshape(-1))
    out = {"benchmark": "profile_density", "date": time.strftime("%Y-%m-%d %H:%M:%S"), **provenance(),
           "device": be.device_name, "command": " ".join(sys.argv), "runs": []}
    for n in args.grids:
        arrays = {}
        for label, defines in (("constant tables", {"NRT_TABLES_CONSTANT": 1}), ("global tables", None)):
            d = be.device_zeros(n**3, np.float32)
            kernel_args = (d, np.int32(n), np.int32(n), np.int32(n), np.int32(MODEL_TURBULENCE),
                           np.float32(dust.offset[0]), np.float32(dust.offset[1]), np.float32(dust.offset[2]),
                           np.float32(dust.scale), np.float32(0.0), np.float32(dust.floor), stars,
                           np.int32(len(scene.stars)), np.int32(BUMP_SUBSAMPLES))
            times = []
            for _ in range(args.repeats + 1):
                start, stop = cp.cuda.Event(), cp.cuda.Event()
                start.record()
                be.launch("density.cl", "generate_density", n**3, *kernel_args, defines=defines)
                stop.record()
                stop.synchronize()
                times.append(cp.cuda.get_elapsed_time(start, stop))
            arrays[label] = d.get()
            ms = statistics.median(times[1:])
            print(f"{n}^3 {label:16s} {ms:7.3f} ms (median of {args.repeats})")
            out["runs"].append({"grid": n, "tables": label, "kernel_ms": ms, "times_ms": times[1:]})
        same = np.array_equal(arrays["constant tables"].view(np.uint32), arrays["global tables"].view(np.uint32))
        print(f"{n}^3 same bits: {same}")
        out["runs"][-1]["same_bits"] = bool(same)
    save(out, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
