/*
 * nebula_common.h -- the one portable header shared by NebulaRT's OpenCL C and CUDA C kernels.
 *
 * Contents
 *   - portability macros (address spaces, 64-bit types, atomics, math) for OpenCL C 1.2+ and CUDA
 *   - Philox4x64-10 counter-based random numbers (Salmon et al. 2011, "Parallel random numbers:
 *     as easy as 1, 2, 3"); bit-identical to numpy.random.Philox for the same key and counter
 *   - Henyey-Greenstein sampling in a branch-free form that holds for |g| -> 0 and |g| -> 1
 *   - an orthonormal basis without singularities (Duff et al. 2017)
 *   - 3D simplex noise (Gustavson 2005), the thesis's smooth turbulence sum and cubic bump
 *
 * Units: positions in box units (the domain is [0,1]^3), extinction per box unit.
 */
#ifndef NEBULA_COMMON_H
#define NEBULA_COMMON_H

/* ------------------------------------------------------------------------------------------ */
/* Portability                                                                                 */
/* ------------------------------------------------------------------------------------------ */
#if defined(__OPENCL_VERSION__)
/* no contraction of a * b + c into one rounding (CUDA: --fmad=false): the float arithmetic is
   then fixed by the source, not by what the compiler makes of the code around it */
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define NRT_KERNEL __kernel
#define NRT_GLOBAL __global
#define NRT_CONSTANT __constant
#define NRT_DEVICE static inline
typedef ulong nrt_u64;
typedef uint nrt_u32;
typedef long nrt_i64;
#define NRT_GLOBAL_ID() ((nrt_u64)get_global_id(0))
#define NRT_GLOBAL_SIZE() ((nrt_u64)get_global_size(0))
#define NRT_MULHI64(a, b) mul_hi((ulong)(a), (ulong)(b))
/* atom_add on 64-bit integers (cl_khr_int64_base_atomics); returns the old value */
#define NRT_ATOMIC_ADD_U64(p, v) atom_add((volatile __global ulong *)(p), (ulong)(v))
#define NRT_ATOMIC_OR_U32(p, v) atomic_or((volatile __global uint *)(p), (uint)(v))
#define NRT_ATOMIC_ADD_U32(p, v) atomic_add((volatile __global uint *)(p), (uint)(v))
/* work-group (CUDA: block) shared memory, its 64-bit atomics and the group barrier */
#define NRT_FMAF(a, b, c) fma((float)(a), (float)(b), (float)(c))
#define NRT_LOCAL __local
#define NRT_LOCAL_MEM __local
#define NRT_ATOMIC_ADD_U64_LOCAL(p, v) atom_add((volatile __local ulong *)(p), (ulong)(v))
#define NRT_ATOMIC_ADD_U32_LOCAL(p, v) atomic_add((volatile __local uint *)(p), (uint)(v))
#define NRT_BARRIER() barrier(CLK_LOCAL_MEM_FENCE)
#define NRT_LOCAL_ID() ((nrt_u64)get_local_id(0))
#define NRT_LOCAL_SIZE() ((nrt_u64)get_local_size(0))
#define NRT_GROUP_FIRST_ID() ((nrt_u64)get_group_id(0) * (nrt_u64)get_local_size(0))
typedef uchar nrt_u8;
#define NRT_FLOAT_AS_UINT(x) as_uint(x)
#define NRT_UINT_AS_FLOAT(x) as_float(x)
#define NRT_FREXPF(x, e) frexp((float)(x), (e))
/* leading zero bits of a nonzero 64-bit integer */
#define NRT_CLZ64(x) ((int)clz((ulong)(x)))
/* double-precision sqrt, correctly rounded in both languages */
#define NRT_DSQRT(x) sqrt((double)(x))
#elif defined(__CUDACC__) || defined(__CUDACC_RTC__)
#define NRT_KERNEL extern "C" __global__
#define NRT_GLOBAL
#define NRT_CONSTANT __constant__
#define NRT_DEVICE static __device__ __forceinline__
typedef unsigned long long nrt_u64;
typedef unsigned int nrt_u32;
typedef long long nrt_i64;
#define NRT_GLOBAL_ID() ((nrt_u64)blockIdx.x * (nrt_u64)blockDim.x + (nrt_u64)threadIdx.x)
#define NRT_GLOBAL_SIZE() ((nrt_u64)gridDim.x * (nrt_u64)blockDim.x)
#define NRT_MULHI64(a, b) __umul64hi((a), (b))
#define NRT_ATOMIC_ADD_U64(p, v) atomicAdd((unsigned long long *)(p), (unsigned long long)(v))
#define NRT_ATOMIC_OR_U32(p, v) atomicOr((unsigned int *)(p), (unsigned int)(v))
#define NRT_ATOMIC_ADD_U32(p, v) atomicAdd((unsigned int *)(p), (unsigned int)(v))
#define NRT_FMAF(a, b, c) fmaf((a), (b), (c))
#define NRT_LOCAL
#define NRT_LOCAL_MEM __shared__
#define NRT_ATOMIC_ADD_U64_LOCAL(p, v) atomicAdd((unsigned long long *)(p), (unsigned long long)(v))
#define NRT_ATOMIC_ADD_U32_LOCAL(p, v) atomicAdd((unsigned int *)(p), (unsigned int)(v))
#define NRT_BARRIER() __syncthreads()
#define NRT_LOCAL_ID() ((nrt_u64)threadIdx.x)
#define NRT_LOCAL_SIZE() ((nrt_u64)blockDim.x)
#define NRT_GROUP_FIRST_ID() ((nrt_u64)blockIdx.x * (nrt_u64)blockDim.x)
typedef unsigned char nrt_u8;
#define NRT_FLOAT_AS_UINT(x) __float_as_uint(x)
#define NRT_UINT_AS_FLOAT(x) __uint_as_float(x)
#define NRT_FREXPF(x, e) frexpf((x), (e))
#define NRT_CLZ64(x) __clzll((long long)(x))
/* (sqrt is mapped to sqrtf below, for the float code) */
#define NRT_DSQRT(x) __dsqrt_rn((double)(x))
/* single-precision functions under the OpenCL names, for the float code; double-precision
   code (postprocess.cl) uses NRT_DSQRT, exp, pow and rint, which are not remapped */
