"""Distribution of a rod over MPI ranks: METIS over the element graph, node ownership,
PETSc numbering, ghost nodes, scatters and the Jacobian's block sparsity.

Element graph: element e is adjacent to e-1 and e+1 (and across the wrap of a closed rod);
pymetis partitions it (PETSc's Debian build has no METIS).  A node is owned by the rank of
the lowest-numbered element that contains it.  PETSc numbering: nodes sorted by owner, so each
rank owns a contiguous range, and within a rank by natural id (descending where the rank's
stretch meets the others at its first element alone: stretch_descends).  Row elements = the
owned elements, then the other ranks' that hold an owned node (owner computes: RodProblem).
Local nodes = owned nodes, then ghosts (nodes of the row elements owned elsewhere).  Every rank
keeps the O(n) maps
natural <-> PETSc (a rod has at most millions of nodes: cheap, and it keeps contact-pair
bookkeeping simple).
"""
import numpy as np
import scipy.sparse as sp
from mpi4py import MPI
from petsc4py import PETSc

from rodsnes.errors import SceneError

NDOF = 6  # per node: position r (3), rotation increment theta (3)


def allreduce(comm, value, op=MPI.SUM):
    """comm.allreduce(value, op=op) on an mpi4py communicator of several ranks; on one rank
    ``value`` itself, which is what the allreduce gives there (a collective skipped where
    nobody is to meet: the contact term's flags and the mounts' end values are asked for at
    every evaluation)."""
    return value if comm.size == 1 else comm.allreduce(value, op=op)


def metis_parts(nelem, closed, nparts):
    """Element -> rank with pymetis over the chain graph (contiguous pieces)."""
    if nparts == 1:
        return np.zeros(nelem, dtype=np.int64)
    if nelem < nparts:
        raise SceneError(f"-rod_nelem = {nelem} is smaller than the number of ranks {nparts}: "
                         f"use at least {nparts} elements or fewer ranks", ("-rod_nelem",))
    import pymetis
    xadj, adj = chain_graph(nelem, closed)
    _, parts = pymetis.part_graph(nparts, adjacency=pymetis.CSRAdjacency(
        adj_starts=xadj, adjacent=adj))
    parts = np.asarray(parts, dtype=np.int64)
    if len(np.unique(parts)) < nparts:  # METIS may leave a rank empty on tiny graphs
        parts = (np.arange(nelem) * nparts) // nelem
    return parts


def chain_graph(nelem, closed):
    """(xadj, adj): the elements' adjacency, each element's neighbours k - 1 and k + 1 (modulo
    nelem on a closed rod) in CSR, every row sorted and without repeats or the element itself."""
    k = np.arange(nelem)
    nb = np.stack([k - 1, k + 1], axis=1)
    if closed:
        nb = np.sort(nb % max(nelem, 1), axis=1)
        keep = nb != k[:, None]
        keep[:, 1] &= nb[:, 1] != nb[:, 0]        # two elements: one neighbour, not twice
    else:
        keep = (nb >= 0) & (nb < nelem)
    xadj = np.concatenate([[0], np.cumsum(keep.sum(axis=1))])
    return xadj, nb[keep]


def stretch_descends(elem_owner, closed, nranks):
    """Per rank, whether PETSc numbers its nodes against the rod's order: where its stretch
    (its elements, first to last) meets the other ranks' at its first element only (the
    second of two ranks on an open rod), so that every rank's stretch runs toward the nodes it
    shares.  The Schur condensation of several ranks (solve/schur.py) eliminates each
    stretch's interior toward the separator by the chain LU (solve/chain.py), which then reads
    the matrix forward in memory, as on one rank: eliminated backward, the same stretch's LU
    took 8 % longer alone and up to 1.8 x as long with the other rank streaming beside it
    (the planar cantilever at 10^4 elements on 2 ranks), the other rank waiting for it in the
    reduction.  A closed rod's stretches and the middle ones meet others at both ends: in the
    rod's order."""
    out = np.zeros(nranks, dtype=bool)
    if closed or nranks < 2:
        return out
    ne = len(elem_owner)
    ids = np.arange(ne)
    first = np.full(nranks, ne)
    last = np.full(nranks, -1)
    np.minimum.at(first, elem_owner, ids)
    np.maximum.at(last, elem_owner, ids)
    return (first > 0) & (last == ne - 1)


