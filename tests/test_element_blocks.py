"""Element tangents added straight into the value array of a block matrix (model/assembly.py):
the same matrix as MatSetValuesBlocked gives, for BAIJ and SBAIJ, block sizes 3 and 6, split
matrices, the planar step's component block, on 1 and 2 ranks (mpi); the groups that touch a
constrained node or another rank's node go the matrix's way; the places follow a new pattern;
AIJ and a missing kernel keep the old insertion."""
import numpy as np
import pytest
from petsc4py import PETSc

from conftest import build_run, coiled_rollup
from rodsnes.model import assembly, partition
from rodsnes.model.partition import NDOF
from rodsnes.solve.planar import ComponentView, create_block_matrix
from test_assembly import owned_dense, perturbed

ADD = PETSc.InsertMode.ADD


def counted(monkeypatch):
    """Spy on ElementBlocks.add and on the compiled kernel's ElasticRod.tangents_into: the
    groups written straight (direct) and handed back to the matrix's insertion (rest)."""
    from rodsnes.model.elastic import ElasticRod
    seen = {"direct": 0, "rest": 0}
    add, into = assembly.ElementBlocks.add, ElasticRod.tangents_into

    def spy(self, a, b, V, insert):
        handed = []
        add(self, a, b, V, lambda i: (handed.append(len(i)), insert(i)))
        seen["rest"] += sum(handed)
        seen["direct"] += b - a - sum(handed)

    def spy_into(rod, q, r, conn, blocks, *args, **kw):
        done = into(rod, q, r, conn, blocks, *args, **kw)
        if done:
            seen["rest"] += len(blocks.rest)
            seen["direct"] += len(conn) - len(blocks.rest)
        return done
    monkeypatch.setattr(assembly.ElementBlocks, "add", spy)
    monkeypatch.setattr(ElasticRod, "tangents_into", spy_into)
    return seen


def places_checked(monkeypatch):
    """Every ElementBlocks made from now on also checked against numpy's places (the kernel's
    rodsnes_element_places against ElementBlocks._places_numpy): the same places, first
    additions, untouched blocks and completeness.  Returns the list of those checked."""
    made = []
    init = assembly.ElementBlocks.__init__

    def checked(self, *args):
        init(self, *args)
        ref = object.__new__(assembly.ElementBlocks)
        with monkeypatch.context() as m:
            m.setattr(assembly, "available", lambda: False)
            init(ref, *args)
        for name in ("pos", "first", "untouched"):
            assert np.array_equal(getattr(self, name), getattr(ref, name)), name
            assert getattr(self, name).dtype == getattr(ref, name).dtype, name
        assert self.complete == ref.complete
        made.append(self)
    monkeypatch.setattr(assembly.ElementBlocks, "__init__", checked)
    return made


def both_ways(monkeypatch, make, fill):
    """The matrix fill(M) makes in make() straight (A) and by MatSetValuesBlocked (B)."""
    A = make()
    fill(A)
    with monkeypatch.context() as m:
        m.setattr(assembly, "element_blocks", lambda *a, **k: None)
        B = make()
        fill(B)
    return A, B


def assert_same(A, B):
    a, b = owned_dense(A), owned_dense(B)
    assert np.count_nonzero(b) > 3 * b.shape[0]         # something is compared
    # the groups handed back are added after the direct ones of their chunk: a sum of more
    # than two parts may round differently
    assert np.abs(a - b).max() <= 1e-15 * np.abs(b).max()


def _ranks_sum(n):
    return PETSc.COMM_WORLD.tompi4py().allreduce(n)


@pytest.mark.mpi
@pytest.mark.parametrize("symmetric", [False, True])
def test_3d_jacobian_and_hessian_straight_into_the_values(monkeypatch, symmetric):
    """The 3-D Jacobian (MPIBAIJ, block size 6) and Hessian (SBAIJ, upper blocks) of an open
    clamped rod: every element but those at a constrained node (and, on 2 ranks, the one cut
    by the partition, on both) written straight; the same matrix as the insertion gives."""
    made = places_checked(monkeypatch)
    seen = counted(monkeypatch)
    run = perturbed(build_run("mattiasson", rod_nelem=40))
    p = run.problem

    def make():
        return p.layout.create_matrix(p.node_groups(p.patterns), symmetric=symmetric)

    A, B = both_ways(monkeypatch, make, lambda M: p.jacobian(None, p.state.X, M, M,
                                                            symmetric=symmetric))
    assert A.getBlockSize() == NDOF and B.getType() == A.getType()
    assert_same(A, B)
    size = PETSc.COMM_WORLD.getSize()
    direct, rest = _ranks_sum(seen["direct"]), _ranks_sum(seen["rest"])
    # each element once on its rank, a cut one also on the rank of its other nodes (owner
    # computes: Layout.row_elems)
    lay = p.layout
    halo = _ranks_sum(len(lay.row_elems) - len(lay.owned_elems))
    assert halo == size - 1
    assert direct + rest == 40 + halo
    assert 1 <= rest <= 1 + 2 * (size - 1), (direct, rest)   # the clamped end, the cuts
    assert made and all(len(b.pos) for b in made)
    A.destroy()
    B.destroy()


