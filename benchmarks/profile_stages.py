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

    from nebula_rt.density import generate_density
    from nebula_rt.pipeline import stages as pl
    from nebula_rt.pipeline import rgba
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

        light = None  # free the previous run's host buffers (pinned memory goes back to the pool)
        t0 = time.perf_counter()
        rho = step("density", lambda: generate_density(scene, backend))
        # as the pipeline does: summed on the device with the extremes (a former version: on a
        # host thread while the device traces)
        mean = (backend.density_mean(rho) if hasattr(backend, "density_mean")
                else rgba.mean_optical_depth_soon(rho))
        res, J, rel = step("transport", lambda: pl.compute_light(scene, rho, backend, on_device=True))
        light = step("finish on the device (+ arrays to the host)",
                     lambda: pl.finish_light_field(scene, rho, res, J, rel, colour=True, mean_density=mean))
        total = (time.perf_counter() - t0) * 1e3
        print(f"run {rep}: total {total:.1f} ms, kernels {res.timings['kernel_s'] * 1e3:.1f} ms, "
              f"transport set-up {res.timings['setup_s'] * 1e3:.1f} ms")
        for k, v in times.items():
            print(f"   {k:50s} {v:8.1f} ms")
    # the fixed cost: the same pipeline with 1000 packets per band (the kernels take almost
    # nothing, so what is left is the host's work, the small kernels and the copies), and where
    # its time goes by function (the device waits show as the synchronising calls' own time)
    small = scene.with_overrides(["transport.photons=1000"])
    import cProfile
    import pstats

    for rep in range(3):
        light = None
        t0 = time.perf_counter()
        light = pl.Pipeline(backend).run(small)
        sync()
        total = (time.perf_counter() - t0) * 1e3
        print(f"fixed cost {rep}: {total:.2f} ms end to end with 1000 packets per band; "
              + ", ".join(f"{k} {v * 1e3:.2f} ms" for k, v in light.timings.items()))
    prof = cProfile.Profile()
    prof.enable()
    light = pl.Pipeline(backend).run(small)
    sync()
    prof.disable()
    print("-- the fixed cost: functions by own time")
    pstats.Stats(prof).sort_stats("tottime").print_stats(25)
    # host side: which Python functions the transport and the finishing spend their time in
    # (time in a synchronising call includes the device work it waits for)
    for name, fn in [("transport", lambda: pl.compute_light(scene, rho, backend, on_device=True)),
                     ("finish", lambda: pl.finish_light_field(scene, rho, res, J, rel, colour=True))]:
        prof = cProfile.Profile()
        prof.enable()
        fn()
        sync()
        prof.disable()
        print(f"-- {name}: functions by own time")
        pstats.Stats(prof).sort_stats("tottime").print_stats(14)
    # finer: the pieces of the finishing step
    from nebula_rt.transport import finish as pp

    # a fresh run: finishing hands its device sums back (the memory of only what is needed)
    res, J, rel = pl.compute_light(scene, rho, backend, on_device=True)
    ds = res.device_sums
    bands = light.bands
    params = np.stack([res.j_scale, res.sigma_scale, [b.albedo for b in bands]], axis=1)
    nvox = ds.nvox
    for name, fn in [
        ("finish without colour (3 float32 arrays to host)",
         lambda: pp.finish(ds, params, batches=res.batches, collision=False)),
        ("one float32 band to pinned host memory (8 MiB)",
         lambda: backend.to_host(cp.zeros(nvox, cp.float32), backend.host_empty(nvox, np.float32))),
        ("one float32 band to pageable host memory (8 MiB)", lambda: cp.zeros(nvox, cp.float32).get()),
        ("the density's mean on the host (a density read from a file)", lambda: rgba.mean_optical_depth(rho)),
        ("the density's extremes and mean on the device (uncached)",
         lambda: backend.device_density_stats(backend.resident_density(rho), rho.size)
         if hasattr(backend, "device_density_stats") else backend.device_extremes(backend.resident_density(rho))),
        ("auto exposure radix select",
         lambda: pp.auto_exposure_on_device(backend, cp.random.random(nvox, dtype=cp.float32), nvox, 95.0)),
    ]:
        for _ in range(2):
            cp.cuda.Device().synchronize()
            t = time.perf_counter()
            fn()
            cp.cuda.Device().synchronize()
        print(f"   {name:50s} {(time.perf_counter() - t) * 1e3:8.1f} ms")


if __name__ == "__main__":
    main()
