#!/usr/bin/env python
"""The MCX-equivalent scene "neb128" (REFERENCES.md) side by side with MCX.

    python benchmarks/bench_neb128.py [--backend cuda|opencl] [--device SEL] [--photons 2100000 21000000]
                                      [--grid 128] [--mcx pmcx|pmcxcl|none] [--out FILE]

128^3 voxels (or ``--grid`` n^3) of uniform dust, an isotropic source at the centre, optical
depth 1 from the centre to a face (mu_t = 2 per box unit = 2 / n per voxel: 0.015625 at 128^3),
albedo 0.6, g 0.6, one band, no reflection. The scattering cap of 1000 cuts a packet short with probability 0.6^1000
(~1e-222): the terminated count reported is 0. Reported per photon count: NebulaRT's transport kernel time (sum over its
batches, compile excluded after a warm-up; median of 5 runs) and photons per ms, its end-to-end wall time
(transport + normalisation + error estimate; a one-band scene does no colour work), the
absorbed fraction (MCX reports 0.4078), and, when the MCX package is importable, MCX's own
kernel runtime, photons per ms and absorbed fraction on the same scene in the same process.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
N = 128


def nebula_scene(photons: int, backend: str, device: str, n: int = N):
    from nebula_rt.scene import Scene

    return Scene.from_dict(nebula_scene_dict(photons, backend, device, n))


def nebula_scene_dict(photons: int, backend: str, device: str, n: int = N) -> dict:
    """The scene file's tables of :func:`nebula_scene` (benchmarks/bench_mcx.py swaps the dust)."""
    return {
        "grid": {"shape": [n, n, n]},
        "dust": {"model": "uniform", "density": 1.0, "floor": 0.0, "tau": 2.0},
        # no dust bump (the scene default's r = 0.01 is MCX-less extra dust at the source:
        # absorbed 0.4100 against 0.4083 without it at 256^3, benchmarks/results/h200-2026-12-04h/)
        "stars": [{"position": [0.5, 0.5, 0.5], "luminosity": 1.0, "bump_radius": 0.0}],
        "bands": {"list": [{"name": "V", "wavelength": 550.0, "extinction": 1.0, "albedo": 0.6, "g": 0.6}]},
        "transport": {"photons": int(photons), "max_scatterings": 1000, "seed": 1,
                      "backend": backend, "device": device},
    }


def run_nebula(photons: int, backend_name: str, device: str, repeats: int = 5, n: int = N) -> dict:
    from nebula_rt.backends import get_backend
    from nebula_rt.pipeline import Pipeline

    backend = get_backend(backend_name, device)
    Pipeline(backend).run(nebula_scene(10_000, backend_name, device, n), colour=False)  # compile, warm up (same grid)
    scene = nebula_scene(photons, backend_name, device, n)
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        light = Pipeline(backend).run(scene, colour=False)
        runs.append((time.perf_counter() - t0, light.timings["kernel_s"], light))
    wall = statistics.median(r[0] for r in runs)
    light = runs[0][2]
    kernel_s = statistics.median(r[1] for r in runs)
    c = light.transport.counts[0]
    kernel_ms = kernel_s * 1e3
    p_abs = c[1] / photons
    return {
        "code": "NebulaRT", "device": backend.device_name, "photons": photons, "grid": n,
        "kernel_ms": round(kernel_ms, 3), "photons_per_ms": round(photons / kernel_ms),
        "end_to_end_ms": round(wall * 1e3, 3), "absorbed_fraction": p_abs,
        "absorbed_sigma": math.sqrt(p_abs * (1 - p_abs) / photons),
        "terminated": int(c[3]), "repeats": repeats,
    }


def mcx_config(photons: int, n: int = N) -> dict:
    """MCX's scene: per voxel mu_a 0.8 / n and mu_s 1.2 / n (mu_t 2 / n, albedo 0.6), the
    source at the box's centre, n / 2 in MCX's 0-based grid units (issrcfrom0 1; before,
    srcpos 64 with issrcfrom0 0 put it one voxel off the centre along each axis, as
    bench_large_grids.py found)."""
    return dict(nphoton=int(photons), vol=np.ones([n] * 3, "uint8"), tstart=0, tend=1e-6, tstep=1e-6,
                srctype="isotropic", srcpos=[n / 2.0] * 3, srcdir=[0, 0, 1], issrcfrom0=1,
                prop=[[0, 0, 1, 1], [0.8 / n, 1.2 / n, 0.6, 1.0]], isreflect=0, seed=1648335518)


