"""Run ``nebula-rt`` with a fault injected at a named point (the fault-injection tests).

    python cli_with_fault.py POINT SIGNAL -- nebula-rt arguments...

POINT is where the process sends itself a real SIGNAL (SIGINT or SIGTERM; "SIGINTx2" sends
two), or where a failure is made real:

startup            while the scene file is read
mid-launch         during the transport's second launch
after-last-batch   when the trace has returned (the progress bar at 100 %)
during-write       inside the .vti writer, before VTK writes
during-png         inside the PNG rendering
during-build       as the first kernel build starts (cold caches make it seconds inside PoCL)
stalled            before the PNG rendering, which then waits 120 s without polling: only the
                   signal watchdog can end the run in time
fill-disk          the output's file system is filled just before the .vti is written
png-fails          the PNG rendering raises after the .vti was staged
rank1-fails        (under mpiexec) rank 1 alone raises a device error in its second launch
cache-vanishes     PoCL's kernel cache folder (POCL_CACHE_DIR, which the caller sets) is removed
                   just before the first kernel build: that build fails in PoCL for real

The functions are wrapped, not replaced: the real pipeline, kernels and writers run.
"""

from __future__ import annotations

import os
import signal
import sys


def main() -> int:
    point, signame = sys.argv[1], sys.argv[2]
    argv = sys.argv[sys.argv.index("--") + 1:]
    repeat = 2 if signame.endswith("x2") else 1
    sig = getattr(signal, signame.replace("x2", ""), None)

    def fire():
        for _ in range(repeat):
            os.kill(os.getpid(), sig)

    from nebula_rt.cli import commands as cli
    from nebula_rt import pipeline, scene
    from nebula_rt.filters import render, vti
    from nebula_rt.backends import session

    if point == "cache-vanishes":
        import shutil

        import pyopencl as cl

        build = cl.Program.build
        calls = {"n": 0}

        def vanishing(self, *a, **kw):
            calls["n"] += 1
            if calls["n"] == 1:
                shutil.rmtree(os.environ["POCL_CACHE_DIR"])
                print("fault: PoCL's kernel cache folder removed", file=sys.stderr, flush=True)
            return build(self, *a, **kw)
        cl.Program.build = vanishing
    elif point == "rank1-fails":
        from nebula_rt.errors import NebulaError
        from nebula_rt.backends.parallel import world

        run_group = session.DeviceTransport.run_group
        calls = {"n": 0}

        def failing(self, *a, **kw):
            calls["n"] += 1
            if world().rank == 1 and calls["n"] == 2:
                raise NebulaError("the device lost its context (injected on rank 1)")
            return run_group(self, *a, **kw)
        session.DeviceTransport.run_group = failing
    elif point == "startup":
        load = scene.Scene.load.__func__

        def loading(cls, path):
            fire()
            return load(cls, path)
        scene.Scene.load = classmethod(loading)
    elif point == "mid-launch":
        run_group = session.DeviceTransport.run_group
        calls = {"n": 0}

        def launching(self, *a, **kw):
            calls["n"] += 1
            if calls["n"] == 2:
                fire()
            return run_group(self, *a, **kw)
        session.DeviceTransport.run_group = launching
    elif point == "after-last-batch":
        run = pipeline.Pipeline.run

        def running(self, *a, **kw):
            out = run(self, *a, **kw)
            fire()
            return out
        pipeline.Pipeline.run = running
    elif point == "during-write":
        enter = vti.VtkMessages.__enter__

        def entering(self):
            fire()
            return enter(self)
        vti.VtkMessages.__enter__ = entering
    elif point == "during-png":
        png = render.render_rgba_png

        def rendering(*a, **kw):
            fire()
            return png(*a, **kw)
        render.render_rgba_png = rendering
    elif point == "during-build":
        import threading

        import pyopencl as cl

        build = cl.Program.build
        calls = {"n": 0}

        def building(self, *a, **kw):
            calls["n"] += 1
            if calls["n"] == 1:  # from another thread, 0.1 s in: the main thread is inside PoCL
                threading.Timer(0.1, fire).start()
            return build(self, *a, **kw)
        cl.Program.build = building
    elif point == "stalled":
        import time

        png = render.render_rgba_png

        def stalling(*a, **kw):
            fire()
            time.sleep(120)
            return png(*a, **kw)
        render.render_rgba_png = stalling
    elif point == "fill-disk":
        write = vti.write_vti

        def filling(path, *a, **kw):
            with open(os.path.join(os.path.dirname(path), "filler"), "wb") as fh:
                try:
                    while True:
                        fh.write(b"\0" * 4096)
                        fh.flush()
                except OSError:
                    pass
            return write(path, *a, **kw)
        vti.write_vti = filling
    elif point == "png-fails":
        def failing(*a, **kw):
            raise RuntimeError("the PNG renderer failed")
        render.render_rgba_png = failing
    else:
        raise SystemExit(f"unknown fault point {point!r}")
    return cli.main(argv)


if __name__ == "__main__":
    sys.exit(main())
