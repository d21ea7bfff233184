"""The direct linear solves rodsnes defaults to, as defaults in the PETSc options database (a
user's -ksp_type, -pc_type, -pc_factor_mat_solver_type, -mat_mumps_icntl_* win).

The Newton steps (the minimiser's and the Newton path's SNES) factor the Jacobian by PETSc's
own sparse LU (6 x 6 blocks, approximate-minimum-degree ordering); on more than one rank each
rank factors its own stretch of the rod and the ranks share the small Schur complement of the
nodes where the stretches meet (schur.RankSchur, exact: one level of static condensation;
use_rank_schur turns the PCREDUNDANT default, where every rank would factor the whole matrix,
into it).  A rod's Jacobian is a chain of small blocks plus
the contact couplings, and on it PETSc's LU was 3-5 x faster than MUMPS at every size measured
(plectoneme, 60 elements, blocks of 6: 1.8 ms against 4.2 ms per factorisation, 0.6-0.7 ms
split into blocks of 3 as a contact Jacobian is, partition.Layout.create_matrix; cantilever,
1e4 elements: 50-75 ms against 256 ms; 2 ranks, 1e4 elements: 0.16 s against 0.94 s;
tools/bench_scaling.py, docs/bench_scaling.md).  MUMPS stays one option away
(-pc_factor_mat_solver_type mumps, and on several ranks -pc_type lu), and it factors the
symmetric LDL^T whose inertia the stability count and the minimiser's shifts read
(solve/stability.py), where its pivoting is needed.

The ordering is AMD, not PETSc's default nested dissection: on a chain the two are alike
(3-D cantilever, 1e4 elements: 37 against 46 ms per factorisation), but where contact couples
strands the minimum-degree ordering fills far less (plectoneme at 8.5 turns, 60 elements:
fill 1.13 against 1.56, 1.7 against 3.6 ms; over the run from 8.5 to 8.8 turns the
factorisations took 10.5 s against 21.5 s).  An open rod without contact is factored in its own
node order instead (chain_ordering: no more fill, the blocks in memory order, 13-21 % less
time a factorisation), and on one rank by rodsnes' own LU of that chain (use_chain_lu,
chain.ChainPC: the same block arithmetic without PETSc's general sparse machinery, 2.8 against
5.2 ms a factorisation of the planar cantilever's in-plane Jacobian at 10^4 elements).

PETSc's LU is not supernodal: its time grows with the fill far faster than MUMPS's, whose
dense fronts run on BLAS 3.  Where contact couples much of the rod (a coil whose turns touch
along its length) the fill is high and MUMPS is the faster one; measured (per Newton iteration
or factorisation, serial, this 2-core machine, AMD ordering):

    Jacobian                               fill of PETSc's LU   PETSc LU   MUMPS LU
    plectoneme at 8.5 turns, 60 elements   1.13                 1.7 ms     5.1 ms
    bench coil, 200 elements               2.95                 49 ms      28 ms
    bench coil, 1000 elements              3.35                 296 ms     210 ms

so where the fill (nz(L+U) / nz(A), PETSc's MatInfo fill_ratio_needed) of the Jacobian's
pattern exceeds FILL_MUMPS, checked for every new pattern before its first factorisation, the
rest of the run factors by MUMPS (use_mumps_when_filled), unless the user chose the package:
on several ranks each rank its own stretch, with the Schur complement where the stretches
meet (schur.RankSchur, package "mumps"), on a short rod MUMPS over the ranks.  MUMPS is then
ordered by AMD (ICNTL(7) = 0) where that fills the rod's node graph less than nested
dissection: Debian's MUMPS, built without METIS and SCOTCH, would choose PORD, which on the
bench coil at 10^4 elements took 7.3e9 flops and 0.89 s a factorisation against AMD's 4.4e9 and
0.66 s."""
import numpy as np
from petsc4py import PETSc

from rodsnes.model.partition import group_pairs
from rodsnes.solve import chain, schur

