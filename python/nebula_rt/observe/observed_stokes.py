"""Observed Stokes images (FITS) as a table of the degree of polarization about the star.

A polarimetric observation gives images of I, Q and U (surface brightness, a celestial WCS, Q
and U in the IAU convention: the angle from north through east). :func:`stokes_table` sums them
over annuli of angular offset from the scene's most luminous star, as it lies on the sky
(:func:`nebula_rt.observe.calibrate.celestial_wcs`), into the tangential degree of polarization

    P_t = sum (-Q cos 2theta - U sin 2theta) / sum I,

theta each pixel's position angle about the star (east of north; astropy's ``position_angle``),
so that light polarized perpendicular to the line to the star (the centrosymmetric pattern
of a reflection nebula) counts positive, as the model's polarization tables do
(:mod:`nebula_rt.observe.comparison`). Its error is the first-order propagation of the pixels'
errors (independent pixels). The table's offsets are in box units (the observer's distance and
the box's edge), so ``compare`` and ``fit`` take it as any other polarization table.

The intensity should be the nebula's alone: a star's unpolarized light in I lowers P_t. Pixels
within ``mask_arcsec`` of a star are left out; the model's P_t is that of the scattered light
without the PSF, so annuli should be wide beside the observation's PSF.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ..errors import SceneError
from ..scene import units
from .observed_images import read_image
from .observed_tables import ObservedTable


def star_on_sky(scene, direction=(0.0, 0.0, -1.0)):
    """(RA, Dec) in degrees of the scene's most luminous star on the sky (the model image's
    WCS: the box centre at observer.ra, observer.dec), and of every star."""
    from .calibrate import camera_for, celestial_wcs, star_pixels

    cam = camera_for(scene, direction, 64)
    w = celestial_wcs(scene, cam)
    pix = star_pixels(scene, cam)
    ra, dec = w.pixel_to_world_values(pix[:, 0], pix[:, 1])
    k = int(np.argmax([s.luminosity for s in scene.stars]))
    return (float(np.atleast_1d(ra)[k]), float(np.atleast_1d(dec)[k])), np.stack([np.atleast_1d(ra),
                                                                                  np.atleast_1d(dec)], axis=1)


def stokes_table(scene, path, *, intensity, q, u, errors: Sequence = (), wavelength_nm: float,
                 annuli_arcsec: Sequence[float], mask_arcsec: float = 0.0, direction=(0.0, 0.0, -1.0),
                 unit=None, option: str = "stokes") -> ObservedTable:
    """The tangential degree of polarization of an observation in annuli about the star.

    Parameters
    ----------
    scene : nebula_rt.scene.Scene
        With ``[observer]`` (the star's place on the sky, the distance) and ``grid.length``.
    path : str or Path
        The FITS file.
    intensity, q, u : str or int
        The HDUs of I, Q and U (same shape and WCS; Q and U in the IAU convention).
    errors : sequence
        Their 1-sigma error terms, as :func:`nebula_rt.observe.observed_images.read_image` takes
        them (an HDU, ``"5%"``, a surface brightness), for each of I, Q and U alike.
    wavelength_nm : float
        The observation's wavelength.
    annuli_arcsec : sequence of float
        Annulus edges, increasing, arcsec from the star.
    mask_arcsec : float
        Pixels within this distance of any star are left out.

    Returns
    -------
    ObservedTable
        kind "polarization", one row per annulus (offsets in box units).

    Raises
    ------
    SceneError
        Naming ``option`` and what is wrong: HDUs of different shapes or WCS, edges not
        increasing, an annulus with no pixel, a scene without ``[observer]``.
    """
    from astropy.coordinates import SkyCoord
    import astropy.units as au

    from .calibrate import check_scene

    check_scene(scene)
    edges = np.asarray(annuli_arcsec, np.float64)
    if edges.ndim != 1 or len(edges) < 2 or not np.all(np.isfinite(edges)) or np.any(np.diff(edges) <= 0) \
            or edges[0] < 0:
        raise SceneError(f"{option} annuli", list(np.atleast_1d(annuli_arcsec)),
                         "must be at least 2 finite edges >= 0, increasing (arcsec)")
    if not (math.isfinite(float(wavelength_nm)) and float(wavelength_nm) > 0):
        raise SceneError(f"{option} wavelength", wavelength_nm, "must be a wavelength > 0 (nm)")
    imgs = [read_image(path, h, unit=unit, errors=errors, option=option) for h in (intensity, q, u)]
    shape = imgs[0].data.shape
    for im in imgs[1:]:
        if im.data.shape != shape or im.wcs.to_header() != imgs[0].wcs.to_header():
            raise SceneError(option, im.label, f"must have the shape and WCS of {imgs[0].label}")
    (ra, dec), stars = star_on_sky(scene, direction)
    ny, nx = shape
    yy, xx = np.mgrid[0:ny, 0:nx]
    world = imgs[0].wcs.pixel_to_world_values(xx.ravel(), yy.ravel())
    pix = SkyCoord(world[0] * au.deg, world[1] * au.deg, frame="icrs")
    star = SkyCoord(ra * au.deg, dec * au.deg, frame="icrs")
    sep = star.separation(pix).to_value(au.arcsec).reshape(shape)
    theta = star.position_angle(pix).to_value(au.rad).reshape(shape)  # east of north
    keep = np.all([np.isfinite(im.data) & np.isfinite(im.sigma) for im in imgs], axis=0)
    if mask_arcsec > 0:
        for s_ra, s_dec in stars:
            d = SkyCoord(s_ra * au.deg, s_dec * au.deg, frame="icrs").separation(pix).to_value(au.arcsec)
            keep &= d.reshape(shape) > mask_arcsec
    I, Q, U = (im.data.astype(np.float64) for im in imgs)
    sI, sQ, sU = (im.sigma.astype(np.float64) for im in imgs)
    c2, s2 = -np.cos(2 * theta), -np.sin(2 * theta)  # the tangential frame: perpendicular to the radius
    value, error = [], []
    for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        sel = keep & (sep >= lo) & (sep < hi)
        total = I[sel].sum()
        if not sel.any() or not total > 0:
            raise SceneError(f"{option} annuli", [float(lo), float(hi)],
                             "the annulus holds no observed pixel with light: widen it or move it")
        t = (Q[sel] * c2[sel] + U[sel] * s2[sel]).sum()
        p = t / total
        var = ((c2[sel] * sQ[sel]) ** 2 + (s2[sel] * sU[sel]) ** 2).sum() / total**2 \
            + p**2 * (sI[sel] ** 2).sum() / total**2
        value.append(p)
        error.append(math.sqrt(var))
    # arcsec -> box units: one box edge subtends box_length / distance radians
    box_m = units.box_length_cm(scene.grid) / 100.0
    per_arcsec = math.radians(1.0 / 3600.0) * units.distance_metres(scene.observer) / box_m
    lo, hi = edges[:-1] * per_arcsec, edges[1:] * per_arcsec
    if np.any(np.asarray(error) <= 0):
        raise SceneError(f"{option} errors", list(errors), "must give every annulus a positive error")
    return ObservedTable(kind="polarization", path=f"{path} (Stokes {intensity}, {q}, {u})", x=0.5 * (lo + hi),
                         value=np.asarray(value), error=np.asarray(error), lo=lo, hi=hi,
                         x_display=0.5 * (edges[:-1] + edges[1:]), x_unit="arcsec",
                         wavelength=np.full(len(lo), float(wavelength_nm)))
