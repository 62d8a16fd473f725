"""The peel-off image of an asymmetric scene against single scattering integrated in NumPy.

tests/observe/test_sky_physics.py checks the peel-off on a thin sphere centred on the star, seen along
an axis: that scene is symmetric under most of the mistakes a peel-off can make (a flipped
scattering angle, a transposed image, a wrong attenuation at tau 0.05). Here nothing is
symmetric: a uniform block of dust (tau 0.9 along its shortest edge) offset from the star, so
the light reaches it from one side; an oblique line of sight (the star's light crosses the
block about 25 degrees from it: forward scattering, g = 0.3; with the angle's sign flipped the
image would hold a third of the light); a non-square image on a non-cubic grid.

With max_scatterings = 1 a packet peels off at its first scattering and ends at its second
interaction, so the image is exactly the single-scattering image, attenuation on both legs
included. Its expectation, per pixel (u, v the image axes, d the viewing direction, o = -d):

    I = (1 / A) Int_pixel dA Int ds  omega sigma L exp(-tau_in(x)) / (4 pi |x - s|^2)
                                     * Phi_HG(mu) exp(-tau_out(x)),

x on the line of sight through the pixel point, mu = (x - s)/|x - s| . o, tau_in the optical
depth from the star to x, tau_out from x to the box's edge towards the observer. The block's
faces lie on voxel faces, so both are exact chord lengths through the block (slab method),
independent of the transport's voxel walk. Quadrature: S x S sub-rays per pixel (midpoint) and
Gauss-Legendre along each chord; the difference between (4, 24) and (8, 32) is the quadrature
error, added to the tolerance (measured: 2.5e-4 of the total).

Tolerance: 5 x the standard error of the mean over 16 seeds (Student t with 15 degrees of
freedom: P(|t| > 5) = 1.6e-4 per comparison) plus the quadrature error, for the image total
and for blocks of 6 x 7 pixels. The total's standard error is under 0.2 %, so a 1 %
normalisation error is more than 5 sigma.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import centre_star, one_band
from nebula_rt.observe.sky import Camera
from nebula_rt.transport import trace

SHAPE = (32, 28, 24)
# the dust block in voxel indices [lo, hi) per axis, and in box units
LO_IDX, HI_IDX = np.array([11, 4, 11]), np.array([27, 22, 22])
LO, HI = LO_IDX / np.array(SHAPE), HI_IDX / np.array(SHAPE)
STAR = np.array([0.3, 0.45, 0.62])  # outside the block, off the centre of its low-x face
KAPPA, OMEGA, G, L = 2.0, 0.6, 0.3, 1.0
TO_OBSERVER = np.array([0.8, 0.35, 0.5]) / np.linalg.norm([0.8, 0.35, 0.5])
CAMERA = Camera(direction=tuple(-TO_OBSERVER), up=(0.0, 1.0, 0.0), size=(36, 28), extent=0.9,
                center=tuple((LO + HI) / 2))
BLOCK = (6, 7)  # pixels per comparison block
SEEDS = 16
PHOTONS = 400_000


def dust_block() -> np.ndarray:
    rho = np.zeros(SHAPE, np.float32)
    rho[LO_IDX[0]:HI_IDX[0], LO_IDX[1]:HI_IDX[1], LO_IDX[2]:HI_IDX[2]] = 1.0
    return rho


def chord(p, d):
    """Parameters (t0, t1) where the line p + t d enters and leaves the block (slab method;
    t0 >= t1 when it misses). p, d broadcast over (..., 3)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = (LO - p) / d, (HI - p) / d
    return np.nanmax(np.minimum(a, b), axis=-1), np.nanmin(np.maximum(a, b), axis=-1)