FILL_MUMPS = 2.5        # above this fill of PETSc's LU, MUMPS factors faster (module docstring)
ORDERING = "amd"        # PETSc's LU: approximate minimum degree (module docstring)


DEFAULTED = {}          # name -> value of the options rodsnes set (option_default)
MADE = set()            # options prefixes of rodsnes' own solvers this run made (solver_made)


def option_default(name, value):
    """Set -name value in the options database unless the user gave it; returns whether it
    set it."""
    opts = PETSc.Options()
    if opts.hasName(name):
        return False
    opts.setValue(name, value)
    DEFAULTED[name] = str(value)
    return True


def forget_defaults():
    """A new run: the options database is the user's again (a test or an in-process caller
    removes the last run's options), so no option counts as set by option_default, and no
    solver of rodsnes' own is made yet."""
    DEFAULTED.clear()
    MADE.clear()
    schur.MADE.clear()


def solver_made(prefix):
    """A solver of rodsnes' own under the options ``prefix`` (-planar_, -estimate_,
    -interior_) was made: an unused option of it is then not for a solver the run lacks
    (cli.unused_petsc_warnings)."""
    MADE.add(prefix)


def solvers_made():
    """The options prefixes of rodsnes' own solvers this run made (solver_made; the ranks'
    interiors by MUMPS: schur.MADE)."""
    return MADE | schur.MADE


def take_back_defaults():
    """The end of a run: the options option_default set and that still hold its value leave
    the database, which is the user's again.  Without it a second run in the same process
    (the meshes of -rod_tolerance, a script's next scene) took them for the user's: no
    hand-over of a filled pattern to MUMPS, no rank Schur complement, no default it would
    set otherwise."""
    opts = PETSc.Options()
    for name, value in DEFAULTED.items():
        if opts.hasName(name) and opts.getString(name) == value:
            opts.delValue(name)
    DEFAULTED.clear()


_UNSET = object()


def _value(name):
    """-name's value ("" for a flag), _UNSET where it is not set; read from the whole database
    (PetscOptionsGetAll), which marks no option used: a question about an option is no use of
    it (the misspelt -planar_ksp_typ, asked about, went unreported as unused)."""
    value = PETSc.Options().getAll().get(name, _UNSET)
    return "" if value is None else value


def peek(name, default=None):
    """-name's value (\"\" for a flag), ``default`` where it is not set; marks it not used."""
    value = _value(name)
    return default if value is _UNSET else value


def is_default(name):
    """Whether -name holds the value option_default set (not one the user gave)."""
    value = _value(name)
    return value is not _UNSET and name in DEFAULTED and DEFAULTED[name] == value


def user_chose(name):
    """Whether the user gave -name (it is set, and not by option_default)."""
    return _value(name) is not _UNSET and not is_default(name)


def mumps_fill_room(problem, prefix=""):
    """With a term whose pattern follows the state (contact), room for the fill MUMPS's
    analysis did not see (contact pairs come and go between factorisations; without it
    INFOG(1) = -9): -<prefix>mat_mumps_icntl_14 100."""
    if problem.moving_pattern:
        option_default(prefix + "mat_mumps_icntl_14", "100")


def mumps_ordering(problem, prefix=""):
    """MUMPS's ordering for the KSP or PC of options prefix ``prefix``: minimum degree
    (-<prefix>mat_mumps_icntl_7 0) where it fills the problem's node graph no more than
    nested dissection (pattern_fill), unless the user chose one.  Debian's MUMPS, built
    without METIS and SCOTCH, would choose PORD: on the bench coil at 10^4 elements 7.3e9
    flops and 0.89 s a factorisation against AMD's 4.4e9 and 0.66 s; the planar cantilever's
    in-plane Hessian of 10^4 elements (the stability count's LDL^T) 136 / 58 ms (analysis and
    first factorisation / a factorisation) against 69 / 42 ms."""
    if pattern_fill(problem, "amd") <= pattern_fill(problem, "nd"):
        option_default(prefix + "mat_mumps_icntl_7", "0")


