"""Branch switching by relaxation (relax.py, stability.lowest_eigenpair, NewtonSolver.switch_branch):
the pseudo-time term against finite differences, the lowest eigenpair of the energy Hessian on the
twisted Michell ring, the perfect Euler column relaxed from the straight (unstable) state onto
the buckled elastica, the twisted clamped rod jumping into a loop at a fold, and the refusal
for non-conservative loads."""
import numpy as np
import pytest
from petsc4py import PETSc
from scipy.optimize import brentq
from scipy.special import ellipk

from conftest import build_run, gathered_positions, run_case, set_options

# the Newton path's own machinery (rodsnes/solver.py, relax.py, arclength.py)
pytestmark = pytest.mark.usefixtures("newton_path")


def _small_problem_layout(case="michell", **kw):
    """Mesh and a serial layout of a small scene (no solve)."""
    from rodsnes.mesh import build_mesh
    from rodsnes.partition import Layout
    from rodsnes.scene import read_scene
    scene = read_scene(["rodsnes"], set_options(case, **kw))
    mesh = build_mesh(scene.rod, scene.bc)
    return mesh, Layout(PETSc.COMM_SELF, mesh)


def test_relaxation_term_residual_and_tangent_match_finite_differences():
    from rodsnes import so3
    from rodsnes.relax import RelaxationTerm
    mesh, lay = _small_problem_layout(rod_nelem=2, rod_order=3)     # 6 nodes of a ring
    n = mesh.n_nodes
    rng = np.random.default_rng(7)
    term = RelaxationTerm(mesh, lay, c=3.0, c_rot=0.7)
    assert abs(term.M.sum() - mesh.length) < 1e-14 and np.all(term.M > 0)   # lumped int N_i ds
    a = mesh.x_init + 0.05 * rng.standard_normal((n, 3))
    qa = so3.qmul(so3.qexp(0.8 * rng.standard_normal((n, 3))), mesh.q_init)
    term.set_anchor(a, qa)

    def energy(r, q):
        return term.energy(r, q)

    def residual(r, q):
        F = np.zeros((n, 6))
        term.add_residual(r, q, F)
        return F

    def tangent(r, q):
        P = lay.create_matrix()
        term.add_jacobian(r, q, P)
        P.assemble()
        return P.convert("dense").getDenseArray().copy()

    def moved(r, q, i, k, h):
        r2, q2 = r.copy(), q.copy()
        if k < 3:
            r2[i, k] += h
        else:
            e = np.zeros(3)
            e[k - 3] = h
            q2[i] = so3.qmul(so3.qexp(e), q[i])      # R <- exp(theta^x) R, as SNES moves it
        return r2, q2

    # at the anchor: zero energy and residual, tangent diag(c M I, c_rot M I)
    assert energy(a, qa) == 0.0 and np.abs(residual(a, qa)).max() == 0.0
    K0 = tangent(a, qa)
    want = np.diag(np.repeat(term.M, 6) * np.tile([3.0] * 3 + [0.7] * 3, n))
    assert np.abs(K0 - want).max() < 1e-14
    # away from the anchor (rotations up to ~1.5 rad): residual = dE, tangent = dF (exact
    # J_l^{-1}(psi) on the rotation block), both by central differences
    r = a + 0.1 * rng.standard_normal((n, 3))
    q = so3.qmul(so3.qexp(0.5 * rng.standard_normal((n, 3))), qa)
    F, K = residual(r, q), tangent(r, q)
    h = 1e-6
    for point, (FF, KK) in (("anchor", (residual(a, qa), K0)), ("away", (F, K))):
        r0, q0 = (a, qa) if point == "anchor" else (r, q)
        for i in range(n):
            for k in range(6):
                rp, qp = moved(r0, q0, i, k, h)
                rm, qm = moved(r0, q0, i, k, -h)
                dE = (energy(rp, qp) - energy(rm, qm)) / (2 * h)
                assert abs(dE - FF[i, k]) < 1e-8 * (1 + abs(FF[i, k])), (point, i, k)
                dF = ((residual(rp, qp) - residual(rm, qm)) / (2 * h)).ravel()
                assert np.abs(dF - KK[:, 6 * i + k]).max() < 1e-7, (point, i, k)


