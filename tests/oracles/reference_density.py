"""Reference (oracle) implementation of NebulaRT's dust density formulas.

This module is a deliberately plain, vectorised NumPy (float64) transcription of
the density specification.  It exists so that the OpenCL density kernel, which
was written independently from the same specification, can be checked against
it; it therefore favours literal agreement with the specification over speed
or cleverness, and it must never import anything from the kernel side.

Coordinates are in *box units*: the simulation box is the unit cube
``[0, 1]^3`` whatever the grid shape, so voxels of a grid ``(nx, ny, nz)`` have
edge lengths ``(1/nx, 1/ny, 1/nz)`` and need not be cubic.  Densities are
dimensionless multiples of the scene's reference density (the caller scales
them to physical units).

Contents
--------
simplex_noise3
    Stefan Gustavson's 3D simplex noise (2005 Java reference), bit for bit in
    float64 where the operations allow.
turbulence
    Seven-octave sum of shifted simplex noise (thesis listing A.14).
cubic
    Compact cubic bump kernel ``(1 - d^2/r^2)^3``.
voxel_centres, bump_voxel_average
    Voxel geometry and the voxel-averaged star bump.
density_turbulence, density_uniform
    The two density models.
"""

from __future__ import annotations

from typing import Sequence, Tuple

import numpy as np

__all__ = [
    "F3",
    "G3",
    "GRAD3",
    "OCTAVE_SHIFT",
    "PERM",
    "TURBULENCE_EXPONENTS",
    "bump_voxel_average",
    "cubic",
    "density_turbulence",
    "density_uniform",
    "simplex_noise3",
    "turbulence",
    "voxel_centres",
]

# ---------------------------------------------------------------------------
# Simplex noise constants (Gustavson, "Simplex noise demystified", 2005)
# ---------------------------------------------------------------------------

#: Skew factor for 3D, (sqrt(3+1) - 1)/3 = 1/3; written as a division exactly as
#: in the Java source so the float64 value is identical.
F3 = 1.0 / 3.0
#: Unskew factor for 3D, (1 - 1/sqrt(3+1))/3 = 1/6.
G3 = 1.0 / 6.0

#: The 12 gradient directions (edge midpoints of a cube), in Gustavson's order.
#: Integer-valued like the Java ``int grad3[][]``; the dot products are taken in
#: float64, which represents -1, 0 and 1 exactly, so nothing is lost.
GRAD3 = np.array(
    [
        (1, 1, 0), (-1, 1, 0), (1, -1, 0), (-1, -1, 0),
        (1, 0, 1), (-1, 0, 1), (1, 0, -1), (-1, 0, -1),
        (0, 1, 1), (0, -1, 1), (0, 1, -1), (0, -1, -1),
    ],
    dtype=np.int32,
)
GRAD3.setflags(write=False)

# Ken Perlin's permutation of 0..255 (the table of "Improved Noise", 2002, which
# Gustavson reuses).  Any other permutation gives a different (equally valid)
# noise field, so the kernel must use exactly this one.
_PERLIN_P = (
    151, 160, 137, 91, 90, 15, 131, 13, 201, 95, 96, 53, 194, 233, 7, 225,
    140, 36, 103, 30, 69, 142, 8, 99, 37, 240, 21, 10, 23, 190, 6, 148,
    247, 120, 234, 75, 0, 26, 197, 62, 94, 252, 219, 203, 117, 35, 11, 32,
    57, 177, 33, 88, 237, 149, 56, 87, 174, 20, 125, 136, 171, 168, 68, 175,
    74, 165, 71, 134, 139, 48, 27, 166, 77, 146, 158, 231, 83, 111, 229, 122,
    60, 211, 133, 230, 220, 105, 92, 41, 55, 46, 245, 40, 244, 102, 143, 54,
    65, 25, 63, 161, 1, 216, 80, 73, 209, 76, 132, 187, 208, 89, 18, 169,
    200, 196, 135, 130, 116, 188, 159, 86, 164, 100, 109, 198, 173, 186, 3, 64,
    52, 217, 226, 250, 124, 123, 5, 202, 38, 147, 118, 126, 255, 82, 85, 212,
    207, 206, 59, 227, 47, 16, 58, 17, 182, 189, 28, 42, 223, 183, 170, 213,
    119, 248, 152, 2, 44, 154, 163, 70, 221, 153, 101, 155, 167, 43, 172, 9,
    129, 22, 39, 253, 19, 98, 108, 110, 79, 113, 224, 232, 178, 185, 112, 104,
    218, 246, 97, 228, 251, 34, 242, 193, 238, 210, 144, 12, 191, 179, 162, 241,
    81, 51, 145, 235, 249, 14, 239, 107, 49, 192, 214, 31, 181, 199, 106, 157,
    184, 84, 204, 176, 115, 121, 50, 45, 127, 4, 150, 254, 138, 236, 205, 93,
    222, 114, 67, 29, 24, 72, 243, 141, 128, 195, 78, 66, 215, 61, 156, 180,
)

