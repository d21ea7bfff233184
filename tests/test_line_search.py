"""The minimiser's line search on a one-dimensional energy E(alpha) (minimize.EnergyMinimizer
._line_search, on a stub whose energy is a function of the step): a first trial that meets
Armijo's condition but falls by less than INTERPOLATE of the linear prediction is also
interpolated, a full step that falls as if linear is extrapolated within the move limits,
and Newton's end game (a quadratic trial that falls by half the slope) is taken as it is."""
import pytest
from petsc4py import PETSc

from rodsnes.solve import minimize


class _Line(minimize.EnergyMinimizer):
    """EnergyMinimizer on the line x = alpha d (one unknown, d = 1): E(alpha) = energy(x)."""

    def __init__(self, energy, longest=8.0):
        self.energy = energy
        self.longest = longest
        self.problem = None
        self.roundoff, self.energy_scale = 1e-12, 1.0
        self._trial = None
        self.evaluations = []

    def energy_at(self, X):
        x = X.getArray(readonly=True)[0]
        self.evaluations.append(x)
        return self.energy(x), None

    def _longest_step(self, d, most=1.0):
        return min(most, self.longest)


def _search(energy, slope, longest=8.0):
    m = _Line(energy, longest)
    X = PETSc.Vec().createSeq(1)
    X.set(0.0)
    Xt, d = X.duplicate(), X.duplicate()
    d.set(1.0)
    ok, alpha, tries = m._line_search(X, Xt, d, slope, 1.0, 1.0, energy(0.0), None)
    assert Xt.getArray(readonly=True)[0] == pytest.approx(alpha, abs=0)   # Xt is at alpha
    assert m._trial[0] == energy(alpha)                                  # and its energy
    return ok, alpha, tries, m.evaluations


def test_a_step_past_the_minimum_is_interpolated():
    """E = (a - 0.55)^2 - 0.3025: E(1) = -0.1 meets Armijo's condition (slope -1.1) but is 9 %
    of the linear prediction; the quadratic's minimiser 0.55 is tried and taken."""
    ok, alpha, tries, evals = _search(lambda a: (a - 0.55) ** 2 - 0.3025, -1.1)
    assert ok is True and tries == 0
    assert alpha == pytest.approx(0.55, rel=1e-12) and len(evals) == 2


def test_a_step_too_short_is_extrapolated_within_the_move_limits():
    """E = -a up to a = 3, then a steep wall: 2 is taken (4 is up the wall); with the move
    limit at 1.5 times the step, none is tried."""
    wall = lambda a: -a + (10.0 * (a - 3.0) ** 2 if a > 3.0 else 0.0)
    ok, alpha, _, evals = _search(wall, -1.0)
    assert ok is True and alpha == 2.0 and evals == [1.0, 2.0, 4.0]
    ok, alpha, _, evals = _search(wall, -1.0, longest=1.5)
    assert ok is True and alpha == 1.0 and evals == [1.0]


def test_newtons_step_on_a_quadratic_is_taken_as_it_is():
    """E = (a - 1)^2: the full step falls by half the slope (-2): one evaluation, alpha 1."""
    ok, alpha, tries, evals = _search(lambda a: (a - 1.0) ** 2, -2.0)
    assert ok is True and alpha == 1.0 and evals == [1.0]


def test_switched_off_the_first_acceptable_trial_is_taken(monkeypatch):
    monkeypatch.setattr(minimize, "INTERPOLATE", 0.0)
    monkeypatch.setattr(minimize, "EXTRAPOLATE", 0.0)
    ok, alpha, _, evals = _search(lambda a: (a - 0.55) ** 2 - 0.3025, -1.1)
    assert alpha == 1.0 and evals == [1.0]
