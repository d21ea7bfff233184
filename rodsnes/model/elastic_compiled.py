"""Compiled elastic element kernel: ElasticRod.element_terms (elastic.py) fused per element in C.

rodsnes/model/_elastic_kernel.c (plain C99, built by setup.py as the extension rodsnes.model._elastic_kernel
and loaded here with ctypes) evaluates, element by element and Gauss point by Gauss point,
the same quantities as the batched numpy kernel:

    energy_e = sum_q wJ_q W(e_q, e0_q),   g_a = (dE/dr_a, B(q_a)^T dE/dq_a),
    H_ab = T_a^T Hraw_ab T_b + delta_ab (-1/4 q_a . dE/dq_a I - [not symmetric] 1/2 g_theta^x),

with Wz = De^T S and Wzz = De^T C De + S.D2e in closed form (no D2e array), including the
curvature bound W_kappa = mu_kappa/2 <kappa - kappa_max>^2.  Equal to the numpy kernel to
round-off (tests/test_elastic_compiled.py).

C entry point:

    int rodsnes_elastic_terms_lanes(int ne, int nn, int nq,
                              const double *N, const double *dN, const double *wJ,
                              const double *C, int limit, double kappa_max, double mu_kappa,
                              const double *qe, const double *xe, const double *e0,
                              int tangent, int symmetric, const int *comps, int ncomp,
                              int lanes, double *energy, double *vec, double *H);
                         (lanes: elements at once, 1, 2 or 4 (AVX2), 0 the most it runs)
    int rodsnes_elastic_energy(int ne, int nn, int nq, ... the same ..., const double *e0,
                               double *energy);          (the energy alone: line searches)
    int rodsnes_elastic_plane_tangent_lanes(int ne, int nn, int nq, ... the same ...,
                                            const double *e0, int axis, int lanes, double *H);
                         (the in-plane tangent of a planar state: planar.PlanarSystem)
    int rodsnes_elastic_strains(int ne, int nn, int nq, const double *N, const double *dN,
                                const double *qe, const double *xe, double *strain);
                         (the strains at the points of N, dN: ElasticRod.strains,
                          strains_at_nodes)
    int rodsnes_elastic_node_residual_lanes(int ne, int nn, int nq, ... the same ...,
                                      const double *qn, const double *xn, const int64_t *conn,
                                      const double *e0, int lanes, double *energy,
                                      double *node_vec);
                         (the residual summed per node, the elements' nodes gathered in C:
                          RodProblem.residual)
    int rodsnes_elastic_node_energy(... the same but node_vec ..., double *energy);
                         (the energy, the elements' nodes gathered in C: the line searches)
    int rodsnes_elastic_tangents_into(int ne, int nn, int nq, ... the same ...,
                                      const double *qn, const double *xn, const int64_t *conn,
                                      const double *e0, int axis, int symmetric,
                                      const int *comps, int ncomp, int lanes,
                                      const int32_t *pos, const signed char *first,
                                      int k, int bs, double *a);
                         (the in-plane (axis >= 0) or 3-D tangents added into a block matrix's
                          values as they are made: RodProblem.jacobian, assembly.py)
"""
import collections
import ctypes

import numpy as np

from rodsnes import compiled

_MAX_NODES = 8          # MAXNN in _elastic_kernel.c


def library_path():
    """Path of the built shared library (the extension module file), or None."""
    return compiled.library_path("rodsnes.model._elastic_kernel")


# the kernel's C entries by name (compiled.Foreign each)
Kernel = collections.namedtuple(
    "Kernel", "terms energy plane_tangent strains node_residual node_energy tangents_into")


def _declare(lib):
    """The C functions of the built library, with their signatures (compiled.Foreign)."""
    c_int, c_dbl, f64 = ctypes.c_int, ctypes.c_double, compiled.F64
    rod = [c_int, c_int, c_int, f64, f64, f64, f64, c_int, c_dbl, c_dbl]     # ne .. mu_kappa
    common = rod + [f64, f64, f64]                          # qe, xe, e0
    nodes = rod + [f64, f64, compiled.I64, f64]             # qn, xn, conn, e0
    fn = compiled.Foreign(lib.rodsnes_elastic_terms_lanes,
                          common + [c_int, c_int, ctypes.c_void_p, c_int, c_int, f64, f64, f64],
                          c_int)
    en = compiled.Foreign(lib.rodsnes_elastic_energy, common + [f64], c_int)
    pl = compiled.Foreign(lib.rodsnes_elastic_plane_tangent_lanes, common + [c_int, c_int, f64],
                          c_int)
    st = compiled.Foreign(lib.rodsnes_elastic_strains,
                          [c_int, c_int, c_int, f64, f64, f64, f64, f64], c_int)
    nr = compiled.Foreign(lib.rodsnes_elastic_node_residual_lanes, nodes + [c_int, f64, f64],
                          c_int)
    ne_ = compiled.Foreign(lib.rodsnes_elastic_node_energy, nodes + [f64], c_int)
    into = compiled.Foreign(lib.rodsnes_elastic_tangents_into,
                            nodes + [c_int, c_int, ctypes.c_void_p, c_int, c_int, compiled.I32,
                                     compiled.I8, c_int, c_int, ctypes.c_void_p], c_int)
    return Kernel(fn, en, pl, st, nr, ne_, into)


