#!/usr/bin/env python
"""Scaling over ranks: a scene traced by 1..N MPI ranks (``trace(comm=world())`` or
``Pipeline(comm=world())``), kernel and reduction times apart, and the bits compared with the
one-rank run.

    python benchmarks/bench_ranks.py --ranks 1 2 [--backend opencl] [--grid 64] [--photons 1e6] [--out FILE]
    python benchmarks/bench_ranks.py --ranks 1 2 4 8 --backend cuda --grid 512 --photons 1e9 1e10
    python benchmarks/bench_ranks.py --ranks 1 2 4 8 --backend cuda --grid 512 --photons 1e9 --weak
    python benchmarks/bench_ranks.py --ranks 1 2 4 8 --backend cuda --scene thesis --grid 512 --photons 1e8

Scenes: ``neb`` (the neb medium on n^3: uniform dust, optical depth 1 centre to face, albedo
0.6, g 0.6, a star at the centre; the transport stage alone) and ``thesis`` (the thesis scene,
examples/scenes/thesis-default.toml, on n^3 with its 3 bands, end to end through the pipeline:
density, transport, light field and colour). ``--weak``: the photons are per rank.

Each configuration runs as ``mpiexec -n N python bench_ranks.py --child ...`` (CUDA ranks take
the GPUs of the node by local rank; PoCL ranks share the cores), with NVLink multicast off
(NCCL_NVLS_ENABLE=0). Rank 0 reports the wall time (the transport's for ``neb``, the
pipeline's for ``thesis``), the kernel time (its own launches), the reduction time (adding the
ranks' slots and tallies: NCCL on the GPUs, or through the host, ``reduce_path``), and a
SHA-256 of the sums and counts (``neb``) or of every output array (``thesis``), which must
equal the one-rank run's. Efficiency: T_1 / (N T_N) for strong scaling, T_1 / T_N for weak.
On a machine with fewer cores (or GPUs) than ranks the ranks share them and the figures
measure the code path, not scaling: the JSON says so. ``--allreduce host`` forces the sums
through the host (NEBULA_RT_ALLREDUCE), for comparison.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: photons of the warm-up run (same grid and scene): enough that the run's automatic choices
#: (regions, sorted order, the error estimate by batches or packets) are the timed run's, so
#: its kernels compile outside the timing (NVRTC at 512^3: about 6 s)
WARMUP_MAX = 100_000_000


def child(backend_name: str, device: str, n: int, photons: int, scene_name: str = "neb") -> dict:
    import numpy as np

    from nebula_rt.backends import get_backend
    from nebula_rt.backends.parallel import world

    comm = world()
    if backend_name == "cuda" and not device:
        import cupy

        device = str(comm.local_rank % cupy.cuda.runtime.getDeviceCount())
    backend = get_backend(backend_name, device)
    if scene_name == "thesis":
        from nebula_rt.pipeline import Pipeline
        from nebula_rt.scene import Scene

        scene = Scene.load(ROOT / "examples" / "scenes" / "thesis-default.toml").with_overrides(
            [f"grid.shape=[{n},{n},{n}]", f"transport.photons={photons}",
             f'transport.backend="{backend_name}"', f'transport.device="{device}"'])
        # warm-up on the same grid with up to 1e8 photons: the kernels of the run's options
        # (regions, sorted order, the estimate by batches or packets) compile outside the timing
        Pipeline(backend, comm=comm).run(scene.with_overrides([f"transport.photons={min(photons, WARMUP_MAX)}"]))
        comm.barrier()
        t0 = time.perf_counter()
        light = Pipeline(backend, comm=comm).run(scene)
        wall = time.perf_counter() - t0
        res = light.transport
        h = hashlib.sha256()
        for name, a in sorted(light.point_arrays().items()):
            h.update(name.encode() + np.ascontiguousarray(a).tobytes())
        digest, bands = h.hexdigest(), len(light.bands)
        del light
    else:
        from nebula_rt.optics.bands import Band
        from nebula_rt.scene import Star
        from nebula_rt.transport import trace

        rho = np.ones((n, n, n), np.float32)
        band_list = [Band(name="V", wavelength=550.0, extinction=1.0, albedo=0.6, g=0.6)]
        stars = [Star(position=(0.5, 0.5, 0.5), luminosity=1.0, temperature=None, bump_radius=0.0)]
        trace(rho, band_list, stars, tau=2.0, photons=min(photons, WARMUP_MAX), backend=backend, comm=comm)  # warm-up
        comm.barrier()
        t0 = time.perf_counter()
        res = trace(rho, band_list, stars, tau=2.0, photons=photons, backend=backend, comm=comm)
        wall = time.perf_counter() - t0
        digest = hashlib.sha256(res.raw_sum.tobytes() + res.raw_m2.tobytes() + res.counts.tobytes()).hexdigest()
        bands = 1
    gpus = None
    if backend_name == "cuda":
        import cupy

        gpus = int(cupy.cuda.runtime.getDeviceCount())
    return {"scene": scene_name, "ranks": comm.size, "grid": n, "photons": photons, "bands": bands,
            "device": backend.device_name, "gpus": gpus,
            "wall_s": round(wall, 4), "kernel_s": round(res.timings["kernel_s"], 4),
            "reduce_s": round(res.timings.get("reduce_s", 0.0), 4), "reduce_path": res.reduce_path,
            "batches": int(res.batches), "error_estimate": res.error_estimate,
            "absorbed_fraction": float(res.counts[0, 1] / res.counts[0, 0]), "sha256": digest}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--grid", type=int, nargs="+", default=[64])
    ap.add_argument("--photons", type=float, nargs="+", default=[1e6])
    ap.add_argument("--backend", default="opencl", choices=("opencl", "cuda"))
    ap.add_argument("--device", default="", help="device selector (default: PoCL on opencl, by local rank on cuda)")
    ap.add_argument("--scene", default="neb", choices=("neb", "thesis"))
    ap.add_argument("--weak", action="store_true", help="--photons per rank (weak scaling)")
    from nebula_rt.backends.parallel import ALLREDUCE_CHOICES

    ap.add_argument("--allreduce", default="", choices=("",) + ALLREDUCE_CHOICES,
                    help="how the ranks add their device slots (NEBULA_RT_ALLREDUCE; default: auto)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--child", nargs=2, type=float, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    device = args.device or ("Portable Computing Language" if args.backend == "opencl" else "")
    if args.child:
        rec = child(args.backend, device, int(args.child[0]), int(args.child[1]), args.scene)
        from nebula_rt.backends.parallel import world

        if world().rank == 0:
            print("RESULT " + json.dumps(rec), flush=True)
        return 0
    mpiexec = shutil.which("mpiexec")
    if mpiexec is None:
        print("mpiexec not found (Debian: openmpi-bin)", file=sys.stderr)
        return 1
    # NVLink multicast off, also in the ranks mpiexec starts
    env = dict(os.environ, NCCL_NVLS_ENABLE="0", TORCH_SYMM_MEM_DISABLE_MULTICAST="1", NVSHMEM_DISABLE_NVLS="1")
    if args.allreduce:
        env["NEBULA_RT_ALLREDUCE"] = args.allreduce
    records = []
    for n in args.grid:
        for p in args.photons:
            base = None
            for r in args.ranks:
                total = int(p) * (r if args.weak else 1)
                cmd = [mpiexec, "--allow-run-as-root", "--oversubscribe", "-n", str(r), sys.executable,
                       str(Path(__file__).resolve()), "--backend", args.backend, "--device", device,
                       "--scene", args.scene, "--child", str(n), str(total)]
                proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
                lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
                if proc.returncode != 0 or not lines:
                    rec = {"scene": args.scene, "ranks": r, "grid": n, "photons": total,
                           "error": (proc.stderr or proc.stdout)[-800:]}
                else:
                    rec = json.loads(lines[-1][len("RESULT "):])
                    if base is None and r == 1:
                        base = rec
                    if rec.get("gpus") is not None and r > rec["gpus"]:
                        rec["note"] = f"{r} ranks share {rec['gpus']} GPU(s): the code path, not scaling"
                    if base is not None:
                        if not args.weak:  # the same photons: the same bits
                            rec["same_bits_as_one_rank"] = rec["sha256"] == base["sha256"]
                        rec["efficiency"] = round(base["wall_s"] / ((1 if args.weak else r) * rec["wall_s"]), 3)
                        rec["kernel_efficiency"] = round(
                            base["kernel_s"] / ((1 if args.weak else r) * max(rec["kernel_s"], 1e-9)), 3)
                records.append(rec)
                print(json.dumps(rec), flush=True)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from provenance import provenance  # benchmarks/provenance.py

    out = {"benchmark": "bench_ranks", "date": time.strftime("%Y-%m-%d %H:%M:%S"), **provenance(),
           "cpu_count": os.cpu_count(), "backend": args.backend, "scene": args.scene,
           "scaling": "weak" if args.weak else "strong", "allreduce": args.allreduce or "auto",
           "note": ("ranks beyond the cores (or GPUs) share them: a functional check of the code path"
                    if max(args.ranks) > (os.cpu_count() or 1) and args.backend == "opencl" else ""),
           "command": " ".join(["benchmarks/bench_ranks.py"] + (argv or sys.argv[1:])), "records": records}
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
