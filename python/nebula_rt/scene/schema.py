"""The scene schema: every scene parameter declared once.

Each field of the scene's dataclasses (:mod:`nebula_rt.scene`) carries a :class:`Param` in its
metadata: documentation, unit, range or choices, and how a panel shows it (label, group,
advanced). Its default is the dataclass field's default. Everything else reads the
declaration from here instead of repeating it:

- the scene classes' docstrings (their ``Parameters`` sections are generated),
- the VTK algorithms' setters and their defaults (``nebula_rt.filters.properties``),
- the ParaView proxies' property XML: order, groups, domains, tooltips, visibility
  (``plugin/nebula_rt_paraview``),
- the CLI's choices.

Why dataclass metadata and not a schema library (pydantic v2 was considered): the scene's
validation rules are NebulaRT's own (float32 representability on the device, int32 and
uint64 limits, the error contract ``SceneError(parameter, value, allowed)`` that names the
parameter and the allowed range); a schema library would wrap each of them in a custom
validator and translate its errors back. What was repeated by hand were the declarations, and
field metadata holds them with no new dependency for ParaView's own Python.

Keys are dotted scene-file keys: ``"transport.photons"``, ``"dust.tau"``; a star's fields are
``"stars.position"`` etc. (the same for every star).

This module never imports VTK.
"""

from __future__ import annotations

import dataclasses
import textwrap
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Optional, Tuple

__all__ = ["Param", "param", "parameters", "label", "interval", "range_text", "document"]


@dataclass(frozen=True)
class Param:
    """The declaration of one scene parameter (its default is the field's default).

    Attributes
    ----------
    doc : str
        What it is and does, in sentences (the tooltip and the docstring).
    type : str
        Shown in the docstring: ``"float"``, ``"int"``, ``"str"``, ``"tuple of 3 float"``...
    unit : str
        Unit of the value ("box units", "K", "nm", "s"; "" for none).
    lo, hi : float or int or None
        Numeric range (None: unbounded on that side); for tuples, of every element.
    lo_open : bool
        The range excludes ``lo`` (> lo rather than >= lo).
    choices : tuple of str
        The allowed strings (an enumeration), in the order a panel lists them.
    choice_labels : tuple of str
        The panel's texts of the choices, where they differ from the choices themselves.
    label : str
        The panel's label ("" = the field name, capitalised).
    group : str
        The panel group ("" = none).
    advanced : bool
        Shown only under the panel's advanced (gear) toggle.
    auto : bool
        The parameter is ``"auto"`` (the value chosen from the data) or a number in the range:
        a panel shows a check box ("Auto <label>") and the number, enabled while it is off.
    number : float or None
        With ``auto``: the number a panel holds until one is chosen (and the scene's value once
        the check box is cleared).
    hi_open : bool
        The range excludes ``hi`` (< hi rather than <= hi).
    float32 : bool
        The value reaches the device as float32: besides the range (``lo`` 0 meaning "0, or at
        least the smallest normal float32"), its magnitude must lie in the normal float32 range.
    off : bool
        0 is allowed below the range, meaning "off" (``transport.target_error``).
    what : str
        How a refusal names the value ("a right ascension in degrees"; "" = by its type).
    note : str
        The refusal's reason or unit, in parentheses ("int32 on the device").
    allowed : str
        The refusal's whole text, for a value whose form a range cannot say (a length with
        units, a spectrum); "" = made from the range and choices.
    convert : callable or None
        Text or number -> the value, raising TypeError or ValueError, for a type whose
        conversion :data:`nebula_rt.scene.values.CONVERT` does not hold.
    check : callable or None
        A check of the converted value beyond the range and choices (a known length unit).

    The range, choices and these fields are the validation too (:func:`nebula_rt.scene.rules.rule`):
    nothing else states a parameter's range.
    """

    doc: str
    type: str = ""
    unit: str = ""
    lo: Optional[float] = None
    hi: Optional[float] = None
    lo_open: bool = False
    choices: Tuple[str, ...] = ()
    choice_labels: Tuple[str, ...] = ()
    label: str = ""
    group: str = ""
    advanced: bool = False
    auto: bool = False
    number: Optional[float] = None
    hi_open: bool = False
    float32: bool = False
    off: bool = False
    what: str = ""
    note: str = ""
    allowed: str = ""
    convert: Optional[Callable[[Any], Any]] = None
    check: Optional[Callable[[Any], bool]] = None


