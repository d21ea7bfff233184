"""The LU of a rank's stretch of a rod, without fill, that gives its inverse's trailing block
without a whole substitution (schur.RankSchur on several ranks); on one rank the Newton step's
LU of an open rod without contact (ChainPC, linear.use_chain_lu) and the stability count.

An open rod's chain without contact is eliminated in its own node order, or the reversed one,
with no fill: every block the elimination updates is already in the pattern
(``ChainLU.plan`` checks it).  rodsnes/solve/_chain_kernel.c factors a SeqBAIJ matrix of such a
pattern in place of a copy of its values (block LU, each diagonal block inverted with partial
pivoting inside it, no pivoting between blocks: as PETSc's own BAIJ LU) and solves with the
factors over a range of the order.

What it is for: in the condensation of schur.py each rank needs A_GN (A_II^-1)_NN A_NG, N the
few interior rows next to the separator.  PETSc's LU hands out no part of its factors, so that
block costs a whole forward and backward substitution for each separator unknown (3 on a
planar rod cut once, 6 in 3-D).  With N among the last rows T of the order of elimination
(the natural order where N is the stretch's end, the reversed one where it is its start),
A_II^-1 on T is U_TT^-1 L_TT^-1, so its N block takes substitutions over T alone (the
``tail``), and an application one whole solve, as on one rank.  The same factors of a symmetric
matrix give its inertia: H = L D L^T is a congruence, so H's negative eigenvalues are those
of the pivot blocks D (stability.Inertia on one rank).
"""
import collections
import ctypes

import numpy as np
from petsc4py import PETSc

from rodsnes import compiled, petsc_lib
from rodsnes.profiling import logged
from rodsnes.solve import petsc_exit

I32, I8 = compiled.I32, compiled.I8
MAX_BS = 8                  # the kernel's largest block size


# the kernel's C entries by name (compiled.Foreign each)
Kernel = collections.namedtuple("Kernel", "plan streams factor solve")


def _declare(lib):
    i32, f64, c_int = I32, compiled.F64, ctypes.c_int
    plan = compiled.Foreign(lib.rodsnes_chain_plan,
                            [c_int, i32, i32, c_int, i32, ctypes.c_void_p, ctypes.c_int64],
                            ctypes.c_int64)
    streams = compiled.Foreign(lib.rodsnes_chain_streams,
                               [c_int, i32, i32, i32, c_int, i32, i32, i32, i32], None)
    # the entry's name changes with its arguments: a library built from an older source lacks
    # it and the kernel counts as not built (compiled.load), instead of being misread
    factor = compiled.Foreign(lib.rodsnes_chain_factor_streams,
                              [c_int, c_int, i32, i32, i32, i32, i32, c_int, i32,
                               ctypes.c_void_p, I8, f64, ctypes.c_void_p], c_int)
    solve = compiled.Foreign(lib.rodsnes_chain_solve_streams,
                             [c_int, c_int, i32, i32, i32, c_int, f64, c_int, c_int, f64], c_int)
    return Kernel(plan, streams, factor, solve)


_load = compiled.loader("rodsnes.solve._chain_kernel", _declare)


def available():
    """True when the compiled kernel is built and loads."""
    return bool(_load())


def factorable(mat):
    """Whether ChainLU can factor ``mat``: a SeqBAIJ matrix whose value array is reachable
    (petsc_lib.values_of), the kernel built (whether its pattern fills is plan's to say)."""
    return (mat.getType() == PETSc.Mat.Type.SEQBAIJ and available()
            and petsc_lib.has_value_array(mat))


def _streams(ai, aj, diag, direction):
    """The factors' two streams (_chain_kernel.c's rodsnes_chain_streams): (place, col, lofs,
    uofs) - the slot of each block of the CSR, the block column of each slot, and per order
    position s the first slot of its row's multipliers (lofs, slots 0 .. nL - 1, each row's in
    its order of elimination: ascending columns for +1, descending for -1) and of its inverted
    diagonal block, its upper blocks after it in ascending columns (uofs, from nL).  int32
    each."""
    n = len(ai) - 1
    place, col = np.empty(int(ai[-1]), dtype=I32), np.empty(int(ai[-1]), dtype=I32)
    lofs, uofs = np.empty(n + 1, dtype=I32), np.empty(n + 1, dtype=I32)
    _load().streams(n, ai, aj, diag, int(direction), place, col, lofs, uofs)
    return place, col, lofs, uofs


def plan_of(mat, direction=1, out=()):
    """ChainLU.plan for the SeqBAIJ ``mat``'s block pattern, or None where the kernel cannot
    read it (factorable) or the elimination would fill."""
    if not factorable(mat):
        return None
    ai, aj = mat.getRowIJ(compressed=True)
    return ChainLU.plan(ai, aj, mat.getBlockSize(), direction, out)


