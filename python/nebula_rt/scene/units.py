"""Physical units beside the box units: what they convert to, exactly, and where the numbers come from.

The transport works in box units (the box is [0, 1]^3, ``dust.tau`` the optical depth across
one box edge at density 1 in the reference band, star luminosities in any unit). A scene may
instead give physical quantities; each converts to the box-unit key it replaces, in float64,
before anything is traced, so a physical scene traces the same bits as the box-unit scene
with the converted values (``tests/scene/test_units.py``):

- the box edge ``grid.length`` (a number in ``grid.unit``, or a quantity such as ``"3 pc"``)
  and the distance ``observer.distance`` ("140 pc", or a number in pc), through
  ``astropy.units``;
- the dust, one of

  * ``dust.hydrogen_density`` n_H (H nuclei per cm^3 at density 1):
    ``tau = n_H C_ref L``, with L the box edge in cm and C_ref the dust model's extinction
    cross-section per H nucleon in the reference band (:func:`reference_cext`);
  * ``dust.mass_density`` rho_d (g of dust per cm^3 at density 1): n_H = rho_d / m_d, m_d the
    model's dust mass per H nucleon (1.870e-26 g for R_V = 3.1, from the header of Draine's
    table; :func:`nebula_rt.optics.dust_tables.dust_mass_per_h`);
  * ``dust.visual_extinction`` A_V (mag across one box edge at density 1):
    ``tau = A_V / (2.5 log10 e) x C_ref / C_V``, C_V the table's row marked "V filter"
    (0.547 um: 4.896e-22 cm^2 per H for R_V = 3.1, so A_V / N_H = 5.32e-22 mag cm^2);

- a star's luminosity, one of

  * ``stars.luminosity_lsun`` L (bolometric, in the nominal solar luminosity 3.828e26 W, IAU
    2015 Resolution B3): the traced luminosity is the part inside the bands' range,
    ``L x pi int B_lambda(T) dlambda / (sigma T^4)`` (:func:`inside_fraction`; it needs the
    star's ``temperature``), in L_sun;
  * ``stars.absolute_magnitude`` M_V (AB, through the Bessell V passband of ``speclite``):
    the blackbody of ``temperature`` whose AB magnitude in V at 10 pc is M_V
    (:func:`bolometric_from_absolute_magnitude`), then as above.

- a star's ``temperature`` from its MK spectral type ``stars.spectral_type`` ("B2V",
  "B2.5 IV", "K0III"), by ``stars.spectral_calibration`` (:func:`temperature_from_spectral_type`):

  * ``"pecaut-mamajek-2013"``: the mean dwarf sequence of Pecaut & Mamajek (2013, ApJS 208, 9;
    E. Mamajek's table, version 2024.05.15, shipped as ``data/pecaut_mamajek_dwarfs.csv``) with
    the intrinsic colours B-V, U-B, V-Rc, V-Ic (:func:`dwarf_properties`), interpolated between
    its half-subtype rows; dwarfs (class V) from O3V to M9.5V only;
  * ``"de-jager-1987"``: de Jager & Nieuwenhuijzen (1987, A&A 177, 217), their 20-coefficient
    Chebyshev polynomial in spectral type and luminosity class (Eq. 2b), as PyAstronomy's
    ``SpecTypeDeJager`` evaluates it; O1-M10 and the classes V, IV, III, II, Ib, Iab, Ia, Ia+.
    Against Pecaut & Mamajek it is 4.5 % cooler in the median over their types and 9.3 % at
    B7V (the Sun, G2V, comes out at 5587 K against 5772 K);
  * ``"auto"`` (the default): the first for a dwarf inside its range, the second otherwise.

The dust model is Draine's (2003, ARA&A 41, 241; ApJ 598, 1017) Milky Way dust
(:mod:`nebula_rt.optics.dust_tables`) of the band preset: R_V = 3.1 for ``spectral-8`` /
``spectral-16``, 5.5 for ``spectral-8-dense``, where C_ref is the reference band's band average
(the scale those presets' relative extinctions are divided by, so that every band's
``tau x extinction`` is its own band-averaged cross-section times the H column); for
``thesis-rgb`` and explicit ``[[bands.list]]`` it is R_V = 3.1 at the reference band's
wavelength (the thesis's factors are that curve at 677 / 550 / 439 nm).

astropy is imported only when a physical quantity is used (its import takes about 0.6 s).
"""

