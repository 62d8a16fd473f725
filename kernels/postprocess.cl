/*
 * postprocess.cl -- from the transport's batch sums to the output arrays, on the device.
 *
 * Only the final arrays travel to the host, and the sums' memory is reused as the outputs
 * appear (peak: the sums and J, then the outputs):
 *
 *   light_cells:            J, its relative error and the emissivity (float32, band-major,
 *       x fastest), the error written over the centred sums of squares it comes from, for
 *       a range of bands (emissivity_cells: the emissivity after the sums are freed, where
 *       the light is made after the transport);
 *   finish_voxels, pass 0:  the opacity byte of rgba and a brightness key per voxel for the
 *       exposure;
 *   key_histogram, select_rank_bins, key_histogram_low, select_level: the exposure
 *       percentile, exactly, by a radix select on the device (two passes of 2^16 bins), the
 *       exposure left in device memory for pass 1: no round trip to the host;
 *   finish_voxels, pass 1:  the colour bytes of rgba at the chosen exposure (the colour is
 *       recomputed from J rather than stored: reading J again costs less memory than a
 *       float colour buffer on large grids).
 *
 * The arithmetic follows the NumPy reference (nebula_rt.transport.trace,
 * nebula_rt.pipeline.assemble_light_field and rgba_from_emissivity) operation by operation,
 * in double precision; only the band sum of the colour matrix may round differently.
 */
#include "nebula_common.h"

/* Luminance weights of linear sRGB (Rec. 709), for the gamut mapping. */
#define NRT_LUMA_R 0.2126
#define NRT_LUMA_G 0.7152
#define NRT_LUMA_B 0.0722
/* Visible voxels (alpha >= this) set the auto exposure (pipeline.AUTO_EXPOSURE_MIN_ALPHA). */
#ifndef NRT_MIN_ALPHA
#define NRT_MIN_ALPHA 0.01
#endif

/* (fmin/fmax are the float versions under CUDA: see nebula_common.h) */
NRT_DEVICE double nrt_dmax(double a, double b) { return a > b ? a : b; }
NRT_DEVICE double nrt_dmin(double a, double b) { return a < b ? a : b; }

/* Standard error of a total of `batches` batch totals from their sum x1 and centred sum of
   squares q = sum (x - mean)^2 (batch means; nebula_rt.transport.batch_standard_error). */
NRT_DEVICE double nrt_batch_se(double x1, double q, double batches)
{
    if (batches < 2.0)
        return x1 < 0.0 ? -x1 : x1; /* one batch: no spread to measure, report 100 % */
    return NRT_DSQRT(nrt_dmax(q * (batches / (batches - 1.0)), 0.0));
}

/* Stored centred sums of squares are float32 x 2^-64 (see fold_batches in transport.cl). */
#define NRT_M2_UP 18446744073709551616.0 /* 2^64 */

/* sRGB transfer curve (IEC 61966-2-1) of x in [0, 1] -> 0..255. */
NRT_DEVICE nrt_u8 nrt_srgb8(double x)
{
    double e = (x <= 0.0031308) ? 12.92 * x : 1.055 * pow(x, 1.0 / 2.4) - 0.055;
    double v = rint(e * 255.0);
    v = v < 0.0 ? 0.0 : (v > 255.0 ? 255.0 : v);
    return (nrt_u8)v;
}

/* The emissivity of band k's cell: albedo x sigma x the float32 J (the output's own
   precision, which the float64 sums do not improve). */
NRT_DEVICE float nrt_emissivity(const NRT_GLOBAL double *band_params, int k, double rho, float j32)
{
    return (float)(band_params[4 * k + 2] * (band_params[4 * k + 1] * rho) * (double)j32);
}

/*
 * light_cells: J, its relative error and (with_emis) the emissivity per cell i0 .. n - 1
 * (cells: n_bands * nvox, band-major; a range of whole bands) as float32, the first pass of
 * the finishing.
 * band_params: per band 4 doubles: J scale (J = sum x scale, or for
 * the collision estimator J = sum / sigma x scale), extinction per box unit at density 1
 * (tau k_b), albedo, batches folded.
 * mode 0: from the sum s1 of the batch totals and their centred sum of squares m2 (float32
 *     x 2^-64); rel32 may be m2 itself (each cell is read before it is written, by the same
 *     work item), so the error needs no memory of its own;
 * mode 1: from J and its relative error already computed (filtered), in j64 and rel64.
 */
