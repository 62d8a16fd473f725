/*
 * A probe of a different transport for the neb medium (benchmarks/probe_binned_deposits.py):
 * flights sampled without visiting voxels, their track lengths binned by block of voxels and
 * added in on-chip memory. Not the library's transport: it measures whether the deposits can
 * go past the atomic walk limit (README, "Beside MCX and MCX-CL").
 *
 * Coordinates are voxel units, the box [0, N]^3. Analog packets from an isotropic point
 * source at P_SRC, extinction KAPPA rho per voxel length (no walk through the voxels: a uniform
 * medium's free path in closed form, tau / KAPPA; else delta tracking), albedo ALBEDO, Henyey-Greenstein
 * G. Each flight is cut where it crosses a block face (blocks of BB^3 voxels, NBLK per axis);
 * each piece is a record (start point, length, direction) that one work group later draws
 * into the block's cells in local memory, then adds the block's sums to the grid's once.
 *
 * Three passes of the same walk (the same random numbers, so the same flights):
 *   MODE_COUNT  each work group counts its records per block (local histogram), then adds the
 *               counts to the blocks' totals and keeps its offsets within each block;
 *   MODE_WRITE  the records written to their block's bucket (bucket start + the group's offset
 *               + the group's running count);
 *   MODE_DIRECT each record drawn at once into the grid with global 64-bit atomics (the same
 *               draw, so the same sums: the check of the binned passes).
 *
 * Build-time: N, BB, NBLK (= N / BB), KAPPA, ALBEDO, G, MODE, SCALE (fixed-point units per
 * voxel length), P_SRC, DENSITY (0: uniform; 1: a density per voxel, delta tracking against
 * each block's largest density).
 */
#include "nebula_common.h"

#define NB3 (NBLK * NBLK * NBLK)
#define BB3 (BB * BB * BB)
#define REC_WORDS 8
#ifndef DRAW_FLAT
#define DRAW_FLAT 0
#endif
#ifndef HIST_GLOBAL
#define HIST_GLOBAL 0
#endif
#ifndef DRAW_VARIANT
#define DRAW_VARIANT 0
#endif
#define PROBE_INF NRT_UINT_AS_FLOAT(0x7f800000u)
/* a record as two 16-byte stores and loads (its address is a multiple of 32 bytes) */
#if defined(__OPENCL_VERSION__)
#define PROBE_STORE4(ptr, a, b, c, d) vstore4((float4)((a), (b), (c), (d)), 0, (ptr))
#define PROBE_LOAD4(ptr) vload4(0, (ptr))
typedef float4 probe_f4;
#else
#define PROBE_STORE4(ptr, a, b, c, d) (*(float4 *)(ptr) = make_float4((a), (b), (c), (d)))
#define PROBE_LOAD4(ptr) (*(const float4 *)(ptr))
typedef float4 probe_f4;
#endif

/* distance along d from p to the face of voxel (or block) i of edge h on the side d points to;
   infinite where d is 0 */
NRT_DEVICE float probe_face(float p, float d, float inv, int i, float h)
{
    float f = (d > 0.0f) ? (float)(i + 1) * h : (float)i * h;
    float t = (f - p) * inv;
    return (d == 0.0f) ? PROBE_INF : t;
}

NRT_DEVICE int probe_clampi(int v, int lo, int hi)
{
    return v < lo ? lo : (v > hi ? hi : v);
}

/* Draw the segment from p along d of length len into the block (bx, by, bz): a DDA from p's
   voxel (clamped into the block: p lies on the block's face up to rounding), each visit's
   length in fixed point. LOCAL: into the block's cells lo/hi (32-bit words with the carry);
   else into the grid's cells with 64-bit atomics. */
