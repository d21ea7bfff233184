"""Self-contact term (rodsnes.contact): gap, closest point, residual, tangent, search (serial, numpy)."""
import numpy as np
import pytest
from scipy.optimize import brentq

from rodsnes.contact import search
from rodsnes.contact.monomials import monomials
from rodsnes.contact.projection import ContactKernel, default_exclusion, default_penalty
from rodsnes.model import fe

EPS = 0.1


# ------------------------------------------------------------------------------------------
# helpers: a whole rod evaluated as "own = all elements"
# ------------------------------------------------------------------------------------------
class Rod:
    def __init__(self, X, p, closed, L, eps=EPS, mu=1.0, delta=None, nqc=None, reach=None):
        self.p, self.closed, self.L, self.eps = p, closed, float(L), eps
        nn = len(X)
        self.nelem = nn // p if closed else (nn - 1) // p
        assert (self.nelem * p == nn) if closed else (self.nelem * p + 1 == nn)
        self.nn = nn
        self.h = self.L / self.nelem
        self.delta = default_exclusion(eps) if delta is None else delta
        self.reach = 2 * eps + 0.05 if reach is None else reach
        self.ids = np.arange(self.nelem)
        self.conn = search.element_node_ids(self.ids, p, self.nelem, closed)
        self.k = ContactKernel(p, nqc or p + 1, eps, mu, self.delta, self.L, self.nelem, closed)

    def pairs(self, X):
        c, r = search.element_bounds(X[self.conn])
        return search.candidate_pairs(self.ids, c, r, self.ids, c, r, self.reach, self.L, self.h,
                                 self.closed, self.delta)

    def eval(self, X, pairs, tangent=False):
        xe = X[self.conn]
        return self.k.evaluate(self.ids, xe, self.ids, xe, pairs, tangent=tangent)

    def energy(self, X, pairs):
        return self.eval(X, pairs)["energy"]

    def active_nodes(self, out):
        """Nodes (nact, 2(p+1)) of [slave element, master element] of every active point."""
        a = out["active"]
        return np.concatenate([self.conn[a[:, 0]], self.conn[a[:, 1]]], axis=1)

    def residual(self, X, pairs):
        return self.assemble(self.eval(X, pairs))

    def assemble(self, out):
        """The nodal residual (nn, 3) of an evaluation."""
        R = np.zeros((self.nn, 3))
        np.add.at(R, self.active_nodes(out), out["vec"])
        return R

    def slaves_reaching(self, pairs, node):
        """The slave elements whose contact term can put a force on ``node``: those holding it
        and those with a candidate master holding it (each slave element's term depends on its
        own nodes and its candidates' only: the split of the slaves over ranks)."""
        hold = np.flatnonzero((self.conn == node).any(axis=1))
        return np.union1d(hold, pairs[np.isin(pairs[:, 1], hold), 0])

    def residual_at(self, X, pairs, node):
        """residual(X, pairs)[node] from the slave elements that reach the node alone (a
        fraction of the evaluation on a long rod)."""
        mine = pairs[np.isin(pairs[:, 0], self.slaves_reaching(pairs, node))]
        return self.residual(X, mine)[node]

    def tangent(self, X, pairs, switch_points=True):
        """The assembled tangent (3 nn, 3 nn) and the evaluation; without ``switch_points``
        the switch-point terms (out["switch_mat"]) are left out."""
        out = self.eval(X, pairs, tangent=True)
        nodes = self.active_nodes(out)
        dof = (3 * nodes[:, :, None] + np.arange(3)).reshape(len(out["active"]), -1)
        K = np.zeros((3 * self.nn, 3 * self.nn))
        np.add.at(K, (dof[:, :, None], dof[:, None, :]), out["mat"])
        sw = out["switch"]
        if len(sw) and switch_points:
            nodes = np.concatenate([self.conn[sw[:, 0]], self.conn[sw[:, 1]], self.conn[sw[:, 2]]],
                                   axis=1)
            dof = (3 * nodes[:, :, None] + np.arange(3)).reshape(len(sw), -1)
            np.add.at(K, (dof[:, :, None], dof[:, None, :]), out["switch_mat"])
        return K, out


def polyline(waypoints, nel, p):
    """Nodes along straight pieces waypoints[i] -> waypoints[i+1] with nel[i] elements each."""
    W = np.asarray(waypoints, dtype=float)
    pts = [W[:1]]
    for i, n in enumerate(nel):
        t = np.linspace(0.0, 1.0, n * p + 1)[1:, None]
        pts.append(W[i] + t * (W[i + 1] - W[i]))
    return np.concatenate(pts)


def helix(p, nelem, a=0.3, pitch=0.17, turns=2.2, noise=0.0, seed=0):
    b = pitch / (2 * np.pi)
    w = np.hypot(a, b)
    Lg = turns * 2 * np.pi * w
    s = np.linspace(0.0, Lg, nelem * p + 1)
    ph = s / w
    X = np.stack([a * np.cos(ph), a * np.sin(ph), b * ph], axis=1)
    X += noise * np.random.default_rng(seed).standard_normal(X.shape)
    return X, Lg


def hairpin(p, nelem, leg=1.0, rho=0.075):
    """Two legs (along -x) at distance 2 rho joined by a half circle of radius rho, by arclength."""
    Lg = 2 * leg + np.pi * rho
    s = np.linspace(0.0, Lg, nelem * p + 1)
    X = np.zeros((len(s), 3))
    a = s < leg
    X[a] = np.stack([s[a], 0 * s[a], 0 * s[a]], axis=1)
    c = (s >= leg) & (s <= leg + np.pi * rho)
    th = (s[c] - leg) / rho
    X[c] = np.stack([leg + rho * np.sin(th), rho * (1 - np.cos(th)), 0 * th], axis=1)
    b = s > leg + np.pi * rho
    X[b] = np.stack([leg - (s[b] - leg - np.pi * rho), 2 * rho + 0 * s[b], 0 * s[b]], axis=1)
    return X, Lg


