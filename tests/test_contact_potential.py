"""The pair-potential contact law (-contact_model potential, rodsnes.contact.potential): its
calibration against the closest-point law, gradient and tangent against finite differences,
smoothness where closest points race, the quadrature's ripple, the option, and the assembled
problem (tangent, two ranks against one, a Newton solve)."""
import os

import numpy as np
import pytest
from petsc4py import PETSc

from conftest import natural_residuals, run_case, tangent_against_finite_differences
from rodsnes.contact.potential import (ONSET, PotentialKernel, law_energy, law_force,
                                       law_stiffness, line_force_per_stiffness, onset_layer,
                                       pair_stiffness)
from test_contact_math import Rod, check_gradient, check_tangent, hairpin, polyline
from test_contact_zones import largest_step

DATA = os.path.join(os.path.dirname(__file__), "data")


def potential_rod(X, p, closed, L, eps, mu, nqc=5, reach=None, **kw):
    rod = Rod(X, p, closed, L, eps=eps, mu=mu, delta=np.pi * eps, nqc=nqc, reach=reach)
    rod.k = PotentialKernel(p, nqc, eps, mu, rod.delta, L, rod.nelem, closed, **kw)
    return rod


def test_onset_law_is_twice_differentiable():
    """psi, psi', psi'' (module docstring, Onset law): each the derivative of the one before
    (central differences), all three continuous at a = 0 and at a = a_s, psi'' = 1 beyond a_s;
    a_s = 0 is the quadratic law, whose psi'' jumps from 0 to 1 at a = 0."""
    a_s = onset_layer(0.025, 0.01)
    assert a_s == pytest.approx(ONSET * 0.01 * 0.05) and a_s > 0
    a = np.linspace(1e-3, 3.0, 301) * a_s
    da = 1e-6 * a_s
    for law in (a_s, 0.0):
        fd1 = (law_energy(a + da, law) - law_energy(a - da, law)) / (2 * da)
        fd2 = (law_force(a + da, law) - law_force(a - da, law)) / (2 * da)
        assert np.allclose(fd1, law_force(a, law), rtol=1e-7, atol=1e-9 * a_s)
        assert np.allclose(fd2, law_stiffness(a, law), rtol=1e-6, atol=1e-6)
    for f in (law_energy, law_force, law_stiffness):
        lo, hi = f(a_s * (1 - 1e-12), a_s), f(a_s * (1 + 1e-12), a_s)
        assert abs(hi - lo) <= 1e-9 * abs(hi)
        assert abs(f(1e-12 * a_s, a_s)) <= 1e-12
    assert law_stiffness(2 * a_s, a_s) == 1.0
    assert law_stiffness(1e-12 * a_s, 0.0) == 1.0                   # the C^1 law's jump


@pytest.mark.parametrize("onset", [None, 0.0])
def test_line_force_law_of_two_straight_strands(onset):
    """f_1(d) (module docstring, (2)) against its small-penetration form: (16/15) sqrt(eps)
    d^2.5 / a_s within the onset layer, (8/3) sqrt(eps) d^1.5 for the quadratic law (a_s = 0);
    and k makes the force mu d* at the promised penetration d*."""
    eps, pen = 0.025, 0.01
    a_s = onset_layer(eps, pen, onset)
    for d in (1e-6, 1e-5):
        small = 16 / 15 * np.sqrt(eps) * d ** 2.5 / a_s if a_s else 8 / 3 * np.sqrt(eps) * d ** 1.5
        assert line_force_per_stiffness(eps, d, a_s) == pytest.approx(small, rel=20 * d / eps)
    d = pen * 2 * eps
    k = pair_stiffness(3.0, eps, pen, onset)
    assert k * line_force_per_stiffness(eps, d, a_s) == pytest.approx(3.0 * d, rel=1e-12)
    assert line_force_per_stiffness(eps, 0.0, a_s) == 0.0


@pytest.mark.parametrize("p", [2, 3])
def test_parallel_strands_carry_the_closest_point_force_at_the_promised_penetration(p):
    """Two straight legs of a hairpin at distance 2 eps - d*: away from the bend and the free
    ends every slave point carries mu d* (the closest-point law's force there), to the
    accuracy of the inner quadrature, whose integrand is C^1 where the couples leave the 2 eps
    ball (measured: 4.8e-4 (p = 2) and 1.1e-3 (p = 3) at the default nqp; the quadratic law's
    integrand has kinks there: 3.3e-3 and 4.2e-3)."""
    eps, mu, pen = 0.1, 1e4, 0.01
    d = pen * 2 * eps
    X, L = hairpin(p, 40, leg=2.0, rho=eps - d / 2)
    rod = potential_rod(X, p, False, L, eps, mu, nqc=p + 2)
    out = rod.eval(X, rod.pairs(X))
    s = rod.k.slave_arclength(rod.ids)
    middle = (np.abs(s - 1.0) < 0.5)                 # the first leg, away from its ends
    f = out["force"][middle]
    assert np.all(np.abs(f / (mu * d) - 1) < 2e-3), np.abs(f / (mu * d) - 1).max()
    assert np.allclose(out["gap"][middle], d, rtol=1e-9)


def crossing(x_cross, eps, d, h=0.05):
    """One open rod: a straight master piece along x from the rod's start (0, 0, 0) to
    (1, 0, 0), connectors, and a straight slave piece along y at height 2 eps - d crossing over
    x = x_cross, its middle element centred on the crossing.  The two straight pieces have
    elements of length h; the connectors do not (their arclength is nominal), and where the
    last one comes down to the slave piece it touches itself: only the crossing point is
    meant to be read (not totals)."""
    z = 2 * eps - d
    W = [[0, 0, 0], [1, 0, 0], [1, 0, 1], [x_cross, -0.525, 1], [x_cross, -0.525, z],
         [x_cross, 0.525, z]]
    nel = [20, 20, 20, 20, 21]
    return polyline(W, nel, 3), sum(nel) * h


