"""Equilibria past an instability, on the default path (the minimiser: every load step ends
on a stable equilibrium, so a buckling, a snap into a loop or a writhing ring is a descent),
and the Newton path's own pieces (-load_path newton): the lowest eigenpair of the energy
Hessian on the twisted Michell ring left on the circle, the perfect Euler column past
buckling ending on the elastica, the twisted clamped rod past its fold ending on a loop, the
twisted ring writhing into self-contact, a restart from an unstable state, the sliding gauge,
the Newton path's predictor retry and stagnation test.  (The phantom ring passing through
itself: tests/test_minimize.py.)"""
import numpy as np
import pytest
from petsc4py import PETSc
from scipy.optimize import brentq
from scipy.special import ellipk

from conftest import build_run, gathered_positions, run_case


@pytest.mark.mpi
def test_lowest_eigenvector_of_the_twisted_ring_is_the_writhing_mode():
    """Perfect Michell ring (nu = 0) at 2.5 turns, beyond sqrt(3), left on the circle by the Newton
    path (a zero of the residual): lam < 0 with H v = lam v; the
    mode leaves the plane: most of it lies in the out-of-plane unknowns (z, theta_x, theta_y) and
    its out-of-plane displacement is the two-wave (n = 2) writhing pattern.  (It is not purely
    out-of-plane: the twist couples the in-plane n = 2 deflection into it, so in- and out-of-plane
    motions alone are both stable.)  The dense and the sparse shift-invert path agree."""
    from rodsnes.model import so3
    from rodsnes.solve.stability import hessian, lowest_eigenpair, negative_eigenvalues
    run = run_case("michell", load_twist_turns=2.5, rod_imperfection=0, rod_nelem=16, load_steps=4,
                   load_path="newton")
    assert run.ok
    p = run.problem
    assert negative_eigenvalues(p) == 2                 # the n = 2 pair (n = 3 needs sqrt 8 turns)
    lam, v, info = lowest_eigenpair(p)
    assert info["method"] == "dense" and info["n"] == 6 * run.mesh.n_nodes
    assert lam < -1e-4
    H = hessian(p)
    r = v.duplicate()
    H.mult(v, r)
    r.axpy(-lam, v)
    assert abs(v.norm() - 1) < 1e-12 and r.norm() < 1e-6 * abs(lam), r.norm()
    V = run.layout.allgather_nodes(v.getArray(readonly=True).reshape(-1, 6))
    out, inp = np.linalg.norm(V[:, [2, 3, 4]]), np.linalg.norm(V[:, [0, 1, 5]])
    assert out**2 > 0.55 and out > inp, (out, inp)
    # displacement without its rigid part (node 0 is held, which mixes rigid motion in)
    X = run.mesh.x_init
    c = X.mean(0)
    G = np.zeros((3 * len(X), 6))
    for i, x in enumerate(X - c):
        G[3 * i:3 * i + 3, :3] = np.eye(3)
        G[3 * i:3 * i + 3, 3:] = -so3.hat(x)
    u = V[:, 0:3].ravel()
    ud = (u - G @ np.linalg.lstsq(G, u, rcond=None)[0]).reshape(-1, 3)
    assert np.linalg.norm(ud[:, 2]) > 0.5 * np.linalg.norm(ud[:, 0:2])
    phi = np.arctan2(X[:, 1] - c[1], X[:, 0] - c[0])
    B = np.stack([np.ones_like(phi)] + [f(k * phi) for k in range(1, 5) for f in (np.cos, np.sin)], 1)
    co = np.linalg.lstsq(B, ud[:, 2], rcond=None)[0]
    amp = np.array([abs(co[0])] + [np.hypot(co[2 * k - 1], co[2 * k]) for k in range(1, 5)])
    assert np.argmax(amp) == 2 and amp[2] > 4 * np.delete(amp, 2).max(), amp
    # the sparse path (shift-invert Lanczos + inverse-iteration refinement) finds the same pair
    lam2, v2, info2 = lowest_eigenpair(p, nneg=2, dense_max=0)
    assert info2["method"] == "eigsh"
    assert abs(lam2 - lam) < 1e-8 * abs(lam) and abs(v.dot(v2)) > 1 - 1e-9


def _elastica_tip():
    k = np.sqrt(brentq(lambda m: (2 * ellipk(m) / np.pi) ** 2 - 1.2, 1e-9, 0.99))
    return 2 * k / ellipk(k * k)


