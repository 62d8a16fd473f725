"""Calibrated sky images: surface brightness in MJy/sr and mag/arcsec^2, a Gaussian PSF, a
celestial WCS, FITS.

A sky image in box units (:mod:`nebula_rt.observe.sky`'s ray march or the transport's peel-off) holds,
per band b, the scattered intensity I_b in traced luminosity per box-unit area per steradian.
With the stars' luminosities in L_sun (``stars.luminosity_lsun`` or ``absolute_magnitude``,
:mod:`nebula_rt.scene.units`), the box edge L (``grid.length``) and the distance D
(``observer.distance``):

- surface brightness, band-averaged per unit frequency:
  ``S_nu,b = I_b L_sun / L^2 / dnu_b`` (W m^-2 Hz^-1 sr^-1; x 1e20 for MJy/sr), dnu_b the band's
  frequency width (its edges: :func:`nebula_rt.optics.colour_convert.band_edges`, over which the band
  carries the star's light). Surface brightness does not depend on the distance;
- each star as a point source of flux density ``F_nu,b = L_b exp(-tau_b) L_sun / (4 pi D^2) /
  dnu_b``, tau_b its optical depth to the observer (:func:`nebula_rt.transport.line_of_sight.line_of_sight_tau`),
  at its projected position;
- the image (scattered light and stars) convolved with a Gaussian PSF of FWHM
  ``observer.psf_fwhm`` (arcsec), integrated over each pixel (so the flux is kept exactly
  except what the PSF carries out of the field);
- pixels of side ``theta = pixel_size L / D`` radians on the tangent plane (an exact gnomonic
  projection of the plane through the box centre perpendicular to the line of sight), the
  WCS a TAN projection with its reference point the box centre at (``observer.ra``,
  ``observer.dec``) and the image's up axis at ``observer.position_angle`` east of north;
  east is to the left at position angle 0 (the sky as seen from inside);
- in passbands X (Bessell B, V, R and SDSS g, r, i, ``speclite``), the AB surface brightness
  ``mu_X = -2.5 log10(S_nu,X arcsec^2 / 3631 Jy)`` mag/arcsec^2 (with
  ``observer.magnitude_system = "Vega"``: minus the passband's m_AB - m_Vega, Vega's own AB
  magnitude through it from the CALSPEC spectrum alpha_lyr_stis_011; ``"Vega-Blanton2007"``:
  Blanton & Roweis 2007's offsets; :func:`nebula_rt.scene.units.ab_minus_vega`), with S_nu,X the photon-counting
  mean ``int S_lambda R lambda dl / int (c / lambda^2) R lambda dl``. S_lambda is the
  per-band nebula/star ratio interpolated across wavelength (the hat functions of the colour
  conversion) times the stars' full blackbody spectrum, so the parts of a passband beyond the
  bands' range (R and i reach 900 / 840 nm) take the outermost band's ratio; each star's own
  light is its spectrum through its dust at every wavelength, the extinction law beyond the
  bands (:func:`nebula_rt.observe.colours.star_transmission`).

FITS (:func:`write_fits`): an empty primary HDU with the run's description, then one image HDU
per band (``SB_<band>``, MJy/sr) and per passband (``MAG_BESSELL_B``, ``_V``, ``_R``,
``MAG_SDSS_G``, ``_R``, ``_I``: mag/arcsec^2, AB), each with the celestial WCS, and a table
``STARS`` (FITS pixel, RA, Dec, flux densities in Jy, AB magnitudes). A polarized scene
(``bands.polarization``) adds, after the bands, ``Q_<band>`` and ``U_<band>``: Stokes Q and U
of the scattered light in MJy/sr with the same WCS, ``POLCONV = 'IAU'`` (the angle from north
through east; :mod:`nebula_rt.observe.polarimetry`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..optics import colour_convert
from ..scene import units
from ..optics.colour_convert import band_edges, hat_basis
from ..optics.blackbody import planck_lambda, stefan_boltzmann
from ..density.generate import scene_density
from ..density.octree import Octree
from ..errors import SceneError
from ..transport.line_of_sight import density_column, line_of_sight_tau
from ..pipeline.rgba import _dominant_source
from .colours import star_transmission
from .polarimetry import errors_to_celestial, stokes_hdus, to_celestial
from .psf import convolve_psf, convolve_psf_error, psf_weights
from .sky import Camera, sky_image
from ..transport.tails import fits_cards
from ..transport.request import TransportRequest, scene_backend

#: Passbands of the magnitude images: name -> speclite filter (declared with the loader)
PASSBANDS = units.PASSBANDS
#: FITS extension of each passband's magnitude image (extension names are case-blind: R and r differ by system)
PASSBAND_EXTENSIONS = {"B": "MAG_BESSELL_B", "V": "MAG_BESSELL_V", "R": "MAG_BESSELL_R", "g": "MAG_SDSS_G",
                       "r": "MAG_SDSS_R", "i": "MAG_SDSS_I"}
#: the FITS comment of each magnitude system (observer.magnitude_system; the offsets:
#: nebula_rt.scene.units.ab_minus_vega)
MAGSYS_COMMENT = {"AB": "magnitudes: AB (3631 Jy)",
                  "Vega": "magnitudes: Vega = 0 (CALSPEC alpha_lyr_stis_011)",
                  "Vega-Blanton2007": "magnitudes: Vega (AB - offset, Blanton+ 2007)"}
#: the FITS comment of a passband's ABVEGA card, by magnitude system
ABVEGA_COMMENT = {"Vega": "m_AB - m_Vega subtracted (CALSPEC Vega)",
                  "Vega-Blanton2007": "m_AB - m_Vega subtracted (Blanton+ 2007)"}
ARCSEC_RAD = math.pi / (180.0 * 3600.0)
C_LIGHT = 299_792_458.0
#: W m^-2 Hz^-1 in MJy
W_M2_HZ_PER_MJY = 1e-20
#: Sky image methods: the transport's peel-off (the phase function's angle dependence) or the
#: ray march of the emissivity (isotropic scattering per voxel; no new trace of a light field)
METHODS = ("peel-off", "ray-march")
#: The box edge may be at most this fraction of the distance: the image is a distant
#: observer's parallel projection, whose error in angle is of order (L / D)^2
MAX_BOX_OVER_DISTANCE = 0.1


def check_scene(scene) -> None:
    """What a calibrated image needs of a scene, checked before any work: a distance, every
    star's luminosity in physical units, and a box small against the distance."""
    if scene.observer.distance is None:
        raise SceneError("observer.distance", None, "must be given for a calibrated sky image: a distance "
                         "such as '140 pc' (or a number in pc)")
    for i, s in enumerate(scene.stars):
        if not units.physical_star(s):
            raise SceneError(f"stars[{i}].luminosity", s.luminosity,
                             "is in scene units: a calibrated sky image needs the luminosity in physical "
                             f"units, stars[{i}].luminosity_lsun (L_sun) or stars[{i}].absolute_magnitude, "
                             "with the star's temperature")
    box = units.box_length_cm(scene.grid) / 100.0
    dist = units.distance_metres(scene.observer)
    if not box <= MAX_BOX_OVER_DISTANCE * dist:
        raise SceneError("observer.distance", scene.observer.distance,
                         f"must be at least {1 / MAX_BOX_OVER_DISTANCE:g} box edges (grid.length = "
                         f"{scene.grid.length!r}): the sky image is a distant observer's")