#define fmin fminf
#define fmax fmaxf
#define floor floorf
#define sqrt sqrtf
#define log logf
#define cos cosf
#define sin sinf
#define copysign copysignf
#define fabs fabsf
#define exp2 exp2f
#define expm1 expm1f
#define log1p log1pf
#else
#error "nebula_common.h needs OpenCL C or CUDA C"
#endif

#define NRT_PI_F 3.14159265358979323846f

/* ------------------------------------------------------------------------------------------ */
/* Shared constants and parameter structs (declared once, in nebula_rt/backends/kernel_params.py;      */
/* pasted in here)                                                                             */
/* ------------------------------------------------------------------------------------------ */
/* NRT_PARAM_STRUCTS */

/* ------------------------------------------------------------------------------------------ */
/* Philox4x64-10                                                                               */
/* ------------------------------------------------------------------------------------------ */
/* Constants of Random123 (and numpy's philox.h). */
#define NRT_PHILOX_M0 0xD2E7470EE14C6C93UL
#define NRT_PHILOX_M1 0xCA5A826395121157UL
#define NRT_PHILOX_W0 0x9E3779B97F4A7C15UL
#define NRT_PHILOX_W1 0xBB67AE8584CAA73BUL

typedef struct {
    nrt_u64 v[4];
} nrt_u64x4;

NRT_DEVICE nrt_u64x4 nrt_philox4x64_10(nrt_u64x4 ctr, nrt_u64 k0, nrt_u64 k1)
{
    for (int round = 0; round < 10; ++round) {
        if (round > 0) {
            k0 += NRT_PHILOX_W0;
            k1 += NRT_PHILOX_W1;
        }
        nrt_u64 hi0 = NRT_MULHI64(NRT_PHILOX_M0, ctr.v[0]);
        nrt_u64 lo0 = NRT_PHILOX_M0 * ctr.v[0];
        nrt_u64 hi1 = NRT_MULHI64(NRT_PHILOX_M1, ctr.v[2]);
        nrt_u64 lo1 = NRT_PHILOX_M1 * ctr.v[2];
        nrt_u64x4 out;
        out.v[0] = hi1 ^ ctr.v[1] ^ k0;
        out.v[1] = lo1;
        out.v[2] = hi0 ^ ctr.v[3] ^ k1;
        out.v[3] = lo0;
        ctr = out;
    }
    return ctr;
}

