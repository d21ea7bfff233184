"""Self-contact as a term of the parallel problem: search, halo exchange through a PETSc star
forest, assembly (DESIGN.md: "partition.py and problem.py own all communication"; this module is
the contact part of that communication around the pure kernel of contact.py).

Per evaluation (residual or Jacobian), on every rank:
  1. bounding spheres of the owned elements (contact.element_bounds), allgathered (4 doubles
     per element: the only global exchange, O(N));
  2. candidate pairs (owned element, any element) from a cKDTree (contact.candidate_pairs),
     reach = 2 eps + margin;
  3. the nodes of the candidate master elements are fetched from their owners through a PetscSF
     (leaves = needed nodes, roots = owned nodes); the SF is rebuilt only when that node set
     changes;
  4. the kernel evaluates gap, closest points, energy, residual and tangent on owned slave points;
  5. slave-side residual goes into the owned/ghost rows; master-side residual is sent back to
     the owners through the same SF (reduce with MPI.SUM); tangent blocks go straight into the
     global matrix (MatSetValuesBlocked with off-process rows, communicated at assembly).
The Jacobian's block pattern holds the candidate pairs found with a wider margin
(pattern_reach) at the start of every load step, and before every Newton step the candidates of
the iterate (within reach) are checked against it (RodProblem.ensure_pattern): a pair outside
the pattern gets a new, wider-preallocated matrix before any value is set.  Entries are never
inserted beyond the preallocation: on PETSc 3.18, a new off-diagonal block inserted into an
assembled MPIBAIJ lands in a wrong column, and MUMPS reuses a symbolic analysis that no longer
fits (a segfault).
"""
import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from . import contact as ck, so3
from .partition import add_position_blocks
from .contact_potential import PotentialKernel
from .support import SupportTerm


