#!/usr/bin/env python
"""The thesis headline end to end (density, transport, finishing with colour, arrays on the
host), repeated, with the finishing's light made band by band while the transport folds
(``backend.light_while_folding``, as built) and after it, the runs of the two interleaved so
that the GPU's clocks and the host's state affect both alike. Prints and saves JSON.

    python benchmarks/bench_headline.py --backend cuda [--repeats 15] [--grid 128]
        [--photons 2.1e6] [--modes while after] [--out FILE.json]

A fresh Pipeline each run (no stage is reused); the backend, its compiled kernels and memory
pools are warm (one run with 1000 packets and one full run first, not counted). Reported per
mode: the median and the least of the wall time and of the pipeline's own stage timings.
Another version of the library (e.g. a former commit's python/ on PYTHONPATH) runs with
``--modes while`` (a backend without the attribute ignores it).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))

from profile_timeline import add_headline_arguments, headline_setup, synchronizer  # noqa: E402
from provenance import provenance, save  # noqa: E402  (benchmarks/provenance.py)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_headline_arguments(ap)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--modes", nargs="+", default=["while", "after"], choices=["while", "after"])
    ap.add_argument("--label", default="as built", help="what the library on the path is (for the listing)")
    ap.add_argument("--out", default="")
    args = ap.parse_args(argv)
    from nebula_rt.pipeline import Pipeline

    backend, scene = headline_setup(args)
    sync = synchronizer(backend)
    for mode in args.modes:
        backend.light_while_folding = mode == "while"
        Pipeline(backend).run(scene)
    rows: dict = {m: [] for m in args.modes}
    for _ in range(args.repeats):
        for mode in args.modes:
            backend.light_while_folding = mode == "while"
            sync()
            t0 = time.perf_counter()
            light = Pipeline(backend).run(scene)
            sync()
            wall = (time.perf_counter() - t0) * 1e3
            rows[mode].append({"wall_ms": wall, **{k.replace("_s", "_ms"): v * 1e3 for k, v in light.timings.items()}})
            del light
    out = {"benchmark": "bench_headline", "date": time.strftime("%Y-%m-%d %H:%M:%S"), **provenance(),
           "device": backend.device_name, "command": " ".join(sys.argv), "grid": args.grid,
           "photons": int(args.photons), "label": args.label, "runs": rows, "summary": {}}
    for mode, runs in rows.items():
        keys = runs[0].keys()
        med = {k: statistics.median(r[k] for r in runs) for k in keys}
        least = {k: min(r[k] for r in runs) for k in keys}
        out["summary"][mode] = {"median": med, "least": least}
        print(f"{args.label:10s} light {mode:5s} end to end median {med['wall_ms']:6.2f} ms (least "
              f"{least['wall_ms']:6.2f}); " + ", ".join(f"{k[:-3]} {v:.2f}" for k, v in med.items() if k != "wall_ms")
              + " ms",
              flush=True)
    save(out, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
