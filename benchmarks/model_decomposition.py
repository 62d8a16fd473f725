#!/usr/bin/env python
"""Measured inputs of the domain-decomposition model (docs/domain_decomposition.md).

    python benchmarks/model_decomposition.py [--grid 64] [--photons 2e5] [--out FILE]

For each reference scene (examples/scenes/*.toml at --grid^3) one real run of each estimator
gives, per packet and band: the path length inside the box (box units: the track-length sums
/ fixed-point scale), the interactions (the collision counts) and the fraction that escapes.
A packet's straight segments of total length L, isotropic on average, cross the planes of a
decomposition into k blocks per axis about 1.5 L k times (a segment of length l and direction
d crosses l |d_a| k planes normal to axis a in expectation; <|d_x| + |d_y| + |d_z|> = 1.5 over
the sphere). The largest share of the deposits any one block takes (its load) comes from the
run's J x sigma per block. Both go into the model of the doc.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def measure(scene_path: Path, grid: int, photons: int, backend) -> dict:
    from nebula_rt.density import generate_density
    from nebula_rt.scene import Scene
    from nebula_rt.transport.plan import FIXED_POINT_BITS
    from nebula_rt.transport import trace

    scene = Scene.load(scene_path).with_overrides([f"grid.shape=[{grid},{grid},{grid}]", f"transport.photons={photons}"])
    rho = generate_density(scene, backend)
    bands = scene.bands.resolve()
    kw = dict(tau=scene.dust.tau, photons=photons, seed=3, backend=backend,
              max_scatterings=scene.transport.max_scatterings)
    track = trace(rho, bands, scene.stars, estimator="track-length", **kw)
    coll = trace(rho, bands, scene.stars, estimator="collision-filter", **kw)
    scale = 2.0**FIXED_POINT_BITS * grid
    path = track.raw_sum.reshape(len(bands), -1).sum(axis=1) / scale / photons  # box units per packet
    interactions = coll.raw_sum.reshape(len(bands), -1).sum(axis=1) / photons
    escaped = track.counts[:, 2] / photons
    out = {"scene": scene_path.stem, "grid": grid, "photons": photons, "bands": [b.name for b in bands],
           "path_per_packet_box": [round(float(x), 4) for x in path],
           "interactions_per_packet": [round(float(x), 4) for x in interactions],
           "escaped_fraction": [round(float(x), 4) for x in escaped], "blocks": {}}
    light = track.raw_sum.sum(axis=0)  # the deposits of all bands: where the work is
    for k in (2, 4, 8, 16):
        b = grid // k
        per_block = light.reshape(k, b, k, b, k, b).sum(axis=(1, 3, 5)).ravel()
        share = per_block / per_block.sum()
        out["blocks"][k] = {"ranks": k**3,
                            "crossings_per_packet": [round(float(1.5 * x * k), 3) for x in path],
                            "largest_block_share": round(float(share.max()), 4),
                            "imbalance": round(float(share.max() * k**3), 2)}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--grid", type=int, default=64)
    ap.add_argument("--photons", type=float, default=2e5)
    ap.add_argument("--device", default="Portable Computing Language")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    from nebula_rt.backends import get_backend

    backend = get_backend("opencl", args.device)
    records = [measure(p, args.grid, int(args.photons), backend) for p in sorted((ROOT / "examples" / "scenes").glob("*.toml"))]
    for r in records:
        print(json.dumps(r))
    if args.out:
        Path(args.out).write_text(json.dumps({"benchmark": "model_decomposition", "date": time.strftime("%Y-%m-%d"),
                                              "device": backend.device_name, "records": records}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
