"""Mie grains (``bands.polarization = "mie"``, nebula_rt.optics.mie and kernels/polarization.cl)
against answers neither made:

- the matrix of one sphere against Bohren & Huffman's published BHMIE example (1983, Appendix
  A: m = 1.55, x = 5.213; S11 normalised forward, -S12 / S11, S33 / S11, S34 / S11 every 9
  degrees, printed to 6 digits, as transcribed in miepython's tests/test_mie.py) and its
  efficiencies (Q_sca = Q_ext = 3.10543, g = 0.63314);
- a size distribution's albedo and g against scipy's adaptive quadrature of the efficiencies
  over the power law (independent of the module's own nodes);
- the kernel's table against the exact S11 between its nodes, and its normalisation;
- the kernel's scattering angles against exact bin probabilities of the exact S11 (chi^2), the
  azimuths of polarized light by 1 + s12 (q cos 2phi + u sin 2phi), and the new Stokes vector,
  V included, against Bohren & Huffman's matrix product with the exact Mie elements.
"""

from __future__ import annotations

import math

import miepython
import numpy as np
import pytest
from scipy import integrate, stats

from nebula_rt.backends import probes
from nebula_rt.errors import SceneError
from nebula_rt.optics.mie import Grains, mie_bands, mie_optics
from nebula_rt.optics.bands import Band
from nebula_rt.optics.polarization import Polarization

#: Bohren & Huffman (1983), Appendix A, the BHMIE example: angle, S11 / S11(0), -S12 / S11 (POL),
#: S33 / S11, S34 / S11
BH_TABLE = np.array([
    [0.0, 1.0, 0.0, 1.0, 0.0],
    [9.0, 0.785390, -0.459811e-02, 0.999400, 0.343261e-01],
    [18.0, 0.356897, -0.458541e-01, 0.986022, 0.160184],
    [27.0, 0.766119e-01, -0.364744, 0.843603, 0.394076],
    [36.0, 0.355355e-01, -0.534997, 0.686967, -0.491787],
    [45.0, 0.701845e-01, 0.959953e-02, 0.959825, -0.280434],
    [54.0, 0.574313e-01, 0.477927e-01, 0.985371, 0.163584],
    [63.0, 0.219660e-01, -0.440604, 0.648043, 0.621216],
    [72.0, 0.125959e-01, -0.831996, 0.203255, -0.516208],
    [81.0, 0.173750e-01, 0.341670e-01, 0.795354, -0.605182],
    [90.0, 0.124601e-01, 0.230462, 0.937497, 0.260742],
    [99.0, 0.679093e-02, -0.713472, -0.717397e-02, 0.700647],
    [108.0, 0.954239e-02, -0.756255, -0.394748e-01, -0.653085],
    [117.0, 0.863419e-02, -0.281215, 0.536251, -0.795835],
    [126.0, 0.227421e-02, -0.239612, 0.967602, 0.795798e-01],
    [135.0, 0.543998e-02, -0.850804, 0.187531, -0.490882],
    [144.0, 0.160243e-01, -0.706334, 0.495254, -0.505781],
    [153.0, 0.188852e-01, -0.891081, 0.453277, -0.226817e-01],
    [162.0, 0.195254e-01, -0.783319, -0.391613, 0.482752],
    [171.0, 0.301676e-01, -0.196194, -0.962069, 0.189556],
    [180.0, 0.383189e-01, 0.0, -1.0, 0.0],
])
#: the example's sphere: radius 0.525 micron, m = 1.55, wavelength 0.6328 micron (x = 5.2128)
WAVELENGTH = 632.8  # nm
BH_GRAINS = Grains(n=1.55, k=0.0, radius_min=0.525, radius_max=0.525)