@pytest.mark.mpi
def test_lowest_eigenvector_of_the_twisted_ring_is_the_writhing_mode():
    """Perfect Michell ring (nu = 0) at 2.5 turns, beyond sqrt(3): lam < 0 with H v = lam v; the
    mode leaves the plane: most of it lies in the out-of-plane unknowns (z, theta_x, theta_y) and
    its out-of-plane displacement is the two-wave (n = 2) writhing pattern.  (It is not purely
    out-of-plane: the twist couples the in-plane n = 2 deflection into it, so in- and out-of-plane
    motions alone are both stable.)  The dense and the sparse shift-invert path agree."""
    from rodsnes import so3
    from rodsnes.stability import hessian, lowest_eigenpair, negative_eigenvalues
    run = run_case("michell", load_twist_turns=2.5, rod_imperfection=0, rod_nelem=16, load_steps=4)
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
def test_perfect_euler_column_switches_onto_the_buckled_elastica():
    """Clamped-free column at 1.2 P_cr without imperfection: plain Newton stays on the straight,
    unstable state (negative eigenvalues); with -stability (switching on by default) the run
    leaves it at P_cr and ends on the elastica, tip deflection 2k/K(k), stable.  On two ranks
    the same tip as on one (the buckling plane of the isotropic column is neutral: compare the
    in-plane deflection and |y|)."""
    from rodsnes.stability import negative_eigenvalues
    exact = _elastica_tip()
    plain = run_case("euler", rod_imperfection=0, stability=False)
    assert plain.ok
    assert np.abs(gathered_positions(plain)[:, 1:]).max() < 1e-12      # straight
    assert negative_eigenvalues(plain.problem) == 2                     # unstable in y and z
    run = run_case("euler", rod_imperfection=0, stability=True)
    assert run.ok
    sw = [s for s in run.solver.switches if s["switched"]]
    assert len(sw) == 1 and len(run.solver.switches) == 1
    sw = sw[0]
    assert sw["negative_before"] == 2 and sw["negative_after"] == 0
    assert sw["energy_after"] < sw["energy_before"] and sw["energy_monotone"]
    switched = [r for r in run.solver.results if getattr(r, "branch_switch", False)]
    assert len(switched) == 1 and switched[0].negative_eigenvalues == 0
    assert switched[0].lam < 1.0 and abs(switched[0].lam - 1 / 1.2) < 2e-3   # at P_cr (+ shear)
    assert all(h["negative_eigenvalues"] == 0 for h in run.history)     # stable all along
    x = gathered_positions(run)[-1]
    assert abs(abs(x[1]) - exact) < 2e-3, (x, exact)
    assert abs(np.hypot(x[1], x[2]) - exact) < 1e-5                    # 16 cubic elements
    if PETSc.COMM_WORLD.getSize() > 1:
        ser = run_case("euler", comm=PETSc.COMM_SELF, rod_imperfection=0, stability=True,
                       outdir=run.outdir + f"_serial{PETSc.COMM_WORLD.getRank()}")
        xs = gathered_positions(ser)[-1]
        assert ser.ok and abs(xs[0] - x[0]) < 1e-8
        assert abs(np.hypot(xs[1], xs[2]) - np.hypot(x[1], x[2])) < 1e-8
        assert abs(abs(xs[1]) - abs(x[1])) < 1e-3            # plane may turn by roundoff


TWISTED = dict(rod_length=1, rod_radius=0.025, rod_youngs=1e6, rod_shear=666666.6666666666,
               rod_nelem=8, rod_imperfection=1e-3, bc_start="clamped", bc_end="sliding",
               bc_end_turns=1.25, load_end_force="3,0,0", load_steps=10, load_min_step=1e-4)


