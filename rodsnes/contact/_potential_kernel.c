/* Pair-potential contact kernel of rodsnes (C99, no Python API; loaded with ctypes by
 * rodsnes/contact/potential_compiled.py).  Computes what the numpy path of
 * contact_potential.PotentialKernel computes (_near_couples, _residual, add_tangent), element
 * pair by element pair, without the (pairs, nqp, nqp + 2) arrays:
 *
 *   D_qj = xs_q - xm_j,  r = |D|,  a = 2 eps - r,  W = wJ_q wm_j,  nu = D / r
 *   E    = k sum W psi(a)
 *   dE/dx_A       = - sum W k psi'(a) Ntil_A nu,                Ntil = [N(xi_q), -N(xi_j)]
 *   d2E/dx_A dx_B = sum W k Ntil_A Ntil_B [ (psi'' + psi'/r) nu nu^T - (psi'/r) I ]
 *
 * over the couples in contact: admissible (|s_q - sigma_j| >= delta, periodic on a ring, on the
 * pairs the exclusion cuts) and r < 2 eps.  psi is the onset law of contact/potential.py
 * (a_s = 0: the quadratic law) with its wall.  Distances and the exclusion test are evaluated
 * with the same floating-point operations, in the same order, as the numpy path (build with
 * -ffp-contract=off: no fused multiply-adds), so the couples in contact are the same ones;
 * sums over couples differ from numpy's by round-off only.
 *
 * The couples are listed sorted by (pair, q, j); a row is a pair with a couple of W > 0.
 * The list is made in chunks of at most maxc couples (the caller's buffers, a bounded
 * size): a chunk ends before the first pair whose couples might not fit, and the next
 * call goes on from there with the running sums (state), so the result does not
 * depend on the chunk size.
 * The pass skips, pair by pair, the slave points farther than 2 eps from the bounding sphere of
 * the master points and the master points farther than 2 eps from that of the slave points.
 * The energy is summed with Neumaier's compensation (numpy sums pairwise: the two agree to
 * round-off of the sum, not of its ~1e4 terms).
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

typedef struct {
    int64_t nqp, nm, n1;
    const double *xs, *xm;          /* (no, nqp, 3), (npool, nm, 3) */
    const int64_t *oi, *mi;         /* (nn) slave / master element of each pair */
    const double *Np, *Nm;          /* (nqp, n1), (nm, n1) */
    const double *wpJ, *wm;         /* (nqp), (nn, nm) */
    double two_eps;
    const double *law;             /* {a_s, a_b, a_w, a_max} */
    double k;
} Setup;

/* The law (contact/potential.py, Onset law and The wall): law = {a_s, a_b, a_w, a_max}, a_w = 0
 * for no wall; a_max clips the depth of a couple (+inf but for the report's pass,
 * potential_compiled.report_force).  wall() adds the barrier x^2 B(t), t = (a_w - a) / x, x = a_w - a_b,
 * B = -(t - 1)^2 ln t, and its first two derivatives in a (which = 0, 1, 2); +inf from a_w. */
static double wall(double a, const double *law, int which)
{
    const double a_b = law[1], a_w = law[2];
    if (!(a_w > 0.0) || a <= a_b)
        return 0.0;
    if (a >= a_w)
        return INFINITY;
    const double x = a_w - a_b, t = (a_w - a) / x, u = t - 1.0, lt = log(t);
    if (which == 0)
        return -x * x * u * u * lt;
    if (which == 1)
        return x * (2.0 * u * lt + u * u / t);
    return -2.0 * lt - 4.0 * u / t + u * u / (t * t);
}

static double law_energy(double a, const double *law)
{
    const double a_s = law[0];
    const double w = wall(a, law, 0);
    if (a_s <= 0.0)
        return 0.5 * a * a + w;
    return (a < a_s ? a * a * a / (6.0 * a_s) : a * (0.5 * a - 0.5 * a_s) + a_s * a_s / 6.0) + w;
}

static double law_force(double a, const double *law)
{
    const double a_s = law[0];
    const double w = wall(a, law, 1);
    if (a_s <= 0.0)
        return a + w;
    return (a < a_s ? a * a / (2.0 * a_s) : a - 0.5 * a_s) + w;
}

static double law_stiffness(double a, const double *law)
{
    const double a_s = law[0];
    const double w = wall(a, law, 2);
    if (a_s <= 0.0)
        return 1.0 + w;
    return fmin(a / a_s, 1.0) + w;
}

/* D = xs[oi[p], q] - xm[mi[p], j] */
static void couple_vector(const Setup *S, int64_t p, int64_t q, int64_t j, double *D)
{
    const double *x = S->xs + (S->oi[p] * S->nqp + q) * 3;
    const double *y = S->xm + (S->mi[p] * S->nm + j) * 3;
    D[0] = x[0] - y[0];
    D[1] = x[1] - y[1];
    D[2] = x[2] - y[2];
}