@pytest.mark.mpi
@pytest.mark.parametrize("symmetric", [False, True])
def test_planar_block_straight_into_the_values(monkeypatch, symmetric):
    """The planar step's in-plane block (block size 3, through ComponentView and the plane
    kernel) and the in-plane Hessian (SBAIJ): the same matrices."""
    made = places_checked(monkeypatch)
    seen = counted(monkeypatch)
    run = build_run("mattiasson", rod_nelem=30)
    p = run.problem
    pl = p.planar
    p.set_load(0.6)
    X = p.state.X
    lo = X.getOwnershipRange()[0]
    d = np.random.default_rng(5).normal(size=(X.getSize() // NDOF, 3)) * 1e-2
    with X as a:                # a planar state off equilibrium
        a = a.reshape(-1, NDOF)
        mine = slice(lo // NDOF, lo // NDOF + len(a))
        free = ~p.constraints.block_mask[mine][:, pl.plane.inplane]
        a[:, pl.plane.inplane] += np.where(free, d[mine], 0.0)

    def fill(M):
        p.jacobian(None, p.state.X, M, M, symmetric=symmetric,
                   view=ComponentView(M, pl.plane.inplane, p.constraints, pl.plane))

    A, B = both_ways(monkeypatch, lambda: create_block_matrix(p, p.patterns, symmetric),
                     fill)
    assert A.getBlockSize() == 3
    assert_same(A, B)
    assert _ranks_sum(seen["direct"]) >= 30 - PETSc.COMM_WORLD.getSize()
    assert made and all(len(b.pos) for b in made)
    A.destroy()
    B.destroy()


@pytest.mark.mpi
@pytest.mark.parametrize("symmetric", [False, True])
def test_split_contact_matrix_straight_into_the_values(monkeypatch, symmetric):
    """With contact the matrix is split (block size 3, two blocks a node): an element's
    tangent is 2k x 2k blocks of 3, written straight as well; the contact blocks go the
    matrix's way."""
    made = places_checked(monkeypatch)
    seen = counted(monkeypatch)
    run = coiled_rollup()
    p = run.problem
    p.ensure_pattern()

    def make():
        return p.layout.create_matrix(p.node_groups(p.patterns), symmetric=symmetric,
                                      positions_only=p.positions_only())

    A, B = both_ways(monkeypatch, make, lambda M: p.jacobian(None, p.state.X, M, M,
                                                            symmetric=symmetric))
    assert partition.is_split(A) and A.getBlockSize() == 3
    assert_same(A, B)
    assert _ranks_sum(seen["direct"]) >= 12 - 1 - PETSc.COMM_WORLD.getSize()
    assert made and all(len(b.pos) for b in made)
    A.destroy()
    B.destroy()


def small_baij(bs, symmetric, nodes=7):
    """A sequential (S)BAIJ matrix of a chain of 2-node groups (i, i + 1), preallocated."""
    n = nodes
    ai = [0]
    aj = []
    for i in range(n):
        cols = [j for j in (i - 1, i, i + 1) if 0 <= j < n and (not symmetric or j >= i)]
        aj += cols
        ai.append(len(aj))
    M = PETSc.Mat().create(comm=PETSc.COMM_SELF)
    M.setSizes((n * bs, n * bs), bsize=bs)
    M.setType(PETSc.Mat.Type.SEQSBAIJ if symmetric else PETSc.Mat.Type.SEQBAIJ)
    M.setPreallocationCSR((np.array(ai, dtype=PETSc.IntType), np.array(aj, dtype=PETSc.IntType)))
    if symmetric:
        M.setOption(PETSc.Mat.Option.IGNORE_LOWER_TRIANGULAR, True)
    M.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, False)
    return M


class Touched:
    def __init__(self, n, hit=()):
        self.touched = np.zeros(n, dtype=bool)
        self.touched[list(hit)] = True


@pytest.mark.parametrize("bs", [3, 6])
@pytest.mark.parametrize("symmetric", [False, True])
def test_kernel_adds_blocks_as_mat_set_values_blocked(bs, symmetric):
    """Random group tangents (symmetric ones for SBAIJ) added straight equal MatSetValuesBlocked
    of them, the touched groups handed back; after an entry outside the pattern (a new
    nonzero state) the places are found again."""
    rng = np.random.default_rng(bs)
    n = 7
    G = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1).astype(PETSc.IntType)
    V = rng.normal(size=(n - 1, 2 * bs, 2 * bs))
    if symmetric:
        V = V + V.transpose(0, 2, 1)
    touch = Touched(n, hit=[0])
    A, B = small_baij(bs, symmetric), small_baij(bs, symmetric)
    for M in (A, B):
        M.zeroEntries()
    blocks = assembly.element_blocks(A, touch, G, bs)
    assert blocks is not None and list(blocks.rest) == [0]
    for a, b in ((0, 2), (2, n - 1)):
        blocks.add(a, b, V[a:b], lambda i, a=a: A.setValuesBlockedRCV(
            G[a:b][i], G[a:b][i], V[a:b][i], addv=ADD))
    B.setValuesBlockedRCV(G, G, V, addv=ADD)
    for M in (A, B):
        M.assemble()
    assert np.array_equal(A[:, :], B[:, :])
    assert assembly.element_blocks(A, touch, G, bs) is blocks        # kept with the pattern
    # a new nonzero (0, n - 1) moves the places in row 0: found again
    for M in (A, B):
        M.setValuesBlocked([0], [n - 1], np.ones(bs * bs), addv=ADD)
        M.assemble()
    again = assembly.element_blocks(A, touch, G, bs)
    assert again is not blocks
    for M in (A, B):
        M.zeroEntries()
    again.add(0, n - 1, V, lambda i: A.setValuesBlockedRCV(G[i], G[i], V[i], addv=ADD))
    B.setValuesBlockedRCV(G, G, V, addv=ADD)
    for M in (A, B):
        M.assemble()
    assert np.array_equal(A[:, :], B[:, :])


@pytest.mark.parametrize("symmetric", [False, True])
def test_places_of_groups_outside_the_pattern_or_touched(monkeypatch, symmetric):
    """The compiled places against numpy's on a chain with touched groups and a group whose
    block lies outside the pattern (then incomplete: element_blocks gives None)."""
    made = places_checked(monkeypatch)
    n = 7
    G = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1).astype(PETSc.IntType)
    A = small_baij(3, symmetric)
    assert assembly.element_blocks(A, Touched(n, hit=[0, 4]), G, 3) is not None
    far = np.concatenate([G, [[0, 3]]]).astype(PETSc.IntType)      # block (0, 3): none
    assert assembly.element_blocks(A, Touched(n), far, 3) is None
    assert len(made) == 2 and made[0].complete and not made[1].complete
    assert list(made[0].rest) == [0, 3, 4]


