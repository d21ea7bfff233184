"""The fast paths of the closest-point contact law against the plain ones they replace: the sampled
Newton projection (ClosestPoint) against the per-problem reference it was rewritten from (Horner
sampling, Newton with its own backtracking loop, one problem set at a time), the bisection of a cut
with several levels per closest-point search (ContactZones.bisect_kind) against one step per search,
and all strands in one pass against strand by strand (evaluate_strand on each strand's pairs, summed
as ContactKernel.evaluate describes)."""
import numpy as np
import pytest

from rodsnes.contact.closest_point import ClosestPoint, phi, phi_derivatives
from rodsnes.contact.monomials import monomials
from rodsnes.contact.search import strand_index
from rodsnes.contact.zones import ContactZones

from test_contact_math import EPS
from test_contact_strands import sandwich
from test_contact_zones import crossing, noisy_helix, plectoneme_end_loop


def sampled_newton_reference(k, P, A, lo, hi):
    """The sampled Newton search of ClosestPoint.project (k), as it was written before the
    batched version (ClosestPoint.sampled_newton): phi = |r(xi) - P|^2 / 2 at 4p+1 samples by Horner,
    Newton from every discrete local minimum with steps of at most one sample spacing, clamped
    to [lo, hi], halved until phi rises by at most 1e-14 phi (a Newton step below 1e-9 always
    taken), converged when a step moves by <= 1e-13; the best start per problem."""
    M, ns, p = len(P), k.nsamp, k.p
    X = lo[:, None] + (hi - lo)[:, None] * np.linspace(0.0, 1.0, ns)[None, :]
    D = np.repeat(A[:, p][:, None, :], ns, axis=1)
    for j in range(p - 1, -1, -1):
        D = D * X[:, :, None] + A[:, j][:, None, :]
    D -= P[:, None, :]
    F = 0.5 * np.einsum("msd,msd->ms", D, D)
    left = np.concatenate([np.full((M, 1), np.inf), F[:, :-1]], axis=1)
    right = np.concatenate([F[:, 1:], np.full((M, 1), np.inf)], axis=1)
    ismin = (F <= left) & (F <= right)
    ismin[:, 1:] &= ~(ismin[:, :-1] & (F[:, 1:] == F[:, :-1]))
    pid, sid = np.nonzero(ismin)
    x, fx = X[pid, sid].copy(), F[pid, sid].copy()
    for i in range(len(x)):
        a, q, l, h = A[pid[i]], P[pid[i]], lo[pid[i]], hi[pid[i]]
        dx = (h - l) / (ns - 1)
        scale = q @ q + np.sum(a * a)
        for _ in range(k.MAXIT):
            f0, g, H = (v[0] for v in phi_derivatives(np.array([x[i]]), a[None], q[None]))
            newton = H > 0.0
            step = float(np.clip(-g / H if newton else -np.sign(g) * dx, -dx, dx))
            tol = 1e-14 * f0 + 1e-30 * scale
            xnew, fnew, done = x[i], f0, False
            for _bt in range(k.MAXBT):
                xt = float(np.clip(x[i] + step, l, h))
                ft = phi(np.array([xt]), a[None], q[None])[0]
                if ft <= f0 + tol or (newton and abs(step) < 1e-9):
                    xnew, fnew, done = xt, ft, True
                    break
                step *= 0.5
            moved = abs(xnew - x[i])
            x[i], fx[i] = xnew, fnew
            if moved <= 1e-13 or not done:
                break
    xi, f = np.empty(M), np.full(M, np.inf)
    for i in range(len(x)):
        if fx[i] < f[pid[i]]:
            xi[pid[i]], f[pid[i]] = x[i], fx[i]
    return xi, f


