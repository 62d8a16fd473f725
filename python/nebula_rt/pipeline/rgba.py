"""The colour stage: the light field's bands -> linear sRGB emission and opacity for the
volume renderer (colour-science's colour matching functions, the exposure, the white point)."""


import math
from typing import Optional

import numpy as np

from .. import exact_sum
from ..optics import colour_convert
from . import output_contract as contract
from ..array_api import array_module, to_numpy
from ..optics.bands import reference_band_index
from ..errors import SceneError
from ..limits import FLOAT32_MAX
from ..scene.model import Scene
from ..transport.result import TransportResult



#: Auto exposure: percentile of the per-voxel max colour component, over voxels at least this opaque.
AUTO_EXPOSURE_PERCENTILE = 95.0
AUTO_EXPOSURE_MIN_ALPHA = 0.01

#: Auto opacity (colour.opacity_scale = "auto"): the rgba volume's alpha gets the optical depth
#: scaled so that the box's mean optical depth across one edge is this. A composited ray then
#: sums S (1 - exp(-tau)) over its path, S the colour (the source function, which the opacity
#: does not change): with the dust's own opacity a thin nebula (the scene's default, tau 1: a
#: mean of 0.027) showed under 3 % of its colour and a very thick one only its near face. At 3 a
#: ray through the box keeps exp(-1.5) = 22 % of the light of the far half, so the whole nebula
#: shows and lit rays reach most of the display range; the thesis's 128^3 nebula has 3.4 of its
#: own (factor 0.88), so its picture hardly changes (docs/paraview.md has both measured).
AUTO_OPACITY_MEAN_TAU = 3.0


def mean_optical_depth(density, sigma_scale: float = 1.0) -> float:
    """The reference band's mean optical depth across the box (one box edge): ``sigma_scale``
    (extinction per box unit at density 1) x the mean density, which is also the mean over the
    box's columns, along any axis, of their optical depths.

    A float32 density (the pipeline's and the output's) is summed exactly and its mean rounded
    once (:mod:`nebula_rt.exact_sum`), as the device sums it with the density's extremes
    (:meth:`~nebula_rt.backends.base.Backend.density_mean`): the light field's colour and Nebula
    Colour's (from the output's density array) find the same bits. Other arrays (Nebula
    Colour's optical depths from the emissivity, float64) are summed in float64, one z slice at
    a time in the VTK point order (x fastest), with one slice of memory."""
    rho = to_numpy(density)
    if rho.size == 0:
        return 0.0
    if rho.dtype == np.float32:
        return float(sigma_scale) * exact_sum.mean_float32(rho)
    total = 0.0
    for k in range(rho.shape[2]):
        total += float(np.sum(np.ravel(np.asarray(rho[:, :, k], dtype=np.float64), order="F")))
    return float(sigma_scale) * (total / rho.size)


def opacity_factor(opacity_scale, mean_tau: float) -> float:
    """The factor on each voxel's optical depth in rgba's alpha: ``opacity_scale`` when it is a
    number; for ``"auto"`` the one that makes ``mean_tau`` (:func:`mean_optical_depth`)
    :data:`AUTO_OPACITY_MEAN_TAU` (1 where there is no dust to scale)."""
    if opacity_scale != "auto":
        return float(opacity_scale)
    if not (math.isfinite(mean_tau) and mean_tau > 0.0):
        return 1.0
    return AUTO_OPACITY_MEAN_TAU / mean_tau


def _voxel_edge(shape) -> float:
    """Geometric-mean voxel edge (box units): the length alpha = 1 - exp(-sigma h) uses."""
    return float(np.prod([1.0 / n for n in shape]) ** (1.0 / 3.0))


def _dominant_temperature(stars):
    """Temperature of the most luminous star (None: flat spectrum or a measured one)."""
    star = max(stars, key=lambda s: s.luminosity)
    return star.temperature or None  # (0: flat)


def colour_source_from_field_data(fd):
    """The star spectrum a light field's colours use, from its field data (a
    :class:`~nebula_rt.pipeline.output_contract.LightFieldData` or the flat mapping): the scene's most
    luminous star (measured spectrum, temperature or flat) when the scene TOML is there, else
    ``colour_temperature`` (0: flat)."""
    if not isinstance(fd, contract.LightFieldData):
        fd = contract.LightFieldData.from_field_data(fd)
    if fd.scene is not None:

        return _dominant_source(Scene.loads(fd.scene).stars)
    t = fd.colour_temperature or 0.0
    return t if t > 0 else None


