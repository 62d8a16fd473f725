/*
 * transport.cl -- Monte Carlo photon packet transport through a piecewise-constant voxel grid.
 *
 * One work item traces one packet of one band; the bands of a launch go in one grid
 * (gid = band * count + i). Packets leave a star isotropically (the star is chosen with
 * probability L_star,b / L_b), fly an exponentially distributed optical depth -ln(1 - xi)
 * that is spent exactly voxel by voxel (3D DDA, Amanatides & Woo 1987), and at the interaction
 * scatter with probability albedo_b (analog: every packet carries the same energy, so energy
 * tallies are integer packet counts and conservation is exact) into a Henyey-Greenstein
 * direction, or are absorbed. A packet that would scatter more than max_scatterings times is
 * terminated and tallied as such.
 *
 * Extinction per box unit: sigma_b(v) = sigma_scale[b] * rho(v), sigma_scale[b] = tau * k_b.
 * (The thesis multiplied the free PATH by k_b, sending blue light farther; physically the
 * extinction scales with k_b.)
 *
 * Estimators (compile-time, only what the scene asks for is built):
 *   NRT_TRACK_LENGTH: every flight segment adds its length (box units) x NRT fixed-point scale
 *                     to the voxel it crosses;
 *   NRT_COLLISION:    every interaction adds 1 to the voxel it happens in (J = count / sigma).
 *
 * Accumulation is in unsigned 64-bit fixed point with integer atomics: integer addition is
 * associative, so the sums are exact and identical whatever the thread order. A cell that
 * reaches 2^63 raises *overflow instead of wrapping silently (checked as it is added, or by the
 * fold with NRT_ACC_RED, see below); the host then re-traces the batch in halves (same photons,
 * same random numbers).
 *
 * Tallies per band (tallies[4 b + t]): 0 emitted, 1 absorbed, 2 escaped, 3 terminated.
 *
 * NRT_PACKET_SQ (the error estimate by packets, transport.error_estimate = "packets"): besides
 * its deposits, a packet adds the square of what it deposited into a voxel during one visit
 * (its consecutive deposits there, summed) to that voxel's cell of sq, rounded to nearest in
 * units of 2^sq_shift (square) fixed-point units. The host then has, per cell, the sum of the
 * packets' contributions and of their squares, and the error of the total without batches.
 */
#include "nebula_common.h"

#ifndef NRT_TRACK_LENGTH
#define NRT_TRACK_LENGTH 0
#endif
#ifndef NRT_COLLISION
#define NRT_COLLISION 0
#endif
#ifndef NRT_PACKET_SQ
#define NRT_PACKET_SQ 0
#endif

/* Headroom limit of a fixed-point cell: 2^63 (tests lower it to exercise the overflow path). */
#ifndef NRT_ACC_LIMIT_BITS
#define NRT_ACC_LIMIT_BITS 63
#endif
#define NRT_ACC_LIMIT (1UL << NRT_ACC_LIMIT_BITS)
#define NRT_INF_F 3.0e38f

/*
 * Performance options (all give the same bits; benchmarks/tune_cuda.py measures them):
 *   NRT_ACC_RED      deposits are added without reading the old value back (a reduction the
 *                    GPU need not wait for); the fold then flags any cell at or past the
 *                    headroom limit. The host enables it only where no cell can wrap past
 *                    2^64 within one launch, so "final >= limit" is exactly "some partial
 *                    sum reached the limit" (deposits are non-negative), and on a flag it
 *                    re-runs with checked adds.
 *   NRT_PREFETCH     load the density of the voxel the packet steps into next while the
 *                    current voxel is being scored (the DDA path does not depend on the
 *                    density, so the load's latency overlaps this voxel's work).
 *   NRT_GROUP_TALLY  per work group, the packet tallies and the deposits into the block of
 *                    (2 NRT_HOT_HALF + 1)^3 voxels around the emitting star's voxel (which
 *                    every packet crosses first: the hottest cells of a point source, where
 *                    the adds of all packets in flight queue on the same addresses) are summed
 *                    in local memory and added to global memory once.
 *   NRT_IDX32        32-bit voxel indices (grids below 2^32 voxels).
 *   NRT_SORTED       work items take their packets in the order of `order` (the launch's
 *                    packets sorted by cell, star and first direction, emission_keys): the
 *                    packets of a warp then fly their first flight side by side, so their
 *                    deposits and density loads share cache sectors instead of scattering
 *                    over the grid (integer deposits: the order changes no bit).
 */
#ifndef NRT_ACC_RED
#define NRT_ACC_RED 0
#endif
#ifndef NRT_PREFETCH
#define NRT_PREFETCH 0
#endif
#ifndef NRT_GROUP_TALLY
#define NRT_GROUP_TALLY 0
#endif
#ifndef NRT_IDX32
#define NRT_IDX32 0
#endif
#ifndef NRT_SORTED
#define NRT_SORTED 0
#endif
/* weighted packets with 128-bit cells, images and tallies (transport.method = "biased") */
#ifndef NRT_BIASED
#define NRT_BIASED 0
#endif
#if NRT_BIASED && (NRT_GROUP_TALLY || NRT_ACC_RED)
#error "NRT_BIASED takes checked 128-bit adds: no NRT_GROUP_TALLY or NRT_ACC_RED"
#endif
#ifndef NRT_PEEL
#define NRT_PEEL 0
#endif
/*
 * Heavy-tail diagnostic (nebula_rt.transport.tails, docs/physics.md): per packet -- one history: a
 * weighted packet with all its split copies -- the sum of what it adds to the peel-off image
 * (NRT_PEEL) and, weighted packets with the track-length estimator, of what it deposits into
 * the voxels of each of NRT_TAIL_CLASSES classes of optical depth from the stars. As the packet
 * ends, each nonzero sum adds 1 to its bin of a histogram of NRT_TAIL_BINS half-octave bins
 * (nrt_tail_add) in the cell's tally block, after the energy tallies: image first, then the
 * depth classes.
 * Integer counts of sums the same on every device (the image's: integers; J's: float32 sums
 * of the same floats in the same order): the same bits in any order, on any device and
 * number of ranks. The host reads the distribution of the packets' contributions from it
 * (the variance of the variance, the largest packet's share, the tail's slope), which batch
 * means cannot: they see a tail only where a batch happened to sample it.
 */
#ifndef NRT_TAIL_CLASSES
#define NRT_TAIL_CLASSES 0
#endif
#define NRT_TAIL_HISTS (NRT_PEEL + NRT_TAIL_CLASSES)
/* 64-bit words per accumulator cell and per tally block (4 counts, or 5 tallies of 128 bits
   when biased; then the heavy-tail histograms) */
#define NRT_CELL_WORDS (NRT_BIASED ? 2 : 1)
#define NRT_TALLY_BASE (NRT_BIASED ? NRT_TALLY_WEIGHTED : NRT_TALLY_ANALOG)
#define NRT_TALLY_WORDS (NRT_TALLY_BASE + NRT_TAIL_HISTS * NRT_TAIL_BINS)
/* direction bins of the sort key: 2^NRT_SORT_BITS along mu and along phi, in Morton order */
#ifndef NRT_SORT_BITS
#define NRT_SORT_BITS 8
#endif
/*
 * Measurement probes (benchmarks/bench_large_grids.py --tuning; they give wrong light fields and
 * the library never sets them): what the voxel deposits and the density loads cost.
 *   NRT_PROBE_DEPOSIT 1  no voxel deposits (the walk, the density loads and the tallies only);
 *                    2  each deposit as a 32-bit atomic add of v >> 28 into the low half of the
 *                       slot (the memory traffic of an accumulator half as wide);
 *                    3  each deposit also adds its square into the voxel whose index differs in
 *                       bit NRT_PROBE_MIRROR_BIT (the traffic of a second array of the grid's
 *                       size, as a per-packet sum of squares would make);
 *   NRT_PROBE_UNIFORM 1  every density load reads voxel 0 (no density traffic).
 *   NRT_PROBE_SQ      1  NRT_PACKET_SQ without the squares' adds (what the visit bookkeeping
 *                       costs); 2  the squares added into the slot's neighbouring cell (idx ^ 1,
 *                       the same 32-byte sector: what the adds would cost interleaved).
 *   NRT_PROBE_HOT_HALF h >= 0: the walk's deposits into the voxels within h voxels (on every
 *                       axis) of voxel (NRT_PROBE_HOT_X, _Y, _Z) are dropped (what the adds to
 *                       the few voxels every packet crosses cost: same-address atomics); -1
 *                       makes the same test and drops nothing (the control).
 */
#ifndef NRT_PROBE_DEPOSIT
#define NRT_PROBE_DEPOSIT 0
#endif
#ifndef NRT_PROBE_UNIFORM
#define NRT_PROBE_UNIFORM 0
#endif
#ifndef NRT_PROBE_SQ
#define NRT_PROBE_SQ 0
#endif
#ifndef NRT_PROBE_MIRROR_BIT
#define NRT_PROBE_MIRROR_BIT 20
#endif
#ifndef NRT_PROBE_HOT_X
#define NRT_PROBE_HOT_X 0
#define NRT_PROBE_HOT_Y 0
#define NRT_PROBE_HOT_Z 0
#endif
#if NRT_PROBE_UNIFORM
#define NRT_RHO(density, i) ((density)[0])
#else
#define NRT_RHO(density, i) ((density)[i])
#endif
#if NRT_IDX32
typedef nrt_u32 nrt_idx;
#else
typedef nrt_u64 nrt_idx;
#endif
/* stars whose voxels get a work-group accumulator: a block of NRT_HOT_SIDE^3 voxels centred on
   the star's voxel (clipped by the grid's faces: cells outside it stay zero). Dropping the
   deposits into 3^3 / 5^3 / 17^3 voxels around the star made the thesis scene's kernel 10 / 13
   / 16 % faster on an H200 (NRT_PROBE_HOT_HALF; benchmarks/results/h200-2026-12-04c/): the
   adds of every packet in flight to the same few addresses queue in the L2's atomic units.
   Blocks of 7^3 (half 3): kernel packets per ms on an H100, thesis 128^3 / neb 128^3, 628k /
   629k with 5^3, 635k / 637k with 7^3, 630k with 9^3, once the local adds were two 32-bit
   atomics instead of a compare-and-swap loop (benchmarks/results/h100-2026-12-05c/; with the
   loop, on an H200, 5^3 and 7^3 were equal). 11 KiB of local memory per group. */
#define NRT_HOT_STARS 4
#ifndef NRT_HOT_HALF
#define NRT_HOT_HALF 3
#endif
#define NRT_HOT_SIDE (2 * NRT_HOT_HALF + 1)
#define NRT_HOT_CELLS (NRT_HOT_SIDE * NRT_HOT_SIDE * NRT_HOT_SIDE)
/* the origin of no block (every voxel's offset from it is at least NRT_HOT_SIDE) */
#define NRT_NO_HOT (-(1 << 30))
#define NRT_NO_VOXEL ((nrt_idx)(-1))

/* CUDA: the global pointer x as computed, opaque to the optimiser (which would otherwise form it
   again from its operands at every use, under the transport kernel's register cap: 9 instructions
   per deposit instead of 1), and still known to point to global memory (REDG, not a generic
   atomic that tests the address space first) */
#if defined(__CUDACC__) || defined(__CUDACC_RTC__)
#define NRT_OPAQUE_PTR(x) do { asm volatile("" : "+l"(x)); __builtin_assume(__isGlobal(x)); } while (0)
#else
#define NRT_OPAQUE_PTR(x) ((void)0)
#endif

/* Add v to a fixed-point cell, raising *overflow if the cell reaches the headroom limit. */
NRT_DEVICE void nrt_acc_add_checked(NRT_GLOBAL nrt_u64 *cell, nrt_u64 v, NRT_GLOBAL nrt_u32 *overflow)
{
    if (v == 0)
        return;
    nrt_u64 old = NRT_ATOMIC_ADD_U64(cell, v);
    if (v >= NRT_ACC_LIMIT || old >= NRT_ACC_LIMIT - v)
        NRT_ATOMIC_OR_U32(overflow, 1u);
}

/* A transport deposit: checked, or (NRT_ACC_RED) a reduction checked by the fold (a zero adds
   nothing: no test for it, one branch less per step). */
NRT_DEVICE void nrt_acc_add(NRT_GLOBAL nrt_u64 *cell, nrt_u64 v, NRT_GLOBAL nrt_u32 *overflow)
{
#if NRT_ACC_RED
    (void)overflow;
    NRT_ATOMIC_ADD_U64(cell, v);
#else
    nrt_acc_add_checked(cell, v, overflow);
#endif
}

/* Fixed-point units of x at `scale` units per 1, rounded to nearest with one rounding (an
   explicit fused multiply-add: the same bits whatever a compiler would contract). */
NRT_DEVICE nrt_u64 nrt_fixed(float x, float scale)
{
    return (nrt_u64)NRT_FMAF(x, scale, 0.5f);
}

/* Count a packet's nonzero score (hi:lo, 128 bits) in its half-octave bin of hist: bin 2 m for
   [2^m, 1.5 2^m), 2 m + 1 for [1.5 2^m, 2^(m + 1)) (m the leading bit). */
/* The histograms of a cell's tally block. Every packet ends with an increment of a few bins,
   all the lanes of a warp on the same few addresses: on an H200 that costs 17-23 % of the
   weighted packets' kernel (benchmarks/results/h200-2026-12-03b/). Counting in the work
   group's local memory cost more (a barrier at the end holds every block until its longest
   packet ends). */
#define NRT_TAIL_OF(tally) ((tally) + NRT_TALLY_BASE)

NRT_DEVICE void nrt_tail_add(NRT_GLOBAL nrt_u64 *hist, nrt_u64 lo, nrt_u64 hi)
{
    if ((lo | hi) == 0)
        return;
    int m = hi != 0 ? 127 - NRT_CLZ64(hi) : 63 - NRT_CLZ64(lo);
    int next = m == 0 ? 0 : (int)((m - 1 >= 64 ? hi >> (m - 65) : lo >> (m - 1)) & 1UL);
    NRT_ATOMIC_ADD_U64(&hist[2 * m + next], 1UL);
}

/* Flat index (x fastest) of voxel (ix, iy, iz). */
NRT_DEVICE nrt_idx nrt_voxel_index(int ix, int iy, int iz, int nx, int ny)
{
    return (nrt_idx)ix + (nrt_idx)nx * ((nrt_idx)iy + (nrt_idx)ny * (nrt_idx)iz);
}

/* Voxel of a point (clamped into the box). */
NRT_DEVICE void nrt_voxel_of(const float *p, int nx, int ny, int nz, int *ix, int *iy, int *iz)
{
    *ix = min(max((int)floor(p[0] * (float)nx), 0), nx - 1);
    *iy = min(max((int)floor(p[1] * (float)ny), 0), ny - 1);
    *iz = min(max((int)floor(p[2] * (float)nz), 0), nz - 1);
}

/* Distance (box units) from p along d to the exit face of voxel [i h, (i+1) h) on one axis. */
NRT_DEVICE float nrt_face_distance(float p, float d, float inv_d, int i, float h)
{
    /* by selects (the same bits as branching on the sign of d): the face is i + 1 going up, i
       going down; none along d = 0 */
    float t = ((float)(i + (d > 0.0f ? 1 : 0)) * h - p) * inv_d;
    return fabs(d) > 0.0f ? t : NRT_INF_F;
}

/*
 * Cross the face of axis ax (0 x, 1 y, 2 z) into the voxel whose index on that axis is i_next:
 * that axis' index and face distance change (from the flight's start point p along d), the
 * other two stay. By selects: the lanes of a SIMD group step along different axes.
 */
NRT_DEVICE void nrt_cross_face(int ax, int i_next, const float *p, float d_ax, const float *inv_d,
                               float hx, float hy, float hz, int *ix, int *iy, int *iz,
                               float *tx, float *ty, float *tz)
{
    float t_ax = nrt_face_distance(ax == 0 ? p[0] : (ax == 1 ? p[1] : p[2]), d_ax,
                                   ax == 0 ? inv_d[0] : (ax == 1 ? inv_d[1] : inv_d[2]), i_next,
                                   ax == 0 ? hx : (ax == 1 ? hy : hz));
    *ix = ax == 0 ? i_next : *ix;
    *iy = ax == 1 ? i_next : *iy;
    *iz = ax == 2 ? i_next : *iz;
    *tx = ax == 0 ? t_ax : *tx;
    *ty = ax == 1 ? t_ax : *ty;
    *tz = ax == 2 ? t_ax : *tz;
}

