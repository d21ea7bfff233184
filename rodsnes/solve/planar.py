"""Planar scenes on three unknowns per node (-rod_planar auto|on|off; docs/planar.md).

A scene whose reference centreline, directors, intrinsic curvature, supports and loads all lie
in one plane normal to a coordinate axis e_a (with one director d_k = +-e_a at every node) has
the reflection through that plane as a symmetry: the energy E(S x) = E(x), S the reflection in
the chart x = (r, theta) of the spatial rotation increments (problem.py: R = exp(theta^x) R_ref;
under S the in-plane positions and theta_a are even, r_a and the two in-plane components of
theta odd).  At a planar state the gradient is then even, g_out = 0, and the Hessian and the
consistent tangent commute with S, so they are block diagonal,

    K = [[K_ii, 0], [0, K_oo]],     K d = -g  <=>  K_ii d_i = -g_i,  d_o = 0,

with i the in-plane unknowns (two position components and theta_a per node) and o the three
others.  Newton restricted to the in-plane block gives exactly the 3-D iterates with half the
unknowns and a block size of 3 instead of 6 (a factorisation of about an eighth of the flops).

PlanarSystem makes every linear solve of the run on the in-plane block: the minimiser's Newton
step (tangent_solve) and its inertia-controlled LDL^T (PlanarInertia), and the SNES's KSP on
the Newton path (a python PC on a python operator: attach).  The blocks are assembled directly
(ComponentView: the 6 x 6 nodal blocks the problem and its terms set, cut to the chosen
components, Dirichlet rows and columns masked), never as the full matrix.

Guard: at every solve the out-of-plane share of the right-hand side (the residual) must be at
round-off, |g_o| <= max(GUARD |g|, residual floor); if it is not, the state was not planar
(a 3-D restart state, a scene the detection misjudged): the run says so and goes on in 3-D.

A planar equilibrium need not be stable out of plane (lateral-torsional buckling): at the end of
every converged step the out-of-plane Hessian H_oo is factored by LDL^T (MUMPS, ICNTL(13) = 1),
whose negative pivots are the out-of-plane negative eigenvalues (out_of_plane_count); the
minimiser's load path then goes on in 3-D from that state (load_path.LoadPath.check_plane).
"""
import ctypes

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from rodsnes.model.partition import NDOF, DirichletRows, _upper_blocks, kept, preallocate_blocks
from rodsnes.model.scales import residual_floor
from rodsnes.model.term import same_patterns
from rodsnes.solve.linear import (LUChoice, direct_solver_defaults, failed_solve, is_default,
                                  option_default, set_up_ahead, solver_made)
from rodsnes import petsc_lib
from rodsnes.solve import petsc_exit
from rodsnes.solve.stability import Inertia, inertia_of

# the out-of-plane share of a residual that is still round-off (relative to |g|)
GUARD = 1e-8
PREFIX = "planar_"                 # the in-plane Newton step's KSP (the run's LU, solve/linear.py)
STABILITY_PREFIX = "planar_stability_"   # the in-plane and out-of-plane LDL^T
# a node out of the plane by less than this share of L has not left it (PlanarSystem.in_plane:
# a 3-D minimisation at a saddle its count cannot see moves the nodes by round-off)
IN_PLANE = 1e-9
# the unprefixed options of the Newton step's linear solver that the in-plane step takes over
# (not its monitors and views: the user's would print twice, once for each solver)
CARRIED = ("ksp_", "pc_", "sub_", "redundant_", "mat_mumps_")

_INSERT = int(PETSc.InsertMode.INSERT_VALUES)
_PETSC_INT = ctypes.c_int64 if np.dtype(PETSc.IntType).itemsize == 8 else ctypes.c_int32


