/* Fused elastic element kernel of rodsnes (C99, no Python API; loaded with ctypes by
 * rodsnes/model/elastic_compiled.py).  Computes exactly what ElasticRod.element_terms (elastic.py)
 * computes, element by element and quadrature point by quadrature point, without any
 * intermediate arrays beyond the element's own accumulators.
 *
 * Per element (nodal quaternions q_a aligned so that q_a . q_0 >= 0, positions x_a) and per
 * Gauss point, with z = (p, p', r') in R^11:
 *   p = sum_a N_a q_a,  p' = sum_a N'_a q_a,  r' = sum_a N'_a x_a,  n2 = |p|^2
 *   Nz = (g, 2w):  g = Rq(p)^T r' = [s I + 2 pv pv^T - 2 p0 pv^x] r',  s = p0^2 - |pv|^2
 *                  w = p0 pv' - p0' pv - pv x pv'
 *   e  = Nz / n2 = (v, u),   De = DN / n2 - 2 Nz p^T / n2^2   (p columns only)
 *   law: S = C (e - e0),  W = 1/2 (e-e0).C(e-e0), and where kappa = |(u1, u2)| > kappa_max
 *        W += mu/2 (kappa - kappa_max)^2,  S_u12 += mu (kappa - kappa_max) n,  n = (u1, u2)/kappa,
 *        Cb = mu [(1 - kappa_max/kappa) I + (kappa_max/kappa) n n^T]  on the (u1, u2) block
 *   Wz  = De^T S = DN^T S / n2 - 2 (S.Nz) p / n2^2
 *   Wzz = De^T C De + (Cb on (u1,u2)) + S.D2N / n2 - 2/n2^2 (p v^T + v p^T)
 *         - 2 (S.Nz)/n2^2 I_pp + 8 (S.Nz)/n2^3 p p^T,   v = DN^T S
 * with the closed forms of the blocks of S.D2N (a = S_v, b = r', c = S_u):
 *   pp : 2 [[a.b, (a x b)^T], [a x b, a b^T + b a^T - (a.b) I]]
 *   pr': X, X[0] = 2 (p0 a + pv x a), X[1+m][l] = 2 (a_m pv_l - pv_m a_l + (pv.a) d_ml + p0 a^x_ml)
 *   pp': 2 [[0, c^T], [-c, c^x]]
 * The p'r' block of Wzz vanishes (g does not depend on p', w not on r').
 * Raw nodal gradient/Hessian in y_a = (q_a, x_a): q dofs see (N_a p, N'_a p'), x dofs N'_a r';
 * then the chart: g_a = (dE/dx_a, B_a^T dE/dq_a), H_ab = T_a^T Hraw_ab T_b,
 * H_aa(theta, theta) += -1/4 (q_a . dE/dq_a) I  (and, unless symmetric, -1/2 g_theta^x),
 * B(q) = 1/2 [-qv^T; q0 I - qv^x].
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#define MAXNN 8     /* nodes per element supported (orders 1..7) */

#if defined(__GNUC__)
#define ALWAYS_INLINE inline __attribute__((always_inline))
#else
#define ALWAYS_INLINE inline
#endif

typedef struct {
    int nq;
    const double *N, *dN, *wJ, *C;
    int limit;
    double kappa_max, mu_kappa;
} Setup;

/* Quantities at one quadrature point: energy density, dW/dz and the blocks of d2W/dz2. */
typedef struct {
    double W;
    double Wz[11];
    double Wpp[16], Wpd[16], Wdp[16], Wdd[16];   /* 4x4 row-major: p-p, p-p', p'-p, p'-p' */
    double Wpr[12];                              /* 4x3: p - r' */
    double Wrr[9];                               /* 3x3: r' - r' */
} PointTerms;

