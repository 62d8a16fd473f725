/*
 * tree.cl -- Monte Carlo transport through an adaptive density: a forest of octrees in flat
 * arrays (nebula_rt.density.octree: child[node] >= 0 the first of 8 children, octant
 * c = ix + 2 iy + 4 iz; < 0 a leaf, its density at leaf_density[-1 - child]; the first
 * rx ry rz nodes the root cells, x fastest).
 *
 * One work item traces one analog packet of one band, drawing its random numbers in the order
 * of transport.cl's analog packets (the star, the direction, each flight's optical depth, the
 * absorption test, the scattering angle and azimuth), so on a tree whose leaves are a uniform
 * grid's voxels a packet flies the path it flies there. The walk steps from leaf to leaf: the
 * leaf holding a point is found from the root grid down, a point on a cell's face going to
 * the side the packet moves to, and each leaf's exit is the nearest of its three far faces.
 * The track-length estimator adds each segment's length (box units) x track_scale to the leaf's
 * 64-bit fixed-point cell (integer atomics: exact, any thread order); per band the tallies
 * count emitted, absorbed, escaped and terminated packets.
 */
#include "nebula_common.h"

#ifndef NRT_TREE_MAX_DEPTH
#define NRT_TREE_MAX_DEPTH 20
#endif
#define NRT_INF_TREE 3.0e38f

/* The leaf holding p (moving along d: a coordinate on a face goes to the side d points to);
   its integer corner and cells per axis at its level go to c, n, its box's low corner and
   size to lo, h. A face is formed as (index) x (1 / cells) at every level, the same float
   whichever level forms it (1 / (r 2^L) is 1 / r scaled by a power of 2), so a point put on a
   leaf's face compares equal to its ancestors' midplanes there. */
NRT_DEVICE int nrt_tree_locate(const NRT_GLOBAL int *child, int rx, int ry, int rz, const float *p,
                               const float *d, int *c, int *n, float *lo, float *h)
{
    int r[3] = {rx, ry, rz};
    for (int a = 0; a < 3; ++a) {
        float x = p[a] * (float)r[a];
        int i = (int)floor(x);
        /* on a root face moving down: the cell below */
        if ((float)i == x && d[a] < 0.0f)
            i -= 1;
        c[a] = min(max(i, 0), r[a] - 1);
    }
    int node = c[0] + rx * (c[1] + ry * c[2]);
    int *scale = n;
    scale[0] = rx, scale[1] = ry, scale[2] = rz;
    for (int level = 0; level <= NRT_TREE_MAX_DEPTH; ++level) {
        int k = child[node];
        if (k < 0) {
            for (int a = 0; a < 3; ++a) {
                h[a] = 1.0f / (float)scale[a];
                lo[a] = (float)c[a] * h[a];
            }
            return -1 - k;
        }
        int oct = 0;
        for (int a = 0; a < 3; ++a) {
            /* the children's shared face, as the children's faces are formed: (2 c + 1) / (2 scale) */
            float mid = (float)(2 * c[a] + 1) * (1.0f / (float)(2 * scale[a]));
            int up = p[a] > mid || (p[a] == mid && d[a] > 0.0f);
            c[a] = 2 * c[a] + up;
            scale[a] *= 2;
            oct += up << a;
        }
        node = k + oct;
    }
    return -1; /* deeper than NRT_TREE_MAX_DEPTH: not a tree the host made */
}

/* Distance from p along d to the nearest far face of the leaf (corner c, low corner lo, size
   h), formed as locate forms faces; its axis goes to ax. */
NRT_DEVICE float nrt_tree_exit(const float *p, const float *d, const int *c, const float *lo, const float *h,
                               int *ax)
{
    float t_exit = NRT_INF_TREE;
    *ax = 0;
    for (int a = 0; a < 3; ++a) {
        float t = d[a] > 0.0f ? ((float)(c[a] + 1) * h[a] - p[a]) / d[a]
                : (d[a] < 0.0f ? (lo[a] - p[a]) / d[a] : NRT_INF_TREE);
        t = fmax(t, 0.0f);
        if (t < t_exit) {
            t_exit = t;
            *ax = a;
        }
    }
    return t_exit;
}

#ifndef NRT_PEEL
#define NRT_PEEL 0
#endif

#if NRT_PEEL
/* Optical depth from x along o to the box's edge, leaf by leaf (the walk's steps). */
NRT_DEVICE float nrt_tree_tau_to_edge(const NRT_GLOBAL int *child, const NRT_GLOBAL float *leaf_density, int rx,
                                      int ry, int rz, float sig_b, const float *x, const float *o)
{
    float p[3] = {x[0], x[1], x[2]};
    float lo[3], h[3], tau = 0.0f;
    int c[3], n[3];
    int leaf = nrt_tree_locate(child, rx, ry, rz, p, o, c, n, lo, h);
    while (leaf >= 0) {
        int ax;
        float t_exit = nrt_tree_exit(p, o, c, lo, h, &ax);
        tau += sig_b * leaf_density[leaf] * t_exit;
        int up = o[ax] > 0.0f;
        if ((up && c[ax] + 1 == n[ax]) || (!up && c[ax] == 0))
            break;
        for (int a = 0; a < 3; ++a)
            p[a] = p[a] + o[a] * t_exit;
        p[ax] = (float)(c[ax] + up) * h[ax];
        leaf = nrt_tree_locate(child, rx, ry, rz, p, o, c, n, lo, h);
    }
    return tau;
}
#endif

/* Track lengths per leaf of one band's cells (leaves), tallies[4 band + t]; NRT_PEEL: the
   peel-off image per band (W x H fixed-point units, rounded stochastically as transport.cl's
   analog packets round theirs: the same draws). */
