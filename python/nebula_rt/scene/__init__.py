"""The scene: what a user declares (the TOML scene file), checked and in box units.

- :mod:`~nebula_rt.scene.sections`: the tables and their keys, declared once (range, choices,
  unit, panel group) -- what the CLI, the filters and ParaView's panels are built from;
- :mod:`~nebula_rt.scene.rules`: the checks of the values, each failure naming the key;
- :mod:`~nebula_rt.scene.model`: :class:`Scene`, a scene file parsed, checked and converted;
- :mod:`~nebula_rt.scene.overrides`: ``--set key=value`` and the filters' properties;
- :mod:`~nebula_rt.scene.schema`: the declaration types (``Param``) and their readers;
- :mod:`~nebula_rt.scene.sky_schema`: the sky camera's keys, declared the same way;
- :mod:`~nebula_rt.scene.units`: physical units and their conversions to box units.

The names below are the scene's public API (``nebula_rt.scene.Scene``, ``Star``, the tables'
dataclasses and the declaration readers). This package never imports VTK.
"""

from ..errors import SceneError
from .model import Scene
from .sections import (
    AUTO_THICK,
    AUTO_THIN,
    BACKENDS,
    DUST_MODELS,
    ERROR_ESTIMATES,
    ESTIMATORS,
    G_COLOUR,
    G_DEVICE,
    G_DUST,
    G_GRID,
    G_OBSERVER,
    G_OPTICS,
    G_QUALITY,
    G_STARS,
    G_TRANSPORT,
    G_UNITS,
    MAG_SYSTEMS,
    MAX_PHOTONS,
    MAX_SEED,
    METHODS,
    QUALITIES,
    QUALITY_PRESETS,
    SECTIONS,
    STRETCHES,
    WHITE_POINTS,
    BandsConfig,
    Colour,
    Dust,
    Grid,
    Observer,
    Star,
    Transport,
    declaration,
    default,
    parameters,
)

__all__ = [
    "AUTO_THICK",
    "AUTO_THIN",
    "BACKENDS",
    "BandsConfig",
    "Colour",
    "DUST_MODELS",
    "Dust",
    "ERROR_ESTIMATES",
    "ESTIMATORS",
    "G_COLOUR",
    "G_DEVICE",
    "G_DUST",
    "G_GRID",
    "G_OBSERVER",
    "G_OPTICS",
    "G_QUALITY",
    "G_STARS",
    "G_TRANSPORT",
    "G_UNITS",
    "Grid",
    "MAG_SYSTEMS",
    "MAX_PHOTONS",
    "MAX_SEED",
    "METHODS",
    "Observer",
    "QUALITIES",
    "QUALITY_PRESETS",
    "SECTIONS",
    "STRETCHES",
    "Scene",
    "SceneError",
    "Star",
    "Transport",
    "WHITE_POINTS",
    "declaration",
    "default",
    "parameters",
]
