"""Self-contact as a term of the parallel problem: search, halo exchange through a PETSc star
forest, assembly (DESIGN.md: "partition.py and problem.py own all communication"; this module is
the contact part of that communication around the pure kernel of contact.py).

Per evaluation (residual, line-search trial or Jacobian), on every rank:
  1. bounding spheres of the owned elements (contact.element_bounds);
  2. candidate pairs (owned element, any element), a Verlet list: a search (spheres allgathered,
     4 doubles per element: the only global exchange, O(N); a cKDTree, contact.candidate_pairs)
     within reach + skin (reach = 2 eps + margin) is kept while no sphere has moved by skin / 2
     since (the largest move |dc| + max(dR, 0) over all ranks, one allreduce): then no pair's
     sphere distance has fallen by more than skin, and every pair within reach now was within
     reach + skin then;
  3. the nodes of the candidate master elements are fetched from their owners through a PetscSF
     (leaves = needed nodes, roots = owned nodes); the SF is rebuilt only when that node set
     changes (with a new search).  What the list fixes (the masters, their nodes, the rows
     of every candidate) is made once per list (_verlet_plan), and the SF's check is skipped
     while the list stays;
  4. the candidates within reach at these positions: the sphere test of candidate_pairs on the
     current spheres (the same pairs as a fresh search within reach);
  5. the kernel evaluates energy and residual on owned slave points; the tangent and the report
     (gap, penetration, KKT picture) only when a caller asks for them (``evaluate``), made later
     from what the residual kept at the same positions;
  6. slave-side residual goes into the owned/ghost rows; master-side residual is sent back to
     the owners through the same SF (reduce with MPI.SUM), both by scatter.add_in_order (the
     sums of np.add.at, bit for bit, a fraction of its time); tangent blocks go straight into the
     global matrix (MatSetValuesBlocked with off-process rows, communicated at assembly).
The Jacobian's block pattern holds the element pairs that can touch (capsules within
2 eps + PATTERN_MARGIN eps) at the start of every load step, and before every Jacobian the
pairs that the iterate's tangent couples are checked against it (RodProblem.ensure_pattern,
pattern_covers): a pair outside the pattern gets a new, wider-preallocated matrix before any
value is set.  Entries
are never inserted beyond the preallocation: on PETSc 3.18, a new off-diagonal block inserted
into an assembled MPIBAIJ lands in a wrong column, and MUMPS reuses a symbolic analysis that no
longer fits (a segfault).

ContactTerm implements the problem's term interface (model/term.Term): energy, residual,
tangent, the moving pattern of element pairs, the step limits (nodes near contact, the
deepest penetration, the clearance), the penalty's promise and the KKT report.
"""
import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from rodsnes.profiling import logged
from rodsnes.contact import projection as ck
from rodsnes.contact import search
from rodsnes.contact.scatter import add_in_order, in_order_rows
from rodsnes.model import so3
from rodsnes.model.partition import add_position_blocks, allreduce
from rodsnes.model.term import Term
from rodsnes.contact.potential import WALL, PotentialKernel
from rodsnes.contact.mounts import SupportTerm

# a raise of the penalty (-contact_penalty_adapt) aims this much beyond the depth it must bring
# back to its mark: mu <- RAISE mu d / d_mark (promised_penalty, ease_wall)
RAISE = 1.25


