"""The Cosserat element: tangent = derivative of the residual, objectivity, path independence,
interpolation order, and the strain measures themselves."""
import numpy as np
import pytest

from rodsnes.model import elastic, fe, so3

RNG = np.random.default_rng(7)
STIFF = [3.0, 4.0, 50.0, 1.0, 2.0, 1.5]   # GA1, GA2, EA, EI1, EI2, GJ


def random_elements(p, ne=3, h=0.3, spread=0.6):
    qe = so3.qexp(RNG.normal(size=(ne, p + 1, 3)) * spread)
    xe = np.cumsum(RNG.normal(size=(ne, p + 1, 3)) * 0.1 + np.array([h / p, 0, 0]), axis=1)
    return qe, xe


def perturbed(qe, xe, dx, dth):
    return so3.qmul(so3.qexp(dth), qe), xe + dx


@pytest.mark.parametrize("p,bound", [(1, False), (2, False), (3, False), (4, False),
                                     (2, True), (3, True)])
def test_residual_is_gradient_and_tangent_is_derivative_of_residual(p, bound):
    """bound: the thickness bound on bending is active at about half of the points."""
    ne, nn, h = 2, p + 1, 0.3
    rod = elastic.ElasticRod(p, p + 1, h, STIFF)
    qe, xe = random_elements(p, ne, h)
    rod.set_reference(RNG.normal(size=(ne, p + 1, 6)) * 0.1 + [0, 0, 1, 0, 0, 0])
    if bound:
        kappa = np.linalg.norm(rod.strains(qe, xe)[..., 3:5], axis=-1)
        rod.set_curvature_limit(np.median(kappa), 30.0)
        assert 0.3 < np.mean(kappa > rod.kappa_max) < 0.7
        E_free = rod.energy(qe, xe)
        rod.kappa_max = None
        assert E_free > rod.energy(qe, xe) + 1e-3        # the bound costs energy where active
        rod.kappa_max = np.median(kappa)
    _, vec, H = rod.element_terms(qe, xe)
    eps = 1e-6
    g_fd = np.zeros_like(vec)
    H_fd = np.zeros_like(H)
    for a in range(nn):
        for i in range(6):
            d = np.zeros((ne, nn, 6))
            d[:, a, i] = eps
            plus = perturbed(qe, xe, d[..., :3], d[..., 3:])
            minus = perturbed(qe, xe, -d[..., :3], -d[..., 3:])
            Ep = np.array([rod.energy(plus[0][e:e + 1], plus[1][e:e + 1], rod.e0[e:e + 1]) for e in range(ne)])
            Em = np.array([rod.energy(minus[0][e:e + 1], minus[1][e:e + 1], rod.e0[e:e + 1]) for e in range(ne)])
            g_fd[:, a, i] = (Ep - Em) / (2 * eps)
            rp = rod.element_terms(*plus, tangent=False)[1]
            rm = rod.element_terms(*minus, tangent=False)[1]
            H_fd[:, :, a * 6 + i] = ((rp - rm) / (2 * eps)).reshape(ne, -1)
    assert np.abs(g_fd - vec).max() < 1e-7 * np.abs(vec).max()
    assert np.abs(H_fd - H).max() < 1e-7 * np.abs(H).max()
    # the symmetric variant is the chart Hessian: equal to the consistent one up to -1/2 g^x
    _, _, Hs = rod.element_terms(qe, xe, symmetric=True)
    assert np.allclose(Hs, Hs.transpose(0, 2, 1), atol=1e-10 * np.abs(Hs).max())
    assert np.abs(Hs - H).max() > 1e-6   # not at equilibrium: they must differ


def test_objectivity_rigid_rotation_leaves_strains_and_energy():
    p = 3
    rod = elastic.ElasticRod(p, p + 1, 0.3, STIFF)
    qe, xe = random_elements(p)
    rod.set_reference(np.tile([0, 0, 1.0, 0, 0, 0], (3, p + 1, 1)))
    Q = so3.qexp(np.array([2.1, -0.4, 1.3]))
    e1 = rod.strains(qe, xe)
    qe2 = so3.qmul(Q, qe)
    xe2 = xe @ so3.rot(Q).T + np.array([5.0, -2.0, 1.0])
    e2 = rod.strains(qe2, xe2)
    assert np.allclose(e1, e2, atol=1e-13)
    assert rod.energy(qe, xe) == pytest.approx(rod.energy(qe2, xe2), rel=1e-13)
    # and the sign of the nodal quaternions does not matter (q and -q are one rotation)
    flip = qe * np.where(RNG.random((3, p + 1, 1)) < 0.5, -1.0, 1.0)
    assert np.allclose(rod.strains(flip, xe), e1, atol=1e-13)