/*
 * One random stream per photon packet: key = (seed, band), counter = (photon, block, 0, stream).
 * stream is 0 for every packet; the weighted packets' split copies take streams 1, 2, ... of
 * their packet (kernels/transport.cl), so each copy has random numbers of its own.
 * Each Philox call yields 4 x 64 bits, used as 8 x 32 bits (low word first, as numpy's
 * next_uint32 does). Nothing depends on which thread traces the packet, so results are
 * independent of scheduling.
 */
typedef struct {
    nrt_u64 key0, key1;
    nrt_u64 photon;
    nrt_u64 block;
    nrt_u64 stream;
    nrt_u64 b0, b1, b2, b3; /* the current block's 4 outputs, kept as scalars so that the
                               state stays in registers (an indexed array goes to local memory) */
    int pos;                 /* next 32-bit word, 0..8 */
} nrt_rng;

NRT_DEVICE void nrt_rng_init(nrt_rng *r, nrt_u64 seed, nrt_u64 band, nrt_u64 photon)
{
    r->key0 = seed;
    r->key1 = band;
    r->photon = photon;
    r->block = 0;
    r->stream = 0;
    r->b0 = r->b1 = r->b2 = r->b3 = 0;
    r->pos = 8;
}

NRT_DEVICE nrt_u32 nrt_rng_u32(nrt_rng *r)
{
    if (r->pos >= 8) {
        nrt_u64x4 c;
        c.v[0] = r->photon;
        c.v[1] = r->block;
        c.v[2] = 0;
        c.v[3] = r->stream;
        nrt_u64x4 o = nrt_philox4x64_10(c, r->key0, r->key1);
        r->b0 = o.v[0];
        r->b1 = o.v[1];
        r->b2 = o.v[2];
        r->b3 = o.v[3];
        r->block += 1;
        r->pos = 0;
    }
    int q = r->pos >> 1;
    nrt_u64 w = (q == 0) ? r->b0 : (q == 1) ? r->b1 : (q == 2) ? r->b2 : r->b3;
    nrt_u32 out = (r->pos & 1) ? (nrt_u32)(w >> 32) : (nrt_u32)(w & 0xFFFFFFFFUL);
    r->pos += 1;
    return out;
}

/* Uniform float in [0, 1): the top 24 bits, so 1.0f is never returned. */
NRT_DEVICE float nrt_rng_uniform(nrt_rng *r)
{
    return (float)(nrt_rng_u32(r) >> 8) * 5.9604644775390625e-8f; /* 2^-24 */
}

/* Exponential optical depth: -ln(1 - xi) with xi in [0,1), never -ln(xi) (which is inf at 0).
   The formula on its own, so that the test kernel sample_tau_at checks the very code the
   transport runs at xi = 0 (tau = 0) and at the largest xi, 1 - 2^-24 (tau = 24 ln 2). */
NRT_DEVICE float nrt_tau_of_xi(float xi)
{
    return -log(1.0f - xi);
}

NRT_DEVICE float nrt_sample_tau(nrt_rng *r)
{
    return nrt_tau_of_xi(nrt_rng_uniform(r));
}

/* ------------------------------------------------------------------------------------------ */
/* Directions and Henyey-Greenstein                                                            */
/* ------------------------------------------------------------------------------------------ */
/* float32 keeps 1 - |g| resolvable only down to about 1e-4 (REFERENCES.md). */
#define NRT_G_LIMIT (1.0f - 1.0e-4f)