from __future__ import annotations

import functools
import math
from typing import Any, Optional, Tuple

import numpy as np

from ..errors import SceneError
from ..optics.blackbody import planck_lambda, stefan_boltzmann

#: Nominal solar luminosity, W (IAU 2015 Resolution B3; ``astropy.constants.L_sun``).
L_SUN_W = 3.828e26
#: The AB magnitude system's zero point: 3631 Jy (Oke & Gunn 1983, ApJ 266, 713).
AB_ZERO_JY = 3631.0
#: Magnitudes per unit optical depth, 2.5 log10(e).
MAG_PER_TAU = 2.5 / math.log(10.0)
#: Distance of absolute magnitudes, pc.
ABSOLUTE_MAGNITUDE_DISTANCE_PC = 10.0
#: Length units named in messages (any astropy length unit is accepted; "ly" is lyr).
LENGTH_UNITS_TEXT = "pc, kpc, Mpc, AU, ly, lyr, km, m, cm, R_sun, ... (astropy.units)"
_ALIASES = {"ly": "lyr"}
#: The band presets' dust model: R_V of Draine's table and whether its extinctions are band averages
#: (the spectral presets: n equal bands over 380-780 nm).
PRESET_DUST = {"spectral-8": ("3.1", 8), "spectral-16": ("3.1", 16), "spectral-8-dense": ("5.5", 8)}
DEFAULT_RV = "3.1"
#: The default unit of ``grid.unit``: known to be a length without importing astropy.
DEFAULT_LENGTH_UNIT = "pc"
#: One parsec in metres, exact by definition (648000 / pi au; IAU 2015 Resolution B2), for a
#: number in pc checked without importing astropy.
PARSEC_M = 648000.0 / math.pi * 149_597_870_700.0
#: A physical length (``grid.length``, ``observer.distance``) in metres. The calibration squares
#: it in float64 (a star's flux L / (4 pi D^2), the surface brightness L / L_box^2), so that its
#: square must stay a normal float64 (2.2e-308 to 1.8e308): within [1e-150, 1e150] m. A distance
#: of "1e308 Mpc" (3e330 m, infinite in float64) made the pixel scale 0 and the PSF divide by it.
LENGTH_RANGE_M = (1e-150, 1e150)
LENGTH_RANGE_TEXT = "within [1e-150, 1e150] m (its square is formed in float64)"


def _units():
    import astropy.units as u

    return u


@functools.lru_cache(maxsize=256)
def _unit_metres(name: str) -> Optional[float]:
    """Metres in one ``name`` (an astropy length unit), None if it is no length."""
    u = _units()
    try:
        with u.add_enabled_aliases({k: getattr(u, v) for k, v in _ALIASES.items()}):
            unit = u.Unit(name.strip())
        return float(unit.to(u.m))
    except (ValueError, TypeError, u.UnitsError):
        return None


def is_length_unit(name: Any) -> bool:
    """``name`` is a string astropy reads as a length unit ("pc", "AU", "ly", "km")."""
    if not isinstance(name, str) or not name.strip():
        return False
    if name == DEFAULT_LENGTH_UNIT:
        return True
    return _unit_metres(name) is not None


def _split_quantity(text: str) -> Tuple[float, str]:
    """"3 pc" -> (3.0, "pc"); ValueError if no number leads."""
    parts = text.strip().split(None, 1)
    if len(parts) == 2:
        return float(parts[0]), parts[1]
    # "3pc": the longest numeric prefix
    for k in range(len(text), 0, -1):
        try:
            return float(text[:k]), text[k:]
        except ValueError:
            continue
    raise ValueError(text)


def length_metres(value: Any, unit: str = DEFAULT_LENGTH_UNIT) -> float:
    """A length in metres: a number in ``unit``, or a quantity string such as "3 pc" (its own
    unit). ValueError when it is neither, TypeError for other types."""
    if isinstance(value, bool):
        raise TypeError
    if isinstance(value, str):
        number, name = _split_quantity(value)
        metres = _unit_metres(name)
        if metres is None:
            raise ValueError(value)
        return number * metres
    if not isinstance(value, (int, float)):
        raise TypeError
    metres = _unit_metres(unit)
    if metres is None:
        raise ValueError(unit)
    return float(value) * metres