def band_frequency_widths(wavelengths_nm) -> tuple[np.ndarray, np.ndarray]:
    """(edges (n, 2) nm, frequency width (n,) Hz) of each band, in the bands' order."""

    wl = np.asarray(wavelengths_nm, np.float64)
    e = band_edges(wl)
    order = np.argsort(wl)
    edges = np.empty((wl.size, 2))
    edges[order, 0], edges[order, 1] = e[:-1], e[1:]
    dnu = C_LIGHT / (edges[:, 0] * 1e-9) - C_LIGHT / (edges[:, 1] * 1e-9)
    return edges, dnu


def star_spectra(scene, wavelength_nm) -> np.ndarray:
    """L_lambda of every star (n_stars, n_wl), L_sun per m: bolometric L x pi B_lambda / (sigma T^4)."""
    wl = np.asarray(wavelength_nm, np.float64) * 1e-9
    bands = scene.bands.resolve()
    out = []
    for i, s in enumerate(scene.stars):
        _, lbol = units.star_luminosity(s, i, bands)
        out.append(lbol * math.pi * planck_lambda(wl, s.temperature)
                   / (stefan_boltzmann() * s.temperature ** 4))
    return np.array(out)


def passband_grid(name: str) -> tuple[np.ndarray, np.ndarray]:
    """(wavelength nm on a 0.25 nm grid over the passband, its response there)."""
    wl_x, resp = units.passband(PASSBANDS[name])
    wl = np.arange(math.floor(wl_x[0]), math.ceil(wl_x[-1]) + 0.25, 0.25)
    return wl, np.interp(wl, wl_x, resp, left=0.0, right=0.0)


