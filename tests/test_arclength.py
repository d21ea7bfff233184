"""Pseudo-arclength continuation around a fold (-load_arclength, rodsnes/solve/arclength.py).

The scene: a clamped rod under a small end tension, its end turned 1.25 times (sliding end), no
contact (test_relax's TWISTED).  The nearly straight twisted rod's path folds at load 0.990;
the default path (the minimiser) snaps from there onto a stable loop.  Pseudo-arclength
continuation instead follows the branch: back through its unstable part (one negative
eigenvalue) to a second fold at load 0.418, then on, stable, with the load increasing, to the
loop at load 1.
"""
import numpy as np
import pytest

from conftest import run_case

# the Newton path's continuation (rodsnes/solve/newton.py, arclength.py)
pytestmark = [pytest.mark.usefixtures("newton_path"), pytest.mark.slow]

TWISTED = dict(rod_length=1, rod_radius=0.025, rod_youngs=1e6, rod_shear=666666.6666666666,
               rod_nelem=8, rod_imperfection=1e-3, bc_start="clamped", bc_end="sliding",
               bc_end_turns=1.25, load_end_force="3,0,0", load_steps=10, load_min_step=1e-4)


@pytest.fixture(scope="module")
def branch():
    """The continuation stopped inside the fold's unstable part (-load_arclength_max_steps 10),
    restarted from its directory to the end; and the default path's snap to compare with."""
    first = run_case(None, stability=True, load_arclength=True, load_arclength_max_steps=10,
                     load_arclength_its=12, **TWISTED)
    res_first = list(first.solver.results)
    rest = run_case(None, stability=True, load_arclength=True, load_arclength_its=12,
                    restart=first.outdir, outdir=first.outdir, **TWISTED)
    snap = run_case(None, load_path="auto", **TWISTED)
    return first, res_first, rest, snap


def test_arclength_follows_the_branch_around_both_folds(branch):
    """The arclength points: the load turns at 0.990 and at 0.418; one negative eigenvalue
    exactly where the load falls (a simple fold changes the Hessian's inertia by one where the
    load turns), none elsewhere; every point at the load steps' tolerance; Lk = Tw + Wr."""
    from rodsnes.io.results import read_step
    first, res_first, rest, _ = branch
    res = res_first + list(rest.solver.results)
    tol = first.solver.tolerance()
    assert all(r.converged and r.fnorm <= tol for r in res)
    arc = [i for i, r in enumerate(res) if getattr(r, "arclength", False)]
    assert arc and arc == list(range(arc[0], arc[-1] + 1))          # one stretch
    lam = np.array([r.lam for r in res])
    nneg = np.array([r.negative_eigenvalues for r in res])
    i0, i1 = arc[0] - 1, arc[-1]
    top = i0 + int(np.argmax(lam[i0:i1 + 1]))
    bottom = top + int(np.argmin(lam[top:i1 + 1]))
    assert 0.990 < lam[top] < 0.9905 and 0.40 < lam[bottom] < 0.43, (lam[top], lam[bottom])
    falling = np.diff(lam) < 0
    for i in range(1, len(res)):
        if i in (top + 1, bottom + 1):      # a step across a turning point: either side
            continue
        assert nneg[i] == (1 if falling[i - 1] else 0), (i, lam[i - 1], lam[i], nneg[i])
    assert nneg[:top + 1].max() == 0 and nneg[bottom + 1:].max() == 0
    assert (nneg[top + 1:bottom + 1] == 1).all()
    assert lam[-1] == 1.0
    for i in range(len(rest.history) + len(res_first)):
        a = read_step(first.outdir, i + 1)["attrs"]
        assert abs(a["link"] - (a["twist"] + a["writhe"])) < 1e-9


