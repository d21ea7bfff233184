"""Equilibria against exact solutions (shared/REFERENCES.md), Newton's quadratic convergence,
and one versus two ranks."""
import numpy as np
import pytest
from petsc4py import PETSc
from scipy.optimize import brentq
from scipy.special import ellipk

from conftest import gathered_positions, run_case


def tip(run):
    return gathered_positions(run)[-1]


@pytest.mark.mpi
@pytest.mark.parametrize("f, exact", [(0.25, (0.636620, 0.636620)), (0.5, (0.0, 0.636620)),
                                      (0.75, (-0.212207, 0.212207)), (1.0, (0.0, 0.0))])
def test_rollup_tip_in_one_load_step(f, exact):
    """Simo & Vu-Quoc: M = f 2 pi EI/L rolls the rod into an arc of curvature M/EI."""
    run = run_case("rollup", load_end_moment=f"0,0,{f * 2 * np.pi * 100 / 10!r}")
    assert run.ok and run.problem.lam == 1.0 and len(run.history) == 1
    x = tip(run) / 10.0
    assert np.hypot(x[0] - exact[0], x[1] - exact[1]) < 2e-6     # table has 6 digits
    assert abs(x[2]) < 1e-12
    k = f * 2 * np.pi / 10
    # the whole centreline lies on the exact circle x = sin(ks)/k, y = (1 - cos ks)/k
    X = gathered_positions(run)
    s = run.mesh.s_nodes
    ex = np.stack([np.sin(k * s) / k, (1 - np.cos(k * s)) / k], 1)
    assert np.abs(X[:, :2] - ex).max() < 2e-5 * 10        # 8 cubic elements per circle


def test_rollup_two_turns_in_one_step_converges_quadratically():
    run = run_case("rollup_two_turns")
    assert run.ok and len(run.history) == 1
    assert np.linalg.norm(tip(run)) < 1e-6            # tip back at the clamp after 2 turns
    h = np.array(run.solver.last_history)
    assert len(h) <= 8
    # quadratic convergence: once in the basin, each residual is below C |F_prev|^2
    rel = h / h[0]
    tail = [(rel[i], rel[i + 1]) for i in range(len(rel) - 1) if rel[i] < 1e-2 and rel[i + 1] > 1e-13]
    assert tail, rel
    for a, b in tail:
        assert b < 50 * a**2, rel


@pytest.mark.parametrize("lam, ref", [(1, (0.056433, 0.301721, 0.461352)),
                                      (2, (0.160642, 0.493457, 0.781750)),
                                      (5, (0.387628, 0.713792, 1.215368)),
                                      (10, (0.554996, 0.810609, 1.430286))])
