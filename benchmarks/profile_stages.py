#!/usr/bin/env python
"""Where the end-to-end time of the thesis headline goes, step by step, on a CUDA GPU.

    python benchmarks/profile_stages.py [--grid 128] [--photons 2100000]

Times each post-processing step with a device synchronisation around it (so asynchronous
work is attributed to the step that launched it). A development aid, not a benchmark: the
synchronisations themselves cost a little.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--grid", type=int, default=128)
    ap.add_argument("--photons", type=float, default=2.1e6)
    args = ap.parse_args()
    import cupy as cp

    from nebula_rt import pipeline as pl
    from nebula_rt.backends import get_backend
    from nebula_rt.scene import Scene

    backend = get_backend("cuda", "")
    scene = Scene.load(ROOT / "examples/scenes/thesis-default.toml").with_overrides(
        [f"grid.shape=[{args.grid},{args.grid},{args.grid}]", f"transport.photons={int(args.photons)}"])
    pl.Pipeline(backend).run(scene.with_overrides(["grid.shape=[8,8,8]", "transport.photons=1000"]))
    for rep in range(2):
        times = {}
        sync = cp.cuda.Device().synchronize

        def step(name, fn):
            sync()
            t = time.perf_counter()
            out = fn()
            sync()
            times[name] = (time.perf_counter() - t) * 1e3
            return out

        t0 = time.perf_counter()
        rho = step("density", lambda: pl.generate_density(scene, backend))
        res, J, rel = step("transport", lambda: pl.compute_light(scene, rho, backend, on_device=True))
        light, emis, rho_x = step("assemble (emissivity, float32 copies to host)",
                                  lambda: pl.assemble_light_field(scene, rho, res, J, rel, with_device_emissivity=True))
        step("colour (rgba to host)", lambda: pl.colour_rgba(scene, light.bands, rho_x, emis, res))
        total = (time.perf_counter() - t0) * 1e3
        print(f"run {rep}: total {total:.1f} ms, kernels {res.timings['kernel_s'] * 1e3:.1f} ms")
        for k, v in times.items():
            print(f"   {k:50s} {v:8.1f} ms")
    # finer: the colour stage's pieces
    bands = light.bands
    sig_ref = scene.dust.tau * bands[1].extinction * rho_x
    for name, fn in [
        ("to_numpy of one float32 band (8 MiB)", lambda: pl.to_numpy(J[0].astype(cp.float32))),
        ("astype float32 of J", lambda: J.astype(cp.float32)),
        ("tensordot emissivity x (3, nb)", lambda: cp.tensordot(emis, cp.ones((3, 3)), axes=([0], [1]))),
        ("percentile of 1M", lambda: cp.percentile(cp.random.random(1_000_000), 95)),
        ("rgba_from_emissivity", lambda: pl.rgba_from_emissivity(emis, sig_ref, wavelengths_nm=np.array([677., 550., 439.]),
                                                                  band_luminosity=res.band_luminosity, temperature=20000.0)),
    ]:
        cp.cuda.Device().synchronize()
        t = time.perf_counter()
        fn()
        cp.cuda.Device().synchronize()
        print(f"   {name:50s} {(time.perf_counter() - t) * 1e3:8.1f} ms")


if __name__ == "__main__":
    main()
