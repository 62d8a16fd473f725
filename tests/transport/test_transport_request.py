"""The one place where a scene becomes a run (nebula_rt.transport.request).

- Every [transport] key a run takes reaches the request, from a scene whose every value differs
  from its default (set here, not read back from the code under test).
- A light field through the request is the same bits as trace() called by hand with the
  scene's values: the request changes no result.
- A peel-off image honours transport.error_estimate: "packets" cannot serve an image and is
  refused naming the key, where the peel-off paths used to drop it silently.
(tests/test_layering.py checks that no other module calls trace() or picks the scene's device.)
"""

from __future__ import annotations

import numpy as np
import pytest

from nebula_rt.observe import calibrate
from nebula_rt.errors import SceneError
from nebula_rt.pipeline import compute_light
from nebula_rt.scene import Scene
from nebula_rt.observe.sky import Camera
from nebula_rt.transport import trace
from nebula_rt.transport import TransportRequest
from test_calibrate import sphere_scene

KEYS = {"photons": 3000, "estimator": "collision-filter", "method": "biased", "error_estimate": "batches",
        "max_scatterings": 77, "seed": 12, "batch_size": 500, "time_limit": 30.0}


def _scene(**transport):
    return Scene.from_dict({"grid": {"shape": [8, 8, 8]}, "dust": {"model": "uniform", "density": 1.0, "tau": 2.0},
                            "stars": [{"position": [0.5, 0.5, 0.5], "luminosity": 1.0}],
                            "bands": {"preset": "thesis-rgb"}, "transport": transport})


def test_every_transport_key_reaches_the_request():
    scene = _scene(**KEYS)
    cam = Camera(direction=(0.0, 0.0, 1.0), size=(4, 4))
    r = TransportRequest.from_scene(scene, peel=cam)
    assert {k: getattr(r, k) for k in KEYS} == KEYS
    assert r.tau == 2.0 and r.target_error == 0.0 and r.peel is cam and r.peel_bins is None
    assert [b.name for b in r.bands] == ["R", "G", "B"] and len(r.stars) == 1
    targeted = TransportRequest.from_scene(_scene(photons=9000, target_error=0.05))
    assert (targeted.photons, targeted.target_error) == (9000, 0.05)


def test_the_light_field_is_the_same_bits_as_a_trace_by_hand(backend):
    scene = _scene(photons=4000, seed=3, max_scatterings=50)
    rho = np.ones(scene.grid.shape, np.float32)
    res, J, rel = compute_light(scene, rho, backend)
    t = scene.transport
    by_hand = trace(rho, scene.bands.resolve(), scene.stars, tau=scene.dust.tau, photons=t.photons, seed=t.seed,
                    max_scatterings=t.max_scatterings, estimator=t.estimator, method=t.method,
                    error_estimate=t.error_estimate, batch_size=t.batch_size, backend=backend)
    assert J.tobytes() == by_hand.J.tobytes() and rel.tobytes() == by_hand.rel_error.tobytes()
    assert res.method == by_hand.method == "analog"


def test_a_peel_off_image_refuses_packets_by_name(tmp_path, backend):
    s = sphere_scene(tmp_path, seed=1).with_overrides(['transport.error_estimate="packets"'])
    cam = calibrate.camera_for(s, direction=(0.0, 0.0, 1.0), size=8, extent=2.0)
    with pytest.raises(SceneError, match=r"transport.error_estimate = 'packets': .*a peel-off image"):
        calibrate.peel_off_sky(s, cam, backend)


@pytest.mark.parametrize("method", ["analog", "biased"])
def test_a_peel_off_image_without_the_light_field_is_the_same_bits(backend, method):
    """light_field=False deposits nothing into the voxels and folds no J, and traces all
    batches in one launch; the image, its ring sums per batch and the energy tallies are the
    same bits as the full run's (the deposits draw no random numbers), and J is absent."""
    scene = _scene(photons=6000, seed=5, method=method, max_scatterings=200)
    rho = np.ones(scene.grid.shape, np.float32)
    cam = Camera(direction=(0.0, 0.0, -1.0), size=(12, 12), center=(0.5, 0.5, 0.5))
    bins = (np.arange(144) % 5).reshape(12, 12)
    full = TransportRequest.from_scene(scene, peel=cam, peel_bins=bins).trace(rho, backend)
    image = TransportRequest.from_scene(scene, peel=cam, peel_bins=bins, light_field=False).trace(rho, backend)
    assert full.method == image.method == method
    assert image.J is None and image.rel_error is None and image.device_sums is None and full.J is not None
    assert image.peel_image.tobytes() == full.peel_image.tobytes()
    assert image.peel_error.tobytes() == full.peel_error.tobytes()
    assert image.peel_bin_batches.tobytes() == full.peel_bin_batches.tobytes()
    assert np.array_equal(np.asarray(image.counts), np.asarray(full.counts)) and image.batches == full.batches
    assert image.peel_image.sum() > 0


def test_a_run_without_the_light_field_refuses_what_it_cannot_serve(backend):
    scene = _scene(photons=2000)
    rho = np.ones(scene.grid.shape, np.float32)
    with pytest.raises(SceneError, match="light_field.*peel-off image"):
        TransportRequest.from_scene(scene, light_field=False).trace(rho, backend)
    cam = Camera(direction=(0.0, 0.0, -1.0), size=(4, 4))
    targeted = _scene(photons=4000, target_error=0.05)
    with pytest.raises(SceneError, match="transport.target_error.*error of J"):
        TransportRequest.from_scene(targeted, peel=cam, light_field=False).trace(rho, backend)
    packets = _scene(photons=2000, error_estimate="packets")
    with pytest.raises(SceneError, match="transport.error_estimate"):
        TransportRequest.from_scene(packets, peel=cam, light_field=False).trace(rho, backend)
