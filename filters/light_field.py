"""Nebula Light Field: photon transport through any vtkImageData's density array, or through
an adaptive density (a vtkHyperTreeGrid or vtkOverlappingAMR cell array, traced leaf by leaf)."""

from __future__ import annotations

import warnings

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkDataObject, vtkImageData
from vtkmodules.vtkCommonExecutionModel import vtkAlgorithm, vtkStreamingDemandDrivenPipeline

from nebula_rt.pipeline import output_contract as contract
from nebula_rt.transport import scene_backend
from nebula_rt.errors import NebulaWarning, SceneError
from nebula_rt.limits import check_float32_array
from nebula_rt.pipeline.stages import compute_light, finish_light_field
from nebula_rt.scene import Scene
from nebula_rt.scene.units import SPECTRAL_CALIBRATIONS

from .base import NebulaAlgorithm, default_reference_band, default_star_row, shallow_copy_image, stars_from_flat
from .controller import vtk_world
from .image_data import add_field_data, add_point_arrays, cell_array, field_data_dict, image_geometry, point_array
from .properties import Property, bind, init_values, scene_values

#: The light field's properties bound to scene keys, in the panel's order (density source and
#: dust optics, stars, transport, quality, device); defaults, choices and ranges come from the
#: scene schema. Stars, OverrideOptics and the density array are the filter's own.
LIGHT_FIELD_PROPERTIES = (
    Property("Tau", "dust.tau"),
    Property("BandPreset", "bands.preset"),
    Property("Albedo", "bands.albedo", enabled_by=("OverrideOptics", 1)),
    Property("G", "bands.g", enabled_by=("OverrideOptics", 1)),
    Property("Polarization", "bands.polarization", widget="enum"),
    Property("PeakPolarization", "bands.peak_polarization", enabled_by=("Polarization", 2)),
    # Mie grains of a material (a scene file may give the refractive index itself: grain_n, grain_k)
    Property("GrainMaterial", "bands.grain_material", enabled_by=("Polarization", 3)),
    Property("GrainRadiusMin", "bands.grain_radius_min", enabled_by=("Polarization", 3)),
    Property("GrainRadiusMax", "bands.grain_radius_max", enabled_by=("Polarization", 3)),
    Property("GrainSizeSlope", "bands.grain_size_slope", enabled_by=("Polarization", 3)),
    # a tabulated matrix (a file)
    Property("GrainMatrix", "bands.grain_matrix", widget="file", enabled_by=("Polarization", 4)),
    Property("Estimator", "transport.estimator", widget="enum"),
    Property("Method", "transport.method", widget="enum"),
    Property("ErrorEstimate", "transport.error_estimate", widget="enum"),
    Property("FilterRadius", "transport.filter_radius", enabled_by=("Estimator", 1)),
    Property("MaxScatterings", "transport.max_scatterings"),
    Property("Seed", "transport.seed"),
    Property("Quality", "transport.quality", widget="enum"),
    Property("TargetError", "transport.target_error", enabled_by=("Quality", 0)),
    Property("Photons", "transport.photons"),
    Property("TimeLimit", "transport.time_limit"),
    Property("Backend", "transport.backend"),
    Property("Device", "transport.device"),
    Property("BatchSize", "transport.batch_size"),
    Property("BoxLength", "grid.length"),
    Property("ParticleMass", "dust.particle_mass"),
    Property("ParticleSmoothing", "dust.particle_smoothing"),
    Property("LeafParticles", "dust.leaf_particles"),
    Property("TreeDepth", "dust.tree_depth"),
)
#: What the Stars' luminosity column is (the filter's LuminosityUnit): the scene's luminosity, or
#: the bolometric luminosity in L_sun (stars.luminosity_lsun; needs each star's temperature)
LUMINOSITY_UNITS = ("scene units", "L_sun")


