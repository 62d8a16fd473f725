"""Makes NebulaRT (``nebula_rt``) importable in ParaView's Python, on import.

NebulaRT and its dependencies (pyopencl, colour-science, scipy) must be importable by
ParaView's Python *without* a VTK wheel in front of ParaView's VTK. The recommended set-up
(docs/paraview.md) is ``source scripts/pv-env.sh`` before starting ParaView: it puts
``plugin/site`` (a sitecustomize) on PYTHONPATH and names the ``.venv-pv`` site-packages. When
that was not done, this module tries the same with ``<repo>/.venv-pv`` as a fallback, and
otherwise fails with an ImportError saying what to do. It is the first thing the package
imports, so the plugin's entry file (``plugin/NebulaRT.py``) only imports.
"""

import os
import sys

_PLUGIN = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _ensure_nebula_rt():
    try:
        import nebula_rt.filters  # noqa: F401
        return
    except ImportError as first:
        error = first
    # Fallback: the repository's ParaView venv (scripts/setup.sh makes it), activated the way
    # plugin/site/sitecustomize.py does it.
    site_dir = os.path.join(_PLUGIN, "site")
    if site_dir not in sys.path:
        sys.path.append(site_dir)
    from nebula_rt_site import activate, default_site_packages

    dirs = [d for d in os.environ.get("NEBULA_RT_SITE_PACKAGES", "").split(os.pathsep) if d]
    dirs = dirs or default_site_packages(os.path.dirname(_PLUGIN))
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
