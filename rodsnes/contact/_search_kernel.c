/* Geometry of the contact's candidate search in C (rodsnes/contact/search_compiled.py, loaded
 * with ctypes; plain C99, no Python API): the same formulas as rodsnes/contact/search.py's
 * element_bounds and segment_distance, element by element and row by row, without numpy's
 * temporaries (a few hundred elements are 20 numpy calls' overhead: the plectoneme's contact
 * evaluation).  Equal to numpy's to round-off (numpy's einsum sums a 3-vector's products in
 * another order; the capsule test's 1e-9 margin is far above it).
 *
 *   int rodsnes_element_bounds(int64_t ne, int n1, int ns, const double *NsT, const double *x,
 *                              double padc, double *c, double *R);
 *   int rodsnes_segment_distance(int64_t n, const double *p1, const double *q1,
 *                                const double *p2, const double *q2, double *out);
 */
#include <math.h>
#include <stdint.h>

#define MAX_SAMPLES 1024
#define MAX_NODES 16

/* clamped to [0, 1], NaN kept (numpy's minimum(maximum(v, 0), 1)) */
static inline double unit(double v) { return v < 0.0 ? 0.0 : (v > 1.0 ? 1.0 : v); }

static inline double dot3(const double *a, const double *b)
{
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

/* Bounding spheres of ne Lagrange elements x (ne, n1, 3): the samples x^T NsT (NsT (n1, ns):
 * the shape functions at ns equispaced points) give the centre c (the middle of their box) and
 * the radius R_s (their farthest from c); R = R_s + padc max_a |x_a - c| + 1e-12 (that +
 * max_d |c_d|), padc = (Dxi^2 / 8) 1.05 Lambda2_p (0 below order 2).  Returns 0, or -1 for
 * more samples or nodes than it holds. */
int rodsnes_element_bounds(int64_t ne, int n1, int ns, const double *NsT, const double *x,
                           double padc, double *c, double *R)
{
    if (ns < 1 || ns > MAX_SAMPLES || n1 < 1 || n1 > MAX_NODES || ne < 0)
        return -1;
    double pts[MAX_SAMPLES][3];
    for (int64_t e = 0; e < ne; e++) {
        const double *xe = x + e * 3 * n1;
        double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
        for (int j = 0; j < ns; j++) {
            double v[3] = {0.0, 0.0, 0.0};
            for (int a = 0; a < n1; a++) {
                const double w = NsT[a * ns + j];
                v[0] += xe[3 * a] * w;
                v[1] += xe[3 * a + 1] * w;
                v[2] += xe[3 * a + 2] * w;
            }
            for (int d = 0; d < 3; d++) {
                pts[j][d] = v[d];
                lo[d] = v[d] < lo[d] ? v[d] : lo[d];
                hi[d] = v[d] > hi[d] ? v[d] : hi[d];
            }
        }
        const double cb[3] = {0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), 0.5 * (lo[2] + hi[2])};
        double r2 = 0.0;
        for (int j = 0; j < ns; j++) {
            const double u = pts[j][0] - cb[0], v = pts[j][1] - cb[1], w = pts[j][2] - cb[2];
            const double q = u * u + v * v + w * w;
            r2 = q > r2 ? q : r2;
        }
        double s2 = 0.0;
        for (int a = 0; a < n1; a++) {
            const double u = xe[3 * a] - cb[0], v = xe[3 * a + 1] - cb[1],
                         w = xe[3 * a + 2] - cb[2];
            const double q = u * u + v * v + w * w;
            s2 = q > s2 ? q : s2;
        }
        const double spread = sqrt(s2);
        const double cmax = fmax(0.0, fmax(fabs(cb[0]), fmax(fabs(cb[1]), fabs(cb[2]))));
        int finite = 1;             /* a node not finite: NaN bounds, as numpy's reductions */
        for (int k = 0; k < 3 * n1; k++)
            finite &= isfinite(xe[k]);
        for (int d = 0; d < 3; d++)
            c[3 * e + d] = finite ? cb[d] : NAN;
        R[e] = finite ? sqrt(r2) + padc * spread + 1e-12 * (spread + cmax) : NAN;
    }
    return 0;
}

/* Distances between the segments [p1, q1] and [p2, q2], row by row (n rows of 3): the clamped
 * solution of the two lines' normal equations (search.segment_distance's operations).
 * Returns 0. */
int rodsnes_segment_distance(int64_t n, const double *p1, const double *q1, const double *p2,
                             const double *q2, double *out)
{
    for (int64_t i = 0; i < n; i++) {
        const double *P1 = p1 + 3 * i, *Q1 = q1 + 3 * i, *P2 = p2 + 3 * i, *Q2 = q2 + 3 * i;
        double d1[3], d2[3], r[3];
        for (int k = 0; k < 3; k++) {
            d1[k] = Q1[k] - P1[k];
            d2[k] = Q2[k] - P2[k];
            r[k] = P1[k] - P2[k];
        }
        const double a = dot3(d1, d1), e = dot3(d2, d2), b = dot3(d1, d2);
        const double c = dot3(d1, r), f = dot3(d2, r);
        const double a_ = a > 0.0 ? a : 1.0, e_ = e > 0.0 ? e : 1.0;
        const double den = a * e - b * b;
        double s = den > 1e-14 * a * e ? unit((b * f - c * e) / (den > 0.0 ? den : 1.0)) : 0.0;
        double t = (b * s + f) / e_;
        s = t < 0.0 ? unit(-c / a_) : (t > 1.0 ? unit((b - c) / a_) : s);
        s = a > 0.0 ? s : 0.0;
        t = e > 0.0 ? unit(t) : 0.0;
        double w[3];
        for (int k = 0; k < 3; k++)
            w[k] = r[k] + d1[k] * s - d2[k] * t;
        out[i] = sqrt(dot3(w, w));
    }
    return 0;
}
