"""Polarized scattering as the transport kernel runs it (kernels/polarization.cl, float32).

The expected values are written here from their sources, not from the kernel: Rayleigh's
matrix (Chandrasekhar 1960; Bohren & Huffman 1983, eq. 5.8), White's (1979, ApJ 229, 954)
approximation, the inverse of Rayleigh's cumulative distribution, the joint density of the
scattering angles of polarized light, S11 (1 + s12 (q cos 2 phi + u sin 2 phi)), integrated
exactly over bins, and the geometry of dipole scattering (the electric vector of singly
scattered unpolarized light is perpendicular to the scattering plane). Histogram tests use
Pearson's chi^2 against its distribution (p > 1e-4 on fixed seeds).
"""

import numpy as np
import pytest
from scipy import stats

from nebula_rt.backends import probes
from nebula_rt.optics.polarization import Polarization

RAYLEIGH = Polarization("rayleigh")


def white(p_l):
    return Polarization("white", peak=p_l)


def hg(mu, g):
    return (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * mu) ** 1.5)


# (the cosines as float32 holds them: the oracle at the same points)
MU = np.linspace(-1.0, 1.0, 201).astype(np.float32).astype(np.float64)


def test_rayleigh_matrix(backend):
    """S11 = 3 (1 + mu^2) / (16 pi) (normalised over the sphere), and unpolarized light is
    polarized by sin^2 / (1 + cos^2), fully at 90 degrees; S33 / S11 = 2 mu / (1 + mu^2)."""
    m = probes.mueller_at(backend, RAYLEIGH, MU).astype(np.float64)
    np.testing.assert_allclose(m[:, 0], 3 * (1 + MU**2) / (16 * np.pi), rtol=2e-6)
    np.testing.assert_allclose(-m[:, 1], (1 - MU**2) / (1 + MU**2), atol=2e-6)
    np.testing.assert_allclose(m[:, 2], 2 * MU / (1 + MU**2), atol=2e-6)
    assert np.all(m[:, 3] == 0)
    assert -m[100, 1] == pytest.approx(1.0, abs=1e-7)  # mu = 0
    # a pure scatterer: S12^2 + S33^2 = S11^2
    np.testing.assert_allclose(m[:, 1] ** 2 + m[:, 2] ** 2, 1.0, atol=5e-6)
    # the phase function integrates to 1 over the sphere (2 pi int dmu)
    assert 2 * np.pi * np.trapezoid(m[:, 0], MU) == pytest.approx(1.0, abs=1e-4)


@pytest.mark.parametrize("g, p_l", [(0.6, 0.5), (-0.3, 0.25), (0.0, 1.0), (0.9, 0.0)])
def test_white_matrix(backend, g, p_l):
    """White's approximation: the HG phase function, -S12 / S11 = p_l sin^2 / (1 + cos^2)
    (p_l at 90 degrees) and Rayleigh's S33 / S11; never more than fully polarizing."""
    m = probes.mueller_at(backend, white(p_l), MU, g=g).astype(np.float64)
    np.testing.assert_allclose(m[:, 0], hg(MU, g), rtol=1e-5)
    np.testing.assert_allclose(-m[:, 1], p_l * (1 - MU**2) / (1 + MU**2), atol=2e-6)
    np.testing.assert_allclose(m[:, 2], 2 * MU / (1 + MU**2), atol=2e-6)
    assert -m[100, 1] == pytest.approx(p_l, abs=1e-7)
    assert np.all(m[:, 1] ** 2 + m[:, 2] ** 2 + m[:, 3] ** 2 <= 1 + 5e-6)


def test_rayleigh_scattering_cosine_inverts_its_distribution(backend):
    """mu(xi) solves F(mu) = (mu^3 + 3 mu + 4) / 8 = xi (the cumulative distribution of
    3 (1 + mu^2) / 8) at every xi, the extremes included, and grows with xi."""
    xi = np.concatenate([[0.0, 2.0**-24, 0.5, 1 - 2.0**-24], np.linspace(0, 1 - 2.0**-24, 100_001)]).astype(np.float32)
    mu = probes.rayleigh_mu_at(backend, xi).astype(np.float64)
    assert np.all(np.abs(mu) <= 1.0)
    cdf = (mu**3 + 3 * mu + 4) / 8
    np.testing.assert_allclose(cdf, xi.astype(np.float64), atol=3e-7)
    order = np.argsort(xi[4:], kind="stable")
    assert np.all(np.diff(mu[4:][order]) >= 0)