def test_one_sphere_matches_bohren_and_huffman():
    optics = mie_optics(BH_GRAINS, [WAVELENGTH])
    t = optics.table[0]
    i = (BH_TABLE[:, 0] * 4).astype(int)  # the table's nodes every 0.25 degree
    np.testing.assert_allclose(np.degrees(np.arccos(np.clip(t[0, i], -1, 1))), BH_TABLE[:, 0], atol=1e-6)
    # within the printed digits (6 significant)
    np.testing.assert_allclose(t[2, i] / t[2, 0], BH_TABLE[:, 1], rtol=2e-6, atol=1e-7)
    np.testing.assert_allclose(-t[3, i], BH_TABLE[:, 2], atol=2e-6)
    np.testing.assert_allclose(t[4, i], BH_TABLE[:, 3], atol=2e-6)
    np.testing.assert_allclose(t[5, i], BH_TABLE[:, 4], atol=2e-6)
    a = BH_GRAINS.radius_min
    assert optics.c_sca[0] / (math.pi * a * a) == pytest.approx(3.10543, abs=1e-5)
    assert optics.c_ext[0] / (math.pi * a * a) == pytest.approx(3.10543, abs=1e-5)
    assert optics.g[0] == pytest.approx(0.63314, abs=1e-5)
    assert optics.albedo[0] == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("q", [3.5, 2.0])
def test_size_distribution_against_adaptive_quadrature(q):
    """C_ext, C_sca and g of a power law from scipy's quad of the efficiencies over a (the
    module uses its own nodes in ln a): within 2e-4."""
    grains = Grains(n=1.7, k=0.03, radius_min=0.01, radius_max=0.4, size_slope=q)
    wl = 500.0
    k = 2 * math.pi / (wl * 1e-3)
    m = complex(1.7, -0.03)  # miepython's sign of k

    def eff(a, which):
        qe, qs, _, g = miepython.efficiencies_mx(m, k * a)
        return {"ext": qe, "sca": qs, "gsca": qs * g}[which] * math.pi * a * a * a ** -q

    norm = integrate.quad(lambda a: a ** -q, 0.01, 0.4)[0]
    ext, sca, gsca = (integrate.quad(eff, 0.01, 0.4, args=(w,), limit=400, epsrel=1e-9)[0] / norm
                      for w in ("ext", "sca", "gsca"))
    o = mie_optics(grains, [wl])
    assert o.c_ext[0] == pytest.approx(ext, rel=2e-4)
    assert o.c_sca[0] == pytest.approx(sca, rel=2e-4)
    assert o.albedo[0] == pytest.approx(sca / ext, rel=2e-4)
    assert o.g[0] == pytest.approx(gsca / sca, rel=2e-4)
    # the tabulated phase function's mean cosine is the grains' g (the table resolves S11)
    t = o.table[0]
    mean_cos = integrate.trapezoid(t[0] * t[2], t[0]) * -1.0
    assert mean_cos == pytest.approx(o.g[0], abs=2e-4)


def test_table_between_its_nodes_and_its_normalisation():
    """p(mu) linear between the nodes against the exact S11 of one sphere at the midpoints
    (x = 12, a strong forward peak and deep minima): within 0.6 % (the curvature between nodes
    0.25 degree apart); the cumulative probability runs from 0 to 1, and p integrates to 1."""
    lam = 0.5
    a = 12.0 * lam / (2 * math.pi)
    grains = Grains(n=1.5, k=0.01, radius_min=a, radius_max=a)
    t = mie_optics(grains, [lam * 1e3]).table[0]
    mid_theta = 0.5 * (np.arccos(np.clip(t[0, 1:], -1, 1)) + np.arccos(np.clip(t[0, :-1], -1, 1)))
    mu = np.cos(mid_theta)
    s1, s2 = miepython.S1_S2(complex(1.5, -0.01), 12.0, mu, norm="wiscombe")
    qe, qs, _, _ = miepython.efficiencies_mx(complex(1.5, -0.01), 12.0)
    exact = (np.abs(s1) ** 2 + np.abs(s2) ** 2) / 2 / (math.pi * 12.0**2 * qs) * 2 * math.pi  # p(mu), int = 1
    frac = (mu - t[0, 1:]) / (t[0, :-1] - t[0, 1:])
    linear = t[2, 1:] + frac * (t[2, :-1] - t[2, 1:])
    np.testing.assert_allclose(linear, exact, rtol=6e-3)
    assert t[1, 0] == 0.0 and t[1, -1] == 1.0 and np.all(np.diff(t[1]) >= 0)
    assert integrate.trapezoid(t[2], t[0]) * -1.0 == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("x", [50.0, 199.0])
