"""The library core never imports VTK or ParaView (DESIGN.md layers)."""

import subprocess
import sys

CORE = ["nebula_rt", "nebula_rt.scene", "nebula_rt.bands", "nebula_rt.backends", "nebula_rt.density",
        "nebula_rt.transport", "nebula_rt.filtering", "nebula_rt.colour_convert", "nebula_rt.pipeline",
        "nebula_rt.cli", "nebula_rt.io_vti", "nebula_rt.render"]


def test_core_imports_without_vtk():
    code = ("import sys\n" + "".join(f"import {m}\n" for m in CORE) +
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('vtk', 'vtkmodules', 'pyvista', 'paraview'))\n"
            "print(bad)\nassert not bad, bad\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