# the kernel's ctypes function, or False when the library is not built or does not load.
_load = compiled.loader("rodsnes.model._elastic_kernel", _declare)


def available():
    """True when the compiled kernel is built and loads."""
    return bool(_load())


def _f64(a, shape, name):
    a = np.ascontiguousarray(a, dtype=np.float64)
    if a.shape != shape:
        raise ValueError(f"{name} has shape {a.shape}, expected {shape}")
    return a


def _rod_arguments(rod, e0, ne):
    """The kernel's arguments of the rod (N, dN, wJ, C, limit, kappa_max, mu_kappa), its
    reference strains e0 for ne elements (the rod's by default), and (nn, nq)."""
    if not _load():
        raise RuntimeError("the compiled elastic kernel is not built (run pip install -e .)")
    e0 = rod.e0 if e0 is None else e0
    if e0 is None:
        raise ValueError("no reference strains e0 (ElasticRod.set_reference)")
    nq, nn = rod.N.shape
    if nn > _MAX_NODES:
        raise ValueError(f"order {nn - 1} exceeds the compiled kernel's {_MAX_NODES - 1}")
    e0 = np.ascontiguousarray(np.broadcast_to(np.asarray(e0, dtype=np.float64), (ne, nq, 6)))
    limit = rod.kappa_max is not None
    args = (_f64(rod.N, (nq, nn), "N"), _f64(rod.dN, (nq, nn), "dN"),
            _f64(rod.wJ, (nq,), "wJ"), _f64(rod.C, (6,), "C"), int(limit),
            float(rod.kappa_max) if limit else 0.0, float(rod.mu_kappa))
    return args, e0, (nn, nq)


def _inputs(rod, qe, xe, e0):
    """The kernel's common arguments (after ne, nn, nq) and (ne, nn, nq)."""
    qe = np.asarray(qe)
    ne = qe.shape[0]
    args, e0, (nn, nq) = _rod_arguments(rod, e0, ne)
    qe = _f64(qe, (ne, nn, 4), "qe")
    xe = _f64(xe, (ne, nn, 3), "xe")
    return args + (qe, xe, e0), (ne, nn, nq)


def _lanes_info(info, entry, lanes):
    """The error of a lane entry's return code: ValueError for a width the processor cannot
    run (-2), RuntimeError for any other failure."""
    if info == -2:
        raise ValueError(f"lanes={lanes}: this processor has no AVX2")
    if info != 0:
        raise RuntimeError(f"{entry} failed ({info})")


def element_terms(rod, qe, xe, e0=None, tangent=True, symmetric=False, out=None, comps=None,
                  lanes=0):
    """(energy (ne,), vec (ne, p+1, 6), H (ne, 6(p+1), 6(p+1)) or None) of ElasticRod rod:
    the same as rod.element_terms(qe, xe, e0, tangent, symmetric), computed in C; ``out``:
    (energy, vec, H or None) arrays of those shapes to write into.  ``comps``: the tangent cut
    in C to these components of every node, H (ne, c(p+1), c(p+1)) with c = len(comps), rows
    and columns (node, component) (planar.ComponentView's block, without the 6 x 6 tangents
    written out and gathered).  ``lanes``: elements at once, 1, 2 or 4 (AVX2), 0 the most the
    processor runs (the same numbers bit for bit; ValueError for 4 without AVX2)."""
    args, (ne, nn, nq) = _inputs(rod, qe, xe, e0)
    nc = 6 if comps is None else len(comps)
    cut = None
    if comps is not None:
        cut = np.ascontiguousarray(comps, dtype=np.intc)
        if not 1 <= nc <= 6 or cut.min() < 0 or cut.max() > 5:
            raise ValueError(f"comps {comps}: 1 to 6 components in 0..5")
    if out is not None:
        energy, vec, H = out
        if energy.shape != (ne,) or vec.shape != (ne, nn, 6) or \
                (tangent and (H is None or H.shape != (ne, nc * nn, nc * nn))):
            raise ValueError("out does not match the elements")
        H = H if tangent else None
    else:
        energy = np.empty(ne)
        vec = np.empty((ne, nn, 6))
        H = np.empty((ne, nc * nn, nc * nn)) if tangent else None
    info = _load().terms(ne, nn, nq, *args, int(bool(tangent)), int(bool(symmetric)),
                         None if cut is None else cut.ctypes.data, nc, int(lanes), energy, vec, H)
    _lanes_info(info, "rodsnes_elastic_terms_lanes", lanes)
    return energy, vec, H