def valid_length(value: Any, zero: bool = False, unit: Optional[str] = None) -> bool:
    """A finite length > 0 (or 0 when ``zero``): a number, or a quantity string of a length,
    whose metres (in the quantity's own unit, or a number's ``unit`` where known) lie in
    :data:`LENGTH_RANGE_M`."""
    metres = None
    if isinstance(value, str):
        try:
            number, name = _split_quantity(value)
        except ValueError:
            return False
        metres = _unit_metres(name)
        if metres is None:
            return False
        value = number
    elif unit is not None:
        metres = PARSEC_M if unit == "pc" else _unit_metres(unit)
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and (
        value > 0 or (zero and value == 0))
    if ok and value and metres is not None:
        ok = LENGTH_RANGE_M[0] <= float(value) * metres <= LENGTH_RANGE_M[1]  # inf past float64: refused
    return ok


def valid_distance(value: Any) -> bool:
    """``observer.distance``: :func:`valid_length` with numbers in pc."""
    return valid_length(value, unit="pc")


def length_allowed(what: str = "a length > 0", number_unit: str = "grid.unit") -> str:
    return (f"must be {what}: a number (in {number_unit}) or a quantity such as '3 pc', {LENGTH_RANGE_TEXT}; "
            f"units: {LENGTH_UNITS_TEXT}")


def box_length_cm(grid) -> float:
    """The box edge in cm (``grid.length`` in ``grid.unit``, or its own unit)."""
    return length_metres(grid.length, grid.unit) * 100.0


def distance_metres(observer) -> float:
    """``observer.distance`` in metres (a number is in pc); 0.0 when not given."""
    if observer.distance is None:
        return 0.0
    return length_metres(observer.distance, "pc")


# --- dust -------------------------------------------------------------------------------------


def dust_model(bands_config) -> Tuple[str, Optional[int]]:
    """(R_V of Draine's table, n of a spectral preset or None) of the scene's bands."""
    preset = bands_config.preset if bands_config.list is None else None
    if preset in PRESET_DUST:
        return PRESET_DUST[preset]
    return DEFAULT_RV, None


def reference_cext(bands_config, bands) -> Tuple[float, str]:
    """The dust model's extinction cross-section per H nucleon in the reference band, cm^2,
    and how it was taken (words for messages and summaries)."""
    from ..optics import dust_tables
    from ..optics.bands import reference_band_index

    rv, n = dust_model(bands_config)
    if n is not None:
        c = dust_tables.spectral_reference_cext(n, rv)
        how = (f"Draine (2003) R_V = {rv}, averaged over the reference band "
               f"({bands[reference_band_index(bands)].name})")
    else:
        ref = bands[reference_band_index(bands)]
        c = dust_tables.cext_at(rv, ref.wavelength)
        how = f"Draine (2003) R_V = {rv} at the reference band's {ref.wavelength:g} nm"
    return c, how


def tau_from_hydrogen_density(n_h: float, cext_ref: float, box_cm: float) -> float:
    """tau = n_H C_ref L (n_H per cm^3, C_ref cm^2 per H, L cm)."""
    return float(n_h) * float(cext_ref) * float(box_cm)


def tau_from_mass_density(rho_dust: float, mass_per_h: float, cext_ref: float, box_cm: float) -> float:
    """tau = (rho_d / m_d) C_ref L (rho_d g per cm^3, m_d g of dust per H nucleon)."""
    return tau_from_hydrogen_density(float(rho_dust) / float(mass_per_h), cext_ref, box_cm)


def tau_from_visual_extinction(a_v: float, cext_ref: float, cext_v: float) -> float:
    """tau_ref = A_V / (2.5 log10 e) x C_ref / C_V (A_V in mag across one box edge)."""
    return float(a_v) / MAG_PER_TAU * float(cext_ref) / float(cext_v)


#: the dust keys that set dust.tau, in the order a message lists them
DUST_KEYS = ("hydrogen_density", "mass_density", "visual_extinction")