class ChainLU:
    """The LU without fill of a SeqBAIJ matrix of block CSR (ai, aj) and block size bs,
    eliminated in the natural order (direction +1) or the reversed one (-1).  Made by
    ``ChainLU.plan``; factor() at every new set of values, solve() after."""

    def __init__(self, ai, aj, bs, direction, diag, target, out):
        self.ai, self.aj, self.bs, self.dir = ai, aj, bs, direction
        self.n = len(ai) - 1
        self.place, self.col, self.lofs, self.uofs = _streams(ai, aj, diag, direction)
        self.target = self.place[target]    # the updates' slots in the streams
        # the factors' storage, touched now: a fresh page's first touch costs about 2 us on a
        # VM (a tenth of a factorisation's time at 10^4 elements), paid in the plan (a
        # solver's set-up) rather than in the first factorisation
        self.values = np.empty(int(ai[-1]) * bs * bs)
        self.values.fill(0.0)
        self.failed_row = None          # the row of a singular pivot block (last factor)
        self.stale = False              # the last factor() found another pattern
        self.negative = None            # the last factor()'s count (inertia=True)
        # how each block enters the factorisation: as it is (0), or, for the block rows taken
        # out, zero (1: their rows' and columns' other blocks) and the identity (2: their
        # diagonal blocks)
        self.kind = np.zeros(len(aj), dtype=I8)
        if len(out):
            # the blocks of the rows taken out and those in their columns: a pass over the
            # columns and the rows' own slots, not a row index for every block (0.43 -> 0.15
            # ms of a plan of 1.0 ms on a planar stretch of 15000 nodes)
            out = np.unique(np.asarray(out, dtype=np.int64))
            taken = np.zeros(self.n, dtype=bool)
            taken[out] = True
            starts, ends = ai[out].astype(np.int64), ai[out + 1].astype(np.int64)
            own = np.repeat(starts - np.cumsum(np.concatenate([[0], (ends - starts)[:-1]])),
                            ends - starts) + np.arange(int((ends - starts).sum()))
            hit = np.union1d(own, np.flatnonzero(taken[aj]))
            rows = np.searchsorted(ai, hit, side="right") - 1
            self.kind[hit] = np.where(rows == aj[hit], 2, 1)

    @classmethod
    def plan(cls, ai, aj, bs, direction, out=()):
        """The ChainLU of that pattern, or None when its elimination in that direction would
        fill (or a row has no diagonal block, or the kernel is not built).  ``out``: block
        rows taken out of the system (their rows and columns the identity's at every
        factorisation: a separator's, schur.py)."""
        fns = _load()
        if not fns or not 1 <= bs <= MAX_BS:
            return None
        plan = fns.plan
        ai = np.ascontiguousarray(ai, dtype=I32)
        aj = np.ascontiguousarray(aj, dtype=I32)
        n = len(ai) - 1
        diag = np.empty(n, dtype=I32)
        count = plan(n, ai, aj, int(direction), diag, None, 0)
        if count < 0:
            return None
        target = np.empty(max(count, 1), dtype=I32)
        plan(n, ai, aj, int(direction), diag, target.ctypes.data, count)
        return cls(ai, aj, bs, int(direction), diag, target[:count], out)

    def order_position(self, rows):
        """Where the block rows ``rows`` come in the order of elimination (and the rows at the
        order positions ``rows``: the map is its own inverse)."""
        rows = np.asarray(rows)
        return rows if self.dir > 0 else self.n - 1 - rows

    @logged("ChainFactor")
    def factor(self, mat=None, values=None, inertia=False):
        """Factor the values of the SeqBAIJ ``mat`` (or the array ``values``, blocks column by
        column), the rows taken out made the identity's (the matrix itself unchanged: each
        row is copied as its turn comes; ``stale`` and False where ``mat`` no longer has the
        planned pattern).  With ``inertia`` (a symmetric matrix): ``negative``
        the number of its negative eigenvalues, the sum over the pivot blocks' (H = L D L^T, a
        congruence; each block's by its own LDL^T with Bunch-Kaufman pivoting).  Returns
        False at a singular diagonal block (``failed_row``: its row)."""
        fns = _load()
        self.stale = False
        if mat is not None and (mat.getBlockSize() != self.bs or mat.getInfo(
                PETSc.Mat.InfoType.LOCAL)["nz_used"] != self.values.size):
            # not the pattern planned for (a block inserted since): nothing read; the caller
            # plans anew
            self.stale = True
            self.failed_row = self.negative = None
            return False
        neg = ctypes.c_int(0)
        count = ctypes.addressof(neg) if inertia else None

        def run(source):
            return fns.factor(self.n, self.bs, self.ai, self.place, self.lofs, self.uofs,
                              self.col, self.dir, self.target, source, self.kind, self.values,
                              count)
        if mat is not None:
            with petsc_lib.values_of(mat) as ptr:
                code = run(ptr)
        else:
            values = np.ascontiguousarray(values, dtype=np.float64)
            if values.shape != self.values.shape:
                raise ValueError(f"{values.shape} values: {self.values.shape} expected")
            code = run(values.ctypes.data)
        self.failed_row = None if code == 0 else code - 1
        self.negative = neg.value if inertia and code == 0 else None
        return code == 0

    @logged("ChainSolve")
    def solve(self, x, first=0, last=0):
        """x <- A^-1 x in place (x: n bs values, contiguous), restricted: the forward
        substitution over the order positions first..n-1, the backward one over n-1..last
        (first = n: none; last = n: none)."""
        _load().solve(self.n, self.bs, self.lofs, self.uofs, self.col, self.dir, self.values,
                      int(first), int(last), x)
        return x


