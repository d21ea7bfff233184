"""Link, twist and writhe (rodsnes.topology): exact polygon values, Lk = Tw + Wr, sign
conventions, invariances, convergence to the smooth Gauss integral, open-rod closure."""
import numpy as np
import pytest

from rodsnes.model import topology as topo
from rodsnes.model.topology import close_open_rod, link, topology, twist, writhe

RNG = np.random.default_rng(11)


# ----------------------------------------------------------------------------- curves
def circle(n=400, radius=1.3):
    s = np.arange(n) / n * 2 * np.pi
    x = radius * np.c_[np.cos(s), np.sin(s), 0 * s]
    t = np.c_[-np.sin(s), np.cos(s), 0 * s]
    nrm = np.c_[np.cos(s), np.sin(s), 0 * s]
    return s, x, t, nrm


def turned(d, t, ang):
    """d rotated by ang about the unit tangent t (right-handed: d -> t x d)."""
    return np.cos(ang)[:, None] * d + np.sin(ang)[:, None] * np.cross(t, d)


def torus_curve(p, q, ph, R=2.0, r=0.8):
    """(p, q) torus curve: p turns about the torus axis, q about the tube (p = 1: a
    toroidal supercoil).  Returns points, derivative d/dphi, surface normal."""
    c, s = np.cos(q * ph), np.sin(q * ph)
    cp, sp = np.cos(p * ph), np.sin(p * ph)
    x = np.c_[(R + r * c) * cp, (R + r * c) * sp, r * s]
    dx = np.c_[-r * q * s * cp - p * (R + r * c) * sp, -r * q * s * sp + p * (R + r * c) * cp,
               r * q * c]
    nrm = np.c_[c * cp, c * sp, s]
    return x, dx, nrm


def gauss_quadrature_writhe(p, q, M):
    """Brute-force trapezoid rule for the smooth Gauss double integral on an M x M grid
    (the diagonal, where the integrand tends to 0, is left out).  Error O(M^-2)."""
    ph = np.arange(M) / M * 2 * np.pi
    x, dx, _ = torus_curve(p, q, ph)
    h = 2 * np.pi / M
    tot = 0.0
    for i0 in range(0, M, 250):
        sl = slice(i0, i0 + 250)
        d = x[sl, None] - x[None]
        num = np.einsum("ijk,ijk->ij", np.cross(dx[sl, None], dx[None]), d)
        den = np.einsum("ijk,ijk->ij", d, d) ** 1.5
        den[den == 0] = np.inf
        tot += np.sum(num / den)
    return tot * h * h / (4 * np.pi)


def random_rotation():
    Q, R = np.linalg.qr(RNG.normal(size=(3, 3)))
    Q = Q * np.sign(np.diag(R))
    return Q if np.linalg.det(Q) > 0 else -Q


def node_normal_projection(x, g):
    """A constant vector g projected normal to the node tangents (a director field)."""
    e = np.diff(x, axis=0)
    tn = np.vstack([e[:1], e[:-1] + e[1:], e[-1:]])
    tn /= np.linalg.norm(tn, axis=1)[:, None]
    d = g - (tn @ g)[:, None] * tn
    return d / np.linalg.norm(d, axis=1)[:, None], tn


def assert_integer(v, tol=1e-8):
    assert abs(v - round(v)) < tol, v


# ----------------------------------------------------------------------------- planar
def test_planar_curves_have_zero_writhe_and_lifting_them_does_not():
    t = np.arange(800) / 800 * 2 * np.pi
    _, circ, _, _ = circle()
    peanut = np.c_[(1 + 0.7 * np.cos(2 * t)) * np.cos(t), (1 + 0.7 * np.cos(2 * t)) * np.sin(t),
                   0 * t]   # non-convex, figure-eight-like (waisted) simple curve
    Q = random_rotation()
    for x in (circ, peanut, peanut @ Q.T + [0.3, -2.0, 5.0], circ @ Q.T):
        assert abs(writhe(x)) < 1e-10
    lifted = peanut.copy()
    lifted[:, 2] = 0.3 * np.sin(2 * t) + 0.2 * np.cos(t)
    assert abs(writhe(lifted)) > 0.1