def param(default: Any = dataclasses.MISSING, *, default_factory: Any = dataclasses.MISSING, **kw) -> Any:
    """A dataclass field with its :class:`Param` declaration (keyword arguments)."""
    meta = {"param": Param(**kw)}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def _field_default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return f.default_factory()  # type: ignore[misc]
    return None


def parameters(sections) -> Iterator[Tuple[str, Param, Any]]:
    """Every declared parameter of ``sections`` ((table name, dataclass) pairs, e.g.
    :data:`nebula_rt.scene.SECTIONS`) as (key, declaration, default), in their order."""
    for section, cls in sections:
        for f in dataclasses.fields(cls):
            p = f.metadata.get("param")
            if p is not None:
                yield f"{section}.{f.name}", p, _field_default(f)


def declaration(sections, key: str) -> Param:
    """The declaration of ``key`` among ``sections``' parameters; KeyError if none."""
    for k, p, _ in parameters(sections):
        if k == key:
            return p
    raise KeyError(key)


def default(sections, key: str) -> Any:
    """The default value of ``key`` among ``sections``' parameters; KeyError if none."""
    for k, _, d in parameters(sections):
        if k == key:
            return d
    raise KeyError(key)


class Declarations:
    """The lookups of one set of ``sections`` (``(table name, dataclass)`` pairs): the scene's
    (:mod:`nebula_rt.scene.sections`) and the sky image's (:mod:`nebula_rt.scene.sky_schema`)
    export its bound methods as their ``parameters``, ``declaration`` and ``default``."""

    def __init__(self, sections):
        self.sections = sections

    def parameters(self) -> Iterator[Tuple[str, Param, Any]]:
        """Every declared parameter as (key, :class:`Param`, default), in the tables' order."""
        return parameters(self.sections)

    def declaration(self, key: str) -> Param:
        """The declaration of ``key`` (``"transport.photons"``); KeyError if none."""
        return declaration(self.sections, key)

    def default(self, key: str) -> Any:
        """The default value of ``key``; KeyError if none."""
        return default(self.sections, key)


def label(key: str, p: Param) -> str:
    """The panel label of ``key`` declared by ``p``."""
    return p.label or key.rsplit(".", 1)[1].replace("_", " ").capitalize()


def _num(x) -> str:
    """A bound as people write it: 2**53 rather than its digits (int32's largest, 2147483647,
    stays in digits: the number VTK and C print)."""
    if isinstance(x, int) and abs(x) >= 2**20:
        for k in range(20, 130):
            if x == 2**k:
                return f"2**{k}"
        return str(x)
    return f"{x:g}"


def interval(p: Param) -> str:
    """The range of a declaration in words: "in [0, 360)", "> 0", ">= 0" ("" for none)."""
    if p.lo is not None and p.hi is not None:
        return f"in {'(' if p.lo_open else '['}{_num(p.lo)}, {_num(p.hi)}{')' if p.hi_open else ']'}"
    if p.lo is not None:
        return f"{'>' if p.lo_open else '>='} {_num(p.lo)}"
    if p.hi is not None:
        return f"{'<' if p.hi_open else '<='} {_num(p.hi)}"
    return ""


def range_text(p: Param) -> str:
    """The allowed values of a declaration in words ("" when any value of its type is)."""
    if p.choices:
        return "one of " + ", ".join(repr(c) for c in p.choices)
    text = interval(p)
    if p.off:
        text = "0 (off) or " + text
    if p.auto:
        return "'auto' or a number " + text if text else "'auto' or a number"
    return text


def document(cls: type) -> type:
    """Class decorator: append the numpy-style ``Parameters`` section of a scene dataclass,
    made from its fields' declarations, to its docstring (the summary stays as written)."""
    lines = ["", "Parameters", "----------"]
    for f in dataclasses.fields(cls):
        p = f.metadata.get("param")
        if p is None:
            continue
        head = f"{f.name} : {p.type}" if p.type else f.name
        extra = []
        if p.unit:
            extra.append(p.unit)
        rng = range_text(p)
        if rng:
            extra.append(rng)
        extra.append(f"default {_field_default(f)!r}")
        body = f"{p.doc} ({'; '.join(extra)})."
        lines.append(head)
        lines.extend(textwrap.wrap(body, 92, initial_indent="    ", subsequent_indent="    ",
                                   break_on_hyphens=False))
    summary = textwrap.dedent(cls.__doc__ or "").rstrip()
    cls.__doc__ = summary + "\n" + "\n".join(lines) + "\n"
    return cls


