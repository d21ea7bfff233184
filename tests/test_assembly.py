"""Jacobian assembly: the Dirichlet rows and columns masked in every block before insertion
(partition.DirichletRows) give bit for bit the matrix of MatZeroRowsColumns(P, rows, 1) applied
to the assembled sum, and the contact's position blocks (partition.add_position_blocks) enter
only their 3 x 3 position parts, bit for bit as the dense 6 x 6 blocks did.  Open and closed
rods, with and without contact, 1 and 2 ranks (mpi)."""
from mpi4py import MPI
import numpy as np
import pytest
from petsc4py import PETSc

from conftest import build_run, coiled_rollup
from rodsnes.model import partition
from rodsnes.model import problem as problem_module
from rodsnes.model.partition import NDOF, DirichletRows, add_position_blocks


def perturbed(run, lam=1.0, seed=0, size=1e-3):
    """The run's state moved by a small random step (every dof) at load factor lam: a state
    with nonzero tangent entries everywhere, not an equilibrium."""
    p = run.problem
    rng = np.random.default_rng(seed + PETSc.COMM_WORLD.getRank())
    with p.state.X as a:
        a += size * rng.normal(size=a.shape)
    p.lam = lam
    return run


def summed_then_zeroed(p, P, H, rows, cols, symmetric=False):
    """The elastic tangents H of the node groups ``cols``, this rank setting the block rows
    ``rows`` (MatSetValues' own way: rows of other ranks stashed, negative ones ignored), and
    the terms' tangents summed into P, assembled, then MatZeroRowsColumns(P, rows, 1)."""
    r, q = p.state.local_config(p.state.X)
    P.zeroEntries()
    V = partition.node_view(P)          # node blocks of 6 (a split contact Jacobian: of 3)
    V.setValuesBlockedRCV(rows.astype(PETSc.IntType), cols.astype(PETSc.IntType), H,
                          addv=PETSc.InsertMode.ADD)
    for t in p.terms:
        t.add_jacobian(p.lam, r, q, V, symmetric=symmetric)
    P.assemble()
    P.zeroRowsColumns(p.constraints.is_rows, 1.0)


def zero_rows_columns_reference(p, P, symmetric=False):
    """The definition: elastic and terms' tangents summed into P as they are (the elastic ones
    of every element holding an owned node, this rank's rows: owner computes), assembled,
    then MatZeroRowsColumns(P, rows, 1)."""
    r, q = p.state.local_config(p.state.X)
    lay = p.layout
    _, _, H = p.elastic.element_terms(q[lay.row_lconn], r[lay.row_lconn], tangent=True,
                                      symmetric=symmetric)
    summed_then_zeroed(p, P, H, lay.row_rows, lay.row_gconn, symmetric)


def stashed_sum(p, P, F, symmetric=False):
    """The sums owner computes replaces: the owned elements' tangents and residual rows (and
    the terms'), the rows of other ranks' nodes sent to their owners (the matrix's stash, the
    residual's reverse scatter); the Dirichlet rows and columns as MatZeroRowsColumns."""
    X = p.state.X
    r, q = p.state.local_config(X)
    lay = p.layout
    e0 = p.elastic.e0[:p.n_elems]
    _, Floc, H = p.elastic.element_terms(q[lay.lconn], r[lay.lconn], e0, tangent=True,
                                         symmetric=symmetric)
    P.setOption(PETSc.Mat.Option.NO_OFF_PROC_ENTRIES, False)
    summed_then_zeroed(p, P, H, lay.gconn, lay.gconn, symmetric)
    loc = np.zeros((len(lay.local_nodes), NDOF))
    np.add.at(loc, lay.lconn, Floc)
    for t in p.terms:
        if t.owner_computes:        # its own rows whole: summed once, by their owner
            mine = np.zeros_like(loc)
            t.add_residual(p.lam, r, q, mine)
            loc[:lay.n_owned] += mine[:lay.n_owned]
        else:
            t.add_residual(p.lam, r, q, loc)
    F.set(0.0)
    lay.add_to_global(loc, F)
    with F as fa:
        rows = p.constraints.rows_local
        fa[rows] = X.getArray(readonly=True)[rows] - np.where(
            rows % NDOF < 3, p.constraints.target_own, 0.0)