def rel(a, b):
    return np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300)


def check_gradient(rod, X, pairs, step, tol=1e-6, ndir=3, seed=0, maxrows=40):
    """Residual vs central differences of the energy: every dof of (up to maxrows random) nodes
    in contact, plus random directions over all nodes (which would expose a missing node)."""
    R = rod.residual(X, pairs)
    rows = np.flatnonzero(np.abs(R).sum(axis=1) > 0)
    assert len(rows) > 0
    if len(rows) > maxrows:
        rows = np.sort(np.random.default_rng(seed).choice(rows, maxrows, replace=False))
    E = lambda Y: rod.energy(Y, pairs)
    G = np.zeros_like(R)
    for i in rows:
        for j in range(3):
            Xp, Xm = X.copy(), X.copy()
            Xp[i, j] += step
            Xm[i, j] -= step
            G[i, j] = (E(Xp) - E(Xm)) / (2 * step)
    err = rel(R[rows], G[rows])
    rng = np.random.default_rng(seed)
    for _ in range(ndir):
        v = rng.standard_normal(X.shape)
        dE = (E(X + step * v) - E(X - step * v)) / (2 * step)
        err = max(err, abs(dE - np.sum(R * v)) / (np.linalg.norm(R) * np.linalg.norm(v)))
    assert err < tol, err
    return err


def check_tangent(rod, X, pairs, step, tol=1e-5, ndir=3, seed=0, maxcols=None):
    """Tangent vs central differences of the residual: the columns of the dofs in contact and
    random directions over all nodes."""
    K, out = rod.tangent(X, pairs)
    cols = np.flatnonzero(np.abs(K).sum(axis=0) > 0)
    rng = np.random.default_rng(seed)
    if maxcols is not None and len(cols) > maxcols:
        cols = np.sort(rng.choice(cols, maxcols, replace=False))
    KF = fd_jacobian(rod, X, pairs, step, cols)
    err = rel(K[:, cols], KF)
    for _ in range(ndir):
        v = rng.standard_normal(X.shape)
        dR = (rod.residual(X + step * v, pairs) - rod.residual(X - step * v, pairs)) / (2 * step)
        err = max(err, rel(K @ v.ravel(), dR.ravel()))
    assert err < tol, err
    return K, out


# ------------------------------------------------------------------------------------------
# 0. parameters
# ------------------------------------------------------------------------------------------
def test_default_parameters():
    assert default_exclusion(0.2) == pytest.approx(0.2 * np.pi)
    EI, eps = 3.0, 0.05
    mu = default_penalty(EI, eps)
    assert mu == pytest.approx(5 * EI / eps ** 4)
    # the tight-contact line force 0.2 EI/eps^3 (measured on the plectoneme), carried as 2 mu d
    # in a two-sided contact (see test_gap_parallel_segments), penetrates 1 % of the diameter
    assert (0.2 * EI / eps ** 3) / (2 * mu) == pytest.approx(0.01 * 2 * eps)
    assert default_penalty(EI, eps, penetration=0.005) == pytest.approx(2 * mu)


# ------------------------------------------------------------------------------------------
# 1. gap values
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("p", [1, 2, 3, 4])
def test_gap_parallel_segments(p):
    a = 0.15
    W = [(-1, 0, 0), (1, 0, 0), (1, 0, 5), (2, a, 5), (2, a, 0), (-2, a, 0)]
    nel = [8, 4, 2, 4, 16]
    X = polyline(W, nel, p)
    rod = Rod(X, p, False, L=0.25 * sum(nel), reach=0.5)
    out = rod.eval(X, rod.pairs(X))
    gA = out["gap"][:8]
    assert np.allclose(gA, 2 * EPS - a, atol=1e-12, rtol=0)
    # B points over A (|x| < 0.8) see A at distance a too, with sbar at the foot of the normal
    xq = rod.k.xq
    eB = np.arange(sum(nel) - 16, sum(nel))
    xB = (2 - 0.25 * (eB[:, None] - eB[0] + (xq[None, :] + 1) / 2))
    m = np.abs(xB) < 0.8
    assert np.allclose(out["gap"][eB][m], 2 * EPS - a, atol=1e-12)
    assert np.allclose(out["sbar"][eB][m], xB[m] + 1.0, atol=1e-12)  # A: s = x + 1
    # line force of a two-sided contact = 2 mu d: the vertex node of A at x = 0 (elements 3, 4,
    # uniformly penetrated, both as slave and as master) carries 2 mu d * (int N_end ds) * 2
    mu = rod.k.mu
    R = rod.residual(X, rod.pairs(X))
    xg, wg = fe.gauss_legendre(p + 1)
    int_end = 0.25 / 2 * np.sum(wg * fe.lagrange(p, xg)[0][:, 0])
    assert R[4 * p] == pytest.approx([0.0, 2 * mu * (2 * EPS - a) * 2 * int_end, 0.0], abs=1e-14)


@pytest.mark.parametrize("p", [1, 3])
def test_gap_crossing_segments(p):
    c = 0.12
    W = [(-1, 0, 0), (1, 0, 0), (1, -3, -3), (0, -3, c), (0, 3, c)]
    nel = [8, 6, 4, 24]
    X = polyline(W, nel, p)
    rod = Rod(X, p, False, L=0.25 * sum(nel), reach=1.0)
    out = rod.eval(X, rod.pairs(X))
    xq = -1 + 0.25 * (np.arange(8)[:, None] + (rod.k.xq[None, :] + 1) / 2)
    m = np.hypot(xq, c) < 0.3     # beyond, A's own points at arclength delta are closer
    assert np.allclose(out["gap"][:8][m], 2 * EPS - np.hypot(xq[m], c), atol=1e-12, rtol=0)
    # closest point on B is its crossing point (0, 0, c): B starts at s = 18*0.25, y = -3
    assert np.allclose(out["sbar"][:8][m], 18 * 0.25 + 3.0, atol=1e-12)
    act = out["active"]
    assert len(act) > 0 and set(act[:, 0]) >= {3, 4}