@pytest.mark.parametrize("p", [1, 2, 3, 4])
def test_sampled_projection_is_the_reference_search(p):
    """Random elements (curved: random monomial coefficients), random points, random slots
    (whole elements, parts, and degenerate slots lo = hi): the batched sampled search returns
    the reference's minimiser and minimum.  Where the reference's search misses the global
    minimum (it only samples), so does the batched one: the same algorithm, not a better one."""
    rng = np.random.default_rng(p)
    k = ClosestPoint(p, eps=0.01, delta=0.05, L=1.0, nelem=10, closed=False)
    M = 400
    A = rng.normal(scale=0.3, size=(M, p + 1, 3))
    P = rng.normal(scale=0.5, size=(M, 3))
    lo, hi = np.sort(rng.uniform(-1.0, 1.0, size=(2, M)), axis=0)
    lo[:100], hi[:100] = -1.0, 1.0
    hi[100:120] = lo[100:120]
    xi_ref, f_ref = sampled_newton_reference(k, P, A, lo, hi)
    xi, f = k.sampled_newton(P, A, lo, hi)
    assert np.all(np.abs(f - f_ref) <= 1e-12 * np.maximum(f_ref, 1e-300) + 1e-300)
    assert np.max(np.abs(xi - xi_ref)) < 1e-12
    # and the full projection (roots where phi may be non-convex) is never worse
    xi2, f2 = k.project(P, A, lo, hi)
    assert np.all(f2 <= f * (1 + 1e-14))


@pytest.mark.parametrize("p", [2, 3, 4])
def test_bounded_slots_and_monotone_slots_keep_the_closest_point(p):
    """Random curved elements, each slave point with 6 slots (next to each other, as ``find``
    passes them): projecting with the Bernstein bound (``project`` with ``point``: slots that
    cannot hold the point's closest point are left out) gives every point the minimum and
    minimiser of projecting every slot; and where the Bernstein coefficients of phi' show phi
    monotone on the slot (``_monotone``), all the roots of phi' (``stationary_minimum`` without
    the mask) give the same ends."""
    rng = np.random.default_rng(10 + p)
    k = ClosestPoint(p, eps=0.01, delta=0.05, L=1.0, nelem=10, closed=False)
    npt, ns = 300, 6
    A = rng.normal(scale=0.3, size=(npt * ns, p + 1, 3))
    P = np.repeat(rng.normal(scale=0.5, size=(npt, 3)), ns, axis=0)
    lo, hi = np.sort(rng.uniform(-1.0, 1.0, size=(2, npt * ns)), axis=0)
    lo[::2], hi[::2] = -1.0, 1.0
    point = np.repeat(np.arange(npt), ns)
    xi_all, f_all = k.project(P, A, lo, hi)
    xi, f = k.project(P, A, lo, hi, point)
    f_all, f, xi_all, xi = (v.reshape(npt, ns) for v in (f_all, f, xi_all, xi))
    best = np.argmin(f_all, axis=1)
    assert np.array_equal(np.argmin(f, axis=1), best)
    rows = np.arange(npt)
    assert np.allclose(f[rows, best], f_all[rows, best], rtol=1e-13, atol=0.0)
    assert np.allclose(xi[rows, best], xi_all[rows, best], rtol=0.0, atol=1e-12)
    assert 0.5 * f.size < np.count_nonzero(np.isinf(f)) < f.size - npt      # bounded away
    Dc = A.copy()
    Dc[:, 0] -= P
    mono = k._monotone(k._taylor(Dc, lo, hi - lo), Dc, np.ones(len(P), dtype=bool))
    assert 0 < np.count_nonzero(mono) < len(mono)
    x_roots, f_roots = k.stationary_minimum(P, A, lo, hi)
    x_ends, f_ends = k.stationary_minimum(P, A, lo, hi, mono)
    assert np.array_equal(x_ends[mono], x_roots[mono]) and np.array_equal(f_ends[mono],
                                                                          f_roots[mono])
    assert np.all((x_ends[mono] == lo[mono]) | (x_ends[mono] == hi[mono]))
    assert np.allclose(f_ends[~mono], f_roots[~mono], rtol=1e-13, atol=0.0)