def test_large_spheres_get_finer_angles(x):
    """Beyond size parameter 50 the table's steps shrink with x (the forward peak is about 1 / x
    radian wide): at x = 199, 2881 angles. One sphere's minima are then too deep and narrow for
    any fixed grid, but the probability the piecewise-linear p puts in the wrong place,
    int |p_table - p_exact| dmu at the midpoints, stays below 1 %."""
    lam = 0.5
    a = x * lam / (2 * math.pi)
    t = mie_optics(Grains(n=1.5, k=0.01, radius_min=a, radius_max=a), [lam * 1e3]).table[0]
    assert t.shape[-1] == 1 + 720 * math.ceil(x / 50.0)
    mid = 0.5 * (np.arccos(np.clip(t[0, 1:], -1, 1)) + np.arccos(np.clip(t[0, :-1], -1, 1)))
    mu = np.cos(mid)
    s1, s2 = miepython.S1_S2(complex(1.5, -0.01), x, mu, norm="wiscombe")
    _, qs, _, _ = miepython.efficiencies_mx(complex(1.5, -0.01), x)
    exact = (np.abs(s1) ** 2 + np.abs(s2) ** 2) / (x * x * qs)  # 2 pi S11
    frac = (mu - t[0, 1:]) / (t[0, :-1] - t[0, 1:])
    linear = t[2, 1:] + frac * (t[2, :-1] - t[2, 1:])
    assert np.sum(np.abs(linear - exact) * (t[0, :-1] - t[0, 1:])) < 0.01


def _exact(grains, lam_nm, mu):
    """S11 (per sr, over the sphere 1) and S12/S11, S33/S11, S34/S11 of one sphere from miepython
    directly (Bohren & Huffman's signs: S34 from m = n - i k's S1 S2*)."""
    a = grains.radius_min
    x = 2 * math.pi * a / (lam_nm * 1e-3)
    m = complex(grains.n, -grains.k)
    s1, s2 = miepython.S1_S2(m, x, mu, norm="wiscombe")
    _, qs, _, _ = miepython.efficiencies_mx(m, x)
    s11 = (np.abs(s1) ** 2 + np.abs(s2) ** 2) / 2
    c = s1 * np.conj(s2)
    return s11 / (math.pi * x * x * qs), (np.abs(s2) ** 2 - np.abs(s1) ** 2) / 2 / s11, c.real / s11, c.imag / s11


GRAINS = Grains(n=1.6, k=0.02, radius_min=0.3, radius_max=0.3)  # x = 3.4 at 550 nm
MIE = Polarization("mie", grains=GRAINS)


def test_kernel_matrix_is_the_exact_one(backend):
    mu = np.linspace(-1, 1, 801)
    m = probes.mueller_at(backend, MIE, mu, wavelength=550.0).astype(np.float64)
    s11, r12, r33, r34 = _exact(GRAINS, 550.0, mu)
    np.testing.assert_allclose(m[:, 0], s11, rtol=2e-3)
    for k, r in ((1, r12), (2, r33), (3, r34)):
        np.testing.assert_allclose(m[:, k], r, atol=2e-3)
    assert np.all(m[:, 1] ** 2 + m[:, 2] ** 2 + m[:, 3] ** 2 <= 1 + 1e-5)


