/*
 * tree.cl -- the walk of a packet through an adaptive density: a forest of octrees in flat
 * arrays (nebula_rt.density.octree: child[node] >= 0 the first of 8 children, octant
 * c = ix + 2 iy + 4 iz; < 0 a leaf, its density at leaf_density[-1 - child]; the first
 * rx ry rz nodes the root cells, x fastest). Included by transport.cl in place of the grid's
 * walk where the run is on a tree (NRT_TREE): the kernel around it (trace_photons: the
 * launch's packets, batch slots of one cell per leaf, tallies, work-group sums, images) and
 * the fold are the grid's.
 *
 * The density buffer holds the leaves' densities, then the nodes' child entries (int32). A
 * packet draws its random numbers in the order of the grid's analog packets (the star, the
 * direction, each flight's optical depth, the absorption test, the scattering angle and
 * azimuth), so on a tree whose leaves are a uniform grid's voxels it flies the path it flies
 * there. The walk steps from leaf to leaf: the leaf holding a point is found from the root
 * grid down, a point on a cell's face going to the side the packet moves to, and each leaf's
 * exit is the nearest of its three far faces. The estimators deposit into the leaf's cell as
 * the grid's walk does into a voxel's.
 */

#ifndef NRT_TREE_MAX_DEPTH
#define NRT_TREE_MAX_DEPTH 20
#endif
/* NRT_TREE_ASCEND: the analog walk keeps the nodes of its leaf's ancestors (a stack of
   NRT_TREE_MAX_DEPTH + 1 ints), and the next leaf is found from the lowest ancestor the two
   cells share instead of from the root grid (the neighbour search of SOC's hierarchical grids
   and of VTK's hyper tree grid cursors, with no memory beyond the walk's). The same leaves,
   the same bits; what it costs and saves: docs/adaptive_grids.md. */
#ifndef NRT_TREE_ASCEND
#define NRT_TREE_ASCEND 0
#endif
#define NRT_INF_TREE 3.0e38f

/* From node (integer corner c, cells per axis n and cell size h at its level) down to the
   leaf holding p (moving along d: a coordinate on a face goes to the side d points to); the
   leaf's corner, cells per axis, low corner and size go to c, n, lo, h, its node to *node.
   A face is formed as (index) x (1 / cells) at every level, the same float whichever level
   forms it (1 / (r 2^L) is 1 / r scaled by a power of 2), so a point put on a leaf's face
   compares equal to its ancestors' midplanes there. The cell size of a level is the root
   cell's halved level by level: the same floats as dividing at every level (a scaling by
   2^-L is exact), without three divisions per level. */
NRT_DEVICE int nrt_tree_descend(const NRT_GLOBAL int *child, int *node, const float *p, const float *d, int *c,
                                int *n, float *lo, float *h, int *anc, int *lev)
{
    (void)anc, (void)lev;
    for (int level = 0; level <= NRT_TREE_MAX_DEPTH; ++level) {
        int k = child[*node];
        if (k < 0) {
            for (int a = 0; a < 3; ++a)
                lo[a] = (float)c[a] * h[a];
            return -1 - k;
        }
        int oct = 0;
        for (int a = 0; a < 3; ++a) {
            /* the children's shared face, as the children's faces are formed: (2 c + 1) / (2 n) */
            h[a] *= 0.5f;
            float mid = (float)(2 * c[a] + 1) * h[a];
            int up = p[a] > mid || (p[a] == mid && d[a] > 0.0f);
            c[a] = 2 * c[a] + up;
            n[a] *= 2;
            oct += up << a;
        }
        *node = k + oct;
#if NRT_TREE_ASCEND
        if (anc != 0 && *lev < NRT_TREE_MAX_DEPTH)
            anc[++*lev] = *node;
#endif
    }
    return -1; /* deeper than NRT_TREE_MAX_DEPTH: not a tree the host made */
}

/* The leaf holding p, from the root grid down (nrt_tree_descend). anc, lev (NRT_TREE_ASCEND,
   or 0): the nodes from the root cell down to the leaf's, and the leaf's level. */
