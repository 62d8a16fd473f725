"""Proxy ``NebulaSkyImage`` (Filters > NebulaRT > Nebula Sky Image).

Its properties are made from the VTK filter's properties, bound to the sky image's declarations
(:data:`nebula_rt.filters.sky_image.SKY_IMAGE_PROPERTIES`, :mod:`nebula_rt.sky_schema`): one
class-level property XML in the panel's order; the setters are the VTK filter's own, inherited.
"""

from paraview.util.vtkAlgorithm import smdomain, smhint, smproperty, smproxy

from nebula_rt.filters import sky_image as _base

from . import _xml

PANEL = "\n".join([
    _xml.bound_properties(_base.SKY_IMAGE_PROPERTIES),
    _xml.property_groups(
        ("Camera", ["ViewDirection", "ViewUp", "ImageSize", "Extent"]),
        ("Picture", ["IncludeStars", "AutoExposure", "Exposure"]),
    ),
])


@smproxy.filter(name="NebulaSkyImage", label="Nebula Sky Image", support_reload=False)
@smhint.xml(_xml.MENU)
@_xml.proxy_doc(_base.NebulaSkyImage)
@smhint.xml(_xml.SKY_IMAGE_DISPLAY)
@smproperty.xml(PANEL)
@smproperty.input(name="Input", port_index=0)
@smdomain.datatype(dataTypes=["vtkImageData"], composite_data_supported=False)
@_xml.doc("The output of Nebula Light Field (it must carry its density array).")
class NebulaSkyImage(_base.NebulaSkyImage):
    """What a telescope far away sees along View Direction: a 2D image with ``I_<band>``,
    ``scattered_<band>`` (float) and ``rgb`` (uint8 x 3; shown directly with Map Scalars off; see
    nebula_rt_paraview.view.show_sky_image)."""
