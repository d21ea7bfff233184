"""-restart DIR resumes from the last complete step of DIR and ends where an uninterrupted run ends."""
import os
import shutil
import tempfile

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from conftest import gathered_positions, run_case

# the Newton path's load steps (the minimiser's: tests/test_minimize.py)
pytestmark = pytest.mark.usefixtures("newton_path")


def _cut_copy(comm, base):
    """base/cut: a copy of the run in base/full as if interrupted - the same file, but only two
    steps complete when it stopped.  Collective."""
    cut = os.path.join(base, "cut")
    if comm.rank == 0:
        shutil.copytree(os.path.join(base, "full"), cut)
        with h5py.File(os.path.join(cut, "result.h5"), "r+") as f:
            f.attrs["last_step"] = 2
    comm.Barrier()
    return cut


@pytest.mark.mpi
def test_restart_from_an_interrupted_run_matches_the_uninterrupted_one():
    """Collective: on 2 ranks the restart appends to rank 0's file (every rank learns last_step)."""
    comm = MPI.COMM_WORLD
    base = comm.bcast(tempfile.mkdtemp(prefix="rodsnes_restart_") if comm.rank == 0 else None, root=0)
    try:
        full = run_case("mattiasson", outdir=os.path.join(base, "full"), load_steps=4)
        assert full.ok
        cut = _cut_copy(comm, base)
        resumed = run_case("mattiasson", outdir=cut, load_steps=4, restart=cut)
        assert resumed.ok
        assert [h["load"] for h in resumed.history] == [0.75, 1.0]
        assert np.abs(gathered_positions(resumed) - gathered_positions(full)).max() < 1e-9
        if comm.rank == 0:
            with h5py.File(os.path.join(cut, "result.h5"), "r") as f:
                assert f.attrs["last_step"] == 4
                assert sorted(f["steps"]) == ["00000", "00001", "00002", "00003", "00004"]
                assert f["steps/00003"].attrs["load"] == 0.75
    finally:
        comm.Barrier()
        if comm.rank == 0:
            shutil.rmtree(base, ignore_errors=True)


def test_restart_from_an_unstable_step_takes_the_steps_the_run_would_have_taken(tmp_path):
    """The Newton path with -stability: the imperfect Michell ring at 1.7 turns, short of the
    fold near 1.72 turns that the imperfection makes of Michell's bifurcation (sqrt(3) turns),
    stays on the circle past 1.67 turns, where its near-symmetry mode falls below the neutral
    band (stability.NEUTRAL): accepted with a negative eigenvalue after the cut-backs.  A restart from such a step, in
    the middle of the increments growing again after the cut-backs, starts (1) from that
    eigenvalue count (Run.nneg0), so it does not take its own state for a loss of stability
    and cut every step back; (2) from the increment the interrupted run would have taken next
    (next_increment in result.h5) and (3) with the secant predictor through the step before:
    it takes the same load steps with the same Newton iterations as the uninterrupted run."""
    kw = dict(load_twist_turns=1.7, stability=True, rod_nelem=8,
              load_steps=10, load_max_cutbacks=3)
    full = run_case("michell", outdir=str(tmp_path / "full"), **kw)
    assert full.ok
    h = full.history
    # the step with the shortest next increment among the unstable ones
    k = 1 + min((i for i in range(len(h)) if h[i]["negative_eigenvalues"] > 0),
                key=lambda i: h[i]["next_increment"])
    assert h[k - 1]["next_increment"] < 1e-3 and len(h) - k > 10
    cut = tmp_path / "cut"
    shutil.copytree(tmp_path / "full", cut)
    with h5py.File(cut / "result.h5", "r+") as f:
        f.attrs["last_step"] = k
    resumed = run_case("michell", outdir=str(cut), restart=str(cut), **kw)
    n0 = h[k - 1]["negative_eigenvalues"]
    assert n0 > 0 and resumed.nneg0 == n0
    assert resumed.dlam0 == h[k - 1]["next_increment"] and resumed.prev0 is not None
    assert resumed.ok
    assert all(r["negative_eigenvalues"] >= n0 for r in resumed.history)
    np.testing.assert_allclose([r["load"] for r in resumed.history], [r["load"] for r in h[k:]],
                               rtol=0, atol=1e-13)
    assert [r["newton_iterations"] for r in resumed.history] == [r["newton_iterations"] for r in h[k:]]
    assert np.abs(gathered_positions(resumed) - gathered_positions(full)).max() < 1e-8