def circle(p, nelem, R):
    n = nelem * p
    ph = 2 * np.pi * np.arange(n) / n
    return np.stack([R * np.cos(ph), R * np.sin(ph), 0 * ph], axis=1), 2 * np.pi * R


@pytest.mark.parametrize("p", [1, 2, 3, 4])
def test_circle_no_false_contact(p):
    for R, nelem in [(1.1 * EPS, 24), (2 * EPS, 24), (10 * EPS, 80)]:
        X, L = circle(p, nelem, R)
        rod = Rod(X, p, True, L)
        out = rod.eval(X, rod.pairs(X))
        g = out["gap"]
        assert np.all(g <= 0.0), (R, g.max())
        if R < 3 * EPS:   # every point has candidates; by symmetry all elements see the same gap
            assert np.all(np.isfinite(g))
            assert np.allclose(g, g[:1], atol=1e-12)   # incl. the elements across the wrap
            # the closest admissible point of a circle of radius R sits at arclength delta
            ds = np.abs(out["sbar"] - rod.k.slave_arclength(rod.ids))
            ds = np.minimum(ds, L - ds)
            assert np.allclose(ds, rod.delta, atol=1e-9)
    # the check is sharp: a too small exclusion or a non-periodic exclusion creates contact
    X, L = circle(p, 24, 1.1 * EPS)
    small = Rod(X, p, True, L, delta=0.5 * np.pi * EPS)
    assert small.eval(X, small.pairs(X))["gap"].max() > 0.3 * EPS
    Xo = np.concatenate([X, X[:1]])        # same curve as an open rod: the two ends touch
    ro = Rod(Xo, p, False, L)
    go = ro.eval(Xo, ro.pairs(Xo))["gap"]
    assert go[0, 0] > 1.5 * EPS and go[-1, -1] > 1.5 * EPS


@pytest.mark.parametrize("p", [1, 2, 3, 4])
def test_closed_wraparound_stadium(p):
    """Closed stadium; node 0 in the middle of a straight: contacts across the wrap are found,
    and the exclusion is periodic (the neighbours across s = 0 = L are excluded)."""
    a = 0.15
    rho = a / 2
    # arclength-parametrised nodes: straight y=0 from x=0 to 1, cap, straight y=a back to -1,
    # cap, straight y=0 from -1 to 0.  Elements: 4 + 1 + 8 + 1 + 4 (h = 0.25 on the straights)
    nel = [4, 1, 8, 1, 4]
    pieces = []
    t = lambda n: np.linspace(0, 1, n * p + 1)[:-1]
    u = t(4); pieces.append(np.stack([u, 0 * u, 0 * u], 1))
    th = np.pi * t(1); pieces.append(np.stack([1 + rho * np.sin(th), rho * (1 - np.cos(th)), 0 * th], 1))
    u = t(8); pieces.append(np.stack([1 - 2 * u, a + 0 * u, 0 * u], 1))
    th = np.pi * t(1); pieces.append(np.stack([-1 - rho * np.sin(th), rho * (1 + np.cos(th)), 0 * th], 1))
    u = t(4); pieces.append(np.stack([-1 + u, 0 * u, 0 * u], 1))
    X = np.concatenate(pieces)
    nelem = sum(nel)
    L = 0.25 * nelem
    rod = Rod(X, p, True, L)
    out = rod.eval(X, rod.pairs(X))
    s = rod.k.slave_arclength(rod.ids)
    for e in (0, nelem - 1):            # the two elements touching node 0
        x = s[e] if e == 0 else s[e] - L
        assert np.allclose(out["gap"][e], 2 * EPS - a, atol=1e-12)
        assert np.allclose(out["sbar"][e], 2.25 - x, atol=1e-12)
    # and from the other side: points of the y = a straight over x in (-0.25, 0.25) find sbar
    # across the wrap (near s = 0 or s = L)
    e_mid = [8, 9]
    sb = out["sbar"][e_mid]
    xb = 1 - (s[e_mid] - 1.25)
    assert np.allclose(np.mod(sb, L), np.mod(xb, L), atol=1e-12)


# ------------------------------------------------------------------------------------------
# 2. closest point vs brute force
# ------------------------------------------------------------------------------------------
def brute_closest(P, xm, p):
    """Dense sampling + root of phi' between the neighbours of the best sample."""
    xs = np.linspace(-1, 1, 20001)
    N = fe.lagrange(p, xs)[0]
    pts = N @ xm
    j = int(np.argmin(np.linalg.norm(pts - P, axis=1)))

    def dphi(x):
        N, dN, _ = fe.lagrange(p, [x])
        return float((N @ xm - P)[0] @ (dN @ xm)[0])

    lo, hi = xs[max(j - 1, 0)], xs[min(j + 1, len(xs) - 1)]
    cands = [lo, hi, xs[j]]
    if dphi(lo) < 0 < dphi(hi):
        cands.append(brentq(dphi, lo, hi, xtol=1e-15))
    d = [np.linalg.norm(fe.lagrange(p, [x])[0] @ xm - P) for x in cands]
    k = int(np.argmin(d))
    return cands[k], d[k]


