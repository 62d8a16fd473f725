#!/usr/bin/env python
"""Run one scene on several backends/devices with the same seed and compare.

    python benchmarks/compare_backends.py --run cuda: --run opencl:NVIDIA --save-dir DIR
    python benchmarks/compare_backends.py --compare DIR/*.npz     # pairwise comparison

Same seed means the same packets with the same random numbers on every device (counter-based
Philox keyed by seed, band and packet index). Devices differ only in float rounding (log, sin,
cos, division), which moves a packet's interaction points by ulps and, rarely, flips a
decision at a voxel face or an albedo threshold; after that flip the packet's history differs.
So packet counts agree to a small fraction of a per cent and J voxel by voxel to within the
statistical error, not bit for bit. Saved: J (float32), packet counts, device name.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENE_OVERRIDES = ["grid.shape=[64,64,64]", "transport.photons=1000000", "transport.seed=7"]


def run(spec: str, save_dir: Path, extra=()) -> Path:
    from nebula_rt.backends import get_backend
    from nebula_rt.pipeline import Pipeline
    from nebula_rt.scene import Scene

    name, _, device = spec.partition(":")
    backend = get_backend(name, device)
    scene = Scene.load(ROOT / "examples/scenes/thesis-default.toml").with_overrides(SCENE_OVERRIDES + list(extra))
    light = Pipeline(backend).run(scene, colour=False)
    slug = "".join(c if c.isalnum() else "-" for c in backend.device_name.lower())[:48]
    tag = "".join(c if c.isalnum() else "-" for c in "-".join(extra))[:40]
    out = save_dir / f"light-{slug}{'-' + tag if tag else ''}.npz"
    # counts as float64: a biased run's are 128-bit weight sums (their ratios are what compare)
    np.savez_compressed(out, J=light.J, rel=light.rel_error,
                        counts=np.array(light.transport.counts.tolist(), dtype=np.float64),
                        device=backend.device_name)
    print(f"{backend.device_name}: counts {light.transport.counts.tolist()} -> {out}")
    return out


def compare(paths: list[Path], extra=()) -> dict:
    data = {p: np.load(p) for p in paths}
    report = []
    for a, b in itertools.combinations(paths, 2):
        A, B = data[a], data[b]
        ca, cb = A["counts"].astype(float), B["counts"].astype(float)
        n = ca[0, 0]
        J1, J2 = A["J"].astype(float), B["J"].astype(float)
        se = np.sqrt((J1 * A["rel"]) ** 2 + (J2 * B["rel"]) ** 2)
        lit = (J1 > 0) & (A["rel"] < 0.05)
        z = (J1 - J2)[lit] / np.where(se[lit] > 0, se[lit], 1)
        row = {
            "a": str(A["device"]), "b": str(B["device"]),
            "max_count_difference_fraction": float(np.max(np.abs(ca - cb)) / n),
            "identical_voxels_fraction": float(np.mean(J1 == J2)),
            "median_abs_rel_diff_lit": float(np.median(np.abs(J1 - J2)[lit] / J1[lit])),
            "z_mean": float(z.mean()), "z_std": float(z.std()), "z_abs_gt5_fraction": float(np.mean(np.abs(z) > 5)),
        }
        report.append(row)
        print(json.dumps(row, indent=2))
    return {"scene": "examples/scenes/thesis-default.toml", "overrides": SCENE_OVERRIDES + list(extra),
            "pairs": report}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", action="append", default=[], help="BACKEND:DEVICE, e.g. cuda: or opencl:NVIDIA")
    ap.add_argument("--save-dir", default=".", help="where the .npz files go")
    ap.add_argument("--compare", nargs="*", default=None, help=".npz files to compare pairwise")
    ap.add_argument("--out", default=None, help="JSON report of the comparison")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="another scene override, e.g. transport.method=\"biased\"")
    args = ap.parse_args(argv)
    saved = [run(spec, Path(args.save_dir), args.set) for spec in args.run]
    paths = [Path(p) for p in (args.compare or [])] + saved
    if len(paths) >= 2:
        rep = compare(paths, args.set)
        if args.out:
            Path(args.out).write_text(json.dumps(rep, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
