"""The clamps' mounts as obstacles (with self-contact, ``-contact_supports``): the clamping axis
beyond both ends of a rod clamped at its start and sliding at its end.

The link of such a rod is counted with the closure at infinity along the clamping axis
(topology.close_open_rod): the half-lines

    H_0 = {x_0 - t t_0},   H_1 = {x_N + t t_N},   t >= 0,

behind the start clamp (x_0, tangent t_0) and beyond the sliding end (x_N, tangent t_N, the
axis it slides on).  A rod that passes through H_0 or H_1 changes that link by +-1 without
passing through itself: it has gone round a clamp, which the clamp's mount forbids (the stem
behind the fixed clamp, the rail the sliding one runs on).  Without the mounts the energy of a
twisted rod can fall by going round (the plectoneme at 9.415 turns: relaxation looped a strand
behind the start clamp, E 320.7 -> 312.4, and every step beyond changed the link by 1 or 2).
Each half-line is a rigid obstacle of zero thickness in contact with the rod's tube:

    g_k(s) = R - dist(r(s), H_k),      E_s = mu sum_k int psi(<g_k(s)>) ds,
    psi(g) = g^2 / 2 + beta(g),

with the self-contact's penalty mu and R = a + 2 (eps - a), a the tube's radius and eps the
law's (-contact_standoff): the rod stands as far off a mount as off another strand, and
g_k - 2 (eps - a) is the depth into the tube that the promise bounds (R = eps = a without a
standoff), at the contact's Gauss points, leaving out
the arclength delta (the contact exclusion) next to clamp k, which the rod leaves along the
axis.  beta is the pair potential's wall (-contact_wall; potential.py, The wall: 0 up to a_b,
infinite at a_w, in the same depths g as the couples' a), so that the promise holds against
the mounts as against another strand; without the wall (or with the closest-point law)
beta = 0.  The line searches cap every trial's deepest penetration, the mounts' included,
short of a_w (ContactTerm.depth_allowed): a mount without the barrier could be pressed up to
that cap, where every step that pressed it further was cut to nothing (the plectoneme with
-contact_standoff 0.05 stalled so at 8.47 turns, 200 iterations a try).  With c = p +
max((r - p).e, 0) e the closest point of H = {p + t e} and n = (r - c) / dist:

    dE/dr(s) = -mu psi'(<g>) n,        dE/dp = +mu psi'(<g>) n      (p = x_N slides; x_0 is held)
    d2E/dr2 = mu [psi''(<g>) n n^T - psi'(<g>) (A - n n^T) / dist] =: H,
    d2E/dr dp = -H,   d2E/dp2 = H,

A = I - e e^T on the half-line's body, I at its end point p.  E_s is C1 (the distance to a
convex set is C1 outside it).  The sliding end's coupling blocks (each element with the end
node) are preallocated once (``pattern_pairs``: O(N) blocks).  Pure numpy but for
``SupportTerm``, which adds to the parallel residual and Jacobian (ContactTerm calls it)."""
import numpy as np
from mpi4py import MPI

from rodsnes.contact import search
from rodsnes.contact.potential import wall_law
from rodsnes.contact.scatter import add_in_order, in_order_rows
from rodsnes.model.partition import add_position_blocks, allreduce


def half_line_distance(x, p, e, projector=True):
    """Distance of points x (M, 3) to the half-line {p + t e, t >= 0} (|e| = 1): dist (M,),
    unit normal n = (x - c) / dist (M, 3) and (with ``projector``, else None) the projector A
    (M, 3, 3) of the distance's Hessian (A - n n^T) / dist (I - e e^T where the closest point c
    is on the body, I at p)."""
    v = np.asarray(x, dtype=float) - p
    t = v @ e
    body = t > 0.0
    w = v - np.where(body, t, 0.0)[:, None] * e
    dist = np.linalg.norm(w, axis=1)
    n = w / np.where(dist > 0.0, dist, 1.0)[:, None]
    if not projector:
        return dist, n, None
    A = np.broadcast_to(np.eye(3), (len(v), 3, 3)).copy()
    A[body] -= np.outer(e, e)
    return dist, n, A


def penalty(x, wds, p, e, eps, mu, hessian=True, wall=None):
    """mu sum_q wds_q psi(<g_q>) with g = eps - dist(x_q, H) for the half-line H = {p + t e},
    psi(g) = g^2/2, plus the wall's barrier (``wall`` = (a_b, a_w): potential.wall_law; +inf
    from a_w on): energy, g (M,), gradient dE/dx (M, 3) and (with ``hessian``, else None)
    Hessian H (M, 3, 3) per point (module docstring; d/dp is minus the gradient, and -H, H)."""
    return penalty_at(*half_line_distance(x, p, e, projector=hessian), wds, eps, mu, wall)