def preallocate_blocks(mat, ai, aj):
    """MatSetPreallocationCSR of a BAIJ or SBAIJ matrix with the block CSR (ai, aj): every
    block present, an explicit zero.  A sequential matrix takes each block row in one
    insertion, column-oriented meanwhile (of zeros the order is immaterial), where PETSc inserts
    a row-oriented matrix's blocks one at a time (the in-plane matrix of 10^4 cubic elements:
    3.7 -> 2.5 ms); an MPI type, on one rank too (-mat_type mpibaij), cannot take the option
    before its blocks exist (MPIBAIJ's MatSetOption reaches into them: a segmentation fault)."""
    sequential = mat.getType() in (PETSc.Mat.Type.SEQBAIJ, PETSc.Mat.Type.SEQSBAIJ)
    if sequential:
        mat.setOption(PETSc.Mat.Option.ROW_ORIENTED, False)
    mat.setPreallocationCSR((ai, aj))
    if sequential:
        mat.setOption(PETSc.Mat.Option.ROW_ORIENTED, True)


def group_pairs(groups):
    """(rows, cols): every ordered pair of nodes within each group of ``groups`` (a list of
    (m, k) node arrays coupled all-to-all), concatenated; duplicates kept."""
    rows = [np.repeat(g, g.shape[1], axis=1).ravel() for g in groups]
    cols = [np.tile(g, (1, g.shape[1])).ravel() for g in groups]
    return np.concatenate(rows), np.concatenate(cols)


