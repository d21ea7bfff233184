"""Stability of an equilibrium: the inertia of the energy Hessian.

At an equilibrium the consistent tangent equals the (symmetric) Hessian of the total energy in
the exponential chart (elastic.py).  Its number of negative eigenvalues, from a MUMPS LDL^T
(Cholesky-type) factorisation (-mat_mumps_icntl_13 1 for a parallel-correct count), is the
number of independent directions in which the energy decreases: 0 means a stable (local
minimum) equilibrium.  Dirichlet rows hold 1 on the diagonal and count as positive.  An open
rod's Hessian without contact is counted by the chain LDL^T (chain.py, the pivot blocks'
inertias; on several ranks schur.RankSchur, Haynsworth's inertia additivity) where its factors
are backward stable (Inertia.CHAIN_BACKWARD), by MUMPS otherwise.

lowest_eigenpair gives the lowest eigenvalue of the same (unscaled) Hessian and its eigenvector
(the buckling or writhing mode of an unstable equilibrium; tests/test_relax.py):
the matrix is gathered to rank 0 (dense LAPACK up to DENSE_MAX dofs, sparse shift-invert beyond),
the vector broadcast and scattered back to the owned rows of the SNES layout.
"""
import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from rodsnes.collective import on_root
from rodsnes.model.assembly import set_diagonal
from rodsnes.model.term import same_patterns
from rodsnes.solve import chain, schur
from rodsnes.solve.linear import is_default, mumps_fill_room, mumps_ordering, option_default


def zero_shift(A):
    """1000 eps max|diag(A)|: the round-off scale of A's entries, against which the chain
    LDL^T's backward error is judged (Inertia.CHAIN_BACKWARD).  Collective."""
    d = A.getDiagonal()
    out = 1e3 * np.finfo(float).eps * d.norm(PETSc.NormType.INFINITY)
    d.destroy()
    return out


# The inertia is counted on H + tau M (Sylvester: the eigenvalues of H v = lambda M v below
# -tau), M the rod's lumped mass metric (stability_metric), tau the larger of
#   NEUTRAL x EI_min / L^4: an eigenvalue above it is neutral, not an instability (the Euler
#     column's falls by 13.4 EI / L^4 per unit of relative load past buckling: a state within
#     ~0.1 % of a critical load counts as stable; the imperfect twisted ring's near-symmetry,
#     -2e-3 EI / L^4, is neutral), and
#   ROUNDOFF x eps max(H_ii / M_ii) over the position rows: the round-off of an exact zero mode
#     (a buckled isotropic column turned about its load axis: |lambda| <= 0.6 eps max(H_ii /
#     M_ii) measured at 16-200 elements), ~eps EA / h^2.  Not the rotation rows': their ratio,
#     GA EA / EI from the shear on any mesh, is no bending mode's round-off and hid the
#     buckling of a column with EA = GA = 1e8 EI / L^2 (19 EI / L^4).
# Both are mesh-independent in the metric, where H's own eigenvalues shrink with h while its
# diagonal grows as 1 / h: a shift of eps |H| I certified a straight column past its buckling
# load as stable from a few hundred elements on.
NEUTRAL = 1e-2
ROUNDOFF = 10.0
# a band this many times NEUTRAL (round-off's) is reported as a coarse count (Run)
COARSE = 10.0
# how fast a buckling eigenvalue of H v = lambda M v falls past its critical load: 13.4 EI/L^4
# per unit of relative load for the clamped-free Euler column (the note of a wide band: the
# overload a state may carry and still count as stable)
FALL = 13.4
# the overload a band may hide before the run warns of it (Run): 5 %
WARN_OVERLOAD = 0.05


def lumped_metric(problem, l2):
    """A lumped metric per unit line density, (owned nodes, 6): m_i = int N_i ds on the position
    rows, m_i l2 on the rotation rows, 1 on the Dirichlet rows.  Collective."""
    from rodsnes.model.mesh import lumped_weights
    m = lumped_weights(problem.mesh, problem.layout)
    M = np.empty((len(m), 6))
    M[:, 0:3] = m[:, None]
    M[:, 3:6] = (m * l2)[:, None]
    M.reshape(-1)[problem.constraints.rows_local] = 1.0
    return M


