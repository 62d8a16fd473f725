"""Simulated nebulae against observed ones: B-V colour and nebula/star ratio versus offset.

What an observer measures of a reflection nebula is its colour relative to the star that lights
it. From a sky image (:func:`nebula_rt.sky.sky_image`, scattered light only) this module
measures, in annuli of projected offset from the star:

- Delta(B-V) = (B-V)_nebula - (B-V)_star in the Bessell B and V passbands (Bessell 1990,
  PASP 102, 1181; the curves shipped by ``speclite``): with r_b the nebula/star ratio of band b, r(lambda) its hat-function
  interpolation (as the colour conversion does) and S the star's spectrum,

      Delta(B-V) = -2.5 log10[ (int r S B dl / int S B dl) / (int r S V dl / int S V dl) ];

- the nebula/star ratio r_b per band, relative to the band nearest 550 nm.

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

from .colour_convert import hat_basis, star_spectrum

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11
    import tomli as tomllib

PASSBANDS = {"B": "bessell-B", "V": "bessell-V"}


@functools.lru_cache(maxsize=None)
def passband(name: str) -> tuple[np.ndarray, np.ndarray]:
    """(wavelength nm, response) of a Bessell passband ("B" or "V"), from speclite."""
    import speclite.filters

    f = speclite.filters.load_filter(PASSBANDS[name])
    return np.asarray(f.wavelength, np.float64) / 10.0, np.asarray(f.response, np.float64)


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
        Delta(B-V), mag.
    ratio : ndarray (n_bands, n_bins)
        Nebula/star ratio per band relative to the band nearest 550 nm.
    wavelength_nm : ndarray (n_bands,)
    pixels : ndarray (n_bins,)
        Pixels with scattered light in each annulus.
    """

    offset: np.ndarray
    delta_bv: np.ndarray
    ratio: np.ndarray
    wavelength_nm: np.ndarray
    pixels: np.ndarray


def _annuli(scattered, img_origin, pixel_size, u, v, star_pos, direction, band_lum, wl, source, edges):
    """Profiles from a scattered-light image (n_bands, W, H) whose pixel (p, q) is centred at
    img_origin + pixel_size (p u + q v)."""
    nb, w, h = scattered.shape
    P, Q = np.meshgrid(np.arange(w), np.arange(h), indexing="ij")
    centres = img_origin[None, None, :] + pixel_size * (P[..., None] * u + Q[..., None] * v)
    dvec = np.asarray(direction, float) / np.linalg.norm(direction)
    rel = np.asarray(star_pos) - centres
    offset = np.linalg.norm(rel - (rel @ dvec)[..., None] * dvec, axis=-1)
    edges = np.linspace(0.0, 0.5, 9) if edges is None else np.asarray(edges, float)
    nbins = len(edges) - 1
    summed = np.zeros((nb, nbins))
    pixels = np.zeros(nbins, int)
    lit = scattered.sum(axis=0) > 0
    for k in range(nbins):
        m = (offset >= edges[k]) & (offset < edges[k + 1]) & lit
        pixels[k] = int(m.sum())
        summed[:, k] = scattered[:, m].sum(axis=1)
    r = summed / np.asarray(band_lum)[:, None]
    vb = int(np.argmin(np.abs(wl - 550.0)))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(r[vb] > 0, r / r[vb], np.nan)
    return Profiles(offset=0.5 * (edges[1:] + edges[:-1]), delta_bv=delta_b_minus_v(r, wl, source),
                    ratio=ratio, wavelength_nm=wl, pixels=pixels)


def _camera(star, direction, size):
    from .sky import Camera

    return Camera(direction=tuple(direction), size=(size, size), extent=1.0, center=tuple(star.position))