/*
 * Henyey-Greenstein cosine mu and sin(theta) from xi in [0,1], branch-free:
 *   d = 1 - g + 2 g xi
 *   mu = [2 xi (1+g^2)(1-g+g xi) - (1-g)^2] / d^2
 *   sin(theta) = 2 (1-g^2) sqrt(xi (1-xi) (1-g+g xi) (1+g xi)) / d^2
 * The textbook (1 + g^2 - f^2)/(2g) cancels catastrophically for small |g|; this form is exact
 * at g = 0 (mu = 2 xi - 1) and keeps sin(theta) accurate near |mu| = 1. It is evaluated for
 * |g| only, using the symmetry mu(g, xi) = -mu(-g, 1 - xi): for g < 0, d = 1 - g + 2 g xi
 * would cancel as xi -> 1 (d -> 1 + g), while with |g| every term is positive. The reflection
 * is a select, not a divergent branch.
 */
NRT_DEVICE void nrt_sample_hg(float g, float xi, float *mu, float *sin_theta)
{
    g = fmin(fmax(g, -NRT_G_LIMIT), NRT_G_LIMIT);
    float ga = fabs(g);
    float x = (g < 0.0f) ? 1.0f - xi : xi;
    float a = 1.0f - ga + ga * x;
    float b = 1.0f + ga * x;
    float d = a + ga * x;
    float inv_d2 = 1.0f / (d * d);
    float omg = 1.0f - ga;
    float m = (2.0f * x * (1.0f + ga * ga) * a - omg * omg) * inv_d2;
    /* 1 - g^2 as (1 - |g|)(1 + |g|): 1 - |g| is exact, while 1 - g * g cancels (a 3e-4
       relative error in sin(theta) at |g| = 0.9999 unless the compiler happens to fuse it) */
    float s = 2.0f * (omg * (1.0f + ga)) * sqrt(fmax(0.0f, x * (1.0f - x) * a * b)) * inv_d2;
    m = (g < 0.0f) ? -m : m;
    *mu = fmin(fmax(m, -1.0f), 1.0f);
    *sin_theta = fmin(s, 1.0f);
}

/* Orthonormal basis (t1, t2) perpendicular to the unit vector n (Duff et al. 2017, JCGT 6(1)). */
NRT_DEVICE void nrt_onb(float nx, float ny, float nz, float *t1, float *t2)
{
    float sign = copysign(1.0f, nz);
    float a = -1.0f / (sign + nz);
    float b = nx * ny * a;
    t1[0] = 1.0f + sign * nx * nx * a;
    t1[1] = sign * b;
    t1[2] = -sign * nx;
    t2[0] = b;
    t2[1] = sign + ny * ny * a;
    t2[2] = -ny;
}

/* Turn the unit direction d by polar angle (mu, sin_theta) and azimuth phi about itself. */
NRT_DEVICE void nrt_rotate(float *d, float mu, float sin_theta, float phi)
{
    float t1[3], t2[3];
    nrt_onb(d[0], d[1], d[2], t1, t2);
    float c = sin_theta * cos(phi);
    float s = sin_theta * sin(phi);
    float x = c * t1[0] + s * t2[0] + mu * d[0];
    float y = c * t1[1] + s * t2[1] + mu * d[1];
    float z = c * t1[2] + s * t2[2] + mu * d[2];
    /* renormalise so rounding does not accumulate over many scatterings */
    float inv = 1.0f / sqrt(x * x + y * y + z * z);
    d[0] = x * inv;
    d[1] = y * inv;
    d[2] = z * inv;
}

/* Isotropic unit direction. */
NRT_DEVICE void nrt_sample_isotropic(nrt_rng *r, float *d)
{
    float mu = 2.0f * nrt_rng_uniform(r) - 1.0f;
    float phi = 2.0f * NRT_PI_F * nrt_rng_uniform(r);
    float st = sqrt(fmax(0.0f, 1.0f - mu * mu));
    d[0] = st * cos(phi);
    d[1] = st * sin(phi);
    d[2] = mu;
}

/* ------------------------------------------------------------------------------------------ */
/* Peel-off images: the phase function, the pixel, the stochastic rounding of a deposit        */
/* (transport.cl and tree.cl)                                                                   */
/* ------------------------------------------------------------------------------------------ */
NRT_DEVICE float nrt_hg_phase(float g, float mu)
{
    g = fmin(fmax(g, -NRT_G_LIMIT), NRT_G_LIMIT); /* as the sampling clamps it */
    float gg = g * g;
    float den = 1.0f + gg - 2.0f * g * mu;
    /* 1 - g^2 as (1 - |g|)(1 + |g|): no cancellation as |g| -> 1 */
    return ((1.0f - fabs(g)) * (1.0f + fabs(g))) / (4.0f * NRT_PI_F * den * sqrt(den));
}

