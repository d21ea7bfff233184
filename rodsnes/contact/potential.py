"""Self-contact as a penalty pair potential between centreline points (pure numpy; no MPI, no
PETSc): the -contact_model potential alternative to the closest-point model of contact.py.

    E_c = k int_0^L ds int_{I(s)} psi(a) dsigma,   a = <2 eps - |r(s) - r(sigma)|>        (1)

I(s) is the exclusion set of contact.py (|s - sigma| >= delta, periodic on a ring).  Every
couple of centreline points closer than 2 eps repels; there is no closest point.  Why: the
closest-point gap d(s) = 2 eps - min_sigma |r(s) - r(sigma)| is smooth only while the minimum is
unique and non-degenerate.  Its second derivative along the master is |r'|^2 - D . r'' =
1 - rho, rho = g nu . kappa (g the distance, nu the normal, kappa the master's curvature
vector): where the slave point sits at a centre of curvature of the master (rho -> 1) the
distance along the master is flat, the closest point races, and a C0 kink of the Lagrange
centreline, however small, makes a second minimum; ties between the two move the force from
one set of nodes to another.  A tight two-ply (the plectoneme) is exactly there: its strands
wind round each other at a pitch angle near 45 degrees, where rho = 2 sin^2(alpha) -> 1
(measured rho = 0.94 - 0.96 along the ply from 9.1 to 9.7 turns, up to 1.9 where the ply meets
its end loop).  (1) has no minimum to pick: it is C^2 in the nodes, whatever the geometry
(Onset law).

Onset law.  psi is the penalty's quadratic a^2/2 with a cubic onset layer 0 < a < a_s:

    psi(a) = a^3 / (6 a_s)                        a <= a_s
             a^2/2 - a_s a/2 + a_s^2/6            a >= a_s,    psi'' = min(a / a_s, 1)    (3)

so psi, psi' and psi'' are 0 at a = 0 and continuous at a_s, and the Hessian of (1) is
continuous as point couples enter and leave the 2 eps ball.  a_s = ONSET x d* with ONSET = 1
(d* the promised penetration, below): a couple at the promised depth is at the end of the
layer, the contact's working range is cubic and deeper penetration grows no stiffer than the
quadratic law.  ONSET = 0 (or ``PotentialKernel(onset=0)``) is the quadratic law
psi = a^2/2, which is only C^1 in the nodes: each couple entering the ball adds k W nu nu^T to
the Hessian at once (tests/test_contact_potential.py: the normal stiffness of an element
jumps by a quarter of its value), and its quadrature integrand has kinks at the ball's edge.
Why the onset: the quadratic law's quadrature ripples the energy as strands slide along each
other 17 times more (1.1e-3 of the energy at the default nqp against 6.6e-5) and misses the
force of parallel strands by 4e-3 against 1e-3; the plectoneme from the straight rod to 8
turns (serial, same session, the minimiser's shift memory cleared at every load step) took
462 s, 312 steps, 10335 Newton iterations with the onset law, 877 s, 457 steps, 17691 with
the quadratic law.  It does not shorten the iterations of a load step where the plectoneme's
arm swings round the end-to-end axis (a near-zero mode, lowest eigenvalue of H v = l M v
~ 5e-9 of the diagonal: 10 - 200 iterations either way): along Newton's direction the energy
there is a smooth quartic in the step length, E0 + g.d (a - a^2/2) + c4 a^4 with
c4 ~ 10 |g.d|, the straight step's chord of a rotation, with either law.

Penalty law.  For two straight parallel strands at distance g = 2 eps - d (d > 0 penetration),
the inner integral of (1) is Phi(d) = k int psi(<2 eps - sqrt(g^2 + t^2)>) dt, so a slave
point carries the line force

    f(d) = Phi'(d) = k int_{|t| < t0} psi'(2 eps - r) g / r dt,   r = sqrt(g^2 + t^2),
    t0 = sqrt(4 eps^2 - g^2)                                                          (2)

(~ (16/15) k sqrt(eps) d^(5/2) / a_s within the layer, (8/3) k sqrt(eps) d^(3/2) with the
quadratic law).  k is set from the closest-point penalty mu (-contact_penalty, or its default)
so that both models give the same force at the promised penetration
d* = -contact_penetration x 2 eps: k = mu d* / f_1(d*) (``pair_stiffness``, f_1: (2) with
k = 1).  Below d* the potential is softer than mu d, above it stiffer; the
-contact_penalty_adapt raises of mu act on k in proportion.

The wall (-contact_wall, on by default).  The penalty alone lets the depth grow with the
force: a load step that presses harder than mu was set for ends beyond the promise, and the
step had to be solved again with a raised mu (the plectoneme: 10 such re-solves from the
straight rod to 10 turns).  With the wall, the promise is part of the law: psi gains the
barrier of IPC (Li et al. 2020),

    beta(a) = x^2 B(t),   B(t) = -(t - 1)^2 ln t,   t = (a_w - a) / x,   a_b < a < a_w      (4)

0 up to a_b = a_w - x, C^2 there (beta'' = B''(t) = 0 at t = 1), infinite at the wall a_w.
Its stiffness beta'' is dimensionless as psi'' is (the same k), 6.4 halfway through the
barrier, 122 at t = 0.1, so no point couple comes to a_w whatever the load.  a_w stands short
of the promised depth d* by the couples' sampling error (``sampling_error``: two strands
touching between the sample points are closer than their closest couple, by at most
(h_s^2 + h_m^2) / (8 g) for the largest spacings h_s, h_m of the slave and master points,
g = 2 eps - d*), so that the report's closest-point depth keeps the promise too; the
barrier's range x = WALL x the promised penetration into the tube (-contact_penetration x
2 radius; with a standoff the law acts from 2 eps, the tube's surface lies deeper), so the
standoff's soft start is untouched.  A state beyond the wall has infinite energy: the line
searches refuse it (ContactTerm.depth_allowed caps every trial short of a_w).  The report
evaluates the law at its own points, up to the sampling error deeper than the couples; there
its depth is that of the deepest couple.  With -contact_penalty_adapt a converged load step
whose deepest couple sits in the barrier (a > a_b) keeps its state (it keeps the promise) and
raises mu for the next step, 1.25 mu a / a_b (ContactTerm.ease_wall, both load paths, once the step is written: RodProblem.ease_walls): the
barrier takes the overshoot within a step, the penalty the growth of the force between steps,
and nothing is solved twice.  Measured on cases/plectoneme.opts from the straight rod (Intel Xeon
VM, back to back): 31 load steps, 2378 Newton iterations, 22.8 s with the penalty alone (10
re-solves, 0.99 % the deepest converged penetration); 29, 2401, 22.7 s with the wall (0
re-solves, 11 raises between steps, 0.93 %); docs/contact.md (The wall) has four more scenes
(0-23 % more iterations where the contact works inside the barrier) and where the wall cannot
see the depth (the edge of the exclusion in a loop tighter than the flexure bound: the
re-solve stays there).  A barrier over the whole promise without the
raises between steps (the penalty at its default throughout) took 6823 iterations: Newton
inside a log barrier is slow, so the barrier is the guard, not the working range.

End caps.  A slave point beside an open rod's end sees only the half line of material that
is there, so (1) gives it half the force a point beside a strand's middle gets (the closest-point
law, whose closest point sits on the end, gives the full mu d: the end is a ball).  Each open
end therefore carries a point couple of length weight c = mu d* / (2 k psi'(d*)) (mu / (2 k)
with the quadratic law): beside the end at d* the half line gives mu d* / 2 and the cap
k c psi'(d*) = mu d* / 2, together the middle's mu d* (the
force on the slave point; the end itself, as slave, sees a whole strand, as with the
closest-point law, so the total over the two strands is in the same proportion as there).  On the
plectoneme the tail presses on the clamped start: without the caps, switching to this law at
9.72 turns pushed it 2.5 % in and -contact_penalty_adapt raised mu 8.5x.

Discretisation.  Gauss-Legendre points (nqp per element, both integrals) on every candidate
element pair (e, m) of ``contact.candidate_pairs``:

    E_c = sum_(e,m) sum_(q,j) W_qj k psi(a_qj),   W_qj = w_q w_j J^2, J = h/2,
    (plus, at an open rod's end, the end point as a master point of weight w_q J c)
    a_qj = <2 eps - |D_qj|>,   D_qj = r_e(xi_q) - r_m(xi_j),   0 where dist(s_q, sigma_j) < delta.

The exclusion is a mask on fixed arclength points, so it never moves.  With nu = D/|D| and
Ntil = [N(xi_q), -N(xi_j)] over the 2(p+1) nodes of [e, m]:

    dE/dx_A   = - sum W k psi'(a) Ntil_A nu
    d2E/dx_A dx_B = sum W k Ntil_A Ntil_B [ (psi'' + psi'/|D|) nu nu^T - (psi'/|D|) I ]  (a > 0)

nqp resolves the contact support: one slave point at d* touches a master stretch of length
2 t0(d*) (0.014 for the plectoneme, 0.85 of an element), and nqp puts 12 points on it
(``points_per_element``; -contact_quadrature sets nqp instead; a mesh that would need more than
48 points per element is refused, scene.py: a contact zone smaller than the quadrature's
spacing is seen by a few couples that enter and leave one at a time, and Newton cycles).  The quadrature error then
ripples the energy as strands slide along each other (tests/test_contact_potential.py measures
it); it falls with nqp and h, and is smaller with the onset layer (Onset law).

Reported (same keys as ContactKernel.evaluate): the gap d = 2 eps - min |D| at the nqc Gauss
points of the slave elements, by the closest-point projection of contact.py (a diagnostic here:
the penetration the penalty promises, the KKT picture; d_active also holds the depth
2 eps - min_j |D_qj| at the nqp points, so that the deepest point of a crossing between two
reporting points is seen); the force is the line force density |f(s)|, f(s) = -d/dr(s) of the
inner integral over all masters, at the same points (a point squeezed between two strands
reports the net force, where the closest-point law's per-strand sum reports the sum of the
magnitudes); total_force = int |f| ds by the nqp rule; complementarity = int <d> |f| ds by the
nqc rule; active rows are the element pairs (e, m) with a point couple in contact (one tangent
block each).

Cost: each part is made only when asked for (``PotentialKernel.evaluate``): the energy and
residual always, over the element pairs whose capsules come within 2 eps (the others hold no
couple in contact: ``contact.capsules_within``); the tangent (``add_tangent``) and the report
(``add_report``) from what the residual kept, at the same positions.  The rows of the pairs'
elements and of the master pool are functions of the ids alone, kept while they stay
(``_pair_rows``: an evaluation's numpy glue costs about as much as the compiled kernel).  Of
the near pairs' nqp (nqp + 2) couples only those in contact (|D| < 2 eps, admissible: a fifth to a third of
them in the plectoneme's two-ply) are kept, as a flat list sorted by (pair, q, j); the energy,
the residual and the tangent are sums over that list (per row and slave point, per row and
master point), contracted with the shape functions.  The compiled kernel
(potential_compiled.py, rodsnes/contact/_potential_kernel.c; ``kernel="auto"`` uses it when built)
makes the list, the energy and the residual rows in one pass over the couples, and the tangent
blocks from the list; the numpy path (``kernel="numpy"``) is its reference: the same couples
(the same floating-point operations on the distances and the exclusion), sums equal to
round-off.  ``depth`` = max 2 eps - |D_qj| over the admissible couples of the near pairs (the
potential's own points; -inf without any): RodProblem.precheck's penetration limit compares
it at the iterate and at its trials, with no closest point.

Memory: the passes over the near pairs go in chunks of at most ``CHUNK_COUPLES`` point couples
(``pair_chunks``; the compiled kernel stops where the next pair might not fit its couple
buffers and goes on from there with its running sums), so a pass holds the couples in contact
and a bounded scratch, whatever N: on the bench coil (N = 1000, 11918 near pairs of 43 x 45
couples, 83202 in contact) the list's buffers had been sized for all 23 million couples
(715 MB allocated) and the report's line force held 4-d arrays of every near pair (201 MB).
The chunks do not change the result: the same couples, depth, rows, residual and tangent, the
compiled energy bit for bit (one compensated sum carried across the chunks), numpy's to the
round-off of its chunks' sums.  The Jacobian's pattern (``pairs_within``) holds the pairs
with a couple of these points within reach, not every pair whose capsules are.
"""
import functools

