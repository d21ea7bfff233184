"""Frictionless self-contact of a rod: penalty term on the centreline (pure numpy; no MPI, no PETSc).

Model (Moakher, Chamekh & Mani-Aouadi, "Mathematical and numerical treatments of elastic rods with
frictionless self contact", slides "Gap function", "Closest point", "Penalized energy"):

    d(s)  = 2 eps - min_{sigma in I(s)} |r(s) - r(sigma)|                       (gap, > 0 = penetration)
    I(s)  = { sigma in [0, L] : dist(s, sigma) >= delta }                        (exclusion set)
            dist = |s - sigma| (open rod),  min(|s - sigma|, L - |s - sigma|) (closed rod)
    E_c   = (mu/2) int_0^L <d(s)>^2 ds,     <x> = max(x, 0)                      (penalty energy)
    f_c   = mu <d(s)> nu(s),  nu = (r(s) - r(sbar)) / |r(s) - r(sbar)|           (slave line force)

Discretisation.  Lagrange elements of order p (rodsnes.fe): element e spans s in [e h, (e+1) h],
h = L / nelem, s = e h + (xi + 1) h / 2, with nodes x_e (p+1, 3).  The slave points are the nqc
Gauss points (xi_q, w_q) of the caller's own elements, so

    E_c ~= sum_{own e} sum_q  w_q J (mu/2) <d(s_eq)>^2,        J = h / 2.

The master point sbar is found by a closest-point projection onto the interpolated centreline of
every candidate element m (from ``candidate_pairs``), restricted to the admissible part of m,
I(s) cap [m h, (m+1) h], which is a union of at most two intervals ("slots").  On each slot we
minimise phi(xi) = |x_m(xi) - r(s)|^2 / 2 by a safeguarded Newton iteration (started from every
discrete local minimum of 4p+1 equispaced samples; steps limited to one sample spacing; clamped to
the slot; backtracking on phi), vectorised over all (slave point, candidate, slot, start).  Where
phi may be non-convex on the slot (a Bernstein lower bound of phi'' is not positive), a minimum
can hide between two samples next to a maximum; there every real root of the polynomial phi'
(companion eigenvalues) is a candidate as well (``_stationary_min``).  The
global minimum over candidates is kept; a closest point shared by two elements (a node) is thus
counted once.  Before projecting many slots (more than ``PRUNE``), they are pruned exactly: a slot
whose element's bounding sphere is farther from the slave point than an admissible slot end of
another candidate cannot hold the minimum.  Cost: O(#pairs * nqc) vectorised work, no Python loop
over elements or points.  The samples of all slots are one matrix product (in the slot
coordinate t, xi = lo + (hi - lo) t, the monomials of the sample fractions are fixed:
``_taylor``), and the Newton iterations of all starts run together (``_newton``).  An evaluation is a sequence of such searches (report points,
zone samples, the steps of the root findings and bisections below); since each costs about the
same whatever its number of points, every search serves as many points as it can: all strands
at once (``evaluate``), the roots at both ends of the zones in one Illinois solve, several
levels of every bisection of a cut per search (``_bisect_kind``).

Bounding spheres (``element_bounds``).  For a Lagrange curve r(xi) the sampled points r(xi_j)
(spacing Dxi) lie in a ball B(c, R_s); linear interpolation between samples stays in it
(convexity), and |r - linear interpolant| <= Dxi^2/8 max|r''| with
|r''(xi)| = |sum_a N_a''(xi) (x_a - c)| <= Lambda2_p max_a |x_a - c|, Lambda2_p = max sum_a |N_a''|.
So R = R_s + (Dxi^2 / 8) Lambda2_p max_a |x_a - c| is a proven bound (we add 5 % to Lambda2_p).

Formulas used (per slave Gauss point in contact, d > 0; "x" = the 2(p+1) nodal positions of
[slave element, master element], node-major index 3a+i):

    D = r(s) - r(sbar) = sum_a N_a(xi_q) x_{e,a} - sum_b N_b(xibar) x_{m,b},  g = |D|, nu = D/g
    Ntil = [ N_a(xi_q) (a = 0..p),  -N_b(xibar) (b = 0..p) ]       (so D = sum_A Ntil_A x_A)
    d = 2 eps - g

  residual (first variation; slide "The first variation of dJ_c": the closest-point motion drops
  out because r'(sbar) . nu = 0, or because sbar is fixed on a bound):

    dE/dx_A = - w J mu d  Ntil_A nu

  tangent (second variation).  With phi(x, xi) = |D|^2/2, Phi(x) = phi(x, xibar(x)),
  g = sqrt(2 Phi) and, for an interior closest point (phi_xi = 0, implicit function theorem
  dxibar/dx = -phi_xixi^-1 phi_xxi):

    Phi_xx = phi_xx - phi_xxi phi_xxi^T / phi_xixi,    g_xx = Phi_xx / g - g_x g_x^T / g

    d2E/dx_A,i dx_B,j = w J mu [ Ntil_A Ntil_B ( (2 eps / g) nu_i nu_j - (d / g) delta_ij )
                                 + (d / (g k)) c_{A,i} c_{B,j} ]          (last term: interior only)

    k = phi_xixi = |t|^2 - D . r2        t = d r / d xi (xibar),  r2 = d^2 r / d xi^2 (xibar)
    c = phi_xxi:  c_{e,a} = -N_a(xi_q) t,   c_{m,b} = N_b(xibar) t - N_b'(xibar) D

  This is the slide's Q_c / (2 eps - d) with k = |r'(sbar)|^2 - r''(sbar).(r(s) - r(sbar)): the
  slide's denominator |r'|^2 + r''.(r(s) - r(sbar)) has the wrong sign of the curvature term
  (verified by finite differences in tests/test_contact_math.py).  The ratio c c^T / k is the same in
  xi or in arclength units.  If the closest point sits on a bound of its slot (element end, rod end,
  exclusion boundary) xibar is fixed and the last term is absent (point-to-point distance).  If
  k <= 0 (degenerate projection: the slave point at a centre of curvature of the master curve) the
  last term is also dropped.  Since E_c uses <d>^2, energy and residual are C^1 / C^0 across d = 0.
  E_c is not C^2 where the closest point jumps between candidates or where a slave point crosses
  the exclusion boundary; a closest point that lands exactly on a node where the curve is smooth
  (C^1) is treated as a bound (measure-zero set; the interior formula applies a hair away).

Segments (contact zones, ``segments=True``, the default of -contact).  Instead of the nqc fixed
Gauss points, E_c is integrated over the zones {s : d(s) > 0} of every slave element: found by
sampling (nseg points), refining the maxima of d (root of d') and the roots of d, then split
wherever the kind of closest point changes (``_kind``: a master node, the interior of a master
element, a bound), because there d(s) has a kink (node crossed or stuck to, bound reached) or
the closest point jumps to another strand.  Each piece gets nqz Gauss points.  Kinds name master
nodes, not element ends, so the tie between the two elements sharing a node is no change; cuts
are found by bisection to 1e-13 in xi, from both sides of a change, and move continuously with
the configuration: the residual is a continuous function of the nodes (tested on a rod with C0
kinks at every node).  The residual and tangent keep the pointwise formulas above: the
integrand vanishes at zone ends, and is continuous across a cut at a node.

Switch points.  Where the closest point jumps from (A, xi_A) to (B, xi_B) at a cut c (to another
strand, or across a node seen from its concave side), g_A(c) = g_B(c), so energy and residual
stay continuous, but the integrand of the residual differs on the two sides and c moves with
the nodes: d/dx int r = ... + J (r_A(c) - r_B(c)) dc/dx, with r = -mu d g_x per unit xi and
dc/dx = -phi_x / phi_xi, phi = g_A - g_B (``_switch_terms``):

    K_sw = J mu d phi_x phi_x^T / phi_xi  over the nodes [slave, A, B],
    phi_xi = (nu_A - nu_B) . dr/dxi (c) > 0,
    phi_x  = [ N(c) (nu_A - nu_B),  -N_A(xi_A) nu_A,  N_B(xi_B) nu_B ].

The two closest points come from the ends of the bisection bracket of the cut (1e-13 apart);
a cut whose two closest points coincide (a node crossed or stuck to) adds nothing.  Not
covered: a jump between two minima of one element (no change of kind, so no cut), and the
derivative of the zone quadrature's own error as its cuts move (large where a closest point
races near a centre of curvature of the master).

Sign conventions of the outputs: ``vec`` is dE_c/dx (the residual, i.e. minus the contact force on
the nodes); the caller adds both the slave and the master block (node ids may repeat when the two
elements share a node or coincide).
"""
import numpy as np
from scipy.spatial import cKDTree

from rodsnes.profiling import logged
from rodsnes.model import fe

__all__ = ["default_exclusion", "default_penalty", "element_bounds", "candidate_pairs",
           "spheres_within", "element_capsules", "segment_distance", "capsules_within",
           "element_node_ids", "max_arclength_distance", "co_master_pairs", "strand_index",
           "ContactKernel"]


# --------------------------------------------------------------------------------------------
# parameters
# --------------------------------------------------------------------------------------------
def default_exclusion(eps):
    """delta = pi eps (slide "Gap function": I(s) excludes |sigma - s| < delta).

    A rod of radius eps cannot be bent to a centreline radius R < eps (its inner surface would fold).
    On a circle of radius R >= eps, points at arclength distance t in [delta, pi R] have chord
    2 R sin(t / 2R) >= 2 R sin(pi eps / 2R) >= 2 eps (R sin(a/R) increases with R because
    tan x >= x), with equality only at R = eps.  So no admissibly bent rod gets a false contact
    with its own neighbourhood, while delta is as small as possible so that genuine contacts at
    arclength distance >= pi eps (e.g. a tight loop) are still seen.
    """
    return np.pi * float(eps)


def default_penalty(EI, eps, penetration=0.01):
    """mu = EI / (20 * penetration * eps^4) = 5 EI / eps^4 for 1 % penetration of the diameter 2 eps
    (penetration = -contact_penetration; -contact_penalty_adapt raises mu where the loads press
    harder than this estimate, solver.NewtonSolver.keep_penetration).

    Line force of a tight contact: m' + r' x n = 0 gives |n_perp| ~ |m'| and the line force
    balances the shear-force gradient, f = |n'| ~ |m''| = EI |kappa''|; in a tight contact
    (plectoneme strands, a loop pulled tight, a rod wrapped on itself) the curvature changes by
    O(1/eps) over an arclength O(eps), so f = c EI / eps^3.  The constant is measured, on the
    tightest contact of the cases, the plectoneme (cases/plectoneme.opts, two strands wound round
    each other, 3.6 turns): its peak line force between the strands is 0.2 - 0.4 EI/eps^3, so
    c = 0.2 (an earlier c = 1 gave 0.2 - 0.4 % penetration there and Newton 2.5x the
    iterations per load step: the penalty stiffness steepens the walls of the soft valleys in
    which the plectoneme moves).
    Penalty law: the slave point s carries f_c = mu <d>, and, E_c being an integral over all of
    [0, L], the strand it touches is itself slave of s's strand with the same penetration; so each
    strand of a two-sided contact receives a line force 2 mu d (checked in the tests on two
    parallel segments).  Asking c EI/eps^3 = 2 mu d with d = penetration * 2 eps gives
    mu = c EI / (4 penetration eps^4).  Measured with this default on the plectoneme: the deepest
    penetration is about 1 % of the diameter (README, Plectoneme).  An order-of-magnitude rule:
    long, gently loaded contacts (f << EI/eps^3) penetrate less, very tight knots more;
    -contact_penalty sets mu directly (the penetration falls as 1/mu in a line contact).
    """
    return 0.2 * float(EI) / (4.0 * float(penetration) * float(eps) ** 4)


