"""Polarized transport (``trace(polarization=...)``) against answers the kernel did not make.

- Single scattering (``max_scatterings = 1``: the second interaction terminates a packet
  before it peels off) of a central star's light in a uniform box, Rayleigh scattering, analog
  and weighted packets: the
  images of I, Q and U are line-of-sight integrals computed here in NumPy (Gauss-Legendre over
  each pixel and along the line of sight): the light scattered at r from the star, attenuated
  exp(-sigma r) on the way in and exp(-sigma (1 - z)) on the way out, by S11 (I) and, for Q and
  U, by the polarized part -S12 (3 (1 - mu^2) / (16 pi)) with its electric vector perpendicular
  to the scattering plane (tangential about the star). Every pixel is its own group of the run's
  batch sums (``peel_bins``), so the errors of any linear statistic are the batch means' own;
  tolerances are 4.5 of them, and the z-scores' spread (their honesty) is checked too.
- The degree of polarization against projected offset (annuli) against the same integrals.
- Multiple scattering (White's approximation): Q = U = 0 in total about a central star, and the
  pattern is centrosymmetric (no radial component in any annulus, a tangential one in every one).
- Turning the camera about the line of sight turns the angles: the same packets peel off the
  same light, so the image totals of Q + iU turn by exp(-2 i alpha) to rounding.
- Energy is conserved, launches and the transport by regions give the same bits, and what
  polarization cannot take is refused by name.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from conftest import centre_star, one_band

from nebula_rt.errors import SceneError
from nebula_rt.observe.sky import Camera
from nebula_rt.optics.mie import Grains, mie_bands
from nebula_rt.optics.mueller_table import read_matrix
from nebula_rt.optics.polarization import Polarization
from nebula_rt.transport import trace

RAYLEIGH = Polarization("rayleigh")
N_PIX = 24
SIGMA = 0.2  # extinction per box unit: optical depth 0.1 from the star to a face


def _batch_stat(batches, weights):
    """Total and batch-means standard error of sum(weights x pixel) from per-pixel batch sums
    (batches, pixels)."""
    x = batches @ weights
    m = x.size
    return x.sum(), math.sqrt(m * x.var(ddof=1))


def _rayleigh(mu):
    """S11 (per sr) and -S12 (the polarized part, tangential where positive) of dipole scattering."""
    return 3 * (1 + mu**2) / (16 * np.pi), 3 * (1 - mu**2) / (16 * np.pi)


#: one sphere for the Mie case: x = 2 pi a / lambda = 2.74 at 550 nm, m = 1.6 + 0.02 i
MIE_GRAINS = Grains(n=1.6, k=0.02, radius_min=0.24, radius_max=0.24)


def _mie_exact(mu):
    """S11 (per sr) and -S12 of MIE_GRAINS from miepython's amplitudes directly (not the table)."""
    import miepython

    x = 2 * np.pi * MIE_GRAINS.radius_min / 0.55
    m = complex(MIE_GRAINS.n, -MIE_GRAINS.k)
    fine = np.linspace(-1.0, 1.0, 40_001)
    s1, s2 = miepython.S1_S2(m, x, fine, norm="wiscombe")
    a1, a2 = np.abs(s1) ** 2, np.abs(s2) ** 2
    _, qs, _, _ = miepython.efficiencies_mx(m, x)
    c = 1.0 / (2 * np.pi * x * x * qs)  # S11 = (|S1|^2 + |S2|^2) / (2 k^2 C_sca)
    return np.interp(mu, fine, (a1 + a2) * c), np.interp(mu, fine, (a1 - a2) * c)


#: a tabulated matrix (bands.polarization = "matrix"): the Pinte et al. 2009 benchmark's grains
PINTE_MATRIX = Path(__file__).resolve().parents[2] / "benchmarks" / "data" / "pinte2009" / "mueller_matrix_1um.dat"


def _table_exact(mu):
    """S11 (per sr) and -S12 of the file's rows (linear in theta between them, S11 flat and S12
    zero beyond its first and last angles), normalised here by a fine quadrature over the sphere."""
    a = np.loadtxt(PINTE_MATRIX)
    t = np.concatenate([[0.0], a[:, 0], [180.0]])
    s11 = np.concatenate([a[:1, 1], a[:, 1], a[-1:, 1]])
    s12 = np.concatenate([[0.0], a[:, 2], [0.0]])
    fine = np.linspace(0.0, 180.0, 360_001)
    f = np.interp(fine, t, s11) * np.sin(np.radians(fine))
    norm = 2 * np.pi * np.sum(0.5 * (f[1:] + f[:-1])) * np.radians(fine[1] - fine[0])
    theta = np.degrees(np.arccos(np.clip(mu, -1.0, 1.0)))
    return np.interp(theta, t, s11) / norm, -np.interp(theta, t, s12) / norm


