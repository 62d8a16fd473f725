"""The Pinte et al. (2009, A&A 498, 967) polarization benchmark's disk, star and grains, for
NebulaRT (benchmarks/bench_pinte2009.py runs it).

The configuration, as the benchmark defines it (and Hyperion's own test of it,
hyperion/model/tests/test_bit_level.py, TestPinteBenchmark, restates it):

- a point star at the centre (T 4000 K, R 2 R_sun: at one wavelength only its position matters);
- a flared disk between cylindrical radii 0.1 and 400 AU with sharp edges, surface density
  Sigma ~ R^-1.5 and a Gaussian vertical profile of scale height h = 10 AU (R / 100 AU)^1.125,
  so rho(R, z) = rho_0 (R / 100 AU)^-2.625 exp(-z^2 / 2 h^2);
- grains of astronomical silicate, 1 micron spheres, at 1 micron: albedo 0.6474786, their
  scattering matrix tabulated by the benchmark (benchmarks/data/pinte2009/);
- the disk's optical depth at 1 micron along the midplane from 0.1 to 400 AU: 1e3, 1e4, 1e5 or
  1e6 (dust masses 3e-8 to 3e-5 M_sun);
- images at 1 micron, 251 pixels over 900 AU, at inclinations with cos i = 0.05 ... 0.95
  (69.5 and 87.1 degrees in the polarization figures).

The box is a cube of 900 AU about the star (box units: 900 AU). The density lives on an
octree refined where it matters to the scattered light: a cell splits while it is larger than
``fraction`` of its distance from the star and the dust over that distance has an optical
depth of at least ``tau_floor`` (the disk's surface, where the starlight scatters, and below);
each leaf holds the mean of the density at 4^3 points inside it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parent / "data" / "pinte2009"
MATRIX = DATA / "mueller_matrix_1um.dat"
CUTS = DATA / "published_cuts_tau1e6.csv"
#: the benchmark's albedo at 1 micron (its web site's optical properties)
ALBEDO = 0.6474786
BOX_AU = 900.0
R_IN_AU, R_OUT_AU = 0.1, 400.0
H0_AU, R0_AU, FLARING, SIGMA_SLOPE = 10.0, 100.0, 1.125, -1.5
#: the midplane density's exponent: Sigma / h
RHO_SLOPE = SIGMA_SLOPE - FLARING


def density(R, z):
    """The disk's density (1 at R = 100 AU in the midplane) at cylindrical radius R and height
    z (AU)."""
    R = np.asarray(R, np.float64)
    z = np.asarray(z, np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
        h = H0_AU * (R / R0_AU) ** FLARING
        rho = (R / R0_AU) ** RHO_SLOPE * np.exp(-0.5 * (z / h) ** 2)
    return np.where((R >= R_IN_AU) & (R <= R_OUT_AU), rho, 0.0)


def midplane_column_box() -> float:
    """The integral of the midplane density from R_in to R_out, in box units (so that ``tau``
    per box at density 1 times it is the midplane optical depth)."""
    a = RHO_SLOPE + 1.0
    integral_au = R0_AU / a * ((R_OUT_AU / R0_AU) ** a - (R_IN_AU / R0_AU) ** a)
    return integral_au / BOX_AU


def tau_per_box(midplane_tau: float) -> float:
    """NebulaRT's ``tau`` (optical depth across the box at density 1) for a midplane optical
    depth ``midplane_tau`` from R_in to R_out."""
    return float(midplane_tau) / midplane_column_box()


_OCTANTS = np.array(list(np.ndindex(2, 2, 2)))[:, ::-1]  # child c = ix + 2 iy + 4 iz


def _cell_points(lo, size, n):
    """(cells, n^3, 3) points at the centres of an n^3 lattice inside each cell (box units)."""
    g = (np.arange(n) + 0.5) / n
    lattice = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    return lo[:, None, :] + size * lattice[None, :, :]


def _au(points):
    """Cylindrical R and z (AU) of box points (the star at the centre, the disk's axis z)."""
    p = (points - 0.5) * BOX_AU
    return np.hypot(p[..., 0], p[..., 1]), p[..., 2]


def build_tree(midplane_tau: float, fraction: float = 0.1, height: float = 0.5, tau_floor: float = 1e-3,
               roots: int = 8, max_level: int = 18, samples: int = 4, chunk: int = 200_000):
    """The disk on an octree (:class:`nebula_rt.density.octree.Octree`) and NebulaRT's ``tau``.

    A cell splits (down to ``max_level`` levels below ``roots`` per axis) where tau x (its
    largest sampled density) x its nearest point's distance from the star (at least R_in) is at
    least ``tau_floor``, while its edge is larger than ``fraction`` of that distance or than
    ``height`` scale heights at its nearest cylindrical radius (the vertical profile resolved:
    cells taller than h would average the midplane's density down, and with it the inner
    disk's shadow). Each leaf's density is the mean of ``samples``^3 points inside it."""
    from nebula_rt.density.octree import Octree

    tau = tau_per_box(midplane_tau)
    corners = np.stack(np.unravel_index(np.arange(roots ** 3), (roots,) * 3, order="F"), axis=1).astype(np.int64)
    child_levels, dens = [], []
    next_node, leaves = roots ** 3, 0
    for level in range(max_level + 1):
        size = 1.0 / (roots * 2 ** level)
        lo = corners * size
        n = len(corners)
        rho_max = np.empty(n)
        rho_mean = np.empty(n)
        for s in range(0, n, chunk):
            R, z = _au(_cell_points(lo[s:s + chunk], size, samples))
            rho = density(R, z)
            rho_max[s:s + chunk], rho_mean[s:s + chunk] = rho.max(axis=1), rho.mean(axis=1)
        # the nearest point of the cell to the star (box units)
        nearest = np.clip(0.5, lo, lo + size)
        dist = np.maximum(np.linalg.norm(nearest - 0.5, axis=1), R_IN_AU / BOX_AU)
        r_near = np.maximum(np.hypot(nearest[:, 0] - 0.5, nearest[:, 1] - 0.5) * BOX_AU, R_IN_AU)
        h_box = H0_AU * (r_near / R0_AU) ** FLARING / BOX_AU
        split = ((tau * rho_max * dist >= tau_floor) & ((size > fraction * dist) | (size > height * h_box))
                 if level < max_level else np.zeros(n, bool))
        c = np.empty(n, np.int64)
        inner = np.flatnonzero(split)
        leaf = np.flatnonzero(~split)
        c[inner] = next_node + 8 * np.arange(inner.size)
        c[leaf] = -1 - (leaves + np.arange(leaf.size))
        next_node += 8 * inner.size
        leaves += leaf.size
        child_levels.append(c)
        dens.append(rho_mean[leaf])
        corners = (2 * corners[inner][:, None, :] + _OCTANTS[None, :, :]).reshape(-1, 3)
        if not len(corners):
            break
    tree = Octree(roots=(roots,) * 3, child=np.concatenate(child_levels).astype(np.int32),
                  density=np.concatenate(dens).astype(np.float32))
    return tree, tau


def midplane_tau_of(tree, tau: float, samples: int = 200_001) -> float:
    """The optical depth along the midplane from R_in to R_out through the tree's leaves (the
    discretised disk's, to compare with the definition's): a fine line of points just above the
    midplane (a point on it would lie on the cells' faces)."""
    r = np.geomspace(R_IN_AU, R_OUT_AU, samples)
    pts = np.stack([0.5 + r / BOX_AU, np.full_like(r, 0.5), np.full_like(r, 0.5 + 1e-9)], axis=1)
    rho = tree.density[tree.locate(pts)].astype(np.float64)
    return float(np.sum(0.5 * (rho[1:] + rho[:-1]) * np.diff(r)) / BOX_AU * tau)


def camera(inclination_deg: float, pixels: int = 251):
    """The benchmark's image: ``pixels`` over 900 AU (the box), the observer at inclination i
    from the disk's axis (+z), on the -y side; the image's x along the disk's major axis (box x),
    its up the projection of +z (the far side of the disk up)."""
    from nebula_rt.observe.sky import Camera

    i = math.radians(inclination_deg)
    return Camera(direction=(0.0, math.sin(i), -math.cos(i)), up=(0.0, 0.0, 1.0), size=(pixels, pixels), extent=1.0)


def read_cuts(path: Path = CUTS):
    """The published cuts (digitized): {cut: dict(x_au, consensus, spread, skirt, pinball, mcmax, mcfost)}
    and the header's cut positions {cut: (axis, offset_au, inclination)}."""
    positions = {}
    for line in path.read_text().splitlines():
        parts = line.split()
        if line.startswith("# cut ") and parts[2].isdigit():
            _, _, k, axis, off, inc = parts[:6]
            positions[int(k)] = (axis, float(off), float(inc))
    rows = [line.split(",") for line in path.read_text().splitlines() if line and not line.startswith("#")]
    names, rows = rows[0], rows[1:]
    a = np.array([[float(v) if v else np.nan for v in r] for r in rows])
    out = {}
    for k in sorted(set(a[:, 0].astype(int))):
        sel = a[:, 0].astype(int) == k
        out[k] = {name: a[sel, j] for j, name in enumerate(names) if name != "cut"}
    return out, positions
