"""Nebula Sky Image with Units "MJy/sr" and the FITS writer, through the plugin's proxies.

    pvpython sky_fits.py OUT.fits PHOTONS

The light field of a uniform 12^3 density (Luminosity Unit L_sun, Spectral Types "A0 V", Box
Length 0.2 pc), its sky
image calibrated at 50 pc (RA 30, Dec -20, PA 25 deg, PSF 40 arcsec) and saved with
``SaveData(OUT.fits)``. RESULT: ``last_errors`` of the three algorithms, the sky image's arrays
and field-data keys, the proxies' property groups of the sky image, and the sum of the
``sb_G`` array.
"""

import sys

import _common
import numpy as np
from paraview import servermanager, simple
from nebula_rt_paraview.view import load_plugin
from vtkmodules.util.numpy_support import vtk_to_numpy

load_plugin()
out, photons = sys.argv[1], int(sys.argv[2])
star = [0.61, 0.43, 0.5, 100.0, 9000.0, 0.0]
dust = simple.NebulaDustDensity(GridShape=[12, 12, 12], Model="uniform", UniformDensity=1.0, Floor=0.0,
                                Stars=star, Device=_common.TEST_DEVICE)
light = simple.NebulaLightField(dust, Stars=star, Tau=1.5, Photons=photons, Device=_common.TEST_DEVICE)
light.DensityArray = ["POINTS", "density"]
light.LuminosityUnit = "L_sun"
light.SpectralTypes = "A0 V"  # in place of the Stars' 9000 K
light.BoxLength = 0.2
sky = simple.NebulaSkyImage(light, ImageSize=[24, 24], Units="MJy/sr", Distance="50 pc", RA=30.0, Dec=-20.0,
                            PositionAngle=25.0, PSFFWHM=40.0, Stretch="asinh", AsinhQ=4.0)
sky.UpdatePipeline()
simple.SaveData(out, proxy=sky)
data = servermanager.Fetch(sky)
names = [data.GetPointData().GetArrayName(i) for i in range(data.GetPointData().GetNumberOfArrays())]
fd = [data.GetFieldData().GetAbstractArray(i).GetName() for i in range(data.GetFieldData().GetNumberOfArrays())]
sb = vtk_to_numpy(data.GetPointData().GetArray("sb_G")).astype(np.float64)
algs = {n: p.GetClientSideObject() for n, p in (("light", light), ("sky", sky))}

# the plain VTK filters with the same values, in this process (so on this ParaView's device)
from nebula_rt.filters import NebulaDustDensity, NebulaLightField, NebulaSkyImage  # noqa: E402

d2 = NebulaDustDensity()
d2.SetGridShape(12, 12, 12)
d2.SetModel("uniform")
d2.SetUniformDensity(1.0)
d2.SetFloor(0.0)
d2.SetStars(star)
d2.SetDevice(_common.TEST_DEVICE)
l2 = NebulaLightField()
l2.SetInputConnection(d2.GetOutputPort())
l2.SetStars(star)
l2.SetTau(1.5)
l2.SetPhotons(photons)
l2.SetDevice(_common.TEST_DEVICE)
l2.SetLuminosityUnit(1)
l2.SetSpectralTypes("A0 V")
l2.SetBoxLength(0.2)
s2 = NebulaSkyImage()
s2.SetInputConnection(l2.GetOutputPort())
s2.SetImageSize(24, 24)
s2.SetUnits(1)
s2.SetDistance("50 pc")
s2.SetRA(30.0)
s2.SetDec(-20.0)
s2.SetPositionAngle(25.0)
s2.SetPSFFWHM(40.0)
s2.Update()
sb2 = vtk_to_numpy(s2.GetOutputDataObject(0).GetPointData().GetArray("sb_G")).astype(np.float64)
_common.result(last_errors={n: a.last_error for n, a in algs.items()}, arrays=names, field_data=fd,
               sb_G_sum=float(sb.sum()), same_as_vtk=bool(np.array_equal(sb, sb2)), vtk_error=s2.last_error,
               star=[algs["light"].last_light.scene.stars[0].spectral_type,
                     algs["light"].last_light.scene.stars[0].temperature],
               groups=[g.GetXMLLabel() for g in
                                                  [sky.SMProxy.GetPropertyGroup(i)
                                                   for i in range(sky.SMProxy.GetNumberOfPropertyGroups())]])
