"""The example notebooks run from top to bottom without errors, on the test device.

Each notebook in ``examples/notebooks`` is executed with nbclient in a kernel running *this*
interpreter (a kernel spec written to a temporary folder points at ``sys.executable``, so a
``python3`` kernel spec elsewhere on the machine cannot pick another Python). The notebooks read
their OpenCL device from ``NEBULA_RT_DEVICE``; it is pinned to the test device (PoCL unless
``NEBULA_RT_TEST_DEVICE`` says otherwise). Their last cell prints ``SUMMARY {json}``, which the
tests check: exact energy balance, stage execution counts, images produced.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from conftest import TEST_DEVICE

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")
pytest.importorskip("pyvista")

from jupyter_client.kernelspec import KernelSpecManager  # noqa: E402  (after the skips)
from jupyter_client.manager import AsyncKernelManager  # noqa: E402

NOTEBOOKS = Path(__file__).resolve().parents[2] / "examples" / "notebooks"
CELL_TIMEOUT_S = 60


@pytest.fixture(scope="module")
def kernel_dir(tmp_path_factory) -> Path:
    """A kernel spec folder whose ``python3`` runs this interpreter."""
    root = tmp_path_factory.mktemp("kernels")
    spec = root / "python3"
    spec.mkdir()
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "NebulaRT test kernel",
        "language": "python",
    }))
    return root


def run_notebook(name: str, kernel_dir: Path, tmp_path: Path, monkeypatch) -> tuple[object, dict]:
    """Execute ``examples/notebooks/<name>``; return the executed notebook and its summary."""
    monkeypatch.setenv("NEBULA_RT_DEVICE", TEST_DEVICE)
    monkeypatch.setenv("IPYTHONDIR", str(tmp_path / "ipython"))
    monkeypatch.setenv("JUPYTER_RUNTIME_DIR", str(tmp_path / "runtime"))
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    km = AsyncKernelManager(kernel_name="python3",
                            kernel_spec_manager=KernelSpecManager(kernel_dirs=[str(kernel_dir)]))
    client = nbclient.NotebookClient(
        nb, km=km, timeout=CELL_TIMEOUT_S, allow_errors=False,
        resources={"metadata": {"path": str(NOTEBOOKS)}},  # the kernel's working directory
    )
    client.execute()  # raises CellExecutionError, naming the cell, if any cell fails

    code_cells = [c for c in nb.cells if c.cell_type == "code"]
    for cell in code_cells:
        assert not [o for o in cell.get("outputs", []) if o.get("output_type") == "error"], cell.source
    text = "".join(o.get("text", "") for o in code_cells[-1].outputs if o.get("output_type") == "stream")
    lines = [ln for ln in text.splitlines() if ln.startswith("SUMMARY ")]
    assert len(lines) == 1, f"the last cell must print one SUMMARY line, got {text!r}"
    return nb, json.loads(lines[0][len("SUMMARY "):])


def png_outputs(nb) -> int:
    return sum(1 for c in nb.cells if c.cell_type == "code"
               for o in c.get("outputs", []) if "image/png" in o.get("data", {}))


def expect_test_device(device: str) -> None:
    if TEST_DEVICE == "Portable Computing Language":
        # PoCL names its CPU device after the processor; the pipeline reports "platform: device"
        assert "portable computing language" in device.lower() or "pocl" in device.lower() or "cpu" in device.lower(), device


def test_nebula_tour(kernel_dir, tmp_path, monkeypatch):
    nb, summary = run_notebook("nebula_tour.ipynb", kernel_dir, tmp_path, monkeypatch)
    expect_test_device(summary["device"])
    assert summary["grid"] == [48, 48, 48]
    assert summary["photons"] == 200_000
    assert summary["energy_balance_exact"] == {"R": True, "G": True, "B": True}
    # the exposure change re-ran the colour stage only
    assert summary["executions"] == {"density": 1, "transport": 1, "colour": 2}
    auto, fixed = summary["exposures"]
    assert fixed == pytest.approx(4 * auto, rel=1e-12)
    h, w, c = summary["volume_image_shape"]
    assert (h, w, c) == (420, 420, 3)
    assert summary["volume_image_mean"] > 1.0  # not a black picture
    assert summary["sky_method"] in ("NebulaSkyImage filter", "projected emissivity")
    assert len(summary["sky_image_shape"]) == 3 and summary["sky_image_shape"][2] == 3
    # slices, volume, exposure comparison, sky image
    assert png_outputs(nb) >= 4


def test_vtk_filters(kernel_dir, tmp_path, monkeypatch):
    nb, summary = run_notebook("vtk_filters.ipynb", kernel_dir, tmp_path, monkeypatch)
    expect_test_device(summary["device"])
    assert summary["dimensions"] == [40, 40, 40]
    assert summary["energy_balance_exact"] == {"R": True, "G": True, "B": True}
    assert summary["executions_initial"] == {"density": 1, "light field": 1, "colour": 1}
    assert summary["executions_after_exposure"] == {"density": 1, "light field": 1, "colour": 2}
    assert summary["executions_after_albedo"] == {"density": 1, "light field": 2, "colour": 3}
    auto, fixed = summary["exposures"]
    assert fixed == pytest.approx(4 * auto, rel=1e-12)
    esc = summary["escape_fraction_G"]
    assert esc["0.3"] < esc["0.6"]  # less scattering, more absorption, fewer escape
    assert png_outputs(nb) >= 2


def test_adaptive_densities(kernel_dir, tmp_path, monkeypatch):
    nb, summary = run_notebook("adaptive_densities.ipynb", kernel_dir, tmp_path, monkeypatch)
    expect_test_device(summary["device"])
    assert summary["grid"] == [48, 48, 48]
    assert summary["energy_balance_exact"] == {"R": True, "G": True, "B": True}
    assert 0 < summary["leaves"] < summary["voxels"] / 4  # the background merged
    assert summary["snapshot_leaves"] > 100
    got, want = summary["snapshot_mass"]
    assert got == pytest.approx(want, rel=1e-6)  # the particles' mass kept on the leaves
    assert summary["lit_fraction"] > 0.9
    # the light per leaf drawn by pyvista: every leaf a cell, a picture with something in it
    shown, leaves = summary["pyvista_leaves"]
    assert shown == leaves > 100 and summary["pyvista_image_mean"] > 1.0
    assert png_outputs(nb) >= 3