def test_closest_point_matches_brute_force_p3():
    p, nelem = 3, 10
    rng = np.random.default_rng(7)
    nchecked = ninterior = nend = 0
    for trial in range(12):
        th = np.deg2rad([-110, -37, 37, 110]) + 0.15 * rng.standard_normal(4)
        xm = np.stack([np.cos(th), np.sin(th), 0.2 * rng.standard_normal(4)], axis=1)
        xm += 0.08 * rng.standard_normal(xm.shape)
        ctr = np.array([0.0, 0.0, 0.0]) if trial % 2 == 0 else np.array([1.5, 0.0, 0.0])
        xs = ctr + 0.35 * rng.standard_normal((4, 3))
        k = ContactKernel(p, 5, eps=1.0, mu=1.0, delta=0.3, L=10.0, nelem=nelem, closed=False)
        out = k.evaluate([0], xs[None], [nelem - 1], xm[None], [[0, nelem - 1]])
        rq = k.Nq @ xs
        for q in range(5):
            xi_b, dist_b = brute_closest(rq[q], xm, p)
            xi_k = (out["sbar"][0, q] - (nelem - 1)) * 2 - 1
            assert abs((2.0 - out["gap"][0, q]) - dist_b) < 1e-10 and abs(xi_k - xi_b) < 1e-10, \
                (trial, q, xi_k, xi_b)
            nchecked += 1
            ninterior += abs(xi_b) < 1 - 1e-9
            nend += abs(xi_b) >= 1 - 1e-9
    assert nchecked == 60 and ninterior > 20 and nend > 3


def test_projection_finds_global_minimum_of_two_basins():
    """A quartic element with two nearly equal local minima of the distance; for x0 near -0.015
    the best of the start samples lies in the wrong basin (a single-start Newton fails)."""
    p = 4
    nod = fe.reference_nodes(p)
    xm = np.stack([0.5 * nod, 2.0 * (nod + 0.75) ** 2 * (nod - 0.70) ** 2, 0 * nod], axis=1)
    k = ContactKernel(p, 3, eps=1.0, mu=1.0, delta=0.1, L=10.0, nelem=10, closed=False)
    A = np.einsum("ka,ad->kd", k.C, xm)
    x0 = np.linspace(-0.05, 0.05, 41)
    P = np.stack([x0, -0.3 + 0 * x0, 0 * x0], axis=1)
    xi, f = k.closest_point.project(P, np.repeat(A[None], len(P), axis=0), -np.ones(len(P)),
                                    np.ones(len(P)))
    for i in range(len(P)):
        xb, db = brute_closest(P[i], xm, p)
        assert abs(xi[i] - xb) < 1e-10 and abs(np.sqrt(2 * f[i]) - db) < 1e-12, (x0[i], xi[i], xb)
    assert np.any(xi < 0) and np.any(xi > 0)


def test_projection_respects_exclusion_inside_element():
    """h > 2 delta: a point's own element is a candidate, minus (s - delta, s + delta)."""
    p = 2
    X = np.array([[0, 0, 0], [0.5, 0.3, 0], [1.0, 0.0, 0], [1.5, 0.3, 0], [2.0, 0, 0.0]])
    rod = Rod(X, p, False, L=2.0, eps=1.0, delta=0.2, reach=5.0)
    pairs = rod.pairs(X)
    assert [0, 0] in pairs.tolist() and [1, 1] in pairs.tolist()
    out = rod.eval(X, pairs)
    s = rod.k.slave_arclength(rod.ids)
    ds = np.abs(out["sbar"] - s)
    assert np.all(ds >= 0.2 - 1e-12)
    assert np.any(np.abs(ds - 0.2) < 1e-12)    # (nearly straight) closest at the exclusion edge


# ------------------------------------------------------------------------------------------
# 3. residual = d energy ; 4. tangent = d residual
# ------------------------------------------------------------------------------------------
def helix_config(p, seed):
    nelem = 24
    X, L = helix(p, nelem, noise=0.012, seed=seed)
    return Rod(X, p, False, L), X


@pytest.mark.parametrize("p", [1, 2, pytest.param(3, marks=pytest.mark.slow),
                               pytest.param(4, marks=pytest.mark.slow)])
def test_residual_is_energy_gradient_helix(p):
    rod, X = helix_config(p, seed=p)
    pairs = rod.pairs(X)
    out = rod.eval(X, pairs)
    assert len(out["active"]) > 20 and out["gap"].max() > 0.02
    check_gradient(rod, X, pairs, 1e-6)


def end_configs(p):
    """Configurations whose closest points sit on slot bounds."""
    cfgs = []
    # (a) rod end: A along y crossing just beyond the free end of B (B ends at x = -0.05)
    c = 0.1
    W = [(0, -1, 0), (0, 1, 0), (-1, 3, -2), (-1, 0, c), (-0.05, 0, c)]
    nel = [8, 6, 6, 4]
    X = polyline(W, nel, p)
    cfgs.append(("rod end", Rod(X, p, False, L=0.25 * sum(nel), reach=0.5), X))
    # (b) a corner node (element end inside the rod): the apex of a V, seen from above
    W = [(-1, -1, 0), (0, 0, 0), (1, -1, 0), (2, 2, 2), (-1, 0.1, 0.05), (1, 0.1, 0.05)]
    nel = [6, 6, 6, 6, 8]
    X = polyline(W, nel, p)
    cfgs.append(("corner", Rod(X, p, False, L=0.25 * sum(nel), reach=0.5), X))
    # (c) exclusion boundary: a hairpin of radius < eps
    X, L = hairpin(p, 22)
    cfgs.append(("exclusion", Rod(X, p, False, L), X))
    return cfgs


