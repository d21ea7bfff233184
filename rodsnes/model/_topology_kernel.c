/* The Gauss double integral of writhe and link over pairs of straight segments
 * (rodsnes/model/topology.py, _gauss_block): plain C99, no Python API, loaded with ctypes by
 * rodsnes/model/topology.py.  For segments (P_a P_a+1, Q_b Q_b+1) with the unit vectors
 * v00 = u(P_a - Q_b), v10 = u(P_a+1 - Q_b), v11 = u(P_a+1 - Q_b+1), v01 = u(P_a - Q_b+1):
 *     4 pi G_ab = -2 (atan2(v00.(v10 x v11), 1 + v00.v10 + v10.v11 + v00.v11)
 *                   + atan2(v00.(v11 x v01), 1 + v00.v11 + v11.v01 + v01.v00))
 * the signed solid angle of the parallelogram {a(s) - b(t)} as two Van Oosterom-Strackee
 * triangles: the numpy path's formula, with the two atan2 joined into one (the angle of the
 * product of the two complex numbers; atan2 was most of the time) and summed in another
 * order: equal to round-off (tests/test_topology_kernel.py).
 *
 *   double rodsnes_gauss_sum(P, np, Q, nq, self, closed)
 *       P (np, 3), Q (nq, 3) vertices (np - 1 and nq - 1 segments); self = 0: the sum over
 *       all segment pairs; self = 1 (Q = P): over pairs a < b of non-adjacent segments
 *       (b > a + 1), without the pair (0, m - 1) of a closed polygon of m segments.
 */
#include <math.h>
#include <stdint.h>

static inline void unit(const double *p, const double *q, double *u)
{
    double d0 = p[0] - q[0], d1 = p[1] - q[1], d2 = p[2] - q[2];
    double r = sqrt(d0 * d0 + d1 * d1 + d2 * d2);
    u[0] = d0 / r; u[1] = d1 / r; u[2] = d2 / r;
}

static inline double dot(const double *a, const double *b)
{
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

static inline double triple(const double *a, const double *b, const double *c)
{
    /* a . (b x c) */
    return a[0] * (b[1] * c[2] - b[2] * c[1]) + a[1] * (b[2] * c[0] - b[0] * c[2])
         + a[2] * (b[0] * c[1] - b[1] * c[0]);
}

double rodsnes_gauss_sum(const double *P, int64_t np, const double *Q, int64_t nq,
                         int self, int closed)
{
    int64_t m = np - 1, n = nq - 1;
    double total = 0.0;
    double v00[3], v10[3], v11[3], v01[3];
    for (int64_t a = 0; a < m; a++) {
        int64_t b0 = self ? a + 2 : 0;
        if (b0 >= n)
            continue;
        double row = 0.0;
        unit(P + 3 * a, Q + 3 * b0, v00);
        unit(P + 3 * (a + 1), Q + 3 * b0, v10);
        for (int64_t b = b0; b < n; b++) {
            unit(P + 3 * (a + 1), Q + 3 * (b + 1), v11);
            unit(P + 3 * a, Q + 3 * (b + 1), v01);
            if (!(self && closed && a == 0 && b == m - 1)) {
                double d0010 = dot(v00, v10), d1011 = dot(v10, v11), d0011 = dot(v00, v11);
                double d1101 = dot(v11, v01), d0100 = dot(v01, v00);
                /* the two triangles' half angles arg(z1) + arg(z2) = arg(z1 z2): one atan2
                 * (the parallelogram's solid angle lies in (-2 pi, 2 pi), so its half in
                 * (-pi, pi), the range of atan2) */
                double y1 = triple(v00, v10, v11), x1 = 1.0 + d0010 + d1011 + d0011;
                double y2 = triple(v00, v11, v01), x2 = 1.0 + d0011 + d1101 + d0100;
                row += -2.0 * atan2(y1 * x2 + y2 * x1, x1 * x2 - y1 * y2);
            }
            /* the next pair's first column is this pair's second */
            v00[0] = v01[0]; v00[1] = v01[1]; v00[2] = v01[2];
            v10[0] = v11[0]; v10[1] = v11[1]; v10[2] = v11[2];
        }
        total += row;
    }
    return total;
}