def passband_weights(band_wavelengths_nm, wl, response, spectra) -> np.ndarray:
    """w (n_spectra, n_bands): the photon-counting mean f_nu through a passband (``wl`` nm,
    ``response``) of the spectrum ``sum_b r_b h_b(lambda) spectra[k](lambda)`` is
    ``sum_b w[k, b] r_b``; h_b the hat functions of the bands. ``spectra`` per unit wavelength
    (per m) on ``wl``; w in their units x m per Hz."""

    lam = wl * 1e-9
    h = hat_basis(band_wavelengths_nm, wl)
    norm = np.trapezoid(C_LIGHT / lam**2 * response * lam, lam)
    sp = np.atleast_2d(spectra)
    return np.trapezoid(h[None, :, :] * (sp * response * lam)[:, None, :], lam, axis=2) / norm


def passband_mean(wl, response, spectrum) -> float:
    """The photon-counting mean f_nu of ``spectrum`` (per m, on ``wl`` nm) through a passband
    (``response`` on ``wl``): int S R lambda dl / int (c / lambda^2) R lambda dl, in the
    spectrum's units x m per Hz (as :func:`passband_weights`)."""
    lam = np.asarray(wl, np.float64) * 1e-9
    return float(np.trapezoid(spectrum * response * lam, lam) / np.trapezoid(C_LIGHT / lam**2 * response * lam, lam))


def pixel_angle(scene, camera) -> float:
    """The side of one pixel of ``camera``'s image on the sky, radians (small angle: pixel side
    x box edge / distance)."""
    box_m = units.box_length_cm(scene.grid) / 100.0
    return camera.pixel_size * box_m / units.distance_metres(scene.observer)


def star_pixels(scene, camera) -> np.ndarray:
    """(n_stars, 2) image pixel coordinates (p, q) of each star in ``camera``'s image (pixel
    centres at integers)."""
    _, u, v = camera.basis()
    rel = np.array([s.position for s in scene.stars], np.float64) - camera.origin()[None, :]
    return np.stack([rel @ u / camera.pixel_size, rel @ v / camera.pixel_size], axis=1)


def celestial_wcs(scene, camera):
    """The TAN WCS of an image of ``camera`` (module docstring): FITS pixel (p + 1, q + 1) is
    image pixel [p, q]."""
    from astropy.wcs import WCS

    _, u, v = camera.basis()
    rel = np.array([0.5, 0.5, 0.5]) - camera.origin()
    ps = camera.pixel_size
    scale_deg = math.degrees(ps * units.box_length_cm(scene.grid) / 100.0 / units.distance_metres(scene.observer))
    pa = math.radians(scene.observer.position_angle)
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.cunit = ["deg", "deg"]
    w.wcs.radesys = "ICRS"
    w.wcs.crval = [scene.observer.ra, scene.observer.dec]
    w.wcs.crpix = [float(rel @ u / ps) + 1.0, float(rel @ v / ps) + 1.0]
    # (east, north) of one pixel along p (the image's u) and q (v): u points west at PA 0
    w.wcs.cd = scale_deg * np.array([[-math.cos(pa), math.sin(pa)], [math.sin(pa), math.cos(pa)]])
    w.wcs.set()
    return w


