/*
 * density.cl -- dust density on the voxel grid (thesis Eq. 3.2 and 3.3).
 *
 *   rho(v) = max(floor, sum_stars bump_s(v) + base(v))
 *   base(v) = scale * max(0, turbulence(v + offset))   (model "turbulence", thesis Eq. 3.2)
 *           = uniform_density                          (model "uniform")
 *
 * v is the voxel centre ((i + 0.5) / nx, ...) in box units. The star's cubic bump (Eq. 3.3) is
 * averaged over each voxel with SUBSAMPLES^3 midpoint samples: a bump smaller than a voxel
 * (the thesis's r = 0.01 is under one voxel of a 64^3 grid) would otherwise vanish or not,
 * depending on whether a voxel centre happens to fall inside it.
 * Output index: i + nx * (j + ny * k) (x fastest, as VTK point data).
 */
#include "nebula_common.h"

#define NRT_MODEL_TURBULENCE 0
#define NRT_MODEL_UNIFORM 1

NRT_DEVICE float nrt_bump_average(int i, int j, int k, float hx, float hy, float hz,
                                  float sx, float sy, float sz, float r, int subsamples)
{
    if (!(r > 0.0f))
        return 0.0f;
    float x0 = (float)i * hx, y0 = (float)j * hy, z0 = (float)k * hz;
    /* closest point of the voxel box to the star: skip voxels the bump cannot reach */
    float cx = fmin(fmax(sx, x0), x0 + hx) - sx;
    float cy = fmin(fmax(sy, y0), y0 + hy) - sy;
    float cz = fmin(fmax(sz, z0), z0 + hz) - sz;
    float r2 = r * r;
    if (cx * cx + cy * cy + cz * cz >= r2)
        return 0.0f;
    float sum = 0.0f;
    float inv = 1.0f / (float)subsamples;
    for (int c = 0; c < subsamples; ++c) {
        float dz = z0 + ((float)c + 0.5f) * inv * hz - sz;
        for (int b = 0; b < subsamples; ++b) {
            float dy = y0 + ((float)b + 0.5f) * inv * hy - sy;
            for (int a = 0; a < subsamples; ++a) {
                float dx = x0 + ((float)a + 0.5f) * inv * hx - sx;
                sum += nrt_cubic(dx * dx + dy * dy + dz * dz, r2);
            }
        }
    }
    return sum * inv * inv * inv;
}

/* The base density (no bumps, no floor) at the centre of cell (i, j, k) of an n x n x n grid
 * ((i + 0.5) h + offset, h = 1 / n): generate_density's voxels and density_cells' octree cells
 * share it, so a tree's finest cells have the uniform grid's bits. */
NRT_DEVICE float nrt_base_density(NRT_NOISE_PARAM int i, int j, int k, float hx, float hy, float hz, int model,
                                  float ox, float oy, float oz, float scale, float uniform_density)
{
    if (model != NRT_MODEL_TURBULENCE)
        return uniform_density;
    float x = ((float)i + 0.5f) * hx + ox;
    float y = ((float)j + 0.5f) * hy + oy;
    float z = ((float)k + 0.5f) * hz + oz;
    return scale * fmax(0.0f, nrt_turbulence(NRT_NOISE_ARG x, y, z));
}

NRT_KERNEL void generate_density(NRT_GLOBAL float *out, int nx, int ny, int nz, int model,
                                 float ox, float oy, float oz, float scale,
                                 float uniform_density, float floor_density,
                                 const NRT_GLOBAL float *stars, /* x, y, z, bump radius */
                                 int n_stars, int subsamples)
{
    NRT_NOISE_TABLES();
    nrt_u64 gid = NRT_GLOBAL_ID();
    nrt_u64 n = (nrt_u64)nx * (nrt_u64)ny * (nrt_u64)nz;
    if (gid >= n)
        return;
    int i = (int)(gid % (nrt_u64)nx);
    int j = (int)((gid / (nrt_u64)nx) % (nrt_u64)ny);
    int k = (int)(gid / ((nrt_u64)nx * (nrt_u64)ny));
    float hx = 1.0f / (float)nx, hy = 1.0f / (float)ny, hz = 1.0f / (float)nz;
    float base = nrt_base_density(NRT_NOISE_ARG i, j, k, hx, hy, hz, model, ox, oy, oz, scale, uniform_density);
    float bump = 0.0f;
    for (int s = 0; s < n_stars; ++s) {
        bump += nrt_bump_average(i, j, k, hx, hy, hz, stars[4 * s], stars[4 * s + 1],
                                 stars[4 * s + 2], stars[4 * s + 3], subsamples);
    }
    out[gid] = fmax(floor_density, bump + base);
}

