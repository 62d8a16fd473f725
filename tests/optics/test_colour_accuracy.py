"""Band colours against full-spectrum colours (CIE Delta E 2000).

A nebula's spectrum is the star's spectrum S times a slowly varying dust ratio r(lambda). The
transport gives one number per band: r_b = (band-integrated nebula) / (band-integrated star),
the ratio of what the band's packets deposit to what the star emits in the band. The colour
conversion interpolates r_b across wavelength (hat functions) and multiplies by the full S
(nebula_rt.optics.colour_convert.band_to_xyz_matrix). The reference integrates S r with the 1 nm CIE
1931 functions. Scenes, with Draine's R_V = 3.1 dust (albedo a, extinction C) for r:
  thin:  r = a C / (a C)_V            (single scattering, optically thin)
  thick: r = thin x exp(-tau_V (C / C_V - 1)), tau_V = 2 (extinction reddens the light)
Colours are compared in CIELAB with the star as the white, both scaled so that the reference
has L* = 50. No Monte Carlo here: the numbers are exact for the band layout, so the tests
assert the README's figures (measured: worst 0.149 for 8 bands, 0.037 for 16, 0.572 for the
thesis's 3, over the stars and scenes below).
"""

from __future__ import annotations

import colour
import numpy as np
import pytest

from nebula_rt.optics.bands import PRESETS
from nebula_rt.optics.colour_convert import _cmfs_1nm, band_to_xyz_matrix, star_spectrum
from nebula_rt.optics.dust_tables import draine_table


def dust_ratio(wl, scene):
    t = draine_table("3.1")
    a = np.interp(wl, t["wavelength_nm"], t["albedo"])
    c = np.interp(wl, t["wavelength_nm"], t["cext"])
    c_v = np.interp(550.0, t["wavelength_nm"], t["cext"])
    r = a * c / (np.interp(550.0, t["wavelength_nm"], t["albedo"]) * c_v)
    if scene == "thick":
        r = r * np.exp(-2.0 * (c / c_v - 1.0))
    return r


def band_edges(centres):
    """Each band is the wavelengths nearer its centre than any other, within 380-780 nm."""
    c = np.sort(centres)
    return np.concatenate([[380.0], 0.5 * (c[1:] + c[:-1]), [780.0]])


def delta_e(preset, temperature, scene):
    bands = PRESETS[preset]
    centres = np.array([b.wavelength for b in bands])
    order = np.argsort(centres)
    edges = band_edges(centres)
    wl = np.arange(380.0, 781.0)
    s = star_spectrum(temperature, wl)
    n = s * dust_ratio(wl, scene)
    r = np.empty(len(bands))
    for k, b in enumerate(order):
        inside = (wl >= edges[k]) & (wl <= edges[k + 1])
        r[b] = np.trapezoid(n[inside], wl[inside]) / np.trapezoid(s[inside], wl[inside])
    xyz_bands = band_to_xyz_matrix(centres, temperature) @ r
    wl_c, cmf = _cmfs_1nm()
    s_c = star_spectrum(temperature, wl_c)
    xyz_ref = (s_c * dust_ratio(np.clip(wl_c, 380, 780), scene)) @ cmf / (s_c @ cmf[:, 1])
    white = (s_c @ cmf) / (s_c @ cmf[:, 1])
    scale = 0.184 / xyz_ref[1]  # L* = 50 for the reference
    lab = [colour.XYZ_to_Lab(x * scale, colour.XYZ_to_xy(white)) for x in (xyz_bands, xyz_ref)]
    return float(colour.delta_E(lab[0], lab[1], method="CIE 2000"))


# the README's claims: Delta E 2000 <= 0.15 with 8 bands, <= 0.04 with 16, 0.57 with 3
BOUND = {"spectral-8": 0.15, "spectral-16": 0.04}


@pytest.mark.parametrize("preset", ["spectral-8", "spectral-16"])
@pytest.mark.parametrize("temperature", [5800.0, 14000.0, 20000.0])
@pytest.mark.parametrize("scene", ["thin", "thick"])
def test_eight_or_more_bands_match_the_full_spectrum(preset, temperature, scene):
    de = delta_e(preset, temperature, scene)
    assert de <= BOUND[preset], de


def test_three_bands_are_coarser_but_close():
    # the thesis's three bands: 0.57 at worst here (REFERENCES.md reports up to 2.5 in
    # thicker dust); more bands are better
    worst = max(delta_e("thesis-rgb", t, s) for t in (5800.0, 20000.0) for s in ("thin", "thick"))
    assert round(worst, 2) == 0.57, worst
    assert worst > max(delta_e("spectral-8", t, s) for t in (5800.0, 20000.0) for s in ("thin", "thick"))
