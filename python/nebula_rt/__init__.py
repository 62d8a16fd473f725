"""NebulaRT: radiative transfer of starlight in reflection nebulae.

The library (this package) imports no VTK, pyvista or ParaView; its domains are subpackages
(docs/design.md, "Where things live"): ``scene`` (what a user declares), ``optics`` (bands,
dust, colour), ``density``, ``backends`` (the devices and the kernels' parameters),
``transport`` (packets -> light, with errors), ``pipeline`` (stages, outputs), ``observe``
(sky images, calibration, comparisons, fits) and ``cli``. The VTK layer is
``nebula_rt.filters``.

The modules' earlier flat names (``nebula_rt.bands``, ``nebula_rt.calibrate``,
``nebula_rt.fit``...) are kept for users' scripts: :data:`MOVED` maps each to its home, and
importing the old name gives the same module object.
"""

import importlib
import importlib.abc
import importlib.util
import sys
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _distribution_version

from .errors import (
    AccumulatorOverflowError,
    BackendUnavailableError,
    CancelledError,
    NebulaError,
    NebulaWarning,
    SceneError,
)

#: The modules' earlier flat names -> their homes (``import nebula_rt.bands`` gives
#: ``nebula_rt.optics.bands`` itself, so a monkeypatch or an ``isinstance`` sees one module)
MOVED = {
    "bands": "optics.bands",
    "dust_tables": "optics.dust_tables",
    "colour_convert": "optics.colour_convert",
    "units": "scene.units",
    "schema": "scene.schema",
    "sky_schema": "scene.sky_schema",
    "kernel_params": "backends.kernel_params",
    "kernel_source": "backends.kernel_source",
    "parallel": "backends.parallel",
    "transport_request": "transport.request",
    "importance": "transport.importance",
    "tails": "transport.tails",
    "line_of_sight": "transport.line_of_sight",
    "filtering": "transport.filtering",
    "filtering_opencl": "transport.filtering_opencl",
    "resources": "transport.resources",
    "postprocess": "transport.finish",
    "analytic": "transport.analytic",
    "output_contract": "pipeline.output_contract",
    "outputs": "pipeline.outputs",
    "io_vti": "pipeline.io_vti",
    "sky": "observe.sky",
    "calibrate": "observe.calibrate",
    "comparison": "observe.comparison",
    "observed_tables": "observe.observed_tables",
    "observed_images": "observe.observed_images",
    "image_compare": "observe.image_compare",
    "fit": "observe.fit",
    "cli_fit": "cli.fit",
    "cli_image": "cli.image",
}


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds ``nebula_rt.<old name>`` and hands out the module at its home (no copy, no shim
    file): the import system then binds the old name to the same module object."""

    def find_spec(self, fullname, path=None, target=None):
        package, _, name = fullname.rpartition(".")
        if package == __name__ and name in MOVED:
            return importlib.util.spec_from_loader(fullname, self)
        return None

    def create_module(self, spec):
        return importlib.import_module(f"{__name__}.{MOVED[spec.name.rpartition('.')[2]]}")

    def exec_module(self, module):
        pass  # the home module ran already


if not any(isinstance(f, _MovedModules) for f in sys.meta_path):
    sys.meta_path.append(_MovedModules())

try:  # declared once, in pyproject.toml
    __version__ = _distribution_version("nebula-rt")
except PackageNotFoundError:  # the sources on sys.path without an install
    __version__ = "0+unknown"

__all__ = [
    "AccumulatorOverflowError",
    "BackendUnavailableError",
    "CancelledError",
    "MOVED",
    "NebulaError",
    "NebulaWarning",
    "SceneError",
    "__version__",
]
