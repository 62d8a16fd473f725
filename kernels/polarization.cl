/*
 * polarization.cl -- polarized scattering (transport.cl with NRT_POLAR; sampling.cl's test
 * kernels). Included after nebula_common.h; no includes of its own.
 *
 * A packet carries, besides its direction d, the normalised Stokes vector (q, u, v) = (Q, U,
 * V) / I of its light and the reference direction e (a unit vector perpendicular to d) that
 * Q and U refer to: in the right-handed frame (e1, e2, d) = (e, d x e, d), Q = I_e1 - I_e2,
 * U = I_(e1+e2) - I_(e1-e2) (the 45-degree analysers), the polarization angle counted from e1
 * towards e2. An analog packet's intensity stays one unit: every scattering samples the
 * polarized phase function exactly and divides the new Stokes vector by its intensity.
 *
 * Scattering by a particle with mirror symmetry (Bohren & Huffman 1983, ch. 3 and 13): in the
 * frame of the scattering plane (e1 in the plane), the Mueller matrix
 *     | S11 S12  0   0  |
 *     | S12 S11  0   0  |
 *     |  0   0  S33 S34 |
 *     |  0   0 -S34 S33 |
 * of the scattering angle theta alone (S11 per steradian: the phase function). The kinds
 * (NRT_POLAR, and `kind` below):
 *   1  Rayleigh (dipole) scattering: S11 = 3 (1 + mu^2) / (16 pi), S12 = -3 (1 - mu^2) / (16 pi),
 *      S33 = 3 (2 mu) / (16 pi), S34 = 0 (the band's g plays no part);
 *   2  Henyey-Greenstein intensity with White's (1979, ApJ 229, 954) approximation of the
 *      linear polarization, as in Code & Whitney (1995, ApJ 441, 400): S11 = HG(g, mu),
 *      S12 = -p_l S11 (1 - mu^2) / (1 + mu^2), S33 = S11 2 mu / (1 + mu^2), S34 = 0 (White's
 *      circular term is not modelled); per band p_l, the linear polarization of unpolarized
 *      light scattered through 90 degrees (pol[0]).
 *   3  spherical grains by Mie theory (nebula_rt.optics.mie): per band a table at pol + pol[0]
 *      of pol[1] scattering angles (0 to 180 degrees in equal steps) with the rows mu, the
 *      cumulative probability from mu = 1, p(mu) = 2 pi S11, S12 / S11, S33 / S11, S34 / S11
 *      (then a guide table of the cumulative probability, nrt_mie_mu),
 *      all linear in mu between the nodes: theta is sampled exactly from that piecewise-linear
 *      p (a binary search and the root of a quadratic), and S34 makes V.
 * All keep S12^2 + S33^2 + S34^2 <= S11^2 (equality for Rayleigh, for White at p_l = 1 and for
 * single Mie spheres), so no scattering makes light more than fully polarized.
 * Unpolarized light scattered through theta is polarized by -S12 / S11, perpendicular to the
 * scattering plane where S12 < 0 (Rayleigh: sin^2 theta / (1 + cos^2 theta)).
 *
 * A scattering (Peest et al. 2017, A&A 601, A92, as SKIRT does it): theta from S11 (the
 * marginal of the polarized phase function over the azimuth), then the azimuth phi of the
 * scattering plane, counted from e towards d x e, from its conditional density
 * (1 + s12 (q cos 2 phi + u sin 2 phi)) / (2 pi), s12 = S12 / S11, by rejection (at most two
 * tries on average). The Stokes vector is rotated into the scattering plane (e -> e_phi =
 * e cos phi + (d x e) sin phi), multiplied by the matrix and normalised; the new direction is
 * d' = mu d + sin(theta) e_phi and the new reference e' = mu e_phi - sin(theta) d, the
 * direction in the scattering plane perpendicular to d'.
 */

#define NRT_POLAR_RAYLEIGH 1
#define NRT_POLAR_WHITE 2
#define NRT_POLAR_MIE 3

typedef struct {
    float q, u, v; /* Q / I, U / I, V / I */
    float e[3];    /* the reference direction: unit, perpendicular to the packet's direction */
} nrt_stokes;

/* Unpolarized light leaving a star along d (the reference: the first axis of d's basis). */
NRT_DEVICE void nrt_stokes_unpolarized(const float *d, nrt_stokes *s)
{
    float t2[3];
    nrt_onb(d[0], d[1], d[2], s->e, t2);
    s->q = s->u = s->v = 0.0f;
}

