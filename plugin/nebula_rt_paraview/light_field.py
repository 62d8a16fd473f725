"""Proxy ``NebulaLightField`` (Filters > NebulaRT > Nebula Light Field).

Its properties are made from the VTK filter's schema-bound properties
(:data:`nebula_rt.filters.light_field.LIGHT_FIELD_PROPERTIES`): one class-level property XML in
the panel's order (5.11 would sort properties declared on methods by the methods' names); the
setters are the VTK filter's own, inherited.
"""

from paraview.util.vtkAlgorithm import smdomain, smhint, smproperty, smproxy

from nebula_rt.filters import light_field as _base
from nebula_rt.filters.base import default_reference_band, default_star_row
from nebula_rt.scene import G_DUST, G_OPTICS, G_STARS, G_UNITS
from nebula_rt.scene.units import SPECTRAL_CALIBRATIONS

from . import _xml
from .remote_abort import ADDRESS_PROPERTY, Addressed

_REF = default_reference_band()

OVERRIDE_OPTICS = """
<IntVectorProperty name="OverrideOptics" label="Override Optics" command="SetOverrideOptics"
    number_of_elements="1" default_values="0">
  <BooleanDomain name="bool"/>
  <Documentation>Use Albedo and G in every band (else each band's own values, as a scene file
    without bands.albedo and bands.g).</Documentation>
</IntVectorProperty>"""

LUMINOSITY_UNIT = """
<IntVectorProperty name="LuminosityUnit" label="Luminosity Unit" command="SetLuminosityUnit"
    number_of_elements="1" default_values="0" panel_visibility="advanced">
  <EnumerationDomain name="enum"><Entry value="0" text="scene units"/><Entry value="1" text="L_sun"/></EnumerationDomain>
  <Documentation>What the Stars' luminosity column is: scene units, or the bolometric luminosity
    in L_sun (scene key stars.luminosity_lsun: the traced luminosity is then the blackbody's part
    inside the bands, and Nebula Sky Image can calibrate its image; each star needs its
    temperature).</Documentation>
</IntVectorProperty>"""

SPECTRAL_TYPES = """
<StringVectorProperty name="SpectralTypes" label="Spectral Types" command="SetSpectralTypes"
    number_of_elements="1" default_values="" panel_visibility="advanced">
  <Documentation>MK spectral types of the stars, in the Stars' order, separated by ";" (such as
    "B2V; A0 III"; an empty entry keeps that star's temperature): each sets its star's
    temperature in place of the Stars' column (scene key stars.spectral_type, by Spectral
    Calibration).</Documentation>
</StringVectorProperty>
<StringVectorProperty name="SpectralCalibration" label="Spectral Calibration" command="SetSpectralCalibration"
    number_of_elements="1" default_values="auto" panel_visibility="advanced">
  %s
  <Documentation>How Spectral Types set the temperatures (scene key
    stars.spectral_calibration): auto (Pecaut and Mamajek 2013 for a dwarf from O3V to M9.5V, de
    Jager and Nieuwenhuijzen 1987 otherwise), pecaut-mamajek-2013 (dwarfs only) or de-jager-1987
    (every class).</Documentation>
</StringVectorProperty>""" % ('<StringListDomain name="list">%s</StringListDomain>'
                              % "".join('<String value="%s"/>' % c for c in SPECTRAL_CALIBRATIONS))

RESOLUTION = """
<IntVectorProperty name="Resolution" label="Resolution" command="SetResolution"
    number_of_elements="3" default_values="%d %d %d">
  <IntRangeDomain name="range" min="2 2 2"/>
  <Documentation>For an adaptive input (a hyper tree grid, an AMR hierarchy or particles): voxels per axis
    of the light field's image over the input's bounds (each voxel the exact-overlap average of
    the leaves it covers). An image input keeps its own grid.</Documentation>
</IntVectorProperty>""" % _base.NebulaLightField.DEFAULT_RESOLUTION

PANEL = _xml.panel(
    _base.LIGHT_FIELD_PROPERTIES,
    defaults={"bands.albedo": _REF.albedo, "bands.g": _REF.g},
    head=[_xml.DENSITY_ARRAY, RESOLUTION],
    extra={"<Albedo": OVERRIDE_OPTICS,
           "<Estimator": _xml.STARS_FROM_INPUT + _xml.stars_property(default_star_row(), ("StarsFromInput", 0)),
           "<BoxLength": LUMINOSITY_UNIT + SPECTRAL_TYPES},
    # the filter's own properties: the density array, the optics switch, the stars and their units
    own_groups={"DensityArray": G_DUST, "OverrideOptics": G_OPTICS, "StarsFromInput": G_STARS, "Stars": G_STARS,
                "LuminosityUnit": G_UNITS, "SpectralTypes": G_UNITS, "SpectralCalibration": G_UNITS,
                "Resolution": G_DUST})


@smproxy.filter(name="NebulaLightField", label="Nebula Light Field", support_reload=False)
@smhint.xml(_xml.MENU)
@_xml.proxy_doc(_base.NebulaLightField)
@smhint.xml(_xml.LIGHT_FIELD_DISPLAY)
@smproperty.xml(_xml.LIGHT_FIELD_PORTS)
@smproperty.xml(PANEL)
@smproperty.xml(ADDRESS_PROPERTY)
@smproperty.input(name="Input", port_index=0)
@smdomain.datatype(dataTypes=list(_base.NebulaLightField.INPUT_TYPES), composite_data_supported=True)
@_xml.doc("The dust density: a vtkImageData (e.g. Nebula Dust Density, or a .vti file), an adaptive "
          "vtkHyperTreeGrid (.htg) or vtkOverlappingAMR (.vthb) traced leaf by leaf, or SPH particles (a "
          "vtkPolyData with mass and smoothing-length point arrays) deposited on an octree.")
@_xml.input_with_array_domain()
class NebulaLightField(Addressed, _base.NebulaLightField):
    """Traces photon packets from the stars through the input's dust density; adds per band
    ``J_<band>``, ``emissivity_<band>``, ``rel_error_<band>`` and the run's field data."""

    # -- the repeatable Stars property: RemoveAllStars, then AddStar per star ----------------
    def AddStar(self, *row):  # one row of nebula_rt.filters.base.STAR_COLUMNS
        self.SetStars(list(self._stars) + list(row))

    def RemoveAllStars(self):
        self.SetStars([])