def stability_metric(problem):
    """The rod's lumped mass metric (lumped_metric with l2 = (EI1 + EI2) / (2 EA), the bending
    radius of gyration squared of a section of one modulus): the eigenvalues of H v = lambda
    M v (rho A omega^2 of the rod's small vibrations) converge with the mesh.  Collective."""
    rod = problem.scene.rod
    return lumped_metric(problem, (rod.EI1 + rod.EI2) / (2.0 * rod.EA))


def neutral_shift(problem, diagonal, metric, positions):
    """(tau M, tau): the shift the inertia is counted under (NEUTRAL, ROUNDOFF above), a new
    Vec like ``diagonal`` (H's diagonal) from ``metric`` (M of H's rows: stability_metric);
    ``positions`` marks H's position rows (the round-off term's).  The widest band in
    problem.stats["neutral_band"].  Collective."""
    rod = problem.scene.rod
    scale = min(rod.EI1, rod.EI2) / rod.length ** 4
    d = diagonal.getArray(readonly=True)[positions]
    m = metric.getArray(readonly=True)[positions]
    big = problem.layout.comm.tompi4py().allreduce(
        float(np.max(np.abs(d) / m)) if len(d) else 0.0, op=MPI.MAX)
    tau = max(NEUTRAL * scale, ROUNDOFF * np.finfo(float).eps * big)
    shift = metric.copy()
    shift.scale(tau)
    # the widest band of the run, in units of EI_min / L^4 (summary.json's neutral_band)
    problem.stats["neutral_band"] = max(problem.stats.get("neutral_band", 0.0), tau / scale)
    return shift, tau


def metric_rows(problem, comps=slice(None)):
    """(M, positions) of H's owned rows, the components ``comps`` of each node: the values of
    stability_metric and which rows are positions (the round-off term's, neutral_shift).
    Collective."""
    positions = np.zeros((problem.layout.n_owned, 6), dtype=bool)
    positions[:, 0:3] = True
    return stability_metric(problem)[:, comps].ravel(), positions[:, comps].ravel()


