"""Overrides of a scene's keys (``--set transport.photons=1e6``, the filters' properties): the
value parsed from text and set into the scene's dict, the derived box-unit values dropped so
that their physical keys convert again."""

from __future__ import annotations

import re
import sys
from typing import Any, Dict

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from ..errors import SceneError
from . import units
from .rules import _Rule, _SCHEMA, _TABLE_NAMES


def _drop_derived(d: Dict[str, Any], overridden) -> None:
    """Drop the box-unit values that physical keys set (dust.tau, a star's luminosity) from
    the scene dict of :meth:`Scene.with_overrides`, so that they are converted again from the
    physical keys as overridden; one overridden itself stays (and must then agree)."""
    dust = d.get("dust")
    if isinstance(dust, dict) and any(dust.get(k) is not None for k in units.DUST_KEYS) \
            and not overridden & {"dust.tau", "dust"}:
        dust.pop("tau", None)
    stars = d.get("stars")
    if isinstance(stars, list) and "stars" not in overridden:
        for i, s in enumerate(stars):
            if isinstance(s, dict) and (s.get("luminosity_lsun") is not None or s.get("absolute_magnitude")
                                        is not None) and not overridden & {f"stars.{i}.luminosity", f"stars.{i}"}:
                s.pop("luminosity", None)
            if isinstance(s, dict) and s.get("spectral_type") is not None \
                    and not overridden & {f"stars.{i}.temperature", f"stars.{i}"}:
                s.pop("temperature", None)


def _parse_toml(text: str, where: str) -> Dict[str, Any]:
    """TOML text -> dict; SceneError("(toml)", where, ...) on malformed or pathologically
    nested text (tomllib recurses once per nesting level)."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SceneError("(toml)", where, f"not valid TOML: {e}") from None
    except RecursionError:
        raise SceneError("(toml)", where, "not valid TOML: arrays or tables nested too deeply") from None
    except ValueError as e:  # Python's own limit: an integer of more than 4300 digits
        raise SceneError("(toml)", where, f"not valid TOML here: {str(e).split(';')[0]}") from None


_NUMERIC_ARRAY = re.compile(r"= \[\n((?:[ \t]+[-+0-9.eE_infa]+,\n)+)\]")


def _parse_value(raw: str) -> Any:
    try:
        parsed = tomllib.loads("v = " + raw)
    except Exception:
        return raw
    if set(parsed) != {"v"}:  # e.g. an embedded newline: not a single value
        return raw
    return parsed["v"]


def _apply_override(d: Dict[str, Any], key: str, value: Any) -> None:
    norm = re.sub(r"\[(\d+)\]", r".\1", key)
    tokens = norm.split(".")
    if not key or any(t == "" for t in tokens):
        raise SceneError(key, value, "an override key is dotted, e.g. transport.photons")

    container: Any = d
    schema: Any = _SCHEMA
    for depth, tok in enumerate(tokens):
        last = depth == len(tokens) - 1
        where = ".".join(tokens[:depth]) or "(scene)"
        if isinstance(schema, dict):
            if tok not in schema:
                if depth == 0:
                    allowed = "unknown table; allowed tables: " + ", ".join(_TABLE_NAMES.values())
                else:
                    allowed = "unknown key; allowed keys: " + ", ".join(repr(k) for k in schema)
                raise SceneError(key, value, allowed)
            if last:
                container[tok] = value
                if tokens[:depth] == ["bands"] and tok == "preset":
                    container.pop("list", None)
                return
            sub = schema[tok]
            if isinstance(sub, _Rule):
                raise SceneError(key, value, f"{'.'.join(tokens[: depth + 1])} is a value, not a table")
            if tok not in container:
                container[tok] = {} if isinstance(sub, dict) else []
            container, schema = container[tok], sub
            if isinstance(schema, dict) and not isinstance(container, dict):
                raise SceneError(key, value, f"{'.'.join(tokens[: depth + 1])} is not a table")
        else:  # array of tables
            n = len(container) if isinstance(container, list) else 0
            if not tok.isdigit() or int(tok) >= n:
                raise SceneError(
                    key,
                    value,
                    f"{where} is an array of {n} table(s): use {where}.N.key with N in 0..{n - 1}",
                )
            i = int(tok)
            if last:
                container[i] = value
                return
            container, schema = container[i], schema[0]
            if not isinstance(container, dict):
                raise SceneError(key, value, f"{where}.{i} is not a table")