NRT_KERNEL void light_cells(const NRT_GLOBAL double *s1, const NRT_GLOBAL float *m2,
                            const NRT_GLOBAL double *j64, const NRT_GLOBAL double *rel64,
                            const NRT_GLOBAL float *density, const NRT_GLOBAL double *band_params,
                            nrt_u64 nvox, nrt_u64 i0, nrt_u64 n, int mode, int collision, int with_emis,
                            NRT_GLOBAL float *J32, NRT_GLOBAL float *rel32, NRT_GLOBAL float *emis32)
{
    nrt_u64 i = i0 + NRT_GLOBAL_ID();
    if (i >= n)
        return;
    int k = (int)(i / nvox);
    double rho = (double)density[i - (nrt_u64)k * nvox];
    double J, rel;
    if (mode == 0) {
        double x1 = s1[i];
        double se = nrt_batch_se(x1, (double)m2[i] * NRT_M2_UP, band_params[4 * k + 3]);
        rel = (x1 > 0.0) ? se / x1 : 1.0;
        if (collision) {
            double sig = band_params[4 * k + 1] * rho;
            J = (sig > 0.0) ? x1 / sig : 0.0;
            J *= band_params[4 * k];
        } else {
            J = x1 * band_params[4 * k];
        }
    } else {
        J = j64[i];
        rel = rel64[i];
    }
    float j32 = (float)J;
    J32[i] = j32;
    rel32[i] = (float)rel;
    if (with_emis)
        emis32[i] = nrt_emissivity(band_params, k, rho, j32);
}

/* emissivity_cells: the emissivity of cells i0 .. n - 1 from the float32 J, where the
   finishing makes it after the sums' memory is freed (large grids). */
NRT_KERNEL void emissivity_cells(const NRT_GLOBAL float *J32, const NRT_GLOBAL float *density,
                                 const NRT_GLOBAL double *band_params, nrt_u64 nvox, nrt_u64 i0, nrt_u64 n,
                                 NRT_GLOBAL float *emis32)
{
    nrt_u64 i = i0 + NRT_GLOBAL_ID();
    if (i >= n)
        return;
    int k = (int)(i / nvox);
    emis32[i] = nrt_emissivity(band_params, k, (double)density[i - (nrt_u64)k * nvox], J32[i]);
}

/*
 * finish_voxels: per voxel, over all bands, from the float32 J (emissivity = albedo x sigma x
 * J of the float32 J, as light_cells stores it).
 * to_rgb: 3 x n_bands (row-major), band emissivity / (L_b sigma_ref) -> linear sRGB, white
 * balance included.
 *   pass 0: the opacity byte of rgba and the brightness key of the exposure;
 *   pass 1: the colour bytes of rgba at the exposure dsel[2] (select_level's, or the scene's),
 *       recomputed from J rather than stored: a float colour buffer would cost more memory
 *       than reading J again.
 */
