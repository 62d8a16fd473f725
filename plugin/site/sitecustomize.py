"""Start-up fixes for NebulaRT inside ParaView (pvpython, pvbatch and the GUI).

Put this folder on PYTHONPATH (scripts/pv-env.sh does). It is not a plugin: only the entry
file ``plugin/NebulaRT.py`` belongs on PV_PLUGIN_PATH, since ParaView loads every .py there.

1. ParaView 5.11's Python-plugin loader calls ``inspect.getargspec``, which Python 3.11
   removed; alias it to ``getfullargspec`` (harmless on newer ParaView).
2. ``NEBULA_RT_SITE_PACKAGES`` (os.pathsep-separated) names site-packages folders holding
   NebulaRT and its dependencies (pyopencl, colour-science, scipy, matplotlib), built for
   ParaView's Python and *without* a VTK wheel, which would clash with ParaView's own VTK.
   ``nebula_rt_site.activate`` puts them in front of the system's packages (so a newer
   numpy/scipy wins over the distribution's), processes their .pth files (so an editable
   install of NebulaRT works) and fixes shadowed namespace packages (``mpl_toolkits``).

3. NumPy 2.4 removed ``numpy.in1d``, which ParaView 5.11's ``vtkmodules.numpy_interface``
   (Python Calculator, Python Annotation: the state files' labels) still binds at import; alias
   it to ``numpy.isin`` (what ``in1d`` became) when a newer numpy is the one found.

If a distribution already has a sitecustomize (Debian's lives in /etc/python3.X and only sets
up apport), this one, being first on PYTHONPATH, replaces it for ParaView's processes.
"""

import inspect
import os

if not hasattr(inspect, "getargspec"):
    inspect.getargspec = inspect.getfullargspec

_dirs = [d for d in os.environ.get("NEBULA_RT_SITE_PACKAGES", "").split(os.pathsep) if d]
if _dirs:
    from nebula_rt_site import activate

    activate(_dirs)
    del activate
del _dirs

try:
    import numpy as _np
except ImportError:
    pass
else:
    if "in1d" not in dir(_np) and hasattr(_np, "isin"):
        _np.in1d = _np.isin
    del _np
