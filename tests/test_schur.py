"""solve/schur.py: exact solves over several ranks by static condensation (RankSchur), the
default LU of a chain on more than one rank (solve/linear.py); its interior (the rank's
diagonal block, with the identity on the separator rows it owns while it is factored) taking new
values by re-assembly, by ADD_VALUES without zeroEntries, under -mat_type aij and after a
failed factorisation, on 2 and 3 ranks (make test-mpi, or mpirun -n 3 --oversubscribe)."""
import numpy as np
import pytest
from petsc4py import PETSc

from conftest import build_run, perturb_state
from rodsnes.solve import schur


class _Ranges:
    """What separator reads of a matrix: block size and ownership ranges."""

    def __init__(self, bs, ranges):
        self.bs, self.ranges = bs, np.asarray(ranges)

    def getBlockSize(self):
        return self.bs

    def getOwnershipRanges(self):
        return self.ranges * self.bs


def test_the_separator_cuts_every_coupling_between_ranks():
    """On a chain of 12 cubic elements (37 nodes) owned by three ranks, and with node groups
    (contact pairs) spanning ranks: after removing the separator no group holds the interior
    nodes of two ranks; a cut between two elements costs one node (its first owner keeps the
    others), and the nodes next to it are those that share a group with it."""
    run = build_run("mattiasson", rod_nelem=12)
    p = run.problem
    n = p.mesh.n_nodes
    assert np.array_equal(p.layout.nat2petsc, np.arange(n))     # serial: natural order
    # ranks own nodes 0-11, 12-23, 24-36: cut at the element ends 12 and 24 (as the layout
    # cuts between elements); the groups' nodes (natural) in the serial layout's numbering
    for ranges, extra in (([0, 12, 24, n], None),
                          ([0, 12, 24, n], np.array([[0, 1, 2, 3, 30, 31, 32, 33],
                                                     [4, 5, 6, 7, 14, 15, 16, 17]]))):
        p.patterns = [None] * len(p.terms)
        if extra is not None:
            p.node_groups = lambda pats, extra=extra: extra
        A = _Ranges(6, ranges)
        sep, near = schur.separator(p, A)
        owner = np.searchsorted(np.asarray(ranges), np.arange(n), side="right") - 1
        groups = [p.layout.nat2petsc[p.mesh.conn]]
        if extra is not None:
            groups.append(p.layout.nat2petsc[extra])
        for rows in groups:
            for g in rows:
                inner = g[~np.isin(g, sep)]
                assert len(np.unique(owner[inner])) <= 1, (g, sep)
                if np.isin(g, sep).any():
                    assert np.isin(inner, near).all()
        if extra is None:
            # a chain cut at two places: one node each, owned by the later rank
            assert list(sep) == [12, 24] and list(owner[sep]) == [1, 2]
        else:
            assert len(sep) > 2
        assert not np.isin(near, sep).any()
    # an element cut 1 + 3 (nodes 9 | 10 11 12): its one node is the separator, whoever owns it
    p.patterns = [None] * len(p.terms)
    p.node_groups = lambda pats: None
    sep, _ = schur.separator(p, _Ranges(6, [0, 10, 24, n]))
    assert list(sep) == [9, 24]


def _smooth(A):
    """(b, x): b = A x for a smooth x (a well-posed solve)."""
    x = A.createVecRight()
    lo, hi = x.getOwnershipRange()
    with x as a:
        a[:] = np.sin(0.01 * np.arange(lo, hi))
    b = x.duplicate()
    A.mult(x, b)
    return b, x


def _system(run):
    """The run's Jacobian at its start, and b = J x for a smooth x."""
    p = run.problem
    p.set_load(0.3)
    p.residual(None, p.state.X, p.F)
    p.jacobian(None, p.state.X, p.J, p.J)
    return (p.J,) + _smooth(p.J)


def _ksp(A, ctx):
    """KSP preonly with the python PC ``ctx`` on A."""
    ksp = PETSc.KSP().create(comm=A.getComm())
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType("python")
    pc.setPythonContext(ctx)
    ksp.setOperators(A)
    return ksp


def _solve(A, b, ctx):
    y = b.duplicate()
    _ksp(A, ctx).solve(b, y)
    return y


def _backward(A, b, v):
    """Normwise backward error |A v - b| / (|A| |v| + |b|)."""
    r = b.duplicate()
    A.mult(v, r)
    r.axpy(-1.0, b)
    return r.norm() / (A.norm(PETSc.NormType.INFINITY) * v.norm() + b.norm())


