"""RankSchur's kept interior (the rank's diagonal block, or a kept copy of it with the identity
on the separator rows it owns): the condensed solve against a fresh RankSchur and PETSc's LU on
2 and 3 ranks (make test-mpi, or mpirun -n 3 --oversubscribe; a middle rank owning separator
nodes on both sides, a ring whose separator node 0 is rank 0's) for new values by re-assembly,
by ADD_VALUES without zeroEntries, under -mat_type aij, and after a failed factorisation."""
import numpy as np
import pytest
from petsc4py import PETSc

from conftest import build_run
from rodsnes.solve import schur


# -- helpers ---------------------------------------------------------------------------------
def _perturb(p, scale=1e-3, seed=3):
    """A deterministic small motion of every unconstrained dof (same on any number of ranks:
    drawn for the global dofs, each rank takes its own)."""
    X = p.state.X
    lo, hi = X.getOwnershipRange()
    n = X.getSize()
    rng = np.random.default_rng(seed)
    d = rng.normal(size=n) * scale
    with X as a:
        free = np.ones(hi - lo, dtype=bool)
        free[p.constraints.rows_local] = False
        a[free] += d[lo:hi][free]


def _lu(A, b):
    ksp = PETSc.KSP().create(comm=A.getComm())
    ksp.setType("preonly")
    ksp.getPC().setType("redundant")
    ksp.setOperators(A)
    x = b.duplicate()
    ksp.solve(b, x)
    return x


def _ksp(A, ctx):
    ksp = PETSc.KSP().create(comm=A.getComm())
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType("python")
    pc.setPythonContext(ctx)
    ksp.setOperators(A)
    return ksp


def _check(ksp, A, p):
    """ksp's solution of A x = b for a smooth x (b = A x) is a fresh RankSchur's (the kept
    blocks hold A's values: a stale block would differ at O(1)) and within a loose factor of
    the LU's error (at a perturbed state the condensation's error is 3-250 x the LU's, 1e-9 to
    1e-6, on 2-4 ranks, as with an extracted interior)."""
    x = A.createVecRight()
    lo, hi = x.getOwnershipRange()
    with x as a:
        a[:] = np.sin(0.01 * np.arange(lo, hi))
    b = x.duplicate()
    A.mult(x, b)
    y = b.duplicate()
    ksp.solve(b, y)
    fresh = b.duplicate()
    _ksp(A, schur.RankSchur(p)).solve(b, fresh)

    def err(v, ref=x):
        d = v.copy()
        d.axpy(-1.0, ref)
        return d.norm() / ref.norm()
    e, e_lu = err(y), err(_lu(A, b))
    assert err(y, fresh) <= 1e-12, err(y, fresh)
    assert e <= 1e3 * e_lu + 1e-9 and e_lu < 1e-3, (e, e_lu)
    return y


@pytest.mark.mpi
@pytest.mark.parametrize("case,kw", [("mattiasson", dict(rod_nelem=60, rod_planar="off")),
                                     ("michell", dict(rod_nelem=48))])
