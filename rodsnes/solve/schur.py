"""Exact linear solves over several ranks by one level of static condensation: RankSchur, the
preconditioner (a python PC, applied once by KSP preonly) that rodsnes' LU becomes on more
than one rank (linear.LUChoice).

Every rank owns a contiguous stretch of the rod (model/partition.py).  The separator G is the
set of nodes that, in an element or a term's node group spanning several ranks, are not owned
by the rank that owns most of its nodes (``separator``): removing them leaves every rank's
other rows, its interior I_r, coupled to no other rank's interior.  Then

    A = [[A_II, A_IG], [A_GI, A_GG]],   A_II = diag(A_{I_r I_r}),

and A x = b is solved exactly by

    W_r = A_{I_r I_r}^-1 A_{I_r G},   S = A_GG - sum_r A_{G I_r} W_r      (the Schur complement)
    y_r = A_{I_r I_r}^-1 b_{I_r},   S x_G = b_G - sum_r A_{G I_r} y_r,   x_{I_r} = y_r - W_r x_G.

Each rank factors its own interior by PETSc's LU (AMD ordering, as the one-rank solve: its
diagonal block, with the identity on the separator rows it owns, so nothing is extracted) and
solves for the columns of W_r (as many as G has unknowns: one node's on a rod cut once); the
ranks add their parts of S (dense, small) and every rank factors it.

Where the rank's stretch is a chain that its own node order, or the reversed one, eliminates
without fill, with the interior rows N next to the separator at the end of that order (an open
rod without contact, cut once at each end stretch: chain.py), the rank factors a copy of its
diagonal block's values by chain.ChainLU instead (the separator's rows and columns the
identity's in the copy).  As A_IG has entries on the rows N only and N lies among the last
rows T of the order,

    A_{G I_r} A_{I_r I_r}^-1 A_{I_r G} = A_GN [U_TT^-1 L_TT^-1]_NN A_NG,

substitutions over those last few rows (the ``tail``) instead of a whole substitution for each
separator unknown, and the application is one forward and one backward substitution, the
tail's in between: z = L^-1 b_I; y_N = U^-1 z on the tail; x_G; z -= L^-1 A_IG x_G on the
tail; x_I = U^-1 z.  The planar cantilever at 10^4 elements on 2 ranks: 17.3 -> 14.5 ms an
iteration; in 3-D 51.4 -> 38.8 ms (docs/parallel.md).  Against PCREDUNDANT,
where every rank gathers the whole matrix and factors all of it, each rank factors only its
share (the planar cantilever at 10^4 elements on 2 ranks: docs/parallel.md).

Where contact couples much of the rod (linear.use_mumps_when_filled: a pattern PETSc's LU fills
in) each rank factors its interior by MUMPS (``package="mumps"``), which forms in the same
factorisation the Schur complement T of the interior unknowns N next to the separator
(MatFactorSetSchurIS, through ctypes: petsc4py 3.18 lacks it; N eliminated last).  As A_IG
has entries on the rows N only and the N block of A_II^-1 is T^-1,

    A_{G I_r} A_{I_r I_r}^-1 A_{I_r G} = A_GN T^-1 A_NG,

no column solves (as many as G has unknowns: hundreds where the turns of a coil touch across
the cut, each costing a whole forward and backward substitution), and x_{I_r} =
A_{I_r I_r}^-1 (b_{I_r} - A_{I_r G} x_G), a second interior solve.  Against MUMPS over the
ranks, whose factorisation scales 1.3 x on 2 ranks and whose redistribution of the matrix not
at all, the bench coil at 10^4 elements: 1.03-1.07 against 1.51 s per Newton iteration on 2
ranks (1.86 s on one; docs/bench_scaling.md).

Where the rod is short (fewer than MIN_NODES_PER_RANK nodes a rank, or
MIN_NODES_PER_RANK_MUMPS with MUMPS interiors: the condensation's fixed cost outweighs what it
saves), the separator large (contact coupling much of the rod across ranks: more than
SCHUR_MAX unknowns) or some rank has no interior, the PC factors the whole matrix instead:
PCREDUNDANT with PETSc's LU on every rank (the previous default), or MUMPS over the ranks.
The couplings' rows, the interior's symbolic factorisation and the index sets are kept while
the matrix and its separator stay (each rank's own objects: a rank may make them anew alone);
condensing or not is decided from global data alike on every rank, without communication.
A failed factorisation on any rank fails the PC on every rank as PETSc's LU's zero pivot does
(petsc_lib.set_pc_failed: the KSP says DIVERGED_PCSETUP_FAILED, its solution Inf; the
application NaN), which fails the Newton step.
"""
import ctypes
import functools

import numpy as np
from scipy.linalg import lapack
from mpi4py import MPI
from petsc4py import PETSc

from rodsnes import petsc_lib
from rodsnes.solve import chain, petsc_exit
from rodsnes.model.partition import any_column, is_split, split_index