def test_a_point_over_a_rod_end_gets_the_force_of_a_point_over_its_middle():
    """End caps (module docstring): a straight strand crossing over a straight one at right
    angles, at depth d*, over the middle and over the rod's end point: the line force at the
    crossing is mu d* in both (over the end: the half line plus the cap), to the quadrature's
    accuracy (measured: 0.99988 and 1.00019 mu d*; the quadratic law, 1.0071 and 1.0039);
    without the cap, over the end, 0.5004."""
    eps, mu, pen = 0.1, 1e4, 0.01
    d = pen * 2 * eps
    f = {}
    for where, x in (("middle", 0.5), ("end", 0.0)):
        X, L = crossing(x, eps, d)
        rod = potential_rod(X, 3, False, L, eps, mu)
        cap = rod.k.cap
        for with_cap in (True, False):
            rod.k.cap = cap if with_cap else 0.0
            out = rod.eval(X, rod.pairs(X))
            f[where, with_cap] = out["force"][90, 2] / (mu * d)        # the crossing point
            assert out["gap"][90, 2] == pytest.approx(d, rel=1e-9)
    assert f["middle", True] == f["middle", False] == pytest.approx(1.0, abs=2e-3)
    assert f["end", True] == pytest.approx(1.0, abs=2e-3)
    assert f["end", False] == pytest.approx(0.5, abs=2e-3)


@pytest.mark.parametrize("law", ["projection", "potential"])
def test_the_report_sees_a_rod_end_pressed_into_a_strand(law):
    """An open rod's end pressed end-on into a strand at depth d, the rod leaving it at right
    angles: the report's Gauss points, the first xi_1 along the last element, stand clear of
    the strand, the end itself is d deep.  The report (its deepest, which the penalty's
    promise and summary.json read) counts the end: the clamped end of a short plectoneme
    (-rod_length 0.5 -bc_end_turns 14) was 1.15 % of the diameter deep while it said 0.89 %."""
    from rodsnes.contact.term import ContactTerm
    eps, mu, d = 0.1, 1e4, 0.001
    W = [[0, 0, 0], [1, 0, 0], [1, 0, 1], [0.5, 0, 1], [0.5, 0, 2 * eps - d]]
    nel = [20, 20, 10, 20]
    X, L = polyline(W, nel, 3), sum(nel) * 0.05
    rod = Rod(X, 3, False, L, eps=eps, mu=mu) if law == "projection" else \
        potential_rod(X, 3, False, L, eps, mu)
    out = rod.eval(X, rod.pairs(X))
    if law == "potential":
        rod.k.add_report(out)
    assert out["end_depth"] == pytest.approx(d, rel=1e-9)
    # the Gauss points: the end's element clear, the strand's under it less deep than d (the
    # connectors' corners touch themselves: not read)
    assert out["gap"][-1].max() < 0.0 and out["gap"][8:12].max() < 0.99 * d
    assert ContactTerm.deepest_local(out, report=True) >= d * (1 - 1e-9)
    # reversed, the end is the rod's start (s = 0)
    Xr = X[::-1].copy()
    out = rod.eval(Xr, rod.pairs(Xr))
    if law == "potential":
        rod.k.add_report(out)
    assert out["end_depth"] == pytest.approx(d, rel=1e-9) and out["gap"][0].max() < 0.0


@pytest.mark.parametrize("onset", [None, 0.0])
@pytest.mark.parametrize("nel, p", [(1, 3), (2, 3), (1, 2)])
def test_gradient_and_tangent_on_one_or_two_elements_folded_onto_themselves(nel, p, onset):
    """A rod of one or two elements folded back onto itself: couples within one element
    (e == m), both end caps in one element, caps acting (the energy changes with them)."""
    if nel == 1:
        X = np.array([[0, 0, 0], [1, 0, 0], [1, 0.12, 0], [0, 0.12, 0.0]]) if p == 3 else \
            np.array([[0, 0, 0], [1, 0.06, 0], [0, 0.12, 0.0]])
    else:
        X = np.array([[0, 0, 0], [0.5, 0, 0], [1, 0, 0], [1.05, 0.06, 0], [1, 0.12, 0],
                      [0.5, 0.12, 0], [0, 0.12, 0.0]])
    X = X + 1e-3 * np.random.default_rng(0).standard_normal(X.shape)
    rod = potential_rod(X, p, False, 2.2, 0.1, 1e4, nqp=16, onset=onset)
    pairs = rod.pairs(X)
    assert np.any(pairs[:, 0] == pairs[:, 1])
    E = rod.energy(X, pairs)
    cap, rod.k.cap = rod.k.cap, 0.0
    assert rod.energy(X, pairs) < E
    rod.k.cap = cap
    check_gradient(rod, X, pairs, 1e-7, tol=1e-6)
    K, _ = check_tangent(rod, X, pairs, 1e-7, tol=1e-5)
    assert np.abs(K - K.T).max() <= 1e-12 * np.abs(K).max()


