"""Start-up fixes for NebulaRT inside ParaView (pvpython, pvbatch and the GUI).

Put this folder on PYTHONPATH (scripts/pv-env.sh does). It is not a plugin: only the entry
file ``plugin/NebulaRT.py`` belongs on PV_PLUGIN_PATH, since ParaView loads every .py there.

1. ParaView 5.11's Python-plugin loader calls ``inspect.getargspec``, which Python 3.11
   removed; alias it to ``getfullargspec`` (harmless on newer ParaView).
2. ``NEBULA_RT_SITE_PACKAGES`` (os.pathsep-separated) names site-packages folders holding
   NebulaRT and its dependencies (pyopencl, colour-science, scipy), built for ParaView's Python
   and *without* a VTK wheel, which would clash with ParaView's own VTK. They go in front of
   the system's packages (so a newer numpy/scipy wins over the distribution's) and their .pth
   files are processed (so an editable install of NebulaRT works).
"""

import inspect
import os
import site
import sys

if not hasattr(inspect, "getargspec"):
    inspect.getargspec = inspect.getfullargspec

for _dir in reversed([d for d in os.environ.get("NEBULA_RT_SITE_PACKAGES", "").split(os.pathsep) if d]):
    if os.path.isdir(_dir):
        _before = list(sys.path)
        site.addsitedir(_dir)
        _added = [p for p in sys.path if p not in _before]
        sys.path[:] = [_dir] + _added + [p for p in _before if p != _dir]
