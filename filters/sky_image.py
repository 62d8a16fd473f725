"""Nebula Sky Image: what a telescope sees along a chosen direction."""

from __future__ import annotations

import re

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkImageData
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline

from nebula_rt import colour_convert
from nebula_rt import output_contract as contract
from nebula_rt.errors import SceneError
from nebula_rt.limits import check_float32_array
from nebula_rt.pipeline import colour_source_from_field_data
from nebula_rt.scene import Scene
from nebula_rt.sky import Camera, sky_image
from nebula_rt.transport import star_band_luminosities

from nebula_rt.sky_schema import validate_exposure

from .base import NebulaAlgorithm
from .image_data import add_field_data, add_point_arrays, field_data_dict, point_array
from .properties import Property, bind, init_values

#: The sky image's properties, bound to its declarations (nebula_rt.sky_schema), in the
#: panel's order: the camera, then the picture
SKY_IMAGE_PROPERTIES = (
    Property("ViewDirection", "sky.direction"),
    Property("ViewUp", "sky.up"),
    Property("ImageSize", "sky.size"),
    Property("Extent", "sky.extent"),
    Property("IncludeStars", "sky.include_stars", widget="bool"),
    Property("Exposure", "sky.exposure", widget="auto", flag="AutoExposure"),
)

#: Auto exposure of the sky image: this percentile of the scattered light's max colour
#: component (among lit pixels) maps to full scale; star pixels saturate.
SKY_EXPOSURE_PERCENTILE = 99.0


