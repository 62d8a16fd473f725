#!/usr/bin/env python
"""Transport-kernel variants on a CUDA GPU, side by side in one run.

    python benchmarks/tune_cuda.py [--variant FILE.cl ...] [--out FILE.json]

Times the transport kernels (median of repeats, after a warm-up) as built, with each of the
kernel's performance options (``TRANSPORT_TUNING``: unchecked adds, density prefetch,
work-group tallies) switched off alone, on alone and all off, with 64- and 256-thread blocks
(default 128), with contracted a * b + c (``--fmad=true``), and each extra kernel named with
``--variant`` (a transport source in ``kernels/``, e.g. an older version kept aside for
comparison). Every configuration without contraction must give the same bits: the sums of
each scene are compared with the first configuration's. Scenes:

  - neb128 (uniform, tau 1 centre to face, a = g = 0.6, one band) with 2.1M and 21M photons;
  - the thesis nebula at 128^3, 3 bands x 2.1M packets.

The kernel time is the sum over the launches (trace + fold), as the other benchmarks report.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))


def kernel_ms(backend, scene, repeats: int):
    from nebula_rt.pipeline import Pipeline
    from nebula_rt.transport import trace

    rho = Pipeline(backend).density(scene)
    t = scene.transport

    def once(photons):
        return trace(rho, scene.bands.resolve(), scene.stars, tau=scene.dust.tau, photons=photons,
                     max_scatterings=t.max_scatterings, seed=t.seed, backend=backend, on_device=True)

    once(10_000)  # compile
    times, digest = [], None
    for _ in range(repeats):
        res = once(t.photons)
        times.append(res.timings["kernel_s"] * 1e3)
        s1, s2 = (a.get() for a in res.device_sums.host_sums())
        digest = hashlib.sha256(s1.tobytes() + s2.tobytes() + res.counts.tobytes()).hexdigest()[:16]
    return statistics.median(times), digest


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variant", nargs="*", default=[], help="extra transport sources in kernels/")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    from bench_neb128 import nebula_scene
    from nebula_rt.backends.cuda import CUDABackend
    from nebula_rt.scene import Scene

    thesis = Scene.load(ROOT / "examples/scenes/thesis-default.toml").with_overrides(
        ["grid.shape=[128,128,128]", "transport.photons=2100000", 'transport.backend="cuda"'])
    scenes = {"neb128 2.1M": (nebula_scene(2_100_000, "cuda", ""), 2_100_000),
              "neb128 21M": (nebula_scene(21_000_000, "cuda", ""), 21_000_000),
              "thesis 128^3 3x2.1M": (thesis, 3 * 2_100_000)}
    from nebula_rt.backends.base import TRANSPORT_TUNING

    none = {k: 0 for k in TRANSPORT_TUNING}
    block = CUDABackend("").trace_block
    configs = [("transport.cl", {}, block)]
    configs += [("transport.cl", {k: 0}, block) for k in TRANSPORT_TUNING]
    configs += [("transport.cl", dict(none, **{k: 1}), block) for k in TRANSPORT_TUNING]
    configs += [("transport.cl", none, 256), ("transport.cl", {}, 64), ("transport.cl", {}, 256)]
    configs += [("transport.cl", {}, -block)]  # negative: with contracted a * b + c (--fmad=true)
    configs += [(v, none, 256) for v in args.variant]
    rows, digests = [], {}
    for source, tuning, block in configs:
        be = CUDABackend("", trace_block=abs(block), transport_tuning=tuning, fmad=block < 0)
        be.transport_program = source
        label = ",".join(f"{k[4:].lower()}={v}" for k, v in tuning.items()) or "default"
        row = {"source": source, "tuning": tuning, "block": abs(block), "fmad": block < 0}
        for name, (scene, packets) in scenes.items():
            ms, digest = kernel_ms(be, scene, args.repeats if "21M" not in name else max(1, args.repeats // 2))
            same = digests.setdefault(name, digest) == digest
            row[name] = {"kernel_ms": round(ms, 3), "packets_per_ms": round(packets / ms), "same_bits": same}
        rows.append(row)
        print(f"{source:18s} {label:44s} block {abs(block):3d}{' fmad' if block < 0 else ''} " + "  ".join(
            f"{k}: {v['kernel_ms']:7.2f} ms ({v['packets_per_ms'] / 1e3:6.1f}k/ms{'' if v['same_bits'] else ' BITS DIFFER'})"
            for k, v in row.items() if isinstance(v, dict) and "kernel_ms" in v), flush=True)
    if args.out:
        import cupy as cp

        props = cp.cuda.runtime.getDeviceProperties(0)
        Path(args.out).write_text(json.dumps({
            "benchmark": "tune_cuda", "device": props["name"].decode(),
            "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "command": " ".join(["benchmarks/tune_cuda.py"] + (argv or sys.argv[1:])), "rows": rows}, indent=2) + "\n")
        print(f"saved {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
