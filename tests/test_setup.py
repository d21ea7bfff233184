"""The solver's set-up before the path (Run._execute, in the log stage profiling.SET_UP): the
Newton step's matrix made and its LU chosen and planned for the pattern (linear.set_up_ahead),
so that the path's iterations find them made; serially (the chain LU) and on 2 ranks (the
ranks' condensation, schur.RankSchur.plan)."""
import numpy as np
import pytest
from petsc4py import PETSc

from conftest import build_run, gathered_positions
from rodsnes.model import partition
from rodsnes.solve import chain, load_path, newton, planar, schur


def _counting(monkeypatch):
    """Counts of the matrices made (in-plane and full) and of the LU plans (the chain's, the
    ranks' condensations) from now on."""
    n = {"matrices": 0, "plans": 0, "condensations": 0}

    def counted(key, fun):
        def inner(*a, **k):
            n[key] += 1
            return fun(*a, **k)
        return inner
    monkeypatch.setattr(planar, "create_block_matrix",
                        counted("matrices", planar.create_block_matrix))
    monkeypatch.setattr(partition.Layout, "create_matrix",
                        counted("matrices", partition.Layout.create_matrix))
    monkeypatch.setattr(chain.ChainLU, "plan",
                        classmethod(counted("plans", chain.ChainLU.plan.__func__)))
    monkeypatch.setattr(schur.RankSchur, "_condense",
                        counted("condensations", schur.RankSchur._condense))
    return n


def _run(solver_class, monkeypatch, ahead=True, **kw):
    """The cantilever's run (40 cubic elements, 2 load steps), condensed on several ranks
    however short; the counts (_counting) after the set-up and before and after the path
    (the path's end, PathEnd's stability count, after it)."""
    with monkeypatch.context() as m:
        m.setattr(schur, "MIN_NODES_PER_RANK", 0)
        n = _counting(m)
        seen = {}
        setup, path = solver_class.setup, solver_class.run

        def counted_setup(self):
            if ahead:
                setup(self)
            seen["set-up"] = dict(n)

        def counted_path(self, *a, **k):
            seen["path from"] = dict(n)
            out = path(self, *a, **k)
            seen["path to"] = dict(n)
            return out
        m.setattr(solver_class, "setup", counted_setup)
        m.setattr(solver_class, "run", counted_path)
        run = build_run("mattiasson", rod_nelem=40, load_steps=2, rod_error_estimate="off",
                        **kw)
        assert run.execute()
    return run, seen


@pytest.mark.mpi
@pytest.mark.parametrize("kw,solver_class,kinds", [
    # the Newton path's in-plane matrix; with -stability the in-plane and out-of-plane Hessian
    # blocks' of every step's count too
    (dict(load_path="newton"), newton.NewtonSolver, 1),
    (dict(load_path="newton", stability=True), newton.NewtonSolver, 3),
    # in 3-D the full J (made with the problem); with -stability the full Hessian's
    (dict(load_path="newton", rod_planar="off"), newton.NewtonSolver, 1),
    (dict(load_path="newton", rod_planar="off", stability=True), newton.NewtonSolver, 2),
    # the minimiser's in-plane Newton step's and the in-plane and out-of-plane Hessian blocks'
    # (its LDL^T at every iteration, the out-of-plane count at every step); in 3-D the full
    # J's and the Hessian's
    (dict(load_path="minimize"), load_path.LoadPath, 3),
    (dict(load_path="minimize", rod_planar="off"), load_path.LoadPath, 2)])
def test_the_set_up_makes_what_the_path_then_only_fills(kw, solver_class, kinds, monkeypatch):
    """The set-up makes the Newton step's matrix (the in-plane one, or the full one made with
    the problem) and the LU's plan for it (serially the chain LU's; on several ranks the
    condensation, whose stretches are chains), and the Hessian's where the path counts every
    step or iteration; the path's iterations make none of them again.  The answer is the one
    of a run whose set-up is left to the first iteration, to round-off."""
    several = PETSc.COMM_WORLD.getSize() > 1
    run, seen = _run(solver_class, monkeypatch, **kw)
    made = seen["set-up"]
    assert made["matrices"] == kinds
    assert made["plans"] == kinds and made["condensations"] == (kinds if several else 0)
    assert seen["path to"] == seen["path from"] == made
    lazy, seen_lazy = _run(solver_class, monkeypatch, ahead=False, **kw)
    assert seen_lazy["set-up"]["plans"] == seen_lazy["set-up"]["condensations"] == 0
    # the same matrices and plans, made in the first iteration instead
    assert seen_lazy["path to"]["plans"] == seen["path to"]["plans"]
    assert seen_lazy["path to"]["matrices"] == seen["path to"]["matrices"]
    np.testing.assert_allclose(gathered_positions(run), gathered_positions(lazy),
                               rtol=0, atol=1e-12)


def test_a_snes_type_the_set_up_cannot_set_up_is_its_solves_to_fail():
    """-snes_type qn on the Newton path: SNESSetUp ahead of the path goes as the solve's own
    would (the set-up gives the SNES its solution vector), and the steps fail as solves, the
    run ending without a traceback (exit code 3, not 2 from a PETSc error at the set-up)."""
    run = build_run("mattiasson", rod_nelem=20, load_steps=2, rod_error_estimate="off",
                    load_path="newton", rod_planar="off", snes_type="qn")
    assert not run.execute()
    assert run.history == [] and run.solver.fail_reason is None