def owned_dense(P):
    """The owned rows of P as a dense array (all columns)."""
    lo, hi = P.getOwnershipRange()
    n = P.getSize()[1]
    return P.getValues(np.arange(lo, hi, dtype=PETSc.IntType), np.arange(n, dtype=PETSc.IntType))


def assert_bitwise_equal(A, B):
    assert A.shape == B.shape
    assert np.array_equal(A.view(np.int64), B.view(np.int64)), \
        f"max |diff| {np.abs(A - B).max()} in {np.count_nonzero(A != B)} entries"


def masked_against_reference(run, symmetric=False):
    p = run.problem
    p.ensure_pattern()
    J = p.J
    ref = J.duplicate()
    if partition.is_split(J):           # (a duplicate does not carry the attribute)
        ref.setAttr(partition.SPLIT_ATTR, True)
    zero_rows_columns_reference(p, ref, symmetric)
    p.jacobian(None, p.state.X, J, J, symmetric=symmetric)
    A, B = owned_dense(J), owned_dense(ref)
    assert_bitwise_equal(A, B)
    ref.destroy()
    return A


def constrained_rows_are_identity(run, A):
    """The masked matrix has the identity on this rank's constrained rows (and it is not all
    zero elsewhere: the test compares something)."""
    p = run.problem
    lo = p.J.getOwnershipRange()[0]
    for row in p.constraints.rows_global:
        e = np.zeros(A.shape[1])
        e[row] = 1.0
        assert np.array_equal(A[row - lo], e)
    assert np.count_nonzero(A) > 10 * A.shape[0]


SCENES = {
    "mattiasson": lambda: perturbed(build_run("mattiasson", rod_nelem=10, rod_error_estimate="off")),
    "helix": lambda: perturbed(build_run("helix", rod_nelem=10)),
    "michell": lambda: perturbed(build_run("michell", rod_nelem=10), lam=0.5),
    "rollup_contact": lambda: coiled_rollup(),
}
# owner computes beside a term that sends its ghost rows (contact): a distributed load, whose
# rows of the other ranks' nodes must not be sent too
OWNER_SCENES = {**SCENES,
                "rollup_contact_gravity": lambda: coiled_rollup(load_gravity="0,-3,0"),
                "mattiasson_gravity": lambda: perturbed(build_run(
                    "mattiasson", rod_nelem=10, rod_error_estimate="off",
                    load_gravity="0.5,-3,0"))}


@pytest.mark.mpi
@pytest.mark.parametrize("scene", sorted(SCENES))
@pytest.mark.parametrize("symmetric", [False, True])
def test_masked_blocks_give_the_zero_rows_columns_matrix(scene, symmetric):
    run = SCENES[scene]()
    A = masked_against_reference(run, symmetric)
    constrained_rows_are_identity(run, A)


@pytest.mark.mpi
@pytest.mark.parametrize("scene", sorted(OWNER_SCENES))
@pytest.mark.parametrize("symmetric", [False, True])
def test_owner_computes_gives_the_stashed_sums(scene, symmetric):
    """Every rank summing the rows of its own nodes from every element holding one (Layout.
    row_elems: owner computes, no rows sent) gives the residual and the Jacobian that the
    owned elements' rows sent to their owners gave (the stash, the reverse scatter): the
    same terms in another order of addition, to round-off.  The boundary rows differ from
    their one-element parts (the test would see a dropped element), and a distributed load's
    ghost rows sent beside contact's would count it twice there."""
    run = OWNER_SCENES[scene]()
    p = run.problem
    p.ensure_pattern()
    J = p.J
    ref = J.duplicate()
    if partition.is_split(J):
        ref.setAttr(partition.SPLIT_ATTR, True)
    F, Fref = p.F.duplicate(), p.F.duplicate()
    stashed_sum(p, ref, Fref, symmetric)
    p.jacobian(None, p.state.X, J, J, symmetric=symmetric)
    p.residual(None, p.state.X, F)
    A, B = owned_dense(J), owned_dense(ref)
    assert np.abs(A - B).max() <= 1e-13 * np.abs(B).max()
    f, fref = F.getArray(readonly=True), Fref.getArray(readonly=True)
    scale = MPI.COMM_WORLD.allreduce(np.abs(fref).max(initial=0.0), op=MPI.MAX)
    assert np.abs(f - fref).max(initial=0.0) <= 1e-13 * scale
    ref.destroy()


