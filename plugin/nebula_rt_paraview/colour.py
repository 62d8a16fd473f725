"""Proxy ``NebulaColour`` (Filters > NebulaRT > Nebula Colour).

White Point and Opacity Scale are made from the VTK filter's schema-bound properties
(:data:`nebula_rt.filters.colour.COLOUR_PROPERTIES`); Auto Exposure and Exposure, which
together are the scene's ``colour.exposure`` ("auto" or a number), are declared here.
"""

from paraview.util.vtkAlgorithm import smdomain, smhint, smproperty, smproxy

from nebula_rt.filters import colour as _base

from . import _xml

EXPOSURE = """
<IntVectorProperty name="AutoExposure" label="Auto Exposure" command="SetAutoExposure"
    number_of_elements="1" default_values="1">
  <BooleanDomain name="bool"/>
  <Documentation>Choose the exposure from the scattered light (else use Exposure; scene key
    colour.exposure = "auto").</Documentation>
</IntVectorProperty>
<DoubleVectorProperty name="Exposure" label="Exposure" command="SetExposure" number_of_elements="1"
    default_values="1.0">
  <DoubleRangeDomain name="range" min="0.01" max="100.0"/>
  <Documentation>Multiplier of the linear colour before the sRGB curve (with Auto Exposure off;
    scene key colour.exposure).</Documentation>
  <Hints><PropertyWidgetDecorator type="GenericDecorator" mode="enabled_state" property="AutoExposure"
    value="0" /></Hints>
</DoubleVectorProperty>"""

PANEL = EXPOSURE + "\n" + _xml.bound_properties(_base.COLOUR_PROPERTIES)


@smproxy.filter(name="NebulaColour", label="Nebula Colour", support_reload=False)
@smhint.xml(_xml.MENU)
@smhint.xml(_xml.VOLUME)
@smproperty.xml(PANEL)
@smproperty.input(name="Input", port_index=0)
@smdomain.datatype(dataTypes=["vtkImageData"], composite_data_supported=False)
@_xml.doc("The output of Nebula Light Field.")
class NebulaColour(_base.NebulaColour):
    """sRGB colour and opacity of a Nebula Light Field output: adds ``rgba`` (uint8 x 4, shown
    directly with Map Scalars off; see nebula_rt_paraview.view.show_rgba_volume) and
    ``rgb_linear``. Changing these properties never re-traces photons."""
