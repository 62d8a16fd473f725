"""Numerical stability at the extremes: every case has a known answer or a clear error.

Tolerances are derived, never tuned:
- packet fractions P: binomial sigma = sqrt(P (1 - P) / N) (sqrt(2) times that for the
  difference of two independent runs); assertions at 5 sigma;
- intensities and track lengths: standard error of the mean over independent seeds, or over
  packets where the host reproduces every packet's direction from the kernel's own random
  stream; 5 sigma plus the stated discretisation/quadrature error of the reference;
- float32 effects: counted in ulps (u = 2^-24) of the operations involved.

Geometry used throughout: the unit box, uniform density 1, a star at the centre. Along a
direction d the distance to the boundary is s(d) = 0.5 / max_i |d_i| (and the same along -d), so
direction averages of functions of s are integrals over the six faces (`direction_average`).
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from scipy import integrate

from conftest import centre_star, one_band, voxel_centres
from nebula_rt.backends import probes
from nebula_rt.errors import AccumulatorOverflowError, NebulaError, SceneError
from nebula_rt.transport.plan import FIXED_POINT_BITS, batch_plan
from nebula_rt.transport.result import exact_packet_energy
from nebula_rt.transport import trace
from test_transport_physics import shell_means, voxel_average_point_source

U32 = 2.0**-24  # float32 unit roundoff (ulp of 1 / 2)
G_LIMIT = float(np.float32(1) - np.float32(1e-4))  # the kernel's clamp of |g|


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------
def direction_average(f, order=64):
    """Isotropic average of f(s), s the distance from the box centre to the boundary.

    One face (z = 1) by symmetry: a point (x, y) of it is at distance s = |(x-.5, y-.5, .5)| and
    subtends dOmega = 0.5 / s^3 dx dy; 6 faces / 4 pi. Gauss-Legendre of ``order``^2 nodes on a
    smooth integrand (error far below 1e-9, checked by f = 1)."""
    x, w = np.polynomial.legendre.leggauss(order)
    x, w = 0.5 * (x + 1), 0.5 * w
    X, Y = np.meshgrid(x, x, indexing="ij")
    W = np.outer(w, w)
    s = np.sqrt((X - 0.5) ** 2 + (Y - 0.5) ** 2 + 0.25)
    return float(6.0 / (4 * np.pi) * np.sum(W * f(s) * 0.5 / s**3))


def rod_escape(T, albedo):
    """Rod model (exact back-scattering, g = -1): a packet starting at the centre of a rod of
    half optical length T escapes with 1 / (cosh(m T) + m sinh(m T) / (1 + albedo)),
    m = sqrt(1 - albedo^2) (from E+' = E+ - a E-, E-' = a E+ - E-, E+(T) = E-(-T) = 1)."""
    m = math.sqrt(1 - albedo * albedo)
    return 1.0 / (np.cosh(m * T) + m * np.sinh(m * T) / (1 + albedo))


def hg_mean_sin(g):
    """E[sin theta] of HG: the mean first-order deflection of one scattering."""
    p = lambda m: 0.5 * (1 - g * g) / (1 + g * g - 2 * g * m) ** 1.5  # noqa: E731
    pts = [1 - 1e-6, 1 - 1e-4, 1 - 1e-2]
    return integrate.quad(lambda m: math.sqrt(max(0.0, 1 - m * m)) * p(m), -1, 1, points=pts, limit=500)[0]


def assert_exact_energy(res, n):
    c = res.counts
    assert np.all(c[:, 0] == n)
    assert np.all(c[:, 1] + c[:, 2] + c[:, 3] == c[:, 0])
    e = res.energy
    assert np.all(e[:, 1] + e[:, 2] + e[:, 3] == e[:, 0])  # float64, no rounding at all
    assert np.all(np.isfinite(res.J)) and np.all(res.J >= 0)
    assert np.all(np.isfinite(res.rel_error))


def total_track(res):
    """Summed path length (box units) of all packets of band 0, from the fixed-point sums."""
    return float(res.raw_sum[0].sum()) / (2.0**FIXED_POINT_BITS * max(res.J.shape[1:]))


def kernel_directions(backend, n, seed=1, photon0=0):
    """The initial directions of packets photon0.. as the kernel draws them (one star, so no
    star choice): its own Philox words, then mu = 2 u1 - 1, phi = 2 pi u2, in float64 from the
    float32 uniforms (the kernel's float32 cos/sin differ by a few ulps)."""
    w = probes.photon_stream_u32(backend, seed, 0, photon0, 2, n).astype(np.uint64)
    u = (w >> np.uint64(8)).astype(np.float64) * U32
    mu = (2 * u[:, 0].astype(np.float32) - np.float32(1)).astype(np.float64)
    phi = (np.float32(2 * np.pi) * u[:, 1].astype(np.float32)).astype(np.float64)
    st = np.sqrt(np.maximum(0.0, 1 - mu * mu))
    return np.stack([st * np.cos(phi), st * np.sin(phi), mu], axis=1)


S_MAX = math.sqrt(3) / 2  # longest centre-to-boundary distance


# --------------------------------------------------------------------------------------------
# 1. g at the extremes
# --------------------------------------------------------------------------------------------
KAPPA = 2.0  # extinction per box unit: optical depth 1 centre-to-face
ALB = 0.6
N_G = 100_000
GS = [-1.0, -0.999999, -1e-7, 0.0, 1e-7, 0.999999, 1.0]


@pytest.fixture(scope="module")
def g_runs(backend):
    rho = np.ones((16, 16, 16), np.float32)
    out = {}
    for k, g in enumerate(GS):
        # seeds differ except for g = +-0.999999 (same seed as +-1: see the clamp test)
        seed = {-0.999999: 1, 0.999999: 7}.get(g, k + 1)
        out[g] = trace(rho, one_band(ALB, g), centre_star(), tau=KAPPA, photons=N_G, seed=seed,
                       backend=backend)
    return out


@pytest.mark.parametrize("g", GS)
def test_g_extremes_finite_and_exact(g_runs, g):
    res = g_runs[g]
    assert_exact_energy(res, N_G)
    assert res.counts[0, 3] == 0  # albedo 0.6: 1000 scatterings have probability 0.6^1000


def test_g_clamp_is_exact(g_runs):
    """|g| = 0.999999 and 1 both clamp to 1 - 1e-4 in float32: same seed, the same bits."""
    for a, b in ((1.0, 0.999999), (-1.0, -0.999999)):  # seeds 7 and 7, 1 and 1
        ra, rb = g_runs[a], g_runs[b]
        assert np.array_equal(ra.counts, rb.counts)
        assert ra.raw_sum.tobytes() == rb.raw_sum.tobytes()


def test_g_near_zero_is_continuous(g_runs):
    """g = -1e-7, 0, 1e-7 (independent seeds): escape fractions agree within 5 sigma of the
    difference of two binomial fractions (the true difference, |dP/dg| 1e-7 < 1e-6, is nil)."""
    p = {g: g_runs[g].counts[0, 2] / N_G for g in (-1e-7, 0.0, 1e-7)}
    pm = np.mean(list(p.values()))
    sig = math.sqrt(2 * pm * (1 - pm) / N_G)
    for a, b in ((-1e-7, 0.0), (1e-7, 0.0), (-1e-7, 1e-7)):
        assert abs(p[a] - p[b]) < 5 * sig + 1e-6, (p, sig)


def _deflection_bound(mean_interactions, kappa_path):
    """Systematic effect of the clamp (the kernel's g = +-1 is +-(1 - 1e-4)): each scattering
    turns the line by a mean E[sin theta] (first order), changing the remaining exit distance
    by at most |grad_d s| E[sin] <= sqrt(3) s_max E[sin]; the escape probability changes by at
    most kappa_path (optical depth per box unit) times that, per interaction."""
    return mean_interactions * kappa_path * math.sqrt(3) * S_MAX * hg_mean_sin(G_LIMIT)


def test_g_plus_one_is_no_deflection(g_runs):
    """g = 1: a scattered packet keeps its direction, so only absorption removes packets: escape
    = <exp(-(1 - albedo) kappa s)>. Isotropic (g = 0) and backward give clearly other values."""
    want = direction_average(lambda s: np.exp(-(1 - ALB) * KAPPA * s))
    got = g_runs[1.0].counts[0, 2] / N_G
    sig = math.sqrt(want * (1 - want) / N_G)
    # mean interactions <= 1 / (1 - albedo) (geometric series in an infinite medium)
    tol = 5 * sig + _deflection_bound(1 / (1 - ALB), KAPPA)
    assert abs(got - want) < tol, (got, want, sig, tol)
    back = direction_average(lambda s: rod_escape(KAPPA * s, ALB))
    assert abs(back - want) > 2 * tol  # the check can tell the two apart


def test_g_minus_one_is_the_rod_model(g_runs):
    """g = -1: every scattering reverses the packet on its line through the centre, and the box
    is centre-symmetric, so each direction is a rod of half optical length kappa s(d):
    escape = <rod_escape(kappa s)> over directions."""
    want = direction_average(lambda s: rod_escape(KAPPA * s, ALB))
    got = g_runs[-1.0].counts[0, 2] / N_G
    sig = math.sqrt(want * (1 - want) / N_G)
    tol = 5 * sig + _deflection_bound(1 / (1 - ALB), KAPPA)
    assert abs(got - want) < tol, (got, want, sig, tol)


def test_g_plus_one_albedo_one_is_vacuum(backend):
    """Albedo 1, g = 1: nothing is absorbed, nothing deflected: everything escapes and the track
    of every packet is its straight vacuum path. Same seed as a vacuum run: the first random
    words (the direction) are the same, so the summed track lengths differ only by the clamp's
    deflections (bound: mean interactions kappa s_max, each changing the remaining path by
    <= sqrt(3) s_max E[sin theta]) and float32 rounding of the extra segment ends."""
    rho = np.ones((16, 16, 16), np.float32)
    n = 50_000
    vac = trace(rho, one_band(1.0, 1.0), centre_star(), tau=0.0, photons=n, seed=3, backend=backend)
    fwd = trace(rho, one_band(1.0, 1.0), centre_star(), tau=KAPPA, photons=n, seed=3, backend=backend)
    assert_exact_energy(fwd, n)
    assert fwd.counts[0, 2] == n and fwd.counts[0, 1] == 0 and fwd.counts[0, 3] == 0
    tv, tf = total_track(vac), total_track(fwd)
    bound = n * KAPPA * S_MAX * math.sqrt(3) * S_MAX * hg_mean_sin(G_LIMIT) + tv * 8 * U32
    assert abs(tf - tv) < bound, (tf / tv - 1, bound / tv)


def test_g_minus_one_albedo_one_track_length(backend):
    """Albedo 1, g = -1: a 1D random walk on the packet's line until it escapes. Rod model: mean
    optical path from the centre to escape T^2 + T (T = kappa s), i.e. track kappa s^2 + s.
    8 seeds, SE of their mean; plus the clamp's deflections (mean interactions <= T_max^2 +
    T_max, each changing the remaining path <= sqrt(3) E[sin theta] times the mean track)."""
    rho = np.ones((16, 16, 16), np.float32)
    n, runs = 20_000, 8
    per = []
    for seed in range(1, runs + 1):
        res = trace(rho, one_band(1.0, -1.0), centre_star(), tau=KAPPA, photons=n, seed=seed, backend=backend)
        assert_exact_energy(res, n)
        assert res.counts[0, 2] == n
        per.append(total_track(res) / n)
    want = direction_average(lambda s: KAPPA * s * s + s)
    got, se = np.mean(per), np.std(per, ddof=1) / math.sqrt(runs)
    t_max = KAPPA * S_MAX
    defl = (t_max**2 + t_max) * math.sqrt(3) * hg_mean_sin(G_LIMIT) * want
    assert abs(got - want) < 5 * se + defl, (got, want, se, defl)
    assert se / want < 0.01


# --------------------------------------------------------------------------------------------
# 2. albedo 0 and 1
# --------------------------------------------------------------------------------------------
def test_albedo_zero_escape_is_exp_minus_tau(backend):
    n = 100_000
    res = trace(np.ones((16, 16, 16), np.float32), one_band(0.0, 0.6), centre_star(), tau=KAPPA,
                photons=n, seed=5, backend=backend)
    assert_exact_energy(res, n)
    assert res.counts[0, 3] == 0  # never scatters
    want = direction_average(lambda s: np.exp(-KAPPA * s))
    got = res.counts[0, 2] / n
    assert abs(got - want) < 5 * math.sqrt(want * (1 - want) / n), (got, want)


@pytest.mark.parametrize("max_scatterings", [0, 3, 1000])
@pytest.mark.filterwarnings("ignore::nebula_rt.errors.NebulaWarning")  # terminates packets on purpose
def test_albedo_one_never_absorbs(backend, max_scatterings):
    """Albedo 1 ends only by escape or the cap: absorbed = 0, emitted = escaped + terminated.
    With cap 0 every interacting packet is terminated: escaped = P0 = <exp(-kappa s)>."""
    n = 50_000
    res = trace(np.ones((16, 16, 16), np.float32), one_band(1.0, 0.6), centre_star(), tau=4 * KAPPA,
                photons=n, max_scatterings=max_scatterings, seed=6, backend=backend)
    assert_exact_energy(res, n)
    c = res.counts[0]
    assert c[1] == 0 and c[2] + c[3] == n
    if max_scatterings == 0:
        want = direction_average(lambda s: np.exp(-4 * KAPPA * s))
        assert abs(c[2] / n - want) < 5 * math.sqrt(want * (1 - want) / n)
    if max_scatterings == 1000:
        assert c[3] == 0  # tau 4 centre-to-face: a walk of >1000 scatterings has no chance


# --------------------------------------------------------------------------------------------
# 3. density 0, 1e-30, and optically very thick
# --------------------------------------------------------------------------------------------
def vacuum_shell_check(backend, shape, star, edges, photons, runs, L=2.5, order=(4, 3)):
    """J from ``runs`` seeds against L / (16 pi^2 r^2) averaged over the same voxels (Gauss-
    Legendre of two orders; their difference is the quadrature error), in shells of r."""
    rho = np.zeros(shape, np.float32)
    fields = []
    for seed in range(1, runs + 1):
        res = trace(rho, one_band(0.0), centre_star(L, star), tau=1.0, photons=photons, seed=seed,
                    backend=backend)
        assert_exact_energy(res, photons)
        assert res.counts[0, 2] == photons  # everything escapes
        fields.append(res.J[0])
    X, Y, Z = voxel_centres(shape)
    r = np.sqrt((X - star[0]) ** 2 + (Y - star[1]) ** 2 + (Z - star[2]) ** 2)
    mask = (r >= edges[0]) & (r < edges[-1])
    refs = []
    for o in order:
        ref = np.zeros(shape)
        ref[mask] = voxel_average_point_source(shape, star, 0.0, L, mask, o)
        refs.append(shell_means(ref, r, edges))
    want, quad_err = refs[0], np.abs(refs[0] - refs[1])
    per_run = np.array([shell_means(f, r, edges) for f in fields])
    got = per_run.mean(axis=0)
    se = per_run.std(axis=0, ddof=1) / math.sqrt(runs)
    assert np.all(np.abs(got - want) < 5 * se + quad_err), (got / want - 1, se / want, quad_err / want)
    assert np.all(se / want < 0.02)
    return got / want - 1, se / want


def test_vacuum_point_source(backend):
    shape = (24, 24, 24)
    edges = np.array([3, 5, 7, 9, 11]) / 24.0
    vacuum_shell_check(backend, shape, (0.5, 0.5, 0.5), edges, 40_000, 6)


def test_density_1e_minus_30_is_vacuum(backend):
    """rho = 1e-30 (a normal float32; sigma = 2e-30 per box unit): the same seed gives the same
    tracks as vacuum bit for bit (a packet interacts only if it draws tau < sigma * s ~ 1e-30,
    i.e. xi = 0 exactly: probability 2^-24 per packet, N 2^-24 = 0.003 expected here)."""
    shape, n = (16, 16, 16), 50_000
    vac = trace(np.zeros(shape, np.float32), one_band(0.6), centre_star(), tau=KAPPA, photons=n, seed=2,
                backend=backend)
    tiny = trace(np.full(shape, 1e-30, np.float32), one_band(0.6), centre_star(), tau=KAPPA, photons=n,
                 seed=2, backend=backend)
    assert_exact_energy(tiny, n)
    assert np.array_equal(tiny.counts, vac.counts) and tiny.counts[0, 2] == n
    assert tiny.raw_sum.tobytes() == vac.raw_sum.tobytes()


@pytest.mark.parametrize("tau_voxel", [1e3, 1e6])
def test_optically_very_thick(backend, tau_voxel):
    """tau 1e3 (and 1e6) per voxel, albedo 0.6: everything is absorbed within the 8 voxels around
    the star, no overflow, energy exact. The track-length absorption (1 - a) sigma sum(track)
    estimates the absorbed energy L: per packet (1 - a) kappa (total path) is a geometric sum
    of exponentials, itself Exp(1), so the estimate has relative sigma 1/sqrt(N); plus float32
    rounding of each segment (<= 4 ulps) and of the fixed-point deposit (< 2^-32 voxel)."""
    shape, n = (16, 16, 16), 100_000
    kappa = tau_voxel * shape[0]
    res = trace(np.ones(shape, np.float32), one_band(0.6), centre_star(), tau=kappa, photons=n, seed=4,
                backend=backend)
    assert_exact_energy(res, n)
    assert res.counts[0, 1] == n  # all absorbed: nothing escapes 8e3 optical depths
    J = res.J[0]
    assert np.all(J[:7] == 0) and np.all(J[9:] == 0) and np.all(J[:, :7] == 0) and np.all(J[:, :, 9:] == 0)
    est = (1 - ALB) * kappa * total_track(res) / n
    assert abs(est - 1) < 5 / math.sqrt(n) + 4 * U32, est - 1


# --------------------------------------------------------------------------------------------
# 4. grids 2x2x2 and 97x64x33
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", [(2, 2, 2), (97, 64, 33)])
def test_odd_grids_albedo_zero_escape(backend, shape):
    """Uniform dust looks the same on any grid: escape with albedo 0 = <exp(-kappa s)>, and with
    albedo 0.6 / g 0.6 finite and exact."""
    n = 50_000
    rho = np.ones(shape, np.float32)
    res = trace(rho, one_band(0.0), centre_star(), tau=KAPPA, photons=n, seed=8, backend=backend)
    assert_exact_energy(res, n)
    want = direction_average(lambda s: np.exp(-KAPPA * s))
    assert abs(res.counts[0, 2] / n - want) < 5 * math.sqrt(want * (1 - want) / n)
    res = trace(rho, one_band(0.6, 0.6), centre_star(), tau=KAPPA, photons=n, seed=9, backend=backend)
    assert_exact_energy(res, n)


def test_odd_grid_vacuum_field(backend):
    """97 x 64 x 33: anisotropic voxels whose faces are not exact in float32."""
    edges = np.array([0.12, 0.2, 0.28, 0.36, 0.44])
    vacuum_shell_check(backend, (97, 64, 33), (0.5, 0.5, 0.5), edges, 40_000, 6)


# --------------------------------------------------------------------------------------------
# 5. stars on faces and corners, in an empty voxel, in very dense dust
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("star", [(1.0, 0.5, 0.5), (0.0, 0.5, 0.5), (1.0, 1.0, 1.0), (0.5, 1.0, 0.0)])
@pytest.mark.parametrize("shape", [(16, 16, 16), (97, 64, 33)])
def test_star_on_boundary_in_dust(backend, star, shape):
    """A star exactly on a face/edge/corner (1.0 must not index voxel n): finite, exact; the
    outward half (or 7/8) of the packets leaves at once, so fewer interact than from inside."""
    n = 20_000
    res = trace(np.ones(shape, np.float32), one_band(0.6, 0.6), centre_star(1.0, star), tau=KAPPA,
                photons=n, seed=10, backend=backend)
    assert_exact_energy(res, n)
    outward = 0.5 if sum(c in (0.0, 1.0) for c in star) == 1 else 0.75 if sum(c in (0.0, 1.0) for c in star) == 2 else 0.875
    # at least the outward fraction escapes (binomial 5 sigma below it)
    assert res.counts[0, 2] / n > outward - 5 * math.sqrt(outward * (1 - outward) / n)


@pytest.mark.parametrize("star", [(1.0, 0.5, 0.5), (1.0, 1.0, 1.0)])
def test_star_on_boundary_vacuum_field(backend, star):
    """In vacuum the inward packets give the full point-source field inside the box."""
    edges = np.array([4, 6, 8, 10, 12]) / 24.0
    vacuum_shell_check(backend, (24, 24, 24), star, edges, 40_000, 6)


def test_star_in_empty_voxel_and_in_dense_dust(backend):
    shape, n = (16, 16, 16), 50_000
    star = (0.5 + 1 / 32, 0.5 + 1 / 32, 0.5 + 1 / 32)  # centre of voxel (8, 8, 8)
    rho = np.ones(shape, np.float32)
    rho[8, 8, 8] = 0.0
    res = trace(rho, one_band(0.0), centre_star(1.0, star), tau=KAPPA, photons=n, seed=11, backend=backend)
    assert_exact_energy(res, n)
    # albedo 0: J in the empty voxel is the vacuum field there (no packet is absorbed before it
    # leaves the voxel); its track per packet is the distance to the voxel faces: mean over
    # directions of 1/32 / max|d_i| = (1/16) direction_average(s)
    track_in_void = res.raw_sum[0, 8, 8, 8] / (2.0**FIXED_POINT_BITS * 16) / n
    want = direction_average(lambda s: s) / 16
    # per-packet track in [1/32, sqrt(3)/32]: sigma <= (sqrt(3) - 1)/64 / sqrt(n)
    assert abs(track_in_void - want) < 5 * (math.sqrt(3) - 1) / 64 / math.sqrt(n), (track_in_void, want)
    rho[8, 8, 8] = 1e6  # optical depth 1.25e5 across the star's voxel
    res = trace(rho, one_band(0.6), centre_star(1.0, star), tau=KAPPA, photons=n, seed=12, backend=backend)
    assert_exact_energy(res, n)
    assert res.counts[0, 1] == n
    assert np.count_nonzero(res.J[0]) == 1


# --------------------------------------------------------------------------------------------
# 6. more than 2^32 packets: 64-bit photon indices
# --------------------------------------------------------------------------------------------
def test_photon_streams_past_2_32(backend):
    from test_rng import numpy_philox_block

    photon0, n, m, seed = 2**32 - 2, 5, 8, 77
    got = probes.photon_stream_u32(backend, seed, 1, photon0, m, n)
    assert len({tuple(r) for r in got.tolist()}) == n  # distinct streams (no 32-bit aliasing)
    for i in range(n):
        raw = numpy_philox_block((seed, 1), (photon0 + i, 0, 0, 0)).random_raw(4)
        want = [f(int(w)) for w in raw for f in (lambda w: w & 0xFFFFFFFF, lambda w: w >> 32)]
        assert [int(v) for v in got[i]] == want
    # the stream of photon 2^32 + k is not that of photon k
    low = probes.photon_stream_u32(backend, seed, 1, 0, m, 3)
    assert not np.array_equal(low, got[2:5])


@pytest.mark.parametrize("photons", [5 * 2**32, 5 * 2**32 + 12345])
def test_batch_plan_and_energy_past_2_32(photons):
    plan = batch_plan(photons)
    assert plan == batch_plan(photons)  # deterministic
    sizes = [c for _, c in plan]
    assert sum(sizes) == photons and max(sizes) - min(sizes) <= 1 and len(plan) >= 16
    assert all(s == plan[k - 1][0] + plan[k - 1][1] for k, (s, _) in enumerate(plan) if k > 0)
    assert plan[0][0] == 0
    L = 3.7
    q = exact_packet_energy(L, photons)
    assert abs(q * photons / L - 1) < 2.0 ** -(52 - photons.bit_length())
    # any split emitted = absorbed + escaped + terminated is exact in float64
    a, b = photons // 3 + 1, photons // 7 + 5
    c = photons - a - b
    for k in (a, b, c, photons):
        assert Fraction(k * q) == Fraction(k) * Fraction(q)
    assert a * q + b * q + c * q == photons * q


def test_kernel_batch_index_past_2_32(backend):
    """The kernel maps 64-bit photon indices to batch slots: a launch straddling the boundary of
    two batches beyond 2^32 counts each packet in its own batch."""
    from nebula_rt.backends import TransportSetup

    photons = 5 * 2**32 + 12345
    plan = batch_plan(photons)
    base, extra = divmod(photons, len(plan))
    assert extra > 0
    k = extra  # the first batch of size base: crosses the two branches of nrt_batch_of
    start = plan[k][0] - 300
    assert start > 2**32
    setup = TransportSetup(
        density=np.ones((4, 4, 4), np.float32), sigma_scale=np.array([1.0], np.float32),
        albedo=np.array([0.6], np.float32), g=np.array([0.6], np.float32),
        stars=np.array([[0.5, 0.5, 0.5]], np.float32), star_cdf=np.ones((1, 1), np.float32),
        estimator="track-length", max_scatterings=10, seed=1, track_scale=2.0**32 * 4)
    session = backend.transport_session(setup, 2)
    try:
        tallies, overflow = session.run_group(start, 500, base, extra, k - 1, 2)
    finally:
        session.close()
    assert not overflow.any()
    assert [int(t[0, 0]) for t in tallies] == [300, 200]
    assert all(int(t[0, 1] + t[0, 2] + t[0, 3]) == int(t[0, 0]) for t in tallies)


def test_scene_accepts_5e9_photons():
    from nebula_rt.scene import Scene

    assert Scene.from_dict({"transport": {"photons": 5_000_000_000}}).transport.photons == 5_000_000_000
    assert Scene.from_dict({"transport": {"photons": 5e9}}).transport.photons == 5_000_000_000
    with pytest.raises(SceneError) as e:
        Scene.from_dict({"transport": {"photons": 2**53 + 2}})
    assert e.value.parameter == "transport.photons"
    with pytest.raises(SceneError, match="transport.photons"):
        Scene.from_dict({"transport": {"photons": 0}})


# --------------------------------------------------------------------------------------------
# 7. fixed-point accumulators near overflow
# --------------------------------------------------------------------------------------------
def test_accumulator_overflow_recovery_in_vacuum(backend):
    """Vacuum 8^3, star at the centre: every packet crosses one of the 8 central voxels, leaving
    >= 1 voxel edge (2^32 units) there. Headroom 2^38 (64 edges) overflows the 16 batches of
    625 packets (~78 per central voxel, >= 2^38 units); halving recovers bit for bit."""
    kw = dict(tau=0.0, photons=10_000, seed=2, backend=backend)
    rho = np.zeros((8, 8, 8), np.float32)
    normal = trace(rho, one_band(0.0), centre_star(), **kw)
    split = trace(rho, one_band(0.0), centre_star(), _acc_limit_bits=38, **kw)
    assert normal.batches == 16 and split.batches > 16
    assert split.raw_sum.tobytes() == normal.raw_sum.tobytes()
    assert np.array_equal(split.counts, normal.counts)
    assert split.J.tobytes() == normal.J.tobytes()
    # a single packet deposits >= 2^32 units in its first voxel: headroom 2^32 cannot hold it
    with pytest.raises(AccumulatorOverflowError, match="single packet") as e:
        trace(rho, one_band(0.0), centre_star(), _acc_limit_bits=32, **kw)
    assert isinstance(e.value, NebulaError) and "dust.tau" in str(e.value)


# --------------------------------------------------------------------------------------------
# 8. xi = 0 in the free-path sampling
# --------------------------------------------------------------------------------------------
def test_free_path_at_xi_zero(backend):
    xi = np.array([0.0, U32, 0.5, 1 - 2 * U32, 1 - U32], np.float32)
    tau = probes.sample_tau_at(backend, xi).astype(np.float64)
    assert np.all(np.isfinite(tau)) and tau[0] == 0.0
    want = -np.log1p(-xi.astype(np.float64))
    # float32 log: 1 - xi is exact on the 2^-24 grid; OpenCL allows log 3 ulps
    assert np.all(np.abs(tau - want) <= 3 * np.spacing(want.astype(np.float32)).astype(np.float64) + 1e-30), (tau, want)
    assert tau[-1] == pytest.approx(24 * math.log(2), rel=4 * U32)


# --------------------------------------------------------------------------------------------
# 9. float32 positions on 1024 voxels along x
# --------------------------------------------------------------------------------------------
def _x_lengths(dirs, s, bounds):
    """Per packet, the length of the straight track (centre, direction d, length s) with
    x < bound, for each bound: (N, len(bounds))."""
    dx = dirs[:, 0:1]
    xa = 0.5 + np.minimum(0.0, s[:, None] * dx)
    xb = 0.5 + np.maximum(0.0, s[:, None] * dx)
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.clip((bounds[None, :] - xa) / (xb - xa), 0.0, 1.0)
    frac = np.where(xb > xa, frac, (bounds[None, :] > 0.5).astype(float))
    return frac * s[:, None]


def _group_integral(gb, order):
    """(1/4 pi) int dV / r^2 over the slabs [gb[k], gb[k+1]] x [0,1]^2 (star at the centre): the
    expected vacuum track of one packet there. Gauss-Legendre order^3 per slab; smooth where
    the slab does not touch x = 0.5 (r >= 1/16); 48 vs 32 nodes gives the quadrature error."""
    x, w = np.polynomial.legendre.leggauss(order)
    out = []
    for a, b in zip(gb[:-1], gb[1:]):
        if a < 0.5 <= b or a == 0.5:
            out.append(np.nan)
            continue
        xs, ws = 0.5 * (b - a) * (x + 1) + a, 0.5 * (b - a) * w
        ys, wy = 0.5 * (x + 1), 0.5 * w
        X, Y, Z = np.meshgrid(xs, ys, ys, indexing="ij")
        W = ws[:, None, None] * wy[None, :, None] * wy[None, None, :]
        out.append(np.sum(W / ((X - 0.5) ** 2 + (Y - 0.5) ** 2 + (Z - 0.5) ** 2)) / (4 * np.pi))
    return np.array(out)


def test_float32_positions_on_1024_voxels(backend):
    """1024 x 4 x 4 vacuum grid (voxels 1/1024 thick in x): float32 resolves 6e-8 near x = 1,
    1.6e4 times finer than a voxel, so the DDA must cross every x-slab in order. The host
    reproduces each packet's direction from the kernel's own random stream and computes its
    exact straight track; per x-slab and in total the kernel must agree to float32 rounding
    (per segment <= 4 ulps: 1/d, face - p, times, fixed-point scale; direction <= 8 ulps from the
    float32 cos/sin/sqrt), and J per slab group must match L / (16 pi^2 r^2) within 5 SE."""
    shape, n, L = (1024, 4, 4), 100_000, 1.0
    res = trace(np.zeros(shape, np.float32), one_band(0.0), centre_star(L), tau=0.0, photons=n, seed=1,
                backend=backend)
    assert_exact_energy(res, n)
    d = kernel_directions(backend, n, seed=1)
    with np.errstate(divide="ignore"):
        s = np.min(0.5 / np.abs(d), axis=1)
    scale = 2.0**FIXED_POINT_BITS * 1024
    # total track
    t_kernel = float(res.raw_sum[0].sum()) / scale
    t_host = float(s.sum())
    rel_total = t_kernel / t_host - 1
    assert abs(rel_total) < 12 * U32, rel_total
    # every x-slab
    bounds = np.arange(1025) / 1024.0
    slab_host = np.zeros(1024)
    for k in range(0, n, 5000):
        slab_host += np.diff(_x_lengths(d[k:k + 5000], s[k:k + 5000], bounds), axis=1).sum(axis=0)
    slab_kernel = res.raw_sum[0].sum(axis=(1, 2)) / scale
    slab_err = np.abs(slab_kernel - slab_host)
    # Per slab, beyond 12 ulps of its track: where a packet crosses a y or z face, the kernel
    # moves x by p += d t (not snapped: <= 1 ulp(x)), which shifts ulp(x)/|d_x| of track from
    # that slab to its neighbour (a shift of the y crossing itself stays within the slab).
    # x faces k/1024 are exact in float32, so x-crossings add no such term.
    yz_shift = np.zeros(1024)
    with np.errstate(divide="ignore", invalid="ignore"):
        for ax in (1, 2):
            for c in (0.25, 0.75):
                t = (c - 0.5) / d[:, ax]
                hit = (t > 0) & (t < s)
                xc = 0.5 + d[hit, 0] * t[hit]
                ulp = np.spacing(np.abs(xc).astype(np.float32)).astype(np.float64)
                idx = np.clip((xc * 1024).astype(int), 0, 1023)
                yz_shift += np.bincount(idx, weights=ulp / np.abs(d[hit, 0]), minlength=1024)
    # The transverse coordinates are NOT snapped at x crossings: p[y] += d_y t adds <= ulp/2
    # (2^-25 below 1) per DDA step, with a constant increment, so the rounding adds up
    # systematically. A packet that leaves through a y or z face after k steps leaves at a t
    # off by <= k 2^-25 / |d_exit| (measured below: this dominates the slab errors).
    with np.errstate(divide="ignore"):
        exit_ax = np.argmin(0.5 / np.abs(d), axis=1)
    side = exit_ax > 0
    x_exit = 0.5 + d[side, 0] * s[side]
    steps = np.abs(np.floor(x_exit * 1024) - 512) + 4  # x crossings + at most 4 y/z crossings
    idx = np.clip((x_exit * 1024).astype(int), 0, 1023)
    d_exit = np.abs(d[side][np.arange(side.sum()), exit_ax[side]])
    exit_drift = np.bincount(idx, weights=steps * 2.0**-25 / d_exit, minlength=1024)
    bound = 12 * U32 * slab_host + yz_shift + exit_drift + n * 16 * 0.5 / scale
    assert np.all(slab_err <= bound), np.max(slab_err / bound)
    # The kernel measures every face crossing from the flight's start point, so the
    # accumulated drift term must not be needed: the bound without it holds too.
    bound_no_drift = 12 * U32 * slab_host + yz_shift + n * 16 * 0.5 / scale
    print(f"1024x4x4: max slab err / bound without drift term {np.max(slab_err / bound_no_drift):.3f}")
    assert np.all(slab_err <= bound_no_drift), np.max(slab_err / bound_no_drift)
    slab_rel = slab_err / slab_host
    # J per group of 64 slabs against the analytic field; SE from the per-packet lengths
    gb = np.arange(17) / 16.0
    per_packet = np.diff(_x_lengths(d, s, gb), axis=1)  # (n, 16)
    mean_len = per_packet.mean(axis=0)
    se_len = per_packet.std(axis=0, ddof=1) / math.sqrt(n)
    ok = np.array([b < 0.5 or a > 0.5 for a, b in zip(gb[:-1], gb[1:])])  # star not on the group
    want48, want32 = _group_integral(gb, 48), _group_integral(gb, 32)
    quad_err = np.abs(want48 - want32)
    want = want48
    J_kernel = res.J[0].reshape(16, 64, 4, 4).mean(axis=(1, 2, 3))  # equal voxels: group mean
    J_want = L * want / (4 * np.pi * (1 / 16))
    J_se = L * se_len / (4 * np.pi * (1 / 16))
    J_quad = L * quad_err / (4 * np.pi * (1 / 16))
    assert np.all(np.abs(J_kernel[ok] - J_want[ok]) < 5 * J_se[ok] + J_quad[ok]), ((J_kernel / J_want - 1)[ok], (J_se / J_want)[ok])
    assert np.all(np.abs(mean_len[ok] - want[ok]) < 5 * se_len[ok] + quad_err[ok])
    print(f"1024x4x4: total track rel error {rel_total:.3e}, max slab abs error {slab_err.max():.3e} box units, "
          f"slab rel error max {slab_rel.max():.3e} rms {np.sqrt(np.mean(slab_rel**2)):.3e}, "
          f"max err/bound {np.max(slab_err / bound):.3f}, "
          f"J/analytic - 1 {np.nanmax(np.abs(J_kernel / J_want - 1)):.3e} (SE {np.nanmax(J_se / J_want):.3e})")