def test_the_corrector_converges_like_newton_at_the_same_load():
    """Newton on the bordered system (F = 0 and the arclength constraint) against plain Newton
    at fixed load from the same predicted state, at the load the corrector converged to: on
    the unstable part of the branch (a soft mode: both converge quadratically only once |F| <
    1e-6, with |F_k+1| / |F_k|^2 up to 1e4) the corrector needs at most one iteration more per
    step (plain Newton is given the load the corrector finds; the corrector finds it too).  A wrong border (F_lambda, the constraint row) would leave it
    converging linearly."""
    from rodsnes.solve.arclength import Arclength
    run = run_case(None, stability=True, load_arclength=True, load_arclength_max_steps=2,
                   **TWISTED)
    # two points do not reach past the fold: the run says the continuation stopped, not
    # "Newton failed after N cut-backs"
    assert not run.ok and "continuation around the fold at load 0.99" in run.solver.fail_reason
    assert "-load_arclength_max_steps (2 points)" in run.solver.fail_reason
    solver, p = run.solver, run.solver.problem
    arc = Arclength(solver)
    pairs = []
    corrector = arc.corrector

    def both(t, ds, snap_n, lam_n):
        res = corrector(t, ds, snap_n, lam_n)
        if res.converged:
            keep = p.state.snapshot()
            p.state.restore(snap_n)
            p.state.X.axpy(ds, t[0])                 # the same predicted state
            plain = solver.solve_at(res.lam)
            pairs.append((res, plain))
            p.state.restore(keep)
            p.set_load(res.lam)
        return res
    arc.corrector = both
    arc.max_steps = 5
    from rodsnes.io.results import read_step
    prev = p.state.snapshot_of_step(read_step(run.outdir, -2)), solver.results[-2].lam
    arc.around(1.0, prev=prev)
    assert len(pairs) == 5
    for res, plain in pairs:
        assert plain.converged and res.negative_eigenvalues == 1
        assert res.its <= plain.its + 1, (res.history, plain.history)


@pytest.mark.mpi
def test_a_restart_inside_the_continuation_ends_where_the_default_path_does(branch):
    """The run stopped after 10 arclength steps on the unstable branch (one negative eigenvalue,
    the fold's load stored with the step); the restart goes on from its last two points (secant)
    around the second fold and ends, stable, at load 1 on the same loop as the default path's
    snap past the fold: the same energy to 1e-12, link, twist, writhe to 1e-8 (writhe -0.98;
    without contact the rod passes through itself on the way, link 1.25 -> -0.75).  Serial and
    on 2 ranks."""
    from rodsnes.io.results import read_step
    first, res_first, rest, snap = branch
    assert not first.ok and len([r for r in res_first if getattr(r, "arclength", False)]) == 10
    assert res_first[-1].negative_eigenvalues == 1
    assert rest.ok and snap.ok and snap.path == "minimize"
    lam = [r.lam for r in rest.solver.results]
    assert getattr(rest.solver.results[0], "arclength", False) and min(lam) < 0.43
    a, b = read_step(first.outdir, -1)["attrs"], read_step(snap.outdir, -1)["attrs"]
    assert a["load"] == b["load"] == 1.0 and a["negative_eigenvalues"] == 0
    assert abs(a["energy"] - b["energy"]) <= 1e-12 * abs(b["energy"])
    for k in ("link", "twist", "writhe"):
        assert abs(a[k] - b[k]) < 1e-8, k
    assert abs(a["writhe"] + 0.98) < 0.01


def test_a_fold_met_again_is_not_gone_round_twice(monkeypatch):
    """A continuation that brings the path back to the fold it started from (a closed loop of
    equilibria) is not repeated: the second time the fold is met, the run ends there and says
    why.  Here the continuation is replaced by one that returns at once, as if it had come
    round."""
    from rodsnes.solve.newton import NewtonSolver
    calls = []

    def around(self, lam_fold, on_step, prev=None, ds=None, stop=1.0):
        calls.append(self.problem.lam)
        if len(calls) > 2:                 # round and round: fail, do not hang
            raise RuntimeError(f"the fold was gone round {len(calls)} times")
        return True, None, self.problem.lam, 0
    monkeypatch.setattr(NewtonSolver, "_around_fold", around)
    run = run_case(None, stability=True, load_arclength=True, **TWISTED)
    assert not run.ok and len(calls) == 1 and 0.990 < calls[0] < 0.9905
    assert abs(run.problem.lam - calls[0]) < 1e-12
    assert "came back to it (a closed loop of equilibria)" in run.solver.fail_reason