NRT_KERNEL void trace_tree(const NRT_GLOBAL int *child, const NRT_GLOBAL float *leaf_density, int rx, int ry, int rz,
                           const NRT_GLOBAL float *optics, /* per band: tau k_b, albedo, g, 0 */
                           const NRT_GLOBAL float *stars, const NRT_GLOBAL float *star_cdf, int n_stars,
                           nrt_u64 seed, nrt_u64 photon_start, nrt_u64 count, int n_bands, int max_scatterings,
                           float track_scale, nrt_u64 n_leaves, NRT_GLOBAL nrt_u64 *acc, NRT_GLOBAL nrt_u64 *tallies,
                           const NRT_GLOBAL float *peel, float peel_scale, NRT_GLOBAL nrt_u64 *image)
{
#if !NRT_PEEL
    (void)peel, (void)peel_scale, (void)image;
#endif
    nrt_u64 total = count * (nrt_u64)n_bands;
    for (nrt_u64 it = NRT_GLOBAL_ID(); it < total; it += NRT_GLOBAL_SIZE()) {
        int band = (int)(it / count);
        nrt_u64 photon = photon_start + it % count;
        float sig_b = optics[4 * band], alb_b = optics[4 * band + 1], g_b = optics[4 * band + 2];
        NRT_GLOBAL nrt_u64 *band_acc = acc + (nrt_u64)band * n_leaves;
        NRT_GLOBAL nrt_u64 *tally = tallies + 4 * band;
        nrt_rng rng;
        nrt_rng_init(&rng, seed, (nrt_u64)band, photon);
        /* the emitting star: one uniform, only with several stars (as transport.cl) */
        const NRT_GLOBAL float *cdf = star_cdf + band * n_stars;
        int s = 0;
        if (n_stars > 1) {
            float u = nrt_rng_uniform(&rng);
            while (s < n_stars - 1 && u >= cdf[s])
                ++s;
        }
        float p[3] = {stars[4 * s], stars[4 * s + 1], stars[4 * s + 2]};
        float d[3];
        nrt_sample_isotropic(&rng, d);
        NRT_ATOMIC_ADD_U64(&tally[0], 1UL);
        int scatterings = 0;
        float tau = nrt_sample_tau(&rng);
        float lo[3], h[3];
        int c[3], n[3];
        int leaf = nrt_tree_locate(child, rx, ry, rz, p, d, c, n, lo, h);
        for (;;) {
            if (leaf < 0) { /* (a malformed tree) */
                NRT_ATOMIC_ADD_U64(&tally[3], 1UL);
                break;
            }
            int ax;
            float t_exit = nrt_tree_exit(p, d, c, lo, h, &ax);
            float sigma = sig_b * leaf_density[leaf];
            float tau_seg = sigma * t_exit;
            if (sigma > 0.0f && tau_seg >= tau) {
                float t = tau / sigma;
                NRT_ATOMIC_ADD_U64(&band_acc[leaf], (nrt_u64)NRT_FMAF(t, track_scale, 0.5f));
                for (int a = 0; a < 3; ++a)
                    p[a] = fmin(fmax(p[a] + d[a] * t, lo[a]), lo[a] + h[a]);
                if (nrt_rng_uniform(&rng) >= alb_b) {
                    NRT_ATOMIC_ADD_U64(&tally[1], 1UL);
                    break;
                }
                if (scatterings >= max_scatterings) {
                    NRT_ATOMIC_ADD_U64(&tally[3], 1UL);
                    break;
                }
                ++scatterings;
#if NRT_PEEL
                {
                    nrt_u64 pixel;
                    if (nrt_peel_pixel(peel, p, &pixel)) {
                        const float o[3] = {peel[0], peel[1], peel[2]};
                        float mu_o = d[0] * o[0] + d[1] * o[1] + d[2] * o[2];
                        float wgt = nrt_hg_phase(g_b, mu_o) *
                                    exp(-nrt_tree_tau_to_edge(child, leaf_density, rx, ry, rz, sig_b, p, o));
                        nrt_u64 v = nrt_fixed_stochastic(wgt, peel_scale, seed, (nrt_u64)band, photon,
                                                         (nrt_u64)scatterings, 0);
                        if (v)
                            NRT_ATOMIC_ADD_U64(&image[(nrt_u64)band * (nrt_u64)peel[13] * (nrt_u64)peel[14] + pixel], v);
                    }
                }
#endif
                float mu, sin_theta;
                nrt_sample_hg(g_b, nrt_rng_uniform(&rng), &mu, &sin_theta);
                nrt_rotate(d, mu, sin_theta, 2.0f * NRT_PI_F * nrt_rng_uniform(&rng));
                tau = nrt_sample_tau(&rng);
                /* the point stays in this leaf (d only changed): locate again for the new d's
                   tie-breaks on a face */
                leaf = nrt_tree_locate(child, rx, ry, rz, p, d, c, n, lo, h);
                continue;
            }
            NRT_ATOMIC_ADD_U64(&band_acc[leaf], (nrt_u64)NRT_FMAF(t_exit, track_scale, 0.5f));
            tau -= tau_seg;
            for (int a = 0; a < 3; ++a)
                p[a] = p[a] + d[a] * t_exit;
            /* on the exit face exactly (formed as locate forms faces), so the next leaf is the
               one beyond it; a face of the box: the packet escapes */
            int up = d[ax] > 0.0f;
            if ((up && c[ax] + 1 == n[ax]) || (!up && c[ax] == 0)) {
                NRT_ATOMIC_ADD_U64(&tally[2], 1UL);
                break;
            }
            p[ax] = (float)(c[ax] + up) * h[ax];
            leaf = nrt_tree_locate(child, rx, ry, rz, p, d, c, n, lo, h);
        }
    }
}
