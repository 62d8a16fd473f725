"""Proxy ``NebulaSkyImage`` (Filters > NebulaRT > Nebula Sky Image).

Its properties are made from the VTK filter's properties (:data:`nebula_rt.filters.sky_image.SKY_IMAGE_PROPERTIES`),
bound to the sky image's declarations (:mod:`nebula_rt.scene.sky_schema`: the camera and the exposure)
and to the scene's (the tone curve, the observer), with Units, the filter's own, before the
observer it enables: one class-level property XML in the panel's order; the setters are the
VTK filter's own, inherited.
"""

from xml.sax.saxutils import quoteattr

from paraview.util.vtkAlgorithm import smdomain, smhint, smproperty, smproxy

from nebula_rt.filters import sky_image as _base
from nebula_rt.scene import G_OBSERVER

from . import _xml
from .remote_abort import ADDRESS_PROPERTY, Addressed

UNITS = """
<IntVectorProperty name="Units" label="Units" command="SetUnits" number_of_elements="1" default_values="0">
  <EnumerationDomain name="enum">%s</EnumerationDomain>
  <Documentation>box units: the image in the light field's units; MJy/sr: also calibrated, sb_&lt;band&gt;
    (MJy/sr) and mag_&lt;passband&gt; (AB mag/arcsec^2) with a celestial WCS (File &gt; Save Data as
    .fits writes it). Needs the stars in L_sun (Nebula Light Field's Luminosity Unit) and a
    Distance (or the scene's [observer] table).</Documentation>
</IntVectorProperty>""" % "".join('<Entry value="%d" text=%s/>' % (i, quoteattr(u)) for i, u in enumerate(_base.SKY_UNITS))

PANEL = _xml.panel(_base.SKY_IMAGE_PROPERTIES, defaults=_base.SKY_PANEL_DEFAULTS, extra={"<Distance": UNITS},
                   own_groups={"Units": G_OBSERVER})


@smproxy.filter(name="NebulaSkyImage", label="Nebula Sky Image", support_reload=False)
@smhint.xml(_xml.MENU)
@_xml.proxy_doc(_base.NebulaSkyImage)
@smhint.xml(_xml.SKY_IMAGE_DISPLAY)
@smproperty.xml(PANEL)
@smproperty.xml(ADDRESS_PROPERTY)
@smproperty.input(name="Input", port_index=0)
@smdomain.datatype(dataTypes=["vtkImageData"], composite_data_supported=False)
@_xml.doc("The output of Nebula Light Field (it must carry its density array).")
class NebulaSkyImage(Addressed, _base.NebulaSkyImage):
    """What a telescope far away sees along View Direction: a 2D image with ``I_<band>``,
    ``scattered_<band>`` (float) and ``rgb`` (uint8 x 3; shown directly with Map Scalars off; see
    nebula_rt_paraview.view.show_sky_image)."""