def test_strains_of_a_circular_arc_are_exact():
    """A circle of radius rho with d3 = tangent: v = (0,0,1), u = (0, 1/rho, 0) at every point
    for nodal data sampled from it (up to interpolation error, which falls as h^p)."""
    rho = 2.0
    errs = []
    for ne in (4, 8, 16):
        p = 3
        L = 2 * np.pi * rho * 0.25
        h = L / ne
        s = (np.arange(ne)[:, None] * p + np.arange(p + 1)[None, :]) * h / p
        ph = s / rho
        x = np.stack([rho * np.sin(ph), rho * (1 - np.cos(ph)), 0 * ph], axis=-1)
        t = np.stack([np.cos(ph), np.sin(ph), 0 * ph], axis=-1)
        q = so3.quat_from_rot(so3.frame_from_tangent(t))
        rod = elastic.ElasticRod(p, p + 1, h, STIFF)
        e = rod.strains(q, x)
        errs.append(np.abs(e - [0, 0, 1, 0, 1 / rho, 0]).max())
    rates = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert errs[-1] < 1e-5
    assert np.all(rates > 2.7)      # curvature converges as h^p, p = 3


def test_quaternion_projection_interpolates_rotations_at_order_p_plus_1():
    """Rotation interpolation error of a strongly twisted frame field falls as h^(p+1)."""
    def frame(s):
        return so3.qmul(so3.qexp(np.stack([s, 0.3 * s**2, np.sin(s)], -1)), so3.qexp(np.stack([0 * s, 0 * s, 3 * s], -1)))
    for p in (1, 2, 3, 4):
        errs = []
        for ne in (8, 16, 32):
            h = 1.0 / ne
            s_nodes = (np.arange(ne)[:, None] * p + np.arange(p + 1)[None, :]) * h / p
            qn = elastic.align_signs(frame(s_nodes))
            xi = np.linspace(-0.9, 0.9, 7)
            N, _, _ = fe.lagrange(p, xi)
            pq = np.einsum("qa,eai->eqi", N, qn)
            pq /= np.linalg.norm(pq, axis=-1, keepdims=True)
            s_pts = np.arange(ne)[:, None] * h + (xi[None, :] + 1) * h / 2
            exact = frame(s_pts)
            err = np.linalg.norm(so3.qlog(so3.qmul(so3.qconj(exact), pq)), axis=-1).max()
            errs.append(err)
        rate = np.log2(errs[-2] / errs[-1])
        assert rate > p + 1 - 0.3, (p, errs)


def test_so3_round_trips():
    th = RNG.normal(size=(50, 3)) * 2
    q = so3.qexp(th)
    R = so3.rot(q)
    assert np.allclose(np.einsum("nij,nkj->nik", R, R), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    q2 = so3.quat_from_rot(R)
    assert np.allclose(np.abs(np.einsum("ni,ni->n", q, q2)), 1.0, atol=1e-12)
    # exp(theta^x) a = a + theta x a + ... : compare with the matrix exponential series
    from scipy.linalg import expm
    for t in th[:5]:
        assert np.allclose(expm(so3.hat(t)), so3.rot(so3.qexp(t)), atol=1e-12)


def test_quaternion_product_is_the_product_of_rotations():
    """R(a * b) = R(a) R(b) for unit quaternions, batched and broadcast (one against many), and
    qexp near 0 (its series branch) agrees with the rotation matrix series."""
    a = so3.qexp(RNG.normal(size=(40, 3)))
    b = so3.qexp(RNG.normal(size=(40, 3)))
    assert np.allclose(so3.rot(so3.qmul(a, b)), so3.rot(a) @ so3.rot(b), atol=1e-13)
    one = so3.qmul(a[3], b)
    assert one.shape == (40, 4)
    assert np.allclose(so3.rot(one), so3.rot(a[3]) @ so3.rot(b), atol=1e-13)
    assert np.allclose(so3.qmul(a[:, None, :], b[None, :5, :]).shape, (40, 5, 4))
    tiny = np.array([[3e-9, -1e-9, 2e-9], [0.0, 0.0, 0.0]])
    assert np.allclose(so3.rot(so3.qexp(tiny)), np.eye(3) + so3.hat(tiny), atol=1e-16)


def test_lagrange_values_are_lagranges_n():
    """fe.lagrange_values (the basis alone, for the error estimate's 8e4 sample points) equals
    fe.lagrange's N to round-off, orders 1-7, and is a partition of unity."""
    from rodsnes.model import fe
    for order in range(1, 8):
        xi = np.random.default_rng(order).uniform(-1.0, 1.0, 500)
        N = fe.lagrange_values(order, xi)
        assert np.abs(N - fe.lagrange(order, xi)[0]).max() < 1e-13
        assert np.abs(N.sum(axis=1) - 1.0).max() < 1e-13