def penalty_at(dist, n, A, wds, eps, mu, wall=None):
    """penalty() from the points' distance, normal and (None: no Hessian) projector.  A point at
    or beyond the wall makes the energy infinite and its gradient and Hessian not finite (a
    trial the line search refuses), without warnings."""
    if wall is None:
        return _penalty_at(dist, n, A, wds, eps, mu, None)
    with np.errstate(invalid="ignore", over="ignore"):
        return _penalty_at(dist, n, A, wds, eps, mu, wall)


def _penalty_at(dist, n, A, wds, eps, mu, wall):
    hessian = A is not None
    g = eps - dist
    act = g > 0.0
    gp = np.where(act, g, 0.0)
    psi, force = 0.5 * gp ** 2, gp.copy()
    if wall is not None:
        psi = psi + wall_law(gp, wall, 0)
        force = force + wall_law(gp, wall, 1)
    energy = mu * float(np.sum(wds * psi))
    grad = -(mu * wds * force)[:, None] * n
    if not hessian:
        return energy, g, grad, None
    stiff = act.astype(float)
    if wall is not None:
        stiff = stiff + wall_law(gp, wall, 2)
    nn = np.einsum("mi,mj->mij", n, n)
    curv = (A - nn) / np.where(act, dist, 1.0)[:, None, None]
    H = (mu * wds * stiff)[:, None, None] * nn - (mu * wds * force)[:, None, None] * curv
    return energy, g, grad, H


