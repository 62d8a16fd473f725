"""The command line end to end, density files, and stage caching in the pipeline."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import TEST_DEVICE
from nebula_rt.errors import SceneError
from nebula_rt.filters.vti import read_vti
from nebula_rt.pipeline import Pipeline
from nebula_rt.scene import Scene

ROOT = Path(__file__).resolve().parents[2]
SMALL = ["grid.shape=[20,16,12]", "transport.photons=20000", f'transport.device="{TEST_DEVICE}"']


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "nebula_rt.cli", *args], capture_output=True, text=True)


def test_cli_writes_the_output_contract(tmp_path):
    out = tmp_path / "neb.vti"
    png = tmp_path / "neb.png"
    args = ["render", str(ROOT / "examples/scenes/thesis-default.toml"), "-o", str(out), "--png", str(png), "-q"]
    for s in SMALL:
        args += ["--set", s]
    proc = run_cli(*args)
    assert proc.returncode == 0, proc.stderr
    arrays, field, spacing, origin, dims = read_vti(out)
    assert dims == (20, 16, 12)
    assert spacing == pytest.approx((1 / 20, 1 / 16, 1 / 12))
    assert origin == pytest.approx((0.5 / 20, 0.5 / 16, 0.5 / 12))
    expected = {"density", "rgba"} | {f"{p}_{b}" for p in ("J", "emissivity", "rel_error") for b in "RGB"}
    assert set(arrays) == expected
    for name, a in arrays.items():
        if name == "rgba":
            assert a.dtype == np.uint8 and a.shape == (20, 16, 12, 4)
        else:
            assert a.dtype == np.float32 and a.shape == (20, 16, 12)
            assert np.all(np.isfinite(a))
    for b in "RGB":
        e = [field[f"{t}_{b}"] for t in ("emitted", "absorbed", "escaped", "terminated")]
        assert e[0] == e[1] + e[2] + e[3]
        assert field[f"packets_emitted_{b}"] == 20000
    assert field["photons"] == 20000 and field["seed"] == 1
    # the scene travels with the data and reproduces it
    scene = Scene.loads(field["scene"])
    assert tuple(scene.grid.shape) == (20, 16, 12) and scene.transport.photons == 20000
    # emissivity = albedo * extinction * J
    tau = scene.dust.tau
    np.testing.assert_allclose(arrays["emissivity_B"], 0.6 * tau * 1.324 * arrays["density"] * arrays["J_B"], rtol=1e-5)
    assert png.stat().st_size > 1000


@pytest.mark.parametrize(
    "override,param",
    [
        ("transport.photons=0", "transport.photons"),
        ("bands.g=1.5", "bands.g"),
        ("bands.albedo=-0.1", "bands.albedo"),
        ("stars.0.position=[0.5,0.5,1.5]", "stars[0].position"),
        ("grid.shape=[1,8,8]", "grid.shape"),
        ("transport.estimator=\"photon-map\"", "transport.estimator"),
        ("bands.preset=\"ultraviolet\"", "bands.preset"),
    ],
)
def test_cli_bad_input_names_the_parameter_and_writes_nothing(tmp_path, override, param):
    out = tmp_path / "neb.vti"
    proc = run_cli("render", str(ROOT / "examples/scenes/thesis-default.toml"), "-o", str(out), "--set", override, "-q")
    assert proc.returncode == 2
    assert param in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_cli_missing_backend_is_explained(tmp_path):
    proc = run_cli("render", str(ROOT / "examples/scenes/homogeneous.toml"), "-o", str(tmp_path / "a.vti"),
                   "--backend", "cuda", "-q")
    assert proc.returncode == 3 and "cuda" in proc.stderr.lower()
    proc = run_cli("render", str(ROOT / "examples/scenes/homogeneous.toml"), "-o", str(tmp_path / "a.vti"),
                   "--device", "no-such-device", "-q")
    assert proc.returncode == 3 and "no-such-device" in proc.stderr
    assert list(tmp_path.iterdir()) == []


# --- density files --------------------------------------------------------------------------
def file_scene(path, shape=(8, 6, 4)):
    return Scene.from_dict({
        "grid": {"shape": list(shape)},
        "dust": {"model": "file", "file": str(path), "floor": 0.0, "tau": 2.0},
        "transport": {"photons": 2000, "device": TEST_DEVICE},
    })


def test_density_file_npy_and_vti(tmp_path, backend):
    from nebula_rt.filters.vti import write_vti

    rng = np.random.default_rng(1)
    data = rng.uniform(0, 2, size=(8, 6, 4))
    np.save(tmp_path / "d.npy", data)
    write_vti(tmp_path / "d.vti", {"density": data.astype(np.float32)}, {}, (1, 1, 1))
    p = Pipeline(backend)
    np.testing.assert_allclose(p.density(file_scene(tmp_path / "d.npy")), data, rtol=1e-6)
    np.testing.assert_allclose(p.density(file_scene(tmp_path / "d.vti")), data, rtol=1e-6)


@pytest.mark.parametrize("case", ["missing", "garbage", "shape", "nan", "negative", "array"])
def test_bad_density_file(tmp_path, backend, case):
    from nebula_rt.filters.vti import write_vti

    path = tmp_path / "d.npy"
    good = np.ones((8, 6, 4))
    if case == "garbage":
        path.write_bytes(b"not a numpy file")
    elif case == "shape":
        np.save(path, np.ones((8, 6, 5)))
    elif case == "nan":
        bad = good.copy(); bad[1, 2, 3] = np.nan; np.save(path, bad)
    elif case == "negative":
        bad = good.copy(); bad[0, 0, 0] = -1; np.save(path, bad)
    elif case == "array":
        path = tmp_path / "d.vti"
        write_vti(path, {"rho": good.astype(np.float32)}, {}, (1, 1, 1))
    with pytest.raises(SceneError) as err:
        Pipeline(backend).density(file_scene(path))
    assert err.value.parameter == "dust.file"
    assert str(path) in str(err.value)


# --- stage caching --------------------------------------------------------------------------
def test_stages_rerun_only_when_their_inputs_change(backend):
    scene = Scene.load(ROOT / "examples/scenes/thesis-default.toml").with_overrides(
        ["grid.shape=[12,12,12]", "transport.photons=3000"])
    p = Pipeline(backend)
    p.run(scene)
    assert dict(p.executions) == {"density": 1, "transport": 1, "colour": 1}
    p.run(scene.with_overrides(["colour.exposure=2.0"]))  # colour only
    assert dict(p.executions) == {"density": 1, "transport": 1, "colour": 2}
    p.run(scene.with_overrides(["bands.albedo=0.3"]))  # re-trace, same density
    assert dict(p.executions) == {"density": 1, "transport": 2, "colour": 3}
    p.run(scene.with_overrides(["dust.offset=[1.5,0.5,0.5]"]))  # everything
    assert dict(p.executions) == {"density": 2, "transport": 3, "colour": 4}
