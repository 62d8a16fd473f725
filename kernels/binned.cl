/*
 * Binned deposits (the backend's transport tuning "deposits": "binned"; docs/physics.md): the
 * track-length estimator of analog packets on a grid, with the flights sampled by delta
 * tracking instead of a walk through the voxels, and their track lengths added block by block
 * in local memory instead of one global atomic add per voxel visit.
 *
 * Why: the walk's global adds are its limit (benchmarks/results/h100-2026-12-05d: the same
 * visits added with the same atomics but no walk ran no faster), and from 256^3 up binning them
 * by block went 2-3x past it.
 *
 * How, for a sub-launch of one band's packets photon_start .. + count (one or more batch
 * slots; a bin is a slot's block):
 *   - a flight is sampled by delta tracking (Woodcock) against the largest density of each
 *     majorant cell (NRT_MAJ^3 voxels, rho_max): a tentative collision at the cell's majorant
 *     is real with probability rho / rho_max, else the flight goes on; where a cell's density
 *     is uniform every tentative collision is real;
 *   - the flight is cut where it crosses a block face; each piece (start, length, direction:
 *     a 32-byte record) belongs to one block;
 *   - NRT_BIN_MODE 0 (count): each work group counts its pieces per bin of the two slots its
 *     consecutive packets lie in (local memory, or its own rows of `ghist` for large grids),
 *     then adds its counts to the bins' totals, keeping the offsets (group_off) the totals
 *     had; the pieces of packets in any other slot are drawn at once with global atomics;
 *   - NRT_BIN_MODE 1 (write): the same walk (the same random numbers: the same pieces) writes
 *     each record at its bin's bucket start + the group's offset + its running count;
 *   - NRT_BIN_MODE 2 (direct): each piece drawn at once with a global atomic add per visit
 *     (the check of the other two: the same sums, bit for bit);
 *   - binned_draw: one work group per chunk of a bin's records draws them into the block's
 *     cells in local memory (64-bit sums as two 32-bit words with the carry), then adds each
 *     nonzero cell to the slot once (checked against the headroom).
 * Every visit's deposit is nrt_fixed(length, track_scale), and integer sums do not depend on
 * the order: the same bits for any launch split, device or number of ranks. The random numbers
 * are spent differently from the walk's (kernels/transport.cl), so the two give different bits
 * for the same seed, each an unbiased estimate of the same J.
 */
#include "transport.cl"

#ifndef NRT_BIN_MODE
#define NRT_BIN_MODE 0
#endif
#ifndef NRT_BLOCK
#define NRT_BLOCK 16
#endif
/* blocks per axis (ceil(n / NRT_BLOCK)) and in all */
#define NRT_BX ((NRT_NX + NRT_BLOCK - 1) / NRT_BLOCK)
#define NRT_BY ((NRT_NY + NRT_BLOCK - 1) / NRT_BLOCK)
#define NRT_BZ ((NRT_NZ + NRT_BLOCK - 1) / NRT_BLOCK)
#define NRT_NBLOCKS (NRT_BX * NRT_BY * NRT_BZ)
/* delta tracking's majorant cells: NRT_MAJ^3 voxels, NRT_CPB of them along a block's edge (on
   the lognormal medium, 4^3 cells make about 3.5x fewer tentative collisions than 16^3
   blocks: docs/physics.md) */
#ifndef NRT_MAJ
#define NRT_MAJ NRT_BLOCK
#endif
#if NRT_BLOCK % NRT_MAJ
#error "a block's edge must be a whole number of majorant cells"
#endif
#define NRT_CPB (NRT_BLOCK / NRT_MAJ)
#define NRT_MX ((NRT_NX + NRT_MAJ - 1) / NRT_MAJ)
#define NRT_MY ((NRT_NY + NRT_MAJ - 1) / NRT_MAJ)
#define NRT_MZ ((NRT_NZ + NRT_MAJ - 1) / NRT_MAJ)
#define NRT_BLOCK_CELLS (NRT_BLOCK * NRT_BLOCK * NRT_BLOCK)
#ifndef NRT_BIN_GLOBAL
#define NRT_BIN_GLOBAL 0 /* 1: the groups' counts per block in global memory (ghist) */
#endif
#define NRT_REC_WORDS 8

