"""Make NebulaRT's packages importable in ParaView's Python (used by ``sitecustomize.py`` and,
as a fallback, by the plugin's entry file ``plugin/NebulaRT.py``).

``activate(dirs)`` puts site-packages folders (NebulaRT and its dependencies, built for
ParaView's Python, *without* a VTK wheel: one would clash with ParaView's own VTK) in front of
the system's packages, processes their .pth files (so an editable install of NebulaRT works)
and binds namespace packages of those folders that a regular package of the same name further
down the path would shadow (matplotlib >= 3.7's ``mpl_toolkits`` against Debian's matplotlib
3.6 one, whose ``mplot3d`` breaks a newer matplotlib; colour-science imports it; Debian's
``matplotlib-*-nspkg.pth`` even registers it at start-up). Nothing is imported for that.
"""

import glob
import importlib.machinery
import importlib.util
import os
import site
import sys

#: namespace packages (no ``__init__.py``) that a distribution ships as regular packages
NAMESPACE_PACKAGES = ("mpl_toolkits",)


def default_site_packages(repo):
    """``<repo>/.venv-pv/lib/pythonX.Y/site-packages`` for the running Python, if it exists."""
    pattern = os.path.join(repo, ".venv-pv", "lib", "python%d.%d" % sys.version_info[:2], "site-packages")
    return [d for d in glob.glob(pattern) if os.path.isdir(d)]


def activate(dirs):
    """Put ``dirs`` (first = highest priority) in front of ``sys.path``; see the module doc."""
    dirs = [d for d in dirs if d and os.path.isdir(d)]
    for d in reversed(dirs):
        before = list(sys.path)
        site.addsitedir(d)
        added = [p for p in sys.path if p not in before]
        sys.path[:] = [d] + added + [p for p in before if p != d]
    for d in dirs:
        for name in NAMESPACE_PACKAGES:
            pkg = os.path.join(d, name)
            if not os.path.isdir(pkg) or os.path.exists(os.path.join(pkg, "__init__.py")):
                continue
            if any(m.startswith(name + ".") for m in sys.modules):
                continue  # too late: a submodule is already imported
            current = sys.modules.get(name)
            if current is not None and list(getattr(current, "__path__", []))[:1] == [pkg]:
                continue
            spec = importlib.machinery.PathFinder.find_spec(name, [d])
            if spec is not None and spec.submodule_search_locations is not None:
                sys.modules[name] = importlib.util.module_from_spec(spec)
