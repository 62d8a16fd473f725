"""NebulaRT ParaView plugin: the only entry file of this folder.

Load it with Tools > Manage Plugins > Load New (this file), or put this folder on
PV_PLUGIN_PATH (ParaView then loads every .py/.xml in it, which is why nothing else lives at
this level). It adds the NebulaRT menu (Filters > NebulaRT and Sources > NebulaRT) with

- Nebula Dust Density (source)        proxy name ``NebulaDustDensity``
- Nebula Light Field (filter)         proxy name ``NebulaLightField``
- Nebula Colour (filter)              proxy name ``NebulaColour``
- Nebula Sky Image (filter)           proxy name ``NebulaSkyImage``
- Nebula Polarization Vectors (filter) proxy name ``NebulaPolarizationVectors`` (a polarized
  sky image's vectors, drawn as glyphs over it)
- Nebula Sky View (view)              proxy name ``NebulaSkyView`` (where sky images open)
- a writer of calibrated sky images   proxy name ``NebulaSkyFitsWriter`` (File > Save Data, .fits)
- a reader of fit results             proxy name ``NebulaFitResultReader`` (File > Open, the
  ``nebula-rt fit --json`` file)

Modelled on ParaView's ``Examples/Plugins/ComplexPythonArchitecture``: this file only makes the
package ``nebula_rt_paraview`` (next to it) importable and imports from it. The package's first
import (``nebula_rt_paraview._environment``) makes NebulaRT itself importable or says what to
do (docs/paraview.md); its proxies are thin decorated subclasses of the VTK algorithms in
``nebula_rt.filters``; ``nebula_rt_paraview.defaults`` installs what Apply shows.
"""

import os
import sys

# This folder on the Python path, so the proxies' package imports (also on a server process,
# which imports the proxies' classes by their qualified names).
_HERE = os.path.dirname(os.path.abspath(__file__))
if _HERE not in sys.path:
    sys.path.append(_HERE)

paraview_plugin_name = "NebulaRT"

# the proxies (the plugin loader exports every decorated class found in this module, and
# NebulaSkyView's view definition: every object with a _pvsm_proxy_xml)
from nebula_rt_paraview import (  # noqa: E402,F401
    NebulaColour,
    NebulaDustDensity,
    NebulaFitResultReader,
    NebulaLightField,
    NebulaPolarizationVectors,
    NebulaSkyFitsWriter,
    NebulaSkyImage,
    NebulaSkyView,
)
from nebula_rt_paraview import defaults  # noqa: E402,F401  (what Apply shows)
from nebula_rt_paraview import renamed  # noqa: E402,F401  (former names in pvpython scripts)
from nebula_rt import __version__ as paraview_plugin_version  # noqa: E402,F401  (pyproject.toml)
