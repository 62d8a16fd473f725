"""Proxy ``NebulaSkyImage`` (Filters > NebulaRT > Nebula Sky Image)."""

from paraview.util.vtkAlgorithm import smdomain, smhint, smproperty, smproxy

from nebula_rt.filters import sky_image as _base

from . import _xml


UNITS = """
<IntVectorProperty name="Units" label="Units" command="SetUnits" number_of_elements="1" default_values="0">
  <EnumerationDomain name="enum"><Entry value="0" text="box units"/><Entry value="1" text="MJy/sr"/></EnumerationDomain>
  <Documentation>box units: the image in the light field's units; MJy/sr: also calibrated, sb_&lt;band&gt;
    (MJy/sr) and mag_&lt;passband&gt; (AB mag/arcsec^2) with a celestial WCS (File &gt; Save Data as
    .fits writes it). Needs the stars in L_sun (Nebula Light Field's Luminosity Unit) and a
    Distance (or the scene's [observer] table).</Documentation>
</IntVectorProperty>"""

PANEL = "\n".join([
    _xml.bound_properties(_base.SKY_PICTURE_PROPERTIES),
    UNITS,
    _xml.bound_properties(_base.SKY_OBSERVER_PROPERTIES, defaults={"observer.distance": ""}),
])


@smproxy.filter(name="NebulaSkyImage", label="Nebula Sky Image", support_reload=False)
@smhint.xml(_xml.MENU)
@smproperty.xml(PANEL)
@smhint.xml(_xml.SKY_IMAGE_DISPLAY)
@smproperty.input(name="Input", port_index=0)
@smdomain.datatype(dataTypes=["vtkImageData"], composite_data_supported=False)
@_xml.doc("The output of Nebula Light Field (it must carry its density array).")
class NebulaSkyImage(_base.NebulaSkyImage):
    """What a telescope far away sees along View Direction: a 2D image with ``I_<band>``,
    ``scattered_<band>`` (float) and ``rgb`` (uint8 x 3; shown directly with Map Scalars off; see
    nebula_rt_paraview.view.show_sky_image)."""

    @smproperty.intvector(name="AutoExposure", label="Auto Exposure", default_values=1)
    @_xml.boolean()
    @_xml.doc("Choose the exposure from the scattered light (stars saturate); else use Exposure.")
    def SetAutoExposure(self, flag):
        return super().SetAutoExposure(flag)

    @smproperty.doublevector(name="Exposure", default_values=1.0)
    @smdomain.doublerange(min=0.01, max=100.0)
    @_xml.shown_when("AutoExposure", 0, mode="enabled_state")
    @_xml.doc("Multiplier of the linear colour before the sRGB curve (with Auto Exposure off).")
    def SetExposure(self, v):
        return super().SetExposure(v)

    @smproperty.doublevector(name="Extent", default_values=0.0)
    @smdomain.doublerange(min=0.0, max=2.0)
    @_xml.doc("Field of view (box units); 0 fits the whole box whatever the direction.")
    def SetExtent(self, e):
        return super().SetExtent(e)

    @smproperty.intvector(name="ImageSize", label="Image Size", default_values=[256, 256])
    @smdomain.intrange(min=1, max=4096)
    @_xml.doc("Width and height of the image in pixels.")
    def SetImageSize(self, w, h):
        return super().SetImageSize(w, h)

    @smproperty.intvector(name="IncludeStars", label="Include Stars", default_values=1)
    @_xml.boolean()
    @_xml.doc("Add each star's attenuated direct light to the pixel it falls in.")
    def SetIncludeStars(self, flag):
        return super().SetIncludeStars(flag)

    @smproperty.doublevector(name="ViewDirection", label="View Direction", default_values=[0.0, 0.0, -1.0])
    @_xml.doc("Direction the telescope looks in (from the observer into the box).")
    def SetViewDirection(self, x, y, z):
        return super().SetViewDirection(x, y, z)

    @smproperty.doublevector(name="ViewUp", label="View Up", default_values=[0.0, 1.0, 0.0])
    @_xml.doc("Up direction of the image (made perpendicular to View Direction).")
    def SetViewUp(self, x, y, z):
        return super().SetViewUp(x, y, z)

    @smproperty.xml(_xml.property_groups(
        ("Camera", ["ViewDirection", "ViewUp", "ImageSize", "Extent"]),
        ("Picture", ["IncludeStars", "AutoExposure", "Exposure", "Stretch", "AsinhQ"]),
        ("Observer", ["Units", "Distance", "RA", "Dec", "PositionAngle", "PSFFWHM"]),
    ))
    def zz_property_groups(self):
        """Carries the PropertyGroups (its name sorts last)."""
