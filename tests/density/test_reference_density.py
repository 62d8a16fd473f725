"""Self-consistency tests of the density oracle ``tests/oracles/reference_density.py``.

These tests check the oracle against the specification and against hand
derivations only; they never touch the OpenCL kernel (that comparison lives
elsewhere and relies on this module being right).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from oracles.reference_density import (
    GRAD3,
    OCTAVE_SHIFT,
    PERM,
    TURBULENCE_EXPONENTS,
    bump_voxel_average,
    cubic,
    density_turbulence,
    density_uniform,
    simplex_noise3,
    turbulence,
    voxel_centres,
)

# ---------------------------------------------------------------------------
# Independent scalar transcription of Gustavson's Java SimplexNoise.noise(x,y,z)
# (plain Python, explicit branches) used to check the vectorised branch logic.
# Only the tables are shared with the module (they are checked separately).
# ---------------------------------------------------------------------------


def _java_noise3(xin: float, yin: float, zin: float) -> float:
    F3 = 1.0 / 3.0
    G3 = 1.0 / 6.0
    perm = [int(v) for v in PERM]
    grad3 = [tuple(int(c) for c in g) for g in GRAD3]

    def dot(g, x, y, z):
        return g[0] * x + g[1] * y + g[2] * z

    s = (xin + yin + zin) * F3
    i = math.floor(xin + s)
    j = math.floor(yin + s)
    k = math.floor(zin + s)
    t = (i + j + k) * G3
    X0 = i - t
    Y0 = j - t
    Z0 = k - t
    x0 = xin - X0
    y0 = yin - Y0
    z0 = zin - Z0
    if x0 >= y0:
        if y0 >= z0:
            i1, j1, k1, i2, j2, k2 = 1, 0, 0, 1, 1, 0
        elif x0 >= z0:
            i1, j1, k1, i2, j2, k2 = 1, 0, 0, 1, 0, 1
        else:
            i1, j1, k1, i2, j2, k2 = 0, 0, 1, 1, 0, 1
    else:
        if y0 < z0:
            i1, j1, k1, i2, j2, k2 = 0, 0, 1, 0, 1, 1
        elif x0 < z0:
            i1, j1, k1, i2, j2, k2 = 0, 1, 0, 0, 1, 1
        else:
            i1, j1, k1, i2, j2, k2 = 0, 1, 0, 1, 1, 0
    x1 = x0 - i1 + G3
    y1 = y0 - j1 + G3
    z1 = z0 - k1 + G3
    x2 = x0 - i2 + 2.0 * G3
    y2 = y0 - j2 + 2.0 * G3
    z2 = z0 - k2 + 2.0 * G3
    x3 = x0 - 1.0 + 3.0 * G3
    y3 = y0 - 1.0 + 3.0 * G3
    z3 = z0 - 1.0 + 3.0 * G3
    ii = i & 255
    jj = j & 255
    kk = k & 255
    gi0 = perm[ii + perm[jj + perm[kk]]] % 12
    gi1 = perm[ii + i1 + perm[jj + j1 + perm[kk + k1]]] % 12
    gi2 = perm[ii + i2 + perm[jj + j2 + perm[kk + k2]]] % 12
    gi3 = perm[ii + 1 + perm[jj + 1 + perm[kk + 1]]] % 12
    n = []
    for gi, x, y, z in ((gi0, x0, y0, z0), (gi1, x1, y1, z1), (gi2, x2, y2, z2), (gi3, x3, y3, z3)):
        tc = 0.6 - x * x - y * y - z * z
        if tc < 0:
            n.append(0.0)
        else:
            tc *= tc
            n.append(tc * tc * dot(grad3[gi], x, y, z))
    return 32.0 * (n[0] + n[1] + n[2] + n[3])


# ---------------------------------------------------------------------------
# Tables
# ---------------------------------------------------------------------------


def test_permutation_table():
    assert PERM.dtype == np.int32 and PERM.shape == (512,)
    # Doubled copy of a permutation of 0..255.
    assert np.array_equal(PERM[:256], PERM[256:])
    assert sorted(PERM[:256].tolist()) == list(range(256))
    # Perlin's table: first and last entries as printed in "Improved Noise".
    assert PERM[:10].tolist() == [151, 160, 137, 91, 90, 15, 131, 13, 201, 95]
    assert PERM[250:256].tolist() == [78, 66, 215, 61, 156, 180]


def test_gradients():
    expected = [(1, 1, 0), (-1, 1, 0), (1, -1, 0), (-1, -1, 0),
                (1, 0, 1), (-1, 0, 1), (1, 0, -1), (-1, 0, -1),
                (0, 1, 1), (0, -1, 1), (0, 1, -1), (0, -1, -1)]
    assert [tuple(g) for g in GRAD3.tolist()] == expected


def test_turbulence_constants():
    assert TURBULENCE_EXPONENTS == (0.05, 2.0, 4.0, 6.0, 12.0, 8.0, 0.0)
    assert OCTAVE_SHIFT == (31.4159265, 27.1828183, 14.1421356)


# ---------------------------------------------------------------------------
# Simplex noise
# ---------------------------------------------------------------------------


def test_noise_range():
    rng = np.random.default_rng(12345)
    p = rng.uniform(-100.0, 100.0, size=(3, 100_000))
    n = simplex_noise3(*p)
    assert n.shape == (100_000,)
    assert np.all(np.isfinite(n))
    assert np.all(np.abs(n) <= 1.0)
    # Not degenerate: the field actually uses most of its range.
    assert n.max() > 0.7 and n.min() < -0.7


def test_noise_zero_at_origin_exactly():
    # Hand derivation: at (0,0,0) the skew gives cell (0,0,0) and x0=y0=z0=0,
    # so corner 0 has dot = 0.  Branch "x0>=y0>=z0" gives corners (1,0,0) and
    # (1,1,0); their unskewed offsets are (-5/6, 1/6, 1/6) (r^2 = 27/36 = 0.75),
    # (-2/3, -2/3, 1/3) (r^2 = 1) and corner 3 (-1/2,-1/2,-1/2) (r^2 = 0.75):
    # all beyond r^2 = 0.6, so every term is 0.
    assert float(simplex_noise3(0.0, 0.0, 0.0)) == 0.0
    # (1/2, 1/2, 1/2) is the unskewed lattice point (1, 1, 1): same argument.
    assert float(simplex_noise3(0.5, 0.5, 0.5)) == 0.0


def test_noise_zero_at_all_simplex_vertices():
    # Every simplex vertex is the unskewed lattice point v = m - (sum m)/6 for
    # integer m.  Its own corner has dot = 0, and the squared distance to any
    # other vertex is |m|^2 - (sum m)^2/4 >= 0.75 > 0.6 (minimum at m = (1,0,0)
    # or (1,1,1)), so no other corner reaches it.  Rounding can put the point a
    # few ulp into a neighbouring cell, hence a tiny tolerance away from 0.
    rng = np.random.default_rng(7)
    m = rng.integers(-300, 300, size=(3, 2000)).astype(np.float64)
    v = m - m.sum(axis=0) / 6.0
    assert np.max(np.abs(simplex_noise3(*v))) < 1e-12


def test_noise_hand_computed_single_corner():
    # Within 0.866 - sqrt(0.6) = 0.09 of the origin vertex no other vertex is
    # within reach (see above), so only the origin vertex contributes:
    # noise(p) = 32 * (0.6 - |p|^2)^4 * dot(g, p).
    # Its gradient index, read off Perlin's table: perm[0] = 151,
    # perm[151] = 17, perm[17] = 36, 36 % 12 = 0  ->  g = (1, 1, 0).
    assert PERM[0] == 151 and PERM[151] == 17 and PERM[17] == 36
    w = 32.0 * (0.6 - 0.05 ** 2) ** 4 * 0.05  # 0.2039255400625...
    assert w == pytest.approx(0.2039255400625, rel=1e-12)
    # (0.05, 0, 0): cell (0,0,0), origin is corner 0, dot = +0.05.
    assert float(simplex_noise3(0.05, 0.0, 0.0)) == pytest.approx(w, rel=1e-13)
    # (0, -0.05, 0): skewed coords are slightly negative, so the cell is
    # (-1,-1,-1) and the origin is its corner 3, hashed through
    # ii = 255 + 1 = 256 -> the doubled table gives the same gradient.
    assert float(simplex_noise3(0.0, -0.05, 0.0)) == pytest.approx(-w, rel=1e-13)
    # (0, 0, 0.05): g_z = 0, so the value is exactly 0.
    assert float(simplex_noise3(0.0, 0.0, 0.05)) == 0.0


def test_noise_matches_scalar_java_transcription():
    rng = np.random.default_rng(99)
    p = rng.uniform(-300.0, 300.0, size=(3, 1500))
    # Include ties of the branch comparisons (x == y, y == z, ...) on purpose.
    p[1, :100] = p[0, :100]
    p[2, 100:200] = p[1, 100:200]
    p[2, 200:300] = p[0, 200:300]
    p[:, 300:310] = p[0, 300:310]
    got = simplex_noise3(*p)
    want = np.array([_java_noise3(*p[:, n]) for n in range(p.shape[1])])
    # Same float64 operations in the same order: identical results.
    assert np.array_equal(got, want)


def test_noise_broadcasting_and_shape():
    x = np.linspace(0.0, 3.0, 4)[:, None, None]
    y = np.linspace(0.0, 2.0, 3)[None, :, None]
    z = np.array([0.25, 0.75])
    n = simplex_noise3(x, y, z)
    assert n.shape == (4, 3, 2) and n.dtype == np.float64
    assert n[2, 1, 1] == float(simplex_noise3(x[2, 0, 0], y[0, 1, 0], z[1]))
    assert simplex_noise3(0.3, 0.2, 0.1).shape == ()


def test_noise_continuity_random_points():
    rng = np.random.default_rng(2024)
    p = rng.uniform(-50.0, 50.0, size=(3, 20_000))
    e = rng.normal(size=(3, 20_000))
    e /= np.linalg.norm(e, axis=0)
    diff = np.abs(simplex_noise3(*p) - simplex_noise3(*(p + 1e-6 * e)))
    assert diff.max() < 1e-4


def test_noise_seams_are_small():
    # Known property of Gustavson's 2005 3D noise with t = 0.6 - r^2: a corner
    # of a neighbouring simplex can still be within sqrt(0.6) when the point
    # crosses a simplex face, so the field has tiny jumps there (cf.
    # ashima/webgl-noise#21; 0.5 would be seamless).  The specification asks
    # for 0.6, so the oracle keeps the seams; this test pins their size, which
    # bounds oracle/kernel differences where float32 picks the other simplex.
    rng = np.random.default_rng(5)
    h = 5e-6
    s = np.arange(40_000) * h
    worst = 0.0
    for _ in range(4):
        o = rng.uniform(-20.0, 20.0, size=3)
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        v = simplex_noise3(*(o[:, None] + d[:, None] * s))
        worst = max(worst, float(np.abs(np.diff(v)).max()))
    # Gradient norm is < 7, so a smooth step is < 3.5e-5; seams are < 1e-2.
    assert worst < 1e-2


# ---------------------------------------------------------------------------
# Turbulence
# ---------------------------------------------------------------------------


def test_turbulence_is_the_specified_octave_sum():
    rng = np.random.default_rng(3)
    x, y, z = rng.uniform(-2.0, 3.0, size=(3, 50))
    want = np.zeros(50)
    for i, e in enumerate((0.05, 2.0, 4.0, 6.0, 12.0, 8.0, 0.0)):
        f = 2.0 ** e
        want = want + simplex_noise3(f * x + i * 31.4159265,
                                     f * y + i * 27.1828183,
                                     f * z + i * 14.1421356) / f
    np.testing.assert_allclose(turbulence(x, y, z), want, rtol=0, atol=1e-15)


# ---------------------------------------------------------------------------
# Cubic kernel and voxel geometry
# ---------------------------------------------------------------------------


def test_cubic_values():
    r = 0.2
    np.testing.assert_allclose(cubic([0.0, 0.1, -0.1, 0.2, 0.3], r),
                               [1.0, 27.0 / 64.0, 27.0 / 64.0, 0.0, 0.0], rtol=1e-14, atol=0)
    assert np.all(cubic(np.linspace(0, 1, 11), 0.0) == 0.0)
    with pytest.raises(ValueError):
        cubic(0.0, -1.0)


def test_voxel_centres():
    xc, yc, zc = voxel_centres((2, 3, 4))
    assert xc.shape == yc.shape == zc.shape == (2, 3, 4)
    assert xc[1, 0, 0] == 0.75 and xc[0, 2, 3] == 0.25
    assert yc[0, 2, 0] == pytest.approx(5.0 / 6.0) and yc[1, 0, 3] == pytest.approx(1.0 / 6.0)
    assert zc[0, 0, 3] == 0.875 and zc[1, 2, 0] == 0.125


# ---------------------------------------------------------------------------
# Voxel-averaged bump
# ---------------------------------------------------------------------------


def _bump_brute_force(shape, s, r, subsamples):
    """The definition, evaluated for every voxel (no culling)."""
    s = np.asarray(s, dtype=np.float64)
    out = np.zeros(shape)
    frac = (np.arange(subsamples) + 0.5) / subsamples
    for i in range(shape[0]):
        for j in range(shape[1]):
            for k in range(shape[2]):
                px = i / shape[0] + frac * (1.0 / shape[0])
                py = j / shape[1] + frac * (1.0 / shape[1])
                pz = k / shape[2] + frac * (1.0 / shape[2])
                P = np.stack(np.meshgrid(px, py, pz, indexing="ij"))
                d = np.sqrt(((P - s[:, None, None, None]) ** 2).sum(axis=0))
                out[i, j, k] = cubic(d, r).mean()
    return out


@pytest.mark.parametrize(
    "s, r, sub",
    [
        ((0.5, 0.5, 0.5), 0.3, 8),      # interior, several voxels
        ((0.1, 0.95, 0.3), 0.25, 4),    # near an edge of the box
        ((1.1, 0.5, -0.05), 0.3, 3),    # outside the box, sphere pokes in
        ((0.4, 0.6, 0.5), 2.0, 2),      # sphere covers the whole box
        ((0.51, 0.33, 0.62), 0.05, 5),  # smaller than a voxel
        ((3.0, 3.0, 3.0), 0.5, 4),      # entirely outside: all zero
    ],
)
def test_bump_equals_brute_force(s, r, sub):
    shape = (6, 5, 4)
    got = bump_voxel_average(shape, s, r, subsamples=sub)
    want = _bump_brute_force(shape, s, r, sub)
    assert got.shape == shape and got.dtype == np.float64
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)


def test_bump_zero_radius_and_errors():
    assert np.all(bump_voxel_average((4, 4, 4), (0.5, 0.5, 0.5), 0.0) == 0.0)
    with pytest.raises(ValueError):
        bump_voxel_average((4, 4, 4), (0.5, 0.5, 0.5), -0.1)
    with pytest.raises(ValueError):
        bump_voxel_average((4, 4, 4), (0.5, 0.5), 0.1)


def _bump_mass_analytic(r):
    # Integral of (1 - rho^2/r^2)^3 over the ball of radius r:
    # 4 pi r^3 int_0^1 (1-u^2)^3 u^2 du = 4 pi r^3 (1/3 - 3/5 + 3/7 - 1/9)
    # = 4 pi r^3 * 16/315 = 64 pi r^3 / 315.
    return 64.0 * math.pi * r ** 3 / 315.0


def test_bump_mass_analytic_constant():
    # Cross-check the closed form above by quadrature (guards the constant).
    r = 0.3
    val, _ = integrate.quad(lambda rho: 4 * math.pi * rho ** 2 * (1 - rho ** 2 / r ** 2) ** 3, 0, r)
    assert val == pytest.approx(_bump_mass_analytic(r), rel=1e-12)


@pytest.mark.parametrize("shape", [(48, 48, 48), (32, 48, 40)])
def test_bump_mass(shape):
    r = 0.3
    b = bump_voxel_average(shape, (0.5, 0.5, 0.5), r)
    mass = b.sum() / (shape[0] * shape[1] * shape[2])  # sum * voxel volume
    assert mass == pytest.approx(_bump_mass_analytic(r), rel=1e-2)
    assert b.max() <= 1.0 and b.min() >= 0.0


# ---------------------------------------------------------------------------
# Density models
# ---------------------------------------------------------------------------

_STARS = [((0.5, 0.5, 0.5), 0.2), ((0.1, 0.8, 0.3), 0.15)]


def test_density_uniform_and_floor():
    shape = (8, 6, 5)
    bumps = bump_voxel_average(shape, *_STARS[0]) + bump_voxel_average(shape, *_STARS[1])
    d = density_uniform(shape, 0.5, 0.2, _STARS)
    np.testing.assert_allclose(d, 0.5 + bumps, rtol=1e-15, atol=0)
    # Floor above the background: applied everywhere the bumps are small.
    d = density_uniform(shape, 0.0, 0.2, _STARS)
    np.testing.assert_array_equal(d, np.maximum(bumps, 0.2))
    assert d.min() == 0.2 and d.max() > 0.2
    # No stars: constant background, or the floor if that is higher.
    assert np.all(density_uniform(shape, 0.3, 0.1, []) == 0.3)
    assert np.all(density_uniform(shape, 0.0, 0.1, []) == 0.1)


def test_density_turbulence_definition_and_floor():
    shape = (10, 8, 6)
    offset = (0.3, -1.7, 2.5)
    floor = 0.05
    xc, yc, zc = voxel_centres(shape)
    turb = turbulence(xc + offset[0], yc + offset[1], zc + offset[2])
    bumps = bump_voxel_average(shape, *_STARS[0]) + bump_voxel_average(shape, *_STARS[1])
    d = density_turbulence(shape, offset, 2.0, floor, _STARS)
    assert d.shape == shape and d.dtype == np.float64
    np.testing.assert_allclose(d, np.maximum(bumps + 2.0 * np.maximum(0.0, turb), floor),
                               rtol=1e-15, atol=0)
    # Negative turbulence is clipped to 0 and then raised to the floor.
    assert np.any((turb < 0) & (bumps == 0))
    assert np.all(d[(turb < 0) & (bumps == 0)] == floor)
    assert d.min() >= floor


def test_density_turbulence_no_stars_zero_scale_is_floor():
    d = density_turbulence((5, 4, 3), (0.0, 0.0, 0.0), 0.0, 0.125, [])
    assert np.all(d == 0.125)
