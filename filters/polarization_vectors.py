"""Nebula Polarization Vectors: the polarization pattern of a sky image as points to glyph."""

from __future__ import annotations

import warnings

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkImageData, vtkPolyData

from nebula_rt.errors import NebulaWarning, SceneError
from nebula_rt.observe.polarimetry import vector_field
from nebula_rt.pipeline import output_contract as contract
from nebula_rt.scene import sky_schema
from nebula_rt.scene.rules import rule

from .base import NebulaAlgorithm
from .image_data import field_data_dict, point_array
from .properties import Property, bind, init_values

#: the filter's properties, bound to the sky image's declarations (keys ``sky.vector_*``)
POLARIZATION_VECTOR_PROPERTIES = (
    Property("Band", "sky.vector_band"),
    Property("BlockSize", "sky.vector_block"),
    Property("VectorScale", "sky.vector_scale"),
    Property("MinSignalToNoise", "sky.vector_snr"),
)


@bind(POLARIZATION_VECTOR_PROPERTIES)
class NebulaPolarizationVectors(NebulaAlgorithm):
    """One polarization vector per block of pixels of a polarized sky image (Nebula Sky Image
    with Method peel-off of a scene with bands.polarization).

    I, Q and U of ``Band`` are summed over blocks of ``BlockSize`` pixels a side (their errors in
    quadrature); each block whose degree of polarization P is at least ``MinSignalToNoise`` of
    its error becomes a line segment centred on the block, along the polarization angle (north
    is the image's +y, east its -x: the IAU convention), P x ``VectorScale`` blocks long: a
    headless glyph, the classic polarization map, drawn over the picture one pixel in front of
    it (+z). Cell data: ``polarization`` (P times the unit vector along the angle), ``P``,
    ``P_error`` and ``angle`` (degrees from north through east). ParaView shows the lines over
    the sky image in its view; pyvista plots them as they are.
    """

    def __init__(self):
        super().__init__(nInputPorts=1, nOutputPorts=1, inputType="vtkImageData", outputType="vtkPolyData")
        init_values(self)

    def _execute(self, request, inInfo, outInfo):
        if self._values["sky.vector_band"] is None:  # (ParaView's empty string property)
            self._values["sky.vector_band"] = ""
        for prop in POLARIZATION_VECTOR_PROPERTIES:
            p = sky_schema.declaration(prop.key)
            r = rule(p)
            r.validate(prop.key, self._values[prop.key])
        band, step = str(self._values["sky.vector_band"]), int(self._values["sky.vector_block"])
        snr = float(self._values["sky.vector_snr"])
        inp = vtkImageData.GetData(inInfo[0])
        fd = contract.SkyImageData.from_field_data(field_data_dict(inp), need=("band_names",))
        if fd.polconv != "IAU":
            raise SceneError("input", fd.sky_method or "ray-march",
                             "must be a polarized sky image: Nebula Sky Image with Method peel-off of a scene "
                             "with bands.polarization (Nebula Light Field's Polarization)")
        names = list(fd.band_names)
        band = band or names[0]
        if band not in names:
            raise SceneError("sky.vector_band", band, "must be one of the image's bands: " + ", ".join(names))
        w, h, _ = inp.GetDimensions()
        if step > min(w, h):
            raise SceneError("sky.vector_block", step, f"must be at most the image's smaller side ({min(w, h)} pixels)")

        def arr(spec):
            return point_array(inp, spec.name(band))[:, :, 0].astype(np.float64)

        centres, p, p_err, chi, keep = vector_field(
            arr(contract.SKY_SCATTERED), arr(contract.SKY_Q), arr(contract.SKY_U), arr(contract.SKY_SCATTERED_ERROR),
            arr(contract.SKY_Q_ERROR), arr(contract.SKY_U_ERROR), step=step, snr=snr)
        origin, spacing = np.array(inp.GetOrigin()), np.array(inp.GetSpacing())
        centre = origin[:2] + centres[keep] * spacing[:2]
        a = np.radians(chi[keep])
        unit = np.stack([-np.sin(a), np.cos(a)], axis=1)  # north = +y, east = -x
        half = 0.5 * float(self._values["sky.vector_scale"]) * step * spacing[0] * p[keep]
        n = len(centre)
        xyz = np.empty((2 * n, 3))
        xyz[0::2, :2] = centre - half[:, None] * unit
        xyz[1::2, :2] = centre + half[:, None] * unit
        # a pixel in front of the image (towards a viewer at +z, the sky view's): the lines are not
        # hidden in the image's plane
        xyz[:, 2] = origin[2] + spacing[0]
        out = vtkPolyData.GetData(outInfo)
        pts = vtkPoints()
        pts.SetData(numpy_to_vtk(np.ascontiguousarray(xyz), deep=1))
        out.SetPoints(pts)
        lines = vtkCellArray()
        for i in range(n):
            lines.InsertNextCell(2)
            lines.InsertCellPoint(2 * i)
            lines.InsertCellPoint(2 * i + 1)
        out.SetLines(lines)
        vec = np.column_stack([unit * p[keep][:, None], np.zeros(n)])
        for spec, values in ((contract.POLARIZATION_VECTOR, vec), (contract.POLARIZATION_DEGREE, p[keep]),
                             (contract.POLARIZATION_DEGREE_ERROR, p_err[keep]),
                             (contract.POLARIZATION_ANGLE, chi[keep])):
            v = numpy_to_vtk(np.ascontiguousarray(values, np.float32), deep=1)
            v.SetName(spec.name())
            out.GetCellData().AddArray(v)
        out.GetCellData().SetActiveVectors(contract.POLARIZATION_VECTOR.name())
        out.GetCellData().SetActiveScalars(contract.POLARIZATION_DEGREE.name())
        self.last_vectors = (centres[keep], p[keep], chi[keep])
        if not n:
            warnings.warn(f"no block of band {band} is polarized above {snr:g} of its error: trace more packets "
                          f"(Nebula Light Field's Photons) or raise BlockSize", NebulaWarning)
