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
    h = 1.0 / np.asarray(shape, float)
    X, Y, Z = voxel_centres(shape)
    lo = np.stack([X[mask], Y[mask], Z[mask]], axis=1) - 0.5 * h
    return box_average_point_source(lo, lo + h, star, kappa, luminosity, order)


def box_average_point_source(lo, hi, star, kappa, luminosity, order=6):
    """Averages of the pure absorber's J(r) (as :func:`voxel_average_point_source`) over boxes
    [lo, hi) ((n, 3) box units each, e.g. a tree's leaves): a 1-D array of n. Boxes holding or
    touching the source are poorly integrated: leave them out."""
    nodes, weights = np.polynomial.legendre.leggauss(order)
    lo, hi = np.asarray(lo, float).reshape(-1, 3), np.asarray(hi, float).reshape(-1, 3)
    c, h = 0.5 * (lo + hi), hi - lo
    total = np.zeros(len(lo))
    for a, wa in zip(nodes, weights):
        for b, wb in zip(nodes, weights):
            for k, wc in zip(nodes, weights):
                dx = c[:, 0] + 0.5 * a * h[:, 0] - star[0]
                dy = c[:, 1] + 0.5 * b * h[:, 1] - star[1]
                dz = c[:, 2] + 0.5 * k * h[:, 2] - star[2]
                r = np.sqrt(dx * dx + dy * dy + dz * dz)
                total += wa * wb * wc * luminosity * np.exp(-kappa * r) / (16 * np.pi**2 * r * r)
    return total / 8.0
