"""The load path's predictor (load_path.LoadPath.predict) on the 7.2-turn plectoneme
(tests/data/plectoneme_7.2): the secant moves no node further than the minimiser's move
limits (the rest of the end's turn arrives as twist, which moves no node), and a step whose
end turned by more than half a turn is extrapolated as that turn, not the short way round.
Either way the predicted state's link is the imposed one.  The Newton path's predictor
(newton.NewtonSolver._predict) keeps to the same move limits."""
import os

import numpy as np
import pytest

from conftest import build_run, run_case

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SEVEN_TURNS = os.path.join(ROOT, "tests", "data", "plectoneme_7.2")


def _link(run):
    return run.problem.topology()["link"]


@pytest.mark.mpi
def test_a_long_steps_secant_stays_within_the_move_limits_and_keeps_the_link():
    """0.8 turns on from 7.2: the whole secant would move nodes by several contact radii (a
    strand was once carried through another this way); the predicted move is within the
    limits (the minimiser's _longest_step of it is 1) and the link is 8.0."""
    run = build_run("plectoneme", restart=SEVEN_TURNS)
    p, lp = run.problem, run.solver
    m = lp.minimizer
    link0, X0, snap = _link(run), p.state.X.copy(), p.state.snapshot()
    dl = 0.08
    prev, lam_prev = run.prev0
    p.state.predict(prev, dl / (run.lam0 - lam_prev), lp.twist_angles(run.lam0 - lam_prev))
    whole = p.state.X.copy()
    whole.axpy(-1.0, X0)
    p.state.restore(snap)
    assert m._longest_step(whole) < 0.5                  # the whole secant: cut
    lp.predict(run.prev0, run.lam0, dl)
    X = p.state.X.copy()
    X.axpy(-1.0, X0)
    with X as a:
        a.reshape(-1, 6)[:, 3:6] = 0.0                    # positions (rotations: recentred)
    p.state.restore(snap)
    assert m._longest_step(X) == pytest.approx(1.0, abs=1e-12) or m._longest_step(X) == 1.0
    lp.predict(run.prev0, run.lam0, dl)
    p.set_load(run.lam0 + dl, refresh=False)
    assert abs(_link(run) - (link0 + 10 * dl)) < 1e-2


@pytest.mark.mpi
def test_an_end_turned_more_than_half_a_turn_is_extrapolated_as_a_turn():
    """A step before whose end turned by 0.6 turn (the state untwisted by 0.6 turn as the step
    before), and a next step of half its length: every node turns on by half its twist of
    the step before, exactly the twist predictor's rotation.  Near the end the relative
    rotation, up to 216 degrees, has a logarithm of -144 degrees, and half of it is not the
    turn the load asks for: taken the short way round, the nodes past 5/6 of the rod turn
    back, 180 degrees from their neighbours on the other side."""
    run = build_run("plectoneme", restart=SEVEN_TURNS)
    p, lp = run.problem, run.solver
    snap = p.state.snapshot()
    lp.twist_predictor(-0.06)
    before = p.state.snapshot()
    p.state.restore(snap)
    lp.twist_predictor(0.03)
    want = p.state.q_ref.copy()
    p.state.restore(snap)
    lp.predict((before, run.lam0 - 0.06), run.lam0, 0.03)
    got = p.state.q_ref
    # the same rotations (a quaternion and its negative are one)
    assert np.abs(np.abs(np.einsum("ij,ij->i", got, want)) - 1.0).max() < 1e-10


@pytest.mark.mpi
@pytest.mark.parametrize("steps", [12, 20])
def test_the_newton_paths_secant_keeps_to_the_move_limits(steps):
    """rollup_contact (the Newton path: an end moment) in 12 or 20 load steps: the unlimited
    secant of a step 1.5 x the last carried the free end past the clamped end's cap, and the
    run converged, exit 0, on another equilibrium (tip outside the first turn, energy 237.95
    against 206.2347).  Limited, every step count ends on the documented one."""
    ref = run_case("rollup_contact")
    run = run_case("rollup_contact", load_steps=steps)
    assert ref.ok and run.ok
    e, e_ref = run.problem.energy(), ref.problem.energy()
    assert abs(e - e_ref) <= 1e-8 * abs(e_ref), (e, e_ref)
    assert abs(e_ref - 206.2347) < 1e-3
