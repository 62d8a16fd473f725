"""ParaView proxies of NebulaRT (``plugin/NebulaRT.py`` is the plugin's entry file).

Each proxy is a thin ``paraview.util.vtkAlgorithm``-decorated subclass of the VTK algorithm of
the same name in ``nebula_rt.filters``: the decorators describe the properties and their
widgets; the setters are the base class's (they store the value and call ``Modified()``;
validation happens when the pipeline executes).

Proxy names (``NebulaDustDensity``, ``NebulaLightField``, ``NebulaColour``, ``NebulaSkyImage``)
and property names are API: state files (.pvsm) store them.

``nebula_rt_paraview.view`` holds pvpython helpers (showing ``rgba`` as a volume, loading
state files safely); it imports ``paraview.simple`` and is not imported here.
``nebula_rt_paraview.display`` sets up the default displays (installed on import of
``nebula_rt_paraview.defaults``, which the plugin's entry file imports);
``nebula_rt_paraview.views`` defines the view ``NebulaSkyView``.
"""

# NebulaRT itself importable first (or an ImportError saying what to do)
from . import _environment  # noqa: F401  (isort: skip)

# Import ParaView proxies from the Python files; keep helpers internal.
from .colour import NebulaColour
from .dust_density import NebulaDustDensity
from .fit_result import NebulaFitResultReader
from .light_field import NebulaLightField
from .polarization_vectors import NebulaPolarizationVectors
from .sky_fits_writer import NebulaSkyFitsWriter
from .sky_image import NebulaSkyImage
from .views import NebulaSkyView

#: proxy names (group "sources" for the dust density, "filters" for the others)
PROXY_NAMES = ("NebulaDustDensity", "NebulaLightField", "NebulaColour", "NebulaSkyImage")

__all__ = ["NebulaColour", "NebulaDustDensity", "NebulaFitResultReader", "NebulaLightField",
           "NebulaPolarizationVectors", "NebulaSkyFitsWriter", "NebulaSkyImage", "NebulaSkyView", "PROXY_NAMES"]