/* a record as two 16-byte stores and loads (records start at multiples of 32 bytes) */
#if defined(__OPENCL_VERSION__)
#define NRT_STORE4(ptr, a, b, c, d) vstore4((float4)((a), (b), (c), (d)), 0, (ptr))
#define NRT_LOAD4(ptr) vload4(0, (ptr))
#else
#define NRT_STORE4(ptr, a, b, c, d) (*(float4 *)(ptr) = make_float4((a), (b), (c), (d)))
#define NRT_LOAD4(ptr) (*(const float4 *)(ptr))
#endif

NRT_DEVICE int nrt_clampi(int v, int lo, int hi)
{
    return v < lo ? lo : (v > hi ? hi : v);
}

/*
 * The visits of the piece from p along d of length len (box units) inside block (bx, by, bz):
 * a DDA from p's voxel (clamped into the block and the grid: p lies on the block's face up to
 * rounding), each visit's deposit v = nrt_fixed(length, scale) handed to DEPOSIT with its voxel
 * (ix, iy, iz). A step out of the block or the grid by rounding ends the piece (what is left,
 * below a float32 ulp of len, is not added).
 */
#define NRT_DRAW_PIECE(DEPOSIT)                                                                   \
    do {                                                                                          \
        const int x0 = bx * NRT_BLOCK, y0 = by * NRT_BLOCK, z0 = bz * NRT_BLOCK;                  \
        const int x1 = min(x0 + NRT_BLOCK, NRT_NX), y1 = min(y0 + NRT_BLOCK, NRT_NY),             \
                  z1 = min(z0 + NRT_BLOCK, NRT_NZ);                                               \
        const float inv0 = 1.0f / d0, inv1 = 1.0f / d1, inv2 = 1.0f / d2;                         \
        int ix = nrt_clampi((int)floor(p0 * (float)NRT_NX), x0, x1 - 1);                          \
        int iy = nrt_clampi((int)floor(p1 * (float)NRT_NY), y0, y1 - 1);                          \
        int iz = nrt_clampi((int)floor(p2 * (float)NRT_NZ), z0, z1 - 1);                          \
        float tx = nrt_face_distance(p0, d0, inv0, ix, hx);                                       \
        float ty = nrt_face_distance(p1, d1, inv1, iy, hy);                                       \
        float tz = nrt_face_distance(p2, d2, inv2, iz, hz);                                       \
        float t_cur = 0.0f;                                                                       \
        for (;;) {                                                                                \
            float t_next = fmin(tx, fmin(ty, tz));                                                \
            int end = t_next >= len;                                                              \
            float t_end = end ? len : t_next;                                                     \
            nrt_u64 v = nrt_fixed(fmax(0.0f, t_end - t_cur), scale);                              \
            DEPOSIT;                                                                              \
            if (end)                                                                              \
                break;                                                                            \
            t_cur = t_end;                                                                        \
            int on_x = tx <= ty && tx <= tz;                                                      \
            int on_y = !on_x && ty <= tz;                                                         \
            int ax = on_x ? 0 : (on_y ? 1 : 2);                                                   \
            float d_ax = on_x ? d0 : (on_y ? d1 : d2);                                            \
            int i_next = (on_x ? ix : (on_y ? iy : iz)) + (d_ax > 0.0f ? 1 : -1);                 \
            if (i_next < (on_x ? x0 : (on_y ? y0 : z0)) || i_next >= (on_x ? x1 : (on_y ? y1 : z1))) \
                break;                                                                            \
            const float p_[3] = {p0, p1, p2}, inv_[3] = {inv0, inv1, inv2};                       \
            nrt_cross_face(ax, i_next, p_, d_ax, inv_, hx, hy, hz, &ix, &iy, &iz, &tx, &ty, &tz); \
        }                                                                                         \
    } while (0)

NRT_DEVICE void nrt_draw_global(NRT_GLOBAL nrt_u64 *band_acc, NRT_GLOBAL nrt_u32 *overflow, int bx, int by,
                                int bz, float p0, float p1, float p2, float d0, float d1, float d2, float len,
                                float scale, float hx, float hy, float hz)
{
    NRT_DRAW_PIECE(nrt_acc_add_checked(&band_acc[nrt_voxel_index(ix, iy, iz, NRT_NX, NRT_NY)], v, overflow));
}

NRT_DEVICE void nrt_draw_local(NRT_LOCAL nrt_u64 *cells, int bx, int by, int bz, float p0, float p1, float p2,
                               float d0, float d1, float d2, float len, float scale, float hx, float hy, float hz)
{
    NRT_DRAW_PIECE(nrt_local_add(&cells[((iz - z0) * NRT_BLOCK + (iy - y0)) * NRT_BLOCK + (ix - x0)], v));
}

