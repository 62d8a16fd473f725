"""The sky image of a thin uniform sphere against single scattering (REFERENCES.md).

Sphere of radius R = 0.4 about the star, optical depth tau_R = kappa R = 0.02, albedo 0.5,
g = 0 (isotropic scattering: the sky image's isotropic emissivity is then exact). Single
scattering seen at projected offset b:

    I1(b) = omega kappa L / (4 pi b) Int_{theta_m}^{pi - theta_m} Phi dtheta,  Phi = 1 / (4 pi),

times the attenuation exp(-kappa (r + l_out)) along the way, here integrated numerically along
each pixel's chord (without attenuation the quadrature reproduces REFERENCES' 0.16667 at
b/R = 0.5). What single scattering leaves out and the grid adds is measured, not assumed:
- the grid: a run with albedo 1e-4 (J is then the star's direct light alone) against the same
  formula shows the voxelisation (partial-volume sphere, J averaged over 1/48-box voxels,
  piecewise-constant emissivity along the rays): within 2.5 % for b in [0.1, 0.35);
- light scattered more than once adds, relative to single scattering, between 0 and about
  omega tau_R (the chance of a second scattering), here 1 %; allowed up to 2 omega tau_R.
MC tolerance: 5 x the standard error of the mean of 4 seeds per annulus.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import centre_star, one_band
from nebula_rt.observe.sky import Camera, sky_image
from nebula_rt.transport import trace
from test_transport_physics import partial_volume_sphere

N = 48
R = 0.4
TAU_R = 0.02
OMEGA = 0.5
L = 1.0


def single_scattering(b, kappa, nodes=400):
    """I1 at projected offsets b (array), attenuation included, Gauss-Legendre on the chord."""
    x, w = np.polynomial.legendre.leggauss(nodes)
    b = np.asarray(b, float)
    half = np.sqrt(np.maximum(R * R - b * b, 0.0))
    z = half[..., None] * x  # along the line of sight, 0 at the plane of the star, + towards us
    r = np.sqrt(b[..., None] ** 2 + z**2)
    l_out = half[..., None] - z
    f = np.exp(-kappa * (r + l_out)) / (r * r)
    return OMEGA * kappa * L / (16 * math.pi**2) * (f * w).sum(axis=-1) * half


def test_reference_value_of_the_chord_integral():
    # without attenuation: I1 (4 pi b) / (omega kappa L) = Int Phi dtheta = 0.16667 at b/R = 0.5
    b = 0.5 * R
    x, w = np.polynomial.legendre.leggauss(400)
    half = math.sqrt(R * R - b * b)
    z = half * x
    integral = (w / (b * b + z * z)).sum() * half * b / (4 * math.pi)
    assert abs(integral - 0.16667) < 1e-5


def test_thin_sphere_image_is_single_scattering(backend):
    kappa = TAU_R / R
    rho = partial_volume_sphere((N, N, N), R)
    cam = Camera(direction=(0.0, 0.0, -1.0), size=(64, 64), extent=1.0)

    def image(albedo, seed):
        res = trace(rho, one_band(albedo=albedo, g=0.0), centre_star(L), tau=kappa, photons=400_000,
                    seed=seed, backend=backend)
        emis = albedo * kappa * rho.astype(np.float64)[None] * res.J
        return sky_image(emis, kappa * rho.astype(np.float64)[None], cam).scattered[0]

    images = [image(OMEGA, seed) for seed in range(1, 5)]
    direct_only = image(1e-4, 1)  # J is then the star's direct light alone (scattered ~1e-6)
    p = np.arange(64)
    P, Q = np.meshgrid(p, p, indexing="ij")
    img0 = sky_image(np.zeros((1, N, N, N)), np.zeros((1, N, N, N)), cam)
    cx = img0.origin[0] + img0.pixel_size * P
    cy = img0.origin[1] + img0.pixel_size * Q
    b = np.hypot(cx - 0.5, cy - 0.5)
    want_px = single_scattering(b, kappa)
    edges = np.array([0.1, 0.15, 0.2, 0.25, 0.3, 0.35])
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (b >= lo) & (b < hi)
        got = np.array([im[m].mean() for im in images])
        want = want_px[m].mean()
        se = got.std(ddof=1) / math.sqrt(len(got))
        grid = direct_only[m].mean() / (want * 1e-4 / OMEGA)
        assert abs(grid - 1) < 0.025, (lo, grid)
        excess = got.mean() / want / grid - 1  # multiple scattering
        assert -5 * se / want < excess < 2 * OMEGA * TAU_R + 5 * se / want, (lo, excess)
        assert abs(got.mean() / want - 1) < 5 * se / want + 0.025 + 2 * OMEGA * TAU_R, (lo, got.mean() / want)
        assert se / want < 0.01  # the test has teeth


# --------------------------------------------------------------------------------------------
# Peel-off images: the phase function's angle dependence (g != 0)
# --------------------------------------------------------------------------------------------
def single_scattering_hg(b, kappa, g, omega, nodes=400):
    """I1 with a Henyey-Greenstein phase function: the scattering angle at a point of the line
    of sight is that between the star's outgoing ray and the line of sight, cos = z / r."""
    x, w = np.polynomial.legendre.leggauss(nodes)
    b = np.asarray(b, float)
    half = np.sqrt(np.maximum(R * R - b * b, 0.0))
    z = half[..., None] * x  # towards the observer
    r = np.sqrt(b[..., None] ** 2 + z**2)
    phi = (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * z / r) ** 1.5)
    f = phi * np.exp(-kappa * (r + half[..., None] - z)) / (r * r)
    return omega * kappa * L / (4 * math.pi) * (f * w).sum(axis=-1) * half