@pytest.mark.slow
def test_twisted_clamped_rod_jumps_into_a_loop_at_the_fold():
    """Clamped rod, small end tension, end turned 1.25 times (sliding end), no contact: the
    twisted, nearly straight rod's path folds at ~1.24 turns (imperfection 1e-3 L): no
    equilibrium beyond it, plain Newton stops there.  With -stability the run relaxes at the
    load of the shortest failed step (a jump) onto a stable loop (|writhe| ~ 1), the energy
    lower and falling all along the relaxation.  Without contact the rod may pass through
    itself on the way (here it does: link 1 -> -1, a change by 2 at one crossing)."""
    from rodsnes.output import read_step
    plain = run_case(None, stability=True, stability_switch="false", **TWISTED)
    assert not plain.ok and 0.95 < plain.problem.lam < 1.0
    run = run_case(None, stability=True, **TWISTED)
    assert run.ok and run.problem.lam == 1.0
    res = run.solver.results
    jumps = [i for i, r in enumerate(res) if getattr(r, "jump", False)]
    assert len(jumps) == 1 and len(run.solver.switches) == 1
    j = jumps[0]
    info = res[j].switch_info
    assert res[j].branch_switch and res[j].negative_eigenvalues == 0 and res[j].converged
    assert abs(res[j].lam - plain.problem.lam) < 1e-3
    assert info["energy_monotone"] and info["energy_after"] < info["energy_before"] - 1.0
    assert all(h["negative_eigenvalues"] == 0 for h in run.history)
    before, after = read_step(run.outdir, j)["attrs"], read_step(run.outdir, j + 1)["attrs"]
    # Lk of the open rod = turns put in (continuous in the load) + 2 per crossing
    dlink = after["link"] - before["link"] - 1.25 * (after["load"] - before["load"])
    assert min(abs(dlink), abs(abs(dlink) - 2)) < 1e-6               # 0 or one crossing
    assert abs(before["writhe"]) < 0.1 and abs(abs(after["writhe"]) - 1) < 0.05, (before, after)
    X = gathered_positions(run)
    assert np.hypot(X[:, 1], X[:, 2]).max() > 0.2                   # a loop, not a straight rod


@pytest.mark.slow
def test_a_jump_with_overshoot_relaxes_beyond_the_fold():
    """-stability_jump_overshoot 0.005: the same fold (at load 0.990), but the jump relaxes at
    the last converged load + 0.005 (not at the shortest step tried, 1e-4 beyond it), onto the
    same stable loop."""
    from rodsnes.output import read_step
    run = run_case(None, stability=True, stability_jump_overshoot=0.005, **TWISTED)
    assert run.ok
    res = run.solver.results
    j = [i for i, r in enumerate(res) if getattr(r, "jump", False)]
    assert len(j) == 1
    j = j[0]
    assert abs(res[j].lam - (res[j - 1].lam + 0.005)) < 1e-12
    assert res[j].negative_eigenvalues == 0 and res[j].switch_info["energy_monotone"]
    after = read_step(run.outdir, j + 1)["attrs"]
    assert abs(abs(after["writhe"]) - 1) < 0.05
    assert all(h["negative_eigenvalues"] == 0 for h in run.history)


def test_branch_switching_is_refused_for_non_conservative_loads(capsys):
    """Energy is no merit with an end moment or a follower force: an unstable step is kept, with
    one message."""
    from rodsnes.scene import read_scene
    from rodsnes.solver import StepResult, _nonconservative
    scene = read_scene(["rodsnes"], set_options("euler", load_end_force_follower=True))
    assert "follower" in _nonconservative(scene.loads)
    assert _nonconservative(read_scene(["rodsnes"], set_options("euler")).loads) is None
    run = run_case("rollup", rod_nelem=4)          # end moment
    solver = run.solver
    solver.switch, solver.quiet = True, False
    assert "end moment" in solver.switch_refused
    for _ in range(2):
        res = StepResult(1.0, True, 1, 2, 0.0, [], 0.0)
        res.negative_eigenvalues = 1
        assert solver._maybe_switch(res) is False and res.branch_switch is False
    out = capsys.readouterr().out
    if PETSc.COMM_WORLD.getRank() == 0:
        assert out.count("branch switching refused") == 1 and "end moment" in out
    assert solver.switches == []


@pytest.mark.slow
def test_twisted_ring_beyond_michell_leaves_the_unstable_circle():
    """T = 2.5 > sqrt(3) turns (nu = 0): plain load stepping stays on the unstable circle;
    with -stability the ring leaves it (branch switch), writhes during the relaxation and,
    having no contact term, passes through itself: the link changes by 2 and the energy ends
    below the circle's.  (A writhed equilibrium needs self-contact: the bifurcation is
    subcritical.)"""
    # 12 elements (the case has 24): the same fold, jump and crossing in half the time
    run = run_case("michell", load_twist_turns=2.5, stability=True, rod_nelem=12)
    assert run.ok
    # the attempts beyond the fold (no equilibrium near) stop at -load_stagnation_its (15)
    # iterations without progress, not at -snes_max_it (40); then the jump
    assert run.solver.stagnations >= 3
    assert run.summary(converged=True)["stagnated_solves"] == run.solver.stagnations
    assert any(sw.get("jump") for sw in run.solver.switches)
    circle = run_case("michell", load_twist_turns=2.5, rod_nelem=12, outdir=run.outdir + "_plain")
    assert circle.ok
    assert run.last_energy < 0.5 * circle.last_energy
    assert abs(abs(run.last_topology["link"] - circle.last_topology["link"]) - 2) < 1e-6
    assert run.history[-1].get("negative_eigenvalues") == 0


