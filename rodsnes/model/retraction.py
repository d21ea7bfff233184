"""The step's retraction: a Newton step taken so that it turns the rod's pieces instead of
stretching them (the Newton path's steps, solve/newton.py).

A step x + d in the exponential chart moves each node by dr and turns its frame by
exp(dtheta).  Between two neighbouring nodes the chord c = r_b - r_a becomes c + dc, while the
frames turn by about the mean t = (dtheta_a + dtheta_b) / 2.  Where the step turns a piece of
the rod by an angle t, the linear chord c + t x c is longer than the turned one exp(t) c by
|t|^2 |c| / 2: a stretch strain of |t|^2 / 2 that the stiffness EA answers at second order.
A nearly inextensible cantilever (EA = 1e6 EI / L^2) went |F| 5 -> 2.6e6 after its first
Newton step, and every other iteration was spent taking that stretch back.  The retraction
adds to every chord the second-order part of its turn,

    e = (exp(t^x) - I - t^x) c          (Rodrigues: (s - 1) t x c + k t x (t x c),
                                          s = sin|t| / |t|, k = (1 - cos|t|) / |t|^2),

summed along the rod from the nodes whose position components are held: a node's correction
is the sum of the excesses e between it and the held nodes, each component on its own (a
clamp holds three, a sliding end two): between two held nodes the sum's mismatch is spread
linearly in arclength, beyond the last one it is carried unchanged, a component held nowhere
keeps its mean, and a ring's mismatch around the loop is spread around it first.  The held
components themselves are not moved.

x + d + a(d), a = O(|d|^2), agrees with x + d to first order, so Newton keeps its quadratic
convergence (Newton on a manifold with any first-order retraction), and a rigid turn of the
whole rod about a clamp is taken exactly.  It is meant for Newton's steps, whose positions and
frames turn together (the consistent tangent links them), on a rod without contact: on the
minimiser's shifted steps (H + sigma M, positions and frames moving each by its own gradient)
and where contact holds strands of a ply together (the correction moves them relative to each
other) it was measured to cost iterations (docs/solver.md, The Newton path).

Collective: every rank computes the chords of its own elements (the compiled kernel,
so3_compiled.chord_turns, or the numpy path here, its reference), the sums along the rod come
from the ranks' runs of consecutive elements (one allgather), the held nodes' sums from their
owners (one allreduce).
"""
import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from rodsnes.model import so3_compiled
from rodsnes.model.partition import NDOF

# below this |t|^2 the series of s - 1 and k (their closed forms lose digits to cancellation)
SERIES = 1e-4


def turn_excess(t, c):
    """(exp(t^x) - I - t^x) c for rows of rotation vectors t and vectors c, (n, 3) each."""
    a2 = np.einsum("ij,ij->i", t, t)
    small = a2 < SERIES
    a = np.sqrt(np.where(small, 1.0, a2))
    sh, ch = np.sin(0.5 * a), np.cos(0.5 * a)
    sm1 = np.where(small, -a2 / 6.0 * (1.0 - a2 / 20.0 * (1.0 - a2 / 42.0)),
                   2.0 * sh * ch / a - 1.0)
    k = np.where(small, 0.5 - a2 / 24.0 * (1.0 - a2 / 30.0 * (1.0 - a2 / 56.0)),
                 2.0 * sh * sh / np.where(small, 1.0, a2))
    u = np.cross(t, c)
    return sm1[:, None] * u + k[:, None] * np.cross(t, u)


def chord_turns(conn, x, theta, alpha, compiled=True):
    """(ne, p + 1, 3): for each element (conn: its p + 1 local nodes) the turn excesses of its
    chords, t = alpha (theta_a + theta_b) / 2, summed over its first j chords (j = 0..p).  x,
    theta: (n_local, 3) positions and turns.  The compiled kernel where it is built (and
    ``compiled``), else numpy."""
    if compiled:
        out = so3_compiled.chord_turns(conn, x, theta, alpha)
        if out is not None:
            return out
    conn = np.asarray(conn)
    ne, p1 = conn.shape
    c = x[conn[:, 1:]] - x[conn[:, :-1]]
    t = 0.5 * alpha * (theta[conn[:, 1:]] + theta[conn[:, :-1]])
    e = turn_excess(t.reshape(-1, 3), c.reshape(-1, 3)).reshape(ne, p1 - 1, 3)
    out = np.zeros((ne, p1, 3))
    np.cumsum(e, axis=1, out=out[:, 1:])
    return out


