"""Proxy ``NebulaDustDensity`` (Sources > NebulaRT > Nebula Dust Density).

Its properties are made from the VTK source's schema-bound properties
(:data:`nebula_rt.filters.dust_density.DUST_DENSITY_PROPERTIES`), in the panel's order; the
setters are the VTK source's own, inherited.
"""

from paraview.util.vtkAlgorithm import smhint, smproperty, smproxy

from nebula_rt.filters import dust_density as _base
from nebula_rt.filters.base import default_star_row
from nebula_rt.scene import G_STARS

from . import _xml
from .remote_abort import ADDRESS_PROPERTY, Addressed

PANEL = _xml.panel(_base.DUST_DENSITY_PROPERTIES, extra={"<Backend": _xml.stars_property(default_star_row())},
                   own_groups={"Stars": G_STARS})


@smproxy.source(name="NebulaDustDensity", label="Nebula Dust Density", support_reload=False)
@smhint.xml(_xml.MENU)
@_xml.proxy_doc(_base.NebulaDustDensity)
@smhint.xml(_xml.VOLUME)
@smproperty.xml(PANEL)
@smproperty.xml(ADDRESS_PROPERTY)
class NebulaDustDensity(Addressed, _base.NebulaDustDensity):
    """Dust density on an nx x ny x nz grid spanning the box [0, 1]^3 (thesis Eq. 3.2/3.3):
    point array ``density`` on the voxel centres."""

    # -- the repeatable Stars property: RemoveAllStars, then AddStar per star ----------------
    def AddStar(self, *row):  # one row of nebula_rt.filters.base.STAR_COLUMNS
        self.SetStars(list(self._stars) + list(row))

    def RemoveAllStars(self):
        self.SetStars([])
