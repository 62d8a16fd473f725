"""A polarized nebula through the plugin's proxies: Nebula Light Field with Polarization white
(or mie: MRN grains of astronomical silicate; or matrix: the Pinte et al. 2009 benchmark's
tabulated matrix), Nebula Sky Image with Method peel-off, Nebula Polarization Vectors' segments
shown over it.

    pvpython polarization.py OUT.png PHOTONS [white|mie|matrix]

RESULT: the filters' last errors; the sky image's Q_ and U_ arrays and its field data; the
vectors' points, arrays and angles, each vector's position angle about the star (the pattern
is centrosymmetric where the light is tangentially polarized); the glyph display's settings as
the plugin made them.
"""

import os
import sys

import _common
import numpy as np
from paraview import servermanager, simple
from nebula_rt_paraview.view import load_plugin
from vtkmodules.util.numpy_support import vtk_to_numpy

load_plugin()
png, photons = sys.argv[1], int(sys.argv[2])
kind = sys.argv[3] if len(sys.argv) > 3 else "white"
MATRIX = os.path.join(_common.REPO, "benchmarks", "data", "pinte2009", "mueller_matrix_1um.dat")
optics = {"white": dict(Polarization="white", PeakPolarization=0.6),
          "mie": dict(Polarization="mie", GrainMaterial="astronomical-silicate", GrainRadiusMin=0.005,
                      GrainRadiusMax=0.25, GrainSizeSlope=3.5),
          "matrix": dict(Polarization="matrix", GrainMatrix=MATRIX)}[kind]
star = [0.5, 0.5, 0.5, 1.0, 9000.0, 0.0]
dust = simple.NebulaDustDensity(GridShape=[24, 24, 24], Model="uniform", UniformDensity=1.0, Floor=0.0, Stars=star,
                                Device=_common.TEST_DEVICE)
light = simple.NebulaLightField(dust, Stars=star, Tau=2.0, Photons=photons, Device=_common.TEST_DEVICE,
                                **optics)
light.DensityArray = ["POINTS", "density"]
sky = simple.NebulaSkyImage(light, ImageSize=[96, 96], Extent=1.0, Method="peel-off")
vectors = simple.NebulaPolarizationVectors(sky, BlockSize=8, MinSignalToNoise=3.0, VectorScale=1.5)
view = simple.CreateView("NebulaSkyView")
simple.Show(sky, view)
shown = simple.Show(vectors, view)
simple.Render(view)
simple.SaveScreenshot(png, view, ImageResolution=[500, 500])

img = servermanager.Fetch(sky)
vec = servermanager.Fetch(vectors)
arrays = [img.GetPointData().GetArrayName(i) for i in range(img.GetPointData().GetNumberOfArrays())]
fd = [img.GetFieldData().GetAbstractArray(i).GetName() for i in range(img.GetFieldData().GetNumberOfArrays())]
pts = vtk_to_numpy(vec.GetPoints().GetData()).astype(np.float64) if vec.GetNumberOfPoints() else np.zeros((0, 3))
mid = 0.5 * (pts[0::2] + pts[1::2])
angle = vtk_to_numpy(vec.GetCellData().GetArray("angle")).astype(np.float64) if len(mid) else np.zeros(0)
# a tangential pattern: the vector is perpendicular to the line to the star's image (the centre);
# position angle of a point from north (+y) through east (-x)
cx, cy = 0.5, 0.5
pa = np.degrees(np.arctan2(-(mid[:, 0] - cx), mid[:, 1] - cy)) if len(mid) else np.zeros(0)
off = np.mod(angle - pa - 90.0, 180.0)
off = np.minimum(off, 180.0 - off)
seg = pts[1::2] - pts[0::2]
seg_angle = np.mod(np.degrees(np.arctan2(-seg[:, 0], seg[:, 1])), 180.0)  # the segment's own angle
algs = {n: p.GetClientSideObject() for n, p in (("light", light), ("sky", sky), ("vectors", vectors))}
_common.result(last_errors={n: a.last_error for n, a in algs.items()},
               arrays=arrays, field_data=fd, vectors=int(vec.GetNumberOfPoints()),
               vector_arrays=[vec.GetCellData().GetArrayName(i) for i in range(vec.GetCellData().GetNumberOfArrays())],
               cells=int(vec.GetNumberOfCells()), tangential_deviation_deg=[float(x) for x in off],
               # (tangential or radial: grains whose polarization changes sign with the angle)
               aligned_deviation_deg=[float(min(x, 90.0 - x)) for x in off],
               segment_vs_angle_deg=float(np.max(np.abs(((seg_angle - angle) + 90.0) % 180.0 - 90.0))) if len(mid) else 0.0,
               z=[float(z) for z in pts[:, 2]], display={"Representation": str(shown.Representation),
                                                         "DiffuseColor": list(shown.DiffuseColor)})
