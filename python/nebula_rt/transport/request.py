"""The one place where a scene becomes a transport run.

Every observable traces through a :class:`TransportRequest` built by
:meth:`TransportRequest.from_scene`: the light field (:mod:`nebula_rt.pipeline`), the
calibrated sky image (:mod:`nebula_rt.observe.calibrate`), the annulus profiles
(:mod:`nebula_rt.observe`, :mod:`nebula_rt.observe.comparison`) and through them the fits. So every
``[transport]`` key reaches every run the same way (a peel-off path that dropped
``transport.error_estimate`` silently ignored a value it would have refused), and a new key is
added here once. ``tests/test_layering.py`` keeps it so: no other module calls
:func:`nebula_rt.transport.trace` or picks a scene's device.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional

from ..backends import Backend, get_backend
from .result import TransportResult
from .run import trace


def scene_backend(scene, comm=None) -> Backend:
    """The device the scene's ``transport.backend`` and ``transport.device`` select; with
    several ranks (``comm``, :mod:`nebula_rt.backends.parallel`) and no ``transport.device``, CUDA ranks
    take the GPUs of their node by local rank."""
    device = scene.transport.device
    if comm is not None and comm.size > 1 and not device and scene.transport.backend in ("auto", "cuda"):
        from ..backends.cuda import cuda_available

        if cuda_available():
            import cupy  # optional: the CUDA path

            device = str(comm.local_rank % cupy.cuda.runtime.getDeviceCount())
    return get_backend(scene.transport.backend, device)


@dataclass(frozen=True)
class TransportRequest:
    """Everything :func:`~nebula_rt.transport.trace` takes besides the density and the device.

    Attributes
    ----------
    bands : tuple of nebula_rt.optics.bands.Band
        The scene's bands, resolved.
    stars : tuple of nebula_rt.scene.Star
    tau : float
        ``dust.tau``: optical depth across one box edge at density 1, reference band.
    photons : int
        Packets per band, or the budget of an error-targeted run (after ``transport.quality``).
    target_error : float
        0, or the lit-region error to stop at (after ``transport.quality``).
    time_limit : float
        Seconds (0: none).
    estimator, method, error_estimate : str
        ``transport.estimator``, ``transport.method``, ``transport.error_estimate``.
    max_scatterings, seed, batch_size : int
    peel : nebula_rt.observe.sky.Camera or None
        A peel-off image's camera.
    peel_bins : int ndarray (W, H) or None
        With ``peel``: the pixel groups whose batch sums the run keeps.
    """

    bands: tuple
    stars: tuple
    tau: float
    photons: int
    target_error: float
    time_limit: float
    estimator: str
    method: str
    error_estimate: str
    max_scatterings: int
    seed: int
    batch_size: int
    peel: Any = None
    peel_bins: Any = None

    @classmethod
    def from_scene(cls, scene, peel=None, peel_bins=None) -> "TransportRequest":
        """The run ``scene`` asks for, with a peel-off image by ``peel`` (a Camera) if given."""
        t = scene.transport
        photons, target_error = t.effective()
        return cls(bands=tuple(scene.bands.resolve()), stars=tuple(scene.stars), tau=float(scene.dust.tau),
                   photons=int(photons), target_error=float(target_error), time_limit=float(t.time_limit),
                   estimator=t.estimator, method=t.method, error_estimate=t.error_estimate,
                   max_scatterings=int(t.max_scatterings), seed=int(t.seed), batch_size=int(t.batch_size),
                   peel=peel, peel_bins=peel_bins)

    def trace(self, density, backend: Backend, *, progress: Optional[Callable[[int, int], None]] = None,
              cancel: Optional[Callable[[], bool]] = None, on_device: bool = False, comm=None) -> TransportResult:
        """Trace the request through ``density`` on ``backend`` (see
        :func:`nebula_rt.transport.trace` for ``progress``, ``cancel``, ``on_device``, ``comm``)."""
        return trace(density, list(self.bands), list(self.stars), tau=self.tau, photons=self.photons,
                     target_error=self.target_error, time_limit=self.time_limit, estimator=self.estimator,
                     method=self.method, error_estimate=self.error_estimate, max_scatterings=self.max_scatterings,
                     seed=self.seed, batch_size=self.batch_size, backend=backend, progress=progress, cancel=cancel,
                     on_device=on_device, comm=comm, peel=self.peel, peel_bins=self.peel_bins)
