"""The clamps' mounts as obstacles (rodsnes/contact/mounts.py, -contact_supports): the half-line
distance and penalty derivatives, the assembled tangent against finite differences of the
assembled residual with the rod pressing on both mounts, one rank against two, no cost where
the rod stays clear, and the option refused with other supports.  (The relaxation at 9.415
turns that went round the start clamp is a 45-minute batch run.)"""
import os

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc
from scipy.interpolate import CubicSpline

from conftest import build_run, natural_residuals, place, tangent_against_finite_differences
from rodsnes.contact import mounts as support
from rodsnes.errors import SceneError

SETUP = dict(rod_nelem=16, load_steps=1, rod_imperfection=0, contact_model="projection")

# waypoints of a centreline that leaves the start clamp along +x, passes behind it across the
# start's mount (x < 0 near the axis), then beyond the sliding end across its mount (x > x_N),
# before it arrives at x_N = 0.4 along +x (the end's cap, x_N itself, cannot be touched without
# the tube pressing into its own last stretch: the kernel's test covers it)
WAYPOINTS = np.array([[0.0, 0.0, 0.0], [0.12, 0.0, 0.0], [0.2, 0.15, 0.0], [0.0, 0.22, 0.01],
                      [-0.15, 0.012, 0.008], [0.0, -0.2, 0.0], [0.4, -0.22, 0.0],
                      [0.58, 0.01, -0.012], [0.5, 0.25, 0.0], [0.3, 0.3, -0.15],
                      [0.2, 0.0, -0.12], [0.3, 0.0, 0.0], [0.4, 0.0, 0.0]])


def pressed(comm=None, outdir=None, **kw):
    """The plectoneme scene, unloaded, put on the WAYPOINTS curve: the tube presses into both
    mounts, and nowhere into itself."""
    run = build_run("plectoneme", comm=comm, outdir=outdir, **{**SETUP, **kw})
    chord = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(WAYPOINTS, axis=0), axis=1))]
    curve = CubicSpline(chord / chord[-1], WAYPOINTS, bc_type=((1, [1.0, 0, 0]), (1, [1.0, 0, 0])))
    u = run.mesh.s_nodes / run.mesh.length
    t = curve(u, 1)
    place(run, curve(u), t / np.linalg.norm(t, axis=1)[:, None])
    return run


def test_half_line_distance_and_its_derivatives():
    rng = np.random.default_rng(0)
    p, e = np.array([0.3, -0.1, 0.2]), np.array([0.0, 0.6, 0.8])
    x = p + rng.normal(scale=0.05, size=(40, 3))
    dist, n, A = support.half_line_distance(x, p, e)
    # the closest point by brute force over the half-line
    t = np.linspace(0.0, 1.0, 200001)
    brute = np.array([np.linalg.norm(xi - p - t[:, None] * e, axis=1).min() for xi in x])
    assert np.abs(dist - brute).max() < 1e-9
    body = (x - p) @ e > 0
    assert body.any() and (~body).any()           # both the body and the end point are met
    eps, mu = 0.03, 7.0
    w = rng.uniform(0.5, 1.5, size=len(x))
    E, g, grad, H = support.penalty(x, w, p, e, eps, mu)
    assert (g > 0).any() and (g < 0).any()
    h = 1e-6
    for i in np.flatnonzero(g > 1e-4)[:6]:
        for k in range(3):
            dx = np.zeros_like(x)
            dx[i, k] = h
            Ep = support.penalty(x + dx, w, p, e, eps, mu)
            Em = support.penalty(x - dx, w, p, e, eps, mu)
            assert (Ep[0] - Em[0]) / (2 * h) == pytest.approx(grad[i, k], rel=1e-6, abs=1e-9)
            assert (Ep[2][i] - Em[2][i]) / (2 * h) == pytest.approx(H[i][:, k], rel=1e-5, abs=1e-7)
    # translating the half-line's end point is minus translating the points (d/dp = -d/dx)
    dp = np.array([1e-6, 0.0, 0.0])
    Ep, Em = support.penalty(x, w, p + dp, e, eps, mu)[0], support.penalty(x, w, p - dp, e, eps, mu)[0]
    assert (Ep - Em) / 2e-6 == pytest.approx(-grad[:, 0].sum(), rel=1e-6)


