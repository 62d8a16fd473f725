"""Sky images: what a distant observer sees of the nebula (scattered light plus the stars).

The transport stage gives, per band ``b``, the scattered emissivity ``j_b`` (luminosity per
box-unit volume per steradian, isotropic) and the extinction coefficient ``sigma_b`` (per box
unit), both constant inside each voxel.  This module integrates the formal solution of the
transfer equation along parallel rays (orthographic projection, observer at infinity)::

    I_b = integral over the ray of  j_b(x) exp(-tau_b(x -> observer)) dl

and adds the stars' direct, attenuated light ``L_b / (4 pi) exp(-tau_b(star -> observer))``.

Conventions
-----------
* Lengths are in box units: the box is ``[0, 1]^3``; voxel ``[i, j, k]`` of an ``(nx, ny, nz)``
  grid spans ``[i/nx, (i+1)/nx) x [j/ny, (j+1)/ny) x [k/nz, (k+1)/nz)``.
* ``Camera.direction`` is the viewing direction, from the observer into the scene.  Light
  reaching the observer therefore travels along ``-direction``, and the observer sits at
  ``-infinity * direction``.
* Images are numpy arrays indexed ``[p, q]`` of shape ``(W, H)``: ``p`` runs along the width
  (image axis ``u``, to the right), ``q`` along the height (image axis ``v``, up), and ``q = 0``
  is the *bottom* row.  To display with matplotlib's ``imshow`` use ``image.T`` with
  ``origin="lower"``.
* Intensities are in luminosity per box-unit area per steradian, so ``image.sum() *
  pixel_size**2`` is the flux-like quantity ``luminosity per steradian`` leaving the scene
  towards the observer.

No VTK import here: the module needs numpy only.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from ..backends.capacity import host_available_bytes
from ..errors import CancelledError, ResourceError
from ..scene import sky_schema as _declared

__all__ = ["Camera", "SkyImage", "sky_image"]

#: Below this optical depth of a segment, ``(1 - exp(-x)) / sigma`` is replaced by its series
#: ``ds (1 - x/2)`` (relative error < x^2/6 < 2e-13), which also covers ``sigma = 0``.
_THIN_SEGMENT = 1.0e-6

#: Upper bound on ``rays x bands`` per chunk of the march: every per-step temporary is a
#: ``(n_bands, rays)`` float64 array, so this caps them at 2 MiB each whatever the image size.
_CHUNK_ELEMENTS = 1 << 18


def _vector3(name: str, value) -> tuple[float, float, float]:
    """Check a 3-vector of finite reals and return it as a tuple of floats."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be 3 real numbers, got {value!r}") from exc
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be 3 finite real numbers, got {value!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


@dataclass(frozen=True)
class Camera:
    """An orthographic camera (observer at infinity) looking at the box.

    Parameters
    ----------
    direction : tuple of 3 float
        Viewing direction, from the observer into the scene (any length from 1e-150, components
        within +-1e150: ``sky.direction``'s rule; it is normalised).  Light reaching the
        observer travels along ``-direction``.
    up : tuple of 3 float
        Rough "up" of the image (the same rule); its component perpendicular to ``direction`` becomes the image
        axis ``v``.  If it is (nearly) parallel to ``direction``, the first of the box axes
        ``+y, +z, +x`` least aligned with ``direction`` is used instead (deterministic).
    size : tuple of 2 int
        Image size in pixels ``(W, H)``, each in [1, 2**31 - 1] (VTK's int32 extents).
    extent : float
        Side of the field of view along ``u`` (the width) in box units; the height is
        ``extent * H / W`` so pixels are square.  ``0`` (default) means ``sqrt(3)``, the box's
        diagonal, so a square image holds the whole box for any direction.
    center : tuple of 3 float
        Box position (box units) on the central ray of the image.

    Notes
    -----
    The image axes are ``u = normalize(up_perp x (-d))`` (right) and ``v = (-d) x u`` (up), with
    ``d`` the unit viewing direction, so ``(u, v, -d)`` is right-handed: looking down ``-z``
    with ``up = +y`` gives ``u = +x`` and ``v = +y``, the usual x-right, y-up picture.

    Raises
    ------
    ValueError
        A parameter is malformed; the message names it (``Camera.direction`` ...).
    """

    # the defaults and the size's range are the sky image's declarations (nebula_rt.scene.sky_schema)
    direction: tuple[float, float, float] = _declared.default("sky.direction")
    up: tuple[float, float, float] = _declared.default("sky.up")
    size: tuple[int, int] = _declared.default("sky.size")
    extent: float = _declared.default("sky.extent")
    center: tuple[float, float, float] = (0.5, 0.5, 0.5)

    def __post_init__(self):
        # Frozen dataclass: normalise the stored types through object.__setattr__ so that
        # equality and hashing see plain tuples of floats/ints whatever the caller passed.
        # a direction is normalised in float64: the declared rule (sky.direction, sky.up) keeps
        # its squares from overflowing or vanishing (a NaN or empty image otherwise)
        direction = _vector3("Camera.direction", self.direction)
        if not _declared.valid_direction(direction):
            raise ValueError(f"Camera.direction {_declared.DIRECTION_ALLOWED}, got {self.direction!r}")
        up = _vector3("Camera.up", self.up)
        if not _declared.valid_direction(up):
            raise ValueError(f"Camera.up {_declared.DIRECTION_ALLOWED}, got {self.up!r}")
        try:
            size = tuple(self.size)
        except TypeError as exc:
            raise ValueError(f"Camera.size must be 2 integers (W, H) >= 1, got {self.size!r}") from exc
        lo, hi = _declared.declaration("sky.size").lo, _declared.declaration("sky.size").hi
        if (
            len(size) != 2
            or any(isinstance(s, bool) or not isinstance(s, numbers.Integral) for s in size)
            or any(not lo <= int(s) <= hi for s in size)
        ):
            raise ValueError(f"Camera.size must be 2 integers (W, H) in [{lo}, {hi}], got {self.size!r}")
        if isinstance(self.extent, bool) or not isinstance(self.extent, numbers.Real):
            raise ValueError(f"Camera.extent must be a real number >= 0, got {self.extent!r}")
        extent = float(self.extent)
        if not math.isfinite(extent) or extent < 0.0:
            raise ValueError(f"Camera.extent must be a finite number >= 0 (0 = sqrt(3)), got {self.extent!r}")
        center = _vector3("Camera.center", self.center)
        object.__setattr__(self, "direction", direction)
        object.__setattr__(self, "up", up)
        object.__setattr__(self, "size", (int(size[0]), int(size[1])))
        object.__setattr__(self, "extent", extent)
        object.__setattr__(self, "center", center)

    @property
    def field_of_view(self) -> float:
        """Width of the field of view in box units (``extent``, or ``sqrt(3)`` when 0)."""
        return self.extent if self.extent > 0.0 else math.sqrt(3.0)

    @property
    def pixel_size(self) -> float:
        """Side of one (square) pixel in box units: ``field_of_view / W``."""
        return self.field_of_view / self.size[0]

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit vectors ``(d, u, v)``: viewing direction, image right, image up.

        Returns
        -------
        d, u, v : numpy.ndarray of shape (3,)
            Orthonormal, with ``(u, v, -d)`` right-handed.
        """
        d = np.asarray(self.direction, float)
        d = d / np.linalg.norm(d)
        # Components below 1e-6 are the rounding of a view along a box face (sin(pi) = 1.2e-16):
        # they are made exactly 0. Else a scattering that float32 puts exactly on that face
        # (at a slab's edge) leaves through it at once in the peel-off, unattenuated, where the
        # light really crosses the whole slab along the face: one such packet in 75,000 gave
        # 57 % of the light behind a slab of optical depth 25 (tests/transport/test_trust_slab.py).
        d = np.where(np.abs(d) < 1.0e-6, 0.0, d)
        d = d / np.linalg.norm(d)
        up = np.asarray(self.up, float)
        up = up / np.linalg.norm(up)
        # 1e-6 in sin(angle): beyond that the projected "up" is dominated by rounding of d.
        if np.linalg.norm(np.cross(up, d)) < 1.0e-6:
            candidates = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
            up = candidates[int(np.argmin(np.abs(candidates @ d)))]  # argmin: first on ties
        u = np.cross(up, -d)
        u /= np.linalg.norm(u)
        v = np.cross(-d, u)
        v /= np.linalg.norm(v)  # already unit up to rounding; renormalise for orthonormality
        return d, u, v

    def origin(self) -> np.ndarray:
        """Box position (box units) of the centre of pixel ``(0, 0)`` (bottom-left)."""
        _, u, v = self.basis()
        w, h = self.size
        ps = self.pixel_size
        # Pixel (p, q) centre: center + ((p + 0.5)/W - 0.5) * extent u
        #                              + ((q + 0.5)/H - 0.5) * extent * H/W v.
        return (np.asarray(self.center, float)
                + (0.5 - 0.5 * w) * ps * u
                + (0.5 - 0.5 * h) * ps * v)


@dataclass(frozen=True, eq=False)
class SkyImage:
    """Result of :func:`sky_image`.

    Images are indexed ``[band, p, q]`` with shape ``(n_bands, W, H)``; ``p`` runs to the right
    along ``u_axis``, ``q`` upwards along ``v_axis`` (``q = 0`` is the bottom row).  Intensities
    are in luminosity per box-unit area per steradian.

    Attributes
    ----------
    scattered : numpy.ndarray, float64, (n_bands, W, H)
        Scattered light of the dust, attenuated on its way to the observer.
    direct : numpy.ndarray, float64, (n_bands, W, H)
        Direct, attenuated light of the stars, each spread uniformly over the pixel containing
        its projection (value = ``L/(4 pi) exp(-tau) / pixel_size**2``).
    intensity : numpy.ndarray, float64, (n_bands, W, H)
        ``scattered + direct``.
    tau_star : numpy.ndarray, float64, (n_stars, n_bands)
        Optical depth from each star to the observer (also for stars outside the field of view).
    pixel_size : float
        Side of one square pixel in box units.
    camera : Camera
        The camera used.
    u_axis, v_axis : numpy.ndarray, (3,)
        Unit vectors of the image's right and up directions in box coordinates.
    origin : numpy.ndarray, (3,)
        Box position of the centre of pixel ``(0, 0)``; pixel ``(p, q)`` is centred at
        ``origin + pixel_size * (p * u_axis + q * v_axis)``.
    """

    scattered: np.ndarray
    direct: np.ndarray
    intensity: np.ndarray
    tau_star: np.ndarray
    pixel_size: float
    camera: Camera
    u_axis: np.ndarray
    v_axis: np.ndarray
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))


def _check_medium(emissivity, sigma) -> tuple[np.ndarray, np.ndarray]:
    arrays = []
    for name, value in (("emissivity", emissivity), ("sigma", sigma)):
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name} must be a real (n_bands, nx, ny, nz) array") from exc
        if arr.ndim != 4 or min(arr.shape) < 1:
            raise ValueError(f"{name} must have shape (n_bands, nx, ny, nz) with every size >= 1, "
                             f"got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be finite (found NaN or infinity)")
        if np.any(arr < 0.0):
            raise ValueError(f"{name} must be non-negative (min {arr.min()!r})")
        arrays.append(arr)
    if arrays[0].shape != arrays[1].shape:
        raise ValueError(f"emissivity and sigma must have the same shape, got {arrays[0].shape} "
                         f"and sigma {arrays[1].shape}")
    return arrays[0], arrays[1]


def _check_stars(stars, star_band_luminosity, n_bands) -> tuple[np.ndarray, np.ndarray]:
    try:
        pos = np.asarray(stars if stars is not None else (), dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError("stars must be a sequence of (3,) positions in box units") from exc
    if pos.size == 0:
        pos = pos.reshape(0, 3)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"stars must be a sequence of (3,) positions, got shape {pos.shape}")
    if not np.all(np.isfinite(pos)):
        raise ValueError("stars positions must be finite")
    n_stars = pos.shape[0]
    if star_band_luminosity is None:
        if n_stars:
            raise ValueError("star_band_luminosity (n_stars, n_bands) is required when stars are given")
        return pos, np.zeros((0, n_bands))
    try:
        lum = np.asarray(star_band_luminosity, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError("star_band_luminosity must be a real (n_stars, n_bands) array") from exc
    if lum.size == 0 and n_stars == 0:
        lum = lum.reshape(0, n_bands)
    if lum.shape != (n_stars, n_bands):
        raise ValueError(f"star_band_luminosity must have shape (n_stars, n_bands) = "
                         f"{(n_stars, n_bands)}, got {lum.shape}")
    if not np.all(np.isfinite(lum)) or np.any(lum < 0.0):
        raise ValueError("star_band_luminosity must be finite and non-negative")
    return pos, lum


def _box_interval(points: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Slab intersection of the lines ``points + t d`` with ``[0, 1]^3``.

    Returns ``(t_in, t_out)``; the line misses the box where ``t_out <= t_in``.
    """
    t_in = np.full(points.shape[0], -np.inf)
    t_out = np.full(points.shape[0], np.inf)
    for axis in range(3):
        x = points[:, axis]
        if d[axis] == 0.0:
            # Parallel to this slab: inside for every t or for none (closed slab, so a ray
            # grazing a face still sees the boundary voxels).
            outside = (x < 0.0) | (x > 1.0)
            t_in = np.where(outside, np.inf, t_in)
            t_out = np.where(outside, -np.inf, t_out)
            continue
        t0 = (0.0 - x) / d[axis]
        t1 = (1.0 - x) / d[axis]
        t_in = np.maximum(t_in, np.minimum(t0, t1))
        t_out = np.minimum(t_out, np.maximum(t0, t1))
    return t_in, t_out


def _march(points, d, t_hi, j_flat, s_flat, shape, ds_max, emission=True):
    """Integrate along ``points + t d`` for ``t`` in ``(-inf, t_hi]`` clipped to the box.

    The observer is at ``t = -inf``; the march goes away from it, so the transmission factor
    ``exp(-tau)`` of each segment is that of everything already crossed.

    Parameters
    ----------
    points : (m, 3) float array, box units.
    d : (3,) unit viewing direction.
    t_hi : float or (m,) array, upper end of the ray parameter (``inf`` for pixels, ``0`` for a
        star at ``points``).
    j_flat, s_flat : (n_bands, nx*ny*nz) emissivity and extinction, C order.
    shape : (nx, ny, nz).
    ds_max : float, longest segment, box units.
    emission : bool, whether to integrate ``j`` (False: only the optical depth).

    Returns
    -------
    intensity : (n_bands, m) float64 (zeros when ``emission`` is False).
    tau : (n_bands, m) float64, optical depth over the whole interval.
    """
    n_bands = s_flat.shape[0]
    m = points.shape[0]
    intensity = np.zeros((n_bands, m))
    tau = np.zeros((n_bands, m))
    t_in, t_out = _box_interval(points, d)
    t_out = np.minimum(t_out, t_hi)
    length = np.where(t_out > t_in, t_out - t_in, 0.0)
    # Equal segments no longer than ds_max that tile [t_in, t_out] exactly; the 1e-9 slack
    # keeps L/ds_max = 10.000000000000002 from adding a segment, so that along a box axis the
    # segment ends stay on voxel faces (and the midpoint rule is then exact).
    n_seg = np.where(length > 0.0, np.maximum(np.ceil(length / ds_max - 1.0e-9), 1.0), 0.0).astype(np.int64)
    ds = np.where(n_seg > 0, length / np.maximum(n_seg, 1), 0.0)
    t_start = np.where(n_seg > 0, t_in, 0.0)
    nx, ny, nz = shape
    dims = np.array([nx, ny, nz], dtype=np.int64)
    for k in range(int(n_seg.max(initial=0))):
        # Work only on the rays still inside the box: long and short chords share a chunk.
        act = np.flatnonzero(n_seg > k)
        dsa = ds[act]
        mid = points[act] + (t_start[act] + (k + 0.5) * dsa)[:, None] * d
        # Voxel holding the midpoint; the clip only absorbs rounding at the box faces.
        idx = np.clip(np.floor(mid * dims).astype(np.int64), 0, dims - 1)
        flat = (idx[:, 0] * ny + idx[:, 1]) * nz + idx[:, 2]
        sig = s_flat[:, flat]
        x = sig * dsa
        if emission:
            jj = j_flat[:, flat]
            thin = x < _THIN_SEGMENT
            # Exact segment integral of j exp(-sigma s) ds: j (1 - e^{-x}) / sigma, with expm1
            # so that small x does not lose digits to cancellation.
            seg = np.where(thin, jj * dsa * (1.0 - 0.5 * x),
                           jj * -np.expm1(-x) / np.where(thin, 1.0, sig))
            tau_a = tau[:, act]
            intensity[:, act] += seg * np.exp(-tau_a)
            tau[:, act] = tau_a + x
        else:
            tau[:, act] += x
    return intensity, tau


#: float64 images of (n_bands, W, H) a sky image holds at once (scattered, direct,
#: intensity) and the picture made from it needs besides (its colour and tone steps)
SKY_IMAGE_ARRAYS = 6


def sky_image_bytes(n_bands: int, size) -> int:
    """Host memory a sky image of ``n_bands`` bands and ``size`` (W, H) pixels needs (bytes)."""
    w, h = (int(n) for n in size)
    return SKY_IMAGE_ARRAYS * 8 * int(n_bands) * w * h


def check_sky_image_memory(n_bands: int, size, parameter: str = "sky.size") -> None:
    """Refuse a sky image the host's available memory cannot hold, naming ``parameter``
    (ResourceError), before any work."""
    need, avail = sky_image_bytes(n_bands, size), host_available_bytes()
    if need > avail:
        raise ResourceError(parameter, tuple(int(n) for n in size),
                            f"a sky image of {n_bands} bands needs about {need / 2**30:.3g} GiB of host memory "
                            f"({SKY_IMAGE_ARRAYS} float64 images of W x H per band); {avail / 2**30:.3g} GiB is available")


def sky_image(emissivity, sigma, camera: Camera, *, stars: Sequence = (),
              star_band_luminosity: Optional[np.ndarray] = None, step: float = 0.5,
              progress: Optional[Callable[[int, int], None]] = None,
              cancel: Optional[Callable[[], bool]] = None) -> SkyImage:
    """Render what a distant observer sees: attenuated scattered light plus the stars.

    For every pixel ray and band ``b`` computes ``I_b = integral j_b(x) exp(-tau_b(x ->
    observer)) dl``.  The chord of the ray through the box (slab intersection) is cut into equal
    segments no longer than ``step * min(1/nx, 1/ny, 1/nz)``; each segment takes ``j`` and
    ``sigma`` of the voxel holding its midpoint and is integrated exactly for a constant medium:
    ``j / sigma (1 - exp(-sigma ds)) exp(-tau)``, with ``tau`` the optical depth of the segments
    between it and the observer.  Rays missing the box give 0.

    Parameters
    ----------
    emissivity : array_like, (n_bands, nx, ny, nz)
        Scattered emissivity ``j_b`` per voxel: luminosity per box-unit volume per steradian,
        isotropic; >= 0.
    sigma : array_like, (n_bands, nx, ny, nz)
        Extinction coefficient per voxel in 1 / box unit; >= 0.
    camera : Camera
        Viewing geometry and image size.
    stars : sequence of (3,) positions, optional
        Star positions in box units (inside or outside the box).
    star_band_luminosity : array_like, (n_stars, n_bands), optional
        Luminosity of each star per band (isotropic emission); required when ``stars`` is not
        empty.
    step : float
        Longest segment as a fraction of the smallest voxel edge (> 0).  With ``step <= 1`` and
        the view along a box axis the segments never straddle a voxel face, and the result is
        exact for the piecewise-constant medium; otherwise a segment straddling a face is
        assigned to one voxel, an error that shrinks linearly with ``step``.
    progress : callable(done, total), optional
        Called after every chunk of pixel rays with the pixels done so far.
    cancel : callable() -> bool, optional
        Polled before every chunk (a chunk marches about 2^18 band-pixels, well under a
        second); True raises :class:`~nebula_rt.errors.CancelledError`.

    Returns
    -------
    SkyImage
        Images of shape ``(n_bands, W, H)`` indexed ``[b, p, q]`` (``q = 0`` at the bottom), in
        luminosity per box-unit area per steradian; see :class:`SkyImage`.  A star contributes
        ``L_b / (4 pi) exp(-tau_b) / pixel_size**2`` to the pixel containing its projection, so
        ``direct.sum(axis=(1, 2)) * pixel_size**2`` is its attenuated luminosity per steradian.
        Stars outside the field of view are left out of ``direct`` (``tau_star`` still holds
        their optical depth).

    Raises
    ------
    ValueError
        Malformed input; the message names the parameter (``emissivity``, ``sigma``,
        ``camera``, ``stars``, ``star_band_luminosity``, ``step``).
    ResourceError
        (``sky.size``) the images would not fit the host's available memory.
    CancelledError
        ``cancel`` returned True.
    """
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a nebula_rt.observe.sky.Camera, got {type(camera).__name__}")
    j, s = _check_medium(emissivity, sigma)
    if isinstance(step, bool) or not isinstance(step, numbers.Real) or not math.isfinite(step) or step <= 0:
        raise ValueError(f"step must be a finite number > 0 (fraction of a voxel edge), got {step!r}")
    n_bands, nx, ny, nz = j.shape
    star_pos, star_lum = _check_stars(stars, star_band_luminosity, n_bands)
    check_sky_image_memory(n_bands, camera.size)

    d, u, v = camera.basis()
    w, h = camera.size
    ps = camera.pixel_size
    origin = camera.origin()
    ds_max = float(step) / max(nx, ny, nz)
    j_flat = j.reshape(n_bands, -1)
    s_flat = s.reshape(n_bands, -1)
    shape = (nx, ny, nz)

    # Pixels in [p, q] C order (flat index p * H + q), so the result reshapes to (W, H).
    scattered = np.empty((n_bands, w * h))
    chunk = max(256, _CHUNK_ELEMENTS // n_bands)
    for start in range(0, w * h, chunk):
        if cancel is not None and cancel():
            raise CancelledError("sky image cancelled")
        stop = min(start + chunk, w * h)
        p_idx, q_idx = np.divmod(np.arange(start, stop), h)
        pts = origin + ps * (p_idx[:, None] * u + q_idx[:, None] * v)
        scattered[:, start:stop] = _march(pts, d, np.inf, j_flat, s_flat, shape, ds_max)[0]
        if progress is not None:
            progress(stop, w * h)
    scattered = scattered.reshape(n_bands, w, h)

    direct = np.zeros((n_bands, w, h))
    n_stars = star_pos.shape[0]
    tau_star = np.zeros((n_stars, n_bands))
    if n_stars:
        # The star sits at t = 0 on its own ray; the light crosses t in (-inf, 0] to the observer.
        _, tau = _march(star_pos, d, 0.0, j_flat, s_flat, shape, ds_max, emission=False)
        tau_star = tau.T.copy()
        rel = star_pos - origin
        # Pixel (p, q) covers centre +- ps/2, hence the + 0.5 before the floor.
        p_star = np.floor(rel @ u / ps + 0.5).astype(np.int64)
        q_star = np.floor(rel @ v / ps + 0.5).astype(np.int64)
        seen = (p_star >= 0) & (p_star < w) & (q_star >= 0) & (q_star < h)
        flux = star_lum * np.exp(-tau_star) / (4.0 * np.pi) / ps**2  # (n_stars, n_bands)
        for i in np.flatnonzero(seen):
            direct[:, p_star[i], q_star[i]] += flux[i]

    return SkyImage(scattered=scattered, direct=direct, intensity=scattered + direct,
                    tau_star=tau_star, pixel_size=ps, camera=camera,
                    u_axis=u, v_axis=v, origin=origin)