NRT_DEVICE int nrt_tree_locate(const NRT_GLOBAL int *child, int rx, int ry, int rz, const float *p,
                               const float *d, int *c, int *n, float *lo, float *h, int *node, int *anc, int *lev)
{
    int r[3] = {rx, ry, rz};
    for (int a = 0; a < 3; ++a) {
        float x = p[a] * (float)r[a];
        int i = (int)floor(x);
        /* on a root face moving down: the cell below */
        if ((float)i == x && d[a] < 0.0f)
            i -= 1;
        c[a] = min(max(i, 0), r[a] - 1);
        n[a] = r[a];
        h[a] = 1.0f / (float)r[a];
    }
    *node = c[0] + rx * (c[1] + ry * c[2]);
#if NRT_TREE_ASCEND
    if (anc != 0) {
        *lev = 0;
        anc[0] = *node;
    }
#endif
    return nrt_tree_descend(child, node, p, d, c, n, lo, h, anc, lev);
}

/* The leaf beyond the face of axis ax the point p lies on (up: the far face), for a packet
   moving along d out of the leaf (node, corner c, ...): where the cell across shares the
   leaf's parent (half the crossings) it is the leaf's sibling, 8 children being stored
   together (octant bit ax flipped), and the walk goes down from there; else from the root
   grid. The same leaf either way (the same comparisons at every level below). */
NRT_DEVICE int nrt_tree_next(const NRT_GLOBAL int *child, int rx, int ry, int rz, const float *p, const float *d,
                             int ax, int up, int *c, int *n, float *lo, float *h, int *node, int *anc, int *lev)
{
    int r_ax = ax == 0 ? rx : (ax == 1 ? ry : rz);
    if (n[ax] > r_ax && (c[ax] & 1) == (up ? 0 : 1)) {
        c[ax] += up ? 1 : -1;
        *node += up ? (1 << ax) : -(1 << ax);
#if NRT_TREE_ASCEND
        if (anc != 0)
            anc[*lev] = *node;
#endif
        return nrt_tree_descend(child, node, p, d, c, n, lo, h, anc, lev);
    }
#if NRT_TREE_ASCEND
    if (anc != 0) {
        /* the cells on the two sides of the face share their ancestors above level L - s, s
           one more than the low bits of c[ax] that a step up (down) carries through (ones,
           or zeros); below the roots, the walk goes down from that ancestor */
        int bit = up ? 1 : 0, s = 1;
        while (s <= *lev && ((c[ax] >> (s - 1)) & 1) == bit)
            ++s;
        if (s <= *lev) {
            float scale = (float)(1 << s); /* exact: the ancestor's cell size */
            for (int a = 0; a < 3; ++a) {
                c[a] >>= s;
                n[a] >>= s;
                h[a] *= scale;
            }
            *lev -= s;
            *node = anc[*lev];
            return nrt_tree_descend(child, node, p, d, c, n, lo, h, anc, lev);
        }
    }
#endif
    return nrt_tree_locate(child, rx, ry, rz, p, d, c, n, lo, h, node, anc, lev);
}

/* Distance from p along d (1 / d: inv_d) to the nearest far face of the leaf (corner c, low
   corner lo, size h), formed as locate forms faces; its axis goes to ax. Times 1 / d, as the
   grid's walk forms its face distances (nrt_face_distance). */
NRT_DEVICE float nrt_tree_exit(const float *p, const float *d, const float *inv_d, const int *c, const float *lo,
                               const float *h, int *ax)
{
    float t_exit = NRT_INF_TREE;
    *ax = 0;
    for (int a = 0; a < 3; ++a) {
        float t = d[a] > 0.0f ? ((float)(c[a] + 1) * h[a] - p[a]) * inv_d[a]
                : (d[a] < 0.0f ? (lo[a] - p[a]) * inv_d[a] : NRT_INF_TREE);
        t = fmax(t, 0.0f);
        if (t < t_exit) {
            t_exit = t;
            *ax = a;
        }
    }
    return t_exit;
}