@pytest.mark.mpi
def test_assembled_tangent_matches_finite_differences_on_the_mounts():
    run = pressed()
    p = run.problem
    X = p.state.X
    F = X.duplicate()
    p.residual(None, X, F)
    c = run.contact.summary()
    assert c["support_points"] > 0 and c["support_force"] > 0 and c["support_min_gap"] < 0
    out = run.contact.last["support"]
    assert c["active_points"] == 0           # the tube does not touch itself
    # each mount is pressed (on some rank)
    loc = np.array([float(out["gap"][0].max(initial=-1)), float(out["gap"][1].max(initial=-1))])
    tot = np.empty_like(loc)
    run.contact.comm.Allreduce(loc, tot, op=MPI.MAX)
    assert tot[0] > 0 and tot[1] > 0
    J = p.layout.create_matrix(run.contact.extra_pattern(p.state.local_config()[0]))
    p.jacobian(None, X, J, J)
    assert J.getInfo(PETSc.Mat.InfoType.GLOBAL_SUM)["mallocs"] == 0
    fd, Jv, v = tangent_against_finite_differences(p, J, seed=5)
    assert (fd - Jv).norm() / Jv.norm() < 1e-6
    # the same with the mounts' part alone: without it the error is that part
    off = pressed(contact_supports="false")
    Joff = off.problem.layout.create_matrix(off.contact.extra_pattern(
        off.problem.state.local_config()[0]))
    off.problem.jacobian(None, off.problem.state.X, Joff, Joff)
    Jv2 = X.duplicate()
    Joff.mult(v, Jv2)
    assert (fd - Jv2).norm() / Jv.norm() > 1e-3


@pytest.mark.mpi
def test_two_ranks_give_the_serial_mount_forces():
    par = pressed()
    ser = pressed(comm=PETSc.COMM_SELF, outdir=par.outdir + f"_s{PETSc.COMM_WORLD.getRank()}")
    nat1, nat2 = natural_residuals(par, ser)
    assert np.abs(nat1 - nat2).max() < 1e-9 * np.abs(nat2).max()
    assert par.problem.energy() == pytest.approx(ser.problem.energy(), rel=1e-12)
    c1, c2 = par.contact.summary(), ser.contact.summary()
    assert c1["support_force"] == pytest.approx(c2["support_force"], rel=1e-12)
    assert c1["support_points"] == c2["support_points"] > 0


def test_the_mounts_cost_energy_only_where_the_tube_presses_into_them():
    on, off = pressed(), pressed(contact_supports="false")
    assert on.problem.energy() > off.problem.energy()
    # the straight rod between its clamps does not touch them
    straight_on = build_run("plectoneme", **SETUP)
    straight_off = build_run("plectoneme", contact_supports="false", **SETUP)
    assert straight_on.problem.energy() == straight_off.problem.energy()
    assert straight_on.contact.supports is not None and straight_off.contact.supports is None


def test_mounts_asked_for_with_other_supports_are_refused():
    with pytest.raises(SceneError, match="-contact_supports"):
        build_run("plectoneme", bc_end="clamped", load_end_force="0,0,0", contact_supports=True,
                  **SETUP)
    # not asked for: silently off where they do not apply
    run = build_run("plectoneme", bc_end="clamped", load_end_force="0,0,0", **SETUP)
    assert run.contact.supports is None


def test_the_mounts_take_the_contact_wall():
    """With the pair potential's wall (a_b, a_w) the mounts' law is psi(g) = g^2/2 + beta(g),
    the couples' barrier in the same depths: 0 below a_b (the plain penalty there, bit for
    bit), energy, gradient and Hessian against central differences inside the barrier, the
    energy infinite from a_w on (a trial the line search refuses), without a warning."""
    import warnings
    rng = np.random.default_rng(1)
    p, e = np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    eps, mu, wall = 0.03, 7.0, (0.004, 0.005)
    # points above the half-line's body at depths g = eps - dist across the barrier
    g = np.array([0.001, 0.0035, 0.0042, 0.0046, 0.0049])
    ang = rng.uniform(0.0, 2.0 * np.pi, size=len(g))
    x = np.stack([rng.uniform(0.1, 0.9, size=len(g)), (eps - g) * np.cos(ang),
                  (eps - g) * np.sin(ang)], axis=1)
    w = rng.uniform(0.5, 1.5, size=len(g))
    E0, g0, grad0, H0 = support.penalty(x[:2], w[:2], p, e, eps, mu)
    E1, g1, grad1, H1 = support.penalty(x[:2], w[:2], p, e, eps, mu, wall=wall)
    assert E1 == E0 and np.array_equal(grad1, grad0) and np.array_equal(H1, H0)
    E, gg, grad, H = support.penalty(x, w, p, e, eps, mu, wall=wall)
    assert np.allclose(gg, g, atol=1e-12)
    assert E > E0 + 0.5 * mu * np.sum(w[2:] * g[2:] ** 2)      # the barrier's energy on top
    h = 1e-8
    for i in range(2, len(g)):
        for k in range(3):
            dx = np.zeros_like(x)
            dx[i, k] = h
            Ep = support.penalty(x + dx, w, p, e, eps, mu, wall=wall)
            Em = support.penalty(x - dx, w, p, e, eps, mu, wall=wall)
            assert (Ep[0] - Em[0]) / (2 * h) == pytest.approx(grad[i, k], rel=1e-5, abs=1e-9)
            assert (Ep[2][i] - Em[2][i]) / (2 * h) == pytest.approx(H[i][:, k], rel=1e-4,
                                                                  abs=1e-6 * np.abs(H[i]).max())
    # stiffer toward the wall, infinite at and beyond it
    assert np.all(np.diff([H[i][1:, 1:].trace() / w[i] for i in range(2, len(g))]) > 0)
    beyond = x.copy()
    beyond[-1, 1:] *= (eps - 0.0051) / (eps - g[-1])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Eb, _, gradb, _ = support.penalty(beyond, w, p, e, eps, mu, wall=wall)
    assert Eb == np.inf and not np.all(np.isfinite(gradb))