def load_system_libstdcxx() -> None:
    """Load the system libstdc++ before pmcxcl is imported. pmcxcl links libstdc++ statically
    and exports its locale facets' unique symbols: loaded first, they break the iostreams of
    PoCL's LLVM (its build options end at the first number, and the kernel fails with
    "stdint.h not found"). The system libstdc++ loaded first owns them."""
    import ctypes
    import ctypes.util

    ctypes.CDLL(ctypes.util.find_library("stdc++"), mode=ctypes.RTLD_GLOBAL)


_MCX_CHILD = """
import json, sys, time
import numpy as np
sys.path.insert(0, {here!r})
from bench_neb128 import load_system_libstdcxx, mcx_config
load_system_libstdcxx()
mcx = __import__({module!r})
mcx.run(mcx_config(10_000, {n}))  # first call JIT-compiles (pmcx has no Hopper code; pmcxcl builds its kernel)
runs = []
for _ in range(3):  # the median run by MCX's kernel time
    t0 = time.perf_counter()
    res = mcx.run(mcx_config({photons}, {n}))
    wall = time.perf_counter() - t0
    stat = {{k: (float(v) if isinstance(v, (int, float)) else None) for k, v in res.get("stat", {{}}).items()}}
    runs.append((stat.get("runtime") or 0.0, wall, stat))
runtime, wall, stat = sorted(runs, key=lambda r: r[0])[1]
print("MCXRESULT" + json.dumps({{"wall": wall, "stat": stat}}))
"""


def run_mcx(photons: int, module: str, n: int = N) -> dict | None:
    """Run MCX in a child process of this benchmark (pmcxcl and NebulaRT's pyopencl load two
    different PoCL builds, which abort when they share a process). None if not installed."""
    try:
        __import__("importlib.util").util.find_spec(module).name
    except AttributeError:
        return None
    code = _MCX_CHILD.format(here=str(Path(__file__).parent), module=module, photons=int(photons), n=int(n))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    line = next((l for l in proc.stdout.splitlines() if l.startswith("MCXRESULT")), None)
    if line is None:
        print(proc.stdout[-2000:], proc.stderr[-2000:], file=sys.stderr)
        raise RuntimeError(f"{module} failed (exit {proc.returncode})")
    out = json.loads(line[len("MCXRESULT"):])
    stat = out["stat"]
    runtime = stat.get("runtime") or float("nan")  # ms, MCX's own kernel timer
    e_abs, e_tot = stat.get("energyabs"), stat.get("energytot")
    return {
        "code": module, "device": "same device", "photons": photons, "grid": n, "kernel_ms": runtime,
        "photons_per_ms": round(photons / runtime) if runtime > 0 else None,
        "end_to_end_ms": round(out["wall"] * 1e3, 3),
        "absorbed_fraction": (e_abs / e_tot) if e_abs is not None and e_tot else None,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="cuda")
    ap.add_argument("--device", default="")
    ap.add_argument("--photons", type=float, nargs="+", default=[2.1e6, 2.1e7])
    ap.add_argument("--mcx", default="pmcx", help="pmcx (CUDA), pmcxcl (OpenCL) or none")
    ap.add_argument("--grid", type=int, default=N, help="voxels per edge (the medium scaled: optical depth 1)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    rows = []
    for p in (int(x) for x in args.photons):
        ours = run_nebula(p, args.backend, args.device, n=args.grid)
        rows.append(ours)
        theirs = run_mcx(p, args.mcx, args.grid) if args.mcx != "none" else None
        if theirs:
            rows.append(theirs)
            ours["ratio_vs_mcx"] = round(ours["photons_per_ms"] / theirs["photons_per_ms"], 3) if theirs["photons_per_ms"] else None
        for r in rows[-2 if theirs else -1:]:
            print(f"{r['code']:9s} {r['photons']:>11,d} photons  kernel {r['kernel_ms']:9.2f} ms  "
                  f"{r['photons_per_ms']!s:>9} photons/ms  end to end {r['end_to_end_ms']:9.2f} ms  "
                  f"absorbed {r['absorbed_fraction']}", flush=True)
    from provenance import provenance  # benchmarks/provenance.py

    result = {"benchmark": "neb128", "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
              **provenance(), "command": " ".join(["benchmarks/bench_neb128.py"] + (argv or sys.argv[1:])),
              "reference_absorbed_fraction_mcx": 0.4078, "rows": rows}
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
        print(f"saved {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