def test_not_for_aij_nor_without_the_kernel(monkeypatch):
    """An AIJ matrix (-mat_type aij), a block size other than the tangents', a group with a
    block outside the pattern and a missing kernel keep MatSetValuesBlocked (element_blocks
    returns None); tangents of the wrong shape are refused before the C call."""
    G = np.array([[0, 1], [1, 2]], dtype=PETSc.IntType)
    touch = Touched(3)
    aij = PETSc.Mat().createAIJ((9, 9), nnz=9, comm=PETSc.COMM_SELF)
    aij.setUp()
    assert assembly.element_blocks(aij, touch, G, 3) is None
    baij = small_baij(3, False, nodes=3)
    assert assembly.element_blocks(baij, touch, G, 6) is None
    blocks = assembly.element_blocks(baij, touch, G, 3)
    with pytest.raises(ValueError):
        blocks.add(0, 2, np.zeros((2, 6, 3)), lambda i: None)
    # a group whose block is outside the pattern: its insertion would allocate and move the
    # places of the chunks after it (stale places wrote 3.1 where entries were 3.5): all of them
    # the matrix's way
    chain = small_baij(3, False, nodes=4)
    assert assembly.element_blocks(chain, Touched(4), G, 3) is not None
    assert assembly.element_blocks(chain, Touched(4), np.array([[0, 1], [0, 2]],
                                                               dtype=PETSc.IntType), 3) is None
    monkeypatch.setattr(assembly, "available", lambda: False)
    assert assembly.element_blocks(baij, touch, G, 3) is None