@pytest.mark.slow
def test_twisted_ring_beyond_michell_writhes_into_self_contact():
    """cases/michell_contact.opts (T = 2.5 > sqrt(3) turns, radius L/100, contact on): the load
    path leaves the circle near Michell's threshold, the ring writhes until its strands touch
    and follows the writhed, self-contacting branch to load 1.  Checks: converged at every step
    with the residual at tolerance, stable at the end, writhe of the order of the excess link
    and Lk = Tw + Wr = 0 (the ring cannot change its link: the contact keeps the strands
    apart), contact active and the penetration within the penalty's promise (1 % of the
    diameter), the sliding gauge's reaction zero to roundoff (it removes a symmetry, it
    holds no force), energy below the (unstable) circle's."""
    run = run_case("michell_contact")
    assert run.ok
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
    circle = run_case("michell_contact", contact=False, stability=False,
                      outdir=run.outdir + "_plain")
    assert circle.ok and abs(circle.last_topology["writhe"]) < 1e-3
    assert s["energy"] < circle.last_energy


@pytest.mark.mpi
def test_sliding_gauge_only_on_uniform_closed_rings_and_it_holds_no_force():
    """hold_sliding: a closed ring of uniform stress-free strains gets one held coordinate (of
    the node opposite node 0, along its tangent); with -rod_closed_gauge 0, on an open rod, or on
    a ring whose stress-free shape is not uniform, none.  On a circle in equilibrium it carries
    no force."""
    kw = dict(rod_nelem=8, load_twist_turns=0.5, load_steps=1)
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
    rod = run_case("euler", load_steps=1, outdir=run.outdir + "_open")
    assert not rod.problem.hold_sliding()


def test_a_failed_predicted_step_is_tried_again_from_the_last_state(tmp_path):
    """A load step that fails from the secant predictor is solved once more from the last
    converged state, at the same load, before it is cut back (the secant can carry a strand
    into another); summary.json counts these retries."""
    from rodsnes.solver import StepResult
    run = build_run("mattiasson", outdir=tmp_path, rod_nelem=4, load_steps=4)
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
    run = run_case("rollup", rod_nelem=2, load_steps=1)
    sv = run.solver
    assert sv.stagnation_its == 15

    def feed(norms):
        for it, f in enumerate(norms):
            r = sv._converged(sv.snes, it, (0.0, 0.0, f))
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



def test_levenberg_marquardt_phase_keeps_the_floor_of_the_first_stiffness(monkeypatch):
    """relax(): the LM phase starts at the flow's last c but its floor is 1e-12 x the first c.
    (Failed damped solves had grown the flow's c to 4e16 at the plectoneme's fold; a floor of
    1e-12 x that pinned LM at c = 4e4 for 200 steps.)"""
    from rodsnes import relax as rx
    calls = []

    def phase(solver, lam, c0, tol, max_steps=200, single_step=False, **kw):
        calls.append(dict(c0=c0, single_step=single_step, **kw))
        out = rx.RelaxResult()
        out.steps, out.energies, out.log, out.c_last = 3, [1.0, 0.9], [(), ()], 4e16
        out.ok = single_step
        return out

    monkeypatch.setattr(rx, "relax_phase", phase)
    out = rx.relax(None, 0.5, 147.0, 1e-9, max_steps=20)
    assert out.ok and len(calls) == 2
    assert calls[1]["single_step"] and calls[1]["c0"] == 4e16
    assert calls[1]["c_min"] == pytest.approx(1e-12 * 147.0)