#define PROBE_DRAW_BODY(DEPOSIT)                                                               \
    const int x0 = bx * BB, y0 = by * BB, z0 = bz * BB;                                        \
    float inv0 = 1.0f / d0, inv1 = 1.0f / d1, inv2 = 1.0f / d2;                                \
    int ix = probe_clampi((int)floor(p0), x0, x0 + BB - 1);                                    \
    int iy = probe_clampi((int)floor(p1), y0, y0 + BB - 1);                                    \
    int iz = probe_clampi((int)floor(p2), z0, z0 + BB - 1);                                    \
    float tx = probe_face(p0, d0, inv0, ix, 1.0f);                                             \
    float ty = probe_face(p1, d1, inv1, iy, 1.0f);                                             \
    float tz = probe_face(p2, d2, inv2, iz, 1.0f);                                             \
    float t_cur = 0.0f;                                                                        \
    for (;;) {                                                                                 \
        float t_next = fmin(tx, fmin(ty, tz));                                                 \
        int end = t_next >= len;                                                               \
        float t_end = end ? len : t_next;                                                      \
        nrt_u32 v = (nrt_u32)NRT_FMAF(fmax(0.0f, t_end - t_cur), SCALE, 0.5f);                  \
        DEPOSIT;                                                                               \
        if (end)                                                                               \
            break;                                                                             \
        t_cur = t_end;                                                                         \
        int on_x = tx <= ty && tx <= tz;                                                       \
        int on_y = !on_x && ty <= tz;                                                          \
        float d_ax = on_x ? d0 : (on_y ? d1 : d2);                                             \
        int step = d_ax > 0.0f ? 1 : -1;                                                       \
        int i_next = (on_x ? ix : (on_y ? iy : iz)) + step;                                    \
        int lo_ax = on_x ? x0 : (on_y ? y0 : z0);                                              \
        if (i_next < lo_ax || i_next >= lo_ax + BB)                                            \
            break; /* out of the block by rounding: the rest (< 1 ulp of len) is dropped */    \
        float t_ax = probe_face(on_x ? p0 : (on_y ? p1 : p2), d_ax,                            \
                                on_x ? inv0 : (on_y ? inv1 : inv2), i_next, 1.0f);             \
        ix = on_x ? i_next : ix;                                                               \
        iy = on_y ? i_next : iy;                                                               \
        iz = (!on_x && !on_y) ? i_next : iz;                                                   \
        tx = on_x ? t_ax : tx;                                                                 \
        ty = on_y ? t_ax : ty;                                                                 \
        tz = (!on_x && !on_y) ? t_ax : tz;                                                     \
    }

NRT_DEVICE void probe_draw_global(NRT_GLOBAL nrt_u64 *sums, int bx, int by, int bz, float p0, float p1,
                                  float p2, float d0, float d1, float d2, float len)
{
    PROBE_DRAW_BODY(if (v) NRT_ATOMIC_ADD_U64(&sums[((nrt_u64)iz * N + iy) * N + ix], (nrt_u64)v))
}

NRT_DEVICE void probe_draw_local(NRT_LOCAL nrt_u32 *lo, NRT_LOCAL nrt_u32 *hi, int bx, int by, int bz,
                                 float p0, float p1, float p2, float d0, float d1, float d2, float len)
{
    /* A visit's v < 2^26 (SCALE 2^24, at most sqrt(3) voxels; converted to 32 bits, the same
       integer as a 64-bit conversion) goes in two words, its low 16
       bits and the rest: a straight piece visits a cell once, so a chunk of at most 2^12
       records adds below 2^28 to either word, and neither add needs its old value (no
       round trip: the adds are issued and the lane goes on). */
    PROBE_DRAW_BODY({
        int c = ((iz - z0) * BB + (iy - y0)) * BB + (ix - x0);
#if DRAW_VARIANT == 0
        NRT_ATOMIC_ADD_U32_LOCAL(&lo[c], v & 0xFFFFu);
        NRT_ATOMIC_ADD_U32_LOCAL(&hi[c], v >> 16);
#elif DRAW_VARIANT == 1 /* timing only (wrong sums): one local atomic per visit */
        NRT_ATOMIC_ADD_U32_LOCAL(&lo[c], v);
#else /* timing only (wrong sums, races): plain local adds */
        lo[c] += v;
#endif
    })
}

/* One piece of a flight, in block (b0, b1, b2) from q along d for len: counted, written or
   drawn (MODE). */
#if MODE == MODE_DIRECT
#define PROBE_EMIT(b0, b1, b2, q0, q1, q2, len)                                              \
    do {                                                                                      \
        ++records;                                                                            \
        probe_draw_global(sums, (b0), (b1), (b2), (q0), (q1), (q2), d[0], d[1], d[2], (len)); \
    } while (0)
