"""A run computes, allocates and keeps only what its scene asks for; proven by counters.

(Colour or exposure changes that do not re-trace, and albedo changes that do not regenerate
the density, are tested in test_cli_and_pipeline.py::test_stages_rerun_only_when_their_inputs_change.)
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from conftest import TEST_BACKEND, TEST_DEVICE
from nebula_rt.pipeline import Pipeline
from nebula_rt.scene import Scene

ROOT = Path(__file__).resolve().parents[2]


def one_band_scene(shape=(12, 12, 12), photons=20_000) -> Scene:
    return Scene.from_dict({
        "grid": {"shape": list(shape)},
        "dust": {"model": "uniform", "density": 1.0, "tau": 2.0},
        "stars": [{"position": [0.5, 0.5, 0.5], "luminosity": 1.0}],
        "bands": {"list": [{"name": "V", "wavelength": 550.0, "extinction": 1.0, "albedo": 0.6, "g": 0.6}]},
        "transport": {"photons": photons},
    })


def thesis_scene(shape=(12, 12, 12), photons=20_000) -> Scene:
    return Scene.load(ROOT / "examples/scenes/thesis-default.toml").with_overrides(
        [f"grid.shape={list(shape)}", f"transport.photons={photons}"])


def test_only_requested_bands_are_traced(backend):
    one = Pipeline(backend).run(one_band_scene(), colour=False)
    three = Pipeline(backend).run(thesis_scene(), colour=False)
    # packets emitted per band, and nothing for bands the scene does not list
    assert one.transport.counts.shape == (1, 4) and int(one.transport.counts[0, 0]) == 20_000
    assert three.transport.counts.shape == (3, 4) and np.all(three.transport.counts[:, 0] == 20_000)
    # device cells exist for the requested bands only
    assert one.J.shape == (1, 12, 12, 12) and three.J.shape == (3, 12, 12, 12)
    assert one.transport.device_bytes < three.transport.device_bytes


def test_single_band_scene_skips_colour(backend):
    p = Pipeline(backend)
    light = p.run(one_band_scene())
    assert "colour" not in p.executions and light.rgba is None
    assert "rgba" not in light.point_arrays()
    three = Pipeline(backend)
    assert three.run(thesis_scene()).rgba is not None and three.executions["colour"] == 1


def test_memory_is_allocated_for_requested_outputs_and_reported(backend):
    scene = thesis_scene(shape=(16, 12, 10))
    nb, nvox = 3, 16 * 12 * 10
    no_colour = Pipeline(backend).run(scene, colour=False)
    colour = Pipeline(backend).run(scene)
    m0, m1 = no_colour.memory, colour.memory
    # finishing: J, error and emissivity as float32 (12 B per cell) plus, with colour, the
    # brightness key and rgba (8 B per voxel)
    assert 12 * nb * nvox <= m0["finish_device_bytes"] < 12 * nb * nvox + 4096
    assert m1["finish_device_bytes"] - m0["finish_device_bytes"] >= 8 * nvox - 16
    # transport: slots x 8 B + sums 12 B per cell (float64 sum, float32 centred squares) +
    # density, as reported by the session, and J and the emissivity (8 B per cell) made band by
    # band during the last fold (transport.plan.light_while_folding)
    slots = no_colour.transport.device_bytes - 12 * nb * nvox - 4 * nvox - 8 * nb * nvox
    assert slots > 0 and slots % (8 * nb * nvox + 32 * nb + 4) == 0
    # finishing: first the sums, J and the emissivity (the error is written over the
    # squares), then the outputs once the float64 sums are freed
    first = 12 * nb * nvox + 4 * nvox + 8 * nb * nvox
    then = 4 * nvox + 12 * nb * nvox + 8 * nvox
    assert m1["device_peak_bytes"] == max(m1["transport_device_bytes"], first, then)
    assert m1["host_peak_rss_bytes"] > 0
    assert colour.field_data()["device_memory_peak_bytes"] == m1["device_peak_bytes"]


def test_cli_reports_memory_and_renders_one_band(tmp_path):
    scene = tmp_path / "one.toml"
    scene.write_text(one_band_scene().to_toml())
    out, png = tmp_path / "one.vti", tmp_path / "one.png"
    proc = subprocess.run([sys.executable, "-m", "nebula_rt.cli", "render", str(scene), "-o", str(out),
                           "--png", str(png), "--set", f'transport.device="{TEST_DEVICE}"',
                           "--set", f'transport.backend="{TEST_BACKEND}"'], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert '"peak_device_mib"' in proc.stdout and '"peak_host_rss_mib"' in proc.stdout
    assert png.stat().st_size > 1000 and out.exists()
