#!/usr/bin/env python
"""Transport by regions: kernel packets per ms against the region size, on any backend.

    python benchmarks/bench_regions.py [--backend opencl|cuda] [--device SEL] [--grids 64 128 256]
        [--shifts 0 4 5 6] [--photons 4e5] [--repeats 2] [--tail 4096] [--out FILE.json]

Scene: the neb medium of benchmarks/bench_large_grids.py on n^3 voxels (uniform dust, optical
depth 1 from the centre to a face, albedo 0.6, g 0.6, a point source at the centre). For every
grid and region shift (regions of 2^shift voxels a side; 0: no regions, every packet traced in
one go) the transport's kernel time (``timings["kernel_s"]``: its launches, the region passes
and their sorts included) of the best of ``--repeats`` runs after a warm-up, packets per ms of
it, and the packet counts, which must be the same for every shift (same bits). ``--tail``: the
packets left below which a launch's last pass runs them to the end (``region_tail``).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "python"))
from provenance import provenance  # noqa: E402  (benchmarks/provenance.py)

from nebula_rt.optics.bands import Band  # noqa: E402
from nebula_rt.scene.sections import Star  # noqa: E402
from nebula_rt.transport import trace  # noqa: E402


def make_backend(kind: str, device: str, tuning: dict):
    if kind == "cuda":
        from nebula_rt.backends.cuda import CUDABackend

        return CUDABackend(device, transport_tuning=tuning)
    from nebula_rt.backends.opencl import OpenCLBackend

    return OpenCLBackend(device or "Portable Computing Language", transport_tuning=tuning)


def _registers(be):
    """Registers per thread of the transport kernel as built (CUDA; None elsewhere)."""
    try:
        regs = [int(k.attributes["num_regs"]) for key, k in be._kernels.items() if "trace_photons" in str(key)]
    except (AttributeError, KeyError, TypeError):
        return None
    return max(regs) if regs else None


def run(args) -> dict:
    bands = [Band(name="V", wavelength=550.0, extinction=1.0, albedo=0.6, g=0.6)]
    stars = [Star(position=(0.5, 0.5, 0.5), luminosity=1.0, temperature=None, bump_radius=0.0)]
    photons = int(args.photons)
    rows = []
    for n in args.grids:
        rho = np.ones((n, n, n), np.float32)
        counts0 = None
        for shift, regcap in [(s, r) for s in args.shifts for r in (args.regcaps or [None])]:
            tuning = {"NRT_REGIONS": int(shift)}
            if shift:
                tuning["region_tail"] = int(args.tail)
            if regcap is not None:
                tuning["max_registers"] = int(regcap)
            be = make_backend(args.backend, args.device, tuning)
            if args.warmup:  # build the kernels, warm the device up
                trace(rho[:16, :16, :16].copy(), bands, stars, tau=2.0, photons=20_000, backend=be)
            best = None
            for _ in range(max(1, args.repeats)):
                t0 = time.perf_counter()
                res = trace(rho, bands, stars, tau=2.0, photons=photons, seed=3, backend=be)
                wall = time.perf_counter() - t0
                k = float(res.timings["kernel_s"])
                best = (k, wall) if best is None or k < best[0] else best
            counts = np.asarray(res.counts).tolist()
            counts0 = counts if counts0 is None else counts0
            row = {"grid": n, "shift": int(shift), "regcap": regcap, "registers": _registers(be),
                   "photons": photons, "kernel_s": best[0], "wall_s": best[1],
                   "kernel_packets_per_ms": photons / (best[0] * 1e3), "counts": counts,
                   "same_counts_as_first": counts == counts0}
            rows.append(row)
            print(f"{n:5d}^3  regions {'2^' + str(shift) if shift else 'none':>5s}  registers {row['registers']} "
                  f"(cap {'default' if regcap is None else regcap or 'none'})  kernel {best[0]:7.3f} s  "
                  f"wall {best[1]:7.3f} s  {row['kernel_packets_per_ms']:9.1f} pkt/ms  counts {counts}", flush=True)
    return {"benchmark": "bench_regions", "device": be.device_name, "backend": args.backend,
            "host": platform.node(), "date": time.strftime("%Y-%m-%d"),
            **provenance(),
            "command": " ".join(["benchmarks/bench_regions.py"] + sys.argv[1:]), "tail": args.tail, "rows": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="opencl", choices=("opencl", "cuda"))
    ap.add_argument("--device", default="")
    ap.add_argument("--grids", type=int, nargs="+", default=[64, 128, 256])
    ap.add_argument("--shifts", type=int, nargs="+", default=[0, 4, 5, 6])
    ap.add_argument("--photons", type=float, default=4e5)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--tail", type=int, default=4096)
    ap.add_argument("--regcaps", type=int, nargs="+", default=None,
                    help="CUDA: register caps to build the transport kernel with (tuning max_registers; "
                         "0: none; default: the backend's)")
    ap.add_argument("--warmup", type=int, default=1, help="0: no warm-up trace (the profiler then counts "
                                                         "the measured run's launches from 0)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    out = run(args)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1))
        print(f"saved {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
