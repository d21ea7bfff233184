"""The Newton path's retraction (rodsnes/model/retraction.py): the turn excess of a chord is
Rodrigues' exp(t) c - c - t x c (compiled and numpy alike); a rigid turn of the rod about its
clamp, or of a ring about its held node, is taken exactly; the correction is second order in
the step; held position components do not move; 1 rank = 2 ranks; and the Newton path no
longer spends every other iteration undoing a stretch (Mattiasson's nearly inextensible
cantilever: fewer iterations, the same equilibrium)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import build_run, run_case
from rodsnes.model import retraction, so3_compiled
from rodsnes.model.partition import NDOF


def test_turn_excess_is_rodrigues_minus_the_linear_turn():
    rng = np.random.default_rng(4)
    for scale in (1e-7, 3e-3, 0.02, 0.7, 2.5):
        t = scale * rng.standard_normal((50, 3))
        c = rng.standard_normal((50, 3))
        exact = Rotation.from_rotvec(t).apply(c) - c - np.cross(t, c)
        got = retraction.turn_excess(t, c)
        assert np.abs(got - exact).max() <= 1e-14 * max(1.0, scale ** 2) * 10, scale


def test_the_compiled_chord_turns_equal_numpys():
    assert so3_compiled.available(), "rodsnes.model._rotation_kernel is not built: make install"
    rng = np.random.default_rng(5)
    for p in (1, 2, 3, 4):
        ne = 7
        n = ne * p + 1
        conn = np.arange(ne)[:, None] * p + np.arange(p + 1)[None, :]
        dofs = rng.standard_normal((n, NDOF))              # read in place, stride 6
        for alpha in (1e-6, 0.01, 0.4, 1.7):
            a = retraction.chord_turns(conn, dofs[:, 0:3], dofs[:, 3:6], alpha, compiled=True)
            b = retraction.chord_turns(conn, dofs[:, 0:3], dofs[:, 3:6], alpha, compiled=False)
            assert a.shape == (ne, p + 1, 3) and np.all(a[:, 0] == 0.0)
            assert np.abs(a - b).max() <= 1e-13 * max(np.abs(b).max(), 1e-300), (p, alpha)


def _rigid_step(run, theta, centre):
    """The direction of a rigid turn theta about ``centre``: d_r = theta x (r - centre) at the
    owned nodes, d_theta = theta; and the exact turned positions."""
    p = run.problem
    d = p.state.X.duplicate()
    with p.state.X as xa, d as da:
        x = xa.reshape(-1, NDOF)[:, 0:3].copy()
        da = da.reshape(-1, NDOF)
        da[:, 0:3] = np.cross(theta, x - centre)
        da[:, 3:6] = theta
    exact = Rotation.from_rotvec(theta).apply(x - centre) + centre
    return d, x, exact


@pytest.mark.mpi
def test_a_rigid_turn_about_the_clamp_is_taken_exactly():
    """The straight cantilever turned by 0.9 rad about its clamp: x + d stretches it (its tip
    0.9^2 / 2 of the length off), the retracted step lands on the turned rod to round-off."""
    run = build_run("mattiasson", rod_nelem=5, rod_order=3, load_path="newton")
    p = run.problem
    R = retraction.Retraction(p)
    theta = np.array([0.2, -0.3, 0.82])
    d, x, exact = _rigid_step(run, theta, np.zeros(3))
    corr = R.correction(p.state.X, 1.0, d)
    dr = d.getArray(readonly=True).reshape(-1, NDOF)[:, 0:3]
    assert np.abs(x + dr + corr - exact).max() < 1e-13
    straight = float(np.abs(x + dr - exact).max()) if len(x) else 0.0
    assert p.layout.comm.tompi4py().allreduce(straight, op=max) > 0.3   # the straight step is not
    R.destroy()


@pytest.mark.mpi
def test_a_ring_turned_about_its_held_node_stays_a_ring():
    """Michell's ring (node 0 held) turned rigidly by 0.6 rad about node 0: exact."""
    run = build_run("michell", rod_nelem=12, load_path="newton")
    p = run.problem
    R = retraction.Retraction(p)
    x0 = run.mesh.x_init[0]
    d, x, exact = _rigid_step(run, np.array([0.1, 0.5, -0.3]), x0)
    corr = R.correction(p.state.X, 1.0, d)
    dr = d.getArray(readonly=True).reshape(-1, NDOF)[:, 0:3]
    assert np.abs(x + dr + corr - exact).max() < 1e-13
    R.destroy()


