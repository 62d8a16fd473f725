"""The NebulaRT proxies as ParaView built them from the schema, and one run.

    pvpython schema_layers.py DENSITY.vti DENSITY.npy PHOTONS

RESULT: ``properties``: per property in the panel's order (ParaView's ordered iterator) its
class, label, default elements, panel visibility and domain (range bounds, enumeration
texts, string list); ``groups``: the property groups with their properties; ``hashes``:
SHA-256 of each J_<band> array's bytes of a light field with every property at its default
except Photons and Device, three ways in this process (so on this ParaView's OpenCL device):
``proxy`` (the proxy on ParaView's reader of DENSITY.vti), ``vtk`` (the plain VTK filter on
VTK's reader of the same file), ``scene`` (a scene file's dict with dust.file = DENSITY.npy
through the Pipeline), and ``scene_vti`` (the same with dust.file = DENSITY.vti: read by VTK's
own reader in this Python, which has no pyvista: ``pyvista_importable``);
``int_photons_from_float``: the photons a ``Photons=1e4`` assignment stores. The same
descriptions for the density source, the colour and the sky image (``*_properties``).
"""

import hashlib
import sys

import _common
import numpy as np
from paraview import servermanager, simple
from nebula_rt_paraview.view import load_plugin
from vtkmodules.util.numpy_support import vtk_to_numpy

load_plugin()
path, npy, photons = sys.argv[1], sys.argv[2], int(sys.argv[3])

spm = servermanager.vtkSMProxyManager.GetProxyManager().GetActiveSessionProxyManager()


def describe(group, name):
    """(properties in the panel's order, property groups) of a proxy's prototype."""
    proto = spm.GetPrototypeProxy(group, name)
    props = []
    it = servermanager.vtkSMOrderedPropertyIterator()
    it.SetProxy(proto)
    it.Begin()
    while not it.IsAtEnd():
        pname, prop = it.GetKey(), it.GetProperty()
        entry = {"name": pname, "class": prop.GetClassName(), "label": prop.GetXMLLabel(),
                 "panel_visibility": prop.GetPanelVisibility()}
        if hasattr(prop, "GetElement") and hasattr(prop, "GetNumberOfElements") and pname != "Input":
            # a prototype's elements are the defaults
            entry["default"] = [prop.GetElement(i) for i in range(prop.GetNumberOfElements())]
        dit = prop.NewDomainIterator()
        dit.Begin()
        while not dit.IsAtEnd():
            dom = dit.GetDomain()
            cls = dom.GetClassName()
            if cls in ("vtkSMDoubleRangeDomain", "vtkSMIntRangeDomain"):
                lo = dom.GetMinimum(0) if dom.GetMinimumExists(0) else None
                hi = dom.GetMaximum(0) if dom.GetMaximumExists(0) else None
                entry["range"] = [lo, hi]
            elif cls == "vtkSMEnumerationDomain":
                entry["enum"] = [dom.GetEntryText(i) for i in range(dom.GetNumberOfEntries())]
            elif cls == "vtkSMStringListDomain":
                entry["strings"] = [dom.GetString(i) for i in range(dom.GetNumberOfStrings())]
            elif cls == "vtkSMBooleanDomain":
                entry["bool"] = True
            dit.Next()
        props.append(entry)
        it.Next()
    groups = {}
    for i in range(proto.GetNumberOfPropertyGroups()):
        g = proto.GetPropertyGroup(i)
        groups[g.GetXMLLabel()] = [g.GetPropertyName(j) for j in range(g.GetNumberOfProperties())]
    return props, groups


props, groups = describe("filters", "NebulaLightField")
density_props, density_groups = describe("sources", "NebulaDustDensity")
colour_props, _ = describe("filters", "NebulaColour")
sky_props, sky_groups = describe("filters", "NebulaSkyImage")

reader = simple.XMLImageDataReader(FileName=[path])
light = simple.NebulaLightField(reader, Photons=photons, Device=_common.TEST_DEVICE)
light.UpdatePipeline()
out = servermanager.Fetch(light)


def j_hashes(dataset):
    pd = dataset.GetPointData()
    return {pd.GetArrayName(i): hashlib.sha256(np.ascontiguousarray(vtk_to_numpy(pd.GetArray(i))).tobytes()).hexdigest()
            for i in range(pd.GetNumberOfArrays()) if pd.GetArrayName(i).startswith("J_")}


hashes = {"proxy": j_hashes(out)}
# the plain VTK filter on VTK's own reader
from nebula_rt.filters.light_field import NebulaLightField  # noqa: E402
from vtkmodules.vtkIOXML import vtkXMLImageDataReader  # noqa: E402

r = vtkXMLImageDataReader()
r.SetFileName(path)
lf = NebulaLightField()
lf.SetInputConnection(r.GetOutputPort())
lf.SetPhotons(photons)
lf.SetDevice(_common.TEST_DEVICE)
lf.Update()
hashes["vtk"] = j_hashes(lf.GetOutputDataObject(0))
# a scene file's values through the pipeline
from nebula_rt.backends import get_backend  # noqa: E402
from nebula_rt.pipeline.stages import Pipeline  # noqa: E402
from nebula_rt.scene.model import Scene  # noqa: E402

rho = np.load(npy)
scene = Scene.from_dict({"grid": {"shape": list(rho.shape)}, "dust": {"model": "file", "file": npy},
                         "transport": {"photons": photons, "device": _common.TEST_DEVICE}})
res = Pipeline(get_backend("auto", _common.TEST_DEVICE)).run(scene, colour=False)
# J is indexed [x, y, z]; VTK's arrays run x fastest
hashes["scene"] = {f"J_{b.name}": hashlib.sha256(np.ascontiguousarray(res.J[i].ravel(order="F"), np.float32).tobytes()).hexdigest()
                   for i, b in enumerate(res.bands)}
# the same density from the .vti, as a scene file names it (dust.model = "file"): VTK's reader
scene_vti = Scene.from_dict({"grid": {"shape": list(rho.shape)}, "dust": {"model": "file", "file": path},
                             "transport": {"photons": photons, "device": _common.TEST_DEVICE}})
res = Pipeline(get_backend("auto", _common.TEST_DEVICE)).run(scene_vti, colour=False)
hashes["scene_vti"] = {f"J_{b.name}": hashlib.sha256(np.ascontiguousarray(res.J[i].ravel(order="F"), np.float32).tobytes()).hexdigest()
                       for i, b in enumerate(res.bands)}
try:
    import pyvista  # noqa: F401
    pyvista_importable = True
except ImportError:
    pyvista_importable = False
light.Photons = 1e4  # a float where an integer is meant
stored = light.GetProperty("Photons").GetData()
_common.result(properties=props, groups=groups, density_properties=density_props,
               density_groups=density_groups, colour_properties=colour_props, sky_properties=sky_props,
               sky_groups=sky_groups, hashes=hashes, int_photons_from_float=stored, pyvista_importable=pyvista_importable,
               last_error=light.GetClientSideObject().last_error)
