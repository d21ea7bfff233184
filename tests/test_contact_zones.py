"""Contact-zone integration (ContactKernel(segments=True), the default of -contact).

The penalty integral (mu/2) int <d>^2 ds is taken over the zones where d > 0, found on every
slave element near contact by sampling, refining the maxima of d and finding the roots of d,
with the Gauss points mapped onto each zone.  A contact narrower than the Gauss-point spacing
(two strands crossing at an angle, a sliding free end) is then integrated accurately and its
energy varies smoothly as the contact slides along the rod, which Gauss points at fixed places
cannot do.  The residual and tangent keep their pointwise formulas: the integrand and its first
derivative vanish at the zone ends, so moving ends add nothing (Leibniz rule)."""
import numpy as np
import pytest
from scipy.integrate import quad

from rodsnes.contact.closest_point import ClosestPoint
from rodsnes.contact.search import co_master_pairs
from rodsnes.model import fe

from test_contact_math import EPS, Rod, check_gradient, check_tangent, polyline

NEL = 8                 # elements per strand of length 2


def crossing(p, alpha, g0, shift=0.0, nqc=None, mu=1.0, segments=True):
    """Two straight strands of length 2 (NEL elements of length h = 2/NEL each) crossing at
    angle alpha at distance g0: A along x through the origin, B along (cos a, sin a, 0) through
    (shift, 0, g0); joined far away by a bridge of 48 elements (along x, up, across, down).  The
    kernel's arclength is parametric (h per element), exact on the strands."""
    u = np.array([np.cos(alpha), np.sin(alpha), 0.0])
    c = np.array([shift, 0.0, g0])
    W = [(-1.0, 0, 0), (1.0, 0, 0), (3.0, 0, 0), (3.0, 0, 4.0), tuple(c + u + (0, 0, 4.0)),
         tuple(c + u), tuple(c - u)]
    nel = [NEL, 8, 16, 8, 16, NEL]
    X = polyline(W, nel, p)
    nelem = sum(nel)
    L = nelem * 2.0 / NEL
    rod = Rod(X, p, False, L, mu=mu, nqc=nqc, reach=0.5)
    rod.k = type(rod.k)(p, nqc or p + 1, EPS, mu, rod.delta, L, nelem, False, segments=segments)
    return rod, X


def exact_energy(alpha, g0, mu=1.0):
    """Both strands are slave in turn: 2 x (mu/2) int <2 eps - sqrt(g0^2 + s^2 sin^2 a)>^2 ds."""
    sa = np.sin(alpha)
    w = np.sqrt((2 * EPS) ** 2 - g0 ** 2) / sa
    f = lambda s: (2 * EPS - np.sqrt(g0 ** 2 + (s * sa) ** 2)) ** 2
    return 2 * 0.5 * mu * quad(f, -w, w, epsabs=0, epsrel=1e-13)[0]


@pytest.mark.parametrize("p", [1, 2, 3])
@pytest.mark.parametrize("alpha", [np.pi / 2, np.pi / 6])
def test_crossing_energy_exact(p, alpha):
    """A crossing whose contact zone (width ~ 2 sqrt(4 eps d)/sin a ~ 0.03) is a fraction of a
    Gauss spacing: the zone integral matches the exact integral to 1e-8; fixed Gauss points are
    off by tens of percent (or miss it)."""
    g0 = 2 * EPS * (1 - 1e-3)
    E = exact_energy(alpha, g0)
    for shift in (0.0, 0.0371, 0.113):
        rod, X = crossing(p, alpha, g0, shift)
        out = rod.eval(X, rod.pairs(X))
        assert 2 <= out["zones"] <= 4                  # one zone per strand (split at a node)
        assert abs(out["energy"] - E) < 1e-8 * E, (shift, out["energy"], E)
    rod, X = crossing(p, alpha, g0, 0.0371, segments=False)
    Eg = rod.eval(X, rod.pairs(X))["energy"]
    assert abs(Eg - E) > 1e-3 * E


