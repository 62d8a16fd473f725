/*
 * sampling.cl -- the header's random-number and direction samplers exposed as kernels, so that
 * tests check the very code the transport kernel runs (Philox bits against numpy, HG moments).
 */
#include "nebula_common.h"
#include "polarization.cl"

/* out[4 i .. 4 i + 3] = Philox4x64-10(counter = (c0 + i, c1, c2, c3), key = (k0, k1)) */
NRT_KERNEL void philox_blocks(NRT_GLOBAL nrt_u64 *out, nrt_u64 k0, nrt_u64 k1, nrt_u64 c0,
                              nrt_u64 c1, nrt_u64 c2, nrt_u64 c3, nrt_u64 n)
{
    nrt_u64 i = NRT_GLOBAL_ID();
    if (i >= n)
        return;
    nrt_u64x4 c;
    c.v[0] = c0 + i;
    c.v[1] = c1;
    c.v[2] = c2;
    c.v[3] = c3;
    nrt_u64x4 r = nrt_philox4x64_10(c, k0, k1);
    for (int w = 0; w < 4; ++w)
        out[4 * i + w] = r.v[w];
}

/* The first m 32-bit words of the per-photon stream (seed, band, photon): out[m i + w]. */
NRT_KERNEL void photon_stream_u32(NRT_GLOBAL nrt_u32 *out, nrt_u64 seed, nrt_u64 band,
                                  nrt_u64 photon0, int m, nrt_u64 n)
{
    nrt_u64 i = NRT_GLOBAL_ID();
    if (i >= n)
        return;
    nrt_rng r;
    nrt_rng_init(&r, seed, band, photon0 + i);
    for (int w = 0; w < m; ++w)
        out[(nrt_u64)m * i + w] = nrt_rng_u32(&r);
}

/*
 * Henyey-Greenstein scattering as the transport kernel does it: a random old direction, a new
 * one from nrt_sample_hg + nrt_rotate; out[i] = dot(new, old) measured from the vectors (so a
 * sign or frame error in the rotation shows), norm[i] = |new|.
 */
NRT_KERNEL void hg_cosines(NRT_GLOBAL float *out, NRT_GLOBAL float *norm, float g, nrt_u64 seed,
                           nrt_u64 n)
{
    nrt_u64 i = NRT_GLOBAL_ID();
    if (i >= n)
        return;
    nrt_rng r;
    nrt_rng_init(&r, seed, 0, i);
    float d[3];
    nrt_sample_isotropic(&r, d);
    float old[3] = {d[0], d[1], d[2]};
    float mu, st;
    nrt_sample_hg(g, nrt_rng_uniform(&r), &mu, &st);
    nrt_rotate(d, mu, st, 2.0f * NRT_PI_F * nrt_rng_uniform(&r));
    out[i] = d[0] * old[0] + d[1] * old[1] + d[2] * old[2];
    norm[i] = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
}

/* nrt_sample_hg at given xi (tests the extremes xi = 0 and 1 directly). */
NRT_KERNEL void hg_at(NRT_GLOBAL float *mu, NRT_GLOBAL float *sin_theta,
                      const NRT_GLOBAL float *xi, float g, nrt_u64 n)
{
    nrt_u64 i = NRT_GLOBAL_ID();
    if (i >= n)
        return;
    float m, s;
    nrt_sample_hg(g, xi[i], &m, &s);
    mu[i] = m;
    sin_theta[i] = s;
}

/* nrt_tau_of_xi (the free-path optical depth) at given xi (tests xi = 0 and the largest xi). */
NRT_KERNEL void sample_tau_at(NRT_GLOBAL float *tau, const NRT_GLOBAL float *xi, nrt_u64 n)
{
    nrt_u64 i = NRT_GLOBAL_ID();
    if (i >= n)
        return;
    tau[i] = nrt_tau_of_xi(xi[i]);
}

/* nrt_mueller of kind `kind` at given mu: out[4 i .. 4 i + 3] = S11, S12 / S11, S33 / S11,
   S34 / S11 (pol: the band's parameters, kernels/polarization.cl). */