@pytest.mark.parametrize("q, u", [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)])
def test_kernel_scattering_follows_the_exact_matrix(backend, q, u):
    """(mu, phi) of 400k scatterings against the exact bin probabilities of
    S11 (1 + s12 (q cos 2phi + u sin 2phi)) (chi^2), phi from +x towards +y; the new Stokes
    vector against Bohren & Huffman's product at each packet's own angles: in the scattering
    plane's frame (q_r, u_r) = (q cos 2phi + u sin 2phi, -q sin 2phi + u cos 2phi) becomes
    (s12 + q_r, s33 u_r, -s34 u_r) / (1 + s12 q_r) -- V from U through S34."""
    n = 400_000
    out = probes.scatter_polarized_from(backend, MIE, q, u, seed=11, n=n, wavelength=550.0).astype(np.float64)
    d, e = out[:, :3], out[:, 3:6]
    mu, phi = d[:, 2], np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
    mu_edges = np.cos(np.radians(np.linspace(0, 180, 13)))[::-1]
    phi_edges = np.linspace(0, 2 * np.pi, 9)
    counts, _, _ = np.histogram2d(mu, phi, bins=[mu_edges, phi_edges])
    fine = np.linspace(-1, 1, 200_001)
    s11, r12, _, _ = _exact(GRAINS, 550.0, fine)
    cum_i = integrate.cumulative_trapezoid(2 * math.pi * s11, fine, initial=0.0)
    cum_p = integrate.cumulative_trapezoid(2 * math.pi * s11 * r12, fine, initial=0.0)
    pi_mu = np.diff(np.interp(mu_edges, fine, cum_i))
    pp_mu = np.diff(np.interp(mu_edges, fine, cum_p))
    c2 = (np.sin(2 * phi_edges[1:]) - np.sin(2 * phi_edges[:-1])) / 2
    s2 = -(np.cos(2 * phi_edges[1:]) - np.cos(2 * phi_edges[:-1])) / 2
    p = (pi_mu[:, None] * np.diff(phi_edges)[None, :] + pp_mu[:, None] * (q * c2 + u * s2)[None, :]) / (2 * math.pi)
    assert p.sum() == pytest.approx(1.0, abs=1e-6)
    chi2, pval = stats.chisquare(counts.ravel(), n * p.ravel())
    assert pval > 1e-4, (chi2, pval)
    np.testing.assert_allclose(np.linalg.norm(e, axis=1), 1.0, atol=1e-5)
    assert np.max(np.abs(np.sum(d * e, axis=1))) < 1e-5
    # the new state, in the new frame (e' in the scattering plane: the product's own frame)
    _, r12, r33, r34 = _exact(GRAINS, 550.0, mu)
    qr = q * np.cos(2 * phi) + u * np.sin(2 * phi)
    ur = -q * np.sin(2 * phi) + u * np.cos(2 * phi)
    den = 1 + r12 * qr
    keep = np.abs(mu) < 0.999  # (the azimuth of a packet along the axis is lost in float32)
    for col, expect in ((6, (r12 + qr) / den), (7, r33 * ur / den), (8, -r34 * ur / den)):
        err = np.abs(out[keep, col] - expect[keep])
        assert np.max(err) < 1e-2 and np.median(err) < 5e-4, (col, np.max(err), np.median(err))
    if u:
        assert np.max(np.abs(out[:, 8])) > 0.3  # circular polarization made from linear
    else:
        assert np.all(out[:, 8] == 0.0) if q == 0 else True


def test_refractive_index_from_the_shipped_table():
    """astronomical silicate at its own tabulated wavelengths (Draine 2003 via optool)."""
    m = Grains().refractive_index([550.0621, 999.871])
    np.testing.assert_allclose(m.real, [1.6904, 1.6863], rtol=1e-6)
    np.testing.assert_allclose(m.imag, [0.02986, 0.03077], rtol=1e-6)


def test_mie_bands_and_refusals():
    bands = [Band("B", 440.0, 1.3, 0.5, 0.5), Band("V", 550.0, 1.0, 0.5, 0.5)]
    out = mie_bands(bands, Grains())
    assert out[1].extinction == 1.0 and out[0].extinction > 1.0  # small grains: bluer extinction
    assert all(0.5 < b.albedo < 1.0 and 0.3 < b.g < 0.8 for b in out)
    with pytest.raises(SceneError, match="bands.grain_k"):
        Grains(n=1.5, k=[0.1, 0.1]).refractive_index([440.0])  # a list of another length
    with pytest.raises(SceneError, match="bands.grain_radius_max"):
        Grains(radius_min=0.2, radius_max=0.1)
    with pytest.raises(SceneError, match="bands.grain_material"):
        Grains().refractive_index([0.01])  # below the table's 0.062 nm
    with pytest.raises(SceneError, match="bands.grain_radius_max"):
        mie_optics(Grains(radius_min=10.0, radius_max=20.0), [400.0])  # size parameter 314, beyond 200
    with pytest.raises(SceneError, match="scatter nothing"):
        mie_optics(Grains(n=1.0, k=0.0, radius_min=0.1, radius_max=0.1), [550.0])  # m = 1


