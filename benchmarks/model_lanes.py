#!/usr/bin/env python
"""How many SIMD lanes a warp keeps busy, one packet per work item against several per work item.

    python benchmarks/model_lanes.py [--grids 64 128 256] [--packets 200000] [--refill 1 4 16 64] [--out FILE]

A model, not a measurement: the neb medium's histories (a box of side 1, an isotropic source at
its centre, extinction 2 per box edge, albedo 0.6, Henyey-Greenstein g 0.6) are drawn with
NumPy, and each packet's work W is the number of iterations of the transport kernel's one loop:
one per voxel face its flights cross on an n^3 grid, plus one per interaction. A warp of 32
lanes that traces one packet per lane takes as long as its longest packet, so it keeps
mean(W) / max(W) of its lanes busy. With R packets per lane a group's 32 R packets go, in
order, to whichever lane is free first, so the warp takes the longest lane's sum instead.
Reported per grid: W's mean and percentiles and the busy share of the lanes for each R.

The one-packet share (0.48 at 128^3) matches the lanes an H200 profile measured in the
thesis kernel's voxel step (15.8 of 32). The refill's share is the most it could gain in a
kernel that issues as fast as its lanes allow. On the H200 such a kernel was slower
(benchmarks/results/h200-2026-12-05/): a lane that starts a packet while the others step runs
the emission's code alone, which this model leaves out.
"""

from __future__ import annotations

import argparse
import heapq
import json
import sys
from pathlib import Path

import numpy as np

LANES = 32


def _isotropic(rng, m):
    mu = 2.0 * rng.random(m) - 1.0
    phi = 2.0 * np.pi * rng.random(m)
    s = np.sqrt(1.0 - mu * mu)
    return np.stack([s * np.cos(phi), s * np.sin(phi), mu], 1)


def _hg_turn(rng, d, g):
    """New directions after Henyey-Greenstein scattering of directions d (m, 3)."""
    m = d.shape[0]
    xi = rng.random(m)
    mu = (1.0 + g * g - ((1.0 - g * g) / (1.0 - g + 2.0 * g * xi)) ** 2) / (2.0 * g)
    phi = 2.0 * np.pi * rng.random(m)
    sint = np.sqrt(np.maximum(0.0, 1.0 - mu * mu))
    ux, uy, uz = d[:, 0], d[:, 1], d[:, 2]
    den = np.sqrt(np.maximum(1e-12, 1.0 - uz * uz))
    new = np.stack([sint * (ux * uz * np.cos(phi) - uy * np.sin(phi)) / den + ux * mu,
                    sint * (uy * uz * np.cos(phi) + ux * np.sin(phi)) / den + uy * mu,
                    -sint * np.cos(phi) * den + uz * mu], 1)
    return new / np.linalg.norm(new, axis=1)[:, None]


def histories(n: int, packets: int, mu_t: float = 2.0, albedo: float = 0.6, g: float = 0.6,
              seed: int = 1) -> np.ndarray:
    """Each packet's loop iterations W on an n^3 grid (int64, in emission order)."""
    rng = np.random.default_rng(seed)
    work = np.zeros(packets, np.int64)
    pos = np.full((packets, 3), 0.5)
    d = _isotropic(rng, packets)
    live = np.arange(packets)
    top = 1.0 - 1e-12
    while live.size:
        p, dd = pos[live], d[live]
        s = rng.exponential(1.0 / mu_t, live.size)
        with np.errstate(divide="ignore", invalid="ignore"):
            to_edge = np.where(dd > 0, (1.0 - p) / dd, np.where(dd < 0, -p / dd, np.inf)).min(1)
        escaped = s >= to_edge
        q = np.clip(p + dd * np.minimum(s, to_edge)[:, None], 0.0, top)
        faces = np.abs(np.floor(n * q) - np.floor(n * np.clip(p, 0.0, top))).sum(1).astype(np.int64)
        work[live] += faces + 1
        pos[live] = q
        scatters = ~escaped & (rng.random(live.size) < albedo)
        k = np.nonzero(scatters)[0]
        if k.size:
            d[live[k]] = _hg_turn(rng, dd[k], g)
        live = live[scatters]
    return work


def busy_share(work: np.ndarray, refill: int, lanes: int = LANES) -> float:
    """Share of lane time spent on packets: groups of lanes x refill packets, each packet to the
    lane that is free first (refill 1: one packet per lane)."""
    per = lanes * refill
    if work.size < per:
        raise ValueError(f"--packets {work.size}: R = {refill} needs at least {per} packets (a group of {lanes} lanes)")
    total = span = 0
    for g0 in range(0, work.size - per + 1, per):
        jobs = work[g0:g0 + per]
        if refill == 1:
            span += int(jobs.max())
        else:
            free = [0] * lanes
            for w in jobs.tolist():
                heapq.heappush(free, heapq.heappop(free) + w)
            span += max(free)
        total += int(jobs.sum())
    return total / (lanes * span)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--grids", type=int, nargs="+", default=[64, 128, 256])
    ap.add_argument("--packets", type=int, default=200_000)
    ap.add_argument("--refill", type=int, nargs="+", default=[1, 4, 16, 64])
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    rows = []
    for n in args.grids:
        work = histories(n, args.packets)
        shares = {str(r): round(busy_share(work, r), 4) for r in args.refill}
        rows.append({"grid": n, "mean": float(work.mean()),
                     "percentiles": {str(q): float(np.percentile(work, q)) for q in (50, 90, 99)},
                     "busy_share": shares})
        print(f"{n:5d}^3  W mean {work.mean():7.1f}  p50/p90/p99 {np.percentile(work, 50):.0f}/"
              f"{np.percentile(work, 90):.0f}/{np.percentile(work, 99):.0f}  busy lanes "
              + "  ".join(f"R={r}: {s:.2f}" for r, s in shares.items()), flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps({"model": "neb medium, lanes per warp", "lanes": LANES,
                                              "packets": args.packets, "rows": rows}, indent=2) + "\n")
        print(f"saved {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