def test_a_restart_that_fails_at_once_still_writes_its_summary(tmp_path):
    """A restart whose first step fails (here Newton held to 1 iteration, no cut-back) reports
    the state it started from in summary.json: load, energy, tip, converged = false."""
    import json
    full = run_case("mattiasson", outdir=str(tmp_path / "full"), load_steps=4)
    cut = tmp_path / "cut"
    shutil.copytree(tmp_path / "full", cut)
    with h5py.File(cut / "result.h5", "r+") as f:
        f.attrs["last_step"] = 2
        e2 = float(f["steps/00002"].attrs["energy"])
    resumed = run_case("mattiasson", outdir=str(cut), load_steps=4, restart=str(cut),
                       snes_max_it=1, load_max_cutbacks=0)
    assert full.ok and not resumed.ok and resumed.history == []
    s = json.loads((cut / "summary.json").read_text())
    assert s["converged"] is False and s["load"] == 0.5 and "failure" in s
    assert abs(s["energy"] - e2) < 1e-12 * abs(e2) and len(s["tip_position"]) == 3


def test_a_run_in_stages_with_load_stop_matches_the_run_in_one_go(tmp_path):
    """-load_stop ends a run at a load factor on the grid of -load_steps (0 -> 1); a restart
    from it goes on with the steps the single run takes (same loads, same end state), and a
    restart that already stands at -load_stop is refused with the option named."""
    from rodsnes.errors import SceneError
    full = run_case("mattiasson", outdir=str(tmp_path / "full"), load_steps=4)
    staged = str(tmp_path / "staged")
    first = run_case("mattiasson", outdir=staged, load_steps=4, load_stop=0.5)
    assert first.ok
    assert [h["load"] for h in first.history] == [0.25, 0.5]
    with pytest.raises(SceneError) as ei:
        run_case("mattiasson", outdir=staged, load_steps=4, load_stop=0.5, restart=staged)
    assert "-load_stop" in str(ei.value) and "-load_stop" in ei.value.options
    second = run_case("mattiasson", outdir=staged, load_steps=4, restart=staged)
    assert second.ok
    assert [h["load"] for h in second.history] == [0.75, 1.0]
    assert np.abs(gathered_positions(second) - gathered_positions(full)).max() < 1e-9


def test_a_checkpoint_of_the_last_steps_resumes_like_the_whole_file(tmp_path):
    """tools/checkpoint.py keeps the last two steps of result.h5 (the state and the step before
    for the secant predictor): a restart from it into a new directory takes the same steps and
    ends at the same state as a restart from the whole file, numbering its steps on."""
    import sys
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tools"))
    from checkpoint import checkpoint
    from rodsnes.io import results as output
    full = run_case("mattiasson", outdir=str(tmp_path / "full"), load_steps=4)
    staged = str(tmp_path / "staged")
    assert run_case("mattiasson", outdir=staged, load_steps=4, load_stop=0.75).ok
    assert checkpoint(staged, str(tmp_path / "ckpt")) == [2, 3]
    assert output.read_steps(str(tmp_path / "ckpt")) == [2, 3]
    resumed = run_case("mattiasson", outdir=str(tmp_path / "new"), load_steps=4,
                       restart=str(tmp_path / "ckpt"))
    assert resumed.ok
    assert [h["load"] for h in resumed.history] == [1.0]
    assert output.read_steps(str(tmp_path / "new"))[-1] == 4
    assert np.abs(gathered_positions(resumed) - gathered_positions(full)).max() < 1e-9


