"""The layers of docs/design.md: the library (python/nebula_rt) imports no VTK, pyvista or ParaView;
the VTK layer is nebula_rt.filters, and its part that ParaView runs needs no pyvista."""

from __future__ import annotations

import ast
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

import nebula_rt

LIBRARY = Path(nebula_rt.__file__).resolve().parent
#: top-level packages of the VTK world
VTK_PACKAGES = ("vtk", "vtkmodules", "pyvista", "paraview")
#: the library's modules that reach into the VTK layer, each inside a function (at run time,
#: for an output or input that needs VTK): the CLI writes the .vti and the PNG, the density
#: stage reads a .vti density, and the old name io_vti forwards to nebula_rt.filters.vti
BOUNDARY = {"nebula_rt.cli.commands", "nebula_rt.density.generate", "nebula_rt.pipeline.io_vti"}
ROOT = Path(__file__).resolve().parents[1]


def library_modules() -> dict[str, Path]:
    """Every module of python/nebula_rt (the files themselves, not a list kept by hand; the
    ``python -m`` entry scripts, which run a command when imported, aside)."""
    out = {}
    for p in sorted(LIBRARY.rglob("*.py")):
        if p.name == "__main__.py":
            continue
        parts = p.relative_to(LIBRARY.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def _block(packages) -> str:
    """Python that makes these packages unimportable (as if not installed)."""
    return "import sys\n" + "".join(f"sys.modules[{p!r}] = None\n" for p in packages)


def test_every_library_module_imports_without_vtk():
    """With vtk, vtkmodules, pyvista and paraview unimportable, every module of python/nebula_rt
    imports, and none of them (nor the VTK layer, nebula_rt.filters) is loaded."""
    modules = sorted(library_modules())
    assert "nebula_rt.pipeline.output_contract" in modules and "nebula_rt.cli.commands" in modules
    code = (_block(VTK_PACKAGES) + "import importlib\n"
            f"for m in {modules!r}:\n    importlib.import_module(m)\n"
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in "
            f"{VTK_PACKAGES!r} and sys.modules[m] is not None or m.startswith('nebula_rt.filters'))\n"
            "assert not bad, bad\nprint(len(" + repr(modules) + "))\n")
    proc = _run(code)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.strip() == str(len(modules))


def _imported_names(tree: ast.AST, module: str, is_package: bool):
    """(absolute module name, node, inside a function) of every import in ``tree``: import
    statements anywhere (function bodies too) and importlib.import_module / __import__ calls
    with literal names."""
    package = module if is_package else module.rpartition(".")[0]
    functions = [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
    nested = {id(c) for f in functions for c in ast.walk(f) if c is not f}
    for node in ast.walk(tree):
        lazy = id(node) in nested
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node, lazy
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module
            yield name, node, lazy
            for alias in node.names:  # `from . import filters` names a module too
                yield f"{name}.{alias.name}", node, lazy
        elif isinstance(node, ast.Call):
            f = node.func
            fname = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            if fname in ("import_module", "__import__"):
                for c in ast.walk(node):
                    if isinstance(c, ast.Constant) and isinstance(c.value, str):
                        yield c.value, node, lazy


def _library_imports():
    mods = library_modules()
    for module, path in mods.items():
        tree = ast.parse(path.read_text(), str(path))
        for name, node, lazy in _imported_names(tree, module, path.name == "__init__.py"):
            yield module, path, name, node, lazy


def test_no_library_module_imports_vtk_even_lazily():
    """Imports inside functions never run at import time, so the import system cannot see them:
    the library's source is read instead. No import of vtk/vtkmodules/pyvista/paraview anywhere
    (function bodies and importlib calls included); the VTK layer is reached only from the
    boundary modules, and only inside functions."""
    vtk, crossing = [], []
    for module, path, name, node, lazy in _library_imports():
        where = f"{path.relative_to(LIBRARY.parent)}:{node.lineno} {name}"
        if name.split(".")[0] in VTK_PACKAGES:
            vtk.append(where)
        if name == "nebula_rt.filters" or name.startswith("nebula_rt.filters."):
            if module not in BOUNDARY or not lazy:
                crossing.append(where)
    assert not vtk, vtk
    assert not crossing, crossing


def _cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(comp)

    for v in graph:
        if v not in index:
            visit(v)
    return out


def _modules_under(root: Path, package: str) -> dict[str, Path]:
    """Every module of the package ``package`` whose files are under ``root``."""
    out = {}
    for p in sorted(root.rglob("*.py")):
        parts = (package,) + p.relative_to(root).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def all_modules() -> dict[str, Path]:
    """The library's modules, the VTK layer's (nebula_rt.filters) and the plugin's (its entry
    file, the wrapper package and the site hooks), found from the files."""
    import nebula_rt.filters

    mods = library_modules()
    mods.update(_modules_under(Path(nebula_rt.filters.__file__).resolve().parent, "nebula_rt.filters"))
    plugin = ROOT / "plugin"
    mods.update(_modules_under(plugin / "nebula_rt_paraview", "nebula_rt_paraview"))
    mods["NebulaRT"] = plugin / "NebulaRT.py"
    for p in sorted((plugin / "site").glob("*.py")):
        mods[p.stem] = p
    return mods


def import_graph(mods: dict[str, Path]) -> dict[str, set[str]]:
    """module -> the modules it imports (at the top or inside functions)."""
    graph = {m: set() for m in mods}
    for module, path in mods.items():
        tree = ast.parse(path.read_text(), str(path))
        found = list(_imported_names(tree, module, path.name == "__init__.py"))
        # `from . import x` of a submodule x imports x, not the package's own names (a package
        # is imported before any of its submodules anyway): no edge to the package for it
        bases = {}
        for name, node, _ in found:
            if isinstance(node, ast.ImportFrom) and node.module is None:
                bases.setdefault(id(node), name)  # the first name yielded: the package
        for name, node, _lazy in found:
            base = bases.get(id(node))
            if base == name and all(f"{base}.{a.name}" in mods for a in node.names):
                continue
            if name in mods and name != module:
                graph[module].add(name)
    return graph


def test_no_import_circles():
    """No module imports itself back through others, imports inside functions included: the
    library (the transport and its backends included, since the device's capacity checks and
    the transport's setup sit below both), the VTK layer and the plugin."""
    mods = all_modules()
    assert {"nebula_rt.transport", "nebula_rt.filters.vti", "nebula_rt_paraview.light_field", "NebulaRT"} <= set(mods)
    assert _cycles(import_graph(mods)) == []


def test_the_backends_sit_below_the_transport():
    """The backends never reach up into the transport, its memory estimates or the pipeline."""
    graph = import_graph(all_modules())
    for module, imported in graph.items():
        if module.startswith("nebula_rt.backends"):
            above = {m for m in imported if m.split(".")[:2] in (["nebula_rt", "transport"], ["nebula_rt", "pipeline"])}
            assert not above, (module, above)


#: The library's domains (its subpackages; docs/design.md, "Where things live"), bottom up: a
#: module imports only from its own domain and the ones below it. "core" is the package's own
#: modules (errors, limits, interrupts, array_api).
DOMAINS = ("core", "optics", "scene", "backends", "density", "transport", "pipeline", "observe", "cli")


def domain(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in DOMAINS else "core"


def test_the_domains_are_layers():
    """Every import of a library module (inside functions too) goes to its own domain or one
    below it, so a domain can be read, tested and changed with only those below in mind; every
    subpackage is in the list, so a new one must be placed."""
    mods = library_modules()
    packages = {m.split(".")[1] for m, p in mods.items() if p.name == "__init__.py" and m.count(".") == 1}
    assert packages == set(DOMAINS) - {"core"}
    upward = [f"{m} -> {d}" for m, ds in import_graph(mods).items() for d in ds
              if DOMAINS.index(domain(d)) > DOMAINS.index(domain(m))]
    assert not upward, upward


def test_the_vtk_layer_that_paraview_runs_needs_no_pyvista():
    """ParaView's Python has VTK but no pyvista (docs/paraview.md: never install it there): the
    VTK algorithms, image_data and the controller communicator import without it; .vti files
    and PNGs (the io extra) need it."""
    code = (_block(["pyvista"]) + "import nebula_rt.filters, nebula_rt.filters.image_data, "
            "nebula_rt.filters.controller\n"
            "from nebula_rt.filters import NebulaColour, NebulaDustDensity, NebulaLightField, NebulaSkyImage\n"
            "try:\n    import nebula_rt.filters.vti\nexcept ImportError as e:\n    print('vti needs', e.name)\n")
    proc = _run(code)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.strip() == "vti needs pyvista"


def test_a_vti_density_reads_without_pyvista(tmp_path):
    """dust.model = "file" with a .vti where pyvista is absent (ParaView's Python): VTK's own
    reader (nebula_rt.filters.density_file) gives the array bit for bit, a cell array too, and
    a file that is not VTK, or lacks the array, is refused naming dust.file and the file.
    (tests/paraview/test_paraview.py runs the same in pvpython.)"""
    code = _block(["pyvista"]) + f"""
import numpy as np
from pathlib import Path
from vtkmodules.util.numpy_support import numpy_to_vtk
from vtkmodules.vtkCommonDataModel import vtkImageData
from vtkmodules.vtkIOXML import vtkXMLImageDataWriter
from nebula_rt.density import load_density_file
from nebula_rt.errors import SceneError
d = Path({str(tmp_path)!r})
a = np.random.default_rng(3).random((5, 4, 3)).astype(np.float32)
img = vtkImageData(); img.SetDimensions(5, 4, 3)
arr = numpy_to_vtk(np.ravel(a, order="F"), deep=True); arr.SetName("rho"); img.GetPointData().AddArray(arr)
w = vtkXMLImageDataWriter(); w.SetInputData(img); w.SetFileName(str(d / "a.vti")); assert w.Write() == 1
got = load_density_file(d / "a.vti", "rho", (5, 4, 3))
assert np.array_equal(got, a.astype(np.float64)), "values"
(d / "bad.vti").write_bytes(b"not VTK at all" * 20)
for name, array in (("bad.vti", "rho"), ("a.vti", "density")):
    try:
        load_density_file(d / name, array, (5, 4, 3))
    except SceneError as e:
        print(e.parameter, Path(e.value).name, e.allowed)
assert "pyvista" not in sys.modules or sys.modules["pyvista"] is None
"""
    proc = _run(code)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert lines[0].startswith("dust.file bad.vti could not be read as density data") and "unreadable" in lines[0]
    assert lines[1].startswith("dust.file a.vti") and "no array named 'density'" in lines[1] and "rho (point)" in lines[1]


def test_old_io_vti_name_forwards_to_the_vtk_layer():
    """``nebula_rt.io_vti`` (shown by earlier docs) imports without VTK and hands out the VTK
    layer's functions on use, with a DeprecationWarning naming the new place."""
    pytest.importorskip("pyvista")
    from nebula_rt import io_vti
    from nebula_rt.filters import image_data, vti

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert io_vti.write_vti is vti.write_vti and io_vti.read_vti is vti.read_vti
        assert io_vti.to_image_data is image_data.to_image_data
    assert len(caught) == 3 and all(issubclass(w.category, DeprecationWarning) for w in caught)
    assert "nebula_rt.filters.vti.write_vti" in str(caught[0].message)
    with pytest.raises(AttributeError):
        io_vti.add_point_arrays  # noqa: B018 - not one the docs showed
    proc = _run(_block(VTK_PACKAGES) + "import nebula_rt.io_vti as m\n"
                "try:\n    m.write_vti\nexcept ImportError as e:\n    print('needs', e.name.split('.')[0])\n")
    assert proc.returncode == 0 and proc.stdout.strip() == "needs vtkmodules", proc.stdout + proc.stderr


def test_one_place_turns_a_scene_into_a_run():
    """Only nebula_rt.transport.request calls the transport's trace() (or its request form,
    or the planner) and reads the scene's
    device (transport.backend, transport.device): every observable, filter and command gets
    its run and its device from there, so a [transport] key reaches every run alike."""
    import nebula_rt.filters

    mods = library_modules()
    mods.update(_modules_under(Path(nebula_rt.filters.__file__).resolve().parent, "nebula_rt.filters"))
    home = "nebula_rt.transport.request"
    tracing, device = [], []
    for module, path in mods.items():
        if module == home or module.startswith("nebula_rt.transport"):
            continue
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and any(
                    a.name in ("trace", "trace_request", "plan_transport") for a in node.names):
                base = node.module or ""
                if base.split(".")[-1] in ("transport", "run", "plan", "request") and "transport" in base:
                    tracing.append(f"{module}:{node.lineno}")
            if (isinstance(node, ast.Attribute) and node.attr in ("backend", "device")
                    and isinstance(node.value, ast.Attribute) and node.value.attr == "transport"):
                device.append(f"{module}:{node.lineno} .transport.{node.attr}")
    assert not tracing, tracing
    assert not device, device


def test_the_modules_earlier_names_are_the_modules_at_their_homes():
    """Every earlier flat name of nebula_rt.MOVED imports (in a fresh interpreter, by the import
    statement users wrote) as the very module at its home, which exists as a file; no file is
    left at an old name, so there is one module per name."""
    moved = nebula_rt.MOVED
    assert {"bands", "calibrate", "fit", "transport_request", "tails", "sky", "comparison"} <= set(moved)
    mods = library_modules()
    for old, home in moved.items():
        assert f"nebula_rt.{home}" in mods, home
        assert f"nebula_rt.{old}" not in mods, old
    code = "import importlib, sys\n" + "".join(
        f"import nebula_rt.{old} as a\nassert a is sys.modules['nebula_rt.{home}'] is importlib.import_module("
        f"'nebula_rt.{home}'), {old!r}\n" for old, home in moved.items()) + "print('ok')\n"
    proc = _run(code)
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stdout + proc.stderr


def test_the_plugins_entry_file_only_imports():
    """plugin/NebulaRT.py, as ParaView's Examples/Plugins/ComplexPythonArchitecture: its folder
    on sys.path, the plugin's name, and imports; no functions, no work of its own (making
    NebulaRT importable and installing the displays happen in the package it imports)."""
    tree = ast.parse((ROOT / "plugin" / "NebulaRT.py").read_text())
    kinds = []
    for node in tree.body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            kinds.append("import")
        elif isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            kinds.append("docstring")
        elif isinstance(node, ast.Assign):
            names = [t.id for t in node.targets if isinstance(t, ast.Name)]
            assert names in (["_HERE"], ["paraview_plugin_name"]), ast.dump(node)
            kinds.append("assign")
        elif isinstance(node, ast.If):  # `if _HERE not in sys.path: sys.path.append(_HERE)`
            calls = [n for n in ast.walk(node) if isinstance(n, ast.Call)]
            assert len(calls) == 1 and ast.unparse(calls[0].func) == "sys.path.append", ast.unparse(node)
            kinds.append("path")
        else:
            raise AssertionError(f"line {node.lineno}: {ast.unparse(node)[:80]}")
    assert kinds.count("import") >= 3 and "path" in kinds


def test_the_tests_mirror_the_domains():
    """A change's tests sit beside it: every domain of the library has its folder of tests
    (tests/scene/ for nebula_rt.scene...), on pytest's path in pyproject.toml; only the tests
    of the whole (layers, dependencies, the public API, MPI runs) stay in tests/ itself."""
    import tomllib

    tests = ROOT / "tests"
    folders = {d.name for d in tests.iterdir() if d.is_dir() and any(d.glob("test_*.py"))}
    assert set(DOMAINS) - {"core"} <= folders, set(DOMAINS) - folders
    path = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]["pythonpath"]
    assert {f"tests/{d}" for d in folders} <= set(path)
    assert sorted(p.name for p in tests.glob("test_*.py")) == [
        "test_dependencies.py", "test_layering.py", "test_mpi.py", "test_public_api.py"]


def test_importing_the_library_leaves_colour_science_for_the_first_colour():
    """``import colour`` imports its plotting and matplotlib (1.5-2.7 s on 2 cores): the
    library, its command line and the VTK layer ParaView's plugin imports at start-up leave
    it until a colour is converted, which then imports it."""
    code = ("import sys\n"
            "import nebula_rt, nebula_rt.pipeline, nebula_rt.cli.commands, nebula_rt.observe, nebula_rt.filters\n"
            "print(sorted(m for m in ('colour', 'matplotlib') if m in sys.modules))\n"
            "from nebula_rt.optics import colour_convert\n"
            "colour_convert.XYZ_TO_LINEAR_SRGB\n"
            "print('colour' in sys.modules)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["[]", "True"], r.stdout
