"""Walking a soft valley (rodsnes/solve/valley.py): where the plectoneme's ply lengthens
(7.2 turns, tests/data/plectoneme_7.2), one load step of the plain minimiser crawls for
hundreds of iterations along one near-zero mode; the follower walks the valley floor by
predictor-corrector and the step ends on the same kind of point, a stable minimum, in fewer
iterations."""
import os

import numpy as np
import pytest

from conftest import build_run
from rodsnes.solve import minimize, valley

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SEVEN_TURNS = os.path.join(ROOT, "tests", "data", "plectoneme_7.2")
LOAD = 0.7236           # 0.036 turns on: the step that crawls from this state


def _one_step(monkeypatch, walk, spy=None):
    """The step 0.72 -> LOAD from the checkpoint (its secant predictor, as the run takes it);
    returns (MinimizeResult, energy)."""
    monkeypatch.setattr(minimize, "VALLEY", walk)
    run = build_run("plectoneme", restart=SEVEN_TURNS)
    lp = run.solver
    if spy is not None:
        spy(lp.minimizer)
    lp.predict(run.prev0, run.lam0, LOAD - run.lam0)
    res = lp.minimizer.solve_at(LOAD)
    return res, lp.minimizer.energy_at(run.problem.state.X)[0]


@pytest.mark.mpi
def test_the_crawl_is_walked_to_a_stable_minimum_in_fewer_iterations(monkeypatch):
    plain, E_plain = _one_step(monkeypatch, False)
    walked, E_walked = _one_step(monkeypatch, True)
    assert walked.converged and walked.negative_eigenvalues == 0
    assert plain.valley_points == 0
    assert walked.valley_points >= 5
    # measured (Intel Xeon VM): plain 1005 iterations, at its iteration limit still
    # descending (178 with another watchdog, converged); walking 70, converged.  The path
    # is chaotic in round-off, so the margin is wide
    assert walked.its < 0.6 * plain.its
    # at least as low: the ply slides as far as the plain minimiser takes it, or further
    assert E_walked <= E_plain + 1e-10 * abs(E_plain)


def test_each_corrector_step_stays_on_the_hyperplane(monkeypatch):
    """The bordered step dc = -(a - mu b), K a = g, K b = M v, has <M v, dc> = 0 (the corrector
    minimises on the hyperplane through the predicted point), and descends."""
    seen = []

    def spy(m):
        follower = m.valley
        correct = follower._correct

        def checked(v, Mv, a, b, dc, Xt, out):
            search = m._line_search

            def line_search(X, Xt_, d, slope, *args, **kw):
                seen.append((abs(Mv.dot(d)) / (Mv.norm() * d.norm()), slope))
                return search(X, Xt_, d, slope, *args, **kw)

            m._line_search = line_search
            try:
                return correct(v, Mv, a, b, dc, Xt, out)
            finally:
                m._line_search = search

        follower._correct = checked

    res, _ = _one_step(monkeypatch, True, spy)
    assert res.converged and len(seen) >= 5
    cosines = np.array([c for c, _ in seen])
    # to round-off times the conditioning of K, whose softest eigenvalue is ~1e-10 of its
    # largest here (a and b share a large part along the soft mode that cancels): measured
    # up to 2e-7; a wrong multiplier mu leaves cos of order 1
    assert cosines.max() <= 1e-5
    assert all(slope < 0.0 for _, slope in seen)


def test_no_walk_where_newton_converges(monkeypatch):
    """A step Newton takes in a few iterations never reaches VALLEY_AFTER: the follower costs
    nothing there (the straight twisted rod, before it buckles)."""
    run = build_run("plectoneme", load_stop=0.05)
    assert run.execute()
    assert all(r.valley_points == 0 for r in run.solver.results)
    assert max(r.its for r in run.solver.results) < valley.VALLEY_AFTER


