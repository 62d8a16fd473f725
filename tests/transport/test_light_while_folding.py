"""The light made as the transport's last fold ends (transport.plan.light_while_folding): the
same bits as the light made after the transport, made only where nothing reads the sums
afterwards, and accounted for in the device memory.

The finishing made after the transport is the reference here: it is itself tested against the
NumPy functions (tests/transport/test_postprocess.py and the physics tests)."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import tuned_backend
from nebula_rt.pipeline import Pipeline
from nebula_rt.scene import Scene
from nebula_rt.transport import finish as postprocess
from nebula_rt.transport.request import TransportRequest
from nebula_rt.transport.run import trace_request

SHAPE = (24, 20, 16)


def thesis(*overrides, shape=SHAPE, photons=30_000) -> Scene:
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    return Scene.load(root / "examples/scenes/thesis-default.toml").with_overrides(
        [f"grid.shape={list(shape)}", f"transport.photons={photons}", *overrides])


def counted(be):
    """``be`` with its kernel launches counted by name."""
    calls: dict = {}
    launch = be.launch

    def count(prog, name, n, *args, **kw):
        calls[name] = calls.get(name, 0) + 1
        return launch(prog, name, n, *args, **kw)

    be.launch = count
    return calls


def both(scene, prepare=None, colour=True):
    """The light field with the light made while folding and after, and the emissivity_cells
    launches of each (the light made after the transport makes the emissivity apart)."""
    out = []
    for while_folding in (True, False):
        be = tuned_backend({})
        if prepare is not None:
            prepare(be)
        be.light_while_folding = while_folding
        calls = counted(be)
        out.append((Pipeline(be).run(scene, colour=colour), calls.get("emissivity_cells", 0)))
    return out


def same_light(a, b):
    for name in ("J", "rel_error", "emissivity", "rgba"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert x.shape == y.shape and np.ascontiguousarray(x).tobytes() == np.ascontiguousarray(y).tobytes(), name
    assert repr(a.exposure) == repr(b.exposure)


@pytest.mark.parametrize("case", ["three bands", "a launch per batch", "one band"])
def test_light_made_while_folding_is_the_light_made_after(case):
    """Same bits for J, its error, the emissivity, rgba and the exposure; the light made in
    the transport (light_cells with the emissivity, no emissivity_cells launch afterwards) or
    after it; J and the emissivity (8 B per cell) counted in the transport's device memory."""
    prepare, scene, nb = None, thesis(), 3
    if case == "a launch per batch":  # 16 launches, each folded: only the last fold makes light
        def prepare(be):
            be.launch_packets = 1000
    elif case == "one band":
        d = thesis().to_dict()
        d["bands"] = {"list": [{"name": "V", "wavelength": 550.0, "extinction": 1.0, "albedo": 0.6, "g": 0.6}]}
        scene, nb = Scene.from_dict(d), 1
    (folding, n_folding), (after, n_after) = both(scene, prepare)
    same_light(folding, after)
    assert (n_folding, n_after) == (0, 1)
    nvox = int(np.prod(SHAPE))
    extra = folding.memory["transport_device_bytes"] - after.memory["transport_device_bytes"]
    assert extra == 8 * nb * nvox


# (the estimate by packets warns that this dense scene's stated errors are low: not checked here)
@pytest.mark.filterwarnings("ignore:transport.error_estimate")
@pytest.mark.parametrize("overrides", [
    ["transport.target_error=0.2"],  # the error checks read the squares after the fold
    ['transport.estimator="collision-filter"'],  # the light comes from the filter
    ['transport.error_estimate="packets"'],
])
def test_no_light_while_folding_where_the_sums_are_read_afterwards(overrides):
    (folding, n_folding), (after, n_after) = both(thesis(*overrides))
    same_light(folding, after)
    assert (n_folding, n_after) == (1, 1)


def test_no_light_while_folding_beyond_the_spare_slot_memory():
    """J and the emissivity must fit the slot memory the run leaves unused: with a budget of
    exactly the run's slots there is none, and the light is made after the transport."""
    from nebula_rt.transport.plan import plan_launches

    scene = thesis()
    nvox = int(np.prod(SHAPE))

    def prepare(be):
        plan = plan_launches(scene.transport.photons, 0, False, SHAPE, 3, be)
        be.slot_memory_budget = 8 * plan.bands_per_launch * nvox * plan.slots

    (folding, n_folding), (after, n_after) = both(scene, prepare)
    same_light(folding, after)
    assert (n_folding, n_after) == (1, 1)


def _request_run(make_light: bool, acc_limit_bits: int = 63, tuning=None):
    scene = thesis()
    be = tuned_backend(tuning or {})
    from nebula_rt.pipeline import Pipeline as P

    rho = P(be).density(scene)
    return trace_request(rho, TransportRequest.from_scene(scene), be, on_device=True, make_light=make_light,
                         _acc_limit_bits=acc_limit_bits), scene


def _finish(res, scene):
    bands = scene.bands.resolve()
    params = np.stack([res.j_scale, res.sigma_scale, [b.albedo for b in bands]], axis=1)
    return postprocess.finish(res.device_sums, params, batches=res.band_batches, collision=False, release=True)


def test_overflowed_batches_retraced_in_halves_give_the_same_light():
    """With a headroom of 2^36 batches overflow and are re-traced in halves after the last
    group's fold: that fold is then not the last, and the light is the one made after."""
    outs = []
    for make_light in (True, False):
        res, scene = _request_run(make_light, acc_limit_bits=36)
        assert res.band_batches.min() > 16  # the overflow happened: batches were split
        assert res.device_sums.light is None
        outs.append(_finish(res, scene))
    for name in ("J", "rel_error", "emissivity"):
        assert getattr(outs[0], name).tobytes() == getattr(outs[1], name).tobytes()


def test_sums_turned_into_light_are_not_read_again():
    """After the light was made while folding, the sums' squares hold the error: reading the
    sums raises, and finishing with other band parameters than the light's raises."""
    res, scene = _request_run(True)
    assert res.device_sums.light is not None
    with pytest.raises(RuntimeError, match="turned into light"):
        res.device_sums.host_sums()
    bands = scene.bands.resolve()
    params = np.stack([res.j_scale * 2.0, res.sigma_scale, [b.albedo for b in bands]], axis=1)
    with pytest.raises(ValueError, match="other band parameters"):
        postprocess.finish(res.device_sums, params, batches=res.band_batches, collision=False, release=True)
    ref, _ = _request_run(False)
    made = _finish(res, scene)
    again = _finish(ref, scene)
    assert made.J.tobytes() == again.J.tobytes() and made.emissivity.tobytes() == again.emissivity.tobytes()


def test_a_fold_past_the_headroom_after_unchecked_adds_traces_again():
    """Unchecked adds (NRT_ACC_RED, as on GPUs) with a headroom of 2^36: the last fold finds
    cells past it, read back before the light's copies were started; the light made is
    dropped and the run traced again with checked adds gives the light made after."""
    outs = []
    for make_light in (True, False):
        res, scene = _request_run(make_light, acc_limit_bits=36, tuning={"NRT_ACC_RED": 1})
        assert res.band_batches.min() > 16  # traced again with checked adds, batches split
        outs.append(_finish(res, scene))
    for name in ("J", "rel_error", "emissivity"):
        assert getattr(outs[0], name).tobytes() == getattr(outs[1], name).tobytes()