def test_bisection_several_levels_at_once_is_the_bisection():
    """The cuts of two strands crossing at 60 degrees (the closest point crosses master nodes):
    ``ContactZones.bisect_kind`` with the bisection tree's next levels located in one closest-point search
    returns the cuts and final brackets of one step per search, in fewer searches."""
    rod, X = crossing(3, np.pi / 3, 1.5 * EPS, 0.0371)
    zones, cp = rod.k.zones, rod.k.closest_point
    calls = []
    bisect = zones.bisect_kind

    def spy(*a, **kw):
        calls.append(a)
        return bisect(*a, **kw)
    zones.bisect_kind = spy
    rod.eval(X, rod.pairs(X))
    del zones.bisect_kind
    assert calls and len(calls[0][1]) >= 4                      # 2 cuts, each from both sides

    searches = []
    find = cp.find

    def count(*a, **kw):
        searches.append(len(a[1]))
        return find(*a, **kw)
    cp.find = count
    results = {}
    for points in (1, ContactZones.BISECT_POINTS, 1024):
        zones.BISECT_POINTS = points
        searches.clear()
        results[points] = ([zones.bisect_kind(*a) for a in calls], len(searches))
    del zones.BISECT_POINTS, cp.find
    one, n_one = results[1]
    for points in (ContactZones.BISECT_POINTS, 1024):
        many, n_many = results[points]
        assert n_many < n_one / 2, (points, n_many, n_one)
        for r1, r2 in zip(one, many):
            for v1, v2 in zip(r1, r2):
                assert np.max(np.abs(v1 - v2)) <= 2e-13


@pytest.mark.parametrize("p", [1, 2, 3, 4])
def test_phi_at_several_points_and_its_derivatives_are_the_plain_formulas(p):
    """``phi`` at n points of every problem (x (M, n), as ``stationary_minimum`` takes both slot
    ends) is ``phi`` at each column; ``phi_derivatives`` (one product of the monomials and
    their derivatives with A, one contraction) is |D|^2 / 2, D . r', |r'|^2 + D . r'' of r, r',
    r'' summed one by one."""
    rng = np.random.default_rng(20 + p)
    M = 200
    A = rng.normal(scale=0.3, size=(M, p + 1, 3))
    P = rng.normal(scale=0.5, size=(M, 3))
    x = rng.uniform(-1.0, 1.0, size=(M, 2))
    both = phi(x, A, P)
    assert np.array_equal(both[:, 0], phi(x[:, 0], A, P))
    assert np.array_equal(both[:, 1], phi(x[:, 1], A, P))
    pw, pw1, pw2 = monomials(p, x[:, 0])
    r, r1, r2 = (np.einsum("mk,mkd->md", w, A) for w in (pw, pw1, pw2))
    D = r - P
    plain = (0.5 * np.einsum("md,md->m", D, D), np.einsum("md,md->m", D, r1),
             np.einsum("md,md->m", r1, r1) + np.einsum("md,md->m", D, r2))
    scale = np.einsum("md,md->m", P, P) + np.einsum("mkd,mkd->m", A, A)
    for v, w in zip(phi_derivatives(x[:, 0], A, P), plain):
        assert np.all(np.abs(v - w) <= 1e-14 * scale)


def test_kinds_of_repeated_points_are_searched_once():
    """``ContactZones.kind_at`` (the bisection's test, ``bisect_kind``) searches every distinct
    slave point once and gives every point the kind (``ClosestPoint.kind``) of its own search:
    points of the noisy helix, a third of them repeated."""
    rod, X = noisy_helix(3)
    k = rod.k
    xe = X[rod.conn]
    ctx = k._context(rod.ids, xe, rod.ids, xe, rod.pairs(X))
    rng = np.random.default_rng(5)
    o = rng.integers(0, len(rod.ids), 60)
    xi = rng.uniform(-1.0, 1.0, 60)
    o, xi = np.r_[o, o[::3]], np.r_[xi, xi[::3]]
    searched = []
    find = k.closest_point.find

    def count(*a, **kw):
        searched.append(len(a[1]))
        return find(*a, **kw)
    k.closest_point.find = count
    kinds = k.zones.kind_at(ctx, o, xi)
    del k.closest_point.find
    assert searched == [60]
    plain = k.closest_point.kind(ctx, find(ctx, o, xi))
    assert np.array_equal(kinds, plain) and len(np.unique(plain)) > 5