/* One piece of a flight in block b from q along d for len: counted, written or drawn. Pieces
   of a packet outside the group's two slots (batches smaller than a group's packets) are drawn
   at once with global atomics: the same sums. */
#define NRT_DRAW_NOW(b, q0, q1, q2, len_)                                                                   \
    nrt_draw_global(acc + cell * nvox, overflow + slot, (b)[0], (b)[1], (b)[2], (q0), (q1), (q2), d[0], d[1], \
                    d[2], (len_), track_scale, hx, hy, hz)
#if NRT_BIN_MODE == 2
#define NRT_PIECE(b, q0, q1, q2, len_) NRT_DRAW_NOW(b, q0, q1, q2, len_)
#else
#define NRT_PIECE(b, q0, q1, q2, len_)                                                                     \
    do {                                                                                                   \
        int blk_ = ((b)[2] * NRT_BY + (b)[1]) * NRT_BX + (b)[0];                                           \
        if (w > 1) {                                                                                       \
            if (NRT_BIN_MODE == 0)                                                                         \
                NRT_DRAW_NOW(b, q0, q1, q2, len_);                                                         \
        } else {                                                                                           \
            nrt_u32 k_ = NRT_HIST_ADD(w * NRT_NBLOCKS + blk_);                                             \
            NRT_WRITE_RECORD(w, blk_, k_, (q0), (q1), (q2), (len_));                                       \
        }                                                                                                  \
    } while (0)
#if NRT_BIN_MODE == 1
#define NRT_WRITE_RECORD(w, blk, k, q0, q1, q2, len_)                                                      \
    do {                                                                                                   \
        NRT_GLOBAL float *r_ = rec + (nrt_u64)NRT_REC_WORDS * ((nrt_u64)bucket[(slot - slot0) * NRT_NBLOCKS + (blk)] \
                                                              + my_off[(w) * NRT_NBLOCKS + (blk)] + (k));  \
        NRT_STORE4(r_, q0, q1, q2, len_);                                                                  \
        NRT_STORE4(r_ + 4, d[0], d[1], d[2], 0.0f);                                                        \
    } while (0)
#else
#define NRT_WRITE_RECORD(w, blk, k, q0, q1, q2, len_) ((void)(k))
#endif
#endif
/* the two slots of a work group's window: its counts (local, or its own rows in global
   memory), its tallies */
#define NRT_WINDOW (2 * NRT_NBLOCKS)

/*
 * The walk of packets photon_start .. photon_start + count - 1 of band `band` (band offset
 * lband of the launch's n_lb), which belong to batch slots slot0 .. slot0 + n_slots - 1 (slot =
 * batch - first_batch; cell = slot n_lb + lband: tallies, deposits; bin = (slot - slot0)
 * NRT_NBLOCKS + block). Work group g takes the `per_item` x group-size packets from
 * g per_item (group size), each work item every group-size-th of them, so a group's packets
 * are consecutive and lie in at most two slots where a batch holds at least a group's
 * packets: its window, whose counts per block the group keeps.
 */
