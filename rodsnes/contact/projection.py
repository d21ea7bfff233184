"""Frictionless self-contact of a rod, law 1: the closest-point penalty law (pure numpy; no MPI,
no PETSc).

Model (Moakher, Chamekh & Mani-Aouadi, "Mathematical and numerical treatments of elastic rods
with frictionless self contact", slides "Gap function", "Closest point", "Penalized energy"):

    d(s)  = 2 eps - min_{sigma in I(s)} |r(s) - r(sigma)|                 (gap, > 0 = penetration)
    I(s)  = { sigma in [0, L] : dist(s, sigma) >= delta }                  (exclusion set)
    E_c   = (mu/2) int_0^L <d(s)>^2 ds,     <x> = max(x, 0)                (penalty energy)
    f_c   = mu <d(s)> nu(s),  nu = (r(s) - r(sbar)) / |r(s) - r(sbar)|     (slave line force)

Discretisation.  Lagrange elements of order p (rodsnes.model.fe): element e spans s in [e h,
(e+1) h], h = L / nelem, s = e h + (xi + 1) h / 2, with nodes x_e (p+1, 3).  The slave points
are the nqc Gauss points (xi_q, w_q) of the caller's own elements, so

    E_c ~= sum_{own e} sum_q  w_q J (mu/2) <d(s_eq)>^2,        J = h / 2,

or, with ``segments`` (the default of -contact), the Gauss points of the contact zones
(contact/zones.py, ``ContactZones``).  The pieces of the method live in their own modules:

    contact/search.py         candidate pairs (bounding spheres, capsules), strands
    contact/closest_point.py  the closest admissible point sbar (``ClosestPoint``)
    contact/zones.py          the contact zones and their cuts (``ContactZones``)
    contact/monomials.py      the Lagrange elements in monomial form

and ``ContactKernel`` here is the law: energy, residual, tangent and report of the slave points,
summed over the strands in reach.  An evaluation is a sequence of closest-point searches
(report points, zone samples, the steps of the zones' root findings and bisections); since each
costs about the same whatever its number of points, every search serves as many points as it
can: all strands at once (``evaluate``).

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

Switch points.  Where the closest point jumps from (A, xi_A) to (B, xi_B) at a cut c of the
zones (to another strand, or across a node seen from its concave side), g_A(c) = g_B(c), so
energy and residual stay continuous, but the integrand of the residual differs on the two sides
and c moves with the nodes: d/dx int r = ... + J (r_A(c) - r_B(c)) dc/dx, with r = -mu d g_x
per unit xi and dc/dx = -phi_x / phi_xi, phi = g_A - g_B (``_switch_terms``):

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

from rodsnes.profiling import logged
from rodsnes.model import fe
from rodsnes.contact.closest_point import ClosestPoint, master_pool
from rodsnes.contact.monomials import monomials
from rodsnes.contact.search import strand_index
from rodsnes.contact.zones import ContactZones

__all__ = ["default_exclusion", "default_penalty", "ContactKernel"]


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
# the law
# --------------------------------------------------------------------------------------------
class ContactKernel:
    """Penalty self-contact term evaluated over a set of own (slave) elements."""

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
        self.closest_point = ClosestPoint(order, eps, delta, L, nelem, closed)
        self.C = self.closest_point.C
        # contact-zone integration (contact/zones.py) instead of the nqc Gauss points
        self.segments = bool(segments)
        self.zones = ContactZones(self.closest_point, self.nqc)

    # -- arclength ------------------------------------------------------------------------
    def slave_arclength(self, own_ids):
        """(no, nqc) arclength of the slave Gauss points."""
        own_ids = np.asarray(own_ids, dtype=float)
        return own_ids[:, None] * self.h + (self.xq[None, :] + 1.0) * (0.5 * self.h)

    # -- main entry ---------------------------------------------------------------------------
    @logged("ContactEval")
    def evaluate(self, own_ids, x_own, other_ids, x_other, pairs, tangent=True, report=True):
        """The contact term of every strand in reach, summed:

            E_c = (mu/2) sum_k int <d_k(s)>^2 ds,   d_k(s) = 2 eps - min_{sigma in I(s) cap S_k(s)} |r(s) - r(sigma)|

        S_k(s): the k-th run of consecutive candidate elements of the slave element of s
        (``search.strand_index``), i.e. the k-th strand that passes within reach.  Where one strand is
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
        """``depth`` (the deepest d of the Gauss and zone points: the law's own, which the
        step limits watch; the rod's ends, end_depth, are the report's) and ``reported`` of an
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
        pairs (npair, 2) global ids (e_own, e_other) from ``search.candidate_pairs``.

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
        k no + e (strand k of own element e; ``ClosestPoint.context``)."""
        nqc, h = self.nqc, self.h
        own_ids, x_own, other_ids, x_other, pairs = self.as_inputs(own_ids, x_own, other_ids,
                                                                    x_other, pairs)
        no = len(own_ids)
        out = self.empty_output(no, tangent)
        if not tangent:
            out["_deferred"] = []
        if no == 0 or len(pairs) == 0:
            return self._depth(out)
        ctx = self.closest_point.context(own_ids, x_own, other_ids, x_other, pairs, strand, nk)
        nv = no * nk

        # the Gauss points: reported gap and force, and the quadrature unless segments; the
        # ends of an open rod, reported
        cl, gap, sbar = self.report_points(ctx, nv)
        out["end_depth"] = self.end_depth(ctx)
        out["gap"], out["sbar"], out["force"] = self._merge_strands(gap, sbar, no, nk)
        cuts = None
        if self.segments:
            o_q, xi_q, w_q, nz, cuts = self.zones.quadrature(ctx, gap)
            cl = self.closest_point.find(ctx, o_q, xi_q)
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

    def end_depth(self, ctx):
        """The deepest d = 2 eps - distance at the ends of an open rod (s = 0 and s = L) that
        the own elements (virtual: every strand in reach) hold; -inf for none here, or a ring.
        The report's Gauss points start at xi_1 of the first element and end at xi_nqc of the
        last: the clamped end of a short plectoneme pressed 1.15 % of the diameter into a loop
        while the report, at its first point 0.4 mm on, said 0.89 %, and the penalty's
        promise (-contact_penetration 1 %) was not kept."""
        if self.closed:
            return -np.inf
        ids = ctx["own_ids"]
        first = np.flatnonzero(ids == 0)
        last = np.flatnonzero(ids == self.nelem - 1)
        if not len(first) and not len(last):
            return -np.inf
        o = np.concatenate([first, last])
        xi = np.concatenate([np.full(len(first), -1.0), np.full(len(last), 1.0)])
        return float(self.closest_point.find(ctx, o, xi)["d"].max())

    def report_points(self, ctx, no):
        """The closest point of the nqc Gauss points of the ``no`` own elements: the
        ``ClosestPoint.find`` record, gap d (no, nqc) and sbar (no, nqc), the arclength of the closest
        point (NaN without one)."""
        nqc, h = self.nqc, self.h
        cl = self.closest_point.find(ctx, np.repeat(np.arange(no), nqc), np.tile(self.xq, no))
        has = cl["m"] >= 0
        sb = np.full(len(has), np.nan)
        sb[has] = ctx["pool_ids"][cl["m"][has]] * h + (cl["xi_m"][has] + 1.0) * 0.5 * h
        return cl, cl["d"].reshape(no, nqc), sb.reshape(no, nqc)

    master_pool = staticmethod(master_pool)      # the elements that may hold a master point

    def _context(self, own_ids, x_own, other_ids, x_other, pairs, strand=None, nk=1):
        """``ClosestPoint.context`` (contact/potential.py's PotentialKernel calls it here)."""
        return self.closest_point.context(own_ids, x_own, other_ids, x_other, pairs, strand, nk)

    def _switch_terms(self, ctx, o, left, right, cla, clb, tangent, out):
        """Tangent of the switch points (module docstring, "Switch points"): at a cut c where
        the closest point jumps from (element A, xi_A) on the left to (B, xi_B) on the right,

            K_sw = J mu d phi_x phi_x^T / phi_xi,     phi = g_A - g_B  (phi(c) = 0),

            phi_xi = (nu_A - nu_B) . dr/dxi (c),   phi_x = [ N(c) (nu_A - nu_B) (slave nodes),
                                                            -N_A(xi_A) nu_A,  N_B(xi_B) nu_B ]

        over the nodes [slave element, A, B].  Cuts where the closest point moves continuously
        (a node crossed or stuck to, a bound reached) add nothing: there r_A = r_B.  Fills
        ``out["switch"]`` (nsw, 3) element ids and, with ``tangent``, ``out["switch_mat"]``.
        cla, clb: the closest points at left and right (``ContactZones.split``)."""
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
        Ns, dNs, _ = (mm @ self.C for mm in monomials(self.p, xc))
        t = np.einsum("na,nad->nd", dNs, ctx["x_own"][o])
        dnu = nua - nub
        phi_xi = np.einsum("nd,nd->n", dnu, t)
        # phi_xi > 0: A is closer on the left; a tangential switch (phi_xi ~ 0) is skipped
        ok = phi_xi > 1e-8 * np.linalg.norm(t, axis=1) * np.linalg.norm(dnu, axis=1)
        if not np.any(ok):
            return
        Na = monomials(self.p, cla["xi_m"][ok])[0] @ self.C
        Nb = monomials(self.p, clb["xi_m"][ok])[0] @ self.C
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
        Ns, Nm = cl["N"][act], monomials(self.p, xm)[0] @ self.C
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
        _, dNm, d2Nm = (mm @ self.C for mm in monomials(p, a["xm"]))
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


