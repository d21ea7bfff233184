"""The twisted clamped rod of cases/plectoneme.opts (the PyElastica plectoneme scene: L = 1,
radius 0.025, E = 1e6, G = E/1.5, end clamped in rotation and sliding along the axis under a
small tension), here to 1.5 turns instead of 10 with 40 elements so that it fits the test budget (~3 min): the
straight rod's loop formation is a fold of the stable path, which -stability passes by
relaxation (jump_branch) into a loop in self-contact.  The full 10 turns are a batch run
(README, Plectoneme)."""
import os

import numpy as np
import pytest

from conftest import ROOT, build_run, run_case


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


CHECKPOINTS = os.path.join(ROOT, "cases", "checkpoints")
# checkpoints that break the penetration promise (the stable branch at
# 9.415 turns presses the rod 2.3 % into the start clamp's mount at the penalty of the switch;
# the first load step from it raises the penalty): kept to go on from, with their measured
# penetration held here
OVER_PROMISE = {"plectoneme_9.415_switched": 0.0227}
# the contact law of each checkpoint's path: the closest-point law up to session 24, the pair
# potential of cases/plectoneme.opts since (docs/contact.md: contact law)
PROJECTION = ("plectoneme_7.2", "plectoneme_7.54", "plectoneme_9.12", "plectoneme_9.19",
              "plectoneme_9.41", "plectoneme_9.415_switched", "plectoneme_9.72")


def law(name):
    return "projection" if name in PROJECTION else "potential"


def _checkpoints():
    return sorted(d for d in os.listdir(CHECKPOINTS)
                  if os.path.exists(os.path.join(CHECKPOINTS, d, "result.h5")))


def test_the_plectoneme_checkpoints_are_kept():
    """README (Plectoneme) resumes the 10-turn run from cases/checkpoints/: they must be there."""
    assert len(_checkpoints()) >= 1


@pytest.mark.slow
@pytest.mark.mpi
@pytest.mark.parametrize("name", _checkpoints() if os.path.isdir(CHECKPOINTS) else [])
def test_a_plectoneme_checkpoint_is_an_equilibrium_of_the_current_code(name, tmp_path, monkeypatch):
    """A checkpoint of the batch run (tools/checkpoint.py) read back by -restart, as the README's
    resume command does, is still an equilibrium of this code's rod and contact terms: the
    residual at the stored state within the load steps' tolerance (or twice the residual stored
    with it), Lk = the imposed turns within 1e-2 and Tw + Wr = Lk, penetration within 1 % of
    the diameter (OVER_PROMISE: within its measured value), the stored penalty and energy
    restored.  A change to the energy, the contact
    term or the result format that moves the plectoneme's equilibria fails here."""
    from rodsnes.contact import potential as contact_potential
    from rodsnes.io import results as output
    # the pair-potential checkpoints were made with the quadratic law (no onset layer,
    # contact_potential.ONSET = 0), before the C2 onset became the default
    monkeypatch.setattr(contact_potential, "ONSET", 0.0)
    ckpt = os.path.join(CHECKPOINTS, name)
    last = output.read_step(ckpt, -1)
    run = build_run("plectoneme", outdir=tmp_path, restart=ckpt, contact_model=law(name))
    p = run.problem
    assert run.lam0 == last["attrs"]["load"] and run.step == last["step"]
    assert run.contact.mu == last["attrs"]["contact_penalty"]
    F = p.F.duplicate()
    p.residual(None, p.state.X, F)
    fnorm = F.norm()
    assert fnorm <= max(run.solver.tolerance(), 2 * last["attrs"]["residual_norm"])
    _, energy, cattrs, _, topo = run.observe()
    assert abs(energy - last["attrs"]["energy"]) <= 1e-9 * abs(energy)
    turns = run.scene.bc.end_turns * run.lam0
    assert abs(topo["link"] - turns) < 1e-2
    assert abs(topo["twist"] + topo["writhe"] - topo["link"]) < 1e-9
    assert 0.0 < cattrs["contact_max_penetration"] <= OVER_PROMISE.get(name, 0.01) * (1 + 1e-6)
    if name in OVER_PROMISE:
        assert last["attrs"]["negative_eigenvalues"] == 0 and last["attrs"]["branch_switch"]


@pytest.mark.slow
def test_a_penalty_raise_whose_solve_fails_is_cut_back_to_a_smaller_one(tmp_path):
    """-contact_penalty_adapt: a re-solve at the raised mu that fails (faked: the first solve of
    the raise reports failure without moving) is tried again with the
    geometric mean of the two penalties, and the raises go on from there until the promise
    holds (the plectoneme's switched state at 9.415 turns: x 2.8 failed Newton, x 1.25
    converged in 22 its).  The checkpoint at 7.2 turns held to 0.6 %.  Without the cut-back
    the raise fails and the state keeps its penetration."""
    from rodsnes.solve.newton import StepResult
    ckpt = os.path.join(CHECKPOINTS, "plectoneme_7.2")
    target = 0.006
    run = build_run("plectoneme", outdir=tmp_path, restart=ckpt, load_path="newton",
                    contact_penetration=target,
                    contact_model=law("plectoneme_7.2"))
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
    assert c.deepest(run.problem.state.local_config()[0]) / (2 * c.eps) <= target
    assert res.fnorm <= s.tolerance()
