"""Proxy ``NebulaColour`` (Filters > NebulaRT > Nebula Colour)."""

from paraview.util.vtkAlgorithm import smdomain, smhint, smproperty, smproxy

from nebula_rt.filters import colour as _base

from . import _xml


@smproxy.filter(name="NebulaColour", label="Nebula Colour", support_reload=False)
@smhint.xml(_xml.MENU)
@smhint.xml(_xml.VOLUME)
@smproperty.input(name="Input", port_index=0)
@smdomain.datatype(dataTypes=["vtkImageData"], composite_data_supported=False)
@_xml.doc("The output of Nebula Light Field.")
class NebulaColour(_base.NebulaColour):
    """sRGB colour and opacity of a Nebula Light Field output: adds ``rgba`` (uint8 x 4, shown
    directly with Map Scalars off; see nebula_rt_paraview.view.show_rgba_volume) and
    ``rgb_linear``. Changing these properties never re-traces photons."""

    @smproperty.intvector(name="AutoExposure", label="Auto Exposure", default_values=1)
    @_xml.boolean()
    @_xml.doc("Choose the exposure from the scattered light (else use Exposure).")
    def SetAutoExposure(self, flag):
        return super().SetAutoExposure(flag)

    @smproperty.doublevector(name="Exposure", default_values=1.0)
    @smdomain.doublerange(min=0.01, max=100.0)
    @_xml.shown_when("AutoExposure", 0, mode="enabled_state")
    @_xml.doc("Multiplier of the linear colour before the sRGB curve (with Auto Exposure off).")
    def SetExposure(self, v):
        return super().SetExposure(v)

    @smproperty.doublevector(name="OpacityScale", label="Opacity Scale", default_values=1.0)
    @smdomain.doublerange(min=0.01, max=10.0)
    @_xml.doc("Multiplies each voxel's optical depth in the alpha channel.")
    def SetOpacityScale(self, v):
        return super().SetOpacityScale(v)

    @smproperty.intvector(name="WhitePoint", label="White Point", default_values=0)
    @_xml.enumeration("D65", "E", "star")
    @_xml.doc("White balance: D65 (daylight), E (equal energy) or star (the star's own colour is white).")
    def SetWhitePoint(self, wp):
        return super().SetWhitePoint(wp)