def test_levenberg_marquardt_is_stalled_only_once_back_at_its_first_stiffness(tmp_path, monkeypatch):
    """relax_phase (single_step): a run of rejected steps ends the phase only once c has grown
    back to the phase's first c.  Here every step is first kept (the fake damped solve leaves
    the state: the energy does not rise), so c falls by 3 per step to its floor 1e-12 c0; then
    every step is rejected and c grows by 4 per rejection.  Counting 12 rejections alone
    stopped at c = 4^12 x 1e-12 c0 = 1.7e-5 c0 (the plectoneme's 8.80-turn jump: stopped at
    c = 3 while descending, its first c 7e5); now it goes on until a rejected step was tried
    at c >= c0: c = 4^20 x 1e-12 c0 = 1.1 c0 is rejected the 21st time."""
    from rodsnes import relax as rx
    from rodsnes.solver import StepResult
    solver = build_run("mattiasson", outdir=tmp_path, rod_nelem=4, load_steps=4).solver
    R = PETSc.SNES.ConvergedReason
    calls = []

    def fake(lam):           # one Newton step "taken", the state left as it is
        calls.append(lam)
        if len(calls) <= 40:
            return StepResult(lam, False, 1, R.DIVERGED_MAX_IT, 1.0, [1.0], 0.0)
        return StepResult(lam, False, 1, R.DIVERGED_FNORM_NAN, np.nan, [np.nan], 0.0)

    solver.solve_guarded = fake
    c0 = 10.0
    # the kept steps here go nowhere, which would raise c (IDLE_STEPS, tested below): held off
    # so that c falls to its floor as described
    monkeypatch.setattr(rx, "IDLE_STEPS", 10 ** 6)
    rr = rx.relax_phase(solver, 0.5, c0, 1e-12, max_steps=200, single_step=True)
    assert not rr.ok and "stalled" in rr.message
    assert rr.steps == 40 and rr.rejected == 21
    assert c0 <= rr.c_last < 4 * c0


def test_a_relaxation_step_that_changes_the_link_is_rejected(tmp_path):
    """relax_phase: a step after which the link differs from the start's by 1/2 or more (a
    strand went through another: the plectoneme's 8.80-turn jump, Levenberg-Marquardt, went
    from Lk 8.81 to 6.81, most likely in its end loop, where the motion was largest) is
    rejected like a failed one.  The damped solve is faked (the state stays) and the link
    reported changed for the 2nd and 3rd candidate steps: 2 rejections, counted as crossings.
    (Only with contact: without it the model lets a strand through, e.g. the twisted rod
    without contact snapping into a loop.)"""
    from rodsnes import relax as rx
    from rodsnes.solver import StepResult
    run = build_run("michell", outdir=tmp_path, rod_nelem=8, contact=True)
    solver, p = run.solver, run.problem
    p.set_load(0.5)                       # twisted, not in equilibrium: |F| > 0
    link0 = p.topology()["link"]
    R = PETSc.SNES.ConvergedReason
    solver.solve_guarded = lambda lam: StepResult(lam, False, 1, R.DIVERGED_MAX_IT, 1.0, [1.0], 0.0)
    calls = []
    real = p.topology

    def topology():
        calls.append(1)
        t = real()
        if len(calls) in (3, 4):          # call 1: the start; 2: first step; 3, 4: crossed
            t["link"] += 2.0
        return t

    p.topology = topology
    rr = rx.relax_phase(solver, 0.5, 10.0, 1e-12, max_steps=6, single_step=True)
    assert rr.crossings == 2 and rr.rejected == 2 and rr.steps == 4
    assert abs(real()["link"] - link0) < 1e-9


@pytest.mark.mpi
def test_a_restart_from_an_unstable_state_is_relaxed_onto_a_stable_one():
    """-stability_switch_restart: a restart from an unstable equilibrium (the twisted ring at 2.5
    > sqrt(3) turns, left on the circle by plain load stepping, which stores no inertia) counts
    its negative eigenvalues afresh and relaxes it onto a stable equilibrium at the same load,
    also when the restart stands at -load_stop already: one new step, branch_switch, no
    negative eigenvalue, the energy well below the circle's.  Without -restart, or without
    -stability, the option is refused by name."""
    from rodsnes.output import read_step
    from rodsnes.scene import SceneError
    kw = dict(load_twist_turns=2.5, rod_nelem=12)
    circle = run_case("michell", **kw)          # rank 0's directory on every rank
    assert circle.ok and abs(circle.last_topology["writhe"]) < 1e-3
    nsteps = len(circle.history)
    run = run_case("michell", outdir=circle.outdir + "_relaxed", restart=circle.outdir,
                   stability=True, stability_switch_restart=True, **kw)
    assert run.ok
    assert len(run.history) == 1
    h = run.history[0]
    assert h["load"] == 1.0 and h["branch_switch"] and h["negative_eigenvalues"] == 0
    assert h["residual_norm"] <= run.solver.tolerance()
    assert run.last_energy < 0.5 * circle.last_energy
    last = read_step(run.outdir, -1)
    assert last["step"] == nsteps + 1 and last["attrs"]["branch_switch"]
    for bad in (dict(stability=True), dict(restart=circle.outdir)):
        with pytest.raises(SceneError, match="-stability_switch_restart"):
            build_run("michell", outdir=circle.outdir + "_bad", stability_switch_restart=True,
                      **bad, **kw)