class ChainCount:
    """The chain LDL^T's count of the negative eigenvalues of a symmetric BAIJ matrix H (module
    docstring): chain.ChainLU's pivot blocks on one rank, on several schur.RankSchur (a python
    PC) with its stretches' and the separator's Schur complement's (Haynsworth).  A count is
    taken where the factors solve H x = b, b_i = sin(0.37 i), to a backward error within the
    caller's bound (i the unknown's natural number, Layout.natural_rows: the same b on any
    number of ranks): count(H, bound) gives it or None; solve(b, x) by the last factors;
    ``backward`` the error found, ``structural`` where the condensation cannot count at all (a
    stretch not a chain, the whole-matrix mode)."""

    def __init__(self, layout, lu=None, pc=None):
        self.layout, self.lu, self.pc = layout, lu, pc
        self.backward = None
        self.structural = False

    @classmethod
    def make(cls, H, problem):
        """The ChainCount of H (None for a matrix other than BAIJ, -mat_type aij say, and on one
        rank where its pattern fills in the node order)."""
        if H.getComm().getSize() > 1:
            if H.getType() != PETSc.Mat.Type.MPIBAIJ:
                return None     # each rank's diagonal block is RankSchur's to check (_chain_lu)
            pc = PETSc.PC().create(comm=H.getComm())
            pc.setType(PETSc.PC.Type.PYTHON)
            ctx = schur.RankSchur(problem)
            ctx.inertia = True
            pc.setPythonContext(ctx)
            return cls(problem.layout, pc=pc)
        lu = chain.plan_of(H)
        return None if lu is None else cls(problem.layout, lu=lu)

    def plan(self, H):
        """Before H has values (a solver's set-up): on several ranks the condensation's plan
        (schur.RankSchur.plan); on one the chain LU's, made with the count.  Collective."""
        if self.pc is not None:
            self.pc.setOperators(H)
            self.pc.getPythonContext().plan(self.pc)

    def count(self, H, bound):
        """H's negative eigenvalues, or None (a singular pivot block, factors not backward
        stable within ``bound`` |H| |x|, a stretch not a chain).  Collective."""
        self.backward = None
        if self.lu is not None:
            if not self.lu.factor(H, inertia=True):
                return None
            n = self.lu.negative
        else:
            self.pc.setOperators(H)
            try:
                self.pc.setUp()
            except PETSc.Error:
                return None
            ctx = self.pc.getPythonContext()
            n, self.structural = ctx.negative, ctx.structural
        if n is None or not self._backward_stable(H, bound):
            return None
        return n

    def solve(self, b, x):
        """x = H^-1 b by the last factors.  Collective."""
        if self.lu is not None:
            x.setArray(self.lu.solve(b.getArray(readonly=True).copy()))
        else:
            self.pc.apply(b, x)

    def _backward_stable(self, H, bound):
        """Whether the last factors solve H x = b to a backward error |H x - b| / (|H| |x|) of
        at most ``bound`` / |H| (sets ``backward``).  Collective."""
        b = H.createVecRight()
        lo, hi = b.getOwnershipRange()
        b.setArray(np.sin(0.37 * self.layout.natural_rows(hi - lo)))
        x = b.duplicate()
        self.solve(b, x)
        r = b.duplicate()
        H.mult(x, r)
        r.axpy(-1.0, b)
        norm = H.norm(PETSc.NormType.INFINITY)
        scale = norm * x.norm(PETSc.NormType.INFINITY)
        self.backward = r.norm(PETSc.NormType.INFINITY) / scale if scale > 0 else np.inf
        for v in (b, x, r):
            v.destroy()
        return bool(norm > 0 and self.backward <= bound / norm)

    def destroy(self):
        if self.pc is not None:
            self.pc.destroy()
        self.lu = self.pc = None


