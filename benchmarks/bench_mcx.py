#!/usr/bin/env python
"""NebulaRT beside MCX (pmcx, CUDA) and MCX-CL (pmcxcl, OpenCL) on the same media, in one run.

    python benchmarks/bench_mcx.py [--backend cuda|opencl] [--device SEL] [--codes nebula pmcx pmcxcl]
                                   [--media uniform turbulent] [--grids 64 128] [--photons 1e7]
                                   [--repeats 3] [--sigma-ln 1.0] [--tuning KEY=VALUE ...] [--out FILE]

The scene is bench_neb128's medium scaled to n^3 voxels: an isotropic source at the box centre,
albedo 0.6, g 0.6, no reflection, and extinction 2 per box edge at density 1 (optical depth 1
from the centre to a face of the uniform box). Two media:

* ``uniform``: density 1 everywhere. MCX gets one label (its native byte volume).
* ``turbulent``: a lognormal density rho = exp(sigma G) / <exp(sigma G)>, G a Gaussian random field
  with a Kolmogorov power spectrum P(k) ~ k^-11/3 and unit variance on the grid (seeded, made
  here with NumPy, the same array for every code), mean 1. NebulaRT reads it as its
  ``dust.model = "file"`` (.npy, x-y-z order); MCX and MCX-CL get the same per-voxel absorption
  and scattering as their 2-channel float volume (shape (2, n, n, n): mu_a, mu_s per voxel, which
  they store as two half floats, "muamus_half"; g and n from medium 1). It is the per-voxel
  format both take (pmcxcl refuses pmcx's 4-channel "asgn_float") and the more compact, 4 bytes a
  voxel as NebulaRT's float32 density; half floats round mu_a and mu_s by at most 2^-11.

Coordinates: NebulaRT's box [0, 1]^3 is MCX's [0, n]^3 voxel-edge frame (``issrcfrom0 = 1``, one
voxel = 1 mm = 1/n box), so the source at box (0.5, 0.5, 0.5) is MCX's ``srcpos`` (n/2, n/2, n/2)
and voxel [i, j, k] of the NumPy array is voxel (x, y, z) = (i, j, k) in both codes. The octant
check holds this: each code's absorbed energy in the box's 8 octants (NebulaRT: J rho; MCX: its
fluence times mu_a), as fractions of the total, must agree; a swapped axis of a lognormal medium
moves them. The ``agreement`` block of each row gives the absorbed fractions and the largest
octant difference against the other codes.

Each configuration runs in its own process (NebulaRT's pyopencl and pmcxcl load different PoCL
builds on a CPU machine; a GPU's memory is returned between them). Reported: each code's own kernel
time (median of ``--repeats``, compile excluded after a warm-up at the same grid), packets per ms,
the wall time of a whole run, the absorbed fraction; and per (medium, grid, photons) NebulaRT's
packets per ms over the faster MCX's. A code that is not installed or does not run on this
machine is reported with its reason, not dropped silently.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from tuning import add_tuning_argument  # benchmarks/tuning.py

HERE = Path(__file__).resolve().parent
TAU = 2.0  # extinction per box edge at density 1 (optical depth 1 from the centre to a face)
ALBEDO = 0.6
G = 0.6
KOLMOGOROV_SLOPE = 11.0 / 3.0
MEDIUM_SEED = 20261205
MCX_CODES = ("pmcx", "pmcxcl")


def lognormal_medium(n: int, sigma_ln: float, seed: int = MEDIUM_SEED) -> np.ndarray:
    """A lognormal density on n^3 voxels, float32 (x, y, z), mean exactly 1.

    G is white noise filtered to P(k) ~ k^-11/3 (the mean removed), scaled to unit variance;
    rho = exp(sigma_ln G), divided by its mean. float32 transforms keep 1024^3 within about 13 GB.
    """
    import scipy.fft

    rng = np.random.default_rng(seed)
    spec = scipy.fft.rfftn(rng.standard_normal((n, n, n), dtype=np.float32), workers=-1)
    kx = np.fft.fftfreq(n).astype(np.float32)
    kz = np.fft.rfftfreq(n).astype(np.float32)
    k2 = kx[:, None, None] ** 2 + kx[None, :, None] ** 2 + kz[None, None, :] ** 2
    k2[0, 0, 0] = np.inf  # no mean
    spec *= k2 ** np.float32(-KOLMOGOROV_SLOPE / 4.0)  # amplitude k^(-slope/2)
    del k2
    field = scipy.fft.irfftn(spec, s=(n, n, n), workers=-1).astype(np.float32, copy=False)
    del spec
    field /= np.float32(field.std(dtype=np.float64))
    np.multiply(field, np.float32(sigma_ln), out=field)
    np.exp(field, out=field)
    field /= np.float32(field.mean(dtype=np.float64))
    return field


def octant_fractions(absorbed: np.ndarray) -> list:
    """Shares of ``absorbed`` (n^3, x-y-z) in the box's octants, in (x, y, z) low/high order."""
    h = absorbed.shape[0] // 2
    sums = [float(absorbed[a:a + h, b:b + h, c:c + h].sum(dtype=np.float64))
            for a in (0, h) for b in (0, h) for c in (0, h)]
    total = sum(sums)
    return [s / total for s in sums]