NRT_KERNEL void finish_voxels(const NRT_GLOBAL float *J32, const NRT_GLOBAL float *density,
                              const NRT_GLOBAL double *band_params,
                              const NRT_GLOBAL double *to_rgb, int n_bands, nrt_u64 nvox,
                              int pass, int colour,
                              double sigma_ref_scale, double voxel_edge, double opacity_scale,
                              const NRT_GLOBAL double *dsel, NRT_GLOBAL float *key, NRT_GLOBAL nrt_u8 *rgba)
{
    nrt_u64 v = NRT_GLOBAL_ID();
    if (v >= nvox)
        return;
    double rho = (double)density[v];
    double rgb[3] = {0.0, 0.0, 0.0};
    for (int k = 0; k < n_bands; ++k) {
        nrt_u64 i = (nrt_u64)k * nvox + v;
        double sig_k = band_params[4 * k + 1], alb = band_params[4 * k + 2];
        double emis = alb * (sig_k * rho) * (double)J32[i];
        if (colour) {
            rgb[0] += emis * to_rgb[k];
            rgb[1] += emis * to_rgb[n_bands + k];
            rgb[2] += emis * to_rgb[2 * n_bands + k];
        }
    }
    if (!colour)
        return;
    /* colour of the emissivity per unit reference extinction, gamut-mapped towards grey */
    double sigma_ref = sigma_ref_scale * rho;
    for (int c = 0; c < 3; ++c)
        rgb[c] = (sigma_ref > 0.0) ? rgb[c] / sigma_ref : 0.0;
    double mn = nrt_dmin(rgb[0], nrt_dmin(rgb[1], rgb[2]));
    if (mn < 0.0) {
        double y = NRT_LUMA_R * rgb[0] + NRT_LUMA_G * rgb[1] + NRT_LUMA_B * rgb[2];
        if (y > 0.0) {
            double t = y / (y - mn);
            for (int c = 0; c < 3; ++c)
                rgb[c] = nrt_dmax(y + t * (rgb[c] - y), 0.0);
        } else {
            rgb[0] = rgb[1] = rgb[2] = 0.0;
        }
    }
    if (pass == 0) {
        double alpha = 1.0 - exp(-(sigma_ref * voxel_edge * opacity_scale));
        double a8 = rint(alpha * 255.0);
        rgba[4 * v + 3] = (nrt_u8)(a8 < 0.0 ? 0.0 : (a8 > 255.0 ? 255.0 : a8));
        /* brightness key: the largest component; its sign bit marks voxels too transparent
           to set the exposure (-0.0 stays distinguishable from +0.0 in the bit pattern) */
        float mx = (float)nrt_dmax(rgb[0], nrt_dmax(rgb[1], rgb[2]));
        key[v] = (alpha >= NRT_MIN_ALPHA) ? mx : -mx;
        return;
    }
    /* pass 1: expose; an over-exposed colour is scaled down as a whole (keeps its hue) */
    double exposure = dsel[2], x[3]; /* (select_level's result, or the scene's exposure) */
    for (int c = 0; c < 3; ++c)
        x[c] = nrt_dmax(rgb[c] * exposure, 0.0);
    double mxe = nrt_dmax(nrt_dmax(x[0], nrt_dmax(x[1], x[2])), 1.0);
    for (int c = 0; c < 3; ++c)
        rgba[4 * v + c] = nrt_srgb8(x[c] / mxe);
}

/*
 * The auto exposure's radix select. Keys are non-negative floats (with the sign bit as the
 * visibility flag), whose bit patterns sort like their values, so the high 16 bits pick a bin
 * and the low 16 bits the value inside it. The order statistics are those of the positive
 * finite keys of the visible voxels (or of every voxel when no visible voxel has a finite
 * key), interpolated linearly between ranks as numpy.percentile does, in the host's double
 * arithmetic (nebula_rt.transport.finish.percentile_of_keys).
 *
 * key_histogram: hist[bits >> 16] counts the positive finite keys, hist[65536] the zeros;
 * all_voxels 0 takes only visible voxels, 1 every voxel.
 */
#define NRT_KEY_BINS 65536u

NRT_KERNEL void key_histogram(const NRT_GLOBAL float *key, nrt_u64 n, int all_voxels, NRT_GLOBAL nrt_u32 *hist)
{
    nrt_u64 v = NRT_GLOBAL_ID();
    if (v >= n)
        return;
    nrt_u32 bits = NRT_FLOAT_AS_UINT(key[v]);
    if ((bits >> 31) && !all_voxels)
        return;
    bits &= 0x7FFFFFFFu;
    if (bits >= 0x7F800000u) /* inf or nan: no exposure from these */
        return;
    NRT_ATOMIC_ADD_U32(&hist[bits == 0u ? NRT_KEY_BINS : (bits >> 16)], 1u);
}

/* The select's chunks: 256 chunks of 256 bins of a 2^16-bin histogram. Each one-group kernel
   below finds a rank's chunk from the chunk sums, then its bin inside the chunk, both scans
   over local memory (a serial walk of the 2^16 bins in global memory, or a work item's serial
   sum of its own chunk, took 1.7 ms on an H100). */
#define NRT_CHUNK 256u
#define NRT_CHUNKS 256u

/* bin_chunk_sums: chunks[chunk0 + b / 256] += hist[b] for the bins b < n (n a multiple of
   256: several histograms side by side give their chunks side by side). */
