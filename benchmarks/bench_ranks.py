#!/usr/bin/env python
"""Strong scaling over ranks: the neb medium on n^3 traced by 1..N MPI ranks (``trace(comm=
world())``), kernel and reduction times apart, and the bits compared with the one-rank run.

    python benchmarks/bench_ranks.py --ranks 1 2 [--backend opencl] [--grid 64] [--photons 1e6] [--out FILE]
    python benchmarks/bench_ranks.py --ranks 1 2 4 8 --backend cuda --grid 128 512 --photons 1e8 1e9 1e10

Each configuration runs as ``mpiexec -n N python bench_ranks.py --child ...`` (CUDA ranks take
the GPUs of the node by local rank; PoCL ranks share the cores). Rank 0 reports the transport's
wall time, the kernel time (its own launches), the reduction time (adding the ranks' slots and
tallies through the host), and a SHA-256 of the sums and counts, which must equal the one-rank
run's. Efficiency = T_1 / (N T_N). On a machine with fewer cores (or GPUs) than ranks the
ranks share them and the figures measure the code path, not scaling: the JSON says so.
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


def child(backend_name: str, device: str, n: int, photons: int) -> dict:
    import numpy as np

    from nebula_rt.backends import get_backend
    from nebula_rt.bands import Band
    from nebula_rt.parallel import world
    from nebula_rt.scene import Star
    from nebula_rt.transport import trace

    comm = world()
    if backend_name == "cuda" and not device:
        import cupy

        device = str(comm.local_rank % cupy.cuda.runtime.getDeviceCount())
    backend = get_backend(backend_name, device)
    rho = np.ones((n, n, n), np.float32)
    bands = [Band(name="V", wavelength=550.0, extinction=1.0, albedo=0.6, g=0.6)]
    stars = [Star(position=(0.5, 0.5, 0.5), luminosity=1.0, temperature=None, bump_radius=0.0)]
    trace(np.ones((8, 8, 8), np.float32), bands, stars, tau=2.0, photons=2000, backend=backend, comm=comm)  # warm-up
    comm.barrier()
    t0 = time.perf_counter()
    res = trace(rho, bands, stars, tau=2.0, photons=photons, backend=backend, comm=comm)
    wall = time.perf_counter() - t0
    digest = hashlib.sha256(res.raw_sum.tobytes() + res.raw_m2.tobytes() + res.counts.tobytes()).hexdigest()
    gpus = None
    if backend_name == "cuda":
        import cupy

        gpus = int(cupy.cuda.runtime.getDeviceCount())
    return {"ranks": comm.size, "grid": n, "photons": photons, "device": backend.device_name, "gpus": gpus,
            "wall_s": round(wall, 4), "kernel_s": round(res.timings["kernel_s"], 4),
            "reduce_s": round(res.timings.get("reduce_s", 0.0), 4),
            "absorbed_fraction": float(res.counts[0, 1] / res.counts[0, 0]), "sha256": digest}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--grid", type=int, nargs="+", default=[64])
    ap.add_argument("--photons", type=float, nargs="+", default=[1e6])
    ap.add_argument("--backend", default="opencl", choices=("opencl", "cuda"))
    ap.add_argument("--device", default="", help="device selector (default: PoCL on opencl, by local rank on cuda)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--child", nargs=2, type=float, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    device = args.device or ("Portable Computing Language" if args.backend == "opencl" else "")
    if args.child:
        rec = child(args.backend, device, int(args.child[0]), int(args.child[1]))
        from nebula_rt.parallel import world

        if world().rank == 0:
            print("RESULT " + json.dumps(rec), flush=True)
        return 0
    mpiexec = shutil.which("mpiexec")
    if mpiexec is None:
        print("mpiexec not found (Debian: openmpi-bin)", file=sys.stderr)
        return 1
    env = dict(os.environ, NCCL_NVLS_ENABLE="0")
    records = []
    for n in args.grid:
        for p in args.photons:
            base = None
            for r in args.ranks:
                cmd = [mpiexec, "--allow-run-as-root", "--oversubscribe", "-n", str(r), sys.executable,
                       str(Path(__file__).resolve()), "--backend", args.backend, "--device", device,
                       "--child", str(n), str(int(p))]
                proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
                lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
                if proc.returncode != 0 or not lines:
                    rec = {"ranks": r, "grid": n, "photons": int(p), "error": (proc.stderr or proc.stdout)[-800:]}
                else:
                    rec = json.loads(lines[-1][len("RESULT "):])
                    if base is None and r == 1:
                        base = rec
                    if rec.get("gpus") is not None and r > rec["gpus"]:
                        rec["note"] = f"{r} ranks share {rec['gpus']} GPU(s): the code path, not scaling"
                    if base is not None:
                        rec["same_bits_as_one_rank"] = rec["sha256"] == base["sha256"]
                        rec["efficiency"] = round(base["wall_s"] / (r * rec["wall_s"]), 3)
                records.append(rec)
                print(json.dumps(rec), flush=True)
    out = {"benchmark": "bench_ranks", "date": time.strftime("%Y-%m-%d %H:%M:%S"),
           "cpu_count": os.cpu_count(), "backend": args.backend,
           "note": ("ranks beyond the cores (or GPUs) share them: a functional check of the code path"
                    if max(args.ranks) > (os.cpu_count() or 1) and args.backend == "opencl" else ""),
           "command": " ".join(["benchmarks/bench_ranks.py"] + (argv or sys.argv[1:])), "records": records}
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