@pytest.mark.mpi
def test_an_unfinished_relaxation_is_kept_on_disk_and_goes_on_from_there():
    """A relaxation keeps its state every 25 kept steps and when it ends unfinished in
    DIR/relaxation (one step: not an equilibrium, with the phase and c to go on from), while
    the run's own report stays that of its last equilibrium; a restart
    from there with -stability_switch_restart goes on with it (no new push along an
    eigenvector) to the equilibrium the uninterrupted relaxation finds, and is written as the
    step the switch would have been.  A finished relaxation removes the directory.  Restarting
    from it without -stability_switch_restart is refused by name.  The twisted ring at 2.5
    turns left on the circle: 30 kept steps uninterrupted; cut at -stability_relax_max_it 8."""
    import os
    from rodsnes.output import read_step
    from rodsnes.scene import SceneError
    kw = dict(load_twist_turns=2.5, rod_nelem=12)
    circle = run_case("michell", **kw)
    assert circle.ok
    nsteps = len(circle.history)
    switch = dict(restart=circle.outdir, stability=True, stability_switch_restart=True, **kw)
    # uninterrupted, with a spy on the keeper: kept at 25 steps, removed when finished
    full = build_run("michell", outdir=circle.outdir + "_full", **switch)
    calls = []
    keeper = full.solver.on_relaxation

    def spy(lam, info):        # (collective: every rank looks before rank 0 removes it)
        full.mpi.Barrier()
        calls.append((info["final"], info["ok"], os.path.isdir(os.path.join(full.outdir, "relaxation"))))
        keeper(lam, info)
    full.solver.on_relaxation = spy
    assert full.execute()
    assert calls[0][:2] == (False, False) and calls[-1][:2] == (True, True)
    assert calls[-1][2]            # it was on disk until the relaxation finished
    assert not os.path.exists(os.path.join(full.outdir, "relaxation"))
    # cut short: the run fails, its result.h5 unchanged, the relaxed state kept
    short = run_case("michell", outdir=circle.outdir + "_short", stability_relax_max_it=8, **switch)
    assert not short.ok
    kept = os.path.join(short.outdir, "relaxation")
    assert kept in short.solver.fail_reason
    # its report stays the restart state's (the keeper does not overwrite it)
    assert short.last_energy == pytest.approx(circle.last_energy, rel=1e-12)
    assert short.solver.switches[-1]["energy_after"] == pytest.approx(circle.last_energy, rel=1e-9)
    last = read_step(kept, -1)
    a = last["attrs"]
    assert last["step"] == nsteps + 1 and a["relaxation_unfinished"] and a["branch_switch"]
    assert a["residual_norm"] > short.solver.tolerance()
    assert full.last_energy < a["energy"] < circle.last_energy
    assert a["relaxation_phase"] in ("flow", "lm") and a["relaxation_c"] > 0
    # gone on with: the uninterrupted run's equilibrium, written as step nsteps + 1
    resumed = run_case("michell", outdir=circle.outdir + "_resumed",
                       **dict(switch, restart=kept))
    assert resumed.ok and len(resumed.history) == 1
    h = resumed.history[0]
    assert h["branch_switch"] and h["negative_eigenvalues"] == 0
    assert h["residual_norm"] <= resumed.solver.tolerance()
    assert resumed.solver.switches[0]["eigen_method"] == "resumed relaxation"
    assert abs(resumed.last_energy - full.last_energy) <= 1e-8 * full.last_energy
    assert read_step(resumed.outdir, -1)["step"] == nsteps + 1
    with pytest.raises(SceneError, match="-stability_switch_restart"):
        build_run("michell", outdir=circle.outdir + "_bad", restart=kept, stability=True, **kw)
    # kept as it stalled, with a c grown to where no step moves (the plectoneme: 1.5e25): it
    # goes on from at most the c of a first damped step, to the same equilibrium
    if resumed.rank == 0:
        import shutil
        import h5py
        shutil.copytree(kept, kept + "_stalled")
        with h5py.File(os.path.join(kept + "_stalled", "result.h5"), "a") as f:
            f["steps"][sorted(f["steps"])[-1]].attrs["relaxation_c"] = 1e25
    resumed.mpi.Barrier()
    stalled = run_case("michell", outdir=circle.outdir + "_resumed_stalled",
                       **dict(switch, restart=kept + "_stalled"))
    assert stalled.ok and stalled.history[0]["negative_eigenvalues"] == 0
    assert abs(stalled.last_energy - full.last_energy) <= 1e-8 * full.last_energy


