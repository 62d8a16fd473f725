"""Nebula Dust Density -> Nebula Light Field shown as Apply shows it, in the built-in session or
as the client of a pvserver.

    pvpython client_server.py builtin|PORT OUT.png

With a PORT, connects to ``localhost:PORT`` (a ``pvserver`` started by the test under
mpiexec, with the environment of scripts/pv-env.sh, so the server loads the plugin from
PV_PLUGIN_PATH), then loads the plugin with ``nebula_rt_paraview.view.load_plugin`` (the client
needs its display behaviour; a second LoadPlugin of the same file on the server fails in
ParaView 5.11). Shows the light field with ``Show`` (the plugin's display behaviour adds the
stars), renders at 600 x 500 and saves OUT.png. RESULT: the light field's error, J of the
reference band as fetched to the client (OUT.png.J.npy, with the fetched image's extent:
ParaView's Fetch brings rank 0's piece of a pvserver's output) and its SHA-256, the number of
star points fetched, the representations shown and the camera.
"""

import hashlib
import sys

import _common
from paraview import servermanager, simple

where, png = sys.argv[1], sys.argv[2]
if where != "builtin":
    simple.Connect("localhost", int(where))
from nebula_rt_paraview.view import load_plugin  # noqa: E402

load_plugin()
dust = simple.NebulaDustDensity(Device=_common.TEST_DEVICE, GridShape=[24, 24, 24])
light = simple.NebulaLightField(dust, Device=_common.TEST_DEVICE, Photons=100_000)
view = simple.CreateView("RenderView")
view.ViewSize = [600, 500]
simple.Show(light, view)
simple.Render(view)
simple.SaveScreenshot(png, view, ImageResolution=[600, 500])
error = None
if where == "builtin":
    error = light.GetClientSideObject().last_error
image = servermanager.Fetch(light, idx=0)
import numpy as np  # noqa: E402
from vtkmodules.util.numpy_support import vtk_to_numpy  # noqa: E402

arr = image.GetPointData().GetArray("J_G")
j = vtk_to_numpy(arr) if arr is not None else np.zeros(0, np.float32)
shown = sorted(f"{r.Input.GetXMLName()}:{r.SMProxy.GetProperty('Representation').GetElement(0)}" for r in view.Representations
               if r.Visibility)
np.save(png + ".J.npy", j)
_common.result(error=error, extent=list(image.GetExtent()), j_file=png + ".J.npy", points=int(image.GetNumberOfPoints()), j_sha=hashlib.sha256(j.tobytes()).hexdigest(),
               stars=int(servermanager.Fetch(light, idx=1).GetNumberOfPoints()), shown=shown,
               camera=[list(view.CameraPosition), list(view.CameraFocalPoint), list(view.CameraViewUp),
                       float(view.CameraViewAngle)], png=png)
