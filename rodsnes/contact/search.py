"""Candidate search of self-contact: which element pairs can touch (numpy and scipy, the bounds
and the segment distances in C where search_compiled's kernel is built; no MPI).

A contact at distance below 2 eps needs two centreline points within ``reach`` (2 eps plus a
margin).  Each element is enclosed in a proven bound, and only the pairs whose bounds come
within reach are handed to a contact law (docs/contact.md, section 5):

- bounding spheres (``element_bounds``).  For a Lagrange curve r(xi) the sampled points
  r(xi_j) (spacing Dxi) lie in a ball B(c, R_s); linear interpolation between samples stays in
  it (convexity), and |r - linear interpolant| <= Dxi^2/8 max|r''| with
  |r''(xi)| = |sum_a N_a''(xi) (x_a - c)| <= Lambda2_p max_a |x_a - c|, Lambda2_p = max sum_a
  |N_a''|.  So R = R_s + (Dxi^2 / 8) Lambda2_p max_a |x_a - c| is a proven bound (we add 5 %
  to Lambda2_p).  Two spheres within reach: ``spheres_within``.
- capsules (``element_capsules``): the chord between the end nodes, widened by a proven bound
  of the curve's deviation from it; tighter for slender, gently bent elements.  Two capsules
  within reach: ``capsules_within`` (``segment_distance`` between the chords).
- ``candidate_pairs``: the pairs (own element, any element) whose spheres come within reach and
  whose arclength distance can reach the exclusion delta (``max_arclength_distance``), by a
  cKDTree over the centres, O(N log N).  The parallel term (contact/term.py) keeps them as a
  Verlet list.
- per slave element, its candidates grouped into strands (``strand_index``), and the couples of
  its candidate masters that a switch point of the closest-point law can couple
  (``co_master_pairs``).

Elements are numbered along the rod; ``element_node_ids`` gives their nodes, ``positions`` the
rows of element ids in an array of ids.
"""
import numpy as np
from scipy.spatial import cKDTree

from rodsnes.contact import search_compiled
from rodsnes.model import fe

__all__ = ["element_bounds", "element_capsules", "segment_distance", "spheres_within",
           "capsules_within", "candidate_pairs", "max_arclength_distance", "element_node_ids",
           "strand_index", "co_master_pairs", "positions", "same_bits"]

_NSAMP_BOUNDS = 65
_LAMBDA2 = {}
_NS_BOUNDS = {}
_BOUNDS_BATCH = 2048     # elements per batch of element_bounds
_CHORD = {}              # _chord_deviation_matrix by order


def _lambda2(order):
    """max_xi sum_a |N_a''(xi)| (dense sampling of a piecewise polynomial of degree p-2)."""
    if order not in _LAMBDA2:
        xi = np.linspace(-1.0, 1.0, 4001)
        _, _, d2N = fe.lagrange(order, xi)
        _LAMBDA2[order] = float(np.abs(d2N).sum(axis=1).max())
    return _LAMBDA2[order]


def element_bounds(x_elem):
    """Bounding spheres of interpolated Lagrange elements.

    x_elem (ne, p+1, 3) -> centers (ne, 3), radii (ne,) with |x_e(xi) - c_e| <= R_e for all xi in
    [-1, 1] (proof in the module docstring: sample bound + Dxi^2/8 * Lambda2_p * max_a |x_a - c|,
    covering the overshoot of p >= 2 curves beyond their nodes).  O(ne): per batch of
    _BOUNDS_BATCH elements one matrix product (3 batch, p+1) x (p+1, samples) and reductions
    along the samples (batches keep the samples in cache).
    """
    x = np.asarray(x_elem, dtype=float)
    ne, n1, _ = x.shape
    p = n1 - 1
    if p not in _NS_BOUNDS:
        Ns = fe.lagrange(p, np.linspace(-1.0, 1.0, _NSAMP_BOUNDS))[0]
        _NS_BOUNDS[p] = np.ascontiguousarray(Ns.T)                  # (p+1, samples)
    dxi = 2.0 / (_NSAMP_BOUNDS - 1)
    padc = (dxi ** 2 / 8.0) * 1.05 * _lambda2(p) if p >= 2 else 0.0
    if search_compiled.available():
        return search_compiled.element_bounds(x, _NS_BOUNDS[p], padc)
    return _element_bounds_numpy(x, padc)


