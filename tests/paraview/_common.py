"""Shared bits of the pvpython/pvbatch scripts of tests/paraview/test_paraview.py.

The scripts run in ParaView's Python with the environment of scripts/pv-env.sh; each prints
one line ``RESULT <json>`` that the test parses (exceptions inside a VTK algorithm's
RequestData do not reach pvpython, so the scripts report what they find and the tests judge).
"""

import json
import os
import sys

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(REPO, "plugin"))

#: every test pins the CPU OpenCL device by name (as tests/conftest.py does)
TEST_DEVICE = os.environ.get("NEBULA_RT_TEST_DEVICE", "Portable Computing Language")


def result(**kw):
    sys.stdout.flush()
    print("RESULT " + json.dumps(kw, default=float), flush=True)


def array_stats(dataset, name):
    """(number of tuples, components, all finite, min, max) of a point array, via numpy."""
    import numpy as np
    from vtkmodules.util.numpy_support import vtk_to_numpy

    arr = dataset.GetPointData().GetArray(name)
    if arr is None:
        return None
    a = vtk_to_numpy(arr).astype(np.float64)
    return {"tuples": int(arr.GetNumberOfTuples()), "components": int(arr.GetNumberOfComponents()),
            "finite": bool(np.all(np.isfinite(a))), "min": float(a.min()) if a.size else None,
            "max": float(a.max()) if a.size else None}


def output_summary(proxy):
    """Points and point arrays (with stats) of a proxy's output, fetched to the client."""
    from paraview import servermanager

    proxy.UpdatePipeline()
    data = servermanager.Fetch(proxy)
    pd = data.GetPointData()
    names = [pd.GetArrayName(i) for i in range(pd.GetNumberOfArrays())]
    return {"points": int(data.GetNumberOfPoints()), "dimensions": list(data.GetDimensions()),
            "arrays": {n: array_stats(data, n) for n in names},
            "field": [data.GetFieldData().GetArrayName(i) for i in range(data.GetFieldData().GetNumberOfArrays())]}


def plain_rgba_recipe(reader, view, spacing):
    """The direct-RGBA recipe without the helper: Volume, ColorBy, MapScalars off, the colour
    map fixed to 0..255, a linear opacity ramp, ScalarOpacityUnitDistance = spacing (and the
    alpha channel's unit distance VTK's default, 1). Set after a first render: where the
    plugin's display behaviour sets up a new NebulaRT display, these are then the user's own
    settings, which it leaves alone."""
    from paraview import simple
    from nebula_rt_paraview.view import set_alpha_unit_distance

    display = simple.Show(reader, view)
    simple.Render(view)
    display.SetRepresentationType("Volume")
    display.UseSeparateColorMap = 1
    simple.ColorBy(display, ("POINTS", "rgba"))
    display.MapScalars = 0
    display.LookupTable.AutomaticRescaleRangeMode = "Never"
    display.LookupTable.RescaleTransferFunction(0.0, 255.0)
    display.ScalarOpacityFunction.Points = [0.0, 0.0, 0.5, 0.0, 255.0, 1.0, 0.5, 0.0]
    display.ScalarOpacityUnitDistance = spacing
    display.SetScalarBarVisibility(view, False)
    set_alpha_unit_distance(display, 1.0)
    return display