#if NRT_PEEL
/* Optical depth from x along o to the box's edge, leaf by leaf (the walk's steps). */
NRT_DEVICE float nrt_tree_tau_to_edge(const NRT_GLOBAL int *child, const NRT_GLOBAL float *leaf_density, int rx,
                                      int ry, int rz, float sig_b, const float *x, const float *o)
{
    float p[3] = {x[0], x[1], x[2]};
    const float inv_o[3] = {1.0f / o[0], 1.0f / o[1], 1.0f / o[2]};
    float lo[3], h[3], tau = 0.0f;
    int c[3], n[3], node;
    int leaf = nrt_tree_locate(child, rx, ry, rz, p, o, c, n, lo, h, &node, 0, 0);
    while (leaf >= 0) {
        int ax;
        float t_exit = nrt_tree_exit(p, o, inv_o, c, lo, h, &ax);
        tau += sig_b * leaf_density[leaf] * t_exit;
        int up = o[ax] > 0.0f;
        if ((up && c[ax] + 1 == n[ax]) || (!up && c[ax] == 0))
            break;
        for (int a = 0; a < 3; ++a)
            p[a] = p[a] + o[a] * t_exit;
        p[ax] = (float)(c[ax] + up) * h[ax];
        leaf = nrt_tree_next(child, rx, ry, rz, p, o, ax, up, c, n, lo, h, &node, 0, 0);
    }
    return tau;
}
#endif

#if NRT_PEEL
/* Peel-off of an analog packet scattering at p (incoming direction d; as transport.cl's
   nrt_peel, the optical depth to the edge marched leaf by leaf); returns the units added. */
NRT_DEVICE nrt_u64 nrt_tree_peel(const NRT_GLOBAL int *child, const NRT_GLOBAL float *leaf_density, int rx, int ry,
                                 int rz, float sig_b, float g_b, const NRT_GLOBAL float *pol,
                                 const NRT_GLOBAL float *peel, float peel_scale, const float *p, const float *d,
                                 const nrt_stokes *st, NRT_GLOBAL nrt_u64 *band_image,
                                 NRT_GLOBAL nrt_u64 *band_stokes, NRT_GLOBAL nrt_u32 *overflow, nrt_u64 seed,
                                 int band, nrt_u64 photon, int event)
{
    nrt_u64 pixel;
    if (!nrt_peel_pixel(peel, p, &pixel))
        return 0;
    const float o[3] = {peel[0], peel[1], peel[2]};
    float atten = exp(-nrt_tree_tau_to_edge(child, leaf_density, rx, ry, rz, sig_b, p, o));
    return nrt_peel_deposit(atten, g_b, pol, peel, peel_scale, d, st, pixel, band_image, band_stokes, overflow, seed,
                            band, photon, event);
}
#endif

/*
 * Trace one packet of one band through the tree to its end (transport.cl's nrt_trace_packet
 * for a tree: the same arguments; nx, ny, nz the root cells, cells the leaves, no regions).
 * The deposit macros' voxel coordinates (ix, iy, iz) stay 0: a leaf is in no star block, so
 * every deposit goes to the leaf's cell in the batch slot.
 */