#ifndef NRT_POLAR
#define NRT_POLAR 0
#endif
#include "polarization.cl"
/* Stokes images per band of a batch slot besides I: Q and U, and V where the matrix has
   S34 != 0 (Mie) */
#define NRT_STOKES_IMAGES (NRT_POLAR == NRT_POLAR_MIE ? 3 : NRT_POLAR ? 2 : 0)
/* A scattering's new direction (and, with NRT_POLAR, the packet's new Stokes state) */
#if NRT_POLAR
#define NRT_NEW_DIRECTION() nrt_scatter_polarized(&rng, NRT_POLAR, g_b, pol, d, &stokes)
#define NRT_STOKES_STATE (&stokes)
#else
#define NRT_STOKES_STATE 0
#define NRT_NEW_DIRECTION()                                                      \
    do {                                                                         \
        float mu_, sin_theta_;                                                   \
        nrt_sample_hg(g_b, nrt_rng_uniform(&rng), &mu_, &sin_theta_);           \
        nrt_rotate(d, mu_, sin_theta_, 2.0f * NRT_PI_F * nrt_rng_uniform(&rng)); \
    } while (0)
#endif

#if NRT_PEEL
/*
 * Peel-off images (Yusef-Zadeh, Morris & White 1984, ApJ 278, 186): at every scattering the
 * packet's probability per steradian of leaving towards the observer, the Henyey-Greenstein
 * phase function at the angle between its incoming direction and the line of sight times
 * exp(-tau) to the box's edge along that line, is added to the image pixel the scattering
 * point projects to. The image then has the phase function's full angle dependence, which
 * ray marching an isotropic emissivity cannot have.
 *
 * peel[15]: direction to the observer o (3), image axes u and v (3 + 3), centre of pixel
 * (0, 0) (3), pixel size, W, H.
 */

/*
 * NRT_PEEL_AXIS (0, 1, 2; the host sets it where the direction to the observer is that axis,
 * NRT_PEEL_UP 1 where it points to the axis' high end): the density buffer holds, after the
 * nvox densities, each voxel's column to the edge along that axis, h sum of the densities of
 * the voxels beyond it (box units x density, summed in float64 on the host:
 * nebula_rt.transport.line_of_sight.peel_columns). A peel-off's optical depth is then that
 * column and the rest of its own voxel, in O(1) instead of a march across the grid; it differs
 * from the march's sum by float32 rounding (about 1e-7 of tau), which moves a deposit's
 * stochastic rounding at most.
 */
#ifndef NRT_PEEL_AXIS
#define NRT_PEEL_AXIS -1
#endif
#ifndef NRT_PEEL_UP
#define NRT_PEEL_UP 1
#endif

/* Optical depth from x (in voxel ix, iy, iz) along o to the edge of the box. */
NRT_DEVICE float nrt_tau_to_edge(const NRT_GLOBAL float *density, float sig_b, const float *x,
                                 const float *o, int ix, int iy, int iz, int nx, int ny, int nz)
{
#if NRT_PEEL_AXIS >= 0
    (void)o;
    {
        const int i_ax = NRT_PEEL_AXIS == 0 ? ix : (NRT_PEEL_AXIS == 1 ? iy : iz);
        const float h = 1.0f / (float)(NRT_PEEL_AXIS == 0 ? nx : (NRT_PEEL_AXIS == 1 ? ny : nz));
        /* the rest of this voxel along the axis: to its far face, as the march's face distance */
        const float rest = NRT_PEEL_UP ? (float)(i_ax + 1) * h - x[NRT_PEEL_AXIS] : x[NRT_PEEL_AXIS] - (float)i_ax * h;
        const nrt_u64 i = (nrt_u64)nrt_voxel_index(ix, iy, iz, nx, ny);
        const nrt_u64 nvox = (nrt_u64)nx * (nrt_u64)ny * (nrt_u64)nz;
        return sig_b * (density[i] * fmax(rest, 0.0f) + density[nvox + i]);
    }
#endif
    const float hx = 1.0f / (float)nx, hy = 1.0f / (float)ny, hz = 1.0f / (float)nz;
    float inv_o[3] = {1.0f / o[0], 1.0f / o[1], 1.0f / o[2]};
    float t_cur = 0.0f, tau = 0.0f;
    /* face distances kept from step to step, only the stepped axis' formed again (as in
       nrt_trace_packet: the same bits as forming all three every step) */
    float tx = nrt_face_distance(x[0], o[0], inv_o[0], ix, hx);
    float ty = nrt_face_distance(x[1], o[1], inv_o[1], iy, hy);
    float tz = nrt_face_distance(x[2], o[2], inv_o[2], iz, hz);
    nrt_idx idx = nrt_voxel_index(ix, iy, iz, nx, ny);
    const nrt_idx stride_y = (nrt_idx)nx, stride_z = (nrt_idx)nx * (nrt_idx)ny;
    for (;;) {
        float t_next = fmin(tx, fmin(ty, tz));
        tau += sig_b * density[idx] * fmax(0.0f, t_next - t_cur);
        t_cur = fmax(t_cur, t_next);
        /* the stepped axis by selects, as in nrt_trace_packet */
        int ax = (tx <= ty && tx <= tz) ? 0 : ((ty <= tz) ? 1 : 2);
        float o_ax = ax == 0 ? o[0] : (ax == 1 ? o[1] : o[2]);
        int up = o_ax > 0.0f;
        int i_next = (ax == 0 ? ix : (ax == 1 ? iy : iz)) + (up ? 1 : -1);
        if (i_next < 0 || i_next >= (ax == 0 ? nx : (ax == 1 ? ny : nz)))
            return tau;
        nrt_idx stride = ax == 0 ? (nrt_idx)1 : (ax == 1 ? stride_y : stride_z);
        idx = up ? idx + stride : idx - stride;
        nrt_cross_face(ax, i_next, x, o_ax, inv_o, hx, hy, hz, &ix, &iy, &iz, &tx, &ty, &tz);
    }
}


/*
 * An analog packet's peel-off into pixel `pixel`, its light attenuated by atten = exp(-tau) to
 * the box's edge: the phase function's weight into the band's image or, with NRT_POLAR, the
 * light's I, Q and U (nrt_peel_stokes): I into the band's image, Q and U into its two Stokes
 * images (band_stokes: Q, then U, each of W x H pixels, kept apart from every cell's I image so
 * that the intensities stay one checked block). I's deposits are checked adds; Q and U are signed, added as 64-bit two's
 * complement (integer addition modulo 2^64 is exact and associative, so their sums are exact
 * and the same bits in any order). Each is rounded with I's random word, so |its units| <= I's
 * units deposit by deposit, and every partial sum of it lies within +-I's partial sum, which the
 * checked adds keep below 2^63: read as signed 64-bit integers, the sums are exact. Returns the
 * units added to I (the packet's score, nrt_tail_add).
 */
NRT_DEVICE nrt_u64 nrt_peel_deposit(float atten, float g_b, const NRT_GLOBAL float *pol,
                                    const NRT_GLOBAL float *peel, float peel_scale, const float *d,
                                    const nrt_stokes *st, nrt_u64 pixel, NRT_GLOBAL nrt_u64 *band_image,
                                    NRT_GLOBAL nrt_u64 *band_stokes, NRT_GLOBAL nrt_u32 *overflow, nrt_u64 seed,
                                    int band, nrt_u64 photon, int event)
{
    const float o[3] = {peel[0], peel[1], peel[2]};
#if NRT_POLAR
    const float north[3] = {peel[6], peel[7], peel[8]};
    float iquv[4];
    nrt_peel_stokes(NRT_POLAR, g_b, pol, o, north, d, st, iquv);
    const float wgt = iquv[0] * atten;
    if (!(wgt >= 0.0f))
        return 0;
    const nrt_u64 r = nrt_round_word(seed, (nrt_u64)band, photon, (nrt_u64)event, 0);
    const nrt_u64 v = nrt_fixed_round(wgt, peel_scale, r);
    nrt_acc_add_checked(&band_image[pixel], v, overflow);
    const nrt_u64 pixels = (nrt_u64)peel[13] * (nrt_u64)peel[14];
    for (int k = 0; k < NRT_STOKES_IMAGES; ++k) {
        nrt_u64 n = nrt_fixed_round(fabs(iquv[k + 1]) * atten, peel_scale, r);
        if (n != 0)
            NRT_ATOMIC_ADD_U64(&band_stokes[(nrt_u64)k * pixels + pixel], iquv[k + 1] < 0.0f ? (nrt_u64)0 - n : n);
    }
    return v;
#else
    (void)pol, (void)st, (void)band_stokes;
    float mu = d[0] * o[0] + d[1] * o[1] + d[2] * o[2];
    float wgt = nrt_hg_phase(g_b, mu) * atten;
    if (!(wgt >= 0.0f))
        return 0;
    nrt_u64 v = nrt_fixed_stochastic(wgt, peel_scale, seed, (nrt_u64)band, photon, (nrt_u64)event, 0);
    nrt_acc_add_checked(&band_image[pixel], v, overflow);
    return v;
#endif
}

/* Peel-off of an analog packet at x in voxel (ix, iy, iz) (nrt_peel_deposit). */
NRT_DEVICE nrt_u64 nrt_peel(const NRT_GLOBAL float *density, float sig_b, float g_b,
                            const NRT_GLOBAL float *pol, const NRT_GLOBAL float *peel, float peel_scale,
                            const float *x, const float *d, const nrt_stokes *st, int ix, int iy, int iz,
                            int nx, int ny, int nz, NRT_GLOBAL nrt_u64 *band_image, NRT_GLOBAL nrt_u64 *band_stokes,
                            NRT_GLOBAL nrt_u32 *overflow, nrt_u64 seed, int band, nrt_u64 photon, int event)
{
    nrt_u64 pixel;
    if (!nrt_peel_pixel(peel, x, &pixel))
        return 0;
    const float o[3] = {peel[0], peel[1], peel[2]};
    float atten = exp(-nrt_tau_to_edge(density, sig_b, x, o, ix, iy, iz, nx, ny, nz));
    return nrt_peel_deposit(atten, g_b, pol, peel, peel_scale, d, st, pixel, band_image, band_stokes, overflow, seed,
                            band, photon, event);
}
#endif

/* The emitting star: star s with probability cdf[s] - cdf[s - 1] (one uniform, drawn only
   when there are several stars, so a one-star scene's stream starts at the direction). */
NRT_DEVICE int nrt_choose_star(nrt_rng *rng, const NRT_GLOBAL float *cdf, int n_stars)
{
    int s = 0;
    if (n_stars > 1) {
        float u = nrt_rng_uniform(rng);
        while (s < n_stars - 1 && u >= cdf[s])
            ++s;
    }
    return s;
}

/*
 * Where a packet's tallies and its deposits into its star's voxel go: global memory, or, for
 * the packets of a work group's home cell (NRT_GROUP_TALLY), the group's local sums.
 */
typedef struct {
    NRT_GLOBAL nrt_u64 *tally;  /* this cell's 4 global tallies */
    NRT_LOCAL nrt_u64 *l_tally; /* the group's 4 local tallies (home cell) */
    NRT_LOCAL nrt_u64 *l_hot;   /* the group's sums for this packet's star block (home cell) */
    NRT_LOCAL nrt_u64 *l_hot_sq; /* NRT_PACKET_SQ: the same for the squares */
    int hot_x, hot_y, hot_z;    /* the block's lowest voxel (NRT_NO_HOT: no block) */
    int home;                   /* the packet belongs to the group's home cell */
} nrt_sink;

/*
 * v added to a 64-bit cell of local memory as two 32-bit atomic adds, the low word's carry
 * passed to the high word by the add that made it (the same sum, modulo 2^64, once every add
 * is done): GPUs have no 64-bit atomic add in shared memory (CUDA emulates one with a
 * compare-and-swap loop, which the lanes of a warp adding to one cell run once per lane).
 * The cells are read as 64-bit words only after the group's barrier. nrt_local_add adds the
 * high word unconditionally (straight-line code); nrt_local_count adds 1, the high word only
 * on a carry.
 */
#if defined(__OPENCL_VERSION__) && !defined(__ENDIAN_LITTLE__)
#define nrt_local_add(cell, v) NRT_ATOMIC_ADD_U64_LOCAL(cell, v)
#define nrt_local_count(cell) NRT_ATOMIC_ADD_U64_LOCAL(cell, 1UL)
#else
NRT_DEVICE void nrt_local_add(NRT_LOCAL nrt_u64 *cell, nrt_u64 v)
{
    NRT_LOCAL nrt_u32 *w = (NRT_LOCAL nrt_u32 *)cell; /* little-endian: the low word first */
    nrt_u32 lo = (nrt_u32)v;
    nrt_u32 old = NRT_ATOMIC_ADD_U32_LOCAL(w, lo);
    NRT_ATOMIC_ADD_U32_LOCAL(w + 1, (nrt_u32)(v >> 32) + (nrt_u32)(old + lo < old));
}

NRT_DEVICE void nrt_local_count(NRT_LOCAL nrt_u64 *cell)
{
    NRT_LOCAL nrt_u32 *w = (NRT_LOCAL nrt_u32 *)cell;
    if (NRT_ATOMIC_ADD_U32_LOCAL(w, 1u) == 0xFFFFFFFFu)
        NRT_ATOMIC_ADD_U32_LOCAL(w + 1, 1u);
}
#endif

NRT_DEVICE void nrt_count(const nrt_sink *k, int which)
{
#if NRT_GROUP_TALLY
    if (k->home) {
        nrt_local_count(&k->l_tally[which]);
        return;
    }
#endif
    NRT_ATOMIC_ADD_U64(&k->tally[which], 1UL);
}

/* The cell of voxel (ix, iy, iz) in the packet's star block, or -1 outside it (or without one). */
NRT_DEVICE int nrt_hot_cell(const nrt_sink *k, int ix, int iy, int iz)
{
#if NRT_GROUP_TALLY
    /* unsigned: one compare per axis for both ends of the block */
    nrt_u32 dx = (nrt_u32)(ix - k->hot_x), dy = (nrt_u32)(iy - k->hot_y), dz = (nrt_u32)(iz - k->hot_z);
    if (dx < (nrt_u32)NRT_HOT_SIDE && dy < (nrt_u32)NRT_HOT_SIDE && dz < (nrt_u32)NRT_HOT_SIDE)
        return (int)(dx + (nrt_u32)NRT_HOT_SIDE * (dy + (nrt_u32)NRT_HOT_SIDE * dz));
#else
    (void)k, (void)ix, (void)iy, (void)iz;
#endif
    return -1;
}

/* Deposit v into voxel idx of this band's slot (hot: its cell in the star block kept locally,
   nrt_hot_cell, or -1). */
NRT_DEVICE void nrt_deposit(const nrt_sink *k, NRT_GLOBAL nrt_u64 *band_acc, nrt_idx idx, int hot,
                            nrt_u64 v, NRT_GLOBAL nrt_u32 *overflow)
{
#if NRT_GROUP_TALLY
    if (hot >= 0) {
        nrt_local_add(&k->l_hot[hot], v);
        return;
    }
#else
    (void)hot;
#endif
#if NRT_PROBE_DEPOSIT == 1
    return;
#elif NRT_PROBE_DEPOSIT == 2
    if ((v >> 28) != 0)
        NRT_ATOMIC_ADD_U32((NRT_GLOBAL nrt_u32 *)band_acc + idx, (nrt_u32)(v >> 28));
    return;
#elif NRT_PROBE_DEPOSIT == 3
    if (v != 0)
        NRT_ATOMIC_ADD_U64(&band_acc[idx ^ ((nrt_idx)1 << NRT_PROBE_MIRROR_BIT)], (v >> 16) * (v >> 16));
#endif
    nrt_acc_add(&band_acc[idx], v, overflow);
}

/* nrt_deposit into voxel (ix, iy, iz) (flat index idx), the star block's test inline (no
   cell of -1 to select and test again) */
NRT_DEVICE void nrt_deposit_voxel(const nrt_sink *k, NRT_GLOBAL nrt_u64 *band_acc, nrt_idx idx, int ix, int iy,
                                  int iz, nrt_u64 v, NRT_GLOBAL nrt_u32 *overflow)
{
#if NRT_GROUP_TALLY
    nrt_u32 dx = (nrt_u32)(ix - k->hot_x), dy = (nrt_u32)(iy - k->hot_y), dz = (nrt_u32)(iz - k->hot_z);
    if (dx < (nrt_u32)NRT_HOT_SIDE && dy < (nrt_u32)NRT_HOT_SIDE && dz < (nrt_u32)NRT_HOT_SIDE) {
        nrt_local_add(&k->l_hot[dx + (nrt_u32)NRT_HOT_SIDE * (dy + (nrt_u32)NRT_HOT_SIDE * dz)], v);
        return;
    }
#else
    (void)ix, (void)iy, (void)iz;
#endif
    nrt_deposit(k, band_acc, idx, -1, v, overflow);
}

