"""Small XML helpers shared by the proxy definitions (ServerManager XML snippets).

Only decorators of ParaView 5.11's ``paraview.util.vtkAlgorithm`` are used (``smdomain.xml``,
``smhint.xml``, ``smproperty.xml``): they exist unchanged up to 6.x.
"""

import re
from xml.sax.saxutils import escape, quoteattr

from paraview.util.vtkAlgorithm import smdomain, smhint, smproperty

#: proxy hint: Filters > NebulaRT / Sources > NebulaRT
MENU = '<ShowInMenu category="NebulaRT" />'
#: proxy hint: show the output as a volume in render views
VOLUME = '<RepresentationType view="RenderView" type="Volume" />'
#: proxy hints of Nebula Light Field: port 1 (the stars) as points, the rest as a volume (the
#: hints are read in order, port-specific first); nebula_rt_paraview.display sets the colours
LIGHT_FIELD_DISPLAY = '<RepresentationType view="RenderView" type="Points" port="1" />' + VOLUME
#: the names of Nebula Light Field's output ports (the pipeline browser shows them)
LIGHT_FIELD_PORTS = ('<OutputPort name="Light Field" index="0" /><OutputPort name="Stars" index="1" />'
                     '<OutputPort name="Light per Leaf" index="2" />')
#: proxy hints of Nebula Sky Image: its own 2D view (nebula_rt_paraview.views), as a slice
SKY_IMAGE_DISPLAY = ('<View type="NebulaSkyView" />'
                     '<RepresentationType view="NebulaSkyView" type="Slice" />'
                     '<RepresentationType view="RenderView" type="Slice" />'
                     '<PipelineIcon name="GEOMETRY" />')  # (the icon would be the view's, which has none)

#: proxy hints of Nebula Polarization Vectors: its line segments in the sky image's view, over
#: the picture (nebula_rt_paraview.display draws them white)
POLARIZATION_VECTORS_DISPLAY = ('<View type="NebulaSkyView" />'
                                '<RepresentationType view="NebulaSkyView" type="Surface" />'
                                '<RepresentationType view="RenderView" type="Surface" />'
                                '<PipelineIcon name="GEOMETRY" />')  # (as the sky image's: the view has none)


def help_text(cls):
    """(short help, description) of a proxy from its VTK algorithm's docstring (the one place
    it is written): the summary line, and the paragraphs after it as plain text."""
    import inspect
    import re

    text = inspect.cleandoc(cls.__doc__ or "")
    text = re.sub(r":\w+:`~?([^`]+)`", r"\1", text).replace("``", "")
    paras = [" ".join(p.split()) for p in text.split("\n\n") if p.strip()]
    return paras[0], " ".join(paras[1:]) or paras[0]


def proxy_doc(cls):
    """Class decorator: the proxy's ``<Documentation>`` (its help text: the properties panel's
    help and the menus' status tips) from :func:`help_text` of the VTK algorithm ``cls``."""
    short, body = help_text(cls)
    return smproperty.xml("<Documentation long_help=%s short_help=%s>%s</Documentation>"
                          % (quoteattr(short), quoteattr(short), escape(body)))


def doc(text):
    """``<Documentation>`` (the property's tooltip) nested in the property element."""
    return smdomain.xml("<Documentation>%s</Documentation>" % escape(" ".join(text.split())))


def boolean():
    """A check box (5.11 has no ``smdomain.boolean``)."""
    return smdomain.xml('<BooleanDomain name="bool"/>')


def enumeration(*entries):
    """A combo box over integers: entries are the texts of the values 0, 1, ..."""
    items = "".join('<Entry value="%d" text=%s/>' % (i, quoteattr(t)) for i, t in enumerate(entries))
    return smdomain.xml('<EnumerationDomain name="enum">%s</EnumerationDomain>' % items)


def string_list(*values):
    """A combo box over strings (the string itself is stored in states)."""
    items = "".join("<String value=%s/>" % quoteattr(v) for v in values)
    return smdomain.xml('<StringListDomain name="list">%s</StringListDomain>' % items)


def shown_when(prop, value, mode="visibility"):
    """Show (``mode="visibility"``) or enable (``"enabled_state"``) the widget only while the
    property ``prop`` has ``value``."""
    return smhint.xml('<PropertyWidgetDecorator type="GenericDecorator" mode=%s property=%s value=%s />'
                      % (quoteattr(mode), quoteattr(prop), quoteattr(str(value))))


def property_groups(*groups):
    """``<PropertyGroup>`` elements: ``groups`` are ``(label, [property names])``.

    Hang them on a method whose name sorts last (``zz_property_groups``): ParaView 5.11 orders
    the proxy's XML by method name (5.13+: by line)."""
    out = []
    for label, names in groups:
        props = "".join("<Property name=%s/>" % quoteattr(n) for n in names)
        out.append("<PropertyGroup label=%s>%s</PropertyGroup>" % (quoteattr(label), props))
    return "\n".join(out)