@dataclass
class CalibratedSky:
    """A calibrated sky image; images are indexed [band, p, q] with shape (n, W, H) as
    :class:`nebula_rt.observe.sky.SkyImage` (``q = 0`` the bottom row).

    Attributes
    ----------
    band_names, band_wavelength_nm : list, ndarray (nb,)
    band_edges_nm : ndarray (nb, 2)
    surface_brightness : ndarray (nb, W, H)
        Scattered light plus the stars, PSF-convolved, MJy/sr (band-averaged per unit frequency).
    scattered : ndarray (nb, W, H)
        The scattered light alone, PSF-convolved, MJy/sr.
    passbands : list of str
        Names of the passband images ("B", "V", "R", "g", "r", "i").
    passband_sb : ndarray (np, W, H)
        Photon-counting mean surface brightness through each passband, MJy/sr.
    mag : ndarray (np, W, H)
        Surface brightness, mag/arcsec^2 in ``mag_system`` (NaN where there is no light).
    star_pixel : ndarray (n_stars, 2)
        Image pixel coordinates (p, q) of each star (pixel centres at integers).
    star_flux_jy : ndarray (n_stars, nb)
        Each star's flux density as seen (through its dust), Jy.
    star_mag : ndarray (n_stars, np)
        Each star's magnitude (``mag_system``) as seen through each passband.
    intensity_box, scattered_box : ndarray (nb, W, H)
        The PSF-convolved image and its scattered light in box units (traced luminosity per
        box-unit area per sr), for the true-colour picture.
    band_luminosity : ndarray (nb,)
        The stars' traced luminosity per band, L_sun.
    wcs : astropy.wcs.WCS
    pixel_scale_arcsec, pixel_solid_angle_sr, psf_fwhm_arcsec : float
    method : str
    meta : dict
        FITS header cards of the primary HDU.
    mag_system : str
        "AB" or "Vega" (``observer.magnitude_system``).
    scattered_error : ndarray (nb, W, H) or None
        The batch-means standard error of ``scattered`` (peel-off images), MJy/sr.
    stokes, stokes_error : ndarray (nb, 2, W, H) or None
        A polarized scene's peel-off: Stokes Q and U of the scattered light, PSF-convolved,
        MJy/sr, IAU convention (angle from north through east; :mod:`nebula_rt.observe.polarimetry`),
        and their standard errors.
    """

    band_names: list
    band_wavelength_nm: np.ndarray
    band_edges_nm: np.ndarray
    surface_brightness: np.ndarray
    scattered: np.ndarray
    passbands: list
    passband_sb: np.ndarray
    mag: np.ndarray
    star_pixel: np.ndarray
    star_flux_jy: np.ndarray
    star_mag: np.ndarray
    intensity_box: np.ndarray
    scattered_box: np.ndarray
    band_luminosity: np.ndarray
    wcs: object
    pixel_scale_arcsec: float
    pixel_solid_angle_sr: float
    psf_fwhm_arcsec: float
    method: str
    meta: dict = field(default_factory=dict)
    mag_system: str = "AB"
    scattered_error: Optional[np.ndarray] = None
    stokes: Optional[np.ndarray] = None
    stokes_error: Optional[np.ndarray] = None

    def polarization(self, debias: str = "none"):
        """(P, P error, chi, chi error), each (nb, W, H): the degree of linear polarization of
        the scattered light and its angle east of north in degrees
        (:func:`nebula_rt.observe.polarimetry.polarization_maps`; ``debias="mas"``: P by the
        modified asymptotic estimator, without the Ricean bias of the raw ratio where P is
        within a few of its errors); None for an unpolarized scene."""
        if self.stokes is None:
            return None
        from .polarimetry import polarization_maps

        err = self.stokes_error
        return polarization_maps(self.scattered, self.stokes[:, 0], self.stokes[:, 1], self.scattered_error,
                                 None if err is None else err[:, 0], None if err is None else err[:, 1],
                                 debias=debias)

    def circular_polarization(self):
        """(V / I, its error), each (nb, W, H): the circular polarization of the scattered light
        (V > 0: counterclockwise as the observer sees it, IAU), first order in the errors, NaN
        where I <= 0; None without V (only Mie grains give it)."""
        if self.stokes is None or self.stokes.shape[1] < 3:
            return None
        from .polarimetry import circular_polarization

        return circular_polarization(self.scattered, self.stokes[:, 2], self.scattered_error,
                                     None if self.stokes_error is None else self.stokes_error[:, 2])

    def total_flux_jy(self) -> np.ndarray:
        """(nb,) the image's flux density, Jy: the sum of the pixels times their solid angle."""
        return self.surface_brightness.sum(axis=(1, 2)) * self.pixel_solid_angle_sr * 1e6