/*
 * NRT_PACKET_SQ: add the square of x (a packet's deposits during one visit of voxel idx) to the
 * voxel's cell of band_sq, in units of 2^shift, rounded to nearest (the host's choice of shift
 * keeps every cell below 2^64 whatever the packets do, so the adds need no check).
 */
NRT_DEVICE void nrt_square(const nrt_sink *k, NRT_GLOBAL nrt_u64 *band_sq, nrt_idx idx, int hot, nrt_u64 x,
                           int shift, NRT_GLOBAL nrt_u64 *band_acc)
{
    (void)band_acc; /* NRT_PROBE_SQ 2 only */
    if (x == 0)
        return;
    nrt_u64 lo = x * x, hi = NRT_MULHI64(x, x);
    nrt_u64 v = shift == 0 ? lo : ((hi << (64 - shift)) | (lo >> shift)) + ((lo >> (shift - 1)) & 1UL);
    if (v == 0)
        return;
#if NRT_GROUP_TALLY
    if (hot >= 0) {
        NRT_ATOMIC_ADD_U64_LOCAL(&k->l_hot_sq[hot], v);
        return;
    }
#else
    (void)hot;
#endif
#if NRT_PROBE_SQ == 1
    return;
#elif NRT_PROBE_SQ == 2
    NRT_ATOMIC_ADD_U64(&band_acc[idx ^ 1], v);
    return;
#endif
    NRT_ATOMIC_ADD_U64(&band_sq[idx], v);
}

/* A deposit of the walk. With NRT_PACKET_SQ the packet also sums its deposits during the
   visit of its voxel; NRT_VISIT_END adds the square of that sum as the packet steps into
   another voxel or ends. The visit, not the deposit, is the unit, so where a walk stops for
   the transport by regions (as it steps into another voxel) changes no square. A packet that
   comes back to a voxel later makes a second visit, squared apart (the variance then misses
   the two visits' covariance: small where packets seldom scatter back into a voxel they
   left, see docs/physics.md). */
#if NRT_PACKET_SQ
#define NRT_SCORE(i_, v_)                                                        \
    do {                                                                         \
        nrt_u64 v__ = (v_);                                                      \
        run += v__;                                                              \
        nrt_deposit(sink, band_acc, (i_), nrt_hot_cell(sink, ix, iy, iz), v__, overflow); \
    } while (0)
#define NRT_VISIT_END()                                                          \
    do {                                                                         \
        nrt_square(sink, band_sq, idx, nrt_hot_cell(sink, ix, iy, iz), run, sq_shift, band_acc); \
        run = 0;                                                                 \
    } while (0)
#elif defined(NRT_PROBE_HOT_HALF)
#define NRT_SCORE(i_, v_)                                                        \
    do {                                                                         \
        if (max(max(ix - NRT_PROBE_HOT_X, NRT_PROBE_HOT_X - ix),                \
                max(max(iy - NRT_PROBE_HOT_Y, NRT_PROBE_HOT_Y - iy),            \
                    max(iz - NRT_PROBE_HOT_Z, NRT_PROBE_HOT_Z - iz))) > NRT_PROBE_HOT_HALF) \
            nrt_deposit(sink, band_acc, (i_), nrt_hot_cell(sink, ix, iy, iz), (v_), overflow); \
    } while (0)
#define NRT_VISIT_END() ((void)0)
#elif !NRT_TREE
/* (the deposits of a visit summed in the packet, added once as it leaves the voxel: an
   interaction's deposit joins the visit's last one; the same integer sums) */
#define NRT_MERGE 1
#define NRT_SCORE(i_, v_) (pend += (v_))
#define NRT_VISIT_END()                                                          \
    do {                                                                         \
        nrt_deposit_voxel(sink, band_acc, idx, ix, iy, iz, pend, overflow);      \
        pend = 0;                                                                \
    } while (0)
#else
/* (every deposit and square is of the current voxel: ix, iy, iz are idx's) */
#define NRT_SCORE(i_, v_) nrt_deposit_voxel(sink, band_acc, (i_), ix, iy, iz, (v_), overflow)
#define NRT_VISIT_END() ((void)0)
#endif
#ifndef NRT_MERGE
#define NRT_MERGE 0
#endif
/* An analog packet's interaction: absorbed with probability 1 - albedo, or terminated past
   max_scatterings (each ends the walk, counted), else it scatters once more (the grid's walk
   and the tree's, kernels/tree.cl). */
#define NRT_SCATTER_OR_END()                                                     \
    do {                                                                         \
        if (nrt_rng_uniform(&rng) >= alb_b) {                                    \
            NRT_VISIT_END();                                                     \
            nrt_count(sink, 1);                                                  \
            NRT_TAIL_END();                                                      \
            return 0;                                                            \
        }                                                                        \
        if (scatterings >= max_scatterings) {                                    \
            NRT_VISIT_END();                                                     \
            nrt_count(sink, 3);                                                  \
            NRT_TAIL_END();                                                      \
            return 0;                                                            \
        }                                                                        \
        ++scatterings;                                                           \
    } while (0)
/* an analog packet ends: its peel-off score into the image's heavy-tail histogram */
#if NRT_PEEL
#define NRT_TAIL_END() nrt_tail_add(NRT_TAIL_OF(sink->tally), peel_score, 0UL)
#else
#define NRT_TAIL_END() ((void)peel_score)
#endif

/*
 * Transport by regions (NRT_REGIONS; large grids): the grid is cut into cubes of 2^shift
 * voxels a side, and a packet's walk stops where it steps into another cube. Its state
 * (nrt_packet) is written to memory and the host sorts the stopped packets by (cell, region)
 * before the next pass resumes them: the packets traced side by side then deposit into one
 * region of one slot, whose cells and density stay in the GPU's L2 cache, instead of
 * scattering their atomics over a grid many times the cache's size. The walk resumes with
 * exactly the state it stopped with (the random stream included), and integer deposits add
 * alike in any order, so the result is the same bits as tracing each packet in one go.
 * A pass also starts new packets in the state slots of those that ended (nrt_pass_item), so
 * that passes stay full while the launch has new packets: a region's packets per pass, and
 * with them the deposits that hit L2, would otherwise dwindle pass by pass.
 * region_shift 31 never stops (the last pass of a launch: its few packets run to the end).
 */
#ifndef NRT_REGIONS
#define NRT_REGIONS 0
#endif
#define NRT_NO_REGIONS 31
/* the key of no packet (nothing to resume) */
#define NRT_NO_KEY 0xFFFFFFFFFFFFFFFFUL
/* the bin of a free state slot (its packet ended): the counting sort puts these keys after
   every stopped packet's, and the next pass starts new packets in those slots */
#define NRT_FREE_BIN 0xFFFFFFFEu
#define NRT_KEY_LOW 0xFFFFFFFFUL
/* nrt_packet.item: photon number (< 2^53) | band of the launch << 56 */
#define NRT_ITEM_BAND_SHIFT 56

/* Bin of a stopped packet: its cell (batch slot and band of the launch), then its region
   (regions numbered x fastest, rx x ry x rz of them). */
NRT_DEVICE nrt_u32 nrt_region_bin(nrt_u64 cell, int ix, int iy, int iz, int nx, int ny, int nz, int shift)
{
    nrt_u32 rx = (nrt_u32)((nx + (1 << shift) - 1) >> shift), ry = (nrt_u32)((ny + (1 << shift) - 1) >> shift);
    nrt_u32 rz = (nrt_u32)((nz + (1 << shift) - 1) >> shift);
    nrt_u32 r = (nrt_u32)(ix >> shift) + rx * ((nrt_u32)(iy >> shift) + ry * (nrt_u32)(iz >> shift));
    return (nrt_u32)cell * (rx * ry * rz) + r;
}

/* The random stream as a stopped packet left it: the same block of draws and position. */
NRT_DEVICE void nrt_rng_resume(nrt_rng *r, nrt_u64 seed, nrt_u64 band, nrt_u64 photon, int block, int pos)
{
    nrt_rng_init(r, seed, band, photon);
    if (pos < 8 && block > 0) {
        r->block = (nrt_u64)(block - 1);
        r->pos = 8;
        nrt_rng_u32(r); /* draws block - 1 again (and sets block) */
    }
    r->block = (nrt_u64)block;
    r->pos = pos;
}

#if NRT_REGIONS
/*
 * Work item it of a pass by regions. Items [0, n_resume) resume the stopped packets whose keys
 * (bin << 32 | state slot) lead order[]; the next n_fresh start the current chunk's packets
 * fresh0, fresh0 + 1, ... (photon_start + t % count, band t / count of the chunk's item t, in
 * the emission order emit[] with NRT_SORTED), in the free state slots listed in order[] after
 * the stopped keys (n_free of them), then in the never used ones from hwm on. Items past n_fresh
 * up to n_free only pass their free slot on to the next pass (returns 0).
 */
NRT_DEVICE int nrt_pass_item(nrt_u64 it, const NRT_GLOBAL nrt_u64 *order, const NRT_GLOBAL nrt_u64 *emit,
                             const NRT_GLOBAL nrt_packet *states, nrt_u64 n_resume, nrt_u64 n_fresh,
                             nrt_u64 fresh0, nrt_u64 n_free, nrt_u64 hwm, nrt_u64 photon_start,
                             nrt_u64 count, nrt_u64 *photon, int *lband, nrt_u64 *sl, int *fresh)
{
    if (it < n_resume) {
        *sl = order[it] & NRT_KEY_LOW;
        nrt_u64 item = states[*sl].item;
        *photon = item & ((1UL << NRT_ITEM_BAND_SHIFT) - 1UL);
        *lband = (int)(item >> NRT_ITEM_BAND_SHIFT);
        *fresh = 0;
        return 1;
    }
    nrt_u64 j = it - n_resume;
    *sl = j < n_free ? (order[n_resume + j] & NRT_KEY_LOW) : hwm + (j - n_free);
    if (j >= n_fresh)
        return 0;
    nrt_u64 t = NRT_SORTED ? (emit[fresh0 + j] & NRT_KEY_LOW) : fresh0 + j;
    *lband = (int)(t / count);
    *photon = photon_start + t % count;
    *fresh = 1;
    return 1;
}
#endif

/* The walk's arguments, the grid's (below) and the tree's (tree.cl) alike. */
#define NRT_TRACE_PACKET_PARAMS                                                                         \
    const NRT_GLOBAL float *density, float sig_b, float alb_b, float g_b, const NRT_GLOBAL float *stars, \
        const NRT_GLOBAL float *cdf, int nx, int ny, int nz, int n_stars, nrt_u64 seed, int band,        \
        nrt_u64 photon, int max_scatterings, float track_scale, NRT_GLOBAL nrt_u64 *band_acc,            \
        nrt_sink *sink, NRT_GLOBAL nrt_u32 *overflow, const NRT_GLOBAL float *peel, float peel_scale,    \
        NRT_GLOBAL nrt_u64 *band_image, const NRT_GLOBAL nrt_packet *resume, NRT_GLOBAL nrt_packet *save, \
        int region_shift, nrt_u64 item, NRT_GLOBAL nrt_u64 *band_sq, int sq_shift, nrt_u64 cells,           \
        const NRT_GLOBAL float *pol, NRT_GLOBAL nrt_u64 *band_stokes, NRT_GLOBAL float *stokes_slot

#ifndef NRT_TREE
#define NRT_TREE 0
#endif
#if NRT_TREE
#if NRT_REGIONS || NRT_SORTED || (defined(NRT_PEEL_AXIS) && NRT_PEEL_AXIS >= 0)
#error "a tree is traced without regions, sorted emission or peel-off columns"
#endif
#include "tree.cl"
#else
/*
 * Trace one packet of one band to its end, or (NRT_REGIONS) until it steps into another
 * region: then its state goes to *save and the function returns 1 (else 0). resume: the
 * state of a stopped packet to go on from (0: emit a new one). Deposits go to band_acc (this
 * batch's slot, this band), the outcome to tally 1..3 of the sink (emitted is counted by the
 * caller).
 */