_PROPERTY_NAME = re.compile(r'<\w+VectorProperty\s+name="([^"]+)"')


def panel(props, defaults=None, extra=None, head=(), own_groups=None):
    """A proxy's panel: its schema-bound properties' XML (as :func:`bound_properties`, with
    ``head``, XML of the filter's own properties, first) and its property groups, read from
    the declarations: a bound property sits in its ``Property.panel_group`` (its scene key's
    ``Param.group`` unless the algorithm says otherwise), its "auto" check box and the
    information property of what "auto" chose beside it, and a
    property of the filter's own in ``own_groups[name]``. Groups in the order of their first
    property; every property is in one (a ValueError names one that is not)."""
    body = "\n".join(list(head) + [bound_properties(props, defaults, extra)])
    group_of = {p.name: p.panel_group for p in props}
    group_of.update({p.flag: p.panel_group for p in props if p.flag})
    group_of.update({p.name + "Chosen": p.panel_group for p in props if p.widget == "auto"})
    group_of.update(own_groups or {})
    groups = {}
    for name in _PROPERTY_NAME.findall(body):
        if not group_of.get(name):
            raise ValueError(f"panel property {name} has no group: declare one")
        groups.setdefault(group_of[name], []).append(name)
    return body + "\n" + property_groups(*groups.items())


def star_columns():
    """The Stars table's column headers, in the order of the flat Stars vector
    (nebula_rt.filters.base.STAR_COLUMNS)."""
    from nebula_rt.filters.base import STAR_COLUMNS

    return [header for header, _f, _c in STAR_COLUMNS]


def stars_doc():
    """The Stars table's tooltip: its columns with the star's declarations (the scene keys of
    nebula_rt.filters.base.STAR_COLUMNS)."""
    from nebula_rt import scene
    from nebula_rt.filters.base import STAR_COLUMNS
    from nebula_rt.scene.schema import range_text

    parts = []
    fields = list(dict.fromkeys(f for _h, f, _c in STAR_COLUMNS))
    for field in fields:
        cols = ", ".join(h for h, f, _c in STAR_COLUMNS if f == field)
        key = "stars." + field
        p = scene.declaration(key)
        extra = "; ".join(x for x in (p.unit, range_text(p), "scene key " + key) if x)
        parts.append(f"{cols}: {p.doc} ({extra}).")
    return "One row per star. " + " ".join(parts)


def stars_property(default, enabled_by=None):
    """The repeatable ``Stars`` property: a row of STAR_COLUMNS per star, ``AddStar`` once per
    star after ``RemoveAllStars``; ``default``: the rows it starts with; ``enabled_by``:
    ``(property, value)`` that enables the table.

    The table's columns have headers (``ShowComponentLabels``, read by ParaView's
    pqDoubleVectorPropertyWidget for a repeatable property and handed to its
    pqScalarValueListPropertyWidget). Its "+" copies the selected row, or the last one (5.11's
    pqScalarValueListPropertyWidget; no XML sets a new row's values): the table starts with
    the default star, so "+" adds a visible star, and only a table emptied first gets a row of
    zeros (luminosity 0, refused on Apply naming the star's luminosity)."""
    from nebula_rt.filters.base import STAR_COLUMNS

    values = " ".join(repr(float(v)) for v in default)
    labels = "".join('<ComponentLabel component="%d" label=%s/>' % (i, quoteattr(t))
                     for i, t in enumerate(star_columns()))
    doc = escape(stars_doc())
    hints = "<ShowComponentLabels>%s</ShowComponentLabels>" % labels
    if enabled_by:
        hints += ('<PropertyWidgetDecorator type="GenericDecorator" mode="enabled_state" property=%s '
                  'value=%s />' % (quoteattr(enabled_by[0]), quoteattr(str(enabled_by[1]))))
    hints = "<Hints>%s</Hints>" % hints
    return """
<DoubleVectorProperty name="Stars" label="Stars" command="AddStar" clean_command="RemoveAllStars"
    repeat_command="1" number_of_elements_per_command="%d" use_index="0"
    number_of_elements="%d" default_values="%s">
  <Documentation>%s</Documentation>%s
</DoubleVectorProperty>""" % (len(STAR_COLUMNS), len(default), values, doc, hints)


STARS_FROM_INPUT = """
<IntVectorProperty name="StarsFromInput" label="Stars From Input" command="SetStarsFromInput"
    number_of_elements="1" default_values="1">
  <BooleanDomain name="bool"/>
  <Documentation>Light the density with the stars it was made with (Nebula Dust Density passes
    them on): the stars are entered once. Off, or for an input without stars (a .vti file): the
    Stars table below.</Documentation>
</IntVectorProperty>"""


