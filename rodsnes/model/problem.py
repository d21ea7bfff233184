"""The discrete equilibrium problem: residual and Jacobian of the total energy over the
owned elements, assembled across ranks, with Dirichlet rows (DESIGN.md "problem.py").

State (DESIGN.md "state.py" lives here as RodState): nodal reference rotations q_ref for the
local (owned + ghost) nodes, and the SNES vector X = (r, theta) per node, theta being the
rotation increment about q_ref: R = exp(theta^x) R_ref.  SNES.setUpdate calls recentre():
R_ref <- exp(theta^x) R_ref, theta <- 0 (PETSC_NOTES.md "Manifold update").

Dirichlet rows: residual F_i = X_i - target_i, Jacobian row and column i zeroed with 1 on the
diagonal (MatZeroRowsColumns).  Prescribed rotations are put into q_ref with theta_i = 0.
Closed rods have no ends: node 0 is held fixed, which removes the six rigid-body modes without
changing the equilibrium (the resultant of the internal forces of a free ring vanishes).
"""
import numpy as np
from petsc4py import PETSc

from rodsnes.model import assembly, elastic, fe, so3
from rodsnes.model.partition import NDOF, DirichletRows, SplitBlocks, kept
from rodsnes.errors import SceneError
from rodsnes.model import topology
from rodsnes.model.term import same_patterns

# the largest nodal rotation of one step (rad): the exponential update is exact for any angle,
# but a step that turns a node by more than this is far outside its quadratic model
MAX_ROTATION = 1.0


def reference_strains(rod, mesh, conn, strains):
    """Stress-free strains e0 = (v_hat, u_hat) at the points where ``strains(q, x)`` evaluates.

    Without -rod_kappa0: the strains of the reference shape (stress-free as built).  With it:
    v_hat = (0, 0, 1), u_hat = kappa0, plus the strain change that the imperfection makes to
    the reference shape (so an imperfect, naturally straight rod is imperfect when unloaded)."""
    e = strains(mesh.q_ref[conn], mesh.x_ref[conn])
    if rod.kappa0 is None:
        return e
    e0 = np.zeros_like(e)
    e0[..., 2] = 1.0
    e0[..., 3:6] = rod.kappa0
    if rod.imperfection:
        e0 += e - strains(mesh.q_perfect[conn], mesh.x_perfect[conn])
    return e0


class RodState:
    """q_ref (local nodes) + X; snapshot/restore for rejected load steps."""

    def __init__(self, layout, q_local, X):
        self.layout = layout
        self.q_ref = q_local.copy()
        self.X = X

    def snapshot(self):
        return self.q_ref.copy(), self.X.copy()

    def restore(self, snap):
        self.q_ref[:] = snap[0]
        snap[1].copy(self.X)

    def snapshot_of(self, positions, directors, rotation=None):
        """A snapshot (restore() takes it) of the configuration given by the gathered nodal
        positions (n,3) and directors (n,3,3) of a step in result.h5: q_ref on the local
        nodes, X = (r, theta = 0) on the owned ones.  With ``rotation`` (n,4), the quaternions
        the run held (result.h5 ``rotation``), q_ref is those, bit for bit: the directors'
        quaternion differs from them by round-off, and a restart would not take the
        iterations of the run it resumes."""
        if rotation is not None:
            q = np.array(np.asarray(rotation)[self.layout.local_nodes], dtype=float)
        else:
            q = so3.quat_from_rot(np.asarray(directors)[self.layout.local_nodes])
        X = self.X.duplicate()
        with X as a:
            a = a.reshape(-1, NDOF)
            a[:, 0:3] = np.asarray(positions)[self.layout.owned_nodes]
            a[:, 3:6] = 0.0
        return q, X

    def snapshot_of_step(self, step):
        """snapshot_of a step as io.results.read_step returns it: its positions, directors and,
        where the file has them, the rotation quaternions (a restart resumes bit for bit)."""
        return self.snapshot_of(step["positions"], step["directors"], step.get("rotation"))

    def predict(self, prev, ratio, twist=None):
        """Secant predictor along the load path: from the converged state n (current, theta = 0)
        and the previous converged state ``prev`` (a snapshot), move to
        r + ratio (r_n - r_{n-1}),  theta = ratio log(R_n R_{n-1}^T).
        With ``twist`` (an angle per local node: the material twist about d3 that the last
        step's end turn spread along the rod) that twist is factored out of the relative
        rotation first, R_n = exp(psi^x) R_{n-1} exp(twist e3^x), and extrapolated as twist:
        R = exp(ratio psi^x) R_n exp(ratio twist e3^x).  A node near an end turned by more
        than half a turn in one step then extrapolates its turn, not the short way round."""
        q_prev, X_prev = prev
        no = self.layout.n_owned
        if twist is None:
            psi = so3.log_relative(self.q_ref[:no], q_prev[:no])
        else:
            psi = so3.log_relative(self.q_ref[:no], so3.twisted(q_prev, twist)[:no])
            self.q_ref[:] = so3.twisted(self.q_ref, ratio * twist)
        xp = X_prev.getArray(readonly=True).reshape(-1, NDOF)
        with self.X as a:
            a = a.reshape(-1, NDOF)
            a[:, 0:3] += ratio * (a[:, 0:3] - xp[:, 0:3])
            a[:, 3:6] = ratio * psi

    def recentre(self):
        """Fold theta into the reference rotations: q_ref <- qexp(theta) * q_ref, theta <- 0."""
        xl = self.layout.to_local(self.X)
        th = xl[:, 3:6]
        if np.any(th):
            self.q_ref[:] = so3.rotated(th, self.q_ref, normalize=True)
            with self.X as a:
                a.reshape(-1, NDOF)[:, 3:6] = 0.0

    def local_config(self, X=None):
        """Positions (n_local,3) and rotations q (n_local,4) at the vector X (default: state),
        both new C-contiguous arrays (the kernels' layout: no copy of the owned and ghost
        values first and of the positions again)."""
        xl = self.layout.local_view(self.X if X is None else X)
        th = xl[:, 3:6]
        r = np.array(xl[:, 0:3])
        if not th.any():            # at a recentred iterate: exp(0) q_ref = q_ref, bit for bit
            return r, self.q_ref.copy()
        return r, so3.rotated(th, self.q_ref)


def sliding_axis(q):
    """The coordinate axis a sliding end of rotation q slides along (its tangent d3), or None
    where the tangent lies along no axis."""
    t = so3.rot(q)[:, 2]
    axis = int(np.argmax(np.abs(t)))
    return axis if abs(abs(t[axis]) - 1.0) <= 1e-10 else None


