"""Nebula Colour: band arrays of a light field -> ``rgba`` for direct volume rendering."""

from __future__ import annotations

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkImageData

from nebula_rt import output_contract as contract
from nebula_rt.pipeline import colour_source_from_field_data, rgba_from_emissivity

from .base import ExposureMixin, NebulaAlgorithm, shallow_copy_image
from .image_data import add_field_data, add_point_arrays, field_data_dict, point_array
from .properties import Property, bind, init_values, scene_values

#: The colour's properties bound to scene keys (Auto Exposure and Exposure, which together
#: make colour.exposure = "auto" or a number, are the exposure mixin's)
COLOUR_PROPERTIES = (
    Property("WhitePoint", "colour.white_point", widget="enum"),
    Property("OpacityScale", "colour.opacity_scale"),
    Property("Stretch", "colour.stretch", widget="enum"),
    Property("AsinhQ", "colour.asinh_q", enabled_by=("Stretch", 1)),
)


@bind(COLOUR_PROPERTIES)
class NebulaColour(ExposureMixin, NebulaAlgorithm):
    """sRGB colour of the scattered emissivity and the reference band's voxel opacity.

    Reads the arrays and field data that Nebula Light Field writes; changing exposure, white
    point or opacity re-runs only this filter, never the photon transport.
    Output: the input plus ``rgba`` (uint8 x 4) and ``rgb_linear`` (float32 x 3, exposed linear
    sRGB before the transfer curve); field data ``exposure`` is the exposure used.
    """

    PROPERTIES = {"colour.exposure": "Exposure"}

    def __init__(self):
        super().__init__(nInputPorts=1, nOutputPorts=1, inputType="vtkImageData", outputType="vtkImageData")
        init_values(self)
        self._auto_exposure = True
        self._exposure = 1.0

    def RequestInformation(self, request, inInfo, outInfo):
        """The input's geometry (copied by the executive), and pieces: every rank colours the
        whole light field (global exposure) and gives the piece asked of it."""
        from vtkmodules.vtkCommonExecutionModel import vtkAlgorithm

        outInfo.GetInformationObject(0).Set(vtkAlgorithm.CAN_PRODUCE_SUB_EXTENT(), 1)
        return 1

    def _execute(self, request, inInfo, outInfo):
        from nebula_rt.scene import Colour, Scene  # validation of the colour table

        exposure = "auto" if self._auto_exposure else self._exposure
        Scene.from_dict(scene_values(self._values, {"colour": {"exposure": exposure}}))
        inp = vtkImageData.GetData(inInfo[0])
        has_density = inp.GetPointData().HasArray(contract.DENSITY.name())
        need = ("band_names", "band_wavelength_nm", "band_luminosity", "band_extinction", "tau", "reference_band")
        # without the density, the reference extinction comes from emissivity = albedo sigma J
        fd = contract.LightFieldData.from_field_data(field_data_dict(inp),
                                                     need=need + (() if has_density else ("band_albedo",)))
        emissivity = np.stack([point_array(inp, contract.EMISSIVITY.name(n)) for n in fd.band_names])
        emissivity = emissivity.astype(np.float64)
        ref = fd.reference_band
        if has_density:
            density = point_array(inp, contract.DENSITY.name()).astype(np.float64)
            sigma_ref = fd.tau * float(fd.band_extinction[ref]) * density
        else:
            J = point_array(inp, contract.J.name(fd.band_names[ref])).astype(np.float64)
            alb = float(fd.band_albedo[ref])
            with np.errstate(divide="ignore", invalid="ignore"):
                sigma_ref = np.where(J > 0, emissivity[ref] / (alb * J), 0.0)
        rgba, used, linear = rgba_from_emissivity(
            emissivity, sigma_ref,
            wavelengths_nm=fd.band_wavelength_nm,
            band_luminosity=fd.band_luminosity,
            temperature=colour_source_from_field_data(fd),
            exposure=exposure, white_point=self._values["colour.white_point"],
            opacity_scale=self._values["colour.opacity_scale"],
            stretch=self._values["colour.stretch"],
            asinh_q=self._values["colour.asinh_q"],
            return_linear=True,
        )
        out = vtkImageData.GetData(outInfo)
        shallow_copy_image(out, inp)
        add_point_arrays(out, {contract.RGBA.name(): rgba, contract.RGB_LINEAR.name(): linear})
        add_field_data(out, contract.LightFieldData(exposure=used).to_field_data(complete=False))
        out.GetPointData().SetActiveScalars(contract.RGBA.name())