def single_scattering_image(sub: int, nodes: int, g: float = G, kappa: float = KAPPA) -> np.ndarray:
    """The expected peel-off image (W, H), luminosity per box-unit area per steradian."""
    d, u, v = CAMERA.basis()
    w, h = CAMERA.size
    ps = CAMERA.pixel_size
    off = ((np.arange(sub) + 0.5) / sub - 0.5) * ps
    P, Q, A, B = np.meshgrid(np.arange(w), np.arange(h), off, off, indexing="ij")
    start = CAMERA.origin() + (P * ps + A)[..., None] * u + (Q * ps + B)[..., None] * v
    s0, s1 = chord(start, d)  # s grows away from the observer: s0 is the side facing it
    hit = s1 > s0
    s0, s1 = np.where(hit, s0, 0.0), np.where(hit, s1, 0.0)
    xg, wg = np.polynomial.legendre.leggauss(nodes)
    s = 0.5 * (s0 + s1)[..., None] + 0.5 * (s1 - s0)[..., None] * xg
    x = start[..., None, :] + s[..., None] * d
    ray = x - STAR
    r = np.linalg.norm(ray, axis=-1)
    mu = (ray / r[..., None]) @ TO_OBSERVER
    phase = (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * mu) ** 1.5)
    lam0, lam1 = chord(STAR, ray)  # the star's ray reaches x at lambda = 1
    tau_in = kappa * r * np.clip(np.minimum(lam1, 1.0) - np.maximum(lam0, 0.0), 0.0, None)
    tau_out = kappa * (s - s0[..., None])
    f = OMEGA * kappa * L * np.exp(-tau_in - tau_out) / (4 * math.pi * r * r) * phase
    line = (f * wg).sum(axis=-1) * 0.5 * (s1 - s0)
    return np.where(hit, line, 0.0).mean(axis=(2, 3))


def blocks(img):
    w, h = img.shape[-2:]
    bw, bh = BLOCK
    return img.reshape(img.shape[:-2] + (w // bw, bw, h // bh, bh)).sum(axis=(-1, -3))


@pytest.fixture(scope="module")
def images(backend):
    rho = dust_block()
    return np.array([
        trace(rho, one_band(albedo=OMEGA, g=G), centre_star(L, STAR), tau=KAPPA, photons=PHOTONS, seed=seed,
              backend=backend, peel=CAMERA, max_scatterings=1, light_field=False).peel_image[0]
        for seed in range(1, SEEDS + 1)
    ])


def test_scene_is_asymmetric():
    """The comparison has teeth: the things a symmetric scene cannot see differ here."""
    ref = single_scattering_image(4, 24)
    assert ref.shape == (36, 28)
    assert np.abs(ref - ref[::-1]).sum() > 0.5 * ref.sum()  # mirrored left-right
    assert np.abs(ref - ref[:, ::-1]).sum() > 0.5 * ref.sum()  # upside down
    flipped = single_scattering_image(4, 24, g=-G)  # Phi(-mu): the angle's sign flipped
    assert flipped.sum() < 0.5 * ref.sum()  # measured 0.32
    # the block is optically thick enough that the attenuation matters: tau 0.9-1.5 across it
    assert KAPPA * (HI - LO).min() > 0.8


def test_peel_off_is_single_scattering_of_the_offset_block(images):
    fine, coarse = single_scattering_image(8, 32), single_scattering_image(4, 24)
    quad = np.abs(fine - coarse)
    totals = images.sum(axis=(1, 2))
    se = totals.std(ddof=1) / math.sqrt(SEEDS)
    want = fine.sum()
    assert abs(totals.mean() - want) < 5 * se + quad.sum(), (totals.mean() / want - 1, se / want)
    assert se / want < 0.002  # 1 % in the normalisation is > 5 sigma
    got_b, want_b, quad_b = blocks(images), blocks(fine), blocks(quad)
    se_b = got_b.std(axis=0, ddof=1) / math.sqrt(SEEDS)
    lit = want_b > 0.02 * want_b.max()
    assert lit.sum() >= 12
    dev = np.abs(got_b.mean(axis=0) - want_b)
    assert np.all(dev[lit] < 5 * se_b[lit] + quad_b[lit]), (got_b.mean(axis=0)[lit] / want_b[lit] - 1)
    # pixels the block misses (with a pixel's margin: a sub-ray grid can miss a corner) are dark
    lit_px = np.pad(fine > 0, 1)
    near = np.zeros(fine.shape, bool)
    for i in range(3):
        for j in range(3):
            near |= lit_px[i:i + fine.shape[0], j:j + fine.shape[1]]
    assert (~near).sum() > 50
    assert np.all(images[:, ~near] == 0.0)
