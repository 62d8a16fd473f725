"""The adaptive example's state (state_files/adaptive_cloud.pvsm), loaded as a user loads it.

    pvpython adaptive_state.py STATE.pvsm OUT.png

``load_state_safely`` with the data directory set to the repository (the state's reader names
examples/data/clumpy_cloud.htg relative to it), from a folder elsewhere; the view rendered to
OUT.png at the state's preview size. RESULT: the reader's file name and data type, the light
field's and colour's last errors, the light field's points and the leaves it traced, the PNG.
"""

import os
import sys

import _common
from paraview import simple
from nebula_rt_paraview.view import load_state_safely

state, png = sys.argv[1], sys.argv[2]
os.chdir(os.path.dirname(png))  # not the repository: the data directory finds the file
load_state_safely(state, {"NebulaLightField": 1, "NebulaColour": 1}, data_directory=_common.REPO)
reader = simple.FindSource("clumpy_cloud.htg")
light = simple.FindSource("Light field (adaptive)")
colour = simple.FindSource("Colour (adaptive)")
light.Device = _common.TEST_DEVICE
view = simple.GetViews()[0]
size = [int(x) for x in simple.GetLayout(view).PreviewMode]
simple.Render(view)
simple.SaveScreenshot(png, view, ImageResolution=size)
alg = light.GetClientSideObject()
_common.result(file=str(reader.FileNames[0]),  # (ParaView 5.11's .htg reader: FileNames)
               data_type=reader.GetDataInformation().GetDataSetTypeAsString(), size=size,
               errors=[alg.last_error, colour.GetClientSideObject().last_error],
               points=int(light.GetDataInformation().GetNumberOfPoints()),
               leaves=int(alg.last_light.transport.J.shape[1]) if alg.last_light is not None else 0, png=png)