@pytest.mark.mpi
def test_contact_state_has_contact_blocks_in_the_compared_matrix():
    """The rollup_contact state of the comparison really carries contact tangents: the
    matrix differs from the one without the contact term."""
    run = coiled_rollup()
    p = run.problem
    F = p.F.duplicate()
    p.residual(None, p.state.X, F)
    assert run.contact.summary()["active_points"] > 0
    A = masked_against_reference(run)
    terms = p.terms
    p.terms = [t for t in terms if t is not run.contact]
    try:
        p.jacobian(None, p.state.X, p.J, p.J)
        differs = not np.array_equal(owned_dense(p.J), A)   # on a rank that owns contact rows
        assert PETSc.COMM_WORLD.tompi4py().allreduce(differs, op=MPI.LOR)
    finally:
        p.terms = terms


@pytest.mark.mpi
@pytest.mark.parametrize("max_runs", [0, DirichletRows.MAX_RUNS])
@pytest.mark.parametrize("scene", ["mattiasson", "rollup_contact"])
def test_many_constrained_nodes_in_runs_and_in_one_copy(monkeypatch, max_runs, scene):
    """Constrained dofs on interior nodes (several runs of touched elements, split across the
    ranks): in runs (views between masked copies) and beyond MAX_RUNS (one masked copy); with
    contact also the contact's position blocks (DirichletRows.add_positions)."""
    monkeypatch.setattr(DirichletRows, "MAX_RUNS", max_runs)
    if scene == "mattiasson":
        run = perturbed(build_run("mattiasson", rod_nelem=16, rod_error_estimate="off"))
        held = ((7, 1), (8, 2), (20, 0), (33, 1), (34, 0))
    else:           # 12 cubic elements coiled onto their clamped start: contact at both ends
        run = coiled_rollup()
        held = ((5, 1), (6, 2), (18, 0), (33, 1))
    c = run.problem.constraints
    for node, comp in held:
        c.hold(node, comp, 0.0)
    A = masked_against_reference(run)
    constrained_rows_are_identity(run, A)


def dense_position_blocks(P, layout, nodes, mat):
    """The former add_position_blocks: each 3 x 3 block in a dense 6 x 6 block."""
    rows = layout.nat2petsc[nodes].astype(PETSc.IntType)
    n, k = rows.shape
    K6 = np.zeros((n, k, NDOF, k, NDOF))
    K6[:, :, 0:3, :, 0:3] = mat.reshape(n, k, 3, k, 3)
    P.setValuesBlockedRCV(rows, rows, K6.reshape(n, k * NDOF, k * NDOF),
                          addv=PETSc.InsertMode.ADD)


