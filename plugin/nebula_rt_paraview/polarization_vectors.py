"""Proxy ``NebulaPolarizationVectors`` (Filters > NebulaRT > Nebula Polarization Vectors).

Its properties are made from the VTK filter's (:data:`nebula_rt.filters.polarization_vectors.
POLARIZATION_VECTOR_PROPERTIES`), bound to the sky image's declarations (``sky.vector_*``). Its
output, a line segment per block along the polarization angle (headless glyphs), shows white in
the sky image's view (nebula_rt_paraview.display): the pattern of a polarized nebula about its
star.
"""

from paraview.util.vtkAlgorithm import smdomain, smhint, smproperty, smproxy

from nebula_rt.filters import polarization_vectors as _base

from . import _xml

PANEL = _xml.bound_properties(_base.POLARIZATION_VECTOR_PROPERTIES)


@smproxy.filter(name="NebulaPolarizationVectors", label="Nebula Polarization Vectors", support_reload=False)
@smhint.xml(_xml.MENU)
@_xml.proxy_doc(_base.NebulaPolarizationVectors)
@smhint.xml(_xml.POLARIZATION_VECTORS_DISPLAY)
@smproperty.xml(PANEL)
@smproperty.input(name="Input", port_index=0)
@smdomain.datatype(dataTypes=["vtkImageData"], composite_data_supported=False)
@_xml.doc("The output of Nebula Sky Image with Method peel-off, of a scene with Polarization.")
class NebulaPolarizationVectors(_base.NebulaPolarizationVectors):
    """Polarization vectors of a polarized sky image, one per block of pixels."""