#: Perlin's table doubled to 512 entries, so that the nested look-up
#: ``perm[ii + 1 + perm[jj + 1 + perm[kk + 1]]]`` never needs a second wrap
#: (indices reach at most 255 + 1 + 255 = 511).
PERM = np.array(_PERLIN_P + _PERLIN_P, dtype=np.int32)
PERM.setflags(write=False)

# Float copy of the gradients for the dot products (see GRAD3).
_GRAD3_F = GRAD3.astype(np.float64)

# Radius-squared of a corner's influence; 0.6 is Gustavson's 3D value (the
# kernel is t^4 with t = 0.6 - r^2, zero beyond r^2 = 0.6).
_SIMPLEX_R2 = 0.6
# Final scale factor that brings the 3D result to roughly [-1, 1].
_SIMPLEX_SCALE = 32.0


def _corner_contribution(gi, x, y, z):
    """One simplex corner's contribution ``t^4 * dot(grad, (x, y, z))``.

    Parameters
    ----------
    gi : ndarray of int
        Gradient indices into ``GRAD3`` (0..11).
    x, y, z : ndarray of float64
        Offset of the evaluation point from the corner, in (unskewed) noise
        space units.

    Returns
    -------
    ndarray of float64
        The contribution; exactly 0 where ``t <= 0``.
    """
    # Same operation order as the Java source: 0.6 - x*x - y*y - z*z,
    # then t *= t; n = t * t * dot.
    t = _SIMPLEX_R2 - x * x - y * y - z * z
    g = _GRAD3_F[gi]
    dot = g[..., 0] * x + g[..., 1] * y + g[..., 2] * z
    t2 = t * t
    n = t2 * t2 * dot
    # Java tests t < 0 and the specification t > 0; they agree because t == 0
    # yields t^4 == 0 anyway.  np.where (not multiplication by a mask) keeps the
    # zero exact even if the discarded branch were non-finite.
    return np.where(t > 0.0, n, 0.0)


