"""Binned deposits (backends/binned.py, kernels/binned.cl): delta tracking with the track
lengths binned by block and added in local memory.

- Against analytic solutions and exact bookkeeping: the physics module's own checks, run on a
  backend tuned to binned deposits (a pure absorber's shell averages, the sphere's escape
  without and after one scattering, exact energy conservation, the absorption two ways, the
  overflow recovered).
- Against the walk (kernels/transport.cl), an independent estimate of the same J: per voxel,
  (J_binned - J_walk) / sqrt(err_binned^2 + err_walk^2) over the lit voxels holds the 1- and
  2-sigma intervals at their rates (the stated errors are honest).
- Exactness: every piece added at once with global atomics gives the same sums bit for bit as
  the binned drawing, whatever the sub-launches, chunks and where the counts are kept; the same
  seed the same bits, batches and launches grouped any way.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import test_transport_physics as physics
from conftest import centre_star, one_band, tuned_backend
from nebula_rt.backends import binned as binned_module
from nebula_rt.scene import Star
from nebula_rt.transport import trace
from test_transport_physics import cloud, sphere  # noqa: F401 (module fixtures)


@pytest.fixture(scope="module")
def binned():
    return tuned_backend({"binned_deposits": 1})


def two_stars():
    return [Star(position=(0.5, 0.5, 0.5), luminosity=1.0, temperature=None, bump_radius=0.0),
            Star(position=(0.23, 0.71, 0.4), luminosity=0.5, temperature=None, bump_radius=0.0)]


def run(cloud, backend, **kw):
    args = dict(tau=60.0, photons=20_000, seed=4)
    args.update(kw)
    return trace(cloud, physics.thesis_bands(), two_stars(), backend=backend, **args)


# --- the physics module's checks, binned -------------------------------------------------------
def test_point_source_pure_absorber(binned):
    physics.test_point_source_shell_averages(binned, 3.0)


@pytest.mark.filterwarnings("ignore::nebula_rt.errors.NebulaWarning")  # terminates packets on purpose
def test_sphere_escape_p0_and_p1(binned, sphere):
    physics.test_sphere_escape_p0_and_p1(binned, sphere)


@pytest.mark.filterwarnings("ignore::nebula_rt.errors.NebulaWarning")
def test_energy_conservation_is_exact(binned, cloud):
    physics.test_energy_conservation_is_exact(binned, cloud)


def test_path_length_absorption_matches_counted(binned, cloud):
    physics.test_path_length_absorption_matches_counted(binned, cloud)


def test_overflow_is_detected_and_recovered(binned, cloud):
    physics.test_overflow_is_detected_and_recovered(binned, cloud)


# --- against the walk ----------------------------------------------------------------------------
@pytest.mark.parametrize("majorant", [16, 4])
def test_j_agrees_with_the_walk_within_the_stated_errors(majorant, backend, cloud):
    """Two stars, three bands, a turbulent cloud: the binned J and the walk's differ per lit
    voxel by z = dJ / sqrt(e_b^2 + e_w^2). With two batch-means errors of 16 batches each, z is
    Student's t with about 30 degrees of freedom (Welch-Satterthwaite for equal variances):
    |z| < 1 and < 2 at rates 0.675 and 0.945. The bounds are the binomial 5-sigma of the voxels
    counted as if independent, widened by 0.03 for their correlation through shared packets
    (three seed pairs gave 0.671-0.683 and 0.944-0.950). Delta tracking's majorants on the
    blocks (16^3) and on cells of 4^3 voxels."""
    kw = dict(photons=60_000, batch_size=60_000 // 16)
    binned = tuned_backend({"binned_deposits": 1, "binned_majorant": majorant})
    a, b = run(cloud, binned, seed=11, **kw), run(cloud, backend, seed=12, **kw)
    assert np.all(a.counts[:, 0] == b.counts[:, 0])
    ea, eb = a.J * a.rel_error, b.J * b.rel_error
    lit = (a.J > 0) & (b.J > 0) & np.isfinite(a.rel_error) & np.isfinite(b.rel_error)
    lit &= (a.rel_error < 0.3) & (b.rel_error < 0.3)  # (batch means are near normal there)
    z = (a.J - b.J)[lit] / np.sqrt(ea[lit] ** 2 + eb[lit] ** 2)
    n = z.size
    assert n > 3000
    for k, rate in ((1.0, 0.675), (2.0, 0.945)):
        got = float(np.mean(np.abs(z) < k))
        slack = 5 * math.sqrt(rate * (1 - rate) / n) + 0.03
        assert abs(got - rate) < slack, (k, got, rate, n)
    # and the packets' fates agree (binomial, 5 sigma)
    for t in (1, 2):
        pa, pb = a.counts[:, t] / a.counts[:, 0], b.counts[:, t] / b.counts[:, 0]
        s = np.sqrt(pa * (1 - pa) / a.counts[:, 0] + pb * (1 - pb) / b.counts[:, 0])
        assert np.all(np.abs(pa - pb) < 5 * s), (t, pa, pb)


# --- exactness ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def reference(binned, cloud):
    return run(cloud, binned)


@pytest.mark.parametrize("case", ["direct adds", "global counts", "small sub-launches", "small chunks",
                                  "several packets per work item", "batches smaller than a group"])
def test_the_same_sums_every_way(case, reference, cloud, monkeypatch):
    """Every piece added at once with global 64-bit atomics (tuning 2), the counts per block
    in global memory, sub-launches of 700 packets (several batches each, and batches split
    between two), chunks of 64 records, work items tracing several packets each, and batches
    of 40 packets (a work group's packets then lie in more than the two slots it bins; the
    pieces of the others are added at once): the same sums and tallies as the binned drawing,
    bit for bit."""
    tuning = {"binned_deposits": 2 if case == "direct adds" else 1}
    kw = {}
    if case == "global counts":
        monkeypatch.setattr(binned_module, "LOCAL_BLOCKS", 0)
    elif case == "small sub-launches":
        monkeypatch.setattr(binned_module, "MAX_PACKETS", 700)
    elif case == "small chunks":
        monkeypatch.setattr(binned_module, "CHUNK", 64)
    elif case == "several packets per work item":
        monkeypatch.setattr(binned_module, "GROUP_BYTES", 1)
    elif case == "batches smaller than a group":
        kw = dict(batch_size=40)
    other = run(cloud, tuned_backend(tuning), **kw)
    np.testing.assert_array_equal(other.raw_sum, reference.raw_sum)
    assert np.array_equal(other.counts, reference.counts)


def test_same_seed_same_bits_any_grouping(reference, binned, cloud):
    """The same seed gives the same bits; batches of another size and a launch per batch give
    the same totals; another seed other bits."""
    again = run(cloud, binned)
    assert again.J.tobytes() == reference.J.tobytes() and again.rel_error.tobytes() == reference.rel_error.tobytes()
    other_batches = run(cloud, binned, batch_size=3_000)
    np.testing.assert_array_equal(other_batches.raw_sum, reference.raw_sum)
    small = tuned_backend({"binned_deposits": 1})
    small.launch_packets = 2_500
    np.testing.assert_array_equal(run(cloud, small).raw_sum, reference.raw_sum)
    assert run(cloud, binned, seed=5).J.tobytes() != reference.J.tobytes()


def test_grid_not_a_multiple_of_the_block(binned):
    """A grid of 20 x 17 x 33 voxels (partial blocks on every axis), a star near a corner:
    energy conserved exactly, the track-length absorption within 5 sigma of the count over
    independent runs."""
    rng = np.random.default_rng(3)
    rho = rng.lognormal(0.0, 1.0, (20, 17, 33)).astype(np.float32)
    star = [Star(position=(0.1, 0.93, 0.2), luminosity=1.0, temperature=None, bump_radius=0.0)]
    band = one_band(albedo=0.5, g=0.3)
    diffs = []
    for seed in range(1, 6):
        res = trace(rho, band, star, tau=4.0, photons=30_000, seed=seed, backend=binned)
        c = res.counts[0]
        assert c[1] + c[2] + c[3] == c[0] == 30_000
        sigma = 4.0 * rho.astype(np.float64)
        est = 0.5 * np.sum(sigma * 4 * np.pi * res.J[0] / rho.size)
        diffs.append(est - res.energy[0, 1])
    diffs = np.array(diffs)
    assert abs(diffs.mean()) < 5 * diffs.std(ddof=1) / math.sqrt(len(diffs)) + 1e-9, diffs


@pytest.mark.parametrize("what, kw", [
    ("estimator 'collision-filter'", dict(estimator="collision-filter")),
    ("weighted packets", dict(method="biased")),
    ("the error estimate by packets", dict(error_estimate="packets")),
])
def test_what_binned_deposits_cannot_trace_is_refused(binned, what, kw):
    rho = np.ones((16, 16, 16), np.float32)
    with pytest.raises(ValueError, match=f"binned_deposits = 1 cannot trace this run: .*{what}"):
        trace(rho, one_band(), centre_star(), tau=1.0, photons=2_000, backend=binned, **kw)


def test_auto_error_estimate_takes_batches():
    """"auto" takes the estimate by packets where the walk goes by regions with many packets in
    flight (here forced on a small, thin grid); binned deposits have no regions, so it takes
    batches, which they trace."""
    rho = np.ones((16, 16, 16), np.float32)
    res = {}
    for tuning in ({}, {"binned_deposits": 1}):
        be = tuned_backend(dict(tuning, NRT_REGIONS=3, region_state_bytes=1 << 28))
        res[len(tuning)] = trace(rho, one_band(), centre_star(), tau=0.5, photons=20_000, seed=2, backend=be)
    assert res[0].error_estimate == "packets"  # the walk by regions
    assert res[1].error_estimate == "batches" and res[1].batches > 1


def test_memory_estimate_covers_the_binned_buffers():
    """The resource estimate counts the binned deposits' buffers (records, counts, offsets),
    which the run reports among its device bytes: it covers what the run holds and is not
    more than twice it (the test of the estimate for the walk, tests/transport/test_resources.py)."""
    from nebula_rt.pipeline import Pipeline
    from nebula_rt.scene import Scene
    from nebula_rt.transport import resources

    be = tuned_backend({"binned_deposits": 1})
    s = Scene.default().with_overrides(["transport.photons=4000", "grid.shape=[24,20,16]"])
    est = resources.estimate(s, be)
    assert est.device["binned deposits"] > 0 and est.device["region passes"] == 0
    held = Pipeline(be).run(s).memory["device_peak_bytes"]
    assert held <= est.device_bytes <= 2 * held + (1 << 20), (held, est.device)
    # (the run counts them: it holds more than the walk's run of the same scene)
    assert held > Pipeline(tuned_backend({})).run(s).memory["device_peak_bytes"]


@pytest.mark.filterwarnings("ignore::nebula_rt.errors.NebulaWarning")  # terminates packets on purpose
def test_majorant_cells_of_4_voxels_keep_the_physics(cloud):
    """Majorant cells of 4^3 voxels (the tuning binned_majorant): energy conserved exactly and
    the track-length absorption within 5 sigma of the count (the physics module's checks), and
    a majorant that does not divide the block is refused."""
    be = tuned_backend({"binned_deposits": 1, "binned_majorant": 4})
    physics.test_energy_conservation_is_exact(be, cloud)
    physics.test_path_length_absorption_matches_counted(be, cloud)
    with pytest.raises(ValueError, match="binned_majorant = 5: a divisor of 16"):
        run(cloud, tuned_backend({"binned_deposits": 1, "binned_majorant": 5}))