def lu_defaults(comm, prefix="", added=None):
    """preonly + LU for the KSP of options prefix ``prefix`` (module docstring): PETSc's LU on
    one rank, PETSc's LU of the whole matrix on every rank (redundant) on several, unless the
    user chose a preconditioner or a factorisation package (then LU by it, MUMPS if none);
    wherever that makes PETSc's own LU, its ordering (ordering_default).
    Returns whether the package is rodsnes' choice (use_mumps_when_filled may change it).
    ``added``: a list that receives the names this call set (to take them back)."""
    chosen = user_chose(prefix + "pc_type") or user_chose(prefix + "pc_factor_mat_solver_type")
    if comm.getSize() == 1:
        defaults = (("pc_type", "lu"), ("pc_factor_mat_solver_type", "petsc"))
    elif chosen:
        defaults = (("pc_type", "lu"), ("pc_factor_mat_solver_type", "mumps"))
    else:
        defaults = (("pc_type", "redundant"), ("redundant_pc_type", "lu"),
                    ("redundant_pc_factor_mat_solver_type", "petsc"))
    for name, value in (("ksp_type", "preonly"),) + defaults:
        if option_default(prefix + name, value) and added is not None:
            added.append(prefix + name)
    ordering_default(prefix, added)
    return not chosen


def native_lu_ordering_key(prefix=""):
    """The option that orders PETSc's own LU in the KSP of prefix ``prefix`` as the options
    database makes it (<prefix>pc_factor_mat_ordering_type for PCLU with the petsc package,
    <prefix>redundant_pc_factor_mat_ordering_type for PCREDUNDANT over it), None where that KSP
    does not factor by PETSc's LU (MUMPS, ICC, ILU, an iterative solver ...)."""
    opts = PETSc.Options()
    kind = opts.getString(prefix + "pc_type", "")
    if kind == "redundant":
        inner = prefix + "redundant_"
        if (opts.getString(inner + "pc_type", "lu") == "lu"
                and opts.getString(inner + "pc_factor_mat_solver_type", "petsc") == "petsc"):
            return inner + "pc_factor_mat_ordering_type"
        return None
    if kind == "lu" and opts.getString(prefix + "pc_factor_mat_solver_type", "petsc") == "petsc":
        return prefix + "pc_factor_mat_ordering_type"
    return None


def ordering_default(prefix="", added=None):
    """PETSc's own LU in the KSP of prefix ``prefix`` ordered by ORDERING unless the user gave
    an ordering: -<prefix>pc_factor_mat_ordering_type, which on several ranks (PCREDUNDANT) is
    carried over to the redundant LU.  Nothing for any other preconditioner (PETSc's ICC and
    Cholesky of a BAIJ matrix take no ordering but the natural one)."""
    key = native_lu_ordering_key(prefix)
    if key is None:
        return
    opts = PETSc.Options()
    value = opts.getString(prefix + "pc_factor_mat_ordering_type", ORDERING)
    if option_default(key, value) and added is not None:
        added.append(key)


def lu_ordering(prefix=""):
    """The ordering PETSc's own LU uses in the KSP of prefix ``prefix`` (PETSc's default nd
    where no option says), None where that KSP does not factor by it."""
    key = native_lu_ordering_key(prefix)
    return None if key is None else PETSc.Options().getString(key, "nd")


def direct_solver_defaults(problem, prefix=""):
    """lu_defaults on the problem's communicator, with mumps_fill_room for MUMPS and
    chain_ordering; returns whether the package is rodsnes' choice."""
    auto = lu_defaults(problem.layout.comm, prefix)
    mumps_fill_room(problem, prefix)
    chain_ordering(problem, prefix)
    return auto


