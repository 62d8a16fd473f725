"""A model image against the user's observed FITS image: reprojection, residuals, chi^2, plot.

**The model image** is the calibrated peel-off sky image of :mod:`nebula_rt.observe.calibrate`, the one
``nebula-rt sky --fits`` writes: surface brightness in MJy/sr (scattered light plus the stars
as point sources, convolved with the observer's PSF) on the camera of
:func:`nebula_rt.observe.calibrate.camera_for`, with that image's own celestial WCS
(:func:`nebula_rt.observe.calibrate.celestial_wcs`: the box centre at ``observer.ra``, ``observer.dec``,
image up at ``observer.position_angle`` east of north). Physical units are what make an
observation comparable at all: an observed image is a surface brightness on the sky, and the
calibration (the stars' luminosities in L_sun, the box's edge and the distance) is what turns
the trace's box units into one. The peel-off image, not the ray march, because it carries the
phase function at every scattering (the ray march scatters isotropically per voxel) and
because its batches give every pixel its Monte Carlo error. One scene band (``SB_<band>``,
band-averaged per unit frequency) or one passband (its photon-counting mean surface
brightness, ``bessell-V``, ``sdss2010-r``, ...: :data:`nebula_rt.observe.calibrate.PASSBANDS`) is
compared.

**The observation** (:func:`nebula_rt.observe.observed_images.read_image`, also importable from here):
one 2-D image HDU of a FITS file with a celestial WCS in its header, in a surface brightness per
unit frequency (BUNIT convertible to MJy/sr), and its 1-sigma errors: an error HDU of the same
shape, a constant surface brightness, a relative error (``5%``), or several of these added in
quadrature.

**Reprojection** (:func:`reproject_to_model`) onto the model image's grid with the ``reproject``
package (the ``observe`` extra): ``exact`` (default; ``reproject_exact``) gives each model pixel
the area-weighted mean surface brightness of the observed pixels that overlap it (spherical
polygon overlaps), so flux (surface brightness x solid angle) is conserved and a model pixel,
itself a mean over its area, is compared with the observation's mean over the same area;
``interp`` (``reproject_interp``, bilinear) samples the observation at the model pixels' centres
(faster; right when the observed pixels are much larger than the model's). Only model pixels
wholly inside the observation (footprint 1) enter chi^2.

**Errors through the reprojection.** Both modes are linear in the observed pixels x_k:
out_j = sum_k W_jk x_k. For independent pixels with errors sigma_k the variance is
var_j = sum_k W_jk^2 sigma_k^2, which reprojecting the error image does not give (that is
sum_k W_jk sigma_k, too large by up to the square root of the number of pixels averaged). It is
computed exactly with reproject itself: the observed pixels are split into s x s lattices (every
s-th pixel along each axis, s larger than the number of observed pixels any model pixel touches
along an axis), so that no model pixel receives two pixels of one lattice; reprojecting a
lattice's errors (all other pixels 0) gives W_jk sigma_k for the one k, whose squares summed over
the s^2 lattices are var_j. s is 2 for ``interp`` (bilinear: 2 x 2 neighbours) and grows with the
ratio of the model's pixel to the observed one for ``exact``; beyond :data:`MAX_LATTICE_PASSES`
reprojections the ``exact`` variance takes the bound sum_k W_jk^2 sigma_k^2 <= (Omega_obs /
A_j) sum_k W_jk sigma_k^2 (each overlap a_jk is at most an observed pixel's solid angle
Omega_obs; A_j the covered area), exact for observed pixels wholly inside the model pixel and
too large only through the pixels split by its edges (measured 1.66, 1.38 and 1.13 times the
exact variance for r = 1.5, 2.2 and 5.6 observed pixels across a model pixel: about 1 + 0.75 / r;
docs/observations.md).

**chi^2** (:func:`compare_image`) = sum_j (d_j - m_j)^2 / (sigma_d,j^2 + sigma_m,j^2) over the
pixels used: the observation's error after reprojection and the run's own Monte Carlo error in
quadrature, as :mod:`nebula_rt.observe.comparison` explains for tables (the telescope's noise and the
packets' random numbers are independent). sigma_m is the batch-means standard error of the
calibrated pixel: the trace keeps every batch's image, and the calibration, linear in the
scattered light, is applied to each batch's deviation from the mean. With per-pixel variances
exact, E[chi^2] = n for n pixels; where one observed pixel feeds several model pixels (model
pixels finer than the observed ones) their residuals are correlated and chi^2 scatters more than
sqrt(2 n) about n, so the p-value, which assumes independent pixels, is then too small. The
summary reports how many observed pixels a model pixel spans.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from . import calibrate
from .calibrate import PASSBANDS
from ..errors import SceneError
from .observed_images import ObservedImage, read_image  # noqa: F401 (read_image: also the API here)
from ..transport.plan import batch_count, planned_batch_size
from ..scene.sky_schema import COMPARISON_SIZE

#: How the observation is resampled onto the model image's grid
REPROJECT_MODES = ("exact", "interp")
#: The unit of the comparison
SB_UNIT = "MJy/sr"
#: Most reprojections the exact propagation of the observed errors may take (s^2 lattices); past it
#: the ``exact`` mode's variance takes the area bound (module docstring)
MAX_LATTICE_PASSES = 64
#: Model pixels whose footprint (the covered fraction of the pixel) is below this are left out of chi^2
MIN_FOOTPRINT = 1.0 - 1e-6
#: The per-pixel batch images of the model's trace (batches x bands x pixels x 8 bytes) may take at most this
MAX_PIXEL_BATCH_BYTES = 2 << 30


def _require_reproject():
    try:
        import reproject
    except ImportError:
        raise SceneError("image reprojection", "reproject", "resampling a FITS image onto the model image's grid "
                         "needs the reproject package: pip install 'nebula-rt[observe]' (or pip install reproject)"
                         ) from None
    return reproject


# --------------------------------------------------------------------------------------------
# which model image


def resolve_band(scene, spec=None, header_band=None) -> tuple:
    """("band", index, name) for a scene band or ("passband", key, speclite name) for a passband
    of :data:`nebula_rt.observe.calibrate.PASSBANDS`, from ``spec`` or else the image header's BAND or
    FILTER keyword."""

    names = [b.name for b in scene.bands.resolve()]
    pb = {v: k for k, v in PASSBANDS.items()}
    allowed = f"must be a band of the scene ({', '.join(names)}) or a passband ({', '.join(pb)})"
    for text, from_header in ((spec, False), (header_band, True)):
        if text is None:
            continue
        t = str(text).strip()
        if t in names:
            return "band", names.index(t), t
        if t in pb:
            return "passband", pb[t], t
        if not from_header:
            raise SceneError("--image-band", spec, allowed)
    raise SceneError("--image-band", None, f"names the model image to compare; the image's header has no BAND or "
                     f"FILTER that matches ({header_band!r}): it {allowed}")


# --------------------------------------------------------------------------------------------
# reprojection


@dataclass
class Reprojected:
    """The observation on the model image's grid (FITS order (ny, nx)).

    Attributes
    ----------
    data, error : ndarray
        Surface brightness and its 1-sigma error, MJy/sr (NaN where not covered).
    footprint : ndarray
        Covered fraction of each model pixel (reproject's footprint).
    mode : str
        ``exact`` or ``interp``.
    variance : str
        How the errors were propagated: ``lattice`` (exact, ``passes`` reprojections) or
        ``area bound`` (module docstring).
    passes : int
    pixel_ratio : float
        Observed pixels per model pixel (solid angles at the reference points).
    """

    data: np.ndarray
    error: np.ndarray
    footprint: np.ndarray
    mode: str
    variance: str
    passes: int
    pixel_ratio: float

    @property
    def usable(self) -> np.ndarray:
        """Model pixels wholly inside the observation, with a finite value and error."""
        return (self.footprint >= MIN_FOOTPRINT) & np.isfinite(self.data) & np.isfinite(self.error)


def _pixel_area_sr(wcs) -> float:
    from astropy.wcs.utils import proj_plane_pixel_area

    return float(proj_plane_pixel_area(wcs)) * (math.pi / 180.0) ** 2


def _lattice_stride(wcs_in, wcs_out, shape_out, shape_in, mode: str) -> int:
    """s: more than the observed pixels any model pixel touches along an observed axis."""
    if mode == "interp":
        return 2  # bilinear: pixels floor(x) and floor(x) + 1
    ny, nx = shape_out
    xc, yc = np.meshgrid(np.arange(nx + 1.0) - 0.5, np.arange(ny + 1.0) - 0.5)
    world = wcs_out.pixel_to_world(xc, yc)
    px, py = (np.asarray(a, np.float64) for a in wcs_in.world_to_pixel(world))
    s = 1
    for a in (px, py):
        corners = np.stack([a[:-1, :-1], a[1:, :-1], a[:-1, 1:], a[1:, 1:]])
        lo = np.floor(corners.min(axis=0) + 0.5 - 1e-9)
        hi = np.floor(corners.max(axis=0) + 0.5 + 1e-9)
        inside = (hi >= 0) & (lo <= (shape_in[1] if a is px else shape_in[0]) - 1)
        if inside.any():
            s = max(s, int((hi - lo)[inside].max()) + 1)
    tan = all(str(c).endswith("-TAN") for w in (wcs_in, wcs_out) for c in w.wcs.ctype)
    return s + (0 if tan else 1)  # TAN maps great circles (reproject's pixel edges) to straight lines


def reproject_to_model(obs: ObservedImage, wcs_out, shape_out, mode: str = "exact",
                       variance: str = "auto") -> Reprojected:
    """Resample ``obs`` onto the grid of ``wcs_out`` (``shape_out`` = (ny, nx)) with reproject,
    its errors propagated (module docstring).

    Parameters
    ----------
    mode : str
        ``exact`` (flux-conserving area means) or ``interp`` (bilinear).
    variance : str
        ``auto`` (the lattice up to :data:`MAX_LATTICE_PASSES` reprojections, then the area
        bound), ``lattice`` or ``bound`` (``exact`` only).
    """
    rp = _require_reproject()
    if mode not in REPROJECT_MODES:
        raise SceneError("--reproject", mode, f"must be one of {', '.join(REPROJECT_MODES)}")
    if variance not in ("auto", "lattice", "bound") or (variance == "bound" and mode != "exact"):
        raise SceneError("variance", variance, "must be auto, lattice or (mode exact) bound")
    shape_out = tuple(int(n) for n in shape_out)

    def run(img, **kw):
        if mode == "exact":
            return rp.reproject_exact((img, obs.wcs), wcs_out, shape_out=shape_out, **kw)
        return rp.reproject_interp((img, obs.wcs), wcs_out, shape_out=shape_out, order="bilinear", **kw)

    data, footprint = run(obs.data)
    ratio = _pixel_area_sr(wcs_out) / _pixel_area_sr(obs.wcs)
    # pixels without a usable error leave the comparison: NaN in every lattice as in the data
    sig = np.where(np.isfinite(obs.data) & np.isfinite(obs.sigma), obs.sigma, np.nan)
    s = _lattice_stride(obs.wcs, wcs_out, shape_out, obs.data.shape, mode)
    use_lattice = variance == "lattice" or (variance == "auto" and (mode == "interp" or s * s <= MAX_LATTICE_PASSES))
    if use_lattice:
        base = np.where(np.isnan(sig), np.nan, 0.0)
        var = np.zeros(shape_out)
        for i in range(s):
            for j in range(s):
                img = base.copy()
                img[i::s, j::s] = sig[i::s, j::s]
                var += run(img, return_footprint=False) ** 2
        how, passes = "lattice", s * s
    else:  # sum W^2 sigma^2 <= (Omega_obs / A_j) sum W sigma^2, and <= sum W sigma^2
        mean_var = run(sig ** 2, return_footprint=False)
        with np.errstate(divide="ignore", invalid="ignore"):
            var = mean_var * np.minimum(1.0, 1.0 / (ratio * footprint))
        how, passes = "area bound", 1
    return Reprojected(data=data, error=np.sqrt(var), footprint=footprint, mode=mode, variance=how, passes=passes,
                       pixel_ratio=float(ratio))


def check_overlap(obs: ObservedImage, wcs_out, shape_out) -> int:
    """The number of model pixels whose centre lies on an observed (finite) pixel; a SceneError
    naming the file and HDU where there is none."""
    rp = _require_reproject()
    finite = np.isfinite(obs.data).astype(np.float64)
    m, fp = rp.reproject_interp((finite, obs.wcs), wcs_out, shape_out=tuple(shape_out), order="nearest-neighbor")
    n = int(np.sum((fp > 0) & (m > 0.5)))
    if n == 0:
        ny, nx = obs.data.shape
        c_obs = obs.wcs.pixel_to_world_values((nx - 1) / 2.0, (ny - 1) / 2.0)
        c_mod = wcs_out.pixel_to_world_values((shape_out[1] - 1) / 2.0, (shape_out[0] - 1) / 2.0)
        raise SceneError(f"image {obs.label}", "no overlap with the model image",
                         f"must overlap the model image: the image is centred at (RA, Dec) = ({float(c_obs[0]):.5f}, "
                         f"{float(c_obs[1]):.5f}) deg, the model image at ({float(c_mod[0]):.5f}, "
                         f"{float(c_mod[1]):.5f}) deg (observer.ra, observer.dec; its field: --size, grid.length, "
                         "observer.distance)")
    return n


# --------------------------------------------------------------------------------------------
# the model image


@dataclass
class ModelImage:
    """The calibrated model image of one band or passband (FITS order (ny, nx) = (H, W)).

    Attributes
    ----------
    image, error : ndarray
        Surface brightness and its batch-means Monte Carlo error, MJy/sr.
    wcs : astropy.wcs.WCS
        The calibrated image's own WCS (:func:`nebula_rt.observe.calibrate.celestial_wcs`).
    band : str
        The band's name or the passband's speclite name.
    cal : nebula_rt.observe.calibrate.CalibratedSky
    photons, batches : int
    """

    image: np.ndarray
    error: np.ndarray
    wcs: object
    band: str
    cal: object
    photons: int
    batches: int


def _select(cal, kind: tuple) -> np.ndarray:
    """The (W, H) image of ``kind`` (:func:`resolve_band`) in ``cal``."""
    if kind[0] == "band":
        return cal.surface_brightness[kind[1]]
    return cal.passband_sb[cal.passbands.index(kind[1])]


def check_pixel_batches(scene, size: int) -> None:
    """The per-pixel batch images of the model's trace must fit :data:`MAX_PIXEL_BATCH_BYTES`."""
    import math as _m


    photons, target = scene.transport.effective()
    nvox = _m.prod(scene.grid.shape)
    m = batch_count(photons, planned_batch_size(photons, scene.transport.batch_size, target > 0, nvox), nvox)
    need = 2 * m * len(scene.bands.resolve()) * size * size * 8
    if need > MAX_PIXEL_BATCH_BYTES:
        raise SceneError("--size", size, f"the model's per-pixel batch images would take {need / 2**30:.1f} GiB "
                         f"({m} batches; at most {MAX_PIXEL_BATCH_BYTES / 2**30:.0f} GiB): lower --size, or set "
                         "transport.batch_size for fewer batches")


def model_image(scene, kind: tuple, camera, backend=None, progress=None, cancel=None, comm=None) -> ModelImage:
    """Trace ``scene`` with the peel-off image of ``camera``, calibrate it
    (:func:`nebula_rt.observe.calibrate.peel_off_sky`) and give the image of ``kind``
    (:func:`resolve_band`) with its Monte Carlo error: the batch-means standard error of the
    calibrated pixel, from the calibration (affine in the scattered light: L(x) + c, the stars c)
    of each batch's deviation from the mean, L(d_k) = cal(d_k) - cal(0)."""

    cal, res = calibrate.peel_off_sky(scene, camera, backend, progress=progress, cancel=cancel, pixel_batches=True,
                                      comm=comm)
    w, h = camera.size
    xb = np.asarray(res.peel_bin_batches, np.float64)
    m = xb.shape[0]
    xb = xb.reshape(m, xb.shape[1], w, h)
    slum = np.asarray(res.star_band_luminosity, np.float64)
    tau0 = np.zeros((len(scene.stars), xb.shape[1]))
    zero = _select(calibrate.calibrate(scene, camera, np.zeros_like(xb[0]), slum, tau0), kind)
    total = xb.sum(axis=0)
    m2 = np.zeros((w, h))
    for k in range(m):
        dev = _select(calibrate.calibrate(scene, camera, m * xb[k] - total, slum, tau0), kind) - zero
        m2 += dev * dev
    err = np.sqrt(m2 / (m * max(m - 1, 1))) if m > 1 else np.abs(_select(cal, kind) - zero)
    name = kind[2]
    return ModelImage(image=_select(cal, kind).T.copy(), error=err.T.copy(), wcs=cal.wcs, band=name, cal=cal,
                      photons=int(res.photons), batches=int(m))


# --------------------------------------------------------------------------------------------
# chi^2


@dataclass
class ImageComparison:
    """Residual image, pulls and chi^2 of a model against an observed image on one grid."""

    residual: np.ndarray
    pull: np.ndarray
    chi2: float
    n: int
    mask: Optional[np.ndarray] = None


def compare_image(model, model_err, observed, observed_err, mask=None) -> ImageComparison:
    """chi^2 of ``observed`` (2-D) against ``model`` on the same grid, errors in quadrature.

    Parameters
    ----------
    model, model_err : array_like (H, W)
        The model image (FITS order) and its 1-sigma Monte Carlo error.
    observed, observed_err : array_like (H, W)
        The observation and its 1-sigma error.
    mask : array_like of bool (H, W), optional
        Pixels to use (default every pixel); of those, only where all four are finite and the
        combined error is > 0.
    """
    arrays = {"model": model, "model_err": model_err, "observed": observed, "observed_err": observed_err}
    a = {k: np.asarray(v, np.float64) for k, v in arrays.items()}
    shape = a["observed"].shape
    if a["observed"].ndim != 2:
        raise SceneError("observed", shape, "must be a 2-D image")
    for k, v in a.items():
        if v.shape != shape:
            raise SceneError(k, v.shape, f"must have the observed image's shape {shape} (reproject it first: "
                                         "reproject_to_model)")
    var = a["observed_err"] ** 2 + a["model_err"] ** 2
    ok = np.isfinite(a["model"]) & np.isfinite(a["observed"]) & np.isfinite(var) & (var > 0)
    if mask is not None:
        ok &= np.asarray(mask, bool)
    if not ok.any():
        raise SceneError("observed_err", "no usable pixel", "needs pixels with finite values and errors > 0")
    res = a["observed"] - a["model"]
    with np.errstate(divide="ignore", invalid="ignore"):
        pull = np.where(ok, res / np.sqrt(var), np.nan)
    return ImageComparison(residual=np.where(ok, res, np.nan), pull=pull, chi2=float(np.nansum(pull ** 2)),
                           n=int(ok.sum()), mask=ok)


def star_mask(cal, radius_arcsec: float) -> np.ndarray:
    """(H, W) True within ``radius_arcsec`` of a star's pixel (False everywhere for radius 0)."""
    w, h = cal.surface_brightness.shape[1:]
    return _star_mask((w, h), cal.star_pixel, cal.pixel_scale_arcsec, radius_arcsec)


def _star_mask(size, star_pixel, pixel_arcsec: float, radius_arcsec: float) -> np.ndarray:
    """(H, W) True within ``radius_arcsec`` of a star at ``star_pixel`` ((n, 2) image pixel
    coordinates) in an image of ``size`` (W, H) and pixels of ``pixel_arcsec``."""
    w, h = size
    out = np.zeros((h, w), bool)
    if radius_arcsec > 0:
        r = radius_arcsec / pixel_arcsec
        yy, xx = np.indices((h, w))
        for p, q in star_pixel:
            out |= (xx - p) ** 2 + (yy - q) ** 2 <= r * r
    return out


@dataclass
class ImageResult:
    """A model image against an observation: :func:`compare_observed_image`'s result."""

    model: ModelImage
    observed: Reprojected
    comparison: ImageComparison
    image: str
    masked_stars_arcsec: float = 0.0

    @property
    def p_value(self) -> float:
        from scipy.stats import chi2

        return float(chi2.sf(self.comparison.chi2, self.comparison.n))

    def to_dict(self) -> dict:
        c, o, m = self.comparison, self.observed, self.model
        ok = c.mask
        omega = m.cal.pixel_solid_angle_sr
        return {
            "image": self.image, "band": m.band, "unit": SB_UNIT, "reproject": o.mode,
            "error_propagation": o.variance, "reprojections_for_errors": o.passes,
            "observed_pixels_per_model_pixel": round(o.pixel_ratio, 6),
            "model_pixel_arcsec": round(m.cal.pixel_scale_arcsec, 6), "pixels": c.n,
            "chi2": c.chi2, "dof": c.n, "reduced_chi2": c.chi2 / c.n, "p_value": self.p_value,
            "photons_per_band": m.photons, "batches": m.batches,
            "median_model_to_data_error": float(np.median(m.error[ok] / np.maximum(o.error[ok], 1e-300))),
            "model_flux_jy": float(np.sum(m.image[ok]) * omega * 1e6),
            "observed_flux_jy": float(np.sum(o.data[ok]) * omega * 1e6),
            "masked_stars_arcsec": self.masked_stars_arcsec,
        }


@dataclass
class PreparedImage:
    """An observation reprojected onto the model image, checked before any tracing
    (:func:`prepare_observed_image`): the band, the camera and its WCS, the reprojection."""

    kind: tuple
    camera: object
    wcs: object
    observed: Reprojected
    mask_stars_arcsec: float


def prepare_observed_image(scene, obs: ObservedImage, *, band=None, direction=(0.0, 0.0, -1.0),
                           size: int = COMPARISON_SIZE, mode: str = "exact",
                           mask_stars_arcsec: float = 0.0) -> PreparedImage:
    """What :func:`compare_observed_image` does before its trace: every check (the band, the
    scene on the sky, the overlap, a model pixel wholly inside the image, a star mask that
    leaves some) and the reprojection. The command line runs it in its start-up, where the
    ranks of an MPI job agree on a refusal (one message), and hands it to the comparison.

    Raises
    ------
    SceneError
        As :func:`compare_observed_image`, before anything is traced.
    """
    calibrate.check_scene(scene)
    kind = resolve_band(scene, band, obs.header_band)
    r = mask_stars_arcsec
    if not (isinstance(r, (int, float)) and math.isfinite(r) and r >= 0):
        raise SceneError("--mask-stars", mask_stars_arcsec, "must be a radius in arcsec >= 0")
    check_pixel_batches(scene, size)
    cam = calibrate.camera_for(scene, direction, size)
    wcs = calibrate.celestial_wcs(scene, cam)
    shape = (cam.size[1], cam.size[0])
    check_overlap(obs, wcs, shape)
    rep = reproject_to_model(obs, wcs, shape, mode)
    if not rep.usable.any():
        raise SceneError(f"image {obs.label}", "no model pixel wholly inside it",
                         "must cover at least one whole model pixel with finite values and errors (a larger image, "
                         "or a larger --size for smaller model pixels)")
    # the stars' pixels are known before the trace: a radius that leaves no pixel is refused
    # here, by name, rather than after the trace as an empty comparison
    pixel_arcsec = calibrate.pixel_angle(scene, cam) / calibrate.ARCSEC_RAD  # as the calibration's
    masked = _star_mask(cam.size, calibrate.star_pixels(scene, cam), pixel_arcsec, mask_stars_arcsec)
    if not (rep.usable & ~masked).any():
        raise SceneError("--mask-stars", mask_stars_arcsec,
                         f"leaves none of the {int(rep.usable.sum())} model pixels the image covers to compare: "
                         f"must be a radius in arcsec >= 0 that leaves some (model pixels of {pixel_arcsec:.4g} "
                         "arcsec)")
    return PreparedImage(kind=kind, camera=cam, wcs=wcs, observed=rep, mask_stars_arcsec=float(mask_stars_arcsec))


def compare_observed_image(scene, obs: ObservedImage, *, band=None, direction=(0.0, 0.0, -1.0), size: int = COMPARISON_SIZE,
                           mode: str = "exact", mask_stars_arcsec: float = 0.0, backend=None, progress=None,
                           cancel=None, comm=None, prepared: Optional[PreparedImage] = None) -> ImageResult:
    """Hold ``scene``'s calibrated peel-off image against ``obs``: the observation reprojected
    onto the model image (checked before any tracing), the trace, residuals and chi^2.

    Parameters
    ----------
    scene : nebula_rt.scene.Scene
        With ``[observer]`` distance and stars in physical units (:func:`nebula_rt.observe.calibrate.check_scene`).
    obs : ObservedImage
    band : str, optional
        A scene band or a passband's speclite name (default: the image header's BAND or FILTER).
    direction : (3,) float
        Viewing direction, from the observer into the scene.
    size : int
        Model image pixels per side (over the box's projection, :func:`nebula_rt.observe.calibrate.camera_for`).
    mode : str
        Reprojection, ``exact`` or ``interp``.
    mask_stars_arcsec : float
        Leave out pixels within this radius of each star (its PSF core, often saturated).
    cancel : callable or CancelToken, optional
        As for :func:`nebula_rt.transport.trace`.
    comm : communicator, optional
        The ranks that share the trace (:mod:`nebula_rt.backends.parallel`), as for
        :func:`nebula_rt.transport.trace`: every rank gets the same result.
    prepared : PreparedImage, optional
        :func:`prepare_observed_image`'s result for these arguments, if already made.
    """

    if prepared is None:
        prepared = prepare_observed_image(scene, obs, band=band, direction=direction, size=size, mode=mode,
                                          mask_stars_arcsec=mask_stars_arcsec)
    rep = prepared.observed
    mod = model_image(scene, prepared.kind, prepared.camera, backend, progress=progress, cancel=cancel, comm=comm)
    mask = rep.usable & ~star_mask(mod.cal, prepared.mask_stars_arcsec)
    comp = compare_image(mod.image, mod.error, rep.data, rep.error, mask=mask)
    return ImageResult(model=mod, observed=rep, comparison=comp, image=obs.label,
                       masked_stars_arcsec=prepared.mask_stars_arcsec)


# --------------------------------------------------------------------------------------------
# outputs


def plot(result: ImageResult, path, title: str = "") -> None:
    """Model, data and residuals side by side (PNG), north up on the model's WCS: model and data
    on one asinh scale, the residual in units of the combined error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import AsinhNorm

    m, o, c = result.model, result.observed, result.comparison
    ok = c.mask
    both = np.concatenate([m.image[ok], o.data[ok]])
    lo, hi = np.percentile(both, [1.0, 99.5])
    width = max(float(np.median(o.error[ok])), 1e-12 * max(abs(hi), 1e-30))
    norm = AsinhNorm(linear_width=width, vmin=lo, vmax=hi)
    fig = plt.figure(figsize=(15.5, 5.2))
    panels = [("model", np.where(np.isfinite(m.image), m.image, np.nan), norm, "magma", SB_UNIT),
              ("observed (reprojected)", np.where(o.footprint > 0, o.data, np.nan), norm, "magma", SB_UNIT),
              ("residual / error", c.pull, None, "RdBu_r", "(data - model) / sigma")]
    for k, (name, img, nm, cmap, label) in enumerate(panels):
        ax = fig.add_subplot(1, 3, k + 1, projection=m.wcs)
        kw = {"norm": nm} if nm is not None else {"vmin": -5.0, "vmax": 5.0}
        cm = plt.get_cmap(cmap).with_extremes(bad="0.75")
        im = ax.imshow(img, origin="lower", cmap=cm, interpolation="nearest", **kw)
        ax.set_title(name)
        ax.coords.grid(color="white" if k < 2 else "black", alpha=0.25, linestyle="solid")  # shows north and east
        ax.coords[0].set_axislabel("RA")
        ax.coords[1].set_axislabel("Dec" if k == 0 else " ")
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label=label)
    fig.suptitle(title or f"{result.image}: chi2 = {c.chi2:.1f} for {c.n} pixels")
    fig.tight_layout()
    fig.savefig(str(path), dpi=90, format="png")
    plt.close(fig)


def write_fits(path, result: ImageResult) -> None:
    """The comparison as FITS on the model image's WCS: MODEL, MODEL_ERR, DATA, DATA_ERR,
    RESIDUAL (MJy/sr), PULL (residual / combined error; NaN where not used) and FOOTPRINT."""
    from astropy.io import fits

    hdr = fits.Header()
    hdr["ORIGIN"] = "NebulaRT"
    for k, v in (("IMAGE", result.image[-68:]), ("BAND", result.model.band), ("REPROJ", result.observed.mode),
                 ("CHI2", result.comparison.chi2), ("NPIX", result.comparison.n), ("PVALUE", result.p_value),
                 ("NPHOTON", result.model.photons)):
        hdr[k] = v
    w = result.model.wcs.to_header()
    hdus = [fits.PrimaryHDU(header=hdr)]
    for name, arr, unit in (("MODEL", result.model.image, SB_UNIT), ("MODEL_ERR", result.model.error, SB_UNIT),
                            ("DATA", result.observed.data, SB_UNIT), ("DATA_ERR", result.observed.error, SB_UNIT),
                            ("RESIDUAL", result.comparison.residual, SB_UNIT), ("PULL", result.comparison.pull, ""),
                            ("FOOTPRINT", result.observed.footprint, "")):
        h = w.copy()
        h["BUNIT"] = unit
        hdus.append(fits.ImageHDU(np.asarray(arr, np.float32), header=h, name=name))
    fits.HDUList(hdus).writeto(str(path), overwrite=True)