/* A Mie table's interval [mu_i+1, mu_i] that holds mu (nodes equal in theta, so acos gives it
   to within one; the stored nodes decide). */
NRT_DEVICE int nrt_mie_interval(const NRT_GLOBAL float *t, int n, float mu)
{
    int i = (int)(acos(mu) * (float)(n - 1) * (1.0f / NRT_PI_F));
    i = min(max(i, 0), n - 2);
    if (i > 0 && mu > t[i])
        --i;
    else if (i < n - 2 && mu < t[i + 1])
        ++i;
    return i;
}

/* The scattering cosine of a Mie table from xi in [0, 1): the interval by a binary search of
   the cumulative probabilities, then within it the root t of h (p0 t + (p1 - p0) t^2 / 2) =
   xi - P_i (mu = mu_i - t h), formed as 2 c / (p0 + sqrt(p0^2 + 2 (p1 - p0) c)) (no
   cancellation). The search starts from the guide table after the rows (entry j: the last
   interval with cdf <= j / NRT_MIE_GUIDE), one cell wider on each side than xi's own so that the
   rounding of xi * NRT_MIE_GUIDE cannot leave the answer outside: the interval, the unique one
   with cdf[i] <= xi < cdf[i + 1], is the one a search of the whole table finds. NRT_MIE_GUIDE:
   nebula_rt.backends.kernel_params.CONSTANTS. */
NRT_DEVICE float nrt_mie_mu(const NRT_GLOBAL float *t, int n, float xi)
{
    const NRT_GLOBAL float *cdf = t + n, *p = t + 2 * n, *guide = t + 6 * n;
    int j = min((int)(xi * (float)NRT_MIE_GUIDE), NRT_MIE_GUIDE - 1);
    int lo = j > 0 ? (int)guide[j - 1] : 0;
    int hi = j + 2 <= NRT_MIE_GUIDE ? min((int)guide[j + 2] + 1, n - 1) : n - 1; /* cdf[lo] <= xi < cdf[hi] */
    while (hi - lo > 1) {
        int mid = (lo + hi) >> 1;
        if (cdf[mid] <= xi)
            lo = mid;
        else
            hi = mid;
    }
    float h = t[lo] - t[lo + 1];
    float c = (xi - cdf[lo]) / h;
    float p0 = p[lo], p1 = p[lo + 1];
    float den = p0 + sqrt(fmax(p0 * p0 + 2.0f * (p1 - p0) * c, 0.0f));
    float s = den > 0.0f ? fmin(2.0f * c / den, 1.0f) : 0.5f;
    return fmin(fmax(t[lo] - s * h, -1.0f), 1.0f);
}

/* The Mueller matrix at scattering cosine mu: m[0] = S11 (per sr), m[1..3] = S12, S33, S34
   divided by S11. pol: the band's parameters (kind 2: p_l; kind 3: its table). */
NRT_DEVICE void nrt_mueller(int kind, float g, const NRT_GLOBAL float *pol, float mu, float *m)
{
    mu = fmin(fmax(mu, -1.0f), 1.0f);
    if (kind == NRT_POLAR_MIE) {
        const int n = (int)pol[1];
        const NRT_GLOBAL float *t = pol + (int)pol[0];
        int i = nrt_mie_interval(t, n, mu);
        float f = (t[i] - mu) / (t[i] - t[i + 1]);
        f = fmin(fmax(f, 0.0f), 1.0f);
        for (int k = 0; k < 4; ++k) {
            const NRT_GLOBAL float *row = t + (2 + k) * n;
            m[k] = row[i] + f * (row[i + 1] - row[i]);
        }
        m[0] *= 1.0f / (2.0f * NRT_PI_F);
        return;
    }
    float mm = mu * mu;
    float inv = 1.0f / (1.0f + mm);
    if (kind == NRT_POLAR_RAYLEIGH) {
        m[0] = 3.0f * (1.0f + mm) / (16.0f * NRT_PI_F);
        m[1] = -(1.0f - mm) * inv;
        m[2] = 2.0f * mu * inv;
        m[3] = 0.0f;
        return;
    }
    m[0] = nrt_hg_phase(g, mu);
    m[1] = -pol[0] * (1.0f - mm) * inv;
    m[2] = 2.0f * mu * inv;
    m[3] = 0.0f;
}

