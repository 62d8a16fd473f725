"""Nebula Sky Image: what a telescope sees along a chosen direction."""

from __future__ import annotations

import dataclasses
import re
import warnings

import numpy as np
from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase
from vtkmodules.vtkCommonDataModel import vtkImageData
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline

from nebula_rt.optics import colour_convert
from nebula_rt.pipeline import output_contract as contract
from nebula_rt.errors import NebulaWarning, SceneError
from nebula_rt.limits import check_float32_array
from nebula_rt.scene.sky_schema import G_PICTURE
from nebula_rt.pipeline.rgba import colour_source_from_field_data
from nebula_rt.scene import Scene
from nebula_rt.observe.sky import Camera, check_sky_image_memory, sky_image
from nebula_rt.transport.plan import star_band_luminosities

from nebula_rt.scene.sky_schema import validate_exposure

from .base import NebulaAlgorithm
from .image_data import add_field_data, add_point_arrays, field_data_dict, point_array
from .properties import Property, bind, init_values, scene_values

#: The sky image's properties, in the panel's order: the camera and the picture's stars and
#: exposure, bound to the sky image's own declarations (nebula_rt.scene.sky_schema, keys ``sky.*``);
#: the picture's tone curve, bound to the scene's colour keys (as the Colour filter's); and where
#: the scene is on the sky, bound to the [observer] keys, used by a calibrated image (enabled by
#: Units, the filter's own property, which the panel shows right before them)
SKY_IMAGE_PROPERTIES = (
    Property("Method", "sky.method", widget="enum"),
    Property("ViewDirection", "sky.direction"),
    Property("ViewUp", "sky.up"),
    Property("ImageSize", "sky.size"),
    Property("Extent", "sky.extent"),
    Property("IncludeStars", "sky.include_stars", widget="bool"),
    Property("Exposure", "sky.exposure", widget="auto", flag="AutoExposure"),
    Property("Stretch", "colour.stretch", widget="enum", group=G_PICTURE),
    Property("AsinhQ", "colour.asinh_q", enabled_by=("Stretch", 1), group=G_PICTURE),
    Property("Distance", "observer.distance", enabled_by=("Units", 1)),
    Property("RA", "observer.ra", enabled_by=("Units", 1)),
    Property("Dec", "observer.dec", enabled_by=("Units", 1)),
    Property("PositionAngle", "observer.position_angle", enabled_by=("Units", 1)),
    Property("PSFFWHM", "observer.psf_fwhm", enabled_by=("Units", 1)),
    Property("MagnitudeSystem", "observer.magnitude_system", widget="enum", enabled_by=("Units", 1)),
)
#: The observer's properties among them (the [observer] table's keys)
SKY_OBSERVER_PROPERTIES = tuple(p for p in SKY_IMAGE_PROPERTIES if p.key.startswith("observer."))
#: What the filter and the panel hold where the declared default is None: Distance empty (the
#: light field's scene's own [observer] table is used)
SKY_PANEL_DEFAULTS = {"observer.distance": ""}
#: The Units property: box units only, or also the calibrated arrays (nebula_rt.observe.calibrate)
SKY_UNITS = ("box units", "MJy/sr")

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
    ``SetAutoExposure`` / ``SetExposure``, ``SetStretch``, ``SetDistance``, ...) start at the
    declared defaults (:mod:`nebula_rt.scene.sky_schema` for the camera and the exposure, the scene's
    ``[colour]`` and ``[observer]`` tables for the tone curve and the sky).

    With ``SetUnits(1)`` ("MJy/sr") the image is also calibrated (:mod:`nebula_rt.observe.calibrate`,
    the ray march): ``sb_<band>`` (MJy/sr, scattered light and the stars through a Gaussian PSF)
    and ``mag_<passband>`` (AB mag/arcsec^2 in B, V, R, g, r, i), with the celestial WCS as
    FITS header text in the field data (``wcs_header``; :func:`write_fits` writes the FITS). It
    needs the stars' luminosity in L_sun (Nebula Light Field's LuminosityUnit) and a distance:
    the Distance, RA, Dec, Position Angle and PSF FWHM properties, or, while Distance is empty,
    the light field's scene's ``[observer]`` table.
    """

    #: what names the parameters no bound property sets, in messages
    PROPERTIES = {"stars[0].luminosity": "Nebula Light Field's LuminosityUnit"}

    def __init__(self):
        super().__init__(nInputPorts=1, nOutputPorts=1, inputType="vtkImageData", outputType="vtkImageData")
        init_values(self)
        self._values.update(SKY_PANEL_DEFAULTS)
        self._units = SKY_UNITS[0]

    def SetUnits(self, units):
        """"box units" (0, default) or "MJy/sr" (1): also the calibrated arrays."""
        units = SKY_UNITS[units] if isinstance(units, int) and not isinstance(units, bool) \
            and 0 <= units < len(SKY_UNITS) else units
        if units != self._units:
            self._units = units
            self.Modified()

    def GetUnits(self):
        return self._units

    #: the choices of the sky image's own enumerations (the panel's index -> the value)
    OWN_CHOICES = {"Units": SKY_UNITS}

    def inert_messages(self) -> list:
        """The observer's properties set while Distance is empty in MJy/sr: the light field's
        scene's own [observer] table places the box on the sky instead (Units' own case, box
        units, is the panel's: properties.inert_properties)."""
        if self._units != "MJy/sr" or self._values["observer.distance"] not in ("", None):
            return []
        initial = getattr(self, "_initial_values", {})
        return [f"{p.name} = {self._values[p.key]!r} has no effect: Distance is empty, so the scene's own "
                "[observer] table places the box on the sky; give a Distance to use it"
                for p in SKY_OBSERVER_PROPERTIES
                if p.key != "observer.distance" and p.key in initial and self._values[p.key] != initial[p.key]]

    def _observer(self, scene):
        """The scene placed on the sky: the Distance ... properties, or the scene's own
        [observer] table while Distance is empty."""
        d = self._values["observer.distance"]
        if d in ("", None):
            return scene
        obs = {k.split(".")[1]: self._values[k] for k in (p.key for p in SKY_OBSERVER_PROPERTIES)}
        return scene.with_overrides([f"observer.{k}={v!r}" for k, v in obs.items()])

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
        # the scene's rules of the tone curve (colour.stretch, colour.asinh_q) and of the
        # observer (an empty Distance: the light field's scene's own [observer] table)
        values = {k: v for k, v in self._values.items()
                  if not k.startswith("sky.") and not (k == "observer.distance" and v in ("", None))}
        # in box units the observer's properties place nothing (they are inert, and said so:
        # inert_properties): their values are checked on their own, with a star in physical
        # units standing in for the scene's (a calibrated image's rule on the stars is MJy/sr's)
        stand_in = None if self._units == "MJy/sr" else {
            "stars": [{"position": [0.5, 0.5, 0.5], "luminosity_lsun": 1.0, "temperature": 10000.0}]}
        Scene.from_dict(scene_values(values, stand_in))
        if self._units not in SKY_UNITS:
            raise SceneError("Units", self._units, "must be one of " + ", ".join(repr(u) for u in SKY_UNITS))
        inp = vtkImageData.GetData(inInfo[0])
        fd = contract.LightFieldData.from_field_data(
            field_data_dict(inp),
            need=("band_names", "band_wavelength_nm", "band_extinction", "tau", "scene", "band_luminosity"))
        names = fd.band_names
        check_sky_image_memory(len(names), cam.size)  # (before the arrays are gathered)
        wl, ext = fd.band_wavelength_nm, fd.band_extinction
        emissivity = np.stack([point_array(inp, contract.EMISSIVITY.name(n)) for n in names]).astype(np.float64)
        if not inp.GetPointData().HasArray(contract.DENSITY.name()):
            raise SceneError("input", "density", "the light field must carry its density array")
        rho = point_array(inp, contract.DENSITY.name()).astype(np.float64)
        sigma = fd.tau * ext[:, None, None, None] * rho[None]
        scene = Scene.loads(fd.scene)
        # the stars drawn are the scene text's: they must be the stars whose light the field
        # carries (a foreign or edited file could draw stars that lit nothing)
        traced = np.asarray(fd.band_luminosity, np.float64)
        drawn = star_band_luminosities(scene.stars, wl).sum(axis=0)
        if not np.allclose(drawn, traced, rtol=1e-9, atol=0.0):
            raise SceneError("input", "field data scene",
                             f"must hold the stars that lit the light field: their band luminosities "
                             f"{_numbers(drawn)} differ from the light field's {_numbers(traced)}")
        stars = [s.position for s in scene.stars] if include_stars else []
        slum = star_band_luminosities(scene.stars, wl) if include_stars else None
        method = self._values["sky.method"]
        peel = None
        if method == "peel-off":  # the scene traced again with the camera (its density: the input's)
            peel = self._peel_off(scene, rho, cam)
            emissivity = np.zeros_like(emissivity)  # (the march below adds the stars alone)
        elif scene.bands.polarization != "none":
            warnings.warn(f"Method ray-march has no Stokes Q and U: the scene's bands.polarization = "
                          f"'{scene.bands.polarization}' needs Method peel-off for them", NebulaWarning)
        self._report(0.9 if peel else 0.1, "NebulaRT: ray marching the sky image")
        img = sky_image(emissivity, sigma, cam, stars=stars, star_band_luminosity=slum, cancel=self._abort_requested,
                        progress=lambda done, total: self._report(0.1 + 0.8 * done / max(total, 1),
                                                                  "NebulaRT: ray marching the sky image"))
        if peel is not None:  # the peel-off's scattered light, the march's stars
            img = dataclasses.replace(img, scattered=peel.peel_image, intensity=img.direct + peel.peel_image)
        band_lum = star_band_luminosities(scene.stars, wl).sum(axis=0)
        m = colour_convert.band_to_xyz_matrix(wl, colour_source_from_field_data(fd))
        rgb8, exposure = colour_convert.sky_picture(  # (W, H, 3)
            img.intensity, img.scattered, band_lum, m, exposure, SKY_EXPOSURE_PERCENTILE,
            self._values["colour.stretch"], self._values["colour.asinh_q"])

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
        polconv = None
        if peel is not None:
            for b, n in enumerate(names):
                arrays[contract.SKY_SCATTERED_ERROR.name(n)] = peel.peel_error[b][:, :, None].astype(np.float32)
            if peel.peel_stokes is not None:
                polconv = "IAU"
                for b, n in enumerate(names):
                    for k, (val, err) in enumerate(((contract.SKY_Q, contract.SKY_Q_ERROR),
                                                    (contract.SKY_U, contract.SKY_U_ERROR),
                                                    (contract.SKY_V, contract.SKY_V_ERROR))[:peel.peel_stokes.shape[1]]):
                        arrays[val.name(n)] = peel.peel_stokes[b, k][:, :, None].astype(np.float32)
                        arrays[err.name(n)] = peel.peel_stokes_error[b, k][:, :, None].astype(np.float32)
        calibrated = {}
        if self._units == "MJy/sr":
            from nebula_rt.observe import calibrate

            sky_scene = self._observer(scene)
            calibrate.check_scene(sky_scene)
            cal = calibrate.calibrate(sky_scene, cam, img.scattered, star_band_luminosities(scene.stars, wl),
                                      calibrate.star_tau(scene, scene.bands.resolve(), rho, cam), method,
                                      scattered_error=None if peel is None else peel.peel_error,
                                      stokes=None if peel is None else peel.peel_stokes,
                                      stokes_error=None if peel is None else peel.peel_stokes_error)
            for b, n in enumerate(names):
                arrays[contract.SKY_SURFACE_BRIGHTNESS.name(n)] = cal.surface_brightness[b][:, :, None].astype(np.float32)
            for x, n in enumerate(cal.passbands):
                arrays[contract.SKY_MAG.name(n)] = cal.mag[x][:, :, None].astype(np.float32)
            if cal.stokes is not None:  # on the sky: MJy/sr, north the celestial one
                for b, n in enumerate(names):
                    arrays[contract.SKY_SB_Q.name(n)] = cal.stokes[b, 0][:, :, None].astype(np.float32)
                    arrays[contract.SKY_SB_U.name(n)] = cal.stokes[b, 1][:, :, None].astype(np.float32)
                    if cal.stokes.shape[1] > 2:
                        arrays[contract.SKY_SB_V.name(n)] = cal.stokes[b, 2][:, :, None].astype(np.float32)
            calibrated = dict(sky_units="MJy/sr", wcs_header=cal.wcs.to_header().tostring(),
                              pixel_scale_arcsec=cal.pixel_scale_arcsec, psf_fwhm_arcsec=cal.psf_fwhm_arcsec,
                              passband_names=",".join(cal.passbands), mag_system=cal.mag_system)
            self.last_calibrated = cal
        add_point_arrays(out, arrays)
        add_field_data(out, contract.SkyImageData(
            band_names=names, band_luminosity=band_lum, view_direction=cam.basis()[0], view_up=img.v_axis,
            pixel_size=img.pixel_size, exposure=exposure,
            tau_star=img.tau_star[0] if len(img.tau_star) else None, sky_method=method, polconv=polconv,
            **calibrated).to_field_data())
        out.GetPointData().SetActiveScalars(contract.SKY_RGB.name())


    def _peel_off(self, scene, rho, cam):
        """The peel-off image of ``scene`` through the light field's density ``rho`` seen by
        ``cam`` (the transport again, without J: :func:`nebula_rt.transport.trace`), with the
        panel's progress and Abort."""
        from nebula_rt.transport.request import TransportRequest, scene_backend

        request = TransportRequest.from_scene(scene, peel=cam, light_field=False)
        self._report(0.05, "NebulaRT: tracing the sky image (peel-off)")
        return request.trace(np.asarray(rho, np.float32), scene_backend(scene),
                             progress=lambda done, total: self._report(0.05 + 0.8 * done / max(total, 1),
                                                                       "NebulaRT: tracing the sky image (peel-off)"),
                             cancel=self._abort_requested)