/* The pixel (p H + q) of a peel-off image that point x projects to; 0 where it falls outside.
   peel[15]: direction to the observer o (3), image axes u and v (3 + 3), centre of pixel
   (0, 0) (3), pixel size, W, H. */
NRT_DEVICE int nrt_peel_pixel(const NRT_GLOBAL float *peel, const float *x, nrt_u64 *pixel)
{
    float rx = x[0] - peel[9], ry = x[1] - peel[10], rz = x[2] - peel[11];
    float a = (rx * peel[3] + ry * peel[4] + rz * peel[5]) / peel[12];
    float b = (rx * peel[6] + ry * peel[7] + rz * peel[8]) / peel[12];
    int pi = (int)floor(a + 0.5f), qi = (int)floor(b + 0.5f);
    int w = (int)peel[13], h = (int)peel[14];
    if (pi < 0 || pi >= w || qi < 0 || qi >= h)
        return 0;
    *pixel = (nrt_u64)pi * (nrt_u64)h + (nrt_u64)qi;
    return 1;
}

/*
 * Fixed-point units of a peel-off weight, rounded stochastically: floor(x) + 1 with
 * probability frac(x), x = wgt * scale, so the expected deposit is x (to 2^-64 units) however
 * faint the weight. Rounding to nearest dropped every weight below half a unit, 2^-25 of the
 * forward phase-function peak (with g 0.9: beyond tau about 8.5 towards the observer); the
 * sums stay exact integers. The uniform comes from a Philox block of its own, counter
 * (photon, event, 1, branch) under the packet's key (seed, band): the packet's streams use
 * counters (photon, block, 0, stream), so its random numbers, and everything else it tallies,
 * are untouched, and the image is the same bits on any device and thread order (branch: the
 * split copy of a weighted packet, 0 for every analog one).
 */
NRT_DEVICE nrt_u64 nrt_round_word(nrt_u64 seed, nrt_u64 band, nrt_u64 photon, nrt_u64 event, nrt_u64 branch)
{
    nrt_u64x4 c;
    c.v[0] = photon;
    c.v[1] = event;
    c.v[2] = 1;
    c.v[3] = branch;
    return nrt_philox4x64_10(c, seed, band).v[0];
}

/* wgt x scale rounded down or up by the random word r: up with probability the fraction.
   Monotone in wgt for a given r, so deposits rounded with one r keep their order (a Stokes
   component |Q| <= I stays at most I's units, kernels/polarization.cl). */
NRT_DEVICE nrt_u64 nrt_fixed_round(float wgt, float scale, nrt_u64 r)
{
    float x = NRT_FMAF(wgt, scale, 0.0f);
    float whole = floor(x);
    float frac = x - whole; /* exact for x >= 0 */
    nrt_u64 n = (nrt_u64)whole;
    /* P(r < T) = T 2^-64 with T = floor(frac 2^64): frac 2^64 < 2^64 is a float whose
       conversion truncates only below 2^24, i.e. loses less than 2^-40 of frac */
    if (frac > 0.0f)
        n += (r < (nrt_u64)(frac * 18446744073709551616.0f)) ? 1UL : 0UL;
    return n;
}

NRT_DEVICE nrt_u64 nrt_fixed_stochastic(float wgt, float scale, nrt_u64 seed, nrt_u64 band,
                                        nrt_u64 photon, nrt_u64 event, nrt_u64 branch)
{
    float x = NRT_FMAF(wgt, scale, 0.0f);
    if (x == floor(x)) /* (no random bits needed: the Philox block only where a fraction is left) */
        return (nrt_u64)x;
    return nrt_fixed_round(wgt, scale, nrt_round_word(seed, band, photon, event, branch));
}