def simplex_noise3(x, y, z) -> np.ndarray:
    """Gustavson's 3D simplex noise, vectorised.

    A line-by-line transcription of the Java reference implementation in
    S. Gustavson, "Simplex noise demystified" (2005): skew by ``F3 = 1/3``,
    unskew by ``G3 = 1/6``, ``fastfloor`` = floor, Perlin's permutation table
    ``PERM``, gradient index ``PERM[ii + PERM[jj + PERM[kk]]] % 12`` (plus the
    corner offsets), radial kernel ``t^4`` with ``t = 0.6 - r^2`` and final
    scale 32.

    Parameters
    ----------
    x, y, z : array_like of float
        Coordinates in noise space (dimensionless; one lattice cell has unit
        size in skewed space).  Broadcast against each other.

    Returns
    -------
    ndarray of float64
        Noise values, shape = broadcast shape of the inputs (0-d for scalar
        inputs).  Values lie in about [-1, 1]; the field is C^2-continuous and
        exactly 0 at every simplex vertex.
    """
    x, y, z = np.broadcast_arrays(
        np.asarray(x, dtype=np.float64),
        np.asarray(y, dtype=np.float64),
        np.asarray(z, dtype=np.float64),
    )

    # Skew the input space to find the simplex cell (integer corner i, j, k).
    s = (x + y + z) * F3
    i = np.floor(x + s)
    j = np.floor(y + s)
    k = np.floor(z + s)
    # Unskew the cell origin back to (x, y, z) space.  i + j + k is an integer
    # sum, exact in float64 for any sane input, like Java's int sum.
    t = (i + j + k) * G3
    x0 = x - (i - t)
    y0 = y - (j - t)
    z0 = z - (k - t)

    # Which of the six tetrahedra of the skewed cube holds the point: decided
    # by the ordering of x0, y0, z0, with Gustavson's exact comparisons (>= vs
    # <) so that ties resolve the same way as in the Java code.
    xy = x0 >= y0
    yz = y0 >= z0
    xz = x0 >= z0
    not_xy = ~xy
    conds = [
        xy & yz,                      # X Y Z order
        xy & ~yz & xz,                # X Z Y order
        xy & ~yz & ~xz,               # Z X Y order
        not_xy & (y0 < z0),           # Z Y X order
        not_xy & ~(y0 < z0) & (x0 < z0),  # Y Z X order
        not_xy & ~(y0 < z0) & ~(x0 < z0),  # Y X Z order
    ]
    #            XYZ XZY ZXY ZYX YZX YXZ
    i1 = np.select(conds, [1, 1, 0, 0, 0, 0])
    j1 = np.select(conds, [0, 0, 0, 0, 1, 1])
    k1 = np.select(conds, [0, 0, 1, 1, 0, 0])
    i2 = np.select(conds, [1, 1, 1, 0, 0, 1])
    j2 = np.select(conds, [1, 0, 0, 1, 1, 1])
    k2 = np.select(conds, [0, 1, 1, 1, 1, 0])

    # Offsets of the point from the other three corners, in unskewed space,
    # with the Java expression order (x0 - i1 + G3, x0 - i2 + 2*G3, ...).
    x1 = x0 - i1 + G3
    y1 = y0 - j1 + G3
    z1 = z0 - k1 + G3
    x2 = x0 - i2 + 2.0 * G3
    y2 = y0 - j2 + 2.0 * G3
    z2 = z0 - k2 + 2.0 * G3
    x3 = x0 - 1.0 + 3.0 * G3
    y3 = y0 - 1.0 + 3.0 * G3
    z3 = z0 - 1.0 + 3.0 * G3

    # Hashed gradient indices.  "& 255" on int64 is two's-complement, so
    # negative cells wrap exactly like Java's int & 255.
    ii = i.astype(np.int64) & 255
    jj = j.astype(np.int64) & 255
    kk = k.astype(np.int64) & 255
    gi0 = PERM[ii + PERM[jj + PERM[kk]]] % 12
    gi1 = PERM[ii + i1 + PERM[jj + j1 + PERM[kk + k1]]] % 12
    gi2 = PERM[ii + i2 + PERM[jj + j2 + PERM[kk + k2]]] % 12
    gi3 = PERM[ii + 1 + PERM[jj + 1 + PERM[kk + 1]]] % 12

    n0 = _corner_contribution(gi0, x0, y0, z0)
    n1 = _corner_contribution(gi1, x1, y1, z1)
    n2 = _corner_contribution(gi2, x2, y2, z2)
    n3 = _corner_contribution(gi3, x3, y3, z3)
    # Summed left to right as in Java, then scaled to about [-1, 1].
    return np.asarray(_SIMPLEX_SCALE * (n0 + n1 + n2 + n3), dtype=np.float64)


# ---------------------------------------------------------------------------
# Turbulence
# ---------------------------------------------------------------------------

#: Octave exponents e_i of thesis listing A.14: octave i samples the noise at
#: frequency f_i = 2**e_i and weights it by 1/f_i.  Seven octaves; the seventh
#: exponent is 0 (f = 1), as in the thesis.  Not monotonic on purpose.
TURBULENCE_EXPONENTS = (0.05, 2.0, 4.0, 6.0, 12.0, 8.0, 0.0)

#: Per-octave shift (noise-space units): octave i is sampled at
#: f*p + i*OCTAVE_SHIFT.  The thesis decorrelated octaves with 4D noise and
#: w = i; shifting 3D noise by incommensurate amounts (10*pi, 10*e, 10*sqrt 2)
#: serves the same purpose without a 4D implementation.
OCTAVE_SHIFT = (31.4159265, 27.1828183, 14.1421356)