def test_the_condensed_solve_follows_new_values(case, kw, monkeypatch):
    """On 2 or 3 ranks (on the chain some rank owns no separator node, its interior is its
    diagonal block itself; on the ring every rank owns one): the condensed solve equals the LU's for the first
    Jacobian, for a re-assembled one at another state (zeroEntries and ADD_VALUES), and for
    entries added without zeroEntries (ADD_VALUES then assembly, separator rows included); the
    kept interior is reused (the same object) each time."""
    comm = PETSc.COMM_WORLD
    if comm.getSize() == 1:
        pytest.skip("several ranks only (make test-mpi)")
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK", 0)
    p = build_run(case, **kw).problem
    p.set_load(0.3)
    p.jacobian(None, p.state.X, p.J, p.J)
    A = p.J
    ctx = schur.RankSchur(p)
    ksp = _ksp(A, ctx)
    _check(ksp, A, p)
    assert ctx.mode == "schur"
    mpi = comm.tompi4py()
    owners = mpi.allgather(len(ctx.kept["G"]) > 0)
    # both kinds of interior: the diagonal block itself (a rank owning no separator node)
    # and the kept copy; on the ring every rank owns one (a cut 3 + 1 on each side)
    assert any(owners)
    assert all(owners) if case == "michell" else not all(owners)
    kept = ctx.kept["AII"]
    # another state: a re-assembled Jacobian (P.zeroEntries, blocks added)
    _perturb(p, scale=3e-3)
    p.jacobian(None, p.state.X, p.J, p.J)
    _check(ksp, A, p)
    assert ctx.kept["AII"] is kept and ctx.setups["schur"] == 2
    # entries added to an assembled matrix (no zeroEntries): on every rank's first, last and
    # separator rows
    lo, hi = A.getOwnershipRange()
    bs = A.getBlockSize()
    rows = {lo, lo + 1, hi - 1}
    rows |= {int(lo + g) for g in ctx.kept["G"][:bs]}
    for r in sorted(rows):
        A.setValue(r, r, 5.0e3 * (1 + r % 7), addv=PETSc.InsertMode.ADD_VALUES)
    A.assemble()
    _check(ksp, A, p)
    assert ctx.kept["AII"] is kept and ctx.setups["schur"] == 3


@pytest.mark.mpi
def test_the_condensed_solve_recovers_after_a_failed_interior(monkeypatch):
    """A NaN in one rank's interior fails the solve on every rank; the next Jacobian (same
    matrix, sane values) is solved right by the same PC: the interior's factor is redone on
    every rank, the one holding its diagonal block itself included."""
    comm = PETSc.COMM_WORLD
    if comm.getSize() == 1:
        pytest.skip("several ranks only (make test-mpi)")
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK", 0)
    p = build_run("mattiasson", rod_nelem=60, rod_planar="off").problem
    p.set_load(0.3)
    for bad in range(comm.getSize()):
        p.jacobian(None, p.state.X, p.J, p.J)
        A = p.J
        lo, _ = A.getOwnershipRange()
        if comm.getRank() == bad:
            A.setValue(lo + 20, lo + 20, np.nan, addv=PETSc.InsertMode.INSERT_VALUES)
        A.assemble()
        ctx = schur.RankSchur(p)
        ksp = _ksp(A, ctx)
        y = A.createVecLeft()
        ksp.solve(y.duplicate(), y)
        assert ctx.failed
        p.jacobian(None, p.state.X, p.J, p.J)
        _check(ksp, A, p)
        assert not ctx.failed and ctx.setups["schur"] == 2


@pytest.mark.mpi
def test_the_condensed_solve_of_an_aij_jacobian(monkeypatch):
    """-mat_type aij: the interior is a SeqAIJ diagonal block (its copy zeroed by
    MatZeroRowsColumns_SeqAIJ, copied with SAME_NONZERO_PATTERN at the next set-up): the LU's
    solution at two states."""
    comm = PETSc.COMM_WORLD
    if comm.getSize() == 1:
        pytest.skip("several ranks only (make test-mpi)")
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK", 0)
    try:
        p = build_run("mattiasson", rod_nelem=60, rod_planar="off", mat_type="aij").problem
        assert "aij" in p.J.getType() and "baij" not in p.J.getType()
        p.set_load(0.3)
        p.jacobian(None, p.state.X, p.J, p.J)
        A = p.J
        ctx = schur.RankSchur(p)
        ksp = _ksp(A, ctx)
        _check(ksp, A, p)
        assert ctx.mode == "schur"
        _perturb(p, scale=3e-3)
        p.jacobian(None, p.state.X, p.J, p.J)
        _check(ksp, A, p)
        assert ctx.setups["schur"] == 2
    finally:
        PETSc.Options().delValue("mat_type")


