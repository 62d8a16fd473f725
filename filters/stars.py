"""The stars of a light field as points (the ``Stars`` output of Nebula Light Field).

One vertex per star at its place in the light field's world coordinates, with the star's own
colour (``star_rgb``, uint8 x 3: sRGB through the same band -> XYZ matrix as the nebula's
colours, scaled so its largest component is full scale) and ``luminosity``. ParaView draws
them over the volume (a point sprite per star), so the stars of a rendered nebula are seen.
"""

from __future__ import annotations

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

from nebula_rt.optics import colour_convert
from nebula_rt.pipeline import output_contract as contract
from nebula_rt.errors import SceneError
from nebula_rt.pipeline.rgba import colour_matrix
from nebula_rt.transport.plan import star_band_luminosities


def star_colours(stars, wavelengths_nm, band_luminosity, source, white_point: str = "D65") -> np.ndarray:
    """(n_stars, 3) uint8 sRGB of each star's own light.

    A star's band luminosities go through the matrix of the nebula's colours
    (:func:`nebula_rt.pipeline.colour_matrix`: nebula/star ratio per band -> linear sRGB), so
    the dominant star of a one-star scene comes out as that star's colour; each colour is then
    scaled to full brightness (a star is the brightest thing in the picture) and encoded."""
    to_rgb = colour_matrix(wavelengths_nm, band_luminosity, source, white_point)
    lum = star_band_luminosities(stars, wavelengths_nm)  # (n_stars, n_bands)
    rgb = colour_convert.gamut_map(lum @ to_rgb.T)  # (n_stars, 3) linear sRGB
    peak = rgb.max(axis=1, keepdims=True)
    rgb = np.where(peak > 0, rgb / np.where(peak > 0, peak, 1.0), 1.0)  # no colour: white
    return colour_convert.encode_srgb(rgb, 1.0)


def box_to_world(positions, dims, spacing, origin) -> np.ndarray:
    """Box-unit positions -> world coordinates of an image whose points are the voxels: the
    box [0, 1]^3 is the voxels' outer faces, origin - spacing/2 to origin + (n - 1/2) spacing."""
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    n, h, o = (np.asarray(v, np.float64) for v in (dims, spacing, origin))
    return (o - 0.5 * h) + p * n * h


def star_points(light, dims, spacing, origin) -> vtkPolyData:
    """The stars of ``light`` (a :class:`nebula_rt.pipeline.LightField`) as a vtkPolyData of
    vertices in the world coordinates of an image of ``dims``, ``spacing``, ``origin``."""
    from nebula_rt.pipeline.rgba import _dominant_source

    stars = light.scene.stars
    xyz = box_to_world([s.position for s in stars], dims, spacing, origin)
    try:
        rgb = star_colours(stars, [b.wavelength for b in light.bands], light.transport.band_luminosity,
                           _dominant_source(stars), light.scene.colour.white_point)
    except SceneError:  # a band without starlight has no colour: the stars are drawn white
        rgb = np.full((len(stars), 3), 255, np.uint8)
    out = vtkPolyData()
    pts = vtkPoints()
    pts.SetData(numpy_to_vtk(np.ascontiguousarray(xyz), deep=1))
    out.SetPoints(pts)
    verts = vtkCellArray()
    for i in range(len(stars)):
        verts.InsertNextCell(1)
        verts.InsertCellPoint(i)
    out.SetVerts(verts)
    arrays = {contract.STAR_RGB.name(): np.ascontiguousarray(rgb, np.uint8),
              contract.STAR_LUMINOSITY.name(): np.array([s.luminosity for s in stars], np.float32)}
    for name, a in arrays.items():
        arr = numpy_to_vtk(a, deep=1)
        arr.SetName(name)
        out.GetPointData().AddArray(arr)
    out.GetPointData().SetActiveScalars(contract.STAR_RGB.name())
    return out