class Inertia:
    """The negative eigenvalues of the energy Hessian, counted by the chain LDL^T where it
    applies (an open rod without contact: H in BAIJ, chain.ChainLU on one rank, schur.RankSchur
    on several; module docstring, CHAIN_BACKWARD) and otherwise by MUMPS LDL^T (INFOG(12), the
    negative pivots; -stability_mat_mumps_icntl_13 1 makes the count right on any number of
    ranks; ordered as the Newton step's MUMPS, linear.mumps_ordering).  The Hessian goes into
    an SBAIJ matrix of the problem's layout (the upper block triangle, half the entries;
    Dirichlet rows masked as it is assembled) that is kept, with
    its factorisation's symbolic analysis, while the block pattern stays the same: a count is
    one Hessian assembly and one numeric LDL^T (half the flops of Newton's LU).  The diagonal
    is shifted by tau M (neutral_shift): the count is of the eigenvalues of H v = lambda M v
    below -tau, so that exact zero modes and near-neutral ones count as positive, the same on
    any mesh.  Newton itself factors the consistent tangent by LU: on the symmetric Hessian
    (equal at equilibrium, O(|F|) apart elsewhere) Newton stagnated on the Michell ring's
    unstable branch near its bifurcation (test_restart), where the consistent tangent
    converges.

    On several ranks a Hessian of at most REDUNDANT_MAX unknowns is factored whole on every
    rank (a sequential MUMPS LDL^T of the gathered matrix, MatCreateSubMatrices), not by MUMPS
    over the ranks: MUMPS's parallel factorisation is not reproducible bit for bit (its dynamic
    scheduling changes the order of the sums from run to run), and the minimiser's steps along
    H's shifted factor then made two identical 2-rank runs of the plectoneme part at 7.2 turns
    (different iterations and final states, each a stable equilibrium)."""

    REDUNDANT_MAX = 30000       # unknowns up to which several ranks each factor H whole
    # the chain LDL^T's count is taken where its factors solve H x = b (b fixed) to a backward
    # error |H x - b| <= CHAIN_BACKWARD (t / |H|) |H| |x|, t = zero_shift(H) the round-off
    # scale of H's entries: the factors of H + E with |E| a tenth of t, whose inertia is H's but
    # where an eigenvalue lies within |E| of zero.  Without pivoting between blocks a small
    # pivot block can carry growth (the rod's leading stretch near a critical state of its own:
    # 8e-14 in a roll-up's closed turn counted without the neutral band, while t / |H| is
    # about 1e-13); then MUMPS, pivoting, counts instead.
    CHAIN_BACKWARD = 0.1

    def __init__(self, problem, prefix="stability_"):
        self.problem, self.prefix = problem, prefix
        self.patterns = None
        self.H = None
        self.pc = None
        self.whole = None               # the redundant factorisation's gathered H, IS, scatter
        self.chain = None               # the ChainCount where the chain LDL^T applies
        self.by_chain = False           # the last factorisation was the chain's
        self.fallback = None            # H's AIJ copy for the counts handed to MUMPS
        self.diagonal = None
        self.builds = 0                  # matrices (and symbolic analyses) made
        self.counts = 0
        self.chain_counts = 0            # counts made by the chain LDL^T
        self.comps = slice(None)         # the components of each node H holds
        self.tau = None                  # the last count's tau (neutral_shift)
        self.metric = None               # M of H's rows (stability_metric), with H
        self.metric_rows = None          # metric_rows (lumped_weights: 13 ms at 10^4 elements)

    @property
    def backward(self):
        """The backward error of the chain's last factors (ChainCount), None without them."""
        return None if self.chain is None else self.chain.backward

    @property
    def chain_structural(self):
        """The condensation cannot count by its stretches (a ring, a long middle stretch):
        the kept SBAIJ MUMPS LDL^T from the next assembly on."""
        return self.chain is not None and self.chain.structural

    def _matrix(self, patterns, symmetric=True):
        """The SBAIJ matrix the Hessian goes into (the problem's layout); BAIJ for the chain
        LDL^T (``symmetric`` False)."""
        p = self.problem
        return p.layout.create_matrix(p.node_groups(patterns), symmetric=symmetric,
                                      positions_only=p.positions_only(patterns))

    def _chain_applies(self):
        """The Hessian counted by the chain LDL^T: a pattern that stays, the kernel built, on
        several ranks a rod long enough for the condensation (schur.pays), and no solver or
        MUMPS option given under the prefix (-stability_pc_factor_mat_solver_type mumps, any
        -stability_mat_mumps_*: MUMPS as asked)."""
        p = self.problem
        # the user's options, not those rodsnes set for its own MUMPS LDL^T (option_default)
        asked = [k for k in PETSc.Options().getAll()
                 if k.startswith((self.prefix + "pc_factor_mat_solver_type",
                                  self.prefix + "mat_mumps_")) and not is_default(k)]
        size = p.layout.comm.getSize()
        return (not p.moving_pattern and chain.available() and not asked
                and (size == 1 or schur.pays(p.mesh.n_nodes, size)))

    def _build_chain(self, patterns):
        """H as BAIJ and its ChainCount, where the pattern eliminates without fill in the node
        order (one rank; on several, decided at every count).  Returns whether it was made."""
        H = self._matrix(patterns, symmetric=False)
        counter = ChainCount.make(H, self.problem)
        if counter is None:
            H.destroy()
            return False
        self.H, self.chain, self.patterns = H, counter, patterns
        self.builds += 1
        return True

    def _view(self):
        """What the Hessian is assembled through (None: H itself, Dirichlet rows masked)."""
        return None

    def _build(self, patterns):
        p = self.problem
        self.destroy()
        if self._chain_applies() and self._build_chain(patterns):
            return
        self._build_mumps(patterns)

    def _mumps_pc(self, whole):
        """MUMPS's LDL^T under the prefix, with rodsnes' defaults (sequential where ``whole``:
        every rank factors the gathered H)."""
        p = self.problem
        pc = PETSc.PC().create(comm=PETSc.COMM_SELF if whole else p.layout.comm)
        pc.setOptionsPrefix(self.prefix)
        pc.setType(PETSc.PC.Type.CHOLESKY)
        pc.setFactorSolverType("mumps")
        option_default(self.prefix + "mat_mumps_icntl_13", "1")
        mumps_fill_room(p, self.prefix)
        mumps_ordering(p, self.prefix)
        pc.setFromOptions()
        return pc

    def _build_mumps(self, patterns):
        """H as SBAIJ with MUMPS's LDL^T, kept while the pattern stays."""
        p = self.problem
        self.H = self._matrix(patterns)
        n = self.H.getSize()[0]
        whole = p.layout.comm.getSize() > 1 and n <= self.REDUNDANT_MAX
        if whole:
            self.whole = {"is": PETSc.IS().createStride(n, 0, 1, comm=PETSc.COMM_SELF),
                          "H": None, "scatter": None}
        self.pc = self._mumps_pc(whole)
        self.patterns = patterns
        self.builds += 1

    def _handed_over(self, H):
        """H, the chain's BAIJ, as an AIJ copy flagged symmetric for MUMPS's LDL^T (a count the
        chain could not take); the copy and the PC are kept for the next hand-over of the same
        pattern (refilled in place, a numeric factorisation)."""
        self.fallback = H.convert(PETSc.Mat.Type.AIJ, self.fallback or PETSc.Mat())
        self.fallback.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        if self.pc is None:
            self.pc = self._mumps_pc(False)
        return self.fallback

    def assemble(self, patterns=None):
        """The symmetric Hessian of the problem's current state into H (kept; a new matrix and
        symbolic analysis when the terms' patterns changed).  ``patterns``: the terms' patterns
        to preallocate (RodProblem.patterns; default: the terms' at the current state, e.g. a
        contact search within the preallocation margin).  Collective."""
        p = self.problem
        if patterns is None:
            patterns = p.patterns_at()
        if not same_patterns(patterns, self.patterns):
            self._build(patterns)
        elif self.chain_structural:     # the condensation cannot count: MUMPS, kept, from now
            self.destroy()
            self._build_mumps(patterns)
        p.jacobian(None, p.state.X, self.H, self.H, symmetric=True, view=self._view())
        if self.diagonal is not None:
            self.diagonal.destroy()
        self.diagonal = self.H.getDiagonal()
        return self.H

    def factor(self, shift=None):
        """LDL^T of H + diag(shift) (shift a Vec; None: tau M, neutral_shift) by MUMPS;
        returns the number of negative pivots (INFOG(12)), or -1 when the factorisation failed
        (a zero pivot, MUMPS out of room).  The factor stays for solve().  Collective."""
        H = self.H
        d = self.diagonal.copy()
        if shift is None:
            if self.metric_rows is None:     # the mesh's: once
                self.metric_rows = metric_rows(self.problem, self.comps)
            if self.metric is None:          # a Vec with H
                self.metric = self.diagonal.duplicate()
                self.metric.setArray(self.metric_rows[0])
            shift, self.tau = neutral_shift(self.problem, self.diagonal, self.metric,
                                            self.metric_rows[1])
            d.axpy(1.0, shift)
            shift.destroy()
        else:
            d.axpy(1.0, shift)
        set_diagonal(H, d, add=False)
        d.destroy()
        self.counts += 1
        self.by_chain = False
        if self.chain is not None:
            n = self.chain.count(H, self.CHAIN_BACKWARD * zero_shift(H))
            if n is not None:
                self.by_chain = True
                self.chain_counts += 1
                return n
            # a singular or growing pivot block: this count by MUMPS (pivoting) on an AIJ copy
            A = self._handed_over(H)
        else:
            A = self._gathered(H) if self.whole is not None else H
        self.pc.setOperators(A)
        try:
            self.pc.setUp()
        except PETSc.Error:
            self.pc.reset()
            self.pc.setOperators(A)
            return -1
        F = self.pc.getFactorMatrix()
        if F.getMumpsInfog(1) < 0:
            # a failure MUMPS reports in INFOG(1), not as an error: PETSc 3.18 then skips every
            # later numeric factorisation of this PC (each shift would fail again); reset, as
            # the error branch does
            self.pc.reset()
            self.pc.setOperators(A)
            return -1
        return int(F.getMumpsInfog(12))

    def _gathered(self, H):
        """The whole of H on every rank (a sequential SBAIJ, refilled in place).  Collective."""
        w = self.whole
        if w["H"] is None:
            w["H"] = H.createSubMatrices(w["is"], w["is"])[0]
        else:
            H.createSubMatrices(w["is"], w["is"], submats=[w["H"]])
            # PETSc 3.18 refills an MPIAIJ's submatrix without raising its state (BAIJ and
            # SBAIJ raise it): the PC would see the matrix unchanged and keep the old factor -
            # a stale inertia and solve under -mat_type aij
            w["H"].stateIncrease()
        return w["H"]

    def solve(self, b, x):
        """x = (H + shift)^-1 b with the last factor.  Collective."""
        if self.by_chain:
            self.chain.solve(b, x)
            return
        w = self.whole
        if w is None:
            self.pc.apply(b, x)
            return
        if w["scatter"] is None:
            w["scatter"], w["b"] = PETSc.Scatter.toAll(b)
            w["x"] = w["b"].duplicate()
        w["scatter"].scatter(b, w["b"], addv=PETSc.InsertMode.INSERT_VALUES,
                             mode=PETSc.ScatterMode.FORWARD)
        self.pc.apply(w["b"], w["x"])
        lo, hi = x.getOwnershipRange()
        x.setArray(w["x"].getArray(readonly=True)[lo:hi])

    def setup(self):
        """Before the first count (a solver's set-up, profiling.SET_UP): the matrix H goes into,
        for the terms' present patterns, and its factorisation's plan (the chain LDL^T's) or
        its MUMPS PC, which the first count then finds made.  Collective."""
        patterns = self.problem.patterns_at()
        if not same_patterns(patterns, self.patterns):
            self._build(patterns)
            if self.chain is not None:
                self.chain.plan(self.H)

    def count(self):
        """Negative eigenvalues of the symmetric Hessian at the problem's current state.
        Collective."""
        self.assemble()
        return self.factor()

    def destroy(self):
        w = self.whole or {}
        for obj in (self.pc, self.H, self.diagonal, w.get("H"), w.get("is"), w.get("scatter"),
                    w.get("b"), w.get("x"), self.fallback, self.chain, self.metric):
            if obj is not None:
                obj.destroy()
        self.pc = self.H = self.whole = self.diagonal = self.chain = self.fallback = None
        self.metric = None
        self.by_chain = False


