/* The 3-D element's arithmetic (strains, law, residual, tangent) for LANES elements at once,
 * included by _elastic_kernel.c for each width it builds: LANES 1 (plain double: the scalar
 * kernel, its names as they are), 2 (SSE2) and 4 (AVX2, under GCC's target pragma), with L(name)
 * the names for that width.  Each quantity is a vector of the lanes' values (GCC's vector
 * extension), the arithmetic the same lane by lane, so every width gives the scalar kernel's
 * numbers bit for bit; LANE(v, l) is lane l of v, SPLAT(x) x in every lane.  The formulas are
 * those of _elastic_kernel.c's header comment. */

#if LANES == 1
typedef double VD;
#define SPLAT(x) (x)
#define LANE(v, l) (v)
#else
typedef double VD __attribute__((vector_size(8 * LANES)));
#define SPLAT(x) ((VD){0.0} + (x))
#define LANE(v, l) ((v)[l])
/* the vector (a[i], a[j]) of two 2-lane vectors' entries (b's from 2), and the masks of
 * __builtin_shuffle (GCC's; clang's is __builtin_shufflevector) */
#if LANES == 2 && defined(__clang__)
#define PAIR(a, b, i, j) __builtin_shufflevector((a), (b), i, j)
#else
typedef int64_t VI __attribute__((vector_size(8 * LANES)));
#define PAIR(a, b, i, j) __builtin_shuffle((a), (b), (VI){i, j})
#endif
#endif

/* Whether any lane of m is nonzero. */
static ALWAYS_INLINE int L(any)(VD m)
{
    int out = 0;
    for (int l = 0; l < LANES; l++) out |= LANE(m, l) != 0.0;
    return out;
}

/* Quantities at one quadrature point: energy density, dW/dz and the blocks of d2W/dz2. */
typedef struct {
    VD W;
    VD Wz[11];
    VD Wpp[16], Wpd[16], Wdp[16], Wdd[16];   /* 4x4 row-major: p-p, p-p', p'-p, p'-p' */
    VD Wpr[12];                              /* 4x3: p - r' */
    VD Wrr[9];                               /* 3x3: r' - r' */
} L(PointTerms);