def test_a_checkpoint_of_one_step_resumes_without_a_secant(tmp_path):
    """A checkpoint of the last step only (``--steps 1``, or a state written alone: the
    plectoneme's re-solved switch) has no step before it for the secant predictor: the restart
    predicts from the state itself and ends where the whole run ends (before: KeyError)."""
    import sys
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tools"))
    from checkpoint import checkpoint
    full = run_case("mattiasson", outdir=str(tmp_path / "full"), load_steps=4)
    staged = str(tmp_path / "staged")
    assert run_case("mattiasson", outdir=staged, load_steps=4, load_stop=0.75).ok
    assert checkpoint(staged, str(tmp_path / "ckpt"), nsteps=1) == [3]
    resumed = run_case("mattiasson", outdir=str(tmp_path / "new"), load_steps=4,
                       restart=str(tmp_path / "ckpt"))
    assert resumed.ok and resumed.prev0 is None
    assert [h["load"] for h in resumed.history] == [1.0]
    assert np.abs(gathered_positions(resumed) - gathered_positions(full)).max() < 1e-9


@pytest.mark.mpi
def test_the_ranks_resume_from_rank_0s_reading(monkeypatch):
    """The restart's steps are read on rank 0 alone and sent to every rank (read by each, a
    file another run was still writing gave the ranks different steps and mixed states, then a
    hang): the other ranks' reads fail here and the run still resumes; a directory rank 0
    finds unreadable is refused on every rank."""
    from rodsnes.errors import SceneError
    from rodsnes.io import results
    comm = MPI.COMM_WORLD
    base = comm.bcast(tempfile.mkdtemp(prefix="rodsnes_restart_") if comm.rank == 0 else None, root=0)
    try:
        full = run_case("mattiasson", outdir=os.path.join(base, "full"), load_steps=4)
        cut = _cut_copy(comm, base)
        if comm.rank > 0:
            monkeypatch.setattr(results, "read_step", lambda *a, **k: 1 / 0)
        resumed = run_case("mattiasson", outdir=os.path.join(base, "out"), load_steps=4,
                           restart=cut)
        assert full.ok and resumed.ok
        assert [h["load"] for h in resumed.history] == [0.75, 1.0]
        assert np.abs(gathered_positions(resumed) - gathered_positions(full)).max() < 1e-9
        monkeypatch.undo()
        if comm.rank == 0:          # rank 0 alone cannot read it
            monkeypatch.setattr(results, "read_step", lambda *a, **k: 1 / 0)
        with pytest.raises(SceneError, match="-restart"):
            run_case("mattiasson", outdir=os.path.join(base, "out2"), load_steps=4, restart=cut)
    finally:
        comm.Barrier()
        if comm.rank == 0:
            shutil.rmtree(base, ignore_errors=True)


def test_a_restart_holds_the_sliding_gauge_the_run_held(tmp_path):
    """A closed ring's sliding gauge holds the coordinate of the node opposite node 0 that lay
    most along its tangent when the run started; every step records which (result.h5
    gauge_component), and a restart holds that one at its held value, not the one most along
    the tangent of the writhed state it resumes (a turned tangent would pick another and pose
    another gauge: not the run's path).  The record is changed here to a component the state
    would not pick: the restart holds it."""
    if MPI.COMM_WORLD.Get_size() > 1:
        pytest.skip("one rank (each rank's own tmp_path)")
    kw = dict(rod_nelem=12, load_path="minimize")
    full = run_case("michell", outdir=str(tmp_path / "full"), **kw)
    assert full.ok and full.problem.gauge is not None
    node, comp, _ = full.problem.gauge
    cut = tmp_path / "cut"
    if MPI.COMM_WORLD.rank == 0:
        shutil.copytree(tmp_path / "full", cut)
        with h5py.File(cut / "result.h5", "r+") as f:
            f.attrs["last_step"] = 3
            assert all(f["steps"][k].attrs["gauge_component"] == comp
                       for k in sorted(f["steps"])[1:])
            f["steps"]["00003"].attrs["gauge_component"] = (comp + 1) % 3
    MPI.COMM_WORLD.Barrier()
    resumed = run_case("michell", outdir=str(cut), restart=str(cut), **kw)
    assert resumed.problem.gauge[:2] == (node, (comp + 1) % 3)
    again = tmp_path / "again"
    if MPI.COMM_WORLD.rank == 0:
        shutil.copytree(tmp_path / "full", again)
        with h5py.File(again / "result.h5", "r+") as f:
            f.attrs["last_step"] = 3
    MPI.COMM_WORLD.Barrier()
    same = run_case("michell", outdir=str(again), restart=str(again), **kw)
    assert same.ok and same.problem.gauge[:2] == (node, comp)
    assert np.abs(gathered_positions(same) - gathered_positions(full)).max() < 1e-9