@pytest.mark.parametrize("p", [2, pytest.param(3, marks=pytest.mark.slow)])
def test_crossing_slides_smoothly(p):
    """Sliding the crossing along the strands (straight strands: the exact energy does not
    change): zone integration keeps energy and total force constant to 1e-9, Gauss points make
    them jump."""
    g0 = 2 * EPS * (1 - 2e-3)
    shifts = np.linspace(0.0, 0.25, 26)                # one element length
    Ez, Eg, Fz = [], [], []
    for t in shifts:
        rod, X = crossing(p, np.pi / 3, g0, t)
        out = rod.eval(X, rod.pairs(X))
        Ez.append(out["energy"])
        Fz.append(out["total_force"])
        rod, X = crossing(p, np.pi / 3, g0, t, segments=False)
        Eg.append(rod.eval(X, rod.pairs(X))["energy"])
    Ez, Eg, Fz = map(np.array, (Ez, Eg, Fz))
    assert np.ptp(Ez) < 1e-9 * Ez.mean() and np.ptp(Fz) < 1e-9 * Fz.mean()
    assert np.ptp(Eg) > 0.3 * Eg.mean()


def bend(X, p, amp):
    """Smooth (quadratic) bends of the two strands, exact in every element of order >= 2:
    A sags along z, B along y (generic, non-symmetric contact)."""
    Y = X.copy()
    n = NEL * p + 1
    sA = X[:n, 0]
    Y[:n, 2] += amp * (sA + 0.3) ** 2
    tB = np.linspace(1.0, -1.0, n)
    Y[-n:, 1] -= 0.7 * amp * (tB - 0.2) ** 2
    return Y


@pytest.mark.slow
@pytest.mark.parametrize("p", [1, 2, 3, 4])
def test_zone_tangent_crossing(p):
    """Residual = gradient of the zone-integrated energy, tangent = derivative of the residual
    (central differences), at a crossing of smoothly bent strands (straight for p = 1) in a
    generic position.  (Where a master element boundary has a kink, d(s) has one inside the zone
    and the zone quadrature is less exact: residual and tangent then agree with the differences
    only to that quadrature error, ~1e-5 for the C0 kinks of a rod with noisy nodes.)"""
    rod, X = crossing(p, 1.1, 2 * EPS * (1 - 5e-3), 0.0517)
    if p > 1:
        X = bend(X, p, 0.01)
    pairs = rod.pairs(X)
    check_gradient(rod, X, pairs, 1e-7, tol=1e-6)
    K, out = check_tangent(rod, X, pairs, 1e-8, tol=1e-5)     # the residual varies fast: small step
    assert np.all(out["qp"] == -1) and len(out["active"]) >= 4


@pytest.mark.slow
@pytest.mark.parametrize("p", [2, 3])
def test_zone_line_contact(p):
    """A line contact (helix turns pressed together over their whole length): zone integration
    agrees with 20 points per zone, and residual and tangent are consistent."""
    from test_contact_math import helix
    X, L = helix(p, 24, turns=1.6, noise=0.0)      # every point touches at most one turn
    rod = Rod(X, p, False, L, nqc=p + 1)
    rod.k = type(rod.k)(p, p + 1, rod.eps, rod.k.mu, rod.delta, L, rod.nelem, False, segments=True)
    pairs = rod.pairs(X)
    out = rod.eval(X, pairs)
    fine = type(rod.k)(p, p + 1, rod.eps, rod.k.mu, rod.delta, L, rod.nelem, False, segments=True)
    fine.zones.nqz = 20
    fine.zones.xz, fine.zones.wz = fe.gauss_legendre(20)
    xe = X[rod.conn]
    Ef = fine.evaluate(rod.ids, xe, rod.ids, xe, pairs, tangent=False)["energy"]
    # every kink of d(s) (master nodes, the rod's end) is a cut: the pieces are smooth
    assert out["zones"] > 10 and abs(out["energy"] - Ef) < 1e-10 * Ef
    check_gradient(rod, X, pairs, 1e-7, tol=1e-6, maxrows=6)
    # measured 1.3e-7 (p = 3) and 1.3e-5 (p = 2), the same for steps 1e-7 to 1e-9
    check_tangent(rod, X, pairs, 1e-8, tol={2: 3e-5, 3: 1e-6}[p], maxcols=24)