def test_the_kept_places_survive_the_garbage_collector():
    """The places are kept in the matrix's attributes; they hold no wrapper of the matrix: the
    cyclic garbage collector sees the attributes' dict through every petsc4py wrapper, and a
    collection of the young objects alone took the dict, the places and a short-lived wrapper
    (the SNES callback's) for an unreachable cycle and cleared the dict, every attribute of the
    matrix with it (the split marker: a traceback in the bench coil)."""
    import gc
    bs, n = 3, 7
    G = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1).astype(PETSc.IntType)
    A = small_baij(bs, False)
    A.setAttr("marker", True)
    gc.collect()                                # A's wrapper among the old objects
    ksp = PETSc.KSP().create(comm=PETSc.COMM_SELF)
    ksp.setOperators(A)
    other = ksp.getOperators()[0]               # a second wrapper, as a callback's
    blocks = assembly.element_blocks(other, Touched(n, hit=[]), G, bs)
    assert blocks is not None
    del other, blocks
    ksp.destroy()
    gc.collect(0)
    gc.collect(1)
    assert A.getAttr("marker") is True and A.getAttr(assembly.ATTR) is not None


@pytest.mark.mpi
def test_no_view_outlives_its_jacobian():
    """What the Jacobian's views derive from the constraints alone is kept between Jacobians
    (partition.kept: DirichletRows.touched_of, planar.component_cut), the views themselves,
    which hold their matrix, are not: a matrix destroyed and another made (often at the freed
    one's address), or the wrapper a view had held destroyed while a KSP keeps the matrix (a
    view kept by the matrix's handle, or by a token composed into it, then wrote through a
    dead wrapper: a segmentation fault), get views of their own; every Hessian made so equals
    the first; Constraints.hold's new mask is seen."""
    from rodsnes.solve.stability import hessian
    run = perturbed(build_run("mattiasson", rod_nelem=12))
    p = run.problem
    first = owned_dense(hessian(p))
    for _ in range(4):
        H = p.layout.create_matrix(p.node_groups(p.patterns))
        p.jacobian(None, p.state.X, H, H, symmetric=True)
        assert np.array_equal(owned_dense(H), first)
        H.destroy()
    # the matrix kept alive by a KSP, the wrapper of the last Jacobian destroyed
    H = p.layout.create_matrix(p.node_groups(p.patterns))
    p.jacobian(None, p.state.X, H, H, symmetric=True)
    ksp = PETSc.KSP().create(comm=H.getComm())
    ksp.setOperators(H)
    other = ksp.getOperators()[0]
    H.destroy()
    p.jacobian(None, p.state.X, other, other, symmetric=True)
    assert np.array_equal(owned_dense(other), first)
    ksp.destroy()
    pl = p.planar
    for _ in range(3):
        pl.assemble_tangent()
        J = owned_dense(pl.J)
        pl.J.destroy()                  # the next assemble_tangent makes it anew
        pl.J = None
        pl.assemble_tangent()
        assert np.array_equal(owned_dense(pl.J), J)
    touched = p._dirichlet_touched[1]
    p.constraints.hold(5, 1, 0.0)       # a new mask: its own constrained blocks
    H = hessian(p)
    assert p._dirichlet_touched[1] is not touched
    assert p._dirichlet_touched[1][p.layout.nat2petsc[5]]
    H.destroy()


@pytest.mark.mpi
@pytest.mark.parametrize("planar", [False, True], ids=["3d", "planar"])
def test_a_jacobian_over_garbage_is_the_jacobian_over_zeros(planar):
    """The Jacobian zeroes only the blocks the kernel's first additions do not set
    (ElementBlocks.zero_rest: those no direct element holds, the off-diagonal part on several
    ranks) and stores at those first additions: into a matrix full of garbage it is the same
    matrix, bit for bit, as into a zeroed one (on 1, 2 and 3 ranks: the elements across the
    cuts and at the clamp added after)."""
    from rodsnes.solve.planar import component_view
    run = perturbed(build_run("mattiasson", rod_nelem=30))
    p = run.problem
    rng = np.random.default_rng(PETSc.COMM_WORLD.getRank())

    def make():
        if planar:
            return create_block_matrix(p, p.patterns, symmetric=False)
        return p.layout.create_matrix(p.node_groups(p.patterns))

    def fill(M):
        view = component_view(p, M, p.planar.plane.inplane, p.constraints,
                              p.planar.plane) if planar else None
        p.jacobian(None, p.state.X, M, M, view=view)

    A, B = make(), make()
    fill(A)
    for _ in range(2):          # every entry of the pattern set to garbage, then again
        rows, cols, _ = A.getValuesCSR()
        lo = A.getOwnershipRange()[0]
        for i in range(len(rows) - 1):
            c = cols[rows[i]:rows[i + 1]]
            B.setValues([lo + i], c, rng.normal(size=len(c)))
        B.assemble()
        fill(B)
        a, b = owned_dense(A), owned_dense(B)
        assert np.count_nonzero(a) > 3 * a.shape[0]
        assert np.array_equal(a.view(np.int64), b.view(np.int64))
    A.destroy()
    B.destroy()


