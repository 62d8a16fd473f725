"""The optimiser of a fit and its response surface: Nelder-Mead in the unit cube of the
bounds (:func:`_minimise`), then a quadratic fitted by least squares to designs about the
minimum (:func:`_refine`), whose curvature gives the covariance (:func:`_covariance`)."""

from __future__ import annotations

import math

import numpy as np



def _minimise(obj, z0, step: float, free_idx, fixed_z, fatol: float, maxfev: int):
    """Nelder-Mead over the coordinates ``free_idx`` of the unit cube, the others at ``fixed_z``."""
    from scipy.optimize import minimize

    z0 = np.asarray(z0, np.float64)
    k = len(free_idx)

    def full(y):
        z = np.array(fixed_z, np.float64)
        z[free_idx] = y
        return z

    y0 = z0[free_idx]
    # the initial simplex: a step along each axis, turned inwards at the cube's faces
    simplex = [y0]
    for j in range(k):
        y = y0.copy()
        y[j] = y0[j] + step if y0[j] + step <= 1.0 else y0[j] - step
        simplex.append(y)
    res = minimize(lambda y: obj(full(y)), y0, method="Nelder-Mead", bounds=[(0.0, 1.0)] * k,
                   options={"initial_simplex": np.array(simplex), "xatol": 1e-3, "fatol": fatol, "maxfev": maxfev})
    return full(res.x), float(res.fun)


def _quadratic(zs, fs):
    """Least-squares quadratic f = c + b.z + z.A.z / 2 through points (n, k); returns (c, b, A)
    or None when there are too few points."""
    zs = np.asarray(zs, np.float64)
    fs = np.asarray(fs, np.float64)
    n, k = zs.shape
    pairs = [(i, j) for i in range(k) for j in range(i, k)]
    if n < 1 + k + len(pairs) + 2:
        return None
    cols = [np.ones(n)] + [zs[:, i] for i in range(k)] + [zs[:, i] * zs[:, j] * (0.5 if i == j else 1.0)
                                                         for i, j in pairs]
    coef, *_ = np.linalg.lstsq(np.stack(cols, 1), fs, rcond=None)
    A = np.zeros((k, k))
    for (i, j), c in zip(pairs, coef[1 + k:]):
        A[i, j] = A[j, i] = c
    return coef[0], coef[1:1 + k], A


#: Refinement: design points at this many (quadratic) standard deviations from the centre,
#: where chi^2 has risen by about 4, well above its roughness (about 1 at the fits'
#: Monte Carlo errors: docs/observations.md); the quadratic is fitted to the traced points
#: within REGION standard deviations and DCHI2 of the lowest.
DESIGN_SIGMA, REGION, DCHI2 = 2.0, 3.5, 25.0


#: Largest variance of the design along any direction (a standard deviation of a quarter of the
#: cube): a flat direction would otherwise ask for points far outside.
MAX_VAR = 0.0625


def _capped(V, var) -> np.ndarray:
    """The covariance V diag(var) V^T with each variance in [1e-10, MAX_VAR]."""
    return V @ np.diag(np.clip(var, 1e-10, MAX_VAR)) @ V.T


def _design(k: int) -> np.ndarray:
    """Unit directions of a refinement round: +-e_i and (e_i +- e_j) / sqrt 2 for i < j."""
    out = []
    for i in range(k):
        for s in (-1.0, 1.0):
            e = np.zeros(k)
            e[i] = s
            out.append(e)
    for i in range(k):
        for j in range(i + 1, k):
            for s in (-1.0, 1.0):
                e = np.zeros(k)
                e[i], e[j] = 1.0 / math.sqrt(2.0), s / math.sqrt(2.0)
                out.append(e)
                out.append(-e)
    return np.array(out)


def _refine(obj, z0, cov0, rounds: int = 5):
    """A trust-region quadratic response surface about the minimum: each round traces a design
    of points DESIGN_SIGMA standard deviations out along the axes and diagonals of the present
    covariance, fits chi^2 = c + b.z + z.A.z / 2 by least squares to the traced points near the
    centre, and moves the centre to the quadratic's minimum (at most REGION standard deviations,
    inside the cube), with covariance 2 A^-1. Fitting many points smooths the fine staircase
    that common random numbers leave in chi^2 (Nelder-Mead and a point-by-point profile would
    follow its steps). Stops when the centre moves less than 0.3 standard deviations.
    Returns (centre, covariance or None, chi^2 of the quadratic at the centre)."""
    k = len(z0)
    zc, cov = np.asarray(z0, np.float64), np.asarray(cov0, np.float64)
    f_c = None
    dirs = _design(k)
    for _ in range(rounds):
        L = np.linalg.cholesky(cov)
        for u in dirs:
            obj(np.clip(zc + DESIGN_SIGMA * L @ u, 0.0, 1.0))
        pts = obj.points()
        fmin = min(c for _, c in pts)
        Li = np.linalg.inv(L)
        near = [(z, c) for z, c in pts if c < fmin + DCHI2 and np.linalg.norm(Li @ (z - zc)) < REGION]
        fit = _quadratic([z for z, _ in near], [c for _, c in near]) if len(near) > 0 else None
        if fit is None:
            cov = cov * 0.5  # too few points near: a tighter design (more points fall inside)
            continue
        c0, b, A = fit
        w, V = np.linalg.eigh(A)
        if not np.all(w > 0):
            # not a minimum yet (or flat in some direction): widen the design there, recentre on
            # the lowest trace
            cov = _capped(V, np.where(w > 0, 2.0 / np.maximum(w, 1e-300), MAX_VAR))
            zc = np.asarray(min(pts, key=lambda p: p[1])[0], np.float64)
            continue
        cov_new = _capped(V, 2.0 / w)
        z_new = -np.linalg.solve(A, b)
        step = z_new - zc
        r = np.linalg.norm(Li @ step)
        if r > REGION:
            z_new = zc + step * (REGION / r)
        z_new = np.clip(z_new, 0.0, 1.0)
        moved = np.linalg.norm(np.linalg.solve(np.linalg.cholesky(cov_new), z_new - zc))
        zc, cov = z_new, cov_new
        f_c = float(c0 + b @ zc + 0.5 * zc @ A @ zc)
        if moved < 0.3:
            break
    return zc, cov, f_c


def _local_start(obj, z, grid: int) -> np.ndarray:
    """A first covariance for the refinement: a quadratic through the traced points near ``z``
    when it is a minimum, else a grid cell (or 0.1) wide."""
    pts = [(p, c) for p, c in obj.points() if np.max(np.abs(np.asarray(p) - z)) < 0.25]
    fit = _quadratic([p for p, _ in pts], [c for _, c in pts]) if pts else None
    k = len(z)
    width = 0.25 / grid if grid > 0 else 0.05
    if fit is not None:
        w, V = np.linalg.eigh(fit[2])
        if np.all(w > 0):
            cov = 2.0 * V @ np.diag(1.0 / w) @ V.T
            return cov * min(1.0, 0.0625 / float(np.max(np.diag(cov))))
    return np.eye(k) * width ** 2


def _covariance(params, z, cov):
    """The unit-cube covariance as one of the parameters (through d value / dz; log parameters
    linearised)."""
    if cov is None:
        return None
    jac = np.array([(p.from_unit(min(zi + 1e-6, 1.0)) - p.from_unit(max(zi - 1e-6, 0.0))) /
                    (min(zi + 1e-6, 1.0) - max(zi - 1e-6, 0.0)) for p, zi in zip(params, z)])
    return cov * jac[:, None] * jac[None, :]