def element_energy(rod, qe, xe, e0=None):
    """The energy of every element (ne,) of ElasticRod rod, in C without the strains'
    derivatives: the same as rod.element_terms(...)[0] to round-off."""
    args, (ne, nn, nq) = _inputs(rod, qe, xe, e0)
    energy = np.empty(ne)
    info = _load().energy(ne, nn, nq, *args, energy)
    if info != 0:
        raise RuntimeError(f"rodsnes_elastic_energy failed ({info})")
    return energy


def plane_tangents(rod, qe, xe, axis, e0=None, out=None, lanes=0):
    """The in-plane tangents (ne, 3(p+1), 3(p+1)) of ElasticRod rod at a state in the plane
    normal to e_axis, rows and columns (node, (r_P, r_Q, theta_axis)), P < Q the other axes:
    element_terms(..., comps=(P, Q, 3 + axis)) at such a state (the consistent tangent and the
    Hessian are equal there), made from the six in-plane strain variables instead of the 3-D
    tangent (_elastic_kernel.c, rodsnes_elastic_plane_tangent_lanes; quaternions of any norm, as
    element_terms).  The out-of-plane parts of the state are taken as zero: for planar states
    only (planar.PlanarSystem, whose guard sees the others).  ``out``: an array of that shape
    to write into.  ``lanes``: elements at once, 2 or 4 (AVX2), 0 the most the processor runs
    (the same numbers bit for bit; ValueError for 4 without AVX2)."""
    args, (ne, nn, nq) = _inputs(rod, qe, xe, e0)
    if axis not in (0, 1, 2):
        raise ValueError(f"axis {axis}: 0, 1 or 2")
    if out is None:
        out = np.empty((ne, 3 * nn, 3 * nn))
    elif out.shape != (ne, 3 * nn, 3 * nn) or not out.flags.c_contiguous:
        raise ValueError("out does not match the elements")
    info = _load().plane_tangent(ne, nn, nq, *args, int(axis), int(lanes), out)
    _lanes_info(info, "rodsnes_elastic_plane_tangent_lanes", lanes)
    return out


def strains(N, dN, qe, xe):
    """The material strains e = (v, u) (ne, nq, 6) of the elements' nodal quaternions qe
    (ne, nn, 4) and positions xe (ne, nn, 3) at the points of the shape functions N (nq, nn)
    and their arclength derivatives dN: ElasticRod.strains (the quadrature points) and
    elastic.strains_at_nodes (an element's nodes) in C, equal to their numpy forms to
    round-off."""
    if not _load():
        raise RuntimeError("the compiled elastic kernel is not built (run pip install -e .)")
    N, dN = np.ascontiguousarray(N, dtype=np.float64), np.ascontiguousarray(dN, dtype=np.float64)
    nq, nn = N.shape
    if dN.shape != (nq, nn) or nn > _MAX_NODES:
        raise ValueError(f"shape functions {N.shape}, {dN.shape}: (points, at most "
                         f"{_MAX_NODES} nodes) both")
    qe = np.asarray(qe)
    ne = qe.shape[0]
    out = np.empty((ne, nq, 6))
    info = _load().strains(ne, nn, nq, N, dN, _f64(qe, (ne, nn, 4), "qe"),
                           _f64(xe, (ne, nn, 3), "xe"), out)
    if info != 0:
        raise RuntimeError(f"rodsnes_elastic_strains failed ({info})")
    return out


