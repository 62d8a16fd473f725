#!/usr/bin/env python
"""The adaptive-grid targets, side by side in one run: a tree with 2^depth effective resolution
where the dust is dense against the uniform grids of 2^depth and 2^(depth-1) per edge.

    python benchmarks/bench_tree_targets.py [--backend cuda] [--device ""] [--depth 10]
        [--cell-tau 0.04] [--cell-tau-spread 0.05] [--photons 1e8] [--max-leaves 5e7] [--out FILE.json]

The thesis's nebula (turbulence, tau 128, its star and bump), one band (V: albedo 0.6,
g 0.6), made on an octree by ``dust.octree`` (:mod:`nebula_rt.density.procedural_tree`):
with cell_tau 0.04 a cell is split down to 2^depth per edge where its optical depth across an
edge passes 0.04, i.e. where the density passes 0.04 x 2^(depth-1) / 128 at the last split.
Then, each traced once untimed (kernel builds) and once timed:

- the tree: leaves per level, the time to make it, kernel time, packets per ms, the
  transport's device buffers (``TransportResult.device_bytes``) and the device's own peak
  (CuPy's memory pool) against the target 2 x (tree + one 8-byte accumulator per band per
  leaf) + 1 GiB;
- the uniform grid of 2^(depth-1) per edge: packets per ms (the target: the tree within 1.5x);
- the uniform grid of 2^depth per edge, the same field, another seed: J per voxel against J per leaf on the
  leaves of the deepest level (the same cells): z = difference / the two runs' combined stated
  errors, over the leaves both resolve (relative errors below 0.3): the fraction within 1 and
  2 sigma, the mean z and chi^2 per leaf.

The absorbed and escaped fractions of all three are printed beside each other.
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
from provenance import provenance  # noqa: E402  (benchmarks/provenance.py, beside this script)
from tuning import add_tuning_argument, apply_tuning  # noqa: E402

SCENE = """
[grid]
shape = [64, 64, 64]
[dust]
model = "turbulence"
tau = 128.0
octree = true
tree_depth = {depth}
cell_tau = {cell_tau}
cell_tau_spread = {cell_tau_spread}
[[stars]]
position = [0.5, 0.5, 0.5]
luminosity = 1.0
temperature = 20000.0
bump_radius = 0.01
[[bands.list]]
name = "V"
wavelength = 550.0
extinction = 1.0
albedo = 0.6
g = 0.6
[transport]
photons = {photons}
method = "analog"
estimator = "track-length"
max_scatterings = 1000
seed = 1
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="cuda")
    ap.add_argument("--device", default="")
    ap.add_argument("--depth", type=int, default=10)
    ap.add_argument("--cell-tau", type=float, default=0.04)
    ap.add_argument("--cell-tau-spread", type=float, default=0.05)
    ap.add_argument("--photons", type=float, default=1e8)
    ap.add_argument("--max-leaves", type=float, default=5e7, help="the target's leaf count at most")
    ap.add_argument("--skip-fine-grid", action="store_true", help="no uniform 2^depth run (memory)")
    add_tuning_argument(ap)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    from nebula_rt.backends import get_backend
    from nebula_rt.density import generate_density, scene_density
    from nebula_rt.scene import Scene
    from nebula_rt.transport.request import TransportRequest

    be = get_backend(args.backend, args.device)
    apply_tuning(be, args.tuning)
    scene = Scene.loads(SCENE.format(depth=args.depth, cell_tau=args.cell_tau, cell_tau_spread=args.cell_tau_spread,
                                     photons=int(args.photons)))
    request = TransportRequest.from_scene(scene)
    pool = _device_pool(be)
    out = {"benchmark": "bench_tree_targets", "date": time.strftime("%Y-%m-%d %H:%M:%S"), **provenance(),
           "device": be.device_name, "command": " ".join(["benchmarks/bench_tree_targets.py"] + (argv or sys.argv[1:])),
           "depth": args.depth, "cell_tau": args.cell_tau, "cell_tau_spread": args.cell_tau_spread,
           "photons": int(args.photons), "bands": 1}

    t0 = time.perf_counter()
    tree = scene_density(scene, be)
    made = time.perf_counter() - t0
    lo, hi, _ = tree.leaves()
    level = np.rint(-np.log2(hi[:, 0] - lo[:, 0])).astype(int)
    tree_bytes = int(tree.child.nbytes + tree.density.nbytes)
    out["tree"] = {"leaves": tree.n_leaves, "nodes": int(tree.child.size), "leaves_per_level": np.bincount(level).tolist(),
                   "make_s": round(made, 3), "bytes": tree_bytes}
    print(f"tree: {tree.n_leaves:,} leaves (target <= {args.max_leaves:,.0f}), per level {np.bincount(level).tolist()}, "
          f"made in {made:.1f} s, {tree_bytes / 2**20:.0f} MiB", flush=True)

    def run(label, medium, request=request):
        request.trace(medium, be)  # builds
        if pool is not None:
            pool.free_all_blocks()
        base = pool.used_bytes() if pool is not None else 0
        peak = _PeakWatch(pool)
        t0 = time.perf_counter()
        res = request.trace(medium, be)
        wall = time.perf_counter() - t0
        peak.stop()
        packets = int(res.counts[:, 0].sum())
        rec = {"kernel_s": float(res.timings["kernel_s"]), "wall_s": round(wall, 4),
               "packets_per_ms": packets / (res.timings["kernel_s"] * 1e3),
               "transport_device_bytes": int(res.device_bytes),
               "device_pool_peak_bytes": None if pool is None else int(peak.peak - base),
               "absorbed_fraction": float(res.counts[0, 1] / res.counts[0, 0]),
               "escaped_fraction": float(res.counts[0, 2] / res.counts[0, 0])}
        print(f"{label:<22} kernel {rec['kernel_s'] * 1e3:9.1f} ms  {rec['packets_per_ms']:>10,.0f} packets/ms  "
              f"wall {wall:7.2f} s  device {rec['transport_device_bytes'] / 2**30:6.2f} GiB  "
              f"absorbed {rec['absorbed_fraction']:.5f}  escaped {rec['escaped_fraction']:.5f}", flush=True)
        return rec, res

    out["tree"].update(run(f"tree depth {args.depth}", tree)[0])
    target = 2 * (tree_bytes + 8 * 1 * tree.n_leaves) + 2**30
    out["tree"]["memory_target_bytes"] = target
    print(f"memory target 2 x (tree + one accumulator per leaf) + 1 GiB = {target / 2**30:.2f} GiB", flush=True)

    half = 1 << (args.depth - 1)
    rho_half = generate_density(scene.with_overrides(["dust.octree=false", f"grid.shape=[{half},{half},{half}]"]), be)
    out["grid_half"] = {"shape": half, **run(f"grid {half}^3", rho_half)[0]}
    del rho_half
    out["tree_vs_grid_half_speed"] = out["grid_half"]["packets_per_ms"] / out["tree"]["packets_per_ms"]
    print(f"grid {half}^3 / tree packets per ms: {out['tree_vs_grid_half_speed']:.2f} (target <= 1.5)", flush=True)

    if not args.skip_fine_grid:
        full = 1 << args.depth
        _, res_tree = run("tree (again, for J)", tree)
        rho = generate_density(scene.with_overrides(["dust.octree=false", f"grid.shape=[{full},{full},{full}]"]), be)
        # another seed: the two runs' errors independent, so that z measures the difference
        rec, res_grid = run(f"grid {full}^3 (seed 2)", rho,
                            TransportRequest.from_scene(scene.with_overrides(["transport.seed=2"])))
        out["grid_full"] = {"shape": full, **rec}
        del rho
        fine = level == args.depth
        i = np.rint(lo[fine] * full).astype(np.int64)
        jt, rt = res_tree.J[0][fine], res_tree.rel_error[0][fine]
        jg = res_grid.J[0][i[:, 0], i[:, 1], i[:, 2]]
        rg = res_grid.rel_error[0][i[:, 0], i[:, 1], i[:, 2]]
        both = (jt > 0) & (jg > 0) & (rt < 0.3) & (rg < 0.3)
        z = (jt - jg)[both] / np.sqrt((jt * rt) ** 2 + (jg * rg) ** 2)[both]
        out["agreement"] = {"deepest_leaves": int(fine.sum()), "compared": int(both.sum()),
                            "within_1_sigma": float(np.mean(np.abs(z) < 1)), "within_2_sigma": float(np.mean(np.abs(z) < 2)),
                            "mean_z": float(np.mean(z)), "chi2_per_leaf": float(np.mean(z**2))}
        print(f"J on the {both.sum():,} deepest leaves both resolve: within 1 sigma {out['agreement']['within_1_sigma']:.3f}, "
              f"2 sigma {out['agreement']['within_2_sigma']:.3f}, mean z {out['agreement']['mean_z']:+.3f}, "
              f"chi2 per leaf {out['agreement']['chi2_per_leaf']:.3f}", flush=True)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1))
    return 0


def _device_pool(be):
    """CuPy's memory pool on the CUDA backend (its peak is the device's peak for the run), else None."""
    if getattr(be, "name", "") != "cuda":
        return None
    import cupy as cp

    return cp.get_default_memory_pool()


class _PeakWatch:
    """The pool's peak of used bytes over a run, sampled by a thread every millisecond (CuPy
    keeps no high-water mark)."""

    def __init__(self, pool):
        self.peak = 0
        self._pool = pool
        if pool is None:
            return
        import threading

        self._stop = threading.Event()

        def watch():
            while not self._stop.is_set():
                self.peak = max(self.peak, pool.used_bytes())
                self._stop.wait(0.001)

        self._thread = threading.Thread(target=watch, daemon=True)
        self._thread.start()

    def stop(self):
        if self._pool is not None:
            self._stop.set()
            self._thread.join()
            self.peak = max(self.peak, self._pool.used_bytes())


if __name__ == "__main__":
    sys.exit(main())