@pytest.mark.mpi
def test_a_rank_owning_no_node(monkeypatch):
    """A linear ring of 3 elements whose last element alone is rank 1's: its two nodes are rank
    0's (a node is its first element's rank's), so rank 1's block of the matrix is empty (no
    value array: ElementBlocks.zero_rest read a null address, a TypeError) - the ring's energy
    as one rank finds it."""
    comm = PETSc.COMM_WORLD
    if comm.getSize() != 2:
        pytest.skip("two ranks")
    from rodsnes.model import partition
    from conftest import run_case
    serial = run_case("michell", comm=PETSc.COMM_SELF, rod_nelem=3, rod_order=1,
                      rod_error_estimate="off")
    monkeypatch.setattr(partition, "metis_parts",
                        lambda ne, closed, n: np.array([0] * (ne - 1) + [1]))
    run = run_case("michell", rod_nelem=3, rod_order=1, rod_error_estimate="off")
    assert run.layout.n_owned == (3 if comm.getRank() == 0 else 0)
    assert run.ok and serial.ok
    assert abs(run.problem.energy() - serial.problem.energy()) <= 1e-12 * abs(serial.problem.energy())


@pytest.mark.mpi
@pytest.mark.parametrize("kind", ["3d", "3d-symmetric", "planar", "planar-symmetric",
                                  "split", "split-symmetric", "aij"])
def test_set_diagonal_as_matdiagonalset(kind):
    """assembly.set_diagonal (the minimiser's shifted solves, the stability count's shift)
    gives MatDiagonalSet's matrix bit for bit, adding and inserting, for BAIJ and SBAIJ of
    block size 6 and 3 (the planar block, a split contact matrix) on 1 and 2 ranks, and for a
    new matrix of the same pattern; AIJ goes through MatDiagonalSet."""
    symmetric = kind.endswith("symmetric")
    if kind.startswith("split"):
        run = coiled_rollup()
        run.problem.ensure_pattern()
        assert run.problem.positions_only()
    else:
        run = perturbed(build_run("mattiasson", rod_nelem=20))
    p = run.problem
    pl = p.planar

    def make():
        if kind.startswith("planar"):
            M = create_block_matrix(p, p.patterns, symmetric)
            p.jacobian(None, p.state.X, M, M, symmetric=symmetric,
                       view=ComponentView(M, pl.plane.inplane, p.constraints))
            return M
        M = p.layout.create_matrix(p.node_groups(p.patterns), symmetric=symmetric,
                                   positions_only=p.positions_only())
        assert partition.is_split(M) == kind.startswith("split")
        p.jacobian(None, p.state.X, M, M, symmetric=symmetric)
        return M.convert(PETSc.Mat.Type.AIJ) if kind == "aij" else M

    for rep in range(2):
        A, B = make(), make()
        assert_bitwise_equal_dense(A, B)
        d = A.createVecLeft()
        d.setArray(np.random.default_rng(7 + PETSc.COMM_WORLD.getRank() + 10 * rep)
                   .normal(size=d.getLocalSize()))
        for add in (True, False, True):
            state = A.stateGet()
            assembly.set_diagonal(A, d, add=add)
            assert A.stateGet() > state         # a factorisation of A knows it changed
            B.setDiagonal(d, addv=PETSc.InsertMode.ADD_VALUES if add
                          else PETSc.InsertMode.INSERT_VALUES)
            assert_bitwise_equal_dense(A, B)
        # the value array's way (its places kept on the matrix), or MatDiagonalSet's for AIJ
        assert (A.getAttr(assembly.DIAGONAL_ATTR) is None) == (kind == "aij")
        A.destroy()
        B.destroy()
        d.destroy()


