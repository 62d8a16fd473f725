"""Measure how ParaView composites a uint8 RGBA volume (constant colour and alpha).

    pvpython compositing.py OUT_DIR

White voxels of constant alpha on black, seen along -z in parallel projection; the centre
pixel is compared with per-voxel compositing, 255 (1 - (1 - a/255)^(n - 1)) for n voxels (the
rays cross n - 1 voxel-centre intervals). Each case renders twice: with show_rgba_volume (the
per-voxel opacity mapping) and with the plain recipe (linear opacity ramp,
ScalarOpacityUnitDistance = spacing). RESULT: the cases with both centre values.
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


def make(n, spacing, a):
    path = os.path.join(out, f"const_{n}_{spacing:.6f}_{a}.vti")
    img = vtkImageData()
    img.SetDimensions(n, n, n)
    img.SetSpacing(spacing, spacing, spacing)
    img.SetOrigin(0.5 * spacing, 0.5 * spacing, 0.5 * spacing)
    rgba = np.zeros((n ** 3, 4), np.uint8)
    rgba[:, :3] = 255
    rgba[:, 3] = a
    arr = numpy_to_vtk(rgba, deep=1)
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
    display = show_rgba_volume(reader, view)
    if plain:
        display.ScalarOpacityFunction.Points = [0.0, 0.0, 0.5, 0.0, 255.0, 1.0, 0.5, 0.0]
        display.ScalarOpacityUnitDistance = spacing
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
for n, spacing, a in [(32, 1 / 32, 20), (32, 1.0, 20), (64, 1 / 64, 10), (32, 1 / 32, 5)]:
    path = make(n, spacing, a)
    cases.append({"n": n, "spacing": spacing, "alpha": a,
                  "expected": 255.0 * (1.0 - (1.0 - a / 255.0) ** (n - 1)),
                  "helper": centre(path, spacing, n, plain=False),
                  "plain": centre(path, spacing, n, plain=True)})
_common.result(cases=cases)