def _element_bounds_numpy(x, padc):
    """element_bounds in numpy (the compiled kernel's reference)."""
    ne, n1, _ = x.shape
    p = n1 - 1
    c, rs = np.zeros((ne, 3)), np.zeros(ne)
    xt = np.ascontiguousarray(x.transpose(0, 2, 1))                 # (ne, 3, p+1)
    for b in range(0, ne, _BOUNDS_BATCH):
        xb = xt[b:b + _BOUNDS_BATCH]
        pts = (xb.reshape(-1, n1) @ _NS_BOUNDS[p]).reshape(len(xb), 3, -1)
        cb = 0.5 * (pts.min(axis=2) + pts.max(axis=2))
        pts -= cb[:, :, None]
        c[b:b + _BOUNDS_BATCH] = cb
        rs[b:b + _BOUNDS_BATCH] = np.sqrt(np.einsum("edm,edm->em", pts, pts).max(axis=1))
    dx = x - c[:, None, :]
    spread = np.sqrt(np.einsum("ead,ead->ea", dx, dx).max(axis=1, initial=0.0))
    R = rs + padc * spread + 1e-12 * (spread + np.abs(c).max(axis=1, initial=0.0))
    return c, R


def _chord_deviation_matrix(order):
    """Q (p+1, p+1): the Bernstein coefficients of x(xi) - l(xi), l the chord from the first
    to the last node, are Q x (x the nodal values)."""
    if order not in _CHORD:
        from math import comb
        t = (fe.reference_nodes(order) + 1.0) / 2.0
        V = np.array([[comb(order, k) * tt ** k * (1.0 - tt) ** (order - k)
                       for k in range(order + 1)] for tt in t])
        lam = np.arange(order + 1) / order
        chord = np.zeros((order + 1, order + 1))
        chord[:, 0], chord[:, -1] = 1.0 - lam, lam
        _CHORD[order] = np.linalg.inv(V) - chord
    return _CHORD[order]


def element_capsules(x_elem):
    """Capsules around interpolated Lagrange elements: x_elem (ne, p+1, 3) -> chord ends a, b
    (ne, 3) (the first and last node) and radius rho (ne,) with

        dist(x_e(xi), [a_e, b_e]) <= |x_e(xi) - l_e(xi)| <= rho_e,   l_e the chord at xi,

    because x_e - l_e is a polynomial of degree p vanishing at both ends whose values lie in the
    convex hull of its Bernstein coefficients Q x (``_chord_deviation_matrix``): rho_e = max_k
    |(Q x_e)_k|.  Tighter than the bounding sphere (``element_bounds``) for a slender, gently
    bent element: rho ~ 4/3 (p >= 3; 2 for p = 2) of its sagitta against R ~ h/2."""
    x = np.asarray(x_elem, dtype=float)
    ne, n1, _ = x.shape
    if ne == 0 or n1 < 3:
        return x[:, 0], x[:, -1], np.zeros(ne)
    dev = np.einsum("ka,ead->ekd", _chord_deviation_matrix(n1 - 1), x)   # (ne, p+1, 3)
    return x[:, 0], x[:, -1], np.sqrt(np.einsum("ekd,ekd->ek", dev, dev).max(axis=1))


def segment_distance(p1, q1, p2, q2):
    """Distance between the segments [p1, q1] and [p2, q2] row by row (the closest points by
    the clamped solution of the two lines' normal equations, Ericson, Real-Time Collision
    Detection 5.1.9; parallel segments through s = 0).  Segments of zero length are points.
    In C where the search kernel is built (the same operations, equal to round-off)."""
    if search_compiled.available():
        return search_compiled.segment_distance(p1, q1, p2, q2)
    return _segment_distance_numpy(p1, q1, p2, q2)


