"""Moved: reading and writing ``.vti`` files is NebulaRT's VTK layer, :mod:`nebula_rt.filters.vti`
(and :mod:`nebula_rt.filters.image_data` for vtkImageData in memory).

This name keeps the functions that the documentation showed, importing them from there on
first use (so ``import nebula_rt.pipeline.io_vti`` works without VTK), with a DeprecationWarning.
"""

from __future__ import annotations

import importlib
import warnings

#: old name -> the module that has it now
_MOVED = {
    "read_vti": "nebula_rt.filters.vti",
    "write_vti": "nebula_rt.filters.vti",
    "read_density_array": "nebula_rt.filters.vti",
    "ArrayNotFoundError": "nebula_rt.filters.vti",
    "to_image_data": "nebula_rt.filters.image_data",
    "point_array": "nebula_rt.filters.image_data",
    "field_data_dict": "nebula_rt.filters.image_data",
}

__all__ = sorted(_MOVED)


def __getattr__(name: str):
    if name not in _MOVED:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(f"nebula_rt.pipeline.io_vti.{name} has moved to {_MOVED[name]}.{name}", DeprecationWarning,
                  stacklevel=2)
    return getattr(importlib.import_module(_MOVED[name]), name)