NRT_DEVICE int nrt_trace_packet(NRT_TRACE_PACKET_PARAMS)
{
    (void)cells; /* (NRT_TREE's walk: where the tree's nodes start in the density buffer) */
    nrt_u64 peel_score = 0; /* NRT_PEEL: the packet's peel-off units (heavy-tail diagnostic) */
#if NRT_MERGE
    nrt_u64 pend = 0; /* the packet's deposits during the visit of its voxel under way */
#endif
#if NRT_PACKET_SQ
    nrt_u64 run = 0; /* the packet's deposits during the visit of its voxel under way */
#else
    (void)band_sq;
    (void)sq_shift;
#endif
    nrt_rng rng;
#if NRT_POLAR
    nrt_stokes stokes; /* the packet's polarization */
#else
    (void)pol;
#endif
    (void)band_stokes, (void)stokes_slot; /* (NRT_PEEL with NRT_POLAR; NRT_REGIONS with NRT_POLAR) */
    const float hx = 1.0f / (float)nx, hy = 1.0f / (float)ny, hz = 1.0f / (float)nz;
    int ix, iy, iz, scatterings;
    nrt_idx idx;
    float d[3], inv_d[3], p0[3], tau, t_cur, tx, ty, tz, rho;
#if NRT_REGIONS
    if (resume) {
        nrt_packet q = *resume;
        nrt_rng_resume(&rng, seed, (nrt_u64)band, photon, q.rng_block, q.rng_pos);
        p0[0] = q.p0[0], p0[1] = q.p0[1], p0[2] = q.p0[2];
        d[0] = q.d[0], d[1] = q.d[1], d[2] = q.d[2];
        t_cur = q.t_cur, tau = q.tau;
        ix = q.ix, iy = q.iy, iz = q.iz, scatterings = q.scatterings;
        peel_score = q.peel_score;
#if NRT_POLAR
        stokes.q = stokes_slot[0], stokes.u = stokes_slot[1], stokes.v = stokes_slot[2];
        stokes.e[0] = stokes_slot[3], stokes.e[1] = stokes_slot[4], stokes.e[2] = stokes_slot[5];
#endif
        /* 1 / d and the voxel's face distances by the expressions the walk formed them with
           (the same bits; 24 bytes less state per stopped packet) */
        inv_d[0] = 1.0f / d[0], inv_d[1] = 1.0f / d[1], inv_d[2] = 1.0f / d[2];
        tx = nrt_face_distance(p0[0], d[0], inv_d[0], ix, hx);
        ty = nrt_face_distance(p0[1], d[1], inv_d[1], iy, hy);
        tz = nrt_face_distance(p0[2], d[2], inv_d[2], iz, hz);
        idx = nrt_voxel_index(ix, iy, iz, nx, ny);
        rho = NRT_RHO(density, idx);
    } else
#endif
    {
        nrt_rng_init(&rng, seed, (nrt_u64)band, photon);
        int s = nrt_choose_star(&rng, cdf, n_stars);
        p0[0] = stars[4 * s], p0[1] = stars[4 * s + 1], p0[2] = stars[4 * s + 2];
        nrt_voxel_of(p0, nx, ny, nz, &ix, &iy, &iz);
        idx = nrt_voxel_index(ix, iy, iz, nx, ny);
#if NRT_GROUP_TALLY
        if (sink->home && s < NRT_HOT_STARS) {
            sink->hot_x = ix - NRT_HOT_HALF, sink->hot_y = iy - NRT_HOT_HALF, sink->hot_z = iz - NRT_HOT_HALF;
            sink->l_hot += s * NRT_HOT_CELLS;
#if NRT_PACKET_SQ
            sink->l_hot_sq += s * NRT_HOT_CELLS;
#endif
        }
#endif
        nrt_sample_isotropic(&rng, d);
#if NRT_POLAR
        nrt_stokes_unpolarized(d, &stokes);
#endif

        scatterings = 0;
        /* One loop, one voxel step per iteration; an interaction ends a flight and starts the next
           inside the same iteration. Nesting a flight loop inside a scattering loop made every lane
           of a SIMD group wait at the end of each flight for the group's longest flight; here a lane
           whose flight ends scatters and steps on at once (same random numbers in the same order,
           so the same bits). */
        tau = nrt_sample_tau(&rng);
        inv_d[0] = 1.0f / d[0], inv_d[1] = 1.0f / d[1], inv_d[2] = 1.0f / d[2];
        /* Distances are measured from the flight's start point p0: each face crossing is
           ((face index) h - p0) / d, computed afresh, so float32 rounding does not accumulate
           along the flight (advancing the position voxel by voxel drifted the transverse
           coordinates by up to k 2^-25 after k voxels), and the segment lengths telescope to
           the flight's length. */
        t_cur = 0.0f;
        rho = NRT_RHO(density, idx);
        /* The current voxel's face distances are kept from step to step: a step changes the voxel
           on one axis only, so only that axis' distance is formed again (by the same expression,
           so the same bits as forming all three every step), and the flat index moves by that
           axis' stride. */
        tx = nrt_face_distance(p0[0], d[0], inv_d[0], ix, hx);
        ty = nrt_face_distance(p0[1], d[1], inv_d[1], iy, hy);
        tz = nrt_face_distance(p0[2], d[2], inv_d[2], iz, hz);
    }
    for (;;) {
        float t_next = fmin(tx, fmin(ty, tz));
        float seg = fmax(0.0f, t_next - t_cur);
        /* the neighbour across the nearest face (ties: x, then y), by selects rather than
           branches: the lanes of a SIMD group step along different axes */
        int on_x = tx <= ty && tx <= tz;
        int on_y = !on_x && ty <= tz;
        int on_z = !on_x && !on_y;
        float d_ax = on_x ? d[0] : (on_y ? d[1] : d[2]);
        int up = d_ax > 0.0f;
        int i_next = (on_x ? ix : (on_y ? iy : iz)) + (up ? 1 : -1);
        /* (unsigned: below 0 or past the last voxel in one compare) */
        int leaving = (nrt_u32)i_next >= (nrt_u32)(on_x ? nx : (on_y ? ny : nz));
        int jx = on_x ? i_next : ix, jy = on_y ? i_next : iy, jz = on_z ? i_next : iz;
        nrt_idx jdx = leaving ? idx : nrt_voxel_index(jx, jy, jz, nx, ny);
#if NRT_PREFETCH
        float rho_next = NRT_RHO(density, jdx);
#endif
        float sigma = sig_b * rho;
        float tau_seg = sigma * seg;
        int interact = sigma > 0.0f && tau_seg >= tau;
        if (interact) {
            /* the interaction happens inside this voxel */
            float t = tau / sigma;
#if NRT_TRACK_LENGTH
            NRT_SCORE(idx, nrt_fixed(t, track_scale));
#endif
#if NRT_COLLISION
            NRT_SCORE(idx, 1UL);
#endif
            float t_int = t_cur + t;
            p0[0] = p0[0] + d[0] * t_int;
            p0[1] = p0[1] + d[1] * t_int;
            p0[2] = p0[2] + d[2] * t_int;
            /* scatter with probability albedo (analog Russian roulette), else absorbed */
            NRT_SCATTER_OR_END();
#if NRT_PEEL
            peel_score += nrt_peel(density, sig_b, g_b, pol, peel, peel_scale, p0, d, NRT_STOKES_STATE,
                                   ix, iy, iz, nx, ny, nz, band_image, band_stokes, overflow, seed, band, photon,
                                   scatterings);
#endif
            NRT_NEW_DIRECTION();
            /* the next flight starts here, in the same voxel */
            tau = nrt_sample_tau(&rng);
            inv_d[0] = 1.0f / d[0];
            inv_d[1] = 1.0f / d[1];
            inv_d[2] = 1.0f / d[2];
            t_cur = 0.0f;
            tx = nrt_face_distance(p0[0], d[0], inv_d[0], ix, hx);
            ty = nrt_face_distance(p0[1], d[1], inv_d[1], iy, hy);
            tz = nrt_face_distance(p0[2], d[2], inv_d[2], iz, hz);
            continue;
        }
#if NRT_TRACK_LENGTH
        NRT_SCORE(idx, nrt_fixed(seg, track_scale));
#endif
        tau -= tau_seg;
        t_cur = fmax(t_cur, t_next);
        if (leaving) {
            NRT_VISIT_END();
            nrt_count(sink, 2);
            NRT_TAIL_END();
            return 0;
        }
#if NRT_REGIONS
        /* the voxel index on the stepped axis changes its region (shift 31: never) */
        int crossing = ((i_next ^ (on_x ? ix : (on_y ? iy : iz))) >> region_shift) != 0;
#endif
        NRT_VISIT_END();
        idx = jdx;
        {
            /* into the neighbour: only the stepped axis' face distance is formed again */
            float t_ax = nrt_face_distance(on_x ? p0[0] : (on_y ? p0[1] : p0[2]), d_ax,
                                           on_x ? inv_d[0] : (on_y ? inv_d[1] : inv_d[2]), i_next,
                                           on_x ? hx : (on_y ? hy : hz));
            ix = jx, iy = jy, iz = jz;
            tx = on_x ? t_ax : tx;
            ty = on_y ? t_ax : ty;
            tz = on_z ? t_ax : tz;
        }
#if NRT_REGIONS
        if (crossing) {
            nrt_packet q;
            q.p0[0] = p0[0], q.p0[1] = p0[1], q.p0[2] = p0[2];
            q.d[0] = d[0], q.d[1] = d[1], q.d[2] = d[2];
            q.t_cur = t_cur, q.tau = tau;
            q.ix = ix, q.iy = iy, q.iz = iz, q.scatterings = scatterings;
            q.rng_block = (int)rng.block, q.rng_pos = rng.pos;
            q.item = item;
            q.peel_score = peel_score;
            *save = q;
#if NRT_POLAR
            stokes_slot[0] = stokes.q, stokes_slot[1] = stokes.u, stokes_slot[2] = stokes.v;
            stokes_slot[3] = stokes.e[0], stokes_slot[4] = stokes.e[1], stokes_slot[5] = stokes.e[2];
#endif
            return 1;
        }
#endif
#if NRT_PREFETCH
        rho = rho_next;
#else
        rho = NRT_RHO(density, idx);
#endif
    }
}

#endif /* NRT_TREE */

#if NRT_BIASED
/*
 * Weighted packets (transport.method = "biased") for optically thick dust.
 *
 * A packet carries a weight W, an unsigned 128-bit integer in units of 2^-96 of its emitted
 * energy (NRT_W0 = 2^96), and every change of W is an integer operation whose pieces add back
 * exactly. Every flight is biased; with tau_p the optical depth from the packet to the box's
 * edge along its direction:
 *   - forced scattering: the part W e^-tau_p that would escape is tallied as escaped, the rest
 *     interacts inside the grid (Cashwell & Everett 1959);
 *   - composite biasing (Baes et al. 2016, A&A 590, A55; SKIRT 9's path-length stretching):
 *     the interaction depth is drawn from q = xi p + (1 - xi) / tau_p, p the exponential
 *     truncated to [0, tau_p], and W is multiplied by p / q (at most 1 / xi); the weight this
 *     adds or removes goes to the signed "biasing" tally;
 *   - implicit capture: the interaction absorbs W (1 - albedo) (tallied as absorbed) and
 *     scatters the rest;
 *   - weight windows (importance splitting and Russian roulette; MCNP's weight windows, Booth
 *     1982; Cooper & Larsen 2001): after each scattering the packet's weight is held against
 *     the window of its voxel, W_c = W0 e^-(rate x depth): depth (window[], per voxel) is the
 *     least optical depth of the reference band from a star (nebula_rt.transport.importance), rate
 *     (optics[4 b + 3]) the band's diffusion decay rate times its extinction factor, so W_c
 *     falls as the light field does in thick dust. Above NRT_WINDOW_HIGH W_c the packet is
 *     split into n = W / W_c copies (at most NRT_SPLIT_MAX) that share W exactly; below
 *     NRT_WINDOW_LOW W_c it survives with probability W / W_c at weight W_c, else ends (the
 *     weight created or removed goes to the biasing tally). So as many packets reach optical
 *     depth 60 as leave the star, each carrying e^-60 of its light, where analog packets
 *     arrive with probability e^-60 and path-length stretching alone samples the many-times
 *     scattered light as a rare event.
 * A copy is traced after its packet, depth first: the copies still to run wait on a stack of
 * NRT_SPLIT_DEPTH levels (a level: one split's state and how many copies are left); a packet
 * on a full stack, or one whose packet has made NRT_SPLIT_BUDGET copies, is not split (its
 * weight stays; unbiased, only less efficient). Copy j of a
 * packet (j = 1, 2, ... in the order the copies are made) draws its random numbers from
 * stream j of the packet's Philox counter (nebula_common.h), so a packet's whole tree is the
 * same bits on every device, thread order and number of ranks.
 * So emitted = absorbed + escaped + terminated + biasing holds bit for bit per packet, and the
 * biasing tally's expectation is zero. NRT_FORCED_FLIGHTS (a test option) limits the forced
 * and stretched flights to a packet's first few, the later ones analog (exponential path,
 * absorbed or scattered with probability albedo).
 *
 * Estimators: on a forced flight the track-length one deposits the flight's expected track
 * length, W e^-tau(s) integrated over every voxel of the ray to the edge (exact per voxel:
 * e^-tau0 (1 - e^-sigma L) / sigma), formed on the walk that finds tau_p; on an analog flight
 * W times the path. The collision one deposits W at every interaction. The peel-off image
 * uses W after the absorption. Cells, images and tallies are 128-bit (two 64-bit words, low
 * first) so that weights down to about e^-60 of a packet keep their relative precision while
 * the sums stay exact integers in any order.
 */
#ifndef NRT_BIAS_XI
#define NRT_BIAS_XI 0.5f
#endif
#ifndef NRT_FORCED_FLIGHTS
#define NRT_FORCED_FLIGHTS 0x7FFFFFFF
#endif
/* the uniform component's share per unit of absorption: a packet makes about 1 / (1 - albedo)
   flights, and each multiplies its weight's variance by about 1 + share (1 - albedo), so the
   product stays bounded (about e^share) at every albedo; the uniform spreads the interactions
   evenly in optical depth, which a peel-off from a thick layer wants */
#ifndef NRT_UNIFORM_SHARE
#define NRT_UNIFORM_SHARE 0.5f
#endif
#ifndef NRT_STRETCH_MAX
#define NRT_STRETCH_MAX 0.9f
#endif
#ifndef NRT_WINDOW_HIGH
#define NRT_WINDOW_HIGH 3.0f
#endif
#ifndef NRT_WINDOW_LOW
#define NRT_WINDOW_LOW 0.25f
#endif
#ifndef NRT_SPLIT_MAX
#define NRT_SPLIT_MAX 64
#endif
#ifndef NRT_SPLIT_DEPTH
#define NRT_SPLIT_DEPTH 48
#endif
#ifndef NRT_SPLIT_BUDGET
#define NRT_SPLIT_BUDGET 1024 /* copies per packet at most: a safety valve, see above */
#endif
/* the windows stop falling at 2^-88 of a packet (e^-61): weights there are a few hundred
   units, whose integer products are rounded stochastically (nrt_u128_times_dither), so they
   stay unbiased */
#define NRT_WINDOW_FLOOR 3.2311742677852644e-27f
/* A forced flight's walk goes on past this optical depth only while its remaining weight is
   within e^-NRT_TAU_CUT of the windows on its way (nrt_forced_walk); the part of the weight
   that would fly farther goes to the biasing tally (removed: at most e^-30 = 9e-14 of what
   the windows expect there, below float32's resolution of every factor a weight takes). In
   thick dust the walk to the box's edge is the forced flight's cost. */
#ifndef NRT_TAU_CUT
#define NRT_TAU_CUT 30.0f
#endif
#define NRT_W0_HI 4294967296UL         /* W0 = 2^96: high word 2^32 */
#define NRT_W_CAP_HI 549755813888UL    /* weights are kept below 2^103 (high word 2^39) */
#define NRT_TWO64_F 18446744073709551616.0f
#define NRT_TWO_M64_F 5.42101086242752217e-20f
#define NRT_TWO_M96_F 1.26217744835361888e-29f

typedef struct {
    nrt_u64 lo, hi;
} nrt_u128;

NRT_DEVICE nrt_u128 nrt_u128_of(nrt_u64 lo, nrt_u64 hi)
{
    nrt_u128 r;
    r.lo = lo;
    r.hi = hi;
    return r;
}

NRT_DEVICE nrt_u128 nrt_u128_add(nrt_u128 a, nrt_u128 b)
{
    nrt_u128 r;
    r.lo = a.lo + b.lo;
    r.hi = a.hi + b.hi + (r.lo < a.lo ? 1UL : 0UL);
    return r;
}

/* a - b modulo 2^128 (a signed difference as the tallies hold it) */
NRT_DEVICE nrt_u128 nrt_u128_sub(nrt_u128 a, nrt_u128 b)
{
    nrt_u128 r;
    r.lo = a.lo - b.lo;
    r.hi = a.hi - b.hi - (a.lo < b.lo ? 1UL : 0UL);
    return r;
}

NRT_DEVICE int nrt_u128_less(nrt_u128 a, nrt_u128 b)
{
    return a.hi < b.hi || (a.hi == b.hi && a.lo < b.lo);
}

NRT_DEVICE int nrt_u128_is_zero(nrt_u128 a)
{
    return (a.lo | a.hi) == 0;
}

/* a >> s, s >= 0 */
NRT_DEVICE nrt_u128 nrt_u128_shr(nrt_u128 a, int s)
{
    if (s <= 0)
        return a;
    if (s >= 128)
        return nrt_u128_of(0, 0);
    if (s >= 64)
        return nrt_u128_of(a.hi >> (s - 64), 0);
    return nrt_u128_of((a.lo >> s) | (a.hi << (64 - s)), a.hi >> s);
}

/* floor(a / n) for 1 <= n < 2^32, by 32-bit limbs (each step divides a number below 2^64) */
NRT_DEVICE nrt_u128 nrt_u128_div_small(nrt_u128 a, nrt_u32 n)
{
    nrt_u64 d = (nrt_u64)n;
    nrt_u64 cur = a.hi >> 32, q3 = cur / d;
    cur = ((cur % d) << 32) | (a.hi & 0xFFFFFFFFUL);
    nrt_u64 q2 = cur / d;
    cur = ((cur % d) << 32) | (a.lo >> 32);
    nrt_u64 q1 = cur / d;
    cur = ((cur % d) << 32) | (a.lo & 0xFFFFFFFFUL);
    nrt_u64 q0 = cur / d;
    return nrt_u128_of((q1 << 32) | q0, (q3 << 32) | q2);
}

/* The weight relative to W0, as a float (rounded). */
NRT_DEVICE float nrt_weight_rel(nrt_u128 w)
{
    return ((float)w.hi * NRT_TWO64_F + (float)w.lo) * NRT_TWO_M96_F;
}

/*
 * w x for 0 <= x < 2^24 and w < 2^104: x = m 2^(e - 24) with m a 24-bit integer (frexp), so
 * w x = (w m) >> (24 - e) with w m < 2^128, exactly; the result is rounded down, and then one
 * unit up where the top 32 of the discarded bits exceed r. With r 32 random bits that is
 * stochastic rounding (to 2^-32 of a unit), so that products of weights of a few hundred
 * units, those the deepest windows leave, are unbiased; r = 2^32 - 1 gives floor(w x). NaN
 * and x <= 0 give 0.
 */
NRT_DEVICE nrt_u128 nrt_u128_times_dither(nrt_u128 w, float x, nrt_u32 r)
{
    if (!(x > 0.0f))
        return nrt_u128_of(0, 0);
    int e;
    float f = NRT_FREXPF(x, &e);
    nrt_u64 m = (nrt_u64)(f * 16777216.0f);
    nrt_u128 p;
    p.lo = w.lo * m;
    p.hi = w.hi * m + NRT_MULHI64(w.lo, m);
    int s = 24 - e;
    nrt_u128 q = nrt_u128_shr(p, s);
    if (s <= 0 || s > 128 + 32)
        return q;
    /* the top 32 bits of the s discarded bits */
    nrt_u64 frac;
    if (s >= 32) {
        frac = nrt_u128_shr(p, s - 32).lo & 0xFFFFFFFFUL;
    } else {
        frac = (p.lo << (32 - s)) & 0xFFFFFFFFUL;
    }
    return (frac > (nrt_u64)r) ? nrt_u128_add(q, nrt_u128_of(1, 0)) : q;
}

/* floor(w x) exactly (see nrt_u128_times_dither) */
NRT_DEVICE nrt_u128 nrt_u128_times(nrt_u128 w, float x)
{
    return nrt_u128_times_dither(w, x, 0xFFFFFFFFu);
}