def test_kind_of_a_closest_point_on_a_node_is_the_same_from_both_elements():
    """The kind of closest point (ClosestPoint.kind) names a master node, not an element end:
    a point stuck at node k has kind 2 k whichever of the two elements sharing it won the tie
    (on a ring, node nelem is node 0); strictly inside element m it is 2 m + 1; on an exclusion
    boundary inside element m, -2 - m; without a closest point, -1."""
    k = ClosestPoint(2, EPS, 0.3, 1.0, 4, True)
    ctx = {"pool_ids": np.array([0, 1, 2, 3])}
    cl = {"m": np.array([0, 1, 3, 0, 2, 2, -1]),
          "xi_m": np.array([1.0, -1.0, 1.0, -1.0, 0.3, 0.4, 0.0]),
          "interior": np.array([False, False, False, False, True, False, False])}
    assert list(k.kind(ctx, cl)) == [2, 2, 0, 0, 5, -4, -1]


@pytest.mark.slow
@pytest.mark.parametrize("p", [2, 3])
def test_zone_residual_is_continuous_at_c0_kinks(p):
    """Helix turns pressed together, nodes moved at random (noise 2 % of the contact radius):
    the centreline has C0 kinks at its nodes, closest points stick to them from the convex side
    over short stretches, and there the two elements sharing the node tie.  The residual must
    stay continuous: R(X + h V) - R(X) - h K V, relative to h K V, may not grow as h falls (a
    jump of the residual makes it grow like 1/h).  (It does not vanish either: a middle turn
    touches the turns above and below, its closest point switches between them, and the tangent
    leaves out the motion of that switch point, module docstring.)  Before the kinds were
    canonical, the tie flipped the label, misplaced a cut, and the residual jumped: relative
    errors of 10-600 at h = 1e-7."""
    from test_contact_math import helix
    X, L = helix(p, 24, pitch=0.19, turns=1.6, noise=0.002)
    rod = Rod(X, p, False, L, nqc=p + 1)
    rod.k = type(rod.k)(p, p + 1, rod.eps, rod.k.mu, rod.delta, L, rod.nelem, False, segments=True)
    pairs = rod.pairs(X)
    K, out = rod.tangent(X, pairs)
    R0 = rod.residual(X, pairs).ravel()
    rng = np.random.default_rng(3)
    for _ in range(8):
        V = rng.normal(size=X.shape)
        KV = K @ V.ravel()
        err = []
        for h in (1e-6, 1e-9):
            R1 = rod.residual(X + h * V, pairs).ravel()
            err.append(np.linalg.norm(R1 - R0 - h * KV) / np.linalg.norm(h * KV))
        assert err[1] < 2.0 * err[0] + 1e-3 and err[1] < 1.0, err


def noisy_helix(p):
    from test_contact_math import helix
    X, L = helix(p, 24, pitch=0.19, turns=1.6, noise=0.002)
    rod = Rod(X, p, False, L, nqc=p + 1)
    rod.k = type(rod.k)(p, p + 1, rod.eps, rod.k.mu, rod.delta, L, rod.nelem, False, segments=True)
    return rod, X


def directional_error(rod, X, pairs, step=1e-8, ndir=2, seed=1, switch_points=True):
    """max over random directions v of |K v - (R(X + h v) - R(X - h v)) / 2h| / |K v| (K
    without its switch-point terms unless ``switch_points``)."""
    K, out = rod.tangent(X, pairs, switch_points)
    rng = np.random.default_rng(seed)
    err = 0.0
    for _ in range(ndir):
        v = rng.standard_normal(X.shape)
        dR = (rod.residual(X + step * v, pairs) - rod.residual(X - step * v, pairs)) / (2 * step)
        KV = K @ v.ravel()
        err = max(err, np.linalg.norm(KV - dR.ravel()) / np.linalg.norm(KV))
    return err