SCHUR_MAX = 600         # separator unknowns beyond which the whole matrix is factored instead
PACKAGES = ("petsc", "mumps")       # the interiors' LU (module docstring)
# the most block rows from the first near one to the end of a stretch's order of elimination
# for its own LU without fill (chain.ChainLU: the tail's substitutions run over them); a
# stretch whose near rows lie deeper (a middle rank of three, cut at both ends, unless its
# whole stretch is that short) is factored by PETSc's LU with the separator's column solves
CHAIN_TAIL_MAX = 64
# nodes per rank below which the whole matrix is factored instead: the condensation's fixed
# cost per set-up (the separator's columns, the gathers, the isolation) outweighs what it saves
# on the factorisation.  Measured per Newton iteration on 2 ranks (the cantilever, condensed
# against whole, fastest of three, -log_view's SNESSolve with the between-step writes, 27 Nov
# 2026): planar 500 elements (750 nodes a rank) 7.4 / 7.3 ms, 1000 8.0 / 8.7, 2000 9.4 / 12.1,
# 3000 11.9 / 14.2, 5000 17.6 / 20.5; 3-D 1000 elements 10.3 / 13.3 ms, 2000 16.2 / 24.2, 3000
# 21.0 / 32.9; the plectoneme's 181 nodes 27.8 / 11.7 ms (its pattern changes every few
# iterations).  (4000 before the isolation kept its places and read the block pattern: 3-D
# 1000 elements had been 21.3 / 14.5 ms.)
MIN_NODES_PER_RANK = 1000
# the same where the interiors are factored by MUMPS (a contact-filled pattern: its factorisation
# dwarfs the condensation's fixed cost).  Measured per Newton iteration on 2 ranks, the bench
# coil (tools/bench_scaling.py), condensed against MUMPS over the ranks: 100 elements (301
# nodes) 19.0 / 17.6 ms, 300 elements 37.7 / 40.4 ms, 1000 elements 102 / 135 ms
MIN_NODES_PER_RANK_MUMPS = 400


def pays(n_nodes, ranks, package="petsc"):
    """Whether a rod of ``n_nodes`` nodes on ``ranks`` ranks is long enough for the
    condensation with interiors factored by ``package`` to pay (MIN_NODES_PER_RANK or
    MIN_NODES_PER_RANK_MUMPS nodes a rank)."""
    least = MIN_NODES_PER_RANK_MUMPS if package == "mumps" else MIN_NODES_PER_RANK
    return n_nodes >= least * ranks


WHOLE_PREFIX = "rodsnes_whole_"     # the options of that whole-matrix LU (RankSchur._whole)
WHOLE_MUMPS_PREFIX = WHOLE_PREFIX + "mumps_"    # ... by MUMPS over the ranks (package mumps)
_WHOLE_DEFAULTS = {}    # prefix -> {"users": live RankSchurs, "set": the defaults they put in}
INTERIOR_PREFIX = "interior_"   # the options of the interiors' MUMPS LU (-interior_mat_mumps_*)
MADE = set()                    # INTERIOR_PREFIX once this run made such an LU (linear.solvers_made)


# -- MUMPS's Schur complement (PETSc's MatFactorSetSchurIS ..., which petsc4py 3.18 lacks) ----
_P, _I = ctypes.c_void_p, ctypes.c_int
_SIGNATURES = {"MatFactorSetSchurIS": (_P, _P), "MatFactorGetSchurComplement": (_P, _P, _P),
               "MatFactorRestoreSchurComplement": (_P, _P, _I),
               "MatDenseGetArrayRead": (_P, _P), "MatDenseRestoreArrayRead": (_P, _P),
               "MatDenseGetLDA": (_P, _P)}


def _checked(name, *args):
    """PETSc's ``name`` (petsc_lib) called with ``args``, PETSc.Error on an error code."""
    petsc_lib.call(name, *args, argtypes=_SIGNATURES[name])


def _unchecked(name, *args):
    """The same, its error code ignored (a restore in a finally clause)."""
    petsc_lib.function(name, *_SIGNATURES[name])(*args)


def set_schur_unknowns(F, rows):
    """Before the symbolic factorisation of the MUMPS factor ``F`` (sequential): its Schur
    complement is to be that of the unknowns ``rows`` (local indices), eliminated last."""
    is_ = PETSc.IS().createGeneral(np.asarray(rows, dtype=PETSc.IntType), comm=PETSc.COMM_SELF)
    try:
        _checked("MatFactorSetSchurIS", F.handle, is_.handle)
    finally:
        is_.destroy()