/* floor(x) of a float 0 <= x < 2^128 as a 128-bit integer, exactly (NaN gives 0). */
NRT_DEVICE nrt_u128 nrt_u128_floor(float x)
{
    if (!(x >= 1.0f))
        return nrt_u128_of(0, 0);
    if (x < NRT_TWO64_F)
        return nrt_u128_of((nrt_u64)x, 0);
    /* x >= 2^64 is a multiple of 2^41: its high and low words are exact floats */
    float h = floor(x * NRT_TWO_M64_F);
    return nrt_u128_of((nrt_u64)(x - h * NRT_TWO64_F), (nrt_u64)h);
}

/* Weight units of a relative weight x >= 0 (x W0), rounded down. */
NRT_DEVICE nrt_u128 nrt_weight_units(float x)
{
    return nrt_u128_times(nrt_u128_of(0, NRT_W0_HI), fmin(x, 128.0f));
}

/*
 * Add v to a 128-bit cell (two words, low first) with two 64-bit atomics: the carry out of
 * the low word goes into the high one, so the cell is the exact sum modulo 2^128 in any order.
 * checked: raise *overflow once the cell reaches 2^(64 + NRT_ACC_LIMIT_BITS) (every high-word
 * increment comes through here, so the final high word passes the limit iff some add did).
 */
NRT_DEVICE void nrt_add_wide(NRT_GLOBAL nrt_u64 *cell, nrt_u128 v, NRT_GLOBAL nrt_u32 *overflow, int checked)
{
    nrt_u64 carry = 0;
    if (v.lo != 0) {
        nrt_u64 old = NRT_ATOMIC_ADD_U64(&cell[0], v.lo);
        carry = (old + v.lo < old) ? 1UL : 0UL;
    }
    nrt_u64 h = v.hi + carry;
    if (h != 0) {
        nrt_u64 old = NRT_ATOMIC_ADD_U64(&cell[1], h);
        if (checked && (h >= NRT_ACC_LIMIT || old >= NRT_ACC_LIMIT - h))
            NRT_ATOMIC_OR_U32(overflow, 1u);
    }
}

/* A deposit of x >= 0 units into a 128-bit voxel cell, rounded to nearest. */
NRT_DEVICE void nrt_deposit_wide(NRT_GLOBAL nrt_u64 *band_acc, nrt_idx idx, float x, NRT_GLOBAL nrt_u32 *overflow)
{
    nrt_u128 v = nrt_u128_floor(x + 0.5f);
    if (!nrt_u128_is_zero(v))
        nrt_add_wide(band_acc + 2 * (nrt_u64)idx, v, overflow, 1);
}

/* A weighted packet's J scores per class of depth from the stars (heavy-tail diagnostic). The
   window buffer holds, after the depth map: per axis the map's cell of each voxel layer
   (premultiplied by the map's strides: cell = cx[ix] + cy[iy] + cz[iz], no division in the
   walk), then each band's NRT_TAIL_CLASSES - 1 class edges in the map's units. The sums are
   float32 sums of the float deposits (the same floats, added in the same order, on every
   device: IEEE addition rounds alike) in four scalars: 128-bit sums in an array indexed at
   run time cost 40 % of the weighted packets' time on an H200 (registers, and slow memory). */
#if NRT_TAIL_CLASSES && NRT_TAIL_CLASSES != 4
#error "NRT_TAIL_CLASSES: 4 depth classes (nebula_rt.transport.tails.DEPTH_CLASS_EDGES)"
#endif
typedef struct {
    const NRT_GLOBAL float *window, *cx; /* the map; its cells per x layer (y and z follow) */
    const NRT_GLOBAL int *wn;            /* (NRT_TREE) the map's cells per axis */
    float e0, e1, e2;
    float j0, j1, j2, j3;
} nrt_jtail;

/* Add a deposit of x units to the score of the class of a map cell of depth ``depth``. */
NRT_DEVICE void nrt_jtail_score(nrt_jtail *t, float depth, float x)
{
    if (depth < t->e0)
        t->j0 += x;
    else if (depth < t->e1)
        t->j1 += x;
    else if (depth < t->e2)
        t->j2 += x;
    else
        t->j3 += x;
}

/* Add a deposit of x units into voxel (ix, iy, iz) to the score of the class of the map's cell
   that holds the voxel's centre. */
NRT_DEVICE void nrt_jtail_add(nrt_jtail *t, int ix, int iy, int iz, int nx, int ny, float x)
{
#if NRT_TAIL_CLASSES
    const NRT_GLOBAL float *cy = t->cx + nx;
    nrt_jtail_score(t, t->window[(nrt_u32)t->cx[ix] + (nrt_u32)cy[iy] + (nrt_u32)cy[ny + iz]], x);
#else
    (void)t, (void)ix, (void)iy, (void)iz, (void)nx, (void)ny, (void)x;
#endif
}

/* Add a deposit of x units into the leaf of box [lo, lo + h) (NRT_TREE) to the score of the
   class of the map's cell that holds the leaf's centre (the grid's rule for a voxel). */
NRT_DEVICE void nrt_jtail_add_box(nrt_jtail *t, const float *lo, const float *h, float x)
{
#if NRT_TAIL_CLASSES
    int i[3];
    for (int a = 0; a < 3; ++a)
        i[a] = min((int)((lo[a] + 0.5f * h[a]) * (float)t->wn[a]), t->wn[a] - 1);
    nrt_jtail_score(t, t->window[(nrt_u64)i[0] + (nrt_u64)t->wn[0] * ((nrt_u64)i[1] + (nrt_u64)t->wn[1] * (nrt_u64)i[2])],
                    x);
#else
    (void)t, (void)lo, (void)h, (void)x;
#endif
}

/* A score as float32 into its half-octave bin (as nrt_tail_add: the exponent and the next
   bit; scores below 1 unit: none; infinity: the last bin) */
NRT_DEVICE void nrt_tail_add_float(NRT_GLOBAL nrt_u64 *hist, float x)
{
    if (!(x >= 1.0f))
        return;
    nrt_u32 b = NRT_FLOAT_AS_UINT(x);
    int bin = 2 * ((int)((b >> 23) & 0xFFu) - 127) + (int)((b >> 22) & 1u);
    NRT_ATOMIC_ADD_U64(&hist[bin < NRT_TAIL_BINS ? bin : NRT_TAIL_BINS - 1], 1UL);
}

/* tally t of a 128-bit tally block (5 tallies: emitted, absorbed, escaped, terminated, biasing) */
NRT_DEVICE void nrt_count_wide(NRT_GLOBAL nrt_u64 *tally, int t, nrt_u128 w)
{
    if (!nrt_u128_is_zero(w))
        nrt_add_wide(tally + 2 * t, w, 0, 0);
}

/* The weight windows' depth at x and its gradient (per box unit): the depth map (cells wn[0] x
   wn[1] x wn[2] over the box, x fastest) interpolated linearly between the cell centres
   (constant beyond the outermost ones), so that the window falls smoothly inside a voxel of
   large optical depth instead of in one step at its face. */
NRT_DEVICE float nrt_window_depth(const NRT_GLOBAL float *window, const NRT_GLOBAL int *wn, const float *x,
                                  float *grad)
{
    int i0[3], i1[3];
    float f[3], inside[3];
    for (int k = 0; k < 3; ++k) {
        float u0 = x[k] * (float)wn[k] - 0.5f;
        float u = fmin(fmax(u0, 0.0f), (float)(wn[k] - 1));
        int i = (int)u;
        i0[k] = i;
        i1[k] = i + 1 < wn[k] ? i + 1 : i;
        f[k] = u - (float)i;
        inside[k] = (u == u0 && i1[k] > i) ? (float)wn[k] : 0.0f; /* d u / d x, 0 where clamped */
    }
    nrt_u64 sy = (nrt_u64)wn[0], sz = (nrt_u64)wn[0] * (nrt_u64)wn[1];
    float c00 = window[i0[0] + i0[1] * sy + i0[2] * sz], c10 = window[i1[0] + i0[1] * sy + i0[2] * sz];
    float c01 = window[i0[0] + i1[1] * sy + i0[2] * sz], c11 = window[i1[0] + i1[1] * sy + i0[2] * sz];
    float d00 = window[i0[0] + i0[1] * sy + i1[2] * sz], d10 = window[i1[0] + i0[1] * sy + i1[2] * sz];
    float d01 = window[i0[0] + i1[1] * sy + i1[2] * sz], d11 = window[i1[0] + i1[1] * sy + i1[2] * sz];
    float c0 = c00 + f[0] * (c10 - c00), c1 = c01 + f[0] * (c11 - c01);
    float d0 = d00 + f[0] * (d10 - d00), d1 = d01 + f[0] * (d11 - d01);
    float c = c0 + f[1] * (c1 - c0), e = d0 + f[1] * (d1 - d0);
    /* the interpolant's partial derivatives */
    float cx = (c10 - c00) + f[1] * ((c11 - c01) - (c10 - c00));
    float ex = (d10 - d00) + f[1] * ((d11 - d01) - (d10 - d00));
    grad[0] = inside[0] * (cx + f[2] * (ex - cx));
    grad[1] = inside[1] * ((c1 - c0) + f[2] * ((d1 - d0) - (c1 - c0)));
    grad[2] = inside[2] * (e - c);
    return c + f[2] * (e - c);
}

/* The weight window's centre at a depth, relative to W0 (see above), for a packet that left
   its star at depth d0 (the map's depth there: the interpolation between cell centres does not
   give 0 at the star itself) */
NRT_DEVICE float nrt_window_of(float rate, float depth, float d0)
{
    return fmax(exp(-rate * fmax(depth - d0, 0.0f)), NRT_WINDOW_FLOOR);
}

/* A straight ray through the grid, voxel by voxel (the DDA of nrt_trace_packet). */
typedef struct {
    float p[3], d[3], inv_d[3];
    float tx, ty, tz, t_cur;
    int ix, iy, iz;
    nrt_idx idx;
} nrt_ray;

NRT_DEVICE void nrt_ray_start(nrt_ray *r, const float *p, const float *d, int ix, int iy, int iz, int nx, int ny, int nz)
{
    for (int k = 0; k < 3; ++k) {
        r->p[k] = p[k];
        r->d[k] = d[k];
        r->inv_d[k] = 1.0f / d[k];
    }
    r->ix = ix;
    r->iy = iy;
    r->iz = iz;
    r->t_cur = 0.0f;
    r->tx = nrt_face_distance(p[0], d[0], r->inv_d[0], ix, 1.0f / (float)nx);
    r->ty = nrt_face_distance(p[1], d[1], r->inv_d[1], iy, 1.0f / (float)ny);
    r->tz = nrt_face_distance(p[2], d[2], r->inv_d[2], iz, 1.0f / (float)nz);
    r->idx = nrt_voxel_index(ix, iy, iz, nx, ny);
}

/* Length of the ray inside its current voxel. */
NRT_DEVICE float nrt_ray_segment(const nrt_ray *r)
{
    return fmax(0.0f, fmin(r->tx, fmin(r->ty, r->tz)) - r->t_cur);
}

/* Step into the next voxel; 0 if the ray leaves the box instead. */
NRT_DEVICE int nrt_ray_advance(nrt_ray *r, int nx, int ny, int nz)
{
    float t_next = fmin(r->tx, fmin(r->ty, r->tz));
    int ax = (r->tx <= r->ty && r->tx <= r->tz) ? 0 : ((r->ty <= r->tz) ? 1 : 2);
    float d_ax = ax == 0 ? r->d[0] : (ax == 1 ? r->d[1] : r->d[2]);
    int up = d_ax > 0.0f;
    int i_next = (ax == 0 ? r->ix : (ax == 1 ? r->iy : r->iz)) + (up ? 1 : -1);
    if (i_next < 0 || i_next >= (ax == 0 ? nx : (ax == 1 ? ny : nz)))
        return 0;
    r->t_cur = fmax(r->t_cur, t_next);
    nrt_idx stride = ax == 0 ? (nrt_idx)1 : (ax == 1 ? (nrt_idx)nx : (nrt_idx)nx * (nrt_idx)ny);
    r->idx = up ? r->idx + stride : r->idx - stride;
    nrt_cross_face(ax, i_next, r->p, d_ax, r->inv_d, 1.0f / (float)nx, 1.0f / (float)ny, 1.0f / (float)nz,
                   &r->ix, &r->iy, &r->iz, &r->tx, &r->ty, &r->tz);
    return 1;
}

/* What a weighted packet walks: the grid's voxels (nx ny nz), or (NRT_TREE) the leaves of a
   tree over nx ny nz root cells, its nodes' child entries after the leaves' densities. */
typedef struct {
    int nx, ny, nz;
#if NRT_TREE
    const NRT_GLOBAL int *child;
#endif
} nrt_medium;

/* Where a weighted packet is: its voxel, or its leaf (as the tree walk keeps it). */
typedef struct {
#if NRT_TREE
    int c[3], n[3], node, leaf;
    float lo[3], h[3];
#else
    int ix, iy, iz;
#endif
} nrt_place;

/* The voxel or leaf holding p (a point on a leaf's face: the one d moves into). */
NRT_DEVICE void nrt_place_of(const nrt_medium *m, const float *p, const float *d, nrt_place *q)
{
#if NRT_TREE
    q->leaf = nrt_tree_locate(m->child, m->nx, m->ny, m->nz, p, d, q->c, q->n, q->lo, q->h, &q->node, 0, 0);
#else
    (void)d;
    nrt_voxel_of(p, m->nx, m->ny, m->nz, &q->ix, &q->iy, &q->iz);
#endif
}

/* The cell of a place: its voxel's or its leaf's index. */
NRT_DEVICE nrt_idx nrt_place_index(const nrt_medium *m, const nrt_place *q)
{
#if NRT_TREE
    (void)m;
    return (nrt_idx)(q->leaf < 0 ? 0 : q->leaf);
#else
    return nrt_voxel_index(q->ix, q->iy, q->iz, m->nx, m->ny);
#endif
}

#if NRT_TREE
/* A straight ray through the tree, leaf by leaf (the analog walk's steps): q the point where
   the current leaf was entered, t_cur its distance from the ray's start, seg the length
   inside the leaf, ax the axis of its exit face. */
typedef struct {
    float q[3], d[3], inv_d[3];
    float t_cur, seg;
    int ax;
    nrt_place at;
    nrt_idx idx;
} nrt_mray;

NRT_DEVICE void nrt_mray_start(nrt_mray *r, const nrt_medium *m, const float *p, const float *d, const nrt_place *q)
{
    for (int k = 0; k < 3; ++k) {
        r->q[k] = p[k];
        r->d[k] = d[k];
        r->inv_d[k] = 1.0f / d[k];
    }
    r->at = *q;
    /* a point on one of its leaf's faces (where it scattered): the leaf d moves into */
    int on_face = 0;
    for (int a = 0; a < 3; ++a)
        on_face |= !(p[a] > q->lo[a] && p[a] < (float)(q->c[a] + 1) * q->h[a]);
    if (on_face)
        nrt_place_of(m, p, d, &r->at);
    r->t_cur = 0.0f;
    r->seg = r->at.leaf < 0 ? 0.0f : nrt_tree_exit(r->q, r->d, r->inv_d, r->at.c, r->at.lo, r->at.h, &r->ax);
    r->idx = nrt_place_index(m, &r->at);
}

NRT_DEVICE float nrt_mray_segment(const nrt_mray *r)
{
    return r->seg;
}

/* Step into the next leaf; 0 if the ray leaves the box instead. */
NRT_DEVICE int nrt_mray_advance(nrt_mray *r, const nrt_medium *m)
{
    nrt_place *a = &r->at;
    int ax = r->ax, up = r->d[ax] > 0.0f;
    if (a->leaf < 0 || (up && a->c[ax] + 1 == a->n[ax]) || (!up && a->c[ax] == 0))
        return 0;
    for (int k = 0; k < 3; ++k)
        r->q[k] = r->q[k] + r->d[k] * r->seg;
    r->q[ax] = (float)(a->c[ax] + up) * a->h[ax];
    r->t_cur += r->seg;
    a->leaf = nrt_tree_next(m->child, m->nx, m->ny, m->nz, r->q, r->d, ax, up, a->c, a->n, a->lo, a->h, &a->node,
                            0, 0);
    if (a->leaf < 0)
        return 0; /* (deeper than NRT_TREE_MAX_DEPTH: a tree the host does not make) */
    r->seg = nrt_tree_exit(r->q, r->d, r->inv_d, a->c, a->lo, a->h, &r->ax);
    r->idx = (nrt_idx)a->leaf;
    return 1;
}

