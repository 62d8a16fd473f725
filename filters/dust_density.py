"""Nebula Dust Density: a source producing the dust density grid on the compute device."""

from __future__ import annotations

from vtkmodules.vtkCommonDataModel import vtkImageData
from vtkmodules.vtkCommonExecutionModel import vtkAlgorithm, vtkStreamingDemandDrivenPipeline

from nebula_rt import output_contract as contract
from nebula_rt.backends import get_backend
from nebula_rt.density import generate_density
from nebula_rt.limits import INT32_MAX
from nebula_rt.scene import Scene

from .base import NebulaAlgorithm, stars_from_flat
from .image_data import add_point_arrays

MODELS = ("turbulence", "uniform")


class NebulaDustDensity(NebulaAlgorithm):
    """Dust density on an nx x ny x nz grid spanning the box [0, 1]^3 (box units).

    Point data ``density`` on the voxel centres: origin 0.5/n, spacing 1/n per axis.
    Formula: thesis Eq. 3.2/3.3 (turbulence or uniform, plus each star's cubic bump, floor).
    """

    PROPERTIES = {"grid.shape": "GridShape", "dust.model": "Model", "dust.scale": "Scale",
                  "dust.offset": "Offset", "dust.floor": "Floor", "dust.density": "UniformDensity",
                  "transport.backend": "Backend", "transport.device": "Device"}

    def __init__(self):
        super().__init__(nInputPorts=0, nOutputPorts=1, outputType="vtkImageData")
        d = Scene.default()
        self._shape = tuple(d.grid.shape)
        self._model = d.dust.model
        self._scale = d.dust.scale
        self._offset = tuple(d.dust.offset)
        self._floor = d.dust.floor
        self._uniform = d.dust.density
        self._stars = [0.5, 0.5, 0.5, 1.0, 0.0, 0.01]
        self._backend = "auto"
        self._device = ""

    # -- properties (store and Modified() only; validated in RequestData) ---------------------
    def SetGridShape(self, nx, ny, nz):
        self._shape = (nx, ny, nz)
        self.Modified()

    def SetModel(self, model):
        """"turbulence" or "uniform" (or 0/1)."""
        self._model = MODELS[model] if isinstance(model, int) and 0 <= model < len(MODELS) else model
        self.Modified()

    def SetScale(self, v):
        self._scale = v
        self.Modified()

    def SetOffset(self, x, y, z):
        self._offset = (x, y, z)
        self.Modified()

    def SetFloor(self, v):
        self._floor = v
        self.Modified()

    def SetUniformDensity(self, v):
        self._uniform = v
        self.Modified()

    def SetStars(self, *values):
        """Flat list, 6 numbers per star: x, y, z, luminosity, temperature (0: none), bump radius."""
        self._stars = list(values[0]) if len(values) == 1 and hasattr(values[0], "__len__") else list(values)
        self.Modified()

    def SetBackend(self, name):
        self._backend = name
        self.Modified()

    def SetDevice(self, selector):
        self._device = selector
        self.Modified()

    # -- pipeline -----------------------------------------------------------------------------
    def scene(self) -> Scene:
        """The scene these properties describe (validated)."""
        return Scene.from_dict({
            "grid": {"shape": list(self._shape)},
            "dust": {"model": self._model, "scale": self._scale, "offset": list(self._offset),
                     "floor": self._floor, "density": self._uniform},
            "stars": stars_from_flat(self._stars),
            "transport": {"backend": self._backend, "device": self._device},
        })

    def RequestInformation(self, request, inInfo, outInfo):
        info = outInfo.GetInformationObject(0)
        try:
            nx, ny, nz = (int(n) for n in self._shape)
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
        rho = generate_density(scene, get_backend(scene.transport.backend, scene.transport.device))
        out = vtkImageData.GetData(outInfo)
        nx, ny, nz = rho.shape
        out.SetDimensions(nx, ny, nz)
        out.SetSpacing(1.0 / nx, 1.0 / ny, 1.0 / nz)
        out.SetOrigin(0.5 / nx, 0.5 / ny, 0.5 / nz)
        add_point_arrays(out, {contract.DENSITY.name(): rho})
        out.GetPointData().SetActiveScalars(contract.DENSITY.name())
