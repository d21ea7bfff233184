"""Element tangents added straight into the value array of a block matrix.

MatSetValuesBlocked finds every block of every element by a search in its row and, in
parallel, checks each one's ownership; with the Python around each call (the Dirichlet mask's
and the ownership's runs, partition.py) that was a seventh of the Jacobian.  The places of the
element blocks in the matrix's block CSR do not change while its pattern stays: ElementBlocks
finds them once (per pattern of the matrix) and a C loop (_assembly_kernel.c) adds a chunk of
element tangents at those places.  10^4 cubic elements, serial, fastest of five (27 Nov
2026): the planar step's in-plane Jacobian 11.8 -> 10.2 ms, the 3-D Jacobian 34.2 -> 31.2
ms, their Hessians (SBAIJ) 10.0 -> 9.4 and 29.1 -> 27.5 ms.

Used for the elastic tangents of RodProblem.jacobian where the matrix is BAIJ or SBAIJ with
blocks of a node's unknowns (the 3-D matrix, block size 6; a component block of the planar
step and its Hessian, block size 3) or of its position and rotation (a split matrix, block
size 3: a group of k nodes is 2k blocks).  The groups that touch a constrained node (their
Dirichlet rows and columns are masked: partition.DirichletRows) or a node of another rank go
in through the matrix's own insertion as before; an SBAIJ matrix keeps its upper blocks alone
(as IGNORE_LOWER_TRIANGULAR does).  Without the compiled kernel and for AIJ matrices nothing
changes (``element_blocks`` returns None).
"""
import collections
import ctypes

import numpy as np
from petsc4py import PETSc

from rodsnes import compiled, petsc_lib
from rodsnes.model.partition import any_column, is_split, split_index

I32 = compiled.I32           # the places: block indices of one rank's block CSR
ATTR = "rodsnes_element_blocks"     # the ElementBlocks kept on their matrix (PetscObjectCompose)
_TYPES = {PETSc.Mat.Type.SEQBAIJ: False, PETSc.Mat.Type.MPIBAIJ: False,
          PETSc.Mat.Type.SEQSBAIJ: True, PETSc.Mat.Type.MPISBAIJ: True}   # type -> upper only


# the kernel's C entries by name (compiled.Foreign each)
Kernel = collections.namedtuple("Kernel", "add places")


def _declare(lib):
    add = compiled.Foreign(lib.rodsnes_add_element_blocks,
                           [ctypes.c_void_p, I32, compiled.F64, ctypes.c_int64,
                            ctypes.c_int, ctypes.c_int], ctypes.c_int)
    places = compiled.Foreign(lib.rodsnes_element_places,
                              [ctypes.c_int64, ctypes.c_int, compiled.I64, compiled.I8,
                               ctypes.c_int64, I32, I32, ctypes.c_int, I32, compiled.I8,
                               compiled.I8], ctypes.c_int64)
    return Kernel(add, places)


_load = compiled.loader("rodsnes.model._assembly_kernel", _declare)


def available():
    """True when the compiled kernel is built and loads."""
    return bool(_load())


def value_matrix(mat):
    """(seq, info, key) of the sequential matrix whose value array holds this rank's rows of
    ``mat`` (mat itself, or on several ranks its diagonal block, the ownership square): its
    local MatInfo and the key of its pattern - the value matrix itself (its handle: what is
    kept on mat holds no wrapper), PETSc's nonzero state, and the stored entries (in PETSc
    3.18 a new nonzero of a BAIJ matrix leaves the state as it was).  None where there is no
    such value array."""
    parallel = mat.getComm().getSize() > 1
    if parallel and mat.getOwnershipRange() != mat.getOwnershipRangeColumn():
        return None
    seq = mat.getDiagonalBlock() if parallel else mat
    if not petsc_lib.has_value_array(seq):
        return None
    info = seq.getInfo(PETSc.Mat.InfoType.LOCAL)
    return seq, info, (seq.handle, petsc_lib.nonzero_state(seq), info["nz_used"])


def element_blocks(mat, dirichlet, groups, size):
    """The ElementBlocks of the node groups ``groups`` (n, k) (global PETSc node numbers) in
    ``mat``, the matrix under ``dirichlet`` (partition.DirichletRows: the groups touching its
    ``touched`` nodes go in through it), ``size`` unknowns a node in the tangents; kept on the
    matrix while its pattern stays.  None where it does not apply (module docstring)."""
    kind = mat.getType()
    split = is_split(mat)       # a node's position and rotation in blocks 2n, 2n + 1 of 3
    if kind not in _TYPES or not available() or \
            mat.getBlockSize() * (2 if split else 1) != size:
        return None
    values = value_matrix(mat)
    if values is None:
        return None
    seq, info, state = values
    if info["nz_allocated"] >= 2 ** 31:         # beyond the places' int32
        return None
    kept = mat.getAttr(ATTR)
    if kept is not None and kept.fits(groups, dirichlet.touched, state):
        return kept
    out = ElementBlocks(mat, seq, groups, dirichlet.touched, split, _TYPES[kind], state)
    if not out.complete:
        # a group's block outside the pattern: its insertion would allocate, move the value
        # array's blocks and leave the places of the chunks after it stale - the matrix's way
        # for all (never so for the preallocated element couplings of create_matrix)
        return None
    mat.setAttr(ATTR, out)
    return out