def calibrate(scene, camera, scattered, star_band_luminosity, tau_star, method: str = "peel-off",
              meta: Optional[dict] = None, scattered_error=None, stokes=None, stokes_error=None) -> CalibratedSky:
    """Calibrate a box-unit sky image of ``scene`` seen by ``camera`` (module docstring).

    Parameters
    ----------
    scene : nebula_rt.scene.Scene
        Validated; :func:`check_scene` must pass.
    camera : nebula_rt.observe.sky.Camera
    scattered : ndarray (nb, W, H)
        Scattered intensity, traced luminosity (L_sun) per box-unit area per steradian.
    star_band_luminosity : ndarray (n_stars, nb)
        Each star's traced luminosity per band, L_sun.
    tau_star : ndarray (n_stars, nb)
        Optical depth from each star to the observer.
    method : str
        How ``scattered`` was made (one of :data:`METHODS`), for the header.
    scattered_error : ndarray (nb, W, H), optional
        Its standard error (same units).
    stokes, stokes_error : ndarray (nb, 2, W, H), optional
        Stokes Q and U of ``scattered`` in the camera's frame (``result.peel_stokes``) and their
        errors: calibrated as the intensity, in the IAU convention.
    """
    check_scene(scene)
    bands = scene.bands.resolve()
    names = [b.name for b in bands]
    wl = np.array([b.wavelength for b in bands])
    scat = np.asarray(scattered, np.float64)
    nb, w, h = scat.shape
    slum = np.asarray(star_band_luminosity, np.float64).reshape(len(scene.stars), nb)
    tau = np.asarray(tau_star, np.float64).reshape(len(scene.stars), nb)
    edges, dnu = band_frequency_widths(wl)
    box_m = units.box_length_cm(scene.grid) / 100.0
    dist_m = units.distance_metres(scene.observer)
    ps = camera.pixel_size
    theta = pixel_angle(scene, camera)  # pixel side, rad
    omega = theta * theta
    scale_arcsec = theta / ARCSEC_RAD
    sigma_pix = scene.observer.psf_fwhm / (2.0 * math.sqrt(2.0 * math.log(2.0))) / scale_arcsec

    # stars: flux through their dust, as box-unit intensity spread by the PSF over the pixels
    star_pixel = star_pixels(scene, camera)
    seen = slum * np.exp(-tau)  # L_sun per band, as seen
    direct = np.zeros((nb, w, h))
    spots = []
    for k in range(len(scene.stars)):
        spot = np.outer(psf_weights(w, star_pixel[k, 0], sigma_pix), psf_weights(h, star_pixel[k, 1], sigma_pix))
        spots.append(spot)
        direct += (seen[k] / (4.0 * math.pi) / ps**2)[:, None, None] * spot[None]
    scat_psf = convolve_psf(scat, sigma_pix)
    box_total = scat_psf + direct
    to_mjy = (units.L_SUN_W / box_m**2 / dnu / W_M2_HZ_PER_MJY)[:, None, None]
    sb = box_total * to_mjy
    star_flux = seen * units.L_SUN_W / (4.0 * math.pi * dist_m**2) / dnu[None, :] * 1e26

    # passbands: the scattered light's ratio to the stars' light per band x their full spectrum;
    # each star's own light, its spectrum through its dust at every wavelength (the extinction
    # law beyond the bands: colours.star_transmission)
    band_lum = slum.sum(axis=0)
    ratio = scat_psf / band_lum[:, None, None]  # per box-unit area per sr
    rv = units.dust_model(scene.bands)[0]
    pb = list(PASSBANDS)
    psb = np.empty((len(pb), w, h))
    star_mag = np.empty((len(scene.stars), len(pb)))
    for x, name in enumerate(pb):
        grid, resp = passband_grid(name)
        spectra = star_spectra(scene, grid)  # L_sun per m
        wts = passband_weights(wl, grid, resp, spectra.sum(axis=0)[None])  # L_sun per Hz
        box_x = np.tensordot(wts[0], ratio, axes=(0, 0))  # L_sun per Hz per box-unit area per sr
        for k in range(len(scene.stars)):
            fk = passband_mean(grid, resp, spectra[k] * star_transmission(tau[k], wl, grid, rv))  # L_sun per Hz
            box_x = box_x + fk / (4.0 * math.pi) / ps**2 * spots[k]
            f = fk * units.L_SUN_W / (4.0 * math.pi * dist_m**2) * 1e26  # Jy
            star_mag[k, x] = -2.5 * math.log10(f / units.AB_ZERO_JY) if f > 0 else math.nan
        psb[x] = box_x * units.L_SUN_W / box_m**2 / W_M2_HZ_PER_MJY
    with np.errstate(divide="ignore", invalid="ignore"):
        mag = np.where(psb > 0, -2.5 * np.log10(psb * 1e6 * ARCSEC_RAD**2 / units.AB_ZERO_JY), np.nan)
    system = scene.observer.magnitude_system
    if system != "AB":
        vega = units.ab_minus_vega(system)
        offset = np.array([vega[name] for name in pb])
        mag = mag - offset[:, None, None]
        star_mag = star_mag - offset[None, :]
    scat_err = stokes_mjy = stokes_err = None
    if scattered_error is not None:
        scat_err = convolve_psf_error(scattered_error, sigma_pix) * to_mjy
    if stokes is not None:  # the image's up axis at observer.position_angle east of north
        pa = scene.observer.position_angle
        stokes_mjy = convolve_psf(to_celestial(stokes, pa), sigma_pix) * to_mjy[:, None]
        if stokes_error is not None:
            stokes_err = convolve_psf_error(errors_to_celestial(stokes_error, pa), sigma_pix) * to_mjy[:, None]
    info = {"METHOD": method, "DISTANCE": (dist_m / units._pc_metres(), "distance to the box centre, pc"),
            "BOXEDGE": (box_m / units._pc_metres(), "box edge, pc"),
            "PIXSCALE": (scale_arcsec, "pixel side, arcsec"), "PSFFWHM": (scene.observer.psf_fwhm, "arcsec"),
            "MAGSYS": (system, MAGSYS_COMMENT[system])}
    info.update(meta or {})
    return CalibratedSky(
        band_names=names, band_wavelength_nm=wl, band_edges_nm=edges, surface_brightness=sb,
        scattered=scat_psf * to_mjy, passbands=pb, passband_sb=psb, mag=mag, star_pixel=star_pixel,
        star_flux_jy=star_flux, star_mag=star_mag, intensity_box=box_total, scattered_box=scat_psf, band_luminosity=band_lum,
        wcs=celestial_wcs(scene, camera), pixel_scale_arcsec=scale_arcsec, pixel_solid_angle_sr=omega,
        psf_fwhm_arcsec=float(scene.observer.psf_fwhm), method=method, meta=info, mag_system=system,
        scattered_error=scat_err, stokes=stokes_mjy, stokes_error=stokes_err)