/* The scattering cosine of Rayleigh scattering from xi in [0, 1): the root of
   mu^3 + 3 mu = 8 xi - 4 (the cumulative distribution of 3 (1 + mu^2) / 8), by Cardano's
   formula mu = A - 1 / A, A = cbrt(c + sqrt(c^2 + 1)), c = 4 xi - 2, formed for |c| (no
   cancellation) and given c's sign. */
NRT_DEVICE float nrt_rayleigh_mu(float xi)
{
    float c = 4.0f * xi - 2.0f;
    float a = cbrt(fabs(c) + sqrt(c * c + 1.0f));
    float mu = a - 1.0f / a;
    return fmin(copysign(mu, c), 1.0f);
}

/* Rotate the Stokes vector's reference by angle phi about the direction, given cos(2 phi)
   and sin(2 phi): e -> e cos phi + (d x e) sin phi. */
NRT_DEVICE void nrt_stokes_rotate(float *q, float *u, float c2, float s2)
{
    float q0 = *q, u0 = *u;
    *q = q0 * c2 + u0 * s2;
    *u = -q0 * s2 + u0 * c2;
}

/* Scatter a packet: direction d and Stokes state s change in place (module comment). */
NRT_DEVICE void nrt_scatter_polarized(nrt_rng *rng, int kind, float g, const NRT_GLOBAL float *pol, float *d,
                                      nrt_stokes *s)
{
    float mu, sin_theta;
    if (kind == NRT_POLAR_RAYLEIGH) {
        mu = nrt_rayleigh_mu(nrt_rng_uniform(rng));
        sin_theta = sqrt(fmax(0.0f, (1.0f - mu) * (1.0f + mu)));
    } else if (kind == NRT_POLAR_MIE) {
        mu = nrt_mie_mu(pol + (int)pol[0], (int)pol[1], nrt_rng_uniform(rng));
        sin_theta = sqrt(fmax(0.0f, (1.0f - mu) * (1.0f + mu)));
    } else {
        nrt_sample_hg(g, nrt_rng_uniform(rng), &mu, &sin_theta);
    }
    float m[4];
    nrt_mueller(kind, g, pol, mu, m);
    /* the azimuth: 1 + s12 (q cos 2phi + u sin 2phi) <= 1 + |s12| |(q, u)| by Cauchy-Schwarz */
    float lin = sqrt(s->q * s->q + s->u * s->u);
    float bound = 1.0f + fabs(m[1]) * lin;
    float phi, c2, s2;
    for (;;) {
        phi = 2.0f * NRT_PI_F * nrt_rng_uniform(rng);
        c2 = cos(2.0f * phi);
        s2 = sin(2.0f * phi);
        if (lin == 0.0f || nrt_rng_uniform(rng) * bound <= 1.0f + m[1] * (s->q * c2 + s->u * s2))
            break;
    }
    float cp = cos(phi), sp = sin(phi);
    /* e_phi = e cos phi + (d x e) sin phi */
    float de[3] = {d[1] * s->e[2] - d[2] * s->e[1], d[2] * s->e[0] - d[0] * s->e[2], d[0] * s->e[1] - d[1] * s->e[0]};
    float ep[3], dn[3], en[3];
    for (int k = 0; k < 3; ++k)
        ep[k] = s->e[k] * cp + de[k] * sp;
    for (int k = 0; k < 3; ++k) {
        dn[k] = mu * d[k] + sin_theta * ep[k];
        en[k] = mu * ep[k] - sin_theta * d[k];
    }
    /* the Stokes vector in the scattering plane, through the matrix, normalised */
    float q = s->q, u = s->u, v = s->v;
    nrt_stokes_rotate(&q, &u, c2, s2);
    float i_new = 1.0f + m[1] * q;
    float q_new = m[1] + q;
    float u_new = m[2] * u + m[3] * v;
    float v_new = -m[3] * u + m[2] * v;
    float inv_i = 1.0f / i_new;
    q_new *= inv_i, u_new *= inv_i, v_new *= inv_i;
    /* rounding must not make the light more than fully polarized */
    float p2 = q_new * q_new + u_new * u_new + v_new * v_new;
    if (p2 > 1.0f) {
        float r = 1.0f / sqrt(p2);
        q_new *= r, u_new *= r, v_new *= r;
    }
    s->q = q_new, s->u = u_new, s->v = v_new;
    /* renormalise d', and e' against d' (rounding does not accumulate over many scatterings) */
    float inv = 1.0f / sqrt(dn[0] * dn[0] + dn[1] * dn[1] + dn[2] * dn[2]);
    for (int k = 0; k < 3; ++k)
        d[k] = dn[k] * inv;
    float ed = en[0] * d[0] + en[1] * d[1] + en[2] * d[2];
    for (int k = 0; k < 3; ++k)
        en[k] -= ed * d[k];
    inv = 1.0f / sqrt(en[0] * en[0] + en[1] * en[1] + en[2] * en[2]);
    for (int k = 0; k < 3; ++k)
        s->e[k] = en[k] * inv;
}