class Layout:
    """Owned/ghost nodes of this rank, PETSc numbering and the communication objects."""

    def __init__(self, comm, mesh, parts=None):
        self.comm = comm
        rank, size = comm.getRank(), comm.getSize()
        self.mesh = mesh
        ne, n = mesh.nelem, mesh.n_nodes
        self.elem_owner = metis_parts(ne, mesh.closed, size) if parts is None else np.asarray(parts)
        first_elem = np.full(n, ne, dtype=np.int64)
        np.minimum.at(first_elem, mesh.conn.ravel(), np.repeat(np.arange(ne), mesh.conn.shape[1]))
        self.node_owner = self.elem_owner[first_elem]
        # sorted by (owner, id), or (owner, -id) on the ranks whose stretch meets the others
        # at its first element alone (stretch_descends)
        ids = np.arange(n)
        key = np.where(stretch_descends(self.elem_owner, mesh.closed, size)[self.node_owner],
                       -ids, ids)
        order = np.lexsort((key, self.node_owner))
        self.nat2petsc = np.empty(n, dtype=np.int64)
        self.nat2petsc[order] = np.arange(n)
        self.petsc2nat = order
        counts = np.bincount(self.node_owner, minlength=size)
        self.starts = np.concatenate([[0], np.cumsum(counts)])
        self.owned_elems = np.flatnonzero(self.elem_owner == rank)
        self.owned_nodes = order[self.starts[rank]:self.starts[rank + 1]]   # natural ids
        # owner computes: the rows of an owned node are summed on this rank from every element
        # holding it, its own and the other ranks' that touch it (``row_elems``: the owned
        # elements, then those), so no rank sends another its partial rows (no reverse
        # scatter of the residual, no stash of the Jacobian: RodProblem)
        holds = np.zeros(n, dtype=bool)
        holds[self.owned_nodes] = True
        halo = np.flatnonzero((self.elem_owner != rank) & holds[mesh.conn].any(axis=1))
        self.row_elems = np.concatenate([self.owned_elems, halo])
        touched = np.unique(mesh.conn[self.row_elems].ravel())
        ghosts = np.setdiff1d(touched, self.owned_nodes)
        self.ghost_nodes = ghosts[np.argsort(self.nat2petsc[ghosts])]
        self.local_nodes = np.concatenate([self.owned_nodes, self.ghost_nodes])  # natural ids
        self.n_owned = len(self.owned_nodes)
        nat2local = np.full(n, -1, dtype=np.int64)
        nat2local[self.local_nodes] = np.arange(len(self.local_nodes))
        self.nat2local = nat2local
        self.lconn = nat2local[mesh.conn[self.owned_elems]]
        self.gconn = self.nat2petsc[mesh.conn[self.owned_elems]]   # PETSc block ids
        self.row_lconn = nat2local[mesh.conn[self.row_elems]]       # the same of row_elems
        self.row_gconn = self.nat2petsc[mesh.conn[self.row_elems]]
        # row_gconn with -1 at the nodes of other ranks: the block rows this rank sets
        # (MatSetValues ignores a negative row)
        self.row_rows = np.where(self.row_lconn < self.n_owned, self.row_gconn, -1)
        self.n_global = n
        # vectors and the scatter global -> local (owned + ghost)
        self.x = self.create_vec()
        self.xlocal = PETSc.Vec().createSeq(NDOF * len(self.local_nodes), bsize=NDOF, comm=PETSc.COMM_SELF)
        is_from = PETSc.IS().createBlock(NDOF, self.nat2petsc[self.local_nodes].astype(PETSc.IntType),
                                         comm=PETSc.COMM_SELF)
        self.scatter = PETSc.Scatter().create(self.x, is_from, self.xlocal, None)

    def natural_rows(self, nrows):
        """The natural index (node n, unknown c: n k + c, k = nrows / n_owned unknowns a node)
        of each of this rank's ``nrows`` rows of a vector or matrix over its owned nodes, in
        PETSc's order: one unknown has one number on any number of ranks (a seed drawn from
        it is the same vector however the rod is shared)."""
        k = nrows // max(self.n_owned, 1)
        return (self.owned_nodes[:, None] * k + np.arange(k)).ravel()

    def create_vec(self):
        v = PETSc.Vec().createMPI((NDOF * self.n_owned, NDOF * self.n_global), bsize=NDOF, comm=self.comm)
        v.set(0.0)
        return v

    def to_local(self, X):
        """Owned + ghost values of a global vector, as an (n_local, 6) array (a copy)."""
        return self.local_view(X).copy()

    def local_view(self, X):
        """Owned + ghost values of a global vector, as an (n_local, 6) read-only view of the
        layout's local vector: valid until its next scatter (to_local, add_to_global)."""
        self.scatter.scatter(X, self.xlocal, addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        return self.xlocal.getArray(readonly=True).reshape(-1, NDOF)

    def add_to_global(self, local, F):
        """F += sum over ranks of local (n_local, 6) contributions (reverse scatter-add)."""
        self.xlocal.setArray(np.ascontiguousarray(local, dtype=float).ravel())
        self.scatter.scatter(self.xlocal, F, addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)

    def coupled_groups(self, extra_pairs=None, elems=None):
        """The natural node groups a matrix of this layout couples all-to-all: the elements'
        nodes (``elems``: these elements only) and ``extra_pairs`` ((m, k) natural node ids,
        e.g. the nodes of a contact element pair; None or empty for none)."""
        groups = [self.mesh.conn if elems is None else self.mesh.conn[elems]]
        if extra_pairs is not None and len(extra_pairs):
            groups.append(np.asarray(extra_pairs))
        return groups

    def block_pattern(self, extra_pairs=None):
        """The block nonzero structure of the owned block rows: element coupling + extra node
        groups (coupled_groups), as CSR (ai: offsets per owned block row, aj: global PETSc
        block columns, sorted).  The elements are the row elements (every element holding an
        owned node): the pattern of the whole rod's would be the same rows, at the cost of all
        of them on every rank (2.2 ms of the in-plane matrix's 5.1 on each of 2 ranks at 10^4
        elements)."""
        rows, cols = group_pairs(self.coupled_groups(extra_pairs, elems=self.row_elems))
        r, c = self.nat2petsc[rows], self.nat2petsc[cols]
        rank = self.comm.getRank()
        lo, hi = self.starts[rank], self.starts[rank + 1]
        keep = (r >= lo) & (r < hi)
        # the distinct pairs row by row, columns sorted: scipy's COO -> CSR with its duplicates
        # summed (per-row sorts in C++), where numpy's unique of the pairs' codes sorted them
        # all (10^4 cubic elements on one rank: 0.75 against 3.8 ms in isolation, the whole
        # block pattern 2.0 against 2.95 ms in a run)
        ones = np.ones(int(keep.sum()), dtype=np.int32)
        pattern = sp.coo_matrix((ones, (r[keep] - lo, c[keep])),
                                shape=(hi - lo, self.n_global)).tocsr()
        pattern.sum_duplicates()
        return pattern.indptr.astype(PETSc.IntType), pattern.indices.astype(PETSc.IntType)

    def create_matrix(self, extra_pairs=None, symmetric=False, positions_only=False):
        """MPIBAIJ (block size 6; -mat_type overrides) with the exact block structure of the
        element coupling and the extra node groups, every entry present (explicit zeros).
        symmetric=True: MPISBAIJ, the upper block triangle only (values set below the
        diagonal are ignored), for a symmetric matrix factored by LDL^T (MUMPS Cholesky
        cannot take BAIJ).

        ``positions_only`` (the extra groups couple the nodes' positions only: contact, unless
        -mat_type is given): a split matrix, block size 3, node n's position in block 2n and
        its rotation in 2n + 1 (SplitBlocks, which DirichletRows inserts through), where the
        extra groups' blocks between nodes that no element couples are the 3 x 3 position
        blocks alone.  A contact block of block size 6 is three quarters zeros, which the
        factorisations carry along: on the plectoneme's Jacobian (1086 dofs, 1900 contact
        blocks) PETSc's LU took 1.6-1.9 ms with block size 6, 0.60-0.67 ms split; MUMPS's
        LDL^T of the Hessian 4.3 ms against 2.1 ms over a run.

        Present, not merely preallocated: the first assembly squeezes out preallocated slots
        that hold no value, so contact blocks that are zero at that moment would need mallocs
        later, and on PETSc 3.18 a new off-diagonal block inserted into an assembled MPIBAIJ
        lands in a wrong column.  A pattern change therefore takes a new matrix
        (RodProblem._new_matrix), never an in-place re-preallocation."""
        split = positions_only and SPLIT_CONTACT and extra_pairs is not None \
            and len(extra_pairs) > 0 and not PETSc.Options().hasName("mat_type")
        bs = 3 if split else NDOF
        J = PETSc.Mat().create(comm=self.comm)
        J.setSizes(((NDOF * self.n_owned, NDOF * self.n_global),) * 2, bsize=bs)
        J.setType(PETSc.Mat.Type.SBAIJ if symmetric else PETSc.Mat.Type.BAIJ)
        J.setBlockSize(bs)
        J.setFromOptions()
        if symmetric and J.getType() in (PETSc.Mat.Type.SEQBAIJ, PETSc.Mat.Type.MPIBAIJ):
            # -mat_type baij asks for block storage: of a symmetric matrix its upper triangle
            # (MUMPS's LDL^T takes no BAIJ matrix: the Hessian's factorisation failed and
            # every shift with it, "no positive definite shift")
            J.setType(PETSc.Mat.Type.SBAIJ)
        ai, aj = self.block_pattern(extra_pairs)
        self.pattern_blocks = int(self.comm.tompi4py().allreduce(int(len(aj))))
        row0 = self.starts[self.comm.getRank()]
        if split:                 # the node blocks as blocks of 3, the block rows from 2 row0
            ae, je = self.block_pattern(None)
            full = np.isin(_block_codes(ai, aj, row0, self.n_global),
                           _block_codes(ae, je, row0, self.n_global))
            ai, aj = _split_csr(ai, aj, full)
            row0 *= 2
            J.setAttr(SPLIT_ATTR, True)
        kind = J.getType()
        if kind in (PETSc.Mat.Type.SEQSBAIJ, PETSc.Mat.Type.MPISBAIJ):
            ai, aj = _upper_blocks(ai, aj, row0)
            preallocate_blocks(J, ai, aj)
            # only once the blocks exist (before it, MPISBAIJ crashes in MatSetOption)
            J.setOption(PETSc.Mat.Option.IGNORE_LOWER_TRIANGULAR, True)
        elif kind in (PETSc.Mat.Type.SEQBAIJ, PETSc.Mat.Type.MPIBAIJ):
            preallocate_blocks(J, ai, aj)
        else:                     # -mat_type aij etc.: expand the block structure to scalars
            J.setPreallocationCSR(_scalar_csr(ai, aj, NDOF))
        J.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, False)
        if symmetric:
            J.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        return J

    def gather_nodes(self, owned_values, root=0):
        """Natural-ordered (n, ...) array of per-owned-node values on ``root`` (None elsewhere)."""
        from mpi4py import MPI
        comm = self.comm.tompi4py()
        ids = comm.gather(self.owned_nodes, root=root)
        vals = comm.gather(np.asarray(owned_values), root=root)
        if comm.rank != root:
            return None
        out = np.empty((self.n_global,) + vals[0].shape[1:], dtype=vals[0].dtype)
        for i, v in zip(ids, vals):
            out[i] = v
        return out

    def allgather_nodes(self, owned_values):
        comm = self.comm.tompi4py()
        ids = comm.allgather(self.owned_nodes)
        vals = comm.allgather(np.asarray(owned_values))
        out = np.empty((self.n_global,) + vals[0].shape[1:], dtype=vals[0].dtype)
        for i, v in zip(ids, vals):
            out[i] = v
        return out