def _lu(A, b):
    """PETSc's LU of the whole matrix on every rank: the reference solution."""
    ksp = PETSc.KSP().create(comm=A.getComm())
    ksp.setType("preonly")
    ksp.getPC().setType("redundant")
    ksp.setOperators(A)
    x = b.duplicate()
    ksp.solve(b, x)
    return x


def _condensed_problem(monkeypatch, case, **kw):
    """On several ranks (skipped on one), condensed however short: the case's problem at load
    0.3 with its Jacobian assembled."""
    if PETSc.COMM_WORLD.getSize() == 1:
        pytest.skip("several ranks only (make test-mpi)")
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK", 0)
    p = build_run(case, **kw).problem
    p.set_load(0.3)
    p.jacobian(None, p.state.X, p.J, p.J)
    return p


TEN_TURNS = __import__("os").path.join(__import__("os").path.dirname(__file__), "data",
                                       "plectoneme_10")


def _interior_lu(ctx):
    """The kept object of the rank's interior LU: its chain LU (chain.py) or its KSP."""
    k = ctx.kept
    return k["chain"] if k["chain"] is not None else k["ksp"].handle


@pytest.mark.mpi
@pytest.mark.parametrize("case,kw,chains", [
    ("mattiasson", dict(rod_nelem=40, rod_planar="off"), True),
    ("mattiasson", dict(rod_nelem=40, rod_planar="off"), False),
    ("michell", dict(rod_nelem=24), False),
    # contact pairs and the mounts' end couplings across ranks
    ("plectoneme", dict(restart=TEN_TURNS), False)])
def test_the_condensed_solve_is_the_lu_solve(case, kw, chains, monkeypatch):
    """On 2 ranks a chain (the cantilever) and a ring (michell: cut twice) solved by static
    condensation: the same solution as PETSc's LU of the whole matrix to round-off, by the
    condensation (a separator of one node per cut) and, above SCHUR_MAX, by the whole-matrix
    LU it falls back to; the second set-up of the same matrix reuses its blocks.  The
    cantilever's end stretches are factored by their own LU without fill (``chains``: chain.py,
    the inverse's trailing block without column solves), or by PETSc's LU with the separator's
    column solves (CHAIN_TAIL_MAX < 0), as the ring's stretches, cut at both ends, and the
    plectoneme's, filled by contact, are."""
    if PETSc.COMM_WORLD.getSize() == 1:
        pytest.skip("several ranks only (make test-mpi)")
    if case == "plectoneme" and PETSc.COMM_WORLD.getSize() > 2:
        pytest.skip("60 elements on more than 2 ranks: a separator above SCHUR_MAX")
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK", 0)      # condensed however short
    if not chains:
        monkeypatch.setattr(schur, "CHAIN_TAIL_MAX", -1)
    run = build_run(case, **kw)
    A, b, x = _system(run)
    xr = _lu(A, b)
    ctx = schur.RankSchur(run.problem)
    y = _solve(A, b, ctx)
    assert ctx.mode == "schur" and ctx.setups == {"schur": 1, "whole": 0}
    size = PETSc.COMM_WORLD.getSize()
    # the end stretches of a chain have the separator at one end (a middle one at both: its
    # chain LU only where it is as short as CHAIN_TAIL_MAX)
    chained = PETSc.COMM_WORLD.tompi4py().allgather(ctx.kept["chain"] is not None)
    assert (chained[0] and chained[-1]) if chains else not any(chained)
    cuts = size if run.mesh.closed else size - 1    # one node where consecutive stretches meet
    if case != "plectoneme":
        assert ctx.kept["sep"].size == cuts
    else:           # the contact pairs across the cut add their nodes
        assert ctx.kept["sep"].size > 1

    def error(v):
        e = v.copy()
        e.axpy(-1.0, x)
        return e.norm() / x.norm()

    def as_accurate(v):
        """As accurate as the LU: backward stable as the LU is (backward errors 4e-17 -
        1.2e-16 for both on 2 to 4 ranks; a missed coupling would be O(1)), and the forward
        error, which the Jacobian's condition number makes 1e-9 - 1e-7 for both, of that
        order (it is not a fixed multiple of the LU's: on 3 ranks the michell ring's two
        separators gave 3.7e-8 against 6.7e-9)."""
        return _backward(A, b, v) <= 1e-14 and error(v) < 1e-6
    assert error(xr) < 1e-6 and as_accurate(y), (_backward(A, b, y), error(y), error(xr))
    # a new set-up of the same matrix with new values keeps the blocks and takes the values
    # (2 A: half the solution; stale blocks would give another)
    # the matrix is A as it was: the diagonal block's separator rows and columns, the
    # identity's while factored, have their values back
    Ay, Ay2 = y.duplicate(), y.duplicate()
    A.mult(y, Ay)
    _solve(A, b, schur.RankSchur(run.problem))
    A.mult(y, Ay2)
    assert Ay.equal(Ay2)
    kept, lu_kept = ctx.kept, _interior_lu(ctx)     # the condensation's blocks and interior LU
    A.scale(2.0)
    y2 = _solve(A, b, ctx)
    A.scale(0.5)
    assert ctx.kept is kept and _interior_lu(ctx) == lu_kept and ctx.setups["schur"] == 2
    d = y2.copy()
    d.axpy(-0.5, y)
    assert d.norm() <= 1e-12 * y.norm()
    monkeypatch.setattr(schur, "SCHUR_MAX", 0)
    whole = schur.RankSchur(run.problem)
    yw = _solve(A, b, whole)
    assert whole.mode == "whole"
    assert as_accurate(yw)
    # a rod shorter than MIN_NODES_PER_RANK a rank: the whole matrix too
    monkeypatch.setattr(schur, "SCHUR_MAX", 600)
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK", 4000)
    whole = schur.RankSchur(run.problem)
    yw = _solve(A, b, whole)
    assert whole.mode == "whole"
    assert as_accurate(yw)


