"""How the transport holds its memory: the parameter struct, the batch statistics, the band
groups and the memory plan of large grids.

The transport keeps per cell a float64 sum and a float32 centred sum of squares of the batch
totals (Welford's update) and at most one launch's batch slots, tracing the bands in groups
when one slot of every band would not fit the slot budget. These tests pin what that must
not change (the bits, whatever the grouping) and what it must deliver (a variance that
survives batch totals agreeing to 15 digits; memory within twice the minimum at 512^3 and
1024^3).
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest

from conftest import centre_star
from nebula_rt.backends import kernel_params
from nebula_rt.backends.session import M2_SCALE
from nebula_rt.optics.bands import PRESETS
from nebula_rt.transport import trace


@pytest.mark.parametrize("name", sorted(kernel_params.STRUCTS))
def test_param_struct_layout_matches_the_device(backend, name):
    """The device lays every shared struct out exactly as the host's dtype (every offset and
    the size), so the struct the host uploads (or passes by value) is the struct the kernel
    reads."""
    dt = kernel_params.dtype(name)
    d_in = backend.to_device(np.zeros(dt.itemsize, np.uint8))
    fields = kernel_params.STRUCTS[name]
    d_out = backend.device_zeros(len(fields) + 1, np.uint64)
    backend.launch("sampling.cl", f"{name}_layout", 1, d_in, d_out)
    out = backend.to_host(d_out)
    assert int(out[0]) == dt.itemsize
    assert [int(x) for x in out[1:]] == [dt.fields[name][1] for name, *_ in fields]


def test_param_struct_is_declared_once():
    """The C typedef is generated from the field list (no second declaration to drift)."""
    text = kernel_params.c_struct("nrt_trace_params")
    for name, _t, n, _m in kernel_params.TRACE_PARAMS:
        assert f" {name}{f'[{n}]' if n > 1 else ''};" in text
    with pytest.raises(TypeError, match="missing fields"):
        kernel_params.pack(seed=1)


def test_launch_struct_reaches_the_kernel_by_value(backend):
    """A struct passed by value (the per-launch one) arrives byte for byte, with values that
    need all 64 bits of a u64 field and negative ints."""
    for name in kernel_params.BY_VALUE:
        dt = kernel_params.dtype(name)
        values = {}
        for i, (field, t, n, _m) in enumerate(kernel_params.STRUCTS[name]):
            v = (2**63 + 2**40 + i) if t == "u64" else (-7 - i if t == "i32" else 0.5 + i)
            values[field] = [v] * n if n > 1 else v
        sent = kernel_params.pack(name, **values)
        d_out = backend.device_zeros(dt.itemsize, np.uint8)
        backend.launch("sampling.cl", f"{name}_echo", 1, sent[0], d_out)
        assert backend.to_host(d_out).tobytes() == sent.tobytes()


def _fold(backend, slots: np.ndarray, s1=None, m2=None, k0: int = 0, clear: bool = True, overflow=None):
    """Run the device fold on given slot contents (n_slots, n) -> (sum, centred squares, the
    slots after it)."""
    n_slots, n = slots.shape
    d_acc = backend.to_device(slots.astype(np.uint64).reshape(-1))
    d_s1 = backend.to_device(np.zeros(n) if s1 is None else s1)
    d_m2 = backend.to_device(np.zeros(n, np.float32) if m2 is None else m2)
    d_over = backend.to_device(np.zeros(max(n_slots, 1), np.uint32) if overflow is None
                               else np.asarray(overflow, np.uint32))
    d_seen = backend.device_zeros(1, np.uint32)
    backend.launch("transport.cl", "fold_batches", n, d_acc, d_s1, d_m2, d_over, np.int32(n_slots),
                   np.uint64(n), np.uint64(0), np.int32(k0), d_seen, np.int32(clear),
                   defines={"NRT_TRACK_LENGTH": 1})
    return (backend.to_host(d_s1), backend.to_host(d_m2), backend.to_host(d_acc).reshape(n_slots, n))


def test_the_last_fold_leaves_the_slots_but_clears_an_overflowed_one(backend):
    """The run's last fold (clear 0) gives the statistics of a clearing fold, bit for bit,
    leaves the slots as they were (nothing traces into them again), and still clears a slot
    that overflowed (the host re-traces its batch in halves into a slot)."""
    rng = np.random.default_rng(3)
    slots = rng.integers(0, 2**40, size=(4, 300)).astype(np.uint64)
    slots[:, :7] = 0  # cells no batch reached
    over = [0, 1, 0, 0]
    s1, m2, after = _fold(backend, slots, overflow=over)
    s1_kept, m2_kept, kept = _fold(backend, slots, clear=False, overflow=over)
    assert s1_kept.tobytes() == s1.tobytes() and m2_kept.tobytes() == m2.tobytes()
    assert not after.any()
    assert not kept[1].any()
    assert kept[[0, 2, 3]].tobytes() == slots[[0, 2, 3]].tobytes()
    # the overflowed batch is not folded: the sum is the other three batches'
    assert s1[7] == float(sum(int(slots[g, 7]) for g in (0, 2, 3)))


def test_fold_variance_survives_nearly_equal_batch_totals(backend):
    """Batch totals of 2^45 +- 2^15 (they agree to 9 digits; the squares' spread is 2^-60 of
    the squares, below float64's resolution, so sum x^2 - (sum x)^2 / M would give noise or
    a negative variance): the fold's centred sum of squares matches the exact rational one to
    float32 storage precision, about 2^-24 per batch rounded, sqrt(M) of them (bound 1e-5)."""
    rng = np.random.default_rng(5)
    m, n = 32, 257
    x = (2**45 + rng.integers(-2**15, 2**15, size=(m, n))).astype(np.uint64)
    s1 = np.zeros(n)
    m2 = np.zeros(n, np.float32)
    k = 0
    for g in range(0, m, 8):  # four folds of eight slots, as a run would
        s1, m2, acc = _fold(backend, x[g:g + 8], s1, m2, k)
        k += 8
        assert not acc.any()  # the slots are cleared
    q = m2.astype(np.float64) * M2_SCALE
    for c in range(0, n, 37):
        xs = [int(v) for v in x[:, c]]
        mean = Fraction(sum(xs), m)
        exact = float(sum((Fraction(v) - mean) ** 2 for v in xs))
        assert q[c] == pytest.approx(exact, rel=1e-5)
        assert s1[c] == float(sum(xs))  # exact below 2^53
    naive = (x.astype(np.float64) ** 2).sum(axis=0) - x.astype(np.float64).sum(axis=0) ** 2 / m
    exact0 = float(sum((Fraction(int(v)) - Fraction(sum(int(w) for w in x[:, 0]), m)) ** 2 for v in x[:, 0]))
    assert abs(naive[0] - exact0) > 0.5 * exact0  # what the old sums would have reported


def test_fold_leaves_untouched_cells_alone_and_counts_zeros(backend):
    """A cell no batch reached stays exactly 0; a batch total of 0 after non-zero ones is a
    batch like any other (the variance grows)."""
    slots = np.array([[0, 5], [0, 0], [0, 7]], np.uint64)
    s1, m2, _ = _fold(backend, slots)
    q = m2.astype(np.float64) * M2_SCALE
    assert s1[0] == 0.0 and q[0] == 0.0
    xs = [5, 0, 7]
    mean = sum(xs) / 3
    assert s1[1] == 12.0
    assert q[1] == pytest.approx(sum((v - mean) ** 2 for v in xs), rel=1e-6)


@pytest.fixture(scope="module")
def cloud(backend):
    from nebula_rt.backends.base import MODEL_TURBULENCE

    stars = np.array([[0.5, 0.5, 0.5, 0.05]], np.float32)
    return backend.generate_density((20, 16, 12), MODEL_TURBULENCE, (0.5, 0.5, 0.5), 0.15, 0.0, 1e-4, stars)


@pytest.mark.parametrize("estimator", ["track-length", "collision-filter"])
def test_bands_traced_in_groups_give_the_same_bits(backend, cloud, monkeypatch, estimator):
    """With a slot budget below one slot of every band, the bands are traced one group after
    another (one batch per launch); the tallies, sums, squares and the peel-off image are the
    same bits as with every band and many batches in one launch."""
    from nebula_rt.observe.sky import Camera

    kw = dict(tau=30.0, photons=20_000, seed=9, backend=backend, estimator=estimator,
              peel=Camera(direction=(0.0, 0.0, -1.0), size=(8, 8)))
    together = trace(cloud, PRESETS["thesis-rgb"], centre_star(), **kw)
    nvox = cloud.size
    monkeypatch.setattr(backend, "slot_memory_budget", 8 * nvox)  # one band's slot
    assert backend.launch_plan(nvox, 3, 1250, 16) == (1, 1)
    grouped = trace(cloud, PRESETS["thesis-rgb"], centre_star(), **kw)
    assert grouped.device_bytes < together.device_bytes
    np.testing.assert_array_equal(grouped.counts, together.counts)
    assert grouped.raw_sum.tobytes() == together.raw_sum.tobytes()
    assert grouped.raw_m2.tobytes() == together.raw_m2.tobytes()
    assert grouped.peel_image.tobytes() == together.peel_image.tobytes()
    assert grouped.peel_error.tobytes() == together.peel_error.tobytes()
    assert list(grouped.band_batches) == list(together.band_batches) == [16, 16, 16]


class _LargeGPU:
    """The launch-plan attributes of the CUDA backend on an H200 (132 SMs x 2048 threads x
    32 waves per launch, 1 GiB slot budget), for the memory plan of grids this machine cannot
    hold; the plan and the estimate are pure functions of these."""

    name = "cuda"
    launch_packets = 132 * 2048 * 32
    slot_memory_budget = 1 << 30
    transport_tuning: dict = {}

    from nebula_rt.backends.base import Backend as _B
    from nebula_rt.backends.cuda import CUDABackend as _C

    launch_plan = _B.launch_plan
    region_shifts = _C.region_shifts  # the transport by regions' stopped packets count too


@pytest.mark.parametrize("n", [256, 512, 1024])
@pytest.mark.parametrize("bands", [1, 3])
@pytest.mark.parametrize("photons", [10**7, 10**8, 10**9])
def test_large_grid_memory_within_twice_the_minimum(n, bands, photons):
    """Device peak of the memory estimate (transport, finishing and outputs stages) at 256^3,
    512^3 and 1024^3, the transport by regions' state included: at most 2 x (density + one 64-bit accumulator per band) + 1 GiB (1024^3, one
    band: 25 GiB). The benchmark (benchmarks/bench_large_grids.py) measures the real peak."""
    from nebula_rt.transport import resources
    from nebula_rt.scene import Scene

    band_list = [{"name": f"b{i}", "wavelength": 450.0 + 50 * i, "extinction": 1.0, "albedo": 0.6, "g": 0.6}
                 for i in range(bands)]
    scene = Scene.from_dict({
        "grid": {"shape": [n, n, n]},
        "dust": {"model": "uniform", "density": 1.0, "floor": 0.0, "tau": 2.0},
        "bands": {"list": band_list},
        "transport": {"photons": photons},
    })
    est = resources.estimate(scene, _LargeGPU())
    nvox = n**3
    assert resources.region_bytes(_LargeGPU(), nvox, False) > 0  # in the tracing stage's part
    target = 2 * (4 + 8 * bands) * nvox + (1 << 30)
    assert sum(est.device.values()) <= target, est.device
    if n == 1024 and bands == 1:
        assert sum(est.device.values()) <= 25 * 2**30


def test_auto_batches_grow_with_the_grid():
    """Automatic batches hold up to a packet per 2 voxels on large grids (a fold touches every
    cell, and by regions a batch ends in a dwindling tail of passes), at least 16 batches, and
    never depend on the device."""
    from nebula_rt.transport.plan import batch_count

    assert batch_count(10**8) == math.ceil(10**8 / 2**20)
    assert batch_count(10**8, nvox=128**3) == math.ceil(10**8 / 2**20)  # small grids: as before
    assert batch_count(10**8, nvox=1024**3) == 16
    assert batch_count(10**9, nvox=512**3) == 16  # batches of up to 512^3 / 2 packets
    assert batch_count(10**10, nvox=512**3) == math.ceil(10**10 / (512**3 // 2))
    assert batch_count(10**6, nvox=1024**3) == 16