@pytest.mark.mpi
def test_perfect_euler_column_ends_on_the_buckled_elastica():
    """Clamped-free column at 1.2 P_cr without imperfection: the Newton path (a zero of the
    residual) stays on the straight, unstable state (negative eigenvalues); the default path
    leaves it at P_cr and ends on the elastica, tip deflection 2k/K(k), stable at every step.
    On two ranks the same tip as on one (the buckling plane of the isotropic column is neutral:
    compare the axial tip and the deflection)."""
    from rodsnes.io.results import read_step
    from rodsnes.solve.stability import negative_eigenvalues
    exact = _elastica_tip()
    plain = run_case("euler", rod_imperfection=0, stability=False, load_path="newton")
    assert plain.ok
    assert np.abs(gathered_positions(plain)[:, 1:]).max() < 1e-12      # straight
    assert negative_eigenvalues(plain.problem) == 2                     # unstable in y and z
    run = run_case("euler", rod_imperfection=0)
    assert run.ok and run.path == "minimize"
    assert all(h["negative_eigenvalues"] == 0 for h in run.history)     # stable all along
    # straight below P_cr (1/1.2 of the load, + shear), buckled beyond it
    for k, h in enumerate(run.history, start=1):
        tip = np.asarray(read_step(run.outdir, k)["positions"])[-1]
        if h["load"] < 1 / 1.2 - 2e-3:
            assert np.hypot(tip[1], tip[2]) < 1e-8, (h["load"], tip)
        elif h["load"] > 1 / 1.2 + 2e-3:
            assert np.hypot(tip[1], tip[2]) > 1e-2, (h["load"], tip)
    x = gathered_positions(run)[-1]
    assert abs(np.hypot(x[1], x[2]) - exact) < 1e-5                    # 16 cubic elements
    if PETSc.COMM_WORLD.getSize() > 1:
        ser = run_case("euler", comm=PETSc.COMM_SELF, rod_imperfection=0,
                       outdir=run.outdir + f"_serial{PETSc.COMM_WORLD.getRank()}")
        xs = gathered_positions(ser)[-1]
        assert ser.ok and abs(xs[0] - x[0]) < 1e-8
        assert abs(np.hypot(xs[1], xs[2]) - np.hypot(x[1], x[2])) < 1e-8


TWISTED = dict(rod_length=1, rod_radius=0.025, rod_youngs=1e6, rod_shear=666666.6666666666,
               rod_nelem=8, rod_imperfection=1e-3, bc_start="clamped", bc_end="sliding",
               bc_end_turns=1.25, load_end_force="3,0,0", load_steps=10, load_min_step=1e-4)


@pytest.mark.slow
def test_twisted_clamped_rod_snaps_into_a_loop_past_the_fold():
    """Clamped rod, small end tension, end turned 1.25 times (sliding end), no contact: the
    twisted, nearly straight rod's path folds at ~1.24 turns (imperfection 1e-3 L): no
    equilibrium beyond it, the Newton path stops there.  The default path snaps past the fold
    onto a stable loop (|writhe| ~ 1), stable at every step, and ends at load 1.  Without
    contact the rod may pass through itself on the way (link changed by 0 or 2)."""
    from rodsnes.io.results import read_step
    plain = run_case(None, stability=True, load_path="newton", **TWISTED)
    assert not plain.ok and 0.95 < plain.problem.lam < 1.0
    fold = plain.problem.lam
    run = run_case(None, **TWISTED)
    assert run.ok and run.problem.lam == 1.0 and run.path == "minimize"
    assert all(h["negative_eigenvalues"] == 0 for h in run.history)
    attrs = [read_step(run.outdir, k)["attrs"] for k in range(len(run.history) + 1)]
    j = next(k for k, a in enumerate(attrs) if abs(a["writhe"]) > 0.5)     # the first loop
    before, after = attrs[j - 1], attrs[j]
    assert before["load"] < fold + 1e-3 and after["load"] > fold - 1e-3   # snapped at the fold
    # Lk of the open rod = turns put in (continuous in the load) + 2 per crossing
    dlink = after["link"] - before["link"] - 1.25 * (after["load"] - before["load"])
    assert min(abs(dlink), abs(abs(dlink) - 2)) < 1e-6               # 0 or one crossing
    assert abs(before["writhe"]) < 0.1 and abs(abs(attrs[-1]["writhe"]) - 1) < 0.05, (before, after)
    X = gathered_positions(run)
    assert np.hypot(X[:, 1], X[:, 2]).max() > 0.2                   # a loop, not a straight rod


