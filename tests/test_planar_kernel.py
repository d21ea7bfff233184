"""The compiled kernel's in-plane tangent (elastic_compiled.plane_tangents, the planar Newton
step's) equals the 3-D tangent cut to the in-plane unknowns at planar states, and the finite
differences of the residual's in-plane components: orders 1-4, full and reduced quadrature,
the three planes, the curvature bound active or not, quaternions of either sign."""
import numpy as np
import pytest

from rodsnes.model import elastic_compiled, so3
from rodsnes.model.plane import Plane
import test_elastic_compiled as compiled_test

TOL = 1e-12


def planar_elements(p, nq, ne, axis, rng, h=0.3, frame=None):
    """Consecutive elements of a rod in the plane normal to e_axis: positions in it, rotations
    exp(phi_a e_axis) R_ref (R_ref: d_2 = e_axis and d_3 along the first in-plane axis, or
    ``frame``), random quaternion signs; reference strains of any kind."""
    nn = p + 1
    s = (np.arange(ne)[:, None] * p + np.arange(nn)[None, :]) * (h / p)
    P, Q = [c for c in range(3) if c != axis]
    n = np.eye(3)[axis]
    phi = 1.3 * np.sin(s) + 0.9 * s + 0.15 * rng.normal(size=s.shape)
    if frame is None:
        frame = np.column_stack([np.cross(n, np.eye(3)[P]), n, np.eye(3)[P]])  # d1, d2, d3
    q_ref = so3.quat_from_rot(frame[None])[0]
    qz = so3.qexp(phi[..., None] * n)                                    # exp(phi n)
    qe = so3.qmul(qz, np.broadcast_to(q_ref, qz.shape))
    qe *= np.where(rng.random((ne, nn)) < 0.4, -1.0, 1.0)[..., None]
    xe = np.zeros((ne, nn, 3))
    xe[..., P] = np.cos(0.8 * s) * s + 0.02 * rng.normal(size=s.shape)
    xe[..., Q] = 0.4 * np.sin(1.1 * s) + 0.02 * rng.normal(size=s.shape)
    xe[..., axis] = 0.25
    e0 = rng.normal(size=(ne, nq, 6)) * 0.1 + [0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    return qe, xe, e0


def make_rod(p, nq, ne, axis, rng, bound, frame=None):
    return compiled_test.make_rod(
        p, nq, ne, rng, bound,
        elements=lambda p, nq, ne, rng: planar_elements(p, nq, ne, axis, rng, frame=frame))


def inplane(axis):
    """The in-plane unknowns of the plane normal to e_axis, as the planar step takes them."""
    return list(Plane(axis, 1).inplane)


@pytest.mark.parametrize("bound", [False, True], ids=["free", "curvature_bound"])
@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("p,nq", [(1, 1), (2, 2), (3, 3), (3, 4), (4, 4), (5, 4), (7, 6)])
def test_plane_tangent_equals_cut_3d_tangent(p, nq, axis, bound):
    """Orders 1-7 (the kernel's node counts unrolled, 2-5, and the general loop, 6 and 8)."""
    rng = np.random.default_rng(100 * p + 10 * nq + 3 * axis + bound)
    rod, qe, xe = make_rod(p, nq, 30, axis, rng, bound)
    got = elastic_compiled.plane_tangents(rod, qe, xe, axis)
    ref = np.abs(got).max()
    for symmetric in (False, True):
        cut = elastic_compiled.element_terms(rod, qe, xe, symmetric=symmetric,
                                             comps=inplane(axis))[2]
        err = np.abs(got - cut).max() / ref
        assert err < TOL, f"p={p} nq={nq} axis={axis} symmetric={symmetric}: {err:.2e}"
    if p > 4:
        return
    # and the numpy kernel's cut
    cut = rod.element_terms_numpy(qe, xe)[2]
    idx = (6 * np.arange(p + 1)[:, None] + np.array(inplane(axis))[None, :]).ravel()
    assert np.abs(got - cut[:, idx[:, None], idx[None, :]]).max() < TOL * ref


@pytest.mark.parametrize("bound", [False, True], ids=["free", "curvature_bound"])
def test_plane_tangent_any_frame(bound):
    """A reference frame with no director along the normal (the in-plane variations of a 3-D
    energy are what the kernel differentiates, whatever the frame), the curvature bound
    acting on the in-plane curvature's share of (u1, u2)."""
    rng = np.random.default_rng(7 + bound)
    frame = so3.rot(so3.qexp(np.array([[0.3, -0.7, 1.1]])))[0]
    for axis in (0, 2):
        rod, qe, xe = make_rod(3, 3, 20, axis, rng, bound, frame=frame)
        got = elastic_compiled.plane_tangents(rod, qe, xe, axis)
        cut = elastic_compiled.element_terms(rod, qe, xe, comps=inplane(axis))[2]
        assert np.abs(got - cut).max() < TOL * np.abs(got).max()


def test_plane_tangent_quaternions_of_any_norm():
    """The 3-D kernel's strains are Nz(p) / |p|^2 of p = sum N_a q_a, whatever the norms of
    the q_a; the plane kernel takes them alike (the element's q_0 normalised): nodal
    quaternions scaled by 0.5-2 give the cut 3-D tangent of the same scaled input."""
    rng = np.random.default_rng(17)
    for axis in (0, 1, 2):
        rod, qe, xe = make_rod(3, 3, 25, axis, rng, True)
        qe = qe * rng.uniform(0.5, 2.0, size=qe.shape[:2])[..., None]
        got = elastic_compiled.plane_tangents(rod, qe, xe, axis)
        cut = elastic_compiled.element_terms(rod, qe, xe, comps=inplane(axis))[2]
        assert np.abs(got - cut).max() < TOL * np.abs(got).max()


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_plane_tangent_finite_differences(axis):
    """Central differences of the in-plane residual (the compiled 3-D residual's r_P, r_Q and
    theta_axis components) along in-plane moves of every unknown of one element: positions
    shifted in the plane, rotations exp(h e_axis) R_a."""
    rng = np.random.default_rng(11 + axis)
    p = 3
    rod, qe, xe = make_rod(p, 3, 1, axis, rng, True)
    K = elastic_compiled.plane_tangents(rod, qe, xe, axis)[0]
    comps = inplane(axis)

    def residual(q, x):
        return elastic_compiled.element_terms(rod, q, x, tangent=False)[1][0][:, comps].ravel()

    h = 1e-6
    fd = np.empty_like(K)
    for a in range(p + 1):
        for i, c in enumerate(comps):
            out = []
            for sgn in (1.0, -1.0):
                q, x = qe.copy(), xe.copy()
                if c < 3:
                    x[0, a, c] += sgn * h
                else:
                    q[0, a] = so3.qmul(so3.qexp(sgn * h * np.eye(3)[axis]), q[0, a])
                out.append(residual(q, x))
            fd[:, 3 * a + i] = (out[0] - out[1]) / (2 * h)
    err = np.abs(fd - K).max() / np.abs(K).max()
    assert err < 1e-7, f"axis {axis}: finite differences {err:.2e}"


def test_plane_tangent_arguments():
    rng = np.random.default_rng(3)
    rod, qe, xe = make_rod(2, 2, 4, 2, rng, False)
    with pytest.raises(ValueError, match="axis"):
        elastic_compiled.plane_tangents(rod, qe, xe, 3)
    with pytest.raises(ValueError, match="out"):
        elastic_compiled.plane_tangents(rod, qe, xe, 2, out=np.empty((4, 6, 6)))


def test_planar_jacobian_through_the_plane_kernel(monkeypatch):
    """The planar Newton step's Jacobian (PlanarSystem.assemble_tangent) and the in-plane
    Hessian block (BlockInertia) are made by the plane kernel (ElasticRod.plane_tangents
    called for every element of theirs, and for no element of a view without a plane) and
    equal the 3-D tangents cut to the in-plane block (ComponentView without a plane) on a
    perturbed planar state of a run."""
    from petsc4py import PETSc
    from conftest import build_run
    from rodsnes.solve.planar import ComponentView, create_block_matrix
    run = build_run("mattiasson", rod_nelem=50)
    p = run.problem
    pl = p.planar
    p.set_load(0.6)
    X = p.state.X
    lo, hi = X.getOwnershipRange()
    d = np.random.default_rng(5).normal(size=(X.getSize() // 6, 3)) * 1e-2
    with X as a:
        a = a.reshape(-1, 6)
        free = ~p.constraints.block_mask[:, pl.plane.inplane]
        a[:, pl.plane.inplane] += np.where(free, d[lo // 6:hi // 6], 0.0)

    def dense(M):
        return M.convert(PETSc.Mat.Type.AIJ, PETSc.Mat()).getValuesCSR()[2]

    # the elements whose tangents the plane kernel made: through plane_tangents, or added into
    # the matrix as it made them (tangents_into with a plane: all but those it does not add,
    # which then come through plane_tangents)
    calls = []
    spied, spied_into = type(p.elastic).plane_tangents, type(p.elastic).tangents_into

    def spy(rod, *args, **kw):
        calls.append(len(args[0]))
        return spied(rod, *args, **kw)

    def spy_into(rod, q, r, conn, blocks, *args, **kw):
        done = spied_into(rod, q, r, conn, blocks, *args, **kw)
        if done and kw.get("plane") is not None:
            calls.append(len(conn) - len(blocks.rest))
        return done

    monkeypatch.setattr(type(p.elastic), "plane_tangents", spy)
    monkeypatch.setattr(type(p.elastic), "tangents_into", spy_into)
    cut = {}
    for symmetric in (False, True):
        mats = []
        for plane in (pl.plane, None):
            M = create_block_matrix(p, p.patterns, symmetric=symmetric)
            p.jacobian(None, X, M, M, symmetric=symmetric,
                       view=ComponentView(M, pl.plane.inplane, p.constraints, plane))
            mats.append(dense(M))
        assert np.abs(mats[0] - mats[1]).max() < 1e-12 * np.abs(mats[1]).max()
        cut[symmetric] = mats[1]
    ne = len(p.row_lconn)
    assert sum(calls) == 2 * ne               # the plane views' elements, not the others'
    pl.assemble_tangent(X)                    # the Newton step's, through the plane kernel
    assert sum(calls) == 3 * ne
    assert np.abs(dense(pl.J) - cut[False]).max() < 1e-12 * np.abs(cut[False]).max()
    pl.inertia.assemble()                     # the minimiser's in-plane Hessian
    assert sum(calls) == 4 * ne
    H = dense(pl.inertia.block.H)
    assert np.abs(H - cut[True]).max() < 1e-12 * np.abs(cut[True]).max()


@pytest.mark.parametrize("bound", [False, True], ids=["free", "curvature_bound"])
@pytest.mark.parametrize("p,nq,ne", [(1, 1, 6), (2, 2, 5), (3, 3, 30), (3, 3, 7), (4, 4, 6),
                                     (7, 6, 9), (3, 3, 1), (3, 3, 2), (3, 3, 3)])
def test_two_and_four_lanes_give_the_same_numbers(p, nq, ne, bound):
    """The kernel runs 2 elements at once (SSE2) or 4 (AVX2, where the processor has it): the
    same arithmetic lane by lane, so the same numbers bit for bit, for element counts that fill
    the last group or not; the widest the processor runs is the default."""
    rng = np.random.default_rng(7 * p + nq + ne + bound)
    rod, qe, xe = make_rod(p, nq, ne, 1, rng, bound)
    two = elastic_compiled.plane_tangents(rod, qe, xe, 1, lanes=2)
    assert np.array_equal(elastic_compiled.plane_tangents(rod, qe, xe, 1), two)
    try:
        four = elastic_compiled.plane_tangents(rod, qe, xe, 1, lanes=4)
    except ValueError:
        pytest.skip("no AVX2: two lanes only")
    assert np.array_equal(four, two)
    with pytest.raises(RuntimeError):
        elastic_compiled.plane_tangents(rod, qe, xe, 1, lanes=3)


def test_no_elements_no_tangents():
    """A rank without elements (a group of lanes never starts): an empty result, either width."""
    rng = np.random.default_rng(3)
    rod, qe, xe = make_rod(3, 3, 4, 1, rng, False)
    for lanes in (0, 2):
        out = elastic_compiled.plane_tangents(rod, qe[:0], xe[:0], 1, e0=rod.e0[:0], lanes=lanes)
        assert out.shape == (0, 12, 12)
