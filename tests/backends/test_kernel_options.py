"""The transport kernel's performance options change where sums are formed, never their value.

``TRANSPORT_TUNING`` (kernels/transport.cl): unchecked adds checked by the fold, the next
voxel's density loaded ahead, work-group sums of the tallies and of the star voxels. Integer
addition is associative, so every combination must give the same bits as every other; the
unchecked adds must detect an overflow as surely as checked ones (and then re-run checked);
and the density made on the device must be used there without a second upload.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from conftest import TEST_BACKEND, centre_star, one_band
from conftest import tuned_backend as _backend

from nebula_rt.observe import sky
from nebula_rt.backends.base import TRANSPORT_TUNING, transport_defines
from nebula_rt.optics.bands import Band
from nebula_rt.scene import Star
from nebula_rt.transport.plan import FIXED_POINT_BITS
from nebula_rt.transport.estimate import _no_wrap
from nebula_rt.transport import trace

OPTIONS = tuple(TRANSPORT_TUNING)


def _bands():
    return [Band(name="B", wavelength=450.0, extinction=1.3, albedo=0.6, g=0.5),
            Band(name="R", wavelength=650.0, extinction=0.8, albedo=0.7, g=-0.3)]


def _stars():
    # two stars, one on a voxel face: the work-group sums cover both star voxels
    return [Star(position=(0.5, 0.5, 0.5), luminosity=1.0, temperature=None, bump_radius=0.0),
            Star(position=(0.25, 0.625, 0.4), luminosity=0.6, temperature=None, bump_radius=0.0)]


@pytest.fixture(scope="module")
def cloud():
    rng = np.random.default_rng(11)
    return (rng.random((20, 16, 12)) ** 3).astype(np.float32)


@pytest.mark.parametrize("estimator", ["track-length", "collision-filter"])
def test_every_option_combination_gives_the_same_bits(cloud, estimator):
    """All 2^4 combinations: identical batch sums, centred squares and packet counts (with a
    batch plan of several launches and a peel-off image, which keeps checked adds); the images
    agree to the rounding of their float weights."""
    camera = sky.Camera(direction=(0.0, 0.0, -1.0), size=(12, 10))
    results = []
    for combo in itertools.product((0, 1), repeat=len(OPTIONS)):
        be = _backend(dict(zip(OPTIONS, combo)))
        be.launch_packets = 3 * 2 * 1500  # several launches of 3 batches
        results.append(trace(cloud, _bands(), _stars(), tau=25.0, photons=9000, batch_size=1500,
                             seed=4, estimator=estimator, backend=be, peel=camera))
    ref = results[0]
    assert ref.counts[:, 0].tolist() == [9000, 9000]
    for res in results[1:]:
        np.testing.assert_array_equal(res.raw_sum, ref.raw_sum)
        np.testing.assert_array_equal(res.raw_m2, ref.raw_m2)
        np.testing.assert_array_equal(res.counts, ref.counts)
        # Peel-off weights (phase x exp(-tau) to the edge) and pixel positions are float
        # expressions. With contraction of a * b + c off (CUDA --fmad=false, PoCL honouring
        # FP_CONTRACT OFF) every build rounds them alike and the images match bit for bit.
        # NVIDIA's OpenCL compiler contracts them differently in different builds (54 of 240
        # pixels differed): a deposit may round to the next unit or land in the neighbouring
        # pixel, which conserves the image's total.
        if TEST_BACKEND == "cuda" or "Portable" in be.device_name:
            np.testing.assert_array_equal(res.peel_image, ref.peel_image)
        else:
            np.testing.assert_allclose(res.peel_image.sum(axis=(1, 2)), ref.peel_image.sum(axis=(1, 2)), rtol=1e-6)


def test_unchecked_adds_detect_overflow_and_rerun_checked(cloud):
    """Headroom lowered to 2^36 (16 crossings of the smallest voxel): the hot cells pass it.
    With unchecked adds the fold sees it and the run is repeated with checked adds; the result
    equals a run checked from the start, and both equal the run with full headroom."""
    kw = dict(tau=25.0, photons=12_000, seed=6)
    fast = trace(cloud, one_band(), centre_star(), _acc_limit_bits=36, backend=_backend({"NRT_ACC_RED": 1}), **kw)
    checked = trace(cloud, one_band(), centre_star(), _acc_limit_bits=36, backend=_backend({"NRT_ACC_RED": 0}), **kw)
    normal = trace(cloud, one_band(), centre_star(), backend=_backend({}), **kw)
    assert checked.batches > normal.batches  # the overflow happened and was split
    for res in (fast, checked):
        np.testing.assert_array_equal(res.raw_sum, normal.raw_sum)
        np.testing.assert_array_equal(res.counts, normal.counts)
    assert fast.batches == checked.batches


def test_unchecked_adds_only_within_the_no_wrap_bound():
    """The bound: packets per batch x (max_scatterings + 1) flights x one voxel diagonal of
    track must stay below 2^64; beyond it the kernel is built with checked adds."""
    scale = 2.0**FIXED_POINT_BITS * 128
    assert _no_wrap(2**20, 1000, "track-length", scale, (128, 128, 128))  # the defaults: 2^62.8
    assert not _no_wrap(2**22, 1000, "track-length", scale, (128, 128, 128))  # 2^64.8
    assert not _no_wrap(2**20, 10_000, "track-length", scale, (128, 128, 128))
    assert _no_wrap(2**40, 1000, "collision-filter", scale, (128, 128, 128))  # 1 per interaction
    # a flat box: the diagonal is measured in units of the smallest edge
    assert not _no_wrap(2**20, 1000, "track-length", 2.0**32 * 1024, (1024, 2, 2))
    from nebula_rt.backends.base import TransportSetup

    setup = TransportSetup(density=np.zeros((4, 4, 4), np.float32), sigma_scale=np.ones(1, np.float32),
                           albedo=np.ones(1, np.float32), g=np.zeros(1, np.float32),
                           stars=np.zeros((1, 3), np.float32), star_cdf=np.ones((1, 1), np.float32),
                           estimator="track-length", max_scatterings=10, seed=1, track_scale=1.0)
    assert "NRT_ACC_RED" not in transport_defines(setup)  # unchecked_adds defaults to False
    import dataclasses

    assert transport_defines(dataclasses.replace(setup, unchecked_adds=True))["NRT_ACC_RED"] == 1
    assert "NRT_ACC_RED" not in transport_defines(dataclasses.replace(setup, unchecked_adds=True),
                                                  {"NRT_ACC_RED": 0})


def test_device_density_is_used_without_a_second_upload(backend):
    """generate_density leaves its result on the device and hands back a read-only host copy;
    the transport uses the device copy for exactly that array, uploads any other array, and
    both give the same bits."""
    from nebula_rt import density as dens
    from nebula_rt.scene import Scene

    scene = Scene.from_dict({"grid": {"shape": [12, 10, 8]}, "dust": {"model": "turbulence", "tau": 30.0},
                             "transport": {"photons": 4000}})
    rho = dens.generate_density(scene, backend)
    assert not rho.flags.writeable
    with pytest.raises(ValueError):
        rho[0, 0, 0] = 1.0
    assert backend.resident_density(rho) is not None
    copy = np.array(rho)  # writable: not the resident array
    assert backend.resident_density(copy) is None
    kw = dict(tau=30.0, photons=4000, seed=3, backend=backend)
    a = trace(rho, one_band(), centre_star(), **kw)
    b = trace(copy, one_band(), centre_star(), **kw)
    np.testing.assert_array_equal(a.raw_sum, b.raw_sum)
    # the resident copy survives a transport (its session does not free it)
    c = trace(rho, one_band(), centre_star(), **kw)
    np.testing.assert_array_equal(c.raw_sum, a.raw_sum)


def test_groups_split_into_short_launches_give_the_same_bits(cloud, monkeypatch):
    """A group of batches traced in many short launches (as a cancel-responsive run does on a
    slow device) gives the same sums, counts and image as one launch, options off and on. Short
    launches have global sizes with no small factor, for which an OpenCL runtime may choose
    work groups of fewer than 4 items: the work-group tallies must still reach global memory
    (they were lost before, and the escape counts came out short)."""
    from nebula_rt.transport import run as transport

    camera = sky.Camera(direction=(0.0, 0.0, -1.0), size=(12, 10))
    # every option off, and every option on (the work-group tallies the fix is about)
    for combo in ((0,) * len(OPTIONS), (1,) * len(OPTIONS)):
        runs = []
        for split in (False, True):
            be = _backend(dict(zip(OPTIONS, combo)))
            be.launch_packets = 3 * 2 * 1500
            if split:
                be.first_launch_packets = 997 * 2  # 997 packets per band: prime
                monkeypatch.setattr(transport, "LAUNCH_SECONDS", 1e-4)
            runs.append(trace(cloud, _bands(), _stars(), tau=25.0, photons=9000, batch_size=1500,
                              seed=4, backend=be, peel=camera))
            monkeypatch.setattr(transport, "LAUNCH_SECONDS", 0.25)
        one, many = runs
        c = many.counts
        assert np.all(c[:, 0] == c[:, 1] + c[:, 2] + c[:, 3]), (combo, c)
        np.testing.assert_array_equal(many.counts, one.counts)
        np.testing.assert_array_equal(many.raw_sum, one.raw_sum)
        np.testing.assert_array_equal(many.raw_m2, one.raw_m2)
        if TEST_BACKEND == "cuda" or "Portable" in be.device_name:
            np.testing.assert_array_equal(many.peel_image, one.peel_image)


@pytest.mark.parametrize("error_estimate", ["batches", "packets"])
def test_star_blocks_of_every_size_give_the_same_bits(cloud, error_estimate):
    """The work-group sums of the voxels around each star (NRT_HOT_HALF: blocks of 1, 3^3, 5^3
    and 7^3 voxels) against no work-group sums: the same batch sums, squares (per-packet visit
    squares too) and counts. The stars test the blocks' edges: one in a corner (its block
    mostly outside the grid), one on a face, two whose blocks overlap, and a fifth star beyond
    the NRT_HOT_STARS that get a block."""
    stars = [Star(position=(0.01, 0.02, 0.99), luminosity=1.0, temperature=None, bump_radius=0.0),
             Star(position=(0.5, 0.5, 0.5), luminosity=0.8, temperature=None, bump_radius=0.0),
             Star(position=(0.55, 0.5, 0.45), luminosity=0.6, temperature=None, bump_radius=0.0),
             Star(position=(0.25, 0.625, 0.0), luminosity=0.5, temperature=None, bump_radius=0.0),
             Star(position=(0.8, 0.3, 0.6), luminosity=0.7, temperature=None, bump_radius=0.0)]
    runs = []
    for options in ({"NRT_GROUP_TALLY": 0}, {"NRT_GROUP_TALLY": 1, "NRT_HOT_HALF": 0},
                    {"NRT_GROUP_TALLY": 1, "NRT_HOT_HALF": 1}, {"NRT_GROUP_TALLY": 1, "NRT_HOT_HALF": 2},
                    {"NRT_GROUP_TALLY": 1}):  # (the default: 7^3)
        be = _backend(options)
        batches = {"batch_size": 1500} if error_estimate == "batches" else {}
        runs.append(trace(cloud, _bands(), stars, tau=25.0, photons=6000, seed=9, backend=be,
                          error_estimate=error_estimate, **batches))
    ref = runs[0]
    assert ref.counts[:, 0].tolist() == [6000, 6000]
    for res in runs[1:]:
        np.testing.assert_array_equal(res.counts, ref.counts)
        np.testing.assert_array_equal(res.raw_sum, ref.raw_sum)
        np.testing.assert_array_equal(res.raw_m2, ref.raw_m2)


@pytest.mark.parametrize("estimator", ["track-length", "collision-filter"])
def test_sorted_packet_order_gives_the_same_bits(cloud, estimator):
    """NRT_SORTED (packets traced in the order of cell, star and first direction, a counting
    sort on the device) against the plain order: the same sums, squares, counts and image, with
    two stars, two bands and several batches per launch."""
    camera = sky.Camera(direction=(0.0, 0.0, -1.0), size=(12, 10))
    runs = []
    for tuning in ({"NRT_SORTED": 0}, {"NRT_SORTED": 1}, {"NRT_SORTED": 1, "NRT_SORT_BITS": 10}):
        be = _backend(tuning)
        be.launch_packets = 3 * 2 * 1500
        runs.append(trace(cloud, _bands(), _stars(), tau=25.0, photons=9000, batch_size=1500, seed=8,
                          estimator=estimator, backend=be, peel=camera))
    plain = runs[0]
    for ordered in runs[1:]:
        assert ordered.raw_sum.tobytes() == plain.raw_sum.tobytes()
        assert ordered.raw_m2.tobytes() == plain.raw_m2.tobytes()
        np.testing.assert_array_equal(ordered.counts, plain.counts)
        if TEST_BACKEND == "cuda" or "Portable" in _backend({}).device_name:
            np.testing.assert_array_equal(ordered.peel_image, plain.peel_image)


@pytest.mark.parametrize("sort_bits", [8, 3])
def test_sorted_emission_order_is_every_packet_once_by_cell_star_and_direction(cloud, monkeypatch, sort_bits):
    """The emission order (NRT_SORTED, a counting sort on the device) of launches of two bands,
    two stars and three batch slots (several launches): every work item exactly once, in ascending bins of cell,
    star and leading direction bits (all 2 x NRT_SORT_BITS of them where the bins allow, as
    with 3 bits), the directions spread over many bins."""
    from nebula_rt.backends.regions import EMISSION_MAX_BINS
    from nebula_rt.backends.session import DeviceTransport

    orders = []
    real = DeviceTransport._emission_order

    def spy(self, keys, photon_start, count, first_batch, band0, n_lb, scratch=None):
        out = real(self, keys, photon_start, count, first_batch, band0, n_lb, scratch)
        orders.append((self.backend.to_host(out)[:count * n_lb].copy(), count * n_lb, self.emit_shift,
                       self.n_emit_bins))
        return out

    monkeypatch.setattr(DeviceTransport, "_emission_order", spy)
    be = _backend({"NRT_SORTED": 1, "NRT_SORT_BITS": sort_bits})
    be.launch_packets = 3 * 2 * 1500
    trace(cloud, _bands(), _stars(), tau=25.0, photons=9000, batch_size=1500, seed=8, backend=be)
    assert orders
    for keys, items, shift, n_bins in orders:
        assert n_bins - 1 <= EMISSION_MAX_BINS
        if sort_bits == 3:
            assert shift == 0  # 2 bands x 3 slots x 2 stars x 64 direction bins fit
        np.testing.assert_array_equal(np.sort(keys & np.uint64(0xFFFFFFFF)), np.arange(items, dtype=np.uint64))
        bins = (keys >> np.uint64(32 + shift)).astype(np.int64)
        assert np.all(np.diff(bins) >= 0) and bins.max() < n_bins - 1
        assert np.unique(bins).size > min(n_bins - 1, items) // 8


def test_register_cap_of_the_analog_transport_kernel_only():
    """The register cap (NVIDIA: CUDA's --maxrregcount, NVIDIA OpenCL's -cl-nv-maxrregcount) is
    the backend's per region mode, or the tuning's ``max_registers`` (0: none); the weighted
    packets' kernel and every other program keep the compiler's choice, and a backend without
    caps (PoCL) never sets one. Building with a cap changes no bit: the tests of the transport
    run on the capped builds on NVIDIA GPUs (benchmarks/run_gpu.sh)."""
    from nebula_rt.backends.base import NVIDIA_TRACE_REGISTERS

    be = _backend({})
    assert be.register_cap(be.transport_program, {"NRT_REGIONS": 1}) == (
        NVIDIA_TRACE_REGISTERS[True] if be.trace_registers else 0)
    be.trace_registers = NVIDIA_TRACE_REGISTERS
    assert be.register_cap(be.transport_program, {"NRT_TRACK_LENGTH": 1}) == NVIDIA_TRACE_REGISTERS[False]
    assert be.register_cap(be.transport_program, {"NRT_REGIONS": 1}) == NVIDIA_TRACE_REGISTERS[True]
    assert be.register_cap(be.transport_program, {"NRT_BIASED": 1}) == 0
    assert be.register_cap("density.cl", {}) == 0
    be.transport_tuning = dict(be.transport_tuning, max_registers=96)
    assert be.register_cap(be.transport_program, {"NRT_REGIONS": 1}) == 96
    be.transport_tuning["max_registers"] = 0
    assert be.register_cap(be.transport_program, {}) == 0


@pytest.mark.parametrize("direction", [(0.0, 0.0, -1.0), (1.0, 0.0, 0.0), (0.0, -1.0, 0.0)])
@pytest.mark.parametrize("method", ["analog", "biased"])
def test_peel_columns_give_the_marched_image(cloud, direction, method):
    """An observer along a grid axis: the peel-offs read each voxel's density column
    (``peel_columns``, summed in float64 on the host) instead of marching to the edge. The
    optical depths differ by float32 rounding only, so the deposits' stochastic rounding moves
    a few units at most: per pixel within 1e-5 of the image's largest pixel plus 1e-6
    relative, the totals within 1e-6; J, the counts and the packets' paths are untouched. A
    direction off the axes (checked: no columns) keeps the march."""
    camera = sky.Camera(direction=direction, size=(12, 10))
    kw = dict(tau=25.0, photons=6000, seed=9, peel=camera, method=method)
    col = trace(cloud, _bands(), _stars(), backend=_backend({}), **kw)
    march = trace(cloud, _bands(), _stars(), backend=_backend({"peel_columns": 0}), **kw)
    np.testing.assert_array_equal(col.raw_sum, march.raw_sum)
    np.testing.assert_array_equal(np.asarray(col.counts), np.asarray(march.counts))
    assert march.peel_image.sum() > 0
    np.testing.assert_allclose(col.peel_image.sum(axis=(1, 2)), march.peel_image.sum(axis=(1, 2)), rtol=1e-6)
    np.testing.assert_allclose(col.peel_image, march.peel_image, rtol=1e-6, atol=1e-5 * march.peel_image.max())
    from nebula_rt.backends.transport_setup import transport_defines
    from nebula_rt.transport.plan import plan_transport
    from nebula_rt.transport.request import TransportRequest

    req = TransportRequest(bands=tuple(_bands()), stars=tuple(_stars()), tau=25.0, photons=6000, peel=camera)
    setup = plan_transport(cloud, req, _backend({})).setup  # the columns ran
    axis = int(np.flatnonzero(direction)[0])
    assert setup.peel_axis == (axis, direction[axis] < 0)
    assert transport_defines(setup)["NRT_PEEL_AXIS"] == axis
    assert plan_transport(cloud, req, _backend({"peel_columns": 0})).setup.peel_columns is None


def test_an_oblique_observer_keeps_the_march():
    from nebula_rt.transport.line_of_sight import peel_axis

    assert peel_axis((0.0, 0.0, 1.0)) == (2, True) and peel_axis((-0.0, -2.0, 0.0)) == (1, False)
    assert peel_axis((0.0, 0.6, 0.8)) is None and peel_axis((1e-9, 0.0, 1.0)) is None