NRT_KERNEL void mueller_at(NRT_GLOBAL float *out, const NRT_GLOBAL float *mu, const NRT_GLOBAL float *pol,
                           int kind, float g, nrt_u64 n)
{
    nrt_u64 i = NRT_GLOBAL_ID();
    if (i >= n)
        return;
    float m[4];
    nrt_mueller(kind, g, pol, mu[i], m);
    for (int k = 0; k < 4; ++k)
        out[4 * i + k] = m[k];
}

/* nrt_mie_mu of the Mie table at pol + pol[0] (pol[1] angles) at given xi. */
NRT_KERNEL void mie_mu_at(NRT_GLOBAL float *mu, const NRT_GLOBAL float *xi, const NRT_GLOBAL float *pol, nrt_u64 n)
{
    nrt_u64 i = NRT_GLOBAL_ID();
    if (i >= n)
        return;
    mu[i] = nrt_mie_mu(pol + (int)pol[0], (int)pol[1], xi[i]);
}

/* nrt_rayleigh_mu at given xi. */
NRT_KERNEL void rayleigh_mu_at(NRT_GLOBAL float *mu, const NRT_GLOBAL float *xi, nrt_u64 n)
{
    nrt_u64 i = NRT_GLOBAL_ID();
    if (i >= n)
        return;
    mu[i] = nrt_rayleigh_mu(xi[i]);
}

/*
 * One polarized scattering as the transport does it (nrt_scatter_polarized), of light along
 * +z with the Stokes state (q, u, v) referred to e = +x: out[9 i ..] = the new direction (3),
 * the new reference e' (3) and the new q, u, v, each from photon i's own stream.
 */
NRT_KERNEL void scatter_polarized_from(NRT_GLOBAL float *out, int kind, float g, const NRT_GLOBAL float *pol,
                                       float q, float u, float v, nrt_u64 seed, nrt_u64 n)
{
    nrt_u64 i = NRT_GLOBAL_ID();
    if (i >= n)
        return;
    nrt_rng r;
    nrt_rng_init(&r, seed, 0, i);
    float d[3] = {0.0f, 0.0f, 1.0f};
    nrt_stokes s;
    s.e[0] = 1.0f, s.e[1] = 0.0f, s.e[2] = 0.0f;
    s.q = q, s.u = u, s.v = v;
    nrt_scatter_polarized(&r, kind, g, pol, d, &s);
    for (int k = 0; k < 3; ++k) {
        out[9 * i + k] = d[k];
        out[9 * i + 3 + k] = s.e[k];
    }
    out[9 * i + 6] = s.q;
    out[9 * i + 7] = s.u;
    out[9 * i + 8] = s.v;
}

/* nrt_peel_stokes towards o of light along d with the state (q, u, v) (quv[3 i ..]) referred to e:
   out[4 i ..] = I, Q, U, V per sr in the frame whose reference is `north` (all float3 as 3
   floats per item: d, e, o, north at 12 i ..). */
NRT_KERNEL void peel_stokes_at(NRT_GLOBAL float *out, const NRT_GLOBAL float *vec, const NRT_GLOBAL float *quv,
                               int kind, float g, const NRT_GLOBAL float *pol, nrt_u64 n)
{
    nrt_u64 i = NRT_GLOBAL_ID();
    if (i >= n)
        return;
    float d[3], o[3], north[3], iquv[4];
    nrt_stokes s;
    for (int k = 0; k < 3; ++k) {
        d[k] = vec[12 * i + k];
        s.e[k] = vec[12 * i + 3 + k];
        o[k] = vec[12 * i + 6 + k];
        north[k] = vec[12 * i + 9 + k];
    }
    s.q = quv[3 * i], s.u = quv[3 * i + 1], s.v = quv[3 * i + 2];
    nrt_peel_stokes(kind, g, pol, o, north, d, &s, iquv);
    for (int k = 0; k < 4; ++k)
        out[4 * i + k] = iquv[k];
}

/* How the device lays out the parameter structs (offsets and sizes; tests compare them with
   the host's dtype). */
/* NRT_PARAM_LAYOUT_KERNELS */