/* The point at length t into the current leaf, kept inside its box; and the leaf. */
NRT_DEVICE void nrt_mray_stop(const nrt_mray *r, float t, float *p, nrt_place *q)
{
    for (int k = 0; k < 3; ++k)
        p[k] = fmin(fmax(r->q[k] + r->d[k] * t, r->at.lo[k]), r->at.lo[k] + r->at.h[k]);
    *q = r->at;
}

NRT_DEVICE void nrt_mray_jtail(nrt_jtail *jt, const nrt_mray *r, const nrt_medium *m, float x)
{
    (void)m;
    nrt_jtail_add_box(jt, r->at.lo, r->at.h, x);
}
#else
typedef nrt_ray nrt_mray;

NRT_DEVICE void nrt_mray_start(nrt_mray *r, const nrt_medium *m, const float *p, const float *d, const nrt_place *q)
{
    nrt_ray_start(r, p, d, q->ix, q->iy, q->iz, m->nx, m->ny, m->nz);
}

NRT_DEVICE float nrt_mray_segment(const nrt_mray *r)
{
    return nrt_ray_segment(r);
}

NRT_DEVICE int nrt_mray_advance(nrt_mray *r, const nrt_medium *m)
{
    return nrt_ray_advance(r, m->nx, m->ny, m->nz);
}

/* The point at length t into the current voxel (p the ray's start, moved there); and the voxel. */
NRT_DEVICE void nrt_mray_stop(const nrt_mray *r, float t, float *p, nrt_place *q)
{
    float s = r->t_cur + t;
    p[0] = p[0] + r->d[0] * s;
    p[1] = p[1] + r->d[1] * s;
    p[2] = p[2] + r->d[2] * s;
    q->ix = r->ix;
    q->iy = r->iy;
    q->iz = r->iz;
}

NRT_DEVICE void nrt_mray_jtail(nrt_jtail *jt, const nrt_mray *r, const nrt_medium *m, float x)
{
    nrt_jtail_add(jt, r->ix, r->iy, r->iz, m->nx, m->ny, x);
}
#endif

/*
 * The forced flight's first walk, to the box's edge: returns tau_p, *edge 1 where the walk
 * reached the edge. Past NRT_TAU_CUT it stops (*edge 0) where the flight's remaining weight
 * w e^-tau falls e^-NRT_TAU_CUT below the window there (the light the windows expect there):
 * what it leaves out is that far below what other packets bring (window: the windows' depth
 * map, its cells wn, the band's rate and the packet's depth at its star, d0)
 * and, with the track-length estimator, deposits the flight's expected track length
 * w e^-tau(s) over every voxel it crosses (w: the relative weight; scale: units per box unit).
 */
NRT_DEVICE float nrt_forced_walk(const NRT_GLOBAL float *density, float sig_b, const float *p, const float *d,
                                 const nrt_medium *m, const nrt_place *at, float w, float scale,
                                 NRT_GLOBAL nrt_u64 *band_acc, NRT_GLOBAL nrt_u32 *overflow,
                                 const NRT_GLOBAL float *window, const NRT_GLOBAL int *wn, float rate, float d0,
                                 int *edge, nrt_jtail *jt)
{
    nrt_mray r;
    nrt_mray_start(&r, m, p, d, at);
    float tau = 0.0f, att = w * scale;
    const float log_w = log(w);
    for (;;) {
        float seg = nrt_mray_segment(&r);
        float sigma = sig_b * density[r.idx];
        float ts = sigma * seg;
        float em = expm1(-ts); /* e^-ts - 1, accurate for thin voxels */
#if NRT_TRACK_LENGTH
        /* integral of e^-tau over the segment: (1 - e^-ts) / sigma, or the length if empty */
        float len = sigma > 0.0f ? -em / sigma : seg;
        {
            float x = att * len;
            nrt_deposit_wide(band_acc, r.idx, x, overflow);
            nrt_mray_jtail(jt, &r, m, x);
        }
#else
        (void)jt;
#endif
        att = att + att * em;
        tau += ts;
        if (tau > NRT_TAU_CUT) {
            float t = r.t_cur + seg, x[3], grad[3];
            for (int k = 0; k < 3; ++k)
                x[k] = p[k] + d[k] * t;
            float depth = nrt_window_depth(window, wn, x, grad);
            if (tau > NRT_TAU_CUT + log_w + rate * fmax(depth - d0, 0.0f)) {
                *edge = 0;
                return tau;
            }
        }
        if (!nrt_mray_advance(&r, m)) {
            *edge = 1;
            return tau;
        }
    }
}

/*
 * A walk from p along d until optical depth tau_i is spent; the point and its voxel go to p,
 * ix, iy, iz. Returns 0 if the ray leaves the box first. scale > 0 (an analog flight with the
 * track-length estimator): every voxel crossed gets scale x the length travelled in it.
 */
NRT_DEVICE int nrt_walk_to(const NRT_GLOBAL float *density, float sig_b, float *p, const float *d,
                           const nrt_medium *m, nrt_place *at, float tau_i, float scale,
                           NRT_GLOBAL nrt_u64 *band_acc, NRT_GLOBAL nrt_u32 *overflow, nrt_jtail *jt)
{
    nrt_mray r;
    nrt_mray_start(&r, m, p, d, at);
    for (;;) {
        float seg = nrt_mray_segment(&r);
        float sigma = sig_b * density[r.idx];
        float ts = sigma * seg;
        if (sigma > 0.0f && ts >= tau_i) {
            float t_in = tau_i / sigma;
            if (scale > 0.0f)
            {
                nrt_deposit_wide(band_acc, r.idx, scale * t_in, overflow);
                nrt_mray_jtail(jt, &r, m, scale * t_in);
            }
            nrt_mray_stop(&r, t_in, p, at);
            return 1;
        }
        if (scale > 0.0f)
        {
            nrt_deposit_wide(band_acc, r.idx, scale * seg, overflow);
            nrt_mray_jtail(jt, &r, m, scale * seg);
        }
        tau_i -= ts;
        if (!nrt_mray_advance(&r, m))
            return 0;
    }
}

#if NRT_PEEL
/* Weighted peel-off (w: relative weight after the absorption; branch: the packet's copy) into a
   128-bit image; returns the units added. */
NRT_DEVICE nrt_u128 nrt_peel_wide(const NRT_GLOBAL float *density, float sig_b, float g_b,
                              const NRT_GLOBAL float *peel, float peel_scale, const float *x,
                              const float *d, const nrt_medium *m, const nrt_place *at,
                              NRT_GLOBAL nrt_u64 *band_image, NRT_GLOBAL nrt_u32 *overflow,
                              nrt_u64 seed, int band, nrt_u64 photon, int event, nrt_u64 branch, float w,
                              const NRT_GLOBAL float *pol, const nrt_stokes *st, NRT_GLOBAL nrt_u64 *band_stokes)
{
    nrt_u64 pixel;
    if (!nrt_peel_pixel(peel, x, &pixel))
        return nrt_u128_of(0, 0); /* outside the image */
    const float o[3] = {peel[0], peel[1], peel[2]};
#if NRT_TREE
    (void)at;
    float atten = exp(-nrt_tree_tau_to_edge(m->child, density, m->nx, m->ny, m->nz, sig_b, x, o));
#else
    float atten = exp(-nrt_tau_to_edge(density, sig_b, x, o, at->ix, at->iy, at->iz, m->nx, m->ny, m->nz));
#endif
#if NRT_POLAR
    const float north[3] = {peel[6], peel[7], peel[8]};
    float iquv[4];
    nrt_peel_stokes(NRT_POLAR, g_b, pol, o, north, d, st, iquv);
    float wgt = iquv[0] * atten;
#else
    (void)pol, (void)st, (void)band_stokes;
    float mu = d[0] * o[0] + d[1] * o[1] + d[2] * o[2];
    float wgt = nrt_hg_phase(g_b, mu) * atten;
#endif
    if (!(wgt >= 0.0f))
        return nrt_u128_of(0, 0);
    float xw = NRT_FMAF(wgt * w, peel_scale, 0.0f);
    nrt_u128 v = xw < 16777216.0f
        ? nrt_u128_of(nrt_fixed_stochastic(wgt * w, peel_scale, seed, (nrt_u64)band, photon, (nrt_u64)event, branch), 0)
        : nrt_u128_floor(xw);
    if (!nrt_u128_is_zero(v))
        nrt_add_wide(band_image + 2 * pixel, v, overflow, 1);
#if NRT_POLAR
    /* Q and U: rounded as I (the same random word below 2^24 units, else down), so their
       units stay within I's, and added as 128-bit two's complement (unchecked: exact modulo
       2^128, bounded by I's checked sums) */
    const nrt_u64 pixels = (nrt_u64)peel[13] * (nrt_u64)peel[14];
    const nrt_u64 r = nrt_round_word(seed, (nrt_u64)band, photon, (nrt_u64)event, branch);
    for (int k = 0; k < NRT_STOKES_IMAGES; ++k) {
        float a = fabs(iquv[k + 1]) * atten;
        float xa = NRT_FMAF(a * w, peel_scale, 0.0f);
        nrt_u128 u = xa < 16777216.0f ? nrt_u128_of(nrt_fixed_round(a * w, peel_scale, r), 0) : nrt_u128_floor(xa);
        if (nrt_u128_is_zero(u))
            continue;
        if (iquv[k + 1] < 0.0f) /* -u modulo 2^128 */
            u = nrt_u128_of(~u.lo + 1UL, ~u.hi + (u.lo == 0 ? 1UL : 0UL));
        nrt_add_wide(band_stokes + 2 * ((nrt_u64)k * pixels + pixel), u, overflow, 0);
    }
#endif
    return v;
}
#endif

/* A split packet's copies still to run: where they start, the weight of each, how many are
   left and the stream of the first of them (the next copy to run takes first + left - 1). */
typedef struct {
    float p[3], d[3];
#if !NRT_TREE
    int ix, iy, iz; /* (a tree's leaf is found again from p and d: 12 words a level fewer) */
#endif
    int scatterings;
    nrt_u128 w;
    nrt_u64 first;
    nrt_u32 left;
#if NRT_POLAR
    nrt_stokes st; /* the copies' polarization at the split */
#endif
} nrt_pending;

/* Trace one weighted packet and its split copies (see above); tally: this cell's 5 128-bit
   tallies; window: the windows' depth per voxel; rate: the band's windows' decay rate. */
NRT_DEVICE void nrt_trace_packet_biased(const NRT_GLOBAL float *density, float sig_b, float alb_b,
                                        float g_b, float rate, const NRT_GLOBAL float *window,
                                        const NRT_GLOBAL int *window_shape,
                                        const NRT_GLOBAL float *stars,
                                        const NRT_GLOBAL float *cdf, const nrt_medium *m,
                                        int n_stars, nrt_u64 seed, int band, nrt_u64 photon,
                                        int max_scatterings, float track_scale, float collision_scale,
                                        NRT_GLOBAL nrt_u64 *band_acc, NRT_GLOBAL nrt_u64 *tally,
                                        NRT_GLOBAL nrt_u32 *overflow, const NRT_GLOBAL float *peel,
                                        float peel_scale, NRT_GLOBAL nrt_u64 *band_image,
                                        const NRT_GLOBAL float *pol, NRT_GLOBAL nrt_u64 *band_stokes)
{
    nrt_rng rng;
    nrt_rng_init(&rng, seed, (nrt_u64)band, photon);
    /* the emitting star and first direction: the same draws as the analog packet */
    int s = nrt_choose_star(&rng, cdf, n_stars);
    float p[3] = {stars[4 * s], stars[4 * s + 1], stars[4 * s + 2]};
    float d[3];
    nrt_sample_isotropic(&rng, d);
#if NRT_POLAR
    nrt_stokes stokes; /* the copy's polarization */
    nrt_stokes_unpolarized(d, &stokes);
#else
    (void)pol, (void)band_stokes;
#endif
    nrt_place at;
    nrt_place_of(m, p, d, &at);

    nrt_u128 w = nrt_u128_of(0, NRT_W0_HI);
    nrt_count_wide(tally, 0, w);
    nrt_u128 bias = nrt_u128_of(0, 0); /* weight created (wraps negative) or removed by biasing */
    float grad[3];
    const float d0 = nrt_window_depth(window, window_shape, p, grad); /* the windows' depth at the star */
    int scatterings = 0;
    nrt_u64 branch = 0, streams = 0; /* this copy's stream; the streams handed out so far */
    nrt_pending stack[NRT_SPLIT_DEPTH];
    int top = 0;
    /* the packet's scores (all its copies): peel-off units, J units per depth class */
    nrt_u128 img_score = nrt_u128_of(0, 0);
    nrt_jtail jt;
    jt.window = window;
    jt.wn = window_shape;
    jt.j0 = jt.j1 = jt.j2 = jt.j3 = 0.0f;
#if NRT_TAIL_CLASSES
    jt.cx = window + (nrt_u64)window_shape[0] * (nrt_u64)window_shape[1] * (nrt_u64)window_shape[2];
    {
        /* (a tree's leaves are classed by their centres: no cells per voxel layer) */
        const NRT_GLOBAL float *edges = jt.cx + (NRT_TREE ? 0 : m->nx + m->ny + m->nz)
                                        + (nrt_u64)band * (NRT_TAIL_CLASSES - 1);
        jt.e0 = edges[0], jt.e1 = edges[1], jt.e2 = edges[2];
    }
#else
    jt.cx = window;
    jt.e0 = jt.e1 = jt.e2 = 0.0f;
#endif
    for (;;) {
        int alive = 1;
        /* the windows' log-slope s along the direction per unit optical depth, clamped to
           +-NRT_STRETCH_MAX, and l = 1 - s: the window's angular factor and the flight's
           stretch (below) */
        float depth = nrt_window_depth(window, window_shape, p, grad);
        float sig_here = sig_b * density[nrt_place_index(m, &at)];
        float slope = sig_here > 0.0f ? rate * (grad[0] * d[0] + grad[1] * d[1] + grad[2] * d[2]) / sig_here : 0.0f;
        float lam = 1.0f - fmin(fmax(slope, -NRT_STRETCH_MAX), NRT_STRETCH_MAX);
        {
            /* the weight window at the packet's place and direction: split above it, Russian
               roulette below */
            float wc = nrt_window_of(rate, depth, d0) * lam;
            float ratio = nrt_weight_rel(w) / wc;
            if (ratio > NRT_WINDOW_HIGH && top < NRT_SPLIT_DEPTH && streams < NRT_SPLIT_BUDGET) {
                nrt_u32 n = (nrt_u32)fmin(fmin(ratio, (float)NRT_SPLIT_MAX), (float)(NRT_SPLIT_BUDGET - streams + 1));
                nrt_u128 each = nrt_u128_div_small(w, n);
                nrt_pending *q = &stack[top++];
                for (int k = 0; k < 3; ++k) {
                    q->p[k] = p[k];
                    q->d[k] = d[k];
                }
#if !NRT_TREE
                q->ix = at.ix;
                q->iy = at.iy;
                q->iz = at.iz;
#endif
                q->scatterings = scatterings;
#if NRT_POLAR
                q->st = stokes;
#endif
                q->w = each;
                q->first = streams + 1;
                q->left = n - 1;
                streams += n - 1;
                /* this copy goes on with its share and the remainder of the division */
                w = nrt_u128_sub(w, nrt_u128_times(each, (float)(n - 1)));
            } else if (ratio < NRT_WINDOW_LOW) {
                nrt_u128 t = nrt_weight_units(wc);
                if (nrt_rng_uniform(&rng) < ratio) {
                    bias = nrt_u128_add(bias, nrt_u128_sub(w, t));
                    w = t;
                } else {
                    bias = nrt_u128_add(bias, w);
                    alive = 0;
                }
            }
        }
        /* the first NRT_FORCED_FLIGHTS flights forced and stretched, the later ones analog */
        int forced = scatterings < NRT_FORCED_FLIGHTS;
        float wr = nrt_weight_rel(w);
        if (alive && forced) {
            int edge;
            float tau_p = nrt_forced_walk(density, sig_b, p, d, m, &at, wr, track_scale,
                                          band_acc, overflow, window, window_shape, rate, d0, &edge, &jt);
            /* forced scattering: the part that would leave, exactly (or fly past the cut) */
            nrt_u128 out = (tau_p > 1.0e-30f) ? nrt_u128_times_dither(w, exp(-tau_p), nrt_rng_u32(&rng)) : w;
            if (edge)
                nrt_count_wide(tally, 2, out);
            else
                bias = nrt_u128_add(bias, out);
            w = nrt_u128_sub(w, out);
            if (nrt_u128_is_zero(w)) {
                alive = 0;
            } else {
                /* composite biasing of the interaction depth on [0, tau_p]: the exponential of
                   the dust p (share NRT_BIAS_XI) mixed with the exponential transform
                   q_l = l e^-l tau that follows the windows and the uniform u = 1 / tau_p
                   (share NRT_UNIFORM_SHARE x (1 - albedo)), all truncated to [0, tau_p] */
                float xi_u = NRT_UNIFORM_SHARE * (1.0f - alb_b);
                float tau_c = tau_p;
                float reach = -expm1(-tau_c);           /* 1 - e^-tau_p */
                float reach_l = -expm1(-lam * tau_c);   /* 1 - e^-l tau_p */
                float u1 = nrt_rng_uniform(&rng), u2 = nrt_rng_uniform(&rng);
                float tau_i = (u1 < NRT_BIAS_XI) ? -log1p(-u2 * reach)
                            : (u1 < NRT_BIAS_XI + xi_u) ? u2 * tau_c : -log1p(-u2 * reach_l) / lam;
                tau_i = fmin(tau_i, tau_c);
                /* p / q = 1 / (xi + xi_u u / p + xi_l q_l / p), with u / p = reach e^tau / tau_p and
                   q_l / p = l e^((1 - l) tau) reach / reach_l */
                float f = 1.0f / (NRT_BIAS_XI + xi_u * reach * exp(tau_i) / tau_c
                                  + (1.0f - NRT_BIAS_XI - xi_u) * lam * exp((1.0f - lam) * tau_i) * reach / reach_l);
                nrt_u128 wf = nrt_u128_times_dither(w, f, nrt_rng_u32(&rng));
                if (wf.hi >= NRT_W_CAP_HI) /* a guard only: the windows keep weights near W0 or below */
                    wf = nrt_u128_of(0, NRT_W_CAP_HI - 1UL);
                bias = nrt_u128_add(bias, nrt_u128_sub(w, wf));
                w = wf;
                if (nrt_u128_is_zero(w)) {
                    alive = 0;
                } else if (!nrt_walk_to(density, sig_b, p, d, m, &at, tau_i, 0.0f, band_acc, overflow, &jt)) {
                    nrt_count_wide(tally, 2, w); /* rounding put the point past the edge */
                    alive = 0;
                }
            }
        } else if (alive) {
            /* an analog flight of weight w: the track-length deposits along the path */
            float tau_i = nrt_sample_tau(&rng);
            if (!nrt_walk_to(density, sig_b, p, d, m, &at, tau_i,
                             NRT_TRACK_LENGTH ? wr * track_scale : 0.0f, band_acc, overflow, &jt)) {
                nrt_count_wide(tally, 2, w);
                alive = 0;
            }
        }
        if (alive) {
#if NRT_COLLISION
            nrt_deposit_wide(band_acc, nrt_place_index(m, &at), nrt_weight_rel(w) * collision_scale, overflow);
#endif
            if (forced) {
                /* implicit capture: the absorbed part of the weight, exactly */
                nrt_u128 absorbed = nrt_u128_times_dither(w, 1.0f - alb_b, nrt_rng_u32(&rng));
                nrt_count_wide(tally, 1, absorbed);
                w = nrt_u128_sub(w, absorbed);
                alive = !nrt_u128_is_zero(w);
            } else if (nrt_rng_uniform(&rng) >= alb_b) {
                nrt_count_wide(tally, 1, w);
                alive = 0;
            }
        }
        if (alive && scatterings >= max_scatterings) {
            nrt_count_wide(tally, 3, w);
            alive = 0;
        }
        if (alive) {
            ++scatterings;
#if NRT_PEEL
            img_score = nrt_u128_add(img_score, nrt_peel_wide(density, sig_b, g_b, peel, peel_scale, p, d, m, &at,
                                                              band_image, overflow, seed, band, photon,
                                                              scatterings, branch, nrt_weight_rel(w), pol,
                                                              NRT_STOKES_STATE, band_stokes));
#endif
            NRT_NEW_DIRECTION();
            continue;
        }
        /* this copy has ended: the next one waiting, if any */
        if (top == 0)
            break;
        nrt_pending *q = &stack[top - 1];
        branch = q->first + (nrt_u64)(q->left - 1u);
        for (int k = 0; k < 3; ++k) {
            p[k] = q->p[k];
            d[k] = q->d[k];
        }
#if NRT_TREE
        nrt_place_of(m, p, d, &at);
#else
        at.ix = q->ix;
        at.iy = q->iy;
        at.iz = q->iz;
#endif
        scatterings = q->scatterings;
#if NRT_POLAR
        stokes = q->st;
#endif
        w = q->w;
        if (--q->left == 0u)
            --top;
        nrt_rng_init(&rng, seed, (nrt_u64)band, photon);
        rng.stream = branch;
    }
    nrt_count_wide(tally, 4, bias);
#if NRT_PEEL
    nrt_tail_add(NRT_TAIL_OF(tally), img_score.lo, img_score.hi);
#else
    (void)img_score;
#endif
#if NRT_TAIL_CLASSES
    {
        NRT_GLOBAL nrt_u64 *h = NRT_TAIL_OF(tally) + NRT_PEEL * NRT_TAIL_BINS;
        nrt_tail_add_float(h, jt.j0);
        nrt_tail_add_float(h + NRT_TAIL_BINS, jt.j1);
        nrt_tail_add_float(h + 2 * NRT_TAIL_BINS, jt.j2);
        nrt_tail_add_float(h + 3 * NRT_TAIL_BINS, jt.j3);
    }
#endif
}
#endif /* NRT_BIASED */