def passband_header(hh, name: str, system: str) -> None:
    """The cards of a passband's magnitude image: unit, filter, magnitude system and, for Vega,
    the AB - Vega offset applied."""
    hh["BUNIT"] = "mag/arcsec2"
    hh["FILTER"] = (PASSBANDS[name], "speclite passband")
    hh["MAGSYS"] = (system, MAGSYS_COMMENT[system])
    if system != "AB":
        hh["ABVEGA"] = (units.ab_minus_vega(system)[name], ABVEGA_COMMENT[system])


def sky_hdus(primary: dict, wcs_header, band_images, passband_images, mag_system: str, comments=(), stars=None,
             stokes=None):
    """The calibrated sky image as FITS (the layout of the module docstring), for every writer
    of it (:func:`write_fits`; Nebula Sky FITS Writer, ``nebula_rt.filters.sky_image``).

    Parameters
    ----------
    primary : dict
        The primary header's cards after ``ORIGIN`` (value, or (value, comment)).
    wcs_header : astropy.io.fits.Header
        The celestial WCS every image carries.
    band_images : sequence of (name, ndarray (W, H), dict)
        Each band's surface brightness (MJy/sr) with its extra cards; HDU ``SB_<name>``.
    passband_images : sequence of (name, ndarray (W, H))
        Each passband's magnitudes per arcsec^2 in ``mag_system``; HDU ``MAG_BESSELL_B`` ...
    comments : sequence of str
        Comment lines of the primary header (the scene's TOML).
    stars : astropy.io.fits.BinTableHDU, optional
        The stars' table (``STARS``), last.
    stokes : ndarray (n_bands, 2, W, H), optional
        A polarized scene's Stokes Q and U (MJy/sr, IAU): HDUs ``Q_<name>`` and ``U_<name>``
        after the bands (:func:`nebula_rt.observe.polarimetry.stokes_hdus`).
    """
    from astropy.io import fits

    hdr = fits.Header()
    hdr["ORIGIN"] = "NebulaRT"
    for k, val in primary.items():
        hdr[k] = val
    for line in comments:
        hdr.add_comment(line[:72])
    hdus = [fits.PrimaryHDU(header=hdr)]
    for name, image, cards in band_images:
        hh = wcs_header.copy()
        hh["BUNIT"] = "MJy/sr"
        hh["BAND"] = name
        for k, val in cards.items():
            hh[k] = val
        hdus.append(fits.ImageHDU(np.ascontiguousarray(np.asarray(image).T, np.float32), header=hh, name=f"SB_{name}"))
    if stokes is not None:
        hdus.extend(stokes_hdus(wcs_header, [name for name, _, _ in band_images], stokes))
    for name, image in passband_images:
        hh = wcs_header.copy()
        passband_header(hh, name, mag_system)
        hdus.append(fits.ImageHDU(np.ascontiguousarray(np.asarray(image).T, np.float32), header=hh,
                                  name=PASSBAND_EXTENSIONS[name]))
    if stars is not None:
        hdus.append(stars)
    return fits.HDUList(hdus)


