/* Rotations of rodsnes' nodes (C99, no Python API; loaded with ctypes by
 * rodsnes/model/so3_compiled.py): rodsnes_rotate, out_i = exp(theta_i) * q_i, one pass over the nodes, with
 * the formulas of so3.qexp and so3.qmul (quaternions (w, x, y, z), Hamilton product), and with
 * ``normalize`` out_i / |out_i|.  theta_i = x[i * stride + (0, 1, 2)]: the rotation
 * increments in place in the rows of the local dof array, no copy.  Built with
 * -ffp-contract=off: the same floating-point operations as the numpy path, up to sin and cos.
 */
#define _GNU_SOURCE             /* sincos: glibc's sin and cos of one argument in one call */
#include <math.h>
#include <stdint.h>

void rodsnes_rotate(int64_t n, const double *x, int64_t stride, const double *q, int normalize,
                    double *out)
{
    for (int64_t i = 0; i < n; i++) {
        const double *t = x + i * stride;
        const double t1 = t[0], t2 = t[1], t3 = t[2];
        const double ang = sqrt(t1 * t1 + t2 * t2 + t3 * t3), half = 0.5 * ang;
        double sh, ch;
        sincos(half, &sh, &ch);
        const double s = ang < 1e-8 ? 0.5 - ang * ang / 48.0 : sh / ang;
        const double a0 = ch, a1 = s * t1, a2 = s * t2, a3 = s * t3;
        const double *b = q + 4 * i;
        const double b0 = b[0], b1 = b[1], b2 = b[2], b3 = b[3];
        double *o = out + 4 * i;
        o[0] = a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3;
        o[1] = a0 * b1 + b0 * a1 + (a2 * b3 - a3 * b2);
        o[2] = a0 * b2 + b0 * a2 + (a3 * b1 - a1 * b3);
        o[3] = a0 * b3 + b0 * a3 + (a1 * b2 - a2 * b1);
        if (normalize) {
            const double r = sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2] + o[3] * o[3]);
            o[0] /= r;
            o[1] /= r;
            o[2] /= r;
            o[3] /= r;
        }
    }
}

/* The turn excess of the chords of a step (rodsnes/model/retraction.py, chord_turns): for
 * each of the ne elements (conn: its p + 1 local nodes, row by row) and each chord c between
 * its consecutive nodes a, b (c = x_b - x_a, x the positions at x[node * xs + (0, 1, 2)]),
 * the mean turn t = alpha (th_a + th_b) / 2 (th at th[node * ts + (0, 1, 2)]) and
 * (exp(t^x) - I - t^x) c = (s - 1) t x c + k t x (t x c), s = sin|t| / |t|,
 * k = (1 - cos|t|) / |t|^2 (series below |t| = 1e-2); within[e, j] (3 values) their sum over
 * the element's first j chords, within[e, 0] = 0.  The formulas of retraction.turn_excess. */
void rodsnes_chord_turns(int64_t ne, int64_t p, const int64_t *conn, const double *x,
                         int64_t xs, const double *th, int64_t ts, double alpha, double *within)
{
    for (int64_t e = 0; e < ne; e++) {
        const int64_t *nd = conn + e * (p + 1);
        double *w = within + e * (p + 1) * 3;
        w[0] = w[1] = w[2] = 0.0;
        for (int64_t j = 0; j < p; j++) {
            const double *xa = x + nd[j] * xs, *xb = x + nd[j + 1] * xs;
            const double *ta = th + nd[j] * ts, *tb = th + nd[j + 1] * ts;
            const double c0 = xb[0] - xa[0], c1 = xb[1] - xa[1], c2 = xb[2] - xa[2];
            const double t0 = 0.5 * alpha * (ta[0] + tb[0]), t1 = 0.5 * alpha * (ta[1] + tb[1]),
                         t2 = 0.5 * alpha * (ta[2] + tb[2]);
            const double a2 = t0 * t0 + t1 * t1 + t2 * t2;
            double sm1, k;
            if (a2 < 1e-4) {
                sm1 = -a2 / 6.0 * (1.0 - a2 / 20.0 * (1.0 - a2 / 42.0));
                k = 0.5 - a2 / 24.0 * (1.0 - a2 / 30.0 * (1.0 - a2 / 56.0));
            } else {
                const double a = sqrt(a2);
                double sh, ch;
                sincos(0.5 * a, &sh, &ch);
                sm1 = 2.0 * sh * ch / a - 1.0;
                k = 2.0 * sh * sh / a2;
            }
            const double u0 = t1 * c2 - t2 * c1, u1 = t2 * c0 - t0 * c2, u2 = t0 * c1 - t1 * c0;
            const double v0 = t1 * u2 - t2 * u1, v1 = t2 * u0 - t0 * u2, v2 = t0 * u1 - t1 * u0;
            w[3 * (j + 1) + 0] = w[3 * j + 0] + (sm1 * u0 + k * v0);
            w[3 * (j + 1) + 1] = w[3 * j + 1] + (sm1 * u1 + k * v1);
            w[3 * (j + 1) + 2] = w[3 * j + 2] + (sm1 * u2 + k * v2);
        }
    }
}

/* The retraction's corrections of the owned nodes (rodsnes/model/retraction.py,
 * Retraction.correction), added to their rows: for node i its sum along the rod
 * C = within[flat[i]] + offset[row[i]] (3 values each), less (closed) the loop mismatch
 * loop s_i / length, less per component k its anchor, the held nodes' sums hv_k interpolated
 * linearly at s_i between the held arclengths hs_k (nh_k of them, ascending; constant beyond
 * the first and the last, as numpy.interp; none held: the constant hv_k[0], the mean), times
 * scale into out[i * os + k].  A held node's own anchor is its own sum: exactly zero. */
static double anchor(int64_t nh, const double *hs, const double *hv, double s)
{
    if (nh <= 1 || s <= hs[0]) return hv[0];
    if (s >= hs[nh - 1]) return hv[nh - 1];
    int64_t lo = 0, hi = nh - 1;           /* hs[lo] <= s < hs[hi] */
    while (hi - lo > 1) {
        const int64_t mid = (lo + hi) / 2;
        if (hs[mid] <= s) lo = mid; else hi = mid;
    }
    const double slope = (hv[hi] - hv[lo]) / (hs[hi] - hs[lo]);
    return slope * (s - hs[lo]) + hv[lo];
}

void rodsnes_retract_nodes(int64_t n, const int64_t *flat, const int64_t *row,
                           const double *within, const double *offset, const double *s,
                           int closed, const double *loop, double length,
                           const int64_t *nh, const double *hs0, const double *hv0,
                           const double *hs1, const double *hv1, const double *hs2,
                           const double *hv2, double scale, double *out, int64_t os)
{
    const double *hs[3] = {hs0, hs1, hs2}, *hv[3] = {hv0, hv1, hv2};
    for (int64_t i = 0; i < n; i++) {
        const double *w = within + 3 * flat[i], *o = offset + 3 * row[i];
        for (int k = 0; k < 3; k++) {
            double c = w[k] + o[k];
            if (closed) c -= loop[k] * (s[i] / length);
            c -= anchor(nh[k], hs[k], hv[k], s[i]);
            out[i * os + k] += scale * c;
        }
    }
}
