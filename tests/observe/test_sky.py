"""Sky images (nebula_rt.observe.sky) against analytic solutions of the formal transfer solution.

For a piecewise-constant medium the ray integral I = int j exp(-tau) dl is a finite sum of
exact segment integrals, so wherever the segments do not straddle voxel faces (views along a
box axis with step <= 1, or uniform media) the only error is floating-point rounding and the
tolerance is 1e-9 relative.  Where segments straddle faces the tolerance is a bound derived in
the test from the length of ray assigned to the wrong voxel.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from nebula_rt.observe import sky
from nebula_rt.observe.sky import Camera, sky_image

RTOL_EXACT = 1e-9


def uniform(shape, j, s, n_bands=1):
    """(n_bands, *shape) emissivity and extinction arrays of constant j and sigma."""
    return np.full((n_bands, *shape), float(j)), np.full((n_bands, *shape), float(s))


def centre_pixel(camera):
    """Pixel whose centre is camera.center (needs odd W and H)."""
    w, h = camera.size
    assert w % 2 == 1 and h % 2 == 1
    return w // 2, h // 2


# --------------------------------------------------------------------------------------------
# 1. Uniform box along the axes: the chord is 1 box unit, I = j/sigma (1 - exp(-sigma))
# --------------------------------------------------------------------------------------------
AXES = [(0, 0, -1), (0, 0, 1), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0)]


@pytest.mark.parametrize("direction", AXES)
@pytest.mark.parametrize("s", [0.0, 0.3, 2.5])
def test_uniform_box_along_axis(direction, s):
    j = 1.7
    em, sig = uniform((6, 5, 4), j, s)
    cam = Camera(direction=direction, size=(9, 9), extent=1.0)
    img = sky_image(em, sig, cam)
    expected = j * 1.0 if s == 0.0 else j / s * (1.0 - math.exp(-s * 1.0))
    p, q = centre_pixel(cam)
    assert img.scattered[0, p, q] == pytest.approx(expected, rel=RTOL_EXACT)
    # extent 1 along an axis: every pixel centre lies inside the box's footprint, so every ray
    # has the same chord of length 1.
    np.testing.assert_allclose(img.scattered[0], expected, rtol=RTOL_EXACT)
    assert np.array_equal(img.intensity, img.scattered)  # no stars
    assert img.direct.shape == (1, 9, 9) and not img.direct.any()


def test_rays_missing_the_box_are_zero():
    em, sig = uniform((4, 4, 4), 1.0, 1.0)
    # Field of view 3 box units wide, centred on the box: the outer pixels miss it.
    cam = Camera(size=(30, 30), extent=3.0)
    img = sky_image(em, sig, cam)
    centres_x = img.origin[0] + img.pixel_size * np.arange(30)
    outside = (centres_x < 0) | (centres_x > 1)
    assert not img.scattered[0][outside, :].any()
    assert not img.scattered[0][:, outside].any()
    assert img.scattered[0][~outside][:, ~outside].min() > 0


# --------------------------------------------------------------------------------------------
# 2. Along the diagonal (1, 1, 1)
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("s", [0.0, 1.0, 4.0])
def test_uniform_box_along_diagonal(s):
    """Central ray: the box diagonal, chord sqrt(3): I = j/sigma (1 - exp(-sigma sqrt 3)).

    In a *uniform* medium the voxel a segment's midpoint picks does not matter, so the segment
    discretisation is exact; the only error is the chord length, and near the corners that the
    diagonal passes through the chord of a ray offset by delta from the diagonal is shorter by
    O(delta).  The pixel centre equals camera.center up to rounding (delta ~ 1e-16), hence
    the tolerance RTOL_EXACT.
    """
    j = 0.8
    em, sig = uniform((7, 7, 7), j, s)
    cam = Camera(direction=(1, 1, 1), size=(21, 21))
    img = sky_image(em, sig, cam)
    L = math.sqrt(3.0)
    expected = j * L if s == 0.0 else j / s * -math.expm1(-s * L)
    p, q = centre_pixel(cam)
    assert img.scattered[0, p, q] == pytest.approx(expected, rel=RTOL_EXACT)
    # Elsewhere the chord is shorter and the image can only be dimmer (monotone in L).
    assert img.scattered[0].max() <= expected * (1 + RTOL_EXACT)


@pytest.mark.parametrize("step", [0.5, 0.1, 0.02])
def test_layered_medium_along_diagonal(step):
    """j and sigma vary with z only; central ray along the diagonal, observer at (-inf)^3.

    Exact: the ray crosses z-layer k over l = sqrt(3)/nz, in order of increasing z, so
        I = sum_k j_k/sigma_k (1 - exp(-sigma_k l)) exp(-sum_{m<k} sigma_m l).
    Here segments straddle the z faces.  A straddling segment gives less than e = ds/2 of its
    length the other layer's (j, sigma).  Writing I' - I = int (j' - j) e^{-tau'}
    + int j (e^{-tau'} - e^{-tau}) and using |e^{-a} - e^{-b}| <= |a - b|, with |tau' - tau| <=
    sum over faces f already crossed of |sigma_{f+1} - sigma_f| e:
        |I' - I| <= e [ sum_f |j_{f+1} - j_f| + sum_f |sigma_{f+1} - sigma_f| l sum_{k>f} j_k ].
    A worst-case bound (each face's error at its maximum, none cancelling): first order in ds.
    """
    nz = 6
    jz = np.array([0.2, 1.0, 0.5, 2.0, 0.1, 0.7])
    sz = np.array([0.3, 2.0, 0.8, 0.1, 1.5, 0.6])
    shape = (5, 5, nz)
    em = np.broadcast_to(jz, shape)[None].copy()
    sig = np.broadcast_to(sz, shape)[None].copy()
    cam = Camera(direction=(1, 1, 1), size=(5, 5))
    img = sky_image(em, sig, cam, step=step)

    L = math.sqrt(3.0)
    ell = L / nz
    tau_before = np.concatenate([[0.0], np.cumsum(sz * ell)[:-1]])
    exact = float(np.sum(jz / sz * -np.expm1(-sz * ell) * np.exp(-tau_before)))

    ds = L / math.ceil(L / (step / max(shape)))  # the segment length the march uses
    e = ds / 2
    j_after = np.cumsum(jz[::-1])[::-1][1:]  # sum_{k > f} j_k for faces f = 0 .. nz-2
    bound = e * (np.abs(np.diff(jz)).sum() + (np.abs(np.diff(sz)) * ell * j_after).sum())
    p, q = centre_pixel(cam)
    err = abs(img.scattered[0, p, q] - exact)
    assert err <= bound
    assert bound < 0.8 * exact  # the bound is not vacuous (0.65, 0.13, 0.026 relative)


def test_layered_medium_along_diagonal_aligned_segments():
    """step 0.25 on this grid gives ceil(sqrt3 / (0.25/6)) = 42 = 7 * nz segments, so segment ends
    fall on the z faces and the sampled medium is the true one: exact to RTOL_EXACT."""
    nz = 6
    jz = np.array([0.2, 1.0, 0.5, 2.0, 0.1, 0.7])
    sz = np.array([0.3, 2.0, 0.8, 0.1, 1.5, 0.6])
    shape = (5, 5, nz)
    assert math.ceil(math.sqrt(3) / (0.25 / max(shape))) % nz == 0
    em = np.broadcast_to(jz, shape)[None].copy()
    sig = np.broadcast_to(sz, shape)[None].copy()
    img = sky_image(em, sig, Camera(direction=(1, 1, 1), size=(5, 5)), step=0.25)
    ell = math.sqrt(3.0) / nz
    tau_before = np.concatenate([[0.0], np.cumsum(sz * ell)[:-1]])
    exact = float(np.sum(jz / sz * -np.expm1(-sz * ell) * np.exp(-tau_before)))
    assert img.scattered[0, 2, 2] == pytest.approx(exact, rel=RTOL_EXACT)


# --------------------------------------------------------------------------------------------
# 3. A single emitting voxel: flux conservation and orientation
# --------------------------------------------------------------------------------------------
def one_voxel(shape, index, j, s):
    em = np.zeros((1, *shape))
    em[(0, *index)] = j
    return em, np.full((1, *shape), float(s))


@pytest.mark.parametrize("s", [0.0, 0.7, 3.0])
def test_single_voxel_looking_down_z(s):
    """Image integral sum(I) * pixel_area = int_voxel j exp(-tau) dV.

    Looking down -z the observer is at z = +inf, so tau(x) = sigma (1 - z) and
        int = j hx hy (1 - exp(-sigma hz))/sigma exp(-sigma (1 - z_top))
            = j V exp(-sigma depth) sinh(a)/a,   a = sigma hz/2, depth = 1 - z_centre.
    Pixels are aligned with the voxels (extent 1, W and H multiples of nx, ny) and the
    segments with the z faces (step 0.5), so the sum equals the exact integral to RTOL_EXACT;
    against j V exp(-sigma depth) the tolerance is the voxel-size-dependent
    sinh(a)/a - 1 <= a^2/6 cosh(a).
    """
    shape = (4, 2, 5)
    index = (3, 1, 2)  # x in [0.75, 1), y in [0.5, 1), z in [0.4, 0.6)
    j = 2.0
    em, sig = one_voxel(shape, index, j, s)
    cam = Camera(size=(8, 8), extent=1.0)
    img = sky_image(em, sig, cam)
    assert img.pixel_size == pytest.approx(1 / 8)

    hx, hy, hz = (1.0 / n for n in shape)
    V = hx * hy * hz
    depth = 1.0 - (index[2] + 0.5) * hz
    a = s * hz / 2
    shape_factor = math.sinh(a) / a if a > 0 else 1.0
    exact = j * V * math.exp(-s * depth) * shape_factor
    total = img.scattered[0].sum() * img.pixel_size**2
    assert total == pytest.approx(exact, rel=RTOL_EXACT)
    assert total == pytest.approx(j * V * math.exp(-s * depth), rel=a * a / 6 * math.cosh(a) + RTOL_EXACT)

    # Orientation: u = +x (right), v = +y (up).  The voxel covers exactly p = 6, 7, q = 4..7.
    np.testing.assert_allclose(img.u_axis, [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(img.v_axis, [0, 1, 0], atol=1e-15)
    bright = img.scattered[0] > 0
    expected = np.zeros((8, 8), bool)
    expected[6:8, 4:8] = True
    assert np.array_equal(bright, expected)
    p, q = np.nonzero(bright)
    assert p.min() > 8 / 2 and q.min() >= 8 / 2  # x > 0.5 -> p > W/2, y > 0.5 -> q > H/2


def test_single_voxel_looking_along_plus_x():
    """Looking along +x with up +z: u = -y (right), v = +z; the observer is at x = -inf, so
    depth = x_centre.  A voxel at y > 0.5 appears on the left (p < W/2), at z < 0.5 low."""
    shape = (4, 4, 4)
    index = (2, 3, 0)  # x centre 0.625, y in [0.75, 1), z in [0, 0.25)
    j, s = 1.3, 1.1
    em, sig = one_voxel(shape, index, j, s)
    cam = Camera(direction=(1, 0, 0), up=(0, 0, 1), size=(8, 8), extent=1.0)
    img = sky_image(em, sig, cam)
    np.testing.assert_allclose(img.u_axis, [0, -1, 0], atol=1e-15)
    np.testing.assert_allclose(img.v_axis, [0, 0, 1], atol=1e-15)
    h = 0.25
    a = s * h / 2
    exact = j * h**3 * math.exp(-s * (index[0] + 0.5) * h) * math.sinh(a) / a
    assert img.scattered[0].sum() * img.pixel_size**2 == pytest.approx(exact, rel=RTOL_EXACT)
    expected = np.zeros((8, 8), bool)
    expected[0:2, 0:2] = True  # y in [0.75, 1) -> u in (-0.5, -0.25]; z in [0, 0.25) -> bottom
    assert np.array_equal(img.scattered[0] > 0, expected)


# --------------------------------------------------------------------------------------------
# 4. Stars: attenuation and placement
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("direction", AXES + [(1, 1, 1), (-1, 1, -1)])
def test_star_at_centre(direction):
    """Star at the centre of a uniform box: tau = sigma * (distance to the box face along
    -direction) = sigma/2 along an axis, sigma sqrt(3)/2 along a diagonal; the direct image
    integrates to L/(4 pi) exp(-tau), all in one pixel."""
    s, lum = 1.8, 5.0
    em, sig = uniform((4, 4, 4), 0.0, s)
    cam = Camera(direction=direction, size=(16, 12))
    img = sky_image(em, sig, cam, stars=[(0.5, 0.5, 0.5)], star_band_luminosity=[[lum]])
    n_nonzero = int(np.count_nonzero(np.abs(direction)))
    path = 0.5 * math.sqrt(n_nonzero)
    assert img.tau_star.shape == (1, 1)
    assert img.tau_star[0, 0] == pytest.approx(s * path, rel=RTOL_EXACT)
    flux = img.direct[0].sum() * img.pixel_size**2
    assert flux == pytest.approx(lum / (4 * math.pi) * math.exp(-s * path), rel=RTOL_EXACT)
    assert np.count_nonzero(img.direct) == 1
    assert not img.scattered.any()
    np.testing.assert_array_equal(img.intensity, img.direct)


def test_star_placement_and_observer_side():
    s = 0.9
    em, sig = uniform((5, 5, 5), 0.0, s)
    cam = Camera(size=(10, 10), extent=1.0)  # down -z: observer at z = +inf
    stars = [(0.83, 0.27, 0.5),   # inside: pixel (8, 2), tau = s * 0.5
             (0.5, 0.5, -0.5),    # below the box: its light crosses the whole box, tau = s
             (0.15, 0.95, 1.5),   # above the box (observer side): tau = 0, pixel (1, 9)
             (1.7, 0.5, 0.5)]     # beside the box: its ray misses it (tau = 0), out of view
    lum = np.array([[1.0], [2.0], [3.0], [4.0]])
    img = sky_image(em, sig, cam, stars=stars, star_band_luminosity=lum)
    np.testing.assert_allclose(img.tau_star[:, 0], [0.5 * s, s, 0.0, 0.0], rtol=RTOL_EXACT)
    area = img.pixel_size**2
    expected = np.zeros((10, 10))
    expected[8, 2] += 1.0 / (4 * math.pi) * math.exp(-0.5 * s) / area
    expected[5, 5] += 2.0 / (4 * math.pi) * math.exp(-s) / area  # (0.5, 0.5): pixel 5 = [0.5, 0.6)
    expected[1, 9] += 3.0 / (4 * math.pi) / area
    np.testing.assert_allclose(img.direct[0], expected, rtol=RTOL_EXACT)


def test_star_outside_field_of_view_is_skipped_but_has_tau():
    s = 1.2
    em, sig = uniform((4, 4, 4), 0.0, s)
    cam = Camera(size=(4, 4), extent=0.2)  # sees x, y in [0.4, 0.6] only
    img = sky_image(em, sig, cam, stars=[(0.9, 0.5, 0.25)], star_band_luminosity=[[1.0]])
    assert not img.direct.any()
    assert img.tau_star[0, 0] == pytest.approx(s * 0.75, rel=RTOL_EXACT)


# --------------------------------------------------------------------------------------------
# 5. Per-band extinction
# --------------------------------------------------------------------------------------------
def test_two_bands_ratio():
    """Same j, sigma = (0.5, 3.0): scattered ratio [(1 - e^-s1)/s1] / [(1 - e^-s2)/s2] for the
    unit chord; star at the centre: ratio exp(-(s1 - s2)/2) times the luminosity ratio."""
    s1, s2 = 0.5, 3.0
    shape = (4, 4, 4)
    em = np.ones((2, *shape))
    sig = np.stack([np.full(shape, s1), np.full(shape, s2)])
    cam = Camera(size=(5, 5), extent=1.0)
    img = sky_image(em, sig, cam, stars=[(0.5, 0.5, 0.5)], star_band_luminosity=[[1.0, 2.0]])
    p, q = centre_pixel(cam)
    ratio = img.scattered[0, p, q] / img.scattered[1, p, q]
    expected = (-math.expm1(-s1) / s1) / (-math.expm1(-s2) / s2)
    assert ratio == pytest.approx(expected, rel=RTOL_EXACT)
    np.testing.assert_allclose(img.tau_star[0], [0.5 * s1, 0.5 * s2], rtol=RTOL_EXACT)
    d = img.direct.sum(axis=(1, 2))
    assert d[0] / d[1] == pytest.approx(0.5 * math.exp(-(s1 - s2) / 2), rel=RTOL_EXACT)


# --------------------------------------------------------------------------------------------
# Implementation details that must not change the answer
# --------------------------------------------------------------------------------------------
def test_chunking_does_not_change_the_image(monkeypatch):
    rng = np.random.default_rng(3)
    em = rng.random((2, 5, 4, 3))
    sig = 3 * rng.random((2, 5, 4, 3))
    cam = Camera(direction=(0.3, -1.0, 0.6), up=(0, 0, 1), size=(23, 17))
    ref = sky_image(em, sig, cam).scattered
    monkeypatch.setattr(sky, "_CHUNK_ELEMENTS", 1)  # -> 256-ray chunks, many per image
    np.testing.assert_allclose(sky_image(em, sig, cam).scattered, ref, rtol=1e-13, atol=0)


def test_up_parallel_to_direction_falls_back_deterministically():
    d, u, v = Camera(direction=(0, 0, -2), up=(0, 0, 5)).basis()
    np.testing.assert_allclose(np.array([u, v, -d]) @ np.array([u, v, -d]).T, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(np.cross(u, v), -d, atol=1e-15)  # right-handed
    np.testing.assert_allclose(v, [0, 1, 0], atol=1e-15)  # first fallback: +y
    _, _, v2 = Camera(direction=(0, 3, 0), up=(0, -1, 0)).basis()
    np.testing.assert_allclose(v2, [0, 0, 1], atol=1e-15)  # +y is parallel: next, +z


def test_pixel_centres_follow_the_documented_formula():
    cam = Camera(direction=(1, 2, -2), up=(0, 0, 1), size=(6, 4), extent=1.2, center=(0.4, 0.5, 0.6))
    d, u, v = cam.basis()
    origin = cam.origin()
    W, H, ext = 6, 4, 1.2
    for p, q in [(0, 0), (5, 3), (2, 1)]:
        want = (np.array(cam.center) + ((p + 0.5) / W - 0.5) * ext * u
                + ((q + 0.5) / H - 0.5) * ext * H / W * v)
        np.testing.assert_allclose(origin + cam.pixel_size * (p * u + q * v), want, atol=1e-15)


# --------------------------------------------------------------------------------------------
# 6. Bad inputs
# --------------------------------------------------------------------------------------------
GOOD = uniform((3, 3, 3), 1.0, 1.0)
CAM = Camera(size=(4, 4))


@pytest.mark.parametrize("kwargs, name", [
    (dict(direction=(0, 0, 0)), "direction"),
    (dict(direction=(0, 0)), "direction"),
    (dict(up=(0, 0, 0)), "up"),
    (dict(size=(0, 4)), "size"),
    (dict(size=(4,)), "size"),
    (dict(size=(4.5, 4)), "size"),
    (dict(extent=-1.0), "extent"),
    (dict(extent=float("nan")), "extent"),
    (dict(center=(0.5, float("inf"), 0.5)), "center"),
])
def test_bad_camera(kwargs, name):
    with pytest.raises(ValueError, match=name):
        Camera(**kwargs)


@pytest.mark.parametrize("args, kwargs, name", [
    ((-GOOD[0], GOOD[1]), {}, "emissivity"),
    ((GOOD[0], -GOOD[1]), {}, "sigma"),
    ((GOOD[0], np.full_like(GOOD[1], np.nan)), {}, "sigma"),
    ((GOOD[0][0], GOOD[1][0]), {}, "emissivity"),
    ((GOOD[0], GOOD[1][:, :2]), {}, "sigma"),
    (GOOD, dict(step=0.0), "step"),
    (GOOD, dict(stars=[(0.5, 0.5)], star_band_luminosity=[[1.0]]), "stars"),
    (GOOD, dict(stars=[(0.5, 0.5, 0.5)]), "star_band_luminosity"),
    (GOOD, dict(stars=[(0.5, 0.5, 0.5)], star_band_luminosity=[[1.0, 2.0]]), "star_band_luminosity"),
    (GOOD, dict(stars=[(0.5, 0.5, 0.5)], star_band_luminosity=[[-1.0]]), "star_band_luminosity"),
])
def test_bad_inputs(args, kwargs, name):
    with pytest.raises(ValueError, match=name):
        sky_image(*args, CAM, **kwargs)


def test_camera_must_be_a_camera():
    with pytest.raises(ValueError, match="camera"):
        sky_image(*GOOD, camera=(0, 0, -1))


# --------------------------------------------------------------------------------------------
# Limits: memory checked before work, progress, cancel
# --------------------------------------------------------------------------------------------
def test_an_image_the_memory_cannot_hold_is_refused_before_work(monkeypatch):
    """The images' bytes (sky.SKY_IMAGE_ARRAYS float64 images per band) against the host's
    available memory, before any ray is marched: with 1 MiB available, 3 bands of 32 x 32
    (147 kB) are made and 3 bands of 256 x 256 (9.4 MB) are refused naming sky.size."""
    em, sig = np.ones((3, 4, 4, 4)), np.ones((3, 4, 4, 4))
    monkeypatch.setattr(sky, "host_available_bytes", lambda: 1 << 20)
    marched = []
    monkeypatch.setattr(sky, "_march", lambda *a, **k: marched.append(1) or (np.zeros((3, len(a[0]))), None))
    assert sky_image(em, sig, Camera(size=(32, 32))).scattered.shape == (3, 32, 32) and marched
    marched.clear()
    from nebula_rt.errors import ResourceError

    with pytest.raises(ResourceError, match=r"sky.size = \(256, 256\).*GiB of host memory") as e:
        sky_image(em, sig, Camera(size=(256, 256)))
    assert e.value.parameter == "sky.size" and not marched


def test_progress_reaches_every_pixel_and_cancel_stops_between_chunks(monkeypatch):
    """Progress is reported after every chunk of rays, rising to W x H; a cancel polled before
    every chunk stops the march after the chunks already done (CancelledError)."""
    from nebula_rt.errors import CancelledError

    monkeypatch.setattr(sky, "_CHUNK_ELEMENTS", 1)  # 256-ray chunks
    em, sig = np.ones((2, 4, 4, 4)), np.ones((2, 4, 4, 4))
    cam = Camera(size=(40, 30))  # 1200 rays: 5 chunks
    seen = []
    sky_image(em, sig, cam, progress=lambda done, total: seen.append((done, total)))
    assert [d for d, _ in seen] == [256, 512, 768, 1024, 1200] and {t for _, t in seen} == {1200}
    polls = []
    with pytest.raises(CancelledError):
        sky_image(em, sig, cam, cancel=lambda: polls.append(1) or len(polls) > 2)
    assert len(polls) == 3  # two chunks marched, the third not begun