/* 3-vector helpers: a.b, a x b, and the matrix a^x with a^x b = a x b */
static ALWAYS_INLINE VD L(dot3)(const VD *a, const VD *b)
{
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

static ALWAYS_INLINE void L(cross3)(const VD *a, const VD *b, VD *out)
{
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

static ALWAYS_INLINE void L(hat3)(const VD *a, VD h[3][3])
{
    h[0][0] = SPLAT(0.0);   h[0][1] = -a[2]; h[0][2] = a[1];
    h[1][0] = a[2];  h[1][1] = SPLAT(0.0);   h[1][2] = -a[0];
    h[2][0] = -a[1]; h[2][1] = a[0];  h[2][2] = SPLAT(0.0);
}

/* L(Strain) L(numerators) at a point and their derivatives DN = dNz/dz (e = Nz / n2). */
typedef struct {
    VD n2, inv, inv2;       /* |p|^2, 1/|p|^2, 1/|p|^4 */
    VD Rt[3][3];            /* Rq(p)^T = dg/dr' */
    VD Nz[6];               /* (g, 2w) */
    VD Gp[12], Up[12], Ud[12];   /* 3x4 row-major: dg/dp, d(2w)/dp, d(2w)/dp' */
} L(Strain);

/* The strain L(numerators) alone: Rt = Rq(p)^T = s I + 2 pv pv^T - 2 p0 pv^x (s = p0^2 - |pv|^2),
 * Nz = (Rt r', 2 w) with 2 w = 2 (p0 pv' - p0' pv - pv x pv'); returns |p|^2.  The energy pass
 * (element_energy) needs no more; L(strain_numerators) adds their derivatives. */
/* Rt = Rq(p)^T |p|^2 = s I + 2 pv pv^T - 2 p0 pv^x (s = p0^2 - |pv|^2); returns |p|^2. */
static ALWAYS_INLINE VD L(rotation_numerator)(const VD *p, VD Rt[3][3])
{
    const VD p0 = p[0], pv[3] = {p[1], p[2], p[3]};
    const VD pvpv = L(dot3)(pv, pv);
    const VD s = p0 * p0 - pvpv;
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            Rt[i][j] = 2.0 * pv[i] * pv[j];
    for (int i = 0; i < 3; i++) Rt[i][i] += s;
    Rt[0][1] += 2.0 * p0 * pv[2];  Rt[0][2] -= 2.0 * p0 * pv[1];
    Rt[1][0] -= 2.0 * p0 * pv[2];  Rt[1][2] += 2.0 * p0 * pv[0];
    Rt[2][0] += 2.0 * p0 * pv[1];  Rt[2][1] -= 2.0 * p0 * pv[0];
    return p0 * p0 + pvpv;
}

static ALWAYS_INLINE VD L(numerators)(const VD *p, const VD *dp, const VD *dr,
                                       VD Rt[3][3], VD *Nz)
{
    const VD p0 = p[0], pv[3] = {p[1], p[2], p[3]};
    const VD dp0 = dp[0], dpv[3] = {dp[1], dp[2], dp[3]};
    const VD n2 = L(rotation_numerator)(p, Rt);
    for (int k = 0; k < 3; k++)
        Nz[k] = L(dot3)(Rt[k], dr);
    VD pxdp[3];
    L(cross3)(pv, dpv, pxdp);
    for (int k = 0; k < 3; k++)
        Nz[3 + k] = 2.0 * (p0 * dpv[k] - dp0 * pv[k] - pxdp[k]);
    return n2;
}

static ALWAYS_INLINE void L(strain_numerators)(const VD *p, const VD *dp, const VD *dr,
                                     L(Strain) *z)
{
    const VD p0 = p[0], pv[3] = {p[1], p[2], p[3]};
    const VD dp0 = dp[0], dpv[3] = {dp[1], dp[2], dp[3]};
    z->n2 = L(numerators)(p, dp, dr, z->Rt, z->Nz);
    z->inv = 1.0 / z->n2;
    z->inv2 = z->inv * z->inv;
    /* dg/dp = 2 [p0 r' - pv x r',  pv r'^T - r' pv^T + (pv.r') I + p0 r'^x]
     * d(2w)/dp = 2 [pv', -p0' I + pv'^x],  d(2w)/dp' = 2 [-pv, p0 I - pv^x] */
    const VD pvdr = L(dot3)(pv, dr);
    VD pxdr[3], hr[3][3], hd[3][3], hp[3][3];
    L(cross3)(pv, dr, pxdr);
    L(hat3)(dr, hr);
    L(hat3)(dpv, hd);
    L(hat3)(pv, hp);
    for (int k = 0; k < 3; k++) {
        z->Gp[4 * k] = 2.0 * (p0 * dr[k] - pxdr[k]);
        z->Up[4 * k] = 2.0 * dpv[k];
        z->Ud[4 * k] = -2.0 * pv[k];
        for (int m = 0; m < 3; m++) {
            const double d = (k == m) ? 1.0 : 0.0;
            z->Gp[4 * k + 1 + m] = 2.0 * (pv[k] * dr[m] - dr[k] * pv[m] + pvdr * d + p0 * hr[k][m]);
            z->Up[4 * k + 1 + m] = 2.0 * (hd[k][m] - dp0 * d);
            z->Ud[4 * k + 1 + m] = 2.0 * (p0 * d - hp[k][m]);
        }
    }
}

/* Constitutive law (ElasticRod.law): S = C (e - e0), W = 1/2 (e - e0).S, plus the curvature
 * bound mu/2 <kappa - kappa_max>^2 on (u1, u2) with its tangent Cb (2x2, zero where it is not
 * active).  Returns 1 in the lanes where it is active, else 0. */
static ALWAYS_INLINE VD L(constitutive_law)(const Setup *st, const VD *e, const VD *e0,
                                            VD *S, VD *W, VD *Cb)
{
    VD w = SPLAT(0.0), bound = SPLAT(0.0);
    for (int k = 0; k < 6; k++) {
        const VD de = e[k] - e0[k];
        S[k] = st->C[k] * de;
        w += de * S[k];
    }
    *W = 0.5 * w;
    for (int i = 0; i < 4; i++) Cb[i] = SPLAT(0.0);
    if (!st->limit) return bound;
    for (int l = 0; l < LANES; l++) {
        const double e3 = LANE(e[3], l), e4 = LANE(e[4], l);
        const double kappa = sqrt(e3 * e3 + e4 * e4);
        const double over = kappa - st->kappa_max;
        if (!(over > 0.0)) continue;
        const double n[2] = {e3 / kappa, e4 / kappa};
        const double mu = st->mu_kappa, ratio = st->kappa_max / kappa;
        LANE(*W, l) += 0.5 * mu * over * over;
        LANE(S[3], l) += mu * over * n[0];
        LANE(S[4], l) += mu * over * n[1];
        for (int a = 0; a < 2; a++)
            for (int b = 0; b < 2; b++)
                LANE(Cb[2 * a + b], l) = mu * (((a == b) ? 1.0 - ratio : 0.0) + ratio * n[a] * n[b]);
        LANE(bound, l) = 1.0;
    }
    return bound;
}

/* Material part of Wzz: De^T C De (+ the bound's Cb on the u1, u2 rows); sets the blocks. */
static ALWAYS_INLINE void L(material_tangent)(const Setup *st, const L(Strain) *z, const VD *p,
                                    VD bound, const VD *Cb, L(PointTerms) *t)
{
    const VD inv = z->inv;
    /* De: Dgp = Gp/n2 - 2 g p^T/n2^2, Dup = Up/n2 - 2 (2w) p^T/n2^2, Dud = Ud/n2, Dgr = Rt/n2 */
    VD Dgp[12], Dup[12], Dud[12], Dgr[9];
    for (int k = 0; k < 3; k++) {
        const VD cg = 2.0 * z->inv2 * z->Nz[k], cu = 2.0 * z->inv2 * z->Nz[3 + k];
        for (int i = 0; i < 4; i++) {
            Dgp[4 * k + i] = z->Gp[4 * k + i] * inv - cg * p[i];
            Dup[4 * k + i] = z->Up[4 * k + i] * inv - cu * p[i];
            Dud[4 * k + i] = z->Ud[4 * k + i] * inv;
        }
        for (int l = 0; l < 3; l++) Dgr[3 * k + l] = z->Rt[k][l] * inv;
    }
    /* K = C De */
    VD Kgp[12], Kgr[9], Kup[12], Kud[12];
    for (int k = 0; k < 3; k++) {
        const double cg = st->C[k], cu = st->C[3 + k];
        for (int i = 0; i < 4; i++) {
            Kgp[4 * k + i] = cg * Dgp[4 * k + i];
            Kup[4 * k + i] = cu * Dup[4 * k + i];
            Kud[4 * k + i] = cu * Dud[4 * k + i];
        }
        for (int l = 0; l < 3; l++) Kgr[3 * k + l] = cg * Dgr[3 * k + l];
    }
    if (L(any)(bound)) {        /* Cb is zero in the lanes where the bound is not active */
        for (int i = 0; i < 4; i++) {
            const VD a0 = Dup[i], a1 = Dup[4 + i], b0 = Dud[i], b1 = Dud[4 + i];
            Kup[i] += Cb[0] * a0 + Cb[1] * a1;
            Kup[4 + i] += Cb[2] * a0 + Cb[3] * a1;
            Kud[i] += Cb[0] * b0 + Cb[1] * b1;
            Kud[4 + i] += Cb[2] * b0 + Cb[3] * b1;
        }
    }
    /* De^T K (g does not depend on p', u not on r') */
    for (int i = 0; i < 4; i++) {
        for (int j = 0; j < 4; j++) {
            VD pp = SPLAT(0.0), pd = SPLAT(0.0), dd = SPLAT(0.0);
            for (int k = 0; k < 3; k++) {
                pp += Dgp[4 * k + i] * Kgp[4 * k + j] + Dup[4 * k + i] * Kup[4 * k + j];
                pd += Dup[4 * k + i] * Kud[4 * k + j];
                dd += Dud[4 * k + i] * Kud[4 * k + j];
            }
            t->Wpp[4 * i + j] = pp;
            t->Wpd[4 * i + j] = pd;
            t->Wdd[4 * i + j] = dd;
        }
        for (int l = 0; l < 3; l++) {
            VD pr = SPLAT(0.0);
            for (int k = 0; k < 3; k++) pr += Dgp[4 * k + i] * Kgr[3 * k + l];
            t->Wpr[3 * i + l] = pr;
        }
    }
    for (int l = 0; l < 3; l++)
        for (int m = 0; m < 3; m++)
            t->Wrr[3 * l + m] = Dgr[l] * Kgr[m] + Dgr[3 + l] * Kgr[3 + m] + Dgr[6 + l] * Kgr[6 + m];
}

/* Geometric part of Wzz, S.D2e in closed form (header; a = S_v, b = r', c = S_u), added to
 * the blocks; v = DN^T S, sN = S.Nz.  Then Wdp = Wpd^T. */
static ALWAYS_INLINE void L(geometric_tangent)(const L(Strain) *z, const VD *p, const VD *dr,
                                     const VD *S, const VD *v, VD sN,
                                     L(PointTerms) *t)
{
    const VD p0 = p[0], *pv = p + 1, *a = S, *c = S + 3;
    const VD ab = L(dot3)(a, dr), pva = L(dot3)(pv, a);
    VD axb[3], pxa[3], ha[3][3], hc[3][3];
    L(cross3)(a, dr, axb);
    L(cross3)(pv, a, pxa);
    L(hat3)(a, ha);
    L(hat3)(c, hc);
    const VD i2 = 2.0 * z->inv;
    /* S.D2N / n2 */
    t->Wpp[0] += i2 * ab;
    for (int l = 0; l < 3; l++) {
        t->Wpp[1 + l] += i2 * axb[l];
        t->Wpp[4 * (1 + l)] += i2 * axb[l];
        t->Wpr[l] += i2 * (p0 * a[l] + pxa[l]);
        t->Wpd[1 + l] += i2 * c[l];
        t->Wpd[4 * (1 + l)] -= i2 * c[l];
    }
    for (int m = 0; m < 3; m++)
        for (int l = 0; l < 3; l++) {
            const double d = (m == l) ? 1.0 : 0.0;
            t->Wpp[4 * (1 + m) + 1 + l] += i2 * (a[m] * dr[l] + dr[m] * a[l] - ab * d);
            t->Wpr[3 * (1 + m) + l] += i2 * (a[m] * pv[l] - pv[m] * a[l] + pva * d + p0 * ha[m][l]);
            t->Wpd[4 * (1 + m) + 1 + l] += i2 * hc[m][l];
        }
    /* derivatives of 1/n2: -2/n2^2 (p v^T + v p^T) - 2 sN/n2^2 I_pp + 8 sN/n2^3 p p^T */
    const VD c2 = 2.0 * z->inv2, c8 = 8.0 * sN * z->inv2 * z->inv, cI = 2.0 * sN * z->inv2;
    for (int i = 0; i < 4; i++) {
        for (int j = 0; j < 4; j++) {
            t->Wpp[4 * i + j] += c8 * p[i] * p[j] - c2 * (p[i] * v[j] + v[i] * p[j]);
            t->Wpd[4 * i + j] -= c2 * p[i] * v[4 + j];
        }
        t->Wpp[5 * i] -= cI;
        for (int l = 0; l < 3; l++) t->Wpr[3 * i + l] -= c2 * p[i] * v[8 + l];
    }
    for (int i = 0; i < 4; i++)
        for (int j = 0; j < 4; j++) t->Wdp[4 * j + i] = t->Wpd[4 * i + j];
}

/* W, Wz = De^T S (and with tangent the blocks of Wzz) at a point with interpolated p, p', r'
 * and reference strains e0. */
static inline void L(point_terms)(const Setup *st, const VD *p, const VD *dp,
                               const VD *dr, const VD *e0, int tangent,
                               L(PointTerms) *t)
{
    L(Strain) z;
    L(strain_numerators)(p, dp, dr, &z);
    VD e[6], S[6], Cb[4];
    for (int k = 0; k < 6; k++) e[k] = z.Nz[k] * z.inv;
    const VD bound = L(constitutive_law)(st, e, e0, S, &t->W, Cb);
    /* v = DN^T S, sN = S.Nz;  Wz = v / n2 - 2 sN p / n2^2 on p */
    VD v[11];
    for (int i = 0; i < 4; i++) {
        VD a = SPLAT(0.0), b = SPLAT(0.0);
        for (int k = 0; k < 3; k++) {
            a += z.Gp[4 * k + i] * S[k] + z.Up[4 * k + i] * S[3 + k];
            b += z.Ud[4 * k + i] * S[3 + k];
        }
        v[i] = a;
        v[4 + i] = b;
    }
    for (int l = 0; l < 3; l++)
        v[8 + l] = z.Rt[0][l] * S[0] + z.Rt[1][l] * S[1] + z.Rt[2][l] * S[2];
    VD sN = SPLAT(0.0);
    for (int k = 0; k < 6; k++) sN += S[k] * z.Nz[k];
    for (int i = 0; i < 11; i++) t->Wz[i] = v[i] * z.inv;
    for (int i = 0; i < 4; i++) t->Wz[i] -= 2.0 * sN * z.inv2 * p[i];
    if (!tangent) return;
    L(material_tangent)(st, &z, p, bound, Cb, t);
    L(geometric_tangent)(&z, p, dr, S, v, sN, t);
}

/* B(q) = dq/dtheta = 1/2 [-qv^T; q0 I - qv^x]  (4x3 row-major) */
static inline void L(b_matrix)(const VD *q, VD *B)
{
    const double h = 0.5;
    B[0] = -h * q[1]; B[1] = -h * q[2]; B[2] = -h * q[3];
    B[3] = h * q[0];  B[4] = h * q[3];  B[5] = -h * q[2];
    B[6] = -h * q[3]; B[7] = h * q[0];  B[8] = h * q[1];
    B[9] = h * q[2];  B[10] = -h * q[1]; B[11] = h * q[0];
}

/* p, p' and r' at a Gauss point with shape functions N, dN (x: nodal positions). */
static ALWAYS_INLINE void L(interpolate)(const int NN, const double *N, const double *dN,
                                         const VD q[MAXNN][4], const VD x[MAXNN][3], VD *p,
                                      VD *dp, VD *dr)
{
    for (int i = 0; i < 4; i++) p[i] = dp[i] = SPLAT(0.0);
    for (int i = 0; i < 3; i++) dr[i] = SPLAT(0.0);
    for (int a = 0; a < NN; a++) {
        for (int i = 0; i < 4; i++) {
            p[i] += N[a] * q[a][i];
            dp[i] += dN[a] * q[a][i];
        }
        for (int i = 0; i < 3; i++) dr[i] += dN[a] * x[a][i];
    }
}

/* One element: energy, residual (nn, 6) and, if H != NULL, tangent (6nn x 6nn).
 * NN is a compile-time constant where this is inlined (see element_terms below). */
static ALWAYS_INLINE void L(element)(
    const int NN, const Setup *st, const VD q[MAXNN][4], const VD x[MAXNN][3], const VD *e0,
    int symmetric, VD *energy, VD *vec, VD *H)
{
    const int nq = st->nq, tangent = (H != NULL);
    VD graw[MAXNN][7];
    VD Hqq[MAXNN][MAXNN][16], Hqx[MAXNN][MAXNN][12], Hxx[MAXNN][MAXNN][9];
    for (int a = 0; a < NN; a++)
        for (int i = 0; i < 7; i++) graw[a][i] = SPLAT(0.0);
    if (tangent) {
        for (int a = 0; a < NN; a++)
            for (int b = 0; b < NN; b++) {
                for (int i = 0; i < 16; i++) Hqq[a][b][i] = SPLAT(0.0);
                for (int i = 0; i < 12; i++) Hqx[a][b][i] = SPLAT(0.0);
                for (int i = 0; i < 9; i++) Hxx[a][b][i] = SPLAT(0.0);
            }
    }
    VD E = SPLAT(0.0);
    L(PointTerms) t;
    for (int g = 0; g < nq; g++) {
        const double *N = st->N + g * NN, *dN = st->dN + g * NN, w = st->wJ[g];
        VD p[4], dp[4], dr[3];
        L(interpolate)(NN, N, dN, q, x, p, dp, dr);
        L(point_terms)(st, p, dp, dr, e0 + 6 * g, tangent, &t);
        E += w * t.W;
        for (int a = 0; a < NN; a++) {
            const double wN = w * N[a], wd = w * dN[a];
            for (int i = 0; i < 4; i++) graw[a][i] += wN * t.Wz[i] + wd * t.Wz[4 + i];
            for (int i = 0; i < 3; i++) graw[a][4 + i] += wd * t.Wz[8 + i];
        }
        if (!tangent) continue;
        /* Hraw_ab = w G_a^T Wzz G_b: q-q through Zp_b = N_b Wpp + N'_b Wpd (p rows) and
         * Zd_b = N_b Wdp + N'_b Wdd (p' rows); q-x = N_a N'_b Wpr; x-x = N'_a N'_b Wrr */
        for (int b = 0; b < NN; b++) {
            VD Zp[16], Zd[16];
            for (int i = 0; i < 16; i++) {
                Zp[i] = N[b] * t.Wpp[i] + dN[b] * t.Wpd[i];
                Zd[i] = N[b] * t.Wdp[i] + dN[b] * t.Wdd[i];
            }
            for (int a = 0; a <= b; a++) {
                const double wN = w * N[a], wd = w * dN[a], wdd = wd * dN[b];
                for (int i = 0; i < 16; i++) Hqq[a][b][i] += wN * Zp[i] + wd * Zd[i];
                for (int i = 0; i < 9; i++) Hxx[a][b][i] += wdd * t.Wrr[i];
            }
            const double wdb = w * dN[b];
            for (int a = 0; a < NN; a++) {
                const double c = wdb * N[a];
                for (int i = 0; i < 12; i++) Hqx[a][b][i] += c * t.Wpr[i];
            }
        }
    }
    *energy = E;

    /* chart: g_a = (dE/dx_a, B_a^T dE/dq_a) */
    VD B[MAXNN][12], chart[MAXNN];
    for (int a = 0; a < NN; a++) {
        L(b_matrix)(q[a], B[a]);
        VD *va = vec + 6 * a;
        for (int i = 0; i < 3; i++) va[i] = graw[a][4 + i];
        for (int j = 0; j < 3; j++)
            va[3 + j] = B[a][j] * graw[a][0] + B[a][3 + j] * graw[a][1]
                      + B[a][6 + j] * graw[a][2] + B[a][9 + j] * graw[a][3];
        chart[a] = -0.25 * (q[a][0] * graw[a][0] + q[a][1] * graw[a][1]
                            + q[a][2] * graw[a][2] + q[a][3] * graw[a][3]);
    }
    if (!tangent) return;

    /* H_ab = T_a^T Hraw_ab T_b, T_a = [0 B_a; I 0] from (r, theta) to (q, x) */
    const int ld = 6 * NN;
    for (int a = 0; a < NN; a++) {
        for (int b = 0; b < NN; b++) {
            VD *Hab = H + (6 * a) * ld + 6 * b;   /* rows r_a, theta_a; cols r_b, theta_b */
            VD *Hba = H + (6 * b) * ld + 6 * a;
            /* theta_a - r_b = B_a^T Hqx_ab, and its transpose r_b - theta_a */
            for (int i = 0; i < 3; i++)
                for (int l = 0; l < 3; l++) {
                    const VD *X = Hqx[a][b];
                    const VD s = B[a][i] * X[l] + B[a][3 + i] * X[3 + l]
                                   + B[a][6 + i] * X[6 + l] + B[a][9 + i] * X[9 + l];
                    Hab[(3 + i) * ld + l] = s;
                    Hba[l * ld + 3 + i] = s;
                }
            if (b < a) continue;
            /* r_a - r_b and theta_a - theta_b (b >= a), mirrored to (b, a) */
            const VD *Q = Hqq[a][b];
            VD QB[12];
            for (int i = 0; i < 4; i++)
                for (int j = 0; j < 3; j++)
                    QB[3 * i + j] = Q[4 * i] * B[b][j] + Q[4 * i + 1] * B[b][3 + j]
                                  + Q[4 * i + 2] * B[b][6 + j] + Q[4 * i + 3] * B[b][9 + j];
            for (int i = 0; i < 3; i++)
                for (int j = 0; j < 3; j++) {
                    const VD xx = Hxx[a][b][3 * i + j];
                    const VD tt = B[a][i] * QB[j] + B[a][3 + i] * QB[3 + j]
                                    + B[a][6 + i] * QB[6 + j] + B[a][9 + i] * QB[9 + j];
                    Hab[i * ld + j] = xx;
                    Hab[(3 + i) * ld + 3 + j] = tt;
                    if (b != a) {
                        Hba[j * ld + i] = xx;
                        Hba[(3 + j) * ld + 3 + i] = tt;
                    }
                }
        }
        /* chart term on the diagonal theta block: chart_a I (- 1/2 g_theta^x) */
        VD *D = H + (6 * a + 3) * ld + 6 * a + 3;
        for (int i = 0; i < 3; i++) D[i * ld + i] += chart[a];
        if (!symmetric) {
            const VD *m = vec + 6 * a + 3;
            D[1] += 0.5 * m[2];  D[2] -= 0.5 * m[1];
            D[ld] -= 0.5 * m[2]; D[ld + 2] += 0.5 * m[0];
            D[2 * ld] += 0.5 * m[1]; D[2 * ld + 1] -= 0.5 * m[0];
        }
    }
}

#if LANES > 1
/* out[l][i] = lane l of V[i] for i < n (the lanes with out[l] NULL skipped), LANES entries at
 * a time transposed in registers: reading Hv's vectors whole (a lane read back from a vector
 * just stored waits for the store to complete: copied out lane by lane, the in-plane tangents
 * of 10^4 elements took 7.8 ms instead of 3.2). */
static ALWAYS_INLINE void L(transpose_out)(const VD *V, const int n, double **out)
{
#if LANES == 4
    const int m = n & ~3;
    for (int i = 0; i < m; i += 4) {
        const VI lo = {0, 4, 2, 6}, hi = {1, 5, 3, 7}, first = {0, 1, 4, 5}, last = {2, 3, 6, 7};
        const VD t0 = __builtin_shuffle(V[i], V[i + 1], lo);
        const VD t1 = __builtin_shuffle(V[i], V[i + 1], hi);
        const VD t2 = __builtin_shuffle(V[i + 2], V[i + 3], lo);
        const VD t3 = __builtin_shuffle(V[i + 2], V[i + 3], hi);
        const VD c[LANES] = {__builtin_shuffle(t0, t2, first), __builtin_shuffle(t1, t3, first),
                             __builtin_shuffle(t0, t2, last), __builtin_shuffle(t1, t3, last)};
        for (int l = 0; l < LANES; l++)
            if (out[l] != NULL) memcpy(out[l] + i, &c[l], sizeof(VD));
    }
#else
    const int m = n & ~1;
    for (int i = 0; i < m; i += 2) {
        const VD c[LANES] = {PAIR(V[i], V[i + 1], 0, 2), PAIR(V[i], V[i + 1], 1, 3)};
        for (int l = 0; l < LANES; l++)
            if (out[l] != NULL) memcpy(out[l] + i, &c[l], sizeof(VD));
    }
#endif
    for (int i = m; i < n; i++)
        for (int l = 0; l < LANES; l++)
            if (out[l] != NULL) out[l][i] = LANE(V[i], l);
}

/* The element() of LANES elements at qin[l] (NN, 4; any signs), xin[l] (NN, 3), e0in[l]
 * (nq <= MAXQ points, 6) into energy[l], vec[l] (NN, 6) and H[l] (6NN x 6NN; H NULL: no
 * tangent); a lane whose vec[l] is NULL writes nothing (a last group's padding). */
#define MAXQ 16
static ALWAYS_INLINE void L(elements)(const int NN, const Setup *st, const double **qin,
                                      const double **xin, const double **e0in, int symmetric,
                                      double **energy, double **vec, double **H)
{
    double qb[MAXNN][4][LANES], xb[MAXNN][3][LANES], eb[6 * MAXQ][LANES];
    for (int l = 0; l < LANES; l++) {
        double ql[MAXNN][4];
        align_signs(NN, qin[l], ql);
        for (int a = 0; a < NN; a++) {
            for (int i = 0; i < 4; i++) qb[a][i][l] = ql[a][i];
            for (int i = 0; i < 3; i++) xb[a][i][l] = xin[l][3 * a + i];
        }
        for (int k = 0; k < 6 * st->nq; k++) eb[k][l] = e0in[l][k];
    }
    VD q[MAXNN][4], x[MAXNN][3], e0[6 * MAXQ], E, v[6 * MAXNN];
    memcpy(q, qb, sizeof(VD) * 4 * NN);     /* [a][i][l] is the vectors' layout */
    memcpy(x, xb, sizeof(VD) * 3 * NN);
    memcpy(e0, eb, sizeof(VD) * 6 * st->nq);
    if (H != NULL) {
        VD Hv[36 * MAXNN * MAXNN];
        L(element)(NN, st, q, x, e0, symmetric, &E, v, Hv);
        L(transpose_out)(Hv, 36 * NN * NN, H);
    } else {
        L(element)(NN, st, q, x, e0, symmetric, &E, v, NULL);
    }
    for (int l = 0; l < LANES; l++)
        if (vec[l] != NULL) energy[l][0] = LANE(E, l);
    L(transpose_out)(v, 6 * NN, vec);
}

/* rodsnes_elastic_terms_lanes' work LANES elements at a time, the last group's spare lanes
 * repeating element ne - 1 and writing nothing; with comps the tangents through a buffer, cut
 * (cut_tangent). */
static void L(terms)(int ne, int nn, const Setup *st, const double *qe, const double *xe,
                     const double *e0, int tangent, int symmetric, const int *comps, int ncomp,
                     double *energy, double *vec, double *H)
{
    const int nq = st->nq;
    double Hbuf[LANES * 36 * MAXNN * MAXNN];
#define ELEMENT_GROUPS(NN)                                                                 \
    for (int e = 0; e < ne; e += LANES) {                                                  \
        const double *qg[LANES], *xg[LANES], *eg[LANES];                                   \
        double *Eg[LANES], *vg[LANES], *Hg[LANES];                                         \
        for (int l = 0; l < LANES; l++) {                                                  \
            const int ok = e + l < ne, el = ok ? e + l : ne - 1;                           \
            qg[l] = qe + (long)el * 4 * (NN);                                              \
            xg[l] = xe + (long)el * 3 * (NN);                                              \
            eg[l] = e0 + (long)el * 6 * nq;                                                \
            Eg[l] = energy + el;                                                           \
            vg[l] = ok ? vec + (long)el * 6 * (NN) : NULL;                                 \
            Hg[l] = !ok ? NULL : comps ? Hbuf + (long)l * 36 * (NN) * (NN)                 \
                                       : H + (long)el * 36 * (NN) * (NN);                  \
        }                                                                                  \
        L(elements)(NN, st, qg, xg, eg, symmetric, Eg, vg, tangent ? Hg : NULL);           \
        for (int l = 0; tangent && comps && l < LANES && e + l < ne; l++)                  \
            cut_tangent(NN, Hbuf + (long)l * 36 * (NN) * (NN), comps, ncomp,               \
                        H + (long)(e + l) * ncomp * ncomp * (NN) * (NN));                  \
    }
    BY_NODE_COUNT(ELEMENT_GROUPS)
#undef ELEMENT_GROUPS
}

/* rodsnes_elastic_node_residual_lanes' work LANES elements at a time: each element's nodes
 * gathered (gather_element), its residual rows added to node_vec in the elements' order. */
static void L(node_residual)(int ne, int nn, const Setup *st, const double *qn,
                             const double *xn, const int64_t *conn, const double *e0,
                             double *energy, double *node_vec)
{
    const int nq = st->nq;
#define NODE_GROUPS(NN)                                                                    \
    for (int e = 0; e < ne; e += LANES) {                                                  \
        double qb[LANES][4 * MAXNN], xb[LANES][3 * MAXNN], vb[LANES][6 * MAXNN];           \
        const double *qg[LANES], *xg[LANES], *eg[LANES];                                   \
        double *Eg[LANES], *vg[LANES];                                                     \
        for (int l = 0; l < LANES; l++) {                                                  \
            const int ok = e + l < ne, el = ok ? e + l : ne - 1;                           \
            gather_element(NN, conn + (long)el * (NN), qn, xn, qb[l], xb[l]);              \
            qg[l] = qb[l];                                                                 \
            xg[l] = xb[l];                                                                 \
            eg[l] = e0 + (long)el * 6 * nq;                                                \
            Eg[l] = energy + el;                                                           \
            vg[l] = ok ? vb[l] : NULL;                                                     \
        }                                                                                  \
        L(elements)(NN, st, qg, xg, eg, 0, Eg, vg, NULL);                                  \
        for (int l = 0; l < LANES && e + l < ne; l++) {                                    \
            const int64_t *ce = conn + (long)(e + l) * (NN);                               \
            for (int a = 0; a < (NN); a++)                                                 \
                for (int k = 0; k < 6; k++) node_vec[6 * ce[a] + k] += vb[l][6 * a + k];   \
        }                                                                                  \
    }
    BY_NODE_COUNT(NODE_GROUPS)
#undef NODE_GROUPS
}
#endif