def _dominant_source(stars):
    """The spectrum of the most luminous star (measured pairs, temperature or None) -- sets
    the colour matrix (the white the nebula's colours are measured against)."""
    star = max(stars, key=lambda s: s.luminosity)
    return star.spectral_source()


def scene_opacity_factor(scene, bands, rho, mean_density=None) -> float:
    """The factor on the reference band's optical depth in a scene's rgba alpha
    (:func:`opacity_factor` of ``colour.opacity_scale`` and the density ``rho``).

    ``mean_density``: ``mean_optical_depth(rho)`` (at ``sigma_scale`` 1) already summed
    (:meth:`~nebula_rt.backends.base.Backend.density_mean`); the factor has the same bits either
    way."""
    if scene.colour.opacity_scale != "auto":
        return float(scene.colour.opacity_scale)
    sigma_ref_scale = scene.dust.tau * bands[reference_band_index(bands)].extinction
    if mean_density is None:
        mean_tau = mean_optical_depth(rho, sigma_ref_scale)
    else:
        mean_tau = float(sigma_ref_scale) * float(mean_density)  # = mean_optical_depth(rho, sigma_ref_scale)
    return opacity_factor(scene.colour.opacity_scale, mean_tau)


def colour_rgba(scene, bands, rho, emissivity, res: TransportResult,
                opacity_scale: Optional[float] = None) -> tuple[np.ndarray, float]:
    """Stage 3 for a scene: see :func:`rgba_from_emissivity`. ``opacity_scale``: the factor
    already found (:func:`scene_opacity_factor` of the float32 density, whose mean the output's
    readers find again), else :func:`scene_opacity_factor` of ``rho``. Returns (rgba, exposure
    used)."""
    ref = reference_band_index(bands)
    cfg = scene.colour
    sigma_ref_scale = scene.dust.tau * bands[ref].extinction
    return rgba_from_emissivity(
        emissivity,
        sigma_ref_scale * rho,
        wavelengths_nm=np.array([b.wavelength for b in bands]),
        band_luminosity=res.band_luminosity,
        temperature=_dominant_source(scene.stars),
        exposure=cfg.exposure,
        white_point=cfg.white_point,
        opacity_scale=scene_opacity_factor(scene, bands, rho) if opacity_scale is None else opacity_scale,
        stretch=cfg.stretch,
        asinh_q=cfg.asinh_q,
    )


def colour_matrix(wavelengths_nm, band_luminosity, temperature: Optional[float], white_point: str = "D65") -> np.ndarray:
    """The (3, n_bands) matrix from band emissivities / (sigma_ref L_b) to linear sRGB.

    Bands -> XYZ with the star's spectrum and the 1 nm CIE 1931 functions (nebula/star ratio
    per band), -> linear sRGB (D65, no adaptation), then the white balance ``white_point``
    ("D65": none; "E": equal-energy white; "star": the star's own colour is white).
    """
    lum = np.asarray(band_luminosity, np.float64)
    if not (lum.size and np.all(np.isfinite(lum)) and np.all(lum > 0)):
        # colours are nebula/star ratios per band: a band without starlight has none

        raise SceneError("band_luminosity", [float(x) for x in np.atleast_1d(lum)],
                         "must be finite and > 0 in every band: a band without starlight has no "
                         "colour (the stars' spectra must emit in every band)")
    m = colour_convert.band_to_xyz_matrix(np.asarray(wavelengths_nm, np.float64), temperature)
    to_rgb = colour_convert.xyz_to_srgb_matrix() @ m / lum[None, :]
    if white_point != "D65":
        if white_point == "star":
            white = colour_convert.xyz_to_linear_srgb(m @ np.ones(len(wavelengths_nm)))
        else:  # "E": the equal-energy white
            white = colour_convert.xyz_to_linear_srgb(np.ones(3))
        to_rgb = to_rgb / (white / white.max())[:, None]  # white balance in linear sRGB
    return to_rgb


