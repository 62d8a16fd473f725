"""Proxy ``NebulaColour`` (Filters > NebulaRT > Nebula Colour).

Its properties are made from the VTK filter's schema-bound properties
(:data:`nebula_rt.filters.colour.COLOUR_PROPERTIES`): Auto Exposure and Exposure (the scene's
``colour.exposure``, "auto" or a number), White Point, Auto Opacity and Opacity Scale
(``colour.opacity_scale``, "auto" or a number), Stretch and Asinh Q (the pictures' tone curve).
"""

from paraview.util.vtkAlgorithm import smdomain, smhint, smproperty, smproxy  # noqa: F401

from nebula_rt.filters import colour as _base

from . import _xml

PANEL = _xml.bound_properties(_base.COLOUR_PROPERTIES)


@smproxy.filter(name="NebulaColour", label="Nebula Colour", support_reload=False)
@smhint.xml(_xml.MENU)
@_xml.proxy_doc(_base.NebulaColour)
@smhint.xml(_xml.VOLUME)
@smproperty.xml(PANEL)
@smproperty.input(name="Input", port_index=0)
@smdomain.datatype(dataTypes=["vtkImageData"], composite_data_supported=False)
@_xml.doc("The output of Nebula Light Field.")
class NebulaColour(_base.NebulaColour):
    """sRGB colour and opacity of a Nebula Light Field output: adds ``rgba`` (uint8 x 4, shown
    directly with Map Scalars off; see nebula_rt_paraview.view.show_rgba_volume) and
    ``rgb_linear``. Changing these properties never re-traces photons."""