class ChainPC:
    """The python PC context of the Newton step's LU on one rank where the Jacobian is a chain
    that its own node order eliminates without fill (an open rod without contact:
    linear.use_chain_lu): ChainLU's factorisation at every set-up (each new set of values),
    one forward and one backward substitution an application.  Against PETSc's own LU in the
    same order (the blocks' arithmetic alike, no pivoting between blocks), the planar
    cantilever's in-plane Jacobian at 10^4 cubic elements: 2.8 against 5.2 ms a
    factorisation, 0.67 ms a solve either way; at 10^5 31 against 55 ms.  A singular pivot
    block fails the PC as PETSc's LU at its zero pivot does (petsc_lib.set_pc_failed: the KSP
    says DIVERGED_PCSETUP_FAILED and its solution is Inf) and makes the application NaN.  A
    matrix of another pattern is planned anew; one whose elimination would fill (never an open
    rod's without contact) is factored by PETSc's LU instead."""

    def __init__(self, problem, A=None):
        """For the matrices of ``problem`` (its count of new patterns: its stats, not the
        problem, kept), planned for A if given (``lu`` None: A is no chain)."""
        self.stats = problem.stats
        self.lu = None if A is None else plan_of(A)
        self.key = None if A is None else self.matrix_key(A)    # the matrix lu was planned for
        self.fallback = None            # PETSc's LU, AMD-ordered (a pattern that fills)
        self.failed = False

    def create(self, pc):
        petsc_exit.live(pc)

    def destroy(self, pc):
        petsc_exit.gone(pc)
        self.reset(pc)

    def matrix_key(self, A):
        """What makes a plan stale: the problem's count of new patterns (a new matrix may sit at
        a freed one's address), the matrix's handle and PETSc's nonzero state (a pattern
        changed in place)."""
        return (self.stats.get("pattern_refreshes", 0), A.handle, petsc_lib.nonzero_state(A))

    def reset(self, pc):
        """KSPReset / PCReset: nothing of the old matrices kept."""
        if self.fallback is not None:
            self.fallback.destroy()
            self.fallback = None
        self.lu = self.key = None
        self.failed = False

    def plan(self, pc):
        """The plan for the PC's matrix (its pattern alone), unless made for it already; a
        solver's set-up makes it before the matrix has values (linear.set_up_ahead)."""
        A = pc.getOperators()[1]
        key = self.matrix_key(A)
        if key != self.key:             # another matrix or pattern: planned anew
            self.reset(pc)
            self.lu, self.key = plan_of(A), key

    def setUp(self, pc):
        A = pc.getOperators()[1]
        self.plan(pc)
        if self.lu is None:
            if self.fallback is None:
                self.fallback = PETSc.PC().create(comm=A.getComm())
                self.fallback.setType(PETSc.PC.Type.LU)
                self.fallback.setFactorSolverType("petsc")
                self.fallback.setFactorOrdering("amd")
            self.fallback.setOperators(*pc.getOperators())
            self.fallback.setUp()
            return
        ok = self.lu.factor(A)
        if self.lu.stale:               # blocks inserted since: plan anew
            self.key = None
            self.setUp(pc)
            return
        self.failed = not ok
        petsc_lib.set_pc_failed(pc, self.failed)

    def view(self, pc, viewer):
        """What -ksp_view prints for this PC."""
        if self.fallback is not None:
            viewer.printfASCII("  rodsnes' chain LU: the pattern fills, PETSc's LU instead\n")
            self.fallback.view(viewer)
        elif self.lu is not None:
            viewer.printfASCII(f"  rodsnes' chain LU (rodsnes/solve/chain.py): {self.lu.n} block "
                               f"rows of size {self.lu.bs}, the rod's node order, no fill"
                               f"{', FAILED at a singular pivot block' if self.failed else ''}\n")

    def apply(self, pc, x, y):
        if self.fallback is not None:
            self.fallback.apply(x, y)
            return
        if self.failed:
            y.set(np.nan)
            return
        x.copy(y)
        with y as a:
            self.lu.solve(a)
