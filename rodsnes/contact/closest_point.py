"""Closest-point projection of self-contact: the closest admissible point of a slave point on
its candidate master elements (pure numpy; no MPI, no PETSc).

For a slave point r(s) (element e, local xi; element e spans s in [e h, (e+1) h], s = e h +
(xi + 1) h / 2) the master point sbar minimises the distance over the admissible set

    I(s) = { sigma in [0, L] : dist(s, sigma) >= delta }                          (exclusion set)
           dist = |s - sigma| (open rod),  min(|s - sigma|, L - |s - sigma|) (closed rod)

restricted to every candidate element m (from ``search.candidate_pairs``): I(s) cap [m h,
(m+1) h] is a union of at most two intervals ("slots", ``admissible_slots``).  On each slot

    phi(xi) = |x_m(xi) - r(s)|^2 / 2                                              (``phi``)

is minimised by a safeguarded Newton iteration (``sampled_newton``: started from every discrete
local minimum of 4p+1 equispaced samples; steps limited to one sample spacing; clamped to the
slot; backtracking on phi), vectorised over all (slave point, candidate, slot, start).  Where
phi may be non-convex on the slot (a Bernstein lower bound of phi'' is not positive), a minimum
can hide between two samples next to a maximum; there every real root of the polynomial phi'
(companion eigenvalues) is a candidate as well (``stationary_minimum``); ``project`` is both.
The global minimum over candidates is kept (``ClosestPoint.find``); a closest point shared by
two elements (a node) is thus counted once.  Before projecting many slots (more than
``PRUNE``), they are pruned exactly: a slot whose element's bounding sphere is farther from the
slave point than all of another candidate's sphere cannot hold the minimum (``_prune``); after
the samples, so is a slot whose Bernstein lower bound of phi lies above a sample of another
(``_bounded``), and the roots of phi' are not sought where phi is monotone (``_monotone``).  Cost:
O(#pairs * nqc) vectorised work, no Python loop over elements or points.  The samples of all
slots are one matrix product (in the slot coordinate t, xi = lo + (hi - lo) t, the monomials of
the sample fractions are fixed: ``_taylor``), and the Newton iterations of all starts run
together (``_newton``).

The kind of a closest point (``ClosestPoint.kind``: a master node, the inside of a master
element, an exclusion bound) is what the contact-zone segmentation (contact/zones.py) cuts at;
with ``rival`` the search also returns the runner-up, the nearest minimum of another kind.

The master elements of an evaluation, their monomial coefficients and bounding spheres, and the
candidates of every slave element are gathered once per evaluation (``ClosestPoint.context``).
"""
import numpy as np

from rodsnes.contact.monomials import monomial_matrix, powers
from rodsnes.contact.search import element_bounds, positions

__all__ = ["ClosestPoint", "phi", "phi_derivatives", "master_pool", "master_pool_rows"]


def phi(x, A, P):
    """phi = |r(x) - P|^2 / 2 by Horner, r(x) = sum_k A_k x^k (A (M, p+1, 3) monomial
    coefficients, ``monomials.monomial_matrix``), M points x and P; x (M, n): n points of
    every problem (phi (M, n))."""
    p = A.shape[1] - 1
    if x.ndim > 1:
        A, P = A[:, None], P[:, None]
    xc = x[..., None]
    D = A[..., p, :] * xc
    D += A[..., p - 1, :]
    for j in range(p - 2, -1, -1):
        D *= xc
        D += A[..., j, :]
    D -= P
    return 0.5 * np.einsum("...d,...d->...", D, D)


def phi_derivatives(x, A, P):
    """phi = |r(x) - P|^2 / 2 and its first two x-derivatives, phi' = D . r', phi'' = |r'|^2
    + D . r'' (D = r(x) - P); A (M, p+1, 3) monomial coefficients of r."""
    R = powers(A.shape[1] - 1, x, 2) @ A              # (M, 3, 3): r, r', r''
    R[:, 0] -= P                                         # D
    s = np.einsum("mjd,mjd->mj", R[:, _PHI_LEFT], R[:, _PHI_RIGHT])
    return 0.5 * s[:, 0], s[:, 1], s[:, 2] + s[:, 3]


# phi_derivatives: the four products D . D, D . r', r' . r', D . r'' of the rows (D, r', r'')
_PHI_LEFT, _PHI_RIGHT = [0, 0, 1, 0], [0, 1, 1, 2]


def master_pool(own_ids, x_own, other_ids, x_other):
    """The elements that may hold a master point: other first, then own (first occurrence
    wins), sorted ids and their nodes."""
    pool_ids, first = master_pool_rows(own_ids, other_ids)
    return pool_ids, np.concatenate([x_other, x_own], axis=0)[first]