@pytest.mark.mpi
@pytest.mark.parametrize("chunk", [3, None])
def test_position_blocks_add_as_the_dense_blocks_did(monkeypatch, chunk):
    """Random position tangents of random node groups (some on constrained nodes, some
    repeated) added through DirichletRows on top of the elastic tangent: the same matrix
    bit for bit as the dense 6 x 6 blocks (on up to 2 ranks; to round-off on more), in
    bounded chunks or in one."""
    if chunk is not None:
        monkeypatch.setattr(partition, "POSITION_CHUNK", chunk)
    run = perturbed(build_run("mattiasson", rod_nelem=6, rod_error_estimate="off"))
    p, lay = run.problem, run.layout
    nn = lay.n_global
    rng = np.random.default_rng(1)          # the same groups on every rank
    nodes = rng.integers(0, nn, size=(11, 4))
    nodes[0] = [0, 1, 2, nn - 1]            # the clamped start
    mats = rng.normal(size=(11, 12, 12)) * (1 + PETSc.COMM_WORLD.getRank())
    # the whole graph couples: a dense pattern, so every group is preallocated
    J = lay.create_matrix(np.arange(nn)[None, :])
    out = []
    for add in (dense_position_blocks, add_position_blocks):
        T = DirichletRows(J, p.constraints.block_mask)
        J.zeroEntries()
        r, q = p.state.local_config()
        _, _, H = p.elastic.element_terms(q[p.lconn], r[p.lconn], p.elastic.e0[:p.n_elems],
                                          tangent=True)
        g = lay.gconn.astype(PETSc.IntType)
        T.setValuesBlockedRCV(g, g, H, addv=PETSc.InsertMode.ADD)
        add(T, lay, nodes, mats)
        T.finish(p.constraints.rows_global)
        J.assemble()
        out.append(owned_dense(J))
    if PETSc.COMM_WORLD.getSize() <= 2:
        assert_bitwise_equal(out[1], out[0])
    else:       # from several other ranks the stashed additions arrive in no fixed order
        assert np.abs(out[1] - out[0]).max() <= 1e-14 * np.abs(out[0]).max()
    assert np.count_nonzero(out[1]) > 0


@pytest.mark.mpi
@pytest.mark.parametrize("symmetric", [False, True])
def test_split_contact_jacobian_equals_the_node_block_one(monkeypatch, symmetric):
    """With contact (a term coupling positions only) the Jacobian and the Hessian are split
    (block size 3: a node's position and rotation in blocks 2n and 2n + 1, the contact blocks
    their 3 x 3 position parts alone): bit for bit the matrix of node blocks of 6 on one rank
    (to round-off on two), with a quarter of the stored contact entries."""
    run = coiled_rollup()
    p = run.problem
    p.ensure_pattern()

    def assembled(split):
        monkeypatch.setattr(partition, "SPLIT_CONTACT", split)
        M = p.layout.create_matrix(p.node_groups(p.patterns), symmetric=symmetric,
                                   positions_only=p.positions_only())
        p.jacobian(None, p.state.X, M, M, symmetric=symmetric)
        return M

    S, B = assembled(True), assembled(False)
    assert partition.is_split(S) and not partition.is_split(B)
    assert S.getBlockSize() == 3 and B.getBlockSize() == NDOF
    A, A6 = owned_dense(S), owned_dense(B)
    if symmetric:       # SBAIJ: the upper triangle (a node's diagonal block of 6 holds both)
        lo = S.getOwnershipRange()[0]
        upper = np.arange(A.shape[1])[None, :] >= lo + np.arange(A.shape[0])[:, None]
        A, A6 = np.where(upper, A, 0.0), np.where(upper, A6, 0.0)
    if PETSc.COMM_WORLD.getSize() == 1:
        assert_bitwise_equal(A, A6)
    else:               # the stash of rows owned elsewhere sums blocks of 3 in another order
        assert np.abs(A - A6).max() <= 1e-14 * np.abs(A6).max()
    assert np.count_nonzero(A) > 10 * A.shape[0]
    stored = [M.getInfo(PETSc.Mat.InfoType.GLOBAL_SUM)["nz_used"] for M in (S, B)]
    assert stored[0] < 0.8 * stored[1]
    S.destroy()
    B.destroy()