@pytest.mark.slow
def test_a_plectoneme_pressed_into_a_mount_at_the_wall_goes_on(monkeypatch):
    """The plectoneme with a 5 % standoff at 8.47 turns (tests/data/plectoneme_8.47_standoff,
    from a run of the case with -contact_standoff 0.05): on the next load step the ply
    rearranges and presses the rod into the sliding end's mount.  The line searches cap every
    trial's deepest penetration, a mount's included, short of the wall a_w; while the mounts'
    law had no barrier, the iterates pressed the mount up to that cap, and every step that
    pressed it further was cut to nothing (steps of 1e-5 accepted at E - E0 = -2e-5, 200
    iterations a try, every cut-back down to 1.5e-6 of the load failed: the run stopped at
    8.47 turns).  With the wall in the mounts' law the step converges, stable, its iterates
    pressing the mount into the barrier but never to the wall."""
    data = os.path.join(os.path.dirname(__file__), "data", "plectoneme_8.47_standoff")
    run = build_run("plectoneme", restart=data, contact_standoff=0.05, load_stop=0.847,
                    rod_error_estimate="off")
    ct = run.contact
    assert ct.wall is not None and ct.supports.wall == ct.wall
    deepest = []
    evaluate = ct.supports.evaluate

    def spy(r_loc, tangent=True):
        out = evaluate(r_loc, tangent)
        if np.isfinite(out["energy"]):
            deepest.append(ct.supports.deepest_local(out))
        return out
    monkeypatch.setattr(ct.supports, "evaluate", spy)
    ok = run.execute()
    s = run.summary(converged=ok)
    assert ok and s["stable"] is True and run.problem.lam == pytest.approx(0.847, abs=1e-12)
    assert ct.wall[0] < max(deepest) < ct.wall[1]


@pytest.mark.mpi
def test_the_assembled_tangent_in_the_mounts_barrier_matches_finite_differences():
    """The pair potential's wall in the mounts' law (psi = g^2/2 + beta): with the reach moved
    so that the deepest mount point lies halfway into the barrier (a_b < g < a_w), the
    assembled tangent against central differences of the assembled residual, serial and on
    2 ranks (the barrier's second derivative and the sliding end's coupling)."""
    run = pressed(contact_model="potential")
    ct, p = run.contact, run.problem
    sup = ct.supports
    a_b, a_w = ct.wall
    r_loc = p.state.local_config()[0]
    out = sup.evaluate(r_loc, tangent=False)
    deep = MPI.COMM_WORLD.allreduce(max(float(g.max(initial=-np.inf)) for g in out["gap"]),
                                    op=MPI.MAX)
    sup.reach += a_b + 0.5 * (a_w - a_b) - deep
    ct.kept_evaluation = None
    out = sup.evaluate(r_loc, tangent=False)
    gs = np.concatenate([g[np.isfinite(g)].ravel() for g in out["gap"]])
    inside = MPI.COMM_WORLD.allreduce(int(((gs > a_b) & (gs < a_w)).sum()))
    assert inside > 0
    X = p.state.X
    F = X.duplicate()
    p.residual(None, X, F)
    assert np.isfinite(F.norm()) and np.isfinite(p.energy())
    J = p.layout.create_matrix(ct.extra_pattern(r_loc))
    p.jacobian(None, X, J, J)
    fd, Jv, _ = tangent_against_finite_differences(p, J, seed=5, h=1e-8)
    assert (fd - Jv).norm() / Jv.norm() < 1e-7
