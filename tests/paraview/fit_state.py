"""The fit result's example state, loaded as a user loads it.

    pvpython fit_state.py STATE.pvsm OUT.png

``load_state_safely`` with the data directory set to the repository (the state's reader names
examples/observations/fit-result.json relative to it), from a folder elsewhere; the layout's
view rendered to OUT.png at the state's preview size.
RESULT: the reader's last error and file name, the views (type, script, representations shown),
the number of parameter rows and the PNG.
"""

import os
import sys

import _common
from paraview import servermanager, simple
from nebula_rt_paraview.view import load_state_safely

state, png = sys.argv[1], sys.argv[2]
os.chdir(os.path.dirname(png))  # not the repository: the data directory finds the file
load_state_safely(state, {"NebulaFitResultReader": 1}, data_directory=_common.REPO)
reader = simple.FindSource("fit-result.json")
views = []
for view in simple.GetViews():
    shown = [rep for rep in view.Representations if rep.Visibility]
    views.append({"type": view.GetXMLName(), "script": getattr(view, "Script", None), "shown": len(shown)})
view = simple.GetViews()[0]
layout = simple.GetLayout(view)
size = [int(x) for x in layout.PreviewMode]
simple.Render(view)
simple.SaveScreenshot(png, view, ImageResolution=size)
params = servermanager.Fetch(reader, idx=0)
_common.result(error=reader.GetClientSideObject().last_error, file=reader.FileName, views=views, size=size,
               rows=params.GetNumberOfRows(), png=png)
