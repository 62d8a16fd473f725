"""Transport by regions: packets stopped at region faces and resumed give the same bits.

On large grids the GPU traces each launch in passes (kernels/transport.cl, NRT_REGIONS): a
packet's walk stops where it steps into another cube of 2^shift voxels, its state is stored,
and the stopped packets, sorted by (cell, region), are resumed by the next pass, so that the
packets in flight deposit into one region's cells. Stopping and resuming must change nothing:
the state holds everything the walk needs (its random stream included) and integer deposits
add alike in any order. These tests hold every sum, centred square, tally and peel-off pixel
to the bit against tracing each packet in one go, with regions small enough that packets stop
tens of times, and check the pass machinery itself (the counting sort, launches split for the
state memory, the tail pass, the overflow re-trace).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import tuned_backend as _backend

from nebula_rt.observe import sky
from nebula_rt.backends.session import DeviceTransport
from nebula_rt.optics.bands import Band
from nebula_rt.scene import Star
from nebula_rt.transport import trace


def _bands():
    return [Band(name="B", wavelength=450.0, extinction=1.3, albedo=0.6, g=0.5),
            Band(name="R", wavelength=650.0, extinction=0.8, albedo=0.9, g=-0.3)]


def _stars():
    # one star on a region corner (the centre), one inside a region
    return [Star(position=(0.5, 0.5, 0.5), luminosity=1.0, temperature=None, bump_radius=0.0),
            Star(position=(0.25, 0.625, 0.4), luminosity=0.6, temperature=None, bump_radius=0.0)]


@pytest.fixture(scope="module")
def cloud():
    # a grid that is no multiple of the regions (partial regions at the far faces)
    rng = np.random.default_rng(17)
    return (rng.random((21, 16, 13)) ** 3).astype(np.float32)


def _run(cloud, tuning, estimator="track-length", peel=True, launch=3 * 2 * 1500, **kw):
    be = _backend(tuning)
    be.launch_packets = launch
    camera = sky.Camera(direction=(0.3, -0.2, -1.0), size=(12, 10)) if peel else None
    return trace(cloud, _bands(), _stars(), tau=kw.pop("tau", 12.0), photons=kw.pop("photons", 9000),
                 batch_size=1500, seed=21, estimator=estimator, backend=be, peel=camera, **kw)


def _same(a, b):
    assert a.raw_sum.tobytes() == b.raw_sum.tobytes()
    assert a.raw_m2.tobytes() == b.raw_m2.tobytes()
    np.testing.assert_array_equal(a.counts, b.counts)
    if a.peel_image is not None:
        np.testing.assert_array_equal(a.peel_image, b.peel_image)


@pytest.mark.parametrize("estimator", ["track-length", "collision-filter"])
def test_regions_give_the_same_bits(cloud, estimator):
    """Regions of 2, 4 and 8 voxels (a packet stops up to hundreds of times), with and without
    the sorted emission order and the work-group sums: every sum, square, count and peel-off
    pixel equals the one-go trace's, for two bands, two stars and several batches per launch."""
    plain = _run(cloud, {"NRT_REGIONS": 0}, estimator)
    assert plain.counts[:, 0].tolist() == [9000, 9000]
    for tuning in ({"NRT_REGIONS": 1}, {"NRT_REGIONS": 2}, {"NRT_REGIONS": 3, "NRT_SORTED": 1},
                   {"NRT_REGIONS": 2, "NRT_GROUP_TALLY": 1, "NRT_PREFETCH": 0}):
        _same(_run(cloud, dict(tuning, region_tail=0), estimator), plain)


FULL = {"NRT_REGIONS": 2, "region_tail": 0, "region_state_bytes": 2 * 10**6}
TAIL = dict(FULL, region_tail=500)
SPLIT = dict(FULL, region_state_bytes=300 * 96)