@pytest.mark.slow
@pytest.mark.parametrize("p", [2, 3])
def test_switch_points_complete_the_tangent(p):
    """Where the closest point jumps (here across the concave side of a C0 kink, from the end
    of one master element to the start of the next, or from inside an element to its end node),
    the cut between the two pieces moves with the nodes and the integrand differs on its two
    sides: the tangent gets J mu d phi_x phi_x^T / phi_xi, phi = g_A - g_B
    (docs/contact.md, section 3).  With it, the tangent of the noisy helix agrees with central
    differences of the residual (measured 1e-6 for p = 2, falling like the step, and 1e-5 for
    p = 3); without it, to 7e-2.  For p = 3 the pieces must also be graded toward their cuts
    (ContactZones.cut_levels, ``grade``): without, 4-9e-2."""
    rod, X = noisy_helix(p)
    pairs = rod.pairs(X)
    K, out = check_tangent(rod, X, pairs, 1e-8, tol={2: 1e-5, 3: 1e-4}[p], maxcols=30)
    sw = out["switch"]
    assert len(sw) >= 5
    # the jumps here go across a node (between neighbouring master elements, or from inside an
    # element to its end node)
    assert np.all(np.abs(sw[:, 1] - sw[:, 2]) <= 1) and np.any(sw[:, 1] != sw[:, 2])
    assert np.all(np.einsum("nii->n", out["switch_mat"]) > 0)      # J mu d / phi_xi > 0
    assert directional_error(rod, X, pairs, switch_points=False) > 1e-2
    if p == 3:
        rod.k.zones.grade = 0
        assert directional_error(rod, X, pairs) > 1e-2


def test_co_master_pairs():
    """Two masters of one slave element are coupled when their bounding spheres come within
    the reach; masters of different slaves, or far apart, are not."""
    pairs = np.array([[0, 5], [0, 7], [0, 9], [1, 7], [1, 3]])
    cen = np.zeros((10, 3))
    cen[:, 0] = np.arange(10)
    rad = np.full(10, 0.5)
    assert co_master_pairs(pairs, cen, rad, 1.5).tolist() == [[5, 7], [7, 9]]
    assert co_master_pairs(pairs, cen, rad, 10.0).tolist() == [[3, 7], [5, 7], [5, 9], [7, 9]]
    assert co_master_pairs(np.zeros((0, 2), dtype=int), cen, rad, 1.0).shape == (0, 2)


# ------------------------------------------------------------------------------------------
# zone detection: exclusion bounds, gaps between samples, racing closest points
# ------------------------------------------------------------------------------------------
def tight_arc(p, nelem=10, length=0.5, k0=5.0, a=0.5):
    """A planar arc of curvature k0 (1 + a s), radius below the contact radius (eps = 0.1):
    with a short exclusion every point touches its own neighbourhood, and the closest
    admissible point is the exclusion bound s + delta (the more curved side, turning < pi)."""
    s = np.linspace(0.0, length, 20001)
    th = k0 * (s + 0.5 * a * s ** 2)
    ds = np.diff(s)
    xy = np.zeros((len(s), 2))
    xy[1:, 0] = np.cumsum(0.5 * (np.cos(th[1:]) + np.cos(th[:-1])) * ds)
    xy[1:, 1] = np.cumsum(0.5 * (np.sin(th[1:]) + np.sin(th[:-1])) * ds)
    sn = np.linspace(0.0, length, nelem * p + 1)
    X = np.zeros((len(sn), 3))
    X[:, 0], X[:, 1] = np.interp(sn, s, xy[:, 0]), np.interp(sn, s, xy[:, 1])
    return X, length


def record_cuts(k):
    """Wrap the zone segmentation of kernel k (``ContactZones.split``) to record the cuts (own
    element id, xi) of the evaluations since (one per strand, ``ContactKernel.evaluate``)."""
    rec = {"cuts": (np.zeros(0, dtype=np.int64), np.zeros(0))}
    orig = k.zones.split

    def split(ctx, oz, za, zb):
        r = orig(ctx, oz, za, zb)
        e, xc = rec["cuts"]
        rec["cuts"] = (np.r_[e, ctx["own_ids"][r[3][0]]], np.r_[xc, r[3][1]])
        return r
    k.zones.split = split
    return rec