def _segment_distance_numpy(p1, q1, p2, q2):
    """segment_distance in numpy (the compiled kernel's reference)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = np.einsum("nd,nd->n", d1, d1)
    e = np.einsum("nd,nd->n", d2, d2)
    b = np.einsum("nd,nd->n", d1, d2)
    c = np.einsum("nd,nd->n", d1, r)
    f = np.einsum("nd,nd->n", d2, r)

    def unit(v):                                   # clamped to [0, 1]
        return np.minimum(np.maximum(v, 0.0), 1.0)

    a_, e_ = np.where(a > 0.0, a, 1.0), np.where(e > 0.0, e, 1.0)
    den = a * e - b * b
    s = np.where(den > 1e-14 * a * e, unit((b * f - c * e) / np.where(den > 0.0, den, 1.0)), 0.0)
    t = (b * s + f) / e_
    s = np.where(t < 0.0, unit(-c / a_), np.where(t > 1.0, unit((b - c) / a_), s))
    s = np.where(a > 0.0, s, 0.0)
    t = np.where(e > 0.0, unit(t), 0.0)
    w = r + d1 * s[:, None] - d2 * t[:, None]
    return np.sqrt(np.einsum("nd,nd->n", w, w))


def capsules_within(caps_a, caps_b, reach):
    """Rows whose two capsules (``element_capsules``: chord ends and radius, row by row) come
    within ``reach``: dist(chord_a, chord_b) <= reach + rho_a + rho_b (with 1e-9 reach for the
    roundoff of the distance).  Every couple of points of the two elements closer than
    ``reach`` passes it."""
    (a1, b1, r1), (a2, b2, r2) = caps_a, caps_b
    return segment_distance(a1, b1, a2, b2) <= reach * (1.0 + 1e-9) + r1 + r2


def element_node_ids(ids, order, nelem, closed):
    """Global node ids (len(ids), p+1) of elements ``ids``: e p + a (mod p nelem if closed)."""
    ids = np.asarray(ids, dtype=np.int64)
    nodes = ids[:, None] * order + np.arange(order + 1)[None, :]
    if closed:
        nodes %= order * nelem
    return nodes


def max_arclength_distance(a, b, L, h, closed):
    """max over s in element a, sigma in element b of the (periodic) arclength distance."""
    a = np.asarray(a, dtype=np.int64)
    b = np.asarray(b, dtype=np.int64)
    if not closed:
        return (np.abs(a - b) + 1) * h
    nelem = int(round(L / h))
    k = (b - a) % nelem
    tlo, thi = (k - 1) * h, (k + 1) * h          # sigma - s ranges over [tlo, thi], -h <= tlo

    def pdist(t):
        t = np.mod(t, L)
        return np.minimum(t, L - t)

    m = np.maximum(pdist(tlo), pdist(thi))
    half = 0.5 * L
    m = np.where((tlo <= half) & (thi >= half), half, m)
    if 2 * h >= L:
        m = np.full_like(m, half, dtype=float)
    return m


def candidate_pairs(own_ids, own_centers, own_radii, all_ids, all_centers, all_radii,
                    reach, L, h, closed, delta):
    """Element pairs (e_own, e_other) that may contain a slave/master couple within ``reach``.

    Kept iff |c_own - c_other| <= reach + R_own + R_other (bounding spheres, ``element_bounds``;
    ``spheres_within``) and some sigma in e_other is admissible for some s in e_own, i.e. the
    maximal (periodic) arclength distance between the two elements is >= delta (so e_other ==
    e_own survives only when the element is longer than the exclusion, h >= delta).  reach
    should be 2 eps + a margin (for a contact at distance < 2 eps the two centrelines are within
    2 eps).  Search: cKDTrees over own_centers and all_centers, every couple of centres within
    reach + max(own_radii) + max(all_radii) as index arrays (sparse_distance_matrix, no Python
    loop), then the exact sphere test: O(N log N + pairs).  Returns int64 (npair, 2) of global
    ids, sorted.
    """
    own_ids = np.asarray(own_ids, dtype=np.int64)
    all_ids = np.asarray(all_ids, dtype=np.int64)
    none = np.zeros((0, 2), dtype=np.int64)
    if len(own_ids) == 0 or len(all_ids) == 0:
        return none
    oc = np.asarray(own_centers, dtype=float).reshape(-1, 3)
    orad = np.asarray(own_radii, dtype=float).ravel()
    ac = np.asarray(all_centers, dtype=float).reshape(-1, 3)
    arad = np.asarray(all_radii, dtype=float).ravel()
    near = cKDTree(oc).sparse_distance_matrix(cKDTree(ac), reach + orad.max() + arad.max(),
                                              output_type="ndarray")
    io, ia = near["i"].astype(np.int64), near["j"].astype(np.int64)
    keep = spheres_within(oc[io], orad[io], ac[ia], arad[ia], reach)
    ea, eb = own_ids[io[keep]], all_ids[ia[keep]]
    keep = max_arclength_distance(ea, eb, L, h, closed) >= delta
    ea, eb = ea[keep], eb[keep]
    if not len(ea):
        return none
    n = int(max(own_ids.max(), all_ids.max())) + 1
    key = np.unique(ea * n + eb)                   # sorted by (e_own, e_other), no repeats
    return np.stack([key // n, key % n], axis=1).astype(np.int64)


def spheres_within(ca, ra, cb, rb, reach):
    """|c_a - c_b| <= reach + R_a + R_b row by row: the bounding spheres (``element_bounds``) of
    two elements come within ``reach``, the test of ``candidate_pairs``.  Every couple of
    points of the two elements closer than ``reach`` passes it."""
    d = ca - cb
    return np.sqrt(np.einsum("nd,nd->n", d, d)) <= reach + ra + rb


def strand_index(pairs, nelem, closed, near=0):
    """Strand of every candidate pair (e_own, e_other) among its slave element's candidates:
    the candidates of one slave element, sorted by element id, fall into runs of consecutive
    elements (cyclically on a closed rod), one run per strand that passes within reach.  The
    slave element's own neighbourhood, elements e_own - near .. e_own + near (near: elements
    spanned by the exclusion delta, plus one), counts as candidates, so the rod's own
    continuation on both sides of the excluded stretch is one run.  Runs are numbered 0, 1, ...
    per slave element in order of element id (on a closed rod a run through the last element
    and element 0 is run 0).  Returns (npair,)."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    n = len(pairs)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    own = np.unique(pairs[:, 0])
    j = np.arange(-near, near + 1)
    virt = own[:, None] + j[None, :]
    keep = np.ones(virt.shape, dtype=bool) if closed else (virt >= 0) & (virt < nelem)
    virt = np.mod(virt, nelem)
    allp = np.concatenate([pairs, np.stack([np.broadcast_to(own[:, None], virt.shape)[keep],
                                            virt[keep]], axis=1)])
    allp, inv = np.unique(allp, axis=0, return_inverse=True)     # sorted by (e_own, e_other)
    e, m = allp[:, 0], allp[:, 1]
    first = np.r_[True, e[1:] != e[:-1]]
    start = first | np.r_[True, (m[1:] - m[:-1]) > 1]
    run = np.cumsum(start) - 1
    slave_of = np.cumsum(first) - 1
    idx = run - run[np.flatnonzero(first)][slave_of]
    if closed:
        # a run that ends at the last element goes on at element 0: it is run 0
        last = np.r_[first[1:], True]
        wraps = last & (m == nelem - 1) & (idx > 0)
        wraps &= (m[np.flatnonzero(first)] == 0)[slave_of]
        idx = np.where(np.isin(run, run[wraps]), 0, idx)
    return idx[np.asarray(inv).ravel()[:n]]


