"""NebulaRT: radiative transfer of starlight in reflection nebulae.

The library core (this package) never imports VTK or ParaView; the modules
``nebula_rt.io_vti`` and ``nebula_rt.render`` do, lazily.
"""

from .errors import (
    AccumulatorOverflowError,
    BackendUnavailableError,
    CancelledError,
    NebulaError,
    NebulaWarning,
    SceneError,
)

__version__ = "0.1.0"

__all__ = [
    "AccumulatorOverflowError",
    "BackendUnavailableError",
    "CancelledError",
    "NebulaError",
    "NebulaWarning",
    "SceneError",
    "__version__",
]