@pytest.mark.parametrize("p", [1] + [pytest.param(p, marks=pytest.mark.slow) for p in (2, 3, 4)])
def test_residual_and_tangent_with_closest_point_on_bounds(p):
    rng = np.random.default_rng(10 + p)
    for name, rod, X in end_configs(p):
        X = X + 0.003 * rng.standard_normal(X.shape)
        pairs = rod.pairs(X)
        out = rod.eval(X, pairs)
        assert np.any(~out["interior"]), name
        if name == "rod end":   # closest point = last node of the rod, xi = +1 of the last element
            sel = ~out["interior"] & (out["active"][:, 1] == rod.nelem - 1)
            assert np.any(sel) and np.all(out["xi"][sel] == 1.0)
        if name == "corner":    # the apex node, shared by elements 5 and 6, is counted once
            sel = ~out["interior"] & np.isin(out["active"][:, 1], [5, 6])
            assert np.any(sel)
            key = out["active"][sel, 0] * 10 + out["qp"][sel]
            assert len(np.unique(key)) == len(key)
        # (steps of 1e-7: the tight hairpin has large third derivatives, FD error ~ step^2)
        check_gradient(rod, X, pairs, 1e-7, maxrows=25)
        check_tangent(rod, X, pairs, 1e-7, maxcols=75)


def fd_jacobian(rod, X, pairs, step, cols=None):
    n = 3 * len(X)
    cols = range(n) if cols is None else cols
    out = []
    for c in cols:
        Xp, Xm = X.copy(), X.copy()
        Xp.flat[c] += step
        Xm.flat[c] -= step
        out.append(((rod.residual(Xp, pairs) - rod.residual(Xm, pairs)) / (2 * step)).ravel())
    return np.array(out).T


@pytest.mark.parametrize("p", [1, 2, 3, pytest.param(4, marks=pytest.mark.slow)])
def test_tangent_is_residual_derivative_helix(p):
    rod, X = helix_config(p, seed=20 + p)
    pairs = rod.pairs(X)
    K, out = check_tangent(rod, X, pairs, 1e-6, maxcols=90, ndir=4, seed=p)
    assert np.allclose(K, K.T, atol=1e-12 * np.abs(K).max())
    if p >= 2:
        assert out["interior"].mean() > 0.7     # curved elements, mostly interior closest points
    else:
        assert np.any(~out["interior"])         # polygon: some closest points at vertices


def test_tangent_formula_of_the_docstring_and_slide_sign():
    """Rebuild the tangent from the documented formula: it matches finite differences; without
    the closest-point motion term, or with the slides' sign |r'|^2 + r''.(r(s) - r(sbar)) in its
    denominator, it does not."""
    p = 3
    rod, X = helix_config(p, seed=5)
    pairs = rod.pairs(X)
    K, out = rod.tangent(X, pairs)
    k = rod.k
    v = np.random.default_rng(0).standard_normal(X.shape)
    dR = ((rod.residual(X + 1e-6 * v, pairs) - rod.residual(X - 1e-6 * v, pairs)) / 2e-6).ravel()
    nodes = rod.active_nodes(out)
    dof = (3 * nodes[:, :, None] + np.arange(3)).reshape(len(nodes), -1)
    eps, mu = k.eps, k.mu
    Nm, dNm, d2Nm = fe.lagrange(p, out["xi"])
    xm = X[rod.conn[out["active"][:, 1]]]
    t, r2 = np.einsum("na,nad->nd", dNm, xm), np.einsum("na,nad->nd", d2Nm, xm)
    Nt = np.concatenate([k.Nq[out["qp"]], -Nm], axis=1)
    nu = out["normal"]
    dd = out["d_active"]         # d of each active point (gap holds the deepest strand's)
    g = 2 * eps - dd
    D = g[:, None] * nu
    wJmu = k.wq[out["qp"]] * k.h / 2 * mu
    A3 = (2 * eps / g)[:, None, None] * nu[:, :, None] * nu[:, None, :] - (dd / g)[:, None, None] * np.eye(3)
    Kpp = np.einsum("na,nb,nij->naibj", Nt, Nt, A3 * wJmu[:, None, None])
    c = np.concatenate([-k.Nq[out["qp"]][:, :, None] * t[:, None, :],
                        Nm[:, :, None] * t[:, None, :] - dNm[:, :, None] * D[:, None, :]], axis=1)
    cc = np.einsum("nai,nbj->naibj", c, c)
    inter = out["interior"].astype(float)
    assert inter.mean() > 0.7

    def assemble(mat):
        M = np.zeros_like(K)
        np.add.at(M, (dof[:, :, None], dof[:, None, :]), mat.reshape(len(nodes), dof.shape[1], -1))
        return M

    def with_k(kk):
        fac = inter * wJmu * dd / (g * kk)
        return assemble(Kpp + fac[:, None, None, None, None] * cc)

    tt = np.einsum("nd,nd->n", t, t)
    K_doc = with_k(tt - np.einsum("nd,nd->n", D, r2))
    K_slide = with_k(tt + np.einsum("nd,nd->n", D, r2))
    K_fixed = assemble(Kpp)
    assert rel(K_doc, K) < 1e-12
    assert rel(K @ v.ravel(), dR) < 1e-5
    assert rel(K_slide @ v.ravel(), dR) > 1e-3
    assert rel(K_fixed @ v.ravel(), dR) > 1e-3


@pytest.mark.parametrize("p", [2, 3])
def test_tangent_near_contact_edge(p):
    """A flat parabola just touching a straight piece: 0 < d ~ 1e-4 eps at the apex only."""
    rng = np.random.default_rng(3 + p)
    gap0 = 2 * EPS - 1.5e-4
    nA = 8
    xa = np.linspace(-1, 1, nA * p + 1)
    A = np.stack([xa, -0.02 * xa ** 2, 0 * xa], axis=1)
    W = [A[-1], A[-1] + (0, 0, 2), (2, gap0, 2), (2, gap0, 0), (-2, gap0, 0)]
    Bpart = polyline(W, [4, 4, 4, 16], p)
    X = np.concatenate([A, Bpart[1:]])
    rod = Rod(X, p, False, L=0.25 * (nA + 28), reach=0.5)
    X = X + 1e-7 * rng.standard_normal(X.shape)
    pairs = rod.pairs(X)
    out = rod.eval(X, pairs)
    d = out["gap"][out["gap"] > 0]
    assert len(d) >= 2 and d.max() < 2e-4, d
    check_gradient(rod, X, pairs, 1e-8)
    K, out = check_tangent(rod, X, pairs, 1e-8)
    assert out["interior"].all()


