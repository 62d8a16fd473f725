"""The one place where a scene becomes a transport run.

Every observable traces through a :class:`TransportRequest` built by
:meth:`TransportRequest.from_scene`: the light field (:mod:`nebula_rt.pipeline`), the
calibrated sky image (:mod:`nebula_rt.observe.calibrate`), the annulus profiles
(:mod:`nebula_rt.observe`, :mod:`nebula_rt.observe.comparison`) and through them the fits. So every
``[transport]`` key reaches every run the same way (a peel-off path that dropped
``transport.error_estimate`` silently ignored a value it would have refused), and a new key is
added here once. ``tests/test_layering.py`` keeps it so: no other module calls
:func:`nebula_rt.transport.trace` or picks a scene's device.

A run is described by one request object, whose defaults are the scene's declarations
(:mod:`nebula_rt.scene.sections`); :func:`trace` is the keyword form of the same call, kept
for scripts and notebooks, and builds a request.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional

import numpy as np

from ..backends import Backend, get_backend
from ..scene.sections import default as _declared
from ..optics.polarization import NONE as NO_POLARIZATION, Polarization, polarization_of
from .result import TransportResult
from .run import trace_request


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
    """Everything a run takes besides the density and the device (see :func:`trace` for the
    meaning of every field); the defaults are the scene's.

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
    estimator, method, error_estimate, importance : str
        ``transport.estimator``, ``transport.method``, ``transport.error_estimate``; what
        steers weighted packets' windows.
    max_scatterings, seed, batch_size : int
    peel : nebula_rt.observe.sky.Camera or None
        A peel-off image's camera.
    peel_bins : int ndarray (W, H) or None
        With ``peel``: the pixel groups whose batch sums the run keeps.
    light_field : bool
        False: the peel-off image alone, no J.
    polarization : nebula_rt.optics.polarization.Polarization
        The dust's polarized scattering (``bands.polarization``); the default traces intensity alone.
    """

    bands: tuple
    stars: tuple
    tau: float
    photons: int
    target_error: float = _declared("transport.target_error")
    time_limit: float = _declared("transport.time_limit")
    estimator: str = _declared("transport.estimator")
    method: str = _declared("transport.method")
    error_estimate: str = _declared("transport.error_estimate")
    max_scatterings: int = _declared("transport.max_scatterings")
    seed: int = _declared("transport.seed")
    batch_size: int = _declared("transport.batch_size")
    peel: Any = None
    peel_bins: Any = None
    importance: str = "auto"
    light_field: bool = True
    polarization: Polarization = NO_POLARIZATION

    @classmethod
    def from_scene(cls, scene, peel=None, peel_bins=None, light_field: bool = True) -> "TransportRequest":
        """The run ``scene`` asks for, with a peel-off image by ``peel`` (a Camera) if given
        (``light_field`` False: the image alone, see :func:`trace`)."""
        t = scene.transport
        photons, target_error = t.effective()
        return cls(bands=tuple(scene.bands.resolve()), stars=tuple(scene.stars), tau=float(scene.dust.tau),
                   photons=int(photons), target_error=float(target_error), time_limit=float(t.time_limit),
                   estimator=t.estimator, method=t.method, error_estimate=t.error_estimate,
                   max_scatterings=int(t.max_scatterings), seed=int(t.seed), batch_size=int(t.batch_size),
                   peel=peel, peel_bins=peel_bins, light_field=bool(light_field),
                   polarization=polarization_of(scene))

    def trace(self, density, backend: Backend, *, progress: Optional[Callable[[int, int], None]] = None,
              cancel: Optional[Callable[[], bool]] = None, on_device: bool = False, comm=None,
              _acc_limit_bits: int = 63, _checked_adds: bool = False, make_light: bool = False) -> TransportResult:
        """Trace the request through ``density`` on ``backend`` (see :func:`trace` for
        ``progress``, ``cancel``, ``on_device``, ``comm``; ``make_light``: the device sums
        are finished next, see :func:`~nebula_rt.transport.run.trace_request`)."""
        return trace_request(density, self, backend, progress=progress, cancel=cancel, on_device=on_device,
                             comm=comm, _acc_limit_bits=_acc_limit_bits, _checked_adds=_checked_adds,
                             make_light=make_light)


def trace(
    density: np.ndarray,
    bands,
    stars,
    *,
    tau: float,
    photons: int,
    estimator: str = _declared("transport.estimator"),
    max_scatterings: int = _declared("transport.max_scatterings"),
    seed: int = _declared("transport.seed"),
    batch_size: int = _declared("transport.batch_size"),
    backend: Backend,
    progress: Optional[Callable[[int, int], None]] = None,
    cancel: Optional[Callable[[], bool]] = None,
    _acc_limit_bits: int = 63,
    on_device: bool = False,
    target_error: float = _declared("transport.target_error"),
    time_limit: float = _declared("transport.time_limit"),
    peel=None,
    peel_bins=None,
    comm=None,
    _checked_adds: bool = False,
    method: str = _declared("transport.method"),
    error_estimate: str = _declared("transport.error_estimate"),
    importance: str = "auto",
    light_field: bool = True,
    polarization: Polarization = NO_POLARIZATION,
) -> TransportResult:
    """Trace ``photons`` packets per band through ``density`` and estimate J: the keyword
    form of ``TransportRequest(...).trace(density, backend, ...)``.

    The defaults of the keywords that are scene keys are the scene's (the declarations of
    :mod:`nebula_rt.scene.sections`), so a call and a scene file that leave a key out trace
    alike.

    Parameters
    ----------
    density : ndarray (nx, ny, nz)
        Dust density per voxel (>= 0).
    bands : sequence of nebula_rt.optics.bands.Band
        Band optical properties (extinction relative to the reference band, albedo, g).
    stars : sequence of nebula_rt.scene.Star
        Positions (box units), luminosities, optional temperatures.
    tau : float
        Optical depth across one box edge at density 1 in the reference band.
    photons : int
        Packets per band.
    estimator : {"track-length", "collision-filter"}
        Which tally the kernel accumulates (the collision estimate is unfiltered here).
    progress : callable(done, total), optional
        Called after every group of batches (and after each launch of a group traced in
        several) with the packets per band done so far.
    cancel : callable() -> bool, optional
        Polled before every launch (launches last at most ``LAUNCH_SECONDS``) and after the
        last; True raises :class:`~nebula_rt.errors.CancelledError`.
    target_error : float
        0: trace ``photons`` packets. In (0, 1): trace batch after batch (the plan is made for
        ``photons``, now a budget) until :func:`lit_region_error` is at most this, checked once
        ``MIN_BATCHES`` batches are in and then where the 1/sqrt(N) fall of the error predicts
        the target (O(log N) checks); ``result.photons`` is what was used
        and ``result.achieved_error`` the error reached, sqrt(statistical^2 + bias^2) with the
        bias bound of terminated packets (:func:`terminated_bias`), which more packets do not
        shrink and so does not enter the stopping rule.
    time_limit : float
        Seconds; > 0 stops any run within one launch of this long, keeping the finished
        batches (the photon count then depends on the machine's speed).
    peel : nebula_rt.observe.sky.Camera, optional
        Also make a peel-off image of the scattered light seen by this camera (the phase
        function at every scattering towards the observer, attenuated to the box's edge):
        ``result.peel_image``, luminosity per box-unit area per steradian, (n_bands, W, H),
        the layout of :class:`nebula_rt.observe.sky.SkyImage`; ``result.peel_error`` its batch-means
        standard error per pixel.
    peel_bins : int ndarray (W, H), optional
        With ``peel``: a pixel group per pixel (-1: none); ``result.peel_bin_batches`` then
        holds every batch's image summed over each group, for the errors of statistics of
        several pixels (an annulus's sum: the pixels of a batch are correlated, one packet
        peeling off into many of them).
    on_device : bool
        Leave the sums on the device (``result.device_sums``, for
        :func:`nebula_rt.transport.finish.finish`) instead of computing J and rel_error on the host.
    comm : communicator, optional
        Trace with several processes (:func:`nebula_rt.backends.parallel.world` under ``mpiexec``):
        every rank calls ``trace`` with the same arguments, traces a share of the packets, and
        gets the one-rank result, bit for bit.
    method : {"auto", "analog", "biased"}
        Analog packets, or weighted ones for optically thick dust (forced scattering,
        composite path-length biasing, Russian roulette; kernels/transport.cl, docs/physics.md),
        or the one measured best for this run (:func:`resolve_method`); ``result.method`` says
        which ran.
    error_estimate : {"auto", "batches", "packets"}
        How the error of J is estimated (:func:`resolve_error_estimate`): the spread of batch
        totals, or every packet's contribution per voxel and its square (then
        ``result.batches`` is the packet count: batches of one packet).
    importance : {"auto", "stars", "observer"}
        What steers the weighted packets' windows (:mod:`nebula_rt.transport.importance`): the light
        field from the stars, or the peel-off image's observer (``peel`` needed); ``"auto"``
        takes the observer's when there is a peel-off image, the stars' otherwise.
        ``result.importance`` says which ran ("" for analog packets). J's heavy-tail classes
        (``result.tail_j``) are checked under the stars' windows only.
    light_field : bool
        False (with ``peel``): the peel-off image alone. The kernel deposits nothing into the
        voxels and no batch of J is folded (``result.J``, ``rel_error`` and ``device_sums``
        are None), so the run needs no batch slots and traces every batch in one launch. The
        image is the same bits as with the light field: the deposits draw no random numbers.
        For the observables that read only the image (annulus profiles, sky images, fits),
        where J was most of the work (on an H200 about half a fit trial's time; see
        benchmarks/profile_fit_trace.py). Needs ``peel`` and no ``target_error`` (which is
        J's error).
    polarization : nebula_rt.optics.polarization.Polarization
        Packets carry a Stokes vector and scatter by this Mueller matrix (Rayleigh, the
        bands' Henyey-Greenstein phase function with White's linear polarization, or Mie grains,
        whose optics the bands must carry: :func:`nebula_rt.optics.mie.mie_bands`; analog or
        weighted packets, by regions too). With ``peel``: ``result.peel_stokes``,
        the Q and U images (n_bands, 2, W, H; Mie grains: Q, U and V, (n_bands, 3, W, H)) in the
        units of ``peel_image``, IAU convention
        (the camera's up axis as north, east = the direction to the observer x north: to the
        image's left), and ``result.peel_stokes_error`` their batch-means standard errors.
    """
    request = TransportRequest(
        bands=tuple(bands), stars=tuple(stars), tau=tau, photons=photons, target_error=target_error,
        time_limit=time_limit, estimator=estimator, method=method, error_estimate=error_estimate,
        max_scatterings=max_scatterings, seed=seed, batch_size=batch_size, peel=peel, peel_bins=peel_bins,
        importance=importance, light_field=light_field, polarization=polarization)
    return request.trace(density, backend, progress=progress, cancel=cancel, on_device=on_device, comm=comm,
                         _acc_limit_bits=_acc_limit_bits, _checked_adds=_checked_adds)
