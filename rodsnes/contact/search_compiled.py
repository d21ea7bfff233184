"""The contact search's geometry in C: search.element_bounds and search.segment_distance
computed by rodsnes/contact/_search_kernel.c (plain C99, built by setup.py as the extension
rodsnes.contact._search_kernel, loaded here with ctypes), without numpy's per-call overhead:
for the plectoneme's 60 elements the bounds took 0.14 ms a call in numpy.  Equal to the numpy
forms to round-off (tests/test_contact_math.py)."""
import ctypes

import numpy as np

from rodsnes import compiled


def _declare(lib):
    i64, c_int, c_dbl, f64 = ctypes.c_int64, ctypes.c_int, ctypes.c_double, compiled.F64
    bounds = compiled.Foreign(lib.rodsnes_element_bounds,
                              [i64, c_int, c_int, f64, f64, c_dbl, f64, f64], c_int)
    segments = compiled.Foreign(lib.rodsnes_segment_distance, [i64, f64, f64, f64, f64, f64],
                                c_int)
    return bounds, segments


_load = compiled.loader("rodsnes.contact._search_kernel", _declare)


def available():
    """True when the compiled search kernel is built and loads."""
    return bool(_load())


def element_bounds(x, NsT, padc):
    """(centres (ne, 3), radii (ne,)) of search.element_bounds for the elements x (ne, p+1, 3),
    the shape functions at the samples NsT (p+1, samples) and the pad coefficient padc."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    ne, n1, dim = x.shape
    if dim != 3 or NsT.ndim != 2 or NsT.shape[0] != n1:
        raise ValueError(f"elements {x.shape} and shape functions {NsT.shape} do not match")
    c, R = np.empty((ne, 3)), np.empty(ne)
    if _load()[0](ne, n1, NsT.shape[1], np.ascontiguousarray(NsT), x, float(padc), c, R):
        raise ValueError(f"element bounds: {n1} nodes, {NsT.shape[1]} samples exceed the kernel's")
    return c, R


def segment_distance(p1, q1, p2, q2):
    """search.segment_distance in C."""
    p1, q1, p2, q2 = (np.ascontiguousarray(v, dtype=np.float64) for v in (p1, q1, p2, q2))
    if not p1.shape == q1.shape == p2.shape == q2.shape or p1.shape[1:] != (3,):
        raise ValueError(f"segments {p1.shape} {q1.shape} {p2.shape} {q2.shape}: (n, 3) each")
    out = np.empty(len(p1))
    _load()[1](len(p1), p1, q1, p2, q2, out)
    return out