/* ------------------------------------------------------------------------------------------ */
/* Simplex noise (Gustavson 2005, "Simplex noise demystified"), turbulence, cubic bump         */
/* ------------------------------------------------------------------------------------------ */
/* The noise's tables. Constant memory serves one address per warp at a time, and the
   permutation is read at data-dependent places: on an H100 the thesis's density at 128^3 took
   0.80 ms with the tables there and 0.18 ms from global memory, the same bits
   (benchmarks/profile_density.py). So CUDA reads them from global memory through the caches
   (NRT_TABLES_CONSTANT 1 puts them back). OpenCL C 1.2 allows program-scope arrays only in
   __constant: there each work group copies them into its local memory first
   (NRT_NOISE_TABLES, at the top of a kernel, before any item returns) and the noise reads
   them through the pointer NRT_NOISE_ARG passes on (NRT_NOISE_LOCAL 0: from __constant, as
   before). */
#if defined(__OPENCL_VERSION__) || (defined(NRT_TABLES_CONSTANT) && NRT_TABLES_CONSTANT)
#define NRT_TABLE NRT_CONSTANT
#else
#define NRT_TABLE __device__ const
#endif
#if defined(__OPENCL_VERSION__) && !(defined(NRT_NOISE_LOCAL) && !NRT_NOISE_LOCAL)
#define NRT_NOISE_WORDS (512 + 36) /* the permutation, then the 12 gradients' 3 components */
#define NRT_NOISE_PARAM __local const int *noise_tables,
#define NRT_NOISE_ARG noise_tables,
#define NRT_PERM(i) noise_tables[i]
#define NRT_GRAD(g, c) noise_tables[512 + 3 * (g) + (c)]
#define NRT_NOISE_TABLES()                                                                 \
    __local int noise_tables_l[NRT_NOISE_WORDS];                                           \
    for (nrt_u64 t_ = NRT_LOCAL_ID(); t_ < NRT_NOISE_WORDS; t_ += NRT_LOCAL_SIZE())        \
        noise_tables_l[t_] = t_ < 512 ? nrt_perm[t_] : nrt_grad3[(t_ - 512) / 3][(t_ - 512) % 3]; \
    NRT_BARRIER();                                                                         \
    __local const int *noise_tables = noise_tables_l
#else
#define NRT_NOISE_PARAM
#define NRT_NOISE_ARG
#define NRT_PERM(i) nrt_perm[i]
#define NRT_GRAD(g, c) nrt_grad3[g][c]
#define NRT_NOISE_TABLES() ((void)0)
#endif
NRT_TABLE int nrt_grad3[12][3] = {{1, 1, 0}, {-1, 1, 0}, {1, -1, 0}, {-1, -1, 0},
                                     {1, 0, 1}, {-1, 0, 1}, {1, 0, -1}, {-1, 0, -1},
                                     {0, 1, 1}, {0, -1, 1}, {0, 1, -1}, {0, -1, -1}};

