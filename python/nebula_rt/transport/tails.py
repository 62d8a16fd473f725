"""Heavy-tail diagnostic: is a Monte Carlo error bar to be trusted?

A stated error (batch means, :mod:`nebula_rt.transport`) is the spread of the batch totals, and a
batch total is a sum of packets' contributions. Where those contributions have a heavy tail --
a few packets in a million carrying most of the light, as in light that crossed optical depth
30, or weighted packets whose weights ran away -- the batches agree with each other only
because none of them sampled the tail, and the error is far too small (issue: T(mu=1) behind a
slab of depth 30, 100 sigma off with a stated 10 %). No statistic of the batches can see a tail
they never sampled. The distribution of the packets' own contributions can: its largest
values and how fast their frequency falls say whether the sum has converged (MCNP's
statistical checks; Pederson, Forster & Booth 1997, the variance of the variance).

The kernel (kernels/transport.cl) keeps, per band, a histogram of every packet's total
contribution -- one emitted packet with all its split copies, to the peel-off image and, with
weighted packets, to J in each class of optical depth from the stars -- in half-octave bins
of its fixed-point score (an integer count per bin: the same bits on every device and number
of ranks). From it :func:`tail_check` takes, for the mean contribution x̄ of N packets:

- ``vov``: the variance of the variance, sum (x - x̄)^4 / (sum (x - x̄)^2)^2 - 1 / N. It is
  the squared relative error of the stated variance; MCNP asks for less than 0.1.
- ``largest_share``: the largest single packet's share of the total.
- ``tail_index``: the Hill estimate alpha of the tail P(X > x) ~ x^-alpha, from the largest
  packets (at most :data:`TAIL_PACKETS`); reported, not checked (see the limits below).
- ``relative_error``: the error of the mean from the packets themselves.

Within a half-octave bin a contribution is taken at the bin's geometric centre: the moments
are within a few per cent, which a diagnostic of factors needs no better.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np

from ..backends.kernel_params import CONSTANT

#: half-octave bins of a histogram (kernels/transport.cl, nrt_tail_add)
TAIL_BINS = CONSTANT["NRT_TAIL_BINS"]
#: classes of optical depth (of the band, from the nearest star along the least-depth path:
#: nebula_rt.transport.importance) whose J has its own histogram with weighted packets: [0, 5), [5, 15),
#: [15, 30), 30 and beyond
DEPTH_CLASS_EDGES = (5.0, 15.0, 30.0)
DEPTH_CLASS_NAMES = ("depth 0-5", "depth 5-15", "depth 15-30", "depth 30+")
#: largest packets the tail's slope is estimated from (MCNP: 201)
TAIL_PACKETS = 200
#: fewest contributing packets for a tail estimate at all
MIN_CONTRIBUTING = 40
#: The checks' limits, MCNP's (X-5 Monte Carlo Team 2003, vol. I, sect. 2.6.9): a result fails
#: beyond any of them, or with fewer than MIN_CONTRIBUTING packets. The relative error from
#: the packets themselves must be below 0.05 for a peel-off image (a next-event estimate, MCNP's
#: point detector: above it its stated error is not reliable) and 0.1 for J; the variance of the
#: variance below 0.1; and no packet may carry more than a tenth of the total. Tried on the thick
#: slab against its exact answer (tests/transport/test_tail_diagnostic.py, docs/physics.md): albedo
#: 0.3/0.6/0.9, g 0.6, depth 10-60, 8 seeds x 2e4 packets of the weighted packets, analog
#: packets and the former weighted packets (4 forced flights): every run more than 3 stated
#: sigma off the exact value failed a check (35 of 35 analog, 18 of 18 former); of the 96
#: weighted-packet runs, all right, the 40 at depth 30 and 60 that state 5-20 % failed (trace
#: more packets), none at depth 10 or 20. VOV and the largest share alone (without the error)
#: let a former run 6 sigma off pass (VOV 0.041, share 0.024).
IMAGE_ERROR_LIMIT = 0.05
J_ERROR_LIMIT = 0.1
VOV_LIMIT = 0.1
LARGEST_SHARE_LIMIT = 0.1
# The tail index is not a check, a figure: below 2 it is a tail of infinite variance for an
# unbounded distribution, but weight windows bound a packet's contributions, and on their
# truncated tail the largest 200 packets read 0.2-1.2 at depth 30-60 where the results are
# right (the same runs above).


def bin_edges() -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper edges of the histogram's bins (score units): bin 2m holds [2^m, 1.5 2^m),
    bin 2m + 1 holds [1.5 2^m, 2^(m+1))."""
    b = np.arange(TAIL_BINS)
    base = np.ldexp(1.0, b // 2)
    lo = np.where(b % 2 == 0, base, 1.5 * base)
    hi = np.where(b % 2 == 0, 1.5 * base, 2.0 * base)
    return lo, hi


@dataclasses.dataclass(frozen=True)
class TailCheck:
    """The heavy-tail diagnostic of one tally (an image or a depth class of J, one band).

    Attributes
    ----------
    packets : int
        Packets traced (N, zero contributions included).
    contributing : int
        Packets with a nonzero contribution.
    vov : float
        Variance of the variance (NaN with fewer than 2 contributing packets).
    largest_share : float
        The largest packet's share of the sum (NaN with none contributing).
    tail_index : float
        Hill estimate of alpha in P(X > x) ~ x^-alpha over the largest packets (NaN with fewer
        than :data:`MIN_CONTRIBUTING` contributing).
    relative_error : float
        Relative standard error of the mean from the packets' own spread.
    reasons : tuple of str
        Why the stated error is not to be trusted; empty when every check passed.
    """

    packets: int
    contributing: int
    vov: float
    largest_share: float
    tail_index: float
    relative_error: float
    reasons: tuple = ()

    @property
    def reliable(self) -> bool:
        """Every check passed (or nothing was traced at all)."""
        return not self.reasons

    def summary(self) -> str:
        """One line: the figures and what failed."""
        figures = (f"{self.contributing:,} of {self.packets:,} packets contribute, VOV {self.vov:.3g}, "
                   f"largest packet {100 * self.largest_share:.3g} % of the total, tail index "
                   f"{self.tail_index:.3g}")
        return figures + ("" if self.reliable else ": " + "; ".join(self.reasons))


def tail_check(counts: Sequence[int], packets: int, error_limit: float = IMAGE_ERROR_LIMIT) -> TailCheck:
    """The diagnostic of one histogram of packet contributions.

    Parameters
    ----------
    counts : array of int, (TAIL_BINS,)
        Packets per half-octave bin of their contribution (the kernel's histogram).
    packets : int
        Packets traced, those that contributed nothing included.
    error_limit : float
        The largest relative error (from the packets) whose statement is trusted:
        :data:`IMAGE_ERROR_LIMIT` or :data:`J_ERROR_LIMIT`.
    """
    c = np.asarray(counts, np.float64)
    if c.shape != (TAIL_BINS,):
        raise ValueError(f"a tail histogram has {TAIL_BINS} bins, not {c.shape}")
    n = int(packets)
    k = int(round(c.sum()))
    if k > n:
        raise ValueError(f"{k} contributing packets of {n}")
    if k == 0:
        nan = float("nan")
        return TailCheck(n, 0, nan, nan, nan, 1.0, ("no packet contributed",) if n else ())
    lo, hi = bin_edges()
    top = int(np.nonzero(c)[0][-1])
    # contributions relative to the largest bin's centre (no overflow in the fourth power)
    x = np.sqrt(lo * hi) / math.sqrt(lo[top] * hi[top])
    total = float(np.dot(c, x))
    mean = total / n
    dev = x - mean
    s2 = float(np.dot(c, dev**2)) + (n - k) * mean**2
    s4 = float(np.dot(c, dev**4)) + (n - k) * mean**4
    vov = s4 / s2**2 - 1.0 / n if s2 > 0 else 0.0
    rel = math.sqrt(s2 / (n * (n - 1))) / mean if n > 1 else 1.0
    share = float(x[top]) / total
    alpha = _hill(c, lo, hi, k)
    reasons = []
    if k < MIN_CONTRIBUTING:
        reasons.append(f"only {k} packets contribute (a tail needs {MIN_CONTRIBUTING} at least)")
    if rel > error_limit:
        reasons.append(f"the error from the packets is {100 * rel:.2g} % (above {100 * error_limit:g} %, where an "
                       "error estimate is itself unreliable)")
    if vov > VOV_LIMIT:
        reasons.append(f"the variance of the variance is {vov:.2g} (above {VOV_LIMIT})")
    if share > LARGEST_SHARE_LIMIT:
        reasons.append(f"one packet carries {100 * share:.2g} % of the total (above {100 * LARGEST_SHARE_LIMIT:g} %)")
    return TailCheck(n, k, vov, share, alpha, rel, tuple(reasons))


def _hill(c: np.ndarray, lo: np.ndarray, hi: np.ndarray, k: int) -> float:
    """Hill's estimate of the tail index from binned data: the threshold u is the lower edge of
    the bin where the largest TAIL_PACKETS (at most half the contributing packets) begin, and
    alpha = n_u / sum over the packets from u on of ln(x / u), each packet at its bin's centre
    (in log2 units: no overflow for any score)."""
    if k < MIN_CONTRIBUTING:
        return float("nan")
    want = min(TAIL_PACKETS, k // 2)
    above = np.cumsum(c[::-1])[::-1]  # packets in this bin and above
    first = int(np.nonzero(above >= want)[0][-1])  # the highest bin with `want` packets from it on
    centre = 0.5 * (np.log2(lo[first:]) + np.log2(hi[first:]))
    logs = math.log(2.0) * float(np.dot(c[first:], centre - math.log2(lo[first])))
    return float(above[first]) / logs if logs > 0 else float("inf")


def check_histograms(hist: np.ndarray, packets: Sequence[int], limits: Sequence[float], present=None) -> list:
    """:func:`tail_check` of every histogram of a run: ``hist`` (n_bands, n_tallies, TAIL_BINS),
    ``packets`` per band, ``limits`` the error limit per tally; returns [band][tally] TailCheck,
    or None where ``present`` (bool, (n_bands, n_tallies)) says the tally has no cells (a depth
    class the grid does not reach)."""
    return [[tail_check(hist[b, t], int(packets[b]), limits[t]) if present is None or present[b][t] else None
             for t in range(hist.shape[1])] for b in range(hist.shape[0])]


def class_cells(depth: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Cells of the depth map in each depth class, per band (int64, (n_bands, classes));
    ``edges`` as :func:`class_edges` gives them."""
    d = np.asarray(depth, np.float64).ravel()
    cls = np.stack([np.searchsorted(np.asarray(e, np.float64), d, side="right") for e in edges])
    return np.stack([np.bincount(c, minlength=len(DEPTH_CLASS_NAMES)) for c in cls])


def class_edges(extinction: Sequence[float]) -> np.ndarray:
    """The depth classes' edges in the depth map's units (the reference band's optical depth,
    :func:`nebula_rt.transport.importance.depth_map`) per band: the map's depth times the band's
    extinction factor is the band's own (float32, (n_bands, len(DEPTH_CLASS_EDGES)))."""
    ext = np.asarray(extinction, np.float64).reshape(-1, 1)
    with np.errstate(divide="ignore"):
        return np.where(ext > 0, np.asarray(DEPTH_CLASS_EDGES)[None, :] / ext, np.inf).astype(np.float32)


def failures(checks, band_names: Sequence[str], tally_names: Sequence[str]) -> list[str]:
    """One line per (band, tally) whose check failed: "band B, tally: figures: reasons"."""
    return [f"band {band_names[b]}, {tally_names[t]}: {chk.summary()}" for b, row in enumerate(checks or ())
            for t, chk in enumerate(row) if chk is not None and not chk.reliable]


def figures(checks) -> dict[str, np.ndarray]:
    """The checks [band][tally] as flat float64 arrays (band-major; NaN for a tally with nothing
    to check): ``vov``, ``largest_share``, ``tail_index``, ``reliable`` (1 or 0)."""
    flat = [c for row in checks for c in row]
    nan = float("nan")

    def take(f):
        return np.array([nan if c is None else f(c) for c in flat], np.float64)

    return {"vov": take(lambda c: c.vov), "largest_share": take(lambda c: c.largest_share),
            "tail_index": take(lambda c: c.tail_index), "reliable": take(lambda c: float(c.reliable))}


def fits_cards(checks, band_names: Sequence[str]) -> dict:
    """FITS header cards of an image's checks, one per band ([band] TailCheck): TLOKn (the
    checks passed), TLVOVn, TLSHRn, TLIDXn (figures; left out where not finite), n the band's
    index."""
    cards = {}
    for b, c in enumerate(checks):
        name = band_names[b]
        cards[f"TLOK{b}"] = (bool(c.reliable), f"{name}: error passed heavy-tail checks")
        for key, value, what in (("TLVOV", c.vov, "variance of the variance"),
                                 ("TLSHR", c.largest_share, "largest packet's share"),
                                 ("TLIDX", c.tail_index, "Hill index of the largest packets")):
            if math.isfinite(value):
                cards[f"{key}{b}"] = (float(value), f"{name}: {what}")
    return cards