def chain_ordering(problem, prefix=""):
    """PETSc's own LU of a Jacobian whose pattern stays (no contact) in the rod's natural node
    order where that fills no more than ORDERING's: an open rod's chain is banded in its own
    order (no fill beyond the band, fill 1 with either), and the LU then runs through the
    blocks in memory order: per factorisation, serially, the planar cantilever of 10^4
    elements 6.1 against 7.7 ms (AMD), 3-D with 5000 elements 17.3 against 19.9 ms.  A ring's
    closing element fills the natural order (AMD stays); a contact pattern changes from step
    to step (AMD stays).  Only where the ordering is rodsnes' default (ordering_default), not
    the user's.  The order is the matrix's (PETSc's numbering: on several ranks the stretches
    in rank order, which a partition may not keep along the rod: then the rod's ends meet
    inside the matrix and the natural order fills, pattern_fill sees it).  Returns whether it
    chose the natural order."""
    key = native_lu_ordering_key(prefix)
    if key is None or not is_default(key) or problem.moving_pattern:
        return False
    if pattern_fill(problem, "natural") > pattern_fill(problem, ORDERING):
        return False
    PETSc.Options().setValue(key, "natural")
    DEFAULTED[key] = "natural"
    return True


def pattern_fill(problem, ordering=ORDERING):
    """The fill nz(L+U) / nz(A) of PETSc's LU (ordered by ``ordering``) of the Jacobian's node graph
    (the elements and the terms' node groups), the same on every rank (global data, no
    communication): for a matrix of dense 6 x 6 blocks the block fill is the scalar fill.
    Kept per ordering while the problem's patterns stay (every KSP of the run asks)."""
    kept = getattr(problem, "_fills", None)
    if kept is None or kept[0] is not problem.patterns:
        kept = problem._fills = (problem.patterns, {})
    if ordering not in kept[1]:
        kept[1][ordering] = _node_graph_fill(problem, ordering)
    return kept[1][ordering]


def _node_graph_fill(problem, ordering):
    """pattern_fill of the node graph numbered as PETSc numbers the matrix's blocks (the ranks'
    stretches in rank order: layout.nat2petsc), so that "natural" is PETSc's natural order."""
    n = problem.mesh.n_nodes
    rows, cols = group_pairs(problem.coupled_groups())
    rows, cols = problem.layout.nat2petsc[rows], problem.layout.nat2petsc[cols]
    key = np.unique(rows * n + cols)
    rows, cols = key // n, key % n
    ai = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=n))])
    degree = np.diff(ai).astype(float)
    vals = np.where(rows == cols, degree[rows], -1.0)      # an M-matrix: no zero pivot
    A = PETSc.Mat().createAIJ((n, n), csr=(ai.astype(PETSc.IntType), cols.astype(PETSc.IntType),
                                           vals), comm=PETSc.COMM_SELF)
    ksp = PETSc.KSP().create(PETSc.COMM_SELF)
    try:
        ksp.setType("preonly")
        ksp.getPC().setType("lu")
        ksp.getPC().setFactorSolverType("petsc")
        ksp.getPC().setFactorOrdering(ordering)
        ksp.setOperators(A)
        ksp.setUp()
        return float(ksp.getPC().getFactorMatrix().getInfo().get("fill_ratio_needed", 0.0))
    finally:
        ksp.destroy()
        A.destroy()