/* 3-vector helpers: a.b, a x b, and the matrix a^x with a^x b = a x b */
static ALWAYS_INLINE double dot3(const double *a, const double *b)
{
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

static ALWAYS_INLINE void cross3(const double *a, const double *b, double *out)
{
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

static ALWAYS_INLINE void hat3(const double *a, double h[3][3])
{
    h[0][0] = 0.0;   h[0][1] = -a[2]; h[0][2] = a[1];
    h[1][0] = a[2];  h[1][1] = 0.0;   h[1][2] = -a[0];
    h[2][0] = -a[1]; h[2][1] = a[0];  h[2][2] = 0.0;
}

/* Strain numerators at a point and their derivatives DN = dNz/dz (e = Nz / n2). */
typedef struct {
    double n2, inv, inv2;       /* |p|^2, 1/|p|^2, 1/|p|^4 */
    double Rt[3][3];            /* Rq(p)^T = dg/dr' */
    double Nz[6];               /* (g, 2w) */
    double Gp[12], Up[12], Ud[12];   /* 3x4 row-major: dg/dp, d(2w)/dp, d(2w)/dp' */
} Strain;

/* The strain numerators alone: Rt = Rq(p)^T = s I + 2 pv pv^T - 2 p0 pv^x (s = p0^2 - |pv|^2),
 * Nz = (Rt r', 2 w) with 2 w = 2 (p0 pv' - p0' pv - pv x pv'); returns |p|^2.  The energy pass
 * (element_energy) needs no more; strain_numerators adds their derivatives. */
/* Rt = Rq(p)^T |p|^2 = s I + 2 pv pv^T - 2 p0 pv^x (s = p0^2 - |pv|^2); returns |p|^2. */
static ALWAYS_INLINE double rotation_numerator(const double *p, double Rt[3][3])
{
    const double p0 = p[0], pv[3] = {p[1], p[2], p[3]};
    const double pvpv = dot3(pv, pv);
    const double s = p0 * p0 - pvpv;
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            Rt[i][j] = 2.0 * pv[i] * pv[j];
    for (int i = 0; i < 3; i++) Rt[i][i] += s;
    Rt[0][1] += 2.0 * p0 * pv[2];  Rt[0][2] -= 2.0 * p0 * pv[1];
    Rt[1][0] -= 2.0 * p0 * pv[2];  Rt[1][2] += 2.0 * p0 * pv[0];
    Rt[2][0] += 2.0 * p0 * pv[1];  Rt[2][1] -= 2.0 * p0 * pv[0];
    return p0 * p0 + pvpv;
}

static ALWAYS_INLINE double numerators(const double *p, const double *dp, const double *dr,
                                       double Rt[3][3], double *Nz)
{
    const double p0 = p[0], pv[3] = {p[1], p[2], p[3]};
    const double dp0 = dp[0], dpv[3] = {dp[1], dp[2], dp[3]};
    const double n2 = rotation_numerator(p, Rt);
    for (int k = 0; k < 3; k++)
        Nz[k] = dot3(Rt[k], dr);
    double pxdp[3];
    cross3(pv, dpv, pxdp);
    for (int k = 0; k < 3; k++)
        Nz[3 + k] = 2.0 * (p0 * dpv[k] - dp0 * pv[k] - pxdp[k]);
    return n2;
}

static ALWAYS_INLINE void strain_numerators(const double *p, const double *dp, const double *dr,
                                     Strain *z)
{
    const double p0 = p[0], pv[3] = {p[1], p[2], p[3]};
    const double dp0 = dp[0], dpv[3] = {dp[1], dp[2], dp[3]};
    z->n2 = numerators(p, dp, dr, z->Rt, z->Nz);
    z->inv = 1.0 / z->n2;
    z->inv2 = z->inv * z->inv;
    /* dg/dp = 2 [p0 r' - pv x r',  pv r'^T - r' pv^T + (pv.r') I + p0 r'^x]
     * d(2w)/dp = 2 [pv', -p0' I + pv'^x],  d(2w)/dp' = 2 [-pv, p0 I - pv^x] */
    const double pvdr = dot3(pv, dr);
    double pxdr[3], hr[3][3], hd[3][3], hp[3][3];
    cross3(pv, dr, pxdr);
    hat3(dr, hr);
    hat3(dpv, hd);
    hat3(pv, hp);
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
 * bound mu/2 <kappa - kappa_max>^2 on (u1, u2) with its tangent Cb (2x2).  Returns 1 where
 * the bound is active (Cb set), else 0. */
static ALWAYS_INLINE int constitutive_law(const Setup *st, const double *e, const double *e0,
                                   double *S, double *W, double *Cb)
{
    double w = 0.0;
    for (int k = 0; k < 6; k++) {
        const double de = e[k] - e0[k];
        S[k] = st->C[k] * de;
        w += de * S[k];
    }
    *W = 0.5 * w;
    if (!st->limit) return 0;
    const double kappa = sqrt(e[3] * e[3] + e[4] * e[4]);
    const double over = kappa - st->kappa_max;
    if (!(over > 0.0)) return 0;
    const double n[2] = {e[3] / kappa, e[4] / kappa};
    const double mu = st->mu_kappa, ratio = st->kappa_max / kappa;
    *W += 0.5 * mu * over * over;
    S[3] += mu * over * n[0];
    S[4] += mu * over * n[1];
    for (int i = 0; i < 2; i++)
        for (int j = 0; j < 2; j++)
            Cb[2 * i + j] = mu * (((i == j) ? 1.0 - ratio : 0.0) + ratio * n[i] * n[j]);
    return 1;
}

/* Material part of Wzz: De^T C De (+ the bound's Cb on the u1, u2 rows); sets the blocks. */
static ALWAYS_INLINE void material_tangent(const Setup *st, const Strain *z, const double *p,
                                    int bound, const double *Cb, PointTerms *t)
{
    const double inv = z->inv;
    /* De: Dgp = Gp/n2 - 2 g p^T/n2^2, Dup = Up/n2 - 2 (2w) p^T/n2^2, Dud = Ud/n2, Dgr = Rt/n2 */
    double Dgp[12], Dup[12], Dud[12], Dgr[9];
    for (int k = 0; k < 3; k++) {
        const double cg = 2.0 * z->inv2 * z->Nz[k], cu = 2.0 * z->inv2 * z->Nz[3 + k];
        for (int i = 0; i < 4; i++) {
            Dgp[4 * k + i] = z->Gp[4 * k + i] * inv - cg * p[i];
            Dup[4 * k + i] = z->Up[4 * k + i] * inv - cu * p[i];
            Dud[4 * k + i] = z->Ud[4 * k + i] * inv;
        }
        for (int l = 0; l < 3; l++) Dgr[3 * k + l] = z->Rt[k][l] * inv;
    }
    /* K = C De */
    double Kgp[12], Kgr[9], Kup[12], Kud[12];
    for (int k = 0; k < 3; k++) {
        const double cg = st->C[k], cu = st->C[3 + k];
        for (int i = 0; i < 4; i++) {
            Kgp[4 * k + i] = cg * Dgp[4 * k + i];
            Kup[4 * k + i] = cu * Dup[4 * k + i];
            Kud[4 * k + i] = cu * Dud[4 * k + i];
        }
        for (int l = 0; l < 3; l++) Kgr[3 * k + l] = cg * Dgr[3 * k + l];
    }
    if (bound) {
        for (int i = 0; i < 4; i++) {
            const double a0 = Dup[i], a1 = Dup[4 + i], b0 = Dud[i], b1 = Dud[4 + i];
            Kup[i] += Cb[0] * a0 + Cb[1] * a1;
            Kup[4 + i] += Cb[2] * a0 + Cb[3] * a1;
            Kud[i] += Cb[0] * b0 + Cb[1] * b1;
            Kud[4 + i] += Cb[2] * b0 + Cb[3] * b1;
        }
    }
    /* De^T K (g does not depend on p', u not on r') */
    for (int i = 0; i < 4; i++) {
        for (int j = 0; j < 4; j++) {
            double pp = 0.0, pd = 0.0, dd = 0.0;
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
            double pr = 0.0;
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
static ALWAYS_INLINE void geometric_tangent(const Strain *z, const double *p, const double *dr,
                                     const double *S, const double *v, double sN,
                                     PointTerms *t)
{
    const double p0 = p[0], *pv = p + 1, *a = S, *c = S + 3;
    const double ab = dot3(a, dr), pva = dot3(pv, a);
    double axb[3], pxa[3], ha[3][3], hc[3][3];
    cross3(a, dr, axb);
    cross3(pv, a, pxa);
    hat3(a, ha);
    hat3(c, hc);
    const double i2 = 2.0 * z->inv;
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
    const double c2 = 2.0 * z->inv2, c8 = 8.0 * sN * z->inv2 * z->inv, cI = 2.0 * sN * z->inv2;
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
static inline void point_terms(const Setup *st, const double *p, const double *dp,
                               const double *dr, const double *e0, int tangent,
                               PointTerms *t)
{
    Strain z;
    strain_numerators(p, dp, dr, &z);
    double e[6], S[6], Cb[4];
    for (int k = 0; k < 6; k++) e[k] = z.Nz[k] * z.inv;
    const int bound = constitutive_law(st, e, e0, S, &t->W, Cb);
    /* v = DN^T S, sN = S.Nz;  Wz = v / n2 - 2 sN p / n2^2 on p */
    double v[11];
    for (int i = 0; i < 4; i++) {
        double a = 0.0, b = 0.0;
        for (int k = 0; k < 3; k++) {
            a += z.Gp[4 * k + i] * S[k] + z.Up[4 * k + i] * S[3 + k];
            b += z.Ud[4 * k + i] * S[3 + k];
        }
        v[i] = a;
        v[4 + i] = b;
    }
    for (int l = 0; l < 3; l++)
        v[8 + l] = z.Rt[0][l] * S[0] + z.Rt[1][l] * S[1] + z.Rt[2][l] * S[2];
    double sN = 0.0;
    for (int k = 0; k < 6; k++) sN += S[k] * z.Nz[k];
    for (int i = 0; i < 11; i++) t->Wz[i] = v[i] * z.inv;
    for (int i = 0; i < 4; i++) t->Wz[i] -= 2.0 * sN * z.inv2 * p[i];
    if (!tangent) return;
    material_tangent(st, &z, p, bound, Cb, t);
    geometric_tangent(&z, p, dr, S, v, sN, t);
}

/* B(q) = dq/dtheta = 1/2 [-qv^T; q0 I - qv^x]  (4x3 row-major) */
static inline void b_matrix(const double *q, double *B)
{
    const double h = 0.5;
    B[0] = -h * q[1]; B[1] = -h * q[2]; B[2] = -h * q[3];
    B[3] = h * q[0];  B[4] = h * q[3];  B[5] = -h * q[2];
    B[6] = -h * q[3]; B[7] = h * q[0];  B[8] = h * q[1];
    B[9] = h * q[2];  B[10] = -h * q[1]; B[11] = h * q[0];
}

/* Nodal quaternions with aligned signs: q_a = sign(q_a . q_0) q_a (q and -q are one rotation). */
static ALWAYS_INLINE void align_signs(const int NN, const double *qin, double q[MAXNN][4])
{
    for (int a = 0; a < NN; a++) {
        const double *qa = qin + 4 * a;
        const double dot = qa[0] * qin[0] + qa[1] * qin[1] + qa[2] * qin[2] + qa[3] * qin[3];
        const double sg = (dot < 0.0) ? -1.0 : 1.0;
        for (int i = 0; i < 4; i++) q[a][i] = sg * qa[i];
    }
}

/* p, p' and r' at a Gauss point with shape functions N, dN (xin: nodal positions, (NN, 3)). */
static ALWAYS_INLINE void interpolate(const int NN, const double *N, const double *dN,
                                      double q[MAXNN][4], const double *xin, double *p,
                                      double *dp, double *dr)
{
    for (int i = 0; i < 4; i++) p[i] = dp[i] = 0.0;
    for (int i = 0; i < 3; i++) dr[i] = 0.0;
    for (int a = 0; a < NN; a++) {
        for (int i = 0; i < 4; i++) {
            p[i] += N[a] * q[a][i];
            dp[i] += dN[a] * q[a][i];
        }
        for (int i = 0; i < 3; i++) dr[i] += dN[a] * xin[3 * a + i];
    }
}

/* One element: energy, residual (nn, 6) and, if H != NULL, tangent (6nn x 6nn).
 * NN is a compile-time constant where this is inlined (see element_terms below). */
static ALWAYS_INLINE void element(
    const int NN, const Setup *st, const double *qin, const double *xin, const double *e0,
    int symmetric, double *energy, double *vec, double *H)
{
    const int nq = st->nq, tangent = (H != NULL);
    double q[MAXNN][4], graw[MAXNN][7];
    double Hqq[MAXNN][MAXNN][16], Hqx[MAXNN][MAXNN][12], Hxx[MAXNN][MAXNN][9];
    align_signs(NN, qin, q);
    for (int a = 0; a < NN; a++)
        for (int i = 0; i < 7; i++) graw[a][i] = 0.0;
    if (tangent) {
        for (int a = 0; a < NN; a++)
            for (int b = 0; b < NN; b++) {
                for (int i = 0; i < 16; i++) Hqq[a][b][i] = 0.0;
                for (int i = 0; i < 12; i++) Hqx[a][b][i] = 0.0;
                for (int i = 0; i < 9; i++) Hxx[a][b][i] = 0.0;
            }
    }
    double E = 0.0;
    PointTerms t;
    for (int g = 0; g < nq; g++) {
        const double *N = st->N + g * NN, *dN = st->dN + g * NN, w = st->wJ[g];
        double p[4], dp[4], dr[3];
        interpolate(NN, N, dN, q, xin, p, dp, dr);
        point_terms(st, p, dp, dr, e0 + 6 * g, tangent, &t);
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
            double Zp[16], Zd[16];
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
    double B[MAXNN][12], chart[MAXNN];
    for (int a = 0; a < NN; a++) {
        b_matrix(q[a], B[a]);
        double *va = vec + 6 * a;
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
            double *Hab = H + (6 * a) * ld + 6 * b;   /* rows r_a, theta_a; cols r_b, theta_b */
            double *Hba = H + (6 * b) * ld + 6 * a;
            /* theta_a - r_b = B_a^T Hqx_ab, and its transpose r_b - theta_a */
            for (int i = 0; i < 3; i++)
                for (int l = 0; l < 3; l++) {
                    const double *X = Hqx[a][b];
                    const double s = B[a][i] * X[l] + B[a][3 + i] * X[3 + l]
                                   + B[a][6 + i] * X[6 + l] + B[a][9 + i] * X[9 + l];
                    Hab[(3 + i) * ld + l] = s;
                    Hba[l * ld + 3 + i] = s;
                }
            if (b < a) continue;
            /* r_a - r_b and theta_a - theta_b (b >= a), mirrored to (b, a) */
            const double *Q = Hqq[a][b];
            double QB[12];
            for (int i = 0; i < 4; i++)
                for (int j = 0; j < 3; j++)
                    QB[3 * i + j] = Q[4 * i] * B[b][j] + Q[4 * i + 1] * B[b][3 + j]
                                  + Q[4 * i + 2] * B[b][6 + j] + Q[4 * i + 3] * B[b][9 + j];
            for (int i = 0; i < 3; i++)
                for (int j = 0; j < 3; j++) {
                    const double xx = Hxx[a][b][3 * i + j];
                    const double tt = B[a][i] * QB[j] + B[a][3 + i] * QB[3 + j]
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
        double *D = H + (6 * a + 3) * ld + 6 * a + 3;
        for (int i = 0; i < 3; i++) D[i * ld + i] += chart[a];
        if (!symmetric) {
            const double *m = vec + 6 * a + 3;
            D[1] += 0.5 * m[2];  D[2] -= 0.5 * m[1];
            D[ld] -= 0.5 * m[2]; D[ld + 2] += 0.5 * m[0];
            D[2 * ld] += 0.5 * m[1]; D[2 * ld + 1] -= 0.5 * m[0];
        }
    }
}

/* The element's tangent cut to the components comps[0..nc-1] of every node:
 * Hc[(nc a + i)(nc NN) + nc b + j] = H[(6 a + comps[i])(6 NN) + 6 b + comps[j]]. */
static ALWAYS_INLINE void cut_tangent(const int NN, const double *H, const int *comps, int nc,
                                      double *Hc)
{
    const int ld = 6 * NN, lc = nc * NN;
    for (int a = 0; a < NN; a++)
        for (int i = 0; i < nc; i++) {
            const double *row = H + (6 * a + comps[i]) * ld;
            double *out = Hc + (nc * a + i) * lc;
            for (int b = 0; b < NN; b++)
                for (int j = 0; j < nc; j++)
                    out[nc * b + j] = row[6 * b + comps[j]];
        }
}

/* LOOP(NN) for the element's node count nn: a constant for 2-5 nodes, so that the compiler
 * unrolls the node loops, nn itself beyond. */
#define BY_NODE_COUNT(LOOP)                                                                \
    switch (nn) {                                                                          \
    case 2: LOOP(2); break;                                                                \
    case 3: LOOP(3); break;                                                                \
    case 4: LOOP(4); break;                                                                \
    case 5: LOOP(5); break;                                                                \
    default: LOOP(nn); break;                                                              \
    }

/* One element into the outputs; with comps its tangent through a buffer, cut (cut_tangent). */
#define ELEMENT_LOOP(NN)                                                                   \
    for (int e = 0; e < ne; e++) {                                                         \
        double *He = !tangent ? (double *)0 : comps ? Hbuf : H + (long)e * 36 * (NN) * (NN); \
        element(NN, &st, qe + (long)e * 4 * (NN), xe + (long)e * 3 * (NN),                \
                e0 + (long)e * 6 * nq, symmetric, energy + e, vec + (long)e * 6 * (NN), He); \
        if (tangent && comps)                                                              \
            cut_tangent(NN, Hbuf, comps, ncomp, H + (long)e * ncomp * ncomp * (NN) * (NN)); \
    }

/* Public entry point (see rodsnes/model/elastic_compiled.py).  Arrays are C-contiguous float64:
 *   N, dN (nq, nn) shape functions and their arclength derivatives at the Gauss points,
 *   wJ (nq) weights times Jacobian, C (6) stiffness (GA1, GA2, EA, EI1, EI2, GJ),
 *   limit != 0: curvature bound kappa_max with stiffness mu_kappa,
 *   qe (ne, nn, 4), xe (ne, nn, 3), e0 (ne, nq, 6),
 *   comps (ncomp) or NULL: the tangent cut to these components (0..5) of every node,
 *   outputs energy (ne), vec (ne, nn, 6), H (ne, 6nn, 6nn), or (ne, ncomp nn, ncomp nn) with
 *   comps (ignored unless tangent != 0).
 * Returns 0, or -1 if nn is outside 1..MAXNN or nq < 1. */
int rodsnes_elastic_terms(int ne, int nn, int nq, const double *N, const double *dN,
                          const double *wJ, const double *C, int limit, double kappa_max,
                          double mu_kappa, const double *qe, const double *xe,
                          const double *e0, int tangent, int symmetric, const int *comps,
                          int ncomp, double *energy, double *vec, double *H)
{
    if (nn < 1 || nn > MAXNN || nq < 1 || ne < 0) return -1;
    if (comps && (ncomp < 1 || ncomp > 6)) return -1;
    double Hbuf[36 * MAXNN * MAXNN];
    const Setup st = {nq, N, dN, wJ, C, limit, kappa_max, mu_kappa};
    BY_NODE_COUNT(ELEMENT_LOOP)
    return 0;
}

/* The strains e = Nz / |p|^2 (v, u) of one element at its nq points (N, dN: (nq, NN)). */
static ALWAYS_INLINE void element_strains(const int NN, int nq, const double *N, const double *dN,
                                          const double *qin, const double *xin, double *e)
{
    double q[MAXNN][4];
    align_signs(NN, qin, q);
    for (int g = 0; g < nq; g++) {
        double p[4], dp[4], dr[3], Rt[3][3], Nz[6];
        interpolate(NN, N + g * NN, dN + g * NN, q, xin, p, dp, dr);
        const double inv = 1.0 / numerators(p, dp, dr, Rt, Nz);
        for (int k = 0; k < 6; k++) e[6 * g + k] = Nz[k] * inv;
    }
}

#define STRAIN_LOOP(NN)                                                                    \
    for (int e = 0; e < ne; e++)                                                           \
        element_strains(NN, nq, N, dN, qe + (long)e * 4 * (NN), xe + (long)e * 3 * (NN),   \
                        strain + (long)e * 6 * nq)

/* The material strains (ne, nq, 6) at the points of the shape functions N, dN (nq, nn) (their
 * arclength derivatives): the quadrature points, or an element's nodes (the output's nodal
 * strains).  qe (ne, nn, 4), xe (ne, nn, 3).  Returns 0, or -1. */
int rodsnes_elastic_strains(int ne, int nn, int nq, const double *N, const double *dN,
                            const double *qe, const double *xe, double *strain)
{
    if (nn < 1 || nn > MAXNN || nq < 1 || ne < 0) return -1;
    BY_NODE_COUNT(STRAIN_LOOP)
    return 0;
}

/* Element e's nodes ce[a] (rows of the node arrays qn (nodes, 4), xn (nodes, 3)) copied into
 * the element arrays qb (NN, 4), xb (NN, 3) that the element passes read. */
static ALWAYS_INLINE void gather_element(const int NN, const int64_t *ce, const double *qn,
                                         const double *xn, double *qb, double *xb)
{
    for (int a = 0; a < NN; a++) {
        for (int k = 0; k < 4; k++) qb[4 * a + k] = qn[4 * ce[a] + k];
        for (int k = 0; k < 3; k++) xb[3 * a + k] = xn[3 * ce[a] + k];
    }
}

/* The residual summed per node: element e's nodes conn[e nn + a] gathered (gather_element),
 * its residual rows added to node_vec (nodes, 6, zero on entry) in the order of the elements
 * (the sparse row sum's order), its energy into energy[e]; no element arrays in memory. */
#define NODE_LOOP(NN)                                                                      \
    for (int e = 0; e < ne; e++) {                                                         \
        double qb[4 * MAXNN], xb[3 * MAXNN], vb[6 * MAXNN];                                \
        const int64_t *ce = conn + (long)e * (NN);                                         \
        gather_element(NN, ce, qn, xn, qb, xb);                                            \
        element(NN, &st, qb, xb, e0 + (long)e * 6 * nq, 0, energy + e, vb, (double *)0);   \
        for (int a = 0; a < (NN); a++)                                                     \
            for (int k = 0; k < 6; k++) node_vec[6 * ce[a] + k] += vb[6 * a + k];          \
    }

/* Arguments as rodsnes_elastic_terms but the nodes' qn, xn and the elements' conn (ne, nn) of
 * rows in them; outputs energy (ne) and node_vec (nodes, 6), added to.  Returns 0, or -1. */
int rodsnes_elastic_node_residual(int ne, int nn, int nq, const double *N, const double *dN,
                                  const double *wJ, const double *C, int limit,
                                  double kappa_max, double mu_kappa, const double *qn,
                                  const double *xn, const int64_t *conn, const double *e0,
                                  double *energy, double *node_vec)
{
    if (nn < 1 || nn > MAXNN || nq < 1 || ne < 0) return -1;
    const Setup st = {nq, N, dN, wJ, C, limit, kappa_max, mu_kappa};
    BY_NODE_COUNT(NODE_LOOP)
    return 0;
}

/* Energy alone (the line searches' trials): e = Nz / |p|^2 and W at every point, without the
 * derivatives of the strains (numerators, as the full pass computes them). */
static ALWAYS_INLINE double element_energy(const int NN, const Setup *st, const double *qin,
                                           const double *xin, const double *e0)
{
    double q[MAXNN][4];
    align_signs(NN, qin, q);
    double E = 0.0;
    for (int g = 0; g < st->nq; g++) {
        double p[4], dp[4], dr[3], Rt[3][3], Nz[6], e[6], S[6], Cb[4], W;
        interpolate(NN, st->N + g * NN, st->dN + g * NN, q, xin, p, dp, dr);
        const double inv = 1.0 / numerators(p, dp, dr, Rt, Nz);
        for (int k = 0; k < 6; k++) e[k] = Nz[k] * inv;
        constitutive_law(st, e, e0 + 6 * g, S, &W, Cb);
        E += st->wJ[g] * W;
    }
    return E;
}

#define ENERGY_LOOP(NN)                                                                    \
    for (int e = 0; e < ne; e++)                                                           \
        energy[e] = element_energy(NN, &st, qe + (long)e * 4 * (NN), xe + (long)e * 3 * (NN), \
                                   e0 + (long)e * 6 * nq)

#define NODE_ENERGY_LOOP(NN)                                                               \
    for (int e = 0; e < ne; e++) {                                                         \
        double qb[4 * MAXNN], xb[3 * MAXNN];                                               \
        gather_element(NN, conn + (long)e * (NN), qn, xn, qb, xb);                         \
        energy[e] = element_energy(NN, &st, qb, xb, e0 + (long)e * 6 * nq);                \
    }

/* The energy of every element (ne), its nodes gathered from the node arrays qn, xn by conn
 * (ne, nn) as in rodsnes_elastic_node_residual.  Returns 0, or -1. */
int rodsnes_elastic_node_energy(int ne, int nn, int nq, const double *N, const double *dN,
                                const double *wJ, const double *C, int limit, double kappa_max,
                                double mu_kappa, const double *qn, const double *xn,
                                const int64_t *conn, const double *e0, double *energy)
{
    if (nn < 1 || nn > MAXNN || nq < 1 || ne < 0) return -1;
    const Setup st = {nq, N, dN, wJ, C, limit, kappa_max, mu_kappa};
    BY_NODE_COUNT(NODE_ENERGY_LOOP)
    return 0;
}

/* The energy of every element (ne), arguments as rodsnes_elastic_terms.  Returns 0, or -1. */
int rodsnes_elastic_energy(int ne, int nn, int nq, const double *N, const double *dN,
                           const double *wJ, const double *C, int limit, double kappa_max,
                           double mu_kappa, const double *qe, const double *xe,
                           const double *e0, double *energy)
{
    if (nn < 1 || nn > MAXNN || nq < 1 || ne < 0) return -1;
    const Setup st = {nq, N, dN, wJ, C, limit, kappa_max, mu_kappa};
    BY_NODE_COUNT(ENERGY_LOOP)
    return 0;
}

/* ---- The in-plane tangent of a planar state (planar.PlanarSystem's Newton step) ------------
 *
 * At a state in the plane normal to n = e_axis (positions in it, every rotation R_a =
 * exp(phi_a n^x) R_0) the element's quaternions are q_a = z_a (x) q_0 with z_a = (c_a, s_a n),
 * so p = sum N_a q_a = Z (x) q_0, Z = (c, s n), c = sum N_a c_a, s = sum N_a s_a, and
 *   v = R_0^T G / n2,  G = (c^2 - s^2) r' - 2 c s n x r',    u = R_0^T n k / n2,
 *   k = 2 (c s' - c' s),  n2 = c^2 + s^2,
 * the same strains as the 3-D kernel's, of the six numbers y = (c, s, c', s', r'_P, r'_Q)
 * (P < Q the in-plane axes).  With the stresses S of the law, f = R_0 S_v, m = n.R_0 S_u and
 * Phi = f.G + m k (S held fixed):
 *   W_y  = Phi_y / n2 - Phi Dn2 / n2^2,
 *   W_yy = D_eps^T W_eps,eps D_eps + Phi_yy / n2 - (Phi_y Dn2^T + Dn2 Phi_y^T) / n2^2
 *          - Phi D2n2 / n2^2 + 2 Phi Dn2 Dn2^T / n2^3,
 * eps = (G, k) / n2, W_eps,eps = blockdiag(R_0 Cv R_0^T, a3^T Cu a3) (a3 = R_0^T n; Cu with the
 * curvature bound's Cb).  The unknowns of node a: r_P, r_Q (y_4, y_5 through N'_a) and the
 * rotation increment theta about n, dz_a/dtheta = 1/2 (-s_a, c_a), d2z_a/dtheta2 = -z_a / 4:
 *   K_ab = sum_q w J_a^T W_yy J_b,   K_aa(theta, theta) += sum_q w W_y . d2y/dtheta_a^2.
 * In the plane the consistent tangent is symmetric (the -1/2 g_theta^x term has no (n, n)
 * entry), and K equals the 3-D tangent cut to (P, Q, 3 + axis) (tests/test_planar_kernel.py). */

/* z_a = q_a (x) conj(q_0) / |q_0|: (scalar, component along e_axis).  With the unit q_0 / |q_0|
 * p = sum N_a q_a = Z (x) q_0 / |q_0| for quaternions of any norm, as the 3-D kernel takes them
 * (its strains are Nz(p) / |p|^2). */
static ALWAYS_INLINE void plane_angles(const int NN, double q[MAXNN][4], int axis,
                                       double z[MAXNN][2])
{
    const double *r = q[0];
    const double inv = 1.0 / sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3]);
    const int i = axis, j = (axis + 1) % 3, k = (axis + 2) % 3;
    for (int a = 0; a < NN; a++) {
        const double *qa = q[a];
        /* (qa0, qav) (x) (r0, -rv) = (qa0 r0 + qav.rv, -qa0 rv + r0 qav - qav x rv): the scalar
         * and the axis component of the vector */
        const double cross_i = qa[1 + j] * r[1 + k] - qa[1 + k] * r[1 + j];
        z[a][0] = (qa[0] * r[0] + qa[1] * r[1] + qa[2] * r[2] + qa[3] * r[3]) * inv;
        z[a][1] = (-qa[0] * r[1 + i] + r[0] * qa[1 + i] - cross_i) * inv;
    }
}

/* The plane element's arithmetic on 2 elements at once (SSE2, every x86-64), and on 4 where
 * the processor has AVX2 (the planar cantilever's in-plane tangents of 10^4 cubic elements:
 * 5.6 ms one element at a time, 4.8 ms two, 3.2 ms four; the same numbers bit for bit): one
 * source, _elastic_plane.h, built for each width. */
#define LANES 2
#define VD plane_v2
#define VI plane_i2
#define PLANE(name) plane2_##name
#include "_elastic_plane.h"
#undef LANES
#undef VD
#undef VI
#undef PLANE
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#define PLANE_AVX2 1
#pragma GCC push_options
#pragma GCC target("avx2")
#define LANES 4
#define VD plane_v4
#define VI plane_i4
#define PLANE(name) plane4_##name
#include "_elastic_plane.h"
#undef LANES
#undef VD
#undef VI
#undef PLANE
#pragma GCC pop_options
#endif

/* The in-plane tangents of a planar state, (ne, 3nn, 3nn), rows and columns (node, (P, Q,
 * theta_axis)), P < Q the axes other than axis; arguments as rodsnes_elastic_terms, and lanes:
 * how many elements at once, 2 or 4 (4 where the processor has AVX2), 0 the most it can.
 * Returns 0, -1 for bad arguments, -2 for lanes it cannot run (the same numbers either way). */
int rodsnes_elastic_plane_tangent_lanes(int ne, int nn, int nq, const double *N,
                                        const double *dN, const double *wJ, const double *C,
                                        int limit, double kappa_max, double mu_kappa,
                                        const double *qe, const double *xe, const double *e0,
                                        int axis, int lanes, double *H)
{
    if (nn < 1 || nn > MAXNN || nq < 1 || ne < 0 || axis < 0 || axis > 2) return -1;
    if (lanes != 0 && lanes != 2 && lanes != 4) return -1;
    const Setup st = {nq, N, dN, wJ, C, limit, kappa_max, mu_kappa};
    int avx2 = 0;
#ifdef PLANE_AVX2
    __builtin_cpu_init();
    avx2 = __builtin_cpu_supports("avx2") != 0;
    if (avx2 && lanes != 2) {
        plane4_tangents(ne, nn, &st, qe, xe, e0, axis, H);
        return 0;
    }
#endif
    if (lanes == 4 && !avx2) return -2;
    plane2_tangents(ne, nn, &st, qe, xe, e0, axis, H);
    return 0;
}
