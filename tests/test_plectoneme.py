"""The twisted clamped rod of cases/plectoneme.opts (the PyElastica plectoneme scene: L = 1,
radius 0.025, E = 1e6, G = E/1.5, end clamped in rotation and sliding along the axis under a
small tension), here to 1.5 turns instead of 10 with 40 elements so that it fits the test budget: the
straight rod's loop formation is a descent of the energy minimisation into a loop in
self-contact.  The full 10 turns (README, Plectoneme) are checked through their stored last
state (tests/data/plectoneme_10)."""
import os

import numpy as np
import pytest

from conftest import ROOT, build_run, gathered_positions, run_case


@pytest.mark.slow
def test_twisted_rod_snaps_into_a_loop_in_self_contact():
    """The default path (energy minimisation): converged at every step with the residual at
    tolerance and every step stable (the loop formation, a jump for Newton, is a descent of
    the minimiser); at the end: Lk = imposed turns within 1e-2 (and Lk = Tw + Wr), a loop
    (writhe about 1), contact active with a penetration within the penalty's promise (about
    1 % of the diameter)."""
    turns = 1.5
    run = run_case("plectoneme", bc_end_turns=turns, load_steps=30, rod_nelem=40)
    assert run.ok and run.path == "minimize"
    # the step tolerance, or the roundoff floor of the residual (stiff axial terms)
    tol = max(1e-10 * run.force_scale, run.solver.floor)
    assert run.solver.floor < 1e-8
    assert all(h["residual_norm"] <= tol for h in run.history)
    assert all(h["negative_eigenvalues"] == 0 for h in run.history)
    topo = run.last_topology
    assert abs(topo["link"] - turns) < 1e-2
    assert abs(topo["twist"] + topo["writhe"] - topo["link"]) < 1e-9
    assert 0.7 < topo["writhe"] < 1.2
    c = run.summary(converged=True)["contact"]
    assert c["zones"] >= 1 and c["total_force"] > 1.0 and c["active_points"] > 0
    assert 0.0 < c["max_penetration"] < 0.01
    assert run.history[-1]["negative_eigenvalues"] == 0
    assert np.isfinite(run.last_energy)


# the plectoneme of cases/plectoneme.opts from the straight rod in one command (README,
# Plectoneme): the step before 10 turns (9.98 turns), kept by tools/checkpoint.py
TEN_TURNS = os.path.join(ROOT, "tests", "data", "plectoneme_10")


def test_the_mounts_report_against_the_tube_with_a_standoff(tmp_path):
    """The stored 10-turn state presses on the clamps' mounts; read back with the case's 2 %
    standoff and without one, the mounts' reports are the tube's in both (support_min_gap =
    distance - a, the same), while the law with the standoff presses harder (its mounts act
    from a + 2 (eps_l - a): more force at the same positions)."""
    soft = build_run("plectoneme", outdir=tmp_path / "s", restart=TEN_TURNS)
    hard = build_run("plectoneme", outdir=tmp_path / "h", restart=TEN_TURNS, contact_standoff=0)
    a = soft.contact.radius
    assert soft.contact.supports.reach == pytest.approx(a + 2 * (soft.contact.eps - a), rel=1e-15)
    assert hard.contact.supports.reach == a
    got = []
    for run in (soft, hard):
        run.contact.set_penalty(soft.contact.mu)          # the same mu: only the law differs
        run.contact.report(run.problem.state.local_config()[0])
        got.append(run.contact.summary())
    s, h = got
    assert s["support_points"] > 0 and s["support_force"] > h["support_force"]
    assert s["support_min_gap"] == pytest.approx(h["support_min_gap"], rel=1e-9)
    assert s["support_min_gap"] > -0.01 * 2 * a