def _bin_probabilities(kind_s11, kind_s12, q, u, mu_edges, phi_edges):
    """Exact probabilities of (mu, phi) bins under S11(mu) (1 + s12(mu) (q cos 2phi + u sin 2phi))
    for S11 and S11 s12 given as antiderivatives in mu."""
    a = np.diff(kind_s11(mu_edges))                      # int S11 dmu
    b = np.diff(kind_s12(mu_edges))                      # int S11 s12 dmu
    dphi = np.diff(phi_edges)
    c = np.diff(np.sin(2 * phi_edges)) / 2               # int cos 2phi dphi
    s = -np.diff(np.cos(2 * phi_edges)) / 2              # int sin 2phi dphi
    p = a[:, None] * dphi[None, :] + b[:, None] * (q * c + u * s)[None, :]
    return p / p.sum()


@pytest.mark.parametrize("q, u", [(0.0, 0.0), (1.0, 0.0), (0.0, -1.0), (0.6, 0.3)])
def test_rayleigh_scattering_of_polarized_light(backend, q, u):
    """The scattering angles of light with Stokes state (q, u) follow S11 (1 + s12 (q cos 2phi +
    u sin 2phi)), phi from the reference direction towards d x e (here from +x to +y); the new
    state of unpolarized light is q' = s12(mu) in the scattering plane's frame, and the new
    reference is a unit vector perpendicular to the new direction."""
    n = 400_000
    out = probes.scatter_polarized_from(backend, RAYLEIGH, q, u, seed=7, n=n).astype(np.float64)
    d, e = out[:, :3], out[:, 3:6]
    mu, phi = d[:, 2], np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
    mu_edges, phi_edges = np.linspace(-1, 1, 11), np.linspace(0, 2 * np.pi, 13)
    counts, _, _ = np.histogram2d(mu, phi, bins=[mu_edges, phi_edges])
    # antiderivatives of 3 (1 + mu^2) / 16 pi and of 3 (1 + mu^2) / 16 pi x -(1 - mu^2) / (1 + mu^2)
    p = _bin_probabilities(lambda m: m + m**3 / 3, lambda m: -(m - m**3 / 3), q, u, mu_edges, phi_edges)
    chi2, pval = stats.chisquare(counts.ravel(), n * p.ravel())
    assert pval > 1e-4, (chi2, pval)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(e, axis=1), 1.0, atol=1e-6)
    assert np.max(np.abs(np.sum(d * e, axis=1))) < 1e-6
    assert np.all(out[:, 6] ** 2 + out[:, 7] ** 2 <= 1 + 1e-6)
    if q == u == 0.0:
        np.testing.assert_allclose(out[:, 6], -(1 - mu**2) / (1 + mu**2), atol=2e-6)
        np.testing.assert_allclose(out[:, 7], 0.0, atol=2e-6)
    elif q * q + u * u == 1.0:  # fully polarized: a dipole's field is E's part perpendicular to d'
        chi_in = 0.5 * np.arctan2(u, q)
        field = np.array([np.cos(chi_in), np.sin(chi_in), 0.0])
        perp = field[None, :] - (d @ field)[:, None] * d
        k = perp / np.linalg.norm(perp, axis=1, keepdims=True)
        chi = np.arctan2(np.sum(k * np.cross(d, e), axis=1), np.sum(k * e, axis=1))
        # (along E itself the angle is undefined, and no light goes there; near it float32 loses digits)
        keep = np.linalg.norm(perp, axis=1) > 0.05
        np.testing.assert_allclose(out[keep, 6], np.cos(2 * chi[keep]), atol=2e-5)
        np.testing.assert_allclose(out[keep, 7], np.sin(2 * chi[keep]), atol=2e-5)