def test_damped_solves_at_a_large_stiffness_meet_the_roundoff_of_the_term(capsys):
    """The pseudo-time term c M (x - a) carries a roundoff error eps |x| c M per row; a damped
    solve is converged once its residual is at that floor (RelaxationTerm.roundoff), else every
    solve at a large c fails at its iteration limit (the plectoneme's flow at c > 1e9: 8e-8
    against the elastic floor 3.2e-9).  Mattiasson's cantilever at c = 1e12: all three steps are
    taken (without the term's floor all three damped solves fail), the solver's own floor is
    restored afterwards, and the progress line names the steps and rejections."""
    from rodsnes.relax import relax_phase
    run = build_run("mattiasson", load_steps=10, quiet=False)
    s = run.solver
    floor = s.floor
    s.problem.set_load(0.1)
    rr = relax_phase(s, 0.1, 1e12, s.tolerance(), max_steps=3, progress_every=1)
    assert rr.steps == 3 and rr.rejected == 0 and rr.causes["solve"] == 0
    assert s.floor == floor
    out = capsys.readouterr().out
    if run.comm.getRank() == 0:
        assert "relaxation (flow): 3 steps (0 rejected)" in out


def test_levenberg_marquardt_corrects_its_step_before_judging_it():
    """An LM step is LM_ITS = 2 Newton iterations of the damped problem (the second corrects the
    first's linearisation error): from the straight cantilever at a tenth of Mattiasson's load,
    where a linearised turn stretches the stiff rod (EA = 1e6 EI/L^2) and one iteration is kept
    only for tiny turns (97 steps, 12 rejected), LM converges in at most 20 steps."""
    import rodsnes.relax as R
    run = build_run("mattiasson", load_steps=10)
    s = run.solver
    s.problem.set_load(0.1)
    rr = R.relax_phase(s, 0.1, s._first_stiffness(), s.tolerance(), max_steps=40,
                       single_step=True)
    assert R.LM_ITS == 2
    assert rr.ok and rr.steps <= 20 and rr.rejected <= 2, (rr.steps, rr.rejected)


def test_a_flow_that_no_longer_lowers_the_energy_is_pinned_and_stops():
    """A flow held at a large c (here by c_min; on the plectoneme at 9.415 turns by the floor
    over c's that failed) keeps steps that do not move: once the energy has fallen by less than
    1000 x its roundoff over PINNED_WINDOW kept steps the phase stops ("pinned"), and relax()
    hands over to Levenberg-Marquardt.  The same flow with c free to fall is not pinned."""
    import rodsnes.relax as R
    run = build_run("mattiasson", load_steps=10)
    s = run.solver
    s.problem.set_load(0.1)
    snap = s.problem.state.snapshot()
    rr = R.relax_phase(s, 0.1, 1e12, s.tolerance(), max_steps=200, c_min=1e12)
    assert rr.steps == R.PINNED_WINDOW and rr.message.startswith("pinned"), rr.message
    s.problem.state.restore(snap)
    s.problem.set_load(0.1)
    rr = R.relax_phase(s, 0.1, 1e12, s.tolerance(), max_steps=200)
    assert rr.ok and not rr.message, rr.message


