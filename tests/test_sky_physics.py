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
from nebula_rt.sky import Camera, sky_image
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
                    backend=backend, peel=cam, max_scatterings=1).peel_image[0] for s in range(1, 5)]
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