# ------------------------------------------------------------------------------------------
# 5. search
# ------------------------------------------------------------------------------------------
def random_coil(p, nelem, step, seed):
    rng = np.random.default_rng(seed)
    pts = [np.zeros(3)]
    d = rng.standard_normal(3)
    for _ in range(nelem):
        d = d / np.linalg.norm(d) + 0.9 * rng.standard_normal(3)
        x = pts[-1] + step * d / np.linalg.norm(d)
        if np.linalg.norm(x) > 0.6:          # stay in a ball: a dense coil
            d = -x + 0.3 * rng.standard_normal(3)
            x = pts[-1] + step * d / np.linalg.norm(d)
        pts.append(x)
    P = np.array(pts)
    X = [P[0]]
    for e in range(nelem):
        t = np.linspace(0, 1, p + 1)[1:, None]
        seg = P[e] + t * (P[e + 1] - P[e])
        seg[:-1] += 0.3 * step * rng.standard_normal((p - 1, 3))   # curved, overshooting elements
        X.extend(seg)
    return np.array(X)


@pytest.mark.parametrize("closed", [False, True])
def test_candidate_pairs_equal_brute_force(closed):
    p, nelem, step = 2, 500, 0.1
    X = random_coil(p, nelem, step, seed=1 + closed)
    if closed:
        X = X[:-1]
    L = nelem * step
    eps = 0.05
    rod = Rod(X, p, closed, L, eps=eps, reach=2 * eps + 0.02)
    c, r = search.element_bounds(X[rod.conn])
    got = search.candidate_pairs(rod.ids, c, r, rod.ids, c, r, rod.reach, L, rod.h, closed,
                                 rod.delta)
    # brute force: all pairs sphere test + sampled arclength test
    dist = np.linalg.norm(c[:, None] - c[None], axis=2)
    ok = dist <= rod.reach + r[:, None] + r[None]
    ea, eb = np.nonzero(ok)
    ts = np.linspace(0, 1, 9) * rod.h   # max of |s - sigma| (periodic: up to L/2) over the box
    sa = ea[:, None, None] * rod.h + ts[None, :, None]
    sb = eb[:, None, None] * rod.h + ts[None, None, :]
    ds = np.abs(sa - sb)
    if closed:
        ds = np.minimum(ds, L - ds)
    keep = ds.reshape(len(ea), -1).max(axis=1) >= rod.delta
    ref = np.stack([ea[keep], eb[keep]], axis=1)
    assert len(ref) > 5 * nelem               # a dense coil: many genuine candidates
    assert got.shape == ref.shape and np.array_equal(got, ref)
    # own subset vs all (what one rank does)
    own = rod.ids[rod.ids % 3 == 0]
    sub = search.candidate_pairs(own, c[own], r[own], rod.ids, c, r, rod.reach, L, rod.h, closed,
                                 rod.delta)
    assert np.array_equal(sub, ref[np.isin(ref[:, 0], own)])


@pytest.mark.parametrize("p", [1, 2, 3, 4])
def test_element_bounds_contain_curve(p):
    rng = np.random.default_rng(p)
    x = rng.standard_normal((200, p + 1, 3))
    x[:, :, 0] += 3 * np.linspace(-1, 1, p + 1)           # wiggly elements with overshoot
    c, r = search.element_bounds(x)
    xs = np.linspace(-1, 1, 5001)
    pts = np.einsum("ma,ead->emd", fe.lagrange(p, xs)[0], x)
    far = np.linalg.norm(pts - c[:, None], axis=2).max(axis=1)
    assert np.all(far <= r)
    assert np.all(r <= 1.05 * far + 1e-12)               # and not wastefully large
    if p >= 3:   # the curve does leave the nodes' sphere: the padding is needed
        rn = np.linalg.norm(x - c[:, None], axis=2).max(axis=1)
        assert np.any(far > rn * 1.01)


@pytest.mark.parametrize("p", [1, 2, 3, 4])
def test_element_capsules_contain_curve(p):
    """Every point of an element lies within rho of its chord (element_capsules), rho from the
    Bernstein coefficients of the deviation (wiggly random elements); on a rod's element, an
    arc bent by up to 0.5 rad, rho is within the control polygon's overshoot of the largest
    deviation (a parabola's: 2 for p = 2, 4/3 for p >= 3, 1.36 at 0.5 rad; the sphere's
    radius is h/2)."""
    rng = np.random.default_rng(10 + p)
    x = rng.standard_normal((200, p + 1, 3))
    x[:, :, 0] += 3 * np.linspace(-1, 1, p + 1)
    a, b, rho = search.element_capsules(x)
    xs = np.linspace(-1, 1, 2001)
    pts = np.einsum("ma,ead->emd", fe.lagrange(p, xs)[0], x)
    t = (xs + 1) / 2
    chord = a[:, None] * (1 - t)[None, :, None] + b[:, None] * t[None, :, None]
    dev = np.linalg.norm(pts - chord, axis=2).max(axis=1)
    assert np.all(dev <= rho + 1e-12)
    if p == 1:
        assert np.all(rho == 0)
        return
    th = np.linspace(-1, 1, p + 1)[None, :] * np.linspace(0.05, 0.5, 20)[:, None]   # arcs
    arc = np.stack([np.sin(th), 1 - np.cos(th), 0 * th], axis=2)
    a, b, rho = search.element_capsules(arc)
    pts = np.einsum("ma,ead->emd", fe.lagrange(p, xs)[0], arc)
    chord = a[:, None] * (1 - t)[None, :, None] + b[:, None] * t[None, :, None]
    dev = np.linalg.norm(pts - chord, axis=2).max(axis=1)
    assert np.all(dev <= rho + 1e-15) and np.all(rho <= (2.0 if p == 2 else 1.4) * dev)