# --------------------------------------------------------------------------------------------
# geometry helpers
# --------------------------------------------------------------------------------------------
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
    dxi = 2.0 / (_NSAMP_BOUNDS - 1)
    pad = (dxi ** 2 / 8.0) * 1.05 * _lambda2(p) * spread if p >= 2 else 0.0
    R = rs + pad + 1e-12 * (spread + np.abs(c).max(axis=1, initial=0.0))
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
    Detection 5.1.9; parallel segments through s = 0).  Segments of zero length are points."""
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


def _nearest_per_point(idx, f, pt):
    """Of the candidates idx (indices into f and pt), the one with the smallest f for each point
    pt (ties: the first in order); one index per point that has a candidate."""
    order = idx[np.lexsort((f[idx], pt[idx]))]
    first = np.ones(len(order), dtype=bool)
    first[1:] = pt[order][1:] != pt[order][:-1]
    return order[first]


def _split_record(cl, n):
    """The closest-point records (``ContactKernel._closest``) of the first n points of cl and
    of the rest."""
    return {k: v[:n] for k, v in cl.items()}, {k: v[n:] for k, v in cl.items()}


def _illinois_update(act, a, b, fa, fb, side, A_, B_, FA, FB, c, fc):
    """One Illinois (modified regula falsi) update, in place on the entries act of the
    brackets [a, b] with values fa, fb: the end whose value has the sign of f(c) moves to c;
    the other end's value is halved when the same end moved the time before (side)."""
    left = np.sign(fc) == np.sign(FA)
    a[act] = np.where(left, c, A_)
    fa[act] = np.where(left, fc, FA)
    b[act] = np.where(left, B_, c)
    fb[act] = np.where(left, FB, fc)
    s_new = np.where(left, 1, -1)
    stay = side[act] == s_new
    fb[act] = np.where(stay & left & np.isfinite(fb[act]), 0.5 * fb[act], fb[act])
    fa[act] = np.where(stay & ~left & np.isfinite(fa[act]), 0.5 * fa[act], fa[act])
    side[act] = s_new


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


def _monomial_matrix(order):
    """C (p+1, p+1) with N_a(xi) = sum_k C[k, a] xi^k."""
    nodes = fe.reference_nodes(order)
    V = nodes[:, None] ** np.arange(order + 1)[None, :]
    return np.linalg.inv(V)


def _monomials(order, xi):
    """xi^k, d/dxi xi^k, d2/dxi2 xi^k for k = 0..p: three (len(xi), p+1) arrays."""
    W = _powers(order, np.asarray(xi, dtype=float), 2)
    return W[:, 0], W[:, 1], W[:, 2]


_POWER_TABLES = {}


def _power_tables(order):
    """Exponents E[j, k] = max(k - j, 0) and factors F[j, k] = k! / (k - j)! (0 for k < j) of
    d^j/dxi^j xi^k = F[j, k] xi^E[j, k], j = 0, 1, 2, k = 0..p."""
    if order not in _POWER_TABLES:
        k = np.arange(order + 1)
        E = np.stack([k, np.maximum(k - 1, 0), np.maximum(k - 2, 0)])
        F = np.stack([np.ones(order + 1), k, k * (k - 1)]).astype(float)
        _POWER_TABLES[order] = E, F
    return _POWER_TABLES[order]


def _powers(order, x, nder):
    """d^j/dxi^j xi^k for k = 0..p, j = 0..nder (nder <= 2) at the points x (any shape):
    (x.shape, nder + 1, p + 1); xi^k by repeated products (a cumulative product)."""
    pw = np.empty(x.shape + (order + 1,))
    pw[..., 0] = 1.0
    if order:
        pw[..., 1:] = x[..., None]
        np.cumprod(pw, axis=-1, out=pw)
    if nder == 0:
        return pw[..., None, :]
    E, F = _power_tables(order)
    return F[:nder + 1] * pw[..., E[:nder + 1]]