def _numbers(values) -> str:
    """A short list of numbers for a message."""
    return "[" + ", ".join(f"{float(v):.6g}" for v in values) + "]"


def write_fits(image, path) -> None:
    """Write a calibrated sky image (Nebula Sky Image's output with Units "MJy/sr") as FITS:
    one image HDU per band (``SB_<band>``, MJy/sr), a polarized peel-off's ``Q_<band>`` and
    ``U_<band>`` (MJy/sr, IAU), and one per passband (``MAG_BESSELL_B`` ..., mag/arcsec^2 in the
    image's magnitude system), each with the celestial WCS, as
    :func:`nebula_rt.observe.calibrate.write_fits` names them (without its table of stars).

    Raises
    ------
    SceneError
        (parameter ``Units``) the image was made in box units only.
    """
    from astropy.io import fits

    from nebula_rt.observe.calibrate import MAGSYS_COMMENT, sky_hdus

    fd = contract.SkyImageData.from_field_data(field_data_dict(image), need=("band_names",))
    if fd.sky_units != "MJy/sr" or not fd.wcs_header:
        raise SceneError("Units", "box units", "a FITS sky image needs the calibrated image: set Units to MJy/sr")
    system = fd.mag_system or "AB"
    primary = {"METHOD": fd.sky_method or "ray-march", "PIXSCALE": (fd.pixel_scale_arcsec, "pixel side, arcsec"),
               "PSFFWHM": (fd.psf_fwhm_arcsec, "arcsec"), "MAGSYS": (system, MAGSYS_COMMENT[system])}
    bands = [(n, point_array(image, contract.SKY_SURFACE_BRIGHTNESS.name(n))[:, :, 0], {}) for n in fd.band_names]
    passbands = [(n, point_array(image, contract.SKY_MAG.name(n))[:, :, 0]) for n in fd.passband_names.split(",")]
    stokes = None
    if fd.polconv and image.GetPointData().HasArray(contract.SKY_SB_Q.name(fd.band_names[0])):
        specs = (contract.SKY_SB_Q, contract.SKY_SB_U) + (
            (contract.SKY_SB_V,) if image.GetPointData().HasArray(contract.SKY_SB_V.name(fd.band_names[0])) else ())
        stokes = np.stack([[point_array(image, spec.name(n))[:, :, 0] for spec in specs] for n in fd.band_names])
    sky_hdus(primary, fits.Header.fromstring(fd.wcs_header), bands, passbands, system,
             stokes=stokes).writeto(path, overwrite=True)