def schur_complement(F, n):
    """A copy (n x n) of the Schur complement T = A_NN - A_NF A_FF^-1 A_FN that MUMPS formed in
    the numeric factorisation of ``F`` (set_schur_unknowns), read before any solve (which
    factors it in place)."""
    S, status = ctypes.c_void_p(), ctypes.c_int()
    _checked("MatFactorGetSchurComplement", F.handle, ctypes.byref(S), ctypes.byref(status))
    try:
        if status.value != 0:           # MAT_FACTOR_SCHUR_UNFACTORED
            raise PETSc.Error(73)
        lda = (ctypes.c_int64 if PETSc.IntType().itemsize == 8 else ctypes.c_int32)()
        _checked("MatDenseGetLDA", S, ctypes.byref(lda))
        data = ctypes.POINTER(ctypes.c_double)()
        _checked("MatDenseGetArrayRead", S, ctypes.byref(data))
        try:                            # column-major, leading dimension lda
            T = np.ctypeslib.as_array(data, shape=(n, lda.value))[:, :n].T.copy()
        finally:
            _unchecked("MatDenseRestoreArrayRead", S, ctypes.byref(data))
    finally:
        _unchecked("MatFactorRestoreSchurComplement", F.handle, ctypes.byref(S), status.value)
    return T


def separator(problem, A):
    """(sep, near): the separator's block rows of A (sorted global block indices: the
    problem's nodes, block size 6 or 3, or both blocks of each node of a split matrix) and
    the other block rows that share a group with one of them (the only rows and columns of
    A_IG and A_GI that hold entries).  The separator: in every element and term node group
    (problem.node_groups of its patterns) whose nodes belong to several ranks, the nodes not
    owned by the rank owning most of them (the lowest rank of a tie): the group's other nodes
    are then one rank's.  The same on every rank (the groups are global)."""
    groups = [problem.layout.nat2petsc[g] for g in problem.coupled_groups()]
    if is_split(A):             # a node's position and rotation blocks 2n, 2n + 1
        groups = [split_index(g) for g in groups]
    first = np.asarray(A.getOwnershipRanges()) // A.getBlockSize()
    out = []
    nranks = len(first) - 1
    for rows in groups:
        owner = np.searchsorted(first, rows, side="right") - 1
        span = any_column(owner != owner[:, :1])
        if not span.any():
            continue
        o = owner[span]
        # the rank owning most of the group's nodes keeps them (the lowest of a tie): an
        # element cut 1 + 3 costs one node, not three
        counts = np.stack([(o == r).sum(axis=1) for r in range(nranks)], axis=1)
        keep = counts.argmax(axis=1)[:, None]
        out.append(rows[span][o != keep])
    if not out:                 # no group spans ranks (one rank): nothing to condense
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    sep = np.unique(np.concatenate(out)).astype(np.int64)
    near = np.unique(np.concatenate([rows[any_column(np.isin(rows, sep))].ravel()
                                     for rows in groups]))
    return sep, np.setdiff1d(near, sep).astype(np.int64)


def _unknowns(blocks, size):
    """The unknowns (scalar indices) of the blocks of ``size`` unknowns, block by block."""
    return (np.asarray(blocks)[:, None] * size + np.arange(size)).ravel()


def _dense_lu(M):
    """LAPACK's LU (lu, piv) of the dense M (getrf: scipy's lu_factor without its checks and
    warnings, a fifth of its time on a separator's few unknowns), or None where it is singular
    or not finite (the caller fails the solve)."""
    if not np.isfinite(M).all():
        return None
    lu, piv, info = lapack.dgetrf(M)
    # (a pivot that overflowed to NaN: singular too)
    return (lu, piv) if info == 0 and not np.isnan(lu.diagonal()).any() else None


def _lu_solve(lu, b):
    """x = M^-1 b from _dense_lu(M) (getrs)."""
    return lapack.dgetrs(lu[0], lu[1], b)[0]


def _dense_rows(A, rows, cols):
    """A's entries at (rows, cols) as a dense array: ``rows`` this rank's (global indices),
    ``cols`` global columns; an entry outside the pattern is zero.  One MatGetValues (MatGetRow
    of each row took 0.17 ms a set-up at 10^4 planar elements on 2 ranks)."""
    if not len(rows) or not len(cols):
        return np.zeros((len(rows), len(cols)))
    return A.getValues(rows, cols).reshape(len(rows), len(cols))


def _chain_lu(D, sepb, nearb):
    """(ChainLU, tail) for the interior of the SeqBAIJ diagonal block D (chain.py), its block
    rows ``sepb`` (the separator's) taken out, ``nearb`` the rows next to the separator: the
    direction of elimination whose near rows come last, ``tail`` the order position of the
    first of them.  None where the pattern fills in that direction or the near rows lie deeper
    than CHAIN_TAIL_MAX (or the kernel is not built)."""
    n = D.getSize()[0] // D.getBlockSize()
    best = None
    for direction in (1, -1):
        pos = nearb if direction > 0 else n - 1 - nearb
        tail = int(pos.min()) if len(pos) else n
        if n - tail <= CHAIN_TAIL_MAX and (best is None or tail > best[1]):
            best = (direction, tail)
    if best is None:
        return None
    lu = chain.plan_of(D, best[0], out=sepb)
    return None if lu is None else (lu, best[1])