def _single_scattering_oracle(cam, sigma, nodes=4, n_alpha=64, matrix=_rayleigh, albedo=1.0):
    """(I, Q, U) images (W, H) of the single scattering of a unit-luminosity star at the box
    centre, observer along +z, by ``matrix`` (S11 and -S12 of mu), per pixel area (the pixel
    means of the line-of-sight integrals). Along the line of sight at offset b the angle alpha
    from the star's plane (z - 1/2 = b tan alpha) makes dz / r^2 = dalpha / b and mu = sin alpha."""
    w, h = cam.size
    ps = cam.pixel_size
    origin = cam.origin()
    xg, wg = np.polynomial.legendre.leggauss(nodes)
    ag, wa = np.polynomial.legendre.leggauss(n_alpha)
    p = np.arange(w)[:, None, None, None] + 0.5 * xg[None, None, :, None]
    q = np.arange(h)[None, :, None, None] + 0.5 * xg[None, None, None, :]
    x = origin[0] + p * ps - 0.5
    y = origin[1] + q * ps - 0.5
    b = np.hypot(x, y)
    lo, hi = np.arctan(-0.5 / b), np.arctan(0.5 / b)
    alpha = 0.5 * (hi - lo)[..., None] * ag + 0.5 * (hi + lo)[..., None]
    da = 0.5 * (hi - lo)[..., None] * wa
    mu = np.sin(alpha)
    r = b[..., None] / np.cos(alpha)
    z_out = 0.5 - b[..., None] * np.tan(alpha)  # distance from the point to the face z = 1
    kern = albedo * sigma * np.exp(-sigma * r - sigma * z_out) / (4 * np.pi * b[..., None]) * da
    s11, pol = matrix(mu)
    i_pt = np.sum(kern * s11, axis=-1)
    t_pt = np.sum(kern * pol, axis=-1)
    psi = np.arctan2(y, x)
    wts = np.outer(wg, wg) / 4.0
    mean = lambda a: np.einsum("pqij,ij->pq", a, wts)  # noqa: E731
    return mean(i_pt), mean(t_pt * np.cos(2 * psi)), mean(t_pt * np.sin(2 * psi))


def _pixel_groups(cam):
    w, h = cam.size
    return np.arange(w * h).reshape(w, h)


def _offsets(cam):
    """Per pixel (flattened as the groups): projected offset from the box centre in pixels and
    the position angle psi of the pixel centre (from +x towards +y)."""
    w, h = cam.size
    p, q = np.meshgrid(np.arange(w), np.arange(h), indexing="ij")
    x = cam.origin()[0] + p * cam.pixel_size - 0.5
    y = cam.origin()[1] + q * cam.pixel_size - 0.5
    return (np.hypot(x, y) / cam.pixel_size).ravel(), np.arctan2(y, x).ravel()