@pytest.mark.parametrize("p", [2, pytest.param(3, marks=pytest.mark.slow)])
def test_cuts_where_an_exclusion_bound_crosses_a_node(p):
    """The closest point sits on the exclusion bound s + delta (a rod bent tighter than its
    radius, as at the tip of a plectoneme's end loop); the integrand has a kink where the
    bound crosses a master node, at s = k h - delta: with delta = 2.5 h, the middle of every
    slave element.  The kind of such a closest point (-2 - m) is negative; the bisection that
    locates a change of kind once read a negative target as "not kind ...", so both cuts stayed
    at the samples next to the change (xi = -+1/9) and the kink was inside a piece (on the
    plectoneme: residual noise 5e-8 along a Newton direction, 20 x the tolerance)."""
    X, L = tight_arc(p)
    h = L / 10
    rod = Rod(X, p, False, L, delta=2.5 * h, nqc=p + 1)
    rod.k = type(rod.k)(p, p + 1, rod.eps, rod.k.mu, rod.delta, L, rod.nelem, False,
                        segments=True)
    rec = record_cuts(rod.k)
    pairs = rod.pairs(X)
    out = rod.eval(X, pairs)
    e, xc = rec["cuts"]
    assert out["zones"] == 10 and len(out["switch"]) == 0
    assert np.array_equal(np.sort(e), np.arange(10)) and np.all(np.abs(xc) < 1e-12)
    check_tangent(rod, X, pairs, 1e-7, tol=1e-6, maxcols=12)


def two_passes(p, g0=0.176, w=0.21, gapc=0.078125):
    """A straight strand along x (elements of length 0.25) and, at height g0, two passes across
    it at x1, x2 = gapc -+ w/2 (joined by a U far away, 0.21 apart: not touching each other).
    Along the strand d > 0 in two zones of half-width sqrt(4 eps^2 - g0^2) = 0.095, and the
    gap between them, 0.02 wide, lies between two samples of d (spacing 0.03125) that are
    both in contact."""
    x1, x2 = gapc - w / 2, gapc + w / 2
    W = [(-1, 0, 0), (1, 0, 0), (1, -1.4, 0), (x1, -1.4, g0), (x1, 1.1, g0), (x2, 1.1, g0),
         (x2, -1.15, g0)]
    rod, X, _ = waypoint_rod(W, p)
    return rod, X


def waypoint_rod(W, p, h=0.25):
    """A rod along the straight pieces between waypoints W, elements of about h (a whole number
    per piece), a zone-integrating kernel with mu = 1 whose arclength is parametric (h per
    element: exact on the pieces that are whole multiples of h).  Returns (rod, X, elements per
    piece)."""
    seg = np.linalg.norm(np.diff(np.array(W, dtype=float), axis=0), axis=1)
    nel = [max(1, int(round(s / h))) for s in seg]
    X = polyline(W, nel, p)
    L = sum(nel) * h
    rod = Rod(X, p, False, L, reach=0.3)
    rod.k = type(rod.k)(p, p + 1, EPS, 1.0, rod.delta, L, sum(nel), False, segments=True)
    return rod, X, nel


@pytest.mark.slow
@pytest.mark.parametrize("p", [2, 3, 4])
def test_a_gap_between_two_samples_splits_the_zone(p):
    """The discrete minima of d in contact are refined (root of d'), so a dip below 0 between
    two samples in contact ends one zone and starts the next.  Before, for p = 3, the two
    crossings were one zone with two roots of d inside it: 5 zones instead of 6, tangent vs
    differences 4.4e-4, residual vs differences 7e-7 (on the plectoneme's end loop: residual
    off by 1.7e-4).  Energy: each crossing at right angles gives 2 x (mu/2) int <2 eps -
    sqrt(s^2 + g0^2)>^2 ds (exact_energy)."""
    rod, X = two_passes(p)
    pairs = rod.pairs(X)
    out = rod.eval(X, pairs)
    assert out["zones"] == 6
    E = 2 * exact_energy(np.pi / 2, 0.176)
    assert abs(out["energy"] - E) < 2e-9 * E
    check_gradient(rod, X, pairs, 1e-7, tol=1e-7, maxrows=8)
    check_tangent(rod, X, pairs, 1e-7, tol=1e-6, maxcols=12)


def plectoneme_end_loop():
    """Node positions of the plectoneme (cases/plectoneme.opts: L = 1, 60 cubic elements,
    eps = 0.025, delta = pi eps) at 8.57 turns, during a Newton solve: the end loop, where
    closest points sit on exclusion bounds, d dips below 0 between samples, and at two jumps
    the closest points race (|dxibar/dxi| = 463 and 94)."""
    import os
    X = np.load(os.path.join(os.path.dirname(__file__), "data", "plectoneme_end_loop.npy"))
    eps, mu = 0.025, 1.5239568869908707e7
    rod = Rod(X, 3, False, 1.0, eps=eps, mu=mu, delta=np.pi * eps, nqc=5, reach=0.125)
    rod.k = type(rod.k)(3, 5, eps, mu, rod.delta, 1.0, rod.nelem, False, segments=True)
    return rod, X