@pytest.mark.mpi
def test_the_planar_cantilever_by_condensation_is_the_serial_run(monkeypatch):
    """The planar cantilever (in-plane blocks of block size 3) on 2 ranks, condensed however
    short: the same iterations, energy and tip as on one rank."""
    if PETSc.COMM_WORLD.getSize() == 1:
        pytest.skip("several ranks only (make test-mpi)")
    from conftest import run_case
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK", 0)
    par = run_case("mattiasson", rod_nelem=40, load_path="newton", rod_error_estimate="off")
    ser = run_case("mattiasson", comm=PETSc.COMM_SELF, rod_nelem=40, load_path="newton",
                   rod_error_estimate="off",
                   outdir=par.outdir + f"_s{PETSc.COMM_WORLD.getRank()}")
    assert par.ok and ser.ok and par.problem.planar is not None
    pc = par.problem.planar.ksp.getPC()
    assert pc.getType() == "python" and pc.getPythonContext().setups["schur"] > 0
    assert [h["newton_iterations"] for h in par.history] == \
        [h["newton_iterations"] for h in ser.history]
    sp, ss = par.summary(converged=True), ser.summary(converged=True)
    assert sp["energy"] == pytest.approx(ss["energy"], rel=1e-11)
    assert np.abs(np.subtract(sp["tip_position"], ss["tip_position"])).max() < 1e-10


@pytest.mark.mpi
@pytest.mark.parametrize("tail_max", [schur.CHAIN_TAIL_MAX, -1])
def test_a_failed_interior_fails_on_every_rank(tail_max, monkeypatch):
    """An interior factorisation that fails on one rank (a NaN in its block): the KSP fails on
    every rank as at a failed LU (DIVERGED_PCSETUP_FAILED, the solution not finite: the Newton
    step fails), and no rank waits for another.  By the chain LU and by PETSc's LU
    (CHAIN_TAIL_MAX < 0)."""
    if PETSc.COMM_WORLD.getSize() == 1:
        pytest.skip("several ranks only (make test-mpi)")
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK", 0)
    monkeypatch.setattr(schur, "CHAIN_TAIL_MAX", tail_max)
    run = build_run("mattiasson", rod_nelem=40, rod_planar="off")
    A, b, _ = _system(run)
    lo, hi = A.getOwnershipRange()
    if PETSc.COMM_WORLD.getRank() == 0:
        A.setValue(lo + 12, lo + 12, np.nan, addv=PETSc.InsertMode.INSERT_VALUES)
    A.assemble()
    ctx = schur.RankSchur(run.problem)
    ksp = _ksp(A, ctx)
    y = b.duplicate()
    ksp.solve(b, y)
    assert ctx.failed
    assert ksp.getConvergedReason() == PETSc.KSP.ConvergedReason.DIVERGED_PCSETUP_FAILED
    with y as a:
        assert not np.isfinite(a).any()