class ContactTerm:
    def __init__(self, scene, mesh, layout):
        rod, c = scene.rod, scene.contact
        self.mesh, self.layout = mesh, layout
        self.comm = layout.comm.tompi4py()
        self.eps = float(c.radius if c.radius is not None else rod.radius)
        self.delta = float(c.exclusion if c.exclusion is not None else ck.default_exclusion(self.eps))
        self.penetration = float(c.penetration)     # promised largest <d> / (2 eps)
        self.adapt = bool(c.adapt)
        self.mu = float(c.penalty if c.penalty is not None else
                        ck.default_penalty(min(rod.EI1, rod.EI2), self.eps, self.penetration))
        self.penalty_raises = 0         # -contact_penalty_adapt: re-solves with a raised mu
        self.penalty_failures = 0       # ... that failed (state and mu put back)
        self.nqc = int(c.quadrature if c.quadrature else rod.order + 2)
        self.p = rod.order
        self.model = c.model
        if self.model == "potential":
            self.kernel = PotentialKernel(rod.order, self.nqc, self.eps, self.mu, self.delta,
                                          mesh.length, mesh.nelem, mesh.closed,
                                          penetration=self.penetration,
                                          nqp=c.potential_points)
        else:
            self.kernel = ck.ContactKernel(rod.order, self.nqc, self.eps, self.mu, self.delta,
                                           mesh.length, mesh.nelem, mesh.closed,
                                           segments=c.zones)
        self.step_limit = 0.5 * self.eps                         # largest nodal move per Newton step
        self.reach = 2.0 * self.eps + 0.5 * self.eps            # search margin within a Newton step
        self.pattern_reach = 2.0 * self.eps + 4.0 * self.eps + mesh.h   # preallocation margin per step
        self.own_ids = layout.owned_elems
        self.lconn = layout.lconn
        self.unit = MPI.DOUBLE.Create_contiguous(3).Commit()
        self.sf = None
        self.leaf_nodes = None
        self.last = None
        self.last_min_gap = np.nan
        self.near_local = np.zeros(0, dtype=np.int64)
        self.sf_builds = 0
        self._cache = None              # (positions, evaluation, near_local) of the last one
        self.cache_hits = 0
        # the clamps' mounts (support.py): a rod clamped at its start and sliding at its end
        self.supports = None
        bc = scene.bc
        if c.supports and not mesh.closed and bc.start == "clamped" and bc.end == "sliding":
            self.supports = SupportTerm(mesh, layout, self.kernel, mesh.x_init[0],
                                        so3.rot(mesh.q_init[0])[:, 2],
                                        so3.rot(mesh.q_init[-1])[:, 2])

    def set_penalty(self, mu):
        """Change the penalty stiffness mu (E_c = (mu/2) int <d>^2 ds); drops the cached
        evaluation, whose residual and tangent belong to the old mu."""
        self.mu = float(mu)
        self.kernel.mu = self.mu
        self._cache = None

    # -- communication ----------------------------------------------------------------
    def _pairs(self, r_loc, reach, bounds=False):
        x_own = r_loc[self.lconn]
        cen, rad = ck.element_bounds(x_own)
        ids = self.comm.allgather(self.own_ids)
        all_ids = np.concatenate(ids)
        cens = np.concatenate(self.comm.allgather(cen))
        rads = np.concatenate(self.comm.allgather(rad))
        pairs = ck.candidate_pairs(self.own_ids, cen, rad, all_ids, cens, rads, reach,
                                   self.mesh.length, self.mesh.h, self.mesh.closed, self.delta)
        if bounds:                       # bounding spheres of all elements, by element id
            order = np.argsort(all_ids)
            return x_own, pairs, cens[order], rads[order]
        return x_own, pairs

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

    def _fetch(self, r_loc, nodes):
        self._ensure_sf(nodes)
        root = np.ascontiguousarray(r_loc[:self.layout.n_owned], dtype=float)
        leaf = np.zeros((len(nodes), 3))
        self.sf.bcastBegin(self.unit, root, leaf, MPI.REPLACE)
        self.sf.bcastEnd(self.unit, root, leaf, MPI.REPLACE)
        return leaf

    def _send_back(self, leaf_force):
        root = np.zeros((self.layout.n_owned, 3))
        leaf = np.ascontiguousarray(leaf_force, dtype=float)
        self.sf.reduceBegin(self.unit, leaf, root, MPI.SUM)
        self.sf.reduceEnd(self.unit, leaf, root, MPI.SUM)
        return root

    # -- evaluation -------------------------------------------------------------------
    def evaluate(self, r_loc, tangent):
        """The kernel's evaluation at local positions r_loc (collective).  Residual and Jacobian
        at one iterate, or the line search's accepted trial and the residual after it, see the
        same positions: the last evaluation is kept (with its tangent) and reused when every
        rank's positions are bit for bit those it was made at."""
        hit = self._cache is not None and self._cache[0].shape == r_loc.shape \
            and np.array_equal(self._cache[0], r_loc)
        if self.comm.allreduce(hit, op=MPI.LAND):
            self.cache_hits += 1
            out, self.near_local = self._cache[1], self._cache[2]
            self.last = out
            return out
        out = self._evaluate(r_loc)
        self._cache = (np.array(r_loc, copy=True), out, self.near_local)
        return out

    def _evaluate(self, r_loc):
        m = self.mesh
        x_own, pairs = self._pairs(r_loc, self.reach)
        other = np.unique(pairs[:, 1]) if len(pairs) else np.zeros(0, dtype=np.int64)
        other_nodes = ck.element_node_ids(other, m.order, m.nelem, m.closed)
        nodes = np.unique(other_nodes)
        # every rank takes part in the SF collectives, even with nothing to fetch
        leaf = self._fetch(r_loc, nodes)
        x_other = leaf[np.searchsorted(nodes, other_nodes)] if len(other) else np.zeros((0, m.order + 1, 3))
        out = self.kernel.evaluate(self.own_ids, x_own, other, x_other, pairs, tangent=True)
        out["nodes"] = nodes
        if self.supports is not None:
            out["support"] = self.supports.evaluate(r_loc)
            out["energy"] += out["support"]["energy"]
        # owned nodes of elements within one contact radius of touching something (gap > -eps):
        # the step limiter watches them
        close = np.flatnonzero(out["gap"].max(axis=1) > -self.eps) if len(self.own_ids) else []
        near = np.unique(self.lconn[close]) if len(close) else np.zeros(0, dtype=np.int64)
        self.near_local = near[near < self.layout.n_owned]
        self.last = out
        return out

    def add_residual(self, r_loc, Floc):
        out = self.evaluate(r_loc, tangent=False)
        n1 = self.p + 1
        act = out["active"]
        leaf_force = np.zeros((len(out["nodes"]), 3))
        if len(act):
            own_index = np.searchsorted(self.own_ids, act[:, 0])
            np.add.at(Floc[:, 0:3], self.lconn[own_index], out["vec"][:, :n1])
            m = self.mesh
            master_nodes = ck.element_node_ids(act[:, 1], m.order, m.nelem, m.closed)
            np.add.at(leaf_force, np.searchsorted(out["nodes"], master_nodes), out["vec"][:, n1:])
        Floc[:self.layout.n_owned, 0:3] += self._send_back(leaf_force)
        if self.supports is not None:
            self.supports.add_residual(out["support"], Floc)

    def add_jacobian(self, r_loc, P):
        """The kernel's tangent blocks: [slave, master] per active point, [slave, A, B] per
        switch point, positions only (rotations do not enter the contact energy)."""
        out = self.evaluate(r_loc, tangent=True)
        for elems, mat in ((out["active"], out["mat"]), (out["switch"], out["switch_mat"])):
            if len(elems):
                self._add_blocks(P, elems, mat)
        if self.supports is not None:
            self.supports.add_jacobian(out["support"], P)

    def _add_blocks(self, P, elems, mat):
        m = self.mesh
        nodes = np.concatenate([ck.element_node_ids(elems[:, j], m.order, m.nelem, m.closed)
                                for j in range(elems.shape[1])], axis=1)
        add_position_blocks(P, self.layout, nodes, mat)

    def energy(self, r_loc):
        return self.evaluate(r_loc, tangent=False)["energy"]

    def pattern_pairs(self, r_loc, reach):
        """All ranks' element pairs coupled in the Jacobian by the candidates within ``reach``,
        as sorted unique rows (a, b), a <= b, the same on every rank (collective): every
        candidate pair (slave, master), and every two masters of the same slave element (a
        switch point couples them, ``ContactKernel._switch_terms``, if they lie within 4 eps + margin
        of each other)."""
        _, pairs, cen, rad = self._pairs(r_loc, reach, bounds=True)
        # two closest points of one slave point both lie within 2 eps of it: masters farther
        # apart than 4 eps never share a switch point.  The margin is the evaluation's own
        # (reach - 2 eps), not the wider preallocation margin: these pairs would fill most
        # of the matrix of a compact plectoneme, and ensure_pattern adds any that appear
        if self.model != "potential":           # the pair potential has no switch points
            pairs = np.concatenate([pairs, ck.co_master_pairs(pairs, cen, rad,
                                                              self.reach + 2.0 * self.eps)])
        pairs = np.concatenate(self.comm.allgather(pairs))
        if self.supports is not None:
            pairs = np.concatenate([pairs.reshape(-1, 2), self.supports.pattern_pairs()])
        if len(pairs):
            pairs = np.unique(np.sort(pairs, axis=1), axis=0)
        return pairs.reshape(-1, 2).astype(np.int64)

    def node_groups(self, pairs):
        """Natural node groups (npair, 2(p+1)) coupled all-to-all by the element pairs."""
        if not len(pairs):
            return None
        m = self.mesh
        return np.concatenate([ck.element_node_ids(pairs[:, 0], m.order, m.nelem, m.closed),
                               ck.element_node_ids(pairs[:, 1], m.order, m.nelem, m.closed)], axis=1)

    def extra_pattern(self, r_loc):
        """Natural node groups (npair, 2(p+1)) coupled by candidate pairs of the positions
        r_loc within the preallocation margin, from all ranks (every rank needs the rows it
        owns)."""
        return self.node_groups(self.pattern_pairs(r_loc, self.pattern_reach))

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
        min_gap = min_s (|r(s) - r(sbar)| - 2 eps) over the Gauss points (negative:
        penetration), max_penetration = max <d> / (2 eps), total_force = int f_c ds,
        complementarity = int <d> f_c ds (zero for exact contact; the penalty makes it ~1/mu)
        by the contact quadrature (the zones, by default), active_points = points of that
        quadrature with d > 0 (they carry the contact force), zones = contact zones."""
        out = self.last
        loc = np.array([out["total_force"], out["complementarity"], len(out["d_active"]),
                        out["zones"]], dtype=float)
        tot = self.comm.allreduce(loc)
        dmax = self.deepest()
        self.last_min_gap = -dmax
        return {"min_gap": float(-dmax), "max_penetration": float(max(dmax, 0.0) / (2 * self.eps)),
                "total_force": float(tot[0]), "complementarity": float(tot[1]),
                "active_points": int(tot[2]), "zones": int(tot[3]), "penalty": self.mu,
                "radius": self.eps, "exclusion": self.delta,
                **(self.supports.summary(out["support"]) if self.supports is not None else {})}

    def deepest(self, r_loc=None):
        """max d = 2 eps - distance over all ranks (positive: the deepest penetration), at the
        positions r_loc (local nodes), or of the last evaluation.  Collective.  The deepest
        point of a zone may lie between the Gauss points: the zone points count too."""
        out = self.last if r_loc is None else self.evaluate(r_loc, tangent=False)
        return self.comm.allreduce(self.deepest_local(out), op=MPI.MAX)

    @staticmethod
    def deepest_local(out):
        """max d over this rank's Gauss and zone points of an evaluation ``out``."""
        gap = out["gap"]
        deep = max(float(gap.max()) if gap.size else -np.inf,
                   float(out["d_active"].max()) if len(out["d_active"]) else -np.inf)
        if "support" in out:            # the tube pressing into a clamp's mount (support.py)
            deep = max(deep, SupportTerm.deepest_local(out["support"]))
        return deep

    def qp_fields(self):
        out = self.last
        ids = (self.own_ids[:, None] * self.nqc + np.arange(self.nqc)[None, :]).ravel()
        s = self.kernel.slave_arclength(self.own_ids).ravel()
        gap = out["gap"].ravel()
        return {"ids": ids, "n": self.mesh.nelem * self.nqc,
                "fields": {"qp_s": s, "gap": np.where(np.isfinite(gap), gap, -1e300),
                           "contact_force": out["force"].ravel()}}