@pytest.mark.parametrize("damage, said", [
    (lambda g: g.attrs.__setitem__("load", np.nan), "holds the load nan"),
    (lambda g: g.attrs.__setitem__("load", 7.0), "holds the load 7.0"),
    (lambda g: g["positions"].__setitem__((0, 0), np.nan), "holds positions that are not finite"),
    (lambda g: g["rotation"].__setitem__(slice(None), 0.0),
     "holds rotation quaternions not of unit length"),
    (lambda g: g.attrs.__setitem__("next_increment", 1e-300),
     "holds the next increment 1e-300 (below the load's resolution)")])
def test_a_damaged_last_step_is_refused(tmp_path, damage, said):
    """A result.h5 whose last step is no state rodsnes writes: refused with -restart named (a
    NaN load made the restarted run end at once 'converged', exit 0, with no step; NaN
    positions or a zero quaternion failed the load path blaming the solver; an increment of
    1e-300 divided by zero in the predictor).  A complete run is refused as such, not by
    -load_stop.  (Serial: the damage is written by this process.)"""
    from rodsnes.errors import SceneError
    from rodsnes.io import results as output
    if MPI.COMM_WORLD.size > 1:
        pytest.skip("serial")
    staged = str(tmp_path / "staged")
    assert run_case("mattiasson", outdir=staged, load_steps=4, load_stop=0.5).ok
    with h5py.File(os.path.join(staged, "result.h5"), "r+") as f:
        damage(f["steps"][sorted(f["steps"])[-1]])
    with pytest.raises(SceneError) as ei:
        run_case("mattiasson", outdir=str(tmp_path / "new"), load_steps=4, restart=staged)
    assert said in str(ei.value) and "not a state rodsnes writes" in str(ei.value)
    assert "-restart" in ei.value.options
    done = str(tmp_path / "done")
    assert run_case("mattiasson", outdir=done, load_steps=2).ok
    with pytest.raises(SceneError, match="that run is complete"):
        run_case("mattiasson", outdir=str(tmp_path / "again"), load_steps=2, restart=done)
    assert output.read_steps(done)


@pytest.mark.parametrize("path", ["newton", "minimize"])
def test_a_step_before_at_the_last_ones_load_is_no_secant(tmp_path, path):
    """The step before the last at the same load (a damaged file) made the secant predictor
    divide by zero on either path (exit 4): the restart goes on without it, as from a one-step
    checkpoint, to the end of the run."""
    if MPI.COMM_WORLD.size > 1:
        pytest.skip("serial")
    staged = str(tmp_path / "staged")
    assert run_case("mattiasson", outdir=staged, load_steps=4, load_stop=0.5, load_path=path).ok
    with h5py.File(os.path.join(staged, "result.h5"), "r+") as f:
        names = sorted(f["steps"])
        f["steps"][names[-2]].attrs["load"] = f["steps"][names[-1]].attrs["load"]
    resumed = run_case("mattiasson", outdir=str(tmp_path / "new"), load_steps=4, load_path=path,
                       restart=staged)
    assert resumed.ok and resumed.prev0 is None and resumed.problem.lam == 1.0