# -- the interior takes new values (RankSchur._factor_interior) --------------------------
def _check(ksp, A, p):
    """ksp's solution of A x = b for a smooth x (b = A x) is a fresh RankSchur's (the kept
    blocks hold A's values: a stale block would differ at O(1)) and within a loose factor of
    the LU's error (at a perturbed state the condensation's error is 3-250 x the LU's, 1e-9 to
    1e-6, on 2-4 ranks, as with an extracted interior)."""
    b, x = _smooth(A)
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
@pytest.mark.parametrize("tail_max", [schur.CHAIN_TAIL_MAX, -1])
def test_the_condensed_solve_follows_new_values(case, kw, tail_max, monkeypatch):
    """On 2 or 3 ranks (on the chain some rank owns no separator node, its interior is its
    diagonal block itself; on the ring every rank owns one): the condensed solve equals the LU's for the first
    Jacobian, for a re-assembled one at another state (zeroEntries and ADD_VALUES), and for
    entries added without zeroEntries (ADD_VALUES then assembly, separator rows included); the
    interior is the diagonal block each time (PETSc's LU: no copy; the chain LU copies its
    values at each factorisation).  By the chain LU where it applies and by PETSc's LU
    (CHAIN_TAIL_MAX < 0)."""
    monkeypatch.setattr(schur, "CHAIN_TAIL_MAX", tail_max)
    comm = PETSc.COMM_WORLD
    p = _condensed_problem(monkeypatch, case, **kw)
    A = p.J
    ctx = schur.RankSchur(p)
    ksp = _ksp(A, ctx)
    _check(ksp, A, p)
    assert ctx.mode == "schur"
    mpi = comm.tompi4py()
    owners = mpi.allgather(len(ctx.kept["G"]) > 0)
    # both kinds of interior: the diagonal block as it is (a rank owning no separator node)
    # and with separator rows; on the ring every rank owns one (a cut 3 + 1 on each side)
    assert any(owners)
    assert all(owners) if case == "michell" else not all(owners)
    kept, lu_kept = ctx.kept, _interior_lu(ctx)     # the condensation's blocks and interior LU
    # another state: a re-assembled Jacobian (P.zeroEntries, blocks added)
    perturb_state(p, scale=3e-3)
    p.jacobian(None, p.state.X, p.J, p.J)
    _check(ksp, A, p)
    assert ctx.kept is kept and _interior_lu(ctx) == lu_kept and ctx.setups["schur"] == 2
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
    assert ctx.kept is kept and _interior_lu(ctx) == lu_kept and ctx.setups["schur"] == 3


@pytest.mark.mpi
@pytest.mark.parametrize("tail_max", [schur.CHAIN_TAIL_MAX, -1])
def test_the_condensed_solve_recovers_after_a_failed_interior(tail_max, monkeypatch):
    """A NaN in one rank's interior fails the solve on every rank; the next Jacobian (same
    matrix, sane values) is solved right by the same PC: the interior's factor is redone on
    every rank, the one holding its diagonal block itself included.  By the chain LU and by
    PETSc's LU (CHAIN_TAIL_MAX < 0)."""
    monkeypatch.setattr(schur, "CHAIN_TAIL_MAX", tail_max)
    comm = PETSc.COMM_WORLD
    p = _condensed_problem(monkeypatch, "mattiasson", rod_nelem=60, rod_planar="off")
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
    try:
        p = _condensed_problem(monkeypatch, "mattiasson", rod_nelem=60, rod_planar="off",
                               mat_type="aij")
        assert "aij" in p.J.getType() and "baij" not in p.J.getType()
        A = p.J
        ctx = schur.RankSchur(p)
        ksp = _ksp(A, ctx)
        _check(ksp, A, p)
        assert ctx.mode == "schur"
        perturb_state(p, scale=3e-3)
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
@pytest.mark.parametrize("tail_max", [schur.CHAIN_TAIL_MAX, -1])
def test_a_middle_rank_owning_separator_nodes_on_both_sides(tail_max, monkeypatch):
    """3 ranks (or 2) owning the chain's cubic elements so that each cut is 3 + 1 with the
    lone node on the middle rank: it owns the separator on both sides (its diagonal block has
    the identity at both ends while factored), rank 0 none (its diagonal block as it is).  The
    solution is a fresh condensation's and the LU's, for the first values and for new values (2 A, then ADD_VALUES
    on the separator rows).  By the chain LU where it applies (the middle stretch here is
    short enough for its tail to be the whole of it) and by PETSc's LU (CHAIN_TAIL_MAX < 0)."""
    monkeypatch.setattr(schur, "CHAIN_TAIL_MAX", tail_max)
    comm = PETSc.COMM_WORLD
    size = comm.getSize()
    p = _condensed_problem(monkeypatch, "mattiasson", rod_nelem=20 * size, rod_planar="off")
    perturb_state(p, scale=1e-3)
    p.jacobian(None, p.state.X, p.J, p.J)
    bs = p.J.getBlockSize()
    nb = p.J.getSize()[0] // bs

    def owned(ranges):
        sep, _ = schur.separator(p, _Ranges(bs, ranges))
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