/*
 * The light a packet at direction d with Stokes state s scatters towards the observer, per
 * steradian, as (I, Q, U, V) in the image's frame: reference its up axis `north` (the IAU
 * convention: the polarization angle counted from north towards east, east = o x north on
 * the sky, o the direction to the observer). The scattering plane holds d and o; where they
 * are (anti)parallel it is taken through e, where S12 and the plane's angle vanish anyway.
 */
NRT_DEVICE void nrt_peel_stokes(int kind, float g, const NRT_GLOBAL float *pol, const float *o,
                                const float *north, const float *d, const nrt_stokes *s, float *iquv)
{
    float mu = fmin(fmax(d[0] * o[0] + d[1] * o[1] + d[2] * o[2], -1.0f), 1.0f);
    /* e1: the scattering plane's direction perpendicular to d, |o - mu d| = sin(theta) */
    float e1[3] = {o[0] - mu * d[0], o[1] - mu * d[1], o[2] - mu * d[2]};
    float st = sqrt(e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2]);
    if (st > 1.0e-6f) {
        for (int k = 0; k < 3; ++k)
            e1[k] /= st;
    } else {
        for (int k = 0; k < 3; ++k)
            e1[k] = s->e[k];
        st = 0.0f;
    }
    /* cos and sin of the azimuth from e to e1 about d, then of twice it */
    float de[3] = {d[1] * s->e[2] - d[2] * s->e[1], d[2] * s->e[0] - d[0] * s->e[2], d[0] * s->e[1] - d[1] * s->e[0]};
    float cp = s->e[0] * e1[0] + s->e[1] * e1[1] + s->e[2] * e1[2];
    float sp = de[0] * e1[0] + de[1] * e1[1] + de[2] * e1[2];
    float q = s->q, u = s->u;
    nrt_stokes_rotate(&q, &u, cp * cp - sp * sp, 2.0f * cp * sp);
    float m[4];
    nrt_mueller(kind, g, pol, mu, m);
    float i_o = m[0] * (1.0f + m[1] * q);
    float q_o = m[0] * (m[1] + q);
    float u_o = m[0] * (m[2] * u + m[3] * s->v);
    float v_o = m[0] * (-m[3] * u + m[2] * s->v);
    /* the outgoing reference e_out = mu e1 - sin(theta) d (perpendicular to o), turned to north */
    float eo[3] = {mu * e1[0] - st * d[0], mu * e1[1] - st * d[1], mu * e1[2] - st * d[2]};
    float oe[3] = {o[1] * eo[2] - o[2] * eo[1], o[2] * eo[0] - o[0] * eo[2], o[0] * eo[1] - o[1] * eo[0]};
    float cx = eo[0] * north[0] + eo[1] * north[1] + eo[2] * north[2];
    float sx = oe[0] * north[0] + oe[1] * north[1] + oe[2] * north[2];
    float n2 = cx * cx + sx * sx; /* |e_out| = 1 up to rounding: the double angle from the normalised pair */
    nrt_stokes_rotate(&q_o, &u_o, (cx * cx - sx * sx) / n2, 2.0f * cx * sx / n2);
    /* |Q|, |U|, |V| <= I: the deposits of Q, U and V are bounded by the intensity's (their sums by
       its checked sum), whatever the rounding */
    iquv[0] = i_o;
    iquv[1] = fmin(fmax(q_o, -i_o), i_o);
    iquv[2] = fmin(fmax(u_o, -i_o), i_o);
    iquv[3] = fmin(fmax(v_o, -i_o), i_o);
}
