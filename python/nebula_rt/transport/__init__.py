"""Photon transport: a scene's stars, dust and bands -> the mean intensity per band, with errors.

- :mod:`~nebula_rt.transport.request`: the one place a scene becomes a run (:class:`TransportRequest`,
  and :func:`trace`, its keyword form);
- :mod:`~nebula_rt.transport.plan`: the method and error estimate per run, batches, launches;
- :mod:`~nebula_rt.transport.run`: the packets traced on a backend (``trace_request``);
- :mod:`~nebula_rt.transport.estimate`: intensities, batch-means errors, the lit region;
- :mod:`~nebula_rt.transport.result`: :class:`TransportResult` and the warnings about trust;
- :mod:`~nebula_rt.transport.finish`: finishing the sums on the device (light, errors, colour);
- :mod:`~nebula_rt.transport.importance`, :mod:`~nebula_rt.transport.tails`: weight windows
  and the heavy-tail checks of weighted packets;
- :mod:`~nebula_rt.transport.filtering`, :mod:`~nebula_rt.transport.filtering_opencl`: the
  collision estimator's filter;
- :mod:`~nebula_rt.transport.line_of_sight`: optical depths along rays;
- :mod:`~nebula_rt.transport.resources`: what a run needs in memory, checked before it starts;
- :mod:`~nebula_rt.transport.analytic`: exact answers (point source in vacuum) for checks.
"""

from .request import TransportRequest, scene_backend, trace
from .result import TransportResult

__all__ = ["TransportRequest", "TransportResult", "scene_backend", "trace"]