def _redistributed(A, ranges):
    """A copy of A (MPIBAIJ, same global numbering) whose ranks own the block rows
    [ranges[r], ranges[r + 1]): ownerships the layout does not make."""
    comm = A.getComm()
    bs = A.getBlockSize()
    n = A.getSize()[0]
    every = PETSc.IS().createStride(n, 0, 1, comm=PETSc.COMM_SELF)
    (full,) = A.createSubMatrices([every], [every])
    ai, aj, av = full.getValuesCSR()
    r = comm.getRank()
    lo, hi = bs * ranges[r], bs * ranges[r + 1]
    B = PETSc.Mat().create(comm=comm)
    B.setSizes(((hi - lo, n), (hi - lo, n)), bsize=bs)
    B.setType(PETSc.Mat.Type.BAIJ)
    B.setBlockSize(bs)
    rows = np.arange(lo, hi)
    cols = [aj[ai[i]:ai[i + 1]] // bs for i in rows[::bs]]
    own = lambda c: (c >= lo // bs) & (c < hi // bs)
    B.setPreallocationNNZ(([int(own(np.unique(c)).sum()) for c in cols],
                           [int((~own(np.unique(c))).sum()) for c in cols]))
    for i in rows:
        B.setValues([i], aj[ai[i]:ai[i + 1]], av[ai[i]:ai[i + 1]])
    B.assemble()
    return B


@pytest.mark.mpi
def test_a_middle_rank_owning_separator_nodes_on_both_sides(monkeypatch):
    """3 ranks (or 2) owning the chain's cubic elements so that each cut is 3 + 1 with the
    lone node on the middle rank: it owns the separator on both sides (its kept copy has the
    identity at both ends), rank 0 none (its diagonal block itself).  The solution is a fresh
    condensation's and the LU's, for the first values and for new values (2 A, then ADD_VALUES
    on the separator rows)."""
    comm = PETSc.COMM_WORLD
    size = comm.getSize()
    if size == 1:
        pytest.skip("several ranks only (make test-mpi)")
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK", 0)
    p = build_run("mattiasson", rod_nelem=20 * size, rod_planar="off").problem
    p.set_load(0.3)
    _perturb(p, scale=1e-3)
    p.jacobian(None, p.state.X, p.J, p.J)
    bs = p.J.getBlockSize()
    nb = p.J.getSize()[0] // bs

    class Ranges:                       # what separator reads of a matrix
        def __init__(self, ranges):
            self.ranges = np.asarray(ranges)

        def getBlockSize(self):
            return bs

        def getOwnershipRanges(self):
            return self.ranges * bs

    def owned(ranges):
        sep, _ = schur.separator(p, Ranges(ranges))
        return np.bincount(np.searchsorted(ranges, sep, side="right") - 1, minlength=size)

    # cuts near the even ones (in PETSc's numbering) with the middle rank (rank 1) owning
    # separator nodes on both sides (one on 2 ranks) and rank 0 none
    want = 2 if size >= 3 else 1
    even = [int(round(nb * (i + 1) / size)) for i in range(size - 1)]
    ranges = None
    for d1 in range(-6, 7):
        for d2 in (range(-6, 7) if size >= 3 else [0]):
            cuts = list(even)
            cuts[0] += d1
            if size >= 3:
                cuts[1] += d2
            r = [0] + cuts + [nb]
            o = owned(r)
            if o[0] == 0 and o[1] == want:
                ranges = r
                break
        if ranges is not None:
            break
    assert ranges is not None
    A = _redistributed(p.J, ranges)
    ctx = schur.RankSchur(p)
    ksp = _ksp(A, ctx)
    _check(ksp, A, p)
    assert ctx.mode == "schur"
    G = comm.tompi4py().allgather(len(ctx.kept["G"]) // A.getBlockSize())
    assert G[0] == 0 and G[1] == (2 if size >= 3 else 1), (G, ranges, list(ctx.kept["sep"]))
    A.scale(2.0)
    _check(ksp, A, p)
    lo, hi = A.getOwnershipRange()
    for g in ctx.kept["G"]:
        A.setValue(lo + int(g), lo + int(g), 1.0e4, addv=PETSc.InsertMode.ADD_VALUES)
    A.assemble()
    _check(ksp, A, p)
    assert ctx.setups["schur"] == 3
