"""Simulated nebulae against observed ones: B-V colour and nebula/star ratio versus offset.

What an observer measures of a reflection nebula is its colour relative to the star that lights
it. From a sky image (:func:`nebula_rt.observe.sky.sky_image`, scattered light only) this module
measures, in annuli of projected offset from the star:

- Delta(B-V) = (B-V)_nebula - (B-V)_star in the Bessell B and V passbands (Bessell 1990,
  PASP 102, 1181; the curves shipped by ``speclite``): with r_b the nebula/star ratio of band b, r(lambda) its hat-function
  interpolation (as the colour conversion does) and S the star's spectrum,

      Delta(B-V) = -2.5 log10[ (int r S B dl / int S B dl) / (int r S V dl / int S V dl) ];

- the nebula/star ratio r_b per band, relative to the band nearest 550 nm.

The star is the reference, and there are two (``reference``):

- ``"observed"`` (default): the star as seen, through the dust between it and the observer,
  as an observer measures it: its light in band b times exp(-tau_b), tau_b the optical depth
  from the star to the box's edge towards the observer (:func:`line_of_sight_tau`, an exact
  march through the voxels). Then Delta(B-V) = Delta(B-V)_intrinsic - E(B-V)_star, with
  E(B-V)_star = (B-V)_seen - (B-V)_intrinsic of the star (:func:`star_reddening`), and r_b is
  divided by exp(-tau_b);
- ``"intrinsic"``: the star's own light, as if nothing stood in front of it.

Errors: a peel-off run keeps every batch's annulus sums (``trace(peel_bins=...)``); each
statistic is linearised in them (for Delta(B-V): the passband-weighted sums of the bands) and
its batch-means standard error taken from the batch values of that linear combination, which
holds the correlations between bands and pixels that one packet's many peel-offs make.

Observed values and model predictions to compare with ship in ``data/observations.toml``,
each with its source. :func:`observe_scene` (used by ``nebula-rt compare``) images the
scattered light by peel-off during the transport, so the phase function's dependence on the
scattering angle (and on wavelength through g) is in the colours; :func:`profiles` measures an
existing light field through its isotropic-emissivity sky image instead.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from importlib import resources

import numpy as np

from ..scene import units
from ..optics.colour_convert import hat_basis, star_spectrum
from ..density.generate import scene_density
from ..density.octree import Octree
from ..errors import SceneError
from ..transport.line_of_sight import density_column, line_of_sight_tau
from ..pipeline.outputs import Publication
from ..pipeline.rgba import _dominant_source
from .sky import Camera, sky_image
from ..transport.estimate import batch_standard_error
from ..transport.request import TransportRequest, scene_backend
from ..scene.sky_schema import COMPARISON_SIZE

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11
    import tomli as tomllib

#: the passbands of the colours (Delta(B-V)); the table is nebula_rt.scene.units.PASSBANDS
COLOUR_PASSBANDS = ("B", "V")
#: What Delta(B-V) and the nebula/star ratio are measured against: the star as seen through
#: the dust in front of it (default) or its intrinsic light.
REFERENCES = ("observed", "intrinsic")
REFERENCE_LABELS = {"observed": "star as seen", "intrinsic": "star's intrinsic colour"}


def passband(name: str) -> tuple[np.ndarray, np.ndarray]:
    """(wavelength nm, response) of a Bessell passband of the colours ("B" or "V"):
    :func:`nebula_rt.scene.units.passband`."""
    if name not in COLOUR_PASSBANDS:
        raise KeyError(name)
    return units.passband(units.PASSBANDS[name])


def passband_weights(band_wavelengths_nm, source, name: str) -> np.ndarray:
    """w_b such that int r S X dl / int S X dl = sum_b w_b r_b for passband X (1 nm grid)."""
    wl_x, resp = passband(name)
    wl = np.arange(np.ceil(wl_x[0]), np.floor(wl_x[-1]) + 1.0)
    x = np.interp(wl, wl_x, resp)
    sx = star_spectrum(source, wl) * x
    h = hat_basis(band_wavelengths_nm, wl)
    return np.trapezoid(h * sx[None, :], wl, axis=1) / np.trapezoid(sx, wl)


def delta_b_minus_v(ratio, band_wavelengths_nm, source) -> np.ndarray:
    """Delta(B-V) (mag) of nebula/star ratios ``ratio`` (n_bands, ...); NaN where not positive."""
    r = np.asarray(ratio, np.float64)
    wb = passband_weights(band_wavelengths_nm, source, "B")
    wv = passband_weights(band_wavelengths_nm, source, "V")
    fb = np.tensordot(wb, r, axes=(0, 0))
    fv = np.tensordot(wv, r, axes=(0, 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        out = -2.5 * np.log10(fb / fv)
    return np.where((fb > 0) & (fv > 0), out, np.nan)


def star_transmission(tau_b, band_wavelengths_nm, wl_nm, rv: str = "3.1") -> np.ndarray:
    """exp(-tau(lambda)) on ``wl_nm`` of light seen through optical depths ``tau_b`` per band:
    tau linear in wavelength between the band centres (the hat functions of the colours), and
    beyond the outermost centres the dust's own extinction law, Draine's (2003) table of
    ``rv`` (``nebula_rt.scene.units.dust_model`` of the scene's bands) scaled to the outermost
    band: tau(lambda) = tau_edge C_ext(lambda) / C_ext(lambda_edge). (Holding the end band's
    tau, as the scattered light's ratio is held, would make a reddened star too faint in a
    passband reaching past the bands: SDSS i by 0.013 mag at tau_V 0.76.)"""
    from ..optics import dust_tables

    wl_b = np.asarray(band_wavelengths_nm, np.float64)
    t = np.asarray(tau_b, np.float64)
    wl = np.asarray(wl_nm, np.float64)
    tau = t @ hat_basis(wl_b, wl)
    table = dust_tables.draine_table(rv)

    def cext(x):
        return np.interp(x, table["wavelength_nm"], table["cext"])

    for edge, beyond in ((int(np.argmin(wl_b)), wl < wl_b.min()), (int(np.argmax(wl_b)), wl > wl_b.max())):
        tau[beyond] = t[edge] * cext(wl[beyond]) / cext(wl_b[edge])
    return np.exp(-tau)


def star_reddening(tau_b, band_wavelengths_nm, source, rv: str = "3.1") -> float:
    """E(B-V) = (B-V)_seen - (B-V)_intrinsic (mag) of a star of spectrum ``source`` seen
    through optical depths ``tau_b`` per band: its spectrum times :func:`star_transmission`
    through the Bessell passbands (the colours' weighting, int S T X dl / int S X dl)."""
    colours = []
    for name in ("B", "V"):
        wl_x, resp = passband(name)
        wl = np.arange(np.ceil(wl_x[0]), np.floor(wl_x[-1]) + 1.0)
        sx = star_spectrum(source, wl) * np.interp(wl, wl_x, resp)
        trans = star_transmission(tau_b, band_wavelengths_nm, wl, rv)
        colours.append(np.trapezoid(sx * trans, wl) / np.trapezoid(sx, wl))
    return float(-2.5 * np.log10(colours[0] / colours[1]))


def _check_reference(reference: str) -> str:
    if reference not in REFERENCES:

        raise SceneError("reference", reference, f"must be one of {', '.join(REFERENCES)}")
    return reference


@functools.lru_cache(maxsize=None)
def observations() -> dict:
    """The shipped observed values and model predictions (``data/observations.toml``)."""
    text = resources.files("nebula_rt").joinpath("data/observations.toml").read_text(encoding="utf-8")
    return tomllib.loads(text)


@dataclass
class Profiles:
    """Colour of the scattered light versus projected offset from the star.

    Attributes
    ----------
    offset : ndarray (n_bins,)
        Centre of each annulus, box units.
    delta_bv : ndarray (n_bins,)
        Delta(B-V) against ``reference``, mag.
    ratio : ndarray (n_bands, n_bins)
        Nebula/star ratio per band relative to the band nearest 550 nm, against ``reference``.
    wavelength_nm : ndarray (n_bands,)
    pixels : ndarray (n_bins,)
        Pixels with scattered light in each annulus.
    reference : str
        "observed" (the star as seen through its dust) or "intrinsic".
    star_tau : ndarray (n_bands,)
        Optical depth from the star to the box's edge towards the observer.
    star_ebv : float
        E(B-V) of the star as seen, mag: Delta(B-V)_observed = Delta(B-V)_intrinsic - star_ebv.
    delta_bv_err, ratio_err : ndarray
        Batch-means standard errors (1 sigma) of ``delta_bv`` and ``ratio``; NaN where there
        is no estimate (:func:`profiles`, whose sky image has none).
    batches : int
        Batches behind the errors (0: none).
    """

    offset: np.ndarray
    delta_bv: np.ndarray
    ratio: np.ndarray
    wavelength_nm: np.ndarray
    pixels: np.ndarray
    reference: str = "observed"
    star_tau: np.ndarray = None
    star_ebv: float = 0.0
    delta_bv_err: np.ndarray = None
    ratio_err: np.ndarray = None
    batches: int = 0

    @property
    def delta_bv_intrinsic(self) -> np.ndarray:
        """Delta(B-V) against the star's intrinsic colour."""
        return self.delta_bv + self.star_ebv if self.reference == "observed" else self.delta_bv

    @property
    def delta_bv_observed(self) -> np.ndarray:
        """Delta(B-V) against the star as seen."""
        return self.delta_bv if self.reference == "observed" else self.delta_bv - self.star_ebv


def _offsets(img_origin, pixel_size, u, v, size, star_pos, direction) -> np.ndarray:
    """Projected distance (box units) of every pixel centre from the star, (W, H); pixel
    (p, q) is centred at img_origin + pixel_size (p u + q v)."""
    w, h = size
    P, Q = np.meshgrid(np.arange(w), np.arange(h), indexing="ij")
    centres = img_origin[None, None, :] + pixel_size * (P[..., None] * u + Q[..., None] * v)
    dvec = np.asarray(direction, float) / np.linalg.norm(direction)
    rel = np.asarray(star_pos) - centres
    return np.linalg.norm(rel - (rel @ dvec)[..., None] * dvec, axis=-1)


def _edges(edges) -> np.ndarray:
    return np.linspace(0.0, 0.5, 9) if edges is None else np.asarray(edges, float)


def _labels(offset, edges) -> np.ndarray:
    """Annulus of each pixel (W, H): k where edges[k] <= offset < edges[k + 1], else -1."""
    k = np.searchsorted(edges, offset, side="right") - 1
    return np.where((k >= 0) & (k < len(edges) - 1), k, -1).astype(np.int64)


def _batch_error(y) -> np.ndarray:
    """Batch-means standard error of the total of per-batch values y (batches, ...)."""

    return batch_standard_error(y.sum(axis=0), (y * y).sum(axis=0), y.shape[0])


def _annuli(scattered, labels, edges, band_lum, wl, source, star_tau, reference, bin_batches=None, rv="3.1"):
    """Profiles from a scattered-light image (n_bands, W, H) and its annulus labels (W, H);
    ``bin_batches`` (batches, n_bands, n_bins): the annulus sums of every batch, for errors."""
    nb = scattered.shape[0]
    nbins = len(edges) - 1
    lit = scattered.sum(axis=0) > 0
    pixels = np.array([int(((labels == k) & lit).sum()) for k in range(nbins)])
    summed = np.zeros((nb, nbins))
    for k in range(nbins):
        summed[:, k] = scattered[:, labels == k].sum(axis=1)
    L = np.asarray(band_lum, np.float64)[:, None]
    r = summed / L  # nebula/intrinsic star, per band
    trans = np.exp(-np.asarray(star_tau, np.float64))
    ebv = star_reddening(star_tau, wl, source, rv)
    seen = trans if reference == "observed" else np.ones(nb)
    vb = int(np.argmin(np.abs(wl - 550.0)))
    rs = r / seen[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(rs[vb] > 0, rs / rs[vb], np.nan)
    delta = delta_b_minus_v(r, wl, source) - (ebv if reference == "observed" else 0.0)
    delta_err = np.full(nbins, np.nan)
    ratio_err = np.full((nb, nbins), np.nan)
    batches = 0
    if bin_batches is not None and len(bin_batches) >= 2:
        x = np.asarray(bin_batches, np.float64) / L[None]  # (M, nb, nbins) batch ratios
        batches = x.shape[0]
        wb = passband_weights(wl, source, "B")
        wv = passband_weights(wl, source, "V")
        fb, fv = wb @ r, wv @ r
        with np.errstate(divide="ignore", invalid="ignore"):
            # d Delta = -2.5 / ln 10 (sum wB dr / fB - sum wV dr / fV), per annulus; the
            # star's reddening is no Monte Carlo quantity and adds nothing
            c = -2.5 / np.log(10.0) * (wb[:, None] / fb[None] - wv[:, None] / fv[None])
            delta_err = np.where(np.isfinite(delta), _batch_error(np.einsum("bk,mbk->mk", c, x)), np.nan)
            # d ratio_b = ratio_b (dr_b / r_b - dr_v / r_v)
            y = ratio[None] * (x / r[None] - x[:, vb:vb + 1] / r[None, vb:vb + 1])
            ratio_err = np.where(np.isfinite(ratio) & (r > 0), _batch_error(np.nan_to_num(y)), np.nan)
    return Profiles(offset=0.5 * (edges[1:] + edges[:-1]), delta_bv=delta, ratio=ratio, wavelength_nm=wl,
                    pixels=pixels, reference=reference, star_tau=np.asarray(star_tau, np.float64),
                    star_ebv=ebv, delta_bv_err=delta_err, ratio_err=ratio_err, batches=batches)


def _camera(star, direction, size):

    return Camera(direction=tuple(direction), size=(size, size), extent=1.0, center=tuple(star.position))


def profiles(light, direction=(0.0, 0.0, -1.0), size: int = COMPARISON_SIZE, edges=None,
             reference: str = "observed") -> Profiles:
    """Measure a light field (:class:`nebula_rt.pipeline.LightField`) as an observer would,
    from its sky image (ray marching the emissivity, which treats each voxel's scattered
    light as isotropic: exact for g = 0 only; :func:`observe_scene` has the phase function).

    The scattered light is summed over annuli of projected distance from the most luminous star
    (``edges``, box units; default 8 annuli out to 0.5), each band divided by the stars'
    luminosity in that band, against ``reference`` ("observed": the star as seen through the
    dust in front of it; "intrinsic"). The sky image has no error estimate: the profiles'
    errors are NaN (:func:`observe_scene` has them).
    """

    _check_reference(reference)
    bands = light.bands
    wl = np.array([b.wavelength for b in bands])
    rho = light.density.astype(np.float64)
    sigma = np.array([light.scene.dust.tau * b.extinction for b in bands])[:, None, None, None] * rho[None]
    star = max(light.scene.stars, key=lambda s: s.luminosity)
    cam = _camera(star, direction, size)
    img = sky_image(light.emissivity.astype(np.float64), sigma, cam)
    e = _edges(edges)
    labels = _labels(_offsets(img.origin, img.pixel_size, img.u_axis, img.v_axis, cam.size, star.position,
                              direction), e)
    tau_star = line_of_sight_tau(sigma, star.position, -np.asarray(direction, float))
    return _annuli(img.scattered, labels, e, light.transport.band_luminosity, wl,
                   _dominant_source(light.scene.stars), tau_star, reference, rv=units.dust_model(light.scene.bands)[0])


def observe_scene(scene, direction=(0.0, 0.0, -1.0), size: int = COMPARISON_SIZE, edges=None, backend=None,
                  progress=None, reference: str = "observed", cancel=None, comm=None) -> tuple[Profiles, object]:
    """Trace ``scene`` with a peel-off image seen along ``direction`` (the phase function at
    every scattering towards the observer: forward and backward scattering as they are) and
    measure it as :func:`profiles` does, against ``reference``, with batch-means errors.
    Returns (profiles, transport result). ``comm``: the ranks that share the trace
    (:mod:`nebula_rt.backends.parallel`); every rank gets the same result."""

    _check_reference(reference)
    backend = backend or scene_backend(scene)
    bands = scene.bands.resolve()
    wl = np.array([b.wavelength for b in bands])
    star = max(scene.stars, key=lambda s: s.luminosity)
    cam = _camera(star, direction, size)
    d, u, v = cam.basis()
    e = _edges(edges)
    labels = _labels(_offsets(cam.origin(), cam.pixel_size, u, v, cam.size, star.position, direction), e)
    rho = scene_density(scene, backend)  # a grid, or an octree traced leaf by leaf
    res = TransportRequest.from_scene(scene, peel=cam, peel_bins=labels, light_field=False).trace(
        rho, backend, progress=progress, cancel=cancel, comm=comm)
    if isinstance(rho, Octree):  # the exact sum over the leaves the ray crosses
        tau_star = np.array([scene.dust.tau * b.extinction for b in bands]) * density_column(
            rho, star.position, -np.asarray(direction, float))
    else:
        sigma = np.array([scene.dust.tau * b.extinction for b in bands])[:, None, None, None] * \
            np.asarray(rho, np.float64)[None]
        tau_star = line_of_sight_tau(sigma, star.position, -np.asarray(direction, float))
    prof = _annuli(res.peel_image, labels, e, res.band_luminosity, wl, _dominant_source(scene.stars), tau_star,
                   reference, res.peel_bin_batches, rv=units.dust_model(scene.bands)[0])
    return prof, res


def plot(prof: Profiles, path, title: str = "") -> None:
    """Delta(B-V) versus offset and the nebula/star ratio versus wavelength, beside the shipped
    observations, as a PNG; error bars are the profiles' 1-sigma batch-means errors, and the
    axes name the star reference."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    obs = observations()
    ref = REFERENCE_LABELS[prof.reference]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.4))
    ok = np.isfinite(prof.delta_bv) & (prof.pixels > 0)
    err = None if prof.delta_bv_err is None else np.where(np.isfinite(prof.delta_bv_err), prof.delta_bv_err, 0.0)[ok]
    a1.errorbar(prof.offset[ok], prof.delta_bv[ok], yerr=err, fmt="o-", color="C0", capsize=3,
                label=f"simulated, against the {ref}" + (" through its dust" if prof.reference == "observed" else "")
                + " (1 sigma errors)")
    if prof.reference == "observed" and prof.star_ebv:
        a1.plot(prof.offset[ok], prof.delta_bv_intrinsic[ok], ".:", color="C7",
                label="simulated, against the star's intrinsic colour")
    lo, hi = obs["single_scattering_delta_bv"]["range"]
    a1.axhspan(lo, hi, color="C2", alpha=0.15, label="single scattering, 20-135 deg (model)")
    a1.axhline(obs["mean_delta_bv"]["value"], color="C3", ls="--", label="observed mean")
    a1.axhline(0.0, color="k", lw=0.6)
    a1.set_xlabel("projected offset from the star (box units)")
    a1.set_ylabel(f"Delta(B-V) nebula - {ref} (mag)")
    a1.set_title(f"star's E(B-V) towards the observer {prof.star_ebv:+.3f} mag "
                 f"(tau {prof.star_tau[int(np.argmin(np.abs(prof.wavelength_nm - 550.0)))]:.2f} near 550 nm)",
                 fontsize=9)
    a1.legend(fontsize=7)
    a1.grid(alpha=0.3)
    cmap = plt.get_cmap("viridis")
    order = np.argsort(prof.wavelength_nm)
    for k in range(prof.ratio.shape[1]):
        if prof.pixels[k] and np.all(np.isfinite(prof.ratio[:, k])):
            rerr = None
            if prof.ratio_err is not None and np.all(np.isfinite(prof.ratio_err[:, k])):
                rerr = prof.ratio_err[order, k]
            a2.errorbar(prof.wavelength_nm[order], prof.ratio[order, k], yerr=rerr, fmt="-", capsize=2,
                        color=cmap(k / max(1, prof.ratio.shape[1] - 1)), label=f"offset {prof.offset[k]:.2f}")
    s90 = obs["single_scattering_ratio_90deg"]
    a2.plot(s90["wavelength_nm"], s90["ratio"], "ks", label="single scattering 90 deg (model)")
    a2.set_xlabel("wavelength (nm)")
    a2.set_ylabel(f"nebula / {ref}, relative to 550 nm")
    a2.legend(fontsize=7, ncol=2)
    a2.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()

    try:  # a temporary file unique to this call, renamed onto the target once complete
        with Publication() as pub:
            fig.savefig(pub.stage(path), dpi=110)
            pub.publish()
    finally:
        plt.close(fig)