/* Centre (mean) and radius of the n points x (n, 3). */
static double points_sphere(const double *x, int64_t n, double *c)
{
    c[0] = c[1] = c[2] = 0.0;
    for (int64_t i = 0; i < n; i++)
        for (int d = 0; d < 3; d++)
            c[d] += x[i * 3 + d];
    for (int d = 0; d < 3; d++)
        c[d] /= (double)n;
    double R2 = 0.0;
    for (int64_t i = 0; i < n; i++) {
        const double a = x[i * 3] - c[0], b = x[i * 3 + 1] - c[1], z = x[i * 3 + 2] - c[2];
        const double r2 = a * a + b * b + z * z;
        if (r2 > R2)
            R2 = r2;
    }
    return sqrt(R2);
}

/* |x - c|^2 > (reach + R)^2, with a margin for the round-off: no point within R of c comes
 * within reach of x. */
static int beyond(const double *x, const double *c, double reach, double R)
{
    const double a = x[0] - c[0], b = x[1] - c[1], z = x[2] - c[2];
    const double lim = (reach + R) * (1.0 + 1e-9);
    return a * a + b * b + z * z > lim * lim;
}

/* Couples in contact, energy and residual rows, from pair p0 on, in bounded chunks.
 *   e, m: element ids of the pairs; nelem, h, delta, L, closed: the exclusion.
 *   sq, sm: (x + 1) h / 2 of the slave and master points.
 * Out: the couples (cp, cq, cj, cr) of this chunk, at most maxc >= nqp nm (one pair's worth):
 * the pass stops before the first pair whose couples no longer fit, so that the caller can
 * take the chunk's couples and go on from there with the same buffers; the rows act (pair
 * indices) and vec (rows, 2 n1, 3), indexed over the whole pass (nrow carried in state).
 * state (in/out, carried from chunk to chunk, zero/+inf at the start of a pass):
 *   {energy, its compensation (Neumaier), min |D|^2 over the admissible couples (+inf without
 *    any), number of rows, the next pair to do (nn when done), 1 if prune skipped a point}.
 * The chunks of a pass sum the energy in the order of one pass over all pairs (the same
 * floating-point operations, whatever maxc).  work: (nqp + nm) * 3 doubles.
 * With prune, a pair's slave points farther than 2 eps from the sphere of its master points
 * and master points farther from the sphere of its slave points are skipped (they hold no
 * couple in contact); the min |D|^2 is then exact only if some couple is in contact, and the
 * caller makes the pass again without prune when none is and state[5] says a point was
 * skipped.  Returns the number of couples of the chunk (-1: maxc < nqp nm). */