class ElementBlocks:
    """The places of the blocks of the node groups ``groups`` in the value array of ``seq``
    (the matrix, or its diagonal block on several ranks) for the groups whose nodes are all
    this rank's and none is ``touched``; the others (``rest``) are the caller's to insert.
    Of a split matrix a group of k nodes is one of 2k blocks (position, rotation of each)."""

    def __init__(self, mat, seq, groups, touched, split, upper, state):
        # seq's handle and type, not seq: kept in mat's attributes, a wrapper of it would make
        # a cycle the garbage collector clears (petsc_lib.values_at)
        self.seq = (seq.handle, seq.getType())
        self.groups, self.touched, self.state = groups, touched, state
        bs = mat.getBlockSize()
        lo, hi = (r // bs for r in mat.getOwnershipRange())
        G = np.asarray(groups, dtype=np.int64)
        B = np.asarray(split_index(G) if split else G, dtype=np.int64)   # the matrix's blocks
        n, k = B.shape
        direct = ~any_column((B < lo) | (B >= hi)) & ~any_column(touched[G])
        L = np.ascontiguousarray(B - lo)
        ai, aj = seq.getRowIJ(compressed=True)      # the block CSR (columns sorted in a row)
        self.rest = np.flatnonzero(~direct)
        self.rest_plan = None        # RodProblem._add_rest_tangents' (RestElements)
        self.bs, self.k = bs, k
        self.nblocks = len(aj)
        # the places; the first addition into each block, in the order (group, row, column)
        # the kernels add (a store there: zero_rest); the blocks no direct group holds
        places = _load().places if available() else None
        if places is not None:
            # one pass with a search in each block's row: 0.5 ms at 10^4 planar elements,
            # where numpy's search over every block's code took 7-10 ms
            self.pos = np.empty((n, k, k), dtype=I32)
            self.first = np.empty((n, k, k), dtype=np.int8)
            seen = np.zeros(len(aj), dtype=np.int8)
            missing = places(n, k, L, direct.astype(np.int8), len(ai) - 1,
                             np.ascontiguousarray(ai, dtype=I32),
                             np.ascontiguousarray(aj, dtype=I32), int(upper), self.pos,
                             self.first, seen)
            self.complete = missing == 0
            self.untouched = np.flatnonzero(seen == 0)
            return
        self._places_numpy(L, direct, ai, aj, max(hi - lo, 1), upper)

    def _places_numpy(self, L, direct, ai, aj, ncol, upper):
        """What rodsnes_element_places does (_assembly_kernel.c), with numpy."""
        n, k = L.shape
        rows = np.broadcast_to(L[:, :, None], (n, k, k))
        cols = np.broadcast_to(L[:, None, :], (n, k, k))
        ai, aj = np.asarray(ai, dtype=np.int64), np.asarray(aj, dtype=np.int64)
        codes = np.repeat(np.arange(len(ai) - 1), np.diff(ai)) * ncol + aj
        want = np.where(direct[:, None, None], rows * ncol + cols, -1)
        pos = np.searchsorted(codes, want).clip(0, max(len(codes) - 1, 0))
        found = (codes[pos] == want) if len(codes) else np.zeros(want.shape, dtype=bool)
        pos = np.where(found, pos, -1)
        if upper:       # SBAIJ: the upper blocks alone
            found |= rows > cols
            pos = np.where(rows > cols, -1, pos)
        self.complete = bool(found.all(axis=(1, 2))[direct].all())    # every block in place
        self.pos = np.where(direct[:, None, None], pos, -1).astype(I32)
        flat = self.pos.ravel()
        held = np.flatnonzero(flat >= 0)
        used, at = np.unique(flat[held], return_index=True)
        first = np.zeros(flat.shape, dtype=np.int8)
        first[held[at]] = 1
        self.first = first.reshape(self.pos.shape)
        self.untouched = np.setdiff1d(np.arange(len(aj)), used, assume_unique=True)

    def fits(self, groups, touched, state):
        """Whether these places hold for ``groups`` and ``touched`` at the pattern ``state``."""
        return (state == self.state and groups is self.groups
                and np.array_equal(touched, self.touched))

    def zero_rest(self, mat):
        """Zero what the direct groups' first additions (``first``: stores) do not set: this
        rank's blocks no direct group holds and, on several ranks, the off-diagonal part; the
        rest of the matrix is left as it is (its first additions overwrite it): MatZeroEntries
        without the sweep over every value.  Only with every direct group's tangent added
        after, by a kernel that stores at ``first`` (ElasticRod.tangents_into).  False (nothing
        done) where the matrix's type has no such way (the caller zeroes it all)."""
        kind = mat.getType()
        if kind not in (PETSc.Mat.Type.SEQBAIJ, PETSc.Mat.Type.SEQSBAIJ,
                        PETSc.Mat.Type.MPIBAIJ):
            return False
        if kind == PETSc.Mat.Type.MPIBAIJ:
            diag, off = ctypes.c_void_p(), ctypes.c_void_p()
            petsc_lib.call("MatMPIBAIJGetSeqBAIJ", mat.handle, ctypes.byref(diag),
                           ctypes.byref(off), None)
            if diag.value != self.seq[0]:
                return False
            petsc_lib.call("MatZeroEntries", off)
        if not len(self.untouched):     # (a rank owning no node has no values at all)
            return True
        b2 = self.bs * self.bs
        with self.values() as ptr:
            values = np.ctypeslib.as_array((ctypes.c_double * (self.nblocks * b2))
                                           .from_address(ptr)).reshape(self.nblocks, b2)
            values[self.untouched] = 0.0
        return True

    def values(self):
        """The address of the matrix's value array, as a context (petsc_lib.values_at): for
        the kernels that add at ``pos`` themselves (elastic_compiled.tangents_into)."""
        return petsc_lib.values_at(*self.seq)

    def add(self, a, b, V, insert):
        """Add the tangents V (b - a, k bs, k bs) of groups a..b - 1: the direct ones into the
        value array, then insert(i) for the others (i: their indices in a..b - 1, minus a)."""
        V = np.ascontiguousarray(V, dtype=np.float64)
        kb = self.k * self.bs
        if V.shape != (b - a, kb, kb) or not 0 <= a <= b <= len(self.pos):
            raise ValueError(f"tangents {V.shape} for groups {a}..{b}: ({b - a}, {kb}, {kb}) "
                             "expected")
        with petsc_lib.values_at(*self.seq) as ptr:
            if _load().add(ptr, self.pos[a:b], V, b - a, self.k, self.bs):
                raise ValueError(f"block size {self.bs}: the assembly kernel has 3 and 6")
        lo, hi = np.searchsorted(self.rest, (a, b))
        if hi > lo:
            insert(self.rest[lo:hi] - a)


DIAGONAL_ATTR = "rodsnes_diagonal_places"   # set_diagonal's places, kept on their matrix


def set_diagonal(mat, d, add):
    """The diagonal of ``mat`` set to the entries of the Vec ``d`` (``add``: increased by
    them), as MatDiagonalSet with INSERT_VALUES or ADD_VALUES, the same numbers bit for bit;
    collective (the matrix is assembled after).  A BAIJ or SBAIJ matrix's diagonal entries are
    written in its value array (its diagonal block's on several ranks), at places found once
    per pattern: PETSc 3.18 has no MatDiagonalSet of these types and inserts entry by entry
    (3.4 ms for the in-plane Jacobian of 10^4 cubic elements, twice a shifted solve of the
    minimiser).  Other types, an unassembled matrix, or a row without its diagonal block:
    MatDiagonalSet.  The places are kept while the value matrix, its nonzero state and its
    stored blocks stay, as ElementBlocks' are: a pattern that changes in place keeping all
    three would go unseen, and rodsnes changes none in place (a new pattern is a new matrix,
    RodProblem._new_matrix)."""
    places = _diagonal_places(mat) if mat.isAssembled() else None
    if places is None:
        mat.setDiagonal(d, addv=PETSc.InsertMode.ADD_VALUES if add
                        else PETSc.InsertMode.INSERT_VALUES)
        return
    (handle, kind, nvalues), pos = places
    v = d.getArray(readonly=True)
    if len(v) != len(pos):
        raise ValueError(f"a diagonal of {len(v)} entries for {len(pos)} rows")
    if len(pos):
        with petsc_lib.values_at(handle, kind) as ptr:
            values = np.ctypeslib.as_array((ctypes.c_double * nvalues).from_address(ptr))
            if add:
                values[pos] += v
            else:
                values[pos] = v
    mat.assemble()


def _diagonal_places(mat):
    """((handle, type, values) of the value matrix, the places of the diagonal entries of
    this rank's rows in its value array) for set_diagonal, kept on ``mat`` while its pattern
    stays; None where they cannot be used."""
    values = value_matrix(mat) if mat.getType() in _TYPES else None
    if values is None:
        return None
    seq, _, key = values
    kept = mat.getAttr(DIAGONAL_ATTR)
    if kept is not None and kept[0] == key:
        return kept[1]
    bs = seq.getBlockSize()
    ai, aj = seq.getRowIJ(compressed=True)      # the block CSR
    n = len(ai) - 1
    rows = np.repeat(np.arange(n), np.diff(ai))
    at = np.flatnonzero(aj == rows)
    if len(at) != n or seq.getLocalSize()[0] != n * bs:
        return None
    # each block bs x bs, column by column: its diagonal at i (bs + 1)
    pos = (at[:, None] * (bs * bs) + np.arange(bs) * (bs + 1)).ravel()
    out = ((seq.handle, seq.getType(), len(aj) * bs * bs), pos)
    mat.setAttr(DIAGONAL_ATTR, (key, out))
    return out