def kept(owner, attr, key, make):
    """make(), kept as ``owner.<attr>`` while the tuple ``key`` holds the same objects (by
    identity: they are held with it, so no other object takes their ids).  For what the
    Jacobian's views derive from the constraints alone (DirichletRows.touched_of,
    planar.component_cut: O(global nodes), 0.3 ms a Jacobian at 10^4 elements on every rank);
    never for a view itself, which holds its matrix: a view kept across Jacobians kept a
    destroyed matrix alive, or held a wrapper destroyed since (a segmentation fault)."""
    old = getattr(owner, attr, None)
    if old is None or len(old[0]) != len(key) or any(a is not b for a, b in zip(old[0], key)):
        old = (tuple(key), make())
        setattr(owner, attr, old)
    return old[1]


class DirichletRows:
    """A matrix seen through Dirichlet rows and columns: every block set through it
    (setValuesBlockedRCV, the one way the terms add their tangents) has the entries of
    constrained rows and columns zeroed first; ``finish`` puts 1 on their diagonal.  The result
    is MatZeroRowsColumns(P, rows, 1) of the sum, built before assembly: bit for bit the same
    entries (a masked entry adds +-0.0 to an entry that zeroEntries left at +0.0: it stays
    +0.0), without the O(nnz) sweep of MatZeroRowsColumns, and also where that operation does
    not exist (MPISBAIJ); it keeps a symmetric matrix symmetric.

    Only the groups that touch a constrained node are copied and masked; the runs of untouched
    groups between them go in as views, in their order (the sums of ADD_VALUES are order
    dependent), so the elastic tangent of 10^4 elements with clamped ends copies two elements.

    mask: (global blocks, 6) bool, True on the constrained dofs (PETSc block numbering)."""

    MAX_RUNS = 32       # more runs of touched groups than this: one masked copy of all of V

    def __init__(self, mat, mask, touched=None):
        self.split = is_split(mat)
        self.raw = mat
        local = OwnBlocksFirst.wrap(mat)
        self.mat, self.mask = (SplitBlocks(local) if self.split else local), mask
        # blocks with a constrained dof (touched_of; O(global nodes): the caller may keep it)
        self.touched = self.touched_of(mask) if touched is None else touched

    @staticmethod
    def touched_of(mask):
        """The blocks of ``mask`` (global blocks, dofs) holding a constrained dof."""
        touched = np.zeros(len(mask), dtype=bool)
        touched[np.flatnonzero(mask.ravel()) // mask.shape[1]] = True
        return touched

    def add_positions(self, R, V, addv=None):
        """Position-only tangents V (n, 3k, 3k) of the node groups R (n, k) (PETSc node
        blocks) into a split matrix (SplitBlocks), the constrained position rows and columns
        zeroed first: as setValuesBlockedRCV, the runs of groups that touch a constrained node
        copied and masked, the others in as views (a copy of all of V whenever one group
        touched a support was two thirds of the contact's insertion on the bench coil)."""
        hit = self._touching(R)
        runs = _runs(hit)
        put = self.mat.add_positions
        if len(runs) > self.MAX_RUNS:
            put(R, self._masked_positions(R, V, hit), addv=addv)
            return
        _by_runs(runs, len(R),
                 lambda a, b: put(R[a:b], self._masked_positions(R[a:b], V[a:b], None),
                                  addv=addv),
                 lambda a, b: put(R[a:b], V[a:b], addv=addv))

    def _masked_positions(self, R, V, hit):
        """A copy of the position tangents V with the constrained position rows and columns
        zeroed (hit: the groups that need it, None for all)."""
        V = np.array(V, copy=True)
        idx = np.flatnonzero(hit) if hit is not None else slice(None)
        n = len(V) if hit is None else len(idx)
        keep = ~self.mask[R[idx]][:, :, 0:3].reshape(n, -1)
        V[idx] *= keep[:, :, None] & keep[:, None, :]
        return V

    def setValuesBlockedRCV(self, R, C, V, addv=None):
        R2, C2 = R.reshape(len(R), -1), C.reshape(len(C), -1)
        hit = self._touching(R2)
        if C is not R:
            hit |= self._touching(C2)
        runs = _runs(hit)       # none in the common case (a chunk away from the supports)
        if len(runs) > self.MAX_RUNS:
            self.mat.setValuesBlockedRCV(R, C, self._masked(R2, C2, V, hit), addv=addv)
            return
        put = self.mat.setValuesBlockedRCV
        _by_runs(runs, len(R),
                 lambda a, b: put(R[a:b], C[a:b], self._masked(R2[a:b], C2[a:b], V[a:b], None),
                                  addv=addv),
                 lambda a, b: put(R[a:b], C[a:b], V[a:b], addv=addv))

    def _touching(self, I2):
        """Which groups (rows of the block ids I2) hold a constrained node (a negative id,
        another rank's row that the matrix ignores, holds none)."""
        if I2.size and I2.min() < 0:
            return (np.take(self.touched, np.maximum(I2, 0)) & (I2 >= 0)).any(axis=1)
        return np.take(self.touched, I2).any(axis=1)

    def _masked(self, R2, C2, V, hit):
        """A copy of the groups V with the constrained rows and columns zeroed (hit: the groups
        that need it, None for all; a negative row's values are the matrix's to ignore)."""
        V = np.array(V, copy=True)
        idx = np.flatnonzero(hit) if hit is not None else slice(None)
        n = len(V) if hit is None else len(idx)
        keep_r = ~self.mask[R2[idx]].reshape(n, -1)
        keep_c = ~self.mask[C2[idx]].reshape(n, -1)
        V[idx] *= keep_r[:, :, None] & keep_c[:, None, :]
        return V

    def finish(self, rows_global):
        """Before assembly: 1 on the diagonal of this rank's constrained rows (global scalar
        indices)."""
        if len(rows_global):
            r = np.asarray(rows_global, dtype=PETSc.IntType)[:, None]
            self.raw.setValuesRCV(r, r, np.ones((len(r), 1, 1)), addv=PETSc.InsertMode.ADD)

    def __getattr__(self, name):
        return getattr(self.mat, name)


class OwnBlocksFirst:
    """A parallel BAIJ or AIJ matrix whose groups of blocks (setValuesBlockedRCV) that lie
    wholly in this rank's own rows and columns go straight into its diagonal block (a SeqBAIJ,
    local indices): MatSetValuesBlocked of the MPI matrix checks every block's row and column
    for ownership and looks the off-diagonal ones up, 5.4 against 3.7 ms for the 3-D elastic
    tangent of 5000 cubic elements a rank (10^4 on 2 ranks).  The other groups go through the
    MPI matrix; runs of both kinds in their order, so every entry gets its additions in the
    same order as through the MPI matrix alone (an owned row's entries are added in place
    there too; the other ranks' rows are stashed and added at assembly either way): the
    same sums bit for bit.  Not for SBAIJ (the lower triangle is dropped by the MPI matrix's
    option) nor on one rank (wrap returns the matrix itself)."""

    def __init__(self, mat):
        self.mat = mat
        self.diag = mat.getDiagonalBlock()
        bs = mat.getBlockSize()
        self.lo, self.hi = (r // bs for r in mat.getOwnershipRange())

    @classmethod
    def wrap(cls, mat):
        """mat seen through OwnBlocksFirst where that applies (a square MPI BAIJ or AIJ matrix
        on several ranks, rows and columns owned alike), else mat."""
        if not isinstance(mat, PETSc.Mat) or mat.getComm().getSize() == 1 or \
                mat.getType() not in (PETSc.Mat.Type.MPIBAIJ, PETSc.Mat.Type.MPIAIJ) or \
                mat.getOwnershipRange() != mat.getOwnershipRangeColumn():
            return mat
        return cls(mat)

    def setValuesBlockedRCV(self, R, C, V, addv=None):
        R2, C2 = R.reshape(len(R), -1), C.reshape(len(C), -1)
        own = ((R2 >= self.lo) & (R2 < self.hi)).all(axis=1)
        if C is not R:
            own &= ((C2 >= self.lo) & (C2 < self.hi)).all(axis=1)
        lo = self.lo
        _by_runs(_runs(own), len(R),
                 lambda a, b: self.diag.setValuesBlockedRCV(R[a:b] - lo, C[a:b] - lo, V[a:b],
                                                            addv=addv),
                 lambda a, b: self.mat.setValuesBlockedRCV(R[a:b], C[a:b], V[a:b], addv=addv))

    def __getattr__(self, name):
        return getattr(self.mat, name)


SPLIT_ATTR = "rodsnes_split_blocks"


def is_split(mat):
    """Whether mat is a split matrix of Layout.create_matrix (block size 3, a node's position
    and rotation in blocks 2n and 2n + 1)."""
    return bool(getattr(mat, "getAttr", None) and mat.getAttr(SPLIT_ATTR))


class SplitBlocks:
    """A split matrix (Layout.create_matrix with positions_only) seen in node blocks of 6:
    setValuesBlockedRCV takes node block indices and (n, 6k, 6k) values, as for block size 6
    (the values of node blocks i, j are those of the 3-blocks 2i, 2i + 1 and 2j, 2j + 1 in
    the same order); add_positions inserts position-only tangents into the position blocks
    alone, without the zeros of a node block's rotation rows and columns."""

    split = True

    def __init__(self, mat):
        self.mat = mat

    def setValuesBlockedRCV(self, R, C, V, addv=None):
        self.mat.setValuesBlockedRCV(split_index(R), split_index(C), V, addv=addv)

    def add_positions(self, R, V, addv=None):
        I = (2 * np.asarray(R)).astype(PETSc.IntType)
        self.mat.setValuesBlockedRCV(I, I, V, addv=addv)

    def __getattr__(self, name):
        return getattr(self.mat, name)


def node_view(mat):
    """mat seen in node blocks of 6 (setValuesBlockedRCV): SplitBlocks of a split matrix,
    else mat itself."""
    return SplitBlocks(mat) if is_split(mat) else mat


def split_index(R):
    """Node blocks (n, k) as the 3-blocks (n, 2k) of their positions and rotations."""
    R = np.asarray(R)
    n = len(R)
    R2 = R.reshape(n, -1)
    return np.stack([2 * R2, 2 * R2 + 1], axis=2).reshape(n, -1).astype(PETSc.IntType)


def any_column(B):
    """B.any(axis=1) of a tall bool array of a few columns (node groups), column by column:
    numpy's reduction along a short last axis is slow (120 us on the (10^4, 4) groups of 10^4
    cubic elements, against 20 us)."""
    out = B[:, 0].copy() if B.shape[1] else np.zeros(len(B), dtype=bool)
    for j in range(1, B.shape[1]):
        out |= B[:, j]
    return out


def _by_runs(runs, n, inside, outside):
    """inside(a, b) on the runs [a, b) of ``runs`` and outside(a, b) on the stretches of
    [0, n) between them, in their order (the sums of ADD_VALUES are order dependent)."""
    start = 0
    for a, b in runs:
        if a > start:
            outside(start, a)
        inside(a, b)
        start = b
    if start < n:
        outside(start, n)


def _runs(hit):
    """The maximal runs [a, b) of True in the bool array hit, as an (m, 2) array."""
    d = np.diff(np.concatenate([[0], hit.view(np.int8), [0]]))
    return np.stack([np.flatnonzero(d == 1), np.flatnonzero(d == -1)], axis=1)


def _upper_blocks(ai, aj, row0):
    """The block CSR (ai, aj) of owned block rows row0, row0 + 1, ... restricted to its upper
    triangle (column >= row)."""
    counts = np.diff(ai)
    rows = row0 + np.repeat(np.arange(len(counts)), counts)
    keep = aj >= rows
    ai = np.concatenate([[0], np.cumsum(np.bincount(rows[keep] - row0, minlength=len(counts)))])
    return ai.astype(PETSc.IntType), aj[keep]


def _block_codes(ai, aj, row0, n):
    """A key per block of the block CSR (ai, aj) of owned block rows row0, row0 + 1, ...:
    row * n + column."""
    rows = row0 + np.repeat(np.arange(len(ai) - 1), np.diff(ai))
    return rows.astype(np.int64) * n + aj


def _split_csr(ai, aj, full):
    """The block CSR (block size 3) of a split matrix from the node block CSR (ai, aj) of
    block size 6: a node block (i, j) where ``full`` is all four 3-blocks (2i + a, 2j + b),
    elsewhere the position block (2i, 2j) alone."""
    counts = np.diff(ai)
    i = np.repeat(np.arange(len(counts)), counts)
    r = np.concatenate([2 * i, 2 * i[full], 2 * i[full] + 1, 2 * i[full] + 1])
    c = np.concatenate([2 * aj, 2 * aj[full] + 1, 2 * aj[full], 2 * aj[full] + 1])
    order = np.lexsort((c, r))
    r, c = r[order], c[order]
    a3 = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=2 * len(counts)))])
    return a3.astype(PETSc.IntType), c.astype(PETSc.IntType)


