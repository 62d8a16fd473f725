"""Small XML helpers shared by the proxy definitions (ServerManager XML snippets).

Only decorators of ParaView 5.11's ``paraview.util.vtkAlgorithm`` are used (``smdomain.xml``,
``smhint.xml``, ``smproperty.xml``): they exist unchanged up to 6.x.
"""

from xml.sax.saxutils import escape, quoteattr

from paraview.util.vtkAlgorithm import smdomain, smhint

#: proxy hint: Filters > NebulaRT / Sources > NebulaRT
MENU = '<ShowInMenu category="NebulaRT" />'
#: proxy hint: show the output as a volume in render views
VOLUME = '<RepresentationType view="RenderView" type="Volume" />'
#: proxy hints of Nebula Light Field: port 1 (the stars) as points, the rest as a volume (the
#: hints are read in order, port-specific first); nebula_rt_paraview.display sets the colours
LIGHT_FIELD_DISPLAY = '<RepresentationType view="RenderView" type="Points" port="1" />' + VOLUME
#: the names of Nebula Light Field's output ports (the pipeline browser shows them)
LIGHT_FIELD_PORTS = '<OutputPort name="Light Field" index="0" /><OutputPort name="Stars" index="1" />'
#: proxy hints of Nebula Sky Image: its own 2D view (nebula_rt_paraview.views), as a slice
SKY_IMAGE_DISPLAY = ('<View type="NebulaSkyView" />'
                     '<RepresentationType view="NebulaSkyView" type="Slice" />'
                     '<RepresentationType view="RenderView" type="Slice" />'
                     '<PipelineIcon name="GEOMETRY" />')  # (the icon would be the view's, which has none)


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


def stars_property(default):
    """The repeatable ``Stars`` property: 6 numbers per star, ``AddStar`` once per star after
    ``RemoveAllStars``."""
    values = " ".join(repr(float(v)) for v in default)
    return """
<DoubleVectorProperty name="Stars" label="Stars" command="AddStar" clean_command="RemoveAllStars"
    repeat_command="1" number_of_elements_per_command="6" use_index="0"
    number_of_elements="%d" default_values="%s">
  <Documentation>One row per star: x, y, z (box units, [0, 1]), luminosity, temperature (K; 0 =
    flat spectrum), bump radius (box units; the cubic dust bump around the star, used by Nebula
    Dust Density only).</Documentation>
</DoubleVectorProperty>""" % (len(default), values)


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