def test_a_load_without_energy_leaves_the_continuation_past_the_fold(monkeypatch):
    """Where the loads have no energy the inertia decides no stability: the continuation ends at
    the first point past the fold (the load rising again after it fell), whatever the count -
    here, from the fold on, the solver takes the loads for energy-free and every count says 1 -
    and load stepping goes on to the end (the continuation went on along the branch until a
    count said 0: to the end of the load here)."""
    from rodsnes.solve.arclength import Arclength
    from rodsnes.solve.newton import NewtonSolver
    real = Arclength.around

    def around(self, *args, **kwargs):
        self.solver.conservative = False
        monkeypatch.setattr(NewtonSolver, "negative_eigenvalues", lambda solver: 1)
        return real(self, *args, **kwargs)
    monkeypatch.setattr(Arclength, "around", around)
    run = run_case(None, stability=True, load_arclength=True, **TWISTED)
    assert run.ok
    res = list(run.solver.results)
    arc = [r for r in res if getattr(r, "arclength", False)]
    lam = np.array([r.lam for r in arc])
    assert len(arc) >= 3 and lam.min() < 0.43 and lam[-1] < 0.5 and lam[-1] > lam[-2], lam
    assert res[-1].lam == 1.0 and not getattr(res[-1], "arclength", False)


def test_no_wall_raise_follows_the_continuations_last_point(monkeypatch):
    """A penalty raise for the next step (RodProblem.ease_walls: where contact presses into its
    wall) comes between arclength points and before load stepping goes on, never after the
    last point of a continuation that stops (-load_arclength_max_steps 2: the run ends at its
    second point, which no step follows)."""
    from rodsnes.model.problem import RodProblem
    calls = []
    real = RodProblem.ease_walls

    def ease_walls(self, lam, *args, **kwargs):
        calls.append(lam)
        return real(self, lam, *args, **kwargs)
    monkeypatch.setattr(RodProblem, "ease_walls", ease_walls)
    run = run_case(None, stability=True, load_arclength=True, load_arclength_max_steps=2,
                   **TWISTED)
    arc = [r.lam for r in run.solver.results if getattr(r, "arclength", False)]
    assert not run.ok and len(arc) == 2
    assert arc[0] in calls and arc[-1] not in calls


def test_the_continuation_ends_at_the_load_stop():
    """-load_stop ends a continuation too (a staged run resumes from it): past the fold at
    0.990 the branch of the twisted rod comes back above 0.995 and the run ends there, where
    the continuation went on to the end of the load (a snapping arch with -load_stop 0.2 ended
    at 0.309, exit 0)."""
    run = run_case(None, stability=True, load_arclength=True, load_stop=0.995, **TWISTED)
    assert run.ok and abs(run.problem.lam - 0.995) < 1e-12
    assert any(getattr(r, "arclength", False) for r in run.solver.results)


def test_a_continuation_that_lands_on_another_branch_is_not_taken():
    """A snapping arch (clamped, 20 degrees, gravity toward its centre): the continuation from
    the bifurcation at 0.1285 first converged 15 steps ds away, on the snapped branch, and the
    run wrote that one point as the branch past the fold (exit 0).  A point farther than
    MAX_DRIFT ds from the last is not accepted (ds halved): no two points of the path lie far
    apart."""
    from rodsnes.solve import arclength
    run = run_case(None, rod_length=1, rod_EA=1e5, rod_GA=1e5, rod_EI=1, rod_GJ=1,
                   rod_radius=0.01, rod_shape="arc", rod_arc_angle=20, rod_nelem=16, rod_order=3,
                   bc_start="clamped", bc_end="clamped", load_gravity="-34.73,196.96,0",
                   load_steps=20, load_path="newton", stability=True, load_arclength=True,
                   load_arclength_max_steps=10, rod_error_estimate="off")
    arc = [r for r in run.solver.results if getattr(r, "arclength", False)]
    assert arc and all(abs(b.lam - a.lam) < 0.05 for a, b in zip(arc, arc[1:]))
    assert not run.ok or run.problem.lam < 0.2, run.problem.lam   # not the one point at 0.309
    assert arclength.MAX_DRIFT == 2.0