class NebulaSkyFitsWriter(VTKPythonAlgorithmBase):
    """Writes a calibrated sky image (Nebula Sky Image, Units "MJy/sr") to ``FileName`` as FITS
    (:func:`write_fits`): ``SetFileName``, ``SetInputConnection``, ``Write()``. A failure is
    kept in ``last_error`` and shown on VTK's output window (a writer has no output to empty)."""

    def __init__(self):
        VTKPythonAlgorithmBase.__init__(self, nInputPorts=1, nOutputPorts=0, inputType="vtkImageData")
        self._file_name = ""
        self.last_error = None

    def SetFileName(self, name):
        if name != self._file_name:
            self._file_name = name
            self.Modified()

    def GetFileName(self):
        return self._file_name

    def RequestData(self, request, inInfo, outInfo):
        self.last_error = None
        try:
            name = str(self._file_name or "")
            if not name.lower().endswith((".fits", ".fit", ".fts")):
                raise SceneError("FileName", self._file_name, "must name a .fits file")
            write_fits(vtkImageData.GetData(inInfo[0]), name)
        except Exception as exc:  # noqa: BLE001 - reported, as the NebulaRT filters report
            from vtkmodules.vtkCommonCore import vtkOutputWindow

            self.last_error = f"{type(self).__name__}: {exc}"
            vtkOutputWindow.GetInstance().DisplayErrorText(f"NebulaRT error: {self.last_error}\n")
        return 1

    def Write(self):
        """Write the input now (as VTK writers do)."""
        self.Modified()
        self.Update()
        return 1