def inertia_of(problem):
    """The problem's Inertia (its full Hessian's), made at the first call and kept on the
    problem between counts."""
    if problem.inertia is None:
        problem.inertia = Inertia(problem)
    return problem.inertia


def negative_eigenvalues(problem):
    """Number of negative eigenvalues of the symmetric tangent at the current state."""
    return inertia_of(problem).count()


def negative_eigenvalues_scaled(problem):
    """The same count by a factorisation made afresh: the Hessian in AIJ, Jacobi-scaled
    (a congruence, so the inertia is kept), shifted by neutral_shift, MUMPS Cholesky with
    MatGetInertia (ICNTL(24) null pivots).  The reference the kept-factorisation count is
    tested against."""
    H = hessian(problem)
    A = H.convert(PETSc.Mat.Type.AIJ, PETSc.Mat())
    A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    d = A.getDiagonal()
    values, positions = metric_rows(problem)
    M = d.duplicate()
    M.setArray(values)
    shift, _ = neutral_shift(problem, d, M, positions)
    d.axpy(1.0, shift)
    A.setDiagonal(d)
    for v in (shift, d, M):
        v.destroy()
    # symmetric Jacobi scaling D^-1/2 A D^-1/2 is a congruence, so it keeps the inertia
    # (Sylvester) while bringing axial (EA/h) and bending (EI/h) pivots to one scale, so that
    # MUMPS's null-pivot test does not swallow soft negative directions
    d = A.getDiagonal()
    d.abs()
    d.sqrtabs()
    d.reciprocal()
    A.diagonalScale(d, d)
    pc = PETSc.PC().create(comm=problem.layout.comm)
    pc.setOptionsPrefix("stability_check_")
    pc.setOperators(A)
    pc.setType(PETSc.PC.Type.CHOLESKY)
    pc.setFactorSolverType("mumps")
    for icntl in ("13", "24"):     # 13: inertia over all ranks; 24: null pivots (MatGetInertia needs it)
        option_default("stability_check_mat_mumps_icntl_" + icntl, "1")
    pc.setFromOptions()
    pc.setUp()
    nneg, nzero, npos = pc.getFactorMatrix().getInertia()
    pc.destroy()
    A.destroy()
    H.destroy()
    return int(nneg)