def test_a_relaxation_step_that_presses_the_strands_too_deep_is_rejected(tmp_path):
    """relax_phase with contact: a kept step after which the deepest penetration exceeds
    PENETRATION_GUARD x -contact_penetration (or the start's, if deeper) is rejected (the Newton
    precheck lets each iteration double the penetration, and over the plectoneme's 150-step
    switch at 9.415 turns the strands sank into each other until every step changed the link).
    The damped solve is faked (the state stays) and the deepest penetration reported at 20 %
    of the diameter for the 2nd and 3rd candidate steps: 2 rejections, by cause penetration."""
    from rodsnes import relax as rx
    from rodsnes.solver import StepResult
    run = build_run("michell", outdir=tmp_path, rod_nelem=8, contact=True)
    solver, p = run.solver, run.problem
    p.set_load(0.5)
    R = PETSc.SNES.ConvergedReason
    solver.solve_guarded = lambda lam: StepResult(lam, False, 1, R.DIVERGED_MAX_IT, 1.0, [1.0], 0.0)
    calls = []
    real = p.contact.deepest

    def deepest(r_loc=None):
        calls.append(1)
        d = real(r_loc)
        return 0.2 * 2 * p.contact.eps if len(calls) in (3, 4) else d   # 1: the start

    p.contact.deepest = deepest
    assert rx.PENETRATION_GUARD * p.contact.penetration < 0.2
    rr = rx.relax_phase(solver, 0.5, 10.0, 1e-12, max_steps=6, single_step=True)
    assert rr.causes["penetration"] == 2 and rr.rejected == 2 and rr.steps == 4, rr.causes


def test_a_step_too_long_whatever_c_grows_c_faster(tmp_path):
    """relax_phase: a step rejected as too long (downhill, but a node moved beyond max_move)
    scales c by 1.25 x move / max_move (the move ~ 1/c); when the next one moves nearly as far
    (c is below the stiffness along the step, which is then Newton's whatever c) c grows by the
    full factor 4.  The damped solve is faked as a rigid translation of the Michell ring by
    1.5 max_move (the energy unchanged): c x 1.875, then x 4 at every further rejection."""
    from rodsnes import relax as rx
    from rodsnes.solver import StepResult
    run = build_run("michell", outdir=tmp_path, rod_nelem=8)
    solver, p = run.solver, run.problem
    p.set_load(0.5)
    R = PETSc.SNES.ConvergedReason
    cs = []

    def translate(lam):
        cs.append(p.extra_terms[-1].c)
        with p.state.X as a:
            a.reshape(-1, 6)[:, 0] += 0.15
        return StepResult(lam, False, 1, R.DIVERGED_MAX_IT, 1.0, [1.0], 0.0)

    solver.solve_guarded = translate
    rr = rx.relax_phase(solver, 0.5, 10.0, 1e-12, max_steps=5, single_step=True, max_move=0.1)
    assert rr.steps == 0 and rr.causes["too far"] == 5
    assert np.allclose(np.array(cs[1:]) / np.array(cs[:-1]), [1.875, 4, 4, 4])


def test_levenberg_marquardt_steps_that_go_nowhere_raise_c(monkeypatch):
    """At c's floor the plectoneme's switch at 9.415 turns kept 150 Levenberg-Marquardt steps
    with the energy equal to 1e-11 and |F| unchanged (two Newton iterations that return where
    they started).  Faked here: below c = 1 the damped solve leaves the state as it is.  After
    IDLE_STEPS such kept steps c is raised by grow^3 and the phase converges; without the
    raise it stays below 1 and ends without an equilibrium."""
    import rodsnes.relax as R
    from rodsnes.solver import StepResult
    run = build_run("mattiasson", load_steps=10)
    s, p = run.solver, run.problem
    p.set_load(0.1)
    real = s.solve_guarded
    Rs = PETSc.SNES.ConvergedReason
    seen = []

    def cycling(lam):
        c = p.extra_terms[-1].c
        seen.append(c)
        if c < 1.0:
            return StepResult(lam, False, R.LM_ITS, Rs.DIVERGED_MAX_IT, 1.0, [1.0] * 3, 0.0)
        return real(lam)

    s.solve_guarded = cycling
    snap = p.state.snapshot()
    rr = R.relax_phase(s, 0.1, 1e-3, s.tolerance(), max_steps=60, single_step=True, c_min=1e-9)
    assert rr.ok, rr.message
    assert rr.idle_raises >= 1 and max(seen) >= 1.0
    assert all(c < 1.0 for c in seen[:R.IDLE_STEPS])
    p.state.restore(snap)
    p.set_load(0.1)
    monkeypatch.setattr(R, "IDLE_STEPS", 10 ** 6)
    seen.clear()
    rr = R.relax_phase(s, 0.1, 1e-3, s.tolerance(), max_steps=60, single_step=True, c_min=1e-9)
    assert not rr.ok and max(seen) < 1.0
