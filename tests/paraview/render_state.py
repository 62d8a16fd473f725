"""Load a state file, pin the test device, render, save a screenshot.

    pvpython|pvbatch render_state.py STATE.pvsm OUT.png [--plain]

With --plain: ``LoadState(STATE); Render()`` as a user would type it (the plugin loaded at
start-up from PV_PLUGIN_PATH), else load_state_safely. RESULT: proxies found, last errors,
the display-space box of each Nebula Colour volume (for the test to crop the cubes), the view
size and camera, the layouts (tabs) and their views, the labels' texts, and the albedo label
after an edit of the first light field's Albedo to 0.3.
"""

import sys
import time

import _common
from paraview import servermanager, simple
from nebula_rt_paraview.view import nebula_proxies, load_state_safely, set_compute_device

state, png = sys.argv[1], sys.argv[2]
plain = "--plain" in sys.argv[3:]
t0 = time.time()
if plain:
    simple.LoadState(state)
    found = nebula_proxies()
else:
    found = load_state_safely(state, {"NebulaDustDensity": 1, "NebulaLightField": 4, "NebulaColour": 4})
n_dev = set_compute_device(_common.TEST_DEVICE)
view = simple.GetActiveView() or simple.GetRenderViews()[0]
size = [int(v) for v in view.ViewSize]
simple.Render(view)
simple.SaveScreenshot(png, view, ImageResolution=size)
elapsed = time.time() - t0
camera = {p: [float(x) for x in view.GetPropertyValue(p)] for p in ("CameraPosition", "CameraFocalPoint", "CameraViewUp")}
camera["CameraParallelScale"] = float(view.CameraParallelScale)
layouts = {name: int(len([v for v in simple.GetViews() if simple.GetLayout(v) is lay]))
           for (name, _id), lay in simple.GetLayouts().items()}
preview = {name: [int(x) for x in lay.PreviewMode] for (name, _id), lay in simple.GetLayouts().items()}


def labels():
    """{registration name: text} of the Python Annotation and Text sources."""
    out = {}
    for (name, _id), px in simple.GetSources().items():
        if px.GetXMLName() == "PythonAnnotation":
            px.UpdatePipeline()
            out[name] = servermanager.Fetch(px).GetColumn(0).GetValue(0)
        elif px.GetXMLName() == "TextSource":
            out[name] = px.Text
    return out



# display-space boxes of the colour volumes: project the 8 corners of each (moved) bounds
ren = view.GetRenderer()
boxes = []
for px in found["NebulaColour"]:
    rep = simple.GetDisplayProperties(px, view)
    b = px.GetDataInformation().GetBounds()
    off = list(rep.Position)
    xs, ys = [], []
    for i in (0, 1):
        for j in (2, 3):
            for k in (4, 5):
                ren.SetWorldPoint(b[i] + off[0], b[j] + off[1], b[k] + off[2], 1.0)
                ren.WorldToDisplay()
                x, y, _z = ren.GetDisplayPoint()
                xs.append(x)
                ys.append(y)
    light = px.Input
    boxes.append({"name": [k[0] for k, v in simple.GetSources().items() if v == px][0],
                  "albedo": float(light.SMProxy.GetProperty("Albedo").GetElement(0)),
                  "band_preset": light.SMProxy.GetProperty("BandPreset").GetElement(0),
                  "x0": min(xs), "x1": max(xs), "y0": min(ys), "y1": max(ys),
                  "visible": bool(rep.Visibility), "representation": rep.SMProxy.GetProperty("Representation").GetElement(0)})

errors = {}
for name, proxies in found.items():
    for p in proxies:
        errors.setdefault(name, []).append(p.GetClientSideObject().last_error)
devices = [getattr(getattr(p.GetClientSideObject().last_light, "transport", None), "device", None)
           for p in found["NebulaLightField"]]
texts = labels()
first = next((px for (name, _id), px in simple.GetSources().items() if name == "Light field, albedo 0.2"), None)
edited = None
if first is not None and plain:  # (after everything above: the edit re-traces that branch)
    first.Albedo = 0.3
    edited = labels().get("Label, albedo 0.2")

_common.result(devices=devices, proxies={k: len(v) for k, v in found.items()}, devices_pinned=n_dev, errors=errors,
               boxes=boxes, size=size, seconds=elapsed, camera=camera, layouts=layouts, preview=preview,
               labels=texts, edited_label=edited,
               points=[int(p.GetDataInformation().GetNumberOfPoints()) for p in found["NebulaColour"]])