def write_fits(path, cal: CalibratedSky, scene=None) -> None:
    """Write ``cal`` as FITS (module docstring; :func:`sky_hdus`); ``scene`` adds its TOML to the
    primary header's comments."""
    from astropy.io import fits
    from astropy.table import Table

    bands = [(name, cal.surface_brightness[b], {
        "WAVELEN": (float(cal.band_wavelength_nm[b]), "band centre, nm"),
        "BANDLO": (float(cal.band_edges_nm[b, 0]), "nm"), "BANDHI": (float(cal.band_edges_nm[b, 1]), "nm")})
        for b, name in enumerate(cal.band_names)]
    world = cal.wcs.pixel_to_world_values(cal.star_pixel[:, 0], cal.star_pixel[:, 1])
    stars = Table({"x_pixel": cal.star_pixel[:, 0] + 1.0, "y_pixel": cal.star_pixel[:, 1] + 1.0,
                   "ra": np.atleast_1d(world[0]), "dec": np.atleast_1d(world[1])})
    for b, name in enumerate(cal.band_names):
        stars[f"flux_{name}"] = cal.star_flux_jy[:, b]
        stars[f"flux_{name}"].unit = "Jy"
    for x, name in enumerate(cal.passbands):
        stars[f"mag_{name}"] = cal.star_mag[:, x]
    stars["ra"].unit = stars["dec"].unit = "deg"
    thdu = fits.table_to_hdu(stars)
    thdu.name = "STARS"
    hdus = sky_hdus({"BUNIT": "", **cal.meta}, cal.wcs.to_header(), bands,
                    [(name, cal.mag[x]) for x, name in enumerate(cal.passbands)], cal.mag_system,
                    comments=scene.to_toml().splitlines() if scene is not None else (), stars=thdu,
                    stokes=cal.stokes)
    hdus.writeto(path, overwrite=True)


def picture(cal: CalibratedSky, scene, exposure="auto", percentile: float = 99.0):
    """(uint8 (W, H, 3) sRGB, exposure used) of the calibrated image in true colour: per band
    the ratio to the stars' light, the band -> XYZ matrix of the dominant star, linear sRGB,
    gamut mapping, the exposure (auto: ``percentile`` of the scattered light's largest
    component maps to full scale; stars saturate) and the scene's ``colour.stretch``."""

    m = colour_convert.band_to_xyz_matrix(cal.band_wavelength_nm, _dominant_source(scene.stars))
    return colour_convert.sky_picture(cal.intensity_box, cal.scattered_box, cal.band_luminosity, m, exposure,
                                      percentile, scene.colour.stretch, scene.colour.asinh_q)