def rgba_from_emissivity(
    emissivity: np.ndarray,
    sigma_ref: np.ndarray,
    *,
    wavelengths_nm: np.ndarray,
    band_luminosity: np.ndarray,
    temperature: Optional[float],
    exposure="auto",
    white_point: str = "D65",
    opacity_scale: float = 1.0,
    return_linear: bool = False,
    stretch: str = "linear",
    asinh_q: float = 8.0,
):
    """The ``rgba`` array for direct volume rendering.

    Colour: the emissivity per unit reference-band extinction, j_b / sigma_ref, which has the
    emissivity's colour; a compositing volume renderer that multiplies it by the voxel opacity
    alpha = 1 - exp(-sigma_ref h) then integrates the emissivity along the ray with the
    reference band's attenuation. Bands -> XYZ with the star's spectrum and the 1 nm CIE 1931
    functions (nebula/star ratio per band), -> linear sRGB (D65, no adaptation), white balance
    (``white_point``), gamut mapping, one global exposure, sRGB curve.

    Parameters
    ----------
    emissivity : ndarray (n_bands, nx, ny, nz)
        a_b sigma_b J_b, luminosity per box-unit volume per steradian.
    sigma_ref : ndarray (nx, ny, nz)
        Extinction per box unit in the reference band.
    wavelengths_nm, band_luminosity : ndarray (n_bands,)
        Band centres and the stars' total luminosity per band.
    temperature : float, None or (n, 2) array
        The star spectrum used for the colour matrix: K (blackbody), None (flat) or measured
        (wavelength nm, power) pairs.
    exposure : "auto" or float
    white_point : {"D65", "E", "star"}
    opacity_scale : float or "auto"
        Multiplies the optical depth of a voxel in alpha; "auto": :func:`opacity_factor` of
        ``sigma_ref``'s mean (callers that hold the density pass the factor of
        :func:`mean_optical_depth` of it, which the device's colour uses too).
    stretch, asinh_q : str, float
        The tone curve (``colour.stretch``: "linear", the exposure and the sRGB curve, or
        "asinh", :func:`nebula_rt.optics.colour_convert.encode_asinh` with softening ``asinh_q``).
    return_linear : bool
        Also return the exposed linear sRGB (float32, (nx, ny, nz, 3)) before the sRGB curve.

    Returns
    -------
    rgba : uint8 (nx, ny, nz, 4); exposure used : float; [linear rgb]
    """
    xp = array_module(emissivity, sigma_ref)
    shape = sigma_ref.shape
    sigma_ref = xp.asarray(sigma_ref, dtype=xp.float64)
    safe = xp.where(sigma_ref > 0, sigma_ref, 1.0)
    to_rgb = colour_matrix(wavelengths_nm, band_luminosity, temperature, white_point)
    rgb = xp.tensordot(emissivity, xp.asarray(to_rgb), axes=([0], [1]))  # (nx, ny, nz, 3)
    rgb = xp.where(sigma_ref[..., None] > 0, rgb / safe[..., None], 0.0)
    rgb = colour_convert.gamut_map(rgb)
    h = _voxel_edge(shape)
    if opacity_scale == "auto":
        opacity_scale = opacity_factor("auto", mean_optical_depth(sigma_ref))
    alpha = 1.0 - xp.exp(-sigma_ref * h * opacity_scale)
    if exposure == "auto":
        # J falls as 1/r^2 from the star, so a percentile over all voxels is set by the few
        # around the star and leaves the nebula dark. Expose for the dust that is visible:
        # the 95th percentile of the voxels with at least AUTO_EXPOSURE_MIN_ALPHA opacity
        # maps to full scale (brighter voxels keep their hue and saturate).
        visible = alpha >= AUTO_EXPOSURE_MIN_ALPHA
        sample = rgb[visible] if bool(xp.any(visible)) else rgb.reshape(-1, 3)
        exposure = colour_convert.auto_exposure(sample, percentile=AUTO_EXPOSURE_PERCENTILE)
    else:
        exposure = float(exposure)
    srgb8 = colour_convert.encode_picture(rgb, exposure, stretch, asinh_q)
    a8 = xp.clip(xp.rint(alpha * 255.0), 0, 255).astype(xp.uint8)
    rgba = to_numpy(xp.concatenate([srgb8, a8[..., None]], axis=-1))
    if return_linear:
        # float32: an over-exposed colour saturates at the largest float32 instead of infinity
        linear = xp.minimum(rgb * exposure, FLOAT32_MAX)
        return rgba, float(exposure), to_numpy(linear.astype(xp.float32))
    return rgba, float(exposure)