static int64_t couples_pass(
    int prune, int64_t p0, int64_t nn, int64_t nqp, int64_t nm, int64_t n1,
    const double *xs, const double *xm, const int64_t *oi, const int64_t *mi,
    const int64_t *e, const int64_t *m, int64_t nelem, double h, double delta, double L,
    int closed, const double *sq, const double *sm,
    const double *Np, const double *Nm, const double *wpJ, const double *wm,
    double two_eps, const double *law, double k, int64_t maxc,
    int64_t *cp, int64_t *cq, int64_t *cj, double *cr,
    int64_t *act, double *vec, double *work, double *state)
{
    const double thr = two_eps * two_eps * (1.0 + 1e-12);
    double *Gs = work, *Gm = work + nqp * 3;
    double energy = state[0], lost = state[1], rmin2 = state[2];    /* Neumaier's sum */
    int64_t nc = 0, nrow = (int64_t)state[3], jl[nm], p;
    int pruned = state[5] != 0.0;
    if (maxc < nqp * nm)
        return -1;
    for (p = p0; p < nn; p++) {
        if (nc + nqp * nm > maxc)       /* the pair's couples might not fit: next chunk */
            break;
        int64_t dk = e[p] > m[p] ? e[p] - m[p] : m[p] - e[p];
        if (closed && nelem - dk < dk)
            dk = nelem - dk;
        const int cut = (double)(dk > 1 ? dk - 1 : 0) * h < delta;
        const double se = (double)e[p] * h, sg = (double)m[p] * h;
        const double *wmp = wm + p * nm;
        const double *xsp = xs + oi[p] * nqp * 3, *xmp = xm + mi[p] * nm * 3;
        double cs[3], cm[3], Rs = 0.0, Rm = 0.0;
        int64_t nj = 0;
        if (prune) {
            Rs = points_sphere(xsp, nqp, cs);
            Rm = points_sphere(xmp, nm, cm);
        }
        for (int64_t j = 0; j < nm; j++)
            if (!prune || !beyond(xmp + j * 3, cs, two_eps, Rs))
                jl[nj++] = j;
        pruned |= nj < nm;
        int active = 0;
        for (int64_t q = 0; q < nqp && nj; q++) {
            const double *x = xsp + q * 3;
            if (prune && beyond(x, cm, two_eps, Rm)) {
                pruned = 1;
                continue;
            }
            for (int64_t jj = 0; jj < nj; jj++) {
                const int64_t j = jl[jj];
                const double *y = xmp + j * 3;
                double D[3] = {x[0] - y[0], x[1] - y[1], x[2] - y[2]};
                double r2 = D[0] * D[0];
                r2 += D[1] * D[1];
                r2 += D[2] * D[2];
                if (cut) {
                    double dist = fabs((se + sq[q]) - (sg + sm[j]));
                    if (closed)
                        dist = fmin(dist, L - dist);
                    if (!(dist >= delta))
                        continue;
                }
                if (r2 < rmin2)
                    rmin2 = r2;
                if (!(r2 < thr))
                    continue;
                double r = sqrt(r2);
                if (!(r < two_eps))
                    continue;
                cp[nc] = p;
                cq[nc] = q;
                cj[nc] = j;
                cr[nc] = r;
                nc++;
                if (!(wmp[j] > 0.0))
                    continue;
                if (!active) {
                    memset(work, 0, (size_t)((nqp + nm) * 3) * sizeof(double));
                    active = 1;
                }
                double a = fmin(two_eps - r, law[3]), W = wpJ[q] * wmp[j];
                const double term = W * law_energy(a, law), sum = energy + term;
                lost += fabs(energy) >= fabs(term) ? (energy - sum) + term : (term - sum) + energy;
                energy = sum;
                double g = -k * W * law_force(a, law) / (r > 0.0 ? r : 1.0);
                for (int d = 0; d < 3; d++) {
                    Gs[q * 3 + d] += g * D[d];
                    Gm[j * 3 + d] += g * D[d];
                }
            }
        }
        if (!active)
            continue;
        double *v = vec + nrow * (2 * n1 * 3);
        memset(v, 0, (size_t)(2 * n1 * 3) * sizeof(double));
        for (int64_t q = 0; q < nqp; q++)
            for (int64_t b = 0; b < n1; b++)
                for (int d = 0; d < 3; d++)
                    v[b * 3 + d] += Np[q * n1 + b] * Gs[q * 3 + d];
        for (int64_t j = 0; j < nm; j++)
            for (int64_t b = 0; b < n1; b++)
                for (int d = 0; d < 3; d++)
                    v[(n1 + b) * 3 + d] -= Nm[j * n1 + b] * Gm[j * 3 + d];
        act[nrow++] = p;
    }
    state[0] = energy;
    state[1] = lost;
    state[2] = rmin2;
    state[3] = (double)nrow;
    state[4] = (double)p;
    state[5] = pruned;
    return nc;
}

int64_t rodsnes_potential_residual(
    int prune, int64_t p0, int64_t nn, int64_t nqp, int64_t nm, int64_t n1,
    const double *xs, const double *xm, const int64_t *oi, const int64_t *mi,
    const int64_t *e, const int64_t *m, int64_t nelem, double h, double delta, double L,
    int closed, const double *sq, const double *sm,
    const double *Np, const double *Nm, const double *wpJ, const double *wm,
    double two_eps, const double *law, double k, int64_t maxc,
    int64_t *cp, int64_t *cq, int64_t *cj, double *cr,
    int64_t *act, double *vec, double *work, double *state)
{
    /* prune as a constant: the compiler makes a pass of each kind (a run-time prune in the
     * inner loops made the pass 1.4 times slower, measured on the bench coil) */
    if (prune)
        return couples_pass(1, p0, nn, nqp, nm, n1, xs, xm, oi, mi, e, m, nelem, h, delta, L,
                            closed, sq, sm, Np, Nm, wpJ, wm, two_eps, law, k, maxc, cp, cq, cj,
                            cr, act, vec, work, state);
    return couples_pass(0, p0, nn, nqp, nm, n1, xs, xm, oi, mi, e, m, nelem, h, delta, L,
                        closed, sq, sm, Np, Nm, wpJ, wm, two_eps, law, k, maxc, cp, cq, cj, cr,
                        act, vec, work, state);
}

/* Index of the symmetric 3 x 3 entry (i, k) in the 6 entries (00, 11, 22, 01, 02, 12). */
static const int SYM[9] = {0, 3, 4, 3, 1, 5, 4, 5, 2};