def write_png(path, rgb8) -> None:
    """An 8-bit (W, H, 3) picture as PNG, north-up as displayed (row 0 at the top)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.image

    matplotlib.image.imsave(str(path), np.ascontiguousarray(np.transpose(rgb8, (1, 0, 2))[::-1]), format="png")


def camera_for(scene, direction=(0.0, 0.0, -1.0), size: int = 256, up=(0.0, 1.0, 0.0), extent: float = 0.0):
    """The camera of a calibrated image: centred on the box centre (the WCS reference point)."""

    return Camera(direction=tuple(direction), up=tuple(up), size=(size, size), extent=extent, center=(0.5, 0.5, 0.5))


def peel_off_sky(scene, camera, backend=None, progress=None, cancel=None, pixel_batches: bool = False, comm=None):
    """Trace ``scene`` with a peel-off image for ``camera`` and calibrate it; returns
    (CalibratedSky, transport result). The stars' optical depths to the observer are the
    exact march of :func:`nebula_rt.transport.line_of_sight.line_of_sight_tau`.

    ``pixel_batches``: keep every batch's image (``result.peel_bin_batches``, (batches,
    n_bands, W * H), pixel p * H + q), for the Monte Carlo error of any linear function of the
    calibrated image (:mod:`nebula_rt.observe.image_compare`); otherwise each batch's image sum.
    ``comm``: the ranks that share the trace (:mod:`nebula_rt.backends.parallel`); every rank
    gets the same image."""

    check_scene(scene)
    backend = backend or scene_backend(scene)
    bands = scene.bands.resolve()
    rho = scene_density(scene, backend)  # a grid, or an octree traced leaf by leaf
    bins = (np.arange(camera.size[0] * camera.size[1], dtype=np.int64).reshape(camera.size) if pixel_batches
            else np.zeros(camera.size, np.int64))
    request = TransportRequest.from_scene(scene, peel=camera, peel_bins=bins, light_field=False)
    res = request.trace(rho, backend, progress=progress, cancel=cancel, comm=comm)
    tau = star_tau(scene, bands, rho, camera)
    meta = {"NPHOTON": (int(res.photons), "packets per band"), "SEED": str(request.seed)}
    meta.update(fits_cards(res.tail_image, [b.name for b in bands]))  # the heavy-tail checks
    cal = calibrate(scene, camera, res.peel_image, res.star_band_luminosity, tau, "peel-off", meta,
                    scattered_error=res.peel_error, stokes=res.peel_stokes, stokes_error=res.peel_stokes_error)
    return cal, res


def star_tau(scene, bands, rho, camera) -> np.ndarray:
    """(n_stars, n_bands) optical depth from each star to the observer of ``camera`` (the exact
    march of :func:`nebula_rt.transport.line_of_sight.line_of_sight_tau` through ``rho``, or the
    exact sum over an octree's leaves, :func:`~nebula_rt.transport.line_of_sight.density_column`)."""

    d = camera.basis()[0]
    if isinstance(rho, Octree):  # the exact sum over the leaves the ray crosses
        k = np.array([scene.dust.tau * b.extinction for b in bands], np.float64)
        return np.array([k * density_column(rho, s.position, -d) for s in scene.stars])
    sigma = np.array([scene.dust.tau * b.extinction for b in bands])[:, None, None, None] * \
        np.asarray(rho, np.float64)[None]
    return np.array([line_of_sight_tau(sigma, s.position, -d) for s in scene.stars])


def ray_march_sky(light, camera) -> CalibratedSky:
    """Calibrate the ray-marched sky image of a light field (:class:`nebula_rt.pipeline.LightField`;
    the emissivity scatters isotropically per voxel, :mod:`nebula_rt.observe.sky`)."""

    scene = light.scene
    check_scene(scene)
    bands = light.bands
    rho = light.density.astype(np.float64)
    sigma = np.array([scene.dust.tau * b.extinction for b in bands])[:, None, None, None] * rho[None]
    img = sky_image(light.emissivity.astype(np.float64), sigma, camera)
    tau = star_tau(scene, bands, rho, camera)
    return calibrate(scene, camera, img.scattered, light.transport.star_band_luminosity, tau, "ray-march",
                     {"NPHOTON": (int(light.transport.photons), "packets per band"),
                      "SEED": str(scene.transport.seed)})