def test_energy_ripple_as_strands_slide():
    """Fixed quadrature points on both strands: the energy of two parallel straight strands at
    fixed distance varies as one slides along the other by a fraction of an element (the
    frictionless law should not see it).  Measured, peak-to-peak / mean: 6.6e-5 at the default
    nqp (15 for the plectoneme's h / eps), 2.0e-5 at 30; the quadratic law (a_s = 0), whose
    integrand has kinks at the ball's edge, 1.1e-3 at the default nqp, 1.8e-4 at 20, 4.9e-5
    at 30."""
    eps, mu, pen = 0.025, 5e7, 0.01
    d = pen * 2 * eps
    h = 1 / 60
    nel = 20

    def energy(shift, nqp, onset=None):
        a = polyline([[0, 0, 0], [nel * h, 0, 0]], [nel], 3)
        b = polyline([[nel * h + shift, 2 * eps - d, 0], [shift, 2 * eps - d, 0]], [nel], 3)
        X = np.concatenate([a, b[1:]])                  # one rod: a, a jump, b backwards
        X[3 * nel + 1:] = b[1:]
        rod = potential_rod(X, 3, False, 2 * nel * h, eps, mu, nqp=nqp, onset=onset)
        # keep the interaction of the strands' middles: no end effects
        pairs = rod.pairs(X)
        keep = (pairs[:, 0] >= 5) & (pairs[:, 0] < nel - 5) & (pairs[:, 1] >= nel)
        return rod.eval(X, pairs[keep])["energy"]

    shifts = np.linspace(0, h, 9)
    ripple = {}
    for nqp, onset in ((None, None), (30, None), (None, 0.0), (30, 0.0)):
        E = np.array([energy(t, nqp, onset) for t in shifts])
        ripple[nqp, onset] = np.ptp(E) / E.mean()
    assert ripple[None, None] < 1e-4 and ripple[30, None] < 0.5 * ripple[None, None], ripple
    assert ripple[None, 0.0] > 10 * ripple[None, None], ripple
    assert ripple[30, 0.0] < 0.1 * ripple[None, 0.0], ripple


@pytest.mark.slow
def test_gradient_and_tangent_on_the_plectoneme_end_loop():
    """The end loop of the plectoneme at 8.57 turns (test_contact_zones: closest points on
    exclusion bounds, racing at two jumps): residual and tangent against differences."""
    X = np.load(os.path.join(DATA, "plectoneme_end_loop.npy"))
    rod = potential_rod(X, 3, False, 1.0, 0.025, 1.5239568869908707e7, reach=0.125)
    pairs = rod.pairs(X)
    assert check_gradient(rod, X, pairs, 1e-7, tol=1e-6) < 1e-6
    K, out = check_tangent(rod, X, pairs, 1e-8, tol=1e-5, maxcols=90)
    assert len(out["active"]) > 50 and len(out["switch"]) == 0
    assert np.abs(K - K.T).max() <= 1e-12 * np.abs(K).max()