def input_with_array_domain():
    """Input-array domain of the density array: one-component point or cell arrays."""
    return smdomain.xml('<InputArrayDomain name="input_array" attribute_type="any-except-field" '
                        'number_of_components="1" />')


DENSITY_ARRAY = """
<StringVectorProperty name="DensityArray" label="Density Array" command="SetInputArrayToProcess"
    number_of_elements="5" element_types="0 0 0 0 2" animateable="0">
  <ArrayListDomain name="array_list" attribute_type="Scalars" input_domain_name="input_array">
    <RequiredProperties>
      <Property name="Input" function="Input" />
    </RequiredProperties>
  </ArrayListDomain>
  <Documentation>The dust density: a one-component point or cell array of the input (one value
    per voxel; cells are voxels for a cell array). The grid spans the box [0, 1]^3 whatever its
    spacing.</Documentation>
</StringVectorProperty>"""


# -- properties made from the scene schema (nebula_rt.filters.properties) ---------------------
INT32 = (-2**31, 2**31 - 1)
#: integers past int32 (photon counts, seeds) travel as doubles: exact up to 2^53, which the
#: scene's ranges keep to, and a pvpython ``Photons=1e5`` is taken as the integer it is
DOUBLE_EXACT = 2**53
#: A number whose range spans more than this gets a text field, not a slider: ParaView draws a
#: slider for every one-number range with both ends, and over 2^31 or 2^53 (Photons, Seed,
#: Batch Size, Max Scatterings) its knob sits at the far left for every useful value. The
#: panel's domain then holds the lower end only; the scene's validation keeps the upper one
#: (a value past it is refused at Apply, naming the property and the range).
SLIDER_SPAN = 1e6


def panel_range(p, elements: int):
    """The (min, max) a panel's range domain holds for declaration ``p`` (None: no such end)."""
    lo, hi = p.lo, p.hi
    if elements == 1 and lo is not None and hi is not None and hi - lo > SLIDER_SPAN:
        hi = None
    return lo, hi


def _values_text(v):
    vals = v if isinstance(v, (tuple, list)) else (v,)
    return " ".join(repr(float(x)) if isinstance(x, float) else str(int(x)) for x in vals)


def _key_text(key):
    """How a tooltip names the parameter: a scene key, or the sky image's own (not in scene files)."""
    return ("key " if key.startswith("sky.") else "scene key ") + key


def _tooltip(prop, p):
    from nebula_rt.scene.schema import range_text

    extra = [x for x in (p.unit, range_text(p), _key_text(prop.key)) if x]
    return escape(" ".join(f"{p.doc} ({'; '.join(extra)}).".split()))