def assert_bitwise_equal_dense(A, B):
    a, b = owned_dense(A), owned_dense(B)
    assert np.count_nonzero(a) > a.shape[0]
    assert np.array_equal(a.view(np.int64), b.view(np.int64)), np.abs(a - b).max()


@pytest.mark.parametrize("closed", [False, True])
def test_chain_graph_is_the_elements_adjacency(closed):
    """partition.chain_graph (the graph METIS partitions) row by row: each element's neighbours
    on the rod, sorted, without repeats or the element itself, down to one and two elements."""
    for n in (1, 2, 3, 4, 7, 50):
        xadj, adj = partition.chain_graph(n, closed)
        assert len(xadj) == n + 1 and xadj[0] == 0 and xadj[-1] == len(adj)
        for k in range(n):
            near = {(k - 1) % n, (k + 1) % n} if closed else {j for j in (k - 1, k + 1) if 0 <= j < n}
            assert list(adj[xadj[k]:xadj[k + 1]]) == sorted(near - {k}), (n, k)


@pytest.mark.mpi
@pytest.mark.parametrize("mat_type", [None, "baij", "sbaij", "mpibaij", "mpisbaij"])
@pytest.mark.parametrize("symmetric", [False, True])
def test_preallocated_pattern_as_plain_csr(mat_type, symmetric):
    """partition.preallocate_blocks (column-oriented while a sequential matrix takes its zeros)
    gives the pattern MatSetPreallocationCSR gives, every block present, row-oriented after;
    an MPI type on one rank (-mat_type mpibaij) goes the plain way (its MatSetOption before the
    preallocation was a segmentation fault)."""
    kw = {} if mat_type is None else {"mat_type": mat_type}
    p = build_run("mattiasson", rod_nelem=8, **kw).problem
    A = p.layout.create_matrix(p.node_groups(p.patterns), symmetric=symmetric)
    B = PETSc.Mat().create(comm=A.getComm())    # the same type, by plain CSR
    B.setSizes(A.getSizes(), bsize=A.getBlockSize())
    B.setType(A.getType())
    ai, aj = p.layout.block_pattern(p.node_groups(p.patterns))
    if A.getType() in (PETSc.Mat.Type.SEQSBAIJ, PETSc.Mat.Type.MPISBAIJ):
        ai, aj = partition._upper_blocks(ai, aj, p.layout.starts[PETSc.COMM_WORLD.getRank()])
    B.setPreallocationCSR((ai, aj))
    seq = [M.getDiagonalBlock() if M.getComm().getSize() > 1 else M for M in (A, B)]
    (a1, j1), (a2, j2) = (S.getRowIJ(compressed=True) for S in seq)
    assert np.array_equal(a1, a2) and np.array_equal(j1, j2)
    assert A.getInfo()["nz_used"] == B.getInfo()["nz_used"] > 0
    # row-oriented again: a block inserted row by row lands as given
    lo = A.getOwnershipRange()[0] // A.getBlockSize()
    bs = A.getBlockSize()
    v = np.arange(bs * bs, dtype=float) + 1.0
    A.setValuesBlocked([lo], [lo], v)
    A.assemble()
    got = A.getValues(range(lo * bs, lo * bs + bs), range(lo * bs, lo * bs + bs))
    assert np.array_equal(got, v.reshape(bs, bs))    # (SBAIJ keeps a diagonal block whole)
    A.destroy()
    B.destroy()


def test_set_diagonal_of_an_unassembled_matrix_as_matdiagonalset():
    """A block inserted and not yet assembled moves the row's blocks under the kept places:
    set_diagonal takes MatDiagonalSet's way there, with its result."""
    A, B = small_baij(3, False, nodes=4), small_baij(3, False, nodes=4)
    d = A.createVecLeft()
    d.setArray(np.arange(1.0, 13.0))
    assembly.set_diagonal(A, d, add=True)               # the places kept
    B.setDiagonal(d, addv=PETSc.InsertMode.ADD_VALUES)
    for M in (A, B):
        M.setValuesBlocked([2], [0], np.arange(9.0), addv=PETSc.InsertMode.ADD)
    assert not A.isAssembled()
    assembly.set_diagonal(A, d, add=True)
    B.setDiagonal(d, addv=PETSc.InsertMode.ADD_VALUES)
    assert_bitwise_equal_dense(A, B)
