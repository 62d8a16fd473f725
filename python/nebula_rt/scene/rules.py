"""The checks of a scene's values: type coercion and the per-key rules (range, choices, and
the checks across keys), each failure a :class:`~nebula_rt.errors.SceneError` that names the
key, the value and what is allowed."""

from __future__ import annotations

import math
import numbers
import sys
from dataclasses import fields
from typing import Any, Callable, Dict, Mapping, Optional, Sequence, Tuple, Union

if sys.version_info >= (3, 11):
    pass
else:  # pragma: no cover
    pass

from .. import limits
from ..optics.bands import BAND_KEYS, Band
from ..errors import SceneError
from ..limits import (
    FLOAT32_RANGE_TEXT, INT32_MAX, MAX_OFFSET, TEMPERATURE_RANGE, float32_allowed, in_float32_range)
from . import units
from .sections import BACKENDS, DUST_MODELS, ERROR_ESTIMATES, ESTIMATORS, MAG_SYSTEMS, MAX_PHOTONS, MAX_SEED, METHODS, QUALITIES, QUALITY_PRESETS, STRETCHES, Star, Vec3, WHITE_POINTS


# ---------------------------------------------------------------------------
# type coercion and per-key rules
# ---------------------------------------------------------------------------


def _is_real(v: Any) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _to_float(v: Any) -> float:
    if not _is_real(v):
        raise TypeError
    return float(v)  # may raise OverflowError for huge ints


def _to_int(v: Any) -> int:
    if isinstance(v, bool):
        raise TypeError
    if isinstance(v, numbers.Integral):
        return int(v)
    if _is_real(v):
        f = float(v)
        # a whole float (2.1e6) is an integer; beyond 2**53 a float no longer says which one
        if math.isfinite(f) and f == math.floor(f) and abs(f) <= 2.0**53:
            return int(f)
    raise TypeError


def _to_spectrum(v: Any):
    if v is None:
        return None
    if isinstance(v, (str, bytes)) or not isinstance(v, (list, tuple)):
        raise TypeError
    pairs = []
    for p in v:
        if isinstance(p, (str, bytes)) or not isinstance(p, (list, tuple)) or len(p) != 2:
            raise TypeError
        pairs.append((_to_float(p[0]), _to_float(p[1])))
    return tuple(pairs)


def _valid_spectrum(v) -> bool:
    if v is None:
        return True
    wl = [p[0] for p in v]
    power = [p[1] for p in v]
    return (len(v) >= 2 and all(math.isfinite(x) and 0.0 < x <= 1e5 for x in wl)
            and all(b > a for a, b in zip(wl, wl[1:]))
            and all(math.isfinite(x) and x >= 0.0 for x in power) and any(x > 0.0 for x in power))


def _to_str(v: Any) -> str:
    if not isinstance(v, str):
        raise TypeError
    return v


def _to_opt_str(v: Any) -> Optional[str]:
    return None if v is None else _to_str(v)


def _to_opt_float(v: Any) -> Optional[float]:
    return None if v is None else _to_float(v)


def _three(v: Any) -> list:
    """The 3 items of a list, tuple or 1-d array; TypeError otherwise."""
    if isinstance(v, (str, bytes, Mapping)):
        raise TypeError
    items = list(v)  # TypeError if not iterable
    if len(items) != 3:
        raise TypeError
    return items


def _to_vec3(v: Any) -> Vec3:
    return tuple(_to_float(x) for x in _three(v))  # type: ignore[return-value]


def _to_ivec3(v: Any) -> Tuple[int, int, int]:
    return tuple(_to_int(x) for x in _three(v))  # type: ignore[return-value]


def _to_length(v: Any) -> Union[float, str]:
    """A length: a number (float) or a quantity string ("3 pc"), checked by units.valid_length."""
    return v if isinstance(v, str) else _to_float(v)


def _to_opt_length(v: Any) -> Optional[Union[float, str]]:
    return None if v is None else _to_length(v)


def _finite(v: Optional[float]) -> bool:
    return v is None or math.isfinite(v)


def _opt_nonneg(v: Optional[float]) -> bool:
    return v is None or (math.isfinite(v) and v >= 0)


def _to_auto_or_float(v: Any) -> Union[float, str]:
    if v == "auto" and isinstance(v, str):
        return v
    return _to_float(v)


def _finite_pos(v: float) -> bool:
    return math.isfinite(v) and v > 0


def _finite_nonneg(v: float) -> bool:
    return math.isfinite(v) and v >= 0


def _float32_nonneg(v: float) -> bool:
    """0, or positive within the normal float32 range (limits.FLOAT32_TINY .. FLOAT32_MAX)."""
    return v >= 0 and in_float32_range(v)