@pytest.mark.parametrize("onset", [None, 0.0])
@pytest.mark.parametrize("closed", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_gradient_and_tangent_at_the_edge_of_contact(closed, onset):
    """A hairpin (open) or a stadium (closed) whose legs touch at barely 2 eps: point couples
    enter and leave the contact ball; and p = 2."""
    eps, p = 0.1, 2
    if closed:
        R = eps * (1 - 1e-3)
        n1 = 12
        top = polyline([[0, 0, 0], [2, 0, 0]], [n1], p)
        arc1 = [np.array([2 + R * np.sin(t), R - R * np.cos(t), 0]) for t in np.linspace(0, np.pi, 3 * p + 1)[1:]]
        bot = polyline([[2, 2 * R, 0], [0, 2 * R, 0]], [n1], p)[1:]
        arc2 = [np.array([-R * np.sin(t), R + R * np.cos(t), 0]) for t in np.linspace(0, np.pi, 3 * p + 1)[1:-1]]
        X = np.concatenate([top, np.array(arc1), bot, np.array(arc2)])
        seg = np.linalg.norm(np.diff(np.concatenate([X, X[:1]]), axis=0), axis=1)
        L = seg.sum()
    else:
        X, L = hairpin(p, 30, leg=1.0, rho=eps * (1 - 1e-3))
    X = X + 1e-4 * np.random.default_rng(1).standard_normal(X.shape)
    rod = potential_rod(X, p, closed, L, eps, 1e3, onset=onset)
    pairs = rod.pairs(X)
    check_gradient(rod, X, pairs, 1e-7, tol=1e-6)
    check_tangent(rod, X, pairs, 1e-8, tol=1e-5, maxcols=80)


@pytest.mark.parametrize("onset", [None, 0.0])
def test_tangent_is_continuous_as_couples_enter_the_ball(onset):
    """Module docstring, Onset law: a strand crossing over another at right angles, 1e-4 above
    contact, lowered by t in [0, 3e-4] (couples enter the ball one by one): the largest change of
    the slave element's normal stiffness found by bisection is, over an interval of 3e-13, a
    slope's worth (measured 4.5e-8 of 17) with the onset law; the quadratic law's jumps by a
    couple's k W N^2 (measured 34 of 130)."""
    eps = 0.1
    X0, L = crossing(0.5, eps, -1e-4)
    slave = np.arange(240, len(X0))                     # the straight slave piece
    rod = potential_rod(X0, 3, False, L, eps, 1e4, onset=onset)
    pairs = rod.pairs(X0)
    dofs = 3 * np.arange(270, 274) + 2                  # z of the element over the crossing

    def stiffness(t):
        X = X0.copy()
        X[slave, 2] -= t
        K, _ = rod.tangent(X, pairs)
        return K[np.ix_(dofs, dofs)].sum()

    assert stiffness(0.0) == 0.0
    whole = stiffness(3e-4)
    a, b, fa, fb = largest_step(stiffness, 0.0, 3e-4)
    if onset == 0.0:
        assert abs(fb - fa) > 0.1 * whole, (a, fb - fa, whole)
    else:
        assert abs(fb - fa) < 1e-6 * whole, (a, fb - fa, whole)


def dense_reference(k, X, conn, pairs):
    """Energy, residual rows and tangent blocks of (1) on every candidate pair, dense over the
    couples (the module docstring's formulas, no pair left out), for rows that touch."""
    e, m = pairs[:, 0], pairs[:, 1]
    xs = np.einsum("qa,pad->pqd", k.Np, X[conn[e]])
    xm = np.einsum("ja,pad->pjd", k.Nm, X[conn[m]])
    a, r, nu = k.couples(xs, xm, k.admissible(e, m, k.xp, k.xm))
    W = (k.wp * 0.5 * k.h)[None, :, None] * k.master_weights(m)[:, None, :]
    act = np.flatnonzero((W * a > 0).any(axis=(1, 2)))
    a, r, nu, W = a[act], r[act], nu[act], W[act]
    f1, f2 = law_force(a, k.a_s), law_stiffness(a, k.a_s)
    G = -k.k * (W * f1)[..., None] * nu
    vec = np.concatenate([np.einsum("qa,pqjd->pad", k.Np, G),
                          -np.einsum("ja,pqjd->pad", k.Nm, G)], axis=1)
    c = np.where(a > 0, f1 / r, 0.0)
    on = (a > 0) * k.k * W
    H = (on * (f2 + c))[..., None, None] * np.einsum("pqji,pqjk->pqjik", nu, nu) \
        - (on * c)[..., None, None] * np.eye(3)
    Nt = np.concatenate([np.broadcast_to(k.Np[:, None, :], (k.nqp, k.nqp + 2, k.p + 1)),
                         -np.broadcast_to(k.Nm[None, :, :], (k.nqp, k.nqp + 2, k.p + 1))], axis=2)
    mat = np.einsum("qja,qjb,pqjik->paibk", Nt, Nt, H, optimize=True)
    n = 6 * (k.p + 1)
    return k.k * np.sum(W * law_energy(a, k.a_s)), pairs[act], vec, mat.reshape(len(act), n, n)


@pytest.mark.parametrize("onset", [None, 0.0])
def test_near_pairs_and_the_parts_made_on_demand_against_the_dense_potential(onset):
    """On the plectoneme's 9.72-turn line contact: the pairs left out by the spheres and
    capsules hold no couple in contact (energy, residual and tangent equal the dense reference
    over every candidate pair to roundoff), fewer than two thirds of the candidates are
    evaluated, the residual-only evaluation is the full one's bit for bit, and the tangent and
    report made afterwards are the full evaluation's."""
    X = np.load(os.path.join(DATA, "plectoneme_9.72_line_contact.npy"))
    rod = potential_rod(X, 3, False, 1.0, 0.025, 5.754172062186161e7, reach=2.5 * 0.025,
                        onset=onset)
    pairs = rod.pairs(X)
    k = rod.k
    args = (rod.ids, X[rod.conn], rod.ids, X[rod.conn], pairs)
    full = k.evaluate(*args, tangent=True, report=True)
    E, act, vec, mat = dense_reference(k, X, rod.conn, pairs)
    assert len(act) > 100 and np.array_equal(full["active"], act)
    assert full["energy"] == pytest.approx(E, rel=1e-13)
    assert np.abs(full["vec"] - vec).max() <= 1e-13 * np.abs(vec).max()
    assert np.abs(full["mat"] - mat).max() <= 1e-13 * np.abs(mat).max()
    assert len(full["_near"]["oi"]) < 2 / 3 * len(pairs)
    alone = k.evaluate(*args, tangent=False, report=False)
    assert alone["mat"] is None and not alone["reported"] and np.all(alone["gap"] == -np.inf)
    assert alone["energy"] == full["energy"] and np.array_equal(alone["vec"], full["vec"])
    assert alone["depth"] == full["depth"] > 0
    k.add_report(k.add_tangent(alone))
    for key in ("mat", "gap", "force", "sbar", "d_active"):
        assert np.array_equal(alone[key], full[key]), key
    for key in ("total_force", "complementarity", "zones"):
        assert alone[key] == full[key], key
    # the guard's depth at the point couples against the report's deepest point
    assert full["depth"] == pytest.approx(full["gap"].max(), rel=0.05)


def test_residual_is_smooth_where_the_closest_point_races():
    """The plectoneme at 9.72 turns, strands in line contact (test_contact_zones: a C0-kink
    minimum takes over from the minimum inside an element between two samples; the
    closest-point residual stepped by 5.5 there before the rival cut).  With the pair potential
    the residual at node 51 follows the tangent in a move of node 79 (central differences over
    +-2e-7; a forward difference sees the onset law's third derivative, k / a_s: 38 of 5e4):
    bisecting [0, 2e-7] for the largest change finds none beyond the tangent's prediction."""
    X0 = np.load(os.path.join(DATA, "plectoneme_9.72_line_contact.npy"))
    rod = potential_rod(X0, 3, False, 1.0, 0.025, 5.754172062186161e7, reach=0.125)
    pairs = rod.pairs(X0)
    K, _ = rod.tangent(X0, pairs)
    slope = K[3 * 51 + 2, 3 * 79 + 1]

    def force(t):
        X = X0.copy()
        X[79, 1] += t
        return rod.residual(X, pairs)[51, 2]

    assert abs((force(2e-7) - force(-2e-7)) / 4e-7 - slope) < 1e-6 * abs(slope) + 1e-3
    a, b, fa, fb = largest_step(force, 0.0, 2e-7)
    assert abs(fb - fa) < abs(slope) * (b - a) + 1e-9 * abs(fa), (a, fb - fa)


def test_zones_with_the_potential_and_an_unresolved_mesh_are_refused():
    from conftest import build_run
    from rodsnes.errors import SceneError
    with pytest.raises(SceneError, match="contact_zones"):
        build_run("rollup_contact", contact_model="potential", contact_zones="true",
                  rod_nelem=64)
    # L = 10, eps = 0.1: a contact at 1 % touches 0.056 of the master; 12 points on it need
    # 67 per element of 32
    with pytest.raises(SceneError, match=r"-rod_nelem 45 or more.*-contact_quadrature"):
        build_run("rollup_contact", contact_model="potential")
    run = build_run("rollup_contact", contact_model="potential", contact_quadrature=20)
    assert run.contact.kernel.nqp == 20 and run.contact.nqc == 5
    assert build_run("rollup_contact", contact_model="potential", rod_nelem=45).contact.kernel.nqp == 48
    # a 2 % standoff's softer law (its promise 2.94 % of a diameter 2 % larger) touches 0.097
    # of the master, which 32 elements resolve with 39 points each
    assert build_run("rollup_contact", contact_model="potential",
                     contact_standoff=0.02).contact.kernel.nqp == 39


# the coiled rod's overlap is deeper than the wall (-contact_wall), where the energy is infinite
POTENTIAL = dict(contact_model="potential", contact_quadrature=24, contact_wall=0)


def coiled(comm=None, outdir=None):
    """test_contact.coiled with the pair potential: the free end overlaps the clamped start."""
    from test_contact import coiled as closest_point_coiled
    return closest_point_coiled(comm, outdir, **POTENTIAL)


@pytest.mark.mpi
def test_assembled_tangent_and_two_ranks_with_the_potential():
    par = coiled()
    p = par.problem
    F = p.state.X.duplicate()
    p.residual(None, p.state.X, F)
    assert par.contact.summary()["active_points"] > 0
    J = p.layout.create_matrix(par.contact.extra_pattern(p.state.local_config()[0]))
    p.jacobian(None, p.state.X, J, J)
    fd, Jv, _ = tangent_against_finite_differences(p, J, seed=3)
    assert (fd - Jv).norm() / Jv.norm() < 1e-6
    ser = coiled(comm=PETSc.COMM_SELF, outdir=par.outdir + f"_s{PETSc.COMM_WORLD.getRank()}")
    nat1, nat2 = natural_residuals(par, ser)
    assert np.abs(nat1 - nat2).max() < 1e-9 * np.abs(nat2).max()
    c1, c2 = par.contact.summary(), ser.contact.summary()
    assert c1["total_force"] == pytest.approx(c2["total_force"], rel=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("wall", [0, 1])
def test_rollup_contact_solves_and_newton_converges_fast(wall):
    """The rolled-up rod whose free end lands on its clamped part (cases/rollup_contact.opts,
    48 elements so that 12 points resolve a contact) with the pair potential: every load step
    converges, the penetration keeps the promise, and the tip lands within 1 % of the rod's
    length of the closest-point solution.  Newton from the equilibrium disturbed by 1e-5
    (random, every free dof) converges quadratically to the roundoff floor (1.2e-8).  The
    penalty alone (-contact_wall 0): |F_2| <= 100 |F_1|^2 from the first step, in 3 iterations
    (measured 127 -> 3.9e-5 -> 2.0e-8 -> 1.2e-9; the quadratic law, 127 -> 3.8e-5 -> 2.0e-8 ->
    1.1e-9), like the closest-point law's (127 -> 3.9e-5 -> 2.5e-8 -> 1.2e-9).  With the wall
    (the default) the state sits just inside the barrier (mu raised between steps): the same,
    127 -> 1.1e-4 -> 1.0e-7 -> 1.3e-9, at the floor in 3 or 4 iterations (a fourth where the
    third still fell by more than 10 x: the minimiser stops at the floor once |F| no longer
    falls).  (Its raise once came after the last step too, which left the state off the
    equilibrium of the raised mu: Newton then went to another one, 127 -> 0.21 -> 5.8e-3 ->
    3.6e-6 -> 1.1e-9.)  40 load steps instead of the case's 10: the same equilibria (tip and
    force to 1e-10) in about half the time."""
    kw = dict(rod_nelem=48, load_steps=40)
    pot = run_case("rollup_contact", contact_model="potential", contact_wall=wall, **kw)
    ref = run_case("rollup_contact", **kw)
    assert pot.ok and ref.ok
    sp, sr = pot.summary(converged=True), ref.summary(converged=True)
    assert sp["contact"]["max_penetration"] <= 0.0101
    assert sp["contact"]["total_force"] > 3.0
    assert np.linalg.norm(np.subtract(sp["tip_position"], sr["tip_position"])) < 0.01 * 10
    p, s = pot.problem, pot.solver
    with p.state.X as a:
        d = 1e-5 * np.random.default_rng(0).standard_normal(a.shape)
        d[p.constraints.rows_local] = 0.0
        a[:] += d
    res = s.solve_at(p.lam)
    h = res.history
    assert res.converged and h[0] > 1e2
    at_floor = next(k for k, v in enumerate(h) if v <= s.floor)
    assert h[1] < 1e-5 * h[0] and h[2] <= 100 * h[1] ** 2 and h[-1] <= s.floor, h
    assert at_floor <= (3 if not wall else 4) and len(h) <= at_floor + 2, h
    assert (pot.contact.penalty_eased > 0) == bool(wall)


def evaluation(X, p, closed, L, eps, mu, reach, own, onset=None):
    """(rod, pairs, the arguments of PotentialKernel.evaluate) of a kernel_states() state: the
    candidate pairs of its own elements (``own``; None: all)."""
    rod = potential_rod(X, p, closed, L, eps, mu, reach=reach, onset=onset)
    pairs = rod.pairs(X)
    ids = rod.ids
    if own is not None:
        pairs = pairs[np.isin(pairs[:, 0], own)]
        ids = own
    return rod, pairs, (ids, X[rod.conn[ids]], rod.ids, X[rod.conn], pairs)


def kernel_states():
    """(name, rod, own elements or None) for the compiled-against-numpy comparison: the
    plectoneme's line contact and end loop, dense random coils of orders 1-4, open and closed
    (deep couples: a beyond the onset layer), with own elements a part of the rod as on a rank;
    a helix with near pairs but no couple in contact (negative depth)."""
    from test_contact_math import helix, random_coil
    out = []
    for name in ("plectoneme_9.72_line_contact", "plectoneme_end_loop"):
        X = np.load(os.path.join(DATA, name + ".npy"))
        out.append((name, X, 3, False, 1.0, 0.025, 5.754172062186161e7, 0.0625, None))
    for p in (1, 2, 3, 4):
        for closed in (False, True):
            X = random_coil(p, 40, 0.08, 10 * p)
            X = X[:-1] if closed else X
            out.append((f"coil p{p} closed {closed}", X, p, closed, 3.2, 0.05, 1e3, None, None))
            out.append((f"coil p{p} closed {closed}, own 5-22", X, p, closed, 3.2, 0.05, 1e3,
                        None, np.arange(5, 23)))
    X, L = helix(3, 30, a=0.3, pitch=0.5, turns=2.0)
    out.append(("helix apart", X, 3, False, L, 0.1, 1e3, 0.9, None))
    return out


def same(a, b, rtol=1e-12):
    """a equals b to rtol of b's largest entry (integers and non-finite values exactly)."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape:
        return False
    if b.dtype.kind in "biu":
        return np.array_equal(a, b)
    fin = np.isfinite(b)
    if not np.array_equal(np.isfinite(a), fin) or not np.array_equal(a[~fin], b[~fin],
                                                                    equal_nan=True):
        return False
    return not fin.any() or np.abs(a[fin] - b[fin]).max() <= rtol * np.abs(b[fin]).max()


@pytest.mark.parametrize("onset", [None, 0.0])
def test_compiled_kernel_equals_the_numpy_path(onset):
    """The compiled kernel (rodsnes/contact/_potential_kernel.c through potential_compiled.py) against
    the numpy path of PotentialKernel, and the numpy path against the dense formulas
    (``dense_reference``) where every element is own: energy, residual, depth, active rows,
    tangent and report to 1e-12 (the same couples: depth and rows exactly), with the end caps
    on and off.  `make install` builds the kernel: a missing library is a failure."""
    from rodsnes.contact import potential_compiled
    assert potential_compiled.available(), "the compiled potential kernel is not built"
    for name, X, p, closed, L, eps, mu, reach, own in kernel_states():
        rod, pairs, args = evaluation(X, p, closed, L, eps, mu, reach, own, onset=onset)
        kern = {}
        for kind in ("numpy", "compiled"):
            kern[kind] = PotentialKernel(p, rod.k.nqc, eps, mu, rod.delta, L, rod.nelem, closed,
                                         onset=onset, kernel=kind)
        assert kern["compiled"].compiled and not kern["numpy"].compiled
        for cap in (None, 0.0):
            out = {}
            for kind, k in kern.items():
                if cap is not None:
                    k.cap = cap
                out[kind] = k.evaluate(*args, tangent=True, report=True)
            ref, got = out["numpy"], out["compiled"]
            assert ref["depth"] == got["depth"], name
            assert np.array_equal(ref["active"], got["active"]), name
            for key in ("energy", "vec", "mat", "gap", "force", "total_force",
                        "complementarity", "d_active", "zones"):
                assert same(got[key], ref[key]), (name, cap, key)
            if own is None and len(ref["active"]):
                E, act, vec, mat = dense_reference(kern["numpy"], X, rod.conn, pairs)
                assert np.array_equal(ref["active"], act), name
                assert ref["energy"] == pytest.approx(E, rel=1e-12), name
                assert same(ref["vec"], vec) and same(ref["mat"], mat), name
    assert -np.inf < ref["depth"] < 0 and len(ref["active"]) == 0     # the helix: near, apart


@pytest.mark.parametrize("kind", ["numpy", "compiled"])
def test_chunks_of_the_pass_over_the_near_pairs_do_not_change_the_result(kind):
    """The pass over the near pairs in chunks of a bounded number of point couples (Cost:
    ``chunk_couples``; the compiled kernel's couple buffers, numpy's distance arrays, the
    report's line force) against one chunk: the couples, depth, rows, energy, residual, tangent
    and report bit for bit (compiled) or to round-off of the energy's sum (numpy: its chunks'
    sums), with chunks of one pair, a few pairs and all pairs, on the states of the
    compiled-against-numpy comparison (contact, and the helix's near pairs apart)."""
    if kind == "compiled":
        from rodsnes.contact import potential_compiled
        assert potential_compiled.available(), "the compiled potential kernel is not built"
    for name, X, p, closed, L, eps, mu, reach, own in kernel_states():
        rod, pairs, args = evaluation(X, p, closed, L, eps, mu, reach, own)
        out = {}
        for chunk in (1, 7, None):
            k = PotentialKernel(p, rod.k.nqc, eps, mu, rod.delta, L, rod.nelem, closed, kernel=kind)
            per_pair = k.nqp * (k.nqp + 2)
            k.chunk_couples = 10 ** 12 if chunk is None else chunk * per_pair
            out[chunk] = k.evaluate(*args, tangent=True, report=True)
            if chunk == 1:
                assert len(k.pair_chunks(len(out[chunk]["_near"]["oi"]))) == \
                    len(out[chunk]["_near"]["oi"]), name
        ref = out[None]
        near = ref["_near"]
        assert len(near["oi"]) > 7, name        # several chunks of 7 pairs
        for chunk in (1, 7):
            got = out[chunk]
            for key in ("depth", "active", "vec", "mat", "gap", "force", "d_active",
                        "total_force", "complementarity", "zones"):
                assert np.array_equal(got[key], ref[key]), (name, chunk, key)
            for a, b in zip(got["_near"]["couples"], near["couples"]):
                assert np.array_equal(a, b), (name, chunk)
            if kind == "compiled":
                assert got["energy"] == ref["energy"], (name, chunk)
            else:
                assert got["energy"] == pytest.approx(ref["energy"], rel=1e-14, abs=0.0), \
                    (name, chunk)
    assert ref["depth"] < 0 and len(ref["active"]) == 0        # the helix: near, apart


def test_pattern_pairs_are_the_pairs_with_a_couple_of_points_within_reach():
    """PotentialKernel.pairs_within (the Jacobian's pattern with this law,
    ContactTerm.pattern_pairs): at reach 2 eps exactly the rows of an evaluation (the pairs the
    tangent couples); at 2 eps + 0.5 eps the pairs whose admissible couples of W > 0 come
    within that distance, by the dense couples of every candidate pair; the compiled kernel's
    pairs are numpy's; fewer pairs than the capsules within reach on the plectoneme's line
    contact (the pattern's default reach, 2 eps)."""
    from rodsnes.contact.search import capsules_within, element_capsules
    for name, X, p, closed, L, eps, mu, reach, own in kernel_states():
        rod, pairs, args = evaluation(X, p, closed, L, eps, mu, reach, own)
        k = {kind: PotentialKernel(p, rod.k.nqc, eps, mu, rod.delta, L, rod.nelem, closed,
                                   kernel=kind) for kind in ("numpy", "compiled")}
        rows = k["numpy"].evaluate(*args, tangent=False, report=False)["active"]
        for kind, kern in k.items():
            got = kern.pairs_within(*args, 2.0 * eps)
            assert np.array_equal(got, np.asarray(rows).reshape(-1, 2)), (name, kind)
        wide = 2.5 * eps
        got = k["numpy"].pairs_within(*args, wide)
        assert np.array_equal(k["compiled"].pairs_within(*args, wide), got), name
        # the dense couples of every candidate pair
        kern = k["numpy"]
        e, m = pairs[:, 0], pairs[:, 1]
        xs = np.einsum("qa,pad->pqd", kern.Np, X[rod.conn[e]])
        xm = np.einsum("ja,pad->pjd", kern.Nm, X[rod.conn[m]])
        r = np.linalg.norm(xs[:, :, None, :] - xm[:, None, :, :], axis=3)
        ok = kern.admissible(e, m, kern.xp, kern.xm) & (kern.master_weights(m) > 0)[:, None, :]
        dense = pairs[(ok & (r < wide)).any(axis=(1, 2))]
        assert np.array_equal(got, dense), name
        if name == "plectoneme_9.72_line_contact":
            caps = element_capsules(X[rod.conn])
            near = capsules_within([v[e] for v in caps], [v[m] for v in caps], 2.0 * eps)
            assert 100 < len(rows) < 0.6 * np.count_nonzero(near), \
                (len(rows), np.count_nonzero(near))


def test_wall_law_is_twice_differentiable_and_infinite_at_the_wall():
    """The wall's barrier (module docstring, The wall) added to the onset law: psi, psi',
    psi'' each the derivative of the one before (central differences) inside the barrier,
    continuous where it starts (a_b: the law without it up to there, C^2), growing without
    bound towards the wall a_w and infinite from there on."""
    a_s = onset_layer(0.025, 0.01)
    wall = (0.6 * a_s, a_s)
    a = np.linspace(0.62, 0.999, 200) * a_s
    da = 1e-7 * a_s
    fd1 = (law_energy(a + da, a_s, wall) - law_energy(a - da, a_s, wall)) / (2 * da)
    fd2 = (law_force(a + da, a_s, wall) - law_force(a - da, a_s, wall)) / (2 * da)
    assert np.allclose(fd1, law_force(a, a_s, wall), rtol=1e-6, atol=1e-9 * a_s)
    assert np.allclose(fd2, law_stiffness(a, a_s, wall), rtol=1e-5)
    below = np.linspace(0.0, 0.6, 50) * a_s
    for f in (law_energy, law_force, law_stiffness):
        assert np.array_equal(f(below, a_s, wall), f(below, a_s))
        lo, hi = f(wall[0] * (1 - 1e-12), a_s, wall), f(wall[0] * (1 + 1e-12), a_s, wall)
        assert abs(hi - lo) <= 1e-9 * abs(hi)
        assert np.all(np.isinf(f(np.array([a_s, 1.5 * a_s]), a_s, wall)))
    near = law_stiffness(np.array([0.9, 0.99, 0.999]) * a_s, a_s, wall)
    assert np.all(np.diff(near) > 0) and near[-1] > 1e4 * law_stiffness(0.9 * a_s, a_s)


def wall_state(kind="numpy"):
    """A rod of two elements folded onto itself (as in the test above) with a kernel whose
    wall stands beyond its deepest couple and whose barrier acts on it: (rod, pairs, depth)."""
    X = np.array([[0, 0, 0], [0.5, 0, 0], [1, 0, 0], [1.05, 0.06, 0], [1, 0.12, 0],
                  [0.5, 0.12, 0], [0, 0.12, 0.0]])
    X = X + 1e-3 * np.random.default_rng(0).standard_normal(X.shape)
    rod = potential_rod(X, 3, False, 2.2, 0.1, 1e4, nqp=48, kernel=kind)
    pairs = rod.pairs(X)
    depth = rod.k.evaluate(*evaluation_args(rod, X, pairs), tangent=False, report=False)["depth"]
    # the wall at 1.1 depth (the promise d* = the wall + the sampling error, which depends on
    # d*: a fixed point), its barrier over 40 % of it
    pen = 0.01
    for _ in range(30):
        rod.k = PotentialKernel(3, rod.k.nqc, 0.1, 1e4, rod.delta, 2.2, rod.nelem, False,
                                nqp=48, penetration=pen, wall=0.4 * 1.1 * depth, kernel=kind)
        pen = (1.1 * depth + rod.k.sampling_error()) / (2 * 0.1)
    assert rod.k.wall[1] == pytest.approx(1.1 * depth, rel=1e-6)
    return rod, X, pairs, depth


def evaluation_args(rod, X, pairs):
    return rod.ids, X[rod.conn[rod.ids]], rod.ids, X[rod.conn], pairs


def test_gradient_and_tangent_with_the_wall():
    """Inside the wall's barrier (the deepest couple at 0.91 of the way to the wall, 0.77 of
    it into the barrier): the residual the energy's gradient, the tangent the residual's
    Jacobian (finite differences), symmetric; the compiled kernel equals the numpy path
    (energy, residual, tangent, report) to 1e-12; beyond the wall the energy is infinite."""
    rod, X, pairs, depth = wall_state()
    a_b, a_w = rod.k.wall
    assert a_b < depth < a_w
    plain = rod.k.evaluate(*evaluation_args(rod, X, pairs), tangent=False, report=False)
    check_gradient(rod, X, pairs, 1e-8, tol=1e-6)
    K, _ = check_tangent(rod, X, pairs, 1e-8, tol=1e-5)
    assert np.abs(K - K.T).max() <= 1e-12 * np.abs(K).max()
    from rodsnes.contact import potential_compiled
    assert potential_compiled.available(), "the compiled potential kernel is not built"
    out = {}
    for kind in ("numpy", "compiled"):
        r, *_ = wall_state(kind)
        out[kind] = r.k.evaluate(*evaluation_args(r, X, pairs), tangent=True, report=True)
    for key in ("energy", "vec", "mat", "gap", "force", "total_force", "d_active"):
        assert same(out["compiled"][key], out["numpy"][key]), key
    assert np.isfinite(plain["energy"]) and np.all(np.isfinite(out["numpy"]["force"]))
    # the same fold pressed beyond the wall: the energy is infinite
    Y = X.copy()
    Y[3:] -= [0, 1.5 * (a_w - depth), 0]
    for kind in ("numpy", "compiled"):
        r, *_ = wall_state(kind)
        deep = r.k.evaluate(*evaluation_args(r, Y, pairs), tangent=False, report=False)
        assert deep["depth"] > a_w and deep["energy"] == np.inf


def test_the_reports_line_force_clips_the_depth_at_the_laws_deepest():
    """With the wall the report's line force takes the depth at most the law's deepest couple's
    (c["depth"]: a report point may lie deeper than any of the law's points, where the barrier
    would be larger or infinite): with a clip that binds (half the deepest) the compiled pass
    (the C law's a_max) and the numpy path give the same force to round-off, and a force that
    differs from the unclipped one."""
    from rodsnes.contact import potential_compiled
    assert potential_compiled.available(), "the compiled potential kernel is not built"
    force = {}
    for kind in ("numpy", "compiled"):
        rod, X, pairs, depth = wall_state(kind)
        out = rod.k.evaluate(*evaluation_args(rod, X, pairs), tangent=False, report=False)
        c = out["_near"]
        x_own, no = out["_inputs"][1], len(out["_inputs"][0])
        full = rod.k._report_force(c, x_own, no)
        c["depth"] = 0.5 * depth
        force[kind] = rod.k._report_force(c, x_own, no), full
    (num, num_full), (comp, comp_full) = force["numpy"], force["compiled"]
    assert same(comp, num) and same(comp_full, num_full)
    assert np.abs(num - num_full).max() > 1e-3 * np.abs(num_full).max()


@pytest.mark.parametrize("p", [2, 3])
def test_the_couples_see_the_closest_distance_within_the_sampling_error(p):
    """Two straight strands a distance g apart, crossing at angles from parallel to square,
    the crossing anywhere along both elements: the closest couple of the law's points is
    never farther apart than g by more than PotentialKernel.sampling_error, by which the wall
    stands short of the promise (The wall); crossing square at both elements' middles (an
    even number of points: the middle halfway between two) it is that far apart, to 5 %.
    The report (closest-point projections at its points) never sees closer than g."""
    eps, pen, n, nqp = 0.025, 0.03, 8, 16
    h, g = 1.0 / n, 2 * eps * (1 - pen)
    rng = np.random.default_rng(p)
    s = np.linspace(0.0, 1.0, p * n + 1)
    lower = np.stack([s, 0 * s, 0 * s], 1)
    excess = {}
    for angle in (0.0, 0.3, np.pi / 4, np.pi / 2):
        for at in [(0.0, 0.0)] + [tuple(rng.uniform(-0.5, 0.5, 2)) for _ in range(3)]:
            xc = 0.5 + (0.5 + at[0]) * h                    # in the lower strand's element 4
            t = s - (0.5 + (0.5 + at[1]) * h)               # ... the upper's element 4
            upper = np.stack([xc + t * np.cos(angle), t * np.sin(angle), g + 0 * s], 1)[::-1]
            link = lower[-1] + np.linspace(0, 1, p + 1)[1:-1, None] * (upper[0] - lower[-1])
            X = np.concatenate([lower, link, upper])        # element n links the strands
            rod = potential_rod(X, p, False, (2 * n + 1) * h, eps, 1e6, penetration=pen,
                                nqp=nqp)
            pairs = rod.pairs(X)
            pairs = pairs[((pairs[:, 0] < n) & (pairs[:, 1] > n))
                          | ((pairs[:, 0] > n) & (pairs[:, 1] < n))]
            out = rod.k.evaluate(*evaluation_args(rod, X, pairs), tangent=False, report=True)
            assert out["gap"].max() <= 2 * eps - g + 1e-15
            excess[angle, at] = (2 * eps - g) - out["depth"]
    bound = rod.k.sampling_error()
    assert max(excess.values()) <= bound
    assert excess[np.pi / 2, (0.0, 0.0)] == pytest.approx(bound, rel=0.05)