# PETSc's strided vector functions (petsc4py 3.18 wraps none of them): their argument types
_VEC, _ARRAY_OR_NULL = ctypes.c_void_p, ctypes.c_void_p
_STRIDED = {
    # (Vec v, PetscInt nidx, const PetscInt idxv[], const PetscInt idxs[], Vec s, InsertMode)
    "VecStrideSubSetGather": (_VEC, _PETSC_INT, _ARRAY_OR_NULL, _ARRAY_OR_NULL, _VEC,
                              ctypes.c_int),
    # (Vec s, PetscInt nidx, const PetscInt idxs[], const PetscInt idxv[], Vec v, InsertMode)
    "VecStrideSubSetScatter": (_VEC, _PETSC_INT, _ARRAY_OR_NULL, _ARRAY_OR_NULL, _VEC,
                               ctypes.c_int),
    # (Vec v, NormType, PetscReal nrm[])
    "VecStrideNormAll": (_VEC, ctypes.c_int, _ARRAY_OR_NULL)}


def _strided(name, vecs, *args):
    """PETSc's strided vector function ``name`` on ``args`` (vectors by handle, index and norm
    arrays as numpy arrays or None), where every vector of ``vecs`` (Vec, block size) has
    that block size (a vector of another, as the SNES shell's of block size 1 that
    -snes_test_jacobian multiplies, would be read and written past its end: those strided
    loops trust the block size).  False where it does not apply or cannot be reached (the
    caller's numpy way instead)."""
    if any(v.getBlockSize() != bs for v, bs in vecs):
        return False
    fn = petsc_lib.function(name, *_STRIDED[name])
    if fn is None:
        return False
    code = fn(*(a.ctypes.data if isinstance(a, np.ndarray) else a for a in args))
    if code:
        raise PETSc.Error(code)
    return True


# -- the in-plane and out-of-plane blocks -----------------------------------------------------
def create_block_matrix(problem, patterns, symmetric):
    """A matrix of block size 3 over the problem's nodes with the block pattern of the elements
    and the terms' ``patterns`` (every block present, as partition.Layout.create_matrix):
    BAIJ, or SBAIJ (upper block triangle) when ``symmetric``.  Collective."""
    lay = problem.layout
    n, N = 3 * lay.n_owned, 3 * lay.n_global
    A = PETSc.Mat().create(comm=lay.comm)
    A.setSizes(((n, N), (n, N)), bsize=3)
    A.setType(PETSc.Mat.Type.SBAIJ if symmetric else PETSc.Mat.Type.BAIJ)
    A.setBlockSize(3)
    ai, aj = lay.block_pattern(problem.node_groups(patterns))
    if symmetric:
        ai, aj = _upper_blocks(ai, aj, lay.starts[lay.comm.getRank()])
    preallocate_blocks(A, ai, aj)
    if symmetric:
        A.setOption(PETSc.Mat.Option.IGNORE_LOWER_TRIANGULAR, True)
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, False)
    return A