@pytest.mark.parametrize("g", [0.0, 0.6])
@pytest.mark.filterwarnings("ignore::nebula_rt.errors.NebulaWarning")  # max_scatterings 1 on purpose
def test_peel_off_image_is_single_scattering_at_any_g(backend, g):
    """trace(peel=camera) with at most one scattering per packet (max_scatterings 1: a packet
    peels off at its first scattering and ends at its second interaction) is the single
    scattering image, phase function included; REFERENCES' integral at b/R = 0.5 checks the
    quadrature (0.12654 for g 0.6). Tolerance: 5 x the standard error of the mean of 4 seeds
    plus 1.5 % for the voxelised (partial-volume) sphere."""
    tau_r, omega = 0.05, 0.5
    kappa = tau_r / R
    rho = partial_volume_sphere((N, N, N), R)
    cam = Camera(direction=(0.0, 0.0, -1.0), size=(64, 64), extent=1.0)
    images = [trace(rho, one_band(albedo=omega, g=g), centre_star(L), tau=kappa, photons=1_500_000, seed=s,
                    backend=backend, peel=cam, max_scatterings=1, light_field=False).peel_image[0] for s in range(1, 5)]
    img0 = sky_image(np.zeros((1, N, N, N)), np.zeros((1, N, N, N)), cam)
    p = np.arange(64)
    P, Q = np.meshgrid(p, p, indexing="ij")
    b = np.hypot(img0.origin[0] + img0.pixel_size * P - 0.5, img0.origin[1] + img0.pixel_size * Q - 0.5)
    want_px = single_scattering_hg(b, kappa, g, omega)
    for lo, hi in zip([0.1, 0.175, 0.25], [0.175, 0.25, 0.35]):
        m = (b >= lo) & (b < hi)
        got = np.array([im[m].mean() for im in images])
        want = want_px[m].mean()
        se = got.std(ddof=1) / math.sqrt(len(got))
        assert abs(got.mean() / want - 1) < 5 * se / want + 0.015, (lo, got.mean() / want, se / want)
        assert se / want < 0.02
    # the reference integral itself, without attenuation
    bb, x = 0.5 * R, np.polynomial.legendre.leggauss(400)
    half = math.sqrt(R * R - bb * bb)
    z = half * x[0]
    r = np.sqrt(bb * bb + z * z)
    phi = (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * z / r) ** 1.5)
    integral = (x[1] * phi / (r * r)).sum() * half * bb
    assert abs(integral - {0.0: 0.16667, 0.6: 0.12654}[g]) < 1e-4