def test_lifted_figure_eight_has_writhe_of_its_crossing_sign():
    """Lemniscate with its crossing lifted by +-eps: Wr -> crossing sign as eps -> 0 (the
    curve passes through itself at eps = 0, where Wr jumps by 2; mirror symmetry fixes
    Wr(-eps) = -Wr(eps)).  Right-handed (positive) crossing <=> positive writhe."""
    t = np.arange(1000) / 1000 * 2 * np.pi
    for eps in (0.01, -0.01, 0.05):
        x = np.c_[np.cos(t), np.sin(2 * t) / 2, eps * np.sin(t)]
        # crossing at the origin: t = pi/2 (z = +eps) and t = 3pi/2 (z = -eps)
        t_hi = np.array([-1.0, -1.0, 0.0]) if eps > 0 else np.array([1.0, -1.0, 0.0])
        t_lo = np.array([1.0, -1.0, 0.0]) if eps > 0 else np.array([-1.0, -1.0, 0.0])
        sign = np.sign(np.cross(t_hi, t_lo)[2])     # over x under . viewer (+z)
        wr = writhe(x)
        assert np.sign(wr) == sign
        assert abs(wr - sign) < (0.03 if abs(eps) == 0.01 else 0.1)


# ----------------------------------------------------------------------------- twisted circle
@pytest.mark.parametrize("n", [0, 1, 3, -2])
def test_twisted_circle(n):
    s, x, t, nrm = circle()
    d1 = turned(nrm, t, n * s)
    tw, lk, wr = twist(x, d1), link(x, d1), writhe(x)
    assert abs(tw - n) < 1e-10
    assert_integer(lk)
    assert round(lk) == n
    assert abs(wr) < 1e-10
    # shear: d1 tilted towards the tangent and of non-unit length changes nothing
    d1s = 1.7 * (d1 + 0.4 * t)
    assert abs(twist(x, d1s) - n) < 1e-10
    assert abs(link(x, d1s) - n) < 1e-8
    # the same with the binormal as reference director and a non-uniform twist rate
    ang = n * s + 0.8 * np.sin(2 * s)
    d1b = turned(np.cross(t, nrm), t, ang)
    assert abs(twist(x, d1b) - n) < 1e-10
    assert abs(link(x, d1b) - n) < 1e-8


def test_link_independent_of_ribbon_width_and_chunking(monkeypatch):
    ph = np.arange(300) / 300 * 2 * np.pi
    x, _, nrm = torus_curve(2, 3, ph)
    d1 = turned(nrm, np.gradient(x, axis=0), 2 * ph)
    ref = link(x, d1)
    assert_integer(ref)
    h = np.min(np.linalg.norm(np.diff(x, axis=0), axis=1))
    for w in (1e-6 * h, 1e-2 * h, 0.1 * h):
        assert abs(link(x, d1, ribbon_width=w) - ref) < 1e-8
    wr = writhe(x)
    monkeypatch.setattr(topo, "_PAIRS_PER_CHUNK", 997)
    assert abs(link(x, d1) - ref) < 1e-9
    assert abs(writhe(x) - wr) < 1e-12


# ----------------------------------------------------------------------------- torus curves
@pytest.mark.parametrize("p,q", [(2, 3), (1, 6)])
def test_torus_writhe_matches_gauss_quadrature_and_cwf_holds(p, q):
    """(2,3) trefoil torus knot and a (1,6) toroidal supercoil (6 superhelical turns)."""
    q1, q2 = gauss_quadrature_writhe(p, q, 1000), gauss_quadrature_writhe(p, q, 2000)
    wr_ref = (4 * q2 - q1) / 3                      # Richardson: O(M^-2) -> ~1e-9
    assert abs(q2 - wr_ref) < 1e-4                  # the quadrature itself has converged
    n1, n2 = 1000, 2000
    w1 = writhe(torus_curve(p, q, np.arange(n1) / n1 * 2 * np.pi)[0])
    w2 = writhe(torus_curve(p, q, np.arange(n2) / n2 * 2 * np.pi)[0])
    assert abs(w2 - wr_ref) < 1e-4
    assert abs((4 * w2 - w1) / 3 - wr_ref) < 1e-6   # polygon error is a clean O(h^2)
    # surface framing of a (p, q) torus curve links it p*q times (left-handed for q > 0);
    # k extra right-handed turns of d1 about the tangent add k
    ph = np.arange(600) / 600 * 2 * np.pi
    x, dx, nrm = torus_curve(p, q, ph)
    tng = dx / np.linalg.norm(dx, axis=1)[:, None]
    for k in (0, 2, -3):
        d1 = turned(nrm, tng, k * ph)
        res = topology(x, d1, closed=True)
        assert_integer(res["link"])
        assert round(res["link"]) == -p * q + k
        assert abs(res["link"] - res["twist"] - res["writhe"]) < 1e-8
        assert abs(res["writhe"] - writhe(x)) == 0.0


