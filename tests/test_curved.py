"""A full Newton step tried along its curve (EnergyMinimizer._curved): where the plectoneme's
ply lengthens (7.2 turns, tests/data/plectoneme_7.2) the straight step climbs the contact's
wall at second order and the line search keeps a fraction of it; the step x + d + a / 2, a the
second-order departure of the residual corrected in the stiff modes, goes further down."""
import numpy as np

from conftest import build_run
from rodsnes.solve import minimize
from test_valley import LOAD, SEVEN_TURNS, _one_step as valley_step


def _one_step(monkeypatch, curved, spy=None):
    """The crawling step 0.72 -> LOAD from the checkpoint (test_valley._one_step, the walks
    on), with or without the curved trial; returns (MinimizeResult, energy)."""
    monkeypatch.setattr(minimize, "CURVED", curved)
    return valley_step(monkeypatch, True, spy)


def test_the_departure_from_newtons_prediction_is_second_order(monkeypatch):
    """Along Newton's direction d (K d = -g) the residual departs from the linear prediction
    (1 - t) g as C t^2 (what _curved measures at t = CURVE_H and corrects): at the crawl's
    start the departure at t = 0.1 is 4 x that at t = 0.05, and at t = 0.01 a hundredth of
    that at t = 0.1."""
    monkeypatch.setattr(minimize, "CURVED", False)
    run = build_run("plectoneme", restart=SEVEN_TURNS)
    lp = run.solver
    m, p = lp.minimizer, run.problem
    lp.predict(run.prev0, run.lam0, LOAD - run.lam0)
    p.set_load(LOAD)
    p.state.recentre()
    p.ensure_pattern()
    m.gradient()
    g = p.F.copy()
    d = g.duplicate()
    assert m._newton_step(g, d) and m.by_ksp
    X = p.state.X

    def departure(t):
        Xt = X.copy()
        Xt.axpy(t, d)
        r = g.duplicate()
        p.residual(None, Xt, r)
        r.axpy(-(1.0 - t), g)
        out = r.norm()
        for v in (Xt, r):
            v.destroy()
        return out

    D01, D005, D001 = departure(0.1), departure(0.05), departure(0.01)
    assert D01 > 1e-5 * g.norm()          # far above the residual's round-off
    assert abs(D01 / D005 - 4.0) < 0.4
    assert abs(D01 / D001 - 100.0) < 10.0


def test_the_curved_step_goes_below_the_straight_one(monkeypatch):
    """Every curved step kept lies below Newton's straight full step from the same point (the
    straight one climbs the wall the curve goes round), and below the point it left by
    Armijo's margin; the factor of K is no longer the KSP's after it."""
    seen = []

    def spy(m):
        orig = m._curved

        def curved(X, Xt, d, slope, E0, depth0):
            straight = X.copy()
            straight.axpy(1.0, d)
            E_line = m.energy_at(straight)[0]
            straight.destroy()
            ok = orig(X, Xt, d, slope, E0, depth0)
            if ok:
                seen.append((E0, slope, E_line, m._trial[0], m.by_ksp))
            return ok
        m._curved = curved

    res, _ = _one_step(monkeypatch, True, spy)
    assert res.converged and len(seen) >= 5
    for E0, slope, E_line, E_curve, by_ksp in seen:
        assert E_curve <= E0 + minimize.ARMIJO * slope
        assert E_curve < E_line
        assert not by_ksp
