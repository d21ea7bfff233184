/* Rotations of rodsnes' nodes (C99, no Python API; loaded with ctypes by
 * rodsnes/model/so3_compiled.py): out_i = exp(theta_i) * q_i, one pass over the nodes, with
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