NRT_KERNEL void bin_chunk_sums(const NRT_GLOBAL nrt_u32 *hist, nrt_u64 n, NRT_GLOBAL nrt_u32 *chunks, int chunk0)
{
    nrt_u64 b = NRT_GLOBAL_ID();
    if (b >= n)
        return;
    nrt_u32 h = hist[b];
    if (h != 0u)
        NRT_ATOMIC_ADD_U32(&chunks[(nrt_u64)chunk0 + b / NRT_CHUNK], h);
}

/* (Every work item of the group calls this.) The first bin b of hist (2^16 bins, their chunk
   sums in chunks) at which the running sum passes r (numpy's searchsorted(cumsum, r,
   side="right")) into l_pos[0], and r less the keys of the bins before b into l_pos[1]. */
NRT_DEVICE void nrt_rank_bin(const NRT_GLOBAL nrt_u32 *hist, const NRT_GLOBAL nrt_u32 *chunks, nrt_u64 r,
                             NRT_LOCAL nrt_u32 *l_bins, NRT_LOCAL nrt_u64 *l_pos)
{
    nrt_u32 lid = (nrt_u32)NRT_LOCAL_ID(), items = (nrt_u32)NRT_LOCAL_SIZE();
    for (nrt_u32 j = lid; j < NRT_CHUNKS; j += items)
        l_bins[j] = chunks[j];
    NRT_BARRIER();
    if (lid == 0) {
        nrt_u32 c = 0;
        nrt_u64 before = 0;
        while (c + 1 < NRT_CHUNKS && before + l_bins[c] <= r)
            before += l_bins[c++];
        l_pos[0] = c;
        l_pos[1] = before;
    }
    NRT_BARRIER();
    nrt_u64 c = l_pos[0];
    for (nrt_u32 j = lid; j < NRT_CHUNK; j += items)
        l_bins[j] = hist[c * NRT_CHUNK + j];
    NRT_BARRIER();
    if (lid == 0) {
        nrt_u32 b = 0;
        nrt_u64 before = l_pos[1];
        while (b + 1 < NRT_CHUNK && before + l_bins[b] <= r)
            before += l_bins[b++];
        l_pos[0] = c * NRT_CHUNK + b;
        l_pos[1] = r - before;
    }
    NRT_BARRIER();
}

/*
 * select_rank_bins (one work group, of any size): from the high-bits histograms of the
 * visible voxels and of every voxel (their chunk sums in chunks[0 .. 256) and [256 .. 512)),
 * the ranks k and k + 1 of the percentile (fraction = percentile / 100) among the npos
 * positive keys, and the bins that hold them. sel: all_voxels, npos, the bin of rank k and
 * the rank within it, the same for rank k + 1; dsel[0]: the interpolation weight idx - k.
 */
NRT_KERNEL void select_rank_bins(const NRT_GLOBAL nrt_u32 *hist_vis, const NRT_GLOBAL nrt_u32 *hist_all,
                                 const NRT_GLOBAL nrt_u32 *chunks, double fraction, NRT_GLOBAL nrt_u64 *sel,
                                 NRT_GLOBAL double *dsel)
{
    NRT_LOCAL_MEM nrt_u32 l_bins[NRT_CHUNK];
    NRT_LOCAL_MEM nrt_u64 l_pos[2];
    NRT_LOCAL_MEM nrt_u64 l_count[2];
    int lid0 = NRT_LOCAL_ID() == 0;
    if (lid0) {
        /* nothing visible (not even a zero key): expose for every voxel */
        nrt_u64 seen = hist_vis[NRT_KEY_BINS];
        for (nrt_u32 c = 0; c < NRT_CHUNKS; ++c)
            seen += chunks[c];
        nrt_u64 all = seen == 0, npos = 0;
        for (nrt_u32 c = 0; c < NRT_CHUNKS; ++c)
            npos += chunks[all * NRT_CHUNKS + c];
        l_count[0] = all;
        l_count[1] = npos;
        sel[0] = all;
        sel[1] = npos;
        dsel[0] = 0.0;
    }
    NRT_BARRIER();
    /* every item reaches every barrier: the searches run even without a positive key (PoCL
       mishandled a return before the barriers, though the same for the whole group) */
    nrt_u64 all = l_count[0], npos = l_count[1];
    const NRT_GLOBAL nrt_u32 *hist = all ? hist_all : hist_vis;
    double idx = fraction * (double)(npos > 0 ? npos - 1 : 0);
    nrt_u64 k = (nrt_u64)floor(idx), k1 = k + 1 < npos ? k + 1 : k;
    nrt_rank_bin(hist, chunks + all * NRT_CHUNKS, k, l_bins, l_pos);
    if (lid0 && npos > 0) {
        sel[2] = l_pos[0];
        sel[3] = l_pos[1];
        dsel[0] = idx - (double)k;
    }
    nrt_rank_bin(hist, chunks + all * NRT_CHUNKS, k1, l_bins, l_pos);
    if (lid0 && npos > 0) {
        sel[4] = l_pos[0];
        sel[5] = l_pos[1];
    }
}

