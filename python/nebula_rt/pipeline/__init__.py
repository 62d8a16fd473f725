"""The pipeline: density -> transport (+ filter) -> colour, each stage re-run only when its
inputs change, and the outputs it publishes.

- :mod:`~nebula_rt.pipeline.stages`: :class:`Pipeline`, :class:`LightField`, the stages;
- :mod:`~nebula_rt.pipeline.rgba`: the colour stage (bands -> emission and opacity);
- :mod:`~nebula_rt.pipeline.output_contract`: the outputs' arrays and field data, declared once;
- :mod:`~nebula_rt.pipeline.outputs`: files written whole or not at all.
"""

from .stages import LightField, Pipeline, compute_light

__all__ = ["LightField", "Pipeline", "compute_light"]