def test_segment_distance_against_sampling():
    """segment_distance against the minimum over a fine sampling of the first segment of the
    exact distance to the second, for random, parallel, collinear, crossing and degenerate
    (point) segments."""
    rng = np.random.default_rng(3)
    n = 400
    p1, q1, p2, q2 = (rng.standard_normal((n, 3)) for _ in range(4))
    q2[:50] = p2[:50] + 0.7 * (q1[:50] - p1[:50])           # parallel
    p2[50:80] = p1[50:80] + 2.0 * (q1[50:80] - p1[50:80])     # collinear, apart
    q2[50:80] = p1[50:80] + 3.0 * (q1[50:80] - p1[50:80])
    q1[80:90] = p1[80:90]                                      # a point
    mid = 0.5 * (p1[90:120] + q1[90:120])                      # crossing at the middles
    d = rng.standard_normal((30, 3))
    p2[90:120], q2[90:120] = mid - d, mid + d
    got = search.segment_distance(p1, q1, p2, q2)
    t = np.linspace(0, 1, 801)
    A = p1[:, None] + t[None, :, None] * (q1 - p1)[:, None]
    # distance from each sample of the first segment to the second (its closest point: the
    # projection clipped to the segment)
    u = q2 - p2
    uu = np.einsum("nd,nd->n", u, u)
    tB = np.einsum("nsd,nd->ns", A - p2[:, None], u) / np.where(uu > 0, uu, 1.0)[:, None]
    B = p2[:, None] + np.clip(tB, 0.0, 1.0)[..., None] * u[:, None]
    ref = np.linalg.norm(A - B, axis=2).min(axis=1)
    assert np.all(got <= ref + 1e-12)                          # a lower bound of the sampled ...
    h = np.linalg.norm(q1 - p1, axis=1) / 800                  # distance is 1-Lipschitz along A
    assert np.all(ref - got <= h / 2 + 1e-12)                  # ... to half the sampling's spacing
    assert np.all(got[90:120] < 1e-12)


@pytest.mark.parametrize("p", [1, 2, 3, 4, 7])
def test_search_kernel_equals_numpy(p):
    """The compiled search geometry (search_compiled, used by search.element_bounds and
    segment_distance wherever it is built) equals the numpy forms to round-off: the bounds of
    wiggly elements (the padding of p >= 2 included), the segment distances of random,
    parallel, degenerate (point) and crossing segments; a node not finite gives NaN bounds."""
    from rodsnes.contact import search_compiled
    assert search_compiled.available(), "rodsnes.contact._search_kernel is not built: make install"
    rng = np.random.default_rng(20 + p)
    x = rng.standard_normal((300, p + 1, 3))
    x[:, :, 0] += 3 * np.linspace(-1, 1, p + 1)
    c, r = search.element_bounds(x)
    dxi = 2.0 / (search._NSAMP_BOUNDS - 1)
    c0, r0 = search._element_bounds_numpy(x, (dxi ** 2 / 8.0) * 1.05 * search._lambda2(p)
                                           if p >= 2 else 0.0)
    assert np.abs(c - c0).max() <= 1e-14 * np.abs(c0).max()
    assert np.abs(r - r0).max() <= 1e-14 * r0.max()
    x[7, 1, 2] = np.nan
    c, r = search.element_bounds(x)
    assert np.isnan(r[7]) and np.isnan(c[7]).all() and np.isfinite(r[8:]).all()
    p1, q1, p2, q2 = (rng.standard_normal((500, 3)) for _ in range(4))
    q2[:50] = p2[:50] + 0.7 * (q1[:50] - p1[:50])           # parallel
    q1[50:60] = p1[50:60]                                      # a point
    q2[55:65] = p2[55:65]                                      # a point (and two points)
    mid = 0.5 * (p1[70:90] + q1[70:90])                        # crossing
    p2[70:90], q2[70:90] = mid - 0.3, mid + 0.3
    got, ref = search.segment_distance(p1, q1, p2, q2), search._segment_distance_numpy(p1, q1, p2, q2)
    assert np.abs(got - ref).max() <= 1e-14 * ref.max()
    assert np.all(got[70:90] < 1e-12)
    assert search.segment_distance(*(np.zeros((0, 3)),) * 4).shape == (0,)


@pytest.mark.parametrize("closed", [False, True])
def test_capsule_test_keeps_every_pair_within_reach(closed):
    """capsules_within: on a dense random coil, every candidate pair with a couple of sampled
    points closer than reach passes."""
    p, nelem, step = 3, 200, 0.1
    X = random_coil(p, nelem, step, seed=7)
    if closed:
        X = X[:-1]
    eps = 0.05
    rod = Rod(X, p, closed, nelem * step, eps=eps, reach=2 * eps + 0.05)
    pairs = rod.pairs(X)
    xe = X[rod.conn]
    caps = search.element_capsules(xe)
    keep = search.capsules_within([v[pairs[:, 0]] for v in caps], [v[pairs[:, 1]] for v in caps],
                             2 * eps)
    xs = np.einsum("ma,ead->emd", fe.lagrange(p, np.linspace(-1, 1, 41))[0], xe)
    dmin = np.linalg.norm(xs[pairs[:, 0]][:, :, None] - xs[pairs[:, 1]][:, None], axis=3)
    close = dmin.min(axis=(1, 2)) < 2 * eps
    assert close.sum() > nelem and np.all(keep[close])


