"""The plugin loads, its proxies have the expected names, and each executes on a small grid.

    pvpython|pvbatch check_plugin.py

RESULT: per proxy its group/label/menu/representation hints, help text and property facts; the outputs
(points, arrays with their stats, field data) of a 16^3 pipeline: density -> light field
(two stars) -> colour, light field -> sky image, and a light field on a cell-data density.
"""

import _common
from paraview import servermanager, simple
from nebula_rt_paraview import PROXY_NAMES
from nebula_rt_paraview.view import PROXY_GROUPS, load_plugin, plugin_loaded

loaded_at_start = plugin_loaded()  # PV_PLUGIN_PATH loads it at start-up
load_plugin()

spm = servermanager.vtkSMProxyManager.GetProxyManager().GetActiveSessionProxyManager()
definitions = {}
for name in PROXY_NAMES:
    group = PROXY_GROUPS[name]
    proto = spm.GetPrototypeProxy(group, name) if spm.HasDefinition(group, name) else None
    info = {"group": group, "defined": proto is not None}
    if proto is not None:
        info["label"] = proto.GetXMLLabel()
        d = proto.GetDocumentation()  # the proxy's help text
        info["help"] = {"short": d.GetShortHelp(), "long": d.GetLongHelp(), "description": d.GetDescription()}
        hints = proto.GetHints()
        menu = hints.FindNestedElementByName("ShowInMenu") if hints else None
        info["menu"] = menu.GetAttribute("category") if menu else None
        # the display hints, in order: RepresentationType per (view, port), View, PipelineIcon
        reps, views = [], []
        for i in range(hints.GetNumberOfNestedElements() if hints else 0):
            el = hints.GetNestedElement(i)
            if el.GetName() == "RepresentationType":
                reps.append({"view": el.GetAttribute("view"), "type": el.GetAttribute("type"),
                             "port": el.GetAttribute("port")})
            elif el.GetName() == "View":
                views.append(el.GetAttribute("type"))
        info["representation_hints"] = reps
        info["view_hints"] = views
        # what ParaView picks for port 0 of a render view: the first hint for that view and port
        first = next((h for h in reps if h["view"] in (None, "RenderView") and h["port"] in (None, "0")), None)
        info["representation"] = first["type"] if first else None
        props = {}
        it = proto.NewPropertyIterator()
        it.Begin()
        while not it.IsAtEnd():
            prop = it.GetProperty()
            doc = prop.GetDocumentation()
            entry = {"class": prop.GetClassName(), "doc": bool(doc and doc.GetDescription()),
                     "panel_visibility": prop.GetPanelVisibility()}
            if hasattr(prop, "GetRepeatCommand"):
                entry["repeat"] = int(prop.GetRepeatCommand())
                entry["per_command"] = int(prop.GetNumberOfElementsPerCommand())
            domains = []
            dit = prop.NewDomainIterator()
            dit.Begin()
            while not dit.IsAtEnd():
                domains.append(dit.GetDomain().GetClassName())
                dit.Next()
            entry["domains"] = domains
            props[it.GetKey()] = entry
            it.Next()
        info["properties"] = props
        groups = [proto.GetPropertyGroup(i).GetXMLLabel() for i in range(proto.GetNumberOfPropertyGroups())]
        info["property_groups"] = groups
    definitions[name] = info

# -- execute each proxy on a small grid -------------------------------------------------------
dev = _common.TEST_DEVICE
two_stars = [0.4, 0.5, 0.5, 1.0, 20000.0, 0.01, 0.7, 0.6, 0.5, 0.5, 6000.0, 0.02]
dust = simple.NebulaDustDensity(GridShape=[16, 16, 16], Model="turbulence", Stars=two_stars, Device=dev)
light = simple.NebulaLightField(dust, Photons=20000, Stars=two_stars, Device=dev)
light.DensityArray = ["POINTS", "density"]
colour = simple.NebulaColour(light, WhitePoint="star")
sky = simple.NebulaSkyImage(light, ImageSize=[40, 30], ViewDirection=[0.0, 0.0, -1.0])
# any vtkImageData, a cell array as the density: 15^3 cells
cells = simple.PointDatatoCellData(dust)
light_cells = simple.NebulaLightField(cells, Photons=20000, Device=dev)
light_cells.DensityArray = ["CELLS", "density"]

outputs = {}
for label, px in [("NebulaDustDensity", dust), ("NebulaLightField", light), ("NebulaColour", colour),
                  ("NebulaSkyImage", sky), ("NebulaLightField(cells)", light_cells)]:
    summary = _common.output_summary(px)
    summary["last_error"] = px.GetClientSideObject().last_error
    summary["execution_count"] = px.GetClientSideObject().execution_count
    outputs[label] = summary
outputs["NebulaLightField"]["stars_in_scene"] = len(light.GetClientSideObject().last_light.scene.stars)
outputs["NebulaLightField"]["device"] = light.GetClientSideObject().last_light.transport.device

# error-targeted: the Quality preset (10 % with a 10M budget) stops early
light_q = simple.NebulaLightField(dust, Quality="preview", Stars=two_stars, Device=dev)
light_q.DensityArray = ["POINTS", "density"]
light_q.UpdatePipeline()
fd = light_q.GetClientSideObject().GetOutputDataObject(0).GetFieldData()
outputs["NebulaLightField(preview)"] = {
    name: float(fd.GetArray(name).GetValue(0)) for name in ("photons", "photons_budget", "achieved_error")}

# a spectral band preset (Draine dust read through dust_extinction inside ParaView)
light_s = simple.NebulaLightField(dust, BandPreset="spectral-8", Photons=2000, Stars=two_stars, Device=dev)
light_s.DensityArray = ["POINTS", "density"]
light_s.UpdatePipeline()
pd = light_s.GetClientSideObject().GetOutputDataObject(0).GetPointData()
outputs["NebulaLightField(spectral-8)"] = {
    "J_arrays": sorted(pd.GetArrayName(i) for i in range(pd.GetNumberOfArrays()) if pd.GetArrayName(i).startswith("J_")),
    "last_error": light_s.GetClientSideObject().last_error}

# changing a colour property re-runs the colour only, not the trace
before = light.GetClientSideObject().execution_count
colour.Exposure = 2.0
colour.AutoExposure = 0
colour.UpdatePipeline()
rerun = {"light_executions_added": light.GetClientSideObject().execution_count - before,
         "colour_executions": colour.GetClientSideObject().execution_count}

# ParaView's numpy_interface (Python Calculator, Python Annotation) imports with the venv's numpy
try:
    import vtkmodules.numpy_interface.algorithms  # noqa: F401

    numpy_interface = None
except Exception as exc:  # noqa: BLE001 - reported
    numpy_interface = f"{type(exc).__name__}: {exc}"

# the plugin's view: a render view whose defaults (settings the plugin adds) suit a picture
sky_view = simple.CreateView("NebulaSkyView")
sky_view_facts = {"class": sky_view.SMProxy.GetClassName(),
                  "InteractionMode": int(sky_view.SMProxy.GetProperty("InteractionMode").GetElement(0)),
                  "CameraParallelProjection": int(sky_view.CameraParallelProjection),
                  "Background": [float(c) for c in sky_view.Background]}
simple.Delete(sky_view)

_common.result(loaded_at_start=loaded_at_start, definitions=definitions, outputs=outputs, rerun=rerun,
               sky_view=sky_view_facts, numpy_interface_error=numpy_interface,
               functions=[n for n in ("NebulaDustDensity", "NebulaLightField", "NebulaColour", "NebulaSkyImage")
                          if hasattr(simple, n)])