class ComponentView:
    """The block-size-3 matrix ``mat`` seen as the 6-dof matrix of the problem: every block
    set through it (setValuesBlockedRCV, the one way the problem and its terms add tangents)
    is cut to the components ``comps`` of each node and goes in through partition.DirichletRows
    on the cut mask (Dirichlet rows and columns zeroed); finish() puts 1 on their diagonal.
    The result is the (comps, comps) block of the problem's matrix with MatZeroRowsColumns
    applied.  With ``plane`` (the in-plane block at a planar state) the problem's Jacobian
    makes the elastic tangents of that block directly (ElasticRod.plane_tangents)."""

    def __init__(self, mat, comps, constraints, plane=None, cut=None):
        self.mat, self.comps = mat, np.asarray(comps)
        self.plane = plane                # the Plane whose in-plane block this is, at a planar
        if plane is not None and list(self.comps) != list(plane.inplane):   # state, or None
            raise ValueError("a plane's view has its in-plane components")
        mask, touched, self.rows = component_cut(self.comps, constraints) if cut is None else cut
        self.dirichlet = DirichletRows(mat, mask, touched)
        self._cuts = {}

    def setValuesBlockedRCV(self, R, C, V, addv=None):
        kr, kc = R.reshape(len(R), -1).shape[1], C.reshape(len(C), -1).shape[1]
        # the (comps, comps) entries of every block by one gather of the flattened blocks
        V = np.asarray(V).reshape(len(R), NDOF * kr * NDOF * kc)
        V = V[:, self._cut(kr, kc)].reshape(len(R), 3 * kr, 3 * kc)
        self.dirichlet.setValuesBlockedRCV(R, C, V, addv=addv)

    def add_cut(self, R, C, V, addv=None):
        """setValuesBlockedRCV of blocks already cut to the components (V (n, 3 kr, 3 kc), rows
        and columns (node, component): the elastic kernel's with ``comps``)."""
        self.dirichlet.setValuesBlockedRCV(R, C, V, addv=addv)

    def _cut(self, kr, kc):
        """Flat indices of the (comps, comps) entries in a (NDOF kr, NDOF kc) block, row by row
        (kept per block shape)."""
        key = (kr, kc)
        if key not in self._cuts:
            r = (NDOF * np.arange(kr)[:, None] + self.comps[None, :]).ravel()
            c = (NDOF * np.arange(kc)[:, None] + self.comps[None, :]).ravel()
            self._cuts[key] = (NDOF * kc * r[:, None] + c[None, :]).ravel()
        return self._cuts[key]

    def finish(self, rows_global=None):
        """Before assembly: 1 on the diagonal of this rank's constrained rows of the block."""
        self.dirichlet.finish(self.rows)

    def __getattr__(self, name):
        return getattr(self.mat, name)