@pytest.mark.filterwarnings("ignore::nebula_rt.errors.NebulaWarning")  # max_scatterings 1 on purpose
def test_peel_off_keeps_weights_far_below_one_fixed_point_unit(backend):
    """g 0.999: the phase function falls by 2^-33 from forward to backward, and at projected
    offsets b >= R/2 of a central star every scattering angle exceeds about 28 deg, where a
    deposit is below 0.2 fixed-point units (2^24 units at the forward peak). Rounded to
    nearest, each would be 0 and the image there black; rounded stochastically (unbiased),
    the image is the single-scattering image. max_scatterings 1 makes the peel-off image
    exactly single scattering, attenuation included (tau_R = 0.5, albedo 1), so the reference
    is the chord integral. Tolerance: 5 standard errors of the mean of 4 seeds plus 1.5 % for
    the voxelised sphere, as in the test above."""
    from nebula_rt.transport.estimate import _peel_scale

    g, tau_r = 0.999, 0.5
    kappa = tau_r / R
    rho = partial_volume_sphere((N, N, N), R)
    cam = Camera(direction=(0.0, 0.0, -1.0), size=(64, 64), extent=1.0)
    images = [trace(rho, one_band(albedo=1.0, g=g), centre_star(L), tau=kappa, photons=2_500_000, seed=s,
                    backend=backend, peel=cam, max_scatterings=1, light_field=False).peel_image[0] for s in range(1, 5)]
    img0 = sky_image(np.zeros((1, N, N, N)), np.zeros((1, N, N, N)), cam)
    p = np.arange(64)
    P, Q = np.meshgrid(p, p, indexing="ij")
    b = np.hypot(img0.origin[0] + img0.pixel_size * P - 0.5, img0.origin[1] + img0.pixel_size * Q - 0.5)
    want_px = single_scattering_hg(b, kappa, g, 1.0)
    # the largest deposit at b >= R/2: smallest angle, from a point half a pixel nearer the
    # star in projection and one voxel diagonal beyond the sphere along the line of sight
    b_min = 0.5 * R - img0.pixel_size / math.sqrt(2.0)
    z_max = math.sqrt(R * R - (0.5 * R) ** 2) + math.sqrt(3.0) / N
    mu = z_max / math.hypot(b_min, z_max)
    phase = (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * mu) ** 1.5)
    assert phase * _peel_scale([g]) < 0.2  # every deposit there is far below half a unit
    for lo, hi in ((0.5 * R, 0.65 * R), (0.65 * R, 0.8 * R)):
        m = (b >= lo) & (b < hi)
        got = np.array([im[m].mean() for im in images])
        want = want_px[m].mean()
        se = got.std(ddof=1) / math.sqrt(len(got))
        assert abs(got.mean() / want - 1) < 5 * se / want + 0.015, (lo, got.mean() / want, se / want)
        assert se / want < 0.04  # the test has teeth: rounded to nearest, got would be 0


def test_peel_off_rounding_is_deterministic_and_leaves_the_transport_alone(backend):
    """The stochastic rounding draws from its own Philox counters: the same seed gives the same
    image bits, another seed another image, and the packets' random numbers (hence J's sums
    and the tallies) are those of a run without a camera. Bad pixel groups are refused."""
    rho = partial_volume_sphere((16, 16, 16), R)
    cam = Camera(direction=(0.3, -0.2, -1.0), size=(20, 16), extent=1.0)
    kw = dict(tau=2.0, photons=20_000, backend=backend)
    a = trace(rho, one_band(g=0.9), centre_star(L), seed=3, peel=cam, **kw)
    b = trace(rho, one_band(g=0.9), centre_star(L), seed=3, peel=cam, **kw)
    c = trace(rho, one_band(g=0.9), centre_star(L), seed=4, peel=cam, **kw)
    plain = trace(rho, one_band(g=0.9), centre_star(L), seed=3, **kw)
    np.testing.assert_array_equal(a.peel_image, b.peel_image)
    np.testing.assert_array_equal(a.peel_error, b.peel_error)
    assert not np.array_equal(a.peel_image, c.peel_image)
    np.testing.assert_array_equal(a.raw_sum, plain.raw_sum)
    np.testing.assert_array_equal(a.counts, plain.counts)
    with pytest.raises(ValueError, match="peel_bins"):
        trace(rho, one_band(g=0.9), centre_star(L), seed=3, peel=cam, peel_bins=np.zeros((16, 20), int), **kw)
