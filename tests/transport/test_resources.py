"""Resource-exhausting inputs are refused before any allocation, with the estimate and the
limit; large photon counts cost O(1) bookkeeping.

The estimate is checked against what the run really holds: the transport session reports its
device buffers (``TransportResult.device_bytes``) and the finishing its outputs; the estimate
must cover them (it is an upper bound) without overstating them much.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from conftest import centre_star, one_band
from nebula_rt.transport import resources
from nebula_rt.cli import main
from nebula_rt.errors import CancelledError, ResourceError, SceneError
from nebula_rt.pipeline import Pipeline
from nebula_rt.scene import Scene
from nebula_rt.transport import trace


def scene(*overrides):
    return Scene.default().with_overrides(["transport.photons=4000", *overrides])


@pytest.mark.parametrize("overrides,parameter", [
    (["grid.shape=[2000,2000,2000]"], "grid.shape"),
    (["grid.shape=[3,3,2147483647]"], "grid.shape"),  # more than any device holds, thin
    (["grid.shape=[4096,4096,512]"], "grid.shape"),
])
def test_huge_grids_refused_with_the_estimate(backend, overrides, parameter):
    s = scene(*overrides)
    t0 = time.perf_counter()
    with pytest.raises(ResourceError) as err:
        Pipeline(backend).run(s)
    assert time.perf_counter() - t0 < 5.0  # refused, not attempted
    e = err.value
    assert e.parameter == parameter and "GiB" in str(e)
    # the message has the estimate and the device's limit
    total, max_alloc = backend.memory_limits()
    assert f"{total / 2**30:.2f} GiB" in str(e) or f"{max_alloc / 2**30:.2f} GiB" in str(e) or "available" in str(e)


def test_estimate_covers_what_a_run_holds(backend):
    """The device estimate is at least the transport's real buffers and the finishing's outputs,
    and not more than twice their sum."""
    for over in ([], ["transport.estimator=\"collision-filter\""], ["transport.target_error=0.3"]):
        s = scene("grid.shape=[24,20,16]", *over)
        est = resources.estimate(s, backend)
        light = Pipeline(backend).run(s)
        held = light.memory["device_peak_bytes"]
        assert held <= est.device_bytes <= 2 * held + (1 << 20), (over, held, est.device)


def test_filter_radius_beyond_the_box_costs_the_grid_not_the_radius(backend):
    """A collision-filter radius beyond the box (10 box units; the scene allows up to sqrt 3): the kernel is cut at the grid's extent, which
    changes nothing (a same-size convolution never reaches further) and bounds the memory."""
    from nebula_rt.transport import filtering

    shape = (12, 10, 8)
    k_big = filtering.cubic_kernel(shape, 10.0)
    assert k_big.shape == tuple(2 * n - 1 for n in shape)
    rng = np.random.default_rng(3)
    field = rng.random(shape)
    # reference: the uncut kernel of radius 2 box units (lattice half-width 2n >= n - 1)
    h = 1.0 / np.asarray(shape)
    half = np.floor(2.0 / h).astype(int)
    axes = [np.arange(-m, m + 1) * hh for m, hh in zip(half, h)]
    dx, dy, dz = np.meshgrid(*axes, indexing="ij")
    d2 = (dx * dx + dy * dy + dz * dz) / 4.0
    k_ref = np.where(d2 < 1.0, (1.0 - d2) ** 3, 0.0)
    k_ref /= k_ref.sum()
    cut, _ = filtering.normalised_convolution(field, filtering.cubic_kernel(shape, 2.0))
    ref, _ = filtering.normalised_convolution(field, k_ref)
    np.testing.assert_allclose(cut, ref, rtol=1e-10)
    # the largest radius allowed (the box's diagonal) still reaches beyond the grid; wider ones
    # are refused by the declaration
    with pytest.raises(SceneError, match="filter_radius"):
        scene("grid.shape=[16,16,16]", 'transport.estimator="collision-filter"', "transport.filter_radius=10")
    s = scene("grid.shape=[16,16,16]", 'transport.estimator="collision-filter"', "transport.filter_radius=1.7")
    est = resources.estimate(s, backend)
    assert est.host_bytes < 64 * 2**20
    light = Pipeline(backend).run(s, colour=False)
    assert np.all(np.isfinite(light.J))


def test_photons_2_53_cost_o1_bookkeeping(backend):
    """2^53 packets per band: the plan is computed on demand, the run starts at once and is
    cancelled after its first launch."""
    rho = np.ones((8, 8, 8), np.float32)
    seen = []
    t0 = time.perf_counter()
    with pytest.raises(CancelledError):
        trace(rho, one_band(), centre_star(), tau=1.0, photons=2**53, backend=backend,
              progress=lambda done, total: seen.append(done), cancel=lambda: len(seen) > 0)
    assert time.perf_counter() - t0 < 10.0
    assert 0 < seen[0] < 2**53


def test_cli_refuses_huge_inputs_before_tracing(tmp_path, capsys):
    from conftest import TEST_DEVICE

    pytest.importorskip("vtkmodules")  # a render needs the io extra (absent on a bare GPU machine)

    s = tmp_path / "s.toml"
    s.write_text("[grid]\nshape = [16, 16, 16]\n[transport]\nphotons = 4000\n")
    out = tmp_path / "o.vti"
    for over, name in ((["grid.shape=[2000,2000,2000]"], "grid.shape"),):
        args = ["render", str(s), "-o", str(out), "-q", "--device", TEST_DEVICE]
        for o in over:
            args += ["--set", o]
        assert main(args) == 2
        err = capsys.readouterr().err
        assert name in err and "GiB" in err and "nothing written" in err
    # the sky image of compare: its size is bounded
    assert main(["compare", str(s), "--png", str(tmp_path / "c.png"), "--size", "100000",
                 "--set", 'bands.preset="spectral-8"', "--device", TEST_DEVICE]) == 2
    assert "--size" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == [s]


def test_compare_refuses_a_scene_without_b_and_v(tmp_path, capsys):
    """Delta(B-V) needs bands on both sides of the B and V passbands: a single-band scene is
    refused (it used to report 0.0 in every annulus)."""
    from conftest import TEST_DEVICE

    s = tmp_path / "s.toml"
    s.write_text('[grid]\nshape = [16, 16, 16]\n[transport]\nphotons = 4000\n[bands]\npreset = "thesis-rgb"\n'
                 "[[bands.list]]\nname = \"V\"\nwavelength = 550.0\nextinction = 1.0\nalbedo = 0.6\ng = 0.6\n")
    assert main(["compare", str(s), "--png", str(tmp_path / "c.png"), "--device", TEST_DEVICE]) == 2
    err = capsys.readouterr().err
    assert "bands" in err and "B-V" in err
    assert not (tmp_path / "c.png").exists()
