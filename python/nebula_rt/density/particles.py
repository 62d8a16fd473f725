"""Particle snapshots (SPH) on an octree: a tree refined by particle count, and the particles'
mass deposited onto its leaves with the SPH kernel, the total mass kept exactly.

Particles come as positions (box units, inside the unit box), masses and smoothing lengths h
(box units); the kernel is the cubic spline of Monaghan & Lattanzio (1985) in the convention of
Gadget-2 (Springel 2005) and Phantom's ``W`` with compact support r < h:

    W(q) = 8 / (pi h^3) x (1 - 6 q^2 + 6 q^3)   for q = r / h <= 1/2,
           8 / (pi h^3) x 2 (1 - q)^3            for 1/2 < q <= 1, and 0 beyond.

:func:`refine_by_count` makes the tree: a cell is split while it holds more than
``max_per_leaf`` particles and is above ``max_depth``. :func:`deposit` spreads each particle's
mass over the leaves its kernel reaches: the kernel is sampled at the centres of a lattice of
``samples^3`` points over the particle's support cube, each sample's weight W is given to the
leaf holding it, and the weights of the samples inside the box are normalised to sum to 1, so
the particle's whole mass lands in the box (its part beyond a face is folded back onto the
cells inside) and the leaves' masses sum to the particles' to float64 rounding. A particle far
smaller than its leaf puts all its mass into that leaf; one far larger than the leaves is
resolved by the lattice (``samples`` per support diameter).
"""

from __future__ import annotations

import math

import numpy as np

from ..limits import MAX_TREE_DEPTH
from .octree import Octree, from_boxes

__all__ = ["cubic_spline", "deposit", "particles_on_tree", "refine_by_count"]

#: lattice points per axis of a particle's support cube in :func:`deposit`
DEFAULT_SAMPLES = 8


def cubic_spline(q) -> np.ndarray:
    """W(q) h^3: the cubic spline kernel (the module's doc) as a function of q = r / h."""
    q = np.asarray(q, np.float64)
    w = np.where(q <= 0.5, 1.0 - 6.0 * q * q + 6.0 * q ** 3, 2.0 * np.clip(1.0 - q, 0.0, None) ** 3)
    return 8.0 / math.pi * np.where(q <= 1.0, w, 0.0)


def _check(positions, masses, h):
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    m = np.asarray(masses, np.float64).reshape(-1)
    hh = np.asarray(h, np.float64)
    hh = np.full(len(m), float(hh)) if hh.ndim == 0 else hh.reshape(-1)
    if not (len(p) == len(m) == len(hh)) or not len(p):
        raise ValueError(f"{len(p)} positions, {len(m)} masses and {len(hh)} smoothing lengths: one of each "
                         "per particle, at least one particle")
    for name, x in (("position", p), ("mass", m), ("smoothing length", hh)):
        bad = np.flatnonzero(~np.isfinite(x).reshape(len(x), -1).all(axis=1))
        if bad.size:
            raise ValueError(f"particle {bad[0]}: {name} {x[bad[0]].tolist()} is not finite")
    outside = np.flatnonzero(~np.all((p >= 0.0) & (p <= 1.0), axis=1))
    if outside.size:
        i = outside[0]
        raise ValueError(f"particle {i} at {p[i].tolist()} lies outside the box [0, 1]^3 "
                         f"({outside.size} of {len(p)} do)")
    for name, x in (("mass", m), ("smoothing length", hh)):
        bad = np.flatnonzero(x < 0.0) if name == "mass" else np.flatnonzero(x <= 0.0)
        if bad.size:
            raise ValueError(f"particle {bad[0]}: {name} {x[bad[0]]!r} must be {'>= 0' if name == 'mass' else '> 0'}")
    return p, m, hh