NRT_KERNEL void binned_walk(const NRT_GLOBAL nrt_trace_params *prm, nrt_u64 photon_start, nrt_u64 count,
                            int per_item, int band, int lband, int n_lb, nrt_u64 first_batch, nrt_u64 slot0,
                            const NRT_GLOBAL float *density, const NRT_GLOBAL float *rho_max,
                            const NRT_GLOBAL float *optics, const NRT_GLOBAL float *stars,
                            const NRT_GLOBAL float *star_cdf, NRT_GLOBAL nrt_u64 *acc, NRT_GLOBAL nrt_u64 *tallies,
                            NRT_GLOBAL nrt_u32 *overflow, NRT_GLOBAL nrt_u32 *bin_count, NRT_GLOBAL nrt_u32 *group_off,
                            const NRT_GLOBAL nrt_u32 *bucket, NRT_GLOBAL float *rec, NRT_GLOBAL nrt_u32 *ghist)
{
    const nrt_u64 group = NRT_GROUP_FIRST_ID() / NRT_LOCAL_SIZE(), gsize = NRT_LOCAL_SIZE();
    const nrt_u64 batch_base = prm->batch_base, batch_extra = prm->batch_extra;
    /* the group's packets and the first slot of its window */
    const nrt_u64 g0 = group * gsize * (nrt_u64)per_item;
    const nrt_u64 s_a = g0 < count ? nrt_batch_of(photon_start + g0, batch_base, batch_extra) - first_batch : 0;
    NRT_LOCAL_MEM nrt_u64 l_tally[2 * 4];
#if NRT_BIN_MODE != 2 && !NRT_BIN_GLOBAL
    NRT_LOCAL_MEM nrt_u32 hist[NRT_WINDOW];
    for (int b = (int)NRT_LOCAL_ID(); b < NRT_WINDOW; b += (int)gsize)
        hist[b] = 0;
#define NRT_HIST_ADD(i) NRT_ATOMIC_ADD_U32_LOCAL(&hist[i], 1u)
#define NRT_HIST_READ(i) hist[i]
    (void)ghist;
#else
    /* the group's own rows of counts (count) or running slots (write), zeroed by the host */
    NRT_GLOBAL nrt_u32 *my_hist = ghist + group * NRT_WINDOW;
#define NRT_HIST_ADD(i) NRT_ATOMIC_ADD_U32(&my_hist[i], 1u)
#define NRT_HIST_READ(i) NRT_ATOMIC_ADD_U32(&my_hist[i], 0u)
#endif
    for (nrt_u64 i = NRT_LOCAL_ID(); i < 2 * 4; i += gsize)
        l_tally[i] = 0;
    NRT_BARRIER();
#if NRT_BIN_MODE == 1
    const NRT_GLOBAL nrt_u32 *my_off = group_off + group * NRT_WINDOW;
#endif
    const nrt_u64 nvox = prm->cells, seed = prm->seed;
    const int n_stars = prm->n_stars, max_scatterings = prm->max_scatterings;
    const float track_scale = prm->track_scale;
    const float hx = 1.0f / (float)NRT_NX, hy = 1.0f / (float)NRT_NY, hz = 1.0f / (float)NRT_NZ;
    const float ch[3] = {(float)NRT_MAJ * hx, (float)NRT_MAJ * hy, (float)NRT_MAJ * hz};
    const int cmax[3] = {NRT_MX - 1, NRT_MY - 1, NRT_MZ - 1};
    const float sig_b = optics[4 * band], alb_b = optics[4 * band + 1], g_b = optics[4 * band + 2];
    (void)bin_count, (void)group_off, (void)bucket, (void)rec, (void)slot0;
    for (int k = 0; k < per_item; ++k) {
        const nrt_u64 it = g0 + (nrt_u64)k * gsize + NRT_LOCAL_ID();
        if (it >= count)
            break;
        const nrt_u64 photon = photon_start + it;
        const nrt_u64 slot = nrt_batch_of(photon, batch_base, batch_extra) - first_batch;
        const nrt_u64 cell = slot * (nrt_u64)n_lb + (nrt_u64)lband;
        const nrt_u64 w = slot - s_a; /* 0, 1: the window; more: drawn at once */
#define NRT_TALLY(t)                                                               \
        do {                                                                       \
            if (w < 2)                                                             \
                nrt_local_count(&l_tally[4 * w + (t)]);                            \
            else if (NRT_BIN_MODE != 1)                                            \
                NRT_ATOMIC_ADD_U64(&tallies[NRT_TALLY_WORDS * cell + (t)], 1UL);   \
        } while (0)
        nrt_rng rng;
        nrt_rng_init(&rng, seed, (nrt_u64)band, photon);
        int s = nrt_choose_star(&rng, star_cdf + band * n_stars, n_stars);
        float p[3] = {stars[4 * s], stars[4 * s + 1], stars[4 * s + 2]}, d[3];
        nrt_sample_isotropic(&rng, d);
        NRT_TALLY(0);
        int scatterings = 0;
        for (;;) {
            const float inv[3] = {1.0f / d[0], 1.0f / d[1], 1.0f / d[2]};
            /* the box's exit */
            float t_exit = NRT_INF_F;
            for (int a = 0; a < 3; ++a) {
                float f = d[a] > 0.0f ? 1.0f : 0.0f;
                t_exit = fabs(d[a]) > 0.0f ? fmin(t_exit, (f - p[a]) * inv[a]) : t_exit;
            }
            t_exit = fmax(t_exit, 0.0f);
            /* delta tracking cell by cell (the majorant cells, NRT_MAJ^3 voxels), the flight
               cut into pieces at the blocks' faces: len is where the flight ends (the box's
               exit unless a real collision comes first), t0 where the block's piece began */
            int c[3], b[3];
            float tc[3];
            for (int a = 0; a < 3; ++a) {
                c[a] = nrt_clampi((int)floor(p[a] / ch[a]), 0, cmax[a]);
                b[a] = c[a] / NRT_CPB;
                tc[a] = nrt_face_distance(p[a], d[a], inv[a], c[a], ch[a]);
            }
            float len = t_exit, t = 0.0f, t0 = 0.0f;
            int escaped = 1;
            for (;;) {
                const float t_next = fmin(tc[0], fmin(tc[1], tc[2]));
                const float rmax = rho_max[(c[2] * NRT_MY + c[1]) * NRT_MX + c[0]];
                const float t_end = fmin(t_next, t_exit);
                if (sig_b * rmax > 0.0f) {
                    const float inv_maj = 1.0f / (sig_b * rmax);
                    for (;;) {
                        t += nrt_sample_tau(&rng) * inv_maj;
                        if (t >= t_end)
                            break;
                        float q[3] = {p[0] + d[0] * t, p[1] + d[1] * t, p[2] + d[2] * t};
                        int vx = nrt_clampi((int)floor(q[0] * (float)NRT_NX), c[0] * NRT_MAJ,
                                            min(c[0] * NRT_MAJ + NRT_MAJ, NRT_NX) - 1);
                        int vy = nrt_clampi((int)floor(q[1] * (float)NRT_NY), c[1] * NRT_MAJ,
                                            min(c[1] * NRT_MAJ + NRT_MAJ, NRT_NY) - 1);
                        int vz = nrt_clampi((int)floor(q[2] * (float)NRT_NZ), c[2] * NRT_MAJ,
                                            min(c[2] * NRT_MAJ + NRT_MAJ, NRT_NZ) - 1);
                        float rho = density[nrt_voxel_index(vx, vy, vz, NRT_NX, NRT_NY)];
                        if (nrt_rng_uniform(&rng) * rmax < rho) {
                            len = t, escaped = 0;
                            break;
                        }
                    }
                }
                if (escaped)
                    t = t_end; /* (memoryless: the overshoot dropped, the next cell samples afresh) */
                int on_x = tc[0] <= tc[1] && tc[0] <= tc[2];
                int on_y = !on_x && tc[1] <= tc[2];
                int a = on_x ? 0 : (on_y ? 1 : 2);
                int nc = c[a] + (d[a] > 0.0f ? 1 : -1);
                const int over = t_next >= len;
                /* (out: rounding put the box's exit a hair beyond the last cell's face) */
                const int out = !over && (nc < 0 || nc > cmax[a]);
                if (over || out || nc / NRT_CPB != b[a]) {
                    const float t1 = fmin(t_next, len);
                    if (t1 > t0)
                        NRT_PIECE(b, p[0] + d[0] * t0, p[1] + d[1] * t0, p[2] + d[2] * t0, t1 - t0);
                    t0 = t1;
                }
                if (over || out)
                    break;
                c[a] = nc;
                b[a] = nc / NRT_CPB;
                tc[a] = nrt_face_distance(p[a], d[a], inv[a], nc, ch[a]);
            }
            if (escaped) {
                NRT_TALLY(2);
                break;
            }
            p[0] = p[0] + d[0] * len, p[1] = p[1] + d[1] * len, p[2] = p[2] + d[2] * len;
            /* scatter with probability albedo (analog Russian roulette), else absorbed */
            if (nrt_rng_uniform(&rng) >= alb_b) {
                NRT_TALLY(1);
                break;
            }
            if (scatterings >= max_scatterings) {
                NRT_TALLY(3);
                break;
            }
            ++scatterings;
            float mu, st;
            nrt_sample_hg(g_b, nrt_rng_uniform(&rng), &mu, &st);
            nrt_rotate(d, mu, st, 2.0f * NRT_PI_F * nrt_rng_uniform(&rng));
        }
    }
    NRT_BARRIER();
#if NRT_BIN_MODE != 1 /* (the writing walk repeats the counting walk's packets) */
    for (nrt_u64 i = NRT_LOCAL_ID(); i < 2 * 4; i += gsize)
        if (l_tally[i] != 0)
            NRT_ATOMIC_ADD_U64(&tallies[NRT_TALLY_WORDS * ((s_a + i / 4) * (nrt_u64)n_lb + (nrt_u64)lband) + i % 4],
                               l_tally[i]);
#endif
#if NRT_BIN_MODE == 0
    for (int i = (int)NRT_LOCAL_ID(); i < NRT_WINDOW; i += (int)gsize) {
        nrt_u32 c = NRT_HIST_READ(i);
        nrt_u64 bin = (s_a + (nrt_u64)(i / NRT_NBLOCKS) - slot0) * NRT_NBLOCKS + (nrt_u64)(i % NRT_NBLOCKS);
        group_off[group * NRT_WINDOW + i] = c ? NRT_ATOMIC_ADD_U32(&bin_count[bin], c) : 0u;
    }
#endif
}