/* The base density of octree cells: cell c is (ijk[3c], ijk[3c + 1], ijk[3c + 2]) of the
 * n x n x n grid of its level (density.octree_density refines a tree by these values). */
NRT_KERNEL void density_cells(const NRT_GLOBAL int *ijk, nrt_u64 n_cells, int n, int model,
                              float ox, float oy, float oz, float scale, float uniform_density,
                              NRT_GLOBAL float *out)
{
    NRT_NOISE_TABLES();
    nrt_u64 gid = NRT_GLOBAL_ID();
    if (gid >= n_cells)
        return;
    float h = 1.0f / (float)n;
    out[gid] = nrt_base_density(NRT_NOISE_ARG ijk[3 * gid], ijk[3 * gid + 1], ijk[3 * gid + 2], h, h, h, model,
                                ox, oy, oz, scale, uniform_density);
}

/* Simplex noise and turbulence at given points (used by the tests against the NumPy oracle). */
NRT_KERNEL void sample_noise(const NRT_GLOBAL float *xyz, NRT_GLOBAL float *noise,
                             NRT_GLOBAL float *turb, int n)
{
    NRT_NOISE_TABLES();
    nrt_u64 gid = NRT_GLOBAL_ID();
    if (gid >= (nrt_u64)n)
        return;
    float x = xyz[3 * gid], y = xyz[3 * gid + 1], z = xyz[3 * gid + 2];
    noise[gid] = nrt_simplex3(NRT_NOISE_ARG x, y, z);
    turb[gid] = nrt_turbulence(NRT_NOISE_ARG x, y, z);
}

/*
 * The exact sum of n float32 values, for the density's mean (the colour's auto opacity): each
 * value is its significand m (24 bits, the hidden bit included where the exponent field e is
 * not 0) times 2^(max(e, 1) - 150), so bins[256 s + e] (s the sign bit) += m sums every value
 * of a sign and exponent exactly in 64-bit integers (up to 2^40 values), in any order. The
 * host adds the 512 bins exactly (nebula_rt.exact_sum): the device's and the host's
 * sums of the same array are the same number, so the mean has the same bits on every path.
 * Each work item sums a run of NRT_SIGNIFICAND_RUN consecutive values in a register while
 * their bin stays the same (neighbouring voxels mostly share an exponent), the group in local
 * memory; every item reaches every barrier.
 */
#define NRT_SIGNIFICAND_BINS 512u
#define NRT_SIGNIFICAND_RUN 64u

NRT_KERNEL void significand_sums(const NRT_GLOBAL float *v, nrt_u64 n, NRT_GLOBAL nrt_u64 *bins)
{
    NRT_LOCAL_MEM nrt_u64 l_bins[NRT_SIGNIFICAND_BINS];
    nrt_u64 lid = NRT_LOCAL_ID(), items = NRT_LOCAL_SIZE();
    for (nrt_u64 b = lid; b < NRT_SIGNIFICAND_BINS; b += items)
        l_bins[b] = 0;
    NRT_BARRIER();
    nrt_u64 first = NRT_GLOBAL_ID() * NRT_SIGNIFICAND_RUN;
    nrt_u64 last = first + NRT_SIGNIFICAND_RUN < n ? first + NRT_SIGNIFICAND_RUN : n;
    nrt_u32 bin = 0u;
    nrt_u64 run = 0;
    for (nrt_u64 i = first; i < last; ++i) {
        nrt_u32 bits = NRT_FLOAT_AS_UINT(v[i]);
        nrt_u32 key = bits >> 23;
        nrt_u64 m = (nrt_u64)((bits & 0x7FFFFFu) | ((key & 0xFFu) != 0u ? 0x800000u : 0u));
        if (key != bin && run != 0) {
            NRT_ATOMIC_ADD_U64_LOCAL(&l_bins[bin], run);
            run = 0;
        }
        bin = key;
        run += m;
    }
    if (run != 0)
        NRT_ATOMIC_ADD_U64_LOCAL(&l_bins[bin], run);
    NRT_BARRIER();
    for (nrt_u64 b = lid; b < NRT_SIGNIFICAND_BINS; b += items)
        if (l_bins[b] != 0)
            NRT_ATOMIC_ADD_U64(&bins[b], l_bins[b]);
}