#else
#define PROBE_EMIT(b0, b1, b2, q0, q1, q2, len)                                                         \
    do {                                                                                                 \
        ++records;                                                                                       \
        int blk_ = ((b2) * NBLK + (b1)) * NBLK + (b0);                                                   \
        nrt_u32 slot_ = PROBE_HIST_ADD(blk_);                                                            \
        PROBE_WRITE(blk_, slot_, q0, q1, q2, len);                                                       \
    } while (0)
#if MODE == MODE_WRITE
#define PROBE_WRITE(blk, slot, q0, q1, q2, len)                                                          \
    do {                                                                                                 \
        NRT_GLOBAL float *r_ = rec + (nrt_u64)REC_WORDS * ((nrt_u64)bucket[blk] + my_off[blk] + (slot)); \
        PROBE_STORE4(r_, (q0), (q1), (q2), (len));                                                       \
        PROBE_STORE4(r_ + 4, d[0], d[1], d[2], 0.0f);                                                    \
    } while (0)
#else
#define PROBE_WRITE(blk, slot, q0, q1, q2, len) ((void)(slot))
#endif
#endif

/*
 * The walk: packets first + global id, + global size, ... (< last), each work item tracing its
 * packets one after another. counts[0..2]: absorbed, escaped, records.
 * MODE_COUNT: block_count[NB3] (zeroed), group_off[groups][NB3] out.
 * MODE_WRITE: bucket[NB3] (bucket starts), group_off in, rec out.
 * MODE_DIRECT: sums (the grid's cells) out.
 * DENSITY 0: uniform, each free path in closed form. DENSITY 1: rho per voxel (x fastest) and
 * its maximum per block, rho_max: delta tracking (Woodcock) block by block, a tentative
 * collision at the block's majorant taken as real with probability rho / rho_max.
 * One loop iteration is one piece of a flight (or, DENSITY 1, one tentative collision): a lane
 * whose flight or packet ends starts its next one in the same iteration, so the lanes of a
 * SIMD group stay busy until their last packets (instead of each waiting for the group's
 * longest packet).
 */