def physical_dust_key(dust) -> Optional[str]:
    """The physical dust key given (None: box units). SceneError if more than one is."""
    given = [k for k in DUST_KEYS if getattr(dust, k) is not None]
    if len(given) > 1:
        raise SceneError(f"dust.{given[1]}", getattr(dust, given[1]),
                         f"give one of dust.{', dust.'.join(DUST_KEYS)} (dust.{given[0]} = "
                         f"{getattr(dust, given[0])!r} is given too): each sets dust.tau")
    return given[0] if given else None


def dust_tau(scene, bands) -> Tuple[float, str]:
    """dust.tau from the scene's physical dust key, and the conversion in words. Call only
    when :func:`physical_dust_key` is not None."""
    from ..optics import dust_tables

    key = physical_dust_key(scene.dust)
    value = float(getattr(scene.dust, key))
    if getattr(scene.bands, "polarization", "none") == "matrix":
        raise SceneError(f"dust.{key}", value, "is not taken with bands.polarization = 'matrix' (a tabulated "
                                               "matrix gives no cross-section to convert it with): give dust.tau")
    if getattr(scene.bands, "polarization", "none") == "mie":
        return _mie_dust_tau(scene, bands, key, value)
    rv, _ = dust_model(scene.bands)
    cref, how = reference_cext(scene.bands, bands)
    if key == "visual_extinction":
        cv = dust_tables.v_filter_cext(rv)
        tau = tau_from_visual_extinction(value, cref, cv)
        return tau, (f"A_V = {value:g} mag / {MAG_PER_TAU:.6f} x C_ref {cref:.4e} / C_V {cv:.4e} cm^2 per H "
                     f"({how}; C_V: the table's V filter row)")
    box = box_length_cm(scene.grid)
    if key == "hydrogen_density":
        return tau_from_hydrogen_density(value, cref, box), (
            f"n_H {value:g} cm^-3 x C_ref {cref:.4e} cm^2 per H ({how}) x box edge {box:.4e} cm")
    m = dust_tables.dust_mass_per_h(rv)
    return tau_from_mass_density(value, m, cref, box), (
        f"rho_d {value:g} g cm^-3 / {m:.4g} g of dust per H x C_ref {cref:.4e} cm^2 per H ({how}) "
        f"x box edge {box:.4e} cm")


def _mie_dust_tau(scene, bands, key: str, value: float) -> Tuple[float, str]:
    """dust.tau of Mie grains (``bands.polarization = "mie"``): from their own extinction
    cross-section per grain in the reference band, C_ref, and (A_V) at the V row's wavelength,
    or (a mass density) the grains per cm^3 rho_d / (bulk density x mean grain volume)."""
    from ..optics import mie
    from ..optics.bands import reference_band_index
    from ..optics.polarization import grains_of

    grains = grains_of(scene.bands)
    ref = bands[reference_band_index(bands)]
    cref = float(mie.mie_cext_cm2(grains, [ref.wavelength])[0])
    how = f"the Mie grains' C_ext {cref:.4e} cm^2 per grain at the reference band's {ref.wavelength:g} nm"
    if key == "visual_extinction":
        cv = float(mie.mie_cext_cm2(grains, [mie.V_WAVELENGTH_NM])[0])
        return tau_from_visual_extinction(value, cref, cv), (
            f"A_V = {value:g} mag / {MAG_PER_TAU:.6f} x C_ref / C_V {cv:.4e} cm^2 per grain at "
            f"{mie.V_WAVELENGTH_NM:g} nm ({how})")
    if key != "mass_density":
        raise ValueError(key)
    mass = mie.grain_mass_g(grains, [ref.wavelength])
    box = box_length_cm(scene.grid)
    return tau_from_mass_density(value, mass, cref, box), (
        f"rho_d {value:g} g cm^-3 / {mass:.4e} g per grain ({mie.material_density(grains.material):g} g cm^-3 "
        f"{grains.material}) x {how} x box edge {box:.4e} cm")


# --- stars ------------------------------------------------------------------------------------


def band_range_nm(bands) -> Tuple[float, float]:
    """The wavelength range the bands share a star's light over (nm): 380-780 nm, widened to
    the outermost band centres (:func:`nebula_rt.optics.colour_convert.band_edges`)."""
    from ..optics.colour_convert import band_edges

    e = band_edges([b.wavelength for b in bands])
    return float(e[0]), float(e[-1])