def test_passes_stop_and_resume_packets(cloud, monkeypatch):
    """The passes do what they are for: with regions of 4 voxels every launch takes many passes
    (a packet of this cloud crosses tens of region faces), the tail pass cuts them short, and
    with room for only 1024 packets in flight new packets take the state slots of those that
    ended, pass by pass, so that every pass is full while new packets are left; the bits
    stay."""
    from nebula_rt.backends import kernel_params
    from nebula_rt.backends.regions import REGION_KEY_BYTES

    plain = _run(cloud, {"NRT_REGIONS": 0}, peel=False)
    seen = {}
    real_init = DeviceTransport.__init__

    def spy(self, *a, **k):
        real_init(self, *a, **k)
        self.region_log = []
        seen["session"] = self

    monkeypatch.setattr(DeviceTransport, "__init__", spy)
    per = kernel_params.dtype("nrt_packet").itemsize + REGION_KEY_BYTES
    for tuning in (FULL, TAIL, SPLIT):
        res = _run(cloud, tuning, peel=False)
        _same(res, plain)
        s = seen["session"]
        assert s.region_shift == 2
        # room for a whole launch (9000 packets), or the least (1024)
        assert s.region_capacity == (1024 if tuning is SPLIT else FULL["region_state_bytes"] // per)
        seen[id(tuning)] = s.region_passes
        log = s.region_log
        launches = 2  # 9000 packets x 2 bands in launches of 3 batches x 2 bands x 1500
        assert sum(e[4] for e in log) == launches * 9000  # every packet started once
        if tuning is SPLIT:
            # chunks of 512 photons x 2 bands: 9 per launch; a pass with new packets is full
            # but where its chunk ran out
            fresh = [e for e in log if e[4] > 0]
            assert len(fresh) > 2 * 9 * launches
            assert all(e[0] <= 1024 for e in log)
            assert sum(e[0] < 1024 for e in fresh) <= 9 * launches
    full, tail, split = (seen[id(t)] for t in (FULL, TAIL, SPLIT))
    assert full >= 10 * 2  # packets stop again and again
    assert tail < full
    assert split > full  # fewer packets in flight: more passes


def test_backend_default_uses_regions_from_its_grid_size(monkeypatch):
    """Without a tuning, the backend's own rule decides (PoCL: regions of 32 voxels from 128^3
    on; GPUs: 64 from 256^3, 128 from 1024^3): a 128^3 cloud on the test device is traced as
    its rule says, with the one-go trace's bits, and a 64^3 one on PoCL without regions."""
    from nebula_rt.backends.regions import region_shift_for

    be = _backend({})
    rule = dict(be.region_shifts)
    expect = 0
    for least, shift in sorted(rule.items()):
        expect = shift if 128**3 >= least else expect
    assert region_shift_for(be, 128**3, False) == expect
    assert region_shift_for(be, 128**3, True) == 0  # weighted packets: no region path
    if "Portable" in be.device_name:
        assert expect == 5 and region_shift_for(be, 64**3, False) == 0
    rng = np.random.default_rng(2)
    cloud = (0.5 + rng.random((128, 128, 128))).astype(np.float32)
    kw = dict(tau=4.0, photons=20_000, batch_size=5_000, seed=5)
    auto = trace(cloud, _bands()[:1], _stars(), backend=be, **kw)
    plain = trace(cloud, _bands()[:1], _stars(), backend=_backend({"NRT_REGIONS": 0}), **kw)
    _same(auto, plain)


def test_regions_overflow_retrace_gives_the_same_bits(cloud):
    """Headroom lowered to 2^36 so that the hottest cells overflow (with unchecked adds too):
    the re-trace in halves runs through the passes as well, and the regions' run ends with the
    bits of the one-go runs, with and without the lowered headroom."""
    normal = _run(cloud, {"NRT_REGIONS": 0}, peel=False)
    for acc_red in (0, 1):
        plain = _run(cloud, {"NRT_REGIONS": 0, "NRT_ACC_RED": acc_red}, peel=False, _acc_limit_bits=36)
        regions = _run(cloud, {"NRT_REGIONS": 2, "region_tail": 0, "NRT_ACC_RED": acc_red}, peel=False,
                       _acc_limit_bits=36)
        assert regions.batches > normal.batches  # the overflow happened and was split
        _same(regions, plain)
        np.testing.assert_array_equal(regions.raw_sum, normal.raw_sum)


@pytest.mark.parametrize("shift", [0, 6])
def test_region_sort_counts_and_orders_every_stopped_packet(backend, shift):
    """The counting sort on its own: keys of random bins (and ended packets' empty keys) come
    out grouped by bin, each key exactly once, with more bins than the work group holds in
    local memory and with fewer; with ``shift`` 6 the bin is the key's high half without its
    6 lowest bits (as the emission order sorts by the leading bits of its direction bins)."""
    rng = np.random.default_rng(3)
    for n_bins in (7, 900, 5000, 9000):  # (NRT_LOCAL_BINS is 8192)
        n = 20011
        bins = rng.integers(0, n_bins, n).astype(np.uint64)
        high = (bins << np.uint64(shift)) | rng.integers(0, 1 << shift, n).astype(np.uint64)
        keys = (high << np.uint64(32)) | np.arange(n, dtype=np.uint64)
        keys[rng.random(n) < 0.3] = np.uint64(2**64 - 1)
        d_keys = backend.to_device(keys)
        d_counts = backend.device_zeros(n_bins, np.uint32)
        defines = {"NRT_TRACK_LENGTH": 1, "NRT_REGIONS": 1}
        d_out = backend.device_zeros(n, np.uint64)
        backend.launch_trace("transport.cl", "counting_sort_pass", n, d_keys, np.uint64(n), d_counts,
                             np.int32(n_bins), np.int32(0), d_out, np.int32(shift), defines=defines)
        counts = backend.to_host(d_counts)
        live = keys[keys != np.uint64(2**64 - 1)]
        live_bins = (live >> np.uint64(32 + shift)).astype(np.int64)
        np.testing.assert_array_equal(counts, np.bincount(live_bins, minlength=n_bins))
        first = np.zeros(n_bins, np.uint32)
        first[1:] = np.cumsum(counts[:-1])
        d_cursor = backend.to_device(first)
        backend.launch_trace("transport.cl", "counting_sort_pass", n, d_keys, np.uint64(n), d_cursor,
                             np.int32(n_bins), np.int32(1), d_out, np.int32(shift), defines=defines)
        out = backend.to_host(d_out)[:live.size]
        assert sorted(out.tolist()) == sorted(live.tolist())
        assert np.all(np.diff((out >> np.uint64(32 + shift)).astype(np.int64)) >= 0)


def test_regions_grow_where_their_bins_would_pass_the_local_ones(cloud):
    """The sort counts its bins in local memory up to LOCAL_SORT_BINS (the kernel's
    NRT_LOCAL_BINS): a session whose cells and regions would need more bins takes regions twice
    as large until they fit (unless the tuning sets the size), and traces the same bits."""
    import re
    from pathlib import Path

    from nebula_rt.backends import session as session_mod

    source = (Path(__file__).resolve().parents[2] / "kernels" / "transport.cl").read_text()
    assert int(re.search(r"#define NRT_LOCAL_BINS (\d+)", source).group(1)) == session_mod.LOCAL_SORT_BINS
    shifts = []
    real = DeviceTransport._setup_regions

    def spy(self, tuning):
        shifts.append((self.region_shift, self._region_bins(self.region_shift), self._region_bins(self.region_shift - 1)))
        return real(self, tuning)

    kw = dict(tau=25.0, photons=8000, batch_size=1000, seed=4, peel=None)  # 8 slots of 2 bands
    plain = trace(cloud, _bands(), _stars(), backend=_backend({"NRT_REGIONS": 0}), **kw)
    be = _backend({})
    be.region_shifts = ((1, 1),)  # regions of 2 voxels on any grid: far more bins than fit
    try:
        DeviceTransport._setup_regions = spy
        grown = trace(cloud, _bands(), _stars(), backend=be, **kw)
    finally:
        DeviceTransport._setup_regions = real
    assert shifts and all(s > 1 and bins <= session_mod.LOCAL_SORT_BINS < finer for s, bins, finer in shifts)
    _same(grown, plain)


def test_bin_counts_become_first_positions_on_the_device(backend):
    """scan_bins (one work group): the exclusive prefix sum of the counts in place, for fewer
    bins than work items, a few per item and many per item, and the count of every bin but the
    last after them (the packets a region pass stopped, which the host reads)."""
    rng = np.random.default_rng(5)
    for n_bins in (1, 7, 513, 4097, 70001):
        counts = rng.integers(0, 3000, n_bins).astype(np.uint32)
        d = backend.to_device(np.concatenate([counts, np.array([12345], np.uint32)]))
        backend.launch_trace("transport.cl", "scan_bins", 1, d, np.int32(n_bins),
                             defines={"NRT_TRACK_LENGTH": 1, "NRT_REGIONS": 1})
        got = backend.to_host(d)
        first = np.concatenate([[0], np.cumsum(counts[:-1], dtype=np.uint64)]).astype(np.uint32)
        np.testing.assert_array_equal(got[:n_bins], first)
        assert int(got[n_bins]) == int(counts[:-1].sum(dtype=np.uint64))


def test_a_group_traced_in_several_launches_streams_across_them(cloud, monkeypatch):
    """Launches of about 300 packets (a group of 3 batches of 1500 then takes about 30): the
    packets in flight at the end of one launch go on in the next launch of the group, so each
    group ends in one tail pass, not one per launch, with the one-go trace's bits. A time limit
    that stops the run between two launches of a group first finishes the packets in flight:
    every packet emitted is absorbed, escaped or terminated."""
    from nebula_rt.transport import run as transport_mod

    plain = _run(cloud, {"NRT_REGIONS": 0}, peel=False)
    sessions, drains = [], []
    real_init, real_run = DeviceTransport.__init__, DeviceTransport.run_group

    def spy(self, *a, **k):
        real_init(self, *a, **k)
        self.region_log = []
        sessions.append(self)

    def run_group(self, *a, **k):
        drains.append(k.get("drain", True))
        return real_run(self, *a, **k)

    monkeypatch.setattr(DeviceTransport, "__init__", spy)
    monkeypatch.setattr(DeviceTransport, "run_group", run_group)
    monkeypatch.setattr(transport_mod, "LAUNCH_SECONDS", 1e-6)  # the smallest launches: 1 packet per band

    def small(tuning, **kw):
        be = _backend(tuning)
        be.launch_packets, be.first_launch_packets = 3 * 2 * 1500, 600
        return trace(cloud, _bands(), _stars(), tau=12.0, photons=kw.pop("photons", 9000),
                     batch_size=kw.pop("batch_size", 1500), seed=21, backend=be, **kw)

    res = small({"NRT_REGIONS": 2, "region_tail": 50})
    _same(res, plain)
    log = sessions[-1].region_log
    assert drains.count(False) >= 20 and drains.count(True) == 2  # many launches, 2 groups
    assert sum(e[3] == 31 for e in log) == 2  # one tail pass per group
    assert sum(e[4] for e in log) == 2 * 9000

    # stopped by the time limit after the first launch of a group of batches of 150 (its
    # first 300 packets per band: two whole batches are kept)
    drains.clear()
    cut = small({"NRT_REGIONS": 2, "region_tail": 50}, photons=90_000, time_limit=1e-9, batch_size=150)
    counts = np.asarray(cut.counts, dtype=np.int64)
    assert counts[0, 0] == 300 and drains[:2] == [False, True]
    np.testing.assert_array_equal(counts[:, 0], counts[:, 1] + counts[:, 2] + counts[:, 3])
    assert drains[-1] is True and sessions[-1]._stream is None