def test_refinement_converges_on_nonuniform_samplings():
    ref = (4 * gauss_quadrature_writhe(2, 3, 2000) - gauss_quadrature_writhe(2, 3, 1000)) / 3
    errs = []
    for n in (200, 400, 800, 1600):
        u = np.arange(n) / n * 2 * np.pi
        ph = u + 0.25 * np.sin(u)                    # a different parametrisation
        errs.append(abs(writhe(torus_curve(2, 3, ph)[0]) - ref))
    ratios = np.array(errs[:-1]) / np.array(errs[1:])
    assert np.all((ratios > 3.0) & (ratios < 5.0)), (errs, ratios)
    assert errs[-1] < 1e-4


def test_invariances():
    ph = np.arange(500) / 500 * 2 * np.pi
    x, dx, nrm = torus_curve(3, 2, ph)
    tng = dx / np.linalg.norm(dx, axis=1)[:, None]
    d1 = turned(nrm, tng, 4 * ph + 0.5 * np.sin(3 * ph))
    base = topology(x, d1, True)
    Q = random_rotation()
    variants = {
        "rigid": (x @ Q.T + [10.0, -3.0, 7.0], d1 @ Q.T),
        "start shifted": (np.roll(x, 123, axis=0), np.roll(d1, 123, axis=0)),
        "reversed": (x[::-1], d1[::-1]),
        "repeated end node": (np.vstack([x, x[:1]]), np.vstack([d1, d1[:1]])),
        "scaled": (2.5 * x, d1),
    }
    for name, (xv, dv) in variants.items():
        res = topology(xv, dv, True)
        for key in ("link", "twist", "writhe"):
            assert abs(res[key] - base[key]) < 1e-10, (name, key)
    M = np.diag([1.0, -1.0, 1.0])                      # mirror flips all three
    res = topology(x @ M, d1 @ M, True)
    for key in ("link", "twist", "writhe"):
        assert abs(res[key] + base[key]) < 1e-10, key
    assert abs(base["writhe"]) > 1.0


# ----------------------------------------------------------------------------- open rods
@pytest.mark.parametrize("n", [0, 1, 3, -2])
def test_open_straight_rod_twisted_n_turns(n):
    s = np.linspace(0.0, 1.0, 150)
    x = np.c_[4.0 * s, 0 * s, 0 * s]
    d1 = np.c_[0 * s, np.cos(2 * np.pi * n * s), np.sin(2 * np.pi * n * s)]
    for Q, shift, axis in ((np.eye(3), 0.0, None), (random_rotation(), 3.0, [1.0, 0, 0])):
        ax = None if axis is None else np.asarray(axis) @ Q.T
        res = topology(x @ Q.T + shift, d1 @ Q.T, closed=False, axis=ax)
        assert_integer(res["link"])
        assert round(res["link"]) == n
        assert abs(res["twist"] - n) < 1e-10
        assert abs(res["writhe"]) < 1e-10


def test_open_rod_fractional_turns_count_as_imposed():
    """A straight rod twisted by a fraction of a turn between its clamps: Tw and Lk are the
    turns put in (the closure's rotation is taken back out), Wr = 0."""
    s = np.linspace(0.0, 1.0, 150)
    x = np.c_[4.0 * s, 0 * s, 0 * s]
    for n in (2.25, -0.75, 0.4, 2.4217):
        d1 = np.c_[0 * s, np.cos(2 * np.pi * n * s), np.sin(2 * np.pi * n * s)]
        assert abs(twist(x, d1, closed=False) - n) < 1e-10
        res = topology(x, d1, closed=False)
        assert abs(res["link"] - n) < 1e-8
        assert abs(res["twist"] - n) < 1e-10
        assert abs(res["writhe"]) < 1e-10