@pytest.mark.parametrize("quv", [(0.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.3, 0.0, 0.9), (-0.5, 0.5, -0.5)])
def test_kernel_peel_off_is_the_matrix_product(backend, quv):
    """A packet along +z with state (q, u, v) referred to +x peels off towards o in the x-z
    plane (the scattering plane holds the reference: no rotation in), read in the frame whose
    north is the outgoing reference mu e1 - sin(theta) d (no rotation out): (I, Q, U, V) =
    S11 (1 + s12 q, s12 + q, s33 u + s34 v, -s34 u + s33 v) with the exact Mie elements."""
    theta = np.radians(np.linspace(3.0, 177.0, 59))
    n = theta.size
    d = np.tile([0.0, 0.0, 1.0], (n, 1))
    e = np.tile([1.0, 0.0, 0.0], (n, 1))
    o = np.stack([np.sin(theta), np.zeros(n), np.cos(theta)], axis=1)
    north = np.stack([np.cos(theta), np.zeros(n), -np.sin(theta)], axis=1)
    out = probes.peel_stokes_at(backend, MIE, d, e, o, north, np.tile(quv, (n, 1)), wavelength=550.0).astype(np.float64)
    s11, s12, s33, s34 = _exact(GRAINS, 550.0, np.cos(theta))
    q, u, v = quv
    expect = s11[:, None] * np.stack([1 + s12 * q, s12 + q, s33 * u + s34 * v, -s34 * u + s33 * v], axis=1)
    np.testing.assert_allclose(out, expect, atol=4e-3 * s11.max(), rtol=4e-3)
    if u or v:
        assert np.max(np.abs(out[:, 3])) > 0.1 * s11.min()


def test_a_scene_with_mie_grains():
    """bands.polarization = "mie": the bands carry the grains' albedo, g and extinction (the
    reference band keeps extinction 1); what Mie grains fix themselves is refused by name."""
    from nebula_rt.scene import Scene

    base = {"grid": {"shape": [8, 8, 8]}, "bands": {"polarization": "mie", "grain_n": 1.6, "grain_k": 0.02,
                                                    "grain_radius_min": 0.3, "grain_radius_max": 0.3}}
    scene = Scene.from_dict(base)
    bands = scene.bands.resolve()
    ref = [b.name for b in bands].index("G")
    assert bands[ref].extinction == 1.0
    o = mie_optics(GRAINS, [b.wavelength for b in bands])
    np.testing.assert_allclose([b.albedo for b in bands], o.albedo)
    np.testing.assert_allclose([b.g for b in bands], o.g)
    np.testing.assert_allclose([b.extinction for b in bands], o.c_ext / o.c_ext[ref])
    for extra, key in (({"albedo": 0.5}, "bands.albedo"), ({"g": 0.5}, "bands.g")):
        with pytest.raises(SceneError, match=key):
            Scene.from_dict({**base, "bands": {**base["bands"], **extra}})
    with pytest.raises(SceneError, match="dust.hydrogen_density"):  # no dust-to-gas ratio
        Scene.from_dict({**base, "dust": {"hydrogen_density": 100.0}})
    with pytest.raises(SceneError, match="dust.mass_density"):  # n and k give no bulk density
        Scene.from_dict({**base, "grid": {"shape": [8, 8, 8], "length": "0.1 pc"}, "dust": {"mass_density": 1e-23}})
    # A_V and a mass density through the grains' own cross-sections (astronomical silicate: 3.3 g cm^-3,
    # Draine 2003 as optool's file states it; the V row of Draine's tables at 0.547 micron)
    sil = {"grid": {"shape": [8, 8, 8], "length": "0.1 pc"}, "bands": {"polarization": "mie"}}
    o = mie_optics(Grains(), [550.0, 547.0])
    a_v = Scene.from_dict({**sil, "dust": {"visual_extinction": 2.0}})
    assert a_v.dust.tau == pytest.approx(2.0 / (2.5 * math.log10(math.e)) * o.c_ext[0] / o.c_ext[1], rel=1e-12)
    rho = Scene.from_dict({**sil, "dust": {"mass_density": 1e-23}})
    grains_per_cm3 = 1e-23 / (3.3 * o.grain_volume * 1e-12)
    assert rho.dust.tau == pytest.approx(grains_per_cm3 * o.c_ext[0] * 1e-8 * 0.1 * 3.0856775814913673e18, rel=1e-9)
    with pytest.raises(SceneError, match="bands.grain_n"):  # a list of another length than the bands'
        Scene.from_dict({**base, "bands": {**base["bands"], "grain_n": [1.6, 1.6]}})
    with pytest.raises(SceneError, match="bands.grain_radius_max"):  # grains without Mie scattering
        Scene.from_dict({"bands": {"polarization": "white", "grain_radius_max": 1.0}})