def component_cut(comps, constraints):
    """(mask, touched, rows) of the (comps, comps) block under ``constraints``: the Dirichlet
    mask cut to the components, its blocks holding a constrained dof, and this rank's
    constrained rows of the block (global indices)."""
    comps = np.asarray(comps)
    mask = constraints.block_mask[:, comps]
    mask.setflags(write=False)          # kept by identity, as the constraints' own
    where = np.full(NDOF, -1)
    where[comps] = np.arange(3)
    rows = np.asarray(constraints.rows_global, dtype=np.int64)
    keep = where[rows % NDOF] >= 0
    return mask, DirichletRows.touched_of(mask), 3 * (rows[keep] // NDOF) + where[rows[keep] % NDOF]


def component_view(owner, mat, comps, constraints, plane=None):
    """The ComponentView of ``mat``, its cut (component_cut: O(global nodes)) kept on ``owner``
    while the components and the constraints stay (partition.kept)."""
    cut = kept(owner, "_component_cut",
               (comps, constraints.block_mask, constraints.rows_global),
               lambda: component_cut(comps, constraints))
    return ComponentView(mat, comps, constraints, plane, cut)


class BlockInertia(Inertia):
    """stability.Inertia on the (comps, comps) block of the energy Hessian: the block assembled
    into an SBAIJ matrix of block size 3 (kept with its MUMPS analysis while the terms'
    patterns stay), LDL^T with ICNTL(13) = 1, the negative pivots counted; factor and solve
    take vectors of the block."""

    def __init__(self, problem, comps, prefix=STABILITY_PREFIX, plane=None):
        super().__init__(problem, prefix)
        self.comps = np.asarray(comps)
        self.plane = plane                # the Plane of an in-plane block (ComponentView)

    def _matrix(self, patterns, symmetric=True):
        return create_block_matrix(self.problem, patterns, symmetric=symmetric)

    def _view(self):
        return component_view(self, self.H, self.comps, self.problem.constraints, self.plane)


class PlanarInertia:
    """The minimiser's factorisation (minimize.EnergyMinimizer.factor): the in-plane block's
    (BlockInertia) while the run is planar, the full Hessian's (problem.inertia) once it has
    left the plane.  Takes and gives vectors of the full 6-dof layout."""

    def __init__(self, planar):
        self.planar = planar
        self.block = BlockInertia(planar.problem, planar.plane.inplane, plane=planar.plane)
        self.planar_factor = True          # the last assemble() was of the in-plane block
        self._b = self._x = None

    @property
    def full(self):
        return inertia_of(self.planar.problem)

    @property
    def diagonal(self):
        return self.block.diagonal if self.planar_factor else self.full.diagonal

    def assemble(self, patterns=None):
        self.planar_factor = self.planar.active
        if self.planar_factor:
            return self.block.assemble(patterns)
        return self.full.assemble(patterns)

    def factor(self, shift=None):
        if not self.planar_factor:
            return self.full.factor(shift)
        s = None if shift is None else self.planar.restrict(shift)
        try:
            return self.block.factor(s)
        finally:
            if s is not None:
                s.destroy()

    def solve(self, b, x):
        if not self.planar_factor:
            return self.full.solve(b, x)
        bi = self.planar.restrict(b)
        xi = bi.duplicate()
        self.block.solve(bi, xi)
        self.planar.expand(xi, x)
        bi.destroy()
        xi.destroy()

    def count(self):
        self.assemble()
        return self.factor()


class PlanarSystem:
    """The run's linear algebra on the in-plane block (module docstring).  ``active`` while the
    run is planar; leave() ends it (the guard, or an out-of-plane instability) for the rest of
    the run."""

    def __init__(self, problem, plane, say=None, prefix=PREFIX):
        self.problem, self.plane = problem, plane
        self._inplane_ids = np.ascontiguousarray(plane.inplane, dtype=PETSc.IntType)
        self.prefix = prefix              # of the in-plane step's KSP (the error estimate's own)
        self.comm = problem.layout.comm.tompi4py()
        self.active = True
        self.left = None                  # (load, why) where the run left the plane
        self.floor = residual_floor(problem.scene.rod)
        self.say = say or (lambda text: None)
        self.J = None                     # the in-plane consistent tangent (BAIJ, bs 3)
        self._patterns = None
        self.ksp = None                   # its LU (prefix planar_)
        self.full_ksp = None              # the 3-D solve of the Newton path after leave()
        self.failure = None               # why the last failed solve failed (linear.failed_solve)
        self.inertia = PlanarInertia(self)
        self.out_inertia = BlockInertia(problem, plane.outplane)
        self.stats = {"planar_solves": 0, "out_of_plane_counts": 0}
        self.solver = None
        self._work = {}                   # kept block-3 vectors of the solves (work)

    # -- vectors ------------------------------------------------------------------------
    def _block_vec(self):
        """A new block-3 Vec of the in-plane unknowns.  Collective."""
        lay = self.problem.layout
        return PETSc.Vec().createMPI((3 * lay.n_owned, 3 * lay.n_global), bsize=3,
                                     comm=lay.comm)

    def restrict(self, v, out=None):
        """The in-plane components of the 6-dof vector v as a new (or ``out``) block-3 Vec
        (PETSc's VecStrideSubSetGather: one pass, where numpy's gather and copy took 0.2 ms
        at 10^4 elements)."""
        out = self._block_vec() if out is None else out
        if not _strided("VecStrideSubSetGather", ((v, NDOF), (out, 3)), v.handle, 3,
                        self._inplane_ids, None, out.handle, _INSERT):
            a = v.getArray(readonly=True).reshape(-1, NDOF)[:, self.plane.inplane]
            with out as o:
                o[:] = a.ravel()
        return out

    def work(self, name):
        """A block-3 Vec of the in-plane unknowns kept for the solves (``name``: which one)."""
        if name not in self._work:
            self._work[name] = self._block_vec()
        return self._work[name]

    def expand(self, vi, v):
        """v <- vi on the in-plane components, 0 on the others."""
        v.zeroEntries()
        if not _strided("VecStrideSubSetScatter", ((vi, 3), (v, NDOF)), vi.handle, 3, None,
                        self._inplane_ids, v.handle, _INSERT):
            with v as a:
                a.reshape(-1, NDOF)[:, self.plane.inplane] = \
                    vi.getArray(readonly=True).reshape(-1, 3)

    def out_of_plane_share(self, v):
        """(|v_o|, |v|) over all ranks, from the norms of v's six components (PETSc's
        VecStrideNormAll: one pass and one reduction, where numpy's took 0.23 ms at 10^4
        elements)."""
        norms = np.zeros(NDOF)
        if _strided("VecStrideNormAll", ((v, NDOF),), v.handle, int(PETSc.NormType.NORM_2),
                    norms):
            sq = norms ** 2
            return float(np.sqrt(sq[self.plane.outplane].sum())), float(np.sqrt(sq.sum()))
        a = v.getArray(readonly=True)
        o = a.reshape(-1, NDOF)[:, self.plane.outplane].ravel()
        loc = np.array([float(o @ o), float(a @ a)])
        tot = np.empty(2)
        self.comm.Allreduce(loc, tot, op=MPI.SUM)
        return tuple(np.sqrt(tot))

    def holds(self, g):
        """The guard: True while the run is planar and the residual g has no out-of-plane share
        beyond round-off; else the run leaves the plane (said) and False.  Collective."""
        if not self.active:
            return False
        norms = np.array(self.out_of_plane_share(g))
        self.comm.Bcast(norms, root=0)      # rank 0's decision (MPI promises no equal sums)
        go, gn = norms
        if go <= max(GUARD * gn, self.floor):
            return True
        self.leave("the residual has an out-of-plane part (|g_out| = %.3e of |g| = %.3e): the "
                   "state is not planar" % (go, gn), "the state left the plane")
        return False

    def leave(self, why, short="not planar"):
        """Go on in 3-D for the rest of the run (``short``: the reason in summary.json's
        model)."""
        if not self.active:
            return
        self.active = False
        self.left = (self.problem.lam, short)
        self.say("  load %.6f: %s; going on in 3-D" % (self.problem.lam, why))

    def model(self):
        """summary.json's ``model``."""
        text = self.plane.model()
        if self.left is not None:
            text += ", 3-D from load %.6f (%s)" % self.left
        return text

    # -- the in-plane Newton step --------------------------------------------------------
    def setup(self, counts=False):
        """Before the first Newton iteration (a solver's set-up, profiling.SET_UP): the
        in-plane block's matrix of the terms' present patterns, its LU's KSP, and the LU's
        choice and plan for that pattern (linear.set_up_ahead), which the first
        assemble_tangent and solve_block then find made; with ``counts`` (the path counts
        negative eigenvalues at every step, or every iteration) the in-plane and out-of-plane
        Hessian blocks' too (stability.Inertia.setup).  Collective."""
        if self.active:
            J = self._matrix()
            set_up_ahead(self._inner_ksp(), self.lu, self.problem, J)
            if counts:
                self.inertia.block.setup()
                self.out_inertia.setup()

    def _matrix(self):
        """J, made anew for the terms' present patterns where it has others (a new contact
        pair), the LU's KSP reset then."""
        p = self.problem
        if self.J is None or not same_patterns(p.patterns, self._patterns):
            if self.J is not None:
                self.J.destroy()
            self.J = create_block_matrix(p, p.patterns, symmetric=False)
            self._patterns = p.patterns
            if self.ksp is not None:
                self.ksp.reset()
        return self.J

    def assemble_tangent(self, X=None):
        """The in-plane block of the consistent tangent at X (default: the state) into J."""
        p = self.problem
        p.jacobian(None, p.state.X if X is None else X, self._matrix(), self.J,
                   view=component_view(self, self.J, self.plane.inplane, p.constraints,
                                       self.plane))

    def _inner_ksp(self):
        if self.ksp is None:
            opts = PETSc.Options()
            pre = self.prefix
            # the run's in-plane step takes the 3-D step's choice (the user's or its default),
            # every option of its KSP, PC and factorisation (options/iterative.opts' tolerance,
            # overlap and subdomain solver too: with its type alone the cantilever of 200
            # elements took 122 iterations for 22); a solver of its own (-estimate_*) its own
            # (read from the whole database, which marks none used: a misspelt -ksp_typo stays
            # unread, and is not counted among the options given where the step fails)
            given = opts.getAll()
            keys = [k for k in given if k.startswith(CARRIED) and not
                    any(w in k for w in ("monitor", "view", "converged_reason"))] \
                if pre == PREFIX else ()
            for key in keys:
                value = "" if given[key] is None else given[key]
                if is_default(key):
                    option_default(pre + key, value)
                elif pre + key not in given:
                    opts.setValue(pre + key, value)
            self.lu = LUChoice(direct_solver_defaults(self.problem, pre))
            solver_made(pre)
            ksp = PETSc.KSP().create(comm=self.problem.layout.comm)
            ksp.setOptionsPrefix(pre)
            ksp.setFromOptions()
            self.ksp = ksp
        return self.ksp

    def solve_block(self, b, x):
        """x = J_ii^-1 b_i on the in-plane components, 0 on the others (J assembled); False
        when the factorisation failed.  Collective."""
        ksp = self._inner_ksp()
        ksp.setOperators(self.J)
        self.lu.check(ksp, self.problem)
        bi = self.restrict(b, out=self.work("b"))
        xi = self.work("x")
        self.stats["planar_solves"] += 1
        try:
            ksp.solve(bi, xi)
            ok = ksp.getConvergedReason() >= 0
            if not ok:
                self.failure = failed_solve(ksp)
        except PETSc.Error as err:
            self.failure = failed_solve(ksp, err)
            ksp.reset()
            ok = False
        if ok:
            self.expand(xi, x)
        return ok

    def tangent_solve(self, b, x):
        """The minimiser's Newton step in the plane: J_ii at the state, x = J^-1 b."""
        self.assemble_tangent()
        return self.solve_block(b, x)

    # -- the Newton path's SNES ----------------------------------------------------------
    def attach(self, solver, jacobian=None):
        """Make the SNES of the Newton path (newton.NewtonSolver; the error estimate's interior
        stage, estimate.EnrichedProblem) solve on the in-plane block: its Jacobian callback
        assembles J_ii (or, after leave(), the full J: snes_jacobian, or ``jacobian`` which
        calls it), its operator is a python matrix of the full size that multiplies by it
        (_Operator), and its KSP's PC a python PC that solves J_ii y_i = x_i, y_o = 0 (or the
        full system)."""
        self.solver = solver
        p = self.problem
        lay = p.layout
        n, N = NDOF * lay.n_owned, NDOF * lay.n_global
        self.shell = PETSc.Mat().createPython(((n, N), (n, N)), context=_Operator(self),
                                              comm=lay.comm)
        self.shell.setBlockSize(NDOF)       # its vectors: a node's 6 unknowns a block
        self.shell.setUp()
        solver.snes.setJacobian(jacobian or self.snes_jacobian, self.shell)
        self.attach_pc(solver.snes.getKSP())
        p.on_pattern_change = self._pattern_changed

    def attach_pc(self, ksp):
        """The SNES's KSP: preonly with the planar python PC."""
        ksp.setType(PETSc.KSP.Type.PREONLY)
        pc = ksp.getPC()
        pc.setType(PETSc.PC.Type.PYTHON)
        pc.setPythonContext(_PlanarPC(self))

    def _pattern_changed(self, J):
        if self.full_ksp is not None:
            self.full_ksp.reset()

    def snes_jacobian(self, snes, X, J, P):
        """The attached SNES's Jacobian: J_ii into J (the full J after leave())."""
        if self.active:
            self.assemble_tangent(X)
        else:
            self.problem.jacobian(snes, X, self.problem.J, self.problem.J)
        J.assemble()

    def full_solve(self, b, x):
        """The 3-D solve with the full J (assembled by the Jacobian callback), by the 3-D
        step's solver, under the attached SNES's options prefix: the Newton path's (none), or
        the estimate's own (-estimate_*), the LU chosen for the pattern as the 3-D step's (linear.LUChoice: on
        several ranks each rank's stretch, MUMPS where contact fills it)."""
        if self.full_ksp is None:
            pre = self.solver.snes.getOptionsPrefix() or ""     # the attached SNES's
            self.full_lu = LUChoice(direct_solver_defaults(self.problem, pre))
            self.full_ksp = PETSc.KSP().create(comm=self.problem.layout.comm)
            self.full_ksp.setOptionsPrefix(pre)
            self.full_ksp.setFromOptions()
        self.full_ksp.setOperators(self.problem.J)
        self.full_lu.check(self.full_ksp, self.problem)
        try:
            self.full_ksp.solve(b, x)
            if self.full_ksp.getConvergedReason() >= 0:
                return True
            self.failure = failed_solve(self.full_ksp)
        except PETSc.Error as err:
            self.failure = failed_solve(self.full_ksp, err)
            self.full_ksp.reset()
        return False

    # -- stability -----------------------------------------------------------------------
    def in_plane(self):
        """Whether every node still lies in the scene's plane (within IN_PLANE of L of the
        first node's place at rest: a planar scene's nodes share it), after the run may have
        left it for 3-D.  Collective."""
        p = self.problem
        axis = self.plane.axis
        r, _ = p.state.local_config()
        z0 = float(p.mesh.x_init[0, axis])
        off = float(np.abs(r[:p.layout.n_owned, axis] - z0).max(initial=0.0))
        return self.comm.allreduce(off, op=MPI.MAX) <= IN_PLANE * p.mesh.length

    def out_of_plane_count(self):
        """Negative eigenvalues of the out-of-plane block H_oo of the energy Hessian at the
        current (planar) state: one LDL^T.  Collective."""
        self.stats["out_of_plane_counts"] += 1
        n = self.out_inertia.count()
        return int(self.comm.allreduce(n, op=MPI.MAX))

    def negative_eigenvalues(self):
        """(in-plane, out-of-plane) negative eigenvalues of the Hessian at a planar state."""
        n_in = int(self.comm.allreduce(self.inertia.block.count(), op=MPI.MAX))
        return n_in, self.out_of_plane_count()


class _Operator:
    """The SNES's operator of the planar Newton path, of the full size: y = J_ii x_i on the
    in-plane components and 0 on the others (the Jacobian lives in PlanarSystem.J), or the
    problem's full J once the run left the plane.  KSP preonly never multiplies by it; a line
    search that takes the slope J d (-snes_linesearch_type bt) does."""

    def __init__(self, planar):
        self.planar = planar

    def mult(self, A, x, y):
        pl = self.planar
        if not pl.active:
            pl.problem.J.mult(x, y)
            return
        xi = pl.restrict(x, out=pl.work("b"))
        yi = pl.work("x")
        pl.J.mult(xi, yi)
        pl.expand(yi, y)


class _PlanarPC:
    """The SNES's PC of the planar Newton path: y = J_ii^-1 x_i on the in-plane components
    (after the guard on x, the residual), or the full solve once the run left the plane.  A
    failed factorisation fails the PC (petsc_lib.set_pc_failed: the SNES's linear solve fails,
    SNES_DIVERGED_LINEAR_SOLVE, and the load is cut back) and returns NaN."""

    def __init__(self, planar):
        self.planar = planar

    def create(self, pc):
        petsc_exit.live(pc)         # released before the interpreter exits (petsc_exit.py)

    def destroy(self, pc):
        petsc_exit.gone(pc)

    def setUp(self, pc):
        pass

    def apply(self, pc, x, y):
        pl = self.planar
        if pl.active and not pl.holds(x):
            p = pl.problem
            p.jacobian(None, p.state.X, p.J, p.J)     # this iterate's, in 3-D
        ok = pl.solve_block(x, y) if pl.active else pl.full_solve(x, y)
        petsc_lib.set_pc_failed(pc, not ok)
        if not ok:
            y.set(np.nan)