def _float32_pos(v: float) -> bool:
    return v > 0 and in_float32_range(v, zero=False)


def _one_of(options: Sequence[str]) -> str:
    return "one of: " + ", ".join(repr(o) for o in options)


class _Rule:
    """How one TOML key is converted (type) and checked (range)."""

    __slots__ = ("convert", "check", "allowed")

    def __init__(
        self,
        convert: Callable[[Any], Any],
        allowed: str,
        check: Optional[Callable[[Any], bool]] = None,
    ):
        self.convert = convert
        self.allowed = allowed
        self.check = check

    def coerce(self, param: str, value: Any) -> Any:
        try:
            return self.convert(value)
        except (TypeError, ValueError, OverflowError):
            raise SceneError(param, value, self.allowed) from None

    def validate(self, param: str, value: Any) -> None:
        v = self.coerce(param, value)
        if self.check is not None and not self.check(v):
            # Report vectors as the TOML writes them: [x, y, z].
            raise SceneError(param, list(value) if isinstance(value, tuple) else value, self.allowed)


_ANY_STR = _Rule(_to_str, "must be a string")

GRID_RULES: Dict[str, _Rule] = {
    "shape": _Rule(
        _to_ivec3,
        f"must be a list of 3 integers, each in [2, {INT32_MAX}] (int32 on the device)",
        lambda v: all(2 <= n <= INT32_MAX for n in v),
    ),
    "length": _Rule(_to_length, units.length_allowed("a finite length > 0"), units.valid_length),
    "unit": _Rule(_to_str, f"must be a length unit: {units.LENGTH_UNITS_TEXT}", units.is_length_unit),
}

DUST_RULES: Dict[str, _Rule] = {
    "model": _Rule(_to_str, _one_of(DUST_MODELS), lambda v: v in DUST_MODELS),
    "density": _Rule(_to_float, float32_allowed("a number"), _float32_nonneg),
    "file": _ANY_STR,
    "array": _ANY_STR,
    "scale": _Rule(_to_float, float32_allowed("a number"), _float32_nonneg),
    "offset": _Rule(
        _to_vec3,
        f"must be a list of 3 numbers in [-{MAX_OFFSET:g}, {MAX_OFFSET:g}] (box units; beyond, the float32 "
        "turbulence loses its structure: docs/physics.md)",
        lambda v: all(abs(x) <= MAX_OFFSET for x in v),  # False for NaN
    ),
    "floor": _Rule(_to_float, float32_allowed("a number"), _float32_nonneg),
    "tau": _Rule(_to_float, float32_allowed("a number"), _float32_nonneg),
    "hydrogen_density": _Rule(_to_opt_float, "must be a number of H nuclei per cm^3 >= 0 (finite; or omitted)",
                              _opt_nonneg),
    "mass_density": _Rule(_to_opt_float, "must be a dust mass density in g cm^-3 >= 0 (finite; or omitted)",
                          _opt_nonneg),
    "visual_extinction": _Rule(_to_opt_float, "must be an A_V in mag >= 0 (finite; or omitted)", _opt_nonneg),
}

STAR_RULES: Dict[str, _Rule] = {
    "position": _Rule(
        _to_vec3,
        "must be a list of 3 finite numbers in [0, 1] (box units)",
        lambda v: all(0.0 <= x <= 1.0 for x in v),
    ),
    "luminosity": _Rule(_to_float, float32_allowed("a number > 0", zero=False), _float32_pos),
    "temperature": _Rule(
        _to_opt_float,
        f"must be in [{TEMPERATURE_RANGE[0]:g}, {TEMPERATURE_RANGE[1]:g}] (K), or omitted",
        lambda v: v is None or TEMPERATURE_RANGE[0] <= v <= TEMPERATURE_RANGE[1],
    ),
    "bump_radius": _Rule(
        _to_float,
        f"must be 0 or a number in [{limits.fmt(limits.FLOAT32_TINY)}, 1) (box units; float32)",
        lambda v: v == 0.0 or limits.FLOAT32_TINY <= v < 1.0,
    ),
    "spectrum": _Rule(
        _to_spectrum,
        "must be a list of at least 2 [wavelength nm, relative power] pairs, wavelengths "
        "increasing in (0, 1e5], powers finite, >= 0 and not all 0 (or omitted)",
        _valid_spectrum,
    ),
    "luminosity_lsun": _Rule(_to_opt_float, "must be a bolometric luminosity in L_sun: a finite number > 0 "
                             "(or omitted)", lambda v: v is None or _finite_pos(v)),
    "absolute_magnitude": _Rule(_to_opt_float, "must be an absolute magnitude M_V in mag (AB, Bessell V): a "
                                "finite number (or omitted)", _finite),
    "spectral_type": _Rule(_to_opt_str, "must be " + units.SPECTRAL_TYPE_FORM + " (or omitted)",
                           lambda v: v is None or units.parse_spectral_type(v) is not None),
}

