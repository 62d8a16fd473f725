"""Every package the code imports is declared in pyproject.toml (a dependency or an extra).

The imports are read from the source (function bodies included) of the library, the VTK layer
and the plugin; each is mapped to the distribution that installs it by the installed packages'
own metadata (importlib.metadata.packages_distributions). Not installed here, and so named by
hand: tomli (Python < 3.11 only) and CuPy (the CUDA path). ParaView's own modules come with
ParaView, which pip does not install; so does PyQt5, which the plugin imports only inside the
GUI: it must be the binding of the Qt that ParaView links (Debian's python3-pyqt5, installed by
scripts/setup.sh beside ParaView and named in pyproject.toml's comments), never a pip wheel,
which brings a Qt of its own.
"""

from __future__ import annotations

import ast
import importlib.metadata
import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("python/nebula_rt", "filters", "plugin")
OWN = {"nebula_rt", "nebula_rt_paraview", "nebula_rt_site"}
WITH_PARAVIEW = {"paraview", "PyQt5"}
NOT_INSTALLED_HERE = {"tomli": ["tomli"], "cupy": ["cupy-cuda12x"], "cupyx": ["cupy-cuda12x"]}


def _normal(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def imported_packages() -> set[str]:
    names = set()
    for root in SOURCES:
        for path in (ROOT / root).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    names.update(a.name.split(".")[0] for a in node.names)
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n not in OWN}


def declared() -> set[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"]) + [r for extra in project["optional-dependencies"].values() for r in extra]
    return {_normal(re.match(r"[A-Za-z0-9_.\-]+", r).group(0)) for r in reqs}


def test_every_imported_package_is_declared():
    names = imported_packages()
    assert {"numpy", "pyopencl", "colour", "matplotlib", "cupy", "vtkmodules"} <= names
    have = importlib.metadata.packages_distributions()
    want = declared()
    missing = []
    for name in sorted(names - WITH_PARAVIEW):
        dists = have.get(name) or NOT_INSTALLED_HERE.get(name)
        assert dists, f"{name}: not installed here and not named in NOT_INSTALLED_HERE"
        if not any(_normal(d) in want for d in dists):
            missing.append(f"{name} ({', '.join(dists)})")
    assert not missing, f"imported but not declared in pyproject.toml: {missing}"


def test_the_version_is_declared_once():
    """pyproject.toml holds the version; the package and the ParaView plugin read it from the
    installed metadata, and no source file repeats it."""
    import nebula_rt

    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert nebula_rt.__version__ == version
    repeated = [str(p.relative_to(ROOT)) for root in SOURCES for p in (ROOT / root).rglob("*.py")
                if f'"{version}"' in p.read_text() or f"'{version}'" in p.read_text()]
    assert not repeated, repeated