# --------------------------------------------------------------------------------------------
# the kernel
# --------------------------------------------------------------------------------------------
class ContactKernel:
    """Penalty self-contact term evaluated over a set of own (slave) elements."""

    MAXIT = 60          # Newton iterations of the projection
    MAXBT = 40          # backtracking halvings
    CHUNK = 16384       # projection problems per vectorised batch
    PRUNE = 96          # slots beyond which _closest prunes them before projecting
    BISECT_POINTS = 32  # slave points per _closest call of _bisect_kind (its tree levels)

    def __init__(self, order, nqc, eps, mu, delta, L, nelem, closed, segments=False):
        self.p = int(order)
        self.nqc = int(nqc)
        self.eps = float(eps)
        self.mu = float(mu)
        self.delta = float(delta)
        self.L = float(L)
        self.nelem = int(nelem)
        self.closed = bool(closed)
        self.h = self.L / self.nelem
        self.xq, self.wq = fe.gauss_legendre(self.nqc)
        self.Nq = fe.lagrange(self.p, self.xq)[0]
        self.C = _monomial_matrix(self.p)
        self.nsamp = 4 * self.p + 1 if self.p > 1 else 3
        from math import comb
        # fractions of the slot (_project): the start samples, and with them the 2p - 1 points
        # whose phi'' values give its Bernstein coefficients
        self._t_start = np.linspace(0.0, 1.0, self.nsamp)
        self._t_check = np.concatenate([self._t_start, np.linspace(0.0, 1.0, 2 * self.p - 1)])
        # their monomials and derivatives as rows (3 n, p+1), and the Taylor shift (_taylor)
        self._T_start, self._T_check = (_powers(self.p, t, 2).reshape(-1, self.p + 1)
                                        for t in (self._t_start, self._t_check))
        kk = np.arange(self.p + 1)
        self._kmj = np.maximum(kk[None, :] - kk[:, None], 0)
        self._binom = np.array([[comb(k, j) for k in kk] for j in kk], dtype=float)
        # coefficient k of d^j D / dxi^j is (k + j)! / k! Dc_{k+j} (_phi_rows)
        self._row_index = np.minimum(kk[None, :] + np.arange(3)[:, None], self.p)   # (3, p+1)
        self._row_factor = np.array([[np.prod(np.arange(k + 1, k + j + 1)) if k + j <= self.p
                                      else 0.0 for k in kk] for j in range(3)])[:, :, None]
        # phi'(xi) = sum_n c_n xi^n, c_n = sum_{i + j - 1 = n} j D_i . A_j  (_stationary_min)
        nb = 2 * self.p - 2                   # degree of phi'' (_project)
        tb = np.linspace(0.0, 1.0, nb + 1)
        V = np.array([[comb(nb, k) * t ** k * (1 - t) ** (nb - k) for k in range(nb + 1)]
                      for t in tb])
        self._to_bernstein = np.linalg.inv(V)
        self.nonconvex = 0                    # projections that needed _stationary_min
        q = self.p + 1
        self._dphi = np.zeros((q, q, 2 * self.p))
        for i in range(q):
            for j in range(1, q):
                self._dphi[i, j, i + j - 1] = j
        # contact-zone integration (module docstring, "Segments"): samples per slave element
        self.segments = bool(segments)
        self.nseg = max(2 * self.p + 3, self.nqc + 2)
        # Gauss points per zone: d ~ d0 - k s^2 near a crossing (<d>^2 a quartic), and deep
        # penetrations are far from polynomial: 8 points keep the quadrature error below 1e-8
        self.nqz = max(self.nqc + 3, 8)
        self.grade = 4                 # levels of geometric grading toward cuts beyond
        #                                2 log2 of the closest points' racing rate (_cut_levels)
        self.xz, self.wz = fe.gauss_legendre(self.nqz)

    # -- arclength ------------------------------------------------------------------------
    def slave_arclength(self, own_ids):
        """(no, nqc) arclength of the slave Gauss points."""
        own_ids = np.asarray(own_ids, dtype=float)
        return own_ids[:, None] * self.h + (self.xq[None, :] + 1.0) * (0.5 * self.h)

    def admissible_slots(self, s, m):
        """Admissible part of element m for slave arclength s: I(s) cap [m h, (m+1) h].

        s, m (M,) -> lo, hi (M, 2) in xi of the (at most two) intervals, valid (M, 2).
        Open: excluded (s - delta, s + delta).  Closed: the admissible arc [s + delta,
        s + L - delta] (mod L) intersected with the element arc (at most two pieces)."""
        u = np.asarray(s, dtype=float) - np.asarray(m, dtype=float) * self.h
        lo, hi, valid = self._slots(u)
        return self._to_xi(lo), self._to_xi(hi), valid

    def _slots(self, u):
        """``admissible_slots`` of slave points at element-local arclength u (any shape) from
        the element start: lo, hi (u.shape, 2) in arclength from the element start, valid."""
        h, L, dl = self.h, self.L, self.delta
        lo = np.empty(u.shape + (2,))
        if not self.closed:
            lo[..., 0] = 0.0
            lo[..., 1] = np.maximum(0.0, u + dl)
            hi = np.full(u.shape + (2,), h)
            hi[..., 0] = np.minimum(h, u - dl)
            valid = np.empty(u.shape + (2,), dtype=bool)
            valid[..., 0] = u - dl >= 0.0
            valid[..., 1] = u + dl <= h
        else:
            lad = L - 2.0 * dl
            lo[..., 0] = np.mod(u + dl, L)
            lo[..., 1] = lo[..., 0] - L
            hi = np.minimum(lo + lad, h)
            np.maximum(lo, 0.0, out=lo)
            valid = (hi >= lo) & (lad >= 0.0)
        valid &= hi >= lo
        return lo, hi, valid

    def _to_xi(self, t):
        """Element-local arclength t to xi, clamped to [-1, 1]."""
        return np.minimum(np.maximum(2.0 * t / self.h - 1.0, -1.0), 1.0)

    # -- projection -------------------------------------------------------------------------
    def _fgh(self, x, A, P):
        """phi = |r(x) - P|^2/2 and its first two xi-derivatives; A (M, p+1, 3) monomials."""
        pw, pw1, pw2 = _monomials(self.p, x)
        r = np.einsum("mk,mkd->md", pw, A)
        r1 = np.einsum("mk,mkd->md", pw1, A)
        r2 = np.einsum("mk,mkd->md", pw2, A)
        D = r - P
        return 0.5 * np.einsum("md,md->m", D, D), np.einsum("md,md->m", D, r1), \
            np.einsum("md,md->m", r1, r1) + np.einsum("md,md->m", D, r2)

    def _f(self, x, A, P):
        D = A[:, self.p].copy()
        for j in range(self.p - 1, -1, -1):
            D = D * x[:, None] + A[:, j]
        D -= P
        return 0.5 * np.einsum("md,md->m", D, D)

    def project(self, P, A, lo, hi):
        """argmin_{xi in [lo, hi]} |r(xi) - P|^2 for M problems. Returns xi (M,), phi (M,)."""
        M = len(P)
        xi_out = np.empty(M)
        f_out = np.empty(M)
        for b0 in range(0, M, self.CHUNK):
            sl = slice(b0, min(M, b0 + self.CHUNK))
            x, f, nonconvex = self._project(P[sl], A[sl], lo[sl], hi[sl], True)
            # where phi may be non-convex on the slot, a minimum may hide between samples
            flat = np.flatnonzero(nonconvex)
            if flat.size:
                x2, f2 = self._stationary_min(P[sl][flat], A[sl][flat], lo[sl][flat], hi[sl][flat])
                better = f2 < f[flat]
                x[flat[better]], f[flat[better]] = x2[better], f2[better]
            xi_out[sl], f_out[sl] = x, f
            self.nonconvex += int(flat.size)
        return xi_out, f_out

    def _project_chunk(self, P, A, lo, hi):
        """The sampled Newton search of ``project`` alone (no roots where phi is not convex)."""
        return self._project(P, A, lo, hi, False)[:2]

    def _taylor(self, Dc, lo, w):
        """Coefficients B (S, p+1, 3) of D(lo + w t) = sum_j B_j t^j, from those of D(xi) =
        sum_k Dc_k xi^k: B_j = sum_k C(k, j) lo^(k-j) w^j Dc_k."""
        LW = _powers(self.p, np.stack([lo, w], axis=1), 0)                 # (S, 2, 1, p+1)
        return (self._binom * LW[:, 0, 0, self._kmj] * LW[:, 1, 0, :, None]) @ Dc

    def _project(self, P, A, lo, hi, check):
        """Sampled Newton search for argmin phi, phi = |r(xi) - P|^2 / 2 on [lo, hi], S
        problems (A (S, p+1, 3) monomial coefficients of r): phi at nsamp equispaced samples;
        from every discrete local minimum a safeguarded Newton iteration (steps limited to one
        sample spacing, clamped to the slot, backtracking on phi until phi does not rise by
        more than 1e-14 phi; a Newton step below 1e-9 is always taken; converged when a step
        moves xi by <= 1e-13), all starts at once; the best start per problem.  With ``check``
        also whether phi may be non-convex on the slot: phi'' = |r'|^2 + D . r'' is a
        polynomial of degree 2p - 2 whose Bernstein coefficients on [lo, hi] (from its values at
        2p - 1 equispaced points) bound it from below; where one is not positive a minimum may
        hide between two samples next to a maximum (``project`` then takes every stationary
        point).  The samples of all problems are one matrix product: in the slot's own
        coordinate t (xi = lo + (hi - lo) t) the monomials of the sample fractions are fixed
        (``_taylor``).  Returns xi (S,), phi (S,), nonconvex (S,) bool or None."""
        S, ns, n1 = len(P), self.nsamp, self.p + 1
        Dc = np.array(A, dtype=float)
        Dc[:, 0] -= P
        w = hi - lo
        t, T = (self._t_check, self._T_check) if check and self.p > 1 else \
            (self._t_start, self._T_start)
        n = len(t)
        B = self._taylor(Dc, lo, w).transpose(1, 0, 2).reshape(n1, 3 * S)
        R = (T @ B).reshape(n, 3, S, 3)                     # D and its t-derivatives
        F = 0.5 * np.einsum("nsd,nsd->ns", R[:ns, 0], R[:ns, 0])     # phi at the samples
        ws = np.where(w > 0.0, w, 1.0)                    # phi' = phi_t / w, phi'' = phi_tt / w^2
        nonconvex = np.zeros(S, dtype=bool) if check else None     # (p = 1: phi'' constant)
        if check and self.p > 1:
            Rc = R[ns:]
            Hc = (np.einsum("nsd,nsd->sn", Rc[:, 1], Rc[:, 1])
                  + np.einsum("nsd,nsd->sn", Rc[:, 0], Rc[:, 2])) / (ws * ws)[:, None]
            nonconvex = ~((Hc @ self._to_bernstein.T).min(axis=1) > 0.0) & (w > 0.0)
        ismin = np.ones(F.shape, dtype=bool)
        ismin[1:] &= F[1:] <= F[:-1]
        ismin[:-1] &= F[:-1] <= F[1:]
        # plateaus (e.g. degenerate slot hi == lo): keep only the first sample of a run
        ismin[1:] &= ~(ismin[:-1] & (F[1:] == F[:-1]))
        pid, sid = np.nonzero(ismin.T)                    # problem by problem
        Rs = R[sid, :, pid]                               # (starts, 3, 3) at the starts
        wp = ws[pid]
        x = lo[pid] + w[pid] * t[sid]
        f = F[sid, pid]
        g = np.einsum("md,md->m", Rs[:, 0], Rs[:, 1]) / wp
        h = (np.einsum("md,md->m", Rs[:, 1], Rs[:, 1])
             + np.einsum("md,md->m", Rs[:, 0], Rs[:, 2])) / (wp * wp)
        x, f = self._newton(Dc[pid], lo[pid], hi[pid], w[pid] / (ns - 1),
                            (np.einsum("md,md->m", P, P)
                             + np.einsum("mkd,mkd->m", A, A))[pid], x, f, g, h)
        # best start per problem
        order = np.lexsort((f, pid))
        first = np.ones(len(order), dtype=bool)
        first[1:] = pid[order][1:] != pid[order][:-1]
        best = order[first]
        xi_out = np.empty(S)
        f_out = np.full(S, np.inf)
        xi_out[pid[best]] = x[best]
        f_out[pid[best]] = f[best]
        return xi_out, f_out, nonconvex

    def _phi_rows(self, Dc):
        """Per problem (S,), the monomial coefficients (S, p+1, 24) of the factors of the four
        products D . D, D . r', r' . r', D . r'' (``_phi_at``): D = sum_k Dc_k xi^k, r' and
        r'' its xi-derivatives."""
        C3 = Dc[:, self._row_index] * self._row_factor                     # (S, 3, p+1, 3)
        return C3[:, [0, 0, 1, 0, 0, 1, 1, 2]].transpose(0, 2, 1, 3).reshape(len(Dc), self.p + 1,
                                                                             24)

    def _phi_at(self, Q, x):
        """phi = |D|^2 / 2, phi' = D . r', phi'' = |r'|^2 + D . r'' at x (S,) from ``_phi_rows``
        (one matrix product and one contraction)."""
        R = (_powers(self.p, x, 0) @ Q).reshape(len(x), 2, 4, 3)
        s = np.einsum("skd,skd->sk", R[:, 0], R[:, 1])
        return 0.5 * s[:, 0], s[:, 1], s[:, 2] + s[:, 3]

    def _newton(self, Dc, lo, hi, dx, scale, x, f, g, h):
        """The safeguarded Newton iteration of ``_project`` from the starts x with phi, phi',
        phi'' = f, g, h there, all starts at once.  A start that has converged or given up is
        frozen (its step bound dx set to 0: its later steps are 0 and leave it where it is);
        the working rows are compacted when few remain.  Returns xi and phi of every start."""
        n = len(x)
        x_out, f_out = x.copy(), f.copy()
        wid = np.arange(n)                   # the working rows' start indices
        Q = self._phi_rows(Dc)
        dx = dx.copy()
        ndx = -dx
        tiny = 1e-30 * scale
        for _ in range(self.MAXIT):
            newton = h > 0.0
            step = np.sign(g)
            step *= ndx
            np.divide(-g, h, out=step, where=newton)
            np.maximum(step, ndx, out=step)
            np.minimum(step, dx, out=step)
            xt = x + step
            np.maximum(xt, lo, out=xt)
            np.minimum(xt, hi, out=xt)
            ft, gt, ht = self._phi_at(Q, xt)
            ok = ft <= f + (1e-14 * f + tiny)
            if not ok.all():
                ok |= newton & (np.abs(step) < 1e-9)
                if not ok.all():
                    self._backtrack(Q, lo, hi, x, f, f + (1e-14 * f + tiny), newton, step,
                                    np.flatnonzero(~ok), xt, ft, gt, ht, ok)
            stop = (np.abs(xt - x) <= 1e-13) | ~ok       # converged, or gave up (x, f kept)
            x, f, g, h = xt, ft, gt, ht
            if not stop.any():
                continue
            dx[stop] = 0.0
            ndx[stop] = 0.0
            na = np.count_nonzero(dx)
            if na == 0:
                break
            if na <= n // 4 and n > 64:                  # compact the working rows
                x_out[wid], f_out[wid] = x, f
                keep = np.flatnonzero(dx)
                wid, Q, lo, hi, dx, ndx, tiny, x, f, g, h = (
                    v[keep] for v in (wid, Q, lo, hi, dx, ndx, tiny, x, f, g, h))
                n = na
        x_out[wid], f_out[wid] = x, f
        return x_out, f_out

    def _backtrack(self, Q, lo, hi, x, f, limit, newton, step, rows, xt, ft, gt, ht, ok):
        """Halve the Newton steps of the rows whose trial raised phi above ``limit`` until one
        does not (at most MAXBT trials in all); fills xt, ft, gt, ht and ok of those accepted in
        place, and puts back x and phi of those that gave up."""
        st = step[rows]
        for _bt in range(1, self.MAXBT):
            st = 0.5 * st
            xb = np.minimum(np.maximum(x[rows] + st, lo[rows]), hi[rows])
            fb, gb, hb = self._phi_at(Q[rows], xb)
            acc = (fb <= limit[rows]) | (newton[rows] & (np.abs(st) < 1e-9))
            r = rows[acc]
            xt[r], ft[r], gt[r], ht[r], ok[r] = xb[acc], fb[acc], gb[acc], hb[acc], True
            rows, st = rows[~acc], st[~acc]
            if rows.size == 0:
                break
        xt[rows], ft[rows] = x[rows], f[rows]

    def _stationary_min(self, P, A, lo, hi):
        """Every stationary point of phi: the real roots of the polynomial phi'(xi) = D(xi) .
        r'(xi) of degree 2p - 1 (eigenvalues of its companion matrix, batched), kept if
        within the slot and polished by Newton steps that may not raise phi, and the two slot
        ends; the smallest phi among them is the global minimum (no sampling: a minimum next
        to a maximum, as in the flat distance valleys of a slave point near a centre of
        curvature of the master, cannot be missed)."""
        M, p = len(P), self.p
        D = A.copy()
        D[:, 0] -= P
        G = np.matmul(D, np.swapaxes(A, 1, 2))                        # D_i . A_j
        c = G.reshape(M, -1) @ self._dphi.reshape(-1, 2 * p)          # phi' coefficients
        deg = 2 * p - 1
        lead = c[:, deg]
        big = np.abs(c).max(axis=1)
        # a (nearly) vanishing leading coefficient: its roots run off to infinity, those in
        # the slot barely move; keep the companion matrix finite
        tiny = np.abs(lead) < 1e-13 * big
        lead = np.where(tiny, np.where(lead < 0, -1.0, 1.0) * 1e-13 * np.maximum(big, 1e-300), lead)
        comp = np.zeros((M, deg, deg))
        if deg > 1:
            comp[:, np.arange(1, deg), np.arange(deg - 1)] = 1.0
        comp[:, :, -1] = -c[:, :deg] / lead[:, None]
        roots = np.linalg.eigvals(comp)
        # near-double roots come out as complex pairs: their real parts are candidates too
        re = roots.real
        ii, jj = np.nonzero((np.abs(roots.imag) <= 1e-4 * (1.0 + np.abs(re)))
                            & (re > lo[:, None]) & (re < hi[:, None]))
        xr = re[ii, jj]
        Ai, Pi = A[ii], P[ii]
        fr = self._f(xr, Ai, Pi)
        for _ in range(3):                     # polish (Newton steps that may not raise phi)
            _, g, H = self._fgh(xr, Ai, Pi)
            st = np.where(H > 0.0, -g / np.where(H > 0.0, H, 1.0), 0.0)
            xt = np.clip(xr + st, lo[ii], hi[ii])
            ft = self._f(xt, Ai, Pi)
            better = ft <= fr
            xr = np.where(better, xt, xr)
            fr = np.where(better, ft, fr)
        flo, fhi = self._f(lo, A, P), self._f(hi, A, P)
        x = np.where(fhi < flo, hi, lo)
        f = np.minimum(flo, fhi)
        order = np.lexsort((fr, ii))              # the best root of every problem
        first = np.ones(len(order), dtype=bool)
        first[1:] = ii[order][1:] != ii[order][:-1]
        b = order[first]
        better = fr[b] < f[ii[b]]
        x[ii[b][better]], f[ii[b][better]] = xr[b][better], fr[b][better]
        return x, f

    # -- main entry ---------------------------------------------------------------------------
    @logged("ContactEval")
    def evaluate(self, own_ids, x_own, other_ids, x_other, pairs, tangent=True, report=True):
        """The contact term of every strand in reach, summed:

            E_c = (mu/2) sum_k int <d_k(s)>^2 ds,   d_k(s) = 2 eps - min_{sigma in I(s) cap S_k(s)} |r(s) - r(sigma)|

        S_k(s): the k-th run of consecutive candidate elements of the slave element of s
        (``strand_index``), i.e. the k-th strand that passes within reach.  Where one strand is
        in reach this is the slides' E_c (the rod's own continuation, a run of its own, lies
        beyond the exclusion and never touches, ``default_exclusion``).  Where a point lies
        between two strands and touches both (three strands in contact: the plectoneme's end
        loop threaded by its tail), the single closest point of the slides jumps between them
        wherever their distances tie; the integrand jumps with it (the force goes to the
        other strand's nodes), and a near tie can flip back and forth between two samples,
        unseen by the zone cuts: residual steps of mu d w (0.2 - 3 at 9.42 turns) as a node
        moved by 1e-9, and every Newton solve stalled at |F| ~ 1.5.  Summed per strand, each
        term is as smooth as a two-strand contact, and a point squeezed between two strands
        is pushed by both.  Same outputs as ``evaluate_strand`` (gap: the deepest d_k,
        force: the sum of mu <d_k>, sbar: of the deepest; the per-point arrays concatenated).

        The report (gap, force, sbar at the Gauss points) is this law's own quadrature, or
        what finds its zones: always made (``report`` is the interface of
        contact_potential.PotentialKernel).  Without ``tangent``, ``add_tangent`` makes mat,
        switch and switch_mat later from what the evaluation kept (``_deferred``).  ``depth``:
        the deepest d over the Gauss and zone points (RodProblem.precheck's penetration limit).

        All strands are evaluated in one pass (``_evaluate``): strand k of own element e is the
        virtual own element k no + e, whose candidates are the pairs of e in strand k, so
        every closest-point search and root finding of all strands shares its calls; the
        outputs are those of ``evaluate_strand`` strand by strand, in the same order."""
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        k = strand_index(pairs, self.nelem, self.closed,
                         int(np.ceil(self.delta / self.h)) + 1)
        nk = int(k.max()) + 1 if len(k) else 1
        return self._evaluate(own_ids, x_own, other_ids, x_other, pairs, k, nk, tangent)

    @staticmethod
    def _depth(out):
        """``depth`` (the deepest d of the Gauss and zone points) and ``reported`` of an
        output."""
        gap, dact = out["gap"], out["d_active"]
        out["depth"] = max(float(gap.max()) if gap.size else -np.inf,
                           float(dact.max()) if len(dact) else -np.inf)
        out["reported"] = True
        return out

    @logged("ContactTangent")
    def add_tangent(self, out):
        """mat, switch and switch_mat of an evaluation made without its tangent (in place;
        nothing to do if it has them): ``_terms_tangent`` and ``_switch_terms`` on the points
        and cuts that the evaluation kept, strand by strand in its order of rows."""
        if out["mat"] is not None:
            return out
        n1 = self.p + 1
        mats, sws, swms = [np.zeros((0, 6 * n1, 6 * n1))], [out["switch"]], \
            [np.zeros((0, 9 * n1, 9 * n1))]
        for ctx, wJ, cl, cuts in out.pop("_deferred"):
            mats.append(self._terms_tangent(ctx, wJ, cl))
            if cuts is not None:
                part = {"switch": np.zeros((0, 3), dtype=np.int64),
                        "switch_mat": np.zeros((0, 9 * n1, 9 * n1))}
                self._switch_terms(ctx, *cuts, True, part)
                sws.append(part["switch"])
                swms.append(part["switch_mat"])
        out["mat"] = np.concatenate(mats)
        out["switch"] = np.concatenate(sws)
        out["switch_mat"] = np.concatenate(swms)
        return out

    @staticmethod
    def add_report(out):
        """The report points of this law are its own Gauss points: always there."""
        return out

    def evaluate_strand(self, own_ids, x_own, other_ids, x_other, pairs, tangent=True,
                        report=True):
        """Gap, energy, residual and tangent of the contact term over the own elements.

        own_ids (no,) global element ids; x_own (no, p+1, 3) their nodal positions;
        other_ids (nt,), x_other (nt, p+1, 3): elements that may hold closest points (own
        elements may be repeated here; missing ids are looked up among the own elements);
        pairs (npair, 2) global ids (e_own, e_other) from ``candidate_pairs``.

        Returns a dict:
          energy  float  the penalty energy of the own slave points: sum_{own e, q} w_q J
                  (mu/2) <d>^2 over the nqc Gauss points, or (segments) over the Gauss points
                  of the contact zones
          total_force, complementarity  int f_c ds, int <d> f_c ds by the same quadrature
          gap     (no, nqc)  d = 2 eps - (distance to the closest admissible point on the
                  candidate elements) at the Gauss points; -inf where the point has no
                  candidate (then the true gap is < 2 eps - reach).  Exact wherever
                  d >= 2 eps - reach.
          force   (no, nqc)  f_c = mu <d> at the Gauss points (the slave side only: in a
                  two-sided contact, where the master strand is slave in turn, each strand
                  gets 2 mu d)
          sbar    (no, nqc)  arclength of the closest point (NaN where none)
          active  (nact, 2)  (own element id, element id holding the closest point), d > 0,
                  one row per quadrature point carrying force
          vec     (nact, 2(p+1), 3)  dE_c/dx for the nodes of [own element, closest element]
          mat     (nact, 6(p+1), 6(p+1))  d2E_c/dx2, index 3a+i (None if not tangent)
          qp      (nact,) Gauss index of the slave point (-1 for a contact-zone point);
          xi_slave (nact,) slave xi; xi (nact,) master xi;
          normal  (nact, 3) nu; interior (nact,) bool (closest point strictly inside its slot)
          zones   number of contact zones (segments; else the number of active Gauss points)
          switch  (nsw, 3)  (own element, element A, element B) of every switch point (segments:
                  a cut where the closest point jumps from A to B)
          switch_mat  (nsw, 9(p+1), 9(p+1))  its tangent term over the nodes [own, A, B]
          depth   the deepest d of the Gauss and zone points (max of gap and d_active)
          reported  True (the report is this law's own quadrature; ``report`` is ignored)
        Without ``tangent``: mat and switch_mat None, switch empty, made by ``add_tangent``.
        """
        return self._evaluate(own_ids, x_own, other_ids, x_other, pairs, None, 1, tangent)

    def _evaluate(self, own_ids, x_own, other_ids, x_other, pairs, strand, nk, tangent):
        """``evaluate_strand`` of every strand (strand (npair,) the strand of every pair, None
        for one), summed as ``evaluate`` describes, in one pass over the virtual own elements
        k no + e (strand k of own element e; ``_context``)."""
        nqc, h = self.nqc, self.h
        own_ids, x_own, other_ids, x_other, pairs = self.as_inputs(own_ids, x_own, other_ids,
                                                                    x_other, pairs)
        no = len(own_ids)
        out = self.empty_output(no, tangent)
        if not tangent:
            out["_deferred"] = []
        if no == 0 or len(pairs) == 0:
            return self._depth(out)
        ctx = self._context(own_ids, x_own, other_ids, x_other, pairs, strand, nk)
        nv = no * nk

        # the Gauss points: reported gap and force, and the quadrature unless segments
        cl, gap, sbar = self.report_points(ctx, nv)
        out["gap"], out["sbar"], out["force"] = self._merge_strands(gap, sbar, no, nk)
        cuts = None
        if self.segments:
            o_q, xi_q, w_q, nz, cuts = self._zones(ctx, gap)
            cl = self._closest(ctx, o_q, xi_q)
            qp = np.full(len(o_q), -1, dtype=np.int64)
            out["zones"] = nz
            self._switch_terms(ctx, *cuts, tangent, out)
        else:
            o_q = np.repeat(np.arange(nv), nqc)
            xi_q = np.tile(self.xq, nv)
            w_q = np.tile(self.wq * (0.5 * h), nv)
            qp = np.tile(np.arange(nqc), nv)
            out["zones"] = int(np.count_nonzero(cl["d"] > 0.0))
        self._terms(ctx, o_q, xi_q, w_q, qp, cl, tangent, out)
        if not tangent:             # what add_tangent needs, at the same positions
            out["_deferred"] = [(ctx, w_q, cl, cuts)]
        return self._depth(out)

    def _merge_strands(self, gap, sbar, no, nk):
        """The report of the own elements from that of the virtual ones (nk no, nqc): gap the
        deepest d over the strands, sbar of the deepest (the first strand of a tie), force the
        sum of mu <d> over the strands."""
        gap, sbar = gap.reshape(nk, no, -1), sbar.reshape(nk, no, -1)
        g, s = gap[0], sbar[0]
        force = self.mu * np.maximum(g, 0.0)
        for j in range(1, nk):
            deeper = gap[j] > g
            s = np.where(deeper, sbar[j], s)
            g = np.maximum(g, gap[j])
            force = force + self.mu * np.maximum(gap[j], 0.0)
        return g, s, force

    # -- building blocks ----------------------------------------------------------------------
    def as_inputs(self, own_ids, x_own, other_ids, x_other, pairs):
        """The arguments of ``evaluate_strand`` as arrays: ids (int64), nodal positions
        (n, p+1, 3), pairs (npair, 2)."""
        n1 = self.p + 1
        own_ids = np.asarray(own_ids, dtype=np.int64).ravel()
        other_ids = np.asarray(other_ids, dtype=np.int64).ravel()
        return (own_ids, np.asarray(x_own, dtype=float).reshape(len(own_ids), n1, 3),
                other_ids, np.asarray(x_other, dtype=float).reshape(len(other_ids), n1, 3),
                np.asarray(pairs, dtype=np.int64).reshape(-1, 2))

    def empty_output(self, no, tangent):
        """The outputs of ``evaluate_strand`` for ``no`` own elements with nothing in contact."""
        n1, nqc = self.p + 1, self.nqc
        return {"energy": 0.0, "total_force": 0.0, "complementarity": 0.0, "zones": 0,
                "gap": np.full((no, nqc), -np.inf), "force": np.zeros((no, nqc)),
                "sbar": np.full((no, nqc), np.nan),
                "active": np.zeros((0, 2), dtype=np.int64), "vec": np.zeros((0, 2 * n1, 3)),
                "mat": np.zeros((0, 6 * n1, 6 * n1)) if tangent else None,
                "qp": np.zeros(0, dtype=np.int64), "xi": np.zeros(0), "xi_slave": np.zeros(0),
                "normal": np.zeros((0, 3)), "interior": np.zeros(0, dtype=bool),
                "d_active": np.zeros(0), "switch": np.zeros((0, 3), dtype=np.int64),
                "switch_mat": np.zeros((0, 9 * n1, 9 * n1)) if tangent else None}

    def report_points(self, ctx, no):
        """The closest point of the nqc Gauss points of the ``no`` own elements: the
        ``_closest`` record, gap d (no, nqc) and sbar (no, nqc), the arclength of the closest
        point (NaN without one)."""
        nqc, h = self.nqc, self.h
        cl = self._closest(ctx, np.repeat(np.arange(no), nqc), np.tile(self.xq, no))
        has = cl["m"] >= 0
        sb = np.full(len(has), np.nan)
        sb[has] = ctx["pool_ids"][cl["m"][has]] * h + (cl["xi_m"][has] + 1.0) * 0.5 * h
        return cl, cl["d"].reshape(no, nqc), sb.reshape(no, nqc)

    @staticmethod
    def master_pool(own_ids, x_own, other_ids, x_other):
        """The elements that may hold a master point: other first, then own (first occurrence
        wins), sorted ids and their nodes."""
        pool_ids = np.concatenate([other_ids, own_ids])
        pool_x = np.concatenate([x_other, x_own], axis=0)
        pool_ids, first = np.unique(pool_ids, return_index=True)
        return pool_ids, pool_x[first]

    def _context(self, own_ids, x_own, other_ids, x_other, pairs, strand=None, nk=1):
        """Master pool (other first, then own; first occurrence wins), monomial coefficients,
        bounding spheres, and the candidate masters of every own element (``cand``, a row per
        own element in the order of the pairs, padded with -1).
        With ``strand`` (the strand of every pair, ``strand_index``) and nk strands the own
        elements are virtual: k no + e is strand k of own element e, with the candidates of e
        in strand k (own_ids and x_own repeated nk times)."""
        pool_ids, pool_x = self.master_pool(own_ids, x_own, other_ids, x_other)
        no = len(own_ids)
        oi = _lookup(own_ids, pairs[:, 0], "own")
        if strand is not None and nk > 1:
            oi = oi + no * np.asarray(strand, dtype=np.int64)
            own_ids = np.tile(own_ids, nk)
            x_own = np.tile(x_own, (nk, 1, 1))
        mi = _lookup(pool_ids, pairs[:, 1], "other")
        order = np.argsort(oi, kind="stable")
        count = np.bincount(oi, minlength=no * nk)
        # the candidates of every own element in the order of the pairs, padded with -1
        cand = np.full((no * nk, int(count.max(initial=0))), -1, dtype=np.int64)
        so = oi[order]
        cand[so, np.arange(len(so)) - (np.cumsum(count) - count)[so]] = mi[order]
        cen, rad = element_bounds(pool_x)
        return {"own_ids": own_ids, "x_own": x_own, "pool_ids": pool_ids, "pool_x": pool_x,
                "A_pool": np.einsum("ka,ead->ekd", self.C, pool_x), "cen": cen, "rad": rad,
                "cand": cand, "own_start": own_ids * self.h,
                "pool_start": pool_ids.astype(float) * self.h, "no": no}

    def _closest(self, ctx, o, xi, rival=False):
        """Closest admissible point of the slave points (own index o, slave xi) (M,) among the
        candidate elements of their element: d = 2 eps - g (-inf without candidate), m (pool
        index, -1 without), xi_m, interior, D = r(s) - r(sbar), g, and N, dN at xi.

        With ``rival``: also the runner-up, the nearest of the per-element minima whose kind
        (``_kind``) is not the closest point's (no pruning then): rival_g (inf without one),
        rival_D, rival_kind, and kind (of the closest point)."""
        p, h = self.p, self.h
        M = len(o)
        NN = (_powers(p, xi, 1).reshape(2 * M, p + 1) @ self.C).reshape(M, 2, p + 1)
        Ns, dNs = NN[:, 0], NN[:, 1]
        P = np.einsum("na,nad->nd", Ns, ctx["x_own"][o])
        s = ctx["own_start"][o] + (xi + 1.0) * (0.5 * h)
        res = {"d": np.full(M, -np.inf), "m": np.full(M, -1, dtype=np.int64), "xi_m": np.zeros(M),
               "interior": np.zeros(M, dtype=bool), "D": np.zeros((M, 3)), "g": np.full(M, np.inf),
               "N": Ns, "dN": dNs, "P": P}
        cand = ctx["cand"][o]                                        # (M, candidates)
        lo, hi, valid = self._slots(s[:, None] - ctx["pool_start"][cand])
        valid &= (cand >= 0)[:, :, None]
        pr_pt, c, slot = np.nonzero(valid)
        if pr_pt.size == 0:
            return res
        pr_m = cand[pr_pt, c]
        pr_lo, pr_hi = self._to_xi(lo[pr_pt, c, slot]), self._to_xi(hi[pr_pt, c, slot])
        A = ctx["A_pool"]
        Pp = P[pr_pt]
        if not rival and len(pr_pt) > self.PRUNE:
            keep = self._prune(ctx, M, Pp, pr_pt, pr_m, pr_lo, pr_hi)
            pr_pt, pr_m, pr_lo, pr_hi, Pp = (a[keep] for a in (pr_pt, pr_m, pr_lo, pr_hi, Pp))
        xm, f = self.project(Pp, A[pr_m], pr_lo, pr_hi)
        # global minimum per slave point (ties, e.g. a shared node: the first one only)
        best = _nearest_per_point(np.arange(len(f)), f, pr_pt)
        b = pr_pt[best]
        res["m"][b] = pr_m[best]
        res["xi_m"][b] = xm[best]
        res["interior"][b] = (xm[best] > pr_lo[best]) & (xm[best] < pr_hi[best])
        Dv = self._offset(ctx, P[b], pr_m[best], xm[best])
        g = np.sqrt(np.einsum("nd,nd->n", Dv, Dv))
        res["D"][b] = Dv
        res["g"][b] = g
        res["d"][b] = 2.0 * self.eps - g
        if rival:
            self._rival(ctx, res, P, pr_pt, pr_m, pr_lo, pr_hi, xm, f, b, best)
        return res

    def _prune(self, ctx, M, Pp, pr_pt, pr_m, pr_lo, pr_hi):
        """The slots (pr_*, sorted by slave point pr_pt) that may hold the closest point of
        their slave point Pp: a slot whose element's bounding sphere is farther from the slave
        point than an admissible point (a slot end) of another slot cannot (exact: the
        projection of the kept slots gives the same closest points; only worth its cost when
        there are many slots)."""
        A = ctx["A_pool"][pr_m]
        lb = np.linalg.norm(Pp - ctx["cen"][pr_m], axis=1) - ctx["rad"][pr_m]
        W = _powers(self.p, np.stack([pr_lo, pr_hi], axis=1), 0)[:, :, 0]     # (n, 2, p+1)
        ends = W @ A - Pp[:, None, :]
        ub = np.sqrt(np.einsum("nkd,nkd->nk", ends, ends).min(axis=1))
        first = np.flatnonzero(np.r_[True, pr_pt[1:] != pr_pt[:-1]])
        best_ub = np.minimum.reduceat(ub, first)
        return lb <= np.repeat(best_ub, np.diff(np.r_[first, len(ub)])) * (1.0 + 1e-9) + 1e-300

    def _rival(self, ctx, res, P, pr_pt, pr_m, pr_lo, pr_hi, xm, f, b, best):
        """The runner-up of ``_closest`` (rival=True): among the per-element minima (pr_*, xm,
        f) of each slave point, the nearest one of another kind than the closest point's."""
        M = len(res["d"])
        kind = self._kind_at(ctx["pool_ids"][pr_m], xm, (xm > pr_lo) & (xm < pr_hi))
        best_kind = np.full(M, -1, dtype=np.int64)
        best_kind[b] = kind[best]
        other = np.flatnonzero(kind != best_kind[pr_pt])
        res["kind"] = best_kind
        res["rival_g"] = np.full(M, np.inf)
        res["rival_D"] = np.zeros((M, 3))
        res["rival_kind"] = np.full(M, -1, dtype=np.int64)
        if other.size == 0:
            return
        rv = _nearest_per_point(other, f, pr_pt)
        q = pr_pt[rv]
        Dv = self._offset(ctx, P[q], pr_m[rv], xm[rv])
        res["rival_D"][q] = Dv
        res["rival_g"][q] = np.linalg.norm(Dv, axis=1)
        res["rival_kind"][q] = kind[rv]

    def _offset(self, ctx, P, m, xm):
        """D = P - r_m(xm): from points P to the points xm of pool elements m."""
        Nm = _monomials(self.p, xm)[0] @ self.C
        return P - np.einsum("na,nad->nd", Nm, ctx["pool_x"][m])

    def _ddxi(self, ctx, o, cl):
        """d'(xi) of the slave points: -nu . dr/dxi where the closest point is stationary
        (interior: its motion drops out) or fixed (a node); at an exclusion bound sbar = s -+
        delta moves with s, dxi_m/dxi = 1, and d' = -nu . (dr/dxi - dr_m/dxi_m)."""
        t = np.einsum("na,nad->nd", cl["dN"], ctx["x_own"][o])
        g = np.where(np.isfinite(cl["g"]) & (cl["g"] > 0), cl["g"], 1.0)
        has = cl["m"] >= 0
        bound = self._kind(ctx, cl) <= -2
        if np.any(bound):
            dNm = _monomials(self.p, cl["xi_m"][bound])[1]
            t[bound] -= np.einsum("nk,nkd->nd", dNm, ctx["A_pool"][cl["m"][bound]])
        return np.where(has, -np.einsum("nd,nd->n", cl["D"], t) / g, 0.0)

    def _solve1d(self, ctx, o, a, b, fa, fb, which, iters=40):
        """Illinois (modified regula falsi) root of f on [a, b], f(a), f(b) of opposite signs,
        vectorised; f = d (which 0) or d' (which 1) of the slave points of own index o.
        Bisection where a value is not finite.  Returns the root (to 1e-13 in xi)."""
        a, b, fa, fb = (np.array(v, dtype=float) for v in (a, b, fa, fb))
        x = 0.5 * (a + b)
        dx_tol = 1e-13
        act = np.arange(len(a))
        side = np.zeros(len(a), dtype=int)
        for _ in range(iters):
            if act.size == 0:
                break
            A_, B_, FA, FB = a[act], b[act], fa[act], fb[act]
            ok = np.isfinite(FA) & np.isfinite(FB) & (FA != FB)
            c = np.where(ok, (A_ * FB - B_ * FA) / np.where(ok, FB - FA, 1.0), 0.5 * (A_ + B_))
            c = np.minimum(np.maximum(c, np.minimum(A_, B_)), np.maximum(A_, B_))
            cl = self._closest(ctx, o[act], c)
            fc = cl["d"] if which == 0 else self._ddxi(ctx, o[act], cl)
            x[act] = c
            _illinois_update(act, a, b, fa, fb, side, A_, B_, FA, FB, c, fc)
            done = (np.abs(b[act] - a[act]) <= dx_tol) | (fc == 0.0)
            act = act[~done]
        return x

    def _bisect_kind(self, ctx, o, a, b, target, negate, iters=60):
        """Bisection of [a, b] (a < b) for where the kind of closest point (``_kind``) of the
        slave points of own index o stops being target (where ``negate``: starts being target;
        kinds may be negative, so the flag is separate): a moves to the midpoint c where the
        test holds at c, b otherwise, until b - a <= 1e-13 (at most ``iters`` steps).  Returns
        the last midpoint and the final bracket ends.

        The steps are the bisection's own, but several at once: the midpoints of the next
        levels of every problem's bisection tree (2^levels - 1 points: every bracket that
        ``levels`` steps can reach) are located in one ``_closest`` call, and the path the
        bisection takes through them is read off; levels from the number of problems
        (``BISECT_POINTS`` points per call at most)."""
        a, b = np.array(a, dtype=float), np.array(b, dtype=float)
        x = 0.5 * (a + b)
        steps = np.zeros(len(a), dtype=np.int64)
        act = np.arange(len(a))
        while act.size:
            na = len(act)
            want = int(np.ceil(np.log2(max(float(np.max(b[act] - a[act])), 1e-300) / 1e-13)))
            levels = int(max(1, min(np.log2(self.BISECT_POINTS / na + 1.0), want,
                                    iters - steps[act].min())))
            # the tree: brackets (lo, hi) of every node, level by level (node j's children:
            # 2j with a moved to its midpoint, 2j + 1 with b moved)
            los, his, mids = [a[act][:, None]], [b[act][:, None]], []
            for lev in range(levels):
                lo_, hi_ = los[lev], his[lev]
                c = 0.5 * (lo_ + hi_)
                mids.append(np.minimum(np.maximum(c, np.minimum(lo_, hi_)), np.maximum(lo_, hi_)))
                if lev + 1 < levels:
                    los.append(np.stack([mids[lev], lo_], axis=2).reshape(na, -1))
                    his.append(np.stack([hi_, mids[lev]], axis=2).reshape(na, -1))
            # the nodes bisection would visit: bracket still wider than 1e-13, steps left
            need = [np.ones((na, 1), dtype=bool)] + \
                [(his[lev] - los[lev] > 1e-13) & (steps[act] + lev < iters)[:, None]
                 for lev in range(1, levels)]
            nodes = [np.nonzero(nd) for nd in need]          # (problem, node) per level
            pr = np.concatenate([p for p, _ in nodes])
            pc = np.concatenate([mids[lev][p, j] for lev, (p, j) in enumerate(nodes)])
            hit = self._kind(ctx, self._closest(ctx, o[act][pr], pc)) == target[act][pr]
            moves_a = hit != negate[act][pr]
            outcome, k0 = [], 0
            for lev, (p, j) in enumerate(nodes):
                out_lev = np.zeros(need[lev].shape, dtype=bool)
                out_lev[p, j] = moves_a[k0:k0 + len(p)]
                outcome.append(out_lev)
                k0 += len(p)
            # follow every problem's path down its tree
            node = np.zeros(na, dtype=np.int64)
            alive = np.arange(na)
            for lev in range(levels):
                nd = node[alive]
                mid = mids[lev][alive, nd]
                left = outcome[lev][alive, nd]
                g = act[alive]
                x[g] = mid
                a[g] = np.where(left, mid, los[lev][alive, nd])
                b[g] = np.where(left, his[lev][alive, nd], mid)
                steps[g] += 1
                node[alive] = 2 * nd + ~left
                done = (b[g] - a[g] <= 1e-13) | (steps[g] >= iters)
                alive = alive[~done]
                if alive.size == 0:
                    break
            act = act[alive]
        return x, a, b

    def _kind(self, ctx, cl):
        """Canonical kind of the closest points: 2 k at master node k (an element end; both
        elements sharing the node give the same kind, so a tie between them is no change),
        2 m + 1 strictly inside element m, -2 - m on a bound inside element m (an exclusion
        boundary), -1 without a closest point.  A change of kind along s is a kink of d(s)
        (node, bound) or a jump of the closest point to another strand."""
        m = cl["m"]
        kind = self._kind_at(ctx["pool_ids"][np.maximum(m, 0)], cl["xi_m"], cl["interior"])
        return np.where(m >= 0, kind, -1)

    def _kind_at(self, e, xi, interior):
        """``_kind`` of points xi of elements e (global ids), interior: strictly inside the
        slot."""
        node = np.where(xi <= -1.0, e, e + 1)
        if self.closed:
            node = np.mod(node, self.nelem)
        return np.where(interior, 2 * e + 1, np.where(np.abs(xi) >= 1.0, 2 * node, -2 - e))

    def _split_zones(self, ctx, oz, za, zb):
        """Split the zones where the integrand has a kink or a jump, which Gauss points must not
        straddle: wherever the kind of closest point (``_kind``) changes, i.e. where it crosses
        a master node (N_m(xibar(s)) has a kink), sticks to or leaves a node (a C0 kink of the
        centreline seen from its convex side), reaches or leaves a bound (rod end, exclusion
        boundary), or jumps to another strand.  The kinds are compared between nqz + 2 points
        of each zone; between two points of different kinds a and b, bisection finds both the
        first point that is not a and the last one that is not b, so that a node the closest
        point sticks to over a short stretch gives its two cuts; where the kinds just inside
        those two cuts differ again, the stretch between them is bracketed the same way (three
        or more changes between two samples), until they agree.  Every cut is a continuous
        function of the configuration (to 1e-13 in xi), and so is the zone quadrature.

        Returns the split zones (own index, xi start, xi end) and the cuts as (own index, xi
        left, xi right, closest points left, closest points right): bracket ends 1e-13 apart
        whose closest points (``_closest``) are those of the two sides (``_cut_levels``,
        ``_switch_terms``); a direct change a -> b gives one cut, not two."""
        n = self.nqz + 2
        t = np.linspace(0.0, 1.0, n)
        Xs = za[:, None] + (zb - za)[:, None] * t[None, :]
        cl = self._closest(ctx, np.repeat(oz, n), Xs.ravel(), rival=True)
        kind = cl["kind"].reshape(-1, n)
        ki, kj = np.nonzero(kind[:, :-1] != kind[:, 1:])
        # brackets (zone, a, b, kind at a, kind at b) to resolve; the stretch between the two
        # cuts of a bracket may hold further changes (node 43 -> inside element 42 -> element
        # 55 of the plectoneme at 9.415 turns, all within one sample spacing: the middle cut was
        # missed, a Gauss point's closest point jumped by 0.22 in xi as the nodes moved by 1e-7,
        # and the residual had steps of 0.05 that no Newton step could settle): bracketed again
        # until the kinds on both inner sides agree
        bz, ba, bb = ki, Xs[ki, kj], Xs[ki, kj + 1]
        ka, kb = kind[ki, kj], kind[ki, kj + 1]
        rz, ra, rb, rka, rkb = self._rival_brackets(ctx, oz, Xs, cl, kind)
        if rz.size:
            bz, ba, bb = np.r_[bz, rz], np.r_[ba, ra], np.r_[bb, rb]
            ka, kb = np.r_[ka, rka], np.r_[kb, rkb]
        if bz.size == 0:
            return oz, za, zb, (oz[:0], za[:0], za[:0], None, None)
        zs, cs, ls, rs = [], [], [], []
        for _ in range(8):
            nk = len(bz)
            cut, left, right = self._bisect_kind(ctx, np.concatenate([oz[bz], oz[bz]]),
                                                 np.tile(ba, 2), np.tile(bb, 2),
                                                 np.concatenate([ka, kb]),
                                                 np.repeat([False, True], nk))
            two = np.abs(cut[nk:] - cut[:nk]) > 1e-12
            distinct = np.r_[np.ones(nk, dtype=bool), two]
            zs.append(np.tile(bz, 2)[distinct])
            cs.append(cut[distinct])
            ls.append(left[distinct])
            rs.append(right[distinct])
            if not np.any(two):
                break
            # the inner sides: the first point past a's cut, the last point before b's
            inner_a, inner_b = right[:nk][two], left[nk:][two]
            oi = oz[bz[two]]
            k1, k2 = np.split(self._kind(ctx, self._closest(ctx, np.r_[oi, oi],
                                                            np.r_[inner_a, inner_b])), 2)
            more = k1 != k2
            if not np.any(more):
                break
            bz, ba, bb, ka, kb = bz[two][more], inner_a[more], inner_b[more], k1[more], k2[more]
        cz, cut = np.concatenate(zs), np.concatenate(cs)
        left, right = np.concatenate(ls), np.concatenate(rs)
        if len(ctx["own_ids"]) > ctx["no"]:          # strand by strand (_context)
            srt = np.argsort(oz[cz] // ctx["no"], kind="stable")
            cz, cut, left, right = cz[srt], cut[srt], left[srt], right[srt]
        oc = oz[cz]
        both = self._closest(ctx, np.r_[oc, oc], np.r_[left, right])
        cuts = (oc, left, right) + _split_record(both, len(oc))
        level = self._cut_levels(ctx, *cuts)
        zid = np.concatenate([np.arange(len(za)), np.arange(len(za)), cz])
        pts = np.concatenate([za, zb, cut])
        lev = np.r_[np.zeros(2 * len(za), dtype=np.int64), level]
        srt = np.lexsort((pts, zid))
        zid, pts, lev = zid[srt], pts[srt], lev[srt]
        same = zid[1:] == zid[:-1]
        a, b, z = pts[:-1][same], pts[1:][same], zid[:-1][same]
        la, lb = lev[:-1][same], lev[1:][same]
        keep = b > a
        a, b, z, la, lb = a[keep], b[keep], z[keep], la[keep], lb[keep]
        a, b, z = self._grade(a, b, z, la, lb)
        return oz[z], a, b, cuts

    def _margin(self, ctx, o, cl):
        """Margin of the runner-up, m = g_rival - g >= 0, and dm/dxi along the slave (each
        distance's derivative D . r'(xi) / g: its closest point is stationary or fixed)."""
        t = np.einsum("na,nad->nd", cl["dN"], ctx["x_own"][o])
        ok = np.isfinite(cl["rival_g"]) & (cl["g"] > 0) & np.isfinite(cl["g"])
        g = np.where(ok, cl["g"], 1.0)
        gr = np.where(ok, cl["rival_g"], 1.0)
        dm = np.einsum("nd,nd->n", cl["rival_D"], t) / gr - np.einsum("nd,nd->n", cl["D"], t) / g
        return np.where(ok, gr - g, np.inf), np.where(ok, dm, 0.0)

    def _rival_brackets(self, ctx, oz, Xs, cl, kind, iters=60):
        """Stretches between two samples of the same kind where the runner-up takes over
        (``_closest`` rival): brackets (zone, a, b, kind at a, kind at b) of the changes there.
        Two nearly parallel strands in line contact have a nearly flat distance along the
        master; a C0 kink of the centreline then holds a minimum of its own next to the one
        inside the element, and the two trade places over stretches narrower than the sample
        spacing (the plectoneme at 9.72 turns: 0.002 in xi, samples 0.2 apart), so no sample
        sees the change and a Gauss point's closest point jumps from four nodes to one as the
        stretch's end crosses it (a residual step of 5.5 of 46 as a node moved by 7e-8).
        Between two samples where the margin m = g_rival - g falls and then rises (dm/dxi < 0
        at a, > 0 at b) its minimum is found (Illinois on dm/dxi); where the runner-up is the
        nearer there (the kind changes on the way, or m < 0), the stretch is bracketed on both
        sides.  A stretch is then cut from the moment it is born (m_min = 0, zero width), and
        the zone quadrature stays continuous."""
        n = Xs.shape[1]
        o = np.repeat(oz, n)
        m, dm = self._margin(ctx, o, cl)
        m, dm = m.reshape(-1, n), dm.reshape(-1, n)
        rk = cl["rival_kind"].reshape(-1, n)
        zi, j = np.nonzero((kind[:, :-1] == kind[:, 1:]) & (rk[:, :-1] == rk[:, 1:])
                           & np.isfinite(m[:, :-1]) & np.isfinite(m[:, 1:])
                           & (dm[:, :-1] < 0.0) & (dm[:, 1:] > 0.0))
        e = np.zeros(0, dtype=np.int64)
        if zi.size == 0:
            return e, np.zeros(0), np.zeros(0), e, e
        iz, xa0, xb0 = zi, Xs[zi, j], Xs[zi, j + 1]
        a, b, fa, fb = xa0.copy(), xb0.copy(), dm[zi, j].copy(), dm[zi, j + 1].copy()
        k0, r0 = kind[zi, j], rk[zi, j]
        found = np.full(len(iz), np.nan)
        found_kind = np.full(len(iz), -1, dtype=np.int64)
        side = np.zeros(len(iz), dtype=int)
        act = np.arange(len(iz))
        for _ in range(iters):
            if act.size == 0:
                break
            A_, B_, FA, FB = a[act], b[act], fa[act], fb[act]
            c = (A_ * FB - B_ * FA) / (FB - FA)
            c = np.clip(c, np.minimum(A_, B_), np.maximum(A_, B_))
            cs = self._closest(ctx, oz[iz[act]], c, rival=True)
            mc, fc = self._margin(ctx, oz[iz[act]], cs)
            other = (cs["kind"] != k0[act])
            found[act[other]] = c[other]
            found_kind[act[other]] = cs["kind"][other]
            lost = ~other & ((cs["rival_kind"] != r0[act]) | ~np.isfinite(mc))
            _illinois_update(act, a, b, fa, fb, side, A_, B_, FA, FB, c, fc)
            done = other | lost | (np.abs(b[act] - a[act]) <= 1e-13) | (fc == 0.0)
            act = act[~done]
        hit = np.flatnonzero(np.isfinite(found) & (found > xa0) & (found < xb0))
        if hit.size == 0:
            return e, np.zeros(0), np.zeros(0), e, e
        iz, xa0, xb0, k0, xs, ks = iz[hit], xa0[hit], xb0[hit], k0[hit], found[hit], found_kind[hit]
        return (np.r_[iz, iz], np.r_[xa0, xs], np.r_[xs, xb0], np.r_[k0, ks], np.r_[ks, k0])

    def _cut_levels(self, ctx, o, left, right, cla, clb):
        """Levels of geometric grading toward every cut (``_grade``): ``grade`` + 2 log2 of the
        racing rate of the closest points on either side, |dxibar/dxi| = |r'(xi) . r_m'(xibar)|
        / phi''(xibar) (phi = |r_m - r|^2 / 2; an interior closest point; 0 at a node or bound).
        Near a fold of the distance function, where the closest point on one side ceases to
        exist, phi'' ~ sqrt(distance to the fold), so the integrand's branch point lies ~
        1/rate^2 beyond the cut; each level halves the distance of the last Gauss points from
        the cut, so 2 log2(rate) levels reach the branch point and ``grade`` more resolve it.
        Measured (tangent against central differences of the residual): the noisy cubic helix
        reaches the differencing floor 9e-8 with grade >= 2 (6e-6 with 1, 1.5e-3 with the 2
        log2(rate) levels alone, > 1e-2 without grading: grade 0 turns it off); the
        plectoneme's end loop (rates up to 463) 4.5e-6 with any grade >= 0, 1.4e-4 with 10 +
        log2(rate) levels.  Cuts with rate <= 2 (node crossings: most of them) get ``grade``
        + 2 levels, not 10 + 1 as before: a contact evaluation of the end loop 1.4x faster."""
        rate = np.ones(len(o))
        for cl in (cla, clb):
            inner = cl["interior"] & (cl["m"] >= 0)
            if not np.any(inner):
                continue
            A = ctx["A_pool"][cl["m"][inner]]
            _, _, H = self._fgh(cl["xi_m"][inner], A, cl["P"][inner])
            tm = np.einsum("mk,mkd->md", _monomials(self.p, cl["xi_m"][inner])[1], A)
            ts = np.einsum("na,nad->nd", cl["dN"][inner], ctx["x_own"][o[inner]])
            r = np.abs(np.einsum("nd,nd->n", ts, tm)) / np.maximum(H, 1e-300)
            rate[inner] = np.maximum(rate[inner], r)
        extra = np.ceil(np.log2(np.minimum(rate, 2.0 ** 30)))
        return self.grade + 2 * extra.astype(np.int64) if self.grade > 0 \
            else np.zeros(len(o), np.int64)

    def _grade(self, a, b, z, la, lb):
        """Pieces [a, b] graded geometrically toward their ends that are cuts: points at
        distances l 2^-j, j = 1..la (from a) and 1..lb (from b) (l: the piece, or half of it
        when both ends are cuts; then j from 0).  Near a cut where the closest point reaches a
        node while the slave point is close to a centre of curvature of the master, the closest
        point races (dxibar/dxi ~ 100) and the integrand has a branch point just beyond the
        cut; one Gauss rule over the piece then leaves a quadrature error whose change as the
        cut moves the tangent does not see (4-9e-2 relative on a noisy cubic helix; graded with
        10 levels, 1e-5).  The points move continuously with the cuts."""
        G = int(max(la.max(initial=0), lb.max(initial=0)))
        if G == 0:
            return a, b, z
        both = (la > 0) & (lb > 0)
        base = np.where(both, 0.5, 1.0) * (b - a)
        k = np.arange(G)
        j = k + 1 - both[:, None]                                   # (n, G): from 0 if both
        frac = base[:, None] * 0.5 ** j
        extra = np.concatenate([np.where(k < la[:, None], a[:, None] + frac, np.nan),
                                np.where(k < lb[:, None], b[:, None] - frac, np.nan)], axis=1)
        ii, jj = np.nonzero(np.isfinite(extra))
        pid = np.concatenate([np.arange(len(a)), np.arange(len(a)), ii])
        pts = np.concatenate([a, b, extra[ii, jj]])
        srt = np.lexsort((pts, pid))
        pid, pts = pid[srt], pts[srt]
        same = (pid[1:] == pid[:-1]) & (pts[1:] > pts[:-1])
        return pts[:-1][same], pts[1:][same], z[pid[:-1][same]]

    def _zones(self, ctx, gap_q):
        """Contact zones {xi : d(xi) > 0} of the own elements and their Gauss points.

        Slave elements within one contact radius of touching (max over the Gauss points of
        d > -eps) are sampled at nseg equispaced xi (ends included); an interior discrete
        maximum of d above -eps is refined (root of d' by Illinois), so a zone narrower than
        the sample spacing (crossing strands) is still found; every run of points with d > 0
        becomes a zone bounded by the roots of d (Illinois) or by the element ends, split where
        the kind of closest point changes (``_split_zones``).  Each piece [a, b] gets the nqz
        Gauss points mapped onto it.  Returns (own index, xi, weight w J) of those points, the
        number of zones, and the cuts of ``_split_zones``."""
        nqc, h = self.nqc, self.h
        none = np.zeros(0, dtype=np.int64)
        empty = (none, np.zeros(0), np.zeros(0), 0, (none, np.zeros(0), np.zeros(0), None, None))
        cand = np.flatnonzero(gap_q.max(axis=1) > -self.eps)
        if cand.size == 0:
            return empty
        S = self.nseg
        xs = np.linspace(-1.0, 1.0, S)
        nc = len(cand)
        o = np.repeat(cand, S)
        xi = np.tile(xs, nc)
        cls = self._closest(ctx, o, xi)
        d = cls["d"].reshape(nc, S)
        dd = self._ddxi(ctx, o, cls).reshape(nc, S)          # d' at the samples
        # refine the discrete maxima of d within eps of contact (an end sample too: the peak
        # may lie between it and its neighbour), so that a zone between two samples is found,
        # and the discrete minima of d in contact, so that a gap between two samples in contact
        # (d dipping below 0) splits their zone
        pad = np.full((nc, 1), np.inf)
        left = np.concatenate([-pad, d[:, :-1]], axis=1)
        right = np.concatenate([d[:, 1:], -pad], axis=1)
        ismax = (d >= left) & (d >= right) & (d > -self.eps)
        left = np.concatenate([pad, d[:, :-1]], axis=1)
        right = np.concatenate([d[:, 1:], pad], axis=1)
        ismin = (d <= left) & (d <= right) & (d > 0.0) & ~ismax
        ei, jj = np.nonzero(ismax | ismin)
        xe, de = [xi.reshape(nc, S)], [d]
        if ei.size:
            om = cand[ei]
            ja, jb = np.maximum(jj - 1, 0), np.minimum(jj + 1, S - 1)
            a, b = xs[ja], xs[jb]
            fa, fb = dd[ei, ja], dd[ei, jb]
            brk = np.where(ismax[ei, jj], (fa > 0.0) & (fb < 0.0), (fa < 0.0) & (fb > 0.0))
            if np.any(brk):
                xr = self._solve1d(ctx, om[brk], a[brk], b[brk], fa[brk], fb[brk], 1)
                dr = self._closest(ctx, om[brk], xr)["d"]
                # append as extra columns, one per refined maximum (padded with -inf)
                rows = ei[brk]
                k = np.zeros(len(rows), dtype=np.int64)
                order = np.argsort(rows, kind="stable")
                rs = rows[order]
                firsts = np.r_[0, np.flatnonzero(rs[1:] != rs[:-1]) + 1]
                k[order] = np.arange(len(rs)) - np.repeat(firsts, np.diff(np.r_[firsts, len(rs)]))
                ncol = int(k.max()) + 1
                X2 = np.full((nc, ncol), 2.0)       # padding beyond the element end: ignored
                D2 = np.full((nc, ncol), -np.inf)
                X2[rows, k] = xr
                D2[rows, k] = dr
                xe.append(X2)
                de.append(D2)
        X = np.concatenate(xe, axis=1)
        D = np.concatenate(de, axis=1)
        srt = np.argsort(X, axis=1, kind="stable")
        X = np.take_along_axis(X, srt, axis=1)
        D = np.take_along_axis(D, srt, axis=1)
        inside = X <= 1.0
        pos = (D > 0.0) & inside
        if not np.any(pos):
            return empty
        prev = np.concatenate([np.zeros((nc, 1), dtype=bool), pos[:, :-1]], axis=1)
        nxt = np.concatenate([pos[:, 1:], np.zeros((nc, 1), dtype=bool)], axis=1)
        r0, c0 = np.nonzero(pos & ~prev)          # zone starts
        r1, c1 = np.nonzero(pos & ~nxt)           # zone ends (same row order: row-major)
        za = X[r0, c0].copy()
        zb = X[r1, c1].copy()
        # roots of d between a start and the point before it (xi = -1 has no point before),
        # and between an end and the point after it, in one solve
        at_start = c0 > 0
        at_end = (c1 + 1 < X.shape[1])
        at_end[at_end] = X[r1[at_end], c1[at_end] + 1] <= 1.0
        if np.any(at_start) or np.any(at_end):
            ra, ca, rb, cb = r0[at_start], c0[at_start], r1[at_end], c1[at_end]
            root = self._solve1d(ctx, cand[np.r_[ra, rb]], np.r_[X[ra, ca - 1], X[rb, cb]],
                                 np.r_[X[ra, ca], X[rb, cb + 1]], np.r_[D[ra, ca - 1], D[rb, cb]],
                                 np.r_[D[ra, ca], D[rb, cb + 1]], 0)
            za[at_start], zb[at_end] = root[:len(ra)], root[len(ra):]
        nz = len(za)
        oz, za, zb, cuts = self._split_zones(ctx, cand[r0], za, zb)
        oz = np.repeat(oz, self.nqz)
        mid, half = 0.5 * (za + zb), 0.5 * (zb - za)
        xq = (mid[:, None] + half[:, None] * self.xz[None, :]).ravel()
        wq = (half[:, None] * self.wz[None, :] * (0.5 * h)).ravel()
        return oz, xq, wq, nz, cuts

    def _switch_terms(self, ctx, o, left, right, cla, clb, tangent, out):
        """Tangent of the switch points (module docstring, "Switch points"): at a cut c where
        the closest point jumps from (element A, xi_A) on the left to (B, xi_B) on the right,

            K_sw = J mu d phi_x phi_x^T / phi_xi,     phi = g_A - g_B  (phi(c) = 0),

            phi_xi = (nu_A - nu_B) . dr/dxi (c),   phi_x = [ N(c) (nu_A - nu_B) (slave nodes),
                                                            -N_A(xi_A) nu_A,  N_B(xi_B) nu_B ]

        over the nodes [slave element, A, B].  Cuts where the closest point moves continuously
        (a node crossed or stuck to, a bound reached) add nothing: there r_A = r_B.  Fills
        ``out["switch"]`` (nsw, 3) element ids and, with ``tangent``, ``out["switch_mat"]``.
        cla, clb: the closest points at left and right (``_split_zones``)."""
        if not tangent or len(o) == 0:
            return
        qa, qb = cla["P"] - cla["D"], clb["P"] - clb["D"]
        d = 2.0 * self.eps - 0.5 * (cla["g"] + clb["g"])
        jump = (cla["m"] >= 0) & (clb["m"] >= 0) & (d > 0.0) & \
            (np.linalg.norm(qa - qb, axis=1) > 1e-5 * self.eps)
        if not np.any(jump):
            return
        o, d = o[jump], d[jump]
        cla = {k: v[jump] for k, v in cla.items()}
        clb = {k: v[jump] for k, v in clb.items()}
        nua = cla["D"] / cla["g"][:, None]
        nub = clb["D"] / clb["g"][:, None]
        xc = 0.5 * (left[jump] + right[jump])
        Ns, dNs, _ = (mm @ self.C for mm in _monomials(self.p, xc))
        t = np.einsum("na,nad->nd", dNs, ctx["x_own"][o])
        dnu = nua - nub
        phi_xi = np.einsum("nd,nd->n", dnu, t)
        # phi_xi > 0: A is closer on the left; a tangential switch (phi_xi ~ 0) is skipped
        ok = phi_xi > 1e-8 * np.linalg.norm(t, axis=1) * np.linalg.norm(dnu, axis=1)
        if not np.any(ok):
            return
        Na = _monomials(self.p, cla["xi_m"][ok])[0] @ self.C
        Nb = _monomials(self.p, clb["xi_m"][ok])[0] @ self.C
        phi_x = np.concatenate([Ns[ok][:, :, None] * dnu[ok][:, None, :],
                                -Na[:, :, None] * nua[ok][:, None, :],
                                Nb[:, :, None] * nub[ok][:, None, :]], axis=1).reshape(len(Na), -1)
        fac = 0.5 * self.h * self.mu * d[ok] / phi_xi[ok]
        out["switch"] = np.stack([ctx["own_ids"][o[ok]], ctx["pool_ids"][cla["m"][ok]],
                                  ctx["pool_ids"][clb["m"][ok]]], axis=1)
        out["switch_mat"] = fac[:, None, None] * phi_x[:, :, None] * phi_x[:, None, :]

    def _terms(self, ctx, o, xi, wJ, qp, cl, tangent, out):
        """Energy, residual and tangent of the slave points (o, xi) with weights w J
        (module docstring, "Formulas used"); fills ``out``."""
        mu = self.mu
        d = cl["d"]
        dpos = np.maximum(d, 0.0)
        out["energy"] = float(0.5 * mu * np.sum(wJ * dpos ** 2))
        out["total_force"] = float(mu * np.sum(wJ * dpos))
        out["complementarity"] = float(mu * np.sum(wJ * dpos ** 2))
        a = self._active(cl, wJ)
        if a is None:
            return
        act, m, xm, d, nu, Nt = a["act"], a["m"], a["xm"], a["d"], a["nu"], a["Nt"]
        cw = a["cw"]
        out["active"] = np.stack([ctx["own_ids"][o[act]], ctx["pool_ids"][m]], axis=1)
        out["vec"] = -(cw * d)[:, None, None] * Nt[:, :, None] * nu[:, None, :]
        out["qp"], out["xi"], out["xi_slave"] = qp[act], xm, xi[act]
        out["d_active"] = d
        out["normal"], out["interior"] = nu, a["interior"]
        if tangent:
            out["mat"] = self._terms_tangent(ctx, wJ, cl)

    def _active(self, cl, wJ):
        """The slave points of the closest-point record cl in contact (d > 0): their mask act,
        master m and xi_m, depth d, offset D, distance g (floored), normal nu, shape functions
        N_s, N_m and Nt = (N_s, -N_m), weights w J mu, interior flags; None when none is."""
        act = cl["d"] > 0.0
        if not np.any(act):
            return None
        xm, g = cl["xi_m"][act], cl["g"][act]
        gs = np.maximum(g, 1e-300)
        Dv = cl["D"][act]
        Ns, Nm = cl["N"][act], _monomials(self.p, xm)[0] @ self.C
        return {"act": act, "m": cl["m"][act], "xm": xm, "d": cl["d"][act], "Dv": Dv, "gs": gs,
                "nu": Dv / gs[:, None], "Ns": Ns, "Nm": Nm,
                "Nt": np.concatenate([Ns, -Nm], axis=1),                 # (nact, 2(p+1))
                "cw": wJ[act] * self.mu, "interior": cl["interior"][act]}

    def _terms_tangent(self, ctx, wJ, cl):
        """d2E_c/dx2 (nact, 6(p+1), 6(p+1)) of the slave points in contact (d > 0) of the
        closest-point record cl with weights w J, in the row order of ``_terms`` (module
        docstring, "Formulas used")."""
        p, eps = self.p, self.eps
        n1 = p + 1
        a = self._active(cl, wJ)
        if a is None:
            return np.zeros((0, 6 * n1, 6 * n1))
        m, d, Dv, gs, nu = a["m"], a["d"], a["Dv"], a["gs"], a["nu"]
        Ns, Nm, Nt, cw, interior = a["Ns"], a["Nm"], a["Nt"], a["cw"], a["interior"]
        _, dNm, d2Nm = (mm @ self.C for mm in _monomials(p, a["xm"]))
        xmn = ctx["pool_x"][m]
        nact = len(d)
        A3 = (2.0 * eps / gs)[:, None, None] * nu[:, :, None] * nu[:, None, :] \
            - (d / gs)[:, None, None] * np.eye(3)[None]
        K = np.einsum("na,nb,nij->naibj", Nt, Nt, A3 * cw[:, None, None], optimize=True)
        t = np.einsum("na,nad->nd", dNm, xmn)
        r2 = np.einsum("na,nad->nd", d2Nm, xmn)
        k = np.einsum("nd,nd->n", t, t) - np.einsum("nd,nd->n", Dv, r2)
        use = interior & (k > 0.0)
        if np.any(use):
            c = np.concatenate([-Ns[:, :, None] * t[:, None, :],
                                Nm[:, :, None] * t[:, None, :] - dNm[:, :, None] * Dv[:, None, :]],
                               axis=1)                           # (nact, 2(p+1), 3)
            fac = np.where(use, cw * d / (gs * np.where(use, k, 1.0)), 0.0)
            K += fac[:, None, None, None, None] * c[:, :, :, None, None] * c[:, None, None, :, :]
        return K.reshape(nact, 6 * n1, 6 * n1)


def _lookup(ids, query, what):
    """Positions of ``query`` in the sorted-or-not unique array ``ids`` (KeyError if missing)."""
    sorter = np.argsort(ids, kind="stable")
    pos = np.searchsorted(ids, query, sorter=sorter)
    pos = np.clip(pos, 0, len(ids) - 1)
    idx = sorter[pos]
    if len(query) and not np.all(ids[idx] == query):
        missing = np.unique(query[ids[idx] != query])
        raise KeyError(f"contact pairs reference {what} elements not supplied: {missing[:10]}")
    return idx