def strand_by_strand(k, ids, xe, pairs, tangent):
    """ContactKernel.evaluate as it was before all strands shared one pass: evaluate_strand on
    the pairs of each strand (contact.strand_index), the outputs summed (gap: the deepest,
    sbar of the deepest, force summed; per-point arrays concatenated strand by strand; depth:
    the deepest d of the Gauss and zone points)."""
    s = strand_index(pairs, k.nelem, k.closed, int(np.ceil(k.delta / k.h)) + 1)
    outs = [k.evaluate_strand(ids, xe, ids, xe, pairs[s == j], tangent)
            for j in range(int(s.max()) + 1)]
    out = outs[0]
    for o in outs[1:]:
        deeper = o["gap"] > out["gap"]
        out["sbar"] = np.where(deeper, o["sbar"], out["sbar"])
        out["gap"] = np.maximum(out["gap"], o["gap"])
        out["force"] = out["force"] + o["force"]
        for key in ("energy", "total_force", "complementarity", "zones"):
            out[key] += o[key]
        for key in ("active", "vec", "qp", "xi", "xi_slave", "normal", "interior", "d_active",
                    "switch"):
            out[key] = np.concatenate([out[key], o[key]])
        if tangent:
            for key in ("mat", "switch_mat"):
                out[key] = np.concatenate([out[key], o[key]])
        else:
            out["_deferred"] += o["_deferred"]
    out["depth"] = max(float(out["gap"].max(initial=-np.inf)),
                       float(out["d_active"].max(initial=-np.inf)))
    return out, int(s.max()) + 1


def close(a, b, rtol):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    if a.dtype.kind in "biu":
        return np.array_equal(a, b)
    fin = np.isfinite(a)
    if not np.array_equal(fin, np.isfinite(b)) or not np.array_equal(a[~fin], b[~fin]) and \
            not np.all(np.isnan(a[~fin]) & np.isnan(b[~fin])):
        return False
    scale = np.abs(a[fin]).max(initial=0.0)
    return np.all(np.abs(a[fin] - b[fin]) <= rtol * scale)


@pytest.mark.parametrize("p", [2, 3])
@pytest.mark.parametrize("tangent", [True, False])
def test_all_strands_in_one_pass_is_strand_by_strand(p, tangent):
    """A straight strand squeezed between two crossing strands (three strands in reach of its
    crossing elements): every output of the one-pass evaluation, per-point arrays in their
    order, tangent made at once or later (add_tangent), equals the strand-by-strand sum."""
    rod, X, _ = sandwich(p, 1.8 * EPS)
    pairs = rod.pairs(X)
    xe = X[rod.conn]
    k = rod.k
    ref, nk = strand_by_strand(k, rod.ids, xe, pairs, tangent)
    out = k.evaluate(rod.ids, xe, rod.ids, xe, pairs, tangent=tangent)
    assert nk >= 3 and out["energy"] > 0 and len(out["active"])
    if not tangent:
        k.add_tangent(ref)
        k.add_tangent(out)
    for key in ("energy", "total_force", "complementarity", "zones", "depth", "gap", "sbar",
                "force", "active", "vec", "mat", "qp", "xi", "xi_slave", "normal", "interior",
                "d_active", "switch", "switch_mat"):
        assert close(ref[key], out[key], 1e-13), key


@pytest.mark.slow
def test_strands_with_cuts_and_switch_points_in_one_pass():
    """The plectoneme's end loop (two strands in reach, cuts and switch points in both): the
    one-pass evaluation has the strand-by-strand energy, residual, tangent and switch points
    (in the same order).  Its per-point arrays agree to 4e-9 only: where the closest point
    crosses a node of a master that the slave crosses at nearly a right angle, the kind of
    closest point changes within a stretch of xi set by rounding (measured: cuts 3e-9 apart
    when the same points are searched in another batch), and the zone's Gauss points follow the
    cut; energy and residual do not see it (the integrand is continuous there)."""
    rod, X = plectoneme_end_loop()
    pairs = rod.pairs(X)
    xe = X[rod.conn]
    k = rod.k
    ref, nk = strand_by_strand(k, rod.ids, xe, pairs, True)
    out = k.evaluate(rod.ids, xe, rod.ids, xe, pairs, tangent=True)
    assert nk == 2 and len(out["switch"]) == 4
    assert abs(out["energy"] - ref["energy"]) <= 1e-13 * ref["energy"]
    assert close(rod.assemble(ref), rod.assemble(out), 1e-12)
    assert np.array_equal(out["switch"], ref["switch"])
    assert close(ref["switch_mat"], out["switch_mat"], 1e-8)
    for key in ("gap", "sbar", "force", "active", "qp", "interior"):
        assert close(ref[key], out[key], 1e-13), key
    for key in ("vec", "mat", "xi_slave", "d_active"):
        assert close(ref[key], out[key], 1e-7), key