/* Ken Perlin's permutation, doubled so that perm[i + perm[j]] never needs a wrap. */
NRT_TABLE int nrt_perm[512] = {
    151, 160, 137, 91,  90,  15,  131, 13,  201, 95,  96,  53,  194, 233, 7,   225, 140, 36,  103,
    30,  69,  142, 8,   99,  37,  240, 21,  10,  23,  190, 6,   148, 247, 120, 234, 75,  0,   26,
    197, 62,  94,  252, 219, 203, 117, 35,  11,  32,  57,  177, 33,  88,  237, 149, 56,  87,  174,
    20,  125, 136, 171, 168, 68,  175, 74,  165, 71,  134, 139, 48,  27,  166, 77,  146, 158, 231,
    83,  111, 229, 122, 60,  211, 133, 230, 220, 105, 92,  41,  55,  46,  245, 40,  244, 102, 143,
    54,  65,  25,  63,  161, 1,   216, 80,  73,  209, 76,  132, 187, 208, 89,  18,  169, 200, 196,
    135, 130, 116, 188, 159, 86,  164, 100, 109, 198, 173, 186, 3,   64,  52,  217, 226, 250, 124,
    123, 5,   202, 38,  147, 118, 126, 255, 82,  85,  212, 207, 206, 59,  227, 47,  16,  58,  17,
    182, 189, 28,  42,  223, 183, 170, 213, 119, 248, 152, 2,   44,  154, 163, 70,  221, 153, 101,
    155, 167, 43,  172, 9,   129, 22,  39,  253, 19,  98,  108, 110, 79,  113, 224, 232, 178, 185,
    112, 104, 218, 246, 97,  228, 251, 34,  242, 193, 238, 210, 144, 12,  191, 179, 162, 241, 81,
    51,  145, 235, 249, 14,  239, 107, 49,  192, 214, 31,  181, 199, 106, 157, 184, 84,  204, 176,
    115, 121, 50,  45,  127, 4,   150, 254, 138, 236, 205, 93,  222, 114, 67,  29,  24,  72,  243,
    141, 128, 195, 78,  66,  215, 61,  156, 180,
    151, 160, 137, 91,  90,  15,  131, 13,  201, 95,  96,  53,  194, 233, 7,   225, 140, 36,  103,
    30,  69,  142, 8,   99,  37,  240, 21,  10,  23,  190, 6,   148, 247, 120, 234, 75,  0,   26,
    197, 62,  94,  252, 219, 203, 117, 35,  11,  32,  57,  177, 33,  88,  237, 149, 56,  87,  174,
    20,  125, 136, 171, 168, 68,  175, 74,  165, 71,  134, 139, 48,  27,  166, 77,  146, 158, 231,
    83,  111, 229, 122, 60,  211, 133, 230, 220, 105, 92,  41,  55,  46,  245, 40,  244, 102, 143,
    54,  65,  25,  63,  161, 1,   216, 80,  73,  209, 76,  132, 187, 208, 89,  18,  169, 200, 196,
    135, 130, 116, 188, 159, 86,  164, 100, 109, 198, 173, 186, 3,   64,  52,  217, 226, 250, 124,
    123, 5,   202, 38,  147, 118, 126, 255, 82,  85,  212, 207, 206, 59,  227, 47,  16,  58,  17,
    182, 189, 28,  42,  223, 183, 170, 213, 119, 248, 152, 2,   44,  154, 163, 70,  221, 153, 101,
    155, 167, 43,  172, 9,   129, 22,  39,  253, 19,  98,  108, 110, 79,  113, 224, 232, 178, 185,
    112, 104, 218, 246, 97,  228, 251, 34,  242, 193, 238, 210, 144, 12,  191, 179, 162, 241, 81,
    51,  145, 235, 249, 14,  239, 107, 49,  192, 214, 31,  181, 199, 106, 157, 184, 84,  204, 176,
    115, 121, 50,  45,  127, 4,   150, 254, 138, 236, 205, 93,  222, 114, 67,  29,  24,  72,  243,
    141, 128, 195, 78,  66,  215, 61,  156, 180};

NRT_DEVICE float nrt_simplex_corner(NRT_NOISE_PARAM int gi, float x, float y, float z)
{
    float t = 0.6f - x * x - y * y - z * z;
    if (t < 0.0f)
        return 0.0f;
    t *= t;
    return t * t * (NRT_GRAD(gi, 0) * x + NRT_GRAD(gi, 1) * y + NRT_GRAD(gi, 2) * z);
}