# -- the lowest eigenpair -------------------------------------------------------------------
DENSE_MAX = 4000
"""Up to this many dofs the eigenpair comes from a dense LAPACK eigh (dsyevr, lowest few pairs
only) on rank 0: O(n^3) flops and 8 n^2 bytes there.  Measured on the 2-core CI machine
(Debian's reference BLAS): 0.2 s at n = 1000, 1.7 s at 2000, 18 s at 4000 (17.5 s for a 3960-dof
ring, where eigsh takes 0.22 s: lower DENSE_MAX if that matters).  Beyond it a
sparse shift-invert Lanczos (scipy eigsh, sigma slightly below 0, one sparse LU of H - sigma I
on rank 0, then two block inverse-iteration steps): O(n) for the banded rod Hessian, 0.2 s
at 3960 and 0.5 s at 7200 dofs."""


def hessian(problem):
    """The symmetric energy Hessian at the current state, in a new BAIJ matrix of the problem's
    layout (Dirichlet rows and columns: identity).  Collective."""
    H = problem.layout.create_matrix(problem.node_groups(problem.patterns_at()))
    problem.jacobian(None, problem.state.X, H, H, symmetric=True)
    return H


def gather_csr(A, layout, root=0):
    """The assembled parallel matrix A as a scipy CSR matrix in NATURAL dof numbering (node
    6 + component) on ``root`` (None elsewhere).  Collective: every rank sends its owned rows
    (getValuesCSR of the AIJ form: global PETSc column numbers)."""
    import scipy.sparse as sp
    comm = layout.comm.tompi4py()
    B = A.convert(PETSc.Mat.Type.AIJ, PETSc.Mat())
    ai, aj, av = B.getValuesCSR()
    B.destroy()
    parts = comm.gather((np.asarray(ai), np.asarray(aj), np.asarray(av)), root=root)
    if comm.rank != root:
        return None
    n = 6 * layout.n_global
    rows, cols, vals = [], [], []
    row0 = 0
    for r, (ai, aj, av) in enumerate(parts):   # rank r holds PETSc rows 6 starts[r] ...
        nr = len(ai) - 1
        rows.append(row0 + np.repeat(np.arange(nr), np.diff(ai)))
        cols.append(aj)
        vals.append(av)
        row0 += nr
    A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    # PETSc dof of natural dof (node, c): 6 nat2petsc[node] + c
    perm = (6 * layout.nat2petsc[:, None] + np.arange(6)[None, :]).ravel()
    return A[perm][:, perm].tocsr()