@pytest.mark.mpi
def test_the_correction_is_second_order_and_leaves_held_components():
    """A random step on the plectoneme's rod (clamped start, sliding end held in two
    components): the correction quarters when the step halves, and the held components'
    corrections are zero (the sliding end moves along its axis only)."""
    run = build_run("plectoneme", rod_nelem=10, contact=False)
    p = run.problem
    R = retraction.Retraction(p)
    d = p.state.X.duplicate()
    rng = np.random.default_rng(int(p.layout.comm.getRank()) + 11)
    with d as a:
        a[:] = 0.05 * rng.standard_normal(a.shape)
    c1 = R.correction(p.state.X, 1.0, d)
    c2 = R.correction(p.state.X, 0.5, d)
    comm = p.layout.comm.tompi4py()
    big = comm.allreduce(float(np.abs(c1).max()), op=max)
    assert big > 0.0
    assert comm.allreduce(float(np.abs(4 * c2 - c1).max()), op=max) < 0.05 * big
    rows = np.asarray(p.constraints.rows_local)
    rows = rows[rows % NDOF < 3]
    assert np.all(c1[rows // NDOF, rows % NDOF] == 0.0)
    R.destroy()


@pytest.mark.mpi
@pytest.mark.parametrize("case", ["euler", "michell"])
def test_one_rank_and_two_give_the_same_correction(case):
    """The correction gathered over the ranks equals the one computed on each rank alone
    (COMM_SELF, the whole rod) to round-off: the sums along the rod meet across the ranks (a
    pinned column; a ring, whose ranks may hold elements at both ends of its numbering)."""
    from petsc4py import PETSc
    runs = [build_run(case, rod_nelem=9, load_path="newton"),
            build_run(case, rod_nelem=9, load_path="newton", comm=PETSc.COMM_SELF)]
    out = []
    for run in runs:
        p = run.problem
        R = retraction.Retraction(p)
        d = p.state.X.duplicate()
        with d as a:
            a = a.reshape(-1, NDOF)
            s = run.mesh.s_nodes[run.layout.owned_nodes]
            a[:, 0:3] = np.stack([0.1 * s, np.sin(3 * s), s * s], 1)
            a[:, 3:6] = np.stack([np.cos(2 * s), 0.3 * s, 0.5 + 0 * s], 1)
        out.append(run.layout.allgather_nodes(R.correction(p.state.X, 0.8, d)))
        R.destroy()
    assert np.abs(out[0] - out[1]).max() < 1e-13 * np.abs(out[1]).max()


def test_newton_steps_along_the_retraction_do_not_stretch_the_cantilever():
    """Mattiasson's cantilever (EA = 1e6 EI / L^2) on the Newton path: the straight steps'
    residual jumps 10^5 x above its start at every other iteration (the stretch of a turn);
    along the retraction it stays within 10^3 x (58 x on 40 elements: the chords' turn is the
    mean of their nodes'), and fewer iterations reach the same equilibrium."""
    runs = {on: run_case("mattiasson", rod_nelem=40, load_steps=2, load_path="newton",
                         rod_error_estimate="off", load_retraction=str(on).lower())
            for on in (True, False)}
    assert all(r.ok for r in runs.values())
    hist = {on: np.array(runs[on].solver.results[0].history) for on in runs}
    assert hist[False].max() > 1e5 * hist[False][0]
    assert hist[True].max() < 1e3 * hist[True][0]
    its = {on: sum(h["newton_iterations"] for h in runs[on].history) for on in runs}
    assert its[True] < its[False]
    e = {on: runs[on].problem.energy() for on in runs}
    assert e[True] == pytest.approx(e[False], rel=1e-10)


@pytest.mark.parametrize("case", ["plectoneme", "michell"])
def test_the_compiled_corrections_equal_numpys(case):
    """The owned nodes' corrections by the C kernels (rodsnes_chord_turns,
    rodsnes_retract_nodes) equal the numpy path's, an open rod held at both ends (two
    components at the sliding one) and a ring, to round-off, held components exactly zero."""
    assert so3_compiled.available(), "rodsnes.model._rotation_kernel is not built: make install"
    run = build_run(case, rod_nelem=10, contact=False, load_path="newton")
    p = run.problem
    d = p.state.X.duplicate()
    with d as a:
        a[:] = 0.2 * np.random.default_rng(7).standard_normal(a.shape)
    fast, slow = (retraction.Retraction(p, compiled=c) for c in (True, False))
    cf, cs = fast.correction(p.state.X, 0.7, d), slow.correction(p.state.X, 0.7, d)
    assert np.abs(cf - cs).max() <= 1e-13 * np.abs(cs).max() and np.abs(cs).max() > 1e-3
    rows = np.asarray(p.constraints.rows_local)
    rows = rows[rows % NDOF < 3]
    assert np.all(cf[rows // NDOF, rows % NDOF] == 0.0)
    fast.destroy()
    slow.destroy()