/*
 * Draw chunks k = group, group + groups, ... < n_chunks: chunk k is records chunk_start[k] ..
 * + chunk_len[k] of bin chunk_bin[k] (slot slot0 + bin / NRT_NBLOCKS, block bin % NRT_NBLOCKS),
 * into the block's cells in local memory, then added to the cell's slot once, checked against
 * the headroom.
 */
NRT_KERNEL void binned_draw(const NRT_GLOBAL nrt_trace_params *prm, nrt_u64 slot0, int lband, int n_lb,
                            const NRT_GLOBAL nrt_u32 *chunk_bin, const NRT_GLOBAL nrt_u32 *chunk_start,
                            const NRT_GLOBAL nrt_u32 *chunk_len, nrt_u64 n_chunks, const NRT_GLOBAL float *rec,
                            NRT_GLOBAL nrt_u64 *acc, NRT_GLOBAL nrt_u32 *overflow)
{
    NRT_LOCAL_MEM nrt_u64 cells[NRT_BLOCK_CELLS];
    const float track_scale = prm->track_scale;
    const float hx = 1.0f / (float)NRT_NX, hy = 1.0f / (float)NRT_NY, hz = 1.0f / (float)NRT_NZ;
    const nrt_u64 groups = NRT_GLOBAL_SIZE() / NRT_LOCAL_SIZE();
    for (nrt_u64 k = NRT_GROUP_FIRST_ID() / NRT_LOCAL_SIZE(); k < n_chunks; k += groups) {
        for (int c = (int)NRT_LOCAL_ID(); c < NRT_BLOCK_CELLS; c += (int)NRT_LOCAL_SIZE())
            cells[c] = 0;
        NRT_BARRIER();
        const nrt_u64 bin = chunk_bin[k], slot = slot0 + bin / NRT_NBLOCKS;
        const int blk = (int)(bin % NRT_NBLOCKS);
        const int bx = blk % NRT_BX, by = (blk / NRT_BX) % NRT_BY, bz = blk / (NRT_BX * NRT_BY);
        const nrt_u64 start = chunk_start[k];
        const int n = (int)chunk_len[k];
        for (int i = (int)NRT_LOCAL_ID(); i < n; i += (int)NRT_LOCAL_SIZE()) {
            const NRT_GLOBAL float *r = rec + (nrt_u64)NRT_REC_WORDS * (start + (nrt_u64)i);
            const float4 a = NRT_LOAD4(r), e = NRT_LOAD4(r + 4);
            nrt_draw_local(cells, bx, by, bz, a.x, a.y, a.z, e.x, e.y, e.z, a.w, track_scale, hx, hy, hz);
        }
        NRT_BARRIER();
        NRT_GLOBAL nrt_u64 *band_acc = acc + (slot * (nrt_u64)n_lb + (nrt_u64)lband) * prm->cells;
        for (int c = (int)NRT_LOCAL_ID(); c < NRT_BLOCK_CELLS; c += (int)NRT_LOCAL_SIZE()) {
            nrt_u64 v = cells[c];
            if (v) {
                int x = bx * NRT_BLOCK + c % NRT_BLOCK, y = by * NRT_BLOCK + (c / NRT_BLOCK) % NRT_BLOCK,
                    z = bz * NRT_BLOCK + c / (NRT_BLOCK * NRT_BLOCK);
                nrt_acc_add_checked(&band_acc[nrt_voxel_index(x, y, z, NRT_NX, NRT_NY)], v, overflow + slot);
            }
        }
        NRT_BARRIER(); /* (the next chunk zeroes the cells) */
    }
}