def inside_fraction(temperature: float, lo_nm: float, hi_nm: float) -> float:
    """The part of a blackbody's bolometric luminosity inside [lo_nm, hi_nm]:
    pi int B_lambda dlambda / (sigma T^4), the trapezoid rule on the 1 nm grid that the band
    luminosities use (:func:`nebula_rt.optics.colour_convert.band_luminosity_fractions`), continued
    to edges inside a 1 nm cell."""
    wl = np.arange(math.floor(lo_nm), math.ceil(hi_nm) + 1.0)
    b = planck_lambda(wl * 1e-9, temperature)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (b[1:] + b[:-1]) * np.diff(wl))])
    edges = np.array([lo_nm, hi_nm])
    b_e = np.interp(edges, wl, b)
    k = np.clip(np.searchsorted(wl, edges, side="right") - 1, 0, wl.size - 1)
    at = cum[k] + 0.5 * (b[k] + b_e) * (edges - wl[k])
    return float((at[1] - at[0]) * 1e-9 * math.pi / (stefan_boltzmann() * float(temperature) ** 4))


#: The passbands NebulaRT measures in, by short name: speclite's curves (Bessell 1990, PASP 102,
#: 1181; SDSS 2010). The calibrated sky images use all of them, the colours (Delta(B-V)) B and V.
PASSBANDS = {"B": "bessell-B", "V": "bessell-V", "R": "bessell-R", "g": "sdss2010-g", "r": "sdss2010-r",
             "i": "sdss2010-i"}


@functools.lru_cache(maxsize=None)
def passband(name: str) -> Tuple[np.ndarray, np.ndarray]:
    """(wavelength nm, response) of a ``speclite`` passband ("bessell-V", "sdss2010-r")."""
    import speclite.filters

    f = speclite.filters.load_filter(name)
    return np.asarray(f.wavelength, np.float64) / 10.0, np.asarray(f.response, np.float64)


def ab_magnitude(f_lambda, wavelength_nm, name: str) -> float:
    """AB magnitude of a spectrum f_lambda (W m^-2 m^-1 on ``wavelength_nm``) through passband
    ``name``, photon counting: m = -2.5 log10(int f_lambda R lambda dl / int f_AB R lambda dl),
    f_AB = 3631 Jy c / lambda^2."""
    wl_x, resp = passband(name)
    wl = np.asarray(wavelength_nm, np.float64)
    r = np.interp(wl, wl_x, resp, left=0.0, right=0.0)
    lam = wl * 1e-9
    f_ab = AB_ZERO_JY * 1e-26 * 299792458.0 / lam**2
    return float(-2.5 * math.log10(np.trapezoid(np.asarray(f_lambda) * r * lam, lam)
                                   / np.trapezoid(f_ab * r * lam, lam)))


#: m_AB - m_Vega of each passband as Blanton & Roweis (2007, AJ 133, 734, Table 1) give it: the
#: calibration of ``observer.magnitude_system = "Vega-Blanton2007"`` (NebulaRT's before the
#: CALSPEC spectrum; it differs from that by up to 0.03 mag)
AB_MINUS_VEGA_BLANTON2007 = {"B": -0.09, "V": 0.02, "R": 0.21, "g": -0.08, "r": 0.16, "i": 0.37}

#: the shipped Vega spectrum (CALSPEC alpha_lyr_stis_011, 300-1000 nm; its header says whence)
VEGA_FILE = "data/calspec_alpha_lyr_stis_011.csv"


@functools.lru_cache(maxsize=None)
def vega_spectrum() -> Tuple[np.ndarray, np.ndarray]:
    """(wavelength nm, f_lambda W m^-2 m^-1) of Vega, CALSPEC's alpha_lyr_stis_011 (Bohlin et
    al. 2020, AJ 160, 21) from 300 to 1000 nm (:data:`VEGA_FILE`)."""
    from importlib import resources

    text = resources.files("nebula_rt").joinpath(VEGA_FILE).read_text(encoding="utf-8")
    rows = np.loadtxt([line for line in text.splitlines() if line and not line[0] in "#w"], delimiter=",")
    # FLAM (erg s^-1 cm^-2 A^-1) = 1e-7 W / (1e-4 m^2 * 1e-10 m) = 1e7 W m^-2 m^-1
    return rows[:, 0] / 10.0, rows[:, 1] * 1e7


