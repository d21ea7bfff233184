"""solve/schur.py: exact solves over several ranks by static condensation (RankSchur), the
default LU of a chain on more than one rank (solve/linear.py)."""
import numpy as np
import pytest
from petsc4py import PETSc

from conftest import build_run
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


def _system(run):
    """The run's Jacobian at its start, and b = J x for a smooth x (a well-posed solve)."""
    p = run.problem
    p.set_load(0.3)
    p.residual(None, p.state.X, p.F)
    p.jacobian(None, p.state.X, p.J, p.J)
    A = p.J
    x = A.createVecRight()
    lo, hi = x.getOwnershipRange()
    with x as a:
        a[:] = np.sin(0.01 * np.arange(lo, hi))
    b = x.duplicate()
    A.mult(x, b)
    return A, b, x


def _solve(A, b, ctx):
    ksp = PETSc.KSP().create(comm=A.getComm())
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType("python")
    pc.setPythonContext(ctx)
    ksp.setOperators(A)
    y = b.duplicate()
    ksp.solve(b, y)
    return y


TEN_TURNS = __import__("os").path.join(__import__("os").path.dirname(__file__), "data",
                                       "plectoneme_10")


@pytest.mark.mpi
@pytest.mark.parametrize("case,kw", [("mattiasson", dict(rod_nelem=40, rod_planar="off")),
                                     ("michell", dict(rod_nelem=24)),
                                     # contact pairs and the mounts' end couplings across ranks
                                     ("plectoneme", dict(restart=TEN_TURNS))])
def test_the_condensed_solve_is_the_lu_solve(case, kw, monkeypatch):
    """On 2 ranks a chain (the cantilever) and a ring (michell: cut twice) solved by static
    condensation: the same solution as PETSc's LU of the whole matrix to round-off, by the
    condensation (a separator of one node per cut) and, above SCHUR_MAX, by the whole-matrix
    LU it falls back to; the second set-up of the same matrix reuses its blocks."""
    if PETSc.COMM_WORLD.getSize() == 1:
        pytest.skip("several ranks only (make test-mpi)")
    if case == "plectoneme" and PETSc.COMM_WORLD.getSize() > 2:
        pytest.skip("60 elements on more than 2 ranks: a separator above SCHUR_MAX")
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK", 0)      # condensed however short
    run = build_run(case, **kw)
    A, b, x = _system(run)
    ref = PETSc.KSP().create(comm=A.getComm())
    ref.setType("preonly")
    ref.getPC().setType("redundant")
    ref.setOperators(A)
    xr = b.duplicate()
    ref.solve(b, xr)
    ctx = schur.RankSchur(run.problem)
    y = _solve(A, b, ctx)
    assert ctx.mode == "schur" and ctx.setups == {"schur": 1, "whole": 0}
    size = PETSc.COMM_WORLD.getSize()
    cuts = size if run.mesh.closed else size - 1    # one node where consecutive stretches meet
    if case != "plectoneme":
        assert ctx.kept["sep"].size == cuts
    else:           # the contact pairs across the cut add their nodes
        assert ctx.kept["sep"].size > 1

    def error(v):
        e = v.copy()
        e.axpy(-1.0, x)
        return e.norm() / x.norm()
    # as accurate as the LU (both backward stable; the Jacobian's condition number makes both
    # errors ~1e-9 here); the plectoneme's ply has a near-zero mode (an eigenvalue ~1e-9 of the
    # diagonal), along which the two round-offs differ more: 4e-8 against 8e-10 (a missed
    # coupling would be O(1))
    slack = 1e-7 if case == "plectoneme" else 1e-13
    assert error(y) <= 3.0 * error(xr) + slack and error(xr) < 1e-6
    # a new set-up of the same matrix with new values keeps the blocks and takes the values
    # (2 A: half the solution; stale blocks would give another)
    kept = ctx.kept["AII"]
    A.scale(2.0)
    y2 = _solve(A, b, ctx)
    A.scale(0.5)
    assert ctx.kept["AII"] is kept and ctx.setups["schur"] == 2
    d = y2.copy()
    d.axpy(-0.5, y)
    assert d.norm() <= 1e-12 * y.norm()
    monkeypatch.setattr(schur, "SCHUR_MAX", 0)
    whole = schur.RankSchur(run.problem)
    yw = _solve(A, b, whole)
    assert whole.mode == "whole"
    assert error(yw) <= 3.0 * error(xr) + slack
    # a rod shorter than MIN_NODES_PER_RANK a rank: the whole matrix too
    monkeypatch.setattr(schur, "SCHUR_MAX", 600)
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK", 4000)
    whole = schur.RankSchur(run.problem)
    yw = _solve(A, b, whole)
    assert whole.mode == "whole"
    assert error(yw) <= 3.0 * error(xr) + slack


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
def test_a_failed_interior_fails_on_every_rank(monkeypatch):
    """An interior factorisation that fails on one rank (a NaN in its block): the solution is
    NaN on every rank (the Newton step fails as a failed LU does), and no rank waits for
    another."""
    if PETSc.COMM_WORLD.getSize() == 1:
        pytest.skip("several ranks only (make test-mpi)")
    monkeypatch.setattr(schur, "MIN_NODES_PER_RANK", 0)
    run = build_run("mattiasson", rod_nelem=40, rod_planar="off")
    A, b, _ = _system(run)
    lo, hi = A.getOwnershipRange()
    if PETSc.COMM_WORLD.getRank() == 0:
        A.setValue(lo + 12, lo + 12, np.nan, addv=PETSc.InsertMode.INSERT_VALUES)
    A.assemble()
    ctx = schur.RankSchur(run.problem)
    y = _solve(A, b, ctx)
    assert ctx.failed
    with y as a:
        assert np.isnan(a).all()
