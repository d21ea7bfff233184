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
the slot; backtracking on phi), vectorised over all (slave point, candidate, slot, start).  The
global minimum over candidates is kept; a closest point shared by two elements (a node) is thus
counted once.  Before projecting, slots are pruned exactly: a slot whose element's bounding
sphere is farther from the slave point than an admissible slot end of another candidate cannot
hold the minimum.  Cost: O(#pairs * nqc) vectorised work, no Python loop over elements or points.

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

Sign conventions of the outputs: ``vec`` is dE_c/dx (the residual, i.e. minus the contact force on
the nodes); the caller adds both the slave and the master block (node ids may repeat when the two
elements share a node or coincide).
"""
import numpy as np
from scipy.spatial import cKDTree

from . import fe

__all__ = ["default_exclusion", "default_penalty", "element_bounds", "candidate_pairs",
           "element_node_ids", "max_arclength_distance", "ContactKernel"]


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
    """mu = EI / (4 * penetration * eps^4) = 25 EI / eps^4 for 1 % penetration of the diameter 2 eps.

    Typical tight-contact line force: m' + r' x n = 0 gives |n_perp| ~ |m'| and the line force
    balances the shear-force gradient, f = |n'| ~ |m''| = EI |kappa''|.  In a tight contact
    (plectoneme strands, a loop pulled tight, a rod wrapped on itself) the curvature changes by
    O(1/eps) over an arclength O(eps) (a contact zone is not shorter than the exclusion length
    pi eps), so f ~ EI / eps^3.
    Penalty law: the slave point s carries f_c = mu <d>, and, E_c being an integral over all of
    [0, L], the strand it touches is itself slave of s's strand with the same penetration; so each
    strand of a two-sided contact receives a line force 2 mu d (checked in the tests on two
    parallel segments).  Asking f = 2 mu d with d = penetration * 2 eps gives
    mu = EI / (4 penetration eps^4).  The contact stiffness per unit length, 2 mu = 50 EI/eps^4,
    is 50x the bending stiffness EI/eps^4 of a rod piece of length eps: stiff enough to be
    accurate, soft enough for well-conditioned Newton systems.  This is an order-of-magnitude
    estimate: long, gently loaded contacts (f << EI/eps^3) penetrate less, very tight knots more.
    """
    return float(EI) / (4.0 * float(penetration) * float(eps) ** 4)


# --------------------------------------------------------------------------------------------
# geometry helpers
# --------------------------------------------------------------------------------------------
_NSAMP_BOUNDS = 65
_LAMBDA2 = {}
_NS_BOUNDS = {}


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
    covering the overshoot of p >= 2 curves beyond their nodes).
    """
    x = np.asarray(x_elem, dtype=float)
    ne, n1, _ = x.shape
    p = n1 - 1
    if ne == 0:
        return np.zeros((0, 3)), np.zeros(0)
    if p not in _NS_BOUNDS:
        _NS_BOUNDS[p] = fe.lagrange(p, np.linspace(-1.0, 1.0, _NSAMP_BOUNDS))[0]
    Ns = _NS_BOUNDS[p]
    pts = np.einsum("ma,ead->emd", Ns, x)
    c = 0.5 * (pts.min(axis=1) + pts.max(axis=1))
    rs = np.linalg.norm(pts - c[:, None, :], axis=2).max(axis=1)
    spread = np.linalg.norm(x - c[:, None, :], axis=2).max(axis=1)
    dxi = 2.0 / (_NSAMP_BOUNDS - 1)
    pad = (dxi ** 2 / 8.0) * 1.05 * _lambda2(p) * spread if p >= 2 else 0.0
    R = rs + pad + 1e-12 * (spread + np.abs(c).max(axis=1))
    return c, R


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

    Kept iff |c_own - c_other| <= reach + R_own + R_other (bounding spheres, ``element_bounds``)
    and some sigma in e_other is admissible for some s in e_own, i.e. the maximal (periodic)
    arclength distance between the two elements is >= delta (so e_other == e_own survives only
    when the element is longer than the exclusion, h >= delta).  reach should be 2 eps + a margin
    (for a contact at distance < 2 eps the two centrelines are within 2 eps).  Search: one
    cKDTree over all_centers, query_ball_point with radius reach + R_own + max(all_radii), then the
    exact sphere test: O(N log N + pairs).  Returns int64 (npair, 2) of global ids, sorted.
    """
    own_ids = np.asarray(own_ids, dtype=np.int64)
    all_ids = np.asarray(all_ids, dtype=np.int64)
    if len(own_ids) == 0 or len(all_ids) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    oc = np.asarray(own_centers, dtype=float).reshape(-1, 3)
    orad = np.asarray(own_radii, dtype=float).ravel()
    ac = np.asarray(all_centers, dtype=float).reshape(-1, 3)
    arad = np.asarray(all_radii, dtype=float).ravel()
    tree = cKDTree(ac)
    lists = tree.query_ball_point(oc, reach + orad + arad.max())
    counts = np.fromiter((len(l) for l in lists), dtype=np.int64, count=len(lists))
    if counts.sum() == 0:
        return np.zeros((0, 2), dtype=np.int64)
    io = np.repeat(np.arange(len(own_ids)), counts)
    ia = np.fromiter((j for l in lists for j in l), dtype=np.int64, count=int(counts.sum()))
    dist = np.linalg.norm(oc[io] - ac[ia], axis=1)
    keep = dist <= reach + orad[io] + arad[ia]
    io, ia = io[keep], ia[keep]
    ea, eb = own_ids[io], all_ids[ia]
    keep = max_arclength_distance(ea, eb, L, h, closed) >= delta
    out = np.stack([ea[keep], eb[keep]], axis=1)
    if len(out):
        out = np.unique(out, axis=0)
    return out.astype(np.int64)


def _monomial_matrix(order):
    """C (p+1, p+1) with N_a(xi) = sum_k C[k, a] xi^k."""
    nodes = fe.reference_nodes(order)
    V = nodes[:, None] ** np.arange(order + 1)[None, :]
    return np.linalg.inv(V)


def _monomials(order, xi):
    """xi^k, d/dxi xi^k, d2/dxi2 xi^k for k = 0..p: three (len(xi), p+1) arrays."""
    xi = np.asarray(xi, dtype=float)
    k = np.arange(order + 1)
    pw = np.empty((len(xi), order + 1))
    pw[:, 0] = 1.0
    for j in range(1, order + 1):
        pw[:, j] = pw[:, j - 1] * xi
    pw1 = np.zeros_like(pw)
    pw1[:, 1:] = k[1:] * pw[:, :-1]
    pw2 = np.zeros_like(pw)
    pw2[:, 2:] = (k[2:] * (k[2:] - 1)) * pw[:, :-2]
    return pw, pw1, pw2


# --------------------------------------------------------------------------------------------
# the kernel
# --------------------------------------------------------------------------------------------
class ContactKernel:
    """Penalty self-contact term evaluated over a set of own (slave) elements."""

    MAXIT = 60          # Newton iterations of the projection
    MAXBT = 40          # backtracking halvings
    CHUNK = 16384       # projection problems per vectorised batch

    def __init__(self, order, nqc, eps, mu, delta, L, nelem, closed):
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
        h, L, dl = self.h, self.L, self.delta
        u = np.asarray(s, dtype=float) - np.asarray(m, dtype=float) * h  # slave, element-local
        if not self.closed:
            lo = np.stack([np.zeros_like(u), np.maximum(0.0, u + dl)], axis=1)
            hi = np.stack([np.minimum(h, u - dl), np.full_like(u, h)], axis=1)
            valid = np.stack([u - dl >= 0.0, u + dl <= h], axis=1)
        else:
            lad = L - 2.0 * dl
            a0 = np.mod(u + dl, L)
            starts = np.stack([a0, a0 - L], axis=1)
            lo = np.maximum(starts, 0.0)
            hi = np.minimum(starts + lad, h)
            valid = (hi >= lo) & (lad >= 0.0)
        valid &= hi >= lo
        to_xi = lambda t: np.clip(2.0 * t / h - 1.0, -1.0, 1.0)
        return to_xi(lo), to_xi(hi), valid

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
            xi_out[sl], f_out[sl] = self._project_chunk(P[sl], A[sl], lo[sl], hi[sl])
        return xi_out, f_out

    def _project_chunk(self, P, A, lo, hi):
        M = len(P)
        ns = self.nsamp
        tt = np.linspace(0.0, 1.0, ns)
        X = lo[:, None] + (hi - lo)[:, None] * tt[None, :]
        D = np.repeat(A[:, self.p][:, None, :], ns, axis=1)          # Horner
        for j in range(self.p - 1, -1, -1):
            D = D * X[:, :, None] + A[:, j][:, None, :]
        D -= P[:, None, :]
        F = 0.5 * np.einsum("msd,msd->ms", D, D)
        left = np.concatenate([np.full((M, 1), np.inf), F[:, :-1]], axis=1)
        right = np.concatenate([F[:, 1:], np.full((M, 1), np.inf)], axis=1)
        ismin = (F <= left) & (F <= right)
        # plateaus (e.g. degenerate slot hi == lo): keep only the first sample of a run
        ismin[:, 1:] &= ~(ismin[:, :-1] & (F[:, 1:] == F[:, :-1]))
        pid, sid = np.nonzero(ismin)
        x = X[pid, sid].copy()
        fx = F[pid, sid].copy()
        Ap, Pp, lop, hip = A[pid], P[pid], lo[pid], hi[pid]
        dx = (hip - lop) / (ns - 1)
        scale = np.einsum("md,md->m", Pp, Pp) + np.einsum("mkd,mkd->m", Ap, Ap)
        act = np.arange(len(x))
        for _ in range(self.MAXIT):
            if act.size == 0:
                break
            xa, Aa, Pa = x[act], Ap[act], Pp[act]
            f0, g, H = self._fgh(xa, Aa, Pa)
            newton = H > 0.0
            step = np.where(newton, -g / np.where(newton, H, 1.0), -np.sign(g) * dx[act])
            step = np.clip(step, -dx[act], dx[act])
            xnew = xa.copy()
            fnew = f0.copy()
            done = np.zeros(len(act), dtype=bool)   # accepted a step (or gave up)
            tol = 1e-14 * f0 + 1e-30 * scale[act]
            pend = np.arange(len(act))
            for _bt in range(self.MAXBT):
                xt = np.clip(xa[pend] + step[pend], lop[act][pend], hip[act][pend])
                ft = self._f(xt, Aa[pend], Pa[pend])
                ok = (ft <= f0[pend] + tol[pend]) | (newton[pend] & (np.abs(step[pend]) < 1e-9))
                acc = pend[ok]
                xnew[acc] = xt[ok]
                fnew[acc] = ft[ok]
                done[acc] = True
                pend = pend[~ok]
                if pend.size == 0:
                    break
                step[pend] *= 0.5
            moved = np.abs(xnew - xa)
            x[act] = xnew
            fx[act] = fnew
            conv = (moved <= 1e-13) | ~done
            act = act[~conv]
        # best start per problem
        order = np.lexsort((fx, pid))
        first = np.ones(len(order), dtype=bool)
        first[1:] = pid[order][1:] != pid[order][:-1]
        best = order[first]
        xi_out = np.empty(M)
        f_out = np.full(M, np.inf)
        xi_out[pid[best]] = x[best]
        f_out[pid[best]] = fx[best]
        return xi_out, f_out

    # -- main entry ---------------------------------------------------------------------------
    def evaluate(self, own_ids, x_own, other_ids, x_other, pairs, tangent=True):
        """Gap, energy, residual and tangent of the contact term over the own elements.

        own_ids (no,) global element ids; x_own (no, p+1, 3) their nodal positions;
        other_ids (nt,), x_other (nt, p+1, 3): elements that may hold closest points (own
        elements may be repeated here; missing ids are looked up among the own elements);
        pairs (npair, 2) global ids (e_own, e_other) from ``candidate_pairs``.

        Returns a dict:
          energy  float  sum_{own e, q} w_q J (mu/2) <d>^2
          gap     (no, nqc)  d = 2 eps - (distance to the closest admissible point on the
                  candidate elements); -inf where the point has no candidate (then the true gap is
                  < 2 eps - reach).  Exact wherever d >= 2 eps - reach.
          force   (no, nqc)  f_c = mu <d> (the slave side only: in a two-sided contact,
                  where the master strand is slave in turn, each strand gets 2 mu d)
          sbar    (no, nqc)  arclength of the closest point (NaN where none)
          active  (nact, 2)  (own element id, element id holding the closest point), d > 0
          vec     (nact, 2(p+1), 3)  dE_c/dx for the nodes of [own element, closest element]
          mat     (nact, 6(p+1), 6(p+1))  d2E_c/dx2, index 3a+i (None if not tangent)
          qp      (nact,) Gauss index of the slave point; xi (nact,) master xi;
          normal  (nact, 3) nu; interior (nact,) bool (closest point strictly inside its slot)
        """
        p, nqc, h, eps, mu = self.p, self.nqc, self.h, self.eps, self.mu
        n1 = p + 1
        own_ids = np.asarray(own_ids, dtype=np.int64).ravel()
        x_own = np.asarray(x_own, dtype=float).reshape(len(own_ids), n1, 3)
        other_ids = np.asarray(other_ids, dtype=np.int64).ravel()
        x_other = np.asarray(x_other, dtype=float).reshape(len(other_ids), n1, 3)
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        no = len(own_ids)

        rs = np.einsum("qa,oad->oqd", self.Nq, x_own)           # slave points (no, nqc, 3)
        s_q = self.slave_arclength(own_ids)
        gap = np.full((no, nqc), -np.inf)
        sbar = np.full((no, nqc), np.nan)
        out = {"energy": 0.0, "gap": gap, "force": np.zeros((no, nqc)), "sbar": sbar,
               "active": np.zeros((0, 2), dtype=np.int64), "vec": np.zeros((0, 2 * n1, 3)),
               "mat": np.zeros((0, 6 * n1, 6 * n1)) if tangent else None,
               "qp": np.zeros(0, dtype=np.int64), "xi": np.zeros(0),
               "normal": np.zeros((0, 3)), "interior": np.zeros(0, dtype=bool)}
        if no == 0 or len(pairs) == 0:
            return out

        # pool of master elements: other first, then own (first occurrence wins)
        pool_ids = np.concatenate([other_ids, own_ids])
        pool_x = np.concatenate([x_other, x_own], axis=0)
        pool_ids, first = np.unique(pool_ids, return_index=True)
        pool_x = pool_x[first]
        oi = _lookup(own_ids, pairs[:, 0], "own")
        mi = _lookup(pool_ids, pairs[:, 1], "other")
        A_pool = np.einsum("ka,ead->ekd", self.C, pool_x)      # monomial coefficients

        # problems: (pair, q, slot)
        npair = len(pairs)
        P_o = np.repeat(oi, nqc)                                # (npair*nqc,)
        P_q = np.tile(np.arange(nqc), npair)
        P_m = np.repeat(mi, nqc)
        lo, hi, valid = self.admissible_slots(s_q[P_o, P_q], pool_ids[P_m])
        sel_pq, sel_slot = np.nonzero(valid)
        if sel_pq.size == 0:
            return out
        pr_o, pr_q, pr_m = P_o[sel_pq], P_q[sel_pq], P_m[sel_pq]
        pr_lo, pr_hi = lo[sel_pq, sel_slot], hi[sel_pq, sel_slot]
        pt = pr_o * nqc + pr_q

        # prune (exactly): a slot whose element's bounding sphere is farther from the slave point
        # than some admissible point (a slot end) of another slot cannot hold the minimum
        P = rs[pr_o, pr_q]
        cen, rad = element_bounds(pool_x)
        lb = np.linalg.norm(P - cen[pr_m], axis=1) - rad[pr_m]
        kk = np.arange(p + 1)
        ub = np.minimum(
            np.linalg.norm(np.einsum("mk,mkd->md", pr_lo[:, None] ** kk, A_pool[pr_m]) - P, axis=1),
            np.linalg.norm(np.einsum("mk,mkd->md", pr_hi[:, None] ** kk, A_pool[pr_m]) - P, axis=1))
        best_ub = np.full(no * nqc, np.inf)
        np.minimum.at(best_ub, pt, ub)
        keep = lb <= best_ub[pt] * (1.0 + 1e-9) + 1e-300
        pr_o, pr_q, pr_m, pr_lo, pr_hi, pt = (a[keep] for a in (pr_o, pr_q, pr_m, pr_lo, pr_hi, pt))
        xi, f = self.project(P[keep], A_pool[pr_m], pr_lo, pr_hi)

        # global minimum per slave point (ties, e.g. a shared node: the first one only)
        order = np.lexsort((f, pt))
        keep = np.ones(len(order), dtype=bool)
        keep[1:] = pt[order][1:] != pt[order][:-1]
        best = order[keep]
        b_o, b_q, b_m, b_xi = pr_o[best], pr_q[best], pr_m[best], xi[best]
        b_int = (b_xi > pr_lo[best]) & (b_xi < pr_hi[best])

        Nm, dNm, d2Nm = (m @ self.C for m in _monomials(p, b_xi))   # = fe.lagrange(p, b_xi)
        xm = pool_x[b_m]
        r_m = np.einsum("na,nad->nd", Nm, xm)
        Dv = rs[b_o, b_q] - r_m
        g = np.linalg.norm(Dv, axis=1)
        d = 2.0 * eps - g
        gap[b_o, b_q] = d
        sbar[b_o, b_q] = pool_ids[b_m] * h + (b_xi + 1.0) * 0.5 * h
        dpos = np.maximum(gap, 0.0)
        out["force"] = mu * dpos
        wJ = self.wq * (0.5 * h)
        out["energy"] = float(0.5 * mu * np.sum(wJ[None, :] * dpos ** 2))

        act = d > 0.0
        if not np.any(act):
            return out
        a_o, a_q, a_m, a_xi = b_o[act], b_q[act], b_m[act], b_xi[act]
        Dv, g, d = Dv[act], g[act], d[act]
        Nm, dNm, d2Nm, xm = Nm[act], dNm[act], d2Nm[act], xm[act]
        interior = b_int[act]
        gs = np.maximum(g, 1e-300)
        nu = Dv / gs[:, None]
        Nt = np.concatenate([self.Nq[a_q], -Nm], axis=1)           # (nact, 2(p+1))
        cw = wJ[a_q] * mu                                           # w J mu
        out["active"] = np.stack([own_ids[a_o], pool_ids[a_m]], axis=1)
        out["vec"] = -(cw * d)[:, None, None] * Nt[:, :, None] * nu[:, None, :]
        out["qp"], out["xi"], out["normal"], out["interior"] = a_q, a_xi, nu, interior
        if tangent:
            nact = len(d)
            A3 = (2.0 * eps / gs)[:, None, None] * nu[:, :, None] * nu[:, None, :] \
                - (d / gs)[:, None, None] * np.eye(3)[None]
            K = np.einsum("na,nb,nij->naibj", Nt, Nt, A3 * cw[:, None, None])
            t = np.einsum("na,nad->nd", dNm, xm)
            r2 = np.einsum("na,nad->nd", d2Nm, xm)
            k = np.einsum("nd,nd->n", t, t) - np.einsum("nd,nd->n", Dv, r2)
            use = interior & (k > 0.0)
            if np.any(use):
                c = np.concatenate([-self.Nq[a_q][:, :, None] * t[:, None, :],
                                    Nm[:, :, None] * t[:, None, :] - dNm[:, :, None] * Dv[:, None, :]],
                                   axis=1)                           # (nact, 2(p+1), 3)
                fac = np.where(use, cw * d / (gs * np.where(use, k, 1.0)), 0.0)
                K += fac[:, None, None, None, None] * c[:, :, :, None, None] * c[:, None, None, :, :]
            out["mat"] = K.reshape(nact, 6 * n1, 6 * n1)
        return out


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