@pytest.mark.mpi
@pytest.mark.parametrize("scene", ["mattiasson", "rollup_contact"])
def test_own_blocks_go_straight_into_the_diagonal_block(monkeypatch, scene):
    """On several ranks the groups wholly in a rank's own rows and columns go into the MPI
    matrix's diagonal block directly (partition.OwnBlocksFirst), the others through the MPI
    matrix, in runs in their order: bit for bit the matrix of insertion through the MPI matrix
    alone (the reference of masked_against_reference), with the contact's split matrix too;
    on one rank the matrix itself is used.  Every element through the matrix's insertion here
    (no ElementBlocks: the compiled kernel adds most of them into the value array itself, and
    the rest by one MatSetValuesBlocked, RestElements)."""
    monkeypatch.setattr(problem_module.assembly, "element_blocks", lambda *a, **k: None)
    sent = {"diag": 0, "mpi": 0}
    own = partition.OwnBlocksFirst

    class Counted(own):
        def setValuesBlockedRCV(self, R, C, V, addv=None):
            R2, C2 = R.reshape(len(R), -1), C.reshape(len(C), -1)
            inside = (((R2 >= self.lo) & (R2 < self.hi)).all(axis=1)
                      & ((C2 >= self.lo) & (C2 < self.hi)).all(axis=1))
            sent["diag"] += int(inside.sum())
            sent["mpi"] += int((~inside).sum())
            super().setValuesBlockedRCV(R, C, V, addv=addv)

    monkeypatch.setattr(partition, "OwnBlocksFirst", Counted)
    run = SCENES[scene]()
    A = masked_against_reference(run)
    constrained_rows_are_identity(run, A)
    if PETSc.COMM_WORLD.getSize() > 1:        # both kinds, on some rank
        total = PETSc.COMM_WORLD.tompi4py().allreduce(np.array([sent["diag"], sent["mpi"]]))
        assert total[0] > 0 and total[1] > 0, total
    else:
        assert sent == {"diag": 0, "mpi": 0}


@pytest.mark.parametrize("bs", [1, 3, 6])
def test_scalar_csr_expands_every_block(bs):
    """partition._scalar_csr (the AIJ preallocation of -mat_type aij): every entry of every
    bs x bs block of a block CSR, rows and columns in order, for block rows given sorted or
    not, empty ones included; against the entries listed one by one."""
    rng = np.random.default_rng(bs)
    for trial in range(12):
        rows = [rng.choice(40, rng.integers(0, 6), replace=False) for _ in range(rng.integers(1, 25))]
        if trial % 2:
            rows = [np.sort(r) for r in rows]
        ai = np.concatenate([[0], np.cumsum([len(r) for r in rows])])
        aj = np.concatenate(rows).astype(np.int64) if any(len(r) for r in rows) else \
            np.zeros(0, dtype=np.int64)
        I, J = partition._scalar_csr(ai, aj, bs)
        want = sorted((i * bs + a, j * bs + b) for i, r in enumerate(rows) for j in r
                      for a in range(bs) for b in range(bs))
        got = [(r, c) for r in range(len(I) - 1) for c in J[I[r]:I[r + 1]]]
        assert got == want and len(I) == len(rows) * bs + 1


@pytest.mark.parametrize("owners, closed, descends", [
    ([0, 0, 1, 1], False, [False, True]),       # the second stretch meets the first at its start
    ([1, 1, 0, 0], False, [True, False]),       # METIS may number the pieces from either end
    ([0, 0, 1, 1, 2, 2], False, [False, False, True]),   # a middle stretch meets both others
    ([2, 2, 0, 0, 1, 1], False, [False, True, False]),
    ([0, 0, 1, 1], True, [False, False]),       # a closed rod: every stretch meets at both ends
    ([0, 0, 0], False, [False]),
])
def test_each_stretch_is_numbered_toward_the_nodes_it_shares(owners, closed, descends):
    from rodsnes.model.partition import stretch_descends
    got = stretch_descends(np.asarray(owners), closed, max(owners) + 1)
    assert got.tolist() == descends


@pytest.mark.mpi
@pytest.mark.parametrize("case, kw", [("mattiasson", dict(rod_nelem=24)),
                                      ("michell", dict(rod_nelem=12)),
                                      ("rollup_contact", dict(rod_nelem=16))])