def _scalar_csr(ai, aj, bs):
    """The scalar CSR (I, J) of a block CSR structure whose blocks are dense bs x bs: scalar
    row i bs + a holds, for each block (i, j) in the order of the block row (sorted here
    where it is not), the columns j bs + 0..bs-1.  Gathers, no sort of the scalar entries
    (the lexsort of 1.35e6 entries took 0.4 s)."""
    ai, aj = np.asarray(ai, dtype=np.int64), np.asarray(aj, dtype=np.int64)
    counts = np.diff(ai)
    row_block = np.repeat(np.arange(len(counts)), counts)
    if len(aj) > 1 and np.any((np.diff(aj) < 0) & (row_block[1:] == row_block[:-1])):
        order = np.lexsort((aj, row_block))
        aj = aj[order]
    cols = (aj[:, None] * bs + np.arange(bs)[None, :]).ravel()      # each block row's columns
    lens = np.repeat(counts * bs, bs)                                 # per scalar row
    starts = np.repeat(ai[:-1] * bs, bs)                              # its block row's first
    ai_s = np.concatenate([[0], np.cumsum(lens)])
    idx = np.arange(ai_s[-1]) - np.repeat(ai_s[:-1] - starts, lens)
    return ai_s.astype(PETSc.IntType), cols[idx].astype(PETSc.IntType)