def _canonical(V, w, tol):
    """One vector of the cluster of lowest eigenvalues, chosen independently of the basis
    LAPACK/ARPACK returns for a (nearly) degenerate cluster (symmetric rods: buckling in y or z;
    rings: the sin/cos pair): P e_k / |P e_k| with P the cluster's projector and k the first
    position dof (natural numbering; any dof for a mode without displacement) where diag(P) is
    largest; the sign makes its largest entry positive."""
    cl = np.flatnonzero(w <= w[0] + tol)
    Vc = V[:, cl]
    d = np.einsum("ij,ij->i", Vc, Vc)
    pos = (np.arange(len(d)) % 6) < 3
    if d[pos].max() > 1e-6 * d.max():
        d = np.where(pos, d, 0.0)
    k = int(np.flatnonzero(d >= (1 - 1e-6) * d.max())[0])
    v = Vc @ Vc[k]
    v /= np.linalg.norm(v)
    a = np.abs(v)
    j = int(np.flatnonzero(a >= (1 - 1e-6) * a.max())[0])
    return (v if v[j] > 0 else -v), len(cl)


def lowest_eigenpair(problem, nneg=None, dense_max=None):
    """The lowest eigenvalue lam of the symmetric energy Hessian H at the current state and its
    unit eigenvector v (a PETSc vector of the SNES layout: positions and rotation increments
    theta per node), with H v = lam v; plain Euclidean eigenproblem of H (no metric).

    H is gathered to rank 0; dense eigh for n <= dense_max (default DENSE_MAX) dofs, else
    scipy.sparse.linalg.eigsh in shift-invert mode about sigma = -1e3 eps max|diag H| for the
    nneg + 4 eigenvalues nearest sigma (nneg: the number of negative eigenvalues if known), of
    which the lowest is taken: the most negative one is missed only if more than 4 positive
    eigenvalues lie closer to 0 than it does.  The vector is broadcast and each rank keeps
    its owned rows.  Returns (lam, v, info) with info = {n, method, seconds, cluster,
    residual}, the same on every rank.  Collective."""
    import time
    t0 = time.perf_counter()
    lay = problem.layout
    comm = lay.comm.tompi4py()
    dense_max = DENSE_MAX if dense_max is None else dense_max
    H = hessian(problem)
    A = gather_csr(H, lay)
    H.destroy()
    # solved on rank 0, its failure raised on every rank (none left waiting for the vector)
    lam, v_nat, info = on_root(comm, _lowest_on_root, A, nneg, dense_max)
    vec = lay.create_vec()
    with vec as a:
        a[:] = v_nat.reshape(-1, 6)[lay.owned_nodes].ravel()
    info["seconds"] = comm.allreduce(time.perf_counter() - t0, op=_max())
    return lam, vec, info