def use_mumps_when_filled(ksp, problem):
    """Before the first factorisation of a new pattern's matrix: where the KSP factors by
    PETSc's LU (PCLU with the petsc package, or PCREDUNDANT, PETSc's LU of the whole matrix on
    every rank) and the fill of the problem's Jacobian exceeds FILL_MUMPS (pattern_fill), its
    PC factors by MUMPS from now on (module docstring).  Returns True when it switched."""
    pc = ksp.getPC()
    kind = pc.getType()
    native = kind == PETSc.PC.Type.REDUNDANT or _is_rank_schur(pc) or (
        kind == PETSc.PC.Type.LU and pc.getFactorSolverType() == "petsc")
    if not native:
        return False
    prefix = ksp.getOptionsPrefix() or ""
    ordering = lu_ordering(prefix) or ORDERING
    fill = pattern_fill(problem, ordering)
    if not fill > FILL_MUMPS:
        return False
    # MUMPS's defaults for the Newton step's and, on several ranks, for RankSchur's stretches
    # and whole matrix: room for the fill, and the ordering (minimum degree where it fills
    # less than nested dissection: on a coil 3.4 against 4.7)
    for pre in (prefix, schur.INTERIOR_PREFIX, schur.WHOLE_MUMPS_PREFIX):
        mumps_fill_room(problem, pre)
        mumps_ordering(problem, pre)
    size = problem.layout.comm.getSize()
    if size > 1 and schur.pays(problem.mesh.n_nodes, size, "mumps"):
        # every rank factors its own stretch by MUMPS, the ranks share the Schur complement
        _retype(pc, PETSc.PC.Type.PYTHON,
                lambda pc: pc.setPythonContext(schur.RankSchur(problem, package="mumps")))
    else:
        _retype(pc, PETSc.PC.Type.LU, lambda pc: pc.setFactorSolverType("mumps"))
    return True


def _retype(pc, kind, configure):
    """pc becomes a fresh PC of type ``kind`` (``configure(pc)`` sets it up) on the same
    operators."""
    ops = pc.getOperators()
    pc.reset()
    pc.setType(kind)
    configure(pc)
    pc.setOperators(*ops)


def _is_rank_schur(pc):
    return (pc.getType() == PETSc.PC.Type.PYTHON
            and isinstance(pc.getPythonContext(), schur.RankSchur))


def use_rank_schur(ksp, problem):
    """On several ranks, where the KSP factors the whole matrix by PETSc's LU on every rank
    (PCREDUNDANT over PETSc's LU, rodsnes' default), its PC becomes schur.RankSchur: each rank
    factors its own stretch of the rod and the ranks share the small interface; not for a rod
    shorter than schur.MIN_NODES_PER_RANK nodes a rank, where it would not pay (the plectoneme
    on 2 ranks: 12.8 ms an iteration by PCREDUNDANT, 13.6 ms through the python PC's whole-matrix
    fallback).  Returns True when it switched."""
    pc = ksp.getPC()
    size = problem.layout.comm.getSize()
    if size == 1 or pc.getType() != PETSc.PC.Type.REDUNDANT:
        return False
    if not schur.pays(problem.mesh.n_nodes, size):
        return False            # too short for the condensation to pay: PCREDUNDANT as it is
    prefix = ksp.getOptionsPrefix() or ""
    opts = PETSc.Options()
    if (opts.getString(prefix + "redundant_pc_type", "lu") != "lu"
            or opts.getString(prefix + "redundant_pc_factor_mat_solver_type", "petsc") != "petsc"):
        return False
    ordering = lu_ordering(prefix) or ORDERING
    _retype(pc, PETSc.PC.Type.PYTHON,
            lambda pc: pc.setPythonContext(schur.RankSchur(problem, ordering)))
    return True


def use_chain_lu(ksp, problem):
    """On one rank, where the KSP factors by PETSc's LU in the rod's own node order
    (chain_ordering's default, not the user's) and the matrix is a chain that order
    eliminates without fill (an open rod without contact), and the user gave no option of
    PETSc's LU (-pc_factor_shift_type ...: they would be ignored), its PC becomes chain.ChainPC:
    rodsnes' own LU of the chain, the same arithmetic block by block without PETSc's symbolic
    factorisation and row lookups (the planar cantilever at 10^4 elements: 2.8 against 5.2 ms
    a factorisation, the solve alike; docs/speed.md).  Returns True when it switched."""
    pc = ksp.getPC()
    if problem.layout.comm.getSize() > 1 or pc.getType() != PETSc.PC.Type.LU:
        return False
    prefix = ksp.getOptionsPrefix() or ""
    key = native_lu_ordering_key(prefix)
    if key is None or not is_default(key) or lu_ordering(prefix) != "natural":
        return False
    if any(user_chose(prefix + name) for name in PETSc.Options(prefix).getAll()
           if name.startswith("pc_factor_")):
        return False            # the user's options of PETSc's LU (a shift, a pivot ...)
    context = chain.ChainPC(problem, ksp.getOperators()[1])
    if context.lu is None:
        return False
    _retype(pc, PETSc.PC.Type.PYTHON, lambda pc: pc.setPythonContext(context))
    return True


