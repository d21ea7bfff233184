"""Compiled pair-potential contact kernel: the couples in contact, energy, residual rows and
tangent blocks of contact_potential.PotentialKernel, element pair by element pair in C.

rodsnes/contact/_potential_kernel.c (plain C99, built by setup.py as the extension
rodsnes.contact._potential_kernel and loaded here with ctypes) goes once over the nqp x (nqp + 2)
point couples of every near element pair, keeps the admissible ones closer than 2 eps (the
same floating-point operations as the numpy path: the same couples), and sums their energy
k W psi(a) and their forces per slave and master point, contracted with the shape functions
into the residual rows; the tangent sums the couples' Hessians (6 entries) per slave point,
per master point and per slave point and master shape function, and contracts them into the
blocks.  The numpy path of PotentialKernel stays the reference: equal to round-off
(tests/test_contact_potential.py).

C entry points (int64 indices, C-contiguous float64 arrays; law = {a_s, a_b, a_w, a_max}: the
onset layer and the wall of PotentialKernel.law, a_w = 0 without the wall, and the depth clip
a_max, +inf but for report_force):

    int64 rodsnes_potential_residual(prune, p0, nn, nqp, nm, n1, xs, xm, oi, mi, e, m, nelem,
        h, delta, L, closed, sq, sm, Np, Nm, wpJ, wm, two_eps, law, k, maxc, cp, cq, cj, cr,
        act, vec, work, state)  -> couples in contact of the chunk from pair p0 (-1: maxc
                                   below one pair's nqp nm); state: the running sums and the
                                   next pair
    int64 rodsnes_potential_tangent(nc, nqp, nm, n1, xs, xm, oi, mi, Np, Nm, wpJ, wm,
        two_eps, law, k, cp, cq, cj, cr, nrow, mat, work)   -> rows (-1: more than nrow)
"""
import ctypes

import numpy as np

from rodsnes import compiled
from rodsnes.contact.scatter import add_in_order, in_order_rows


def library_path():
    """Path of the built shared library (the extension module file), or None."""
    return compiled.library_path("rodsnes.contact._potential_kernel")


def _declare(lib):
    """(residual, tangent): the C functions of the built library with their signatures
    (compiled.Foreign)."""
    f64, i64 = compiled.F64, compiled.I64
    n, x = ctypes.c_int64, ctypes.c_double
    res = compiled.Foreign(lib.rodsnes_potential_residual,
                           [ctypes.c_int, n, n, n, n, n, f64, f64, i64, i64, i64, i64, n, x, x, x,
                            ctypes.c_int,
                            f64, f64, f64, f64, f64, f64, x, f64, x, n, i64, i64, i64, f64, i64,
                            f64, f64, f64], n)
    tan = compiled.Foreign(lib.rodsnes_potential_tangent,
                           [n, n, n, n, f64, f64, i64, i64, f64, f64, f64, f64, x, f64, x,
                            i64, i64, i64, f64, n, f64, f64], n)
    return res, tan


# (residual, tangent), or False when the library is not built or does not load.
_load = compiled.loader("rodsnes.contact._potential_kernel", _declare)


def available():
    """True when the compiled kernel is built and loads."""
    return bool(_load())


def _c(a, dtype=np.float64):
    return np.ascontiguousarray(a, dtype=dtype)


def couples(kern, c, scratch):
    """The couples in contact of the near pairs of ``c`` (PotentialKernel._near_pairs), with
    the energy, the depth and the residual rows, into ``c``: couples (p, q, j, |D|) sorted by
    (pair, q, j), act (the rows' pairs), vec (rows, 2(p+1), 3), energy, depth.  ``scratch``
    (name, shape, dtype) -> array gives the kernel's reusable buffers: the couples are made in
    chunks of at most ``kern.chunk_couples`` point couples' room (_chunked_couples), so the
    memory is that of the couples in contact, not of all the near pairs' nqp (nqp + 2)."""
    oi, mi, e, m = (_c(c[v], np.int64) for v in ("oi", "mi", "e", "m"))
    nn, n1 = len(oi), kern.p + 1
    wm = _c(kern.master_weights(m))
    act = np.empty(nn, dtype=np.int64)
    vec = np.empty((nn, 2 * n1, 3))
    args = (oi, mi, e, m, wm, act, vec)
    cp, cq, cj, cr, state = _chunked_couples(kern, c, args, scratch, prune=1)
    if not len(cp) and state[5]:
        # nothing in contact and points were skipped: the least distance without the skips
        cp, cq, cj, cr, state = _chunked_couples(kern, c, args, scratch, prune=0)
    nrow = int(state[3])
    c.update(couples=(cp, cq, cj, cr), act=act[:nrow], vec=vec[:nrow],
             energy=kern.k * (state[0] + state[1]), wm_table=wm,
             depth=2.0 * kern.eps - float(np.sqrt(state[2])) if nn else -np.inf)
    return c


def rows_within(kern, c, scratch, reach):
    """The near pairs of ``c`` (indices, sorted) with an admissible couple of W > 0 closer than
    ``reach``: the rows of the pass with 2 eps replaced by reach (PotentialKernel.pairs_within;
    no energy: k = 0)."""
    oi, mi, e, m = (_c(c[v], np.int64) for v in ("oi", "mi", "e", "m"))
    nn, n1 = len(oi), kern.p + 1
    act = np.empty(nn, dtype=np.int64)
    vec = np.empty((nn, 2 * n1, 3))
    args = (oi, mi, e, m, _c(kern.master_weights(m)), act, vec)
    state = _chunked_couples(kern, c, args, scratch, prune=1, two_eps=reach, k=0.0)[4]
    return act[:int(state[3])].copy()