@pytest.mark.slow
@pytest.mark.mpi
def test_the_ten_turn_plectoneme_is_an_equilibrium_of_the_current_code(tmp_path):
    """The stored state at 9.98 turns read back by -restart is still an equilibrium of this
    code's rod and contact terms: the residual within the load steps' tolerance (or twice the
    residual stored with it), the stored penalty and energy restored (1e-9), Lk = the imposed
    turns within 1e-9 and Tw + Wr = Lk, penetration within 1 % of the diameter, stable.  The
    last load step from there ends where the run from the straight rod ended: 10 turns, energy
    361.35726 (1e-7), writhe 3.726, stable (the case's 2 % standoff, docs/contact.md).  A change to the energy, the contact term or the
    result format that moves the plectoneme's equilibria fails here."""
    from rodsnes.io import results as output
    last = output.read_step(TEN_TURNS, -1)
    run = build_run("plectoneme", outdir=tmp_path, restart=TEN_TURNS)
    p = run.problem
    assert run.lam0 == last["attrs"]["load"] and run.step == last["step"]
    assert run.contact.mu == last["attrs"]["contact_penalty"]
    F = p.F.duplicate()
    p.residual(None, p.state.X, F)
    assert F.norm() <= max(run.solver.tolerance(), 2 * last["attrs"]["residual_norm"])
    _, energy, cattrs, _, topo = run.observe()
    assert abs(energy - last["attrs"]["energy"]) <= 1e-9 * abs(energy)
    assert abs(topo["link"] - 10.0 * run.lam0) < 1e-9
    assert abs(topo["twist"] + topo["writhe"] - topo["link"]) < 1e-9
    assert 0.0 < cattrs["contact_max_penetration"] <= 0.01
    assert last["attrs"]["negative_eigenvalues"] == 0
    run.execute()
    s = run.summary(converged=True)
    assert run.problem.lam == 1.0 and s["stable"] is True
    assert abs(s["energy"] - 361.357260810899) <= 1e-7 * 361.4
    assert abs(s["topology"]["link"] - 10.0) < 1e-9
    assert abs(s["topology"]["writhe"] - 3.7258) < 1e-3
    assert s["contact"]["max_penetration"] <= 0.01
    # the error estimate's order-4 minimisation settles on the two-ply of the carried state's
    # basin (soft modes under the contact step limits: tip 1.85e-5, centreline 4.83e-3, as the
    # run from the straight rod estimated them; without the standoff 2.62e-5 and 2.95e-3, the
    # same to 1e-11 whatever the LU's ordering; Newton with full steps landed on one of several
    # order-4 equilibria by round-off, centreline 0.003 to 0.097)
    est = s["error_estimate"]
    assert est["converged"] is True
    assert est["tip"] == pytest.approx(1.85e-5, rel=0.05)
    assert est["centreline"] == pytest.approx(4.83e-3, rel=0.05)


@pytest.mark.slow
def test_a_penalty_raise_whose_solve_fails_is_cut_back_to_a_smaller_one(tmp_path):
    """-contact_penalty_adapt: a re-solve at the raised mu that fails (faked: the first solve of
    the raise reports failure without moving) is tried again with the
    geometric mean of the two penalties, and the raises go on from there until the promise
    holds: the 10-turn plectoneme (0.33 % of the diameter) held to 0.3 % by the penalty
    alone (-contact_wall 0: with the wall, that state would stand beyond it).  Without the
    cut-back the raise fails and the state keeps its penetration."""
    from rodsnes.solve.newton import StepResult
    target = 0.003
    run = build_run("plectoneme", outdir=tmp_path, restart=TEN_TURNS, load_path="newton",
                    contact_penetration=target, contact_wall=0)
    s, c = run.solver, run.contact
    newton, tried = s.solve_guarded, []

    def failing_first(lam):
        s.solve_guarded = newton
        tried.append(c.mu)
        return StepResult(lam, False, 0, "faked", np.nan, np.array([]), 0.0)
    s.solve_guarded = failing_first
    res = StepResult(run.lam0, True, 0, "restart", np.nan, np.array([]), 0.0)
    mu0 = c.mu
    s.keep_penetration(res)
    assert len(tried) == 1 and tried[0] > mu0
    assert c.penalty_failures == 0 and c.penalty_raises >= 1 and c.mu > mu0
    assert (c.deepest(run.problem.state.local_config()[0]) - c.offset) / (2 * c.radius) <= target
    assert res.fnorm <= s.tolerance()


def test_a_restart_beyond_the_wall_is_refused_with_the_promise_that_fits(tmp_path):
    """A restart whose state presses deeper than the wall of a tighter -contact_penetration
    (the pair potential's energy infinite there) is refused before any step, with the promise
    that would fit or -contact_wall 0; the promise it names fits, and so does the penalty
    alone."""
    import re
    from rodsnes.errors import SceneError
    with pytest.raises(SceneError, match="-contact_wall 0") as err:
        build_run("plectoneme", outdir=tmp_path / "a", restart=TEN_TURNS,
                  contact_penetration=0.003)
    need = float(re.search(r"-contact_penetration (\S+) or more", str(err.value)).group(1))
    assert 0.003 < need < 0.01
    run = build_run("plectoneme", outdir=tmp_path / "b", restart=TEN_TURNS,
                    contact_penetration=need)
    assert run.contact.deepest(run.problem.state.local_config()[0], report=False) \
        < run.contact.wall[1]
    build_run("plectoneme", outdir=tmp_path / "c", restart=TEN_TURNS, contact_penetration=0.003,
              contact_wall=0)