@pytest.mark.slow
def test_the_plectoneme_end_loop_tangent():
    """Tangent vs central differences of the residual on the real end loop: 4e-6 (measured), against
    1.4e-4 with 10 levels of grading at every cut (before ``ContactZones.cut_levels`` added log2 of
    the racing rate) and 3e-2 without the switch-point terms.  In the Newton solve this was the
    difference between failing at 8.57 turns and steps of 2e-3 of the load in 11-28 iterations."""
    rod, X = plectoneme_end_loop()
    pairs = rod.pairs(X)
    rec = record_cuts(rod.k)
    K0, out = rod.tangent(X, pairs)
    # element 32: the exclusion bound crosses node 84 at xi = 0.4248 (a cut there, none at
    # a sample), and d dips below 0 in [0.7530, 0.9162]: two zones
    e, xc = rec["cuts"]
    assert np.any((e == 32) & (np.abs(xc - 0.424778) < 1e-6))
    assert not np.any((e == 32) & (np.abs(xc - 1 / 3) < 1e-6))
    assert len(out["switch"]) == 4
    directions = [np.random.default_rng(s).standard_normal(X.shape) * 1e-4 for s in (0, 1)]

    def error(K=None):
        if K is None:
            K, _ = rod.tangent(X, pairs)
        err = 0.0
        for v in directions:
            dR = (rod.residual(X + 1e-3 * v, pairs) - rod.residual(X - 1e-3 * v, pairs)) / 2e-3
            KV = K @ v.ravel()
            err = max(err, np.linalg.norm(KV - dR.ravel()) / np.linalg.norm(KV))
        return err
    assert error(K0) < 2e-5
    zones = rod.k.zones
    zones.cut_levels = lambda ctx, o, *sides: np.full(len(o), zones.grade, dtype=np.int64)
    assert error() > 5e-5


@pytest.mark.slow
def test_several_changes_of_closest_point_between_two_samples_are_all_cut():
    """A slave element where the closest point goes from a master node to the inside of the
    element before it and then jumps to another strand, all within one sample spacing (the
    plectoneme relaxing at 9.415 turns, tests/data/plectoneme_9.41_relaxing.h5: slave element
    0, the start of the rod, against elements 42-43 and 55).  Every change must be cut, so that
    no Gauss point straddles one: with the middle cut missed, a Gauss point's closest point
    jumped by 0.22 in xi as a node moved by 1e-7 and the residual had steps of 0.05 (8 x its
    smooth change per 1e-7) that kept Levenberg-Marquardt 7.6e-2 short of the equilibrium.
    Checks: the kind of closest point is the same at all Gauss points of every piece, and the
    contact residual at the node that moves is smooth along 21 moves of 1e-7."""
    import os
    from rodsnes.model.partition import NDOF
    from conftest import build_run
    data = os.path.join(os.path.dirname(__file__), "data", "plectoneme_9.41_relaxing.h5")
    import shutil
    import tempfile
    src = tempfile.mkdtemp(prefix="rodsnes_relaxing_")
    shutil.copy(data, os.path.join(src, "result.h5"))
    run = build_run("plectoneme", restart=src, stability=True,
                    load_path="newton",
                    contact_model="projection")
    c = run.contact
    K = c.kernel
    # the slides' single closest point over all strands (evaluate_strand on every candidate),
    # not the per-strand sum: the three changes lie on two strands, and only the single
    # minimum over both has to cut all three
    K.evaluate = K.evaluate_strand
    seen = []
    quadrature = K.zones.quadrature

    def spy(ctx, gap):
        out = quadrature(ctx, gap)
        seen.append((ctx, out))
        return out
    K.zones.quadrature = spy
    r, q = run.problem.state.local_config()
    r = np.array(r)
    c.evaluate(r, tangent=False)
    pieces = 0
    for ctx, (o_q, xi_q, _, _, _) in seen:
        cl = K.closest_point.find(ctx, o_q, xi_q)
        kind = K.closest_point.kind(ctx, cl).reshape(-1, K.zones.nqz)
        pieces += len(kind)
        # arclength of the closest points: within a piece it may change kind only where it
        # moves on continuously (a node crossed, within the cuts' 1e-13), not jump
        sbar = ((ctx["pool_ids"][cl["m"]] + 0.5 * (cl["xi_m"] + 1.0)) * K.h).reshape(-1,
                                                                                    K.zones.nqz)
        jump = np.abs(np.diff(sbar, axis=1)).max(axis=1)
        mixed = np.flatnonzero(np.any(kind != kind[:, :1], axis=1) & (jump > 1e-6))
        assert mixed.size == 0, f"{mixed.size} pieces straddle a jump of the closest point"
    assert pieces > 1000
    force = []
    for t in np.arange(21) * 1e-7:
        rp = r.copy()
        rp[128, 0] += t
        F = np.zeros((len(r), NDOF))
        c.add_residual(run.problem.lam, rp, q, F)
        force.append(F[128, 0])
    step = np.diff(force)
    assert np.all(np.abs(np.diff(step)) < 0.05 * np.abs(step).max()), step