class RankSchur:
    """The python PC context of the module docstring for the matrices of ``problem``."""

    def __init__(self, problem, ordering="amd", package="petsc"):
        if package not in PACKAGES:
            raise ValueError(f"package {package!r}: one of {PACKAGES}")
        self.problem = problem
        self.ordering = ordering
        self.package = package      # the interiors' LU and the whole matrix's
        self.kept = None            # the condensation of the last matrix (index sets, blocks)
        self.whole = None           # the whole-matrix LU (KSP) where condensation does not pay
        self.mode = None            # "schur" or "whole" for the current matrix
        self.failed = False
        self.setups = {"schur": 0, "whole": 0}
        # with ``inertia`` (a symmetric matrix; stability.Inertia) every set-up counts its
        # negative eigenvalues where every rank's stretch has the chain LU: by Haynsworth's
        # inertia additivity, inertia(A) = inertia(A_II) + inertia(S), A_II's the sum of the
        # stretches' (their pivot blocks', chain.py; the separator rows taken out are identity
        # rows, positive) and S's from its eigenvalues; else None
        self.inertia = False
        self.negative = None
        self.structural = False     # no count because some stretch has no chain LU (or whole)

    # -- life (petsc_exit: a python PC still alive at exit) ---------------------------
    def create(self, pc):
        """petsc4py calls it when the context is set."""
        petsc_exit.live(pc)

    def destroy(self, pc):
        """petsc4py calls it when the PC is destroyed or changes type (collective, as
        PCDestroy): the kept objects go now, not to PETSc's garbage."""
        petsc_exit.gone(pc)
        k, self.kept = self.kept, None
        for name in ("ksp", "AII", "B", "W", "yI", "bI"):
            if k is not None and k.get(name) is not None:
                k[name].destroy()       # AII may be A's diagonal block: only our reference
        if self.whole is not None:
            self.whole.destroy()
            self.whole = None
            mine = _WHOLE_DEFAULTS[self._whole_prefix]
            mine["users"] -= 1
            if not mine["users"]:
                opts = PETSc.Options(self._whole_prefix)
                for name in mine["set"]:
                    opts.delValue(name)
                mine["set"].clear()

    # -- set-up -----------------------------------------------------------------------
    def _key(self, A):
        """What identifies the matrix: its handle, its size and the problem's count of new
        patterns (the same on every rank; a handle alone may be a new matrix at a freed one's
        address)."""
        return (A.handle, A.getSize(), self.problem.stats.get("pattern_refreshes", 0))

    def plan(self, pc):
        """The set-up's part that needs the matrix's pattern alone (the separator, the decision
        to condense, the condensation's index sets, blocks and the stretches' plans), unless
        made for this matrix already: a solver's set-up makes it before the matrix has values
        (linear.set_up_ahead), and the first setUp goes straight to the factorisations.
        Returns whether the matrix is condensed (else the whole-matrix LU, set up with the
        values).  Collective."""
        A = pc.getOperators()[0]
        key = self._key(A)
        if self.kept is not None and self.kept["A"] == key:
            return True
        comm = A.getComm().tompi4py()
        bs = A.getBlockSize()
        rs, re = A.getOwnershipRange()
        # every rank decides alike, without communication: the size, the separator (the
        # contact pairs are gathered to every rank) and the ownership ranges are global, and so
        # is every rank's interior size; a short rod goes to the whole matrix before any of it
        # (the separator of a contact-rich pattern costs 0.7 ms a set-up on the plectoneme).
        # Whether a rank condenses anew or refreshes (setUp) is its own (_condense makes
        # objects of its own alone): a rank whose factorisation failed condenses anew, the
        # others need not
        condense = pays(self.problem.mesh.n_nodes, comm.Get_size(), self.package)
        if condense:
            sep, near = separator(self.problem, A)
            mine = sep[(sep >= rs // bs) & (sep < re // bs)]
            first = np.asarray(A.getOwnershipRanges()) // bs
            interior = np.diff(first) - np.diff(np.searchsorted(sep, first))
            condense = 0 < len(sep) * bs <= SCHUR_MAX and interior.min() > 0
        if not condense:
            self.kept = None
            return False
        self._condense(A, key, sep, mine, near)
        return True

    def setUp(self, pc):
        petsc_exit.live(pc)
        A = pc.getOperators()[0]
        k = self.kept
        if k is not None and k["A"] == self._key(A):
            # the matrix planned or condensed before (the same separator and decision on every
            # rank: kept only in "schur" mode) with new values: its objects refreshed (a Newton
            # iteration's set-up; the decision's arrays and gathers took 0.1-0.2 ms)
            self._refresh(A)
        elif not self.plan(pc):
            self.mode = "whole"
            self.setups["whole"] += 1
            self._whole(A).setUp()
            self.failed = False
            petsc_lib.set_pc_failed(pc, False)
            self.negative = None
            self.structural = True
            return
        self.mode = "schur"
        self.setups["schur"] += 1
        k = self.kept
        self._factor(A, k["comm"])
        petsc_lib.set_pc_failed(pc, self.failed)        # the same on every rank (_factor)
        self.negative = self._count(k["comm"]) if self.inertia else None

    def _count(self, comm):
        """The negative eigenvalues of A (symmetric) from the last set-up (``inertia``), or
        None where some rank's stretch is not factored by the chain LU or the set-up failed.
        Collective."""
        k = self.kept
        lu = k["chain"]
        mine = lu.negative if lu is not None and not self.failed else None
        counts = comm.allgather((mine, lu is not None))
        self.structural = not all(chained for _, chained in counts)
        if any(c is None for c, _ in counts):
            return None
        counts = [c for c, _ in counts]
        S = k["S_dense"]
        return sum(counts) + int((np.linalg.eigvalsh(0.5 * (S + S.T)) < 0.0).sum())

    def _whole(self, A):
        """PETSc's LU of the whole matrix on every rank (PCREDUNDANT; its inner solver set
        through the options of a prefix of its own: petsc4py 3.18 does not reach it)."""
        if self.whole is None:
            prefix = WHOLE_MUMPS_PREFIX if self.package == "mumps" else WHOLE_PREFIX
            opts = PETSc.Options(prefix)
            if self.package == "mumps":     # MUMPS over the ranks (its ICNTLs: linear.py)
                settings = (("ksp_type", "preonly"), ("pc_type", "lu"),
                            ("pc_factor_mat_solver_type", "mumps"))
            else:
                settings = (("ksp_type", "preonly"), ("pc_type", "redundant"),
                            ("redundant_ksp_type", "preonly"), ("redundant_pc_type", "lu"),
                            ("redundant_pc_factor_mat_solver_type", "petsc"),
                            ("redundant_pc_factor_mat_ordering_type", self.ordering))
            # rodsnes' defaults for that prefix, unless given (the user's win), kept in the
            # options database while a RankSchur uses them (MUMPS reads its own at every
            # analysis) and taken out after the last (destroy)
            mine = _WHOLE_DEFAULTS.setdefault(prefix, {"users": 0, "set": []})
            for name, value in settings:
                if not opts.hasName(name):
                    opts[name] = value
                    mine["set"].append(name)
            mine["users"] += 1
            self._whole_prefix = prefix
            ksp = self.whole = PETSc.KSP().create(comm=A.getComm())
            ksp.setOptionsPrefix(prefix)
            ksp.setFromOptions()
        self.whole.setOperators(A)
        return self.whole

    def _condense(self, A, key, sep, mine, near):
        """Index sets, blocks and the interior's KSP for a new matrix or separator.  ``near``:
        this rank's interior block rows next to the separator (A_IG's and A_GI's entries).

        The interior matrix is the rank's diagonal block itself, its separator rows and
        columns made those of the identity while it is factored (``_factor_interior``): the
        same LU as A_II's (the identity rows are uncoupled) in the rank's own row order, so the
        right-hand sides and solutions are the rank's local arrays with the separator's entries
        zero."""
        bs = A.getBlockSize()
        rs, re = A.getOwnershipRange()
        ni, ng = re - rs, len(sep) * bs
        here = near[(near >= rs // bs) & (near < re // bs)]
        unknowns = functools.partial(_unknowns, size=bs)
        k = self.kept = {"A": key, "sep": sep, "near": near, "ni": ni, "ng": ng,
                         "comm": A.getComm().tompi4py(),
                         "G": unknowns(mine - rs // bs),
                         # the separator's unknowns this rank owns, in S's order
                         "Gpos": unknowns(np.searchsorted(sep, mine)),
                         # the interior unknowns next to the separator, in the rank's order
                         "Npos": unknowns(here - rs // bs), "nn": len(here) * bs,
                         # global unknowns of the couplings' rows and columns (_couplings)
                         "rowsN": unknowns(here).astype(PETSc.IntType),
                         "rowsG": unknowns(mine).astype(PETSc.IntType),
                         "colsSN": np.concatenate([unknowns(sep), unknowns(near)]).astype(
                             PETSc.IntType),
                         "nearpos": ng + unknowns(np.searchsorted(near, here))}
        D = k["AII"] = A.getDiagonalBlock()
        k["chain"] = None
        if self.package == "petsc" and bs > 1:
            found = _chain_lu(D, np.unique(k["G"] // bs), here - rs // bs)
            if found is not None:
                # the stretch's own LU without fill (chain.py): no KSP, no column solves
                lu, tail = k["chain"], k["tail"] = found
                k["tail_rows"] = _unknowns(np.sort(lu.order_position(np.arange(tail, lu.n))), bs)
                k["near_in_tail"] = np.searchsorted(k["tail_rows"], k["Npos"])
                k["work"] = np.zeros(ni)    # the tail's substitutions: zero off the tail
                return
        k["isolate"] = []
        if len(k["G"]):
            # what _factor_interior sets to the identity's: the separator's rows (every entry)
            # and the rows holding entries in its columns (those entries), from D's block
            # pattern (MatGetRowIJ of the blocks of a BAIJ matrix: 0.1 ms, where the scalar
            # CSR's copy and its scan took 20 ms a new pattern at 10^4 planar elements on 2
            # ranks; an AIJ matrix's scalar pattern)
            pb = bs if D.getType() == PETSc.Mat.Type.SEQBAIJ else 1    # the pattern's unit
            ai, aj = D.getRowIJ(compressed=pb > 1)
            sepb = np.unique(k["G"] // pb)
            hit = np.isin(aj, sepb)
            touch = np.setdiff1d(np.repeat(np.arange(len(ai) - 1), np.diff(ai))[hit], sepb)
            for rb in np.concatenate([sepb, touch]):
                cols = aj[ai[rb]:ai[rb + 1]]
                cols = _unknowns(cols if rb in sepb else cols[np.isin(cols, sepb)], pb)
                for r in range(rb * pb, (rb + 1) * pb):
                    k["isolate"].append((PETSc.IntType(r), cols.astype(PETSc.IntType)))
        ksp = k["ksp"] = PETSc.KSP().create(comm=PETSc.COMM_SELF)
        ksp.setType(PETSc.KSP.Type.PREONLY)
        pc = ksp.getPC()
        pc.setType(PETSc.PC.Type.LU)
        ksp.setOperators(k["AII"])
        k["bI"] = PETSc.Vec().createSeq(ni, comm=PETSc.COMM_SELF)   # the apply's interior
        k["yI"] = PETSc.Vec().createSeq(ni, comm=PETSc.COMM_SELF)   # right side and solution
        if self.package == "mumps":
            # MUMPS forms the Schur complement of the near unknowns N in its factorisation
            # (-interior_mat_mumps_icntl_*, rodsnes' defaults from linear.py or the user's,
            # are read at its analysis)
            ksp.setOptionsPrefix(INTERIOR_PREFIX)
            MADE.add(INTERIOR_PREFIX)
            pc.setFactorSolverType("mumps")
            ksp.setFromOptions()
            pc.setFactorSetUpSolverType()
            if k["nn"]:
                set_schur_unknowns(pc.getFactorMatrix(), k["Npos"])
            return
        pc.setFactorSolverType("petsc")
        pc.setFactorOrdering(self.ordering)
        k["B"] = PETSc.Mat().createDense((ni, ng), comm=PETSc.COMM_SELF)
        k["B"].setUp()
        k["W"] = PETSc.Mat().createDense((ni, ng), comm=PETSc.COMM_SELF)
        k["W"].setUp()
        k["B"].getDenseArray()[:] = 0.0

    def _refresh(self, A):
        """The same matrix with new values: its diagonal block has them (same patterns)."""
        k = self.kept
        k["AII"] = A.getDiagonalBlock()
        if k["chain"] is None:
            k["ksp"].setOperators(k["AII"])

    def _factor_interior(self):
        """The interior's LU (numeric; symbolic too on a new pattern) of A's diagonal block
        with the identity on the separator's rows and columns while it is factored, then the
        block given its values back: the separator's rows and the few entries of its columns
        (``isolate``), no copy of the block (a copy and MatZeroRowsColumns's sweep cost 1.5 ms
        an iteration at 10^4 elements on 2 ranks, these rows 0.25 ms; not as blocks with
        NEW_NONZERO_LOCATIONS toggled: the block's nonew flag, changed on this rank alone, decides
        a collective in MatAssemblyEnd_MPIBAIJ - a hang).  The KSP then reuses the factors
        (the restored block is not factored again at the solves).  Returns False when the
        factorisation raised."""
        k = self.kept
        D, pc = k["AII"], k["ksp"].getPC()
        # the entries of the rows and columns to isolate (their places kept with the pattern:
        # MatGetValues of those places, 0.1 against 0.4 ms for a MatGetRow of each row)
        saved = [(r, cols, D.getValues(r, cols).ravel()) for r, cols in k["isolate"]]
        if saved:
            for r, cols, _ in saved:    # the identity's rows, zero in its columns
                D.setValues(r, cols, np.where(cols == r, 1.0, 0.0))
            D.assemble()
        ok = True
        try:
            pc.setReusePreconditioner(False)
            k["ksp"].setUp()
        except PETSc.Error:
            ok = False
        finally:
            pc.setReusePreconditioner(True)
            for r, cols, vals in saved:
                D.setValues(r, cols, vals)
            if saved:
                D.assemble()
        return ok

    def _couplings(self, A):
        """(A_IG, A_GG and A_GN) of this rank, dense: A_IG = the rank's interior rows next to
        the separator at the separator's columns; the separator's rows this rank owns at the
        separator's and at every rank's near interior columns, at their places among all
        separator rows (zero elsewhere: _share adds the ranks' rows).  A few rows each
        (MatCreateSubMatrices did the same in 4.9 ms a set-up at 10^4 elements on 2 ranks,
        the whole rank's rows scanned)."""
        k = self.kept
        ng = k["ng"]
        ANS = _dense_rows(A, k["rowsN"], k["colsSN"][:ng])
        rows = np.zeros((ng, len(k["colsSN"])))
        rows[k["Gpos"]] = _dense_rows(A, k["rowsG"], k["colsSN"])
        return ANS, rows

    def _factor(self, A, comm):
        """The interior's LU, W_r, S = A_GG - sum_r A_{G I_r} W_r, and S's LU on every rank."""
        k = self.kept
        ANS, rows = self._couplings(A)
        if k["chain"] is not None:
            self._factor_chain(ANS, rows, comm)
            return
        ok = self._factor_interior()
        if self.package == "mumps":
            if not ok:              # the analysis or factorisation raised: a new KSP next time
                k["A"] = None
            ok, WN = self._factor_mumps(ANS) if ok else (False, None)
            self._share(rows, WN, ok, comm)
            return
        B = k["B"].getDenseArray()
        B[k["Npos"]] = ANS                                  # A_IG: rows next to G only
        # all columns at once (MatMatSolve: 0.84 against 1.1 ms for three KSP solves on a
        # planar stretch of 15000 nodes, 7.0 against 8.9 ms for six in 3-D); after a zero
        # pivot (PETSc defers factor errors) it raises, or leaves W not finite
        if ok:
            try:
                k["ksp"].getPC().getFactorMatrix().matSolve(k["B"], k["W"])
            except PETSc.Error:
                ok = False
        W = k["W"].getDenseArray()
        ok = ok and bool(np.isfinite(W).all())
        self._share(rows, W[k["Npos"]] if ok else None, ok, comm)

    def _tail_solve(self, t, first, last):
        """The chain LU's substitutions restricted to its tail (``first``, ``last``: chain.
        ChainLU.solve) on the vector that is ``t`` on the tail's rows (tail_rows) and zero
        elsewhere; returns the result on the tail's rows.  The work vector is zero off the
        tail: no other row of it is ever written."""
        k = self.kept
        w, rows = k["work"], k["tail_rows"]
        w[rows] = t
        k["chain"].solve(w, first, last)
        return w[rows].copy()

    def _on_tail(self, near):
        """The tail vector that is ``near`` on the near rows, zero on the tail's others."""
        k = self.kept
        t = np.zeros(len(k["tail_rows"]))
        t[k["near_in_tail"]] = near
        return t

    def _factor_chain(self, ANS, rows, comm):
        """The stretch's LU without fill (chain.py) and its part of S from the inverse's
        trailing block: A_GN (A_II^-1)_NN A_NG, (A_II^-1)_TT = U_TT^-1 L_TT^-1 by substitutions
        over the tail T alone.  A failure here is every rank's (_share), never a hang: an error
        raised is a failed factorisation; a matrix no longer of the planned pattern makes the
        next set-up condense anew."""
        k = self.kept
        lu, tail = k["chain"], k["tail"]
        try:
            ok = lu.factor(k["AII"], inertia=self.inertia)
        except (PETSc.Error, RuntimeError, ValueError):
            ok = False
        if lu.stale:
            k["A"] = None
        WN = None
        if ok:
            WN = np.empty_like(ANS)
            for c in range(ANS.shape[1]):
                WN[:, c] = self._tail_solve(self._on_tail(ANS[:, c]), tail, tail)[
                    k["near_in_tail"]]
            ok = bool(np.isfinite(WN).all())
        k["ANS"] = ANS
        self._share(rows, WN, ok, comm)

    def _separator_solution(self, comm, b, yN):
        """x_G = S^-1 (b_G - sum_r A_{G N_r} y_{N_r}), ``yN`` this rank's y_r = A_{I_r I_r}^-1
        b_{I_r} on its near rows N_r.  Collective."""
        k = self.kept
        g = -(k["asn"] @ yN)
        g[k["Gpos"]] += b[k["G"]]
        comm.Allreduce(MPI.IN_PLACE, g, op=MPI.SUM)
        return _lu_solve(k["S"], g)

    def _apply_chain(self, comm, b, y):
        """x = A^-1 b through the chain LU: one forward substitution of b_I, the near rows of
        A_II^-1 b_I by the tail's backward one, x_G, the forward substitution of A_IG x_G over
        the tail, one backward substitution: a solve's work."""
        k = self.kept
        lu, tail = k["chain"], k["tail"]
        z = y.getArray()                    # the substitutions in y's own values (b is x's)
        z[:] = b
        z[k["G"]] = 0.0
        lu.solve(z, 0, lu.n)                                    # z = L^-1 b_I
        rows = k["tail_rows"]
        yT = self._tail_solve(z[rows], lu.n, tail)              # (A_II^-1 b_I) on the tail
        xg = self._separator_solution(comm, b, yT[k["near_in_tail"]])
        z[rows] -= self._tail_solve(self._on_tail(k["ANS"] @ xg), tail, lu.n)
        lu.solve(z, lu.n, 0)                                    # x_I = U^-1 (z - L^-1 A_IG x_G)
        z[k["G"]] = xg[k["Gpos"]]

    def _factor_mumps(self, ANS):
        """The interior's MUMPS LU with T, the Schur complement of its near unknowns N; then
        A_{G I_r} A_II^-1 A_{I_r G} = A_GN T^-1 A_NG (the N block of A_II^-1 is T^-1), no
        column solves.  Returns (ok, -that)."""
        k = self.kept
        ksp = k["ksp"]
        k["ANS"] = ANS
        F = ksp.getPC().getFactorMatrix()
        if F.getMumpsInfog(1) < 0 or F.getMumpsInfog(25) > 0:
            # a failure MUMPS reports in INFOG(1) (no room, ...), or a singular interior: with a
            # Schur complement MUMPS reports none (INFOG(1) = 0, no null pivot under ICNTL(24))
            # but replaces the zero pivot by static pivoting (INFOG(25), its count) and solves
            # to garbage (|A y - b| / |b| = 140, |y| = 1e15, on the coil with a zero row).
            # After INFOG(1) < 0 PETSc 3.18 would skip every later numeric factorisation of
            # this PC: the next set-up makes the interior's KSP anew
            k["A"] = None
            return False, None
        if not k["nn"]:
            return True, np.zeros((0, k["ng"]))
        try:
            lu = _dense_lu(schur_complement(F, k["nn"]))
        except PETSc.Error:
            return False, None
        if lu is None:
            return False, None
        WN = _lu_solve(lu, ANS)
        return bool(np.isfinite(WN).all()), WN

    def _share(self, rows, WN, ok, comm):
        """S = A_GG - sum_r A_{G N_r} W_{N_r} (W_{N_r} = (A_{I_r I_r}^-1 A_{I_r G}) on the
        rank's near rows N_r: ``WN``), factored on every rank, from one reduction: the
        separator rows each rank owns (``rows``: _couplings), each rank's W_{N_r} at its place
        among all near rows, and the ranks that failed (``ok`` False: self.failed on every
        rank).  Keeps A_{G N_r} (``asn``) for the solves."""
        k = self.kept
        ng, nc = k["ng"], rows.shape[1]
        buf = np.zeros(ng * nc + (nc - ng) * ng + 1)
        # views of the buffer: the separator's rows and every rank's W_N
        sep_rows, W = buf[:ng * nc].reshape(ng, nc), buf[ng * nc:-1].reshape(nc - ng, ng)
        sep_rows[:] = rows
        if ok:
            W[k["nearpos"] - ng] = WN
        buf[-1] = 0.0 if ok else 1.0
        comm.Allreduce(MPI.IN_PLACE, buf, op=MPI.SUM)
        k["asn"] = sep_rows[:, k["nearpos"]]
        self.failed = bool(buf[-1] > 0.0)
        if not self.failed:
            S = k["S_dense"] = sep_rows[:, :ng] - sep_rows[:, ng:] @ W
            k["S"] = _dense_lu(S)
            self.failed = k["S"] is None

    # -- solve --------------------------------------------------------------------------
    def apply(self, pc, x, y):
        if self.mode == "whole":
            self.whole.solve(x, y)
            return
        if self.failed:                 # the same on every rank (_factor)
            y.set(np.nan)
            return
        k = self.kept
        comm = pc.getOperators()[0].getComm().tompi4py()
        b = x.getArray(readonly=True)
        if k["chain"] is not None:
            self._apply_chain(comm, b, y)
            return
        bI, yI = k["bI"], k["yI"]
        with bI as a:                   # b_I: the rank's entries, the separator's zero
            a[:] = b
            a[k["G"]] = 0.0
        k["ksp"].solve(bI, yI)
        yv = yI.getArray(readonly=True)
        xg = self._separator_solution(comm, b, yv[k["Npos"]])
        if self.package == "mumps":         # x_I = A_II^-1 (b_I - A_IG x_G): a second solve
            with bI as a:
                a[k["Npos"]] -= k["ANS"] @ xg
            k["ksp"].solve(bI, yI)
            yv = yI.getArray(readonly=True)
            if k["ksp"].getConvergedReason() < 0:
                y.set(np.nan)
                return
        out = y.getArray()
        out[:] = yv
        if self.package != "mumps":         # x_I = y_I - W x_G
            out -= k["W"].getDenseArray() @ xg
        out[k["G"]] = xg[k["Gpos"]]
