#!/usr/bin/env python
"""Where a pipeline run's wall time goes, operation by operation: every call the library makes
to its compute backend (kernel launches, copies, allocations, the transport session's
creation), timed on the host, in two runs of the same scene:

- *as issued*: nothing added; each call's host entry and exit. Asynchronous calls return at
  once, so a long call here is the host waiting (a copy to the host, a read-back), and the
  time between calls is the library's own Python work;
- *serialised*: the device synchronised before and after every call, so each call's time is
  its own device work plus its host work. Their sum against the first run's wall time shows
  how much of the run the device is busy at all.

A development aid for the end-to-end time (the thesis headline's 12 ms target), not a
benchmark: the serialised run is slower than a real one by design.

    python benchmarks/profile_timeline.py --backend cuda [--grid 128] [--photons 2.1e6] [--out t.json]
    python benchmarks/profile_timeline.py --backend opencl --device Portable --grid 32 --photons 2e4
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))
from provenance import provenance, save  # noqa: E402  (benchmarks/provenance.py)

#: the backend's calls that reach the device (nebula_rt.backends.base.Backend)
CALLS = ("generate_density", "transport_session", "to_device", "device_zeros", "host_empty", "to_host",
         "to_host_async", "wait_copy", "upload", "fill_zero", "device_extremes", "map_host", "launch",
         "launch_trace")


def synchronizer(backend):
    """A function that waits for the backend's device to finish its queued work."""
    if getattr(backend, "name", "") == "cuda":
        import cupy as cp

        return cp.cuda.Device().synchronize
    return backend.queue.finish


class Recorder:
    """Wraps ``CALLS`` on a backend instance; each call appends (name, detail, host start,
    host end) in ms from ``t0``. ``serial``: synchronise the device around every call."""

    def __init__(self, backend, serial: bool):
        self.backend, self.serial, self.sync = backend, serial, synchronizer(backend)
        self.rows: list[tuple[str, str, float, float]] = []
        self.t0 = time.perf_counter()
        self.depth = 0  # calls made inside a wrapped call are not recorded twice
        for name in CALLS:
            if hasattr(backend, name):
                setattr(backend, name, self._wrap(name, getattr(backend, name)))

    def _wrap(self, name, fn):
        @functools.wraps(fn)
        def call(*args, **kwargs):
            if self.depth:
                return fn(*args, **kwargs)
            detail = args[1] if name.startswith("launch") and len(args) > 1 else ""
            if name in ("to_device", "to_host", "to_host_async", "upload", "device_zeros", "host_empty"):
                detail = _size(name, args)
            self.depth += 1
            try:
                if self.serial:
                    self.sync()
                t = time.perf_counter()
                out = fn(*args, **kwargs)
                if self.serial:
                    self.sync()
                self.rows.append((name, detail, (t - self.t0) * 1e3, (time.perf_counter() - self.t0) * 1e3))
                return out
            finally:
                self.depth -= 1
        return call

    def restore(self):
        for name in CALLS:
            self.backend.__dict__.pop(name, None)


#: library functions timed as spans of host time (module, attribute), so the listing shows
#: which step of the run the backend calls and the gaps between them belong to
SPANS = (("nebula_rt.pipeline.stages", "scene_density"), ("nebula_rt.transport.resources", "check"),
         ("nebula_rt.pipeline.stages", "compute_light"), ("nebula_rt.transport.run", "plan_transport"),
         ("nebula_rt.transport.run", "run_transport"), ("nebula_rt.transport.run", "estimate_light"),
         ("nebula_rt.transport.run", "warn_if_heavy_tailed"), ("nebula_rt.pipeline.stages", "finish_light_field"),
         ("nebula_rt.transport.finish", "finish"), ("nebula_rt.pipeline.stages", "scene_opacity_factor"))