def test_the_block_pattern_of_the_row_elements_is_the_whole_rods(case, kw):
    """Layout.block_pattern from the elements holding an owned node (row_elems) equals the
    owned rows of the whole rod's pattern, with a term's extra groups (contact pairs) too."""
    from conftest import build_run
    from rodsnes.model.partition import group_pairs
    run = build_run(case, **kw)
    lay, p = run.layout, run.problem
    extra = p.node_groups(p.patterns)
    ai, aj = lay.block_pattern(extra)
    rows, cols = group_pairs(lay.coupled_groups(extra))       # every element on every rank
    r, c = lay.nat2petsc[rows], lay.nat2petsc[cols]
    lo, hi = lay.starts[lay.comm.getRank()], lay.starts[lay.comm.getRank() + 1]
    keep = (r >= lo) & (r < hi)
    code = np.unique(r[keep] * lay.n_global + c[keep])
    want_i = np.concatenate([[0], np.cumsum(np.bincount(code // lay.n_global - lo,
                                                        minlength=hi - lo))])
    assert np.array_equal(ai, want_i) and np.array_equal(aj, code % lay.n_global)


@pytest.mark.parametrize("shape", [(0, 4), (7, 1), (1000, 4), (33, 8), (5, 0)])
def test_any_column_is_any_along_the_rows(shape):
    """partition.any_column, the node groups' row-wise any column by column, is numpy's
    B.any(axis=1)."""
    from rodsnes.model.partition import any_column
    B = np.random.default_rng(shape[0]).random(shape) < 0.15
    got = any_column(B)
    assert got.dtype == bool and np.array_equal(got, B.any(axis=1))
    assert got.base is not B            # a new array, B untouched


@pytest.mark.mpi
@pytest.mark.parametrize("symmetric", [False, True])
def test_the_rest_elements_follow_a_new_mask_at_the_same_nodes(monkeypatch, symmetric):
    """The elements the compiled kernel leaves to the matrix's insertion (the supports', a
    ranks' boundary's: problem.RestElements) keep their rows, columns and Dirichlet mask with
    the element blocks' places; a constraint added at an already constrained node (the same
    blocks touched, the places kept) is a new mask, and the next Jacobian masks by it: bit for
    bit the matrix of every element through the matrix's own insertion.  On 1-3 ranks."""
    from rodsnes.model import assembly
    run = perturbed(build_run("mattiasson", rod_nelem=12, rod_error_estimate="off",
                              bc_start="pinned", bc_end="sliding", bc_end_turns=1.0), lam=0.4)
    p = run.problem
    X = p.state.X
    J = p.layout.create_matrix(p.node_groups(p.patterns), symmetric=True) if symmetric else p.J
    p.jacobian(None, X, J, J, symmetric=symmetric)
    blocks = J.getAttr(assembly.ATTR)
    assert blocks is not None and blocks.rest_plan is not None
    end = p.mesh.n_nodes - 1
    free = [c for c in range(3) if not p.constraints.block_mask[p.layout.nat2petsc[end], c]]
    assert free                            # a sliding end: a position component free
    p.constraints.hold(end, free[0], 0.0)
    p.jacobian(None, X, J, J, symmetric=symmetric)
    assert J.getAttr(assembly.ATTR) is blocks                 # the places kept ...
    A = owned_dense(J)
    monkeypatch.setattr(problem_module.assembly, "element_blocks", lambda *a, **k: None)
    ref = J.duplicate()
    p.jacobian(None, X, ref, ref, symmetric=symmetric)
    assert_bitwise_equal(A, owned_dense(ref))                 # ... the new mask taken
    lo = J.getOwnershipRange()[0]
    for r in p.constraints.rows_global:                       # (held rows: the identity's)
        assert A[r - lo, r] == 1.0
    ref.destroy()
    if symmetric:
        J.destroy()