def master_pool_rows(own_ids, other_ids):
    """``master_pool``'s sorted ids and, for each, its row in [other, own] (the ids alone:
    a caller that keeps them while the ids stay gathers the nodes by these rows)."""
    return np.unique(np.concatenate([other_ids, own_ids]), return_index=True)


def _nearest_per_point(idx, f, pt):
    """Of the candidates idx (indices into f and pt), the one with the smallest f for each point
    pt (ties: the first in order); one index per point that has a candidate."""
    order = idx[np.lexsort((f[idx], pt[idx]))]
    first = np.ones(len(order), dtype=bool)
    first[1:] = pt[order][1:] != pt[order][:-1]
    return order[first]


class ClosestPoint:
    """The closest admissible point on a rod of ``nelem`` Lagrange elements of order ``order``
    (length L, open or ``closed``, contact radius eps, exclusion delta)."""

    MAXIT = 60          # Newton iterations of the projection
    MAXBT = 40          # backtracking halvings
    CHUNK = 16384       # projection problems per vectorised batch
    PRUNE = 96          # slots beyond which ``find`` prunes (``_prune``) and bounds them

    def __init__(self, order, eps, delta, L, nelem, closed):
        self.p = int(order)
        self.eps = float(eps)
        self.delta = float(delta)
        self.L = float(L)
        self.nelem = int(nelem)
        self.closed = bool(closed)
        self.h = self.L / self.nelem
        self.C = monomial_matrix(self.p)
        self.nsamp = 4 * self.p + 1 if self.p > 1 else 3
        from math import comb
        # fractions of the slot (_project): the start samples, and with them the 2p - 1 points
        # whose phi'' values give its Bernstein coefficients
        self._t_start = np.linspace(0.0, 1.0, self.nsamp)
        self._t_check = np.concatenate([self._t_start, np.linspace(0.0, 1.0, 2 * self.p - 1)])
        # their monomials and derivatives as rows (3 n, p+1), and the Taylor shift (_taylor)
        self._T_start, self._T_check = (powers(self.p, t, 2).reshape(-1, self.p + 1)
                                        for t in (self._t_start, self._t_check))
        kk = np.arange(self.p + 1)
        self._kmj = np.maximum(kk[None, :] - kk[:, None], 0)
        self._binom = np.array([[comb(k, j) for k in kk] for j in kk], dtype=float)
        # coefficient k of d^j D / dxi^j is (k + j)! / k! Dc_{k+j} (_phi_rows)
        self._row_index = np.minimum(kk[None, :] + np.arange(3)[:, None], self.p)   # (3, p+1)
        self._row_factor = np.array([[np.prod(np.arange(k + 1, k + j + 1)) if k + j <= self.p
                                      else 0.0 for k in kk] for j in range(3)])[:, :, None]
        # phi'(xi) = sum_n c_n xi^n, c_n = sum_{i + j - 1 = n} j D_i . A_j  (stationary_minimum)
        nb = 2 * self.p - 2                   # degree of phi'' (_project)
        tb = np.linspace(0.0, 1.0, nb + 1)
        V = np.array([[comb(nb, k) * t ** k * (1 - t) ** (nb - k) for k in range(nb + 1)]
                      for t in tb])
        self._to_bernstein = np.linalg.inv(V)
        # phi (degree 2p) at every other start sample (2p + 1 equispaced points) to its
        # Bernstein coefficients on the slot (``_bounded``)
        nf = 2 * self.p
        tf = np.linspace(0.0, 1.0, nf + 1)
        self._phi_to_bernstein = np.linalg.inv(np.array(
            [[comb(nf, k) * t ** k * (1 - t) ** (nf - k) for k in range(nf + 1)] for t in tf]))
        self.nonconvex = 0                    # projections that needed stationary_minimum
        q = self.p + 1
        self._dphi = np.zeros((q, q, 2 * self.p))
        for i in range(q):
            for j in range(1, q):
                self._dphi[i, j, i + j - 1] = j
        # phi' (degree 2p - 1) on the slot: monomial to Bernstein coefficients, b_k = sum_{n <=
        # k} C(k, n) / C(2p - 1, n) c_n (``_monotone``); 3^k >= (|lo| + w)^k on a slot of
        # [-1, 1] (``_size``)
        nd = 2 * self.p - 1
        self._dphi_to_bernstein = np.array([[comb(k, n) / comb(nd, n) if n <= k else 0.0
                                             for k in range(nd + 1)] for n in range(nd + 1)])
        self._three_pow = 3.0 ** np.arange(q)

    # -- the admissible set ---------------------------------------------------------------
    def admissible_slots(self, s, m):
        """Admissible part of element m for slave arclength s: I(s) cap [m h, (m+1) h].

        s, m (M,) -> lo, hi (M, 2) in xi of the (at most two) intervals, valid (M, 2).
        Open: excluded (s - delta, s + delta).  Closed: the admissible arc [s + delta,
        s + L - delta] (mod L) intersected with the element arc (at most two pieces)."""
        u = np.asarray(s, dtype=float) - np.asarray(m, dtype=float) * self.h
        lo, hi, valid = self._slots(u)
        return self._to_xi(lo), self._to_xi(hi), valid

    def _slots(self, u):
        """``admissible_slots`` of slave points at element-local arclength u (any shape) from
        the element start: lo, hi (u.shape, 2) in arclength from the element start, valid."""
        h, L, dl = self.h, self.L, self.delta
        lo = np.empty(u.shape + (2,))
        if not self.closed:
            lo[..., 0] = 0.0
            lo[..., 1] = np.maximum(0.0, u + dl)
            hi = np.full(u.shape + (2,), h)
            hi[..., 0] = np.minimum(h, u - dl)
            valid = np.empty(u.shape + (2,), dtype=bool)
            valid[..., 0] = u - dl >= 0.0
            valid[..., 1] = u + dl <= h
        else:
            lad = L - 2.0 * dl
            lo[..., 0] = np.mod(u + dl, L)
            lo[..., 1] = lo[..., 0] - L
            hi = np.minimum(lo + lad, h)
            np.maximum(lo, 0.0, out=lo)
            valid = (hi >= lo) & (lad >= 0.0)
        valid &= hi >= lo
        return lo, hi, valid

    def _to_xi(self, t):
        """Element-local arclength t to xi, clamped to [-1, 1]."""
        return np.minimum(np.maximum(2.0 * t / self.h - 1.0, -1.0), 1.0)

    # -- projection -------------------------------------------------------------------------
    def project(self, P, A, lo, hi, point=None):
        """argmin_{xi in [lo, hi]} |r(xi) - P|^2 for M problems. Returns xi (M,), phi (M,).
        With ``point`` (M,) (the slave point of every problem, problems of a point next to each
        other) only the smallest phi of every point is wanted: a problem whose slot cannot
        hold it (``_bounded``) is left out (phi inf, xi lo)."""
        M = len(P)
        xi_out = np.empty(M)
        f_out = np.empty(M)
        for b0 in range(0, M, self.CHUNK):
            sl = slice(b0, min(M, b0 + self.CHUNK))
            x, f, nonconvex, monotone = self._project(P[sl], A[sl], lo[sl], hi[sl], True,
                                                      None if point is None else point[sl])
            # where phi may be non-convex on the slot, a minimum may hide between samples
            flat = np.flatnonzero(nonconvex)
            if flat.size:
                x2, f2 = self.stationary_minimum(P[sl][flat], A[sl][flat], lo[sl][flat],
                                                 hi[sl][flat], monotone[flat])
                better = f2 < f[flat]
                x[flat[better]], f[flat[better]] = x2[better], f2[better]
            xi_out[sl], f_out[sl] = x, f
            self.nonconvex += int(flat.size)
        return xi_out, f_out

    def sampled_newton(self, P, A, lo, hi):
        """The sampled Newton search of ``project`` alone (no roots where phi is not convex)."""
        return self._project(P, A, lo, hi, False)[:2]

    def _taylor(self, Dc, lo, w):
        """Coefficients B (S, p+1, 3) of D(lo + w t) = sum_j B_j t^j, from those of D(xi) =
        sum_k Dc_k xi^k: B_j = sum_k C(k, j) lo^(k-j) w^j Dc_k."""
        LW = powers(self.p, np.stack([lo, w], axis=1), 0)                 # (S, 2, 1, p+1)
        return (self._binom * LW[:, 0, 0, self._kmj] * LW[:, 1, 0, :, None]) @ Dc

    def _project(self, P, A, lo, hi, check, point=None):
        """Sampled Newton search for argmin phi, phi = |r(xi) - P|^2 / 2 on [lo, hi], S
        problems (A (S, p+1, 3) monomial coefficients of r): phi at nsamp equispaced samples;
        from every discrete local minimum a safeguarded Newton iteration (steps limited to one
        sample spacing, clamped to the slot, backtracking on phi until phi does not rise by
        more than 1e-14 phi; a Newton step below 1e-9 is always taken; converged when a step
        moves xi by <= 1e-13), all starts at once; the best start per problem.  With ``check``
        also whether phi may be non-convex on the slot: phi'' = |r'|^2 + D . r'' is a
        polynomial of degree 2p - 2 whose Bernstein coefficients on [lo, hi] (from its values at
        2p - 1 equispaced points) bound it from below; where one is not positive a minimum may
        hide between two samples next to a maximum (``project`` then takes every stationary
        point).  The samples of all problems are one matrix product: in the slot's own
        coordinate t (xi = lo + (hi - lo) t) the monomials of the sample fractions are fixed
        (``_taylor``).  With ``point`` (``project``) the problems that cannot hold the smallest
        phi of their point (``_bounded``) get no start (phi inf, xi lo, not nonconvex).
        Returns xi (S,), phi (S,), nonconvex (S,) bool or None, and monotone (S,) bool or None:
        the nonconvex problems whose phi is monotone on the slot (``_monotone``)."""
        S, ns, n1 = len(P), self.nsamp, self.p + 1
        Dc = np.array(A, dtype=float)
        Dc[:, 0] -= P
        w = hi - lo
        t, T = (self._t_check, self._T_check) if check and self.p > 1 else \
            (self._t_start, self._T_start)
        n = len(t)
        Bt = self._taylor(Dc, lo, w)                      # (S, p+1, 3)
        B = Bt.transpose(1, 0, 2).reshape(n1, 3 * S)
        R = (T @ B).reshape(n, 3, S, 3)                     # D and its t-derivatives
        F = 0.5 * np.einsum("nsd,nsd->ns", R[:ns, 0], R[:ns, 0])     # phi at the samples
        ws = np.where(w > 0.0, w, 1.0)                    # phi' = phi_t / w, phi'' = phi_tt / w^2
        nonconvex = np.zeros(S, dtype=bool) if check else None     # (p = 1: phi'' constant)
        monotone = np.zeros(S, dtype=bool) if check else None
        if check and self.p > 1:
            Rc = R[ns:]
            Hc = (np.einsum("nsd,nsd->sn", Rc[:, 1], Rc[:, 1])
                  + np.einsum("nsd,nsd->sn", Rc[:, 0], Rc[:, 2])) / (ws * ws)[:, None]
            nonconvex = ~((Hc @ self._to_bernstein.T).min(axis=1) > 0.0) & (w > 0.0)
        ismin = np.ones(F.shape, dtype=bool)
        ismin[1:] &= F[1:] <= F[:-1]
        ismin[:-1] &= F[:-1] <= F[1:]
        # plateaus (e.g. degenerate slot hi == lo): keep only the first sample of a run
        ismin[1:] &= ~(ismin[:-1] & (F[1:] == F[:-1]))
        scale = np.einsum("md,md->m", P, P) + np.einsum("mkd,mkd->m", A, A)
        if point is not None:
            keep = self._bounded(F, point, scale + self._size(Dc) ** 2)
            ismin &= keep
            if nonconvex is not None:
                nonconvex &= keep
        if check and self.p > 1:
            monotone = self._monotone(Bt, Dc, nonconvex)
        pid, sid = np.nonzero(ismin.T)                    # problem by problem
        Rs = R[sid, :, pid]                               # (starts, 3, 3) at the starts
        wp = ws[pid]
        x = lo[pid] + w[pid] * t[sid]
        f = F[sid, pid]
        g = np.einsum("md,md->m", Rs[:, 0], Rs[:, 1]) / wp
        h = (np.einsum("md,md->m", Rs[:, 1], Rs[:, 1])
             + np.einsum("md,md->m", Rs[:, 0], Rs[:, 2])) / (wp * wp)
        x, f = self._newton(Dc[pid], lo[pid], hi[pid], w[pid] / (ns - 1), scale[pid], x, f, g,
                            h)
        # best start per problem
        order = np.lexsort((f, pid))
        first = np.ones(len(order), dtype=bool)
        first[1:] = pid[order][1:] != pid[order][:-1]
        best = order[first]
        xi_out = np.array(lo, dtype=float)
        f_out = np.full(S, np.inf)
        xi_out[pid[best]] = x[best]
        f_out[pid[best]] = f[best]
        return xi_out, f_out, nonconvex, monotone

    def _size(self, Dc):
        """sum_k 3^k |Dc_k| (S,): bounds |D| and sum_j |B_j| on a slot of [-1, 1] (B the Taylor
        coefficients of D, ``_taylor``), and so the scale of their rounding."""
        return np.sqrt(np.einsum("skd,skd->sk", Dc, Dc)) @ self._three_pow

    def _monotone(self, B, Dc, rows):
        """Of the problems ``rows`` (bool (S,)), those on whose slot phi' keeps one sign: phi is
        monotone there, its minimum is at an end and ``stationary_minimum`` has no stationary
        point to find (on the self-contact scenes, half of those where phi may be non-convex;
        each saves the eigenvalues of a companion matrix).  All Bernstein coefficients of
        phi_t = D . D_t on [0, 1] (degree 2p - 1, from the slot's Taylor coefficients B of D,
        ``_taylor``) have one sign, beyond a margin 1e-11 p size^2 (size = sum_k 3^k |Dc_k|:
        their rounding, and that of B, are below 1e-14 p size^2).  Then the roots of phi' that
        ``stationary_minimum`` would compute lie outside the slot, and its minimum is that of
        the two ends."""
        out = np.zeros(len(B), dtype=bool)
        r = np.flatnonzero(rows)
        if r.size == 0:
            return out
        Br = B[r]
        c = np.matmul(Br, np.swapaxes(Br, 1, 2)).reshape(len(r), -1) \
            @ self._dphi.reshape(-1, 2 * self.p)                      # phi_t coefficients
        b = c @ self._dphi_to_bernstein
        tol = 1e-11 * self.p * self._size(Dc[r]) ** 2
        out[r] = (b.min(axis=1) > tol) | (b.max(axis=1) < -tol)
        return out

    def _bounded(self, F, point, scale):
        """The problems (slots) whose phi may fall to the smallest phi of their slave point
        (``point``), from phi at the samples F (nsamp, S): on its slot phi is a polynomial of
        degree 2p, bounded below by its Bernstein coefficients (from every other sample, 2p + 1
        equispaced points), and the point's smallest phi is at most its smallest sample over its
        slots.  A slot whose bound lies above that cannot hold the point's closest point (exact,
        with a margin 1e-12 (max F + scale) for the rounding of F and of the bound, which is
        below 600 u scale for p <= 4, scale (S,) = |P|^2 + |A|^2 + (sum_k 3^k |Dc_k|)^2: the
        slots that hold it are kept, ties included); its Newton search and roots of phi' are
        not needed.  On the plectoneme the bounding spheres (``_prune``) leave 9 slots per
        slave point, this 1.7 (of them 1.5 hold a minimum as close as the point's closest)."""
        Fb = F[::(len(F) - 1) // (2 * self.p)]
        lb = (self._phi_to_bernstein @ Fb).min(axis=0)
        fmin = F.min(axis=0)
        first = np.flatnonzero(np.concatenate(([True], point[1:] != point[:-1])))
        ub = np.repeat(np.minimum.reduceat(fmin, first), np.diff(first, append=len(point)))
        return lb <= ub + 1e-9 * ub + 1e-12 * (F.max(axis=0) + scale)

    def _phi_rows(self, Dc):
        """Per problem (S,), the monomial coefficients (S, p+1, 24) of the factors of the four
        products D . D, D . r', r' . r', D . r'' (``_phi_at``): D = sum_k Dc_k xi^k, r' and
        r'' its xi-derivatives."""
        C3 = Dc[:, self._row_index] * self._row_factor                     # (S, 3, p+1, 3)
        D, r1, r2 = C3[:, 0], C3[:, 1], C3[:, 2]
        return np.concatenate([D, D, r1, D, D, r1, r1, r2], axis=2,
                              out=np.empty((len(Dc), self.p + 1, 24)))

    def _phi_at(self, Q, x):
        """phi = |D|^2 / 2, phi' = D . r', phi'' = |r'|^2 + D . r'' at x (S,) from ``_phi_rows``
        (one matrix product and one contraction)."""
        R = (powers(self.p, x, 0) @ Q).reshape(len(x), 2, 4, 3)
        s = np.einsum("skd,skd->sk", R[:, 0], R[:, 1])
        return 0.5 * s[:, 0], s[:, 1], s[:, 2] + s[:, 3]

    def _newton(self, Dc, lo, hi, dx, scale, x, f, g, h):
        """The safeguarded Newton iteration of ``_project`` from the starts x with phi, phi',
        phi'' = f, g, h there, all starts at once.  A start that has converged or given up is
        frozen (its step bound dx set to 0: its later steps are 0 and leave it where it is);
        the working rows are compacted when few remain.  Returns xi and phi of every start."""
        n = len(x)
        x_out, f_out = x.copy(), f.copy()
        wid = np.arange(n)                   # the working rows' start indices
        Q = self._phi_rows(Dc)
        dx = dx.copy()
        ndx = -dx
        tiny = 1e-30 * scale
        for _ in range(self.MAXIT):
            newton = h > 0.0
            step = np.sign(g)
            step *= ndx
            np.divide(-g, h, out=step, where=newton)
            np.maximum(step, ndx, out=step)
            np.minimum(step, dx, out=step)
            xt = x + step
            np.maximum(xt, lo, out=xt)
            np.minimum(xt, hi, out=xt)
            ft, gt, ht = self._phi_at(Q, xt)
            ok = ft <= f + (1e-14 * f + tiny)
            if not ok.all():
                ok |= newton & (np.abs(step) < 1e-9)
                if not ok.all():
                    self._backtrack(Q, lo, hi, x, f, f + (1e-14 * f + tiny), newton, step,
                                    np.flatnonzero(~ok), xt, ft, gt, ht, ok)
            stop = (np.abs(xt - x) <= 1e-13) | ~ok       # converged, or gave up (x, f kept)
            x, f, g, h = xt, ft, gt, ht
            if not stop.any():
                continue
            dx[stop] = 0.0
            ndx[stop] = 0.0
            na = np.count_nonzero(dx)
            if na == 0:
                break
            if na <= n // 4 and n > 64:                  # compact the working rows
                x_out[wid], f_out[wid] = x, f
                keep = np.flatnonzero(dx)
                wid, Q, lo, hi, dx, ndx, tiny, x, f, g, h = (
                    v[keep] for v in (wid, Q, lo, hi, dx, ndx, tiny, x, f, g, h))
                n = na
        x_out[wid], f_out[wid] = x, f
        return x_out, f_out

    def _backtrack(self, Q, lo, hi, x, f, limit, newton, step, rows, xt, ft, gt, ht, ok):
        """Halve the Newton steps of the rows whose trial raised phi above ``limit`` until one
        does not (at most MAXBT trials in all); fills xt, ft, gt, ht and ok of those accepted in
        place, and puts back x and phi of those that gave up."""
        st = step[rows]
        for _bt in range(1, self.MAXBT):
            st = 0.5 * st
            xb = np.minimum(np.maximum(x[rows] + st, lo[rows]), hi[rows])
            fb, gb, hb = self._phi_at(Q[rows], xb)
            acc = (fb <= limit[rows]) | (newton[rows] & (np.abs(st) < 1e-9))
            r = rows[acc]
            xt[r], ft[r], gt[r], ht[r], ok[r] = xb[acc], fb[acc], gb[acc], hb[acc], True
            rows, st = rows[~acc], st[~acc]
            if rows.size == 0:
                break
        xt[rows], ft[rows] = x[rows], f[rows]

    def stationary_minimum(self, P, A, lo, hi, monotone=None):
        """Every stationary point of phi: the real roots of the polynomial phi'(xi) = D(xi) .
        r'(xi) of degree 2p - 1 (eigenvalues of its companion matrix, batched), kept if
        within the slot and polished by Newton steps that may not raise phi
        (``_polished_roots``), and the two slot ends; the smallest phi among them is the
        global minimum (no sampling: a minimum next to a maximum, as in the flat distance
        valleys of a slave point near a centre of curvature of the master, cannot be missed).
        ``monotone`` (M,) bool: problems whose phi' keeps one sign on the slot
        (``_monotone``): the ends alone."""
        fe = phi(np.stack([lo, hi], axis=1), A, P)
        flo, fhi = fe[:, 0], fe[:, 1]
        x = np.where(fhi < flo, hi, lo)
        f = np.minimum(flo, fhi)
        rows = np.arange(len(P)) if monotone is None else np.flatnonzero(~monotone)
        ii, xr, fr = self._polished_roots(P, A, lo, hi, rows)
        if ii.size:
            order = np.lexsort((fr, ii))              # the best root of every problem
            first = np.ones(len(order), dtype=bool)
            first[1:] = ii[order][1:] != ii[order][:-1]
            b = order[first]
            better = fr[b] < f[ii[b]]
            x[ii[b][better]], f[ii[b][better]] = xr[b][better], fr[b][better]
        return x, f

    def _polished_roots(self, P, A, lo, hi, rows):
        """The interior candidates of ``stationary_minimum`` for the problems ``rows``: the
        real roots of phi' inside the slot (and the real parts of near-double roots, which
        come out as complex pairs), each polished by three Newton steps that may not raise
        phi.  Returns their problem index, xi and phi (nothing to polish: no work)."""
        p, deg = self.p, 2 * self.p - 1
        none = (rows[:0], np.zeros(0), np.zeros(0))
        if rows.size == 0:
            return none
        Ar, Pr = A[rows], P[rows]
        D = Ar.copy()
        D[:, 0] -= Pr
        G = np.matmul(D, np.swapaxes(Ar, 1, 2))                       # D_i . A_j
        # phi' coefficients, summed row by row (a GEMM rounds a row by its place in the batch:
        # the roots of a point then depended on the points searched with it)
        c = np.einsum("nk,kj->nj", G.reshape(len(rows), -1), self._dphi.reshape(-1, 2 * p))
        lead = c[:, deg]
        big = np.abs(c).max(axis=1)
        # a (nearly) vanishing leading coefficient: its roots run off to infinity, those in
        # the slot barely move; keep the companion matrix finite
        tiny = np.abs(lead) < 1e-13 * big
        lead = np.where(tiny, np.where(lead < 0, -1.0, 1.0) * 1e-13 * np.maximum(big, 1e-300), lead)
        comp = np.zeros((len(rows), deg, deg))
        if deg > 1:
            comp[:, np.arange(1, deg), np.arange(deg - 1)] = 1.0
        comp[:, :, -1] = -c[:, :deg] / lead[:, None]
        roots = np.linalg.eigvals(comp)
        re = roots.real
        ir, jj = np.nonzero((np.abs(roots.imag) <= 1e-4 * (1.0 + np.abs(re)))
                            & (re > lo[rows][:, None]) & (re < hi[rows][:, None]))
        if ir.size == 0:
            return none
        xr = re[ir, jj]
        ii = rows[ir]
        Ai, Pi, loi, hii = A[ii], P[ii], lo[ii], hi[ii]
        fr = phi(xr, Ai, Pi)
        for _ in range(3):                     # polish (Newton steps that may not raise phi)
            _, g, H = phi_derivatives(xr, Ai, Pi)
            st = np.where(H > 0.0, -g / np.where(H > 0.0, H, 1.0), 0.0)
            xt = np.minimum(np.maximum(xr + st, loi), hii)
            ft = phi(xt, Ai, Pi)
            better = ft <= fr
            xr = np.where(better, xt, xr)
            fr = np.where(better, ft, fr)
        return ii, xr, fr

    # -- closest point of slave points --------------------------------------------------------
    def context(self, own_ids, x_own, other_ids, x_other, pairs, strand=None, nk=1):
        """Master pool (other first, then own; first occurrence wins), monomial coefficients,
        bounding spheres, and the candidate masters of every own element (``cand``, a row per
        own element in the order of the pairs, padded with -1).
        With ``strand`` (the strand of every pair, ``search.strand_index``) and nk strands the own
        elements are virtual: k no + e is strand k of own element e, with the candidates of e
        in strand k (own_ids and x_own repeated nk times)."""
        pool_ids, pool_x = master_pool(own_ids, x_own, other_ids, x_other)
        no = len(own_ids)
        oi = positions(own_ids, pairs[:, 0], "own")
        if strand is not None and nk > 1:
            oi = oi + no * np.asarray(strand, dtype=np.int64)
            own_ids = np.tile(own_ids, nk)
            x_own = np.tile(x_own, (nk, 1, 1))
        mi = positions(pool_ids, pairs[:, 1], "other")
        order = np.argsort(oi, kind="stable")
        count = np.bincount(oi, minlength=no * nk)
        # the candidates of every own element in the order of the pairs, padded with -1
        cand = np.full((no * nk, int(count.max(initial=0))), -1, dtype=np.int64)
        so = oi[order]
        cand[so, np.arange(len(so)) - (np.cumsum(count) - count)[so]] = mi[order]
        cen, rad = element_bounds(pool_x)
        return {"own_ids": own_ids, "x_own": x_own, "pool_ids": pool_ids, "pool_x": pool_x,
                "A_pool": np.einsum("ka,ead->ekd", self.C, pool_x), "cen": cen, "rad": rad,
                "cand": cand, "own_start": own_ids * self.h,
                "pool_start": pool_ids.astype(float) * self.h, "no": no}

    def find(self, ctx, o, xi, rival=False):
        """Closest admissible point of the slave points (own index o, slave xi) (M,) among the
        candidate elements of their element: d = 2 eps - g (-inf without candidate), m (pool
        index, -1 without), xi_m, interior, D = r(s) - r(sbar), g, and N, dN at xi.

        With ``rival``: also the runner-up, the nearest of the per-element minima whose kind
        (``kind``) is not the closest point's (no pruning then): rival_g (inf without one),
        rival_D, rival_kind, and kind (of the closest point)."""
        p, h = self.p, self.h
        M = len(o)
        NN = (powers(p, xi, 1).reshape(2 * M, p + 1) @ self.C).reshape(M, 2, p + 1)
        Ns, dNs = NN[:, 0], NN[:, 1]
        P = np.einsum("na,nad->nd", Ns, ctx["x_own"][o])
        s = ctx["own_start"][o] + (xi + 1.0) * (0.5 * h)
        res = {"d": np.full(M, -np.inf), "m": np.full(M, -1, dtype=np.int64), "xi_m": np.zeros(M),
               "interior": np.zeros(M, dtype=bool), "D": np.zeros((M, 3)), "g": np.full(M, np.inf),
               "N": Ns, "dN": dNs, "P": P}
        cand = ctx["cand"][o]                                        # (M, candidates)
        lo, hi, valid = self._slots(s[:, None] - ctx["pool_start"][cand])
        valid &= (cand >= 0)[:, :, None]
        pr_pt, c, slot = np.nonzero(valid)
        if pr_pt.size == 0:
            return res
        pr_m = cand[pr_pt, c]
        pr_lo, pr_hi = self._to_xi(lo[pr_pt, c, slot]), self._to_xi(hi[pr_pt, c, slot])
        A = ctx["A_pool"]
        Pp = P[pr_pt]
        point = None                  # with many slots: pruned, and bounded after the samples
        if not rival and len(pr_pt) > self.PRUNE:
            keep = self._prune(ctx, M, Pp, pr_pt, pr_m, pr_lo, pr_hi)
            pr_pt, pr_m, pr_lo, pr_hi, Pp = (a[keep] for a in (pr_pt, pr_m, pr_lo, pr_hi, Pp))
            point = pr_pt
        xm, f = self.project(Pp, A[pr_m], pr_lo, pr_hi, point)
        # global minimum per slave point (ties, e.g. a shared node: the first one only)
        best = _nearest_per_point(np.arange(len(f)), f, pr_pt)
        b = pr_pt[best]
        res["m"][b] = pr_m[best]
        res["xi_m"][b] = xm[best]
        res["interior"][b] = (xm[best] > pr_lo[best]) & (xm[best] < pr_hi[best])
        Dv = self._offset(ctx, P[b], pr_m[best], xm[best])
        g = np.sqrt(np.einsum("nd,nd->n", Dv, Dv))
        res["D"][b] = Dv
        res["g"][b] = g
        res["d"][b] = 2.0 * self.eps - g
        if rival:
            self._rival(ctx, res, P, pr_pt, pr_m, pr_lo, pr_hi, xm, f, b, best)
        return res

    def _prune(self, ctx, M, Pp, pr_pt, pr_m, pr_lo, pr_hi):
        """The slots (pr_*, sorted by slave point pr_pt) that may hold the closest point of
        their slave point Pp: a slot whose element's bounding sphere is farther from the slave
        point than the whole sphere of another slot's element cannot (exact: the projection of
        the kept slots gives the same closest points; only worth its cost when there are many
        slots).  The far side of a sphere bounds less tightly than the slot's ends did, but
        costs no evaluation of the element, and the slots it leaves are bounded again from
        their samples (``_bounded``): on the plectoneme's end loop and line contact, 10-20 %
        less time in ``find``."""
        dist = np.linalg.norm(Pp - ctx["cen"][pr_m], axis=1)
        lb = dist - ctx["rad"][pr_m]
        ub = dist + ctx["rad"][pr_m]
        first = np.flatnonzero(np.concatenate(([True], pr_pt[1:] != pr_pt[:-1])))
        best_ub = np.minimum.reduceat(ub, first)
        return lb <= np.repeat(best_ub, np.diff(first, append=len(ub))) * (1.0 + 1e-9) + 1e-300

    def _rival(self, ctx, res, P, pr_pt, pr_m, pr_lo, pr_hi, xm, f, b, best):
        """The runner-up of ``find`` (rival=True): among the per-element minima (pr_*, xm,
        f) of each slave point, the nearest one of another kind than the closest point's."""
        M = len(res["d"])
        kind = self._kind_at(ctx["pool_ids"][pr_m], xm, (xm > pr_lo) & (xm < pr_hi))
        best_kind = np.full(M, -1, dtype=np.int64)
        best_kind[b] = kind[best]
        other = np.flatnonzero(kind != best_kind[pr_pt])
        res["kind"] = best_kind
        res["rival_g"] = np.full(M, np.inf)
        res["rival_D"] = np.zeros((M, 3))
        res["rival_kind"] = np.full(M, -1, dtype=np.int64)
        if other.size == 0:
            return
        rv = _nearest_per_point(other, f, pr_pt)
        q = pr_pt[rv]
        Dv = self._offset(ctx, P[q], pr_m[rv], xm[rv])
        res["rival_D"][q] = Dv
        res["rival_g"][q] = np.linalg.norm(Dv, axis=1)
        res["rival_kind"][q] = kind[rv]

    def _offset(self, ctx, P, m, xm):
        """D = P - r_m(xm): from points P to the points xm of pool elements m."""
        Nm = powers(self.p, xm, 0)[:, 0] @ self.C
        return P - np.einsum("na,nad->nd", Nm, ctx["pool_x"][m])

    def kind(self, ctx, cl):
        """Canonical kind of the closest points: 2 k at master node k (an element end; both
        elements sharing the node give the same kind, so a tie between them is no change),
        2 m + 1 strictly inside element m, -2 - m on a bound inside element m (an exclusion
        boundary), -1 without a closest point.  A change of kind along s is a kink of d(s)
        (node, bound) or a jump of the closest point to another strand."""
        m = cl["m"]
        kind = self._kind_at(ctx["pool_ids"][np.maximum(m, 0)], cl["xi_m"], cl["interior"])
        return np.where(m >= 0, kind, -1)

    def _kind_at(self, e, xi, interior):
        """``kind`` of points xi of elements e (global ids), interior: strictly inside the
        slot."""
        node = np.where(xi <= -1.0, e, e + 1)
        if self.closed:
            node = np.mod(node, self.nelem)
        return np.where(interior, 2 * e + 1, np.where(np.abs(xi) >= 1.0, 2 * node, -2 - e))

