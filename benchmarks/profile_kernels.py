#!/usr/bin/env python
"""Where a CUDA transport's device time goes, kernel by kernel: the neb medium (uniform dust,
optical depth 1 centre to face, albedo 0.6, g 0.6, a point source at the centre) on n^3 voxels.

    python benchmarks/profile_kernels.py [--grids 256 512] [--photons 1e8]
        [--tuning "NRT_SORTED=0" "NRT_SORTED=1" ...] [--variant transport_old.cl ...] [--out FILE.json]

Each device call of the backend (every kernel launch, the key sort, fills and copies) is timed
with CUDA events around it and the stream synchronised after it, so the calls do not overlap
(the totals slightly exceed a free-running trace). With ``--free-running`` nothing is
synchronised: the events only mark each call's start and end on the stream, and the time the
stream stood idle before a call (``idle_before_s``: the host had not yet issued it, e.g. while it
waited for a copy and did the Python work of the next pass) is reported beside the device times. Per configuration: the time per kernel name
and calls, launches of the transport kernel with their packets, and the packets per ms of the
transport kernel alone. Each ``--tuning`` entry is one configuration (space-separated
KEY=VALUE options of the transport kernel, ``trace_block=N`` its threads per block, "" for the
backend's defaults), run with the
transport source as built and with each ``--variant`` (another transport source in kernels/,
e.g. an older version kept aside for comparison).
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def profile(n: int, photons: int, tuning: dict, program: str = "", free_running: bool = False,
            error_estimate: str = "batches", scene_file: str = "") -> dict:
    import cupy as cp
    import numpy as np

    from nebula_rt.backends.cuda import CUDABackend
    from nebula_rt.optics.bands import Band
    from nebula_rt.scene import Star
    from nebula_rt.transport import trace

    from nebula_rt.backends.cuda import TRACE_BLOCK

    tuning = dict(tuning)
    block = int(tuning.pop("trace_block", TRACE_BLOCK))
    be = CUDABackend("", transport_tuning=tuning, trace_block=block,
                     compile_options=("-lineinfo",) if LINEINFO else ())
    if program:
        be.transport_program = program
    bands = [Band(name="V", wavelength=550.0, extinction=1.0, albedo=0.6, g=0.6)]
    stars = [Star(position=(0.5, 0.5, 0.5), luminosity=1.0, temperature=None, bump_radius=0.0)]
    if not scene_file:  # (a scene is traced once untimed below, on its own grid)
        trace(np.ones((16, 16, 16), np.float32), bands, stars, tau=2.0, photons=10_000, backend=be)  # compile

    times: dict = collections.defaultdict(float)
    idle: dict = collections.defaultdict(float)
    calls: dict = collections.Counter()
    trace_packets = []
    marks = []  # free running: (name, start event, end event) in the order issued

    def timed(name_of, fn):
        def wrapper(*args, **kwargs):
            start, end = cp.cuda.Event(), cp.cuda.Event()
            start.record()
            out = fn(*args, **kwargs)
            end.record()
            name = name_of(args)
            calls[name] += 1
            if free_running:
                marks.append((name, start, end))
            else:
                end.synchronize()
                times[name] += cp.cuda.get_elapsed_time(start, end) / 1e3
            return out
        return wrapper

    be.launch = timed(lambda a: a[1], be.launch)
    orig_trace = be.launch_trace

    def launch_trace(*args, **kwargs):
        trace_packets.append(int(args[2]))
        return orig_trace(*args, **kwargs)

    be.launch_trace = timed(lambda a: a[1], launch_trace)
    be.fill_zero = timed(lambda a: "fill_zero", be.fill_zero)
    be.to_host = timed(lambda a: "to_host", be.to_host)
    be.upload = timed(lambda a: "upload", be.upload)
    if scene_file:
        # a scene's own transport (as the pipeline runs it: the sums stay on the device), traced
        # once untimed so that every kernel it needs is built
        from nebula_rt.density import generate_density
        from nebula_rt.scene import Scene
        from nebula_rt.transport.request import TransportRequest

        scene = Scene.load(scene_file).with_overrides([f"grid.shape=[{n},{n},{n}]", f"transport.photons={photons}"])
        rho = generate_density(scene, be)
        request = TransportRequest.from_scene(scene)
        request.trace(rho, be, on_device=True)
        cp.cuda.Device().synchronize()
        times.clear(), idle.clear(), calls.clear(), marks.clear(), trace_packets.clear()
        t0 = time.perf_counter()
        res = request.trace(rho, be, on_device=True)
    else:
        rho = np.ones((n, n, n), np.float32)
        t0 = time.perf_counter()
        res = trace(rho, bands, stars, tau=2.0, photons=photons, backend=be, error_estimate=error_estimate)
    cp.cuda.Device().synchronize()
    wall = time.perf_counter() - t0
    span = 0.0
    for i, (name, start, end) in enumerate(marks):
        times[name] += cp.cuda.get_elapsed_time(start, end) / 1e3
        if i:
            idle[name] += max(0.0, cp.cuda.get_elapsed_time(marks[i - 1][2], start) / 1e3)
    if marks:
        span = cp.cuda.get_elapsed_time(marks[0][1], marks[-1][2]) / 1e3
    t_trace = times.get("trace_photons", 0.0)
    return {"grid": n, "photons": photons, "scene": scene_file, "tuning": tuning, "trace_block": block, "error_estimate": error_estimate, "program": be.transport_program, "wall_s": wall,
            "kernel_s": float(res.timings["kernel_s"]), "batches": int(res.batches),
            "absorbed_fraction": float(res.counts[0, 1] / res.counts[0, 0]),
            "device_s": dict(sorted(times.items(), key=lambda kv: -kv[1])), "calls": dict(calls),
            "free_running": free_running, "span_s": span,
            "idle_before_s": dict(sorted(idle.items(), key=lambda kv: -kv[1])),
            "trace_launches": len(trace_packets), "trace_packets": trace_packets[:64],
            "trace_packets_per_ms": res.counts[:, 0].sum() / (t_trace * 1e3) if t_trace else None}


#: compile with line information (``--lineinfo``: Nsight Compute maps its counters to source lines)
LINEINFO = False


def main(argv=None) -> int:
    global LINEINFO
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--grids", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--photons", type=float, default=1e8)
    ap.add_argument("--tuning", nargs="*", default=[""])
    ap.add_argument("--variant", nargs="*", default=[], help="other transport sources in kernels/")
    ap.add_argument("--error-estimate", default="batches", choices=["auto", "batches", "packets"])
    ap.add_argument("--scene", default="", help="a scene file traced instead of the neb medium (its grid set to each "
                    "of --grids, its photons per band to --photons)")
    ap.add_argument("--free-running", action="store_true", help="no synchronisation: idle gaps between calls")
    ap.add_argument("--lineinfo", action="store_true", help="compile with -lineinfo (for ncu's source page)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    LINEINFO = args.lineinfo
    records = []
    for text in args.tuning:
        tuning = {k: int(v) for k, v in (item.split("=", 1) for item in text.split())}
        for n in args.grids:
            for program in [""] + list(args.variant):
                rec = profile(n, int(args.photons), tuning, program, args.free_running, args.error_estimate,
                              args.scene)
                records.append(rec)
                top = ", ".join(f"{k} {v:.3f} s/{rec['calls'][k]}" for k, v in list(rec["device_s"].items())[:5])
                print(f"{n}^3 {rec['program']:<20} {text or 'defaults':<30} kernel {rec['kernel_s']:.3f} s  trace "
                      f"{rec['trace_packets_per_ms'] or 0:,.0f} pkt/ms  launches {rec['trace_launches']}  [{top}]",
                      flush=True)
                if args.free_running:
                    gaps = ", ".join(f"{k} {v:.3f} s" for k, v in list(rec["idle_before_s"].items())[:5])
                    print(f"    span {rec['span_s']:.3f} s, idle before: {gaps}", flush=True)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"benchmark": "profile_kernels", "date": time.strftime("%Y-%m-%d %H:%M:%S"),
                                              "command": " ".join(["benchmarks/profile_kernels.py"] + (argv or sys.argv[1:])),
                                              "records": records}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