def looped_rod(eps, A=2.0, n=600, arm=4.0):
    """Rod along x with a prolate-cycloid loop in the middle, crossing lifted by ~eps."""
    tt = np.linspace(-np.pi, np.pi, n)
    loop = np.c_[tt - A * np.sin(tt), 1 - A * np.cos(tt), eps * np.sin(tt) * (1 + np.cos(tt))]
    le = np.linspace(0.0, arm, 80)[1:]
    y0 = 1 + A
    x = np.vstack([np.c_[(-np.pi - le)[::-1], 0 * le + y0, 0 * le], loop,
                   np.c_[np.pi + le, 0 * le + y0, 0 * le]])
    # crossing sign: strands at +t1 and -t1 with t1 = A sin t1
    t1 = 2.0
    for _ in range(100):
        t1 = A * np.sin(t1)
    tan = lambda t: np.array([1 - A * np.cos(t), A * np.sin(t), 0.0])
    hi, lo = (tan(t1), tan(-t1)) if eps * np.sin(t1) > 0 else (tan(-t1), tan(t1))
    return x, int(np.sign(np.cross(hi, lo)[2]))


@pytest.mark.parametrize("eps", [0.05, -0.05])
def test_open_rod_with_loop(eps):
    x, sign = looped_rod(eps)
    # d1 normal to the loop plane: no twist, Lk = crossing sign, Wr close to it
    d1, tn = node_normal_projection(x, np.array([0.0, 0.0, 1.0]))
    res = topology(x, d1, closed=False)
    assert_integer(res["link"])
    assert round(res["link"]) == sign
    assert abs(res["link"] - res["twist"] - res["writhe"]) < 1e-8
    assert abs(res["writhe"] - sign) < 0.05
    assert abs(res["twist"]) < 0.05
    # plus 2 right-handed turns imposed at the end: Lk goes up by 2, Wr unchanged
    s = np.linspace(0.0, 1.0, len(x))
    res2 = topology(x, turned(d1, tn, 4 * np.pi * s), closed=False)
    assert round(res2["link"]) == sign + 2
    assert abs(res2["link"] - res2["twist"] - res2["writhe"]) < 1e-8
    assert abs(res2["writhe"] - res["writhe"]) < 1e-12


def test_closure_is_planar_twist_free_and_far_independent():
    s = np.linspace(0.0, 1.0, 300)
    bump = np.sin(np.pi * s) ** 3
    x = np.c_[10 * s, bump * (np.cos(9 * s) + 0.3 * np.sin(5 * s)), bump * (np.sin(7 * s) + 0.2)]
    d1, _ = node_normal_projection(x, np.array([0.0, 1.0, 0.3]))
    d1[0] = d1[-1] = np.array([0.0, 1.0, 0.3]) / np.hypot(1.0, 0.3)
    xc, dc = close_open_rod(x, d1)
    assert np.array_equal(xc[:len(x)], x) and np.array_equal(dc[:len(x)], d1)
    clo = xc[len(x) - 1:]                          # closure nodes incl. both rod ends
    clo = np.vstack([clo, x[:1]])
    nrm = np.cross(clo[1] - clo[0], clo[2] - clo[1])
    assert np.max(np.abs((clo - clo[0]) @ nrm)) < 1e-9 * np.linalg.norm(nrm) * np.max(np.abs(clo))
    # no twist along the closure (the end directors agree, normal to the axis)
    assert abs(twist(clo, np.vstack([dc[len(x) - 1:], d1[:1]]), closed=False)) < 1e-13
    ref = topology(x, d1, closed=False)
    assert abs(ref["writhe"]) > 0.01
    for far in (30.0, 1e3, 1e6):
        xc, dc = close_open_rod(x, d1, far=far)
        assert abs(writhe(xc) - ref["writhe"]) < 1e-10
        assert abs(twist(xc, dc) - ref["twist"]) < 1e-12
        assert abs(link(xc, dc) - ref["link"]) < 1e-8


def test_bad_director_is_rejected():
    s, x, t, nrm = circle(50)
    with pytest.raises(ValueError):
        link(x, t)
    with pytest.raises(ValueError):
        twist(x, nrm[:-1])