NRT_KERNEL void probe_walk(nrt_u64 seed, nrt_u64 first, nrt_u64 last, NRT_GLOBAL nrt_u32 *block_count,
                           NRT_GLOBAL nrt_u32 *group_off, const NRT_GLOBAL nrt_u32 *bucket,
                           NRT_GLOBAL float *rec, NRT_GLOBAL nrt_u64 *sums, NRT_GLOBAL nrt_u64 *counts,
                           const NRT_GLOBAL float *rho, const NRT_GLOBAL float *rho_max,
                           NRT_GLOBAL nrt_u32 *ghist)
{
    (void)ghist;
#if MODE != MODE_DIRECT && !HIST_GLOBAL
    NRT_LOCAL_MEM nrt_u32 hist[NB3];
    for (int b = (int)NRT_LOCAL_ID(); b < NB3; b += (int)NRT_LOCAL_SIZE())
        hist[b] = 0;
#define PROBE_HIST_ADD(blk) NRT_ATOMIC_ADD_U32_LOCAL(&hist[blk], 1u)
#define PROBE_HIST_READ(blk) hist[blk]
#else
    /* the group's counts (MODE_COUNT) or running slots (MODE_WRITE) in global memory, zeroed
       by the host: the blocks of large grids pass the local memory */
    NRT_GLOBAL nrt_u32 *my_hist = ghist + (NRT_GROUP_FIRST_ID() / NRT_LOCAL_SIZE()) * NB3;
#define PROBE_HIST_ADD(blk) NRT_ATOMIC_ADD_U32(&my_hist[blk], 1u)
#define PROBE_HIST_READ(blk) NRT_ATOMIC_ADD_U32(&my_hist[blk], 0u)
#endif
    NRT_LOCAL_MEM nrt_u32 tally[3];
    if (NRT_LOCAL_ID() < 3)
        tally[NRT_LOCAL_ID()] = 0;
    NRT_BARRIER();
    const nrt_u64 group = NRT_GROUP_FIRST_ID() / NRT_LOCAL_SIZE();
#if MODE == MODE_WRITE
    const NRT_GLOBAL nrt_u32 *my_off = group_off + group * NB3;
#endif
    (void)rho, (void)rho_max;
    const nrt_u64 stride = NRT_GLOBAL_SIZE();
    const int bmax = NBLK - 1;
    nrt_u64 photon = first + NRT_GLOBAL_ID();
    nrt_rng rng;
    float p[3], d[3], inv[3], tb[3], t0 = 0.0f, len = 0.0f, t_exit = 0.0f;
    int b[3], escaped = 0;
#if DENSITY == 1
    float t = 0.0f;
#endif
    nrt_u32 records = 0, n_abs = 0, n_esc = 0;
    /* a new flight from p along d */
#define PROBE_START_FLIGHT()                                                              \
    do {                                                                                  \
        inv[0] = 1.0f / d[0], inv[1] = 1.0f / d[1], inv[2] = 1.0f / d[2];                 \
        t_exit = PROBE_INF;                                                               \
        for (int a = 0; a < 3; ++a) {                                                     \
            float f = d[a] > 0.0f ? (float)N : 0.0f;                                      \
            t_exit = d[a] != 0.0f ? fmin(t_exit, (f - p[a]) * inv[a]) : t_exit;           \
        }                                                                                 \
        t_exit = fmax(t_exit, 0.0f);                                                      \
        for (int a = 0; a < 3; ++a) {                                                     \
            b[a] = probe_clampi((int)floor(p[a] * (1.0f / BB)), 0, bmax);                 \
            tb[a] = probe_face(p[a], d[a], inv[a], b[a], (float)BB);                      \
        }                                                                                 \
        t0 = 0.0f;                                                                        \
        PROBE_FLIGHT_LENGTH();                                                            \
    } while (0)
#if DENSITY == 0
#define PROBE_FLIGHT_LENGTH()                                       \
    do {                                                            \
        const float s_ = nrt_sample_tau(&rng) * (1.0f / KAPPA);     \
        len = fmin(s_, t_exit);                                     \
        escaped = s_ >= t_exit;                                     \
    } while (0)
#else
#define PROBE_FLIGHT_LENGTH() (len = t_exit, t = 0.0f, escaped = 1)
#endif
#define PROBE_START_PACKET()                                \
    do {                                                    \
        nrt_rng_init(&rng, seed, 0, photon);                \
        p[0] = P_SRC, p[1] = P_SRC, p[2] = P_SRC;           \
        nrt_sample_isotropic(&rng, d);                      \
        PROBE_START_FLIGHT();                               \
    } while (0)
    int alive = photon < last;
    if (alive)
        PROBE_START_PACKET();
    while (alive) {
        const float t_next = fmin(tb[0], fmin(tb[1], tb[2]));
#if DENSITY == 1
        {
            /* a tentative collision in this block, up to its exit or the box's */
            const float rmax = rho_max[(b[2] * NBLK + b[1]) * NBLK + b[0]];
            const float t_end = fmin(t_next, t_exit);
            int tentative = 0;
            if (rmax > 0.0f) {
                const float t_try = t + nrt_sample_tau(&rng) * (1.0f / (rmax * KAPPA));
                tentative = t_try < t_end;
                t = tentative ? t_try : t_end; /* (memoryless: the overshoot dropped) */
            } else {
                t = t_end;
            }
            if (tentative) {
                int vx = probe_clampi((int)floor(p[0] + d[0] * t), b[0] * BB, b[0] * BB + BB - 1);
                int vy = probe_clampi((int)floor(p[1] + d[1] * t), b[1] * BB, b[1] * BB + BB - 1);
                int vz = probe_clampi((int)floor(p[2] + d[2] * t), b[2] * BB, b[2] * BB + BB - 1);
                float r = rho[((nrt_u64)vz * N + vy) * N + vx];
                if (nrt_rng_uniform(&rng) * rmax >= r)
                    continue; /* a null collision */
                len = t, escaped = 0;
            }
        }
#endif
        const float t1 = fmin(t_next, len);
        const float piece = t1 - t0;
        if (piece > 0.0f)
            PROBE_EMIT(b[0], b[1], b[2], p[0] + d[0] * t0, p[1] + d[1] * t0, p[2] + d[2] * t0, piece);
        int over = t_next >= len;
        if (!over) {
            t0 = t1;
            int on_x = tb[0] <= tb[1] && tb[0] <= tb[2];
            int on_y = !on_x && tb[1] <= tb[2];
            int a = on_x ? 0 : (on_y ? 1 : 2);
            int nb = b[a] + (d[a] > 0.0f ? 1 : -1);
            over = nb < 0 || nb > bmax;
            b[a] = over ? b[a] : nb;
            tb[a] = probe_face(p[a], d[a], inv[a], b[a], (float)BB);
        }
        if (over) {
            int ends = escaped;
            if (!escaped) {
                p[0] = p[0] + d[0] * len, p[1] = p[1] + d[1] * len, p[2] = p[2] + d[2] * len;
                ends = nrt_rng_uniform(&rng) >= ALBEDO;
                n_abs += ends;
            } else {
                ++n_esc;
            }
            if (!ends) {
                float mu, st;
                nrt_sample_hg(G, nrt_rng_uniform(&rng), &mu, &st);
                nrt_rotate(d, mu, st, 2.0f * NRT_PI_F * nrt_rng_uniform(&rng));
                PROBE_START_FLIGHT();
            } else {
                photon += stride;
                alive = photon < last;
                if (alive)
                    PROBE_START_PACKET();
            }
        }
    }
    NRT_ATOMIC_ADD_U32_LOCAL(&tally[0], n_abs);
    NRT_ATOMIC_ADD_U32_LOCAL(&tally[1], n_esc);
    NRT_ATOMIC_ADD_U32_LOCAL(&tally[2], records);
    NRT_BARRIER();
#if MODE != MODE_WRITE /* (the writing walk repeats the counting walk's packets) */
    if (NRT_LOCAL_ID() < 3)
        NRT_ATOMIC_ADD_U64(&counts[NRT_LOCAL_ID()], (nrt_u64)tally[NRT_LOCAL_ID()]);
#endif
#if MODE == MODE_COUNT
    for (int b = (int)NRT_LOCAL_ID(); b < NB3; b += (int)NRT_LOCAL_SIZE()) {
        nrt_u32 c = PROBE_HIST_READ(b);
        group_off[group * NB3 + b] = c ? NRT_ATOMIC_ADD_U32(&block_count[b], c) : 0u;
    }
#else
    (void)block_count, (void)group_off, (void)bucket, (void)rec, (void)sums;
#endif
}

