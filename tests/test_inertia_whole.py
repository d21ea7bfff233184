"""stability.Inertia's whole-on-every-rank factorisation: a failed
factorisation (a Dirichlet row and column made exactly zero by the shift) returns -1 on every
rank and the next factor recovers, as with MUMPS over the ranks; the planar BlockInertia
(block size 3) counts and solves alike both ways; destroy() leaves nothing behind."""
import numpy as np
import pytest

from conftest import inertia_solve, run_case


def _singular_shift(inertia, p):
    """A shift that zeroes the diagonal of the first Dirichlet row (its row and column are
    otherwise zero): H + diag(s) exactly singular."""
    s = inertia.diagonal.duplicate()
    s.set(0.0)
    rows = np.asarray(p.constraints.rows_local)
    with s as a, inertia.diagonal as d:
        if len(rows):
            a[rows[0]] = -d[rows[0]]
    return s


@pytest.mark.mpi
def test_a_failed_factorisation_is_minus_one_on_every_rank_and_the_next_recovers():
    from rodsnes.solve.stability import Inertia
    run = run_case("euler", rod_imperfection=0.0, load_path="newton", rod_planar="off",
                   load_end_force="%r,0,0" % (-1.2 * np.pi ** 2 / 4), load_steps=4)
    p = run.problem
    comm = p.layout.comm.tompi4py()
    got = {}
    for name, big in (("whole", None), ("spread", 0)):
        inertia = Inertia(p)
        if big is not None:
            inertia.REDUNDANT_MAX = big
        inertia.assemble()
        s = _singular_shift(inertia, p)
        bad = inertia.factor(s)
        good = inertia.factor()
        again = inertia.factor(s)
        good2 = inertia.factor()
        got[name] = (bad, good, again, good2)
        s.destroy()
        inertia.destroy()
        assert inertia.pc is None and inertia.H is None and inertia.whole is None
    assert got["whole"] == got["spread"] == (-1, 2, -1, 2), got
    assert comm.allgather(got["whole"]) == [got["whole"]] * comm.size


@pytest.mark.mpi
def test_the_planar_block_inertia_whole_equals_spread(monkeypatch):
    """(MUMPS's two ways: the chain LDL^T, which would count on one rank, set aside.)"""
    from rodsnes.solve.planar import BlockInertia
    monkeypatch.setattr(BlockInertia, "_chain_applies", lambda self: False)
    run = run_case("euler", rod_imperfection=0.0, load_path="newton",
                   load_end_force="%r,0,0" % (-1.2 * np.pi ** 2 / 4), load_steps=4)
    p = run.problem
    pl = p.planar
    assert pl is not None
    xs, counts = [], []
    for big in (None, 0):
        bi = BlockInertia(p, pl.plane.inplane)
        if big is not None:
            bi.REDUNDANT_MAX = big
        bi.assemble()
        counts.append(bi.factor())
        _, x = inertia_solve(bi, 1e-10)
        xs.append(x)
        assert (bi.whole is not None) == (big is None and p.layout.comm.getSize() > 1)
        bi.destroy()
    assert counts[0] == counts[1] == 1, counts
    d = xs[0].copy()
    d.axpy(-1.0, xs[1])
    assert d.norm() <= 1e-6 * xs[1].norm()