# the Jacobian of a problem whose extra couplings are positions only (contact) is split
# (Layout.create_matrix)
SPLIT_CONTACT = True
POSITION_CHUNK = 64    # node groups per insertion of add_position_blocks (a 1 MB temporary)


def add_position_blocks(P, layout, nodes, mat):
    """Add (ADD_VALUES) the position-only tangents mat of the natural node groups nodes (n, k)
    into the block matrix P: into a split matrix (Layout.create_matrix: the Jacobian with
    contact) as blocks of 3 in one insertion (SplitBlocks.add_positions, through DirichletRows
    as every tangent); else each 3 x 3 block into the position part of its 6 x 6 block.
    mat: (n, 3k, 3k), rows and columns ordered (node, component), or the same as (n, k, 3, k, 3)
    (any strides: a transposed view is not copied whole).

    Into a matrix of node blocks of 6 the groups go in POSITION_CHUNK at a time, in their
    order, through one reused (chunk, k, 6, k, 6) block whose rotation parts stay zero: the
    same insertions as one dense
    (n, k, 6, k, 6) array, so the same sums bit for bit, without an array 4 x the tangents'
    size (the coil at 10^4 elements: hundreds of MB) written and read back out of cache.
    Blocked insertion, not scalar (setValuesRCV): on 2 ranks MPIBAIJ adds the scalar stash
    before the block stash, which would change the order of the sums on rows owned elsewhere,
    and through every wrapper (DirichletRows, planar.ComponentView) the one insertion path."""
    rows = layout.nat2petsc[nodes].astype(PETSc.IntType)
    n, k = rows.shape
    if not n:
        return
    view = P if isinstance(P, (DirichletRows, SplitBlocks)) else node_view(P)
    if getattr(view, "split", False):       # a split matrix: the position blocks alone
        view.add_positions(rows, mat.reshape(n, 3 * k, 3 * k), addv=PETSc.InsertMode.ADD)
        return
    m = mat.reshape(n, k, 3, k, 3) if mat.ndim == 3 else mat
    c = min(POSITION_CHUNK, n)
    K6 = np.zeros((c, k, NDOF, k, NDOF))
    for a in range(0, n, c):
        b = min(n, a + c)
        K6[:b - a, :, 0:3, :, 0:3] = m[a:b]
        P.setValuesBlockedRCV(rows[a:b], rows[a:b], K6[:b - a].reshape(b - a, k * NDOF, k * NDOF),
                              addv=PETSc.InsertMode.ADD)
