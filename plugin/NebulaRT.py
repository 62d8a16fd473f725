"""NebulaRT ParaView plugin: the only entry file of this folder.

Load it with Tools > Manage Plugins > Load New (this file), or put this folder on
PV_PLUGIN_PATH (ParaView then loads every .py/.xml in it, which is why nothing else lives at
this level). It adds the NebulaRT menu (Filters > NebulaRT and Sources > NebulaRT) with

- Nebula Dust Density (source)        proxy name ``NebulaDustDensity``
- Nebula Light Field (filter)         proxy name ``NebulaLightField``
- Nebula Colour (filter)              proxy name ``NebulaColour``
- Nebula Sky Image (filter)           proxy name ``NebulaSkyImage``
- Nebula Sky View (view)              proxy name ``NebulaSkyView`` (where sky images open)
- a writer of calibrated sky images   proxy name ``NebulaSkyFitsWriter`` (File > Save Data, .fits)
- a reader of fit results             proxy name ``NebulaFitResultReader`` (File > Open, the
  ``nebula-rt fit --json`` file)

Modelled on ParaView's ``Examples/Plugins/ComplexPythonArchitecture``: this file only makes the
package ``nebula_rt_paraview`` (next to it) importable and imports its proxies, thin
decorated subclasses of the VTK algorithms in ``nebula_rt.filters``.

NebulaRT itself (``nebula_rt``) and its dependencies (pyopencl, colour-science, scipy) must be
importable by ParaView's Python *without* a VTK wheel in front of ParaView's VTK. The
recommended set-up (docs/paraview.md) is ``source scripts/pv-env.sh`` before starting ParaView:
it puts ``plugin/site`` (a sitecustomize) on PYTHONPATH and names the ``.venv-pv``
site-packages. When that was not done, this file tries the same with ``<repo>/.venv-pv`` as a
fallback, and otherwise fails with an ImportError saying what to do.
"""

import os
import sys

_HERE = os.path.dirname(os.path.abspath(__file__))

# Add this folder to the Python path so the proxies' package imports (also on a server
# process, which imports the proxies' classes by their qualified names).
if _HERE not in sys.path:
    sys.path.append(_HERE)

paraview_plugin_name = "NebulaRT"


def _ensure_nebula_rt():
    try:
        import nebula_rt.filters  # noqa: F401
        return
    except ImportError as first:
        error = first
    # Fallback: the repository's ParaView venv (scripts/setup.sh makes it), activated the way
    # plugin/site/sitecustomize.py does it.
    site_dir = os.path.join(_HERE, "site")
    if site_dir not in sys.path:
        sys.path.append(site_dir)
    from nebula_rt_site import activate, default_site_packages

    dirs = [d for d in os.environ.get("NEBULA_RT_SITE_PACKAGES", "").split(os.pathsep) if d]
    dirs = dirs or default_site_packages(os.path.dirname(_HERE))
    if dirs:
        activate(dirs)
        try:
            import nebula_rt.filters  # noqa: F401
            return
        except ImportError as second:
            error = second
    raise ImportError(
        "NebulaRT plugin: cannot import nebula_rt ({}). Make NebulaRT and its dependencies "
        "importable in ParaView's Python {}.{} without a VTK wheel: run scripts/setup.sh, then "
        "`source scripts/pv-env.sh` before starting ParaView (see docs/paraview.md).".format(
            error, *sys.version_info[:2])
    ) from error


_ensure_nebula_rt()

from nebula_rt import __version__ as paraview_plugin_version  # noqa: E402  (declared in pyproject.toml)

# import the proxies (the plugin loader exports every decorated class found in this module,
# and NebulaSkyView's view definition: every object with a _pvsm_proxy_xml)
from nebula_rt_paraview import (  # noqa: E402,F401
    NebulaColour,
    NebulaDustDensity,
    NebulaFitResultReader,
    NebulaLightField,
    NebulaSkyFitsWriter,
    NebulaSkyImage,
    NebulaSkyView,
)

# what Apply (or Show) shows: the true-colour volume with its stars, the sky image in its own
# view (nebula_rt_paraview.display; only where this process has a client)
from nebula_rt_paraview import display as _display  # noqa: E402
from nebula_rt_paraview import views as _views  # noqa: E402

_views.install_view_defaults()
_display.install()
