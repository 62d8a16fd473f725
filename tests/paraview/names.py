"""One name per property and proxy in pvpython, the former ones working with a FutureWarning.

    pvpython names.py

RESULT: for every NebulaRT proxy, the properties whose paraview.simple name (from the label)
differs from the XML name (what VTK and state files use); Method set by its name; the former
names (``TransportMethod``, ``NebulaRTfitresult``) read, set and called, with their warnings.
"""

import warnings

import _common
from paraview import servermanager, simple
from nebula_rt_paraview.view import load_plugin

load_plugin()
dust = simple.NebulaDustDensity(GridShape=[8, 8, 8], Device=_common.TEST_DEVICE)
light = simple.NebulaLightField(dust, Method="analog", Device=_common.TEST_DEVICE)
proxies = {"NebulaDustDensity": dust, "NebulaLightField": light, "NebulaColour": simple.NebulaColour(light),
           "NebulaSkyImage": simple.NebulaSkyImage(light)}


def mismatches(proxy):
    """(python name, XML name) of every property whose two names differ."""
    out = []
    it = servermanager.PropertyIterator(proxy)
    for prop in it:
        xml = it.GetKey()
        python = servermanager._make_name_valid(proxy.SMProxy.GetPropertyName(prop.SMProperty) and
                                                prop.SMProperty.GetXMLLabel() or xml)
        if python != xml:
            out.append([python, xml])
    return out


def value(v):
    """A property's value (an enumeration's is a property object)."""
    return v.GetData() if hasattr(v, "GetData") else v


with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    method_set = value(light.Method)
    light.TransportMethod = "biased"
    method_after_former_set = value(light.Method)
    former_get = value(light.TransportMethod)
    former_reader = simple.NebulaRTfitresult
    reader_names = [n for n in dir(simple) if n in ("NebulaFitResultReader", "NebulaRTfitresult")]

_common.result(
    mismatches={name: mismatches(p) for name, p in proxies.items()},
    method_set=method_set, method_after_former_set=method_after_former_set, former_get=former_get,
    reader_names=reader_names, former_reader_name=former_reader.__name__,
    warnings=[f"{w.category.__name__}: {w.message}" for w in caught],
)
