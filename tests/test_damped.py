"""-load_damped_its N: a load step whose Newton solve failed is solved again by
Levenberg-Marquardt (NewtonSolver.solve_damped) before it is cut back."""
import numpy as np
import pytest

from conftest import gathered_positions, run_case
from rodsnes.scene import SceneError

# the Newton path's own machinery (rodsnes/solver.py, relax.py, arclength.py)
pytestmark = pytest.mark.usefixtures("newton_path")


def test_levenberg_marquardt_takes_the_steps_newton_fails():
    """Mattiasson's cantilever in 10 steps with Newton held to 3 iterations: plain Newton fails
    even after 2 cut-backs and the run stops; with the fallback the steps are taken by
    Levenberg-Marquardt, to the step tolerance, and the path ends at the equilibrium of an
    unhindered run.  LM keeps a step only if the energy falls, and with EA = 1e6 EI / L^2 a
    linearised step that turns the rod by da stretches it by ~da^2/2 at a cost ~EA da^4 / 8:
    with one Newton iteration per LM step the ten load steps took 109, 79, 64, 51, 43, 18, 16,
    14, 14, 13 iterations, with the corrected step (relax.LM_ITS = 2) 28 - 20 (14 - 10 steps)."""
    ref = run_case("mattiasson", load_steps=10)
    held = run_case("mattiasson", load_steps=10, snes_max_it=3, load_max_cutbacks=2)
    damped = run_case("mattiasson", load_steps=10, snes_max_it=3, load_max_cutbacks=2,
                      load_damped_its=40)
    assert ref.ok and damped.ok
    assert not held.ok                                  # plain Newton: cut back, then stopped
    lm = [h for h in damped.history if h.get("damped")]
    assert len(lm) >= 8 and damped.solver.damped_solves >= len(lm)
    assert max(h["newton_iterations"] for h in lm) <= 40      # at most 20 corrected LM steps
    tol = damped.solver.tolerance()
    assert all(h["residual_norm"] <= tol for h in damped.history)
    assert abs(damped.last_energy - ref.last_energy) < 1e-9 * abs(ref.last_energy)
    assert np.abs(gathered_positions(damped) - gathered_positions(ref)).max() < 1e-7


def test_levenberg_marquardt_needs_conservative_loads():
    with pytest.raises(SceneError) as ei:
        run_case("mattiasson", load_end_force_follower="true", load_damped_its=20)
    assert "-load_damped_its" in str(ei.value) and "follower" in str(ei.value)


def test_a_relaxed_equilibrium_survives_a_polish_that_cycles():
    """NewtonSolver._polish: when the undamped solve that confirms a relaxed equilibrium fails
    (next to a contact edge it can 2-cycle away from a state already at tolerance), the relaxed
    state comes back, accepted with its own residual if that meets the tolerance, else not."""
    from rodsnes.relax import undamped_residual_norm
    from rodsnes.solver import StepResult
    run = run_case("mattiasson", load_steps=2)
    s, p = run.solver, run.problem
    x0 = gathered_positions(run).copy()
    tol = s.tolerance()
    f = undamped_residual_norm(p, None)          # the "relaxed" state's residual

    def cycling(lam):           # a Newton solve that wanders off and fails
        with p.state.X as a:
            a[:] += 1e-3
        return StepResult(lam, False, 40, "stagnation", 3.4e-4, np.array([3.4e-4]), 0.0)

    s.solve_guarded = cycling
    res = s._polish(1.0, tol, f)
    assert res.converged and res.reason == "relaxed" and res.fnorm == f <= tol
    assert np.abs(run.layout.allgather_nodes(p.owned_fields()["positions"]) - x0).max() == 0.0
    res = s._polish(1.0, 1e-30, f)
    assert not res.converged
