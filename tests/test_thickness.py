"""The contact tube's thickness bound on bending (-contact_curvature, on with -contact).

A cantilever of length 3 eps under an end moment M = 2 EI/eps: without the bound it bends to the
circle of curvature M/EI = 2/eps, tighter than its own radius.  No two points of it are farther
apart in arclength than pi eps, so the exclusion hides every pair and the contact term alone
cannot stop it.  With the bound, the flexure solves EI kappa + mu_kappa (kappa - 1/eps) = M with
mu_kappa = EI/p (p = -contact_penetration):

    kappa eps = (2 + 1/p) / (1 + 1/p) = 1 + p/(1 + p)          (1.00990 for p = 1 %)

and a pure end moment leaves v = e3 (no force), so the rod is the circular arc of that curvature;
the finite-element solution (8 cubic elements) is within 1e-6 L of it (the rotations'
interpolation between nodes).
The tangent of the bound is checked against finite differences of the residual in
tests/test_elastic.py (test_residual_is_gradient_and_tangent_is_derivative_of_residual[*-True])."""
import math

import numpy as np
import pytest

from conftest import run_case

EPS = 0.01
EI = 1e6 * math.pi * EPS ** 4 / 4


def _cantilever(**kw):
    return run_case(None, rod_length=3 * EPS, rod_radius=EPS, rod_nelem=8, rod_order=3,
                    bc_start="clamped", bc_end="free", load_steps=4,
                    load_end_moment="0,0,%r" % (2 * EI / EPS), **kw)


def _arc_tip(kappa, L=3 * EPS):
    return np.array([math.sin(kappa * L) / kappa, (1 - math.cos(kappa * L)) / kappa, 0.0])


@pytest.mark.mpi
@pytest.mark.parametrize("p", [0.01, 0.05])
def test_end_moment_bends_the_rod_no_tighter_than_its_radius(p):
    run = _cantilever(contact=True, contact_penetration=p)
    assert run.ok
    s = run.summary(converged=run.ok)
    expected = 1 + p / (1 + p)
    assert s["contact"]["max_curvature"] == pytest.approx(expected, rel=1e-6)
    assert s["contact"]["active_points"] == 0           # the exclusion hides every pair
    tip = np.asarray(s["tip_position"])
    assert np.abs(tip - _arc_tip(expected / EPS)).max() < 1e-6 * 3 * EPS
    # Newton through the bound's kink at kappa = 1/eps: no more iterations per load step than
    # the free rod needs (12 for its first step, which bends it by 1.5 rad)
    assert max(h["newton_iterations"] for h in s["steps"]) <= 12


@pytest.mark.mpi
def test_without_the_bound_the_rod_bends_tighter_than_its_radius():
    """-contact_curvature false (or no contact): the circle of curvature M/EI = 2/eps."""
    for kw in (dict(contact=True, contact_curvature="false"), dict()):
        run = _cantilever(**kw)
        assert run.ok
        s = run.summary(converged=run.ok)
        assert "max_curvature" not in s.get("contact", {})
        assert np.abs(np.asarray(s["tip_position"]) - _arc_tip(2 / EPS)).max() < 1e-6 * 3 * EPS
