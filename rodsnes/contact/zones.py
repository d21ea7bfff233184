"""Contact zones of the closest-point law: the quadrature of the penalty integral over the
zones {s : d(s) > 0} of every slave element (pure numpy; no MPI, no PETSc).

Gauss points at fixed places cannot integrate a contact shorter than their spacing (docs/
contact.md, section 3).  With -contact_zones (the law's ``segments``) E_c = (mu/2) int <d>^2 ds
is taken over the zones themselves (``ContactZones.quadrature``):

1. every slave element within eps of contact is sampled at nseg points; the discrete maxima of
   d are refined (root of d' by Illinois' regula falsi), and so are its discrete minima in
   contact (a dip below 0 between two samples ends one zone and starts the next); the roots of
   d bound the zones;
2. each zone is cut wherever the kind of closest point (``ClosestPoint.kind``: a master node,
   the inside of a master element, a bound) changes (``split``), because there d(s) has a kink
   (node crossed or stuck to, bound reached) or the closest point jumps to another strand.
   Kinds name master nodes, not element ends, so the tie between the two elements sharing a
   node is no change; cuts are found by bisection to 1e-13 in xi, from both sides of a change
   (``bisect_kind``), and move continuously with the configuration: the residual is a
   continuous function of the nodes.  Where the runner-up (the nearest minimum of another
   kind) takes over between two samples, its crossing is cut too (``rival_brackets``);
3. each piece gets nqz Gauss points, graded geometrically toward its cuts (``cut_levels``).

The residual and tangent keep the law's pointwise formulas (contact/projection.py): the
integrand vanishes at zone ends, and is continuous across a cut at a node; where the closest
point jumps at a cut, the law adds the switch-point term from the cuts returned here.  Not
covered: a jump between two minima of one element (no change of kind, so no cut), and the
derivative of the zone quadrature's own error as its cuts move (large where a closest point
races near a centre of curvature of the master).

Every step is a sequence of closest-point searches (``ClosestPoint.find``); since each costs
about the same whatever its number of points, every search serves as many points as it can:
the roots at both ends of the zones in one Illinois solve, several levels of every bisection of
a cut per search (``bisect_kind``).
"""
import numpy as np

from rodsnes.model import fe
from rodsnes.contact.closest_point import phi_derivatives
from rodsnes.contact.monomials import monomials

__all__ = ["ContactZones"]


def _split_record(cl, n):
    """The closest-point records (``ClosestPoint.find``) of the first n points of cl and
    of the rest."""
    return {k: v[:n] for k, v in cl.items()}, {k: v[n:] for k, v in cl.items()}


def _distinct(o, xi):
    """The distinct points (o, xi): indices of their first occurrences, and for every point
    the position of its own among them."""
    order = np.lexsort((xi, o))
    os_, xs_ = o[order], xi[order]
    new = np.ones(len(order), dtype=bool)
    new[1:] = (os_[1:] != os_[:-1]) | (xs_[1:] != xs_[:-1])
    inverse = np.empty(len(order), dtype=np.int64)
    inverse[order] = np.cumsum(new) - 1
    return order[new], inverse


def _illinois_update(act, a, b, fa, fb, side, A_, B_, FA, FB, c, fc):
    """One Illinois (modified regula falsi) update, in place on the entries act of the
    brackets [a, b] with values fa, fb: the end whose value has the sign of f(c) moves to c;
    the other end's value is halved when the same end moved the time before (side)."""
    left = np.sign(fc) == np.sign(FA)
    a[act] = np.where(left, c, A_)
    fa[act] = np.where(left, fc, FA)
    b[act] = np.where(left, B_, c)
    fb[act] = np.where(left, FB, fc)
    s_new = np.where(left, 1, -1)
    stay = side[act] == s_new
    fb[act] = np.where(stay & left & np.isfinite(fb[act]), 0.5 * fb[act], fb[act])
    fa[act] = np.where(stay & ~left & np.isfinite(fa[act]), 0.5 * fa[act], fa[act])
    side[act] = s_new


