"""Measure how ParaView composites a uint8 RGBA volume (white voxels, alpha along z).

    pvpython compositing.py OUT_DIR

White voxels on black, seen along -z in parallel projection, with an alpha that is constant
or varies along z (a slab of alpha 30 in an empty box, a ramp, 3 layers of alpha 100); the centre pixel is compared
with per-voxel compositing of the alpha profile interpolated linearly between voxel centres:
255 (1 - T), T = exp(integral of ln(1 - alpha(z)/255) dz / h) over the n - 1 voxel-centre
intervals a ray crosses (constant alpha: T = (1 - a/255)^(n - 1)). Each case renders twice:
with show_rgba_volume (the per-voxel opacity mapping) and with the plain recipe (linear
opacity ramp, ScalarOpacityUnitDistance = spacing). RESULT: the cases with both centre values.
"""

import os
import sys

import numpy as np

import _common  # noqa: F401
from paraview import simple
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkImageData
from vtkmodules.vtkIOImage import vtkPNGReader
from vtkmodules.vtkIOXML import vtkXMLImageDataWriter

from nebula_rt_paraview.view import show_rgba_volume

out = sys.argv[1]
SIZE = 160


def profile(kind, n, a):
    """Alpha (uint8) of the n voxel layers along z."""
    if kind == "const":
        return np.full(n, a, np.uint8)
    if kind in ("slab", "thin"):  # 10 (3) layers in an empty box: the data's alpha range is [0, a]
        half = 5 if kind == "slab" else 1
        p = np.zeros(n, np.uint8)
        p[n // 2 - half:n // 2 + half + (kind == "thin")] = a
        return p
    return np.rint(np.linspace(0, a, n)).astype(np.uint8)  # "ramp"


def expected(alpha):
    """255 (1 - T) for the alpha profile interpolated linearly between voxel centres."""
    z = np.linspace(0.0, len(alpha) - 1.0, 200 * (len(alpha) - 1) + 1)
    a = np.interp(z, np.arange(len(alpha)), alpha.astype(np.float64) / 255.0)
    f = np.log1p(-np.minimum(a, 1.0 - 1e-12))
    return 255.0 * (1.0 - np.exp(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(z))))


def make(n, spacing, alpha):
    path = os.path.join(out, f"box_{n}_{spacing:.6f}_{alpha.min()}_{alpha.max()}_{int(alpha.sum())}.vti")
    img = vtkImageData()
    img.SetDimensions(n, n, n)
    img.SetSpacing(spacing, spacing, spacing)
    img.SetOrigin(0.5 * spacing, 0.5 * spacing, 0.5 * spacing)
    rgba = np.zeros((n, n, n, 4), np.uint8)  # (z, y, x): VTK's point order
    rgba[..., :3] = 255
    rgba[..., 3] = alpha[:, None, None]
    arr = numpy_to_vtk(rgba.reshape(-1, 4), deep=1)
    arr.SetName("rgba")
    img.GetPointData().SetScalars(arr)
    w = vtkXMLImageDataWriter()
    w.SetFileName(path)
    w.SetInputData(img)
    w.Write()
    return path


def centre(path, spacing, n, plain):
    view = simple.CreateView("RenderView")
    view.ViewSize = [SIZE, SIZE]
    view.OrientationAxesVisibility = 0
    if "UseColorPaletteForBackground" in view.ListProperties():
        view.UseColorPaletteForBackground = 0
    view.Background = [0.0, 0.0, 0.0]
    reader = simple.XMLImageDataReader(FileName=[path])
    display = _common.plain_rgba_recipe(reader, view, spacing) if plain else show_rgba_volume(reader, view)
    simple.Render(view)
    c = 0.5 * n * spacing
    view.CameraParallelProjection = 1
    view.CameraFocalPoint = [c, c, c]
    view.CameraPosition = [c, c, c + 10 * n * spacing]
    view.CameraViewUp = [0.0, 1.0, 0.0]
    view.CameraParallelScale = 0.8 * n * spacing
    simple.Render(view)
    png = os.path.join(out, "shot.png")
    simple.SaveScreenshot(png, view, ImageResolution=[SIZE, SIZE])
    r = vtkPNGReader()
    r.SetFileName(png)
    r.Update()
    im = vtk_to_numpy(r.GetOutput().GetPointData().GetScalars()).reshape(SIZE, SIZE, -1)
    simple.Delete(display)
    simple.Delete(reader)
    simple.Delete(view)
    return float(im[SIZE // 2 - 2:SIZE // 2 + 2, SIZE // 2 - 2:SIZE // 2 + 2, :3].mean())


cases = []
for kind, n, spacing, a in [("const", 32, 1 / 32, 20), ("const", 32, 1.0, 20), ("const", 64, 1 / 64, 10),
                            ("const", 32, 1 / 32, 5), ("slab", 32, 1 / 32, 30), ("slab", 32, 1.0, 30),
                            ("ramp", 32, 1 / 32, 40), ("ramp", 48, 1 / 48, 12),
                            # dense voxels on a fine grid: their opacity per world unit rounds to
                            # 1 in float32 (opaque walls) unless the alpha's unit distance is the voxel
                            ("thin", 64, 1 / 64, 100)]:
    alpha = profile(kind, n, a)
    path = make(n, spacing, alpha)
    cases.append({"kind": kind, "n": n, "spacing": spacing, "alpha": a,
                  "expected": expected(alpha),
                  "helper": centre(path, spacing, n, plain=False),
                  "plain": centre(path, spacing, n, plain=True)})
_common.result(cases=cases)