/* Tangent blocks of the rows of rodsnes_potential_residual, from its couples.
 * mat: (rows, 6 n1, 6 n1); work: (nqp + nm + nqp n1) * 6 doubles. */
int64_t rodsnes_potential_tangent(
    int64_t nc, int64_t nqp, int64_t nm, int64_t n1,
    const double *xs, const double *xm, const int64_t *oi, const int64_t *mi,
    const double *Np, const double *Nm, const double *wpJ, const double *wm,
    double two_eps, const double *law, double k,
    const int64_t *cp, const int64_t *cq, const int64_t *cj, const double *cr,
    int64_t nrow, double *mat, double *work)
{
    Setup S = {nqp, nm, n1, xs, xm, oi, mi, Np, Nm, wpJ, wm, two_eps, law, k};
    const int64_t n6 = 6 * n1;
    double *Hs = work, *Hm = work + nqp * 6, *T = work + (nqp + nm) * 6;
    const size_t wsize = (size_t)((nqp + nm + nqp * n1) * 6) * sizeof(double);
    int64_t row = -1, ql[nqp];
    int64_t c = 0;
    while (c < nc) {
        const int64_t p = cp[c];
        int64_t c1 = c;
        while (c1 < nc && cp[c1] == p)
            c1++;
        int active = 0;
        int64_t nq = 0;             /* ql: the slave points with couples (sorted by q) */
        for (int64_t i = c; i < c1; i++) {
            const int64_t q = cq[i], j = cj[i];
            const double wmj = wm[p * nm + j];
            if (!(wmj > 0.0))
                continue;
            if (!active) {
                memset(work, 0, wsize);
                active = 1;
            }
            if (!nq || ql[nq - 1] != q)
                ql[nq++] = q;
            double D[3];
            couple_vector(&S, p, q, j, D);
            const double r = cr[i], a = two_eps - r, W = wpJ[q] * wmj;
            const double rs = r > 0.0 ? r : 1.0, on = k * W;
            const double crr = law_force(a, law) / rs;
            const double coef = on * (law_stiffness(a, law) + crr) / (rs * rs);
            const double U[3] = {coef * D[0], coef * D[1], coef * D[2]};
            double H[6] = {U[0] * D[0], U[1] * D[1], U[2] * D[2],
                           U[0] * D[1], U[0] * D[2], U[1] * D[2]};
            H[0] -= on * crr;
            H[1] -= on * crr;
            H[2] -= on * crr;
            for (int n = 0; n < 6; n++) {
                Hs[q * 6 + n] += H[n];
                Hm[j * 6 + n] += H[n];
            }
            for (int64_t b = 0; b < n1; b++) {
                const double nb = Nm[j * n1 + b];
                double *t = T + (q * n1 + b) * 6;
                for (int n = 0; n < 6; n++)
                    t[n] += nb * H[n];
            }
        }
        c = c1;
        if (!active)
            continue;
        row++;
        if (row >= nrow)
            return -1;
        double *M = mat + row * n6 * n6;
        for (int64_t A = 0; A < n1; A++) {
            for (int64_t B = 0; B < n1; B++) {
                double ss[6] = {0}, mm[6] = {0}, sm[6] = {0};
                for (int64_t iq = 0; iq < nq; iq++) {
                    const int64_t q = ql[iq];
                    const double na = Np[q * n1 + A], w = na * Np[q * n1 + B];
                    const double *t = T + (q * n1 + B) * 6;
                    for (int n = 0; n < 6; n++) {
                        ss[n] += w * Hs[q * 6 + n];
                        sm[n] -= na * t[n];
                    }
                }
                if (B >= A)
                    for (int64_t j = 0; j < nm; j++) {
                        const double w = Nm[j * n1 + A] * Nm[j * n1 + B];
                        for (int n = 0; n < 6; n++)
                            mm[n] += w * Hm[j * 6 + n];
                    }
                for (int i = 0; i < 3; i++) {
                    for (int kk = 0; kk < 3; kk++) {
                        const int n = SYM[i * 3 + kk];
                        /* rows (node, i), columns (node, kk) over [slave nodes, master nodes];
                         * the master-master block is symmetric: its lower half mirrored */
                        M[(A * 3 + i) * n6 + B * 3 + kk] = ss[n];
                        if (B >= A) {
                            M[((n1 + A) * 3 + i) * n6 + (n1 + B) * 3 + kk] = mm[n];
                            M[((n1 + B) * 3 + kk) * n6 + (n1 + A) * 3 + i] = mm[n];
                        }
                        M[(A * 3 + i) * n6 + (n1 + B) * 3 + kk] = sm[n];
                        M[((n1 + B) * 3 + kk) * n6 + A * 3 + i] = sm[n];
                    }
                }
            }
        }
    }
    return row + 1;
}