@functools.lru_cache(maxsize=None)
def ab_minus_vega(system: str = "Vega") -> dict:
    """m_AB - m_Vega of each passband (:data:`PASSBANDS`, by short name): a Vega magnitude is
    the AB magnitude minus this. ``"Vega"``: Vega's own AB magnitude through the passband
    (:func:`ab_magnitude` of :func:`vega_spectrum`, photon counting; Vega is 0 mag in every
    passband of the Vega system); ``"Vega-Blanton2007"``: :data:`AB_MINUS_VEGA_BLANTON2007`."""
    if system == "Vega-Blanton2007":
        return dict(AB_MINUS_VEGA_BLANTON2007)
    if system != "Vega":
        raise ValueError(f"no AB - Vega offsets for the magnitude system {system!r}")
    wl, f = vega_spectrum()
    return {short: ab_magnitude(f, wl, name) for short, name in PASSBANDS.items()}


def blackbody_absolute_magnitude(temperature: float, passband_name: str = "bessell-V") -> float:
    """AB magnitude through ``passband_name`` of a blackbody of 1 L_sun at 10 pc."""
    wl_x, _ = passband(passband_name)
    wl = np.arange(math.floor(wl_x[0]), math.ceil(wl_x[-1]) + 0.25, 0.25)
    d = ABSOLUTE_MAGNITUDE_DISTANCE_PC * _pc_metres()
    f = L_SUN_W / (4.0 * math.pi * d * d) * math.pi * planck_lambda(wl * 1e-9, temperature) / (
        stefan_boltzmann() * float(temperature) ** 4)
    return ab_magnitude(f, wl, passband_name)


def bolometric_from_absolute_magnitude(m_v: float, temperature: float) -> float:
    """L_bol / L_sun of a blackbody of ``temperature`` whose AB magnitude through Bessell V at
    10 pc is ``m_v``; infinite beyond float64 (the luminosity's range check then names the
    magnitude, :func:`absolute_magnitude_range`)."""
    exponent = -0.4 * (float(m_v) - blackbody_absolute_magnitude(temperature))
    return math.inf if exponent > 308.0 else 10.0 ** exponent  # 10^x overflows float64 past x = 308.25


def absolute_magnitude_range(temperature: float, bands, luminosity_range) -> Tuple[float, float]:
    """The absolute magnitudes M_V (brightest, faintest) of a blackbody of ``temperature`` whose
    luminosity inside the bands' range lies in ``luminosity_range`` (L_sun): the inverse of
    :func:`bolometric_from_absolute_magnitude` times :func:`inside_fraction`."""
    lo, hi = band_range_nm(bands)
    m0 = blackbody_absolute_magnitude(temperature) + 2.5 * math.log10(inside_fraction(temperature, lo, hi))
    return m0 - 2.5 * math.log10(luminosity_range[1]), m0 - 2.5 * math.log10(luminosity_range[0])


@functools.lru_cache(maxsize=None)
def _pc_metres() -> float:
    return _unit_metres("pc")


#: an MK spectral type: class letter, subtype 0-9 (decimals allowed; O1-M10 in DJ87) and
#: luminosity class, with optional spaces between
SPECTRAL_TYPE_FORM = ("an MK spectral type: a class O, B, A, F, G, K or M, a subtype (0-9.9, "
                      "O from 1, M up to 10) and a luminosity class V, IV, III, II, Ib, Iab, Ia or "
                      "Ia+, such as \"B2V\", \"B2.5 IV\" or \"K0III\"")
_SPECTRAL_TYPE = r"\s*([OBAFGKM])\s*(\d+(?:\.\d+)?)\s*(Ia\+|Iab|Ia|Ib|III|II|IV|V)\s*"


def parse_spectral_type(text: Any) -> Optional[Tuple[str, str]]:
    """(spectral type, luminosity class) of an MK type ("B2.5 IV" -> ("B2.5", "IV")), or None
    where ``text`` is not one within DJ87's range (O1 to M10)."""
    import re

    m = re.fullmatch(_SPECTRAL_TYPE, text) if isinstance(text, str) else None
    if m is None:
        return None
    letter, sub, lclass = m.groups()
    x = float(sub)
    if not (0.0 <= x < 10.0 or (letter == "M" and x == 10.0)) or (letter == "O" and x < 1.0):
        return None
    return letter + sub, lclass