# Type-only rules for [bands]; ranges are checked by resolve_bands().
BANDS_RULES: Dict[str, _Rule] = {
    "preset": _Rule(_to_opt_str, "must be a preset name (string)"),
    "albedo": _Rule(_to_opt_float, "must be in [0, 1]"),
    "g": _Rule(_to_opt_float, "must be in [-1, 1]"),
    # "list" is handled separately (array of tables).
}
BAND_ENTRY_RULES: Dict[str, _Rule] = {
    "name": _Rule(_to_str, "must be a non-empty name made of [A-Za-z0-9_-]"),
    "wavelength": _Rule(_to_float, "must be a wavelength in nm in [1, 1e5]"),
    "extinction": _Rule(_to_float, "must be a number > 0 (relative to the reference band) in " + FLOAT32_RANGE_TEXT),
    "albedo": _Rule(_to_float, "must be in [0, 1]"),
    "g": _Rule(_to_float, "must be in [-1, 1]"),
}
assert tuple(BAND_ENTRY_RULES) == BAND_KEYS

TRANSPORT_RULES: Dict[str, _Rule] = {
    "photons": _Rule(
        _to_int, "must be an integer in [1, 2**53]", lambda v: 1 <= v <= MAX_PHOTONS
    ),
    "estimator": _Rule(_to_str, _one_of(ESTIMATORS), lambda v: v in ESTIMATORS),
    "method": _Rule(_to_str, _one_of(METHODS), lambda v: v in METHODS),
    "error_estimate": _Rule(_to_str, _one_of(ERROR_ESTIMATES), lambda v: v in ERROR_ESTIMATES),
    "filter_radius": _Rule(_to_float, "must be a finite number > 0 (box units)", _finite_pos),
    "max_scatterings": _Rule(_to_int, f"must be an integer in [0, {INT32_MAX}] (int32 on the device)",
                             lambda v: 0 <= v <= INT32_MAX),
    "seed": _Rule(_to_int, "must be an integer in [0, 2**53] (exact as a double: ParaView's panel, pvpython)",
                  lambda v: 0 <= v <= MAX_SEED),
    "backend": _Rule(_to_str, _one_of(BACKENDS), lambda v: v in BACKENDS),
    "device": _ANY_STR,
    "batch_size": _Rule(_to_int, f"must be an integer in [0, {MAX_PHOTONS}] (0 = automatic)",
                        lambda v: 0 <= v <= MAX_PHOTONS),
    "target_error": _Rule(_to_float, "must be 0 (off) or a number in (0, 1)", lambda v: v == 0 or 0 < v < 1),
    "time_limit": _Rule(_to_float, "must be a finite number >= 0 (seconds; 0 = none)",
                        lambda v: math.isfinite(v) and v >= 0),
    "quality": _Rule(_to_str, "must be one of: '' (none), " + ", ".join(repr(q) for q in QUALITY_PRESETS),
                     lambda v: v in QUALITIES),
}

COLOUR_RULES: Dict[str, _Rule] = {
    "exposure": _Rule(
        _to_auto_or_float,
        "must be 'auto' or a number > 0 in " + FLOAT32_RANGE_TEXT + " (the colours are float32)",
        lambda v: v == "auto" or _float32_pos(v),
    ),
    "white_point": _Rule(_to_str, _one_of(WHITE_POINTS), lambda v: v in WHITE_POINTS),
    "opacity_scale": _Rule(_to_auto_or_float, "must be 'auto' or a finite number > 0",
                           lambda v: v == "auto" or _finite_pos(v)),
    "stretch": _Rule(_to_str, _one_of(STRETCHES), lambda v: v in STRETCHES),
    "asinh_q": _Rule(_to_float, "must be a number in (0, 1e10] (the asinh softening Q)",
                     lambda v: 0.0 < v <= 1e10),
}

OBSERVER_RULES: Dict[str, _Rule] = {
    "distance": _Rule(_to_opt_length, units.length_allowed("a distance > 0", "pc") + " (or omitted)",
                      lambda v: v is None or units.valid_length(v)),
    "ra": _Rule(_to_float, "must be a right ascension in degrees in [0, 360)", lambda v: 0.0 <= v < 360.0),
    "dec": _Rule(_to_float, "must be a declination in degrees in [-90, 90]", lambda v: -90.0 <= v <= 90.0),
    "position_angle": _Rule(_to_float, "must be an angle in degrees in [-360, 360] (east of north)",
                            lambda v: -360.0 <= v <= 360.0),
    "psf_fwhm": _Rule(_to_float, "must be a FWHM in arcsec >= 0 (finite; 0 = no PSF)", _finite_nonneg),
    "magnitude_system": _Rule(_to_str, _one_of(MAG_SYSTEMS), lambda v: v in MAG_SYSTEMS),
}