/*
 * Batch index of a packet in a plan of n_batches batches whose sizes differ by at most one:
 * the first `extra` batches hold base + 1 packets, the others base.
 */
NRT_DEVICE nrt_u64 nrt_batch_of(nrt_u64 photon, nrt_u64 base, nrt_u64 extra)
{
    nrt_u64 big = extra * (base + 1);
    return (photon < big) ? photon / (base + 1) : extra + (photon - big) / base;
}

/*
 * Trace packets [photon_start, photon_start + count) of bands band0 .. band0 + n_lbands - 1
 * (gid = band offset * count + i). They belong to the consecutive batches first_batch,
 * first_batch + 1, ... of the plan (prm->batch_base, prm->batch_extra); each (batch, band)
 * accumulates into its own cell of acc (cell = (batch - first_batch) * n_lbands + band
 * offset), tallies and image, and each batch raises its own overflow flag, so the batch
 * totals stay separable for the error estimate while many batches (and bands) share one
 * launch; the host traces the bands in several launches when one cell of every band would not
 * fit its memory budget. The backends launch one work item per packet; the grid-stride loop
 * keeps the kernel correct for smaller launches too.
 */
NRT_KERNEL void trace_photons(const NRT_GLOBAL nrt_trace_params *prm,
                              const nrt_launch launch,          /* this launch's photons, bands, pass */
                              const NRT_GLOBAL float *density,  /* nx*ny*nz, x fastest */
                              const NRT_GLOBAL float *optics,   /* per band: tau k_b, albedo, g, 0 */
                              const NRT_GLOBAL float *stars,    /* per star: x, y, z, pad */
                              const NRT_GLOBAL float *star_cdf, /* per band: n_stars cdf */
                              NRT_GLOBAL nrt_u64 *acc,      /* slots * n_lbands * nvox */
                              NRT_GLOBAL nrt_u64 *sq,       /* NRT_PACKET_SQ: as acc, the squares */
                              NRT_GLOBAL nrt_u64 *tallies,  /* slots * n_lbands * 4 */
                              NRT_GLOBAL nrt_u32 *overflow, /* slots */
                              NRT_GLOBAL nrt_u64 *image,    /* slots * n_lbands * W * H */
                              const NRT_GLOBAL nrt_u64 *order, /* NRT_SORTED: emission order; NRT_REGIONS:
                                                                  stopped packets' keys, then free slots' */
                              const NRT_GLOBAL nrt_u64 *emit,  /* NRT_REGIONS, NRT_SORTED: the chunk's
                                                                  emission order */
                              NRT_GLOBAL nrt_packet *states,   /* NRT_REGIONS: per state slot */
                              const NRT_GLOBAL float *window,  /* NRT_BIASED: the weight windows' depth
                                                                  per voxel */
                              NRT_GLOBAL nrt_u64 *keys_out)    /* NRT_REGIONS: per item it */
{
    const nrt_u64 photon_start = launch.photon_start, count = launch.count, first_batch = launch.first_batch;
    const nrt_u64 n_resume = launch.n_resume, n_fresh = launch.n_fresh, fresh0 = launch.fresh0;
    const nrt_u64 n_free = launch.n_free, hwm = launch.hwm;
    const int band0 = launch.band0, n_lbands = launch.n_lbands, region_shift = launch.region_shift;
    (void)n_resume, (void)n_fresh, (void)fresh0, (void)n_free, (void)hwm, (void)region_shift; /* NRT_REGIONS */
    const int nx = prm->nx, ny = prm->ny, nz = prm->nz, n_stars = prm->n_stars;
    const nrt_u64 seed = prm->seed, batch_base = prm->batch_base, batch_extra = prm->batch_extra;
    const int max_scatterings = prm->max_scatterings;
    const int sq_shift = prm->sq_shift;
    const float track_scale = prm->track_scale, peel_scale = prm->peel_scale;
    const NRT_GLOBAL float *peel = prm->peel;
    nrt_u64 nvox = prm->cells; /* nx ny nz voxels, or (NRT_TREE) the tree's leaves */
#if NRT_BIASED
    nrt_medium medium;
    medium.nx = nx, medium.ny = ny, medium.nz = nz;
#if NRT_TREE
    medium.child = (const NRT_GLOBAL int *)(density + nvox);
#endif
#endif
#if NRT_REGIONS
    /* a pass (nrt_pass_item): the stopped packets, the chunk's new ones, free slots passed on */
    nrt_u64 total = n_resume + (n_fresh > n_free ? n_fresh : n_free);
#else
    nrt_u64 total = count * (nrt_u64)n_lbands;
#endif
    nrt_u64 stride = NRT_GLOBAL_SIZE();
    nrt_u64 pixels = NRT_PEEL ? (nrt_u64)peel[13] * (nrt_u64)peel[14] : 0;
    /* the home cell (batch slot and band) of the group: that of its first packet */
    nrt_u64 home_cell = 0, home_slot = 0;
    nrt_sink sink;
#if NRT_GROUP_TALLY
    nrt_u64 lid = NRT_LOCAL_ID();
    NRT_LOCAL_MEM nrt_u64 l_tally[4];
    NRT_LOCAL_MEM nrt_u64 l_hot[NRT_HOT_STARS * NRT_HOT_CELLS];
    NRT_LOCAL_MEM nrt_u64 l_hot_sq[NRT_PACKET_SQ ? NRT_HOT_STARS * NRT_HOT_CELLS : 1];
    /* strided: a runtime may choose groups of fewer than 4 (or NRT_HOT_STARS) work items,
       e.g. OpenCL's own choice of local size for a global size with no small factor */
    for (nrt_u64 i = lid; i < 4; i += NRT_LOCAL_SIZE())
        l_tally[i] = 0;
    for (nrt_u64 i = lid; i < NRT_HOT_STARS * NRT_HOT_CELLS; i += NRT_LOCAL_SIZE()) {
        l_hot[i] = 0;
#if NRT_PACKET_SQ
        l_hot_sq[i] = 0;
#endif
    }
    {
        nrt_u64 it0 = NRT_GROUP_FIRST_ID(), photon0 = photon_start;
        int lband0 = 0;
#if NRT_REGIONS
        nrt_u64 sl0;
        int fresh0_;
        if (it0 < total)
            nrt_pass_item(it0, order, emit, states, n_resume, n_fresh, fresh0, n_free, hwm, photon_start, count,
                          &photon0, &lband0, &sl0, &fresh0_);
#else
        nrt_u64 t0 = it0 < total && NRT_SORTED ? (order[it0] & NRT_KEY_LOW) : it0;
        photon0 = photon_start + t0 % count;
        lband0 = (int)(t0 / count);
#endif
        home_slot = nrt_batch_of(photon0, batch_base, batch_extra) - first_batch;
        home_cell = home_slot * (nrt_u64)n_lbands + (nrt_u64)lband0;
    }
    sink.l_tally = l_tally;
    NRT_BARRIER();
#else
    sink.l_tally = 0;
#endif
    for (nrt_u64 it = NRT_GLOBAL_ID(); it < total; it += stride) {
#if NRT_REGIONS
        nrt_u64 photon, sl;
        int lband, fresh;
        if (!nrt_pass_item(it, order, emit, states, n_resume, n_fresh, fresh0, n_free, hwm, photon_start, count,
                           &photon, &lband, &sl, &fresh)) {
            keys_out[it] = ((nrt_u64)NRT_FREE_BIN << 32) | sl; /* a free slot no new packet took */
            continue;
        }
#else
        nrt_u64 t = NRT_SORTED ? (order[it] & NRT_KEY_LOW) : it;
        int lband = (int)(t / count);
        nrt_u64 photon = photon_start + t % count;
        const int fresh = 1;
#endif
        int band = band0 + lband;
        nrt_u64 slot = nrt_batch_of(photon, batch_base, batch_extra) - first_batch;
        nrt_u64 cell = slot * (nrt_u64)n_lbands + (nrt_u64)lband;
#if NRT_BIASED
        nrt_trace_packet_biased(density, optics[4 * band], optics[4 * band + 1], optics[4 * band + 2],
                                optics[4 * band + 3], window, prm->window_shape, stars,
                                star_cdf + band * n_stars, &medium, n_stars, seed, band, photon,
                                max_scatterings, track_scale, prm->collision_scale, acc + 2 * cell * nvox,
                                tallies + NRT_TALLY_WORDS * cell, overflow + slot, peel, peel_scale,
                                image + 2 * cell * pixels, optics + 4 * prm->n_bands + 4 * band,
                                image + prm->image_stokes + 2 * cell * pixels * NRT_STOKES_IMAGES);
#else
        sink.tally = tallies + NRT_TALLY_WORDS * cell;
        sink.home = NRT_GROUP_TALLY && cell == home_cell;
#if NRT_GROUP_TALLY
        sink.l_hot = l_hot;
        sink.l_hot_sq = l_hot_sq;
#else
        sink.l_hot = sink.l_hot_sq = 0;
#endif
        sink.hot_x = sink.hot_y = sink.hot_z = NRT_NO_HOT;
        if (fresh)
            nrt_count(&sink, 0);
#if NRT_REGIONS
        NRT_GLOBAL nrt_u64 *band_acc = acc + cell * nvox;
        NRT_OPAQUE_PTR(band_acc);
        int stopped = nrt_trace_packet(density, optics[4 * band], optics[4 * band + 1], optics[4 * band + 2], stars,
                                       star_cdf + band * n_stars, nx, ny, nz, n_stars, seed, band, photon,
                                       max_scatterings, track_scale, band_acc, &sink,
                                       overflow + slot, peel, peel_scale, image + cell * pixels,
                                       fresh ? 0 : states + sl, states + sl, region_shift,
                                       photon | ((nrt_u64)lband << NRT_ITEM_BAND_SHIFT), sq + cell * nvox, sq_shift,
                                       nvox, optics + 4 * prm->n_bands + 4 * band,
                                       image + prm->image_stokes + cell * pixels * NRT_STOKES_IMAGES,
                                       NRT_POLAR ? (NRT_GLOBAL float *)(states + prm->state_slots) + 6 * sl : 0);
        if (stopped) {
            const NRT_GLOBAL nrt_packet *q = states + sl;
            keys_out[it] = ((nrt_u64)nrt_region_bin(cell, q->ix, q->iy, q->iz, nx, ny, nz, region_shift) << 32) | sl;
        } else {
            keys_out[it] = ((nrt_u64)NRT_FREE_BIN << 32) | sl;
        }
#else
        (void)fresh;
        /* the band slot's first cell: formed once per packet, not again at each deposit */
        NRT_GLOBAL nrt_u64 *band_acc = acc + cell * nvox;
        NRT_OPAQUE_PTR(band_acc);
        nrt_trace_packet(density, optics[4 * band], optics[4 * band + 1], optics[4 * band + 2], stars,
                         star_cdf + band * n_stars, nx, ny, nz, n_stars, seed, band, photon,
                         max_scatterings, track_scale, band_acc, &sink,
                         overflow + slot, peel, peel_scale, image + cell * pixels, 0, 0, NRT_NO_REGIONS, 0,
                         sq + cell * nvox, sq_shift, nvox, optics + 4 * prm->n_bands + 4 * band,
                         image + prm->image_stokes + cell * pixels * NRT_STOKES_IMAGES, 0);
#endif
#endif
    }
#if NRT_GROUP_TALLY
    /* the group's local sums go to global memory once */
    NRT_BARRIER();
    for (nrt_u64 i = lid; i < 4; i += NRT_LOCAL_SIZE())
        if (l_tally[i] != 0)
            NRT_ATOMIC_ADD_U64(&tallies[NRT_TALLY_WORDS * home_cell + i], l_tally[i]);
    for (nrt_u64 i = lid; i < NRT_HOT_STARS * NRT_HOT_CELLS; i += NRT_LOCAL_SIZE()) {
        /* only cells something was added to: those lie inside the grid */
        int s = (int)(i / NRT_HOT_CELLS), c = (int)(i % NRT_HOT_CELLS);
        if (s >= n_stars || (l_hot[i] == 0 && (!NRT_PACKET_SQ || l_hot_sq[NRT_PACKET_SQ ? i : 0] == 0)))
            continue;
        float p[3] = {stars[4 * s], stars[4 * s + 1], stars[4 * s + 2]};
        int ix, iy, iz;
        nrt_voxel_of(p, nx, ny, nz, &ix, &iy, &iz);
        ix += c % NRT_HOT_SIDE - NRT_HOT_HALF;
        iy += (c / NRT_HOT_SIDE) % NRT_HOT_SIDE - NRT_HOT_HALF;
        iz += c / (NRT_HOT_SIDE * NRT_HOT_SIDE) - NRT_HOT_HALF;
        nrt_u64 v = home_cell * nvox + (nrt_u64)nrt_voxel_index(ix, iy, iz, nx, ny);
        nrt_acc_add(&acc[v], l_hot[i], overflow + home_slot);
#if NRT_PACKET_SQ
        if (l_hot_sq[i] != 0)
            NRT_ATOMIC_ADD_U64(&sq[v], l_hot_sq[i]);
#endif
    }
#endif
}