class ContactTerm(Term):
    """Self-contact (and the clamps' mounts) as a term of the problem (module docstring)."""

    name = "contact"
    positions_only = True       # gap and potential depend on the centreline only
    moving_pattern = True
    keeps_link = True
    SKIN = 1.0          # Verlet skin of the candidate search, in eps (module docstring, 2.)
    PATTERN_MARGIN = 0.0    # the Jacobian's pattern: pairs within 2 eps + this, in eps

    def __init__(self, scene, mesh, layout):
        rod, c = scene.rod, scene.contact
        self.mesh, self.layout = mesh, layout
        self.comm = layout.comm.tompi4py()
        # the tube (radius a, the promise p* on its diameter) and the law that keeps it: the
        # law acts from 2 eps = 2 a (1 + standoff) with its own promise p_l (scene.law_tube);
        # depths are the law's (2 eps - distance) inside, the tube's (2 a - distance) in reports
        self.radius = float(scene.contact_radius)
        self.standoff = float(c.standoff)
        self.eps, self.law_penetration = scene.contact_law
        self.offset = 2.0 * (self.eps - self.radius)    # law depth - tube depth
        self.delta = float(c.exclusion if c.exclusion is not None else ck.default_exclusion(self.eps))
        self.penetration = float(c.penetration)     # promised largest <d> / (2 a)
        self.adapt = bool(c.adapt)
        self.mu = float(c.penalty if c.penalty is not None else
                        ck.default_penalty(min(rod.EI1, rod.EI2), self.eps, self.law_penetration))
        self.penalty_raises = 0         # -contact_penalty_adapt: re-solves with a raised mu
        self.penalty_failures = 0       # ... that failed (state and mu put back)
        self.penalty_eased = 0          # ... raises for the next step, no re-solve (the wall)
        self.nqc = int(c.quadrature if c.quadrature else rod.order + 2)
        self.p = rod.order
        self.model = c.model
        self.model_auto = c.model_auto
        if self.model == "potential":
            self.kernel = PotentialKernel(rod.order, self.nqc, self.eps, self.mu, self.delta,
                                          mesh.length, mesh.nelem, mesh.closed,
                                          penetration=self.law_penetration,
                                          nqp=c.potential_points,
                                          wall=(WALL * self.penetration * 2.0 * self.radius
                                                if c.wall else None))
        else:
            self.kernel = ck.ContactKernel(rod.order, self.nqc, self.eps, self.mu, self.delta,
                                           mesh.length, mesh.nelem, mesh.closed,
                                           segments=c.zones)
        # the law's depths where the wall's barrier starts and where it stands (potential.py,
        # The wall), None without one
        self.wall = self.kernel.wall if self.model == "potential" else None
        self.step_limit = 0.5 * self.eps                         # largest nodal move per Newton step
        self.length_scale = self.eps
        self.reach = 2.0 * self.eps + 0.5 * self.eps            # search margin within a Newton step
        self.skin = self.SKIN * self.eps                         # Verlet skin of the search
        self._slots = None              # row of every element in the allgathered arrays
        self.own_ids = layout.owned_elems
        self.lconn = layout.lconn
        self.unit = MPI.DOUBLE.Create_contiguous(3).Commit()
        self.sf = None
        self.leaf_nodes = None
        self.last = None
        self.last_min_gap = np.nan
        self.sf_builds = 0
        self._all_ids = None            # every rank's owned elements, in allgather order
        self.verlet_list = None             # (own centres, own radii, pairs within reach + skin)
        self._plan = None               # what the Verlet list fixes (_verlet_plan)
        self._rows_kept = None          # _residual_rows: the pairs and nodes they are for, rows
        self.searches = 0               # candidate searches made ...
        self.search_reuses = 0          # ... and evaluations that reused one
        self.kept_evaluation = None              # the last evaluation (positions, mu, output, pairs)
        self.cache_hits = 0
        # the clamps' mounts (support.py): a rod clamped at its start and sliding at its end
        self.supports = None
        bc = scene.bc
        if c.supports and not mesh.closed and bc.start == "clamped" and bc.end == "sliding":
            self.supports = SupportTerm(mesh, layout, self.kernel, mesh.x_init[0],
                                        so3.rot(mesh.q_init[0])[:, 2],
                                        so3.rot(mesh.q_init[-1])[:, 2],
                                        reach=self.radius + self.offset, wall=self.wall)

    def set_penalty(self, mu):
        """Change the penalty stiffness mu (E_c = (mu/2) int <d>^2 ds); drops the cached
        evaluation, whose residual and tangent belong to the old mu."""
        self.mu = float(mu)
        self.kernel.mu = self.mu
        self.kept_evaluation = None

    def adopt(self, other):
        """The penalty ``other`` (the contact term of another discretisation) has raised."""
        self.set_penalty(other.mu)

    # -- communication ----------------------------------------------------------------
    def _ensure_sf(self, nodes):
        """PetscSF from the owners of ``nodes`` (natural ids, sorted) to this rank's leaves."""
        same = self.leaf_nodes is not None and np.array_equal(nodes, self.leaf_nodes)
        # building an SF is collective: every rank rebuilds when any rank's node set changed
        if not self.comm.allreduce(not same, op=MPI.LOR):
            return
        lay = self.layout
        owner = lay.node_owner[nodes]
        remote = np.empty(2 * len(nodes), dtype=PETSc.IntType)
        remote[0::2] = owner
        remote[1::2] = lay.nat2petsc[nodes] - lay.starts[owner]
        if self.sf is not None:
            self.sf.destroy()
        sf = PETSc.SF().create(comm=lay.comm)
        sf.setGraph(lay.n_owned, None, remote)
        sf.setFromOptions()
        sf.setUp()
        self.sf, self.leaf_nodes = sf, nodes.copy()
        self.sf_builds += 1

    @logged("ContactHalo")
    def _fetch(self, r_loc, nodes, current=False):
        """The positions of ``nodes`` from their owners (collective).  ``current``: the SF is
        known to be that of ``nodes`` on every rank (_evaluate: no search since it was
        checked), so the check and its allreduce are skipped."""
        if not current:
            self._ensure_sf(nodes)
        root = np.ascontiguousarray(r_loc[:self.layout.n_owned], dtype=float)
        leaf = np.zeros((len(nodes), 3))
        self.sf.bcastBegin(self.unit, root, leaf, MPI.REPLACE)
        self.sf.bcastEnd(self.unit, root, leaf, MPI.REPLACE)
        return leaf

    @logged("ContactHalo")
    def _send_back(self, leaf_force):
        root = np.zeros((self.layout.n_owned, 3))
        leaf = np.ascontiguousarray(leaf_force, dtype=float)
        self.sf.reduceBegin(self.unit, leaf, root, MPI.SUM)
        self.sf.reduceEnd(self.unit, leaf, root, MPI.SUM)
        return root

    # -- evaluation -------------------------------------------------------------------
    def evaluate(self, r_loc, tangent=False, report=False):
        """The kernel's evaluation at local positions r_loc (collective): energy and residual;
        with ``tangent`` its tangent blocks, with ``report`` the report (gap, force and
        penetration at the report points: summary, qp_fields, the penalty's promise).  The last
        evaluation is kept and reused when every rank's positions are bit for bit those it was
        made at and mu is the same (residual and Jacobian at one iterate, the line search's
        accepted trial and the residual after it): a tangent or report asked for later is made
        then, from what the residual kept (kernel.add_tangent, add_report; both local)."""
        st = self.kept_evaluation
        hit = st is not None and st["mu"] == self.kernel.mu and st["r"].shape == r_loc.shape \
            and np.array_equal(st["r"], r_loc)
        if allreduce(self.comm, bool(hit), MPI.LAND):
            self.cache_hits += 1
        else:
            st = self._evaluate(r_loc)
        out = st["out"]
        if tangent and out["mat"] is None:
            self.kernel.add_tangent(out)
            if "support" in out:
                self.supports.add_tangent(out["support"])
        if report:
            self.kernel.add_report(out)
        self.last = out
        return out

    def _candidates(self, r_loc):
        """Nodes of the own elements (no, p+1, 3), their bounding spheres, and the candidate
        pairs within reach + skin of the last search, made anew when some sphere has moved by
        skin / 2 since (module docstring, 2.; the decision is the same on every rank).
        Collective."""
        x_own = r_loc[self.lconn]
        cen, rad = search.element_bounds(x_own)
        s = self.verlet_list
        stale = s is None
        if not stale and len(cen):
            move = np.linalg.norm(cen - s[0], axis=1) + np.maximum(rad - s[1], 0.0)
            stale = not float(move.max()) < 0.5 * self.skin * (1.0 - 1e-6)
        if allreduce(self.comm, bool(stale), MPI.LOR):
            self.verlet_list = (cen, rad, self.search_pairs(cen, rad, self.reach + self.skin))
            self.searches += 1
        else:
            self.search_reuses += 1
        return x_own, cen, rad, self.verlet_list[2]

    @logged("ContactSearch")
    def search_pairs(self, cen, rad, reach, bounds=False):
        """Candidate pairs (own element, any element) within ``reach`` of the bounding spheres
        (cen, rad) of the own elements: the spheres of all ranks allgathered, a cKDTree
        (contact.candidate_pairs).  With ``bounds`` also the spheres of all elements, by
        element id.  Collective."""
        all_ids = self._gathered_ids()
        cens = np.concatenate(self.comm.allgather(cen))
        rads = np.concatenate(self.comm.allgather(rad))
        pairs = search.candidate_pairs(self.own_ids, cen, rad, all_ids, cens, rads, reach,
                                   self.mesh.length, self.mesh.h, self.mesh.closed, self.delta)
        if bounds:
            order = np.argsort(all_ids)
            return pairs, cens[order], rads[order]
        return pairs

    def _verlet_plan(self):
        """What the Verlet list fixes until the next search, made once per list instead of at
        every evaluation: the candidate masters ``other`` (sorted unique), the sorted unique
        nodes the halo fetches and the rows of every master's nodes among them, the rows of
        the candidates' own elements (own_ids) and masters (other); ``own``: the masters are
        the own elements (one rank: every element a candidate); ``halo``: the SF has been
        checked against these nodes.  Kept with the list it belongs to (a search replaces the
        list on every rank at once, _candidates), so it is made anew exactly when the list
        changes."""
        plan = self._plan
        if plan is not None and plan["list"] is self.verlet_list:
            return plan
        m = self.mesh
        cand = self.verlet_list[2]
        other = np.unique(cand[:, 1]) if len(cand) else np.zeros(0, dtype=np.int64)
        other_nodes = search.element_node_ids(other, m.order, m.nelem, m.closed)
        nodes = np.unique(other_nodes)
        plan = {"list": self.verlet_list, "other": other, "nodes": nodes, "halo": False,
                "own": np.array_equal(other, self.own_ids),
                "node_rows": np.searchsorted(nodes, other_nodes) if len(other) else None,
                "io": search.positions(self.own_ids, cand[:, 0], "own") if len(cand) else None,
                "ia": np.searchsorted(other, cand[:, 1])}
        self._plan = plan
        return plan

    def _evaluate(self, r_loc):
        n1 = self.mesh.order + 1
        x_own, cen, rad, cand = self._candidates(r_loc)
        plan = self._verlet_plan()
        other, nodes, io, ia = plan["other"], plan["nodes"], plan["io"], plan["ia"]
        # every rank takes part in the SF collectives, even with nothing to fetch
        leaf = self._fetch(r_loc, nodes, current=plan["halo"])
        plan["halo"] = True
        x_other = leaf[plan["node_rows"]] if len(other) else np.zeros((0, n1, 3))
        # the candidates within reach at these positions: the test of a fresh search (the
        # masters' spheres are the own ones when they are the own elements at the same bits)
        if plan["own"] and search.same_bits(x_other, x_own):
            c_other, r_other = cen, rad
        else:
            c_other, r_other = search.element_bounds(x_other)
        used = np.zeros(len(other), dtype=bool)        # other: sorted unique
        if len(cand):
            within = search.spheres_within(cen[io], rad[io], c_other[ia], r_other[ia], self.reach)
            pairs = cand[within]
            used[ia[within]] = True
        else:
            pairs = cand
        out = self.kernel.evaluate(self.own_ids, x_own, other[used], x_other[used], pairs,
                                   tangent=False, report=False)
        out["nodes"] = nodes
        if self.supports is not None:
            out["support"] = self.supports.evaluate(r_loc, tangent=False)
            out["energy"] += out["support"]["energy"]
        self.kept_evaluation = {"r": np.array(r_loc, copy=True), "mu": self.kernel.mu, "out": out,
                                "pairs": pairs, "near": None}
        return self.kept_evaluation

    @property
    def near_local(self):
        """Owned nodes of the elements near contact at the last evaluation (the step limiter
        of RodProblem.precheck watches them): with the closest-point law the elements with a
        report point within one contact radius of touching (gap > -eps), with the pair
        potential (whose report is made only when asked for) every element with a candidate
        within reach."""
        st = self.kept_evaluation
        if st is None:
            return np.zeros(0, dtype=np.int64)
        if st["near"] is None:
            if not len(self.own_ids):
                close = np.zeros(0, dtype=np.int64)
            elif self.model == "potential":
                close = np.unique(search.positions(self.own_ids, st["pairs"][:, 0], "own"))
            else:
                close = np.flatnonzero(st["out"]["gap"].max(axis=1) > -self.eps)
            near = np.unique(self.lconn[close]) if len(close) else np.zeros(0, dtype=np.int64)
            st["near"] = near[near < self.layout.n_owned]
        return st["near"]

    def add_residual(self, lam, r_loc, q_loc, Floc):
        """Slave-side rows into Floc; master-side rows sent back to their owners (module
        docstring, 6.).  Collective."""
        out = self.evaluate(r_loc)
        n1 = self.p + 1
        act = out["active"]
        leaf_force = np.zeros((len(out["nodes"]), 3))
        if len(act):
            slave, master = self._residual_rows(act, out["nodes"])
            with np.errstate(invalid="ignore"):     # beyond the wall: not finite, refused
                add_in_order(Floc[:, 0:3], slave, out["vec"][:, :n1])
                add_in_order(leaf_force, master, out["vec"][:, n1:])
        Floc[:self.layout.n_owned, 0:3] += self._send_back(leaf_force)
        if self.supports is not None:
            self.supports.add_residual(out["support"], Floc)

    def _residual_rows(self, act, nodes):
        """(slave, master): the additions of the residual rows of the active pairs ``act``
        (in_order_rows) into the local rows of their own elements' nodes and into the fetched
        ``nodes`` of their masters.  Functions of the pairs alone, kept while they stay (the
        pairs in contact change far less often than the positions)."""
        kept = self._rows_kept
        if kept is not None and np.array_equal(kept[0], act) and np.array_equal(kept[1], nodes):
            return kept[2]
        m = self.mesh
        own_index = np.searchsorted(self.own_ids, act[:, 0])
        master_nodes = search.element_node_ids(act[:, 1], m.order, m.nelem, m.closed)
        rows = (in_order_rows(self.lconn[own_index]),
                in_order_rows(np.searchsorted(nodes, master_nodes)))
        self._rows_kept = (act.copy(), nodes.copy(), rows)
        return rows

    def add_jacobian(self, lam, r_loc, q_loc, P, symmetric=False):
        """The kernel's tangent blocks: [slave, master] per active point, [slave, A, B] per
        switch point, positions only (rotations do not enter the contact energy); the same in
        the energy's Hessian (``symmetric``)."""
        out = self.evaluate(r_loc, tangent=True)
        for elems, mat in ((out["active"], out["mat"]), (out["switch"], out["switch_mat"])):
            if len(elems):
                self._add_blocks(P, elems, mat)
        if self.supports is not None:
            self.supports.add_jacobian(out["support"], P)

    @logged("ContactAssemble")
    def _add_blocks(self, P, elems, mat):
        m = self.mesh
        nodes = np.concatenate([search.element_node_ids(elems[:, j], m.order, m.nelem, m.closed)
                                for j in range(elems.shape[1])], axis=1)
        add_position_blocks(P, self.layout, nodes, mat)

    def energy_local(self, lam, r_loc, q_loc):
        """This rank's share of the contact (and mounts') energy.  Collective."""
        return self.evaluate(r_loc)["energy"]

    def trial(self, lam, r_loc, q_loc):
        """(energy share, deepest penetration on this rank at the law's own points) from one
        evaluation without tangent.  Collective."""
        out = self.evaluate(r_loc, tangent=False)
        return out["energy"], self.deepest_local(out)

    def pattern(self, r_loc):
        return self.pattern_pairs(r_loc)

    def covering_pattern(self, r_loc):
        """The pairs that can touch at r_loc (pattern_pairs) and those the tangent there
        couples on any rank.  The pattern it replaces is not kept: a ply that slides over a
        long load step leaves pairs behind that only fill the factorisation (the plectoneme
        from 8.5 to 8.8 turns: the kept pattern grew to 2.3 x its nonzeros and the
        minimisation took 28 s against 20 s).  Collective."""
        n = self.mesh.nelem
        near = self.pattern_pairs(r_loc)
        keys = np.concatenate([near[:, 0] * n + near[:, 1]]
                              + self.comm.allgather(self._coupled_keys(r_loc)))
        return np.stack(np.divmod(np.unique(keys), n), axis=1).astype(np.int64)

    def watched_nodes(self, r_loc=None):
        """near_local, evaluated at r_loc first when given.  Collective then."""
        if r_loc is not None:
            self.evaluate(r_loc)
        return self.near_local

    def pattern_pairs(self, r_loc, margin=None):
        """All ranks' element pairs that the Jacobian may couple near the positions r_loc, as
        sorted unique rows (a, b), a <= b, the same on every rank (collective): the pairs whose
        capsules (contact.element_capsules) come within 2 eps + ``margin`` (PATTERN_MARGIN eps
        by default) of each other, i.e. every pair with a couple of points closer than that;
        with the closest-point law also every two candidate masters of one slave element that
        a switch point can couple (``ContactKernel._switch_terms``); with the pair potential
        only those of them with a couple of its own quadrature points closer than that
        (PotentialKernel.pairs_within: at margin 0 the pairs its tangent couples; the capsules
        held 3 times as many on the bench coil); the mounts' pairs.

        Only pairs that can touch: a wider pattern (the search's Verlet list, 3.5 eps on
        bounding spheres) held 7 times the pairs in contact on the compact plectoneme and
        made its factorisation 3-5 times slower (tools/bench_scaling.py, docs/contact.md).
        An iterate that couples a pair outside the pattern gets a new matrix
        (RodProblem.ensure_pattern, pattern_covers)."""
        margin = self.PATTERN_MARGIN * self.eps if margin is None else float(margin)
        touch = 2.0 * self.eps + margin
        x_el = r_loc[self.lconn]
        pairs, cen, rad = self.search_pairs(*search.element_bounds(x_el), touch, bounds=True)
        # every rank gathers the elements where any rank has candidates (collectives met by
        # all: a rank without candidates of its own took the next allgather for this one's)
        if allreduce(self.comm, int(len(pairs) > 0), op=MPI.MAX):
            lay_ids = self._element_slots()
            x_all = np.concatenate(self.comm.allgather(x_el))
        if len(pairs):
            caps = search.element_capsules(x_all)
            near = search.capsules_within([v[lay_ids[pairs[:, 0]]] for v in caps],
                                      [v[lay_ids[pairs[:, 1]]] for v in caps], touch)
            if self.model != "potential":       # the pair potential has no switch points
                # two closest points of one slave point both lie within 2 eps of it
                pairs = np.concatenate([pairs[near], search.co_master_pairs(
                    pairs[near], cen, rad, 4.0 * self.eps + margin)])
            else:       # a couple of its own points within touch (PotentialKernel.pairs_within)
                pairs = self.kernel.pairs_within(self.own_ids, x_el, self._gathered_ids(), x_all,
                                                 pairs[near], touch)
        pairs = np.concatenate(self.comm.allgather(pairs.reshape(-1, 2)))
        if self.supports is not None:
            pairs = np.concatenate([pairs.reshape(-1, 2), self.supports.pattern_pairs()])
        if len(pairs):
            pairs = np.unique(np.sort(pairs, axis=1), axis=0)
        return pairs.reshape(-1, 2).astype(np.int64)

    def _gathered_ids(self):
        """Every rank's owned elements, in allgather order (gathered once).  Collective the
        first time."""
        if self._all_ids is None:
            self._all_ids = np.concatenate(self.comm.allgather(self.own_ids))
        return self._all_ids

    def _element_slots(self):
        """Row of every element id in arrays allgathered from the owned elements."""
        if self._slots is None:
            ids = self._gathered_ids()
            self._slots = np.empty(self.mesh.nelem, dtype=np.int64)
            self._slots[ids] = np.arange(len(ids))
        return self._slots

    def coupled_pairs(self, r_loc):
        """This rank's element pairs (a, b), a <= b, that the tangent at r_loc couples: every
        (slave, master) in contact and, with the closest-point law, the three pairs of every
        switch point (slave, A, B).  Collective (the evaluation)."""
        n = self.mesh.nelem
        return np.stack(np.divmod(self._coupled_keys(r_loc), n), axis=1)

    def _coupled_keys(self, r_loc):
        """coupled_pairs as sorted unique keys a n + b (n elements): one integer per pair,
        so that sorting and membership are 1-D (np.unique(axis=0) sorts structured rows,
        ten times slower at the plectoneme's few hundred pairs)."""
        out = self.evaluate(r_loc, tangent=True)
        rows = [np.asarray(out["active"], dtype=np.int64).reshape(-1, 2)]
        sw = np.asarray(out["switch"], dtype=np.int64).reshape(-1, 3)
        if len(sw):
            rows += [sw[:, [0, 1]], sw[:, [0, 2]], sw[:, [1, 2]]]
        pairs = np.concatenate(rows)
        lo, hi = np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])
        return np.unique(lo * self.mesh.nelem + hi)

    def pattern_covers(self, r_loc, have):
        """Whether the element pairs ``have`` (sorted unique rows a <= b: the Jacobian's
        preallocated pattern) hold every pair that the tangent at r_loc couples
        (coupled_pairs; each rank checks its own; the mounts' pairs are in every pattern).
        Collective."""
        keys = self._coupled_keys(r_loc)
        ok = True
        if len(keys):
            n = self.mesh.nelem
            held = have[:, 0] * n + have[:, 1] if len(have) else np.zeros(0, dtype=np.int64)
            # rows sorted lexicographically with 0 <= b < n: their keys are sorted
            at = np.searchsorted(held, keys)
            ok = bool(len(held) and at.max() < len(held) and np.array_equal(held[at], keys))
        return self.comm.allreduce(ok, op=MPI.LAND)

    def node_groups(self, pairs):
        """Natural node groups (npair, 2(p+1)) coupled all-to-all by the element pairs."""
        if not len(pairs):
            return None
        m = self.mesh
        return np.concatenate([search.element_node_ids(pairs[:, 0], m.order, m.nelem, m.closed),
                               search.element_node_ids(pairs[:, 1], m.order, m.nelem, m.closed)], axis=1)

    def extra_pattern(self, r_loc):
        """Natural node groups (npair, 2(p+1)) coupled by candidate pairs of the positions
        r_loc within the preallocation margin, from all ranks (every rank needs the rows it
        owns)."""
        return self.node_groups(self.pattern_pairs(r_loc))

    def clearance(self, r_loc, k=48):
        """A lower bound of the free space between strands that have come back toward each
        other (collective):

            c = min |x_i - x_j| - 2 eps  over node pairs with arclength distance a_ij >= delta
                and (|x_i - x_j| < a_ij / 2  or  |x_i - x_j| < 3 eps)

        The second condition leaves out the rod's own continuation (a nearly straight piece has
        |x_i - x_j| ~ a_ij), which cannot be tunnelled through, while a hairpin or a loop about to
        close counts.  Search: the k nearest nodes of every node (scipy cKDTree on the
        allgathered nodes); if none of them counts, the k-th distance bounds the nearest pair
        that does from below.  No strand can reach another by moving less than c / 2, so a
        pseudo-time step whose nodes move less than c / 4 cannot tunnel through the rod."""
        from scipy.spatial import cKDTree
        m, lay = self.mesh, self.layout
        X = lay.allgather_nodes(np.asarray(r_loc[:lay.n_owned], dtype=float))
        n = len(X)
        k = min(k, n)
        dist, idx = cKDTree(X).query(X, k=k)
        arc = np.abs(m.s_nodes[idx] - m.s_nodes[:, None])
        if m.closed:
            arc = np.minimum(arc, m.length - arc)
        counts = (arc >= self.delta) & ((dist < 0.5 * arc) | (dist < 3.0 * self.eps))
        near_min = np.where(counts, dist, np.inf).min(axis=1)
        bound = np.where(np.isfinite(near_min), near_min, dist[:, -1])
        return float(bound.min() - 2.0 * self.eps)

    # -- the KKT picture ----------------------------------------------------------------
    def summary(self):
        """The KKT picture over all ranks, from the last evaluation (the converged state):
        min_gap = min_s (|r(s) - r(sbar)| - 2a) over the Gauss points (negative:
        penetration of the tube of radius a), max_penetration = max <d> / (2a), total_force =
        int f_c ds; the law's (depth d_l = 2 eps - distance, eps = a (1 + standoff)):
        complementarity = int <d_l> f_c ds (zero for exact contact; the penalty makes it ~1/mu,
        a standoff adds about 2 a standoff total_force) by the contact quadrature (the zones, by
        default), active_points = points of that quadrature with d_l > 0 (they carry the
        contact force), zones = contact zones."""
        out = self.kernel.add_report(self.last)
        loc = np.array([out["total_force"], out["complementarity"], len(out["d_active"]),
                        out["zones"]], dtype=float)
        tot = self.comm.allreduce(loc)
        dmax = self.deepest() - self.offset
        self.last_min_gap = -dmax
        return {"min_gap": float(-dmax),
                "max_penetration": float(max(dmax, 0.0) / (2 * self.radius)),
                "total_force": float(tot[0]), "complementarity": float(tot[1]),
                "active_points": int(tot[2]), "zones": int(tot[3]), "penalty": self.mu,
                "radius": self.radius, "standoff": self.standoff, "law_radius": self.eps,
                "exclusion": self.delta,
                **(self.supports.summary(out["support"], self.offset)
                   if self.supports is not None else {})}

    def promised_penalty(self, r_loc):
        """(pen, mu1) at the positions r_loc (collective): pen = max <d> / (2 a) over all
        ranks, the deepest penetration into the tube as a fraction of its diameter, and the
        penalty that keeps the promise p* (-contact_penetration): None while pen <= p*, else
        RAISE mu d_l / d_l*, d_l = d + offset the law's depth, d_l* = p_l 2 eps its promised
        one (equivalently pen <= p*: the law's promise reaches p* into the tube; a line contact
        has d_l ~ 1/mu, so it lands near 0.8 d_l*; a crossing, d_l ~ mu^(-2/3), may need a
        second raise).  The rule of both load paths (-contact_penalty_adapt)."""
        depth = self.deepest(r_loc)
        pen = (depth - self.offset) / (2.0 * self.radius)
        if pen <= self.penetration:
            return pen, None
        return pen, RAISE * self.mu * depth / (self.law_penetration * 2.0 * self.eps)

    def ease_wall(self, r_loc, lam):
        """With the wall (-contact_wall) and -contact_penalty_adapt, after a converged load step
        at r_loc whose deepest couple lies inside the wall's barrier (beyond its start a_b): the
        state keeps the promise (the wall), and the penalty is raised for the next step, which
        then carries its larger forces before the barrier: RAISE mu d / a_b, as
        promised_penalty's (a line contact has d ~ 1/mu).  No re-solve.  Returns the line that
        says so at load ``lam``, or None when nothing was raised.  Collective."""
        if self.wall is None:
            return None
        depth = self.deepest(r_loc, report=False)
        if depth <= self.wall[0]:
            return None
        mu0 = self.mu
        self.set_penalty(RAISE * mu0 * depth / self.wall[0])
        self.penalty_eased += 1
        return (f"  load {lam:.6f}: the contact presses into the wall: penalty {mu0:.4g} -> "
                f"{self.mu:.4g} for the next step")

    def deepest(self, r_loc=None, report=True):
        """max d = 2 eps - distance over all ranks (positive: the deepest penetration), at the
        positions r_loc (local nodes), or of the last evaluation.  Collective.  With ``report``
        (the penalty's promise: -contact_penalty_adapt, the summary) at the report
        points and the law's own points (deepest_local); without, at the law's own points
        alone (RodProblem.precheck compares it at the iterate and its trials, where the pair
        potential makes no report)."""
        out = self.last if r_loc is None else self.evaluate(r_loc, report=report)
        if report:
            self.kernel.add_report(out)
        return self.comm.allreduce(self.deepest_local(out, report), op=MPI.MAX)

    def depth_allowed(self, depth):
        """The deepest penetration a Newton step or a predictor may reach from a state whose
        deepest is ``depth``: twice it, or 2 % of the contact diameter (RodProblem.precheck,
        the minimiser's line search and predictor); never the wall (-contact_wall), where the
        pair potential's energy is infinite."""
        allow = max(2.0 * depth, 0.02 * 2.0 * self.eps)
        if self.wall is None:
            return allow
        return min(allow, self.wall[1] * (1.0 - 1e-9))

    @staticmethod
    def deepest_local(out, report=False):
        """max d over this rank's points of an evaluation ``out``: its ``depth``, at the points
        of the law's own quadrature (the closest-point law's Gauss and zone points, the pair
        potential's point couples); with ``report`` (out has it) the report's gap, end_depth
        and d_active (the report points, an open rod's ends, and the law's own points in
        contact).  The mounts count in both."""
        if report:
            gap = out["gap"]
            deep = max(float(gap.max()) if gap.size else -np.inf,
                       float(out["d_active"].max()) if len(out["d_active"]) else -np.inf,
                       out.get("end_depth", -np.inf))
        else:
            deep = out["depth"]
        if "support" in out:            # the tube pressing into a clamp's mount (support.py)
            deep = max(deep, SupportTerm.deepest_local(out["support"]))
        return deep

    def restart(self, attrs):
        """The adapted penalty of the interrupted run (it never falls along a path)."""
        mu = attrs.get("contact_penalty")
        if self.adapt and mu is not None:
            self.set_penalty(max(self.mu, float(mu)))

    def refuses(self, r_loc):
        """A state beyond the wall (a restart from a run with a larger promise or without the
        wall): the pair potential's energy is infinite there, no minimisation can start."""
        if self.wall is None:
            return None
        depth = self.deepest(r_loc, report=False)
        if depth < self.wall[1]:
            return None
        pen = (depth - self.offset) / (2.0 * self.radius)
        need = (depth + self.kernel.sampling_error() - self.offset) / (2.0 * self.radius)
        return (f"its state presses {pen:.3%} of the diameter into the contact tube, beyond the "
                f"wall that keeps -contact_penetration {self.penetration:g} (the pair "
                f"potential's energy is infinite there): restart with -contact_penetration "
                f"{1.05 * need:.3g} or more, or with -contact_wall 0")

    def report(self, r_loc):
        """The KKT picture (summary) at the local positions r_loc.  Collective."""
        self.evaluate(r_loc, tangent=False)
        return self.summary()

    def run_summary(self, stats):
        """The halo exchange's star forests built, the problem's pattern refreshes and step
        scalings (RodProblem.precheck), the penalty's promise and its raises."""
        s = {"law": self.model, "sf_builds": self.sf_builds,
             "pattern_refreshes": stats.get("pattern_refreshes", 0)}
        for key in ("limited_steps", "penetration_limited_steps", "energy_limited_steps"):
            s[key] = stats.get(key, 0)
        s.update({"penetration_promised": self.penetration, "penalty_adapt": self.adapt,
                  "penalty_raises": self.penalty_raises, "contact_wall": self.wall is not None,
                  "penalty_raises_between_steps": self.penalty_eased,
                  "penalty_raise_failures": self.penalty_failures})
        return s

    def log_text(self):
        return f"  min_gap {self.last_min_gap:+.3e}"

    LAWS = {"potential": "self-contact by the pair potential",
            "projection": "self-contact by the closest-point projection"}

    def describe(self):
        auto = " (-contact_model auto)" if self.model_auto else ""
        return self.LAWS[self.model] + auto

    def qp_fields(self):
        out = self.kernel.add_report(self.last)
        ids = (self.own_ids[:, None] * self.nqc + np.arange(self.nqc)[None, :]).ravel()
        s = self.kernel.slave_arclength(self.own_ids).ravel()
        gap = out["gap"].ravel() - self.offset        # depth into the tube (report points)
        return {"ids": ids, "n": self.mesh.nelem * self.nqc,
                "fields": {"qp_s": s, "gap": np.where(np.isfinite(gap), gap, -1e300),
                           "contact_force": out["force"].ravel()}}