@bind(SKY_IMAGE_PROPERTIES)
class NebulaSkyImage(NebulaAlgorithm):
    """Orthographic image of the nebula seen from far away along ``ViewDirection``.

    Per band, the scattered emissivity is integrated along each pixel's ray with that band's
    extinction, and each star adds its attenuated direct light to the pixel it falls in.
    Output: a W x H x 1 vtkImageData (spacing = pixel size in box units) with ``I_<band>``
    (total), ``scattered_<band>`` (float32; luminosity per box-unit area per steradian),
    ``relative_<band>`` (surface brightness relative to the star, I_b / (L_b / 4 pi): the star's
    luminosity per steradian in the band as the unit, per box-unit^2 of sky) and
    ``rgb`` (uint8 x 3, sRGB through the same band -> XYZ matrix as the volume colours).
    Field data: the camera, ``tau_star_<band>`` (optical depth from the first star to the
    observer), ``exposure``.

    The setters (:data:`SKY_IMAGE_PROPERTIES`: ``SetViewDirection``, ``SetImageSize``, ...,
    ``SetAutoExposure`` / ``SetExposure``) start at the declared defaults
    (:mod:`nebula_rt.sky_schema`).
    """

    def __init__(self):
        super().__init__(nInputPorts=1, nOutputPorts=1, inputType="vtkImageData", outputType="vtkImageData")
        init_values(self)

    def _camera(self) -> Camera:
        v = self._values
        # whole numbers given as floats (ParaView's int properties may arrive so) are pixels; 16.5 is not
        size = tuple(int(x) if isinstance(x, float) and x.is_integer() else x for x in v["sky.size"])
        try:
            return Camera(direction=tuple(v["sky.direction"]), up=tuple(v["sky.up"]), size=size,
                          extent=v["sky.extent"])
        except (ValueError, TypeError) as exc:
            # "Camera.size must be ..., got ...": the key of the field, and what is allowed
            m = re.match(r"Camera\.(\w+) (.*?)(?:, got .*)?$", str(exc))
            if m is None or f"sky.{m.group(1)}" not in v:
                raise SceneError("camera", (v["sky.direction"], v["sky.up"], v["sky.size"], v["sky.extent"]),
                                 str(exc)) from None
            key = f"sky.{m.group(1)}"
            raise SceneError(key, v[key], m.group(2)) from None

    def RequestInformation(self, request, inInfo, outInfo):
        try:
            cam = self._camera()
        except SceneError:
            return 1  # reported in RequestData
        w, h = cam.size
        info = outInfo.GetInformationObject(0)
        info.Set(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT(), 0, w - 1, 0, h - 1, 0, 0)
        info.Set(vtkImageData.SPACING(), cam.pixel_size, cam.pixel_size, 1.0)
        info.Set(vtkImageData.ORIGIN(), 0.5 * cam.pixel_size, 0.5 * cam.pixel_size, 0.0)
        return 1

    def _execute(self, request, inInfo, outInfo):
        cam = self._camera()
        exposure = validate_exposure(self._values["sky.exposure"])
        include_stars = bool(self._values["sky.include_stars"])
        inp = vtkImageData.GetData(inInfo[0])
        fd = contract.LightFieldData.from_field_data(
            field_data_dict(inp), need=("band_names", "band_wavelength_nm", "band_extinction", "tau", "scene"))
        names = fd.band_names
        wl, ext = fd.band_wavelength_nm, fd.band_extinction
        emissivity = np.stack([point_array(inp, contract.EMISSIVITY.name(n)) for n in names]).astype(np.float64)
        if not inp.GetPointData().HasArray(contract.DENSITY.name()):
            raise SceneError("input", "density", "the light field must carry its density array")
        rho = point_array(inp, contract.DENSITY.name()).astype(np.float64)
        sigma = fd.tau * ext[:, None, None, None] * rho[None]
        scene = Scene.loads(fd.scene)
        stars = [s.position for s in scene.stars] if include_stars else []
        slum = star_band_luminosities(scene.stars, wl) if include_stars else None
        self._report(0.1, "NebulaRT: ray marching the sky image")
        img = sky_image(emissivity, sigma, cam, stars=stars, star_band_luminosity=slum)
        band_lum = star_band_luminosities(scene.stars, wl).sum(axis=0)
        m = colour_convert.band_to_xyz_matrix(wl, colour_source_from_field_data(fd))
        ratio = img.intensity / band_lum[:, None, None]
        rgb = colour_convert.gamut_map(colour_convert.xyz_to_linear_srgb(np.tensordot(ratio, m, axes=([0], [1]))))
        if exposure == "auto":
            scat = colour_convert.xyz_to_linear_srgb(
                np.tensordot(img.scattered / band_lum[:, None, None], m, axes=([0], [1])))
            exposure = colour_convert.auto_exposure(scat, percentile=SKY_EXPOSURE_PERCENTILE)
        rgb8 = colour_convert.encode_srgb(rgb, exposure)  # (W, H, 3)

        out = vtkImageData.GetData(outInfo)
        w, h = cam.size
        out.SetDimensions(w, h, 1)
        out.SetSpacing(cam.pixel_size, cam.pixel_size, 1.0)
        out.SetOrigin(0.5 * cam.pixel_size, 0.5 * cam.pixel_size, 0.0)
        # float32 outputs: the star's pixel (L / (4 pi pixel^2)) is the brightest
        check_float32_array("sky.size", list(cam.size), img.intensity * (4.0 * np.pi / band_lum.min()),
                            "the sky image's intensities (relative ones included)", underflow=False)
        arrays = {}
        for b, n in enumerate(names):
            arrays[contract.SKY_INTENSITY.name(n)] = img.intensity[b][:, :, None].astype(np.float32)
            arrays[contract.SKY_SCATTERED.name(n)] = img.scattered[b][:, :, None].astype(np.float32)
            # surface brightness relative to the star: I_b / (L_b / 4 pi), per box-unit^2 of sky
            arrays[contract.SKY_RELATIVE.name(n)] = (
                (img.intensity[b] * (4.0 * np.pi / band_lum[b]))[:, :, None].astype(np.float32))
        arrays[contract.SKY_RGB.name()] = rgb8[:, :, None, :]
        add_point_arrays(out, arrays)
        add_field_data(out, contract.SkyImageData(
            band_names=names, band_luminosity=band_lum, view_direction=cam.basis()[0], view_up=img.v_axis,
            pixel_size=img.pixel_size, exposure=exposure,
            tau_star=img.tau_star[0] if len(img.tau_star) else None).to_field_data())
        out.GetPointData().SetActiveScalars(contract.SKY_RGB.name())