NRT_DEVICE int nrt_trace_packet(NRT_TRACE_PACKET_PARAMS)
{
    (void)resume, (void)save, (void)region_shift, (void)item, (void)track_scale, (void)band_stokes, (void)stokes_slot;
#if !NRT_PEEL
    (void)peel, (void)peel_scale, (void)band_image, (void)g_b;
#endif
    const NRT_GLOBAL float *leaf_density = density;
    const NRT_GLOBAL int *child = (const NRT_GLOBAL int *)(density + cells);
    nrt_u64 peel_score = 0; /* NRT_PEEL: the packet's peel-off units (heavy-tail diagnostic) */
#if NRT_PACKET_SQ
    nrt_u64 run = 0; /* the packet's deposits during the visit of its leaf under way */
#else
    (void)band_sq;
    (void)sq_shift;
#endif
    const int ix = 0, iy = 0, iz = 0;
    nrt_rng rng;
    nrt_rng_init(&rng, seed, (nrt_u64)band, photon);
    int s = nrt_choose_star(&rng, cdf, n_stars);
    float p[3] = {stars[4 * s], stars[4 * s + 1], stars[4 * s + 2]};
    float d[3], inv_d[3];
    nrt_sample_isotropic(&rng, d);
#if NRT_POLAR
    nrt_stokes stokes; /* the packet's polarization */
    nrt_stokes_unpolarized(d, &stokes);
#else
    (void)pol;
#endif
    inv_d[0] = 1.0f / d[0], inv_d[1] = 1.0f / d[1], inv_d[2] = 1.0f / d[2];
    int scatterings = 0;
    float tau = nrt_sample_tau(&rng);
    float lo[3], h[3];
    int c[3], n[3], node, lev = 0;
#if NRT_TREE_ASCEND
    int anc_nodes[NRT_TREE_MAX_DEPTH + 1];
    int *anc = anc_nodes;
#else
    int *anc = 0;
#endif
    int leaf = nrt_tree_locate(child, nx, ny, nz, p, d, c, n, lo, h, &node, anc, &lev);
    nrt_idx idx = (nrt_idx)(leaf < 0 ? 0 : leaf);
    for (;;) {
        if (leaf < 0) { /* (deeper than NRT_TREE_MAX_DEPTH: a tree the host does not make) */
            NRT_VISIT_END();
            nrt_count(sink, 3);
            NRT_TAIL_END();
            return 0;
        }
        int ax;
        float t_exit = nrt_tree_exit(p, d, inv_d, c, lo, h, &ax);
        float sigma = sig_b * leaf_density[leaf];
        float tau_seg = sigma * t_exit;
        if (sigma > 0.0f && tau_seg >= tau) {
            /* the interaction happens inside this leaf */
            float t = tau / sigma;
#if NRT_TRACK_LENGTH
            NRT_SCORE(idx, nrt_fixed(t, track_scale));
#endif
#if NRT_COLLISION
            NRT_SCORE(idx, 1UL);
#endif
            for (int a = 0; a < 3; ++a)
                p[a] = fmin(fmax(p[a] + d[a] * t, lo[a]), lo[a] + h[a]);
            NRT_SCATTER_OR_END();
#if NRT_PEEL
            peel_score += nrt_tree_peel(child, leaf_density, nx, ny, nz, sig_b, g_b, pol, peel, peel_scale, p, d,
                                        NRT_STOKES_STATE, band_image, band_stokes, overflow, seed, band, photon,
                                        scatterings);
#endif
            NRT_NEW_DIRECTION();
            inv_d[0] = 1.0f / d[0], inv_d[1] = 1.0f / d[1], inv_d[2] = 1.0f / d[2];
            tau = nrt_sample_tau(&rng);
            /* the point stays in this leaf (d only changed). Only on one of its faces can the
               new d's tie-break put it in the neighbour (another visit): then it is located
               again; strictly inside (faces formed as locate forms them) it is this leaf's,
               which spares a walk from the root at every scattering */
            int on_face = 0;
            for (int a = 0; a < 3; ++a)
                on_face |= !(p[a] > lo[a] && p[a] < (float)(c[a] + 1) * h[a]);
            if (on_face) {
                int next = nrt_tree_locate(child, nx, ny, nz, p, d, c, n, lo, h, &node, anc, &lev);
                if (next != leaf)
                    NRT_VISIT_END();
                leaf = next;
                idx = (nrt_idx)(leaf < 0 ? 0 : leaf);
            }
            continue;
        }
#if NRT_TRACK_LENGTH
        NRT_SCORE(idx, nrt_fixed(t_exit, track_scale));
#endif
        tau -= tau_seg;
        for (int a = 0; a < 3; ++a)
            p[a] = p[a] + d[a] * t_exit;
        /* on the exit face exactly (formed as locate forms faces), so the next leaf is the
           one beyond it; a face of the box: the packet escapes */
        int up = d[ax] > 0.0f;
        NRT_VISIT_END();
        if ((up && c[ax] + 1 == n[ax]) || (!up && c[ax] == 0)) {
            nrt_count(sink, 2);
            NRT_TAIL_END();
            return 0;
        }
        p[ax] = (float)(c[ax] + up) * h[ax];
        leaf = nrt_tree_next(child, nx, ny, nz, p, d, ax, up, c, n, lo, h, &node, anc, &lev);
        idx = (nrt_idx)(leaf < 0 ? 0 : leaf);
    }
}
