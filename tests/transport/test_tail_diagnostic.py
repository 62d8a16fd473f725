"""The heavy-tail diagnostic (nebula_rt.transport.tails, kernels/transport.cl nrt_tail_add).

- The statistics of a histogram against the same statistics of the raw sample (NumPy on the
  values themselves): the variance of the variance, the largest share, the relative error;
  Hill's index against Pareto samples of known index.
- The kernel's histograms against every packet's own contribution, read back independently:
  a run with batches of one packet gives each packet's image total (``peel_bin_batches``);
  binned on the host, they must give the kernel's counts.
- The same bits whatever the batches (a packet's contribution does not depend on them).
- Honesty on the thick slab against the exact answer (tests/oracles/plane_parallel.py): every
  run more than 3 stated sigma off fails a check (analog packets, and the former weighted
  packets with 4 forced flights, at the depths where they miss), and the weighted packets at
  depth 10 and 20 pass; the warning names the band and the image.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from conftest import tuned_backend
from nebula_rt.transport import tails
from nebula_rt.errors import NebulaWarning
from nebula_rt.transport.plan import plan_transport
from nebula_rt.transport import TransportRequest, trace
from slab_scene import peel_bins, seeded_runs, slab


def _binned(x: np.ndarray) -> np.ndarray:
    """Half-octave histogram of positive integers-as-floats, as the kernel bins them."""
    x = np.asarray(x, np.float64)
    x = x[x > 0]
    m = np.floor(np.log2(x)).astype(np.int64)
    return np.bincount(2 * m + (x >= 1.5 * np.exp2(m)), minlength=tails.TAIL_BINS)


# -- the statistics ------------------------------------------------------------------------


@pytest.mark.parametrize("alpha", [0.8, 1.5, 3.0])
def test_statistics_of_a_pareto_sample(alpha):
    rng = np.random.default_rng(7)
    n = 400_000
    x = (rng.pareto(alpha, n) + 1.0) * 2.0**20
    chk = tails.tail_check(_binned(x), n, error_limit=1.0)
    d = x - x.mean()
    vov = float((d**4).sum() / (d**2).sum() ** 2 - 1.0 / n)
    # a sample's value moves by at most a factor 2^(1/4) to its bin's centre
    assert chk.vov == pytest.approx(vov, rel=0.25)
    assert chk.largest_share == pytest.approx(x.max() / x.sum(), rel=0.25)
    assert chk.relative_error == pytest.approx(d.std() / math.sqrt(n) / x.mean(), rel=0.25)
    # Hill's estimate from 200 packets: 1/sqrt(200) = 7 % statistical, plus the binning
    assert chk.tail_index == pytest.approx(alpha, rel=0.2)
    assert chk.contributing == n


def test_checks_flag_a_few_large_contributions():
    n = 100_000
    x = np.full(n, 2.0**30)
    x[:3] = 2.0**50  # three packets carry almost everything
    chk = tails.tail_check(_binned(x), n)
    assert not chk.reliable
    assert chk.vov > tails.VOV_LIMIT and chk.largest_share > tails.LARGEST_SHARE_LIMIT
    steady = tails.tail_check(_binned(np.full(n, 2.0**30)), n)
    assert steady.reliable and steady.vov < 1e-4 and steady.relative_error < 1e-3


def test_no_contribution_fails_and_zeros_count():
    chk = tails.tail_check(np.zeros(tails.TAIL_BINS, np.int64), 1000)
    assert not chk.reliable and "no packet contributed" in chk.reasons[0]
    few = tails.tail_check(_binned(np.full(10, 2.0**10)), 1000)
    assert any("only 10 packets" in r for r in few.reasons)
    with pytest.raises(ValueError, match="contributing packets"):
        tails.tail_check(_binned(np.full(10, 2.0**10)), 5)


def test_fits_cards_and_field_arrays():
    good = tails.tail_check(_binned(np.full(1000, 2.0**10)), 1000)
    bad = tails.tail_check(np.zeros(tails.TAIL_BINS, np.int64), 1000)
    cards = tails.fits_cards([good, bad], ["B", "V"])
    assert cards["TLOK0"][0] is True and cards["TLOK1"][0] is False
    assert "TLVOV1" not in cards and all(len(k) <= 8 for k in cards)
    f = tails.figures([[good, None], [bad, good]])
    assert np.isnan(f["vov"][1]) and f["reliable"].tolist()[0] == 1.0 and f["reliable"][2] == 0.0


# -- the kernel's histograms ---------------------------------------------------------------


@pytest.mark.parametrize("method", ["analog", "biased"])
def test_histogram_is_every_packets_contribution(backend, method):
    """Batches of one packet give each packet's image total: binned on the host they must be
    the kernel's histogram, bin for bin."""
    rho, bands, stars, kappa, cam = slab(3.0, albedo=0.6, g=0.6)
    kw = dict(tau=kappa, photons=600, seed=5, backend=backend, method=method, peel=cam, batch_size=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NebulaWarning)
        r = trace(rho, bands, stars, peel_bins=peel_bins(cam), **kw)
    request = TransportRequest(bands=tuple(bands), stars=tuple(stars), tau=kappa, photons=600, seed=5,
                               method=method, peel=cam, batch_size=1)
    plan = plan_transport(rho, request, backend)
    # image units per fixed-point unit of the score (transport.estimate_light)
    unit = float(r.packet_energy[0]) / (plan.setup.peel_scale * cam.pixel_size**2)
    per_packet = r.peel_bin_batches[:, 0, 0] / unit
    assert per_packet.size == 600
    # (float64 recovers a weighted packet's 128-bit score to 1e-16: a bin could differ only for a
    # score within that of a bin edge)
    assert np.array_equal(r.tail_hist[0, 0], _binned(np.round(per_packet)))
    assert r.tail_image[0].contributing == int(np.count_nonzero(per_packet))