def turbulence(x, y, z) -> np.ndarray:
    """Seven-octave turbulence sum.

    ``sum_i simplex_noise3(f_i*x + i*sx, f_i*y + i*sy, f_i*z + i*sz) / f_i``
    with ``f_i = 2**TURBULENCE_EXPONENTS[i]``, ``(sx, sy, sz) = OCTAVE_SHIFT``
    and i = 0..6.  Note that there is no absolute value (this is a signed sum
    of octaves, the caller clips it).

    Parameters
    ----------
    x, y, z : array_like of float
        Sample position in box units (plus any scene offset), broadcast
        against each other.

    Returns
    -------
    ndarray of float64
        Turbulence value (dimensionless), broadcast shape of the inputs.
    """
    x, y, z = np.broadcast_arrays(
        np.asarray(x, dtype=np.float64),
        np.asarray(y, dtype=np.float64),
        np.asarray(z, dtype=np.float64),
    )
    sx, sy, sz = OCTAVE_SHIFT
    total = np.zeros(x.shape, dtype=np.float64)
    # Octaves accumulated in listing order (0..6) so the float64 rounding is
    # reproducible; a kernel summing in the same order matches to ~1 ulp.
    for octave, exponent in enumerate(TURBULENCE_EXPONENTS):
        f = 2.0 ** exponent
        total = total + simplex_noise3(
            f * x + octave * sx, f * y + octave * sy, f * z + octave * sz
        ) / f
    return total


# ---------------------------------------------------------------------------
# Bump kernel and voxel geometry
# ---------------------------------------------------------------------------


def _check_radius(r: float) -> float:
    r = float(r)
    if not np.isfinite(r) or r < 0.0:
        raise ValueError(f"bump radius must be finite and >= 0, got {r!r}")
    return r


def _cubic_from_sq(d2, r: float) -> np.ndarray:
    """``cubic`` expressed with the squared distance (no square root needed)."""
    d2 = np.asarray(d2, dtype=np.float64)
    if r == 0.0:
        # Degenerate bump: the specification defines it as zero everywhere
        # (not a delta function), which also avoids 0/0.
        return np.zeros(d2.shape, dtype=np.float64)
    r2 = r * r
    w = 1.0 - d2 / r2
    return np.where(d2 < r2, w * w * w, 0.0)


def cubic(d, r: float) -> np.ndarray:
    """Compact cubic bump ``(1 - d^2/r^2)^3`` for ``d^2 < r^2``, else 0.

    Parameters
    ----------
    d : array_like of float
        Distance from the bump centre (box units; only ``d^2`` matters, so the
        sign is irrelevant).
    r : float
        Bump radius in box units, ``r >= 0``.  ``r == 0`` gives 0 everywhere.

    Returns
    -------
    ndarray of float64
        Kernel value in [0, 1] (dimensionless, 1 at the centre), same shape as
        ``d``.

    Raises
    ------
    ValueError
        If ``r`` is negative or not finite.
    """
    r = _check_radius(r)
    d = np.asarray(d, dtype=np.float64)
    return _cubic_from_sq(d * d, r)


def _check_shape(shape) -> Tuple[int, int, int]:
    shape = tuple(int(n) for n in shape)
    if len(shape) != 3 or any(n < 1 for n in shape):
        raise ValueError(f"shape must be three positive integers, got {shape!r}")
    return shape