class Retraction:
    """x + alpha d taken along the retraction (module docstring) for a problem's rod."""

    def __init__(self, problem, compiled=True):
        """For ``problem``'s rod and layout (collective: the ranks' runs are exchanged)."""
        self.problem = problem
        self.compiled = compiled
        lay = problem.layout
        mesh = lay.mesh
        self.layout = lay
        self.comm = lay.comm.tompi4py()
        self.p, self.closed, self.length = mesh.order, mesh.closed, mesh.length
        self.n = mesh.n_nodes
        self.s_nodes = np.asarray(mesh.s_nodes, dtype=float)
        elems = np.asarray(lay.owned_elems, dtype=np.int64)      # natural ids, ascending
        self.lconn = np.ascontiguousarray(lay.lconn, dtype=np.int64)
        self.owned = np.asarray(lay.owned_nodes, dtype=np.int64)
        self.s_owned = self.s_nodes[self.owned]
        # each owned node's (element row, j) among its owned elements' nodes: the node is
        # owned with the element that holds it first (partition.Layout.node_owner)
        # (elements ascending: a node's first place in their row-major nodes)
        ids, at = np.unique(np.asarray(mesh.conn)[elems].ravel(), return_index=True)
        self.node_flat = at[np.searchsorted(ids, self.owned)].astype(np.int64)  # in within (-1, 3)
        self.node_row = self.node_flat // (self.p + 1)
        self.xlocal = lay.xlocal.duplicate()        # X's local values (d's go to the layout's)
        # runs of consecutive owned elements, and where each element's run starts
        cut = np.flatnonzero(np.diff(elems) != 1) + 1
        starts = np.concatenate([[0], cut]).astype(np.int64) if len(elems) else np.zeros(0, int)
        self.run_starts = starts
        self.run_of = np.repeat(np.arange(len(starts)),
                                np.diff(np.concatenate([starts, [len(elems)]])))
        # every run's first element over all ranks, in the order of the rod: the place of this
        # rank's runs in the exclusive sums
        gathered = self.comm.allgather(elems[starts])
        every = np.concatenate(gathered).astype(np.int64)
        self.order = np.argsort(every, kind="stable")
        self.rank_runs = [len(f) for f in gathered]
        rank = self.comm.Get_rank()
        mine = np.arange(sum(self.rank_runs[:rank]), sum(self.rank_runs[:rank + 1]))
        rank_of_place = np.empty(len(every), dtype=np.int64)
        rank_of_place[self.order] = np.arange(len(every))
        self.my_places = rank_of_place[mine]                  # my runs' places in the rod
        # the runs' totals exchanged as 3 doubles a run and one more a rank (whether its held
        # rows changed): counts and displacements of the Allgatherv
        self.gather_counts = np.array([3 * r + 1 for r in self.rank_runs], dtype=np.int64)
        self.gather_displ = np.concatenate([[0], np.cumsum(self.gather_counts)[:-1]])
        self.held_rows = None               # the Dirichlet rows the held structure is of

    def _held_rows(self):
        """This rank's Dirichlet rows of positions (a copy)."""
        rows = np.asarray(self.problem.constraints.rows_local, dtype=np.int64)
        return rows[rows % NDOF < 3]

    def _make_held(self, rows):
        """The held structure for these rows of this rank (collective): per component this
        rank's owned held local nodes (held), every rank's held natural ids (ids, sorted), and
        where this rank's go among them (slots)."""
        self.held_rows = rows
        self.held = [np.unique(rows[rows % NDOF == k] // NDOF) for k in range(3)]
        everyone = self.comm.allgather([self.owned[h] for h in self.held])
        self.ids = [np.unique(np.concatenate([e[k] for e in everyone])).astype(np.int64)
                    for k in range(3)]
        self.slots = [np.searchsorted(self.ids[k], self.owned[self.held[k]]) for k in range(3)]
        self.free = [k for k in range(3) if len(self.ids[k]) == 0]   # the same on every rank
        self.sizes = np.cumsum([0] + [len(i) for i in self.ids])

    def _sums(self, X, alpha, d):
        """The step's sums along the rod: (within, offset, loop, anchors, held): the elements'
        sums of their chords' excesses (ne, p + 1, 3), each element's sum before it (ne, 3),
        the ring's loop mismatch (3), per component the held arclengths and sums that anchor
        it (a component held nowhere: its mean), this rank's held owned nodes per component.
        Collective."""
        lay = self.layout
        lay.scatter.scatter(X, self.xlocal, addv=PETSc.InsertMode.INSERT,
                            mode=PETSc.ScatterMode.FORWARD)
        x = self.xlocal.getArray(readonly=True).reshape(-1, NDOF)
        th = lay.local_view(d)
        within = chord_turns(self.lconn, x[:, 0:3], th[:, 3:6], alpha, self.compiled)
        wr = within.reshape(-1, 3)
        totals = within[:, -1, :]
        # sums along the rod: this rank's runs' totals, allgathered, in the rod's order (and
        # whether any rank's held rows changed since the held structure was made)
        ex = np.cumsum(totals, axis=0) - totals                  # exclusive, over my elements
        run_tot = (np.add.reduceat(totals, self.run_starts, axis=0) if len(totals)
                   else np.zeros((0, 3)))
        rows = self._held_rows()
        changed = self.held_rows is None or not np.array_equal(rows, self.held_rows)
        send = np.concatenate([run_tot.ravel(), [1.0 if changed else 0.0]])
        recv = np.empty(int(self.gather_counts.sum()))
        self.comm.Allgatherv(send, [recv, (self.gather_counts, self.gather_displ), MPI.DOUBLE])
        flags = recv[self.gather_displ + self.gather_counts - 1]
        if np.any(flags != 0.0):
            self._make_held(rows)
        keep = np.ones(len(recv), dtype=bool)
        keep[self.gather_displ + self.gather_counts - 1] = False
        run_all = recv[keep].reshape(-1, 3)[self.order]
        before = np.concatenate([np.zeros((1, 3)), np.cumsum(run_all, axis=0)])
        held, ids, free, sizes = self.held, self.ids, self.free, self.sizes
        loop = before[-1].copy()
        offset = ex - ex[self.run_starts][self.run_of] + before[self.my_places][self.run_of]
        offset = np.ascontiguousarray(offset)

        def sums(nodes, k):
            """Component k of the sums at these owned nodes (the kernel's arithmetic)."""
            c = np.take(wr[:, k], self.node_flat[nodes]) + np.take(offset[:, k],
                                                                    self.node_row[nodes])
            if self.closed:                              # a ring: its loop's mismatch spread
                c = c - loop[k] * (self.s_owned[nodes] / self.length)
            return c
        # the held nodes' sums from their owners (and each component's mean where none is held)
        packed = np.zeros(int(sizes[3]) + len(free))
        for k in range(3):
            packed[sizes[k] + self.slots[k]] = sums(held[k], k)
        every = np.arange(len(self.owned))
        for i, k in enumerate(free):
            packed[sizes[3] + i] = sums(every, k).sum()
        self.comm.Allreduce(MPI.IN_PLACE, packed, op=MPI.SUM)
        anchors = []
        for k in range(3):
            if k in free:
                anchors.append((np.zeros(1), packed[sizes[3] + free.index(k):][:1] / self.n))
                continue
            hs, hv = self.s_nodes[ids[k]], packed[sizes[k]:sizes[k + 1]]
            if self.closed:          # periodic: the held nodes a loop before and after too
                hs = np.concatenate([hs - self.length, hs, hs + self.length])
                hv = np.concatenate([hv, hv, hv])
            anchors.append((hs, hv))
        return within, offset, loop, anchors, held

    def _add(self, sums, out, scale):
        """out[:, 0:3] += scale x the owned nodes' corrections (out: (n_owned, >= 3) rows)."""
        within, offset, loop, anchors, held = sums
        if self.compiled and so3_compiled.retract_nodes(
                self.node_flat, self.node_row, within, offset, self.s_owned, self.closed, loop,
                self.length, anchors, scale, out):
            return
        C = np.take(within.reshape(-1, 3), self.node_flat, axis=0)
        C += np.take(offset, self.node_row, axis=0)
        if self.closed:
            C -= np.outer(self.s_owned / self.length, loop)
        for k, (hs, hv) in enumerate(anchors):
            C[:, k] -= np.interp(self.s_owned, hs, hv)
            C[held[k], k] = 0.0                         # exactly zero where held
        out[:, 0:3] += scale * C

    def correction(self, X, alpha, d):
        """(n_owned, 3) corrections of the owned nodes' positions for the step X + alpha d (X
        at the step's start, its theta zero: recentred).  Collective."""
        out = np.zeros((len(self.owned), 3))
        self._add(self._sums(X, alpha, d), out, 1.0)
        return out

    def destroy(self):
        self.xlocal.destroy()

    def move(self, X, alpha, d):
        """X <- X + alpha d along the retraction; returns the correction (n_owned, 3) added to
        the positions.  Collective."""
        corr = self.correction(X, alpha, d)
        X.axpy(alpha, d)
        with X as a:
            a.reshape(-1, NDOF)[:, 0:3] += corr
        return corr

    def retract_direction(self, X, Y, step=1.0):
        """SNES's direction Y (its new iterate X - step Y) changed so that the iterate is the
        retracted one: Y's positions less the correction / step.  Collective."""
        sums = self._sums(X, -step, Y)
        with Y as a:
            self._add(sums, a.reshape(-1, NDOF), -1.0 / step)