# -- interiors factored by MUMPS with its Schur complement (a contact-filled pattern) ----------
def test_mumps_forms_the_schur_complement_of_the_chosen_unknowns():
    """schur.set_schur_unknowns and schur_complement (PETSc's MatFactorSetSchurIS and
    MatFactorGetSchurComplement, which petsc4py 3.18 lacks, through ctypes) on a sparse matrix
    of block size 3: T = A_NN - A_NF A_FF^-1 A_FN to round-off, the factor's solve is A's, and
    a new factorisation of new values gives their T."""
    rng = np.random.default_rng(3)
    n = 60
    D = rng.standard_normal((n, n)) * (rng.random((n, n)) < 0.15) + 6.0 * np.eye(n)
    A = PETSc.Mat().createAIJ((n, n), bsize=3, comm=PETSc.COMM_SELF)
    A.setUp()
    rows, cols = np.nonzero(D)
    for i, j in zip(rows, cols):
        A.setValue(int(i), int(j), D[i, j])
    A.assemble()
    A = A.convert("baij")
    ksp = PETSc.KSP().create(comm=PETSc.COMM_SELF)
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType("lu")
    pc.setFactorSolverType("mumps")
    ksp.setOperators(A)
    pc.setFactorSetUpSolverType()
    near = np.arange(40, 55)
    far = np.setdiff1d(np.arange(n), near)
    schur.set_schur_unknowns(pc.getFactorMatrix(), near)
    ref = D[np.ix_(near, near)] - D[np.ix_(near, far)] @ np.linalg.solve(D[np.ix_(far, far)],
                                                                         D[np.ix_(far, near)])
    for scale in (1.0, 2.0):
        if scale != 1.0:
            A.scale(scale)
            ksp.setOperators(A)
        ksp.setUp()
        T = schur.schur_complement(pc.getFactorMatrix(), len(near))
        assert np.abs(T - scale * ref).max() <= 1e-13 * np.abs(ref).max()
        b = A.createVecLeft()
        b.setArray(rng.standard_normal(n))
        x = b.duplicate()
        ksp.solve(b, x)
        assert np.abs(scale * D @ x.getArray() - b.getArray()).max() <= 1e-13 * b.norm()


def _coil_system(elements):
    """The bench coil's Jacobian (turns touching along the rod: a pattern whose fill sends the
    LU to MUMPS, linear.FILL_MUMPS) and b = J x for a smooth x."""
    run = build_run("bench_coil", rod_nelem=elements, rod_length=0.02 * elements)
    return _system(run) + (run,)