def voxel_centres(shape) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxel-centre coordinates of a grid filling the unit box.

    Parameters
    ----------
    shape : sequence of 3 int
        Grid size ``(nx, ny, nz)``.

    Returns
    -------
    xc, yc, zc : ndarray of float64, shape (nx, ny, nz)
        ``xc[i, j, k] = (i + 0.5)/nx`` etc., in box units (``indexing="ij"``,
        so index ``[i, j, k]`` is ``(x, y, z)``).
    """
    nx, ny, nz = _check_shape(shape)
    cx = (np.arange(nx, dtype=np.float64) + 0.5) / nx
    cy = (np.arange(ny, dtype=np.float64) + 0.5) / ny
    cz = (np.arange(nz, dtype=np.float64) + 0.5) / nz
    xc, yc, zc = np.meshgrid(cx, cy, cz, indexing="ij")
    return xc, yc, zc


# Largest number of (voxel, subsample) distance evaluations held in memory at
# once by bump_voxel_average (~8 MB per float64 temporary); bounds memory for
# large bumps without changing the result.
_BUMP_CHUNK_POINTS = 1 << 20


def bump_voxel_average(shape, star_position, r: float, subsamples: int = 8) -> np.ndarray:
    """A star's cubic bump averaged over each voxel.

    For voxel ``(i, j, k)`` the value is the mean of ``cubic(|p - s|, r)`` over
    the ``subsamples**3`` midpoint-rule points
    ``p = voxel_min + (a + 0.5)/subsamples * voxel_size`` (``a = 0 ..
    subsamples-1`` per axis), where ``voxel_min = (i/nx, j/ny, k/nz)`` and
    ``voxel_size = (1/nx, 1/ny, 1/nz)``.  Averaging (rather than sampling at
    the centre) keeps the bump's mass right even when ``r`` is comparable to a
    voxel.

    Only voxels whose box intersects the open ball ``|p - s| < r`` are
    evaluated; every other voxel is exactly 0 under the definition (all its
    points have ``d >= r``), so the result equals the brute-force definition.

    Parameters
    ----------
    shape : sequence of 3 int
        Grid size ``(nx, ny, nz)``.
    star_position : array_like, shape (3,)
        Bump centre ``s`` in box units (may lie outside the box).
    r : float
        Bump radius in box units, ``r >= 0`` (0 gives an all-zero array).
    subsamples : int, optional
        Midpoint-rule points per axis per voxel (default 8, i.e. 512 points).

    Returns
    -------
    ndarray of float64, shape (nx, ny, nz)
        Voxel-averaged bump, dimensionless in [0, 1].

    Raises
    ------
    ValueError
        On a bad shape, position, radius or subsample count.
    """
    shape = _check_shape(shape)
    r = _check_radius(r)
    subsamples = int(subsamples)
    if subsamples < 1:
        raise ValueError(f"subsamples must be >= 1, got {subsamples!r}")
    s = np.asarray(star_position, dtype=np.float64)
    if s.shape != (3,) or not np.all(np.isfinite(s)):
        raise ValueError(f"star_position must be 3 finite numbers, got {star_position!r}")

    out = np.zeros(shape, dtype=np.float64)
    if r == 0.0:
        return out

    n = np.array(shape, dtype=np.float64)
    size = 1.0 / n  # voxel edge lengths, box units

    # Per-axis candidate index ranges: a conservative superset (padded by one
    # voxel against rounding) of the voxels overlapping [s - r, s + r]; the
    # exact box-ball test below makes the final decision.
    lo = np.clip(np.floor((s - r) * n).astype(np.int64) - 1, 0, np.array(shape))
    hi = np.clip(np.ceil((s + r) * n).astype(np.int64) + 1, 0, np.array(shape))
    if np.any(hi <= lo):
        return out
    axes_idx = [np.arange(lo[a], hi[a], dtype=np.int64) for a in range(3)]

    # Distance from s to the nearest point of each voxel box, per axis (0 when
    # s lies within the slab); the box meets the open ball iff the sum of
    # squares is < r^2.
    gaps = []
    for a in range(3):
        vmin = axes_idx[a] / n[a]
        vmax = vmin + size[a]
        gaps.append(np.maximum(np.maximum(vmin - s[a], s[a] - vmax), 0.0))
    gap2 = (
        (gaps[0] ** 2)[:, None, None]
        + (gaps[1] ** 2)[None, :, None]
        + (gaps[2] ** 2)[None, None, :]
    )
    sel = np.nonzero(gap2 < r * r)
    if sel[0].size == 0:
        return out
    vi = axes_idx[0][sel[0]]
    vj = axes_idx[1][sel[1]]
    vk = axes_idx[2][sel[2]]

    # Midpoint-rule fractions of a voxel edge, (a + 0.5)/subsamples.
    frac = (np.arange(subsamples, dtype=np.float64) + 0.5) / subsamples
    per_voxel = subsamples ** 3
    chunk = max(1, _BUMP_CHUNK_POINTS // per_voxel)
    values = np.empty(vi.size, dtype=np.float64)
    for start in range(0, vi.size, chunk):
        stop = min(start + chunk, vi.size)
        # p = voxel_min + frac * voxel_size, per axis: shape (m, subsamples).
        px = (vi[start:stop] / n[0])[:, None] + frac[None, :] * size[0]
        py = (vj[start:stop] / n[1])[:, None] + frac[None, :] * size[1]
        pz = (vk[start:stop] / n[2])[:, None] + frac[None, :] * size[2]
        dx2 = (px - s[0]) ** 2
        dy2 = (py - s[1]) ** 2
        dz2 = (pz - s[2]) ** 2
        d2 = (
            dx2[:, :, None, None]
            + dy2[:, None, :, None]
            + dz2[:, None, None, :]
        )
        values[start:stop] = _cubic_from_sq(d2, r).reshape(stop - start, per_voxel).mean(axis=1)
    out[vi, vj, vk] = values
    return out


def _sum_bumps(shape, stars) -> np.ndarray:
    """Sum of the voxel-averaged bumps of all stars, in list order."""
    total = np.zeros(shape, dtype=np.float64)
    for star in stars:
        position, radius = star
        total = total + bump_voxel_average(shape, position, radius)
    return total


def _check_floor(floor) -> float:
    floor = float(floor)
    if not np.isfinite(floor):
        raise ValueError(f"floor must be finite, got {floor!r}")
    return floor


# ---------------------------------------------------------------------------
# Density models
# ---------------------------------------------------------------------------

Star = Tuple[Sequence[float], float]


def density_turbulence(shape, offset, scale: float, floor: float, stars: Sequence[Star]) -> np.ndarray:
    """Turbulent dust density on a voxel grid.

    ``density = sum_stars bump_voxel_average(shape, s, r)
    + scale * max(0, turbulence(xc + ox, yc + oy, zc + oz))``, then
    ``max(density, floor)``; the turbulence is sampled at voxel centres
    (``voxel_centres``), the bumps are voxel averages with the default 8
    subsamples per axis.

    Parameters
    ----------
    shape : sequence of 3 int
        Grid size ``(nx, ny, nz)``.
    offset : array_like, shape (3,)
        Shift of the turbulence field, box units (selects a different patch of
        the same noise field).
    scale : float
        Multiplier of the clipped turbulence (relative density units).
    floor : float
        Lower clamp applied last (relative density units).
    stars : sequence of (position, bump_radius)
        ``position`` (3,) in box units, ``bump_radius`` >= 0 in box units.

    Returns
    -------
    ndarray of float64, shape (nx, ny, nz)
        Relative density; index ``[i, j, k]`` is ``(x, y, z)``.
    """
    shape = _check_shape(shape)
    off = np.asarray(offset, dtype=np.float64)
    if off.shape != (3,) or not np.all(np.isfinite(off)):
        raise ValueError(f"offset must be 3 finite numbers, got {offset!r}")
    floor = _check_floor(floor)
    xc, yc, zc = voxel_centres(shape)
    turb = turbulence(xc + off[0], yc + off[1], zc + off[2])
    # Negative turbulence means "no dust" rather than negative density.
    density = _sum_bumps(shape, stars) + float(scale) * np.maximum(0.0, turb)
    return np.maximum(density, floor)


def density_uniform(shape, density: float, floor: float, stars: Sequence[Star]) -> np.ndarray:
    """Uniform dust density plus the star bumps.

    ``max(density + sum_stars bump_voxel_average(shape, s, r), floor)``.

    Parameters
    ----------
    shape : sequence of 3 int
        Grid size ``(nx, ny, nz)``.
    density : float
        Uniform background density (relative density units).
    floor : float
        Lower clamp applied last (relative density units).
    stars : sequence of (position, bump_radius)
        ``position`` (3,) in box units, ``bump_radius`` >= 0 in box units.

    Returns
    -------
    ndarray of float64, shape (nx, ny, nz)
        Relative density; index ``[i, j, k]`` is ``(x, y, z)``.
    """
    shape = _check_shape(shape)
    floor = _check_floor(floor)
    result = np.full(shape, float(density), dtype=np.float64) + _sum_bumps(shape, stars)
    return np.maximum(result, floor)