/* key_histogram_low: hist[r * 65536 + (bits & 0xffff)] counts the keys (as select_rank_bins
   chose them) whose high bits are the bin of rank r (r = 0: k, 1: k + 1). */
NRT_KERNEL void key_histogram_low(const NRT_GLOBAL float *key, nrt_u64 n, const NRT_GLOBAL nrt_u64 *sel,
                                  NRT_GLOBAL nrt_u32 *hist)
{
    nrt_u64 v = NRT_GLOBAL_ID();
    if (v >= n || sel[1] == 0)
        return;
    nrt_u32 bits = NRT_FLOAT_AS_UINT(key[v]);
    if ((bits >> 31) && !sel[0])
        return;
    bits &= 0x7FFFFFFFu;
    if (bits == 0u || bits >= 0x7F800000u)
        return;
    if ((nrt_u64)(bits >> 16) == sel[2])
        NRT_ATOMIC_ADD_U32(&hist[bits & 0xFFFFu], 1u);
    if ((nrt_u64)(bits >> 16) == sel[4])
        NRT_ATOMIC_ADD_U32(&hist[NRT_KEY_BINS + (bits & 0xFFFFu)], 1u);
}

/* select_level (one work group, of any size): the percentile's level from the low-bits
   histograms (their chunk sums side by side in chunks), into dsel[1] (-1: no positive key; a
   level is positive), and the exposure 1 / level (1 where there is no positive level) into
   dsel[2], where pass 1 of finish_voxels reads it. */
/* The value of a non-negative finite float32 key's bit pattern as a double, formed from its
   significand and exponent in integers: a float-to-double conversion of a denormal key gives 0
   where the compiler flushes denormals (CUDA's build does). */
NRT_DEVICE double nrt_key_value(nrt_u32 bits)
{
    nrt_u32 e = (bits >> 23) & 0xFFu, m = bits & 0x7FFFFFu;
    return e == 0u ? ldexp((double)m, -149) : ldexp((double)(m | 0x800000u), (int)e - 150);
}

NRT_KERNEL void select_level(const NRT_GLOBAL nrt_u32 *hist, const NRT_GLOBAL nrt_u32 *chunks,
                             const NRT_GLOBAL nrt_u64 *sel, NRT_GLOBAL double *dsel)
{
    NRT_LOCAL_MEM nrt_u32 l_bins[NRT_CHUNK];
    NRT_LOCAL_MEM nrt_u64 l_pos[2];
    double v[2];
    for (int r = 0; r < 2; ++r) { /* (every item reaches every barrier, as in select_rank_bins) */
        nrt_rank_bin(hist + (nrt_u64)r * NRT_KEY_BINS, chunks + (nrt_u64)r * NRT_CHUNKS, sel[3 + 2 * r], l_bins, l_pos);
        v[r] = nrt_key_value(((nrt_u32)sel[2 + 2 * r] << 16) | (nrt_u32)l_pos[0]);
    }
    if (NRT_LOCAL_ID() != 0)
        return;
    if (sel[1] == 0) {
        dsel[1] = -1.0;
        dsel[2] = 1.0;
        return;
    }
    double frac = dsel[0], level = frac == 0.0 ? v[0] : v[0] + frac * (v[1] - v[0]);
    dsel[1] = level;
    dsel[2] = level > 0.0 ? 1.0 / level : 1.0;
}

/*
 * Collision estimator before the filter: the unfiltered J and its variance per cell, from the
 * sums of the batch totals (as nebula_rt.pipeline.filter_collisions computes them):
 * J = sum / sigma x scale, var = (SE x J / sum)^2. n = n_bands * nvox cells.
 */