class Spans:
    """Wraps the :data:`SPANS` functions (those present in the library as imported); each call
    appends (name, host start, host end) in ms from ``t0``."""

    def __init__(self, t0: float):
        import importlib

        self.t0, self.rows, self.saved = t0, [], []
        for mod_name, attr in SPANS:
            mod = importlib.import_module(mod_name)
            fn = getattr(mod, attr, None)
            if fn is None:
                continue
            self.saved.append((mod, attr, fn))
            setattr(mod, attr, self._wrap(f"{mod_name.rsplit('.', 1)[-1]}.{attr}", fn))

    def _wrap(self, name, fn):
        @functools.wraps(fn)
        def call(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.rows.append((name, (t - self.t0) * 1e3, (time.perf_counter() - self.t0) * 1e3))
        return call

    def restore(self):
        for mod, attr, fn in self.saved:
            setattr(mod, attr, fn)


def _size(name, args) -> str:
    """The bytes a copy or allocation moves, for the listing."""
    import numpy as np

    try:
        if name == "device_zeros":
            return f"{int(args[0]) * np.dtype(args[1]).itemsize / 2**20:.2f} MiB"
        if name == "host_empty":
            return f"{int(np.prod(args[0])) * np.dtype(args[1]).itemsize / 2**20:.2f} MiB"
        a = args[1] if name == "upload" else args[0]
        return f"{int(a.nbytes) / 2**20:.2f} MiB"
    except Exception:  # noqa: BLE001  (a listing detail only)
        return ""


def run_once(scene, backend, serial: bool) -> dict:
    from nebula_rt.pipeline import Pipeline

    sync = synchronizer(backend)
    sync()
    rec = Recorder(backend, serial)
    spans = Spans(0.0)
    try:
        rec.t0 = spans.t0 = time.perf_counter()
        light = Pipeline(backend).run(scene)
        sync()
        wall = (time.perf_counter() - rec.t0) * 1e3
    finally:
        rec.restore()
        spans.restore()
    stages = {k: v * 1e3 for k, v in light.timings.items()}
    del light
    return {"wall_ms": wall, "stages_ms": stages, "calls": rec.rows, "spans": sorted(spans.rows, key=lambda r: r[1])}


def summary(run: dict) -> dict:
    """Time per call kind (and kernel), sorted, and the time between calls (the library's own
    host work, and in the run as issued, the host waiting inside no call)."""
    per = defaultdict(lambda: [0, 0.0])
    inside = 0.0
    last = 0.0
    for name, detail, a, b in run["calls"]:
        key = f"{name} {detail}".strip() if name.startswith("launch") else name
        per[key][0] += 1
        per[key][1] += b - a
        inside += b - max(a, last)
        last = max(last, b)
    return {"in_calls_ms": inside, "between_calls_ms": run["wall_ms"] - inside,
            "by_call": sorted(((k, n, t) for k, (n, t) in per.items()), key=lambda r: -r[2])}


def add_headline_arguments(ap) -> None:
    """The backend and the scene of a headline benchmark (the thesis scene at 128^3 with 2.1M
    packets per band unless told otherwise)."""
    ap.add_argument("--backend", default="cuda")
    ap.add_argument("--device", default="")
    ap.add_argument("--scene", default=str(ROOT / "examples/scenes/thesis-default.toml"))
    ap.add_argument("--grid", type=int, default=128)
    ap.add_argument("--photons", type=float, default=2.1e6)


def headline_setup(args):
    """(backend, scene) of :func:`add_headline_arguments`' options, the kernels compiled and
    the memory pools warmed by a run with 1000 packets per band."""
    from nebula_rt.backends import get_backend
    from nebula_rt.pipeline import Pipeline
    from nebula_rt.scene import Scene

    backend = get_backend(args.backend, args.device)
    scene = Scene.load(args.scene).with_overrides(
        [f"grid.shape=[{args.grid},{args.grid},{args.grid}]", f"transport.photons={int(args.photons)}",
         f'transport.backend="{args.backend}"', f'transport.device="{args.device}"'])
    Pipeline(backend).run(scene.with_overrides(["transport.photons=1000"]))  # compile, warm the pools
    return backend, scene


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_headline_arguments(ap)
    ap.add_argument("--list", type=int, default=60, help="calls of the run as issued to print in order")
    ap.add_argument("--out", default="")
    args = ap.parse_args(argv)
    from nebula_rt.pipeline import Pipeline

    backend, scene = headline_setup(args)
    Pipeline(backend).run(scene)
    out = {"benchmark": "profile_timeline", "date": time.strftime("%Y-%m-%d %H:%M:%S"), **provenance(),
           "device": backend.device_name, "command": " ".join(sys.argv), "grid": args.grid,
           "photons": int(args.photons)}
    for mode, serial in (("as_issued", False), ("serialised", True)):
        run = run_once(scene, backend, serial)
        s = summary(run)
        out[mode] = {**run, **s}
        print(f"== {mode}: {run['wall_ms']:.2f} ms end to end ("
              + ", ".join(f"{k} {v:.2f}" for k, v in run["stages_ms"].items())
              + f"); in backend calls {s['in_calls_ms']:.2f} ms, between them {s['between_calls_ms']:.2f} ms")
        for key, n, t in s["by_call"][:16]:
            print(f"   {key:58s} x{n:<4d} {t:8.3f} ms")
        if not serial:
            print(f"-- the first {args.list} calls in order (ms from the start: entry, time in the call)")
            for name, detail, a, b in run["calls"][:args.list]:
                print(f"   {a:8.3f} {b - a:8.3f}  {name} {detail}")
            print("-- the library's steps (ms from the start: entry, time in the step, nested ones included)")
            for name, a, b in run["spans"]:
                print(f"   {a:8.3f} {b - a:8.3f}  [{name}]")
    save(out, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