import numpy as np

from rodsnes.profiling import logged
from rodsnes.model import fe
from rodsnes.contact import potential_compiled
from rodsnes.contact.projection import ContactKernel
from rodsnes.contact.scatter import add_in_order, in_order_rows
from rodsnes.contact.closest_point import master_pool_rows
from rodsnes.contact.search import capsules_within, element_capsules, same_bits
from rodsnes.contact.search import positions as _lookup

__all__ = ["ONSET", "WALL", "DENSITY", "MAX_POINTS", "law_energy", "law_force",
           "law_stiffness", "wall_law", "onset_layer", "pair_stiffness", "support_length", "points_per_element",
           "PotentialKernel"]


ONSET = 1.0             # onset layer a_s / d* of the law (0: the quadratic, C^1 law)
WALL = 0.5              # the wall's barrier acts over this share of the promised penetration


def law_energy(a, a_s, wall=None):
    """psi(a) of (1) per unit k (Onset law): a^2/2 when a_s = 0; a^3 / (6 a_s) below a_s,
    a^2/2 - a_s a/2 + a_s^2/6 above; with ``wall`` = (a_b, a_w) the wall's barrier added
    (wall_law; +inf from a_w on)."""
    a = np.asarray(a, dtype=float)
    if a_s <= 0.0:
        psi = 0.5 * a * a
    else:
        psi = np.where(a < a_s, a * a * a / (6.0 * a_s),
                       a * (0.5 * a - 0.5 * a_s) + a_s * a_s / 6.0)
    return psi if wall is None else psi + wall_law(a, wall, 0)