def test_series_sum_is_miepythons_own():
    """The amplitudes summed here as matrix products are miepython's S1_S2, to rounding."""
    from nebula_rt.optics.mie import _amplitudes, _pi_tau

    mu = np.cos(np.linspace(0, np.pi, 181))
    for m, x in ((complex(1.7, -0.03), 0.05), (complex(1.33, -1e-8), 7.3), (complex(1.5, -1.0), 40.0)):
        an, bn = miepython.coefficients(m, x)
        pi_n, tau_n = _pi_tau(mu, len(an) + 5)
        s1, s2 = _amplitudes(an, bn, pi_n, tau_n)
        r1, r2 = miepython.S1_S2(m, x, mu, norm="wiscombe")
        np.testing.assert_allclose(s1, r1, rtol=1e-10, atol=1e-12 * np.abs(r1).max())
        np.testing.assert_allclose(s2, r2, rtol=1e-10, atol=1e-12 * np.abs(r2).max())


def test_explicit_bands_of_mie_grains():
    """[[bands.list]] with Mie grains: name and wavelength alone; the band nearest 550 nm is the
    reference (extinction 1, as a preset's); a band's own extinction, albedo or g is refused by
    name rather than overwritten."""
    from nebula_rt.scene import Scene

    table = [{"name": "B", "wavelength": 440.0}, {"name": "V", "wavelength": 551.0}, {"name": "I", "wavelength": 800.0}]
    scene = Scene.from_dict({"bands": {"polarization": "mie", "list": table}})
    bands = scene.bands.resolve()
    o = mie_optics(Grains(), [440.0, 551.0, 800.0])
    np.testing.assert_allclose([b.extinction for b in bands], o.c_ext / o.c_ext[1])
    np.testing.assert_allclose([b.albedo for b in bands], o.albedo)
    assert Scene.loads(scene.to_toml()) == scene
    for key, value in (("extinction", 1.2), ("albedo", 0.5), ("g", 0.3)):
        with pytest.raises(SceneError, match=rf"bands.list\[2\].{key}"):
            Scene.from_dict({"bands": {"polarization": "mie", "list": table[:2] + [{**table[2], key: value}]}})


def _field_peel(d, e, o, north, quv, grains=GRAINS, lam_nm=550.0):
    """What a fully polarized wave scatters towards o, from its electric field (no Stokes
    rotations or Mueller matrices): the incoming field in the packet's frame (e, d x e), the
    phase delta = atan2(v, u) on its second component (time dependence e^{-i omega t}), split
    into the parts parallel and perpendicular to the scattering plane (e_perp = d x o / |d x o|,
    e_par = k x e_perp for k = d and k = o, Bohren & Huffman's basis), scattered by their
    amplitudes S2 (parallel) and S1 (perpendicular) -- miepython's conjugated, its m being
    n - i k -- and read in the right-handed frame (north, east = o x north, o):
    I = |E_n|^2 + |E_e|^2, Q = |E_n|^2 - |E_e|^2, U = 2 Re E_n E_e*, V = -2 Im E_n E_e* (V > 0:
    the field turning from north to east, counterclockwise as the observer sees it: IAU 1974),
    per sr of the grains' scattering (S11 integrates to 1)."""
    a = grains.radius_min
    x = 2 * math.pi * a / (lam_nm * 1e-3)
    m = complex(grains.n, -grains.k)
    _, qs, _, _ = miepython.efficiencies_mx(m, x)
    out = []
    for di, ei, oi, ni, (q, u, v) in zip(d, e, o, north, quv):
        field = math.sqrt((1 + q) / 2) * ei + math.sqrt((1 - q) / 2) * np.exp(1j * math.atan2(v, u)) * np.cross(di, ei)
        mu = float(di @ oi)
        perp = np.cross(di, oi)
        perp /= np.linalg.norm(perp)
        s1, s2 = (np.conj(s)[0] for s in miepython.S1_S2(m, x, np.array([mu]), norm="wiscombe"))
        scattered = s2 * (field @ np.cross(di, perp)) * np.cross(oi, perp) + s1 * (field @ perp) * perp
        en, ee = scattered @ ni, scattered @ np.cross(oi, ni)
        stokes = np.array([abs(en) ** 2 + abs(ee) ** 2, abs(en) ** 2 - abs(ee) ** 2, 2 * (en * np.conj(ee)).real,
                           -2 * (en * np.conj(ee)).imag])
        out.append(stokes / (math.pi * x * x * qs))
    return np.array(out)


