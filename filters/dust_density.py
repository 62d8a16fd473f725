"""Nebula Dust Density: a source producing the dust density grid on the compute device."""

from __future__ import annotations

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkImageData
from vtkmodules.vtkCommonExecutionModel import vtkAlgorithm, vtkStreamingDemandDrivenPipeline

from nebula_rt.pipeline import output_contract as contract
from nebula_rt.transport import scene_backend
from nebula_rt.density import generate_density
from nebula_rt.limits import INT32_MAX
from nebula_rt.scene import Scene

from .base import NebulaAlgorithm, default_star_row, stars_from_flat
from .image_data import add_field_data, add_point_arrays
from .properties import Property, bind, init_values, scene_values

#: The source's properties bound to scene keys, in the panel's order; defaults, choices and
#: ranges come from the scene schema. Stars is the source's own (a bump per star).
DUST_DENSITY_PROPERTIES = (
    Property("GridShape", "grid.shape"),
    Property("Model", "dust.model", widget="enum", only=("turbulence", "uniform")),
    Property("Scale", "dust.scale", shown_by=("Model", 0)),
    Property("Offset", "dust.offset", shown_by=("Model", 0)),
    Property("UniformDensity", "dust.density", shown_by=("Model", 1)),
    Property("Floor", "dust.floor"),
    Property("Backend", "transport.backend"),
    Property("Device", "transport.device"),
)


@bind(DUST_DENSITY_PROPERTIES)
class NebulaDustDensity(NebulaAlgorithm):
    """Dust density on an nx x ny x nz grid spanning the box [0, 1]^3 (box units).

    Point data ``density`` on the voxel centres: origin 0.5/n, spacing 1/n per axis.
    Formula: thesis Eq. 3.2/3.3 (turbulence or uniform, plus each star's cubic bump, floor).
    The setters (:data:`DUST_DENSITY_PROPERTIES`) set scene keys with the scene's defaults.
    """

    def __init__(self):
        super().__init__(nInputPorts=0, nOutputPorts=1, outputType="vtkImageData")
        init_values(self)
        self._stars = default_star_row()

    def SetStars(self, *values):
        """Flat list, a row of ``base.STAR_COLUMNS`` per star: x, y, z, luminosity, temperature (0: none), bump radius."""
        self._stars = list(values[0]) if len(values) == 1 and hasattr(values[0], "__len__") else list(values)
        self.Modified()

    # -- pipeline -----------------------------------------------------------------------------
    def scene(self) -> Scene:
        """The scene these properties describe (validated)."""
        return Scene.from_dict(scene_values(self._values, {"stars": stars_from_flat(self._stars)}))

    def RequestInformation(self, request, inInfo, outInfo):
        info = outInfo.GetInformationObject(0)
        try:
            nx, ny, nz = (int(n) for n in self._values["grid.shape"])
            if not all(2 <= n <= INT32_MAX for n in (nx, ny, nz)):
                raise ValueError
        except (TypeError, ValueError, OverflowError):
            nx = ny = nz = 2  # a bad GridShape is reported by RequestData (an extent must be int32)
        info.Set(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT(), 0, nx - 1, 0, ny - 1, 0, nz - 1)
        info.Set(vtkImageData.SPACING(), 1.0 / nx, 1.0 / ny, 1.0 / nz)
        info.Set(vtkImageData.ORIGIN(), 0.5 / nx, 0.5 / ny, 0.5 / nz)
        # pieces: the whole grid is generated (deterministic) and cropped to the piece asked
        info.Set(vtkAlgorithm.CAN_PRODUCE_SUB_EXTENT(), 1)
        return 1

    def _execute(self, request, inInfo, outInfo):
        scene = self.scene()
        self._report(0.0, "NebulaRT: generating dust density")
        rho = generate_density(scene, scene_backend(scene))
        out = vtkImageData.GetData(outInfo)
        nx, ny, nz = rho.shape
        out.SetDimensions(nx, ny, nz)
        out.SetSpacing(1.0 / nx, 1.0 / ny, 1.0 / nz)
        out.SetOrigin(0.5 / nx, 0.5 / ny, 0.5 / nz)
        add_point_arrays(out, {contract.DENSITY.name(): rho})
        add_field_data(out, contract.DensityData(stars=np.asarray(self._stars, np.float64)).to_field_data())
        out.GetPointData().SetActiveScalars(contract.DENSITY.name())
