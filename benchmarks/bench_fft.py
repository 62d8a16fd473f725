#!/usr/bin/env python
"""Collision-filter smoothing on an OpenCL device: host SciPy path vs VkFFT on the device.

    python benchmarks/bench_fft.py [--device SUBSTRING] [--grid 64 128] [--bands 3]
                                   [--radius 0.05] [--out FILE.json]

For ``--bands`` fields (and their variances) of grid^3 float64 held as pyopencl arrays on the
chosen OpenCL device, times the smoothing of all bands by:

(a) host   -- what an OpenCL run does today: copy field and variance device->host,
              ``filtering.normalised_convolution`` (SciPy FFTs) per band with
              variance, copy both results host->device;
(b) device -- ``filtering_opencl.normalised_convolution_cl`` per band (pyvkfft float64
              R2C/C2R FFTs and small pyopencl kernels; nothing but the kernel crosses the bus).

Each timing is the median of 5 runs after one warm-up run (the warm-up pays VkFFT's plan
generation and the OpenCL compile, reported separately as ``device_first_call_ms``). The queue
is finished before the clock stops. Also reported: the maximum element-wise relative difference
between (a) and (b) over all bands, for the field and the variance (the fields are strictly
positive). Without pyvkfft only (a) runs, and the output says so.

The kernel is ``filtering.cubic_kernel((n, n, n), radius)``, radius in box units.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
try:
    import nebula_rt  # noqa: F401
except ImportError:  # run from a checkout without installing the package
    sys.path.insert(0, str(ROOT / "python"))

REPEATS = 5


def _median_ms(fn, queue, repeats=REPEATS):
    times = []
    for _ in range(repeats):
        queue.finish()
        t0 = time.perf_counter()
        fn()
        queue.finish()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times), times


def host_path(queue, fields, variances, kernel, split=None):
    """(a): device->host, SciPy on the host per band, host->device. Returns device arrays."""
    import pyopencl.array as cla

    from nebula_rt.transport.filtering import normalised_convolution

    outs = []
    for f, v in zip(fields, variances):
        t0 = time.perf_counter()
        hf, hv = f.get(queue=queue), v.get(queue=queue)
        t1 = time.perf_counter()
        o, ov = normalised_convolution(hf, kernel, hv)
        t2 = time.perf_counter()
        do, dv = cla.to_device(queue, o), cla.to_device(queue, ov)
        queue.finish()
        t3 = time.perf_counter()
        if split is not None:
            split["d2h"] += (t1 - t0) * 1e3
            split["conv"] += (t2 - t1) * 1e3
            split["h2d"] += (t3 - t2) * 1e3
        outs.append((do, dv))
    return outs


def device_path(queue, fields, variances, kernel):
    """(b): normalised_convolution_cl per band. Returns device arrays."""
    from nebula_rt.transport.filtering_opencl import normalised_convolution_cl

    return [normalised_convolution_cl(queue, f, kernel, v) for f, v in zip(fields, variances)]


def _max_rel(pairs_a, pairs_b):
    rel_out = rel_var = 0.0
    for (ao, av), (bo, bv) in zip(pairs_a, pairs_b):
        ao, av, bo, bv = ao.get(), av.get(), bo.get(), bv.get()
        rel_out = max(rel_out, float(np.max(np.abs(bo - ao) / np.abs(ao))))
        rel_var = max(rel_var, float(np.max(np.abs(bv - av) / np.abs(av))))
    return rel_out, rel_var


def bench_grid(queue, n, bands, radius, with_device, seed=0):
    import pyopencl.array as cla

    from nebula_rt.transport.filtering import cubic_kernel

    shape = (n, n, n)
    kernel = cubic_kernel(shape, radius)
    rng = np.random.default_rng(seed)
    fields = [cla.to_device(queue, rng.random(shape) + 0.05) for _ in range(bands)]
    variances = [cla.to_device(queue, rng.random(shape) * 0.3 + 0.01) for _ in range(bands)]
    queue.finish()
    row = {"grid": n, "bands": bands, "radius": radius, "kernel_shape": list(kernel.shape)}

    ref = host_path(queue, fields, variances, kernel)  # warm-up (and the reference)
    row["host_ms"], row["host_runs_ms"] = _median_ms(
        lambda: host_path(queue, fields, variances, kernel), queue)
    split = {"d2h": 0.0, "conv": 0.0, "h2d": 0.0}
    host_path(queue, fields, variances, kernel, split)
    row["host_split_ms"] = split  # one extra run, for where the host path spends its time

    if with_device:
        from nebula_rt.transport.filtering_opencl import padded_shape

        row["padded_shape"] = list(padded_shape(shape, kernel.shape))
        t0 = time.perf_counter()
        got = device_path(queue, fields, variances, kernel)  # warm-up: plan + compile
        queue.finish()
        row["device_first_call_ms"] = (time.perf_counter() - t0) * 1e3
        row["device_ms"], row["device_runs_ms"] = _median_ms(
            lambda: device_path(queue, fields, variances, kernel), queue)
        row["speedup"] = row["host_ms"] / row["device_ms"]
        row["max_rel_diff_field"], row["max_rel_diff_variance"] = _max_rel(ref, got)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="Portable Computing Language",
                    help='OpenCL device: text in its "platform: device" name, or P:D indices')
    ap.add_argument("--grid", type=int, nargs="+", default=[64, 128], help="grid edges n (n^3 voxels)")
    ap.add_argument("--bands", type=int, default=3, help="number of bands (fields) per smoothing")
    ap.add_argument("--radius", type=float, default=0.05, help="kernel radius in box units")
    ap.add_argument("--out", default=None, help="write the results as JSON to this file")
    args = ap.parse_args(argv)

    import pyopencl as cl

    from nebula_rt.backends.opencl import select_device
    from nebula_rt.transport.filtering_opencl import available

    device, device_name = select_device(args.device)
    queue = cl.CommandQueue(cl.Context([device]))
    with_device = available()
    pyvkfft_version = None
    if with_device:
        from pyvkfft.version import __version__ as pyvkfft_version
    else:
        print("pyvkfft (VkFFT) is not importable: timing only the host path (a). "
              "pyvkfft has no PyPI wheels; build it from source to time the device path (b).")
    print(f"device: {device_name}")

    rows = []
    for n in args.grid:
        row = bench_grid(queue, n, args.bands, args.radius, with_device)
        rows.append(row)
        print(f"  grid {n}^3 done: {json.dumps({k: v for k, v in row.items() if not k.endswith('runs_ms')})}",
              flush=True)

    head = f"{'grid':>6} {'kernel':>10} {'bands':>5} {'host (a) ms':>12} {'d2h/conv/h2d ms':>20}"
    if with_device:
        head += f" {'device (b) ms':>14} {'1st call ms':>12} {'speed-up':>9} {'max rel (f/var)':>20}"
    print()
    print(head)
    for r in rows:
        s = r["host_split_ms"]
        line = (f"{r['grid']:>6} {'x'.join(map(str, r['kernel_shape'])):>10} {r['bands']:>5} "
                f"{r['host_ms']:>12.1f} {s['d2h']:>6.1f}/{s['conv']:>6.1f}/{s['h2d']:>6.1f}")
        if with_device:
            line += (f" {r['device_ms']:>14.1f} {r['device_first_call_ms']:>12.0f} {r['speedup']:>9.2f}"
                     f" {r['max_rel_diff_field']:>9.1e}/{r['max_rel_diff_variance']:.1e}")
        print(line)

    if args.out:
        report = {
            "benchmark": "collision-filter smoothing: host SciPy path vs VkFFT on the OpenCL device",
            "device": device_name,
            "grid": args.grid,
            "bands": args.bands,
            "radius": args.radius,
            "repeats": REPEATS,
            "statistic": "median after one warm-up run",
            "device_path": with_device,
            "note": None if with_device else "pyvkfft not importable: only the host path (a) was timed",
            "pyvkfft": pyvkfft_version,
            "numpy": np.__version__,
            "results": rows,
        }
        Path(args.out).write_text(json.dumps(report, indent=2) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