@bind(LIGHT_FIELD_PROPERTIES)
class NebulaLightField(NebulaAlgorithm):
    """Trace photon packets from the stars through the input's dust density.

    The input is any vtkImageData; its selected scalar array (``SetInputArrayToProcess``, or
    ``SetDensityArrayName``; default the point array ``density``) is the dust density, one value
    per voxel. Its grid spans the box [0, 1]^3 (box units) whatever its spacing: star positions
    and the filter radius are in box units. A cell-data array gives voxels = cells.

    Or an adaptive density: a vtkHyperTreeGrid or a vtkOverlappingAMR (refining by 2) whose
    cell array (default ``density``) holds it; its bounds are the box. Or SPH particles: a
    vtkPolyData whose points carry the point arrays ``ParticleMass`` and ``ParticleSmoothing``
    (scene keys dust.particle_mass and dust.particle_smoothing, default ``mass`` and
    ``smoothing_length``), deposited on an octree over the cube of the points' bounds (its edge
    their largest extent), split while a cell holds more than ``LeafParticles`` particles down to
    ``TreeDepth`` levels (docs/adaptive_grids.md): the density is mass per box volume (box edge
    1). The packets walk the leaves and port 0 is the light field on a uniform grid of
    ``SetResolution`` voxels over the bounds (each voxel the exact-overlap average of the leaves
    it covers), the contract's arrays as for an image input; port 2 (``Light per Leaf``) is
    the light on the tree itself, a vtkHyperTreeGrid over the same bounds with per leaf
    ``J_<band>``, ``rel_error_<band>``, ``emissivity_<band>`` and ``density`` (empty for an
    image input).

    The setters (``SetTau``, ``SetPhotons``, ... : :data:`LIGHT_FIELD_PROPERTIES`) set scene keys, with the
    scene's defaults: the filter with no property set traces what a scene file with no keys
    would. Albedo and G apply with ``SetOverrideOptics(1)`` only (else each band's own).

    Output port 0: the input's arrays plus, per band, ``J_<band>``, ``emissivity_<band>``,
    ``rel_error_<band>``, ``rgba`` (the colour of the scene's defaults: auto exposure, D65,
    auto opacity, as the command line's file has it; Nebula Colour downstream changes it
    without re-tracing), and the run's field data (energies, photons, seed, scene TOML): the
    output contract of docs/design.md. Port 1 (``Stars``): a vtkPolyData with one vertex per star
    at its place in port 0's world coordinates, ``star_rgb`` and ``luminosity``
    (:mod:`nebula_rt.filters.stars`).
    """

    #: its executions reduce with the other ranks of a parallel ParaView: a failure ends the job
    distributed = True
    #: what names the parameters no bound property sets, in messages
    PROPERTIES = {"grid.shape": "input extent", "density": "density array"}
    #: the input types: a uniform density, or an adaptive one traced leaf by leaf
    INPUT_TYPES = ("vtkImageData", "vtkHyperTreeGrid", "vtkOverlappingAMR", "vtkPolyData")
    #: the scene keys that apply to a particle input only
    PARTICLE_KEYS = ("dust.particle_mass", "dust.particle_smoothing", "dust.leaf_particles", "dust.tree_depth")
    #: voxels per axis of port 0 for an adaptive input (SetResolution)
    DEFAULT_RESOLUTION = (64, 64, 64)

    def __init__(self):
        super().__init__(nInputPorts=1, nOutputPorts=3, inputType="vtkDataObject", outputType="vtkImageData")
        self._resolution = self.DEFAULT_RESOLUTION
        init_values(self)
        self._stars = default_star_row()
        # the panel's values of Albedo and G until set (the default preset's reference band)
        ref = default_reference_band()
        self._values["bands.albedo"], self._values["bands.g"] = ref.albedo, ref.g
        self._override_optics = False
        self._stars_from_input = True
        self._input_stars = None  # the stars of the input's field data (Nebula Dust Density)
        self._density_name = None
        self._luminosity_unit = LUMINOSITY_UNITS[0]
        self._spectral_types = ""
        self._spectral_calibration = SPECTRAL_CALIBRATIONS[0]
        self.last_light = None

    # -- the filter's own properties -----------------------------------------------------------
    def SetResolution(self, *values):
        """Voxels per axis of the light field on port 0 for an adaptive input (its bounds cut
        into nx x ny x nz voxels; an image input's own grid is used otherwise)."""
        values = tuple(values[0]) if len(values) == 1 and hasattr(values[0], "__len__") else tuple(values)
        if values != self._resolution:
            self._resolution = values
            self.Modified()

    def GetResolution(self) -> tuple:
        return tuple(self._resolution)

    def _checked_resolution(self) -> tuple[int, int, int]:
        from nebula_rt.limits import INT32_MAX

        r = self._resolution
        ok = len(r) == 3 and all(isinstance(v, (int, np.integer)) or (isinstance(v, float) and v.is_integer())
                                 for v in r)
        if not ok or not all(2 <= int(v) <= INT32_MAX for v in r):
            raise SceneError("Resolution", list(r), f"must be 3 whole numbers of voxels, each in [2, {INT32_MAX}]")
        return tuple(int(v) for v in r)

    def FillInputPortInformation(self, port, info):
        info.Remove(vtkAlgorithm.INPUT_REQUIRED_DATA_TYPE())
        for name in self.INPUT_TYPES:
            info.Append(vtkAlgorithm.INPUT_REQUIRED_DATA_TYPE(), name)
        return 1

    def SetStars(self, *values):
        """Flat list, 6 numbers per star: x, y, z (box units), luminosity, temperature (K, 0 =
        flat spectrum), bump radius (ignored here: the density comes from the input)."""
        self._stars = list(values[0]) if len(values) == 1 and hasattr(values[0], "__len__") else list(values)
        self._stars_set = self._stars != default_star_row()
        self.Modified()

    def SetStarsFromInput(self, flag):
        """Light the density with the stars it was made with, when the input carries them (Nebula
        Dust Density's ``stars`` field data: the stars are entered once); else, and for an input
        without stars (a ``.vti`` file), the Stars property (default on)."""
        self._stars_from_input = bool(flag)
        self.Modified()

    def stars(self) -> list:
        """The flat Stars list this filter traces (6 numbers per star)."""
        if self._stars_from_input and self._input_stars is not None and len(self._input_stars):
            if getattr(self, "_stars_set", False):
                warnings.warn("Stars has no effect: the input's stars (the density's) are traced while StarsFromInput "
                              "is 1; set StarsFromInput to 0 to trace the Stars property's", NebulaWarning)
            return [float(v) for v in self._input_stars]
        return list(self._stars)

    def SetLuminosityUnit(self, unit):
        """What the Stars' luminosity column is: "scene units" (0, default) or "L_sun" (1): the
        bolometric luminosity in solar units (``stars.luminosity_lsun``: the traced luminosity
        becomes the blackbody's part inside the bands, and a sky image can be calibrated)."""
        unit = LUMINOSITY_UNITS[unit] if isinstance(unit, int) and not isinstance(unit, bool) \
            and 0 <= unit < len(LUMINOSITY_UNITS) else unit
        if unit != self._luminosity_unit:
            self._luminosity_unit = unit
            self.Modified()

    def SetSpectralTypes(self, text):
        """MK spectral types of the stars in the Stars' order, separated by ";" ("B2V; A0 III";
        an empty entry keeps that star's temperature column; default none): each sets its
        star's temperature (scene key ``stars.spectral_type``, by SpectralCalibration), in place
        of the column."""
        text = "" if text is None else text
        if text != self._spectral_types:
            self._spectral_types = text
            self.Modified()

    def SetSpectralCalibration(self, calibration):
        """How SpectralTypes set the temperatures (scene key ``stars.spectral_calibration``, for
        every star with a type): "auto" (0, default), "pecaut-mamajek-2013" (1) or
        "de-jager-1987" (2), by name or index."""
        calibration = SPECTRAL_CALIBRATIONS[calibration] if isinstance(calibration, int) and not isinstance(
            calibration, bool) and 0 <= calibration < len(SPECTRAL_CALIBRATIONS) else calibration
        if calibration != self._spectral_calibration:
            self._spectral_calibration = calibration
            self.Modified()

    def inert_messages(self) -> list:
        """SpectralCalibration without SpectralTypes sets nothing; nor does Resolution for an
        image input (its own grid is the light field's), nor do the particle properties for an
        input that is not particles."""
        out = []
        if self._spectral_calibration != SPECTRAL_CALIBRATIONS[0] and not str(self._spectral_types).strip():
            out.append(f"SpectralCalibration = {self._spectral_calibration!r} has no effect: no star has a spectral "
                       "type (SpectralTypes is empty)")
        inp = self.GetInputDataObject(0, 0) if self.GetNumberOfInputConnections(0) else None
        if tuple(self._resolution) != self.DEFAULT_RESOLUTION and isinstance(inp, vtkImageData):
            out.append(f"Resolution = {list(self._resolution)} has no effect: the input is an image, whose own grid "
                       "the light field takes (Resolution is for a hyper tree grid, AMR or particle input)")
        if inp is not None and not inp.IsA("vtkPolyData"):
            initial = getattr(self, "_initial_values", {})
            for prop in self.BOUND_PROPERTIES:
                if prop.key in self.PARTICLE_KEYS and prop.key in initial and self._values[prop.key] != initial[prop.key]:
                    out.append(f"{prop.name} = {self._values[prop.key]!r} has no effect: the input is a "
                               f"{inp.GetClassName()}, not particles (a vtkPolyData)")
        return out

    def GetOverrideOptics(self) -> int:
        return int(self._override_optics)

    def SetOverrideOptics(self, flag):
        """Apply Albedo and G to every band (else each band's own values; default off, as a scene
        file without bands.albedo and bands.g)."""
        self._override_optics = bool(flag)
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
        self._density_chosen = bool(name)
        return (name or "density"), assoc

    def scene(self, shape) -> Scene:
        values = dict(self._values)
        if not self._override_optics:
            values.pop("bands.albedo")
            values.pop("bands.g")
        # (greyed out then; inert_properties says so)
        if values.get("bands.polarization") != "white":
            values.pop("bands.peak_polarization", None)
        if values.get("bands.polarization") != "mie":
            for key in [k for k in values if k.startswith("bands.grain_") and k != "bands.grain_matrix"]:
                values.pop(key)
        if values.get("bands.polarization") != "matrix":
            values.pop("bands.grain_matrix", None)
        stars = stars_from_flat(self.stars())
        if self._luminosity_unit not in LUMINOSITY_UNITS:
            raise SceneError("LuminosityUnit", self._luminosity_unit, "must be one of " +
                             ", ".join(repr(u) for u in LUMINOSITY_UNITS))
        if self._luminosity_unit == "L_sun":
            for star in stars:
                star["luminosity_lsun"] = star.pop("luminosity")
        if not isinstance(self._spectral_types, str):
            raise SceneError("SpectralTypes", self._spectral_types, "must be a text of MK types separated by ';'")
        types = [t.strip() for t in self._spectral_types.split(";")] if self._spectral_types.strip() else []
        if len(types) > len(stars):
            raise SceneError("SpectralTypes", self._spectral_types,
                             f"must hold at most one type per star ({len(stars)}), separated by ';'")
        for star, text in zip(stars, types):
            if text:
                star["spectral_type"] = text
                star["spectral_calibration"] = self._spectral_calibration
                star.pop("temperature", None)
        return Scene.from_dict(scene_values(values, {"grid": {"shape": list(shape)}, "dust": {"model": "uniform"},
                                                     "stars": stars}))

    # -- pipeline ------------------------------------------------------------------------------
    def RequestInformation(self, request, inInfo, outInfo):
        # port 2 (a hyper tree grid) has no extent to stream: with the image's extent copied to
        # it, a request of port 2 alone (ParaView's data information) ran the trace again
        outInfo.GetInformationObject(2).Set(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT(), 0, -1, 0, -1, 0, -1)
        src = inInfo[0].GetInformationObject(0)
        dst = outInfo.GetInformationObject(0)
        if src is None:
            return 1  # no input information: RequestData reports the missing input
        if not isinstance(src.Get(vtkDataObject.DATA_OBJECT()), vtkImageData):
            # an adaptive input: the grid of Resolution (its spacing and origin, from the
            # input's bounds, are set in RequestData)
            try:
                shape = self._checked_resolution()
            except SceneError:
                return 1  # RequestData reports it
            dst.Set(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT(), 0, shape[0] - 1, 0, shape[1] - 1, 0, shape[2] - 1)
            dst.Set(vtkAlgorithm.CAN_PRODUCE_SUB_EXTENT(), 1)
            return 1
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
        if inp is None:
            return self._execute_adaptive(request, inInfo[0].GetInformationObject(0).Get(vtkDataObject.DATA_OBJECT()),
                                          out, outInfo)
        name, assoc = self._selected_array()
        cells = assoc == vtkDataObject.FIELD_ASSOCIATION_CELLS
        try:
            rho = cell_array(inp, name) if cells else point_array(inp, name)
        except KeyError as exc:
            if not self._density_chosen:
                # e.g. a filter made on an input that had not run: ParaView then leaves its
                # Density Array empty, and the input has no array named "density"
                attrs = inp.GetCellData() if cells else inp.GetPointData()
                names = [attrs.GetArrayName(i) for i in range(attrs.GetNumberOfArrays())]
                raise SceneError("density array", None,
                                 "none was chosen and the input has no array named 'density': choose one "
                                 f"(Density Array) of {', '.join(repr(n) for n in names) or 'no arrays'}") from None
            raise SceneError("density array", name, f"must be a {'cell' if cells else 'point'} array of the input ({exc.args[0]})") from None
        if rho.ndim != 3:
            raise SceneError("density array", name, f"must have one component (found shape {rho.shape})")
        rho = rho.astype(np.float64)
        if not np.all(np.isfinite(rho)):
            raise SceneError("density array", name, "must be finite (found NaN or infinity)")
        if np.any(rho < 0):
            raise SceneError("density array", name, f"must be >= 0 (minimum {rho.min()!r})")
        check_float32_array("density array", name, rho, "density values")  # the device's density is float32
        fd = field_data_dict(inp)
        self._input_stars = contract.DensityData.from_field_data(fd).stars if "stars" in fd else None
        scene = self.scene(rho.shape)
        backend = scene_backend(scene)
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
            for key in contract.field_specs(contract.DensityData).values():  # the scene TOML has the stars
                out.GetFieldData().RemoveArray(key.key)
        arrays = light.point_arrays()
        if name != contract.DENSITY.name() or cells:
            arrays.pop(contract.DENSITY.name())  # the input's own array carries it
        add_point_arrays(out, arrays)
        add_field_data(out, light.field_data())
        active = contract.RGBA.name() if light.rgba is not None else contract.J.name(light.bands[light.reference_band].name)
        out.GetPointData().SetActiveScalars(active)
        self._stars_output(request, outInfo, light, out)
        self._tree_output(request, outInfo, None, None, None)
        self.last_light = light

    def _execute_adaptive(self, request, inp, out, outInfo):
        """An adaptive input: its octree traced leaf by leaf, the light field on the grid of
        Resolution over the input's bounds, and on the tree itself on port 2."""
        from nebula_rt.filters.adaptive import octree_from_amr, octree_from_htg

        name, _ = self._selected_array()
        kind = inp.GetClassName() if inp is not None else "nothing"
        shape = self._checked_resolution()
        fd = field_data_dict(inp) if kind == "vtkHyperTreeGrid" else {}
        self._input_stars = contract.DensityData.from_field_data(fd).stars if "stars" in fd else None
        scene = self.scene(shape)
        b = [0.0] * 6
        if kind == "vtkPolyData":
            tree, b = self._particle_tree(inp, scene)
        else:
            try:
                if kind == "vtkHyperTreeGrid":
                    tree = octree_from_htg(inp, name)
                elif kind == "vtkOverlappingAMR":
                    tree = octree_from_amr(inp, name)
                else:
                    raise SceneError("Input", kind, "must be a vtkImageData, vtkHyperTreeGrid, vtkOverlappingAMR or "
                                                    "vtkPolyData (particles)")
            except ValueError as exc:
                raise SceneError("density array", name, f"the adaptive input cannot be traced: {exc}") from None
            inp.GetBounds(b)  # (an AMR hierarchy's GetBounds fills an array)
        backend = scene_backend(scene)
        self._report(0.0, "NebulaRT: tracing")
        res, J, rel = compute_light(scene, tree, backend, progress=self._progress_callback("traced"),
                                    cancel=self._abort_requested, comm=vtk_world())
        lum = np.asarray(res.band_luminosity, np.float64)
        colour = len(scene.bands.resolve()) > 1 and bool(np.all(np.isfinite(lum) & (lum > 0)))
        light = finish_light_field(scene, tree, res, colour=colour)
        spacing = [(b[2 * a + 1] - b[2 * a]) / shape[a] for a in range(3)]
        out.SetDimensions(*shape)
        out.SetSpacing(*spacing)
        out.SetOrigin(*(b[2 * a] + 0.5 * spacing[a] for a in range(3)))  # points at the voxels' centres
        add_point_arrays(out, light.point_arrays())
        add_field_data(out, light.field_data())
        active = contract.RGBA.name() if light.rgba is not None else contract.J.name(light.bands[light.reference_band].name)
        out.GetPointData().SetActiveScalars(active)
        self._stars_output(request, outInfo, light, out)
        self._tree_output(request, outInfo, tree, light, b)
        self.last_light = light

    def _particle_tree(self, poly, scene):
        """(octree, bounds) of a particle input: its points and their ParticleMass and
        ParticleSmoothing arrays, over the cube of the points' bounds (from their low corner, of
        edge their largest extent), deposited by
        :func:`nebula_rt.density.particles.particles_on_tree`."""
        from nebula_rt.density.particles import particles_on_tree
        from nebula_rt.filters.adaptive import particles_of_polydata

        dust = scene.dust
        try:
            pos, mass, h = particles_of_polydata(poly, dust.particle_mass, dust.particle_smoothing)
        except ValueError as exc:
            raise SceneError("Input", "vtkPolyData", f"the particles cannot be read: {exc}") from None
        lo = pos.min(axis=0)
        edge = float((pos.max(axis=0) - lo).max())
        if not (np.isfinite(edge) and edge > 0.0):
            raise SceneError("Input", "vtkPolyData", f"the particles' positions must be finite and span a box "
                                                     f"(their extent is {edge!r})")
        try:
            tree = particles_on_tree((pos - lo) / edge, mass, h / edge, dust.leaf_particles, dust.tree_depth)
        except ValueError as exc:
            raise SceneError("Input", "vtkPolyData", f"the particles cannot be deposited: {exc}") from None
        return tree, [lo[0], lo[0] + edge, lo[1], lo[1] + edge, lo[2], lo[2] + edge]

    # -- the Stars and Light per Leaf ports ------------------------------------------------------
    def FillOutputPortInformation(self, port, info):
        info.Set(vtkDataObject.DATA_TYPE_NAME(), ("vtkImageData", "vtkPolyData", "vtkHyperTreeGrid")[port])
        return 1

    @staticmethod
    def _tree_output(request, outInfo, tree, light, bounds) -> None:
        """Port 2: the light on the tree (:func:`nebula_rt.filters.tree_light.tree_light_htg`,
        over the input's bounds) on piece 0 only, as the stars; empty for an image input."""
        from vtkmodules.vtkCommonDataModel import vtkHyperTreeGrid

        from .controller import vtk_world
        from .tree_light import tree_light_htg

        target = vtkHyperTreeGrid.GetData(outInfo.GetInformationObject(2))
        if target is None:
            return
        info = outInfo.GetInformationObject(2)
        key = vtkStreamingDemandDrivenPipeline.UPDATE_PIECE_NUMBER()
        piece = info.Get(key) if info.Has(key) else vtk_world().rank
        if tree is None or piece:
            target.Initialize()
            return
        target.ShallowCopy(tree_light_htg(tree, light, tuple(float(x) for x in bounds)))

    @staticmethod
    def _stars_output(request, outInfo, light, image) -> None:
        """Port 1: the stars (on piece 0 only: in a parallel ParaView every rank holds the
        whole field, and the stars are drawn once). The piece is the one asked of the port
        whose request runs this execution, else of the other port, else this process's rank:
        a pvserver's ranks execute for the image's request, while port 1 still holds piece 0
        on every rank (each rank made the stars, so a fetch had them once per rank)."""
        from vtkmodules.vtkCommonDataModel import vtkPolyData
        from vtkmodules.vtkCommonExecutionModel import vtkExecutive

        from .controller import vtk_world
        from .stars import star_points

        info = outInfo.GetInformationObject(1)
        target = vtkPolyData.GetData(info)
        key = vtkStreamingDemandDrivenPipeline.UPDATE_PIECE_NUMBER()
        frm = vtkExecutive.FROM_OUTPUT_PORT()
        first = request.Get(frm) if request is not None and request.Has(frm) else 1
        asked = [outInfo.GetInformationObject(p) for p in ((0, 1) if first == 0 else (1, 0))]
        piece = next((i.Get(key) for i in asked if i.Has(key)), None)
        if piece is None:
            piece = vtk_world().rank
        if piece:
            target.Initialize()
            return
        dims, spacing, origin = image_geometry(image)
        target.ShallowCopy(star_points(light, dims, spacing, origin))