NRT_KERNEL void collision_light(const NRT_GLOBAL double *s1, const NRT_GLOBAL float *m2,
                                const NRT_GLOBAL float *density,
                                const NRT_GLOBAL double *band_params, nrt_u64 nvox,
                                nrt_u64 n, NRT_GLOBAL double *J, NRT_GLOBAL double *var)
{
    nrt_u64 i = NRT_GLOBAL_ID();
    if (i >= n)
        return;
    int k = (int)(i / nvox);
    double rho = (double)density[i - (nrt_u64)k * nvox];
    double x1 = s1[i];
    double se = nrt_batch_se(x1, (double)m2[i] * NRT_M2_UP, band_params[4 * k + 3]);
    double sig = band_params[4 * k + 1] * rho;
    double j = (sig > 0.0) ? x1 / sig : 0.0;
    j *= band_params[4 * k];
    double scale = (x1 > 0.0) ? j / x1 : 0.0;
    double e = se * scale;
    J[i] = j;
    var[i] = e * e;
}

/* Relative error of a filtered J from its filtered variance (1 where J is 0). */
NRT_KERNEL void relative_error(const NRT_GLOBAL double *J, const NRT_GLOBAL double *var, nrt_u64 n,
                               NRT_GLOBAL double *rel)
{
    nrt_u64 i = NRT_GLOBAL_ID();
    if (i >= n)
        return;
    double j = J[i];
    rel[i] = (j > 0.0) ? NRT_DSQRT(var[i]) / j : 1.0;
}

/*
 * The lit-region error of a transport so far (nebula_rt.transport.lit_region_error), band by
 * band, in two passes with a key array of one float per voxel:
 *   lit_keys:          key = sigma_b J_b (the light the dust intercepts), or J_b alone
 *                      (use_sigma 0, for a band without dust); its 95th percentile is then
 *                      picked by the radix select of the exposure (key_histogram);
 *   lit_partial_sums:  over the voxels with a positive key at or above the level, the sums of
 *                      w = key and of w rel^2, each work item over its own `chunk` of voxels
 *                      in order (the host adds the partial sums in order: deterministic).
 * band_params as for light_cells; s1 and m2 are the band's cells (offset band * nvox).
 */
NRT_KERNEL void lit_keys(const NRT_GLOBAL double *s1, const NRT_GLOBAL float *density,
                         const NRT_GLOBAL double *band_params, int band, nrt_u64 nvox,
                         int collision, int use_sigma, NRT_GLOBAL float *key)
{
    nrt_u64 v = NRT_GLOBAL_ID();
    if (v >= nvox)
        return;
    double x1 = s1[(nrt_u64)band * nvox + v];
    double sig = band_params[4 * band + 1] * (double)density[v];
    double J;
    if (collision)
        J = (sig > 0.0) ? x1 / sig * band_params[4 * band] : 0.0;
    else
        J = x1 * band_params[4 * band];
    key[v] = (float)(use_sigma ? J * sig : J);
}

NRT_KERNEL void lit_partial_sums(const NRT_GLOBAL double *s1, const NRT_GLOBAL float *m2,
                                 const NRT_GLOBAL float *key, const NRT_GLOBAL double *band_params,
                                 int band, double level, nrt_u64 nvox, nrt_u64 chunk,
                                 NRT_GLOBAL double *partial)
{
    nrt_u64 i = NRT_GLOBAL_ID();
    nrt_u64 first = i * chunk;
    if (first >= nvox)
        return;
    nrt_u64 last = first + chunk < nvox ? first + chunk : nvox;
    double batches = band_params[4 * band + 3];
    double sw = 0.0, swr = 0.0;
    for (nrt_u64 v = first; v < last; ++v) {
        double w = (double)key[v];
        if (w > 0.0 && w >= level) {
            nrt_u64 c = (nrt_u64)band * nvox + v;
            double x1 = s1[c];
            double se = nrt_batch_se(x1, (double)m2[c] * NRT_M2_UP, batches);
            double rel = (x1 > 0.0) ? se / x1 : 1.0;
            sw += w;
            swr += w * rel * rel;
        }
    }
    partial[2 * i] = sw;
    partial[2 * i + 1] = swr;
}