@pytest.fixture(scope="module", params=["analog", "biased", "mie-analog", "matrix-analog"])
def single(backend, request):
    """Analog packets, and weighted ones (forced scattering, 128-bit weights: Q and U as 128-bit
    two's complement), fewer of them: each scatters inside the box once; Rayleigh scattering,
    and one Mie sphere (whose images hold V too)."""
    cam = Camera(direction=(0.0, 0.0, -1.0), size=(N_PIX, N_PIX), extent=1.0)
    rho = np.ones((16, 16, 16), np.float32)
    method = request.param.split("-")[-1]
    photons = 2_000_000 if method == "analog" else 300_000
    bands, pol, matrix = one_band(albedo=1.0, g=0.0), RAYLEIGH, _rayleigh
    if request.param.startswith("mie"):
        pol, matrix = Polarization("mie", grains=MIE_GRAINS), _mie_exact
        bands = mie_bands(one_band(), MIE_GRAINS)
    if request.param.startswith("matrix"):
        table = read_matrix(PINTE_MATRIX)
        pol, matrix, bands = Polarization("matrix", matrix=table), _table_exact, one_band(albedo=0.6474786, g=table.g)
    with pytest.warns(UserWarning, match="max_scatterings = 1"):  # (the second scatterings are cut on purpose)
        res = trace(rho, bands, centre_star(), tau=SIGMA, photons=photons, seed=21,
                    max_scatterings=1, backend=backend, peel=cam, peel_bins=_pixel_groups(cam),
                    polarization=pol, light_field=False, batch_size=photons // 32, method=method)
    assert res.method == method
    return cam, res, _single_scattering_oracle(cam, SIGMA, matrix=matrix, albedo=bands[0].albedo)


def test_single_scattering_images_are_the_line_of_sight_integrals(single):
    """I, Q and U summed over (annulus, sector) groups against the integrals, within 4.5 batch
    standard errors each, and the z-scores spread as the errors say."""
    cam, res, (oi, oq, ou) = single
    c = [int(x) for x in res.counts[0]]
    # (weighted: emitted = absorbed + escaped + terminated + biasing; Rayleigh's albedo is 1)
    assert (c[1] == 0 or res.peel_stokes.shape[1] == 3) and c[0] == sum(c[1:])
    assert res.peel_stokes.shape == (1, res.peel_stokes.shape[1], N_PIX, N_PIX)
    if res.peel_stokes.shape[1] == 3:  # Mie: V, made only from polarized light, is 0 after one scattering
        assert np.all(res.peel_stokes_bin_batches[:, 0, 2] == 0) and np.all(res.peel_stokes[0, 2] == 0)
    else:
        assert res.peel_stokes.shape[1] == 2
    bi = res.peel_bin_batches[:, 0, :]
    bq, bu = res.peel_stokes_bin_batches[:, 0, 0, :], res.peel_stokes_bin_batches[:, 0, 1, :]
    off, psi = _offsets(cam)
    edges = [2.0, 3.0, 4.0, 5.5, 7.0, 9.0, 12.0]
    sector = np.floor(np.mod(psi, 2 * np.pi) / (np.pi / 4)).astype(int)
    z = []
    for a, b in zip(edges[:-1], edges[1:]):
        for s in range(8):
            sel = ((off >= a) & (off < b) & (sector == s)).astype(np.float64)
            for batches, oracle in ((bi, oi), (bq, oq), (bu, ou)):
                total, se = _batch_stat(batches, sel)
                expect = float(oracle.ravel() @ sel)
                z.append((total - expect) / se)
    z = np.array(z)
    assert np.all(np.abs(z) < 4.5), np.round(z, 2)
    assert 0.7 < z.std() < 1.35, z.std()
    assert abs(z.mean()) < 4.5 / math.sqrt(z.size), z.mean()


def test_degree_of_polarization_against_offset(single):
    """P(b) = tangential Q over I in annuli about the star against the integrals' ratio, the
    error propagated from the batch sums (first order); Rayleigh light is strongly polarized
    far from the star and less near it, where the line of sight holds forward and backward
    scatterings."""
    cam, res, (oi, oq, ou) = single
    off, psi = _offsets(cam)
    c2, s2 = np.cos(2 * psi), np.sin(2 * psi)
    bi = res.peel_bin_batches[:, 0, :]
    bt = res.peel_stokes_bin_batches[:, 0, 0, :] * c2 + res.peel_stokes_bin_batches[:, 0, 1, :] * s2
    ot = oq.ravel() * c2 + ou.ravel() * s2
    ps = []
    for a, b in [(2, 4), (4, 6), (6, 8), (8, 10), (10, 12)]:
        sel = ((off >= a) & (off < b)).astype(np.float64)
        xi, xt = bi @ sel, bt @ sel
        m = xi.size
        p = xt.sum() / xi.sum()
        # the ratio's batch-means error: the spread of each batch's linearised contribution
        lin = (xt - p * xi) / xi.mean()
        se = math.sqrt(lin.var(ddof=1) / m)
        expect = float(ot @ sel) / float(oi.ravel() @ sel)
        assert abs(p - expect) < 4.5 * se, (a, b, p, expect, se)
        ps.append(expect)
    if res.peel_stokes.shape[1] == 2:  # Rayleigh
        assert ps[0] < ps[-1] and ps[-1] > 0.5


@pytest.fixture(scope="module")
def symmetric(backend):
    cam = Camera(direction=(0.0, 0.0, -1.0), size=(20, 20), extent=1.0)
    rho = np.ones((16, 16, 16), np.float32)
    return cam, trace(rho, one_band(albedo=0.7, g=0.4), centre_star(), tau=2.0, photons=600_000, seed=5,
                      backend=backend, peel=cam, peel_bins=_pixel_groups(cam), batch_size=37_500,
                      polarization=Polarization("white", peak=0.5), light_field=False)


def test_symmetric_nebula_has_no_net_polarization_and_a_centrosymmetric_pattern(symmetric):
    cam, res = symmetric
    assert res.counts[0, 3] == 0 or res.counts[0, 3] < 10
    bq, bu = res.peel_stokes_bin_batches[:, 0, 0, :], res.peel_stokes_bin_batches[:, 0, 1, :]
    ones = np.ones(bq.shape[1])
    for b in (bq, bu):
        total, se = _batch_stat(b, ones)
        assert abs(total) < 4.5 * se, (total, se)
    off, psi = _offsets(cam)
    c2, s2 = np.cos(2 * psi), np.sin(2 * psi)
    for a, b in [(1.5, 3), (3, 5), (5, 7), (7, 10)]:
        sel = ((off >= a) & (off < b)).astype(np.float64)
        tangential, se_t = _batch_stat(bq * c2 + bu * s2, sel)   # Q in each pixel's radial frame
        radial, se_r = _batch_stat(-bq * s2 + bu * c2, sel)      # U in that frame: 0 by symmetry
        assert tangential > 10 * se_t, (a, b, tangential, se_t)
        assert abs(radial) < 4.5 * se_r, (a, b, radial, se_r)


def test_turning_the_camera_turns_the_polarization_angles(backend):
    """The same seed seen with the camera's up turned about the line of sight: every deposit
    has the same weight and rounding draw, so the I totals are the same integers' sums and the
    totals of Q + iU turn by exp(-2 i alpha), alpha the angle from the old north to the new
    one towards east."""
    rho = np.zeros((12, 12, 12), np.float32)
    rho[8:, 2:10, 3:9] = np.random.default_rng(2).random((4, 8, 6)) + 0.5  # a cloud beside the star
    star = centre_star(position=(0.3, 0.5, 0.45))
    direction = (0.2, -0.3, -0.93)
    runs = []
    for up in ((0.0, 1.0, 0.0), (0.7, 0.4, 0.2)):
        cam = Camera(direction=direction, up=up, size=(40, 40), extent=1.8)
        runs.append((cam, trace(rho, one_band(0.6, 0.5), star, tau=1.5, photons=40_000, seed=8, backend=backend,
                                peel=cam, polarization=Polarization("white", peak=0.4), light_field=False)))
    (c0, r0), (c1, r1) = runs
    d, _, n0 = c0.basis()
    _, _, n1 = c1.basis()
    east0 = np.cross(-d, n0)
    alpha = math.atan2(float(n1 @ east0), float(n1 @ n0))
    assert abs(alpha) > 0.2
    i0, i1 = r0.peel_image.sum(), r1.peel_image.sum()
    assert i1 == pytest.approx(i0, rel=1e-12)
    s0 = complex(r0.peel_stokes[0, 0].sum(), r0.peel_stokes[0, 1].sum())
    s1 = complex(r1.peel_stokes[0, 0].sum(), r1.peel_stokes[0, 1].sum())
    assert abs(s0) > 0.01 * i0  # an off-centre star: a net polarization to turn
    assert abs(s1 - s0 * complex(math.cos(2 * alpha), -math.sin(2 * alpha))) < 2e-5 * i0


def test_polarized_runs_conserve_energy_and_keep_their_bits_over_launches(backend, monkeypatch):
    from nebula_rt.transport import run as transport

    rho = (np.random.default_rng(4).random((10, 8, 6)) ** 2).astype(np.float32)
    cam = Camera(direction=(0.3, 0.2, -0.9), size=(10, 8))
    kw = dict(tau=6.0, photons=9000, batch_size=1500, seed=3, peel=cam, polarization=RAYLEIGH)
    one = trace(rho, one_band(0.7, 0.0), centre_star(), backend=backend, **kw)
    backend.first_launch_packets = 997
    monkeypatch.setattr(transport, "LAUNCH_SECONDS", 1e-4)
    try:
        many = trace(rho, one_band(0.7, 0.0), centre_star(), backend=backend, **kw)
    finally:
        del backend.first_launch_packets
    c = one.counts[0]
    assert c[0] == 9000 and c[0] == c[1] + c[2] + c[3]
    for a, b in ((one.counts, many.counts), (one.raw_sum, many.raw_sum), (one.peel_image, many.peel_image),
                 (one.peel_stokes, many.peel_stokes)):
        np.testing.assert_array_equal(a, b)
    assert np.all(np.abs(one.peel_stokes[0]) <= one.peel_image[0][None] * (1 + 1e-12))


@pytest.mark.parametrize("tuning", [{"NRT_REGIONS": 2}, {"NRT_REGIONS": 3, "region_tail": 50}])
def test_polarized_packets_by_regions_keep_their_bits(tuning):
    """The transport by regions stops packets at region faces and resumes them in later passes:
    a polarized packet's Stokes state travels with it (beside its state slot), so the sums, the
    counts and the I, Q and U images are the bits of the run without regions."""
    from conftest import tuned_backend

    rho = (np.random.default_rng(3).random((24, 20, 16)) ** 2).astype(np.float32)
    cam = Camera(direction=(0.2, -0.3, -0.9), size=(12, 10))
    kw = dict(tau=8.0, photons=12_000, seed=5, batch_size=3000, peel=cam, polarization=Polarization("white", peak=0.5))
    plain = trace(rho, one_band(0.7, 0.5), centre_star(), backend=tuned_backend({}), **kw)
    regions = trace(rho, one_band(0.7, 0.5), centre_star(), backend=tuned_backend(tuning), **kw)
    for key in ("raw_sum", "raw_m2", "counts", "peel_image", "peel_stokes"):
        np.testing.assert_array_equal(getattr(regions, key), getattr(plain, key), err_msg=key)
    assert np.abs(plain.peel_stokes).sum() > 0


def test_mie_packets_keep_their_bits_by_regions_and_over_launches(backend, monkeypatch):
    """Mie grains (Q, U and V images): the transport by regions and more launches give the bits
    of one launch; |Q|, |U|, |V| <= I pixel by pixel; the packets are all accounted for; and
    light scattered more than once is circularly polarized (V != 0 somewhere)."""
    from conftest import tuned_backend

    from nebula_rt.transport import run as transport

    rho = (np.random.default_rng(6).random((20, 16, 12)) ** 2).astype(np.float32)
    cam = Camera(direction=(0.2, -0.3, -0.9), size=(12, 10))
    grains = Grains(n=1.6, k=0.02, radius_min=0.3, radius_max=0.3)
    bands = mie_bands(one_band(), grains)
    kw = dict(tau=8.0, photons=12_000, seed=5, batch_size=3000, peel=cam, polarization=Polarization("mie", grains=grains))
    plain = trace(rho, bands, centre_star(), backend=tuned_backend({}), **kw)
    regions = trace(rho, bands, centre_star(), backend=tuned_backend({"NRT_REGIONS": 2}), **kw)
    backend.first_launch_packets = 997
    monkeypatch.setattr(transport, "LAUNCH_SECONDS", 1e-4)
    try:
        many = trace(rho, bands, centre_star(), backend=backend, **kw)
    finally:
        del backend.first_launch_packets
    for other in (regions, many):
        for key in ("raw_sum", "counts", "peel_image", "peel_stokes"):
            np.testing.assert_array_equal(getattr(other, key), getattr(plain, key), err_msg=key)
    c = plain.counts[0]
    assert c[0] == 12_000 and c[0] == c[1] + c[2] + c[3]
    assert plain.peel_stokes.shape == (1, 3) + cam.size
    assert np.all(np.abs(plain.peel_stokes[0]) <= plain.peel_image[0][None] * (1 + 1e-12))
    assert np.abs(plain.peel_stokes[0, 2]).max() > 0


def test_polarization_is_refused_where_it_cannot_run(backend):
    rho = np.ones((4, 4, 4), np.float32)
    with pytest.raises(SceneError, match="bands.peak_polarization"):
        trace(rho, one_band(), centre_star(), tau=1.0, photons=100, backend=backend,
              polarization=Polarization("white", peak=[0.3, 0.4]))
    with pytest.raises(SceneError, match="bands.peak_polarization"):
        Polarization("white", peak=1.2)
    with pytest.raises(SceneError, match="bands.polarization"):
        Polarization("Mie")
    with pytest.raises(SceneError, match="the grains' albedo"):  # bands without the grains' optics
        trace(rho, one_band(), centre_star(), tau=1.0, photons=100, backend=backend, polarization=Polarization("mie"))