def profiles(light, direction=(0.0, 0.0, -1.0), size: int = 128, edges=None) -> Profiles:
    """Measure a light field (:class:`nebula_rt.pipeline.LightField`) as an observer would,
    from its sky image (ray marching the emissivity, which treats each voxel's scattered
    light as isotropic: exact for g = 0 only; :func:`observe_scene` has the phase function).

    The scattered light is summed over annuli of projected distance from the most luminous star
    (``edges``, box units; default 8 annuli out to 0.5), each band divided by the stars'
    luminosity in that band.
    """
    from .pipeline import _dominant_source
    from .sky import sky_image

    bands = light.bands
    wl = np.array([b.wavelength for b in bands])
    rho = light.density.astype(np.float64)
    sigma = np.array([light.scene.dust.tau * b.extinction for b in bands])[:, None, None, None] * rho[None]
    star = max(light.scene.stars, key=lambda s: s.luminosity)
    img = sky_image(light.emissivity.astype(np.float64), sigma, _camera(star, direction, size))
    return _annuli(img.scattered, img.origin, img.pixel_size, img.u_axis, img.v_axis, star.position, direction,
                   light.transport.band_luminosity, wl, _dominant_source(light.scene.stars), edges)


def observe_scene(scene, direction=(0.0, 0.0, -1.0), size: int = 128, edges=None, backend=None,
                  progress=None, cancel=None) -> tuple[Profiles, object]:
    """Trace ``scene`` with a peel-off image seen along ``direction`` (the phase function at
    every scattering towards the observer: forward and backward scattering as they are) and
    measure it as :func:`profiles` does. Returns (profiles, transport result)."""
    from .backends import get_backend
    from .density import generate_density
    from .pipeline import _dominant_source
    from .transport import trace

    backend = backend or get_backend(scene.transport.backend, scene.transport.device)
    bands = scene.bands.resolve()
    wl = np.array([b.wavelength for b in bands])
    star = max(scene.stars, key=lambda s: s.luminosity)
    cam = _camera(star, direction, size)
    t = scene.transport
    photons, target = t.effective()
    res = trace(generate_density(scene, backend), bands, scene.stars, tau=scene.dust.tau, photons=photons,
                estimator=t.estimator, max_scatterings=t.max_scatterings, seed=t.seed,
                batch_size=t.batch_size, backend=backend, target_error=target, time_limit=t.time_limit,
                progress=progress, cancel=cancel, peel=cam)
    d, u, v = cam.basis()
    prof = _annuli(res.peel_image, cam.origin(), cam.pixel_size, u, v, star.position, direction,
                   res.band_luminosity, wl, _dominant_source(scene.stars), edges)
    return prof, res


def plot(prof: Profiles, path, title: str = "") -> None:
    """Delta(B-V) versus offset and the nebula/star ratio versus wavelength, beside the shipped
    observations, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    obs = observations()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2))
    ok = np.isfinite(prof.delta_bv) & (prof.pixels > 0)
    a1.plot(prof.offset[ok], prof.delta_bv[ok], "o-", color="C0", label="simulated")
    lo, hi = obs["single_scattering_delta_bv"]["range"]
    a1.axhspan(lo, hi, color="C2", alpha=0.15, label="single scattering, 20-135 deg (model)")
    a1.axhline(obs["mean_delta_bv"]["value"], color="C3", ls="--", label="observed mean")
    a1.axhline(0.0, color="k", lw=0.6)
    a1.set_xlabel("projected offset from the star (box units)")
    a1.set_ylabel("Delta(B-V) nebula - star (mag)")
    a1.legend(fontsize=8)
    a1.grid(alpha=0.3)
    cmap = plt.get_cmap("viridis")
    for k in range(prof.ratio.shape[1]):
        if prof.pixels[k] and np.all(np.isfinite(prof.ratio[:, k])):
            order = np.argsort(prof.wavelength_nm)
            a2.plot(prof.wavelength_nm[order], prof.ratio[order, k], "-", color=cmap(k / max(1, prof.ratio.shape[1] - 1)),
                    label=f"offset {prof.offset[k]:.2f}")
    s90 = obs["single_scattering_ratio_90deg"]
    a2.plot(s90["wavelength_nm"], s90["ratio"], "ks", label="single scattering 90 deg (model)")
    a2.set_xlabel("wavelength (nm)")
    a2.set_ylabel("nebula/star ratio relative to 550 nm")
    a2.legend(fontsize=7, ncol=2)
    a2.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
