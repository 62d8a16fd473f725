"""What the ParaView GUI shows, recorded from inside it (tests/paraview/test_paraview_gui.py).

The GUI test plays recorded events (menus, Apply) and, between them, runs this file in the
GUI's own Python shell with ``STEP = "<name>"; exec(open(<this file>).read())`` (the shell
is only the test's observer: nothing here changes what is shown). It writes, under
$NEBULA_GUI_OUT:

- ``<step>-<view>.png``: a screenshot of every view at its size;
- ``<step>.json``: the layouts (tabs) and their views, each view's type, size, camera,
  background and representations (producer, port, representation type, colouring, Map
  Scalars, visibility, colour bar), the stars' display positions, and data facts (the sky
  image's mean rgb); the NebulaRT proxies' Stars values, last errors, exposure and opacity
  factor; ParaView's Abort button (its place on the screen, enabled or not, and when the
  plugin last heard it pressed);
- with ``GRAB = True``: ``<step>-window.png``, the whole screen (the docs' picture).
"""

import json
import os
import traceback

from paraview import servermanager, simple
from paraview.modules import vtkRemotingViews  # noqa: F401 - view proxies wrapped as their own classes

OUT = os.environ["NEBULA_GUI_OUT"]
step = globals().get("STEP", "probe")
record = {"step": step}
try:
    import numpy as np
    from vtkmodules.util.numpy_support import vtk_to_numpy

    layouts = []
    for (name, _id), layout in simple.GetLayouts().items():
        views = [v for v in simple.GetViews() if simple.GetLayout(v) is layout]
        layouts.append({"name": name, "views": [v.GetGlobalIDAsString() for v in views]})
    record["layouts"] = layouts
    record["views"] = []
    for i, view in enumerate(simple.GetViews()):
        v = {"id": view.GetGlobalIDAsString(), "type": view.GetXMLName(), "size": [int(x) for x in view.ViewSize]}
        for prop in ("CameraPosition", "CameraFocalPoint", "CameraViewUp", "CameraViewAngle",
                     "CameraParallelProjection", "CameraParallelScale", "Background"):
            v[prop] = [float(x) for x in view.GetPropertyValue(prop)] if hasattr(
                view.GetPropertyValue(prop), "__len__") else float(view.GetPropertyValue(prop))
        v["UseColorPaletteForBackground"] = int(view.UseColorPaletteForBackground)
        v["InteractionMode"] = int(view.SMProxy.GetProperty("InteractionMode").GetElement(0))  # 0 3D, 1 2D
        layout = simple.GetLayout(view)
        v["preview"] = [int(x) for x in layout.PreviewMode] if layout is not None else None
        reps = []
        for rep in view.Representations:
            inp = rep.SMProxy.GetProperty("Input")
            if inp is None or inp.GetNumberOfProxies() == 0:
                continue
            src, port = inp.GetProxy(0), inp.GetOutputPortForConnection(0)
            rtype = rep.SMProxy.GetProperty("Representation")  # (text representations have none)
            r = {"producer": src.GetXMLName(), "port": int(port), "visible": int(rep.Visibility),
                 "representation": rtype.GetElement(0) if rtype is not None else None}
            if "ColorArrayName" in rep.ListProperties():
                r["color"] = [str(c) for c in rep.ColorArrayName]
                r["map_scalars"] = int(rep.MapScalars)
                lut = rep.LookupTable
                bar = None if lut is None else servermanager.vtkSMTransferFunctionProxy.FindScalarBarRepresentation(
                    lut.SMProxy, view.SMProxy)  # (GetScalarBar would make one)
                r["scalar_bar"] = 0 if bar is None else int(bar.GetProperty("Visibility").GetElement(0))
            if "ScalarOpacityFunction" in rep.ListProperties() and rep.ScalarOpacityFunction is not None:
                r["opacity_points"] = len(rep.ScalarOpacityFunction.Points) // 4
            if src.GetXMLName() == "NebulaLightField" and port == 1 and r["visible"]:
                stars = servermanager.Fetch(servermanager._getPyProxy(src), idx=1)
                # (a failed or cancelled light field: no points, or, fetched from a pvserver's
                # pieces, points without arrays)
                empty = stars.GetPoints() is None or stars.GetPointData().GetArray("star_rgb") is None
                xyz = np.zeros((0, 3)) if empty else vtk_to_numpy(stars.GetPoints().GetData())
                rgb = np.zeros((0, 3)) if empty else vtk_to_numpy(stars.GetPointData().GetArray("star_rgb"))
                ren = view.GetRenderer()
                pos = []
                for p in xyz:
                    ren.SetWorldPoint(float(p[0]), float(p[1]), float(p[2]), 1.0)
                    ren.WorldToDisplay()
                    pos.append([float(c) for c in ren.GetDisplayPoint()[:2]])
                r["stars"] = {"display": pos, "rgb": rgb.astype(int).tolist()}
            if src.GetXMLName() == "NebulaColour" and r["visible"]:
                # the display box of the volume (its bounds moved by the representation's Position)
                b = src.GetDataInformation(0).GetBounds()
                off = [float(c) for c in rep.Position]
                ren = view.GetRenderer()
                xs, ys = [], []
                for i in (0, 1):
                    for j in (2, 3):
                        for k in (4, 5):
                            ren.SetWorldPoint(b[i] + off[0], b[j] + off[1], b[k] + off[2], 1.0)
                            ren.WorldToDisplay()
                            x, y, _z = ren.GetDisplayPoint()
                            xs.append(float(x))
                            ys.append(float(y))
                r["box"] = [min(xs), max(xs), min(ys), max(ys)]
                light = src.GetProperty("Input").GetProxy(0)
                r["albedo"] = float(light.GetProperty("Albedo").GetElement(0))
            if src.GetXMLName() == "PythonAnnotation":
                r["text"] = servermanager.Fetch(servermanager._getPyProxy(src)).GetColumn(0).GetValue(0)
            if src.GetXMLName() == "NebulaSkyImage":
                img = servermanager.Fetch(servermanager._getPyProxy(src))
                rgb = vtk_to_numpy(img.GetPointData().GetArray("rgb")).astype(np.float64)
                r["rgb_mean"] = rgb.mean(axis=0).tolist()
                r["dimensions"] = list(img.GetDimensions())
                ren = view.GetRenderer()
                b = img.GetBounds()
                corners = []
                for x, y in ((b[0], b[2]), (b[1], b[3])):
                    ren.SetWorldPoint(x, y, 0.0, 1.0)
                    ren.WorldToDisplay()
                    corners.append([float(c) for c in ren.GetDisplayPoint()[:2]])
                r["display_corners"] = corners  # the first and last pixel centres
            reps.append(r)
        v["representations"] = reps
        png = os.path.join(OUT, f"{step}-{i}.png")
        simple.SaveScreenshot(png, view, ImageResolution=v["size"])
        v["png"] = png
        record["views"].append(v)
    record["sources"] = sorted(k[0] for k in simple.GetSources())
    # the NebulaRT proxies: their Stars table's values, the last error, the light field's
    # exposure and opacity factor (field data)
    record["proxies"] = {}
    for (name, _id), px in simple.GetSources().items():
        if not px.GetXMLName().startswith("Nebula"):
            continue
        # (in a client/server session the algorithm is the server's: no client-side object)
        algorithm = px.GetClientSideObject()
        entry = {"xml": px.GetXMLName(), "last_error": getattr(algorithm, "last_error", None),
                 "last_warnings": list(getattr(algorithm, "last_warnings", [])),
                 "points": int(px.GetDataInformation(0).GetNumberOfPoints()), "remote": algorithm is None}
        if "Stars" in px.ListProperties():
            entry["Stars"] = [float(x) for x in px.Stars]
        if px.GetXMLName() in ("NebulaLightField", "NebulaColour") and algorithm is not None and entry["last_error"] is None:
            fd = servermanager.Fetch(px).GetFieldData()
            for key in ("exposure", "opacity_scale"):
                arr = fd.GetArray(key)
                entry[key] = float(arr.GetValue(0)) if arr is not None else None
        if px.GetXMLName() == "NebulaLightField" and algorithm is not None:
            tree = algorithm.GetOutputDataObject(2)  # the light per leaf
            cd = tree.GetCellData()
            entry["port2"] = {"class": tree.GetClassName(), "leaves": int(tree.GetNumberOfLeaves()),
                              "arrays": [cd.GetArrayName(i) for i in range(cd.GetNumberOfArrays())]}
        record["proxies"][name] = entry
    # ParaView's Abort button: where it is on the screen (for the test's real mouse click) and,
    # as the plugin heard it, when the last execution saw it pressed and when it ended
    # (time.monotonic: the system-wide CLOCK_MONOTONIC, which the test process reads too)
    from PyQt5 import QtWidgets

    from nebula_rt.filters.base import ABORT_SOURCES

    button = [w for w in QtWidgets.QApplication.instance().allWidgets() if w.objectName() == "AbortButton"]
    centre = button[0].mapToGlobal(button[0].rect().center()) if button else None
    record["abort_button"] = {"screen": [centre.x(), centre.y()] if centre is not None else None,
                              "enabled": bool(button and button[0].isEnabled()),
                              "sources": [{"pressed_at": a.pressed_at, "stopped_at": a.stopped_at}
                                          for a in ABORT_SOURCES]}
    from nebula_rt_paraview import remote_abort

    relay = remote_abort.RELAY
    record["abort_button"]["relay"] = (None if relay is None else
                                       {"pressed_at": relay.pressed_at, "sent_at": relay.sent_at, "ended_at": relay.ended_at})
    # the properties panel: the kinds of widget (Qt class names) that show the counts
    panel = [w for w in QtWidgets.QApplication.instance().allWidgets() if w.objectName() == "ProxyPanel"]
    record["panel_widgets"] = {}
    for name in ("Photons", "Seed", "MaxScatterings", "BatchSize", "Tau"):
        for root in panel:
            found = root.findChild(QtWidgets.QWidget, name)
            if found is not None:
                record["panel_widgets"][name] = sorted({c.metaObject().className()
                                                        for c in found.findChildren(QtWidgets.QWidget)})
    # what the panel's Density Array box shows (its combo box's text)
    record["panel_texts"] = {}
    for root in panel:
        found = root.findChild(QtWidgets.QWidget, "DensityArray")
        box = found.findChild(QtWidgets.QComboBox) if found is not None else None
        if box is not None:
            record["panel_texts"]["DensityArray"] = box.currentText()

    if globals().get("GRAB"):
        from PIL import ImageGrab

        png = os.path.join(OUT, f"{step}-window.png")
        ImageGrab.grab(xdisplay=os.environ["DISPLAY"]).save(png)
        record["window_png"] = png
except Exception:  # noqa: BLE001 - the test reads the traceback
    record["error"] = traceback.format_exc()
with open(os.path.join(OUT, f"{step}.json"), "w") as f:
    json.dump(record, f, indent=1)
