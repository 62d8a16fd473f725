"""NebulaRT: radiative transfer of starlight in reflection nebulae.

The library (this package) imports no VTK, pyvista or ParaView. The VTK layer is
``nebula_rt.filters``: the VTK algorithms, ``.vti`` files (``nebula_rt.filters.vti``) and PNG
rendering (``nebula_rt.filters.render``). The names and types of the outputs' arrays and field
data are declared in ``nebula_rt.output_contract``.
"""

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

try:  # declared once, in pyproject.toml
    __version__ = _distribution_version("nebula-rt")
except PackageNotFoundError:  # the sources on sys.path without an install
    __version__ = "0+unknown"

__all__ = [
    "AccumulatorOverflowError",
    "BackendUnavailableError",
    "CancelledError",
    "NebulaError",
    "NebulaWarning",
    "SceneError",
    "__version__",
]