/* 3D simplex noise in [-1, 1]. */
NRT_DEVICE float nrt_simplex3(NRT_NOISE_PARAM float xin, float yin, float zin)
{
    const float F3 = 1.0f / 3.0f;
    const float G3 = 1.0f / 6.0f;
    float s = (xin + yin + zin) * F3;
    int i = (int)floor(xin + s);
    int j = (int)floor(yin + s);
    int k = (int)floor(zin + s);
    float t = (float)(i + j + k) * G3;
    float x0 = xin - ((float)i - t);
    float y0 = yin - ((float)j - t);
    float z0 = zin - ((float)k - t);
    int i1, j1, k1, i2, j2, k2;
    if (x0 >= y0) {
        if (y0 >= z0) {
            i1 = 1; j1 = 0; k1 = 0; i2 = 1; j2 = 1; k2 = 0;
        } else if (x0 >= z0) {
            i1 = 1; j1 = 0; k1 = 0; i2 = 1; j2 = 0; k2 = 1;
        } else {
            i1 = 0; j1 = 0; k1 = 1; i2 = 1; j2 = 0; k2 = 1;
        }
    } else {
        if (y0 < z0) {
            i1 = 0; j1 = 0; k1 = 1; i2 = 0; j2 = 1; k2 = 1;
        } else if (x0 < z0) {
            i1 = 0; j1 = 1; k1 = 0; i2 = 0; j2 = 1; k2 = 1;
        } else {
            i1 = 0; j1 = 1; k1 = 0; i2 = 1; j2 = 1; k2 = 0;
        }
    }
    float x1 = x0 - (float)i1 + G3, y1 = y0 - (float)j1 + G3, z1 = z0 - (float)k1 + G3;
    float x2 = x0 - (float)i2 + 2.0f * G3, y2 = y0 - (float)j2 + 2.0f * G3,
          z2 = z0 - (float)k2 + 2.0f * G3;
    float x3 = x0 - 1.0f + 3.0f * G3, y3 = y0 - 1.0f + 3.0f * G3, z3 = z0 - 1.0f + 3.0f * G3;
    int ii = i & 255, jj = j & 255, kk = k & 255;
    int gi0 = NRT_PERM(ii + NRT_PERM(jj + NRT_PERM(kk))) % 12;
    int gi1 = NRT_PERM(ii + i1 + NRT_PERM(jj + j1 + NRT_PERM(kk + k1))) % 12;
    int gi2 = NRT_PERM(ii + i2 + NRT_PERM(jj + j2 + NRT_PERM(kk + k2))) % 12;
    int gi3 = NRT_PERM(ii + 1 + NRT_PERM(jj + 1 + NRT_PERM(kk + 1))) % 12;
    return 32.0f * (nrt_simplex_corner(NRT_NOISE_ARG gi0, x0, y0, z0) +
                    nrt_simplex_corner(NRT_NOISE_ARG gi1, x1, y1, z1) +
                    nrt_simplex_corner(NRT_NOISE_ARG gi2, x2, y2, z2) +
                    nrt_simplex_corner(NRT_NOISE_ARG gi3, x3, y3, z3));
}

/*
 * Smooth turbulence (thesis Eq. 2.16, listing A.14): sum over octaves of noise(f p) / f with
 * f = 2^e and the thesis's exponents {0.05, 2, 4, 6, 12, 8, 0} (FSIZE 7; the seventh entry of
 * its 6-element initialiser is 0). The thesis decorrelates octaves through 4D noise with
 * w = octave index; we shift the 3D sample point by octave * NRT_OCTAVE_SHIFT instead.
 */
#define NRT_TURB_OCTAVES 7
NRT_CONSTANT float nrt_turb_exponents[NRT_TURB_OCTAVES] = {0.05f, 2.0f, 4.0f, 6.0f,
                                                           12.0f, 8.0f, 0.0f};
#define NRT_OCTAVE_SHIFT_X 31.4159265f
#define NRT_OCTAVE_SHIFT_Y 27.1828183f
#define NRT_OCTAVE_SHIFT_Z 14.1421356f

NRT_DEVICE float nrt_turbulence(NRT_NOISE_PARAM float x, float y, float z)
{
    float sum = 0.0f;
    for (int o = 0; o < NRT_TURB_OCTAVES; ++o) {
        /* exp2 of the exponent, exact for the integral ones */
        float f = exp2(nrt_turb_exponents[o]);
        float so = (float)o;
        sum += nrt_simplex3(NRT_NOISE_ARG f * x + so * NRT_OCTAVE_SHIFT_X, f * y + so * NRT_OCTAVE_SHIFT_Y,
                            f * z + so * NRT_OCTAVE_SHIFT_Z) / f;
    }
    return sum;
}

/* The thesis's cubic bump (Eq. 3.3): (1 - d^2/r^2)^3 inside r, else 0. */
NRT_DEVICE float nrt_cubic(float d2, float r2)
{
    if (!(d2 < r2))
        return 0.0f;
    float w = 1.0f - d2 / r2;
    return w * w * w;
}

#endif /* NEBULA_COMMON_H */