#: calibrations of T_eff from a spectral type (``stars.spectral_calibration``): Pecaut &
#: Mamajek's mean dwarf sequence (class V only), de Jager & Nieuwenhuijzen's polynomial (every
#: class), or "auto": the first for dwarfs inside its range (O3V-M9.5V), else the second
SPECTRAL_CALIBRATIONS = ("auto", "pecaut-mamajek-2013", "de-jager-1987")
#: the shipped dwarf sequence of Pecaut & Mamajek (its header says whence)
DWARF_FILE = "data/pecaut_mamajek_dwarfs.csv"
#: the intrinsic colours of the dwarf sequence, by column
DWARF_COLOURS = ("B-V", "U-B", "V-Rc", "V-Ic")


def _type_code(spt: str) -> float:
    """A spectral type as a number: O0 = 0, B0 = 10, ... M0 = 60, plus the subtype."""
    return 10.0 * "OBAFGKM".index(spt[0]) + float(spt[1:])


@functools.lru_cache(maxsize=None)
def dwarf_sequence() -> dict:
    """Pecaut & Mamajek's mean dwarf sequence (:data:`DWARF_FILE`): ``code`` (type numbers of
    the rows, :func:`_type_code`), ``T_eff`` (K) and each of :data:`DWARF_COLOURS` (mag; NaN
    where the table gives none)."""
    import csv
    from importlib import resources

    text = resources.files("nebula_rt").joinpath(DWARF_FILE).read_text(encoding="utf-8")
    rows = list(csv.DictReader(line for line in text.splitlines() if not line.startswith("#")))
    out = {"code": np.array([_type_code(r["spectral_type"][:-1]) for r in rows]),
           "T_eff": np.array([float(r["T_eff_K"]) for r in rows])}
    for c in DWARF_COLOURS:
        out[c] = np.array([float(r[c.replace("-", "_")]) if r[c.replace("-", "_")] else math.nan for r in rows])
    return out


def dwarf_properties(text: str) -> dict:
    """T_eff (K) and the intrinsic colours (mag) of a dwarf's spectral type from Pecaut &
    Mamajek's sequence, interpolated linearly in the type number between its rows (T_eff in
    log T_eff); a colour is NaN where either neighbouring row has none. ValueError where
    ``text`` is not a class V type within O3V-M9.5V."""
    parsed = parse_spectral_type(text)
    if parsed is None:
        raise ValueError(f"{text!r} is not {SPECTRAL_TYPE_FORM}")
    spt, lclass = parsed
    seq = dwarf_sequence()
    x = _type_code(spt)
    if lclass != "V" or not seq["code"][0] <= x <= seq["code"][-1]:
        raise ValueError(f"{text!r}: Pecaut & Mamajek (2013) hold dwarfs (luminosity class V) from O3V to M9.5V only")
    exact = np.flatnonzero(seq["code"] == x)  # (a row's own type: its value, not 10^log10 of it)
    t_eff = seq["T_eff"][exact[0]] if exact.size else 10.0 ** np.interp(x, seq["code"], np.log10(seq["T_eff"]))
    out = {"T_eff": float(t_eff)}
    for c in DWARF_COLOURS:
        out[c] = float(np.interp(x, seq["code"], seq[c]))
    return out


def spectral_calibration_of(text: str, calibration: str = "auto") -> str:
    """The calibration that ``calibration`` means for ``text``: "auto" is Pecaut & Mamajek for
    a dwarf inside their range, de Jager & Nieuwenhuijzen otherwise."""
    if calibration != "auto":
        return calibration
    parsed = parse_spectral_type(text)
    seq = dwarf_sequence()
    dwarf = parsed is not None and parsed[1] == "V" and seq["code"][0] <= _type_code(parsed[0]) <= seq["code"][-1]
    return "pecaut-mamajek-2013" if dwarf else "de-jager-1987"


