"""Analytic reference fields for tests and the speed/accuracy trade study."""

from __future__ import annotations

import numpy as np


def voxel_centres(shape):
    """Voxel-centre coordinates (box units), three arrays of ``shape``, index [i, j, k] = x, y, z."""
    axes = [(np.arange(n) + 0.5) / n for n in shape]
    return np.meshgrid(*axes, indexing="ij")


def voxel_average_point_source(shape, star, kappa, luminosity, mask, order=6):
    """Voxel averages of the mean intensity of a point source in a pure absorber.

    J(r) = L exp(-kappa r) / (16 pi^2 r^2) (box units: L per box-unit area per steradian),
    averaged over each masked voxel by Gauss-Legendre quadrature with ``order``^3 nodes.
    Returns a 1-D array over ``mask``'s voxels. Voxels holding or touching the source are
    poorly integrated (a 1/r^2 singularity): mask them out.
    """
    nodes, weights = np.polynomial.legendre.leggauss(order)
    h = 1.0 / np.asarray(shape, float)
    X, Y, Z = voxel_centres(shape)
    cx, cy, cz = X[mask], Y[mask], Z[mask]
    total = np.zeros(cx.size)
    for a, wa in zip(nodes, weights):
        for b, wb in zip(nodes, weights):
            for c, wc in zip(nodes, weights):
                dx = cx + 0.5 * a * h[0] - star[0]
                dy = cy + 0.5 * b * h[1] - star[1]
                dz = cz + 0.5 * c * h[2] - star[2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                total += wa * wb * wc * luminosity * np.exp(-kappa * r) / (16 * np.pi**2 * r * r)
    return total / 8.0
