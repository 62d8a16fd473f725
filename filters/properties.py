"""The VTK algorithms' properties, bound to the scene schema.

A :class:`Property` names a setter (``Set<Name>``, also the ParaView property's name) and the
scene key it sets; :func:`bind` makes the setters and getters of a list of them on a VTK
algorithm class, with the defaults, choices and ranges of the scene schema
(:func:`nebula_rt.scene.parameters`): nothing of a parameter is written here again. The
ParaView proxies (``plugin/nebula_rt_paraview``) make their property XML from the same
:class:`Property` lists, so plain VTK, pyvista, pvpython and the GUI have one set of defaults.

Values are kept as given (a setter never fails: VTK's and ParaView's setters cannot report
an error to the caller) and checked when the algorithm runs, by the scene's own validation,
whose error names the property (:meth:`NebulaAlgorithm.describe_error`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Optional, Sequence, Tuple

from nebula_rt import scene as _scene
from nebula_rt.scene.schema import Param

__all__ = ["Property", "bind", "scene_values"]


@dataclass(frozen=True)
class Property:
    """One property of a NebulaRT VTK algorithm bound to a scene key.

    Attributes
    ----------
    name : str
        ``Set<name>`` / ``Get<name>`` and the ParaView property's name (state-file API).
    key : str
        The scene key it sets (``"transport.photons"``).
    widget : str
        How a choice or a flag is stored: ``"enum"`` (an integer index into the choices, as
        older state files hold it), ``"bool"``, ``"file"`` (a file name: the panel adds a file
        browser), ``"auto"`` (a parameter that is ``"auto"`` or a
        number: the check box ``flag`` and this number, ``Set<flag>`` / ``Set<name>``); ""
        chooses from the declaration (a string list for choices, a number or text otherwise).
    flag : str
        With ``widget="auto"``: the name of the check box that chooses ``"auto"``
        (``"AutoExposure"``; also a state-file name).
    enabled_by : tuple
        ``(property name, value)``: the panel enables the widget only while that property has
        that value (the controlling property comes first in the panel).
    shown_by : tuple
        ``(property name, value)``: the panel shows the widget only then.
    only : tuple of str
        The choices this algorithm offers, where it offers fewer than the scene (the Dust
        Density source makes no density from a file).
    group : str
        The panel group, where this algorithm shows the key elsewhere than its declaration's
        (``Param.group``): the sky image shows the colour's tone curve with its picture.
    """

    name: str
    key: str
    widget: str = ""
    flag: str = ""
    enabled_by: Tuple = ()
    shown_by: Tuple = ()
    only: Tuple[str, ...] = ()
    group: str = ""

    @property
    def panel_group(self) -> str:
        """The panel group the property sits in: ``group``, else its key's declared group."""
        return self.group or self.param.group

    @property
    def choices(self) -> Tuple[str, ...]:
        return self.only or self.param.choices

    @property
    def param(self) -> Param:
        return _schema_of(self.key).declaration(self.key)

    @property
    def default(self) -> Any:
        return _schema_of(self.key).default(self.key)

    @property
    def number(self) -> Any:
        """With ``widget="auto"``: the number the property holds while ``"auto"`` is chosen."""
        d = self.default
        return self.param.number if d == "auto" else d

    @property
    def elements(self) -> int:
        d = self.default
        return len(d) if isinstance(d, (tuple, list)) else 1


def _schema_of(key: str):
    """The module declaring ``key``: the scene's (:mod:`nebula_rt.scene`), or for ``sky.*`` the
    sky image's (:mod:`nebula_rt.scene.sky_schema`), which a scene file does not hold."""
    if key.startswith("sky."):
        from nebula_rt.scene import sky_schema

        return sky_schema
    return _scene


def _coerce(prop: Property, args):
    """The value of a setter call: a choice given by index (ParaView's enumeration) becomes its
    name; vector setters take their elements as arguments or one sequence."""
    if prop.elements > 1:
        vals = args[0] if len(args) == 1 and hasattr(args[0], "__len__") else args
        return tuple(vals)
    (v,) = args
    choices = prop.choices
    if choices and isinstance(v, int) and not isinstance(v, bool) and 0 <= v < len(choices):
        return choices[v]
    labels = prop.param.choice_labels
    if labels and isinstance(v, str) and v in labels and v not in choices:
        return choices[labels.index(v)]
    if prop.key == "transport.device" and v is None:
        return ""  # ParaView hands an empty string over as None
    if prop.param.type == "int" and isinstance(v, float) and v.is_integer():
        return int(v)  # integers past int32 travel as doubles in ParaView (and 1e5 is an integer)
    return v


def bind(props: Sequence[Property]):
    """Class decorator: ``Set<name>`` / ``Get<name>`` for every property, kept in the
    instance's ``_values`` (scene key -> value; the schema's default until set)."""

    def decorate(cls):
        cls.BOUND_PROPERTIES = tuple(getattr(cls, "BOUND_PROPERTIES", ())) + tuple(props)
        for prop in props:
            if prop.widget == "auto":
                _bind_auto(cls, prop)
                continue

            def setter(self, *args, _p=prop):
                value = _coerce(_p, args)
                if self._values.get(_p.key, object()) != value:
                    # the value before the first change: what "changed" means (inert_properties)
                    self.__dict__.setdefault("_initial_values", {}).setdefault(_p.key, self._values.get(_p.key))
                    self._values[_p.key] = value
                    self.Modified()

            def getter(self, _p=prop):
                return self._values[_p.key]

            setter.__name__, getter.__name__ = "Set" + prop.name, "Get" + prop.name
            p = prop.param
            setter.__doc__ = f"{p.doc} (scene key ``{prop.key}``; default {prop.default!r})."
            getter.__doc__ = f"The value of ``{prop.key}`` set by Set{prop.name}."
            setattr(cls, setter.__name__, setter)
            setattr(cls, getter.__name__, getter)
        return cls

    return decorate