def co_master_pairs(pairs, cen, rad, reach):
    """Pairs (a, b), a < b, of candidate masters of the same slave element whose bounding
    spheres (cen, rad indexed by element id) come within ``reach`` of each other, from
    candidate pairs (npair, 2) = (slave, master): the element pairs a switch point can couple
    (both closest points lie within 2 eps of the slave point).  Vectorised: sum over slaves
    of count^2 rows before the unique."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if not len(pairs):
        return pairs
    p = pairs[np.argsort(pairs[:, 0], kind="stable")]
    _, start, cnt = np.unique(p[:, 0], return_index=True, return_counts=True)
    group = np.repeat(np.arange(len(cnt)), cnt)                   # group of every row
    rep = cnt[group]                                              # partners of every row
    i = np.repeat(np.arange(len(p)), rep)
    j = np.repeat(start[group], rep) + (np.arange(rep.sum()) - np.repeat(np.cumsum(rep) - rep, rep))
    a, b = p[i, 1], p[j, 1]
    keep = a < b
    a, b = a[keep], b[keep]
    near = np.linalg.norm(cen[a] - cen[b], axis=1) - rad[a] - rad[b] <= reach
    return np.unique(np.stack([a[near], b[near]], axis=1), axis=0)


def same_bits(a, b):
    """Whether the float64 arrays a and b hold the same bits (shape and every value, the
    sign of zero too): then a function of a, computed again, gives its value at b."""
    a, b = np.ascontiguousarray(a, dtype=np.float64), np.ascontiguousarray(b, dtype=np.float64)
    return a.shape == b.shape and np.array_equal(a.view(np.int64), b.view(np.int64))


def positions(ids, query, what):
    """Positions of ``query`` in the sorted-or-not unique array ``ids`` (KeyError naming the
    ``what`` elements missing)."""
    sorter = np.argsort(ids, kind="stable")
    pos = np.searchsorted(ids, query, sorter=sorter)
    pos = np.clip(pos, 0, len(ids) - 1)
    idx = sorter[pos]
    if len(query) and not np.all(ids[idx] == query):
        missing = np.unique(query[ids[idx] != query])
        raise KeyError(f"contact pairs reference {what} elements not supplied: {missing[:10]}")
    return idx
