"""The checks of a scene's values: each key's rule, made from its declaration (type, range,
choices, the declaration's own check: :func:`rule`), and the checks across keys, each failure a :class:`~nebula_rt.errors.SceneError` that names the
key, the value and what is allowed."""

from __future__ import annotations

import math
from dataclasses import fields
from typing import Any, Callable, Dict, Mapping, Optional, Sequence

from .. import limits
from ..errors import SceneError
from ..limits import in_float32_range
from ..optics.bands import BAND_KEYS, ENTRY_ALLOWED, Band
from .schema import Param, _num, interval
from .sections import BandsConfig, Colour, Dust, Grid, Observer, Star, Transport
from .values import CONVERT, WHAT, is_real, to_float, to_str


class _Rule:
    """How one TOML key is converted (type) and checked (range): made from its declaration
    (:func:`rule`), never written by hand."""

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


def _optional(p: Param) -> bool:
    return p.type.endswith("or None")


def _number_in_range(p: Param, x) -> bool:
    """One number against the declaration's range (finite always; float32's range too). An
    integer is compared as it is: 2**53 + 1 is not 2**53."""
    if not isinstance(x, int) and not math.isfinite(x):
        return False
    if p.off and x == 0:
        return True
    if p.float32:
        if x == 0:
            return p.lo == 0 and not p.lo_open
        if not in_float32_range(x, zero=False):
            return False
    if p.lo is not None and (x < p.lo or (p.lo_open and x == p.lo)):
        return False
    if p.hi is not None and (x > p.hi or (p.hi_open and x == p.hi)):
        return False
    return True


def _check(p: Param) -> Callable[[Any], bool]:
    def check(v: Any) -> bool:
        if v is None:
            return _optional(p)
        if p.auto and isinstance(v, str) and v == "auto":
            return True
        if p.choices:
            ok = v in p.choices
        elif isinstance(v, tuple):
            ok = all(_number_in_range(p, x) for x in v if is_real(x))
        elif is_real(v):
            ok = _number_in_range(p, v)
        else:
            ok = True
        return ok and (p.check is None or bool(p.check(v)))

    return check


def allowed_text(p: Param) -> str:
    """What a refusal of ``p`` says is allowed, made from the declaration (or its ``allowed``)."""
    if p.allowed:
        return p.allowed
    if p.choices:
        labels = p.choice_labels or p.choices
        return "one of: " + ", ".join(repr(c) + (f" ({t})" if t != c else "") for c, t in zip(p.choices, labels))
    what = p.what or WHAT.get(p.type, "a value")
    head = "'auto' or " if p.auto else ""
    if p.off:
        head += "0 (off) or "
    if p.float32:
        if p.lo == 0 and not p.lo_open:
            head += "0 or "
        lo = limits.fmt(limits.FLOAT32_TINY) if p.lo in (None, 0) else _num(p.lo)
        hi = limits.fmt(limits.FLOAT32_MAX) if p.hi is None else _num(p.hi)
        span = f"in [{lo}, {hi}{')' if p.hi_open else ']'}"
    else:
        span = interval(p)
    notes = [p.note or ("the float32 range the device computes in" if p.float32 else "")]
    if _optional(p):
        notes.append("or omitted")
    note = "; ".join(n for n in notes if n)
    return f"must be {head}{what}" + (f" {span}" if span else "") + (f" ({note})" if note else "")


def rule(p: Param) -> _Rule:
    """The conversion, check and refusal text of a declared parameter, all from ``p``."""
    return _Rule(p.convert or CONVERT[p.type], allowed_text(p), _check(p))


def rules_of(cls, skip=()) -> Dict[str, _Rule]:
    """The rules of a table's dataclass, by key (the declared fields, but ``skip``)."""
    return {f.name: rule(f.metadata["param"]) for f in fields(cls) if "param" in f.metadata and f.name not in skip}


GRID_RULES = rules_of(Grid)
DUST_RULES = rules_of(Dust)
STAR_RULES = rules_of(Star)
# [bands]: its "list" (an array of tables) is parsed apart, entry by entry
BANDS_RULES = rules_of(BandsConfig, skip=("list",))
# [[bands.list]] entries: a Band's fields (nebula_rt.optics.bands), whose ranges resolve_bands()
# checks once the bands are known; here their types
BAND_ENTRY_RULES: Dict[str, _Rule] = {
    key: _Rule(to_str if key == "name" else to_float, ENTRY_ALLOWED[key]) for key in BAND_KEYS}
assert tuple(BAND_ENTRY_RULES) == BAND_KEYS
TRANSPORT_RULES = rules_of(Transport)
COLOUR_RULES = rules_of(Colour)
OBSERVER_RULES = rules_of(Observer)

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