/*
 * One work group per chunk of a block's bucket: chunk k is records [chunk_start[k],
 * chunk_start[k] + chunk_len[k]) of block chunk_block[k]. The records are drawn into the
 * block's cells in local memory, which are then added to the grid's.
 */
NRT_KERNEL void probe_draw_chunks(const NRT_GLOBAL nrt_u32 *chunk_block, const NRT_GLOBAL nrt_u32 *chunk_start,
                                  const NRT_GLOBAL nrt_u32 *chunk_len, const NRT_GLOBAL float *rec,
                                  NRT_GLOBAL nrt_u64 *sums)
{
    NRT_LOCAL_MEM nrt_u32 lo[BB3];
    NRT_LOCAL_MEM nrt_u32 hi[BB3];
    const nrt_u64 k = NRT_GROUP_FIRST_ID() / NRT_LOCAL_SIZE();
    for (int c = (int)NRT_LOCAL_ID(); c < BB3; c += (int)NRT_LOCAL_SIZE())
        lo[c] = 0, hi[c] = 0;
    NRT_BARRIER();
    const int blk = (int)chunk_block[k];
    const int bx = blk % NBLK, by = (blk / NBLK) % NBLK, bz = blk / (NBLK * NBLK);
    const nrt_u64 start = chunk_start[k];
    const int n = (int)chunk_len[k];
#if DRAW_FLAT
    /* One iteration draws one voxel visit; a lane whose record ends loads its next at once
       (records lid, lid + group size, ...), so the lanes stay busy to the chunk's end. The
       visit's arithmetic is probe_draw_local's. */
    const int x0 = bx * BB, y0 = by * BB, z0 = bz * BB;
    int i = (int)NRT_LOCAL_ID();
    float p0, p1, p2, d0, d1, d2, len, inv0, inv1, inv2, tx, ty, tz, t_cur;
    int ix, iy, iz;
#define PROBE_LOAD_RECORD()                                                            \
    do {                                                                               \
        const NRT_GLOBAL float *r_ = rec + (nrt_u64)REC_WORDS * (start + (nrt_u64)i);  \
        probe_f4 a_ = PROBE_LOAD4(r_), b_ = PROBE_LOAD4(r_ + 4);                       \
        p0 = a_.x, p1 = a_.y, p2 = a_.z, len = a_.w, d0 = b_.x, d1 = b_.y, d2 = b_.z;  \
        inv0 = 1.0f / d0, inv1 = 1.0f / d1, inv2 = 1.0f / d2;                          \
        ix = probe_clampi((int)floor(p0), x0, x0 + BB - 1);                            \
        iy = probe_clampi((int)floor(p1), y0, y0 + BB - 1);                            \
        iz = probe_clampi((int)floor(p2), z0, z0 + BB - 1);                            \
        tx = probe_face(p0, d0, inv0, ix, 1.0f);                                       \
        ty = probe_face(p1, d1, inv1, iy, 1.0f);                                       \
        tz = probe_face(p2, d2, inv2, iz, 1.0f);                                       \
        t_cur = 0.0f;                                                                  \
    } while (0)
    int live = i < n;
    if (live)
        PROBE_LOAD_RECORD();
    while (live) {
        float t_next = fmin(tx, fmin(ty, tz));
        int end = t_next >= len;
        float t_end = end ? len : t_next;
        nrt_u32 v = (nrt_u32)NRT_FMAF(fmax(0.0f, t_end - t_cur), SCALE, 0.5f);
        int c = ((iz - z0) * BB + (iy - y0)) * BB + (ix - x0);
        NRT_ATOMIC_ADD_U32_LOCAL(&lo[c], (nrt_u32)(v & 0xFFFFu));
        NRT_ATOMIC_ADD_U32_LOCAL(&hi[c], (nrt_u32)(v >> 16));
        int done = end;
        if (!end) {
            t_cur = t_end;
            int on_x = tx <= ty && tx <= tz;
            int on_y = !on_x && ty <= tz;
            float d_ax = on_x ? d0 : (on_y ? d1 : d2);
            int i_next = (on_x ? ix : (on_y ? iy : iz)) + (d_ax > 0.0f ? 1 : -1);
            int lo_ax = on_x ? x0 : (on_y ? y0 : z0);
            done = i_next < lo_ax || i_next >= lo_ax + BB;
            float t_ax = probe_face(on_x ? p0 : (on_y ? p1 : p2), d_ax, on_x ? inv0 : (on_y ? inv1 : inv2),
                                    i_next, 1.0f);
            ix = on_x ? i_next : ix;
            iy = on_y ? i_next : iy;
            iz = (!on_x && !on_y) ? i_next : iz;
            tx = on_x ? t_ax : tx;
            ty = on_y ? t_ax : ty;
            tz = (!on_x && !on_y) ? t_ax : tz;
        }
        if (done) {
            i += (int)NRT_LOCAL_SIZE();
            live = i < n;
            if (live)
                PROBE_LOAD_RECORD();
        }
    }
#else
    for (int i = (int)NRT_LOCAL_ID(); i < n; i += (int)NRT_LOCAL_SIZE()) {
        const NRT_GLOBAL float *r = rec + (nrt_u64)REC_WORDS * (start + (nrt_u64)i);
        probe_f4 a = PROBE_LOAD4(r), b = PROBE_LOAD4(r + 4);
        probe_draw_local(lo, hi, bx, by, bz, a.x, a.y, a.z, b.x, b.y, b.z, a.w);
    }
#endif
    NRT_BARRIER();
    for (int c = (int)NRT_LOCAL_ID(); c < BB3; c += (int)NRT_LOCAL_SIZE()) {
        nrt_u64 v = ((nrt_u64)hi[c] << 16) + (nrt_u64)lo[c];
        if (v) {
            int x = bx * BB + c % BB, y = by * BB + (c / BB) % BB, z = bz * BB + c / (BB * BB);
            NRT_ATOMIC_ADD_U64(&sums[((nrt_u64)z * N + y) * N + x], v);
        }
    }
}