def test_white_scattering_follows_hg_and_its_polarization(backend):
    """White's kind samples mu from the HG phase function, and the azimuth of fully polarized
    light by its s12 = -p_l sin^2 / (1 + cos^2)."""
    g, p_l, n = 0.5, 0.5, 400_000
    out = probes.scatter_polarized_from(backend, white(p_l), 1.0, 0.0, seed=9, n=n, g=g).astype(np.float64)
    mu, phi = out[:, 2], np.mod(np.arctan2(out[:, 1], out[:, 0]), 2 * np.pi)
    mu_edges, phi_edges = np.linspace(-1, 1, 11), np.linspace(0, 2 * np.pi, 13)
    counts, _, _ = np.histogram2d(mu, phi, bins=[mu_edges, phi_edges])
    from scipy import integrate

    def s11_cdf(m):
        return np.array([integrate.quad(lambda x: 2 * np.pi * hg(x, g), -1, v)[0] for v in np.atleast_1d(m)])

    def s12_cdf(m):
        return np.array([integrate.quad(lambda x: -2 * np.pi * hg(x, g) * p_l * (1 - x * x) / (1 + x * x), -1, v)[0]
                         for v in np.atleast_1d(m)])

    p = _bin_probabilities(s11_cdf, s12_cdf, 1.0, 0.0, mu_edges, phi_edges)
    chi2, pval = stats.chisquare(counts.ravel(), n * p.ravel())
    assert pval > 1e-4, (chi2, pval)


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_peel_off_stokes_in_the_observers_frame(backend):
    """Unpolarized light scattered towards o is polarized by -S12 / S11 with its electric
    vector along d x o (perpendicular to the scattering plane); Q and U give that vector's
    angle from north towards east, east = o x north (IAU). Polarized light along +z with
    q = 1 (electric vector along +x) sends S11 (1 + s12 cos 2phi) towards azimuth phi."""
    rng = np.random.default_rng(5)
    n = 2000
    d = _unit(rng.normal(size=(n, 3)))
    o = _unit(rng.normal(size=(n, 3)))
    north = _unit(np.cross(o, _unit(rng.normal(size=(n, 3)))))  # any unit vector perpendicular to o
    e = _unit(np.cross(d, _unit(rng.normal(size=(n, 3)))))      # any reference perpendicular to d
    out = probes.peel_stokes_at(backend, RAYLEIGH, d, e, o, north, np.zeros((n, 2))).astype(np.float64)
    mu = np.sum(d * o, axis=1)
    s11 = 3 * (1 + mu**2) / (16 * np.pi)
    p = (1 - mu**2) / (1 + mu**2)
    k = _unit(np.cross(d, o))
    east = np.cross(o, north)
    chi = np.arctan2(np.sum(k * east, axis=1), np.sum(k * north, axis=1))
    np.testing.assert_allclose(out[:, 0], s11, rtol=1e-5)
    np.testing.assert_allclose(out[:, 1], s11 * p * np.cos(2 * chi), atol=2e-6)
    np.testing.assert_allclose(out[:, 2], s11 * p * np.sin(2 * chi), atol=2e-6)
    # a state referred to another reference: the same light, the same answer (e -> -e, and a
    # fully polarized beam along z seen from every azimuth)
    out2 = probes.peel_stokes_at(backend, RAYLEIGH, d, -e, o, north, np.zeros((n, 2))).astype(np.float64)
    np.testing.assert_allclose(out2, out, atol=2e-6)
    z = np.tile([0.0, 0.0, 1.0], (n, 1))
    x = np.tile([1.0, 0.0, 0.0], (n, 1))
    out3 = probes.peel_stokes_at(backend, RAYLEIGH, z, x, o, north, np.tile([1.0, 0.0], (n, 1))).astype(np.float64)
    phi = np.arctan2(o[:, 1], o[:, 0])
    mu = o[:, 2]
    np.testing.assert_allclose(out3[:, 0], 3 / (16 * np.pi) * ((1 + mu**2) - (1 - mu**2) * np.cos(2 * phi)),
                               atol=2e-6)
    assert np.all(np.hypot(out3[:, 1], out3[:, 2]) <= out3[:, 0] * (1 + 1e-5) + 1e-7)


def test_peel_off_of_polarized_light_is_dipole_radiation(backend):
    """Fully linearly polarized light (electric vector E along angle chi from the reference e
    towards d x e: q = cos 2chi, u = sin 2chi) scattered by a dipole towards o: the scattered
    field is E's part perpendicular to o, so the intensity is 3 / (8 pi) (1 - (E . o)^2) and the
    light stays fully polarized along that part; its angle from north towards east gives Q and
    U (the field built here as a vector, not through Stokes rotations)."""
    rng = np.random.default_rng(8)
    n = 2000
    d = _unit(rng.normal(size=(n, 3)))
    o = _unit(rng.normal(size=(n, 3)))
    north = _unit(np.cross(o, _unit(rng.normal(size=(n, 3)))))
    e = _unit(np.cross(d, _unit(rng.normal(size=(n, 3)))))
    chi_in = rng.uniform(0, np.pi, n)
    field = np.cos(chi_in)[:, None] * e + np.sin(chi_in)[:, None] * np.cross(d, e)
    qu = np.stack([np.cos(2 * chi_in), np.sin(2 * chi_in)], axis=1)
    out = probes.peel_stokes_at(backend, RAYLEIGH, d, e, o, north, qu).astype(np.float64)
    perp = field - np.sum(field * o, axis=1)[:, None] * o
    intensity = 3 / (8 * np.pi) * np.sum(perp * perp, axis=1)
    k = _unit(perp)
    chi = np.arctan2(np.sum(k * np.cross(o, north), axis=1), np.sum(k * north, axis=1))
    np.testing.assert_allclose(out[:, 0], intensity, atol=3e-6)
    np.testing.assert_allclose(out[:, 1], intensity * np.cos(2 * chi), atol=3e-6)
    np.testing.assert_allclose(out[:, 2], intensity * np.sin(2 * chi), atol=3e-6)