def report_force(kern, c, xq, clip, scratch):
    """The line force density at the report points xq (own elements, nqc, 3) of
    PotentialKernel._report_force: the residual's pass with the report points as the slave
    points (their own arclengths for the exclusion, unit weights, the identity as their shape
    functions, none for the masters: each row's slave part is then minus the force of its
    pair at each report point) and the depth at most ``clip``; the rows summed per own
    element in their order (scatter.py).  (no, nqc, 3)."""
    no, nqc = xq.shape[0], xq.shape[1]
    oi, mi, e, m = (_c(c[v], np.int64) for v in ("oi", "mi", "e", "m"))
    nn, nm = len(oi), kern.nqp + 2
    f = np.zeros((no, nqc * 3))
    if not nn:
        return f.reshape(no, nqc, 3)
    act = np.empty(nn, dtype=np.int64)
    vec = np.empty((nn, 2 * nqc, 3))
    points = {"xs": xq, "nqp": nqc, "n1": nqc, "sq": _c((kern.xq + 1.0) * 0.5 * kern.h),
              "Np": np.eye(nqc), "Nm": np.zeros((nm, nqc)), "wpJ": np.ones(nqc)}
    law = kern.law.copy()
    law[3] = clip
    wm = c["wm_table"] if "wm_table" in c else _c(kern.master_weights(m))
    state = _chunked_couples(kern, c, (oi, mi, e, m, wm, act, vec), scratch, prune=1,
                             points=points, law=law)[4]
    nrow = int(state[3])
    if nrow:
        add_in_order(f, in_order_rows(oi[act[:nrow]]), -vec[:nrow, :nqc].reshape(nrow, -1))
    return f.reshape(no, nqc, 3)


def _chunked_couples(kern, c, args, scratch, prune, two_eps=None, k=None, points=None, law=None):
    """One pass of rodsnes_potential_residual over the near pairs, chunk by chunk: each call
    fills the couple buffers (room for max(chunk_couples, nqp (nqp + 2)) couples) from the
    pair where the last stopped, with the running energy, least distance and rows carried in
    ``state``; the chunks' couples are concatenated.  ``two_eps`` and ``k`` replace the
    kernel's 2 eps and k (``rows_within``).  Returns (p, q, j, |D|, state)."""
    res, _ = _load()
    two_eps = 2.0 * kern.eps if two_eps is None else float(two_eps)
    k = kern.k if k is None else float(k)
    law = kern.law if law is None else law
    oi, mi, e, m, wm, act, vec = args
    pts = points or {"xs": c["xs"], "nqp": kern.nqp, "n1": kern.p + 1, "sq": kern._sq,
                     "Np": kern._Npc, "Nm": kern._Nmc, "wpJ": kern._wpJ}
    xs, xm = _c(pts["xs"]), _c(c["xm"])
    nn, nqp, nm, n1 = len(oi), pts["nqp"], kern.nqp + 2, pts["n1"]
    maxc = max(int(kern.chunk_couples), nqp * nm)
    maxc = min(maxc, max(nn * nqp * nm, nqp * nm))
    cp, cq, cj = (scratch(v, (maxc,), np.int64) for v in ("cp", "cq", "cj"))
    cr = scratch("cr", (maxc,), np.float64)
    work = np.empty((nqp + nm) * 3)
    state = np.array([0.0, 0.0, np.inf, 0.0, 0.0, 0.0])
    parts = []
    p0 = 0
    while True:
        nc = res(prune, p0, nn, nqp, nm, n1, xs, xm, oi, mi, e, m, kern.nelem, kern.h,
                 kern.delta, kern.L, int(bool(kern.closed)), pts["sq"], kern._sm, pts["Np"],
                 pts["Nm"], pts["wpJ"], wm, two_eps, law, k, maxc, cp, cq, cj,
                 cr, act, vec, work, state)
        if nc < 0:
            raise RuntimeError("rodsnes_potential_residual: couple buffers below one pair")
        if nc:
            parts.append((cp[:nc].copy(), cq[:nc].copy(), cj[:nc].copy(), cr[:nc].copy()))
        p1 = int(state[4])
        if p1 >= nn:
            break
        if p1 <= p0 and not nc:
            raise RuntimeError("rodsnes_potential_residual: no progress")
        p0 = p1
    if len(parts) == 1:
        return (*parts[0], state)
    if not parts:
        z = np.zeros(0, dtype=np.int64)
        return z, z.copy(), z.copy(), np.zeros(0), state
    return (*(np.concatenate(v) for v in zip(*parts)), state)


def tangent(kern, c):
    """(rows, 6(p+1), 6(p+1)): the tangent blocks of the rows of ``couples``."""
    _, tan = _load()
    nqp, nm, n1 = kern.nqp, kern.nqp + 2, kern.p + 1
    nrow = len(c["act"])
    mat = np.empty((nrow, 6 * n1, 6 * n1))
    work = np.empty((nqp + nm + nqp * n1) * 6)
    p, q, j, r = c["couples"]
    got = tan(len(p), nqp, nm, n1, _c(c["xs"]), _c(c["xm"]), _c(c["oi"], np.int64),
              _c(c["mi"], np.int64), kern._Npc, kern._Nmc, kern._wpJ, c["wm_table"],
              2.0 * kern.eps, kern.law, kern.k, p, q, j, r, nrow, mat, work)
    if got != nrow:
        raise RuntimeError(f"rodsnes_potential_tangent: {got} rows, expected {nrow}")
    return mat