@pytest.mark.mpi
def test_mumps_interiors_condense_a_contact_filled_pattern(monkeypatch):
    """The bench coil on several ranks, each rank's interior factored by MUMPS with the Schur
    complement of its unknowns next to the separator (no column solves): backward stable as
    MUMPS over the ranks, the solution within the LU's error of the smooth x; a second set-up
    takes new values (it solves 2 A y = b as well); above SCHUR_MAX the whole matrix by MUMPS over
    the ranks; a rank's interior that fails to factor (singular, NaN) fails the solve on every
    rank, and the same PC solves the next Jacobian."""
    if PETSc.COMM_WORLD.getSize() == 1:
        pytest.skip("several ranks only (make test-mpi)")
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK_MUMPS", 0)
    A, b, x, run = _coil_system(120 * PETSc.COMM_WORLD.getSize())
    ctx = schur.RankSchur(run.problem, package="mumps")
    y = _solve(A, b, ctx)
    assert ctx.mode == "schur" and ctx.setups == {"schur": 1, "whole": 0}
    assert ctx.kept["sep"].size > 2 and ctx.kept["nn"] > 0     # contact across the cuts
    monkeypatch.setattr(schur, "SCHUR_MAX", 0)
    whole = schur.RankSchur(run.problem, package="mumps")
    opts = PETSc.Options()
    opts["rodsnes_whole_mumps_mat_mumps_icntl_14"] = "80"        # as a user would
    wksp = _ksp(A, whole)
    yw = b.duplicate()
    wksp.solve(b, yw)
    assert whole.mode == "whole"
    assert whole.whole.getPC().getFactorSolverType() == "mumps"
    assert whole.whole.getPC().getFactorMatrix().getMumpsIcntl(14) == 80    # the user's
    # rodsnes' defaults for the whole matrix's prefix leave with the last RankSchur using them;
    # the user's stays
    assert opts.hasName("rodsnes_whole_mumps_pc_factor_mat_solver_type")
    wksp.destroy()
    assert not opts.hasName("rodsnes_whole_mumps_pc_factor_mat_solver_type")
    assert opts.getString("rodsnes_whole_mumps_mat_mumps_icntl_14") == "80"
    opts.delValue("rodsnes_whole_mumps_mat_mumps_icntl_14")
    # backward errors 1e-16 - 1e-15 (a missed coupling: O(1)); forward errors of the smooth x
    # 3.6e-9 against MUMPS's 4.7e-10 (the condensation's, as with PETSc's LU interiors, above)
    stable = max(10.0 * _backward(A, b, yw), 1e-15)
    error = lambda v: np.sqrt(abs((v - x).dot(v - x))) / x.norm()
    assert _backward(A, b, y) <= stable and error(y) < 1e-6
    monkeypatch.setattr(schur, "SCHUR_MAX", 600)
    A.scale(2.0)
    y2 = _solve(A, b, ctx)
    assert ctx.setups["schur"] == 2 and _backward(A, b, y2) <= stable
    # rank 0's interior singular (a zero row: MUMPS's INFOG(1) < 0, no error raised) or NaN:
    # the solve fails everywhere (not finite), no rank waiting; the next sane Jacobian is
    # solved by the same PC
    p = run.problem
    lo, _ = A.getOwnershipRange()
    bad = schur.RankSchur(p, package="mumps")
    first = PETSc.COMM_WORLD.getRank() == 0
    for spoil in ("singular", "nan"):
        if spoil == "singular":
            A.zeroRows([lo + 12] if first else [], diag=0.0)
        else:
            if first:
                A.setValue(lo + 12, lo + 12, np.nan, addv=PETSc.InsertMode.INSERT_VALUES)
            A.assemble()
        yb = _solve(A, b, bad)
        assert bad.failed, (spoil, bad.mode)
        with yb as a:
            assert not np.isfinite(a).any()
        p.jacobian(None, p.state.X, p.J, p.J)
        b2, _ = _smooth(A)
        y3 = _solve(A, b2, bad)
        assert not bad.failed and _backward(A, b2, y3) <= stable


@pytest.mark.mpi
def test_the_header_says_when_the_ranks_cannot_share_the_factorisation():
    """A rod below the condensation's size on several ranks: the run's first line says that
    every rank factors the whole matrix; on one rank, or long enough, it says nothing of it."""
    from conftest import build_run
    short = build_run("mattiasson", rod_nelem=8).header()
    said = "every rank factors the whole matrix" in short
    assert said == (PETSc.COMM_WORLD.getSize() > 1)
    assert "too few to share" not in build_run("mattiasson", rod_nelem=2000).header()


def test_the_separators_dense_lu():
    """The Schur complement's LU (LAPACK getrf and getrs called directly): the solve of a
    regular matrix for vector and matrix right-hand sides, None for a singular or non-finite
    one (the caller fails the PC)."""
    from rodsnes.solve.schur import _dense_lu, _lu_solve
    rng = np.random.default_rng(3)
    S = rng.standard_normal((6, 6)) + 6 * np.eye(6)
    lu = _dense_lu(S)
    for b in (rng.standard_normal(6), rng.standard_normal((6, 3))):
        assert np.allclose(S @ _lu_solve(lu, b), b, rtol=1e-12, atol=1e-12)
    S[3] = 0.0                                   # an exact zero pivot
    assert _dense_lu(S) is None
    assert _dense_lu(np.array([[1.0, np.inf], [0.0, 1.0]])) is None
    assert _dense_lu(np.array([[np.nan]])) is None