def law_force(a, a_s, wall=None):
    """psi'(a): a when a_s = 0; a^2 / (2 a_s) below a_s, a - a_s/2 above (+ the wall's)."""
    a = np.asarray(a, dtype=float)
    if a_s <= 0.0:
        f = a
    else:
        f = np.where(a < a_s, a * a / (2.0 * a_s), a - 0.5 * a_s)
    return f if wall is None else f + wall_law(a, wall, 1)


def law_stiffness(a, a_s, wall=None):
    """psi''(a) for a > 0: 1 when a_s = 0; a / a_s below a_s, 1 above (+ the wall's)."""
    a = np.asarray(a, dtype=float)
    if a_s <= 0.0:
        s = np.ones_like(a)
    else:
        s = np.minimum(a / a_s, 1.0)
    return s if wall is None else s + wall_law(a, wall, 2)


def wall_law(a, wall, order):
    """The wall's barrier (module docstring, The wall) at depths a, wall = (a_b, a_w): its
    ``order``-th derivative in a (0: beta, 1: beta', 2: beta''), only that one computed.
    0 up to a_b, then x^2 B(t), t = (a_w - a) / x, x = a_w - a_b, B(t) = -(t - 1)^2 ln t (IPC's
    barrier), C^2 at a_b; +inf from a_w on."""
    a_b, a_w = wall
    x = a_w - a_b
    a = np.asarray(a, dtype=float)
    t = np.clip((a_w - a) / x, 0.0, 1.0)
    on, inside = a > a_b, a < a_w
    ts = np.where(inside, np.where(on, t, 1.0), 1.0)        # safe t for the logarithms
    lt, u = np.log(ts), ts - 1.0
    if order == 0:
        v = -x * x * u * u * lt
    elif order == 1:
        v = x * (2.0 * u * lt + u * u / ts)
    elif order == 2:
        v = -2.0 * lt - 4.0 * u / ts + u * u / (ts * ts)
    else:
        raise ValueError(f"order {order}: 0, 1 or 2")
    return np.where(inside, np.where(on, v, 0.0), np.inf)


def onset_layer(eps, penetration, onset=None):
    """a_s = onset x d*, d* = penetration x 2 eps (``ONSET`` by default)."""
    return (ONSET if onset is None else float(onset)) * float(penetration) * 2.0 * float(eps)


def line_force_per_stiffness(eps, d, a_s=0.0, n=96):
    """f_1(d): the line force (2) on a point at distance 2 eps - d from a straight line, k = 1,
    with the onset layer a_s."""
    g = 2.0 * eps - d
    if d <= 0.0:
        return 0.0
    t0 = np.sqrt(4.0 * eps ** 2 - g ** 2)
    th, w = fe.gauss_legendre(n)
    # t = t0 sin(pi th / 2): the integrand's kink at the support ends becomes smooth
    t = t0 * np.sin(0.5 * np.pi * th)
    dt = t0 * 0.5 * np.pi * np.cos(0.5 * np.pi * th)
    r = np.hypot(g, t)
    return float(np.sum(w * dt * law_force(np.maximum(2.0 * eps - r, 0.0), a_s) * g / r))


def pair_stiffness(mu, eps, penetration, onset=None):
    """k of (1) with the force mu d* of the closest-point model at d* = penetration x 2 eps."""
    d = float(penetration) * 2.0 * float(eps)
    a_s = onset_layer(eps, penetration, onset)
    return float(mu) * d / line_force_per_stiffness(float(eps), d, a_s)


def support_length(eps, penetration):
    """2 t0(d*): the master stretch a slave point at the promised penetration touches."""
    d = float(penetration) * 2.0 * float(eps)
    return 2.0 * np.sqrt(4.0 * eps ** 2 - (2.0 * eps - d) ** 2)


DENSITY = 12            # default quadrature points on the support length 2 t0(d*)
MAX_POINTS = 48         # most automatic points per element (scene.py refuses a coarser mesh)


def points_per_element(h, eps, penetration, density=DENSITY):
    """Gauss points per element that put ``density`` points on the support length."""
    return int(np.ceil(density * float(h) / support_length(eps, penetration)))


def _quiet_beyond_the_wall(method):
    """A state beyond the wall has infinite energy, and its residual, tangent and report
    infinite or undefined entries (a trial the line search then refuses): no warnings."""
    @functools.wraps(method)
    def quiet(self, *args, **kw):
        if self.wall is None:
            return method(self, *args, **kw)
        with np.errstate(invalid="ignore", over="ignore"):
            return method(self, *args, **kw)
    return quiet


_SYM6 = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))     # entries of a symmetric 3 x 3
_FULL9 = np.array([0, 3, 4, 3, 1, 5, 4, 5, 2])                   # ... back to its 9, row-major


