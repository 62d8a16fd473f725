#!/usr/bin/env python
"""What empty space costs: a mostly empty scene against a full one, same photons.

    python benchmarks/bench_empty_space.py [--backend opencl|cuda] [--device SEL] [--grid 64]
                                           [--photons 1e6] [--out FILE.json]

Scenes on one grid, one band (albedo 0.6, g 0.6), star at the centre:
  full       uniform dust, optical depth 2 from the centre to a face;
  clump      the same dust only inside a sphere of radius 0.15 (2 % of the voxels), vacuum
             elsewhere, the same optical depth through the clump's radius;
  vacuum     no dust at all.
Reported: transport kernel time, packets per ms, and the path per packet in voxel edges (the
summed track length over the voxel edge; a straight path crosses about 1.5 voxels per edge
length: every crossing costs one density load and one tally add), and the time per voxel edge
of path.
The track-length estimator scores J in every voxel a packet crosses, vacuum included (J is
part of the output there), so empty voxels cannot be skipped; what matters is that a voxel
crossing costs the same wherever it is, and that a packet in a mostly empty scene crosses few.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import statistics
import sys
from pathlib import Path

import numpy as np


def density(kind: str, n: int) -> np.ndarray:
    if kind == "full":
        return np.ones((n, n, n), np.float32)
    if kind == "vacuum":
        return np.zeros((n, n, n), np.float32)
    c = (np.arange(n) + 0.5) / n - 0.5
    X, Y, Z = np.meshgrid(c, c, c, indexing="ij")
    return ((X * X + Y * Y + Z * Z) < 0.15**2).astype(np.float32)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--device", default="")
    ap.add_argument("--grid", type=int, default=64)
    ap.add_argument("--photons", type=float, default=1e6)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    from nebula_rt.backends import get_backend
    from nebula_rt.optics.bands import Band
    from nebula_rt.scene import Star
    from nebula_rt.transport.plan import FIXED_POINT_BITS
    from nebula_rt.transport import trace

    backend = get_backend(args.backend, args.device)
    band = [Band(name="V", wavelength=550.0, extinction=1.0, albedo=0.6, g=0.6)]
    star = [Star(position=(0.5, 0.5, 0.5), luminosity=1.0)]
    photons = int(args.photons)
    n = args.grid
    rows = []
    for kind, tau in (("full", 4.0), ("clump", 2.0 / 0.15), ("vacuum", 0.0)):
        rho = density(kind, n)
        trace(rho, band, star, tau=tau, photons=10_000, backend=backend)  # compile
        runs = [trace(rho, band, star, tau=tau, photons=photons, backend=backend) for _ in range(3)]
        kernel = statistics.median(r.timings["kernel_s"] for r in runs)
        res = runs[0]
        # summed track length in box units (fixed point: 2^32 units per voxel edge of 1/n)
        track = float(res.raw_sum.sum()) / (2.0**FIXED_POINT_BITS * n)
        row = {"scene": kind, "grid": n, "photons": photons, "dust_voxels": float(np.mean(rho > 0)),
               "kernel_ms": round(kernel * 1e3, 3), "packets_per_ms": round(photons / (kernel * 1e3)),
               "path_voxel_edges_per_packet": round(track * n / photons, 2),
               "ns_per_voxel_edge": round(kernel * 1e9 / (track * n), 3)}
        rows.append(row)
        print(f"{kind:7s} dust in {row['dust_voxels'] * 100:5.1f} % of voxels: kernel {row['kernel_ms']:9.2f} ms, "
              f"{row['packets_per_ms']:>8} packets/ms, path {row['path_voxel_edges_per_packet']:7.1f} voxel edges/packet, "
              f"{row['ns_per_voxel_edge']:.3f} ns per voxel edge", flush=True)
    result = {"benchmark": "empty_space", "device": backend.device_name,
              "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
              "command": " ".join(["benchmarks/bench_empty_space.py"] + (argv or sys.argv[1:])), "rows": rows}
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
        print(f"saved {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
