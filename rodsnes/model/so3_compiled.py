"""Compiled node rotations: so3.rotated's exp(theta) q per node in one pass of C.

rodsnes/model/_rotation_kernel.c (plain C99, built by setup.py as the extension
rodsnes.model._rotation_kernel and loaded here with ctypes) computes what so3.qmul(so3.qexp(theta),
q) computes (and its normalisation), reading theta in place from the rows of the local dof array.
The numpy path (so3.rotated without the library) is its reference: equal to round-off
(tests/test_so3_compiled.py).  Measured at 3e5 nodes (Intel Xeon VM): numpy 36 ms (qexp 13, qmul 16,
normalisation 7) against C 8 ms (the sines and cosines).

C entry points:

    void rodsnes_rotate(int64 n, const double *x, int64 stride, const double *q, int normalize,
                        double *out)
    void rodsnes_chord_turns(int64 ne, int64 p, const int64 *conn, const double *x, int64 xs,
                             const double *th, int64 ts, double alpha, double *within)
    void rodsnes_retract_nodes(int64 n, const int64 *flat, const int64 *row,
                               const double *within, const double *offset, const double *s,
                               int closed, const double *loop, double length, const int64 *nh,
                               const double *hs0, *hv0, *hs1, *hv1, *hs2, *hv2, double scale,
                               double *out, int64 os)

The other two are the retraction's (rodsnes/model/retraction.py, whose numpy path is their
reference): the turn excess of the chords, and the owned nodes' corrections added to their rows.
"""
import ctypes

import numpy as np

from rodsnes import compiled


def _declare(lib):
    n, vp = ctypes.c_int64, ctypes.c_void_p
    return {"rotate": compiled.Foreign(lib.rodsnes_rotate,
                                       [n, vp, n, compiled.F64, ctypes.c_int, compiled.F64],
                                       None),
            "chord_turns": compiled.Foreign(lib.rodsnes_chord_turns,
                                            [n, n, compiled.I64, vp, n, vp, n,
                                             ctypes.c_double, compiled.F64], None),
            "retract_nodes": compiled.Foreign(
                lib.rodsnes_retract_nodes,
                [n, compiled.I64, compiled.I64, compiled.F64, compiled.F64, compiled.F64,
                 ctypes.c_int, compiled.F64, ctypes.c_double, compiled.I64]
                + [compiled.F64] * 6 + [ctypes.c_double, vp, n], None)}


# the kernel's ctypes function, or False when the library is not built or does not load.
_load = compiled.loader("rodsnes.model._rotation_kernel", _declare)


def available():
    return bool(_load())


def rotate(theta, q, normalize):
    """exp(theta_i) q_i for theta (n, 3), rows of a float64 array whose entries within a row
    are contiguous (a view of the (n, 6) local dofs is read in place), q (n, 4) C-contiguous;
    None when the library is not built or theta is not such a view."""
    fns = _load()
    if not fns or not _rows_of_three(theta) or len(theta) != len(q):
        return None
    q = np.ascontiguousarray(q, dtype=np.float64)
    out = np.empty((len(q), 4))
    if len(q):
        fns["rotate"](len(q), theta.__array_interface__["data"][0], theta.strides[0] // 8, q,
                      int(bool(normalize)), out)
    return out


def _rows_of_three(a):
    """Whether the kernels read (n, >= 3) float64 rows of ``a`` in place: the entries of a row
    contiguous, the rows a whole number of doubles apart (a view of the (n, 6) local dofs)."""
    return (a.dtype == np.float64 and a.ndim == 2 and a.shape[1] >= 3 and a.strides[1] == 8
            and a.strides[0] % 8 == 0)


def chord_turns(conn, x, theta, alpha):
    """(ne, p + 1, 3): retraction.chord_turns by the C kernel (conn (ne, p + 1) local nodes,
    x and theta (n, 3) rows of three contiguous values, read in place); None when the library
    is not built or the arrays are not so laid out."""
    fns = _load()
    if not fns or not (_rows_of_three(x) and _rows_of_three(theta)):
        return None
    conn = np.ascontiguousarray(conn, dtype=np.int64)
    ne, p1 = conn.shape
    out = np.empty((ne, p1, 3))
    if ne:
        fns["chord_turns"](ne, p1 - 1, conn, x.__array_interface__["data"][0],
                           x.strides[0] // 8, theta.__array_interface__["data"][0],
                           theta.strides[0] // 8, float(alpha), out)
    return out


def retract_nodes(flat, row, within, offset, s, closed, loop, length, anchors, scale, out):
    """retraction.Retraction's corrections of the owned nodes by the C kernel, times ``scale``
    added to out[:, 0:3] (out: (n, >= 3) float64 rows of contiguous values, written in place;
    ``anchors``: per component (held arclengths, values)).  False when the library is not
    built or ``out`` is not so laid out."""
    fns = _load()
    if not fns or not (_rows_of_three(out) and out.flags.writeable):
        return False
    n = len(flat)
    if n:
        hs = [np.ascontiguousarray(a[0], dtype=np.float64) for a in anchors]
        hv = [np.ascontiguousarray(a[1], dtype=np.float64) for a in anchors]
        nh = np.array([len(h) for h in hs], dtype=np.int64)
        fns["retract_nodes"](n, flat, row, within, offset, s, int(bool(closed)),
                             np.ascontiguousarray(loop, dtype=np.float64), float(length), nh,
                             hs[0], hv[0], hs[1], hv[1], hs[2], hv[2], float(scale),
                             out.__array_interface__["data"][0], out.strides[0] // 8)
    return True