def test_histograms_do_not_depend_on_batches(backend):
    rho, bands, stars, kappa, cam = slab(12.0, albedo=0.6, g=0.6)
    runs = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NebulaWarning)
        for batch in (250, 1000):
            # the stars' windows: J's depth classes are checked under them only
            runs.append(trace(rho, bands, stars, tau=kappa, photons=4000, seed=3, backend=backend, method="biased",
                              peel=cam, batch_size=batch, importance="stars"))
    assert runs[0].batches != runs[1].batches
    assert np.array_equal(runs[0].tail_hist, runs[1].tail_hist)
    assert runs[0].tail_hist.shape == (1, 1 + len(tails.DEPTH_CLASS_NAMES), tails.TAIL_BINS)
    # the image's packets, then J's per depth class: the slab of depth 12 reaches two classes
    assert runs[0].tail_j[0][0] is not None and runs[0].tail_j[0][1] is not None
    assert runs[0].tail_j[0][2] is None and runs[0].tail_j[0][3] is None


# -- honesty on the thick slab -------------------------------------------------------------

SEEDS = 6
PHOTONS = 20_000


def _pulls(backend, tau, albedo, method="auto"):
    return [((v - exact) / se if se > 0 else math.inf, r.tail_image[0])
            for r, v, se, exact, _ in seeded_runs(backend, tau, albedo, 0.6, seeds=SEEDS, photons=PHOTONS,
                                                  method=method)]


@pytest.mark.parametrize("albedo,tau", [(0.3, 20.0), (0.6, 20.0), (0.6, 30.0), (0.9, 30.0)])
def test_analog_misses_are_flagged(backend, albedo, tau):
    runs = _pulls(backend, tau, albedo, method="analog")
    missed = [(p, c) for p, c in runs if abs(p) > 3]
    assert missed, "analog packets are expected to miss here (else the test tests nothing)"
    assert all(not c.reliable for _, c in missed), [(p, c.summary()) for p, c in missed]


@pytest.mark.parametrize("albedo,tau", [(0.3, 30.0), (0.6, 60.0)])
def test_former_weighted_packets_misses_are_flagged(albedo, tau):
    """Stretching limited to the first 4 flights (the former design) misses at depth 30-60;
    every miss must fail a check."""
    runs = _pulls(tuned_backend({"NRT_FORCED_FLIGHTS": 4}), tau, albedo, method="biased")
    missed = [(p, c) for p, c in runs if abs(p) > 3]
    assert missed
    assert all(not c.reliable for _, c in missed), [(p, c.summary()) for p, c in missed]


@pytest.mark.parametrize("albedo", [0.3, 0.6, 0.9])
@pytest.mark.parametrize("tau", [10.0, 20.0])
def test_weighted_packets_pass_where_they_are_right(backend, albedo, tau):
    runs = _pulls(backend, tau, albedo)
    assert all(abs(p) < 4 for p, _ in runs)
    assert all(c.reliable for _, c in runs), [c.summary() for _, c in runs]


def test_warning_names_band_and_image(backend):
    rho, bands, stars, kappa, cam = slab(30.0, albedo=0.6, g=0.6)
    with pytest.warns(NebulaWarning, match=r"band V, the peel-off image: .*Trace more packets, or use "
                                           r"transport.method = \"biased\""):
        trace(rho, bands, stars, tau=kappa, photons=5000, seed=1, backend=backend, method="analog", peel=cam)