def _node_inputs(rod, qn, xn, conn, e0):
    """The rod's arguments, e0, conn, qn, xn checked (the node arrays hold the elements'
    nodes) and (ne, nn, nq), for the node-gathering passes."""
    conn = np.ascontiguousarray(conn, dtype=np.int64)
    ne = len(conn)
    args, e0, (nn, nq) = _rod_arguments(rod, e0, ne)
    if conn.shape != (ne, nn):
        raise ValueError(f"conn {conn.shape}: (elements, {nn}) expected")
    qn = np.ascontiguousarray(qn, dtype=np.float64)
    xn = np.ascontiguousarray(xn, dtype=np.float64)
    n = len(qn)
    if qn.shape != (n, 4) or xn.shape != (n, 3) or (ne and (conn.min() < 0 or conn.max() >= n)):
        raise ValueError(f"nodes {qn.shape} {xn.shape} do not hold the elements' {conn.shape}")
    return args, e0, conn, qn, xn, (ne, nn, nq)


def node_energy(rod, qn, xn, conn, e0=None):
    """The energy of every element (ne,) of ElasticRod rod, its nodes gathered in C from the
    node arrays qn, xn by conn (node_residual's): element_energy(qn[conn], xn[conn]) without
    the gathered arrays (the line searches' trials)."""
    args, e0, conn, qn, xn, (ne, nn, nq) = _node_inputs(rod, qn, xn, conn, e0)
    energy = np.empty(ne)
    info = _load().node_energy(ne, nn, nq, *args, qn, xn, conn, e0, energy)
    if info != 0:
        raise RuntimeError(f"rodsnes_elastic_node_energy failed ({info})")
    return energy


def node_residual(rod, qn, xn, conn, e0=None, lanes=0):
    """(energy (ne,), the residual summed per node (nodes, 6)) of ElasticRod rod at the nodes'
    quaternions qn (nodes, 4) and positions xn (nodes, 3), its elements' nodes conn (ne, nn)
    (rows of them): element_terms(qn[conn], xn[conn], tangent=False) with its element rows
    summed per node in the elements' order, without the gathered element arrays and the
    sparse row sum (0.7 ms of a 4.5 ms residual at 10^4 cubic elements).  ``lanes``: elements
    at once, as element_terms (the same numbers bit for bit)."""
    args, e0, conn, qn, xn, (ne, nn, nq) = _node_inputs(rod, qn, xn, conn, e0)
    n = len(qn)
    energy, node_vec = np.empty(ne), np.zeros((n, 6))
    info = _load().node_residual(ne, nn, nq, *args, qn, xn, conn, e0, int(lanes), energy,
                                 node_vec)
    _lanes_info(info, "rodsnes_elastic_node_residual_lanes", lanes)
    return energy, node_vec


def tangents_into(rod, qn, xn, conn, e0, pos, values, k, bs, axis=-1, comps=None,
                  symmetric=False, lanes=0, first=None):
    """The tangents of ElasticRod rod's elements conn (ne, nn) (rows of the node arrays qn, xn)
    added into a block matrix's value array (``values``: its address) at the blocks' places
    ``pos`` (ne, k, k) int32 (assembly.ElementBlocks; -1: not added), k blocks of bs unknowns
    an element: plane_tangents of the plane normal to e_axis (``axis`` >= 0) or
    element_terms(..., tangent=True, symmetric, comps)'s tangents, the same numbers, added as
    they are made (no tangents written out and read back).  ``first`` (ne, k, k) int8 or None:
    where 1 the block is stored, not added (assembly.ElementBlocks.first: the matrix not
    zeroed there)."""
    args, e0, conn, qn, xn, (ne, nn, nq) = _node_inputs(rod, qn, xn, conn, e0)
    nc = 3 if axis >= 0 else 6 if comps is None else len(comps)
    cut = None if comps is None or axis >= 0 else np.ascontiguousarray(comps, dtype=np.intc)
    if axis > 2 or (cut is not None and (not 1 <= nc <= 6 or cut.min() < 0 or cut.max() > 5)):
        raise ValueError(f"axis {axis}, comps {comps}: an axis 0..2 (or -1), 1 to 6 components "
                         "in 0..5")
    pos = np.ascontiguousarray(pos, dtype=np.int32)
    if first is not None:
        first = np.ascontiguousarray(first, dtype=np.int8)
    if pos.shape != (ne, k, k) or nc * nn != k * bs or \
            (first is not None and first.shape != pos.shape):
        raise ValueError(f"places {pos.shape} for {ne} elements of {nn} nodes, {nc} unknowns "
                         f"a node: ({ne}, {k}, {k}) with k {k} x bs {bs} = {nc * nn} expected")
    info = _load().tangents_into(ne, nn, nq, *args, qn, xn, conn, e0, int(axis),
                                 int(bool(symmetric)), None if cut is None else cut.ctypes.data,
                                 nc, int(lanes), pos, first, int(k), int(bs), values)
    _lanes_info(info, "rodsnes_elastic_tangents_into", lanes)
