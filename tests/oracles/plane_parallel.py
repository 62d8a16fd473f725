"""Exact plane-parallel radiative transfer for Henyey-Greenstein dust: a test oracle.

Adding-doubling (van de Hulst 1980; Wiscombe 1976) for a homogeneous slab of optical depth
``tau``, albedo ``a`` and HG asymmetry ``g``, azimuth-averaged (the m = 0 Fourier term, all a
point source integrated over the slab's area needs). Nothing of NebulaRT is used: this code is
the independent answer the Monte Carlo transport is held against.

Discretisation: Gauss-Legendre nodes mu_j, weights w_j on (0, 1] per hemisphere ("double
Gauss"), plus output nodes of weight zero (mu = 1 by default), which take part in nothing but
receive light, so the answer at mu = 1 is exact for the quadrature and not interpolated. The
reflection and transmission operators act on intensities: ``I_out = R @ I_in``. A thin layer
of depth delta = tau / 2^n is solved exactly for the discrete ordinates (a matrix exponential
of the two-stream-of-N system), then doubled n times:

    T2 = T (1 - R R)^-1 T,   R2 = R + T (1 - R R)^-1 R T

(a homogeneous layer looks the same from either side). All entries are non-negative and the
doubling subtracts nothing, so transmissions down to 1e-30 keep their relative precision.

The azimuth-averaged HG phase function is in closed form with a complete elliptic integral
(:func:`hg_azimuth_average`), checked against its Legendre series in the oracle's own tests
(``tests/transport/test_plane_parallel_oracle.py``), as are Chandrasekhar's H-function reflection of a
semi-infinite isotropic atmosphere, R + T = 1 at albedo 1, the single-scattering limit, the
discrete-ordinates decay rate of thick slabs and the convergence in the quadrature.

A point source of luminosity L above an infinite slab, integrated over the slab's area, is
the uniform illumination I_in(mu0) = L / (4 pi A mu0) (the power per steradian crossing the
top face is L / 4 pi in every downward direction); the area-integrated power per steradian
leaving in direction mu is then A mu I_out(mu) (:class:`PointSourceSlab`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.linalg import expm, solve
from scipy.special import ellipe, roots_legendre


def hg_azimuth_average(g: float, mu1, mu2):
    """The HG phase function averaged over the azimuth between two directions of polar cosines
    mu1, mu2: p0 = (1 / 2 pi) int p_HG(cos Theta) dphi, with p_HG normalised to
    (1 / 4 pi) int p dOmega = 1, so (1 / 2) int_-1^1 p0 dmu2 = 1.

    cos Theta = mu1 mu2 + s cos(phi), s = sqrt((1 - mu1^2)(1 - mu2^2)); with A = 1 + g^2 -
    2 g mu1 mu2 and B = 2 g s, int_0^pi (A - B cos phi)^-3/2 dphi = 2 E(m) / ((A - B)
    sqrt(A + B)), m = 2 B / (A + B) (Gradshteyn & Ryzhik 2.571), E the complete elliptic
    integral of the second kind.
    """
    mu1, mu2 = np.broadcast_arrays(np.asarray(mu1, float), np.asarray(mu2, float))
    if g == 0.0:
        return np.ones(mu1.shape)
    s = np.sqrt(np.clip((1.0 - mu1**2) * (1.0 - mu2**2), 0.0, None))
    a = 1.0 + g * g - 2.0 * g * mu1 * mu2
    b = 2.0 * g * s
    if g < 0:  # B < 0: phi -> phi + pi turns it into |B|
        b = -b
    m = np.where(a + b > 0, 2.0 * b / (a + b), 0.0)
    integral = 2.0 * ellipe(m) / ((a - b) * np.sqrt(a + b))  # int_0^pi
    return (1.0 - g * g) * integral / math.pi


def hg_azimuth_average_legendre(g: float, mu1, mu2, lmax: int | None = None):
    """The same from the Legendre series p0 = sum (2l + 1) g^l P_l(mu1) P_l(mu2) (for the
    oracle's own tests)."""
    mu1, mu2 = np.broadcast_arrays(np.asarray(mu1, float), np.asarray(mu2, float))
    if lmax is None:
        lmax = 10 if g == 0 else int(math.ceil(math.log(1e-17) / math.log(abs(g)))) + 10
    p_prev1, p_prev2 = np.ones_like(mu1), np.ones_like(mu2)
    p_cur1, p_cur2 = mu1.copy(), mu2.copy()
    total = p_prev1 * p_prev2 + 3.0 * g * p_cur1 * p_cur2
    for el in range(1, lmax):
        p_next1 = ((2 * el + 1) * mu1 * p_cur1 - el * p_prev1) / (el + 1)
        p_next2 = ((2 * el + 1) * mu2 * p_cur2 - el * p_prev2) / (el + 1)
        total = total + (2 * el + 3) * g ** (el + 1) * p_next1 * p_next2
        p_prev1, p_cur1, p_prev2, p_cur2 = p_cur1, p_next1, p_cur2, p_next2
    return total


@dataclass(frozen=True)
class Slab:
    """A homogeneous slab: optical depth, albedo, HG g; ``n`` Gauss nodes per hemisphere;
    ``extra``: output directions (polar cosines in (0, 1]) of weight zero."""

    tau: float
    albedo: float
    g: float
    n: int = 48
    extra: tuple = (1.0,)

    @cached_property
    def nodes(self):
        x, w = roots_legendre(self.n)
        mu = np.concatenate([0.5 * (x + 1.0), np.asarray(self.extra, float)])
        wt = np.concatenate([0.5 * w, np.zeros(len(self.extra))])
        return mu, wt

    def _generator(self):
        """alpha, beta of d I+/dtau = -alpha I+ + beta I- (tau downwards; I- upwards: the
        same with the roles swapped), on the nodes."""
        mu, w = self.nodes
        p_same = hg_azimuth_average(self.g, mu[:, None], mu[None, :])
        p_opp = hg_azimuth_average(self.g, mu[:, None], -mu[None, :])
        # the quadrature's sum of p0 over all directions is off 1 by 1e-6 for a peaked phase
        # function (g 0.9), which a conservative slab turns into an energy error; the forward
        # (diagonal) element takes up the difference, which keeps p0 symmetric and makes every
        # weighted node scatter exactly its energy (Wiscombe 1976). Output nodes (weight 0)
        # keep the exact p0.
        sel = w > 0
        short = 1.0 - 0.5 * ((p_same + p_opp) * w[None, :]).sum(axis=1)
        p_same = p_same.copy()
        idx = np.flatnonzero(sel)
        p_same[idx, idx] += 2.0 * short[idx] / w[idx]
        m_inv = 1.0 / mu[:, None]
        alpha = m_inv * (np.eye(mu.size) - 0.5 * self.albedo * p_same * w[None, :])
        beta = m_inv * (0.5 * self.albedo * p_opp * w[None, :])
        return alpha, beta

    @cached_property
    def operators(self):
        """(R, T): reflection and total (direct + diffuse) transmission operators."""
        if self.tau == 0.0:
            k = self.nodes[0].size
            return np.zeros((k, k)), np.eye(k)
        mu = self.nodes[0]
        # the thin layer: delta / mu_min <= 1/8 keeps its matrix exponential well conditioned
        doublings = max(0, int(math.ceil(math.log2(self.tau * 8.0 / mu.min()))))
        delta = self.tau / 2.0**doublings
        alpha, beta = self._generator()
        k = mu.size
        # [I+(t), I-(t)]' = K [I+, I-]: exact transfer over delta for the discrete ordinates
        phi = expm(np.block([[-alpha, beta], [-beta, alpha]]) * delta)
        p11, p12, p21, p22 = phi[:k, :k], phi[:k, k:], phi[k:, :k], phi[k:, k:]
        # no light enters from below: I-(delta) = 0 = p21 I+(0) + p22 I-(0)
        r = -solve(p22, p21)
        t = p11 + p12 @ r
        eye = np.eye(k)
        for _ in range(doublings):
            gain = solve(eye - r @ r, np.hstack([t, r @ t]))
            r, t = r + t @ gain[:, k:], t @ gain[:, :k]
        return r, t

    def diffuse_transmission(self):
        """T minus the direct beam e^-tau/mu on the diagonal."""
        mu = self.nodes[0]
        return self.operators[1] - np.diag(np.exp(-self.tau / mu))

    def hemispheric(self):
        """(R, T, A) per incident node for a collimated beam: reflected, transmitted (direct
        included) and absorbed fractions of the incident power (weighted nodes only)."""
        mu, w = self.nodes
        r, t = self.operators
        sel = w > 0
        flux_in = mu * w
        refl = (flux_in @ r)[sel] / flux_in[sel]
        trans = (flux_in @ t)[sel] / flux_in[sel]
        return refl, trans, 1.0 - refl - trans


@dataclass(frozen=True)
class PointSourceSlab:
    """An isotropic point source of luminosity 1 just above an infinite slab, integrated over
    the slab's area (the light a distant observer sees in total).

    ``transmitted(mu)`` and ``reflected(mu)``: scattered power per steradian leaving through
    the bottom / top face in the direction of polar cosine mu (an output node of the slab);
    ``absorbed``: the fraction of the luminosity the slab absorbs (half the light goes up and
    never meets it).
    """

    slab: Slab

    def _out(self, op, mu_out: float) -> float:
        mu, w = self.slab.nodes
        i = int(np.argmin(np.abs(mu - mu_out) + (w > 0)))  # an output node of weight zero
        if abs(mu[i] - mu_out) > 1e-12:
            raise ValueError(f"mu = {mu_out} is not an output node of the slab ({self.slab.extra})")
        sel = w > 0
        # I_in(mu0) = 1 / (4 pi A mu0); out: A mu I_out(mu)
        return float(mu[i] * np.sum(op[i, sel] / mu[sel]) / (4.0 * math.pi))

    def transmitted(self, mu_out: float = 1.0) -> float:
        return self._out(self.slab.diffuse_transmission(), mu_out)

    def reflected(self, mu_out: float = 1.0) -> float:
        return self._out(self.slab.operators[0], mu_out)

    @property
    def absorbed(self) -> float:
        mu, w = self.slab.nodes
        return float(0.5 * np.sum(w[w > 0] * self.slab.hemispheric()[2]))


def decay_rate(albedo: float, g: float, n: int = 64) -> float:
    """The slowest decay rate k of the homogeneous discrete-ordinates solutions, I ~ e^-k tau
    (the diffusion eigenvalue of the transport equation): thick slabs transmit ~ e^-k tau."""
    x, w = roots_legendre(2 * n)
    mu = x
    p = hg_azimuth_average(g, mu[:, None], mu[None, :])
    # -k mu phi = -phi + (a / 2) P W phi  ->  (1 - (a / 2) P W) phi = k M phi
    a_mat = np.eye(mu.size) - 0.5 * albedo * p * w[None, :]
    ev = np.linalg.eigvals(np.linalg.solve(np.diag(mu), a_mat))
    ev = ev.real[np.abs(ev.imag) < 1e-9]
    return float(np.min(ev[ev > 1e-12]))