@pytest.mark.slow
def test_twisted_ring_beyond_michell_writhes_into_self_contact():
    """cases/michell_contact.opts (T = 2.5 > sqrt(3) turns, radius L/100, contact on): the load
    path leaves the circle near Michell's threshold, the ring writhes until its strands touch
    and follows the writhed, self-contacting branch to load 1.  Checks: converged at every step
    with the residual at tolerance, stable at the end, writhe of the order of the excess link
    and Lk = Tw + Wr = 0 (the ring cannot change its link: the contact keeps the strands
    apart), contact active and the penetration within the penalty's promise (1 % of the
    diameter), the sliding gauge's reaction zero to roundoff (it removes a symmetry, it
    holds no force), energy below the (unstable) circle's (the Newton path without -stability
    stays on it)."""
    run = run_case("michell_contact")
    assert run.ok and run.path == "minimize"
    s = run.summary(converged=True)
    assert all(h["residual_norm"] < 1e-9 for h in run.history)
    assert run.history[-1].get("negative_eigenvalues") == 0
    topo = s["topology"]
    assert abs(topo["link"]) < 1e-6
    assert abs(topo["twist"] + topo["writhe"]) < 1e-6
    assert 1.0 < topo["writhe"] < 2.5
    c = s["contact"]
    assert c["active_points"] > 0 and c["total_force"] > 0 and c["zones"] >= 1
    assert 0 < c["max_penetration"] < 0.01
    assert abs(s["gauge"]["reaction"]) < 1e-8 * run.force_scale
    circle = run_case("michell_contact", contact=False, stability=False, load_path="newton",
                      outdir=run.outdir + "_plain")
    assert circle.ok and abs(circle.last_topology["writhe"]) < 1e-3
    assert s["energy"] < circle.last_energy


@pytest.mark.mpi
def test_a_restart_from_an_unstable_state_ends_on_a_stable_one():
    """A restart from an unstable equilibrium (the twisted ring beyond sqrt(3) turns, left on the
    circle by the Newton path to load 0.8: negative eigenvalues) goes on, on the default path,
    to load 1 with every step stable: the ring leaves the circle and, having no contact term,
    passes through itself (link changed by 2, as the uninterrupted default path does:
    tests/test_minimize.py)."""
    from rodsnes.solve.stability import negative_eigenvalues
    kw = dict(load_twist_turns=2.5, rod_nelem=12)
    circle = run_case("michell", load_path="newton", load_stop=0.8, **kw)
    assert circle.ok and abs(circle.last_topology["writhe"]) < 1e-3
    assert negative_eigenvalues(circle.problem) > 0
    # the first step's descent from deep on the unstable circle through the ring's crossing
    # takes 143 iterations (of -load_max_it 200)
    run = run_case("michell", outdir=circle.outdir + "_on", restart=circle.outdir, **kw)
    assert run.ok and run.path == "minimize" and run.history[-1]["load"] == 1.0
    assert all(h["negative_eigenvalues"] == 0 for h in run.history)
    assert abs(abs(run.last_topology["link"] - circle.last_topology["link"]) - 2) < 1e-6


@pytest.mark.mpi
def test_sliding_gauge_only_on_uniform_closed_rings_and_it_holds_no_force():
    """hold_sliding: a closed ring of uniform stress-free strains gets one held coordinate (of
    the node opposite node 0, along its tangent); with -rod_closed_gauge 0, on an open rod, or on
    a ring whose stress-free shape is not uniform, none.  On a circle in equilibrium it carries
    no force.  (The Newton path never holds it: the runs here leave it to the test.)"""
    kw = dict(rod_nelem=8, load_twist_turns=0.5, load_steps=1, load_path="newton")
    run = run_case("michell", **kw)
    p = run.problem
    rows = len(p.constraints.rows_global)
    assert p.hold_sliding() and p.gauge[0] == run.mesh.n_nodes // 2
    assert p.gauge_report()["reaction"] == pytest.approx(0.0, abs=1e-9 * run.force_scale)
    assert PETSc.COMM_WORLD.tompi4py().allreduce(len(p.constraints.rows_global) - rows) == 1
    assert not p.hold_sliding()                           # once
    off = run_case("michell", rod_closed_gauge="false", outdir=run.outdir + "_off", **kw)
    assert not off.problem.hold_sliding()
    bumpy = run_case("michell", rod_kappa0=None, outdir=run.outdir + "_b", **kw)   # imperfect as built
    assert not bumpy.problem.hold_sliding()
    rod = run_case("euler", load_steps=1, load_path="newton", outdir=run.outdir + "_open")
    assert not rod.problem.hold_sliding()