def _lowest_on_root(A, nneg, dense_max):
    """lowest_eigenpair's solve of the gathered Hessian A on rank 0: (lam, v, info)."""
    A = 0.5 * (A + A.T)
    n = A.shape[0]
    dmax = float(np.abs(A.diagonal()).max())
    tau = 1e3 * np.finfo(float).eps * dmax
    kk = min(n - 1, max(6, (nneg or 1) + 4))
    if n <= dense_max:
        import scipy.linalg as sl
        w, V = sl.eigh(A.toarray(), subset_by_index=[0, min(n, kk) - 1])
        method = "dense"
    else:
        import scipy.sparse as sp
        from scipy.sparse.linalg import eigsh, splu
        w, V = eigsh(A.tocsc(), k=kk, sigma=-tau, which="LM")
        w = np.sort(w)
        # ARPACK's Ritz vectors are accurate relative to the shift-inverted operator, whose
        # largest eigenvalues are the near-zero modes (rigid motions, symmetries); two steps
        # of block inverse iteration just below the lowest Ritz value + Rayleigh-Ritz bring
        # |H v - lam v| down to roundoff (1e-13 instead of 1e-3 on the Michell ring)
        lu = splu((A - (w[0] - 1e-2 * abs(w[0]) - tau) * sp.identity(n, format="csc")).tocsc())
        for _ in range(2):
            V, _ = np.linalg.qr(lu.solve(V))
        w, Y = np.linalg.eigh(V.T @ (A @ V))
        V = V @ Y
        method = "eigsh"
    v, ncl = _canonical(V, w, 1e-6 * abs(w[0]) + tau)
    lam = float(v @ (A @ v))                     # Rayleigh quotient (= w[0] in a cluster)
    resid = float(np.linalg.norm(A @ v - lam * v))
    return lam, v, {"n": n, "method": method, "cluster": ncl, "residual": resid,
                    "eigenvalues": w.tolist()}


def _max():
    from mpi4py import MPI
    return MPI.MAX