/*
 * Sort keys of a launch's packets (NRT_SORTED): high 32 bits the packet's cell (band offset and
 * batch slot, so a work group's packets share a home cell) and star (together modulo
 * 2^(31 - 2 NRT_SORT_BITS)), then its first direction: the first two uniforms of
 * nrt_sample_isotropic (mu and phi, equal-area bins) in 2^NRT_SORT_BITS x 2^NRT_SORT_BITS bins,
 * interleaved bit by bit (Morton order: consecutive keys stay in a compact patch of the
 * sphere); low 32 bits the work item t (count * n_lbands < 2^32), so that sorting the keys
 * (a counting sort by the high half: counting_sort_pass) yields the order itself. The draws
 * are those nrt_trace_packet makes, in the same order; the key only orders the work (any key
 * gives the same bits).
 */
NRT_DEVICE nrt_u32 nrt_spread_bits(nrt_u32 x) /* bit i -> bit 2i, for x < 2^16 */
{
    x &= 0xFFFFu;
    x = (x | (x << 8)) & 0x00FF00FFu;
    x = (x | (x << 4)) & 0x0F0F0F0Fu;
    x = (x | (x << 2)) & 0x33333333u;
    x = (x | (x << 1)) & 0x55555555u;
    return x;
}

NRT_KERNEL void emission_keys(const NRT_GLOBAL nrt_trace_params *prm, const nrt_launch launch,
                              const NRT_GLOBAL float *star_cdf, NRT_GLOBAL nrt_u64 *keys)
{
    const nrt_u64 photon_start = launch.photon_start, count = launch.count, first_batch = launch.first_batch;
    const int band0 = launch.band0, n_lbands = launch.n_lbands, n_slots = launch.slots;
    nrt_u64 total = count * (nrt_u64)n_lbands;
    for (nrt_u64 t = NRT_GLOBAL_ID(); t < total; t += NRT_GLOBAL_SIZE()) {
        int lband = (int)(t / count);
        int band = band0 + lband;
        nrt_u64 photon = photon_start + t % count;
        nrt_u64 slot = nrt_batch_of(photon, prm->batch_base, prm->batch_extra) - first_batch;
        nrt_rng rng;
        nrt_rng_init(&rng, prm->seed, (nrt_u64)band, photon);
        int s = nrt_choose_star(&rng, star_cdf + band * prm->n_stars, prm->n_stars);
        const nrt_u32 bins = 1u << NRT_SORT_BITS;
        nrt_u32 bm = (nrt_u32)(nrt_rng_uniform(&rng) * (float)bins);
        nrt_u32 bp = (nrt_u32)(nrt_rng_uniform(&rng) * (float)bins);
        bm = bm >= bins ? bins - 1u : bm;
        bp = bp >= bins ? bins - 1u : bp;
        nrt_u32 dir = (nrt_spread_bits(bm) << 1) | nrt_spread_bits(bp);
        /* (the high half stays below 2^31, so that no key is NRT_FREE_BIN's) */
        nrt_u64 group = (((nrt_u64)lband * (nrt_u64)n_slots + slot) * (nrt_u64)prm->n_stars + (nrt_u64)s)
                        & ((1UL << (31 - 2 * NRT_SORT_BITS)) - 1UL);
        keys[t] = ((group << (2 * NRT_SORT_BITS) | (nrt_u64)dir) << 32) | t;
    }
}

/*
 * Counting sort of the packets a pass stopped (NRT_REGIONS): keys (bin << 32 | state slot),
 * NRT_FREE_BIN for the slots of the packets that ended (counted in the last bin, n_bins - 1,
 * so they follow every stopped packet), NRT_NO_KEY for none; and of the emission order
 * (NRT_SORTED). A first pass counts the keys of every bin, scan_bins turns the counts into
 * each bin's first position, and a second pass writes each key to its bin's range. Each work
 * group counts its keys in local memory first and adds one total per bin to global memory
 * (without, every packet leaving the star's region hit the same few counters); with more bins
 * than NRT_LOCAL_BINS the keys go to global memory one by one. The order within a bin depends on the thread order, which changes no bit of
 * the result (integer deposits).
 */
#ifndef NRT_LOCAL_BINS
#define NRT_LOCAL_BINS 8192 /* 32 KiB of local memory (CUDA's static limit per block is 48) */
#endif

/*
 * One pass of the counting sort over keys[0 .. n), by bin (key >> 32) >> bin_shift.
 * bins[b]: with scatter 0, the count of bin b (added to); with scatter 1, the next free
 * position of bin b in out (its first position before the call), each key written there.
 * The emission order (NRT_SORTED) is sorted the same way, by its keys' cell, star and the
 * leading bits of their direction bins.
 */
NRT_KERNEL void counting_sort_pass(const NRT_GLOBAL nrt_u64 *keys, nrt_u64 n, NRT_GLOBAL nrt_u32 *bins, int n_bins,
                                   int scatter, NRT_GLOBAL nrt_u64 *out, int bin_shift)
{
    /* the group's count of each bin, then (scatter) the first position of its range */
    NRT_LOCAL_MEM nrt_u32 l_count[NRT_LOCAL_BINS];
    const int local_bins = n_bins <= NRT_LOCAL_BINS;
    nrt_u64 lid = NRT_LOCAL_ID(), it = NRT_GLOBAL_ID();
    if (local_bins)
        for (nrt_u64 b = lid; b < (nrt_u64)n_bins; b += NRT_LOCAL_SIZE())
            l_count[b] = 0;
    NRT_BARRIER();
    nrt_u64 key = it < n ? keys[it] : NRT_NO_KEY;
    nrt_u32 bin = (nrt_u32)(key >> 32), rank = 0;
    if (bin == NRT_FREE_BIN)
        bin = (nrt_u32)n_bins - 1u; /* free slots: the last bin, after every stopped packet */
    else
        bin >>= bin_shift;
    if (key != NRT_NO_KEY) {
        if (local_bins) {
            rank = NRT_ATOMIC_ADD_U32_LOCAL(&l_count[bin], 1u);
        } else {
            nrt_u32 pos = NRT_ATOMIC_ADD_U32(&bins[bin], 1u);
            if (scatter)
                out[pos] = key;
        }
    }
    NRT_BARRIER();
    /* the group's count of each bin: added to the total, or its range reserved */
    if (local_bins)
        for (nrt_u64 b = lid; b < (nrt_u64)n_bins; b += NRT_LOCAL_SIZE())
            if (l_count[b] != 0)
                l_count[b] = NRT_ATOMIC_ADD_U32(&bins[b], l_count[b]);
    NRT_BARRIER();
    if (scatter && local_bins && key != NRT_NO_KEY)
        out[l_count[bin] + rank] = key;
}

/*
 * The counts of a counting sort's bins[0 .. n_bins) turned into each bin's first position (an
 * exclusive prefix sum, in place), and bins[n_bins] set to the keys of every bin but the last
 * (the packets a region pass stopped; the last bin holds the free slots). Launched as one work
 * group: each work item sums a contiguous run of bins, the first item scans the runs' totals,
 * and each item writes its run's prefix sums. On the device, so that the sort's second pass
 * follows its first without the host in between.
 */
#define NRT_SCAN_ITEMS 1024
NRT_KERNEL void scan_bins(NRT_GLOBAL nrt_u32 *bins, int n_bins)
{
    NRT_LOCAL_MEM nrt_u32 l_run[NRT_SCAN_ITEMS];
    nrt_u64 lid = NRT_LOCAL_ID(), items = NRT_LOCAL_SIZE();
    items = items < NRT_SCAN_ITEMS ? items : NRT_SCAN_ITEMS;
    nrt_u64 n = (nrt_u64)n_bins, per = (n + items - 1) / items;
    nrt_u64 b0 = lid * per, b1 = b0 + per < n ? b0 + per : n;
    nrt_u32 sum = 0;
    if (lid < items) {
        for (nrt_u64 b = b0; b < b1; ++b)
            sum += bins[b];
        l_run[lid] = sum;
    }
    NRT_BARRIER();
    if (lid == 0) {
        nrt_u32 run = 0;
        for (nrt_u64 i = 0; i < items; ++i) {
            nrt_u32 c = l_run[i];
            l_run[i] = run;
            run += c;
        }
    }
    NRT_BARRIER();
    if (lid < items) {
        nrt_u32 run = l_run[lid];
        for (nrt_u64 b = b0; b < b1; ++b) {
            nrt_u32 c = bins[b];
            bins[b] = run;
            run += c;
        }
        if (b0 < b1 && b1 == n)
            bins[n] = bins[n - 1]; /* the last bin's first position */
    }
}

/* The centred sums of squares are stored in float32 times 2^-64, so that any sum of squared
   64-bit totals fits (2^128 is float32's limit) and the smallest non-zero one (about 1 unit^2)
   stays normal. */
#define NRT_M2_DOWN 5.42101086242752217e-20 /* 2^-64 */
#define NRT_M2_UP 18446744073709551616.0    /* 2^64 */
/* 128-bit totals are folded times 2^-32 (exact), so the statistics keep the 64-bit layout:
   squares of totals up to the 2^127 limit stay within float32 x 2^64, and a deposit of 2^16
   units (weights near 2^-72 of a packet) still gives a normal float32 square */
#define NRT_FOLD_SCALE 2.3283064365386963e-10 /* 2^-32 */

/*
 * Fold the batch slots 0..n_slots-1 of the accumulator, in batch order, into per-cell running
 * statistics of the batch totals, and clear them: the sum (float64; exact while below 2^53)
 * and the centred sum of squares M2 = sum (x - mean)^2 (Welford's update, formed in float64,
 * stored in float32 x 2^-64: 4 bytes where a raw sum of squares would need float64 and still
 * lose the variance to cancellation once the batch totals agree to 8 digits). The slots hold
 * cells 0..n-1 of this launch's bands, which are cells cell0 .. cell0 + n - 1 of the sums;
 * the k0 batches folded before are in the sums. A slot whose overflow flag is set is cleared
 * without folding (the host re-traces that batch in halves). clear 0: the slots are not traced
 * into again (the run's last fold), so only an overflowed slot is cleared (writing the zeros
 * back was about a third of the fold's memory traffic). Each cell is folded by one work
 * item in a fixed order, so the sums are deterministic. With NRT_ACC_RED the deposits were not
 * checked as they were added: a cell at or past the headroom limit raises *seen (the host then
 * re-runs with checked adds).
 */
NRT_KERNEL void fold_batches(NRT_GLOBAL nrt_u64 *acc, NRT_GLOBAL double *sum1, NRT_GLOBAL float *m2,
                             const NRT_GLOBAL nrt_u32 *overflow, int n_slots, nrt_u64 n,
                             nrt_u64 cell0, int k0, NRT_GLOBAL nrt_u32 *seen, int clear)
{
    nrt_u64 gid = NRT_GLOBAL_ID();
    if (gid >= n)
        return;
    double s1 = sum1[cell0 + gid];
    double q = (double)m2[cell0 + gid] * NRT_M2_UP;
    double k = (double)k0;
    int past = 0, changed = 0;
    for (int g = 0; g < n_slots; ++g) {
        nrt_u64 i = (nrt_u64)g * n + gid;
#if NRT_BIASED
        /* a 128-bit cell: low word, high word */
        nrt_u64 a = acc[2 * i] | acc[2 * i + 1];
        past |= acc[2 * i + 1] >= NRT_ACC_LIMIT;
        double x = ((double)acc[2 * i + 1] * 18446744073709551616.0 + (double)acc[2 * i]) * NRT_FOLD_SCALE;
#else
        nrt_u64 a = acc[i];
        past |= a >= NRT_ACC_LIMIT;
        double x = (double)a;
#endif
        if (!overflow[g]) {
            if (k > 0.0) {
                double mean_old = s1 / k;
                s1 += x;
                q += (x - mean_old) * (x - s1 / (k + 1.0));
                /* rounded as stored after every batch, so the bits do not depend on how
                   many batches one fold takes */
                q = (double)(float)(q * NRT_M2_DOWN) * NRT_M2_UP;
            } else {
                s1 = x;
            }
            k += 1.0;
        }
        changed |= a != 0;
        if (a != 0 && (clear || overflow[g])) {
#if NRT_BIASED
            acc[2 * i] = 0;
            acc[2 * i + 1] = 0;
#else
            acc[i] = 0;
#endif
        }
    }
    /* cells that no batch has reached yet are left untouched (no memory traffic) */
    if (changed || s1 != 0.0) {
        sum1[cell0 + gid] = s1;
        m2[cell0 + gid] = (float)(q * NRT_M2_DOWN); /* exact: q is a stored value already */
    }
    if (NRT_ACC_RED && past)
        NRT_ATOMIC_OR_U32(seen, 1u);
}

/*
 * The error estimate by packets (NRT_PACKET_SQ), after the run's one batch: the centred sum of
 * squares of the packets' totals per cell, q = S 2^sq_shift - T^2 / N (T the cell's sum, S its
 * sum of squares, N the packets per band), stored as float32 x 2^-64 as the fold stores it,
 * in place of the squares: element i of the float32 view of sq, for cells [i0, i1). Float i
 * lies in 64-bit word i / 2, so a launch over [i0, 2 i0) (or [0, 1)) only overwrites words
 * earlier launches have read: the host launches [0, 1), [1, 2), [2, 4), ... . A cell at or past
 * the headroom limit raises *seen (the shift and scale keep every cell below it).
 */
NRT_KERNEL void packet_m2(const NRT_GLOBAL nrt_u64 *acc, NRT_GLOBAL nrt_u64 *sq, nrt_u64 i0, nrt_u64 i1,
                          double inv_n, double sq_unit, NRT_GLOBAL nrt_u32 *seen)
{
    nrt_u64 i = i0 + NRT_GLOBAL_ID();
    if (i >= i1)
        return;
    nrt_u64 a = acc[i], b = sq[i];
    double t = (double)a;
    double q = (double)b * sq_unit - t * t * inv_n;
    if (a >= NRT_ACC_LIMIT || b >= NRT_ACC_LIMIT)
        NRT_ATOMIC_OR_U32(seen, 1u);
    ((NRT_GLOBAL float *)sq)[i] = (float)(q > 0.0 ? q * NRT_M2_DOWN : 0.0);
}

/* The sums of the run's one batch (NRT_PACKET_SQ) as float64, in place (same width). */
NRT_KERNEL void packet_sum1(NRT_GLOBAL nrt_u64 *acc, nrt_u64 n)
{
    nrt_u64 i = NRT_GLOBAL_ID();
    if (i < n)
        ((NRT_GLOBAL double *)acc)[i] = (double)acc[i];
}

/* Clear a 64-bit buffer. */
NRT_KERNEL void clear_u64(NRT_GLOBAL nrt_u64 *buf, nrt_u64 n)
{
    nrt_u64 gid = NRT_GLOBAL_ID();
    if (gid < n)
        buf[gid] = 0;
}