@pytest.mark.parametrize("segments", [False, True])
def test_tangent_made_later_is_the_tangent_made_at_once(segments):
    """ContactKernel.evaluate without its tangent keeps what add_tangent needs: the tangent
    and switch terms it makes later are those of the evaluation with tangent, bit for bit, and
    the residual is the same with or without (the noisy cubic helix: switch points)."""
    p = 3
    rod, X = helix_config(p, seed=41)
    k = ContactKernel(p, p + 1, rod.eps, 1.0, rod.delta, rod.L, rod.nelem, False,
                        segments=segments)
    pairs = rod.pairs(X)
    args = (rod.ids, X[rod.conn], rod.ids, X[rod.conn], pairs)
    full = k.evaluate(*args, tangent=True)
    alone = k.evaluate(*args, tangent=False)
    assert alone["mat"] is None and len(full["active"]) > 0
    assert alone["energy"] == full["energy"] and np.array_equal(alone["vec"], full["vec"])
    k.add_tangent(alone)
    for key in ("mat", "switch", "switch_mat"):
        assert np.array_equal(alone[key], full[key]), key
    assert len(full["switch"]) > 0 if segments else True


# ------------------------------------------------------------------------------------------
# 6. invariance, action = reaction; partitioned evaluation = serial
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("p", [1, 3])
def test_rigid_motion_invariance_and_action_reaction(p):
    rod, X = helix_config(p, seed=30 + p)
    pairs = rod.pairs(X)
    out = rod.eval(X, pairs)
    Q, _ = np.linalg.qr(np.random.default_rng(1).standard_normal((3, 3)))
    Q *= np.sign(np.linalg.det(Q))
    Y = X @ Q.T + np.array([3.0, -2.0, 7.0])
    out2 = rod.eval(Y, rod.pairs(Y))
    assert out["energy"] > 0
    assert abs(out2["energy"] - out["energy"]) < 1e-12 * out["energy"]
    assert np.allclose(out2["gap"], out["gap"], atol=1e-13)
    R = rod.residual(X, pairs)
    scale = np.abs(R).sum()
    assert np.linalg.norm(R.sum(axis=0)) < 1e-13 * scale                 # total force
    assert np.linalg.norm(np.cross(X, R).sum(axis=0)) < 1e-13 * scale    # total moment
    # each contact pair is action = reaction on its own
    v = out["vec"]
    assert np.abs(v.sum(axis=1)).max() < 1e-15 * np.abs(v).max() * 10


def test_partitioned_evaluation_equals_serial():
    p = 3
    rod, X = helix_config(p, seed=41)
    pairs = rod.pairs(X)
    ref_E = rod.energy(X, pairs)
    ref_R = rod.residual(X, pairs)
    ref_K, _ = rod.tangent(X, pairs)
    c, r = search.element_bounds(X[rod.conn])
    E, R, K = 0.0, np.zeros_like(ref_R), np.zeros_like(ref_K)
    for part in (rod.ids[rod.ids < 9], rod.ids[(rod.ids >= 9) & (rod.ids < 17)], rod.ids[rod.ids >= 17]):
        pr = search.candidate_pairs(part, c[part], r[part], rod.ids, c, r, rod.reach, rod.L, rod.h,
                               False, rod.delta)
        other = np.unique(pr[:, 1])
        out = rod.k.evaluate(part, X[rod.conn[part]], other, X[rod.conn[other]], pr, tangent=True)
        E += out["energy"]
        nodes = np.concatenate([rod.conn[out["active"][:, 0]], rod.conn[out["active"][:, 1]]], axis=1)
        np.add.at(R, nodes, out["vec"])
        dof = (3 * nodes[:, :, None] + np.arange(3)).reshape(len(nodes), -1)
        np.add.at(K, (dof[:, :, None], dof[:, None, :]), out["mat"])
    assert abs(E - ref_E) < 1e-14 * ref_E
    assert np.allclose(R, ref_R, atol=1e-15 * np.abs(ref_R).max(), rtol=1e-13)
    assert np.allclose(K, ref_K, atol=1e-13 * np.abs(ref_K).max())


def test_projection_finds_a_minimum_next_to_a_maximum():
    """A slave point near a centre of curvature of the master sees a flat distance valley whose
    minima can sit next to maxima, between the projection's samples.  Where phi may be
    non-convex on the slot (its Bernstein bound), ClosestPoint.project also takes every real
    root of the polynomial phi' (companion eigenvalues): on the noisy helix (p = 3), slave
    element 15 near xi = 0.274 against master element 0, the sampled search alone misses the
    interior minimum at 16 of 201 points (it returns the node, 3e-6 farther: the gap jumps),
    the full projection at none, against a brute-force search on 40001 points."""
    p = 3
    X, L = helix(p, 24, pitch=0.19, turns=1.6, noise=0.002)
    rod = Rod(X, p, False, L)
    k = rod.k
    xe = X[rod.conn]
    xs = np.linspace(0.27, 0.28, 201)
    P = (monomials(p, xs)[0] @ k.C) @ xe[15]
    A = np.repeat(np.einsum("ka,ad->kd", k.C, xe[0])[None], len(xs), axis=0)
    lo, hi = -np.ones(len(xs)), np.ones(len(xs))
    tt = np.linspace(-1, 1, 40001)
    r = (monomials(p, tt)[0] @ k.C) @ xe[0]
    brute = 0.5 * (((r[None, :, :] - P[:, None, :]) ** 2).sum(axis=2)).min(axis=1)
    cp = k.closest_point
    _, f_sampled = cp.sampled_newton(P, A, lo, hi)
    cp.nonconvex = 0
    _, f = cp.project(P, A, lo, hi)
    assert np.sum(f_sampled > brute + 1e-13) > 5          # the case is a hard one
    assert np.all(f <= brute + 1e-13) and cp.nonconvex > 0
    # and the polynomial roots alone agree with the full projection everywhere
    _, f_roots = cp.stationary_minimum(P, A, lo, hi)
    assert np.allclose(f_roots, f, rtol=1e-12, atol=1e-16)