# Schema tree, used by from_dict and with_overrides: a dict is a table, a
# one-element list an array of tables, a _Rule a leaf value.
_SCHEMA: Dict[str, Any] = {
    "grid": GRID_RULES,
    "dust": DUST_RULES,
    "stars": [STAR_RULES],
    "bands": {**BANDS_RULES, "list": [BAND_ENTRY_RULES]},
    "transport": TRANSPORT_RULES,
    "colour": COLOUR_RULES,
    "observer": OBSERVER_RULES,
}
_TABLE_NAMES = {
    "grid": "[grid]",
    "dust": "[dust]",
    "stars": "[[stars]]",
    "bands": "[bands]",
    "transport": "[transport]",
    "colour": "[colour]",
    "observer": "[observer]",
}


def _unknown_key(param: str, value: Any, allowed_keys: Sequence[str]) -> SceneError:
    return SceneError(
        param, value, "unknown key; allowed keys: " + ", ".join(repr(k) for k in allowed_keys)
    )


def _parse_table(name: str, d: Any, rules: Mapping[str, _Rule]) -> Dict[str, Any]:
    """Check keys, convert types and check the range of each value of one table."""
    if not isinstance(d, Mapping):
        raise SceneError(name, d, "must be a table")
    out = {}
    for key, value in d.items():
        param = f"{name}.{key}"
        if key not in rules:
            raise _unknown_key(param, value, list(rules))
        out[key] = rules[key].coerce(param, value)
        check = rules[key].check
        if check is not None and not check(out[key]):  # here, so that the message shows the value as given
            raise SceneError(param, value, rules[key].allowed)
    return out


def _parse_array(name: str, d: Any) -> list:
    if isinstance(d, (str, bytes, Mapping)) or not isinstance(d, Sequence):
        raise SceneError(name, d, f"must be an array of tables [[{name}]]")
    return list(d)


def _check_dataclass(prefix: str, obj: Any, rules: Mapping[str, _Rule]) -> None:
    for f in fields(obj):
        rules[f.name].validate(f"{prefix}.{f.name}", getattr(obj, f.name))


def _check_star_spectra(stars: Sequence[Star], bands: Sequence[Band]) -> None:
    """Every star's spectrum must overlap the visible range it is integrated over, and every band
    must get light from some star.

    The band luminosities integrate each spectrum over the bands' range (380-780 nm, widened to
    the outermost band centres) and the colours over the CIE range (360-830 nm); a spectrum
    with no power in 380-780 nm made a run fail half-way ("no power in the bands' range") or
    gave NaN colours, and a band without light divides the colour matrix by 0. Only scenes with
    a measured spectrum or a temperature import the colour module for this (a flat spectrum
    lights every band).
    """
    if not any(s.spectral_source() is not None for s in stars):
        return
    import numpy as np

    from ..optics import colour_convert

    with np.errstate(over="ignore", under="ignore"):  # exp overflows far in the Wien tail: power 0 there
        _check_spectra_overlap(stars, bands, colour_convert)


def _check_spectra_overlap(stars, bands, colour_convert) -> None:
    def key_value(i):
        s = stars[i]
        if s.spectrum:
            return f"stars[{i}].spectrum", [list(p) for p in s.spectrum]
        return f"stars[{i}].temperature", s.temperature

    wl = [b.wavelength for b in bands]
    lo, hi = colour_convert.LUMINOSITY_RANGE_NM
    light = [0.0] * len(bands)
    for i, s in enumerate(stars):
        source = s.spectral_source()
        try:
            # one band centred in the visible: its range is exactly 380-780 nm
            colour_convert.band_luminosity_fractions([0.5 * (lo + hi)], source)
            fractions = colour_convert.band_luminosity_fractions(wl, source)
        except ValueError:
            raise SceneError(*key_value(i), f"must have power inside {lo}-{hi} nm, the visible range over "
                                            "which the band luminosities and colours are integrated") from None
        for b, f in enumerate(fractions):
            light[b] += s.luminosity * float(f)
    for b, band in enumerate(bands):
        if not light[b] > 0:  # also NaN
            i = max(range(len(stars)), key=lambda j: stars[j].luminosity)
            raise SceneError(*key_value(i), f"must give every band light: band {band.name!r} "
                                            f"({band.wavelength:g} nm) gets none from any star")