class LUChoice:
    """The LU package of one KSP while it is rodsnes' choice (``auto``, lu_defaults): every new
    pattern's matrix is checked once (use_mumps_when_filled, else on one rank use_chain_lu,
    on several use_rank_schur); after a hand-over to MUMPS, or when the user chose, nothing more is
    checked."""

    def __init__(self, auto):
        self.auto = bool(auto)
        self._checked = None            # the pattern checked: the problem's count of new ones

    def check(self, ksp, problem):
        """Before the factorisation of the problem's Jacobian (or its in-plane block) by
        ``ksp``, once per pattern.  Collective."""
        key = problem.stats.get("pattern_refreshes", 0)
        if self.auto and self._checked != key:
            self._checked = key
            if use_mumps_when_filled(ksp, problem):
                self.auto = False       # contact couples much of the rod: MUMPS from now
            elif not use_chain_lu(ksp, problem):
                use_rank_schur(ksp, problem)


def set_up_ahead(ksp, choice, problem, A):
    """Before the first factorisation (a solver's set-up, rodsnes.profiling.SET_UP): the matrix
    ``A`` (preallocated, its values not yet made) set on ``ksp``, the LU's ``choice``
    (LUChoice) made for its pattern, and what that choice plans from the pattern alone made
    now (a python PC's ``plan``: the chain LU's streams, the ranks' separator and
    condensation), so that the first Newton iteration finds them.  Collective."""
    ksp.setOperators(A)
    choice.check(ksp, problem)
    pc = ksp.getPC()
    if pc.getType() == PETSc.PC.Type.PYTHON:
        plan = getattr(pc.getPythonContext(), "plan", None)
        if plan is not None:
            plan(pc)


def reason_name(kind, value):
    """The name of a PETSc converged reason (kind: "SNES" or "KSP"), e.g.
    DIVERGED_LINEAR_SOLVE for SNES's -3; the number where PETSc has no name for it."""
    reasons = getattr(PETSc, kind).ConvergedReason
    for name in dir(reasons):
        if name.isupper() and getattr(reasons, name) == value and name != "ITERATING":
            return name
    return str(value)


def failed_solve(ksp, error=None):
    """Why a linear solve by ``ksp`` failed, in words a user can act on: its converged reason's
    name and iterations (an iterative solve that did not converge: DIVERGED_MAX_IT after 10000),
    or the PETSc error number; with the solver's KSP and PC types and options prefix."""
    if error is not None:
        what = f"PETSc error {error.ierr}"
    else:
        what = f"KSP {reason_name('KSP', ksp.getConvergedReason())}"
        if ksp.getType() != PETSc.KSP.Type.PREONLY:
            what += f" after {ksp.getIterationNumber()} iterations"
    pre = ksp.getOptionsPrefix() or ""
    pc = ksp.getPC()
    kind = pc.getType()
    if kind == PETSc.PC.Type.PYTHON:        # rodsnes' own LU (chain, ranks' Schur complement)
        return f"{what}, rodsnes' direct solve"
    package = ""
    if kind in (PETSc.PC.Type.LU, PETSc.PC.Type.CHOLESKY):
        try:
            package = f" by {pc.getFactorSolverType()}"
        except PETSc.Error:
            pass
    return f"{what}; -{pre}ksp_type {ksp.getType()}, -{pre}pc_type {kind}{package}"