def test_kernel_peel_off_against_the_scattered_field(backend):
    """Random packets (direction, reference, fully polarized states with linear and circular
    parts) peeled off towards random observers with random north axes: the kernel's I, Q, U, V
    are those of the scattered electric field (:func:`_field_peel`), which shares nothing with
    the kernel's Stokes rotations and Mueller matrix. This fixes the signs: Q from north, U at 45
    degrees towards east, V > 0 for light turning counterclockwise as the observer sees it."""
    rng = np.random.default_rng(3)
    n = 200
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    e = np.cross(d, rng.normal(size=(n, 3)))
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    o = rng.normal(size=(n, 3))
    o /= np.linalg.norm(o, axis=1, keepdims=True)
    north = np.cross(o, rng.normal(size=(n, 3)))
    north /= np.linalg.norm(north, axis=1, keepdims=True)
    quv = rng.normal(size=(n, 3))
    quv /= np.linalg.norm(quv, axis=1, keepdims=True)
    got = probes.peel_stokes_at(backend, MIE, d, e, o, north, quv, wavelength=550.0).astype(np.float64)
    want = _field_peel(d, e, o, north, quv)
    np.testing.assert_allclose(got, want, atol=4e-3 * np.abs(want[:, 0]).max(), rtol=5e-3)
    assert np.max(np.abs(want[:, 3])) > 0.05 * np.abs(want[:, 0]).max()  # circular parts that matter


def test_small_spheres_scatter_as_dipoles(backend):
    """Grains far smaller than the wavelength (x = 0.011) are Rayleigh scatterers: the kernel's
    Mie table gives the matrix its rayleigh kind gives (whose formulas are tested on their own),
    to the table's and the x^2 terms' accuracy."""
    tiny = Polarization("mie", grains=Grains(n=1.5, k=0.0, radius_min=0.001, radius_max=0.001))
    mu = np.linspace(-1, 1, 401)
    mie = probes.mueller_at(backend, tiny, mu, wavelength=550.0).astype(np.float64)
    dipole = probes.mueller_at(backend, Polarization("rayleigh"), mu).astype(np.float64)
    np.testing.assert_allclose(mie[:, 0], dipole[:, 0], rtol=2e-4)
    np.testing.assert_allclose(mie[:, 1:], dipole[:, 1:], atol=2e-4)


def test_kernel_inverts_the_tables_distribution_exactly(backend):
    """nrt_mie_mu at given variates, those next to the guide table's cell edges j / 64 included
    (one float32 step either side), against the inverse of the piecewise-linear distribution in
    float64 NumPy (the interval by a search of the float32 table, then the quadratic's root): the
    guide table only shortens the search, the answer is the interval's."""
    from nebula_rt.optics.mie import GUIDE_CELLS

    grains = Grains(n=1.5, k=0.01, radius_min=1.0, radius_max=1.0)  # x = 11.4: a sharp forward peak
    pol = Polarization("mie", grains=grains)
    t = np.asarray(mie_optics(grains, [550.0]).table[0], np.float32).astype(np.float64)
    edges = np.arange(1, GUIDE_CELLS) / GUIDE_CELLS
    xi = np.concatenate([np.random.default_rng(5).random(20_000), edges,
                         np.nextafter(edges.astype(np.float32), np.float32(0)),
                         np.nextafter(edges.astype(np.float32), np.float32(1)), t[1, 1:-1]]).astype(np.float32)
    got = probes.mie_mu_at(backend, pol, xi, wavelength=550.0).astype(np.float64)
    x = xi.astype(np.float64)
    i = np.clip(np.searchsorted(t[1], x, side="right") - 1, 0, t.shape[1] - 2)
    h = t[0, i] - t[0, i + 1]
    c = (x - t[1, i]) / h
    p0, p1 = t[2, i], t[2, i + 1]
    s = 2 * c / (p0 + np.sqrt(np.maximum(p0 * p0 + 2 * (p1 - p0) * c, 0)))
    want = t[0, i] - np.minimum(s, 1) * h
    np.testing.assert_allclose(got, want, atol=2e-6)
