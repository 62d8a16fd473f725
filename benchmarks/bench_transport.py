#!/usr/bin/env python
"""Transport benchmark on the local OpenCL device: prints a table and saves JSON.

    python benchmarks/bench_transport.py                # thesis headline + smaller grids
    python benchmarks/bench_transport.py --quick        # fewer photons (smoke run)
    python benchmarks/bench_transport.py --device NVIDIA --out benchmarks/results/x.json

Each configuration runs in its own process (so its peak host memory is its own) after a
warm-up run on the same grid with 1000 packets that compiles the kernels (compile time is
reported separately, not included).
Scenes: the thesis default nebula (turbulence, star at the centre, thesis-rgb, albedo = g = 0.6,
tau = 128) at 32^3, 64^3 and the thesis headline 128^3 x 3 bands x 2.1M packets.
Reported (the median of 5 runs after the warm-up, and the first run): wall time of the whole pipeline (density + transport + colour), the transport kernel
time, packets per second over all bands, peak host RSS and the device buffers allocated.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

from provenance import provenance  # noqa: E402  (benchmarks/provenance.py, beside this script)

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "examples" / "scenes" / "thesis-default.toml"

#: runs per configuration after the warm-up; the median run is reported
REPEATS = 5

CONFIGS = [
    {"name": "thesis-32", "shape": [32, 32, 32], "photons": 2_100_000},
    {"name": "thesis-64", "shape": [64, 64, 64], "photons": 2_100_000},
    {"name": "thesis-128 (headline)", "shape": [128, 128, 128], "photons": 2_100_000},
]


def run_single(cfg: dict, device: str, backend_name: str = "opencl") -> dict:
    """Run one configuration in this process and return its measurements."""
    from nebula_rt.backends import get_backend
    from nebula_rt.pipeline import Pipeline
    from nebula_rt.scene import Scene

    overrides = [f"grid.shape={cfg['shape']}", f"transport.photons={cfg['photons']}",
                 f'transport.device="{device}"', f'transport.backend="{backend_name}"']
    scene = Scene.load(SCENE).with_overrides(overrides)
    backend = get_backend(backend_name, device)
    t0 = time.perf_counter()
    # warm up on the same grid: kernels compile, and CuPy specialises some reductions and
    # sorts to the array sizes, so a smaller grid would leave compiling inside the timing
    Pipeline(backend).run(scene.with_overrides(["transport.photons=1000"]))  # (result dropped)
    compile_s = time.perf_counter() - t0
    runs = []
    for _ in range(REPEATS):  # a fresh pipeline each time: every stage runs
        t0 = time.perf_counter()
        light = Pipeline(backend).run(scene)
        wall = time.perf_counter() - t0
        # keep figures, not the light field: as in an application that replaces its previous
        # result, the host buffers of one run are free for the next
        runs.append((wall, dict(light.timings), light.transport.counts.copy()))
        nb, nvox, device = len(light.bands), int(light.density.size), light.transport.device
        del light
    first_wall = runs[0][0]
    wall, timings, counts = sorted(runs, key=lambda r: r[0])[len(runs) // 2]  # the median run
    kernel_s = timings["kernel_s"]
    total_packets = cfg["photons"] * nb
    return {
        "name": cfg["name"],
        "grid": cfg["shape"],
        "bands": nb,
        "photons_per_band": cfg["photons"],
        "wall_s": round(wall, 4),
        "wall_s_first": round(first_wall, 4),
        "repeats": REPEATS,
        "density_s": round(timings["density_s"], 4),
        "transport_s": round(timings["transport_s"], 4),
        "transport_kernel_s": round(kernel_s, 4),
        "finish_s": round(timings["finish_s"], 4),
        "packets_per_s_kernel": round(total_packets / kernel_s),
        "packets_per_s_end_to_end": round(total_packets / wall),
        "compile_and_warmup_s": round(compile_s, 3),
        "peak_host_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        # density (4 B) + batch accumulator (8 B) + sum and sum of squares (2 x 8 B) per band
        "device_buffers_mib": round((4 + nb * 24) * nvox / 2**20, 1),
        "escaped_fraction": [float(x) for x in counts[:, 2] / cfg["photons"]],
        "device": device,
    }





def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="opencl", choices=["opencl", "cuda", "auto"])
    ap.add_argument("--device", default="", help="device selector (default: first GPU, else CPU)")
    ap.add_argument("--quick", action="store_true", help="divide the photon counts by 20")
    ap.add_argument("--only", default=None, help="run only configurations whose name contains this")
    ap.add_argument("--out", default=None, help="JSON output (default benchmarks/results/transport-<device>-<date>.json)")
    ap.add_argument("--single", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.single:
        print(json.dumps(run_single(json.loads(args.single), args.device, args.backend)))
        return 0
    configs = [dict(c) for c in CONFIGS if args.only is None or args.only in c["name"]]
    if args.quick:
        for c in configs:
            c["photons"] //= 20
    rows = []
    for cfg in configs:
        proc = subprocess.run([sys.executable, __file__, "--single", json.dumps(cfg), "--device", args.device,
                               "--backend", args.backend],
                              capture_output=True, text=True)
        if proc.returncode != 0:
            print(proc.stderr, file=sys.stderr)
            return proc.returncode
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(f"{row['name']:24s} grid {'x'.join(map(str, row['grid'])):>11s}  {row['bands']} x {row['photons_per_band']:>9,d} "
              f"packets  wall {row['wall_s']:8.3f} s  kernel {row['transport_kernel_s']:8.3f} s  "
              f"{row['packets_per_s_kernel'] / 1e3:9.1f} k packets/s  peak RSS {row['peak_host_rss_mib']:7.1f} MiB  "
              f"device {row['device_buffers_mib']:6.1f} MiB", flush=True)
    device = rows[0]["device"] if rows else "none"
    result = {
        "benchmark": "transport",
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        **provenance(),
        "command": " ".join([Path(sys.executable).name, "benchmarks/bench_transport.py"] + (argv if argv is not None else sys.argv[1:])),
        "device": device,
        "host": {"machine": platform.machine(), "cpus": os.cpu_count(), "python": platform.python_version()},
        "scene": str(SCENE.relative_to(ROOT)),
        "thesis_reference": {"grid": [128, 128, 128], "bands": 3, "photons_per_band": 2_100_000,
                             "wall_ms": 4013, "device": "GeForce GTS 250"},
        "results": rows,
    }
    slug = "".join(ch if ch.isalnum() else "-" for ch in device.lower()).strip("-")[:40]
    out = Path(args.out) if args.out else ROOT / "benchmarks" / "results" / f"transport-{slug}-{_dt.date.today()}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"saved {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