@pytest.mark.slow
def test_a_kink_minimum_that_takes_over_between_two_samples_is_cut():
    """The plectoneme at 9.72 turns, inside a Newton solve (node positions stored): strands in
    line contact, nearly parallel.  For slave element 26 the distance along master element 17
    has its minimum inside (xi = -0.15) and a second one at node 51 (the C0 kink between
    elements 16 and 17); the node's takes over on slave xi in [0.8260, 0.8290], between two
    samples of the zone's kinds (0.2 apart), and no sample saw it: as node 79 moved by 7.15e-8
    that stretch's end crossed a Gauss point, whose force moved from four nodes to one, and the
    contact force at node 51 stepped by 5.5 of 46 (load steps stalled at 9.7188 turns).  The
    runner-up's margin is minimised between samples (``ContactZones.rival_brackets``): the
    stretch gets its two cuts, and the largest step of that force over moves of node 79 in
    [0, 2e-7] (bisected to 2e-16) is 5e-9 (measured; 5.5 without)."""
    import os
    X0 = np.load(os.path.join(os.path.dirname(__file__), "data",
                              "plectoneme_9.72_line_contact.npy"))
    eps, mu = 0.025, 5.754172062186161e7
    rod = Rod(X0, 3, False, 1.0, eps=eps, mu=mu, delta=np.pi * eps, nqc=5, reach=0.125)
    rod.k = type(rod.k)(3, 5, eps, mu, rod.delta, 1.0, rod.nelem, False, segments=True)

    def moved(t):
        X = X0.copy()
        X[79, 1] += t
        return X

    rec = record_cuts(rod.k)
    X = moved(7.1527e-8)
    pairs = rod.pairs(X)
    R = rod.assemble(rod.eval(X, pairs))
    e, xc = rec["cuts"]
    mine = np.sort(xc[e == 26])
    assert np.any(np.abs(mine - 0.82599) < 1e-4) and np.any(np.abs(mine - 0.82895) < 1e-4), mine
    # the force at node 51 from the slave elements that reach it (28 of 60) is the whole
    # residual's there: the bisection evaluates those alone
    assert np.abs(rod.residual_at(X, pairs, 51) - R[51]).max() <= 1e-12 * np.abs(R[51]).max()

    def force(t):
        X = moved(t)
        return rod.residual_at(X, rod.pairs(X), 51)[2]

    a, b, fa, fb = largest_step(force, 0.0, 2e-7)
    assert abs(fb - fa) < 1e-6 * abs(fa), (a, fb - fa)


def largest_step(f, a, b, halvings=30):
    """Bisect [a, b] keeping the half over which f changes more: a jump of f is found to
    (b - a) 2^-halvings.  Returns a, b, f(a), f(b) of the last interval."""
    fa, fb = f(a), f(b)
    for _ in range(halvings):
        m = 0.5 * (a + b)
        fm = f(m)
        if abs(fm - fa) > abs(fb - fm):
            b, fb = m, fm
        else:
            a, fa = m, fm
    return a, b, fa, fb