class Constraints:
    """Fixed dofs and prescribed end rotation (bc_end_turns), stepped with lambda."""

    def __init__(self, bc, mesh, layout):
        self.layout = layout
        n = mesh.n_nodes
        fixed = []                 # (natural node, component)
        self.end_turns = 0.0       # turns prescribed at the end s = L (stepped with lambda)
        self.rotation_targets = []  # (natural node, callable lam -> q)
        x_init, q_init = mesh.x_init, mesh.q_init
        if mesh.closed:
            fixed += [(0, c) for c in range(6)]
            self.rotation_targets.append((0, lambda lam: q_init[0]))
        else:
            for node, kind in ((0, bc.start), (n - 1, bc.end)):
                if kind in ("clamped", "pinned"):
                    fixed += [(node, c) for c in range(3)]
                if kind in ("clamped", "sliding"):
                    fixed += [(node, c) for c in range(3, 6)]
                if kind == "sliding":
                    axis = sliding_axis(q_init[node])
                    if axis is None:
                        raise SceneError("-bc_end sliding: the end tangent must lie along a coordinate "
                                         f"axis (it is {so3.rot(q_init[node])[:, 2]}); use "
                                         "-bc_end clamped or a straight rod")
                    fixed += [(node, c) for c in range(3) if c != axis]
            if bc.start == "clamped":
                self.rotation_targets.append((0, lambda lam: q_init[0]))
            if bc.end in ("clamped", "sliding"):
                d3 = so3.rot(q_init[n - 1])[:, 2]
                turns = self.end_turns = float(bc.end_turns)
                self.rotation_targets.append(
                    (n - 1, lambda lam: so3.qmul(so3.qexp(2 * np.pi * turns * lam * d3), q_init[n - 1])))
        fixed = sorted(set(fixed))
        nodes = np.array([f[0] for f in fixed], dtype=np.int64)
        comps = np.array([f[1] for f in fixed], dtype=np.int64)
        self._build(nodes, comps, np.where(comps < 3, x_init[nodes, np.minimum(comps, 2)], 0.0))

    def max_load_increment(self, max_turn):
        """The largest load increment whose prescribed end rotation (-bc_end_turns T, applied
        as lambda 2 pi T about the end's axis) turns the end by at most max_turn turns
        (inf without prescribed turns)."""
        return max_turn / abs(self.end_turns) if self.end_turns else np.inf

    def hold(self, node, comp, value):
        """One more fixed position dof (natural node, component 0..2) at ``value``."""
        nodes = np.append(self.nodes, node)
        comps = np.append(self.comps, comp)
        self._build(nodes, comps, np.append(self.target, value))

    def _build(self, nodes, comps, target):
        layout = self.layout
        self.nodes, self.comps, self.target = nodes, comps, target
        gidx = NDOF * layout.nat2petsc[nodes] + comps
        rank = layout.comm.getRank()
        lo, hi = NDOF * layout.starts[rank], NDOF * layout.starts[rank + 1]
        own = (gidx >= lo) & (gidx < hi)
        self.rows_global = gidx[own].astype(PETSc.IntType)
        self.rows_local = (gidx[own] - lo).astype(np.int64)
        self.target_own = self.target[own]
        self.is_rows = PETSc.IS().createGeneral(self.rows_global, comm=layout.comm)
        mask = np.zeros((layout.n_global, NDOF), dtype=bool)      # PETSc block numbering
        mask[layout.nat2petsc[nodes], comps] = True
        # read-only: what is kept from it (the touched blocks, RestElements' masks) is keyed
        # by its identity, so a change of the constraints is a new mask (hold, _build)
        mask.setflags(write=False)
        self.block_mask = mask

    def apply(self, lam, state):
        """Put the prescribed values at load factor lam into the state."""
        lay = self.layout
        for node, fun in self.rotation_targets:
            li = lay.nat2local[node]
            if li >= 0:
                state.q_ref[li] = fun(lam)
        with state.X as a:
            a[self.rows_local] = np.where(self.rows_local % NDOF < 3, self.target_own, 0.0)


class RestElements:
    """The elements of a Jacobian that go in through the matrix's own insertion (RodProblem.
    _add_rest_tangents), prepared once per pattern and Dirichlet mask: their local and global
    node blocks, the rows this rank sets (-1 elsewhere: owner computes) and the Dirichlet
    mask of their tangents' rows and columns (DirichletRows._masked's, for every element at
    once: 1 on an element that touches no constraint).  The tangents then go in masked, by one
    MatSetValuesBlocked of them all in their order: the entries and the order of their
    additions of DirichletRows.setValuesBlockedRCV (the runs it inserts through OwnBlocksFirst
    go into the same rows of the same matrix, in the same order)."""

    def __init__(self, problem, ids, dirichlet):
        self.ids = np.asarray(ids)
        self.dirichlet = dirichlet.mask         # what the plan holds for (its identity)
        g, rows = problem._gconn, problem._rows
        self.lconn = problem.row_lconn[self.ids]
        self.cols = np.ascontiguousarray(g[self.ids], dtype=PETSc.IntType)
        self.rows = np.ascontiguousarray((g if rows is g else rows)[self.ids],
                                         dtype=PETSc.IntType)
        n = len(self.ids)
        mask = dirichlet.mask
        # (the rows of another rank, -1, are the matrix's to ignore: kept)
        keep_r = ~mask[np.maximum(self.rows, 0)] | (self.rows < 0)[:, :, None]
        keep_c = ~mask[self.cols]
        keep_r, keep_c = keep_r.reshape(n, -1), keep_c.reshape(n, -1)
        self.keep = (keep_r[:, :, None] & keep_c[:, None, :]).astype(np.float64)

    def add(self, H, dirichlet):
        """Add the elements' tangents H (n, k c, k c), masked (H is changed), into the matrix
        of ``dirichlet`` (the one this plan was made for; not kept here: the plan lives in the
        matrix's attributes, and a wrapper of the matrix there would make a cycle)."""
        H *= self.keep
        target = SplitBlocks(dirichlet.raw) if dirichlet.split else dirichlet.raw
        target.setValuesBlockedRCV(self.rows, self.cols, H, addv=PETSc.InsertMode.ADD)


