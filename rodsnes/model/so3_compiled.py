"""Compiled node rotations: so3.rotated's exp(theta) q per node in one pass of C.

rodsnes/model/_rotation_kernel.c (plain C99, built by setup.py as the extension
rodsnes.model._rotation_kernel and loaded here with ctypes) computes what so3.qmul(so3.qexp(theta),
q) computes (and its normalisation), reading theta in place from the rows of the local dof array.
The numpy path (so3.rotated without the library) is its reference: equal to round-off
(tests/test_so3_compiled.py).  Measured at 3e5 nodes (Intel Xeon VM): numpy 36 ms (qexp 13, qmul 16,
normalisation 7) against C 8 ms (the sines and cosines).

C entry point:

    void rodsnes_rotate(int64 n, const double *x, int64 stride, const double *q, int normalize,
                        double *out)
"""
import ctypes

import numpy as np

from rodsnes import compiled


def _declare(lib):
    n = ctypes.c_int64
    return compiled.Foreign(lib.rodsnes_rotate,
                            [n, ctypes.c_void_p, n, compiled.F64, ctypes.c_int, compiled.F64],
                            None)


# the kernel's ctypes function, or False when the library is not built or does not load.
_load = compiled.loader("rodsnes.model._rotation_kernel", _declare)


def available():
    return bool(_load())


def rotate(theta, q, normalize):
    """exp(theta_i) q_i for theta (n, 3), rows of a float64 array whose entries within a row
    are contiguous (a view of the (n, 6) local dofs is read in place), q (n, 4) C-contiguous;
    None when the library is not built or theta is not such a view."""
    fn = _load()
    if not fn or theta.dtype != np.float64 or theta.ndim != 2 or theta.shape[1] != 3 \
            or theta.strides[1] != 8 or theta.strides[0] % 8 or len(theta) != len(q):
        return None
    q = np.ascontiguousarray(q, dtype=np.float64)
    out = np.empty((len(q), 4))
    if len(q):
        fn(len(q), theta.__array_interface__["data"][0], theta.strides[0] // 8, q,
           int(bool(normalize)), out)
    return out
