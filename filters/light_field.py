"""Nebula Light Field: photon transport through any vtkImageData's density array."""

from __future__ import annotations

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkDataObject, vtkImageData
from vtkmodules.vtkCommonExecutionModel import vtkAlgorithm, vtkStreamingDemandDrivenPipeline

from nebula_rt import output_contract as contract
from nebula_rt.backends import get_backend
from nebula_rt.errors import SceneError
from nebula_rt.limits import check_float32_array
from nebula_rt.pipeline import compute_light, finish_light_field
from nebula_rt.scene import Scene

from .base import NebulaAlgorithm, shallow_copy_image, stars_from_flat
from .controller import vtk_world
from .image_data import add_field_data, add_point_arrays, cell_array, image_geometry, point_array

ESTIMATORS = ("track-length", "collision-filter")
BACKENDS = ("auto", "opencl", "cuda")


#: ParaView's Quality enumeration ("custom" = no preset)
QUALITY_NAMES = ("custom", "preview", "balanced", "reference")


def _enum(value, options):
    return options[value] if isinstance(value, int) and 0 <= value < len(options) else value


class NebulaLightField(NebulaAlgorithm):
    """Trace photon packets from the stars through the input's dust density.

    The input is any vtkImageData; its selected scalar array (``SetInputArrayToProcess``, or
    ``SetDensityArrayName``; default the point array ``density``) is the dust density, one value
    per voxel. Its grid spans the box [0, 1]^3 (box units) whatever its spacing: star positions
    and the filter radius are in box units. A cell-data array gives voxels = cells.

    Output port 0: the input's arrays plus, per band, ``J_<band>``, ``emissivity_<band>``,
    ``rel_error_<band>``, ``rgba`` (the colour of the scene's defaults: auto exposure, D65,
    opacity scale 1, as the command line's file has it; Nebula Colour downstream changes it
    without re-tracing), and the run's field data (energies, photons, seed, scene TOML): the
    output contract of DESIGN.md. Port 1 (``Stars``): a vtkPolyData with one vertex per star
    at its place in port 0's world coordinates, ``star_rgb`` and ``luminosity``
    (:mod:`nebula_rt.filters.stars`).
    """

    #: its executions reduce with the other ranks of a parallel ParaView: a failure ends the job
    distributed = True

    PROPERTIES = {"dust.tau": "Tau", "bands.preset": "BandPreset", "bands.albedo": "Albedo", "bands.g": "G",
                  "transport.photons": "Photons", "transport.estimator": "Estimator",
                  "transport.filter_radius": "FilterRadius", "transport.max_scatterings": "MaxScatterings",
                  "transport.seed": "Seed", "transport.backend": "Backend", "transport.device": "Device",
                  "transport.batch_size": "BatchSize", "transport.quality": "Quality",
                  "transport.target_error": "TargetError", "grid.shape": "input extent",
                  "density": "density array"}

    def __init__(self):
        super().__init__(nInputPorts=1, nOutputPorts=2, inputType="vtkImageData", outputType="vtkImageData")
        d = Scene.default()
        self._stars = [0.5, 0.5, 0.5, 1.0, 0.0, 0.0]
        self._preset = d.bands.preset
        self._override_optics = True
        self._albedo = 0.6
        self._g = 0.6
        self._tau = d.dust.tau
        self._photons = 100_000
        self._estimator = d.transport.estimator
        self._filter_radius = d.transport.filter_radius
        self._max_scatterings = d.transport.max_scatterings
        self._seed = d.transport.seed
        self._backend = "auto"
        self._device = ""
        self._batch_size = 0
        self._quality = ""
        self._target_error = 0.0
        self._density_name = None
        self.last_light = None

    # -- properties ----------------------------------------------------------------------------
    def SetStars(self, *values):
        """Flat list, 6 numbers per star: x, y, z (box units), luminosity, temperature (K, 0 =
        flat spectrum), bump radius (ignored here: the density comes from the input)."""
        self._stars = list(values[0]) if len(values) == 1 and hasattr(values[0], "__len__") else list(values)
        self.Modified()

    def SetBandPreset(self, name):
        self._preset = name
        self.Modified()

    def SetOverrideOptics(self, flag):
        """Apply Albedo and G to every band (else the preset's own values)."""
        self._override_optics = bool(flag)
        self.Modified()

    def SetAlbedo(self, v):
        self._albedo = v
        self.Modified()

    def SetG(self, v):
        self._g = v
        self.Modified()

    def SetTau(self, v):
        """Optical depth across one box edge at density 1 in the reference band."""
        self._tau = v
        self.Modified()

    def SetPhotons(self, n):
        self._photons = n
        self.Modified()

    def SetQuality(self, name):
        """Quality preset ("" or "custom": Photons and TargetError as set; "preview", "balanced",
        "reference": a target error with a photon budget, see nebula_rt.scene.QUALITY_PRESETS),
        by name or index in that order."""
        name = _enum(name, QUALITY_NAMES)
        self._quality = "" if name == "custom" else name
        self.Modified()

    def SetTargetError(self, e):
        """0: trace Photons packets; in (0, 1): trace until the lit region's relative error is at
        most this, with Photons as the budget."""
        self._target_error = e
        self.Modified()

    def SetEstimator(self, name):
        self._estimator = _enum(name, ESTIMATORS)
        self.Modified()

    def SetFilterRadius(self, r):
        self._filter_radius = r
        self.Modified()

    def SetMaxScatterings(self, n):
        self._max_scatterings = n
        self.Modified()

    def SetSeed(self, s):
        self._seed = s
        self.Modified()

    def SetBackend(self, name):
        self._backend = _enum(name, BACKENDS)
        self.Modified()

    def SetDevice(self, selector):
        self._device = selector
        self.Modified()

    def SetBatchSize(self, n):
        self._batch_size = n
        self.Modified()

    def SetDensityArrayName(self, name):
        """Plain-VTK shortcut for ``SetInputArrayToProcess(0, 0, 0, POINTS, name)``."""
        self.SetInputArrayToProcess(0, 0, 0, vtkDataObject.FIELD_ASSOCIATION_POINTS, name)

    # -- helpers -------------------------------------------------------------------------------
    def _selected_array(self):
        """(name, association) of the density array; default the point array "density"."""
        info = self.GetInputArrayInformation(0)
        name = info.Get(vtkDataObject.FIELD_NAME()) if info is not None and info.Has(vtkDataObject.FIELD_NAME()) else None
        assoc = vtkDataObject.FIELD_ASSOCIATION_POINTS
        if info is not None and info.Has(vtkDataObject.FIELD_ASSOCIATION()):
            assoc = info.Get(vtkDataObject.FIELD_ASSOCIATION())
        return (name or "density"), assoc

    def scene(self, shape) -> Scene:
        bands = {"preset": self._preset}
        if self._override_optics:
            bands.update(albedo=self._albedo, g=self._g)
        return Scene.from_dict({
            "grid": {"shape": list(shape)},
            "dust": {"model": "uniform", "tau": self._tau},
            "stars": stars_from_flat(self._stars),
            "bands": bands,
            "transport": {"photons": self._photons, "estimator": self._estimator,
                          "filter_radius": self._filter_radius, "max_scatterings": self._max_scatterings,
                          "seed": self._seed, "backend": self._backend, "device": self._device,
                          "batch_size": self._batch_size, "quality": self._quality,
                          "target_error": self._target_error},
        })

    # -- pipeline ------------------------------------------------------------------------------
    def RequestInformation(self, request, inInfo, outInfo):
        src = inInfo[0].GetInformationObject(0)
        dst = outInfo.GetInformationObject(0)
        if src is None or not src.Has(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT()):
            return 1  # no input information: RequestData reports the missing input
        ext = list(src.Get(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT()))
        spacing = list(src.Get(vtkImageData.SPACING()) or (1.0, 1.0, 1.0))
        origin = list(src.Get(vtkImageData.ORIGIN()) or (0.0, 0.0, 0.0))
        _, assoc = self._selected_array()
        if assoc == vtkDataObject.FIELD_ASSOCIATION_CELLS:
            # voxels are the input's cells: one point per cell centre
            for ax in range(3):
                if ext[2 * ax + 1] > ext[2 * ax]:
                    ext[2 * ax + 1] -= 1
                    origin[ax] += 0.5 * spacing[ax]
        dst.Set(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT(), *ext)
        dst.Set(vtkImageData.SPACING(), *spacing)
        dst.Set(vtkImageData.ORIGIN(), *origin)
        # every rank computes the whole field and gives the piece asked of it (base.RequestData)
        dst.Set(vtkAlgorithm.CAN_PRODUCE_SUB_EXTENT(), 1)
        return 1

    def _execute(self, request, inInfo, outInfo):
        inp = vtkImageData.GetData(inInfo[0])
        out = vtkImageData.GetData(outInfo)
        name, assoc = self._selected_array()
        cells = assoc == vtkDataObject.FIELD_ASSOCIATION_CELLS
        try:
            rho = cell_array(inp, name) if cells else point_array(inp, name)
        except KeyError as exc:
            raise SceneError("density array", name, f"must be a {'cell' if cells else 'point'} array of the input ({exc.args[0]})") from None
        if rho.ndim != 3:
            raise SceneError("density array", name, f"must have one component (found shape {rho.shape})")
        rho = rho.astype(np.float64)
        if not np.all(np.isfinite(rho)):
            raise SceneError("density array", name, "must be finite (found NaN or infinity)")
        if np.any(rho < 0):
            raise SceneError("density array", name, f"must be >= 0 (minimum {rho.min()!r})")
        check_float32_array("density array", name, rho, "density values")  # the device's density is float32
        scene = self.scene(rho.shape)
        backend = get_backend(scene.transport.backend, scene.transport.device)
        self._report(0.0, "NebulaRT: tracing")
        # in ParaView's parallel engine every rank has the whole density (RequestUpdateExtent),
        # traces a share of the packets, and holds the one-rank result after the reductions
        res, J, rel = compute_light(scene, rho.astype(np.float32), backend, on_device=True,
                                    progress=self._progress_callback("traced"), cancel=self._abort_requested,
                                    comm=vtk_world())
        # the colour of the scene's defaults, as the command line's file has it; not for one
        # band (no colour to show) nor where a band has no starlight (colours are nebula/star
        # ratios per band): Nebula Colour downstream says why
        lum = np.asarray(res.band_luminosity, np.float64)
        colour = len(scene.bands.resolve()) > 1 and bool(np.all(np.isfinite(lum) & (lum > 0)))
        light = finish_light_field(scene, rho.astype(np.float32), res, J, rel, colour=colour)
        if cells:
            dims, spacing, origin = image_geometry(inp)
            out.SetDimensions(*rho.shape)
            out.SetSpacing(*spacing)
            out.SetOrigin(*(o + 0.5 * s for o, s in zip(origin, spacing)))
            add_point_arrays(out, {name: rho.astype(np.float32)})
        else:
            shallow_copy_image(out, inp)
        arrays = light.point_arrays()
        if name != contract.DENSITY.name() or cells:
            arrays.pop(contract.DENSITY.name())  # the input's own array carries it
        add_point_arrays(out, arrays)
        add_field_data(out, light.field_data())
        active = contract.RGBA.name() if light.rgba is not None else contract.J.name(light.bands[light.reference_band].name)
        out.GetPointData().SetActiveScalars(active)
        self._stars_output(outInfo, light, out)
        self.last_light = light

    # -- the Stars port ------------------------------------------------------------------------
    def FillOutputPortInformation(self, port, info):
        info.Set(vtkDataObject.DATA_TYPE_NAME(), "vtkPolyData" if port == 1 else "vtkImageData")
        return 1

    @staticmethod
    def _stars_output(outInfo, light, image) -> None:
        """Port 1: the stars (on piece 0 only: in a parallel ParaView every rank holds the
        whole field, and the stars are drawn once)."""
        from vtkmodules.vtkCommonDataModel import vtkPolyData

        from .stars import star_points

        info = outInfo.GetInformationObject(1)
        target = vtkPolyData.GetData(info)
        piece = info.Get(vtkStreamingDemandDrivenPipeline.UPDATE_PIECE_NUMBER()) \
            if info.Has(vtkStreamingDemandDrivenPipeline.UPDATE_PIECE_NUMBER()) else 0
        if piece:
            target.Initialize()
            return
        dims, spacing, origin = image_geometry(image)
        target.ShallowCopy(star_points(light, dims, spacing, origin))