@functools.lru_cache(maxsize=64)
def temperature_from_spectral_type(text: str, calibration: str = "auto") -> float:
    """Effective temperature (K) of an MK spectral type, by ``calibration``
    (:data:`SPECTRAL_CALIBRATIONS`): Pecaut & Mamajek's dwarf sequence
    (:func:`dwarf_properties`) or de Jager & Nieuwenhuijzen (1987) through PyAstronomy
    (imported here: about 2 s the first time). ValueError where ``text`` is not
    :data:`SPECTRAL_TYPE_FORM` or not a type the calibration holds."""
    parsed = parse_spectral_type(text)
    if parsed is None:
        raise ValueError(f"{text!r} is not {SPECTRAL_TYPE_FORM}")
    if calibration not in SPECTRAL_CALIBRATIONS:
        raise ValueError(f"no spectral-type calibration {calibration!r}: one of {', '.join(SPECTRAL_CALIBRATIONS)}")
    if spectral_calibration_of(text, calibration) == "pecaut-mamajek-2013":
        return dwarf_properties(text)["T_eff"]
    # M10 is DJ87's last type, which PyAstronomy's parser (one subtype digit) cannot spell:
    # its s-value is that of M9 plus one subtype, the same as "M9" with subtype 10 - 9
    spt, lclass = parsed
    import warnings

    with warnings.catch_warnings():  # PyAstronomy's package import touches scipy.misc
        warnings.simplefilter("ignore", DeprecationWarning)
        from PyAstronomy.pyasl.asl.aslExt_1.spectralClass import SpecTypeDeJager

    if spt == "M10" or spt.startswith("M10."):
        spt = "M9.999999"
    _, log_teff = SpecTypeDeJager().lumAndTeff(spt, lclass)
    return float(10.0 ** float(log_teff))


def physical_star(star) -> bool:
    return star.luminosity_lsun is not None or star.absolute_magnitude is not None


def star_luminosity(star, index: int, bands) -> Tuple[float, float]:
    """(traced luminosity in L_sun inside the bands' range, bolometric L_sun) of a star with a
    physical luminosity. SceneError naming the key when it cannot be converted."""
    key = "luminosity_lsun" if star.luminosity_lsun is not None else "absolute_magnitude"
    value = getattr(star, key)
    if star.luminosity_lsun is not None and star.absolute_magnitude is not None:
        raise SceneError(f"stars[{index}].absolute_magnitude", star.absolute_magnitude,
                         f"give one of stars[{index}].luminosity_lsun and stars[{index}].absolute_magnitude")
    if star.spectrum or not star.temperature:
        raise SceneError(f"stars[{index}].{key}", value,
                         f"a bolometric luminosity (L_sun) or an absolute magnitude needs the star's "
                         f"blackbody: give stars[{index}].temperature (K) or stars[{index}].spectral_type and no "
                         f"measured spectrum, or "
                         f"give stars[{index}].luminosity in scene units")
    lbol = float(value) if key == "luminosity_lsun" else bolometric_from_absolute_magnitude(value, star.temperature)
    lo, hi = band_range_nm(bands)
    return lbol * inside_fraction(star.temperature, lo, hi), lbol


def attribute(exc: SceneError, scene) -> SceneError:
    """``exc`` renamed to the physical key that set the box-unit value it names (``dust.tau``,
    ``stars[i].luminosity``), for a check made after the conversion (the device's ranges for
    this density and grid); ``exc`` itself otherwise."""
    import re

    if scene is None or not isinstance(exc, SceneError):
        return exc
    if exc.parameter == "dust.tau":
        try:
            key = physical_dust_key(scene.dust)
        except SceneError:
            key = None
        if key is not None:
            return SceneError(f"dust.{key}", getattr(scene.dust, key),
                              f"gives dust.tau = {exc.value!r}, which {exc.allowed}")
        return exc
    m = re.fullmatch(r"stars\[(\d+)\]\.luminosity", exc.parameter)
    if m and int(m.group(1)) < len(scene.stars) and physical_star(scene.stars[int(m.group(1))]):
        star = scene.stars[int(m.group(1))]
        key = "luminosity_lsun" if star.luminosity_lsun is not None else "absolute_magnitude"
        return SceneError(f"stars[{m.group(1)}].{key}", getattr(star, key),
                          f"gives a luminosity of {exc.value!r} L_sun inside the bands: {exc.allowed}")
    return exc
