"""Prescribed end turns arrive whatever the load steps: a rotation is a point of SO(3), known
only modulo a full turn, so no load step may turn the end by more than solver.MAX_TURN_STEP."""
import numpy as np
import pytest

from conftest import run_case
from rodsnes.solve import newton as solver

# the Newton path's load steps (the minimiser's: tests/test_minimize.py)
pytestmark = pytest.mark.usefixtures("newton_path")

TWISTED = dict(rod_length=1, rod_radius=0.025, rod_youngs=1e6, rod_shear=666666.6666666666,
               rod_nelem=16, bc_start="clamped", bc_end="sliding", load_end_force="3,0,0")


@pytest.mark.parametrize("turns,steps", [(3.0, 1), (0.6, 1), (-6.0, 10), (0.2, 1)])
def test_the_imposed_turns_arrive_as_link(turns, steps):
    """3 turns in one step gave the untwisted rod (link 0), 0.6 turns link -0.4, 6 turns in 10
    steps link -4; now the link is the imposed turns and the steps are at most a quarter turn."""
    run = run_case(None, bc_end_turns=turns, load_steps=steps, **TWISTED)
    assert run.ok
    assert abs(run.last_topology["link"] - turns) < 1e-9
    loads = np.r_[0.0, [h["load"] for h in run.history]]
    assert np.diff(loads).max() * abs(turns) <= solver.MAX_TURN_STEP + 1e-12
    assert len(run.history) == max(steps, int(np.ceil(abs(turns) / solver.MAX_TURN_STEP - 1e-9)))