@pytest.mark.parametrize("path", ["newton", "minimize"])
def test_a_state_pressing_into_the_wall_raises_the_penalty_for_the_next_step(tmp_path, path):
    """The 10-turn state under a promise whose wall's barrier it presses into (-contact_wall,
    0.45 %: the state's deepest couple between the barrier's start and the wall): the step's
    promise check keeps it as it is, no solve, no raise; before the next step (and at the
    start of a restart from it) mu rises to 1.25 mu d / a_b (RodProblem.ease_walls), on both
    load paths; a state short of the barrier raises nothing."""
    from rodsnes.solve.newton import StepResult
    run = build_run("plectoneme", outdir=tmp_path, restart=TEN_TURNS, load_path=path,
                    contact_penetration=0.0045)
    s, c = run.solver, run.contact
    r = run.problem.state.local_config()[0]
    depth = c.deepest(r, report=False)
    assert c.wall[0] < depth < c.wall[1]
    res = StepResult(run.lam0, True, 0, "restart", np.nan, np.array([]), 0.0)
    mu0 = c.mu
    (s.keep_penetration if path == "newton" else s.keep_promise)(res)
    assert res.its == 0 and c.penalty_raises == 0 and c.penalty_eased == 0 and c.mu == mu0
    said = run.problem.ease_walls(run.lam0)
    assert len(said) == 1 and "presses into the wall" in said[0] and c.penalty_eased == 1
    assert c.mu == pytest.approx(1.25 * mu0 * depth / c.wall[0], rel=1e-12)
    run = build_run("plectoneme", outdir=tmp_path / "far", restart=TEN_TURNS, load_path=path)
    assert run.problem.ease_walls(run.lam0) == [] and run.contact.penalty_eased == 0


def test_a_step_pressing_into_the_wall_is_written_with_the_penalty_it_was_solved_with(
        tmp_path, monkeypatch):
    """Three turns from the straight rod: the step at load 0.9508 ends pressing into the wall's
    barrier and raises mu for the next step (1.233e6 -> 1.642e6).  That step is written with
    the mu it was solved with and its energy under it (it was written with the raised mu's,
    24.3144 for 24.2960: contact forces that the elastic ones do not balance, |F| 22); the next
    step records the raised mu; a restart from the raising step raises it again before its
    first step, and ends where the run ends."""
    import shutil
    import h5py
    from mpi4py import MPI
    from rodsnes.contact.term import ContactTerm
    if MPI.COMM_WORLD.Get_size() > 1:
        pytest.skip("one rank (each rank's own tmp_path)")
    real, raised = ContactTerm.ease_wall, []

    def ease_wall(self, r, lam):
        mu0, line = self.mu, real(self, r, lam)
        if line is not None:
            raised.append((lam, mu0, self.mu))
        return line
    monkeypatch.setattr(ContactTerm, "ease_wall", ease_wall)
    comm = MPI.COMM_WORLD
    full = run_case("plectoneme", outdir=tmp_path / "full", bc_end_turns=3)
    assert full.ok and len(raised) == 1
    lam, mu0, mu1 = raised[0]
    k = None
    if comm.rank == 0:
        with h5py.File(tmp_path / "full" / "result.h5", "r") as f:
            steps = [dict(f["steps"][key].attrs) for key in sorted(f["steps"])]
        k = next(i for i, a in enumerate(steps) if a["load"] == lam)
        assert steps[k]["contact_penalty"] == mu0 and steps[k + 1]["contact_penalty"] == mu1
        assert abs(steps[k]["energy"] - 24.29598) < 1e-4, steps[k]["energy"]
        cut = tmp_path / "cut"
        shutil.copytree(tmp_path / "full", cut)
        with h5py.File(cut / "result.h5", "r+") as f:
            f.attrs["last_step"] = k
    comm.Barrier()
    cut = str(tmp_path / "cut")
    resumed = run_case("plectoneme", outdir=cut, restart=cut, bc_end_turns=3)
    assert resumed.ok and len(raised) == 2 and raised[1] == raised[0]
    assert np.abs(gathered_positions(resumed) - gathered_positions(full)).max() < 1e-9
