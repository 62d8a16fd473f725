"""Test oracle: scattered light of a star above a finite uniform slab, by a Monte Carlo of its own.

Independent of the product: NumPy in float64, continuous geometry (no voxels: the slab is the
box [0, 1] x [0, 1] x [0, h]), NumPy's PCG64 random numbers, and its own variance reduction,
textbook rather than the kernel's: the exponential transform on every flight (Levitt 1968: the
extinction kappa (1 - b mu) along the downward cosine mu, b = min(k, 0.8)), implicit capture,
and weight windows on depth alone, set at each collision (split above twice the window, Russian
roulette below a quarter of it; MCNP's weight windows with a plane-parallel importance
e^(k tau), k the diffusion decay rate of tests/oracles/plane_parallel.py). Every collision
peels off towards each observer direction: w p(cos theta) e^(-kappa L), L the path to the
slab's surface, which a convex slab in vacuum gives in closed form. No forced collisions, no
composite (mixture) biasing, no depth map, no voxels.

It answers the TRUST I slab benchmark's question (Gordon et al. 2017, A&A 603, A114: a star
above a 10 x 10 x 3 pc slab, seen from 7 angles) for the light the slab scatters, and is
itself checked against the exact plane-parallel answer on a slab made laterally infinite
(tests/transport/test_slab_oracle_mc.py).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .plane_parallel import decay_rate


@dataclasses.dataclass(frozen=True)
class BoxSlab:
    """A uniform slab [x0, x1] x [y0, y1] x [0, h] (box units) lit by a star of luminosity 1.

    kappa: extinction per box unit; albedo, g: Henyey-Greenstein dust; star: its position
    (above the slab: z > h)."""

    kappa: float
    albedo: float
    g: float
    h: float
    star: tuple
    x0: float = 0.0
    x1: float = 1.0
    y0: float = 0.0
    y1: float = 1.0

    @property
    def tau_z(self) -> float:
        return self.kappa * self.h


#: the exponential transform's parameter at most this (its flights upwards are shortened by 1 + b)
TRANSFORM_MAX = 0.8


def _exit_distance(s: BoxSlab, p: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Distance from points p (inside the slab) along directions d to the slab's surface."""
    lo = np.array([s.x0, s.y0, 0.0])
    hi = np.array([s.x1, s.y1, s.h])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (hi - p) / d, np.where(d < 0, (lo - p) / d, np.inf))
    return np.maximum(t.min(axis=1), 0.0)


def _hg_cos(g: float, u: np.ndarray) -> np.ndarray:
    """Henyey-Greenstein cosines from uniforms u (inverse of the CDF)."""
    if abs(g) < 1e-6:
        return 2.0 * u - 1.0
    f = (1.0 - g * g) / (1.0 - g + 2.0 * g * u)
    return np.clip((1.0 + g * g - f * f) / (2.0 * g), -1.0, 1.0)


def _hg(g: float, mu: np.ndarray) -> np.ndarray:
    """Henyey-Greenstein phase function per steradian."""
    return (1.0 - g * g) / (4.0 * math.pi * (1.0 + g * g - 2.0 * g * mu) ** 1.5)