def test_mattiasson_cantilever(lam, ref):
    run = run_case("mattiasson", load_end_force=f"0,{-lam},0", rod_EA=1e7, rod_GA=1e7,
                   rod_nelem=16, load_steps=max(1, lam // 2))
    assert run.ok
    x = tip(run)
    u, v = 1.0 - x[0], -x[1]
    R = run.last_fields["directors"]
    d3_tip = run.layout.allgather_nodes(R)[-1][:, 2]
    alpha = -np.arctan2(d3_tip[1], d3_tip[0])
    # 6-digit reference values; extensibility P/EA <= 1e-6
    assert abs(u - ref[0]) < 3e-6 and abs(v - ref[1]) < 3e-6 and abs(alpha - ref[2]) < 3e-6


def test_euler_column_buckles_at_the_critical_load_onto_the_elastica():
    """Clamped-free column, P = 1.2 P_cr: tip rotation alpha from 1.2 = (2K(k)/pi)^2, k = sin(alpha/2)
    and tip deflection delta/L = 2k/K(k); below P_cr the column stays nearly straight."""
    run = run_case("euler")
    assert run.ok
    k = np.sqrt(brentq(lambda m: (2 * ellipk(m) / np.pi) ** 2 - 1.2, 1e-9, 0.99))
    x = tip(run)
    assert abs(abs(x[1]) - 2 * k / ellipk(k * k)) < 2e-3       # imperfection 1e-3 L
    below = run_case("euler", load_end_force=f"{-0.8 * np.pi**2 / 4!r},0,0")
    assert below.ok and abs(tip(below)[1]) < 5 * 1e-3
    assert abs(tip(below)[1]) > 1e-3                          # amplified imperfection


def test_force_free_helix_stays_put():
    """The helix with C g = B t under the axial moment B w is an equilibrium: the discrete
    solution moves only by the discretisation error, which falls at least as h^3."""
    errs = []
    for ne in (12, 24, 48):
        run = run_case("helix", rod_nelem=ne)
        assert run.ok
        errs.append(np.abs(gathered_positions(run) - run.mesh.x_init).max())
    assert errs[-1] < 1e-6 * 2.0
    assert errs[0] / errs[1] > 7 and errs[1] / errs[2] > 7, errs


def rigid_fit(X, Y):
    """The rigid motion (R, t) that brings the points X (n, 3) closest to Y (least squares,
    Kabsch), and the largest distance left: max |R X_i + t - Y_i|."""
    cx, cy = X.mean(axis=0), Y.mean(axis=0)
    U, _, Vt = np.linalg.svd((X - cx).T @ (Y - cy))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = (U @ D @ Vt).T
    t = cy - R @ cx
    return R, t, float(np.abs(X @ R.T + t - Y).max())


def test_rigid_fit_finds_a_rigid_motion_and_not_a_deformation():
    rng = np.random.default_rng(4)
    X = rng.normal(size=(12, 3))
    th = 0.3
    R0 = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    R, t, left = rigid_fit(X, X @ R0.T + [1.0, -2.0, 0.5])
    assert left < 1e-13 and np.allclose(R, R0) and np.allclose(t, [1.0, -2.0, 0.5])
    Y = X.copy()
    Y[3] += [1e-6, 0, 0]                      # one point moved: not rigid
    assert rigid_fit(X, Y)[2] > 5e-7


@pytest.mark.mpi
def test_two_ranks_match_one_rank_open_and_closed():
    """The same scene on COMM_WORLD and on COMM_SELF (under mpirun -n 2: 2 ranks vs 1).  The
    clamped cantilever to 1e-9 in the positions; the ring in its shape (the positions to 1e-9
    after the best rigid motion) and its energy: node 0 is held, but the isotropic ring turned
    rigidly about node 0's tangent, its sections spun back about their own, is a symmetry that
    only the imperfection breaks (lowest Hessian eigenvalue 3.3e-10), so each rank count's
    round-off turns it its own way (measured on 3 ranks: by 5e-8, 1.6e-8 in the positions,
    6e-12 left after the fit)."""
    for case, extra in (("mattiasson", dict(load_end_force="0,-5,0", rod_nelem=9, load_steps=2)),
                        ("michell", dict(load_twist_turns=1.2, load_steps=3, rod_nelem=11))):
        par = run_case(case, **extra)
        Xp = gathered_positions(par)
        ser = run_case(case, comm=PETSc.COMM_SELF,
                       outdir=par.outdir + f"_serial{PETSc.COMM_WORLD.getRank()}", **extra)
        Xs = gathered_positions(ser)
        assert par.ok and ser.ok
        if case == "mattiasson":
            assert np.abs(Xp - Xs).max() < 1e-9
        else:
            assert rigid_fit(Xp, Xs)[2] < 1e-9
            assert np.abs(Xp[0] - Xs[0]).max() < 1e-12      # node 0 is held
            assert par.last_energy == pytest.approx(ser.last_energy, rel=1e-10)
        # the same iterations, but for the last one of a load step: at the residual's round-off
        # floor (|g| ~ 1e-12 here) neither the energy (its change below its round-off) nor |g|
        # can decide alike on 1 and 2 ranks whether one more iteration is taken (measured once:
        # at |g| 7.9e-13 the full step's energy change was below the energy's round-off, one
        # rank took it on the watchdog's credit and came back to the point before, the other
        # accepted it).  The ring's last step takes 10 on 1, 2 and 3 ranks (29, 30 and 13 while
        # the valley follower walked its symmetry on round-off descents: valley.py)
        its_p = [h["newton_iterations"] for h in par.history]
        its_s = [h["newton_iterations"] for h in ser.history]
        assert len(its_p) == len(its_s)
        assert all(abs(a - b) <= 1 for a, b in zip(its_p, its_s)), (its_p, its_s)


@pytest.mark.mpi
def test_michell_twisted_ring_loses_stability_at_sqrt3_B_over_C():
    """A ring of a naturally straight isotropic rod (nu = 0: B/C = 1) with excess twist T turns
    is a stable circle for T < sqrt(3) = 1.7321 and an unstable one beyond (negative
    eigenvalues of the energy Hessian: the writhing modes)."""
    from rodsnes.solve.stability import negative_eigenvalues
    counts = {}
    for T in (1.5, 1.70, 1.76, 2.5):
        run = run_case("michell", load_twist_turns=T, load_steps=4, rod_nelem=16, load_path="newton",
                       rod_imperfection=0 if T != 1.5 else 1e-4)   # perfect ring: sharp threshold
        assert run.ok
        counts[T] = negative_eigenvalues(run.problem)
        if T == 1.5:
            X = gathered_positions(run)
            assert np.abs(X[:, 2]).max() < 30 * 1e-4      # circular up to the amplified imperfection
    assert counts[1.5] == 0 and counts[1.70] == 0
    assert counts[1.76] >= 1 and counts[2.5] >= 1, counts


def test_loading_then_unloading_returns_to_the_start():
    """Path independence: load the cantilever to lambda = 10, unload to 0: back to the initial
    configuration (positions and rotations) within solver tolerance."""
    run = run_case("mattiasson", load_steps=5)
    assert run.ok
    for lam in (0.75, 0.5, 0.25, 0.0):
        assert run.solver.solve_at(lam).converged
    fields = run.problem.owned_fields()
    X = run.layout.allgather_nodes(fields["positions"])
    R = run.layout.allgather_nodes(fields["directors"])
    from rodsnes.model import so3
    R0 = so3.rot(run.mesh.q_init)
    assert np.abs(X - run.mesh.x_init).max() < 1e-9
    assert np.abs(R - R0).max() < 1e-9


@pytest.mark.mpi
def test_iterative_solver_setup_reaches_the_same_equilibrium():
    from conftest import ROOT, read_opts_file
    it_opts = {k: v for k, v in read_opts_file(ROOT + "/options/iterative.opts")}
    lu = run_case("mattiasson", load_steps=5)
    it = run_case("mattiasson", load_steps=5, **it_opts)
    assert lu.ok and it.ok
    assert np.abs(gathered_positions(lu) - gathered_positions(it)).max() < 1e-8


@pytest.mark.mpi
@pytest.mark.parametrize("order, nelem", [(3, 8), (1, 16)])
def test_force_resultants_are_the_loads_beyond_the_cut(order, nelem):
    """result.h5's force_n from equilibrium (RodProblem.force_resultants): Mattiasson's
    cantilever under its tip load (0, -10, 0) carries exactly that force everywhere, to the
    residual's tolerance (from the strains, times EA = 1e6, it read 2015 at the root on 8
    cubic elements and -128655 on 16 linear ones); under its own weight w the force at s is
    w (L - s), to O(h) of the load on an element (0.8 % on 8 cubic elements; at the rod's ends
    on linear elements half an element's load).  On 1 and 2 ranks."""
    run = run_case("mattiasson", rod_order=order, rod_nelem=nelem, rod_error_estimate="off")
    n = run.layout.allgather_nodes(run.last_fields["force_n"])
    assert run.ok and np.abs(n - [0.0, -10.0, 0.0]).max() < 1e-6, n
    run = run_case("mattiasson", rod_order=order, rod_nelem=nelem, rod_error_estimate="off",
                   load_end_force="0,0,0", load_gravity="0,-10,0")
    n = run.layout.allgather_nodes(run.last_fields["force_n"])
    s = np.linspace(0.0, 1.0, len(n))
    exact = np.stack([0 * s, -10.0 * (1.0 - s), 0 * s], axis=1)
    err = np.abs(n - exact).max(axis=1)
    assert run.ok and err[1:-1].max() < 0.01 * 10.0, err
    # the rod's end nodes: a linear element's one cut gives n half an element away
    assert err[[0, -1]].max() < (0.5 * 10.0 / nelem + 1e-6 if order == 1 else 0.01 * 10.0), err
