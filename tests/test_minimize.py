"""The energy-minimisation load path (rodsnes/solve/load_path.py and minimize.py, -load_path minimize, the default for
conservative loads): every converged step is a stable equilibrium, saddles are left along
negative curvature, the Hessian is the derivative of the gradient, Newton's end game is
quadratic, prescribed turns arrive as link whatever the step, and the plectoneme forms from
the straight rod without any rule for it."""
import numpy as np
import pytest
from petsc4py import PETSc

from conftest import build_run, run_case
from rodsnes.solve import load_path

TWISTED = dict(rod_length=1, rod_radius=0.025, rod_youngs=1e6, rod_shear=666666.6666666666,
               bc_start="clamped", bc_end="sliding")


def _all_stable(run):
    return all(h.get("negative_eigenvalues") == 0 for h in run.history)


@pytest.mark.mpi
def test_hessian_is_the_derivative_of_the_gradient():
    """H v = (g(x + h v) - g(x - h v)) / 2h at a converged Mattiasson state (where the chart's
    symmetric Hessian is the consistent tangent), for a random v in the chart."""
    run = run_case("mattiasson", load_steps=2, load_stop=0.5)
    assert run.ok and run.path == "minimize"
    p = run.problem
    H = p.inertia.assemble(None)
    v = p.F.duplicate()
    lo, hi = v.getOwnershipRange()
    rng = np.random.default_rng(1)
    v.setArray(rng.standard_normal(hi - lo) * np.tile([1, 1, 1, 1, 1, 1], (hi - lo) // 6))
    with v as a:
        a[p.constraints.rows_local] = 0.0
    Hv = v.duplicate()
    H.mult(v, Hv)
    X0 = p.state.X.copy()
    gp, gm = v.duplicate(), v.duplicate()
    h = 1e-6
    for sign, out in ((1.0, gp), (-1.0, gm)):
        X = X0.copy()
        X.axpy(sign * h, v)
        p.residual(None, X, out)
    fd = gp.copy()
    fd.axpy(-1.0, gm)
    fd.scale(0.5 / h)
    with fd as a:
        a[p.constraints.rows_local] = 0.0
    with Hv as a:
        a[p.constraints.rows_local] = 0.0
    err = fd.copy()
    err.axpy(-1.0, Hv)
    assert err.norm() < 1e-6 * Hv.norm()


def test_newton_end_game_is_quadratic():
    """A load step of a Mattiasson cantilever from a converged state: |g| falls
    quadratically, |g_k+1| / F <= 50 (|g_k| / F)^2 (F the force scale) over the iterations
    above round-off, and the whole load in one step converges too.  (EA = GA = 1e3 EI: with
    the case's 1e6 the residual is an axial force imbalance whose constant hides the
    quadratic rate of the error until round-off; the Newton path shows the same history.)"""
    run = build_run("mattiasson", load_steps=1, rod_EA=1e3, rod_GA=1e3)
    p, m = run.problem, run.solver.minimizer
    p.set_load(0.0)
    assert m.solve_at(1.0).converged                # the whole load at once
    res = m.solve_at(0.9)
    assert res.converged and res.negative_eigenvalues == 0
    g = res.history[res.history > 1e2 * m.floor] / run.force_scale
    assert len(g) >= 3
    assert np.all(g[1:] <= 50.0 * g[:-1] ** 2)


@pytest.mark.mpi
def test_every_step_ends_stable_and_says_so():
    """Euler column past buckling: every step is a minimum (negative_eigenvalues 0 in
    summary.json's steps), the summary says stable, and the tip is the elastica's (the same as
    the Newton path's), in fewer iterations."""
    run = run_case("euler")
    s = run.summary(converged=run.ok)
    assert run.ok and s["path"] == "minimize"
    assert _all_stable(run) and s["stable"] is True and s["negative_eigenvalues"] == 0
    ref = run_case("euler", load_path="newton", stability=True, outdir=run.outdir + "_newton")
    assert ref.ok
    assert np.allclose(s["tip_position"], ref.summary(converged=True)["tip_position"], atol=1e-8)
    assert run.solver.total_its < ref.solver.total_its


@pytest.mark.mpi
@pytest.mark.parametrize("case, kw", [
    ("euler", dict(rod_imperfection=0, rod_planar="off", load_end_force="-6,0,0", load_steps=2)),
    ("ltb", dict())])
def test_a_symmetric_saddle_is_left_the_same_way_on_any_number_of_ranks(case, kw):
    """The perfect column in 3-D past buckling: every plane through its axis holds a buckled
    branch of the same energy, and the lowest mode's seed picks one.  Drawn from the unknowns'
    natural numbers (Layout.natural_rows), not PETSc's, which a rank's stretch numbered from
    its far end changes: the run on the ranks of mpirun ends where the serial run ends (on 2
    and 3 ranks a seed of PETSc's numbers took the tip 0.2-0.7 L elsewhere).  The narrow
    cantilever past lateral-torsional buckling (cases/ltb.opts) has two mirror branches, and
    the gradient is orthogonal to the mode there: the mode's own orientation picks the side
    (EnergyMinimizer._oriented: its largest entry positive), where the sign inverse iteration
    left was round-off (the 2-rank run ended on the mirror image, tip z +0.2804 for -0.2804)."""
    kw = dict(kw, rod_error_estimate="off")
    par = run_case(case, **kw)
    ser = run_case(case, comm=PETSc.COMM_SELF,
                   outdir=par.outdir + f"_s{PETSc.COMM_WORLD.getRank()}", **kw)
    assert par.ok and ser.ok
    tp, ts = (r.summary(converged=True)["tip_position"] for r in (par, ser))
    assert np.hypot(ts[1], ts[2]) > 0.25                    # buckled
    assert case != "ltb" or abs(ts[2]) > 0.2                # ltb: out of its plane
    assert np.allclose(tp, ts, atol=1e-6), (tp, ts)


def test_a_load_step_does_not_depend_on_an_earlier_steps_lowest_mode():
    """The lowest mode an escape found (the inverse iteration's start at the next escape) is
    forgotten at every load step: a step depends on its start state alone, which result.h5
    holds, so that a restart takes the steps the run took (the plectoneme resumed after
    escapes at two earlier steps took 118 iterations for 117 and ended 5e-4 L elsewhere)."""
    runs = []
    for planted in (False, True):
        run = build_run("euler", rod_imperfection=0, rod_planar="off", load_steps=1,
                        rod_error_estimate="off")
        m, p = run.solver.minimizer, run.problem
        if planted:                 # as if an earlier step had escaped along another mode
            m._mode = p.F.duplicate()
            m._mode.setArray(np.cos(np.arange(m._mode.getLocalSize()) * 0.7))
        p.set_load(0.0)
        res = m.solve_at(1.0)
        assert res.converged and res.escapes >= 1
        runs.append((res.its, p.state.X.getArray().copy(), p.state.q_ref.copy()))
    assert runs[0][0] == runs[1][0]
    assert np.array_equal(runs[0][1], runs[1][1]) and np.array_equal(runs[0][2], runs[1][2])


def test_a_saddle_is_left_along_negative_curvature():
    """The perfect column (no imperfection) loaded past buckling in one step: the straight
    state is an equilibrium with one negative eigenvalue, where Newton would stop.  The
    minimiser steps along the lowest mode and ends on the buckled, stable column."""
    run = build_run("euler", rod_imperfection=0, load_steps=1)
    p = run.problem
    p.set_load(0.0)
    res = run.solver.minimizer.solve_at(1.0)
    assert res.converged and res.negative_eigenvalues == 0
    assert res.escapes >= 1 and res.shifts >= 1
    tip = p.owned_fields()["positions"][-1] if p.layout.comm.getSize() == 1 else None
    if tip is not None:
        assert np.hypot(tip[1], tip[2]) > 0.3       # buckled (the straight tip has 0)


@pytest.mark.parametrize("turns,steps", [(3.0, 1), (-2.6, 1), (0.6, 1)])
def test_turns_arrive_in_one_step(turns, steps):
    """Prescribed end turns in one load step: the path splits it to at most
    load_path.MAX_TURN_STEP turns a step and spreads each as twist along the rod; the link is
    the imposed turns.  (Tension 300: the twisted straight rod is stable up to about 7 turns;
    under the plectoneme's tension 3 a rod without contact writhes past 1.1 turns and passes
    through itself, test_phantom_ring_may_pass_through_itself.)"""
    run = run_case(None, bc_end_turns=turns, load_steps=steps, rod_nelem=16,
                   load_end_force="300,0,0", **TWISTED)
    assert run.ok and run.path == "minimize"
    assert abs(run.last_topology["link"] - turns) < 1e-9
    loads = np.r_[0.0, [h["load"] for h in run.history]]
    assert np.diff(loads).max() * abs(turns) <= load_path.MAX_TURN_STEP + 1e-12
    assert _all_stable(run)


def test_phantom_ring_may_pass_through_itself():
    """Michell's ring past its threshold without contact: the minimiser leaves the unstable
    circle and the ring, having no contact term, passes through itself (link changes by 2,
    which the path accepts only without contact) to a stable state far below the circle's
    energy."""
    run = run_case("michell", rod_nelem=12)
    assert run.ok and _all_stable(run)
    circle = run_case("michell", rod_nelem=12, load_path="newton", outdir=run.outdir + "_c")
    assert circle.ok
    assert run.last_energy < 0.5 * circle.last_energy
    assert abs(abs(run.last_topology["link"] - circle.last_topology["link"]) - 2) < 1e-6


def _plectoneme(turns, **kw):
    kw.setdefault("load_steps", max(int(turns * 4), 1))
    opts = dict(TWISTED, contact=True, contact_model="potential", bc_end_turns=turns, **kw)
    return run_case(None, **opts)


def _check_plectoneme(run, turns, resolved=False):
    s = run.summary(converged=run.ok)
    assert run.ok and _all_stable(run)
    topo = s["topology"]
    assert abs(topo["link"] - turns) < 1e-6           # no strand passed through another
    assert topo["writhe"] > 0.3 * turns                # a plectoneme, not the twisted rod
    assert s["contact"]["max_penetration"] <= s["contact"]["penetration_promised"] * (1 + 1e-9)
    # the pair potential's wall holds the promise at every step, without a re-solve (unless
    # ``resolved``: a loop tighter than the flexure bound, docs/contact.md, The wall)
    from rodsnes.io import results as output
    assert s["contact"]["contact_wall"] and (resolved or s["contact"]["penalty_raises"] == 0)
    for i in output.read_steps(run.outdir):
        pen = output.read_step(run.outdir, i)["attrs"]["contact_max_penetration"]
        assert pen <= s["contact"]["penetration_promised"]
    return s


@pytest.mark.slow(seconds=130)
def test_pyelastica_scene_as_posed_ends_on_a_plectoneme():
    """PyElastica's plectoneme scene as it poses it: no end tension, no imperfection.  The
    twisted straight rod stays an equilibrium (a saddle past Greenhill's 1.07 turns): the
    minimiser leaves it along negative curvature and ends on a stable plectoneme with the
    imposed link: the whole 10 turns, 40 elements, 40 nominal load steps (docs/plectoneme.md;
    75-130 s: with no imperfection round-off picks the path)."""
    s = _check_plectoneme(_plectoneme(10.0, rod_nelem=40, load_steps=40), 10.0, resolved=True)
    assert 3.6 < s["topology"]["writhe"] < 3.9


@pytest.mark.slow
@pytest.mark.parametrize("kw,turns", [
    (dict(rod_radius=0.02, load_end_force="5,0,0", rod_nelem=40, rod_imperfection=1e-3), 3.5),
    (dict(load_end_force="1,0,0", rod_nelem=36, rod_imperfection=1e-3), 2.5),
    (dict(rod_radius=0.03, load_end_force="2,0,0", rod_nelem=32), 4.0),
])
def test_plectonemes_no_case_file_shows(kw, turns):
    """Three plectonemes of other radius, tension, turns and mesh than cases/plectoneme.opts,
    from the straight rod in one command: stable at every step, link = turns, writhed,
    penetration within the promise."""
    _check_plectoneme(_plectoneme(turns, **kw), turns)


def test_minimize_refused_for_follower_loads():
    from rodsnes.errors import SceneError
    with pytest.raises(SceneError, match="-load_path"):
        build_run("mattiasson", load_end_force_follower=True, load_path="minimize")
    assert build_run("mattiasson", load_end_force_follower=True).path == "newton"


def test_restart_takes_the_steps_the_run_would_have_taken(tmp_path):
    """A minimise run interrupted after two steps and resumed with -restart: the same next
    increment (next_increment in result.h5), the same secant predictor, hence the same load
    steps and the same final state as the uninterrupted run."""
    import shutil

    import h5py

    from conftest import gathered_positions
    full = run_case("euler", outdir=str(tmp_path / "full"))
    assert full.ok and len(full.history) > 3
    cut = tmp_path / "cut"
    shutil.copytree(tmp_path / "full", cut)
    with h5py.File(cut / "result.h5", "r+") as f:
        f.attrs["last_step"] = 2
    resumed = run_case("euler", outdir=str(cut), restart=str(cut))
    assert resumed.ok and resumed.path == "minimize"
    assert [h["load"] for h in resumed.history] == [h["load"] for h in full.history[2:]]
    assert np.abs(gathered_positions(resumed) - gathered_positions(full)).max() < 1e-9


@pytest.mark.mpi
@pytest.mark.parametrize("case, kw", [("mattiasson", dict(rod_nelem=9, rod_order=3)),
                                      ("mattiasson", dict(rod_nelem=7, rod_order=2)),
                                      ("rollup_contact", dict(rod_nelem=10, rod_order=4)),
                                      ("michell", dict(rod_nelem=6, rod_order=3))])
def test_lumped_weights_are_the_row_sums_of_the_mass_matrix(case, kw):
    """The minimiser's metric (mesh.lumped_weights): int N_i ds of every owned node, np.add.at's
    sums bit for bit, the rod's length in all; open rods and a ring (michell)."""
    from rodsnes.model import fe
    from rodsnes.model.mesh import lumped_weights
    p = build_run(case, **kw).problem
    m, lay = p.mesh, p.layout
    M = lumped_weights(m, lay)
    xi, w = fe.gauss_legendre(m.order + 1)
    we = (w * m.h / 2.0) @ fe.lagrange(m.order, xi)[0]
    ref = np.zeros(m.n_nodes)
    np.add.at(ref, m.conn, np.broadcast_to(we, m.conn.shape))
    assert np.array_equal(M, ref[lay.owned_nodes])
    total = PETSc.COMM_WORLD.tompi4py().allreduce(M.sum())
    assert abs(total - m.length) <= 1e-12 * m.length
    assert (M > 0).all()


def test_a_long_load_step_says_how_it_goes(capsys, monkeypatch):
    """A load step's minimisation prints a progress line every HEARTBEAT seconds (not with
    -quiet): a step that crawled for minutes said nothing.  Here every iteration is past it."""
    from rodsnes.solve import minimize
    monkeypatch.setattr(minimize, "HEARTBEAT", 0.0)
    run = run_case("mattiasson", rod_nelem=8, load_steps=1, quiet=False,
                   rod_error_estimate="off")
    lines = [ln for ln in capsys.readouterr().out.splitlines()
             if ln.startswith("  load 1.000000: ")]
    assert run.ok and len(lines) == run.solver.total_its + 1, lines
    assert lines[0].startswith("  load 1.000000: 0 iterations in 0 s, |g| ")
    assert ", E " in lines[-1]
    run = run_case("mattiasson", rod_nelem=8, load_steps=1, rod_error_estimate="off")
    assert "iterations in" not in capsys.readouterr().out