# --------------------------------------------------------------------------------------------
# children: one configuration each
def nebula_scene(medium_file: str | None, n: int, photons: int, backend: str, device: str):
    """bench_neb128's scene on n^3 voxels, its dust read from ``medium_file`` (None: uniform)."""
    from bench_neb128 import nebula_scene_dict

    from nebula_rt.scene import Scene

    tables = nebula_scene_dict(photons, backend, device, n)
    if medium_file is not None:
        tables["dust"] = {"model": "file", "file": medium_file, "floor": 0.0, "tau": TAU}
    return Scene.from_dict(tables)


def child_nebula(medium_file, n, photons, repeats, backend_name, device, tuning=()) -> dict:
    from nebula_rt.backends import get_backend
    from nebula_rt.pipeline import Pipeline
    from tuning import apply_tuning  # benchmarks/tuning.py

    backend = get_backend(backend_name, device)
    apply_tuning(backend, tuning)
    Pipeline(backend).run(nebula_scene(medium_file, n, 10_000, backend_name, device), colour=False)  # compile
    scene = nebula_scene(medium_file, n, photons, backend_name, device)
    runs = []
    light = None
    for _ in range(max(1, repeats)):
        light = None
        t0 = time.perf_counter()
        light = Pipeline(backend).run(scene, colour=False)
        runs.append((float(light.timings["kernel_s"]), time.perf_counter() - t0))
    kernel_ms = statistics.median(r[0] for r in runs) * 1e3
    c = np.asarray(light.transport.counts[0], np.int64)
    rho = np.ones([n] * 3, np.float32) if medium_file is None else np.load(medium_file, mmap_mode="r")
    p_abs = float(c[1]) / photons
    return {"code": "NebulaRT", "device": backend.device_name, "kernel_ms": round(kernel_ms, 3),
            "photons_per_ms": round(photons / kernel_ms), "end_to_end_ms": round(statistics.median(r[1] for r in runs) * 1e3, 3),
            "absorbed_fraction": p_abs, "absorbed_sigma": math.sqrt(p_abs * (1 - p_abs) / photons),
            "octants": octant_fractions(np.asarray(light.J[0], np.float64) * rho), "repeats": len(runs)}


def mcx_config(medium_file, n: int, photons: int) -> dict:
    """bench_neb128's MCX configuration on n^3 voxels (mu_t = TAU / n per 1 mm voxel, mu_a =
    (1 - albedo) mu_t, mu_s = albedo mu_t); for a medium file, (mu_a, mu_s) per voxel times rho."""
    from bench_neb128 import mcx_config as uniform_config

    cfg = uniform_config(photons, n)
    if medium_file is not None:
        mu_t = TAU / n
        rho = np.load(medium_file)
        vol = np.empty((2, n, n, n), np.float32)  # MCX reads it in Fortran order: (mu_a, mu_s) pairs
        vol[0] = rho * np.float32((1.0 - ALBEDO) * mu_t)
        vol[1] = rho * np.float32(ALBEDO * mu_t)
        cfg["vol"] = vol
    return cfg


def child_mcx(code, medium_file, n, photons, repeats) -> dict:
    from bench_neb128 import load_system_libstdcxx

    load_system_libstdcxx()  # before pmcxcl
    mcx = __import__(code)
    mcx.run(mcx_config(medium_file, n, 10_000))  # first call compiles (pmcx: PTX JIT; pmcxcl: the kernel)
    runs = []
    res = None
    for _ in range(max(1, repeats)):
        res = None
        t0 = time.perf_counter()
        res = mcx.run(mcx_config(medium_file, n, photons))
        wall = time.perf_counter() - t0
        stat = {k: (float(v) if isinstance(v, (int, float)) else None) for k, v in res.get("stat", {}).items()}
        runs.append((stat.get("runtime") or 0.0, wall, stat))
    runtime = statistics.median(r[0] for r in runs)  # ms, MCX's own kernel timer
    stat = runs[-1][2]
    flux = np.asarray(res["flux"], np.float64).reshape(n, n, n, -1).sum(axis=3)
    mua = (1.0 - ALBEDO) * TAU / n * (np.ones([n] * 3) if medium_file is None else np.load(medium_file))
    return {"code": code, "version": getattr(mcx, "__version__", None), "kernel_ms": runtime,
            "photons_per_ms": round(photons / runtime) if runtime > 0 else None,
            "end_to_end_ms": round(statistics.median(r[1] for r in runs) * 1e3, 3),
            "absorbed_fraction": stat["energyabs"] / stat["energytot"], "octants": octant_fractions(flux * mua),
            "repeats": len(runs)}


