"""Nebula Colour: band arrays of a light field -> ``rgba`` for direct volume rendering."""

from __future__ import annotations

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkImageData

from nebula_rt.pipeline import output_contract as contract
from nebula_rt.pipeline.rgba import (
    colour_source_from_field_data, mean_optical_depth, opacity_factor, rgba_from_emissivity)

from .base import NebulaAlgorithm, shallow_copy_image
from .image_data import add_field_data, add_point_arrays, field_data_dict, point_array
from .properties import Property, bind, init_values, scene_values

#: The colour's properties bound to scene keys, in the panel's order: colour.exposure and
#: colour.opacity_scale are "auto" or a number, each a check box (Auto Exposure, Auto Opacity)
#: and its number
COLOUR_PROPERTIES = (
    Property("Exposure", "colour.exposure", widget="auto", flag="AutoExposure"),
    Property("WhitePoint", "colour.white_point", widget="enum"),
    Property("OpacityScale", "colour.opacity_scale", widget="auto", flag="AutoOpacity"),
    Property("Stretch", "colour.stretch", widget="enum"),
    Property("AsinhQ", "colour.asinh_q", enabled_by=("Stretch", 1)),
)


@bind(COLOUR_PROPERTIES)
class NebulaColour(NebulaAlgorithm):
    """sRGB colour of the scattered emissivity and the reference band's voxel opacity.

    Reads the arrays and field data that Nebula Light Field writes; changing exposure, white
    point or opacity re-runs only this filter, never the photon transport.
    Output: the input plus ``rgba`` (uint8 x 4) and ``rgb_linear`` (float32 x 3, exposed linear
    sRGB before the transfer curve); field data ``exposure`` and ``opacity_scale`` are the
    exposure and the opacity factor used ("auto": chosen from the data, as the light field's
    own colour chooses them).
    """

    def __init__(self):
        super().__init__(nInputPorts=1, nOutputPorts=1, inputType="vtkImageData", outputType="vtkImageData")
        init_values(self)

    def RequestInformation(self, request, inInfo, outInfo):
        """The input's geometry (copied by the executive), and pieces: every rank colours the
        whole light field (global exposure) and gives the piece asked of it."""
        from vtkmodules.vtkCommonExecutionModel import vtkAlgorithm

        outInfo.GetInformationObject(0).Set(vtkAlgorithm.CAN_PRODUCE_SUB_EXTENT(), 1)
        return 1

    def _execute(self, request, inInfo, outInfo):
        from nebula_rt.scene.model import Scene  # validation of the colour table

        Scene.from_dict(scene_values(self._values))  # the colour table's rules
        exposure = self._values["colour.exposure"]
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
            density = point_array(inp, contract.DENSITY.name())
            sigma_scale = fd.tau * float(fd.band_extinction[ref])
            sigma_ref = sigma_scale * density.astype(np.float64)
            # the light field's own way, from the density: its default colour and this one agree
            mean_tau = mean_optical_depth(density, sigma_scale)
        else:
            J = point_array(inp, contract.J.name(fd.band_names[ref])).astype(np.float64)
            alb = float(fd.band_albedo[ref])
            with np.errstate(divide="ignore", invalid="ignore"):
                sigma_ref = np.where(J > 0, emissivity[ref] / (alb * J), 0.0)
            mean_tau = mean_optical_depth(sigma_ref)
        opacity = opacity_factor(self._values["colour.opacity_scale"], mean_tau)
        rgba, used, linear = rgba_from_emissivity(
            emissivity, sigma_ref,
            wavelengths_nm=fd.band_wavelength_nm,
            band_luminosity=fd.band_luminosity,
            temperature=colour_source_from_field_data(fd),
            exposure=exposure, white_point=self._values["colour.white_point"],
            opacity_scale=opacity,
            stretch=self._values["colour.stretch"],
            asinh_q=self._values["colour.asinh_q"],
            return_linear=True,
        )
        out = vtkImageData.GetData(outInfo)
        shallow_copy_image(out, inp)
        add_point_arrays(out, {contract.RGBA.name(): rgba, contract.RGB_LINEAR.name(): linear})
        add_field_data(out, contract.LightFieldData(exposure=used, opacity_scale=opacity).to_field_data(complete=False))
        out.GetPointData().SetActiveScalars(contract.RGBA.name())