class ContactZones:
    """The contact zones of the slave elements and their Gauss points, with the closest points
    of ``closest_point`` (a ``ClosestPoint``) and ``nqc`` Gauss points per element for the
    report."""

    BISECT_POINTS = 32  # slave points per closest-point search of ``bisect_kind`` (tree levels)

    def __init__(self, closest_point, nqc):
        self.closest_point = closest_point
        self.p, self.eps, self.h = closest_point.p, closest_point.eps, closest_point.h
        self.nqc = int(nqc)
        # samples per slave element
        self.nseg = max(2 * self.p + 3, self.nqc + 2)
        # Gauss points per zone: d ~ d0 - k s^2 near a crossing (<d>^2 a quartic), and deep
        # penetrations are far from polynomial: 8 points keep the quadrature error below 1e-8
        self.nqz = max(self.nqc + 3, 8)
        self.grade = 4                 # levels of geometric grading toward cuts beyond
        #                                2 log2 of the closest points' racing rate (``cut_levels``)
        self.xz, self.wz = fe.gauss_legendre(self.nqz)

    def quadrature(self, ctx, gap_q):
        """Contact zones {xi : d(xi) > 0} of the own elements and their Gauss points.

        Slave elements within one contact radius of touching (max over the Gauss points of
        d > -eps) are sampled at nseg equispaced xi (ends included); an interior discrete
        maximum of d above -eps is refined (root of d' by Illinois), so a zone narrower than
        the sample spacing (crossing strands) is still found; every run of points with d > 0
        becomes a zone bounded by the roots of d (Illinois) or by the element ends, split where
        the kind of closest point changes (``split``).  Each piece [a, b] gets the nqz
        Gauss points mapped onto it.  Returns (own index, xi, weight w J) of those points, the
        number of zones, and the cuts of ``split``."""
        nqc, h = self.nqc, self.h
        none = np.zeros(0, dtype=np.int64)
        empty = (none, np.zeros(0), np.zeros(0), 0, (none, np.zeros(0), np.zeros(0), None, None))
        cand = np.flatnonzero(gap_q.max(axis=1) > -self.eps)
        if cand.size == 0:
            return empty
        S = self.nseg
        xs = np.linspace(-1.0, 1.0, S)
        nc = len(cand)
        o = np.repeat(cand, S)
        xi = np.tile(xs, nc)
        cls = self.closest_point.find(ctx, o, xi)
        d = cls["d"].reshape(nc, S)
        dd = self._gap_slope(ctx, o, cls).reshape(nc, S)          # d' at the samples
        # refine the discrete maxima of d within eps of contact (an end sample too: the peak
        # may lie between it and its neighbour), so that a zone between two samples is found,
        # and the discrete minima of d in contact, so that a gap between two samples in contact
        # (d dipping below 0) splits their zone
        pad = np.full((nc, 1), np.inf)
        left = np.concatenate([-pad, d[:, :-1]], axis=1)
        right = np.concatenate([d[:, 1:], -pad], axis=1)
        ismax = (d >= left) & (d >= right) & (d > -self.eps)
        left = np.concatenate([pad, d[:, :-1]], axis=1)
        right = np.concatenate([d[:, 1:], pad], axis=1)
        ismin = (d <= left) & (d <= right) & (d > 0.0) & ~ismax
        ei, jj = np.nonzero(ismax | ismin)
        xe, de = [xi.reshape(nc, S)], [d]
        if ei.size:
            om = cand[ei]
            ja, jb = np.maximum(jj - 1, 0), np.minimum(jj + 1, S - 1)
            a, b = xs[ja], xs[jb]
            fa, fb = dd[ei, ja], dd[ei, jb]
            brk = np.where(ismax[ei, jj], (fa > 0.0) & (fb < 0.0), (fa < 0.0) & (fb > 0.0))
            if np.any(brk):
                xr = self._solve1d(ctx, om[brk], a[brk], b[brk], fa[brk], fb[brk], 1)
                dr = self.closest_point.find(ctx, om[brk], xr)["d"]
                # append as extra columns, one per refined maximum (padded with -inf)
                rows = ei[brk]
                k = np.zeros(len(rows), dtype=np.int64)
                order = np.argsort(rows, kind="stable")
                rs = rows[order]
                firsts = np.r_[0, np.flatnonzero(rs[1:] != rs[:-1]) + 1]
                k[order] = np.arange(len(rs)) - np.repeat(firsts, np.diff(np.r_[firsts, len(rs)]))
                ncol = int(k.max()) + 1
                X2 = np.full((nc, ncol), 2.0)       # padding beyond the element end: ignored
                D2 = np.full((nc, ncol), -np.inf)
                X2[rows, k] = xr
                D2[rows, k] = dr
                xe.append(X2)
                de.append(D2)
        X = np.concatenate(xe, axis=1)
        D = np.concatenate(de, axis=1)
        srt = np.argsort(X, axis=1, kind="stable")
        X = np.take_along_axis(X, srt, axis=1)
        D = np.take_along_axis(D, srt, axis=1)
        inside = X <= 1.0
        pos = (D > 0.0) & inside
        if not np.any(pos):
            return empty
        prev = np.concatenate([np.zeros((nc, 1), dtype=bool), pos[:, :-1]], axis=1)
        nxt = np.concatenate([pos[:, 1:], np.zeros((nc, 1), dtype=bool)], axis=1)
        r0, c0 = np.nonzero(pos & ~prev)          # zone starts
        r1, c1 = np.nonzero(pos & ~nxt)           # zone ends (same row order: row-major)
        za = X[r0, c0].copy()
        zb = X[r1, c1].copy()
        # roots of d between a start and the point before it (xi = -1 has no point before),
        # and between an end and the point after it, in one solve
        at_start = c0 > 0
        at_end = (c1 + 1 < X.shape[1])
        at_end[at_end] = X[r1[at_end], c1[at_end] + 1] <= 1.0
        if np.any(at_start) or np.any(at_end):
            ra, ca, rb, cb = r0[at_start], c0[at_start], r1[at_end], c1[at_end]
            root = self._solve1d(ctx, cand[np.r_[ra, rb]], np.r_[X[ra, ca - 1], X[rb, cb]],
                                 np.r_[X[ra, ca], X[rb, cb + 1]], np.r_[D[ra, ca - 1], D[rb, cb]],
                                 np.r_[D[ra, ca], D[rb, cb + 1]], 0)
            za[at_start], zb[at_end] = root[:len(ra)], root[len(ra):]
        nz = len(za)
        oz, za, zb, cuts = self.split(ctx, cand[r0], za, zb)
        oz = np.repeat(oz, self.nqz)
        mid, half = 0.5 * (za + zb), 0.5 * (zb - za)
        xq = (mid[:, None] + half[:, None] * self.xz[None, :]).ravel()
        wq = (half[:, None] * self.wz[None, :] * (0.5 * h)).ravel()
        return oz, xq, wq, nz, cuts

    def split(self, ctx, oz, za, zb):
        """Split the zones where the integrand has a kink or a jump, which Gauss points must not
        straddle: wherever the kind of closest point (``ClosestPoint.kind``) changes, i.e. where it
        crosses a master node (N_m(xibar(s)) has a kink), sticks to or leaves a node (a C0 kink of
        the centreline seen from its convex side), reaches or leaves a bound (rod end, exclusion
        boundary), or jumps to another strand.  The kinds are compared between nqz + 2 points of
        each zone; between two points of different kinds a and b, bisection finds both the first
        point that is not a and the last one that is not b, so that a node the closest point sticks
        to over a short stretch gives its two cuts; where the kinds just inside those two cuts
        differ again, the stretch between them is bracketed the same way (three or more changes
        between two samples), until they agree.  Every cut is a continuous function of the
        configuration (to 1e-13 in xi), and so is the zone quadrature.

        Returns the split zones (own index, xi start, xi end) and the cuts as (own index, xi
        left, xi right, closest points left, closest points right): bracket ends 1e-13 apart
        whose closest points (``ClosestPoint.find``) are those of the two sides (``cut_levels``,
        the law's switch points); a direct change a -> b gives one cut, not two."""
        n = self.nqz + 2
        t = np.linspace(0.0, 1.0, n)
        Xs = za[:, None] + (zb - za)[:, None] * t[None, :]
        cl = self.closest_point.find(ctx, np.repeat(oz, n), Xs.ravel(), rival=True)
        kind = cl["kind"].reshape(-1, n)
        ki, kj = np.nonzero(kind[:, :-1] != kind[:, 1:])
        # brackets (zone, a, b, kind at a, kind at b) to resolve; the stretch between the two
        # cuts of a bracket may hold further changes (node 43 -> inside element 42 -> element
        # 55 of the plectoneme at 9.415 turns, all within one sample spacing: the middle cut was
        # missed, a Gauss point's closest point jumped by 0.22 in xi as the nodes moved by 1e-7,
        # and the residual had steps of 0.05 that no Newton step could settle): bracketed again
        # until the kinds on both inner sides agree
        bz, ba, bb = ki, Xs[ki, kj], Xs[ki, kj + 1]
        ka, kb = kind[ki, kj], kind[ki, kj + 1]
        rz, ra, rb, rka, rkb = self.rival_brackets(ctx, oz, Xs, cl, kind)
        if rz.size:
            bz, ba, bb = np.r_[bz, rz], np.r_[ba, ra], np.r_[bb, rb]
            ka, kb = np.r_[ka, rka], np.r_[kb, rkb]
        if bz.size == 0:
            return oz, za, zb, (oz[:0], za[:0], za[:0], None, None)
        zs, cs, ls, rs = [], [], [], []
        for _ in range(8):
            nk = len(bz)
            cut, left, right = self.bisect_kind(ctx, np.concatenate([oz[bz], oz[bz]]),
                                                 np.tile(ba, 2), np.tile(bb, 2),
                                                 np.concatenate([ka, kb]),
                                                 np.repeat([False, True], nk))
            two = np.abs(cut[nk:] - cut[:nk]) > 1e-12
            distinct = np.r_[np.ones(nk, dtype=bool), two]
            zs.append(np.tile(bz, 2)[distinct])
            cs.append(cut[distinct])
            ls.append(left[distinct])
            rs.append(right[distinct])
            if not np.any(two):
                break
            # the inner sides: the first point past a's cut, the last point before b's
            inner_a, inner_b = right[:nk][two], left[nk:][two]
            oi = oz[bz[two]]
            inner = self.closest_point.find(ctx, np.r_[oi, oi], np.r_[inner_a, inner_b])
            k1, k2 = np.split(self.closest_point.kind(ctx, inner), 2)
            more = k1 != k2
            if not np.any(more):
                break
            bz, ba, bb, ka, kb = bz[two][more], inner_a[more], inner_b[more], k1[more], k2[more]
        cz, cut = np.concatenate(zs), np.concatenate(cs)
        left, right = np.concatenate(ls), np.concatenate(rs)
        if len(ctx["own_ids"]) > ctx["no"]:          # strand by strand (ClosestPoint.context)
            srt = np.argsort(oz[cz] // ctx["no"], kind="stable")
            cz, cut, left, right = cz[srt], cut[srt], left[srt], right[srt]
        oc = oz[cz]
        both = self.closest_point.find(ctx, np.r_[oc, oc], np.r_[left, right])
        cuts = (oc, left, right) + _split_record(both, len(oc))
        level = self.cut_levels(ctx, *cuts)
        zid = np.concatenate([np.arange(len(za)), np.arange(len(za)), cz])
        pts = np.concatenate([za, zb, cut])
        lev = np.r_[np.zeros(2 * len(za), dtype=np.int64), level]
        srt = np.lexsort((pts, zid))
        zid, pts, lev = zid[srt], pts[srt], lev[srt]
        same = zid[1:] == zid[:-1]
        a, b, z = pts[:-1][same], pts[1:][same], zid[:-1][same]
        la, lb = lev[:-1][same], lev[1:][same]
        keep = b > a
        a, b, z, la, lb = a[keep], b[keep], z[keep], la[keep], lb[keep]
        a, b, z = self._graded(a, b, z, la, lb)
        return oz[z], a, b, cuts

    def bisect_kind(self, ctx, o, a, b, target, negate, iters=60):
        """Bisection of [a, b] (a < b) for where the kind of closest point (``ClosestPoint.kind``)
        of the slave points of own index o stops being target (where ``negate``: starts being
        target; kinds may be negative, so the flag is separate): a moves to the midpoint c where the
        test holds at c, b otherwise, until b - a <= 1e-13 (at most ``iters`` steps).  Returns
        the last midpoint and the final bracket ends.
 The steps are the bisection's own, but several at once: the midpoints of the next levels of every
problem's bisection tree (2^levels - 1 points: every bracket that ``levels`` steps can reach) are
located in one ``ClosestPoint.find`` call, and the path the bisection takes through them is read
off; levels from the number of problems
        (``BISECT_POINTS`` points per call at most)."""
        a, b = np.array(a, dtype=float), np.array(b, dtype=float)
        x = 0.5 * (a + b)
        steps = np.zeros(len(a), dtype=np.int64)
        act = np.arange(len(a))
        while act.size:
            na = len(act)
            want = int(np.ceil(np.log2(max(float(np.max(b[act] - a[act])), 1e-300) / 1e-13)))
            levels = int(max(1, min(np.log2(self.BISECT_POINTS / na + 1.0), want,
                                    iters - steps[act].min())))
            # the tree: brackets (lo, hi) of every node, level by level (node j's children:
            # 2j with a moved to its midpoint, 2j + 1 with b moved)
            los, his, mids = [a[act][:, None]], [b[act][:, None]], []
            for lev in range(levels):
                lo_, hi_ = los[lev], his[lev]
                c = 0.5 * (lo_ + hi_)
                mids.append(np.minimum(np.maximum(c, np.minimum(lo_, hi_)), np.maximum(lo_, hi_)))
                if lev + 1 < levels:
                    los.append(np.stack([mids[lev], lo_], axis=2).reshape(na, -1))
                    his.append(np.stack([hi_, mids[lev]], axis=2).reshape(na, -1))
            # the nodes bisection would visit: bracket still wider than 1e-13, steps left
            need = [np.ones((na, 1), dtype=bool)] + \
                [(his[lev] - los[lev] > 1e-13) & (steps[act] + lev < iters)[:, None]
                 for lev in range(1, levels)]
            nodes = [np.nonzero(nd) for nd in need]          # (problem, node) per level
            pr = np.concatenate([p for p, _ in nodes])
            pc = np.concatenate([mids[lev][p, j] for lev, (p, j) in enumerate(nodes)])
            hit = self.kind_at(ctx, o[act][pr], pc) == target[act][pr]
            moves_a = hit != negate[act][pr]
            outcome, k0 = [], 0
            for lev, (p, j) in enumerate(nodes):
                out_lev = np.zeros(need[lev].shape, dtype=bool)
                out_lev[p, j] = moves_a[k0:k0 + len(p)]
                outcome.append(out_lev)
                k0 += len(p)
            # follow every problem's path down its tree
            node = np.zeros(na, dtype=np.int64)
            alive = np.arange(na)
            for lev in range(levels):
                nd = node[alive]
                mid = mids[lev][alive, nd]
                left = outcome[lev][alive, nd]
                g = act[alive]
                x[g] = mid
                a[g] = np.where(left, mid, los[lev][alive, nd])
                b[g] = np.where(left, his[lev][alive, nd], mid)
                steps[g] += 1
                node[alive] = 2 * nd + ~left
                done = (b[g] - a[g] <= 1e-13) | (steps[g] >= iters)
                alive = alive[~done]
                if alive.size == 0:
                    break
            act = act[alive]
        return x, a, b

    def kind_at(self, ctx, o, xi):
        """The kind of closest point (``ClosestPoint.kind``) of the slave points (own index o,
        xi), each distinct point searched once (``_distinct``): the two bisections of a direct
        change a -> b (``split``) visit the same midpoints until a third kind shows."""
        first, inverse = _distinct(o, xi)
        cl = self.closest_point.find(ctx, o[first], xi[first])
        return self.closest_point.kind(ctx, cl)[inverse]

    def rival_brackets(self, ctx, oz, Xs, cl, kind, iters=60):
        """Stretches between two samples of the same kind where the runner-up takes over
        (``ClosestPoint.find`` with rival): brackets (zone, a, b, kind at a, kind at b) of the
        changes there.  Two nearly parallel strands in line contact have a nearly flat distance
        along the master; a C0 kink of the centreline then holds a minimum of its own next to the
        one inside the element, and the two trade places over stretches narrower than the sample
        spacing (the plectoneme at 9.72 turns: 0.002 in xi, samples 0.2 apart), so no sample sees
        the change and a Gauss point's closest point jumps from four nodes to one as the stretch's
        end crosses it (a residual step of 5.5 of 46 as a node moved by 7e-8). Between two samples
        where the margin m = g_rival - g falls and then rises (dm/dxi < 0 at a, > 0 at b) its
        minimum is found (Illinois on dm/dxi); where the runner-up is the nearer there (the kind
        changes on the way, or m < 0), the stretch is bracketed on both sides.  A stretch is then
        cut from the moment it is born (m_min = 0, zero width), and the zone quadrature stays
        continuous."""
        n = Xs.shape[1]
        o = np.repeat(oz, n)
        m, dm = self._margin(ctx, o, cl)
        m, dm = m.reshape(-1, n), dm.reshape(-1, n)
        rk = cl["rival_kind"].reshape(-1, n)
        zi, j = np.nonzero((kind[:, :-1] == kind[:, 1:]) & (rk[:, :-1] == rk[:, 1:])
                           & np.isfinite(m[:, :-1]) & np.isfinite(m[:, 1:])
                           & (dm[:, :-1] < 0.0) & (dm[:, 1:] > 0.0))
        e = np.zeros(0, dtype=np.int64)
        if zi.size == 0:
            return e, np.zeros(0), np.zeros(0), e, e
        iz, xa0, xb0 = zi, Xs[zi, j], Xs[zi, j + 1]
        a, b, fa, fb = xa0.copy(), xb0.copy(), dm[zi, j].copy(), dm[zi, j + 1].copy()
        k0, r0 = kind[zi, j], rk[zi, j]
        found = np.full(len(iz), np.nan)
        found_kind = np.full(len(iz), -1, dtype=np.int64)
        side = np.zeros(len(iz), dtype=int)
        act = np.arange(len(iz))
        for _ in range(iters):
            if act.size == 0:
                break
            A_, B_, FA, FB = a[act], b[act], fa[act], fb[act]
            c = (A_ * FB - B_ * FA) / (FB - FA)
            c = np.clip(c, np.minimum(A_, B_), np.maximum(A_, B_))
            cs = self.closest_point.find(ctx, oz[iz[act]], c, rival=True)
            mc, fc = self._margin(ctx, oz[iz[act]], cs)
            other = (cs["kind"] != k0[act])
            found[act[other]] = c[other]
            found_kind[act[other]] = cs["kind"][other]
            lost = ~other & ((cs["rival_kind"] != r0[act]) | ~np.isfinite(mc))
            _illinois_update(act, a, b, fa, fb, side, A_, B_, FA, FB, c, fc)
            done = other | lost | (np.abs(b[act] - a[act]) <= 1e-13) | (fc == 0.0)
            act = act[~done]
        hit = np.flatnonzero(np.isfinite(found) & (found > xa0) & (found < xb0))
        if hit.size == 0:
            return e, np.zeros(0), np.zeros(0), e, e
        iz, xa0, xb0, k0, xs, ks = iz[hit], xa0[hit], xb0[hit], k0[hit], found[hit], found_kind[hit]
        return (np.r_[iz, iz], np.r_[xa0, xs], np.r_[xs, xb0], np.r_[k0, ks], np.r_[ks, k0])

    def _margin(self, ctx, o, cl):
        """Margin of the runner-up, m = g_rival - g >= 0, and dm/dxi along the slave (each
        distance's derivative D . r'(xi) / g: its closest point is stationary or fixed)."""
        t = np.einsum("na,nad->nd", cl["dN"], ctx["x_own"][o])
        ok = np.isfinite(cl["rival_g"]) & (cl["g"] > 0) & np.isfinite(cl["g"])
        g = np.where(ok, cl["g"], 1.0)
        gr = np.where(ok, cl["rival_g"], 1.0)
        dm = np.einsum("nd,nd->n", cl["rival_D"], t) / gr - np.einsum("nd,nd->n", cl["D"], t) / g
        return np.where(ok, gr - g, np.inf), np.where(ok, dm, 0.0)

    def cut_levels(self, ctx, o, left, right, cla, clb):
        """Levels of geometric grading toward every cut (``_graded``): ``grade`` + 2 log2 of the
        racing rate of the closest points on either side, |dxibar/dxi| = |r'(xi) . r_m'(xibar)|
        / phi''(xibar) (phi = |r_m - r|^2 / 2; an interior closest point; 0 at a node or bound).
        Near a fold of the distance function, where the closest point on one side ceases to
        exist, phi'' ~ sqrt(distance to the fold), so the integrand's branch point lies ~
        1/rate^2 beyond the cut; each level halves the distance of the last Gauss points from
        the cut, so 2 log2(rate) levels reach the branch point and ``grade`` more resolve it.
        Measured (tangent against central differences of the residual): the noisy cubic helix
        reaches the differencing floor 9e-8 with grade >= 2 (6e-6 with 1, 1.5e-3 with the 2
        log2(rate) levels alone, > 1e-2 without grading: grade 0 turns it off); the
        plectoneme's end loop (rates up to 463) 4.5e-6 with any grade >= 0, 1.4e-4 with 10 +
        log2(rate) levels.  Cuts with rate <= 2 (node crossings: most of them) get ``grade``
        + 2 levels, not 10 + 1 as before: a contact evaluation of the end loop 1.4x faster."""
        rate = np.ones(len(o))
        for cl in (cla, clb):
            inner = cl["interior"] & (cl["m"] >= 0)
            if not np.any(inner):
                continue
            A = ctx["A_pool"][cl["m"][inner]]
            _, _, H = phi_derivatives(cl["xi_m"][inner], A, cl["P"][inner])
            tm = np.einsum("mk,mkd->md", monomials(self.p, cl["xi_m"][inner])[1], A)
            ts = np.einsum("na,nad->nd", cl["dN"][inner], ctx["x_own"][o[inner]])
            r = np.abs(np.einsum("nd,nd->n", ts, tm)) / np.maximum(H, 1e-300)
            rate[inner] = np.maximum(rate[inner], r)
        extra = np.ceil(np.log2(np.minimum(rate, 2.0 ** 30)))
        return self.grade + 2 * extra.astype(np.int64) if self.grade > 0 \
            else np.zeros(len(o), np.int64)

    def _graded(self, a, b, z, la, lb):
        """Pieces [a, b] graded geometrically toward their ends that are cuts: points at
        distances l 2^-j, j = 1..la (from a) and 1..lb (from b) (l: the piece, or half of it
        when both ends are cuts; then j from 0).  Near a cut where the closest point reaches a
        node while the slave point is close to a centre of curvature of the master, the closest
        point races (dxibar/dxi ~ 100) and the integrand has a branch point just beyond the
        cut; one Gauss rule over the piece then leaves a quadrature error whose change as the
        cut moves the tangent does not see (4-9e-2 relative on a noisy cubic helix; graded with
        10 levels, 1e-5).  The points move continuously with the cuts."""
        G = int(max(la.max(initial=0), lb.max(initial=0)))
        if G == 0:
            return a, b, z
        both = (la > 0) & (lb > 0)
        base = np.where(both, 0.5, 1.0) * (b - a)
        k = np.arange(G)
        j = k + 1 - both[:, None]                                   # (n, G): from 0 if both
        frac = base[:, None] * 0.5 ** j
        extra = np.concatenate([np.where(k < la[:, None], a[:, None] + frac, np.nan),
                                np.where(k < lb[:, None], b[:, None] - frac, np.nan)], axis=1)
        ii, jj = np.nonzero(np.isfinite(extra))
        pid = np.concatenate([np.arange(len(a)), np.arange(len(a)), ii])
        pts = np.concatenate([a, b, extra[ii, jj]])
        srt = np.lexsort((pts, pid))
        pid, pts = pid[srt], pts[srt]
        same = (pid[1:] == pid[:-1]) & (pts[1:] > pts[:-1])
        return pts[:-1][same], pts[1:][same], z[pid[:-1][same]]

    def _gap_slope(self, ctx, o, cl):
        """d'(xi) of the slave points: -nu . dr/dxi where the closest point is stationary
        (interior: its motion drops out) or fixed (a node); at an exclusion bound sbar = s -+
        delta moves with s, dxi_m/dxi = 1, and d' = -nu . (dr/dxi - dr_m/dxi_m)."""
        t = np.einsum("na,nad->nd", cl["dN"], ctx["x_own"][o])
        g = np.where(np.isfinite(cl["g"]) & (cl["g"] > 0), cl["g"], 1.0)
        has = cl["m"] >= 0
        bound = self.closest_point.kind(ctx, cl) <= -2
        if np.any(bound):
            dNm = monomials(self.p, cl["xi_m"][bound])[1]
            t[bound] -= np.einsum("nk,nkd->nd", dNm, ctx["A_pool"][cl["m"][bound]])
        return np.where(has, -np.einsum("nd,nd->n", cl["D"], t) / g, 0.0)

    def _solve1d(self, ctx, o, a, b, fa, fb, which, iters=40):
        """Illinois (modified regula falsi) root of f on [a, b], f(a), f(b) of opposite signs,
        vectorised; f = d (which 0) or d' (which 1) of the slave points of own index o.
        Bisection where a value is not finite.  Returns the root (to 1e-13 in xi)."""
        a, b, fa, fb = (np.array(v, dtype=float) for v in (a, b, fa, fb))
        x = 0.5 * (a + b)
        dx_tol = 1e-13
        act = np.arange(len(a))
        side = np.zeros(len(a), dtype=int)
        for _ in range(iters):
            if act.size == 0:
                break
            A_, B_, FA, FB = a[act], b[act], fa[act], fb[act]
            ok = np.isfinite(FA) & np.isfinite(FB) & (FA != FB)
            c = np.where(ok, (A_ * FB - B_ * FA) / np.where(ok, FB - FA, 1.0), 0.5 * (A_ + B_))
            c = np.minimum(np.maximum(c, np.minimum(A_, B_)), np.maximum(A_, B_))
            cl = self.closest_point.find(ctx, o[act], c)
            fc = cl["d"] if which == 0 else self._gap_slope(ctx, o[act], cl)
            x[act] = c
            _illinois_update(act, a, b, fa, fb, side, A_, B_, FA, FB, c, fc)
            done = (np.abs(b[act] - a[act]) <= dx_tol) | (fc == 0.0)
            act = act[~done]
        return x
