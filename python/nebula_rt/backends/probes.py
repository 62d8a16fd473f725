"""Kernels exposed for tests and diagnostics.

These run single pieces of the device code -- the simplex noise and turbulence of the density
kernel (``kernels/density.cl``), and the Philox generator, the per-photon random streams, the
Henyey-Greenstein sampler and the free-path sampler of the transport kernel
(``kernels/sampling.cl``) -- so that tests check the very code the production kernels run.
They are not part of the :class:`~nebula_rt.backends.base.Backend` interface: each function is
written once over the backend's device primitives (``to_device``, ``device_zeros``,
``launch``, ``to_host``) and works on every backend.

All functions take host (NumPy) arrays and return new host arrays.
"""

from __future__ import annotations

import numpy as np

from .base import Backend


def sample_noise(backend: Backend, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Simplex noise and turbulence of the density kernel at given points.

    Parameters
    ----------
    backend : Backend
        The device to run on.
    points : array_like, shape (n, 3) (or anything with 3 n elements)
        Points in noise coordinates (dimensionless: the density kernel evaluates the noise at
        box coordinates times ``scale`` plus ``offset``); converted to float32.

    Returns
    -------
    noise, turbulence : ndarray, float32, shape (n,)
        ``nrt_simplex3`` and ``nrt_turbulence`` at each point (dimensionless).
    """
    pts = np.ascontiguousarray(points, np.float32).reshape(-1, 3)
    n = pts.shape[0]
    d_pts = backend.to_device(pts)
    d_noise, d_turb = backend.device_zeros(n, np.float32), backend.device_zeros(n, np.float32)
    backend.launch("density.cl", "sample_noise", n, d_pts, d_noise, d_turb, np.int32(n))
    return backend.to_host(d_noise), backend.to_host(d_turb)


def philox_blocks(backend: Backend, key: tuple[int, int], counter: tuple[int, int, int, int],
                  n: int) -> np.ndarray:
    """Blocks of the Philox4x64-10 generator of the kernel header.

    Parameters
    ----------
    backend : Backend
        The device to run on.
    key : (int, int)
        The two 64-bit key words.
    counter : (int, int, int, int)
        The four 64-bit counter words (c0, c1, c2, c3) of the first block.
    n : int
        Number of blocks.

    Returns
    -------
    ndarray, uint64, shape (n, 4)
        Row ``i`` is Philox4x64-10 of the counter (c0 + i, c1, c2, c3) under ``key``; word 0
        of the counter wraps modulo 2^64 without a carry into word 1.
    """
    n = int(n)
    d_out = backend.device_zeros(4 * n, np.uint64)
    backend.launch("sampling.cl", "philox_blocks", n, d_out, np.uint64(key[0]), np.uint64(key[1]),
                   *(np.uint64(c) for c in counter), np.uint64(n))
    return backend.to_host(d_out).reshape(n, 4)


def photon_stream_u32(backend: Backend, seed: int, band: int, photon0: int, m: int, n: int) -> np.ndarray:
    """The first 32-bit words of the per-photon random streams of the transport kernel.

    Parameters
    ----------
    backend : Backend
        The device to run on.
    seed : int
        Philox key word 0 (the run's seed).
    band : int
        Philox key word 1 (the band index).
    photon0 : int
        Index of the first photon (packet).
    m : int
        Words per photon.
    n : int
        Number of photons: ``photon0 .. photon0 + n - 1``.

    Returns
    -------
    ndarray, uint32, shape (n, m)
        Row ``i`` holds the first ``m`` words of the stream of photon ``photon0 + i``.
    """
    n, m = int(n), int(m)
    d_out = backend.device_zeros(m * n, np.uint32)
    backend.launch("sampling.cl", "photon_stream_u32", n, d_out, np.uint64(seed), np.uint64(band),
                   np.uint64(photon0), np.int32(m), np.uint64(n))
    return backend.to_host(d_out).reshape(n, m)


def hg_cosines(backend: Backend, g: float, seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Henyey-Greenstein scatterings as the transport kernel does them.

    Each of the ``n`` work items draws an isotropic old direction, samples (mu, sin theta)
    with ``nrt_sample_hg`` and rotates the direction with ``nrt_rotate`` (random stream
    ``(seed, band 0, photon i)``).

    Parameters
    ----------
    backend : Backend
        The device to run on.
    g : float
        HG asymmetry parameter (mean scattering cosine, dimensionless, in (-1, 1); the kernel
        clamps it to its ``NRT_G_LIMIT``).
    seed : int
        Philox key word 0.
    n : int
        Number of scatterings.

    Returns
    -------
    mu : ndarray, float32, shape (n,)
        Cosine of the scattering angle, dot(new, old), measured from the two unit vectors.
    norm : ndarray, float32, shape (n,)
        Length |new| of the new direction vector (1 up to float32 rounding).
    """
    n = int(n)
    d_mu, d_norm = backend.device_zeros(n, np.float32), backend.device_zeros(n, np.float32)
    backend.launch("sampling.cl", "hg_cosines", n, d_mu, d_norm, np.float32(g), np.uint64(seed), np.uint64(n))
    return backend.to_host(d_mu), backend.to_host(d_norm)


def hg_at(backend: Backend, g: float, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Henyey-Greenstein sampler ``nrt_sample_hg`` at given uniform variates.

    Parameters
    ----------
    backend : Backend
        The device to run on.
    g : float
        HG asymmetry parameter (dimensionless, in (-1, 1); clamped to ``NRT_G_LIMIT``).
    xi : array_like
        Uniform variates in [0, 1] (any shape, flattened; converted to float32).

    Returns
    -------
    mu, sin_theta : ndarray, float32, shape (xi.size,)
        Cosine and sine of the sampled scattering angle at each xi.
    """
    xi = np.ascontiguousarray(xi, np.float32).reshape(-1)
    n = xi.size
    d_xi = backend.to_device(xi)
    d_mu, d_st = backend.device_zeros(n, np.float32), backend.device_zeros(n, np.float32)
    backend.launch("sampling.cl", "hg_at", n, d_mu, d_st, d_xi, np.float32(g), np.uint64(n))
    return backend.to_host(d_mu), backend.to_host(d_st)


def sample_tau_at(backend: Backend, xi: np.ndarray) -> np.ndarray:
    """The free-path sampler ``nrt_tau_of_xi`` at given uniform variates.

    Parameters
    ----------
    backend : Backend
        The device to run on.
    xi : array_like
        Uniform variates in [0, 1) (any shape, flattened; converted to float32).

    Returns
    -------
    ndarray, float32, shape (xi.size,)
        Optical depth to the next interaction, -ln(1 - xi) in float32 as the transport kernel
        computes it (dimensionless).
    """
    xi = np.ascontiguousarray(xi, np.float32).reshape(-1)
    n = xi.size
    d_xi = backend.to_device(xi)
    d_tau = backend.device_zeros(n, np.float32)
    backend.launch("sampling.cl", "sample_tau_at", n, d_tau, d_xi, np.uint64(n))
    return backend.to_host(d_tau)


def _polar_params(pol, wavelength: float = 550.0) -> np.ndarray:
    """One band's parameters (and Mie table) at ``wavelength`` (nm)."""
    return np.zeros(4, np.float32) if pol is None else np.asarray(pol.kernel_params(1, [wavelength]), np.float32)


def mueller_at(backend: Backend, pol, mu: np.ndarray, g: float = 0.0, wavelength: float = 550.0) -> np.ndarray:
    """The Mueller matrix ``nrt_mueller`` (kernels/polarization.cl) at given scattering cosines.

    Parameters
    ----------
    backend : Backend
    pol : nebula_rt.optics.polarization.Polarization
        The kind and (one band's) parameters.
    mu : array_like
        Cosines of the scattering angle (flattened; float32).
    g : float
        The band's HG asymmetry parameter (kind "white").
    wavelength : float
        The band's wavelength, nm (kind "mie").

    Returns
    -------
    ndarray, float32, shape (mu.size, 4)
        S11 (per sr), S12 / S11, S33 / S11, S34 / S11.
    """
    mu = np.ascontiguousarray(mu, np.float32).reshape(-1)
    n = mu.size
    d_out = backend.device_zeros(4 * n, np.float32)
    backend.launch("sampling.cl", "mueller_at", n, d_out, backend.to_device(mu),
                   backend.to_device(_polar_params(pol, wavelength)),
                   np.int32(pol.kernel_kind), np.float32(g), np.uint64(n))
    return backend.to_host(d_out).reshape(n, 4)


def mie_mu_at(backend: Backend, pol, xi: np.ndarray, wavelength: float = 550.0) -> np.ndarray:
    """Scattering cosines ``nrt_mie_mu`` of a Mie kind's table (one band at ``wavelength``, nm)
    at given uniform variates (float32)."""
    xi = np.ascontiguousarray(xi, np.float32).reshape(-1)
    d_mu = backend.device_zeros(xi.size, np.float32)
    backend.launch("sampling.cl", "mie_mu_at", xi.size, d_mu, backend.to_device(xi),
                   backend.to_device(_polar_params(pol, wavelength)), np.uint64(xi.size))
    return backend.to_host(d_mu)


def rayleigh_mu_at(backend: Backend, xi: np.ndarray) -> np.ndarray:
    """Rayleigh scattering cosines ``nrt_rayleigh_mu`` at given uniform variates (float32)."""
    xi = np.ascontiguousarray(xi, np.float32).reshape(-1)
    d_mu = backend.device_zeros(xi.size, np.float32)
    backend.launch("sampling.cl", "rayleigh_mu_at", xi.size, d_mu, backend.to_device(xi), np.uint64(xi.size))
    return backend.to_host(d_mu)


def scatter_polarized_from(backend: Backend, pol, q: float, u: float, seed: int, n: int,
                           g: float = 0.0, v: float = 0.0, wavelength: float = 550.0) -> np.ndarray:
    """``n`` polarized scatterings (``nrt_scatter_polarized``) of light along +z whose Stokes
    state (q, u, v) refers to +x, each from its own random stream (seed, band 0, photon i).

    Returns
    -------
    ndarray, float32, shape (n, 9)
        The new direction (3), the new reference direction (3), the new q, u and v.
    """
    n = int(n)
    d_out = backend.device_zeros(9 * n, np.float32)
    backend.launch("sampling.cl", "scatter_polarized_from", n, d_out, np.int32(pol.kernel_kind), np.float32(g),
                   backend.to_device(_polar_params(pol, wavelength)), np.float32(q), np.float32(u), np.float32(v),
                   np.uint64(seed), np.uint64(n))
    return backend.to_host(d_out).reshape(n, 9)


def peel_stokes_at(backend: Backend, pol, d, e, o, north, qu, g: float = 0.0, wavelength: float = 550.0) -> np.ndarray:
    """``nrt_peel_stokes``: the light that packets along ``d`` (n, 3) with Stokes states ``qu``
    ((n, 2): q, u; or (n, 3): q, u, v) referred to ``e`` (n, 3) scatter towards ``o`` (n, 3), per
    sr, as (I, Q, U, V) in the frame whose reference is ``north`` (n, 3); float32, shape (n, 4)."""
    qu = np.asarray(qu, np.float32)
    qu = qu.reshape(-1, qu.shape[-1]) if qu.ndim > 1 else qu.reshape(-1, 2)
    if qu.shape[1] == 2:
        qu = np.concatenate([qu, np.zeros((qu.shape[0], 1), np.float32)], axis=1)
    vec = np.ascontiguousarray(np.concatenate([np.asarray(a, np.float32).reshape(-1, 3) for a in (d, e, o, north)],
                                              axis=1), np.float32)
    n = vec.shape[0]
    d_out = backend.device_zeros(4 * n, np.float32)
    backend.launch("sampling.cl", "peel_stokes_at", n, d_out, backend.to_device(vec),
                   backend.to_device(np.ascontiguousarray(qu, np.float32).reshape(-1)), np.int32(pol.kernel_kind),
                   np.float32(g), backend.to_device(_polar_params(pol, wavelength)), np.uint64(n))
    return backend.to_host(d_out).reshape(n, 4)