class SupportTerm:
    """H_0 and H_1 (module docstring) on this rank's owned elements.  ``axis_end``: the sliding
    end's tangent (its slide direction), ``axis_start`` the start clamp's tangent; ``wall``
    the self-contact's wall (a_b, a_w) in the law's depths, or None."""

    def __init__(self, mesh, layout, kernel, x_start, axis_start, axis_end, reach=None,
                 wall=None):
        self.mesh, self.layout, self.kernel = mesh, layout, kernel
        self.reach = float(kernel.eps if reach is None else reach)     # R (module docstring)
        self.wall = wall
        self.comm = layout.comm.tompi4py()
        self.own_ids = layout.owned_elems
        self.lconn = layout.lconn
        self.rows = in_order_rows(self.lconn)          # the residual's additions (scatter.py)
        self.x_start = np.asarray(x_start, dtype=float)
        self.e = (-np.asarray(axis_start, dtype=float) / np.linalg.norm(axis_start),
                  np.asarray(axis_end, dtype=float) / np.linalg.norm(axis_end))
        s = kernel.slave_arclength(self.own_ids)                   # (no, nqc)
        self.wds = np.broadcast_to(kernel.wq * (0.5 * kernel.h), s.shape)
        # the arclength next to each clamp that leaves it along the axis is not in contact
        self.mask = (s >= kernel.delta, s <= mesh.length - kernel.delta)
        self.end = mesh.n_nodes - 1
        li = layout.nat2local[self.end]
        self.end_local = int(li) if 0 <= li < layout.n_owned else -1    # owner's local index
        self.end_row = int(layout.nat2petsc[self.end])

    def end_position(self, r_loc):
        """x_N on every rank (its owner's value).  Collective (on one rank the owner's value
        itself, which is what the allreduce returns there)."""
        x = r_loc[self.end_local] if self.end_local >= 0 else np.zeros(3)
        return allreduce(self.comm, np.array(x, dtype=float))

    def obstacles(self, p_end):
        """(point, direction) of H_0 and H_1, with the sliding end at p_end."""
        return (self.x_start, self.e[0]), (p_end, self.e[1])

    def evaluate(self, r_loc, tangent=True):
        """Energy (this rank), per point g (no, nqc) per obstacle, element residual (no, p+1,
        3), the end node's reaction (3,) of this rank, and with ``tangent`` (or later,
        ``add_tangent``) per active element the Hessian blocks (ne, p+2, p+2, 3, 3) over its
        nodes and the end node.  Collective."""
        k = self.kernel
        X = r_loc[self.lconn]                                        # (no, p+1, 3)
        xq = np.matmul(k.Nq, X)                                      # (no, nqc, 3)
        p_end = self.end_position(r_loc)
        no, n1 = X.shape[0], X.shape[1]
        out = {"energy": 0.0, "vec": np.zeros((no, n1, 3)), "end_force": np.zeros(3),
               "gap": [], "force": np.zeros((no, k.nqc)), "blocks": None, "elems": None,
               "_at": (xq, p_end)}
        for j, (p, e) in enumerate(self.obstacles(p_end)):
            m = self.mask[j]
            if not no or not m.any():
                out["gap"].append(np.full((no, k.nqc), -np.inf))
                continue
            gap = np.full((no, k.nqc), -np.inf)
            dist, n, _ = half_line_distance(xq[m], p, e, projector=False)
            gap[m] = self.reach - dist
            out["gap"].append(gap)
            if not (gap > 0.0).any():            # no point presses into this mount: no force
                continue
            energy, g, grad, _ = penalty_at(dist, n, None, self.wds[m], self.reach, k.mu,
                                            self.wall)
            out["energy"] += energy
            G = np.zeros((no, k.nqc, 3))
            G[m] = grad
            out["vec"] += np.einsum("qa,eqc->eac", k.Nq, G)
            out["end_force"] -= grad.sum(axis=0) if j == 1 else 0.0
            f = np.zeros((no, k.nqc))
            f[m] = np.linalg.norm(grad, axis=1) / self.wds[m]        # line force density
            out["force"] += f
        if tangent:
            self.add_tangent(out)
        return out

    def add_tangent(self, out):
        """The Hessian blocks of an evaluation (in place; nothing to do if it has them): per
        obstacle the elements with a point pressing into it (g > 0)."""
        if out["blocks"] is not None:
            return out
        k = self.kernel
        xq, p_end = out["_at"]
        no, n1 = xq.shape[0], self.lconn.shape[1]
        out["blocks"], out["elems"] = [], []
        for j, (p, e) in enumerate(self.obstacles(p_end)):
            m = self.mask[j]
            act = np.flatnonzero((out["gap"][j] > 0.0).any(axis=1)) if no else []
            if not len(act):
                continue
            Hq = np.zeros((no, k.nqc, 3, 3))
            Hq[m] = penalty(xq[m], self.wds[m], p, e, self.reach, k.mu, wall=self.wall)[3]
            Hq = Hq[act]
            Nq = k.Nq
            B = np.zeros((len(act), n1 + 1, n1 + 1, 3, 3))
            B[:, :n1, :n1] = np.einsum("qa,qb,eqij->eabij", Nq, Nq, Hq, optimize=True)
            if j == 1:                       # the end point slides: its coupling
                NH = np.einsum("qa,eqij->eaij", Nq, Hq)
                B[:, :n1, n1] = -NH
                B[:, n1, :n1] = -NH
                B[:, n1, n1] = Hq.sum(axis=1)
            out["blocks"].append(B)
            out["elems"].append(self.own_ids[act])
        return out

    def add_residual(self, out, Floc):
        """Element residual into the local rows; the end node's reaction, summed over the
        ranks, into its owner's row.  Collective."""
        add_in_order(Floc[:, 0:3], self.rows, out["vec"])      # np.add.at (scatter.py)
        f_end = allreduce(self.comm, out["end_force"])
        if self.end_local >= 0:
            Floc[self.end_local, 0:3] += f_end

    def add_jacobian(self, out, P):
        m = self.mesh
        self.add_tangent(out)
        for elems, B in zip(out["elems"], out["blocks"]):
            nodes = search.element_node_ids(elems, m.order, m.nelem, m.closed)
            nodes = np.concatenate([nodes, np.full((len(elems), 1), self.end)], axis=1)
            add_position_blocks(P, self.layout, nodes, B.transpose(0, 1, 3, 2, 4))

    def pattern_pairs(self):
        """Element pairs (e, last element) for every element: the end node's coupling."""
        n = self.mesh.nelem
        return np.stack([np.arange(n), np.full(n, n - 1)], axis=1).astype(np.int64)

    @staticmethod
    def deepest_local(out):
        """max g over this rank's points (positive: the tube presses into a mount)."""
        return max([float(g.max()) if g.size else -np.inf for g in out["gap"]] + [-np.inf])

    def summary(self, out, offset=0.0):
        """Total force on the mounts, points pressing on them, and the gap to the tube's
        surface (g - offset, offset = 2 (eps - a)), all ranks.  Collective."""
        loc = np.array([float(np.sum(out["force"] * self.wds)),
                        float(sum(int((g > 0).sum()) for g in out["gap"]))])
        tot = self.comm.allreduce(loc)
        return {"support_force": float(tot[0]), "support_points": int(tot[1]),
                "support_min_gap": float(offset - self.comm.allreduce(self.deepest_local(out),
                                                                      op=MPI.MAX))}