def test_a_failed_predicted_step_is_tried_again_from_the_last_state(tmp_path):
    """The Newton path: a load step that fails from the secant predictor is solved once more from the last
    converged state, at the same load, before it is cut back (the secant can carry a strand
    into another); summary.json counts these retries."""
    from rodsnes.solve.newton import StepResult
    run = build_run("mattiasson", outdir=tmp_path, rod_nelem=4, load_steps=4, load_path="newton")
    solver = run.solver
    solve, calls = solver.solve_guarded, []

    def flaky(lam):
        calls.append(lam)
        if len(calls) == 2:                    # the second step, from the predictor
            return StepResult(lam, False, 40, -5, 1.0, [], 0.0)
        return solve(lam)

    solver.solve_guarded = flaky
    assert run.execute()
    assert calls[1] == calls[2] == 0.5 and len(calls) == 5     # retried, not cut back
    assert solver.predictor_retries == 1 and len(run.history) == 4
    import json
    with open(f"{run.outdir}/summary.json") as f:
        assert json.load(f)["predictor_retries"] == 1


def test_newton_that_stops_gaining_fails_early():
    """-load_stagnation_its N: a solve whose best |F| has not halved in N iterations fails (and
    the load step is cut back) instead of running to -snes_max_it.  The residual sequence is the
    one measured at the fold of the Michell ring (cases/michell.opts, load 0.6871): Newton
    2-cycles between ~2e-3 and ~1e-7 and never converges.  A slow but steady solve (|F| halved
    every 6 iterations) is left alone; N = 0 switches the test off."""
    from petsc4py import PETSc
    R = PETSc.SNES.ConvergedReason
    run = run_case("rollup", rod_nelem=2, load_steps=1)          # end moment: the Newton path
    sv = run.solver
    assert run.path == "newton" and sv.stagnation_its == 15

    def feed(norms):
        for it, f in enumerate(norms):
            r = sv.convergence_test(sv.snes, it, (0.0, 0.0, f))
            if r != R.CONVERGED_ITERATING:
                return it, r
        return None, None

    cycle = [4.8e-3, 2.4e-7, 2.1e-3, 9.2e-8] + [2.5e-3, 1.1e-7, 1.7e-3, 9.2e-8] * 8
    it, r = feed(cycle)
    assert (it, r) == (3 + 15, R.DIVERGED_MAX_IT) and sv.stagnated      # best 9.2e-8 at it 3
    slow = [1.0 * 0.5 ** (k / 5.5) for k in range(35)]
    assert feed(slow) == (None, None) and not sv.stagnated
    sv.stagnation_its = 0
    assert feed(cycle) == (None, None)


@pytest.mark.mpi
def test_a_failed_eigen_solve_raises_on_every_rank():
    """lowest_eigenpair solves on rank 0: its failure (a Hessian that is not finite) is raised
    on every rank, none left waiting for the eigenvector."""
    from rodsnes.solve.stability import lowest_eigenpair
    run = build_run("euler", rod_nelem=8, load_path="newton")
    p = run.problem
    with p.state.X as a:
        a[0] = np.nan
    with pytest.raises(ValueError):
        lowest_eigenpair(p)


@pytest.mark.mpi
def test_stability_of_a_load_without_energy_is_counted_not_enforced():
    """-stability with a dead end moment in 3-D (the helix): the loads have no energy, so the
    Hessian's inertia decides no stability; the count is reported (summary.json
    "negative_eigenvalues", "stable": null) and no step is cut back for it.  Before, the
    converged step (3 iterations, 6 negative eigenvalues against none at the start) was cut
    back for being "less stable" until the run failed, exit 3."""
    ref = run_case("helix")
    run = run_case("helix", stability=True)
    assert run.ok and ref.ok
    s = run.summary(converged=True)
    assert s["stable"] is None and s["negative_eigenvalues"] > 0
    assert [h["load"] for h in run.history] == [h["load"] for h in ref.history] == [1.0]
    assert "-stability: a dead end moment is not conservative" in run.header()
    assert abs(run.problem.energy() - ref.problem.energy()) <= 1e-12 * abs(ref.problem.energy())
