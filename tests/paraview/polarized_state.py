"""A polarization example's state (state_files/polarized_nebula.pvsm, mie_nebula.pvsm), loaded as a user loads it.

    pvpython polarized_state.py STATE.pvsm OUT.png

``load_state_safely`` from a folder elsewhere, the light field pinned to the test device; the
sky view rendered to OUT.png at the state's preview size. RESULT: the three filters' last errors,
the sky image's Stokes arrays, the vectors' segments, their median deviation from tangential
about the star, the PNG's size.
"""

import os
import sys

import _common
import numpy as np
from paraview import servermanager, simple
from nebula_rt_paraview.view import load_state_safely
from vtkmodules.util.numpy_support import vtk_to_numpy

state, png = sys.argv[1], sys.argv[2]
os.chdir(os.path.dirname(png))
load_state_safely(state, {"NebulaDustDensity": 1, "NebulaLightField": 1, "NebulaSkyImage": 1,
                          "NebulaPolarizationVectors": 1})
dust = simple.FindSource("Dust (polarized)")
light = simple.FindSource("Light field (polarized)")
sky = simple.FindSource("Sky image (peel-off)")
vectors = simple.FindSource("Polarization vectors")
dust.Device = light.Device = _common.TEST_DEVICE
view = simple.GetViews()[0]
size = [int(x) for x in simple.GetLayout(view).PreviewMode]
simple.Render(view)
simple.SaveScreenshot(png, view, ImageResolution=size)
img, vec = servermanager.Fetch(sky), servermanager.Fetch(vectors)
pts = vtk_to_numpy(vec.GetPoints().GetData()).astype(np.float64) if vec.GetNumberOfPoints() else np.zeros((0, 3))
mid = 0.5 * (pts[0::2] + pts[1::2])
angle = vtk_to_numpy(vec.GetCellData().GetArray("angle")).astype(np.float64) if len(mid) else np.zeros(0)
pa = np.degrees(np.arctan2(-(mid[:, 0] - 0.5), mid[:, 1] - 0.5)) if len(mid) else np.zeros(0)
off = np.abs(((angle - pa - 90.0) + 90.0) % 180.0 - 90.0)
_common.result(errors=[a.GetClientSideObject().last_error for a in (light, sky, vectors)],
               view=view.GetXMLName(), size=size, segments=int(vec.GetNumberOfCells()),
               stokes=[n for n in ("Q_G", "U_G", "V_G") if img.GetPointData().GetArray(n) is not None],
               median_deviation_deg=float(np.median(off)) if len(off) else None, png=png)
