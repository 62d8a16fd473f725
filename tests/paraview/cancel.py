"""Cancelling a long trace from a progress observer stops it between batches.

    pvpython cancel.py

A 24^3 nebula with 10 million packets per band in batches of 20 000 (500 batches; the
bands are traced together, and the library launches groups of consecutive batches, checking
for cancellation between groups). An observer on the VTK object's ProgressEvent sets
AbortExecute at the first progress report (after the first group of batches). RESULT: the
progress seen, the batches that ran, the output's points, last_error, the time taken, and a
following small run (which must work once the abort flag is cleared).
"""

import time

import _common
from paraview import simple
from nebula_rt_paraview.view import load_plugin

PHOTONS, BATCH = 10_000_000, 20_000
load_plugin()
dust = simple.NebulaDustDensity(GridShape=[24, 24, 24], Device=_common.TEST_DEVICE)
dust.UpdatePipeline()
light = simple.NebulaLightField(dust, Photons=PHOTONS, BatchSize=BATCH, Device=_common.TEST_DEVICE)
light.DensityArray = ["POINTS", "density"]
alg = light.GetClientSideObject()

events = []


def on_progress(obj, _event):
    p = obj.GetProgress()
    events.append(p)
    if 0.0 < p < 1.0 and not obj.GetAbortExecute():
        obj.SetAbortExecute(1)  # the user pressed the abort button


tag = alg.AddObserver("ProgressEvent", on_progress)
t0 = time.time()
light.UpdatePipeline()
cancelled_seconds = time.time() - t0
alg.RemoveObserver(tag)
done = max([p for p in events if p < 1.0], default=0.0)
cancelled = {"points": int(light.GetDataInformation().GetNumberOfPoints()), "last_error": alg.last_error,
             "progress_events": len(events), "max_progress": done,
             "batches_run": int(round(done * PHOTONS / BATCH)), "seconds": cancelled_seconds,
             "abort_flag_after": int(alg.GetAbortExecute())}

# The filter is usable afterwards: NebulaRT clears AbortExecute after a cancellation (ParaView
# 5.11's VTK would otherwise cancel every later execution at once).
light.Photons = 20000
light.BatchSize = 0
t0 = time.time()
light.UpdatePipeline()
after = {"points": int(light.GetDataInformation().GetNumberOfPoints()), "last_error": alg.last_error,
         "seconds": time.time() - t0, "batches": alg.last_light.transport.batches if alg.last_light else None}
_common.result(cancelled=cancelled, after=after, total_batches=PHOTONS // BATCH)