def _bind_auto(cls, prop: Property) -> None:
    """``Set<flag>(on)`` and ``Set<name>(number)`` of an "auto or number" parameter: the value
    is ``"auto"`` while the flag is on, else the number (kept while the flag is on, as a
    panel keeps it)."""
    key = prop.key

    def set_flag(self, on, _p=prop):
        value = "auto" if bool(on) else self._numbers[key]
        if self._values[key] != value:
            self._values[key] = value
            self.Modified()

    def get_flag(self):
        return int(self._values[key] == "auto")

    def set_number(self, *args, _p=prop):
        value = _coerce(_p, args)
        if self._numbers[key] != value:
            self.__dict__.setdefault("_initial_numbers", {}).setdefault(key, self._numbers[key])
            self._numbers[key] = value
            if self._values[key] != "auto":
                self._values[key] = value
            self.Modified()

    def get_number(self):
        return self._numbers[key]

    p = prop.param
    set_flag.__name__, get_flag.__name__ = "Set" + prop.flag, "Get" + prop.flag
    set_number.__name__, get_number.__name__ = "Set" + prop.name, "Get" + prop.name
    set_flag.__doc__ = f'On: ``{key}`` = "auto" (chosen from the data); off: the number of Set{prop.name}.'
    set_number.__doc__ = f"{p.doc} (scene key ``{key}`` while {prop.flag} is off; default {prop.number!r})."
    for f in (set_flag, get_flag, set_number, get_number):
        setattr(cls, f.__name__, f)


def init_values(obj) -> None:
    """The schema's defaults of every bound property of ``obj``'s class (and the numbers of
    the "auto or number" ones)."""
    props = type(obj).BOUND_PROPERTIES
    obj._values = {p.key: p.default for p in props}
    obj._numbers = {p.key: p.number for p in props if p.widget == "auto"}


def scene_values(values: Dict[str, Any], base: Optional[dict] = None) -> dict:
    """A scene dict (``{"transport": {"photons": ...}, ...}``) from dotted keys, merged into
    ``base``; keys of ``stars.*`` are left to the caller (a scene has a list of stars)."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in (base or {}).items()}
    for key, value in values.items():
        table, name = key.split(".", 1)
        if table == "stars":
            continue
        if isinstance(value, tuple):
            value = list(value)
        out.setdefault(table, {})[name] = value
    return out


def _enabled(alg, name: str, want) -> bool:
    """Whether the property ``name`` of ``alg`` has the panel value ``want`` (an enumeration's
    index, a flag's 0/1): a bound property's choice, or the algorithm's own property through
    its getter (a text among ``alg.OWN_CHOICES[name]``)."""
    bound = {p.name: p for p in getattr(alg, "BOUND_PROPERTIES", ())}.get(name)
    if bound is not None:
        value, choices = alg._values[bound.key], bound.choices
    else:
        value, choices = getattr(alg, "Get" + name)(), getattr(alg, "OWN_CHOICES", {}).get(name, ())
    if isinstance(value, str) and choices and isinstance(want, int) and 0 <= want < len(choices):
        return value == choices[want]
    return value == want


def _unchanged(a, b) -> bool:
    """Two values of a property are the same setting (an empty text and None are both "not
    given": ParaView's panel sends "" for the Distance that the algorithm holds as None)."""
    return a == b or (a in ("", None) and b in ("", None))


def inert_properties(alg) -> list:
    """The messages for properties changed from their initial value that have no effect now:
    the panel greys them out or hides them (``enabled_by``, ``shown_by``) while the property
    that enables them has another value, and a script that sets them would otherwise change nothing without a word (e.g.
    Albedo without OverrideOptics)."""
    initial = getattr(alg, "_initial_values", {})
    out = []
    for p in getattr(alg, "BOUND_PROPERTIES", ()):
        if not (p.enabled_by or p.shown_by) or p.key not in initial or _unchanged(alg._values[p.key], initial[p.key]):
            continue
        name, want = p.enabled_by or p.shown_by
        if not _enabled(alg, name, want):
            own = getattr(alg, "OWN_CHOICES", {}).get(name, ())
            bound = {q.name: q for q in alg.BOUND_PROPERTIES}.get(name)
            choices = bound.choices if bound is not None else own
            wanted = repr(choices[want]) if choices and 0 <= want < len(choices) else want
            out.append(f"{p.name} = {alg._values[p.key]!r} has no effect: it applies while {name} is {wanted}; "
                       f"set {name} to {wanted} to use it")
    numbers = getattr(alg, "_initial_numbers", {})
    for p in getattr(alg, "BOUND_PROPERTIES", ()):
        # an "auto or number" property's number while its flag chooses "auto"
        if p.widget == "auto" and p.key in numbers and alg._numbers[p.key] != numbers[p.key] \
                and alg._values[p.key] == "auto":
            out.append(f"{p.name} = {alg._numbers[p.key]!r} has no effect: it applies while {p.flag} is 0 "
                       f"(now 1: chosen from the data); set {p.flag} to 0 to use it")
    return out