# --------------------------------------------------------------------------------------------
def _run_child(args: list, timeout: float, tuning=()) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", *map(str, args)]
    if tuning:
        cmd += ["--tuning", *tuning]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"no result within {timeout:.0f} s"}
    line = next((l for l in proc.stdout.splitlines() if l.startswith("RESULT ")), None)
    if line is None:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        return {"error": f"exit {proc.returncode}: " + " | ".join(tail)}
    return json.loads(line[len("RESULT "):])


def _agreement(rows: list) -> None:
    """Per row: the absorbed fraction's and the octants' largest difference from the other codes."""
    ok = [r for r in rows if "absorbed_fraction" in r]
    for r in ok:
        others = [o for o in ok if o is not r]
        r["agreement"] = {o["code"]: {
            "absorbed_difference": r["absorbed_fraction"] - o["absorbed_fraction"],
            "octant_max_difference": max(abs(a - b) for a, b in zip(r["octants"], o["octants"])),
        } for o in others}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--child", nargs=7, metavar="X", help=argparse.SUPPRESS)
    ap.add_argument("--backend", default="cuda")
    ap.add_argument("--device", default="")
    ap.add_argument("--codes", nargs="+", default=["nebula", *MCX_CODES], choices=["nebula", *MCX_CODES])
    ap.add_argument("--media", nargs="+", default=["uniform", "turbulent"], choices=["uniform", "turbulent"])
    ap.add_argument("--grids", type=int, nargs="+", default=[64, 128])
    ap.add_argument("--photons", type=float, nargs="+", default=[1e7])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sigma-ln", type=float, default=1.0, help="standard deviation of ln rho (turbulent)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds for one configuration")
    add_tuning_argument(ap)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.child:
        code, medium_file, n, photons, repeats, backend, device = args.child
        medium_file = None if medium_file == "-" else medium_file
        n, photons, repeats = int(n), int(float(photons)), int(repeats)
        out = (child_nebula(medium_file, n, photons, repeats, backend, device, args.tuning) if code == "nebula"
               else child_mcx(code, medium_file, n, photons, repeats))
        print("RESULT " + json.dumps(out), flush=True)
        return 0

    from provenance import provenance  # benchmarks/provenance.py

    head = {"benchmark": "mcx", "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            **provenance(), "command": " ".join(["benchmarks/bench_mcx.py"] + (argv or sys.argv[1:])),
            "scene": {"tau_per_box_edge": TAU, "albedo": ALBEDO, "g": G, "source": "isotropic, box centre"},
            "tuning": args.tuning}

    def save(groups):
        if args.out:
            Path(args.out).write_text(json.dumps({**head, "groups": groups}, indent=2) + "\n")

    groups = []
    with tempfile.TemporaryDirectory() as tmp:
        for medium in args.media:
            for n in args.grids:
                medium_file = "-"
                stats = None
                if medium == "turbulent":
                    rho = lognormal_medium(n, args.sigma_ln)
                    medium_file = str(Path(tmp) / f"lognormal-{n}.npy")
                    np.save(medium_file, rho)
                    stats = {"sigma_ln": args.sigma_ln, "seed": MEDIUM_SEED, "min": float(rho.min()),
                             "max": float(rho.max()), "std": float(rho.std(dtype=np.float64))}
                    del rho
                for p in (int(x) for x in args.photons):
                    rows = []
                    for code in args.codes:
                        r = _run_child([code, medium_file, n, p, args.repeats, args.backend, args.device], args.timeout,
                                       args.tuning if code == "nebula" else ())
                        r.setdefault("code", {"nebula": "NebulaRT"}.get(code, code))
                        rows.append(r)
                        shown = (f"{r['kernel_ms']:10.2f} ms kernel  {r['photons_per_ms']!s:>9} packets/ms  "
                                 f"absorbed {r['absorbed_fraction']:.5f}" if "kernel_ms" in r else r.get("error"))
                        print(f"{medium:9s} {n:5d}^3 {p:>13,d}  {r['code']:9s} {shown}", flush=True)
                    _agreement(rows)
                    ours = next((r for r in rows if r["code"] == "NebulaRT" and "photons_per_ms" in r), None)
                    mcx = [r["photons_per_ms"] for r in rows if r["code"] in MCX_CODES and r.get("photons_per_ms")]
                    ratio = round(ours["photons_per_ms"] / max(mcx), 3) if ours and mcx else None
                    worst = max((d["octant_max_difference"] for r in rows for d in r.get("agreement", {}).values()),
                                default=None)
                    print(f"{'':9s} {'':6s} {'':13s}  NebulaRT / faster MCX: {ratio}   largest octant difference: "
                          f"{worst if worst is None else f'{worst:.2e}'}", flush=True)
                    groups.append({"medium": medium, "grid": n, "photons": p, "medium_stats": stats,
                                   "ratio_vs_faster_mcx": ratio, "rows": rows})
                    save(groups)  # after each group: a run cut short keeps what it measured
    if args.out:
        print(f"saved {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