class RodProblem:
    """Residual, Jacobian and energy of the rod at load factor ``lam`` (set by the solver): the
    rod's strain energy plus the ``terms`` (model/term.Term: the loads, contact, ...) that the
    run builds from the scene (run.scene_terms), summed in their order.  The problem knows the
    terms only through that interface."""

    def __init__(self, scene, mesh, layout, terms):
        self.scene, self.mesh, self.layout = scene, mesh, layout
        rod = scene.rod
        nq = fe.quadrature_points(rod.quadrature, rod.order)
        self.nq = nq
        stiff = (rod.GA1, rod.GA2, rod.EA, rod.EI1, rod.EI2, rod.GJ)
        self.elastic = elastic.ElasticRod(rod.order, nq, mesh.h, stiff, kernel=rod.kernel)
        lconn = layout.lconn
        own = layout.owned_elems
        # the reference strains of the elements the rows of the owned nodes are summed from
        # (layout.row_elems: the owned ones first, e0[:len(own)])
        e0 = reference_strains(rod, mesh, mesh.conn[layout.row_elems], self.elastic.strains)
        self.e0_base = e0
        self.elastic.set_reference(e0.copy())
        c = scene.contact
        if c.enabled and c.curvature:
            # thickness bound on bending (elastic.py): flexure above 1/eps costs EI/p per unit of
            # squared excess, so a bending moment of twice EI/eps overshoots kappa_max by p
            self.elastic.set_curvature_limit(1.0 / scene.contact_radius,
                                             max(rod.EI1, rod.EI2) / c.penetration)
        self.load_twist = getattr(scene.loads, "twist_turns", 0.0) or 0.0
        self.constraints = Constraints(scene.bc, mesh, layout)
        X = layout.create_vec()
        q_local = mesh.q_init[layout.local_nodes]
        with X as a:
            a = a.reshape(-1, NDOF)
            a[:, 0:3] = mesh.x_init[layout.owned_nodes]
            a[:, 3:6] = 0.0
        self.state = RodState(layout, q_local, X)
        self.terms = list(terms)
        self.lam = 0.0
        self._topology = None              # (state key, topology) of the last topology()
        # every term's pattern (Term.pattern) the Jacobian J is preallocated for
        self.patterns = self.patterns_at(mesh.x_init[layout.local_nodes])
        self._J = None                      # the full Jacobian, made when first asked for (J)
        self.F = layout.create_vec()
        self.lconn = lconn                  # the owned elements' local nodes: the energy
        self.n_elems = len(own)
        # the residual's and tangent's elements (owned, then the others touching an owned
        # node: the owner computes its rows, layout.row_elems), their node blocks (PETSc
        # ids), and the block rows this rank sets (-1: another rank's node; the node blocks
        # themselves where every node is this rank's, as on one rank)
        self.row_lconn = layout.row_lconn
        self._gconn = layout.row_gconn.astype(PETSc.IntType)
        self._rows = (self._gconn if (layout.row_rows >= 0).all()
                      else layout.row_rows.astype(PETSc.IntType))
        # the rows of other ranks' nodes summed into their owners' (reverse scatter, the
        # Jacobian's stash) only where some term needs it (Term.owner_computes); the same on
        # every rank (the terms are the scene's)
        self.sums_ghost_rows = not all(t.owner_computes for t in terms)
        self.stats = {}
        self.inertia = None                 # stability.Inertia, made at the first count
        self.planar = None                  # planar.PlanarSystem of a planar run (run.py)
        self._e0_nodes = None
        self.on_pattern_change = None
        # the largest move per Newton step of a node a term watches (precheck, limit 1; 0: none)
        limits = [t.step_limit for t in self.terms if t.step_limit]
        self.step_limit = min(limits) if limits else 0.0
        # energy as the line search's merit function (precheck, limit 3): only where every
        # term has a potential (loads.nonconservative)
        self.energy_descent = bool(limits) and all(t.conservative for t in self.terms)
        self.gauge = None                   # (node, component, global row) of hold_sliding
        self.gauge_component = None         # the component a restart holds (the run's)
        # uniform stress-free strains of the perfect rod (the imperfection, a device to pick a
        # branch, only weakly breaks the sliding symmetry: hold_sliding's reaction shows how much)
        if rod.kappa0 is not None:
            e_perfect = np.broadcast_to(np.r_[0.0, 0.0, 1.0, rod.kappa0], e0.shape)
        else:
            cp = mesh.conn[own]
            e_perfect = self.elastic.strains(mesh.q_perfect[cp], mesh.x_perfect[cp])
        e_perfect = np.reshape(e_perfect, (-1, NDOF))
        from mpi4py import MPI
        ext = np.concatenate([-np.min(e_perfect, axis=0, initial=np.inf),
                              np.max(e_perfect, axis=0, initial=-np.inf)])
        layout.comm.tompi4py().Allreduce(MPI.IN_PLACE, ext, op=MPI.MAX)   # (-min, max) over ranks
        lo, hi = -ext[:NDOF], ext[NDOF:]
        self.uniform = bool(np.all(hi - lo <= 1e-9 * (1.0 + np.abs(hi) + np.abs(lo))))

    def hold_sliding(self):
        """Gauge for a closed ring of uniform stress-free strains (-rod_closed_gauge): shifting
        the material along the centreline, s -> s + a (then moving the ring rigidly so that
        node 0 is back in place), is a symmetry of the continuous problem, so its writhed
        equilibria come in one-parameter families; the discretisation pins them only weakly
        (lowest Hessian eigenvalue 2.8e-6 against 4.7e-5 next for the writhed Michell ring), and
        a descent or Newton creeps along that valley.  This holds the coordinate of the
        node opposite node 0 that lies most along its tangent at its current value (a
        restart: the one the run held, gauge_component from result.h5).  Called
        by the minimiser at the start of its load path; a circle does not feel it.  Its reaction (the force the discretisation's weak pinning would exert, zero in the
        continuous problem) is reported by gauge_report (summary.json ``gauge``).  Collective."""
        m = self.mesh
        if (self.gauge is not None or not m.closed or not self.scene.rod.closed_gauge
                or not self.uniform):
            return False
        node = m.n_nodes // 2
        lay = self.layout
        r, q = self.state.local_config()
        li = lay.nat2local[node]
        own = li >= 0 and li < lay.n_owned
        comm = lay.comm.tompi4py()
        val = comm.allgather((r[li].copy(), so3.rot(q[li])[:, 2]) if own else None)
        x, t = next(v for v in val if v is not None)
        # a restart holds the coordinate the run held (at its held value), not the one most
        # along the tangent now
        comp = int(np.argmax(np.abs(t))) if self.gauge_component is None else self.gauge_component
        self.constraints.hold(node, comp, float(x[comp]))
        self.gauge = (node, comp, NDOF * int(lay.nat2petsc[node]) + comp)
        return True

    def gauge_report(self):
        """{node, component, reaction} of the sliding gauge at the current state (None without
        one); reaction = the force the held coordinate carries.  Collective."""
        if self.gauge is None:
            return None
        self.residual(None, self.state.X, self.F)
        reaction = self.layout.comm.tompi4py().allreduce(self._gauge_local)
        return {"node": int(self.gauge[0]), "component": "xyz"[self.gauge[1]],
                "reaction": float(reaction)}

    # -- the terms, as the solvers ask for them -----------------------------------------
    @property
    def moving_pattern(self):
        """Some term couples dofs beyond the elements in a pattern that follows the state."""
        return any(t.moving_pattern for t in self.terms)

    @property
    def keeps_link(self):
        """Some term keeps strands from passing through each other (the link is conserved)."""
        return any(t.keeps_link for t in self.terms)

    @property
    def length_scale(self):
        """The smallest length a term resolves (the contact radius), or None."""
        scales = [t.length_scale for t in self.terms if t.length_scale is not None]
        return min(scales) if scales else None

    def adaptive_terms(self):
        """The terms that raise their penalty to keep a promise (-contact_penalty_adapt)."""
        return [t for t in self.terms if t.adapt]

    def ease_walls(self, lam, stop=1.0, say=None):
        """Before the step after a converged (and written) one at load lam, or a restart from
        it, where there is one (lam short of ``stop``): each adaptive term's penalty raised
        where the state presses into its wall (Term.ease_wall), so that the step and the
        restart both start from it while the written step keeps the penalty it was solved
        with.  The lines that say so (each to ``say`` too).  Collective."""
        said = []
        if lam >= stop - 1e-14:
            return said
        for term in self.adaptive_terms():
            line = term.ease_wall(self.state.local_config()[0], lam)
            if line is not None:
                said.append(line)
                if say is not None:
                    say(line)
        return said

    def limiting_terms(self):
        """The terms that limit a Newton step's move (Term.step_limit)."""
        return [t for t in self.terms if t.step_limit]

    def load_terms(self):
        """The terms whose residual changes with lambda (arclength's dF/dlambda)."""
        return [t for t in self.terms if t.depends_on_load]

    def watched_nodes(self, r=None):
        """Owned nodes whose move the step limit bounds (Term.watched_nodes of the limiting
        terms; at r: evaluated there, None: at their last evaluation)."""
        nodes = [t.watched_nodes(r) for t in self.limiting_terms()]
        if len(nodes) == 1:
            return nodes[0]
        return np.unique(np.concatenate(nodes)) if nodes else np.zeros(0, dtype=np.int64)

    def clearance(self, r):
        """The least free space between strands at r over the limiting terms (Term.clearance;
        inf without one).  Collective."""
        return min([t.clearance(r) for t in self.limiting_terms()], default=np.inf)

    def largest_moves(self, d, rows=None):
        """(largest translation, largest rotation) of the nodal step d (owned nodes ``rows``:
        all by default) over all ranks: maxima, the same on every rank.  Collective."""
        from mpi4py import MPI
        a = d.getArray(readonly=True).reshape(-1, NDOF)
        if rows is not None:
            a = a[rows]
        t = float(np.sqrt((a[:, 0:3] ** 2).sum(axis=1)).max()) if len(a) else 0.0
        r = float(np.sqrt((a[:, 3:6] ** 2).sum(axis=1)).max()) if len(a) else 0.0
        out = np.array([t, r])
        self.layout.comm.tompi4py().Allreduce(MPI.IN_PLACE, out, op=MPI.MAX)
        return float(out[0]), float(out[1])

    def longest_step(self, d, most=1.0, reach=1.0):
        """The largest multiple (<= most) of the step d from the state within the move limits:
        no rotation turns by more than MAX_ROTATION, no node a limiting term watches (near a
        possible contact) moves by more than ``reach`` times its step limit (half the contact
        radius), no node by more than half the clearance between strands (or that limit).
        Collective."""
        t, rot = self.largest_moves(d)
        alpha = most
        if rot > MAX_ROTATION:
            alpha = MAX_ROTATION / rot
        limit = reach * self.step_limit       # the terms' (contact: half its radius; 0: none)
        if limit and t * alpha > limit:       # a shorter step is within every move limit
            r, _ = self.state.local_config()
            t_near, _ = self.largest_moves(d, self.watched_nodes(r))
            if t_near * alpha > limit:
                alpha = limit / t_near
            room = max(0.5 * self.clearance(r), limit)
            if t * alpha > room:
                alpha = room / t
        return alpha

    def predict_within_limits(self, snap, prev, ratio, twist=None):
        """The secant predictor (RodState.predict: ``ratio`` times the step from ``prev`` to the
        state ``snap``, the twist ``twist`` factored out) as far along as the move limits let
        any node move, as a line search's step from the state (longest_step): the load paths'
        start of a step.  Returns the share of the secant taken.  Collective."""
        st = self.state
        st.predict(prev, ratio, twist)
        move = st.X.copy()
        move.axpy(-1.0, snap[1])
        st.restore(snap)
        share = self.longest_step(move)
        move.destroy()
        st.predict(prev, share * ratio, twist)
        return share

    def deepest(self, r=None, report=True):
        """The deepest penetration over the terms that measure one (Term.deepest) at the local
        positions r (None: their last evaluation), or None where none does.  Collective."""
        depths = [d for d in (t.deepest(r, report) for t in self.terms) if d is not None]
        return max(depths) if depths else None

    def depth_allowed(self, depth):
        """The deepest penetration a step may reach from ``depth`` (Term.depth_allowed: the
        least over the terms)."""
        return min(t.depth_allowed(depth) for t in self.terms)

    def trial(self, r, q):
        """At a line-search trial (local positions r, rotations q): every term's share of the
        energy on this rank, from one evaluation each (Term.trial), and the deepest
        penetration over all ranks (None where no term measures one).  Collective."""
        shares, deep = [], None
        for t in self.terms:
            e, d = t.trial(self.lam, r, q)
            shares.append(e)
            if d is not None:
                deep = d if deep is None else max(deep, d)
        if deep is not None:
            from mpi4py import MPI
            deep = self.layout.comm.tompi4py().allreduce(deep, op=MPI.MAX)
        return shares, deep

    def report(self):
        """{term name: its section of summary.json} at the current state (Term.report; the
        terms without a name report nothing).  Collective."""
        r, _ = self.state.local_config()
        return {t.name: t.report(r) for t in self.terms if t.name is not None}

    def qp_fields(self):
        """The quadrature-point fields of the last report (Term.qp_fields; the first term
        that has them), {} for none."""
        return next((f for f in (t.qp_fields() for t in self.terms) if f is not None), {})

    # -- load factor ------------------------------------------------------------------
    def set_load(self, lam, refresh=True):
        """Set lambda: prescribed motions into the state, intrinsic twist ramp into e0; with
        refresh, the terms' patterns follow the state (the start of a load step)."""
        self.lam = float(lam)
        self.constraints.apply(self.lam, self.state)
        if refresh:
            self.refresh_pattern()
        if self.load_twist:
            self.elastic.set_reference(self.twisted_reference(self.e0_base))

    # -- matrix pattern -----------------------------------------------------------------
    def patterns_at(self, r=None):
        """Every term's pattern (Term.pattern) at the local positions r (None: the current
        state's, taken only when some pattern moves).  Collective."""
        if r is None and self.moving_pattern:
            r, _ = self.state.local_config()
        return [t.pattern(r) for t in self.terms]

    def pattern_of(self, term):
        """The pattern J is preallocated for, of one of the terms."""
        return self.patterns[self.terms.index(term)]

    def node_groups(self, patterns):
        """The node groups (partition.Layout.create_matrix) of the terms' ``patterns``: None
        for none, else one array."""
        groups = [g for g in (t.node_groups(pat) for t, pat in zip(self.terms, patterns)
                              if pat is not None) if g is not None]
        if not groups:
            return None
        return groups[0] if len(groups) == 1 else np.concatenate(groups)

    def positions_only(self, patterns=None):
        """Whether every term with a pattern (``patterns``, default the current ones) couples
        its node groups by positions only (Term.positions_only): the Jacobian is then split
        (Layout.create_matrix)."""
        patterns = self.patterns if patterns is None else patterns
        return all(t.positions_only for t, pat in zip(self.terms, patterns) if pat is not None)

    def coupled_groups(self):
        """The natural node groups the Jacobian couples all-to-all: the elements' and the
        terms' of the current patterns (Layout.coupled_groups), the same on every rank."""
        return self.layout.coupled_groups(self.node_groups(self.patterns))

    def refresh_pattern(self):
        """At the start of a load step: the Jacobian's pattern follows what the terms couple
        at the current state (Term.pattern: the contact pairs that can touch); a new matrix
        when it changed."""
        if not self.moving_pattern:
            return
        want = self.patterns_at()
        if not same_patterns(want, self.patterns):
            self._new_matrix(want)

    def ensure_pattern(self):
        """Before every Jacobian: every coupling of the iterate's tangent must be preallocated
        (Term.pattern_covers), else a new matrix with the patterns of the iterate
        (Term.covering_pattern: the contact pairs it couples and the pairs that can touch
        there) is made before the Jacobian is assembled.  No entry is ever inserted beyond
        the preallocation (see contact/term.py: PETSc 3.18 MPIBAIJ puts such an entry in a
        wrong column)."""
        if not self.moving_pattern:
            return
        r, _ = self.state.local_config()
        if all(t.pattern_covers(r, pat) for t, pat in zip(self.terms, self.patterns)):
            return
        want = [t.covering_pattern(r) for t in self.terms]
        self._new_matrix(want)
        self.stats["pattern_growths"] = self.stats.get("pattern_growths", 0) + 1

    @property
    def J(self):
        """The Jacobian of all the unknowns (BAIJ, block size 6), preallocated for the elements
        and the terms' patterns; made when first asked for: a run solved in its plane uses its
        own in-plane block (planar.py) and needs this one only if it leaves the plane (at 10^5
        cubic elements 0.43 GB and its preallocation's time).  Collective on its first use."""
        if self._J is None:
            self._J = self.layout.create_matrix(self.node_groups(self.patterns),
                                                positions_only=self.positions_only(self.patterns))
        return self._J

    @property
    def J_made(self):
        """The full Jacobian if it has been made, else None (a question that makes nothing)."""
        return self._J

    def _new_matrix(self, patterns):
        """A fresh matrix preallocated for the elements + the terms' patterns.  Not an in-place
        re-preallocation: MPIBAIJ keeps the old off-diagonal column map through it.  The solver
        (on_pattern_change) takes the new matrix and drops its factorisation.  One not made yet
        is made when first asked for (J), for these patterns."""
        old, self._J = self._J, None
        self.patterns = patterns
        if old is not None:
            if self.on_pattern_change is not None:
                self.on_pattern_change(self.J)
            old.destroy()
        self.stats["pattern_refreshes"] = self.stats.get("pattern_refreshes", 0) + 1

    def twisted_reference(self, e0):
        """Stress-free strains at the current load: u_hat_3 lowered by lambda 2 pi T / L
        (-load_twist_turns T); a copy, e0 itself is kept."""
        e0 = np.array(e0, copy=True)
        if self.load_twist:
            e0[..., 5] -= self.lam * 2 * np.pi * self.load_twist / self.mesh.length
        return e0

    # -- SNES callbacks ---------------------------------------------------------------
    def residual(self, snes, X, F, terms=None):
        """The residual at X into F: the rod's, then every term's (``terms``: these only, e.g.
        load_terms), Dirichlet rows x - target."""
        r, q = self.state.local_config(X)
        # the element rows summed per local node, the elements' nodes gathered in the
        # kernel's pass (ElasticRod.node_residual): over every element of an owned node, so
        # the owned rows are whole here (owner computes) and the ghost rows partial
        _, Floc = self.elastic.node_residual(q, r, self.row_lconn)
        no = self.layout.n_owned
        if self.sums_ghost_rows:
            Floc[no:] = 0.0         # the ghost rows: the terms' alone, summed by their owners
        for t in (self.terms if terms is None else terms):
            if self.sums_ghost_rows and t.owner_computes:
                # its rows of other ranks' nodes are their owners' to compute: not sent
                ghost = Floc[no:].copy()
                t.add_residual(self.lam, r, q, Floc)
                Floc[no:] = ghost
            else:
                t.add_residual(self.lam, r, q, Floc)
        if self.sums_ghost_rows:
            F.set(0.0)
            self.layout.add_to_global(Floc, F)
        xa = X.getArray(readonly=True)
        with F as fa:
            if not self.sums_ghost_rows:
                fa[:] = Floc[:no].ravel()
            if self.gauge is not None:      # its reaction: the unbalanced force it holds
                lo, hi = F.getOwnershipRange()
                row = self.gauge[2]
                self._gauge_local = float(fa[row - lo]) if lo <= row < hi else 0.0
            c = self.constraints
            fa[c.rows_local] = xa[c.rows_local] - np.where(c.rows_local % NDOF < 3, c.target_own, 0.0)

    # elements per call of the compiled kernel in the Jacobian: their tangents (4.6 kB each,
    # cubic) are inserted while they are in cache, instead of 46 MB for 10^4 elements written
    # to memory and read back by the insertion (and by planar.ComponentView's cut).  Tangents
    # of c < 6 components a node (a view's comps) come (6/c)^2 times as many a call, the same
    # bytes (the planar cantilever's in-plane block at 10^4 elements: 13.2 ms with 256 a
    # call, 11.2 with 1024, 10.5 in one call)
    TANGENT_CHUNK = 256

    def jacobian(self, snes, X, J, P, symmetric=False, view=None):
        """The tangent at X into P: the consistent Newton tangent, or with symmetric the chart
        Hessian of the energy (stability.py).  Dirichlet rows and columns hold the identity,
        MatZeroRowsColumns(P, rows, 1) of the sum, but built in every block before it enters
        the matrix (partition.DirichletRows: bit for bit the same, without the O(nnz) sweep
        after assembly, and also for SBAIJ, which lacks that operation in parallel).
        ``view``: P seen through it (planar.ComponentView: a block of the components of every
        node, masked as DirichletRows does; the elastic tangents come cut to its components
        from the kernel and go in by its add_cut; with the view's ``plane``, the in-plane
        block of a planar state, made by ElasticRod.plane_tangents)."""
        r, q = self.state.local_config(X)
        mask = self.constraints.block_mask
        T = view if view is not None else DirichletRows(
            P, mask, kept(self, "_dirichlet_touched", (mask,),
                          lambda: DirichletRows.touched_of(mask)))
        comps = getattr(view, "comps", None)
        plane = getattr(view, "plane", None)
        add = T.setValuesBlockedRCV if comps is None else T.add_cut
        # the elements of the owned rows (e0: (elements, points, 6)); the rows this rank sets
        g, rows, lconn, e0 = self._gconn, self._rows, self.row_lconn, self.elastic.e0
        # no entry of another rank's row (owner computes), unless a term sets such rows, and
        # where no term's pattern moves none outside the matrix's pattern: then the assembly
        # sends nothing and needs no reduction (MatAssemblyEnd of an MPI block matrix decides
        # by two whether some rank added a nonzero)
        P.setOption(PETSc.Mat.Option.NO_OFF_PROC_ENTRIES, not self.sums_ghost_rows)
        P.setOption(PETSc.Mat.Option.NEW_NONZERO_LOCATION_ERR, not self.moving_pattern)
        rc, qc = np.ascontiguousarray(r), np.ascontiguousarray(q)   # np.take copies a strided one
        nc = NDOF if comps is None else len(comps)
        # the elements' blocks straight into the matrix's values where that applies
        blocks = assembly.element_blocks(P, T if view is None else view.dirichlet, g, nc)
        # the elements the compiled kernel adds into the matrix's values as it makes their
        # tangents (assembly.ElementBlocks' places), storing at each block's first addition
        # where the matrix is zeroed only elsewhere (zero_rest); the others (all, without it)
        # by chunks, after
        fused = blocks is not None and self.elastic.kernel == "compiled"
        stored = fused and blocks.zero_rest(P)
        if not stored:
            P.zeroEntries()
        if fused:
            self.elastic.tangents_into(qc, rc, lconn, blocks, e0, plane=plane, comps=comps,
                                       symmetric=symmetric, store_first=stored)
            if len(blocks.rest):
                self._add_rest_tangents(blocks, T if view is None else view.dirichlet, qc, rc,
                                        plane, comps, symmetric)
            todo = ()
            blocks = None
        else:
            todo = np.arange(len(g))
        step = (self.TANGENT_CHUNK * NDOF ** 2 // nc ** 2 if self.elastic.kernel == "compiled"
                else max(len(g), 1))
        for a in range(0, len(todo), step):
            # the tangents of a chunk of elements, inserted while they are in cache (ADD_VALUES
            # in the elements' order: the same sums as one insertion of all of them; an entry
            # gets the tangents of two elements at most, whose sum is the same either way)
            b = min(a + step, len(todo))
            ids = todo[a:b]
            la = lconn[ids]
            qa, xa = np.take(qc, la, axis=0), np.take(rc, la, axis=0)
            ea = None if e0 is None else e0[ids]
            if plane is not None:
                H = self.elastic.plane_tangents(qa, xa, plane, ea, reuse=True)
            else:
                _, _, H = self.elastic.element_terms(qa, xa, ea, tangent=True, symmetric=symmetric,
                                                     reuse=True, comps=comps)
            ga = g[ids]
            ra = ga if rows is g else rows[ids]
            if blocks is None:
                add(ra, ga, H, addv=PETSc.InsertMode.ADD)
            else:
                blocks.add(a, b, H, lambda i: add(ra[i], ga[i], H[i], addv=PETSc.InsertMode.ADD))
        for t in self.terms:
            t.add_jacobian(self.lam, r, q, T, symmetric=symmetric)
        T.finish(self.constraints.rows_global)
        P.assemble()
        self._check_no_mallocs(P)
        if J != P:
            J.assemble()

    def _add_rest_tangents(self, blocks, dirichlet, qc, rc, plane, comps, symmetric):
        """The elastic tangents of the elements the compiled kernel leaves to the matrix's own
        insertion (ElementBlocks.rest: at a constrained node, or holding another rank's node),
        masked by ``dirichlet`` (partition.DirichletRows) and added by one MatSetValuesBlocked
        of them all, with what does not change while the pattern and the constraints stay (the
        elements' rows, columns and Dirichlet mask: RestElements) kept on ``blocks``.  A few
        elements a rank (the clamp's, the one cut by the ranks' boundary): through the
        masked runs of setValuesBlockedRCV they cost 0.3 ms a Jacobian on 2 ranks at 10^4
        planar elements, mostly Python."""
        plan = blocks.rest_plan
        if plan is None or plan.dirichlet is not dirichlet.mask:
            plan = blocks.rest_plan = RestElements(self, blocks.rest, dirichlet)
        qa, xa = np.take(qc, plan.lconn, axis=0), np.take(rc, plan.lconn, axis=0)
        e0 = self.elastic.e0
        ea = None if e0 is None else e0[plan.ids]
        if plane is not None:
            H = self.elastic.plane_tangents(qa, xa, plane, ea, reuse=True)
        else:
            H = self.elastic.element_terms(qa, xa, ea, tangent=True, symmetric=symmetric,
                                           reuse=True, comps=comps)[2]
        plan.add(H, dirichlet)

    def _check_no_mallocs(self, P):
        """Safety net for ensure_pattern: an entry beyond the preallocation would be wrong in
        parallel (PETSc 3.18 MPIBAIJ) and would break the reused factorisation, so it is an
        error, not a slowdown."""
        if not self.moving_pattern:
            return
        mallocs = int(P.getInfo(PETSc.Mat.InfoType.GLOBAL_SUM)["mallocs"])
        if mallocs:
            raise RuntimeError(f"rodsnes: {mallocs} Jacobian entries fell outside the preallocated "
                               "pattern (RodProblem.ensure_pattern missed a coupling)")

    ARMIJO = 0.1        # sufficient decrease of the energy line search (precheck, limit 3)

    def precheck(self, X, Y, F=None):
        """Line-search pre-check for scenes with a term that limits steps (Term.step_limit:
        contact); returns True when the step was changed (scaled: the direction is kept).
        Three limits:

        1. no node a term watches (Term.watched_nodes: a node near a possible contact) moves
           by more than ``step_limit`` (half the contact radius), so one step cannot carry a
           strand through another before the penalty sees it;
        2. the step may not deepen the deepest penetration d_max = max (2 eps - distance) beyond
           max(2 d_max(X), 2 % of the contact diameter).  A Newton step linearised before a new
           contact exists would push the strands into each other, and the penalty answers with
           a residual 1e3 x larger (the plectoneme: |F| 19 -> 8e3, then 40 iterations of chaos);
        3. with conservative loads and the constrained dofs already at their values, the step
           must lower the total energy by a tenth of what its slope promises (Armijo:
           E(s) <= E0 + 0.1 s E'(0), E'(0) = -F . Y from the residual F at X; beyond 1e-11 |E|,
           the roundoff of its sum); a step that fails is shortened to the minimiser of the
           quadratic through E0, E'(0) and E(s), kept within [0.1 s, 0.5 s].  Where
           contact zones open and close from one iterate to the next, full Newton steps can
           cycle: on the plectoneme at 2 turns |F| alternated 20 <-> 2 for 40 iterations with
           the energy going up every other step.  Equilibria are stationary points of the energy,
           and stable ones (the path is kept on them with -stability) minima, so a step that
           raises it has overshot.

        The step is shortened (at most 10 times) until 2 and 3 hold; if 3 never holds (no
        descent along a direction of negative curvature: then steps are halved) the longest
        step that satisfies 2 is taken.  An overshoot that barely lowers the energy (landing
        across the valley, the next step coming back) fails the Armijo test, and the quadratic
        model puts the step near the bottom of the valley.
        Far from contact, and near the solution (small steps, penetration settled, energy
        changes at roundoff), Newton is untouched and converges quadratically."""
        if not self.step_limit:
            return False
        from mpi4py import MPI
        comm = self.layout.comm.tompi4py()
        changed = False
        y = Y.getArray(readonly=True).reshape(-1, NDOF)[self.watched_nodes()]
        move = float(np.sqrt((y[:, 0:3] ** 2).sum(axis=1)).max()) if len(y) else 0.0
        move = comm.allreduce(move, op=MPI.MAX)
        if move > self.step_limit:
            Y.scale(self.step_limit / move)
            self.stats["limited_steps"] = self.stats.get("limited_steps", 0) + 1
            changed = True
        d0 = self.deepest(report=False)                  # as at the trials
        d_allow = None if d0 is None else self.depth_allowed(d0)
        use_energy = self.energy_descent_applies(Y)
        if use_energy:
            r0, q0 = self.state.local_config(X)
            E0 = self.energy_local(r0, q0)
            E0 = comm.allreduce(E0)
            slack = 1e-11 * abs(E0) + 1e-300
        # slope of the energy along the step X - s Y at s = 0: -F . Y (F: the residual at X,
        # SNES's function vector; the energy gradient in the chart of the update)
        slope = -F.dot(Y) if (use_energy and F is not None) else 0.0
        descent = slope < 0.0
        Xt = X.duplicate()
        scale, first_ok = 1.0, None
        for _ in range(11):
            X.copy(Xt)
            Xt.axpy(-scale, Y)                         # X_new = X - Y (line search basic)
            r, q = self.state.local_config(Xt)
            shares, d_trial = self.trial(r, q)         # d_trial: the same on all ranks
            if d_allow is None or d_trial <= d_allow:
                if first_ok is None:
                    first_ok = scale
                if not use_energy:
                    break
                E = comm.allreduce(self.energy_local(r, q, shares))
                if E <= E0 + self.ARMIJO * scale * min(slope, 0.0) + slack:
                    break
                if descent:      # minimiser of the quadratic through E0, slope, E(scale)
                    s_q = -slope * scale ** 2 / (2.0 * (E - E0 - slope * scale))
                    scale = min(max(s_q, 0.1 * scale), 0.5 * scale)
                    continue
            scale *= 0.5
        else:
            scale = first_ok if first_ok is not None else 2.0 * scale
        Xt.destroy()
        if scale < 1.0:
            Y.scale(scale)
            key = "energy_limited_steps" if first_ok is not None and scale < first_ok \
                else "penetration_limited_steps"
            self.stats[key] = self.stats.get(key, 0) + 1
            changed = True
        return changed

    def energy_descent_applies(self, Y):
        """Energy is a merit function for this step: conservative loads, and the step leaves
        every constrained dof where it is (after the first Newton iteration of a load step)."""
        from mpi4py import MPI
        if not self.energy_descent:
            return False
        rows = self.constraints.rows_local         # supports, end rotation, sliding gauge
        moves = bool(np.any(Y.getArray(readonly=True)[rows] != 0.0))
        return not self.layout.comm.tompi4py().allreduce(moves, op=MPI.LOR)

    def energy_local(self, r, q, shares=None):
        """This rank's share of the total energy (elastic, then every term in its order: the
        loads' potential, contact) at local positions r and rotations q; ``shares``: the terms'
        shares when known (trial: precheck and the minimiser take them from the evaluation
        they make anyway)."""
        E = self.elastic.node_energy(q, r, self.lconn, self.elastic.e0[:self.n_elems])
        if shares is None:
            shares = [t.energy_local(self.lam, r, q) for t in self.terms]
        for e in shares:
            E += e
        return E

    def update(self, snes, its):
        self.state.recentre()
        self.ensure_pattern()

    # -- diagnostics --------------------------------------------------------------------
    def energy(self):
        """Total potential energy (elastic + the terms: conservative loads, contact), all
        ranks."""
        r, q = self.state.local_config()
        return self.layout.comm.tompi4py().allreduce(self.energy_local(r, q))

    def max_curvature(self):
        """Largest flexure |(u1, u2)| at the quadrature points times the contact radius eps,
        over all ranks (<= 1: the thickness bound kappa <= 1/eps holds; the penalty lets it
        exceed 1 by about -contact_penetration at a moment of 2 EI/eps); None without the bound.
        Collective."""
        from mpi4py import MPI
        el = self.elastic
        if el.kappa_max is None:
            return None
        r, q = self.state.local_config()
        loc = el.max_flexure(q[self.lconn], r[self.lconn])
        return self.layout.comm.tompi4py().allreduce(loc, op=MPI.MAX) / el.kappa_max

    def topology(self):
        """Link, twist and writhe (topology.topology: Gauss integral for the writhe, open rods
        closed along their end-to-end axis) of the current state, for rings and for open rods
        held in orientation at both ends (clamped or sliding); None for other rods.  A
        degenerate geometry gives NaNs and its message (topology_error).  Collective: every
        rank computes it from the allgathered nodes (the same numbers everywhere)."""
        bc = self.scene.bc
        if not (self.mesh.closed or (bc.start == "clamped" and bc.end in ("clamped", "sliding"))):
            return None
        r, q = self.state.local_config()
        no = self.layout.n_owned
        X = self.layout.allgather_nodes(r[:no])
        D = self.layout.allgather_nodes(so3.rot(q[:no])[:, :, 0])
        # the same state asked again (the load path's link check, then the step's output): the
        # O(N^2) writhe once; X and D are the same on every rank, so is the decision
        key = (X.tobytes(), D.tobytes())
        if self._topology is not None and self._topology[0] == key:
            return dict(self._topology[1])
        axis = None
        if not self.mesh.closed:
            axis = X[-1] - X[0]
            axis = axis / np.linalg.norm(axis) if np.linalg.norm(axis) > 0 else None
        try:
            t = topology.topology(X, D, self.mesh.closed, axis=axis)
            out = {"link": float(t["link"]), "twist": float(t["twist"]), "writhe": float(t["writhe"])}
        except ValueError as err:          # degenerate geometry: report, do not stop the run
            out = {"link": np.nan, "twist": np.nan, "writhe": np.nan, "topology_error": str(err)}
        self._topology = (key, out)
        return dict(out)

    def owned_fields(self):
        """Per owned node: positions (n,3), directors (n,3,3), the unit quaternions (w, x, y, z)
        of the rotations as the state holds them (n,4; a restart resumes from these), material
        strains strain_v,
        strain_u, and spatial stress resultants force_n = R C_v (v - v0), moment_m = R C_u (u - u0)
        (+ the thickness bound's moment where the flexure exceeds it, elastic.ElasticRod.law)
        (strains evaluated at the element nodes and averaged over the elements sharing a node)."""
        r, q = self.state.local_config()
        no = self.layout.n_owned
        R = so3.rot(q[:no])
        compiled = self.elastic.kernel == "compiled"       # -rod_kernel numpy: numpy here too
        e = nodal_average(self.layout, self.lconn, elastic.strains_at_nodes(
            self.mesh.order, self.mesh.h, q[self.lconn], r[self.lconn], compiled))
        if self._e0_nodes is None:
            at_nodes = lambda q, x: elastic.strains_at_nodes(  # noqa: E731
                self.mesh.order, self.mesh.h, q, x, compiled)
            e0 = reference_strains(self.scene.rod, self.mesh, self.mesh.conn[self.layout.owned_elems], at_nodes)
            self._e0_nodes = nodal_average(self.layout, self.lconn, e0)
        S = self.elastic.law(e, self.twisted_reference(self._e0_nodes))[1]
        return {"positions": r[:no].copy(), "directors": R, "rotation": q[:no].copy(),
                "strain_v": e[:, 0:3], "strain_u": e[:, 3:6],
                "force_n": self.force_resultants(r, q),
                "moment_m": np.einsum("nij,nj->ni", R, S[:, 3:6])}

    def force_resultants(self, r, q):
        """The spatial force resultant n per owned node from equilibrium, not from the strains:
        an element's internal nodal forces f_a = dE_e/dr_a (its residual's position rows) sum
        to zero (the energy sees r through r' only), so the force across a cut between its
        nodes a_i and a_(i+1) is n_i = -(f_0 + ... + f_i), the force the part beyond the cut
        exerts; at a node, the mean of the cuts on either side (the elements sharing it
        averaged as the strains are; at an element's ends extrapolated from its two nearest
        cuts).  Exact to the residual's tolerance where no distributed load acts (a tip load);
        under one (gravity, contact) to O(h) of the load's share.  The constitutive
        R C_v (v - v0), from strains at the nodes, multiplies their error by EA: on
        Mattiasson's cantilever (tip load 10, EA = 1e6 EI/L^2) it read 2015 at the root, and
        -128655 on linear elements."""
        no = self.layout.n_owned
        lc = self.lconn
        _, Re, _ = self.elastic.element_terms(q[lc], r[lc], self.elastic.e0[:self.n_elems],
                                              tangent=False)
        f = np.asarray(Re)[:, :, 0:3]
        p = f.shape[1] - 1
        cut = -np.cumsum(f[:, :p], axis=1)                  # (ne, p, 3): segments a_i a_(i+1)
        at = np.empty(f.shape)
        if p > 1:
            # inside, the mean of the two segments; at the element's ends extrapolated from
            # its two nearest (a distributed load makes n linear: its cut forces are n at the
            # segments' middles, for linear elements exactly)
            at[:, 1:p] = 0.5 * (cut[:, :p - 1] + cut[:, 1:])
            at[:, 0] = 1.5 * cut[:, 0] - 0.5 * cut[:, 1]
            at[:, p] = 1.5 * cut[:, p - 1] - 0.5 * cut[:, p - 2]
        else:
            at[:, 0] = at[:, 1] = cut[:, 0]
        vals = np.concatenate([at, np.zeros(at.shape)], axis=2)
        return nodal_average(self.layout, lc, vals)[:no, 0:3].copy()


def nodal_average(layout, lconn, elem_values):
    """Average element-node values (ne, p+1, 6) over the elements sharing each node, across
    ranks; returns (n_owned, 6)."""
    nl = len(layout.local_nodes)
    idx = np.asarray(lconn).ravel()
    vals = np.asarray(elem_values).reshape(len(idx), NDOF)
    # sums per node by bincount (np.add.at is unbuffered: ~10x slower at 10^4 elements)
    acc = np.stack([np.bincount(idx, weights=vals[:, k], minlength=nl) for k in range(NDOF)], axis=1)
    cnt = np.repeat(np.bincount(idx, minlength=nl).astype(float)[:, None], NDOF, axis=1)
    A, Cn = layout.create_vec(), layout.create_vec()
    layout.add_to_global(acc, A)
    layout.add_to_global(cnt, Cn)
    out = (A.getArray(readonly=True) / Cn.getArray(readonly=True)).reshape(-1, NDOF)
    A.destroy()
    Cn.destroy()
    return out