def test_a_step_the_move_limits_cut_short_is_shifted_to_fit_them(monkeypatch):
    """Where the move limits cut Newton's step below minimize.LIMITED (a long load step from
    the 7.2-turn checkpoint, started from the whole secant, which the load path's predictor
    would have cut to the move limits: far from the minimum), the step of K + sigma M
    replaces it: it descends, the limits cut it less, and K is the Jacobian again afterwards
    (its diagonal as before)."""
    seen = []

    def spy(m):
        limited = m._limited_step

        def checked(g, d, slope, alpha):
            diag = m.problem.J.getDiagonal()
            out = limited(g, d, slope, alpha)
            after = m.problem.J.getDiagonal()
            after.axpy(-1.0, diag)
            seen.append((alpha, out, after.norm() / diag.norm(), m._longest_step(d)))
            return out

        m._limited_step = checked

    monkeypatch.setattr(minimize, "VALLEY", True)
    run = build_run("plectoneme", restart=SEVEN_TURNS)
    lp = run.solver
    spy(lp.minimizer)
    lam = run.lam0 + 0.03
    prev, lam_prev = run.prev0
    run.problem.state.predict(prev, (lam - run.lam0) / (run.lam0 - lam_prev),
                              lp.twist_angles(run.lam0 - lam_prev))
    run.problem.state.recentre()
    res = lp.minimizer.solve_at(lam)
    assert res.converged and res.negative_eigenvalues == 0
    assert res.limited_steps == len(seen) >= 3
    for alpha, (slope, alpha2), restored, longest in seen:
        assert slope < 0.0 and alpha2 >= alpha and restored <= 1e-14   # (+ sigma M - sigma M)
        assert alpha2 == longest                 # d holds the step taken
    assert any(a2 > 5 * a for a, (_, a2), _, _ in seen)


def test_a_declined_walk_does_not_delay_the_next():
    """A walk turned down at no cost (Newton's direction is not the soft mode) lets the next
    one come as soon as Newton's directions agree again; a walk that spent iterations without
    taking a valley point doubles the wait; one that took points resets it."""
    f = valley.ValleyFollower(None)
    f.start()
    declined = valley.ValleyResult()
    declined.declined = True
    f.walked(10, declined)
    assert (f.after, f.wait) == (10, valley.VALLEY_AFTER)
    futile = valley.ValleyResult()
    futile.its, futile.rejected = 4, 2
    f.walked(20, futile)
    assert (f.after, f.wait) == (20 + 2 * valley.VALLEY_AFTER, 2 * valley.VALLEY_AFTER)
    f.walked(40, declined)
    assert (f.after, f.wait) == (40, 2 * valley.VALLEY_AFTER)
    took = valley.ValleyResult()
    took.points, took.its = 3, 7
    f.walked(50, took)
    assert (f.after, f.wait) == (50, valley.VALLEY_AFTER)


def test_no_walk_along_a_symmetry(monkeypatch):
    """Michell's isotropic ring at 1.2 turns (node 0 held): turned rigidly about node 0's
    tangent with its sections spun back about their own, it keeps its energy but for the
    imperfection's weak pinning (lowest Hessian eigenvalue 3.3e-10), so Newton's directions
    line up along that mode at the round-off floor.  The follower declines the walk (the
    model's descent is below the energy's round-off) or takes no point (each one's energy
    change is round-off): no valley point, and the last load step converges in 10 iterations
    (29 while points were taken on round-off descents); with the round-off test switched off
    (any descent a walk, any lower energy a point) it walks."""
    from conftest import gathered_positions, run_case
    from test_verification import rigid_fit

    def ring(descends=None):
        if descends is not None:
            monkeypatch.setattr(minimize.EnergyMinimizer, "descends", descends)
        run = run_case("michell", load_twist_turns=1.2, load_steps=3, rod_nelem=11)
        assert run.ok
        return run, run.solver.results[-1]

    run, last = ring()
    assert last.valley_points == 0 and last.its <= 12, (last.valley_points, last.its)
    X = gathered_positions(run)
    walked, last_walked = ring(lambda self, E0, decrease: decrease > 0.0)
    assert last_walked.valley_points > 0 and last_walked.its > last.its + 5
    Y = gathered_positions(walked)
    assert rigid_fit(X, Y)[2] < 1e-9           # the same ring, turned along its symmetry