class PotentialKernel:
    """The pair potential (1) over a set of own (slave) elements; the interface of
    contact.ContactKernel (evaluate, slave_arclength, mu, eps, delta, h, nqc, wq, Nq).
    ``kernel``: "auto" (the compiled kernel if built, else numpy), "compiled" or "numpy"
    (module docstring, Cost)."""

    CHUNK_COUPLES = 1 << 19     # point couples per chunk of a pass over the near pairs (Cost)

    def __init__(self, order, nqc, eps, mu, delta, L, nelem, closed, penetration=0.01, nqp=None,
                 onset=None, kernel="auto", wall=None):
        if kernel not in ("auto", "compiled", "numpy"):
            raise ValueError(f"unknown potential kernel {kernel!r}: use auto, compiled or numpy")
        self.compiled = kernel != "numpy" and potential_compiled.available()
        if kernel == "compiled" and not self.compiled:
            raise RuntimeError("the compiled potential kernel is not built (run pip install -e .)")
        self.gauge = ContactKernel(order, nqc, eps, mu, delta, L, nelem, closed, segments=False)
        g = self.gauge
        self.p, self.nqc, self.eps, self.delta = g.p, g.nqc, g.eps, g.delta
        self.L, self.nelem, self.closed, self.h = g.L, g.nelem, g.closed, g.h
        self.xq, self.wq, self.Nq = g.xq, g.wq, g.Nq
        self.penetration = float(penetration)
        self.a_s = onset_layer(self.eps, self.penetration, onset)
        self.k_per_mu = pair_stiffness(1.0, self.eps, self.penetration, onset)
        self._mu = float(mu)
        if nqp is None:
            nqp = max(self.nqc, points_per_element(self.h, self.eps, self.penetration))
        self.nqp = int(nqp)
        self.xp, self.wp = fe.gauss_legendre(self.nqp)
        # the wall (The wall): short of the promised depth d* by the couples' sampling error,
        # its barrier from there - wall on
        self.wall = None
        if wall:
            a_w = self.penetration * 2.0 * self.eps - self.sampling_error()
            self.wall = (a_w - float(wall), a_w)
        # the compiled kernel's law: (a_s, a_b, a_w, depth clip: +inf but for the report's pass)
        self.law = np.array([self.a_s, *(self.wall if self.wall else (0.0, 0.0)), np.inf])
        self.Np = fe.lagrange(self.p, self.xp)[0]
        # master points: the Gauss points and the two element ends (the rod's end caps)
        self.xm = np.concatenate([self.xp, [-1.0, 1.0]])
        self.Nm = fe.lagrange(self.p, self.xm)[0]
        d = self.penetration * 2.0 * self.eps
        self.cap = 0.5 * d / (self.k_per_mu * float(law_force(d, self.a_s)))
        # shape-function products of the tangent's blocks (add_tangent)
        self._NpT = np.ascontiguousarray(self.Np.T)                     # (p+1, nqp)
        self._NmT = np.ascontiguousarray(self.Nm.T)                     # (p+1, nqp + 2)
        self._NNp = np.einsum("qa,qb->abq", self.Np, self.Np).reshape(-1, self.nqp)
        self._NNm = np.einsum("ja,jb->abj", self.Nm, self.Nm).reshape(-1, self.nqp + 2)
        # weights and arclength offsets of the points (_near_couples, _admissible_couples)
        self._wpJ = self.wp * (0.5 * self.h)
        self._sq = (self.xp + 1.0) * 0.5 * self.h
        self._sm = (self.xm + 1.0) * 0.5 * self.h
        self._wmJ = np.concatenate([self._wpJ, [0.0, 0.0]])
        self._Npc, self._Nmc = np.ascontiguousarray(self.Np), np.ascontiguousarray(self.Nm)
        self._scratch = {}
        self._rows = {}                 # _pair_rows: the ids they were made for, the rows
        self._wm = (None, None)         # master_weights of every element: (cap, table)
        self.chunk_couples = self.CHUNK_COUPLES

    def sampling_error(self):
        """How much closer than the closest couple of points two strands that touch at the
        promised depth d* may come: a point between two sample points h_s apart is at most
        h_s^2 / (8 g) farther from a straight strand at distance g = 2 eps - d* than its
        closest point, on either strand: (h_slave^2 + h_master^2) / (8 g), h the largest
        spacing of the slave points (across element ends too) and of the master points."""
        h_slave = 0.5 * self.h * max(np.diff(self.xp).max(initial=0.0), 2.0 * (1.0 - self.xp[-1]))
        h_master = 0.5 * self.h * np.diff(np.concatenate([[-1.0], self.xp, [1.0]])).max()
        g = 2.0 * self.eps * (1.0 - self.penetration)
        return (h_slave ** 2 + h_master ** 2) / (8.0 * g)

    @property
    def mu(self):
        return self._mu

    @mu.setter
    def mu(self, value):
        self._mu = float(value)
        self.gauge.mu = self._mu

    @property
    def k(self):
        """Pair stiffness of (1)."""
        return self._mu * self.k_per_mu

    def slave_arclength(self, own_ids):
        return self.gauge.slave_arclength(own_ids)

    def master_weights(self, m):
        """(len(m), nqp + 2) arclength weights of the master points of elements m: w_j h/2 at
        the Gauss points; at an open rod's end the end point gets the cap length mu / (2 k)
        (End caps), the other element ends 0: rows of a table of every element, made once
        (the evaluation asks for them at every call)."""
        cap, table = self._wm
        if table is None or cap != self.cap:      # once (tests switch the caps off: cap = 0)
            every = np.arange(self.nelem)
            table = np.zeros((self.nelem, self.nqp + 2))
            table[:, :self.nqp] = self.wp * (0.5 * self.h)
            if not self.closed:
                table[:, self.nqp] = np.where(every == 0, self.cap, 0.0)
                table[:, self.nqp + 1] = np.where(every == self.nelem - 1, self.cap, 0.0)
            self._wm = (self.cap, table)
        return table[np.asarray(m, dtype=np.int64)]

    def admissible(self, e, m, xa, xb):
        """(npair, na, nb) True where dist(s, sigma) >= delta, s in e at xa, sigma in m at xb
        (xi of the slave and master points): admissible_couples over every pair and couple."""
        e, m = np.asarray(e)[:, None, None], np.asarray(m)[:, None, None]
        return self.admissible_couples(e, np.asarray(xa)[None, :, None], m,
                                       np.asarray(xb)[None, None, :])

    def admissible_couples(self, e, xa, m, xb):
        """True where dist(s, sigma) >= delta for slave points xa of elements e and master
        points xb of elements m, couple by couple (arrays that broadcast together)."""
        h = self.h
        dist = np.abs((e * h + (xa + 1.0) * 0.5 * h) - (m * h + (xb + 1.0) * 0.5 * h))
        if self.closed:
            dist = np.minimum(dist, self.L - dist)
        return dist >= self.delta

    def couples(self, xs, xm, adm):
        """a = <2 eps - |D|> (masked), |D| and nu for D = xs_q - xm_j, (npair, na, nb)."""
        D = xs[:, :, None, :] - xm[:, None, :, :]
        r = np.sqrt(np.einsum("pqjd,pqjd->pqj", D, D))
        a = np.where(adm, np.maximum(2.0 * self.eps - r, 0.0), 0.0)
        nu = D / np.where(r > 0.0, r, 1.0)[..., None]
        return a, r, nu

    @logged("ContactEval")
    @_quiet_beyond_the_wall
    def evaluate(self, own_ids, x_own, other_ids, x_other, pairs, tangent=True, report=True):
        """Energy and residual of (1) over the own elements, with the outputs of
        contact.ContactKernel.evaluate_strand (active = element pairs, no switch points); with
        ``tangent`` the tangent blocks (``add_tangent``), with ``report`` the closest-point
        report (``add_report``).  Either can be added later to the same output (it keeps what
        they need under the private key ``_near``); ``reported`` tells whether it has the
        report.  The energy, residual and depth do not depend on tangent or report."""
        g = self.gauge
        inputs = g.as_inputs(own_ids, x_own, other_ids, x_other, pairs)
        no = len(inputs[0])
        out = g.empty_output(no, False)
        out.update(depth=-np.inf, reported=False, _inputs=inputs, _near=None)
        if no and len(inputs[4]):
            out["_near"] = self._near_couples(*inputs)
            self._residual(out)
        if tangent:
            self.add_tangent(out)
        if report:
            self.add_report(out)
        return out

    def _near_couples(self, own_ids, x_own, other_ids, x_other, pairs):
        """The point couples in contact of the element pairs that may be in contact: the near
        pairs (``_near_pairs``) and, of all their couples D = r_e(xi_q) - r_m(xi_j) at the nqp
        slave and nqp + 2 master points, those closer than 2 eps and admissible, as a flat list
        ``couples`` = (pair, q, j, |D|) sorted by (pair, q, j), and the depth: the residual,
        the tangent and the report work on these, O(couples in contact), not on the pairs'
        nqp (nqp + 2) couples.  Made by the compiled kernel (potential_compiled.py, with the
        energy and the residual rows) or by numpy (``_couples_numpy``), the same couples."""
        c = self._near_pairs(own_ids, x_own, other_ids, x_other, pairs)
        if self.compiled:
            return potential_compiled.couples(self, c, self._workspace)
        return self._couples_numpy(c)

    def pairs_within(self, own_ids, x_own, other_ids, x_other, pairs, reach):
        """The element pairs (e, m) of ``pairs`` (own, other) with a couple of the law's points
        closer than ``reach`` (>= 2 eps), admissible and of master weight W > 0, as rows in the
        order of ``pairs``: at reach = 2 eps exactly the rows of an evaluation (the pairs the
        tangent couples), beyond it also the pairs within reach - 2 eps of coupling.  The
        Jacobian's pattern with this law (ContactTerm.pattern_pairs): the pairs whose capsules
        come within 2 eps are 3 times as many on the bench coil (5959 against the 1981 that
        touch, N = 1000), all of them filled in by the factorisation.  The same pass as the
        residual's (compiled or numpy), with 2 eps replaced by ``reach``."""
        own_ids, x_own, other_ids, x_other, pairs = self.gauge.as_inputs(own_ids, x_own, other_ids,
                                                                         x_other, pairs)
        if not len(own_ids) or not len(pairs):
            return np.zeros((0, 2), dtype=np.int64)
        reach = max(float(reach), 2.0 * self.eps)
        c = self._near_pairs(own_ids, x_own, other_ids, x_other, pairs, reach)
        if self.compiled:
            rows = potential_compiled.rows_within(self, c, self._workspace, reach)
        else:
            p, _, j, _ = self._couples_numpy(c, reach)["couples"]
            rows = np.unique(p[self._couple_master_weights(c["m"][p], j) > 0.0])
        return np.stack([c["e"][rows], c["m"][rows]], axis=1).astype(np.int64)

    def _near_pairs(self, own_ids, x_own, other_ids, x_other, pairs, reach=None):
        """The pairs whose capsules (contact.element_capsules) come within 2 eps (``reach``;
        no couple of another pair is closer): own index oi, pool index mi, elements e, m, in
        the order of the pairs; the slave points xs (own, nqp, 3) and master points xm (pool,
        nqp + 2, 3)."""
        first, oi, mi, pool_own = self._pair_rows(own_ids, other_ids, pairs, reach is None)
        pool_x = np.concatenate([x_other, x_own], axis=0)[first]       # gauge.master_pool's
        ko = element_capsules(x_own)
        # the pool's capsules are the own ones when it is the own elements at the same bits
        kp = ko if pool_own and same_bits(pool_x, x_own) else element_capsules(pool_x)
        near = np.flatnonzero(capsules_within([v[oi] for v in ko], [v[mi] for v in kp],
                                              2.0 * self.eps if reach is None else reach))
        return {"oi": oi[near], "mi": mi[near], "e": pairs[near, 0], "m": pairs[near, 1],
                "xs": self.Np @ x_own, "xm": self.Nm @ pool_x}

    def _pair_rows(self, own_ids, other_ids, pairs, slot):
        """(first, oi, mi, own) of ``_near_pairs``: the master pool's rows in [other, own]
        (closest_point.master_pool_rows), the rows of the pairs' own and master elements, and
        whether the pool is the own elements (one rank: every element a candidate).
        Functions of the ids alone, which stay while the Verlet list and the pairs within its
        reach do (most evaluations of a Newton iteration's line search), so they are kept and
        made anew only when an id differs (a slot each for the evaluation and pairs_within);
        the lookups and their KeyError are those of every call."""
        kept = self._rows.get(slot)
        ids = (own_ids, other_ids, pairs)
        if kept is not None and all(np.array_equal(a, b) for a, b in zip(kept[0], ids)):
            return kept[1]
        pool_ids, first = master_pool_rows(own_ids, other_ids)
        rows = (first, _lookup(own_ids, pairs[:, 0], "own"),
                _lookup(pool_ids, pairs[:, 1], "other"), np.array_equal(pool_ids, own_ids))
        self._rows[slot] = (tuple(np.array(a, copy=True) for a in ids), rows)
        return rows

    def _couples_numpy(self, c, reach=None):
        """``couples`` and ``depth`` of the near pairs ``c`` in numpy, chunk by chunk of pairs
        (``pair_chunks``: at most ``chunk_couples`` point couples at a time): the squared
        distances of a chunk's couples (``_squared_distances``), those below 4 eps^2 (a
        superset: the roundoff of the square root), |D| < 2 eps exactly (< ``reach``), the
        exclusion tested on these couples alone (``_admissible_couples``).  The couples and the
        depth do not depend on the chunks."""
        oi, mi, e, m = c["oi"], c["mi"], c["e"], c["m"]
        nqp, nm = self.nqp, self.nqp + 2
        two_eps = 2.0 * self.eps if reach is None else float(reach)
        cut = self._min_arclength(e, m) < self.delta                   # pairs the exclusion cuts
        parts, apart = [], -np.inf
        for lo, hi in self.pair_chunks(len(oi)):
            r2 = self._squared_distances(c["xs"], c["xm"], oi[lo:hi], mi[lo:hi])
            cand = np.flatnonzero(r2 < two_eps * two_eps * (1.0 + 1e-12))
            r = np.sqrt(r2.ravel()[cand])
            keep = r < two_eps
            p, qj = np.divmod(cand, nqp * nm)
            q, j = np.divmod(qj, nm)
            p += lo
            t = np.flatnonzero(keep & cut[p])
            if len(t):
                keep[t] = self._admissible_couples(e[p[t]], m[p[t]], q[t], j[t])
            if not keep.all():
                p, q, j, r = p[keep], q[keep], j[keep], r[keep]
            if len(r):
                parts.append((p, q, j, r))
            elif not parts:         # nothing in contact so far: the least distance apart
                apart = max(apart, self._depth_apart(r2, e[lo:hi], m[lo:hi], cut[lo:hi]))
        if len(parts) == 1:
            c["couples"] = parts[0]
        elif parts:
            c["couples"] = tuple(np.concatenate(v) for v in zip(*parts))
        else:
            z = np.zeros(0, dtype=np.int64)
            c["couples"] = (z, z.copy(), z.copy(), np.zeros(0))
        r = c["couples"][3]
        c["depth"] = two_eps - float(r.min()) if len(r) else apart
        return c

    def pair_chunks(self, npair, per_pair=None):
        """(lo, hi) ranges of the pairs, at most ``chunk_couples`` point couples each (at least
        one pair): the memory of a pass over the near pairs stays bounded, whatever N."""
        per_pair = self.nqp * (self.nqp + 2) if per_pair is None else int(per_pair)
        step = max(1, int(self.chunk_couples) // max(per_pair, 1))
        return [(lo, min(lo + step, npair)) for lo in range(0, npair, step)]

    def _active_couples(self, c):
        """The couples of W > 0 (every Gauss point; the end points only as an open rod's
        caps): the rows' pairs act, and per couple its row, q, j, |D|, a, W, the master weight
        wm and D (made once per evaluation, kept in ``c``)."""
        if "active_couples" not in c:
            p, q, j, r = c["couples"]
            first = np.ones(len(p), dtype=bool)
            np.not_equal(p[1:], p[:-1], out=first[1:])
            t = np.cumsum(first) - 1                # the touching pair (a couple in contact)
            nt = int(t[-1]) + 1 if len(t) else 0
            wm = self._couple_master_weights(c["m"][p], j)
            on = np.flatnonzero(wm > 0.0)
            if len(on) < len(p):
                p, q, j, r, wm, t = p[on], q[on], j[on], r[on], wm[on], t[on]
            first = np.ones(len(p), dtype=bool)
            np.not_equal(p[1:], p[:-1], out=first[1:])
            D = np.take(c["xs"].reshape(-1, 3), c["oi"][p] * self.nqp + q, axis=0)
            D -= np.take(c["xm"].reshape(-1, 3), c["mi"][p] * (self.nqp + 2) + j, axis=0)
            c["active_couples"] = {"act": p[first], "row": np.cumsum(first) - 1, "q": q, "j": j,
                                   "r": r, "a": 2.0 * self.eps - r, "W": self._wpJ[q] * wm,
                                   "wm": wm, "D": D, "t": t, "nt": nt}
        return c["active_couples"]

    def _couple_master_weights(self, m, j):
        """``master_weights`` of the master points j of elements m, couple by couple."""
        w = self._wmJ[j]
        end = np.flatnonzero(j >= self.nqp)
        if len(end) and not self.closed:
            last = np.where(j[end] == self.nqp, 0, self.nelem - 1)
            w[end] = np.where(m[end] == last, self.cap, 0.0)
        return w

    def _workspace(self, name, shape, dtype=np.float64):
        """A scratch array of the kernel, valid until the next call that asks for it (kept
        between calls: fresh large arrays cost their pages' faults every time)."""
        n = int(np.prod(shape))
        buf = self._scratch.get(name)
        if buf is None or len(buf) < n or buf.dtype != dtype:
            buf = self._scratch[name] = np.empty(max(n, 2 * len(buf) if buf is not None else n),
                                                 dtype=dtype)
        return buf[:n].reshape(shape)

    def _squared_distances(self, xs, xm, oi, mi):
        """|D_qj|^2 (npair, nqp, nqp + 2) of the couples of the pairs (slave oi, master mi),
        D = xs[oi, q] - xm[mi, j], coordinate by coordinate (no (npair, nqp, nqp + 2, 3)
        array), in scratch arrays."""
        shape = (len(oi), self.nqp, self.nqp + 2)
        r2, t = self._workspace("r2", shape), self._workspace("t", shape)
        xsT, xmT = xs.transpose(2, 0, 1), xm.transpose(2, 0, 1)
        for d in range(3):
            u = r2 if d == 0 else t
            np.subtract(xsT[d][oi][:, :, None], xmT[d][mi][:, None, :], out=u)
            np.multiply(u, u, out=u)
            if d:
                r2 += t
        return r2

    def _admissible_couples(self, e, m, q, j):
        """True where dist(s, sigma) >= delta for the couples (slave point q of element e,
        master point j of element m), couple by couple (``admissible`` on a list)."""
        h = self.h
        s = e * h + self._sq[q]
        sig = m * h + self._sm[j]
        dist = np.abs(s - sig)
        if self.closed:
            dist = np.minimum(dist, self.L - dist)
        return dist >= self.delta

    def _depth_apart(self, r2, e, m, cut):
        """2 eps - min |D| over the admissible couples of the near pairs (r2 of
        ``_squared_distances``, overwritten) when none is closer than 2 eps; -inf without
        any."""
        if not len(e):
            return -np.inf
        part = np.flatnonzero(cut)
        if len(part):
            r2[part] = np.where(self.admissible(e[part], m[part], self.xp, self.xm), r2[part],
                                np.inf)
        return 2.0 * self.eps - float(np.sqrt(r2.min()))

    def _min_arclength(self, e, m):
        """Least arclength distance between points of elements e and m (periodic on a ring)."""
        k = np.abs(np.asarray(e) - np.asarray(m))
        if self.closed:
            k = np.minimum(k, self.nelem - k)
        return np.maximum(k - 1, 0) * self.h

    def _energy_sum(self, ac, terms):
        """sum W psi(a) of the couples in contact, by numpy's sum over the touching pairs'
        (nqp, nqp + 2) couple grids (zero where no couple is in contact): the round-off of a
        sum over every couple of those pairs, whichever of them are in contact; chunk by chunk
        of touching pairs (``pair_chunks``), the chunks' sums added in order."""
        nqp, nm = self.nqp, self.nqp + 2
        t, qj = ac["t"], ac["q"] * nm + ac["j"]
        total = 0.0
        for lo, hi in self.pair_chunks(ac["nt"]):
            a, b = np.searchsorted(t, [lo, hi])        # couples sorted by pair, so by t
            grid = self._workspace("energy", ((hi - lo) * nqp * nm,))
            grid[:] = 0.0
            grid[(t[a:b] - lo) * (nqp * nm) + qj[a:b]] = terms[a:b]
            total += float(np.sum(grid))
        return total

    @staticmethod
    def _per_point(V, row, idx, nrow, n):
        """(nrow, n, V.shape[1]): the sums of the couples' values V (ncouple, ncomp) per row
        and point idx (slave q or master j)."""
        key = row * n + idx
        out = np.empty((V.shape[1], nrow * n))
        for d in range(V.shape[1]):
            out[d] = np.bincount(key, weights=V[:, d], minlength=nrow * n)
        return np.ascontiguousarray(out.T).reshape(nrow, n, V.shape[1])

    def _residual(self, out):
        """Energy, residual rows (one per element pair with a couple in contact) and depth of
        (1) from the couples in contact of ``_near_couples`` (made there by the compiled
        kernel, here by numpy):

            dE/dx_A = - sum W k psi'(a) Ntil_A nu,   Ntil = [N(xi_q), -N(xi_j)],

        the couples' dE/dD summed per row and slave point q (per master point j), then
        contracted with N(xi_q) (N(xi_j))."""
        n1 = self.p + 1
        c = out["_near"]
        out["depth"] = c["depth"]
        if "vec" in c:
            act, vec, out["energy"] = c["act"], c["vec"], c["energy"]
        else:
            k = self.k
            ac = self._active_couples(c)
            a, W, r, act = ac["a"], ac["W"], ac["r"], ac["act"]
            out["energy"] = k * self._energy_sum(ac, W * law_energy(a, self.a_s, self.wall))
            # dE/dD = -k W psi'(a) nu per couple
            G = (-k * W * law_force(a, self.a_s, self.wall) / np.where(r > 0.0, r, 1.0))[:, None] * ac["D"]
            vec = np.empty((len(act), 2 * n1, 3))
            vec[:, :n1] = self._NpT @ self._per_point(G, ac["row"], ac["q"], len(act), self.nqp)
            vec[:, n1:] = -(self._NmT @ self._per_point(G, ac["row"], ac["j"], len(act),
                                                        self.nqp + 2))
        if self.wall is not None and out["depth"] >= self.wall[1]:
            out["energy"] = np.inf          # beyond the wall (at a couple of any weight)
        nact = len(act)
        if not nact:
            return
        out["active"] = np.stack([c["e"][act], c["m"][act]], axis=1)
        out.update(qp=np.full(nact, -1, dtype=np.int64), xi=np.full(nact, np.nan),
                   xi_slave=np.full(nact, np.nan), normal=np.full((nact, 3), np.nan),
                   interior=np.zeros(nact, dtype=bool), vec=vec)

    @logged("ContactTangent")
    @_quiet_beyond_the_wall
    def add_tangent(self, out):
        """The tangent blocks of an evaluation (in place; nothing to do if it has them), from
        the couples in contact its residual kept:

            d2E/dx_A dx_B = sum W k Ntil_A Ntil_B [ (psi'' + psi'/|D|) nu nu^T - (psi'/|D|) I ]

        over [slave element, master element] of every active pair: the couples' Hessians H
        (6 entries each); the slave-slave block sums them per row and slave point q, then
        contracts with N(xi_q) N(xi_q), the master-master block per row and master point j;
        the slave-master block scatters them onto the row's (q, j) grid and contracts q with
        N(xi_q) and j with N(xi_j): matrix products (compiled: the same sums, pair by pair)."""
        if out["mat"] is not None:
            return out
        n1 = self.p + 1
        out["switch_mat"] = np.zeros((0, 9 * n1, 9 * n1))
        c = out["_near"]
        nact = len(out["active"])
        if not nact:
            out["mat"] = np.zeros((0, 6 * n1, 6 * n1))
            return out
        if "vec" in c:
            out["mat"] = potential_compiled.tangent(self, c)
            return out
        nqp, nm = self.nqp, self.nqp + 2
        ac = self._active_couples(c)
        a, r, D, W, row, q, j = (ac[v] for v in ("a", "r", "D", "W", "row", "q", "j"))
        rs = np.where(r > 0.0, r, 1.0)
        on = self.k * W
        cr = law_force(a, self.a_s, self.wall) / rs
        # H = on (psi'' + psi'/|D|) nu nu^T - on (psi'/|D|) I (nu nu^T = D D^T / |D|^2): 6 entries
        U = (on * (law_stiffness(a, self.a_s, self.wall) + cr) / rs ** 2)[:, None] * D
        H = np.empty((len(a), 6))
        for n, (i, k) in enumerate(_SYM6):
            np.multiply(U[:, i], D[:, k], out=H[:, n])
        H[:, :3] -= (on * cr)[:, None]
        ss = self._NNp @ self._per_point(H, row, q, nact, nqp)          # (nact, (a, b), 6)
        mm = self._NNm @ self._per_point(H, row, j, nact, nm)
        Hd = np.zeros((nact * nqp * nm, 6))
        Hd[(row * nqp + q) * nm + j] = H
        Hq = (self._NpT @ Hd.reshape(nact, nqp, nm * 6)).reshape(nact * n1, nm, 6)
        sm = -(self._NmT @ Hq)                                           # (nact n1, n1, 6)
        ss, mm, sm = (b.reshape(nact, n1, n1, 6)[..., _FULL9].reshape(nact, n1, n1, 3, 3)
                      for b in (ss, mm, sm))                              # [p, a, b, i, k]
        m6 = np.empty((nact, 2 * n1, 3, 2 * n1, 3))
        m6[:, :n1, :, :n1] = ss.transpose(0, 1, 3, 2, 4)
        m6[:, n1:, :, n1:] = mm.transpose(0, 1, 3, 2, 4)
        m6[:, :n1, :, n1:] = sm.transpose(0, 1, 3, 2, 4)
        m6[:, n1:, :, :n1] = sm.transpose(0, 2, 4, 1, 3)
        out["mat"] = m6.reshape(nact, 6 * n1, 6 * n1)
        return out

    def _report_force(self, c, x_own, no):
        """The line force density f(s) = k sum_j w_j psi'(a) nu at the nqc report points of
        the ``no`` own elements (no, nqc, 3), over the master points of the near pairs of
        ``c``; with the wall the depth a at most the law's deepest (c["depth"]: the report
        points are not the law's).  Compiled: the residual's pass over the report points
        (potential_compiled.report_force); numpy: the distances of all couples, the law on
        those in contact (admissible, closer than 2 eps, master weight > 0), chunk by chunk."""
        xq_own = self.Nq @ x_own
        clip = c["depth"] if self.wall is not None else np.inf
        if self.compiled:
            return potential_compiled.report_force(self, c, xq_own, clip, self._workspace)
        nqc, two_eps = self.nqc, 2.0 * self.eps
        f = np.zeros((no * nqc, 3))
        for lo, hi in self.pair_chunks(len(c["oi"]), nqc * (self.nqp + 2)):
            oi, e, m = c["oi"][lo:hi], c["e"][lo:hi], c["m"][lo:hi]
            D = xq_own[oi][:, :, None, :] - c["xm"][c["mi"][lo:hi]][:, None, :, :]
            r2 = np.einsum("pqjd,pqjd->pqj", D, D)
            pi, qi, ji = np.nonzero(r2 < two_eps * two_eps)
            wm = self._couple_master_weights(m[pi], ji)
            ok = (wm > 0.0) & self.admissible_couples(e[pi], self.xq[qi], m[pi], self.xm[ji])
            pi, qi, ji, wm = pi[ok], qi[ok], ji[ok], wm[ok]
            r = np.sqrt(r2[pi, qi, ji])
            a = np.minimum(two_eps - r, clip)
            coef = self.k * wm * law_force(a, self.a_s, self.wall) / np.where(r > 0.0, r, 1.0)
            # np.add.at(f, (own element, point), ...) (scatter.py: the same sums)
            add_in_order(f, in_order_rows(oi[pi] * nqc + qi), coef[:, None] * D[pi, qi, ji])
        return f.reshape(no, nqc, 3)

    @_quiet_beyond_the_wall
    def add_report(self, out):
        """The report of an evaluation (in place; nothing to do if it has it): the gap and
        sbar at the nqc Gauss points by the closest-point projection of contact.py, the line
        force density |f(s)| there, f(s) = k sum_j w_j psi'(a) nu over the master points of the
        near pairs, total_force (nqp rule), complementarity (nqc rule), zones, and d_active: the
        gap > 0 at the report points and the depth > 0 at the nqp points."""
        if out["reported"]:
            return out
        out["reported"] = True
        c = out["_near"]
        if c is None:
            return out
        own_ids, x_own, other_ids, x_other, pairs = out["_inputs"]
        g = self.gauge
        no, nqc, J, k = len(own_ids), self.nqc, 0.5 * self.h, self.k
        ctx = g._context(own_ids, x_own, other_ids, x_other, pairs)
        _, gap, out["sbar"] = g.report_points(ctx, no)
        out["gap"] = gap
        out["end_depth"] = g.end_depth(ctx)     # the ends of an open rod
        out["zones"] = int(np.count_nonzero(gap > 0.0))
        f = self._report_force(c, x_own, no)
        out["force"] = np.linalg.norm(f, axis=2)
        out["complementarity"] = float(np.sum(self.wq * J * np.maximum(gap, 0.0) * out["force"]))
        # total force by the nqp rule over the couples in contact
        fp = np.zeros((no, self.nqp, 3))
        ac = self._active_couples(c)
        if len(ac["act"]):
            coef = ac["wm"] * law_force(ac["a"], self.a_s, self.wall) / np.where(ac["r"] > 0.0, ac["r"], 1.0)
            # np.add.at(fp, (slave element, q), ...) (scatter.py: the same sums)
            add_in_order(fp.reshape(-1, 3),
                         in_order_rows(c["oi"][ac["act"][ac["row"]]] * self.nqp + ac["q"]),
                         k * coef[:, None] * ac["D"])
        out["total_force"] = float(np.sum(self.wp * J * np.linalg.norm(fp, axis=2)))
        # the depth at the nqp points: the deepest couple of each (pair, q) in contact
        p, q, _, r = c["couples"]
        deep = np.zeros(0)
        if len(r):
            key = p * self.nqp + q
            first = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
            deep = np.maximum.reduceat(2.0 * self.eps - r, first)
        out["d_active"] = np.concatenate([gap[gap > 0.0], deep])
        return out
