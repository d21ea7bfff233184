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

typedef struct {
    int nq;
    const double *N, *dN, *wJ, *C;
    int limit;
    double kappa_max, mu_kappa;
} Setup;

/* The element's arithmetic, one element at a time (the scalar kernel: dot3 ... element, see
 * _elastic_lanes.h, which the vector widths below include as well) */
#define LANES 1
#define VD lanes_v1
#define L(name) name
#include "_elastic_lanes.h"
#undef LANES
#undef VD
#undef L
#undef SPLAT
#undef LANE

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

/* The element's nodes as element() and interpolate() take them: q from qin (NN, 4) with
 * aligned signs, x from xin (NN, 3). */
static ALWAYS_INLINE void element_nodes(const int NN, const double *qin, const double *xin,
                                        double q[MAXNN][4], double x[MAXNN][3])
{
    align_signs(NN, qin, q);
    for (int a = 0; a < NN; a++)
        for (int i = 0; i < 3; i++) x[a][i] = xin[3 * a + i];
}

/* element() of the element at qin (NN, 4; any signs), xin (NN, 3). */
static ALWAYS_INLINE void element_at(const int NN, const Setup *st, const double *qin,
                                     const double *xin, const double *e0, int symmetric,
                                     double *energy, double *vec, double *H)
{
    double q[MAXNN][4], x[MAXNN][3];
    element_nodes(NN, qin, xin, q, x);
    element(NN, st, q, x, e0, symmetric, energy, vec, H);
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

/* The element's arithmetic on 2 elements at once (SSE2, every x86-64), and on 4 where the
 * processor has AVX2: the 3-D element (_elastic_lanes.h; its 24 x 24 tangents of 10^4 cubic
 * elements: 21.3 ms one element at a time, 16.7 ms two, 14.6 ms four) and the in-plane tangent
 * (_elastic_plane.h; 5.6 ms one element at a time, 4.8 ms two, 3.2 ms four), the same numbers
 * bit for bit at every width. */
#define LANES 2
#define VD lanes_v2
#define VI lanes_i2
#define L(name) name##_2
#define PLANE(name) plane2_##name
#include "_elastic_lanes.h"
#include "_elastic_plane.h"      /* the last of a width: it undefines the width's macros */
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#define LANES_AVX2 1
#pragma GCC push_options
#pragma GCC target("avx2")
#define LANES 4
#define VD lanes_v4
#define VI lanes_i4
#define L(name) name##_4
#define PLANE(name) plane4_##name
#include "_elastic_lanes.h"
#include "_elastic_plane.h"      /* the last of a width: it undefines the width's macros */
#pragma GCC pop_options
#endif

/* The widest width this processor runs: 4 with AVX2, else 2. */
static int widest_lanes(void)
{
#ifdef LANES_AVX2
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx2")) return 4;
#endif
    return 2;
}

/* The width of the 3-D entries for the caller's ``lanes`` (0: the widest, one element at a
 * time beyond MAXQ points; 1, 2 or 4 as asked) and nq points: 1, 2 or 4, -1 for bad arguments,
 * -2 for a width the processor cannot run. */
static int chosen_lanes(int lanes, int nq)
{
    if (lanes != 0 && lanes != 1 && lanes != 2 && lanes != 4) return -1;
    const int widest = widest_lanes();
    if (lanes > widest) return -2;
    if (lanes == 0) return nq <= MAXQ ? widest : 1;
    return lanes > 1 && nq > MAXQ ? -1 : lanes;
}



/* One element into the outputs; with comps its tangent through a buffer, cut (cut_tangent). */
#define ELEMENT_LOOP(NN)                                                                   \
    for (int e = 0; e < ne; e++) {                                                         \
        double *He = !tangent ? (double *)0 : comps ? Hbuf : H + (long)e * 36 * (NN) * (NN); \
        element_at(NN, &st, qe + (long)e * 4 * (NN), xe + (long)e * 3 * (NN),             \
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
 *   comps (ignored unless tangent != 0),
 *   lanes: elements at once, 1, 2 or 4 (4 only with AVX2), 0 the most the processor runs (the
 *   same numbers bit for bit).
 * Returns 0, -1 for bad arguments, -2 for lanes the processor cannot run. */
int rodsnes_elastic_terms_lanes(int ne, int nn, int nq, const double *N, const double *dN,
                                const double *wJ, const double *C, int limit, double kappa_max,
                                double mu_kappa, const double *qe, const double *xe,
                                const double *e0, int tangent, int symmetric, const int *comps,
                                int ncomp, int lanes, double *energy, double *vec, double *H)
{
    if (nn < 1 || nn > MAXNN || nq < 1 || ne < 0) return -1;
    if (comps && (ncomp < 1 || ncomp > 6)) return -1;
    lanes = chosen_lanes(lanes, nq);
    if (lanes < 0) return lanes;
    const Setup st = {nq, N, dN, wJ, C, limit, kappa_max, mu_kappa};
    if (lanes == 1) {
        double Hbuf[36 * MAXNN * MAXNN];
        BY_NODE_COUNT(ELEMENT_LOOP)
        return 0;
    }
#ifdef LANES_AVX2
    if (lanes == 4) {
        terms_4(ne, nn, &st, qe, xe, e0, tangent, symmetric, comps, ncomp, energy, vec, H);
        return 0;
    }
#endif
    terms_2(ne, nn, &st, qe, xe, e0, tangent, symmetric, comps, ncomp, energy, vec, H);
    return 0;
}

/* The strains e = Nz / |p|^2 (v, u) of one element at its nq points (N, dN: (nq, NN)). */
static ALWAYS_INLINE void element_strains(const int NN, int nq, const double *N, const double *dN,
                                          const double *qin, const double *xin, double *e)
{
    double q[MAXNN][4], x[MAXNN][3];
    element_nodes(NN, qin, xin, q, x);
    for (int g = 0; g < nq; g++) {
        double p[4], dp[4], dr[3], Rt[3][3], Nz[6];
        interpolate(NN, N + g * NN, dN + g * NN, q, x, p, dp, dr);
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


/* The residual summed per node: element e's nodes conn[e nn + a] gathered (gather_element),
 * its residual rows added to node_vec (nodes, 6, zero on entry) in the order of the elements
 * (the sparse row sum's order), its energy into energy[e]; no element arrays in memory. */
#define NODE_LOOP(NN)                                                                      \
    for (int e = 0; e < ne; e++) {                                                         \
        double qb[4 * MAXNN], xb[3 * MAXNN], vb[6 * MAXNN];                                \
        const int64_t *ce = conn + (long)e * (NN);                                         \
        gather_element(NN, ce, qn, xn, qb, xb);                                            \
        element_at(NN, &st, qb, xb, e0 + (long)e * 6 * nq, 0, energy + e, vb, (double *)0); \
        for (int a = 0; a < (NN); a++)                                                     \
            for (int k = 0; k < 6; k++) node_vec[6 * ce[a] + k] += vb[6 * a + k];          \
    }

/* Arguments as rodsnes_elastic_terms but the nodes' qn, xn and the elements' conn (ne, nn) of
 * rows in them; outputs energy (ne) and node_vec (nodes, 6), added to; lanes as
 * rodsnes_elastic_terms_lanes (the sums in the elements' order at every width: the same numbers
 * bit for bit).  Returns 0, -1 for bad arguments, -2 for lanes the processor cannot run. */
int rodsnes_elastic_node_residual_lanes(int ne, int nn, int nq, const double *N,
                                        const double *dN, const double *wJ, const double *C,
                                        int limit, double kappa_max, double mu_kappa,
                                        const double *qn, const double *xn, const int64_t *conn,
                                        const double *e0, int lanes, double *energy,
                                        double *node_vec)
{
    if (nn < 1 || nn > MAXNN || nq < 1 || ne < 0) return -1;
    lanes = chosen_lanes(lanes, nq);
    if (lanes < 0) return lanes;
    const Setup st = {nq, N, dN, wJ, C, limit, kappa_max, mu_kappa};
    if (lanes == 1) {
        BY_NODE_COUNT(NODE_LOOP)
        return 0;
    }
#ifdef LANES_AVX2
    if (lanes == 4) {
        node_residual_4(ne, nn, &st, qn, xn, conn, e0, energy, node_vec);
        return 0;
    }
#endif
    node_residual_2(ne, nn, &st, qn, xn, conn, e0, energy, node_vec);
    return 0;
}

/* Energy alone (the line searches' trials): e = Nz / |p|^2 and W at every point, without the
 * derivatives of the strains (numerators, as the full pass computes them). */
static ALWAYS_INLINE double element_energy(const int NN, const Setup *st, const double *qin,
                                           const double *xin, const double *e0)
{
    double q[MAXNN][4], x[MAXNN][3];
    element_nodes(NN, qin, xin, q, x);
    double E = 0.0;
    for (int g = 0; g < st->nq; g++) {
        double p[4], dp[4], dr[3], Rt[3][3], Nz[6], e[6], S[6], Cb[4], W;
        interpolate(NN, st->N + g * NN, st->dN + g * NN, q, x, p, dp, dr);
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
    const int widest = widest_lanes();
    if (lanes > widest) return -2;
#ifdef LANES_AVX2
    if (widest == 4 && lanes != 2) {
        plane4_tangents(ne, nn, &st, qe, xe, e0, axis, H);
        return 0;
    }
#endif
    plane2_tangents(ne, nn, &st, qe, xe, e0, axis, H);
    return 0;
}

/* ---- the tangents added into a block matrix as they are made -------------------------- */
#include <stdlib.h>
#include "_element_blocks.h"

/* Elements made at a time before they are added: their tangents (INTO_CHUNK x 144 doubles of
 * cubic in-plane elements, 9 kB; 4 x that in 3-D) still in the first-level cache when they
 * are added.  The in-plane tangents of 10^4 cubic elements made and added: 3.0-3.2 ms with
 * 8 a time, 3.2-3.4 with 4 or 16, 3.5-3.8 with 32 (as many numbers; -DINTO_CHUNK=n). */
#ifndef INTO_CHUNK
#define INTO_CHUNK 8
#endif

/* The tangents of ne elements, their nodes gathered from the node arrays qn (nodes, 4), xn
 * (nodes, 3) by conn (ne, nn), e0 (ne, nq, 6): the in-plane tangent of the plane normal to
 * e_axis (axis >= 0: rodsnes_elastic_plane_tangent_lanes), or the 3-D one (axis < 0:
 * rodsnes_elastic_terms_lanes with symmetric, comps), added into the value array a of a block
 * matrix at the blocks' places pos (ne, k, k) (_element_blocks.h; -1: not added here; where
 * first (ne, k, k), or NULL, is 1 stored instead), k blocks of bs unknowns an element (k bs =
 * the tangent's rows).  The same numbers as those entries, INTO_CHUNK elements at a time.  Returns 0, -1 for bad arguments, -2 for lanes the
 * processor cannot run, -3 when no work memory could be had. */
int rodsnes_elastic_tangents_into(int ne, int nn, int nq, const double *N, const double *dN,
                                  const double *wJ, const double *C, int limit,
                                  double kappa_max, double mu_kappa, const double *qn,
                                  const double *xn, const int64_t *conn, const double *e0,
                                  int axis, int symmetric, const int *comps, int ncomp,
                                  int lanes, const int32_t *pos, const signed char *first,
                                  int k, int bs, double *a)
{
    if (nn < 1 || nn > MAXNN || nq < 1 || ne < 0 || axis > 2) return -1;
    const int nc = axis >= 0 ? 3 : comps ? ncomp : 6;
    if (nc < 1 || nc > 6 || nc * nn != k * bs || (bs != 3 && bs != 6)) return -1;
    const int64_t hsize = (int64_t)(nc * nn) * (nc * nn);
    double *work = malloc(sizeof(double) * INTO_CHUNK * (7 * nn + hsize + 1 + 6 * nn));
    if (!work) return -3;
    double *qe = work, *xe = qe + INTO_CHUNK * 4 * nn, *H = xe + INTO_CHUNK * 3 * nn;
    double *energy = H + INTO_CHUNK * hsize, *vec = energy + INTO_CHUNK;
    int info = 0;
    for (int e = 0; e < ne && !info; e += INTO_CHUNK) {
        const int m = ne - e < INTO_CHUNK ? ne - e : INTO_CHUNK;
        for (int i = 0; i < m; i++)
            gather_element(nn, conn + (int64_t)(e + i) * nn, qn, xn, qe + 4 * nn * i,
                           xe + 3 * nn * i);
        const double *e0c = e0 + (int64_t)e * nq * 6;
        if (axis >= 0)
            info = rodsnes_elastic_plane_tangent_lanes(m, nn, nq, N, dN, wJ, C, limit,
                                                       kappa_max, mu_kappa, qe, xe, e0c, axis,
                                                       lanes, H);
        else
            info = rodsnes_elastic_terms_lanes(m, nn, nq, N, dN, wJ, C, limit, kappa_max,
                                               mu_kappa, qe, xe, e0c, 1, symmetric, comps,
                                               ncomp, lanes, energy, vec, H);
        if (!info)
            add_element_blocks(a, pos + (int64_t)e * k * k,
                               first ? first + (int64_t)e * k * k : 0, H, m, k, bs);
    }
    free(work);
    return info;
}
