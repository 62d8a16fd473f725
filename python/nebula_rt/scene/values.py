"""What a scene value may be written as, and how it becomes the value the scene holds: the
conversions from TOML, JSON, ``--set`` text and the panels' numbers, one per declared type
(:data:`CONVERT`), each raising TypeError or ValueError for a value of the wrong kind. The
ranges are checked after, from the declarations (:mod:`nebula_rt.scene.rules`)."""

from __future__ import annotations

import math
import numbers
from pathlib import Path
from typing import Any, Mapping, Optional, Tuple, Union


def is_real(v: Any) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def to_float(v: Any) -> float:
    if not is_real(v):
        raise TypeError
    return float(v)  # may raise OverflowError for huge ints


def to_bool(v: Any) -> bool:
    """TOML's true and false (a panel's checkbox, 0 or 1, too); nothing else is a switch."""
    if isinstance(v, bool):
        return v
    if isinstance(v, numbers.Integral) and int(v) in (0, 1):
        return bool(v)
    raise TypeError


def to_int(v: Any) -> int:
    if isinstance(v, bool):
        raise TypeError
    if isinstance(v, numbers.Integral):
        return int(v)
    if is_real(v):
        f = float(v)
        # a whole float (2.1e6) is an integer; beyond 2**53 a float no longer says which one
        if math.isfinite(f) and f == math.floor(f) and abs(f) <= 2.0**53:
            return int(f)
    raise TypeError


def to_spectrum(v: Any):
    if v is None:
        return None
    if isinstance(v, (str, bytes)) or not isinstance(v, (list, tuple)):
        raise TypeError
    pairs = []
    for p in v:
        if isinstance(p, (str, bytes)) or not isinstance(p, (list, tuple)) or len(p) != 2:
            raise TypeError
        pairs.append((to_float(p[0]), to_float(p[1])))
    return tuple(pairs)


def valid_spectrum(v) -> bool:
    """At least 2 pairs, wavelengths increasing in (0, 1e5] nm, powers finite, >= 0, not all 0."""
    if v is None:
        return True
    wl = [p[0] for p in v]
    power = [p[1] for p in v]
    return (len(v) >= 2 and all(math.isfinite(x) and 0.0 < x <= 1e5 for x in wl)
            and all(b > a for a, b in zip(wl, wl[1:]))
            and all(math.isfinite(x) and x >= 0.0 for x in power) and any(x > 0.0 for x in power))


def to_str(v: Any) -> str:
    if not isinstance(v, str):
        raise TypeError
    return v


def to_opt_str(v: Any) -> Optional[str]:
    return None if v is None else to_str(v)


def to_opt_float(v: Any) -> Optional[float]:
    return None if v is None else to_float(v)


def _three(v: Any) -> list:
    """The 3 items of a list, tuple or 1-d array; TypeError otherwise."""
    if isinstance(v, (str, bytes, Mapping)):
        raise TypeError
    items = list(v)  # TypeError if not iterable
    if len(items) != 3:
        raise TypeError
    return items


def to_vec3(v: Any) -> Tuple[float, float, float]:
    return tuple(to_float(x) for x in _three(v))  # type: ignore[return-value]


def to_ivec3(v: Any) -> Tuple[int, int, int]:
    return tuple(to_int(x) for x in _three(v))  # type: ignore[return-value]


def to_length(v: Any) -> Union[float, str]:
    """A length: a number (float) or a quantity string ("3 pc"), checked by units.valid_length."""
    return v if isinstance(v, str) else to_float(v)


def to_opt_length(v: Any) -> Optional[Union[float, str]]:
    return None if v is None else to_length(v)


def to_auto_or_float(v: Any) -> Union[float, str]:
    if v == "auto" and isinstance(v, str):
        return v
    return to_float(v)


def to_float_or_floats(v: Any) -> Union[float, Tuple[float, ...]]:
    """One number, or a non-empty list of numbers (one per band) as a tuple."""
    if is_real(v):
        return float(v)
    if isinstance(v, (list, tuple)) and v and all(is_real(x) for x in v):
        return tuple(float(x) for x in v)
    raise TypeError


def to_opt_float_or_floats(v: Any) -> Optional[Union[float, Tuple[float, ...]]]:
    return None if v is None else to_float_or_floats(v)


#: The conversion of each declared type (``Param.type``); a declaration with a type not
#: listed names its own (``Param.convert``).
CONVERT = {
    "float": to_float,
    "float or None": to_opt_float,
    "int": to_int,
    "str": to_str,
    "str or None": to_opt_str,
    "tuple of 3 float": to_vec3,
    "tuple of 3 int": to_ivec3,
    "\"auto\" or float": to_auto_or_float,
    "bool": to_bool,
    "float or list of float": to_float_or_floats,
    "float or list of float or None": to_opt_float_or_floats,
}

#: How a refusal names a value of each declared type (``Param.what`` where it says more)
WHAT = {
    "float": "a number", "float or None": "a number", "int": "an integer", "str": "a string",
    "str or None": "a string", "tuple of 3 float": "a list of 3 numbers",
    "tuple of 3 int": "a list of 3 integers, each", "\"auto\" or float": "a number",
    "bool": "true or false",
    "float or list of float": "a number or a list of numbers (one per band), each",
    "float or list of float or None": "a number or a list of numbers (one per band), each",
}


def scene_relative_path(text: str, base_dir) -> Path:
    """A file key's path (``dust.file``, ``bands.grain_matrix``): ``~`` expanded, and a relative
    one taken from ``base_dir`` (the scene file's folder) where there is one."""
    p = Path(text).expanduser()
    if not p.is_absolute() and base_dir is not None:
        p = Path(base_dir) / p
    return p