def refine_by_count(positions, roots, max_per_leaf: int = 8, max_depth: int = 10, masses=None,
                    sigma: float = 0.0, max_tau: float = math.inf) -> Octree:
    """The tree (leaf densities 0) whose cells are split while they hold more than
    ``max_per_leaf`` particles, down to ``max_depth`` levels below ``roots`` root cells; with
    ``masses``, also while the optical depth across a cell's longest edge of the mass whose
    particles' centres it holds, ``sigma`` x mass / volume x edge, exceeds ``max_tau`` (SKIRT's
    maximum optical depth per cell, on the particles' masses before they are spread)."""
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    r = np.array([int(x) for x in roots], np.int64)
    if r.size != 3 or r.min() < 1 or int(max_per_leaf) < 1 or not 0 <= int(max_depth) <= MAX_TREE_DEPTH:
        raise ValueError(f"roots must be 3 positive counts, max_per_leaf >= 1 and max_depth in [0, {MAX_TREE_DEPTH}]; got "
                         f"{roots}, {max_per_leaf}, {max_depth}")
    _check(p, np.zeros(len(p)), 1.0)
    fine = np.minimum(np.floor(p * r * 2.0 ** max_depth).astype(np.int64), r * (1 << max_depth) - 1)
    lo, hi = [], []
    # cells to look at, per level: start with every root (those with no particle are leaves too)
    cells = np.stack(np.unravel_index(np.arange(int(r.prod())), tuple(r), order="F"), axis=1)
    octants = np.array(list(np.ndindex(2, 2, 2)))[:, ::-1]
    for level in range(int(max_depth) + 1):
        size = r * (1 << level)
        key = lambda c: c[:, 0] + size[0] * (c[:, 1] + size[1] * c[:, 2])  # noqa: E731
        held = fine >> (int(max_depth) - level)
        ks, inverse, counts = np.unique(key(held), return_inverse=True, return_counts=True)
        pos = np.searchsorted(ks, key(cells))
        found = (pos < len(ks)) & (ks[np.minimum(pos, len(ks) - 1)] == key(cells))
        n = np.where(found, counts[np.minimum(pos, len(ks) - 1)], 0)
        split = n > int(max_per_leaf)
        if masses is not None and sigma > 0.0:
            cell_mass = np.bincount(inverse.reshape(-1), weights=np.asarray(masses, np.float64), minlength=len(ks))
            m = np.where(found, cell_mass[np.minimum(pos, len(ks) - 1)], 0.0)
            edge = 1.0 / size  # per axis
            split |= sigma * m / float(np.prod(edge)) * float(edge.max()) > max_tau
        split &= level < int(max_depth)
        lo.append(cells[~split] / size)
        hi.append((cells[~split] + 1) / size)
        cells = (2 * cells[split][:, None, :] + octants[None, :, :]).reshape(-1, 3)
        if not len(cells):
            break
    lo, hi = np.concatenate(lo), np.concatenate(hi)
    return from_boxes(lo, hi, np.zeros(len(lo)), tuple(int(x) for x in r))


def deposit(tree: Octree, positions, masses, h, samples: int = DEFAULT_SAMPLES, chunk: int = 20_000):
    """The leaves' masses (n_leaves,) and densities (mass / leaf volume, box units) of the
    particles on ``tree`` (see the module's doc); the masses sum to ``sum(masses)`` to float64
    rounding. Returns (mass, density)."""
    p, m, hh = _check(positions, masses, h)
    k = int(samples)
    if k < 1:
        raise ValueError(f"samples must be >= 1, got {samples!r}")
    u = (np.arange(k) + 0.5) / k * 2.0 - 1.0  # lattice over [-1, 1] per axis, in units of h
    offsets = np.stack(np.meshgrid(u, u, u, indexing="ij"), axis=-1).reshape(-1, 3)
    w0 = cubic_spline(np.linalg.norm(offsets, axis=1))
    if not (w0 > 0).any():  # (one sample: the centre, q = 0)
        w0 = np.ones(len(offsets))
    out = np.zeros(tree.n_leaves, np.float64)
    for s in range(0, len(p), chunk):
        pp, mm, h_ = p[s:s + chunk], m[s:s + chunk], hh[s:s + chunk]
        pts = pp[:, None, :] + h_[:, None, None] * offsets[None, :, :]
        inside = np.all((pts >= 0.0) & (pts <= 1.0), axis=2)
        w = np.where(inside, w0[None, :], 0.0)
        total = w.sum(axis=1)
        # a particle whose lattice lies wholly outside the box (or misses the kernel): its
        # mass goes to the leaf holding it
        lost = total <= 0.0
        w[lost] = 0.0
        w = np.where(total[:, None] > 0, w / np.where(total > 0, total, 1.0)[:, None], 0.0) * mm[:, None]
        leaf = tree.locate(np.where(inside[..., None], pts, pp[:, None, :]).reshape(-1, 3))
        out += np.bincount(leaf, weights=w.reshape(-1), minlength=tree.n_leaves)
        if lost.any():
            out += np.bincount(tree.locate(pp[lost]), weights=mm[lost], minlength=tree.n_leaves)
    lo, hi, _ = tree.leaves()
    return out, out / np.prod(hi - lo, axis=1)


def particles_on_tree(positions, masses, h, max_per_leaf: int, max_depth: int, sigma: float = 0.0,
                      max_tau: float = math.inf) -> Octree:
    """The octree of particles in box units (positions in [0, 1]^3, smoothing lengths ``h``):
    one root cell split while a cell holds more than ``max_per_leaf`` particles (or, with
    ``sigma`` > 0, while its particles' optical depth exceeds ``max_tau``), down to ``max_depth``
    levels (:func:`refine_by_count`), each leaf's density its deposited mass over its volume
    (:func:`deposit`), float32. ValueError names a particle outside the box or a bad value."""
    tree = refine_by_count(positions, (1, 1, 1), max_per_leaf, max_depth, masses, sigma, max_tau)
    _, rho = deposit(tree, positions, masses, h)
    return Octree(tree.roots, tree.child, np.asarray(rho).astype(np.float32))