def _turn(d: np.ndarray, mu: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Directions at angle acos(mu) from d, azimuth phi about it."""
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - mu * mu))
    # an orthonormal pair perpendicular to d
    a = np.where(np.abs(d[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(d, a)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(d, e1)
    out = (mu[:, None] * d + (sin_t * np.cos(phi))[:, None] * e1 + (sin_t * np.sin(phi))[:, None] * e2)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def scattered(slab: BoxSlab, directions, packets: int, seed: int = 1, chunk: int = 50_000):
    """Power per steradian the slab scatters towards each observer direction.

    Parameters
    ----------
    slab : BoxSlab
    directions : array (n_dir, 3)
        Unit vectors towards the observers.
    packets : int
        Packets emitted by the star (downwards: the upper half, which misses the slab, carries
        no scattered light).

    Returns
    -------
    (value, standard error) : arrays (n_dir,)
        The error from the packets' own totals (each packet with all its split copies).
    """
    o = np.asarray(directions, np.float64).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    k = decay_rate(slab.albedo, slab.g)
    star = np.asarray(slab.star, np.float64)
    s1 = np.zeros(o.shape[0])
    s2 = np.zeros(o.shape[0])
    done = 0
    while done < packets:
        n = min(chunk, packets - done)
        tot = _chunk(slab, o, n, rng, k, star)
        s1 += tot.sum(axis=0)
        s2 += (tot**2).sum(axis=0)
        done += n
    mean = s1 / packets
    var = np.maximum(s2 / packets - mean**2, 0.0) / (packets - 1)
    return mean, np.sqrt(var)


def _chunk(s: BoxSlab, o: np.ndarray, n: int, rng, k: float, star: np.ndarray) -> np.ndarray:
    """Per packet of n, its total peel-off towards each direction (n, n_dir)."""
    tot = np.zeros((n, o.shape[0]))
    # downward hemisphere, isotropic: weight 1/2 (of a packet of the star's whole sphere)
    mu = -rng.random(n)
    mu = np.where(mu == 0.0, -1e-12, mu)
    phi = 2.0 * math.pi * rng.random(n)
    st = np.sqrt(1.0 - mu * mu)
    d = np.stack([st * np.cos(phi), st * np.sin(phi), mu], axis=1)
    t = (s.h - star[2]) / d[:, 2]
    p = star[None, :] + t[:, None] * d
    inside = (p[:, 0] >= s.x0) & (p[:, 0] <= s.x1) & (p[:, 1] >= s.y0) & (p[:, 1] <= s.y1)
    hist = np.nonzero(inside)[0]
    p, d = p[inside], d[inside]
    p[:, 2] = s.h
    w = np.full(hist.size, 0.5)
    w0 = 0.5
    b = min(k, TRANSFORM_MAX)
    while hist.size:
        # a flight under the exponential transform towards depth: extinction kappa (1 - b mu),
        # mu the cosine with the downward normal, and the weight times the ratio of the
        # densities, (kappa / kappa*) e^-(kappa - kappa*) s, at the collision
        ks = s.kappa * (1.0 - b * -d[:, 2])
        step = -np.log1p(-rng.random(hist.size)) / ks
        keep = step < _exit_distance(s, p, d)
        w = w * (s.kappa / ks) * np.exp(-(s.kappa - ks) * step)
        hist, p, d, w = hist[keep], p[keep] + step[keep, None] * d[keep], d[keep], w[keep]
        if not hist.size:
            break
        # implicit capture, then peel-off towards every observer
        w = w * s.albedo
        for j in range(o.shape[0]):
            oj = np.broadcast_to(o[j], p.shape)
            c = w * _hg(s.g, d @ o[j]) * np.exp(-s.kappa * _exit_distance(s, p, oj))
            np.add.at(tot[:, j], hist, c)
        # weight windows on depth: split above 2 W, roulette below W / 4 (to W / 2)
        wc = w0 * np.exp(-k * s.kappa * (s.h - p[:, 2]))
        ratio = w / wc
        low = ratio < 0.25
        survive = rng.random(hist.size) < ratio / 0.5
        w = np.where(low, 0.5 * wc, w)
        alive = ~low | survive
        hist, p, d, w, ratio = hist[alive], p[alive], d[alive], w[alive], ratio[alive]
        copies = np.where(ratio > 2.0, np.floor(ratio + rng.random(hist.size)).astype(np.int64), 1)
        copies = np.maximum(copies, 1)
        w = w / copies
        hist, p, d, w = (np.repeat(hist, copies), np.repeat(p, copies, axis=0), np.repeat(d, copies, axis=0),
                         np.repeat(w, copies))
        # scatter
        d = _turn(d, _hg_cos(s.g, rng.random(hist.size)), 2.0 * math.pi * rng.random(hist.size))
    return tot