def bound_property(prop, default=None):
    """The ServerManager XML of one :class:`nebula_rt.filters.properties.Property`: its
    element type, domain, label, tooltip, visibility and the decorator that enables it, all
    from the scene schema. ``default`` replaces a schema default of None (a panel needs a
    value: e.g. Albedo before it overrides anything)."""
    from nebula_rt.scene.schema import label

    p = prop.param
    d = prop.default if default is None else default
    attrs = 'name=%s label=%s command=%s' % (quoteattr(prop.name), quoteattr(label(prop.key, p)),
                                            quoteattr("Set" + prop.name))
    if p.advanced:
        attrs += ' panel_visibility="advanced"'
    n = prop.elements
    flag, enabled_by = "", prop.enabled_by
    if prop.widget == "auto":
        # "auto" or a number: the check box first, then the number it disables
        flag = _auto_flag(prop, p, d == "auto")
        d, enabled_by = prop.number, (prop.flag, 0)
    if prop.widget == "enum":
        texts = [p.choice_labels[p.choices.index(c)] if p.choice_labels else c for c in prop.choices]
        items = "".join('<Entry value="%d" text=%s/>' % (i, quoteattr(t)) for i, t in enumerate(texts))
        tag, dflt = "IntVectorProperty", str(prop.choices.index(d))
        domain = '<EnumerationDomain name="enum">%s</EnumerationDomain>' % items
    elif prop.widget == "bool":
        tag, dflt, domain = "IntVectorProperty", str(int(bool(d))), '<BooleanDomain name="bool"/>'
    elif prop.widget == "file":  # a file name: the panel's text box with a file browser
        tag, dflt, domain = "StringVectorProperty", quoteattr(d)[1:-1], '<FileListDomain name="files"/>'
    elif prop.choices:
        items = "".join("<String value=%s/>" % quoteattr(c) for c in prop.choices)
        tag, dflt = "StringVectorProperty", quoteattr(d)[1:-1]
        domain = '<StringListDomain name="list">%s</StringListDomain>' % items
    elif isinstance(d, str):
        tag, dflt, domain = "StringVectorProperty", quoteattr(d)[1:-1], ""
    else:
        integer = p.type.startswith("int") or p.type.endswith("int")
        if integer and p.lo is not None and p.hi is not None and INT32[0] <= p.lo and p.hi <= INT32[1]:
            tag, dom = "IntVectorProperty", "IntRangeDomain"
        else:
            tag, dom = "DoubleVectorProperty", "DoubleRangeDomain"
            if integer and (p.hi is None or p.hi > DOUBLE_EXACT or p.lo is None or p.lo < -DOUBLE_EXACT):
                # the scene must declare what the panel holds (nebula_rt.scene.MAX_SEED)
                raise ValueError(f"{prop.key}: an integer range past 2**53 cannot be a panel property exactly")
        lo, hi = panel_range(p, n)
        bounds = "".join(' %s="%s"' % (k, _values_text(v)) for k, v in (("min", lo), ("max", hi)) if v is not None)
        if n > 1 and bounds:  # every element in the same range
            bounds = "".join(' %s="%s"' % (k, " ".join([_values_text(v)] * n)) for k, v in (("min", lo), ("max", hi))
                             if v is not None)
        domain = '<%s name="range"%s/>' % (dom, bounds) if bounds else ""
        dflt = _values_text(d)
    hints = ""
    for mode, rule in (("enabled_state", enabled_by), ("visibility", prop.shown_by)):
        if rule:
            hints += ('<PropertyWidgetDecorator type="GenericDecorator" mode="%s" property=%s value=%s />'
                      % (mode, quoteattr(rule[0]), quoteattr(str(rule[1]))))
    if hints:
        hints = "<Hints>%s</Hints>" % hints
    chosen = _chosen_property(prop, p) if prop.widget == "auto" else ""
    return flag + ('<%s %s number_of_elements="%d" default_values="%s">%s<Documentation>%s</Documentation>%s</%s>'
                   % (tag, attrs, n, dflt, domain, _tooltip(prop, p), hints, tag)) + chosen


def _words(name: str) -> str:
    """A property's name as a label: ``AutoExposure`` -> ``Auto Exposure``."""
    return re.sub(r"(?<!^)(?=[A-Z])", " ", name)


def _chosen_property(prop, p):
    """An information property after an "auto or number" property: the value the last
    execution used (``NebulaAlgorithm.chosen``), what "auto" chose, for scripts (pvpython's
    ``GetPropertyValue``; ParaView 5.11's panel shows no information property)."""
    from nebula_rt.scene.schema import label

    vis = ' panel_visibility="advanced"' if p.advanced else ""
    tip = escape(f"The {label(prop.key, p)} the last Apply used: chosen from the data while {prop.flag} is on, "
                 "else the number above (read only).")
    return ('<DoubleVectorProperty name=%s label=%s command=%s information_only="1" number_of_elements="1" '
            'default_values="0"%s><SimpleDoubleInformationHelper/><Documentation>%s</Documentation>'
            '</DoubleVectorProperty>'
            % (quoteattr(prop.name + "Chosen"), quoteattr(_words(prop.name) + " Chosen"),
               quoteattr("Get" + prop.name + "Chosen"), vis, tip))


def _auto_flag(prop, p, on):
    """The check box of an "auto or number" property (``Auto Exposure``: its label from its
    name), shown with the same visibility as the number."""
    from nebula_rt.scene.schema import label

    text = _words(prop.flag)
    tip = escape(" ".join((f"On: {label(prop.key, p)} is chosen from the data ({_key_text(prop.key)} = "
                           f"'auto'); off: the number below. {p.doc}.").split()))
    vis = ' panel_visibility="advanced"' if p.advanced else ""
    return ('<IntVectorProperty name=%s label=%s command=%s number_of_elements="1" default_values="%d"%s>'
            '<BooleanDomain name="bool"/><Documentation>%s</Documentation></IntVectorProperty>'
            % (quoteattr(prop.flag), quoteattr(text), quoteattr("Set" + prop.flag), int(on), vis, tip))


def bound_properties(props, defaults=None, extra=None):
    """The XML of a proxy's schema-bound properties, in the panel's order, with ``extra``
    (name -> XML of a property of the filter's own) placed before the bound property of the
    same name prefixed by ``<``: ``{"<Albedo": override_optics_xml}``."""
    defaults, extra = dict(defaults or {}), dict(extra or {})
    out = []
    for prop in props:
        if "<" + prop.name in extra:
            out.append(extra.pop("<" + prop.name))
        out.append(bound_property(prop, defaults.get(prop.key)))
    out.extend(extra.values())
    return "\n".join(out)
