#!/usr/bin/env python3
"""Independent reference for the planar self-contact case ``cases/rollup_contact.opts``.

numpy/scipy only (no rodsnes code), so the solver can be checked against it.

Problem.  Planar Reissner rod (extensible, shearable), length L, clamped at the origin along +x,
loaded at its free end by the moment M e_z; EI, EA, GA; contact radius eps: points at arclength
distance >= delta (the exclusion, default pi eps) must stay at least 2 eps apart (the
centreline-distance model of rodsnes, which gives the rod hemispherical end caps).  With
M = 1.1 * 2 pi EI / L the free rod would be a circle of curvature M/EI wound 1.1 times, its free
end passing the clamp.

Kinematics and constitutive law, d3 = (cos th, sin th), d1 = (-sin th, cos th):

    r' = (1 + n.d3 / EA) d3 + (n.d1 / GA) d1,      th' = m / EI,
    n' = 0  and  m' + (r' x n).e_z = 0   between point loads,

n, m the force and moment that the part (s, L] exerts on [0, s]; n(L) = the point force on the
free end, m(L) = M.

Mechanics of frictionless point contacts.  Contact forces are internal and pairwise opposite: a
pair (a, b), a < b, puts F on the strand at b and -F at a, F along the line of centres
r(b) - r(a) (frictionless: the gradient of the centreline distance, whether the closest points
are interior points or rod ends).  Balance of the piece [s, L]:

    n(s) = sum of F over the pairs with a <= s < b       (a force at a = 0 goes into the clamp)
    m(s) = M + sum over pairs with s < a of (r(b) - r(a)) x F  +  sum over a <= s < b of (r(b) - r(s)) x F

and (r(b) - r(a)) x F = 0, so before the first contact point n = 0, m = M: an exact circle arc of
curvature M/EI (no stretch, no shear), and between the contact points an elastica under the
constant force n = F.  For one pair (s_P, L), the free end resting on the point s_P of the first
turn, [0, s_P] is the circle and [s_P, L] the elastica.

What the solver shows.  The free end does NOT come to rest on the interior of the first turn: it
is stopped by the clamped end, cap against cap, before it can pass it (rodsnes, 32 cubic elements:
tip at (-0.1996, -0.0129), curvature M/EI at both ends and 0.59 at mid-length, |n| = 3.2 along
the whole rod, the contact zones at both rod ends only).  So s_P = 0 (the circle part shrinks to
nothing), s_t = L, the whole rod is one elastica under n = F with m(0) = m(L) = M, and in the
hard-contact limit (penalty mu -> infinity) the exact conditions are

    r(L) - r(0) = 2 eps e,   F = f e,  f >= 0         (2 equations for f and the unit vector e)

plus the closest-point inequalities t(0).e <= 0, t(L).e <= 0 and the gap >= 0 elsewhere (both
checked by ``Solution.clearance``).  Shooting unknowns (m(0), f, angle of e), residuals
(m(L) - M, r(L) - r(0) - 2 eps e); m(0) = M comes out, as derived.  The tip-on-the-first-turn
configuration (``solve_point_contact``, s_P unknown, F normal to the first turn at P) solves its
point-contact equations but fails the clearance check: the tip strand would pass through the
clamped end's cap.

Penalty (continuum, what rodsnes integrates with its contact zones).  With d = 2 eps - distance
and the line force mu <d> on every slave point, the end-to-end contact has d0 at the rod ends,
falling linearly into each strand: d = d0 - c1 s on the clamped strand, c1 = -t(0).e, and
d = d0 - c2 (L - s) on the free one, c2 = -t(L).e.  Both strands are slave, so the total force
(rodsnes' summary total_force) is

    f = mu d0^2 (1/c1 + 1/c2) / 2,     i.e. d0 = sqrt(2 f / (mu (1/c1 + 1/c2)))  ~ mu^(-1/2),

and the ends sit at 2 eps - d0 (``solve_end_contact_penalty``); curvature of the strands and the
spread of the force directions over the zone (length d0/c) change this by O(d0^2 / eps).

Fixed Gauss points (``-contact_zones 0``): the contact is carried by the first (or last) contact
Gauss point, s_q = 0.047 h from the rod end, pressed by the other end with the force mu d w J; the
exact solution of that discrete law is ``solve_contacts`` with the pair (s_q, L) or (0, L - s_q)
and the compliance 1/(mu w J) (``active_pairs``); it differs from the continuum by about s_q:
an O(h) error of the contact quadrature, not of the elements.

Command line:
    tools/planar_contact_reference.py [--case cases/rollup_contact.opts] [--branches]
                                      [--compare OUTDIR ...] [--json]
prints the reference (contact pairs, force, tip, clamp moment, strain energy, clearance) and, for
each OUTDIR of a solver run, the solver's numbers and its errors against the hard contact, the
penalty contact at the run's mu and (fixed Gauss points) the discrete contact law.  result.h5 and
summary.json are read with h5py and json.
"""
import argparse
import json
import math
import os
import shlex
import sys
from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import minimize, root

RTOL = 1e-12
ATOL = 1e-13


# ------------------------------------------------------------------------------------------------
# the rod
# ------------------------------------------------------------------------------------------------
@dataclass
class PlanarRod:
    L: float = 10.0
    EI: float = 100.0
    EA: float = 1e4
    GA: float = 1e4
    M: float = 1.1 * 2 * math.pi * 100.0 / 10.0
    eps: float = 0.1
    exclusion: float = None           # default pi eps (as in rodsnes)

    def __post_init__(self):
        if self.exclusion is None:
            self.exclusion = math.pi * self.eps

    @classmethod
    def from_opts(cls, path, **over):
        """Read length, EI, EA, GA, radius, end moment (z) from a PETSc options file."""
        vals = {}
        with open(path) as fh:
            for line in fh:
                tok = shlex.split(line.split("#", 1)[0])
                if tok:
                    vals[tok[0].lstrip("-")] = tok[1] if len(tok) > 1 else ""
        mz = float(vals["load_end_moment"].split(",")[2])
        if float(vals.get("contact_standoff", 0.0)):
            raise ValueError(f"{path}: -contact_standoff: the reference is of the law at the tube")
        eps = float(vals.get("contact_radius", vals["rod_radius"]))
        rod = cls(L=float(vals["rod_length"]), EI=float(vals["rod_EI"]), EA=float(vals["rod_EA"]),
                  GA=float(vals["rod_GA"]), M=mz, eps=eps,
                  exclusion=float(vals["contact_exclusion"]) if "contact_exclusion" in vals else None)
        for k, v in over.items():
            setattr(rod, k, v)
        return rod

    # --- planar Reissner equations with a constant internal force F -------------------------
    def rhs(self, s, y, F):
        th, m = y[2], y[3]
        c, sn = math.cos(th), math.sin(th)
        nt = F[0] * c + F[1] * sn              # n . d3
        nd = -F[0] * sn + F[1] * c             # n . d1
        a, b = 1.0 + nt / self.EA, nd / self.GA
        rx, ry = a * c - b * sn, a * sn + b * c
        return [rx, ry, m / self.EI, -(rx * F[1] - ry * F[0])]

    def circle(self, s, m=None):
        """Pure bending (n = 0) from the clamp: exact arc of curvature m/EI (default M/EI)."""
        k = (self.M if m is None else m) / self.EI
        s = np.asarray(s, float)
        th = k * s
        if abs(k) < 1e-300:
            return np.stack([s, 0 * s], -1), th
        return np.stack([np.sin(th) / k, (1 - np.cos(th)) / k], -1), th

    def strain_energy_density(self, th, m, F):
        c, sn = np.cos(th), np.sin(th)
        nt = F[0] * c + F[1] * sn
        nd = -F[0] * sn + F[1] * c
        return 0.5 * m ** 2 / self.EI + 0.5 * nt ** 2 / self.EA + 0.5 * nd ** 2 / self.GA


@dataclass
class Solution:
    """A reference equilibrium: point-contact pairs (a_k, b_k), a_k < b_k, with the force F_k on
    the strand at b_k and -F_k at a_k; n(s) = sum_k F_k [a_k <= s < b_k] (a force at a_k = 0
    goes into the clamp), so n = 0 (an exact circle arc of curvature m(0)/EI) before the first
    contact point and after the last one."""
    rod: PlanarRod
    kind: str
    pairs: list                   # [(a_k, b_k)]
    forces: np.ndarray            # (K, 2) force F_k on the b_k side
    m0: float                     # moment at the clamp
    segments: list = field(repr=False, default=None)   # [(s0, s1, n, dense solution)]

    @property
    def F(self):
        """Resultant contact force on the tip strand (the internal force between the contacts)."""
        return self.forces.sum(axis=0) if len(self.forces) else np.zeros(2)

    @property
    def f(self):
        return float(np.hypot(*self.F))

    @property
    def s_c(self):
        return min((a for a, _ in self.pairs), default=self.rod.L)

    @property
    def s_t(self):
        return max((b for _, b in self.pairs), default=0.0)

    def state(self, s):
        """(r (k,2), theta (k,), m (k,), n (k,2)) at arclengths s."""
        s = np.atleast_1d(np.asarray(s, float))
        r, th, m, n = np.zeros((len(s), 2)), np.zeros(len(s)), np.zeros(len(s)), np.zeros((len(s), 2))
        for i, (s0, s1, F, sol) in enumerate(self.segments):
            a = (s >= s0) & ((s < s1) | (i == len(self.segments) - 1))
            if np.any(a):
                y = sol(s[a])
                r[a], th[a], m[a], n[a] = y[0:2].T, y[2], y[3], F
        return r, th, m, n

    @property
    def tip(self):
        return self.state([self.rod.L])[0][0]

    @property
    def tip_angle(self):
        return float(self.state([self.rod.L])[1][0])

    def strain_energy(self, npts=2001):
        """int (m^2/EI + nt^2/EA + nd^2/GA)/2 ds (Simpson on each segment)."""
        from scipy.integrate import simpson
        E = 0.0
        for s0, s1, F, sol in self.segments:
            s = np.linspace(s0, s1, npts)
            y = sol(s)
            E += simpson(self.rod.strain_energy_density(y[2], y[3], F), x=s)
        return float(E)

    def curvature(self, s):
        return self.state(s)[2] / self.rod.EI

    def clearance(self, nsamp=1500):
        """min over admissible pairs (|s - sigma| >= exclusion) of |r(s) - r(sigma)| - 2 eps:
        dense sampling, then local minimisation of the smallest sampled pairs (bounded to the
        admissible set).  Returns (clearance, s, sigma)."""
        rod = self.rod
        s = np.linspace(0.0, rod.L, nsamp)
        r = self.state(s)[0]
        best = []
        for i0 in range(0, nsamp, 300):
            d = np.linalg.norm(r[i0:i0 + 300, None, :] - r[None, :, :], axis=2)
            ok = np.abs(s[i0:i0 + 300, None] - s[None, :]) >= rod.exclusion
            d = np.where(ok, d, np.inf)
            i, j = np.unravel_index(np.argsort(d, axis=None)[:4], d.shape)
            best += [(d[a, b], s[i0 + a], s[b]) for a, b in zip(i, j)]
        best.sort()
        out = (best[0][0] - 2 * rod.eps, best[0][1], best[0][2])

        def dist(x):
            if abs(x[0] - x[1]) < rod.exclusion:
                return 1e9
            rr = self.state(x)[0]
            return float(np.linalg.norm(rr[0] - rr[1]))

        h = rod.L / (nsamp - 1)
        for _, a, b in best[:6]:
            lo, hi = (max(0.0, a - 2 * h), min(rod.L, a + 2 * h)), (max(0.0, b - 2 * h), min(rod.L, b + 2 * h))
            res = minimize(dist, [a, b], method="L-BFGS-B", bounds=[lo, hi],
                           options=dict(ftol=1e-15, gtol=1e-12))
            if res.fun - 2 * rod.eps < out[0]:
                out = (float(res.fun - 2 * rod.eps), float(res.x[0]), float(res.x[1]))
        return out


# ------------------------------------------------------------------------------------------------
# shooting
# ------------------------------------------------------------------------------------------------
def integrate(rod, pairs, forces, m0, dense=False):
    """Reissner IVP from the clamp (r = 0, theta = 0, m = m0), piecewise constant n between the
    contact points.  Returns the segments [(s0, s1, n, sol)] (sol: dense output or None), the end
    state y(L) = (x, y, theta, m) and the states at the cuts {s: y(s)}.  Raises
    FloatingPointError for an absurd shooting iterate (forces above 1e4 EI/L^2, whose elastica
    would wind thousands of times, or a failed integration)."""
    forces = np.asarray(forces, float).reshape(-1, 2)
    if forces.size and (not np.all(np.isfinite(forces)) or np.abs(forces).max() > 1e4 * rod.EI / rod.L ** 2
                        or abs(m0) > 1e4 * abs(rod.M) + 1e4 * rod.EI / rod.L):
        raise FloatingPointError("shooting iterate out of range")
    cuts = sorted({0.0, rod.L, *[a for a, _ in pairs], *[b for _, b in pairs]})
    y = np.array([0.0, 0.0, 0.0, m0])
    segs, nodes = [], {0.0: y.copy()}
    for s0, s1 in zip(cuts[:-1], cuts[1:]):
        sm = 0.5 * (s0 + s1)
        F = sum((forces[k] for k, (a, b) in enumerate(pairs) if a <= sm < b), np.zeros(2))
        sol = solve_ivp(rod.rhs, (s0, s1), y, args=(F,), method="DOP853", rtol=RTOL, atol=ATOL,
                        dense_output=dense, max_step=rod.L / 8)
        if sol.status != 0:
            raise FloatingPointError(sol.message)
        y = sol.y[:, -1]
        nodes[s1] = y.copy()
        segs.append((s0, s1, F, sol.sol))
    return segs, y, nodes


def free_solution(rod):
    """No contact: the circle of curvature M/EI (shot, not closed form, to test the integrator)."""
    segs, _, _ = integrate(rod, [], [], rod.M, dense=True)
    return Solution(rod, "free", [], np.zeros((0, 2)), rod.M, segs)


def solve_contacts(rod, pairs, compliance=None, guess=None, kind="contacts"):
    """Equilibrium with the point-contact pairs ``pairs`` = [(a_k, b_k)] all active:

        |r(b_k) - r(a_k)| = 2 eps - c_k f_k,   F_k = f_k e_k,  e_k = (r(b_k) - r(a_k)) / |...|,

    c_k = ``compliance`` (0: hard contact, the penalty limit mu -> infinity; 1 / (mu w J): a
    penalty slave point of quadrature weight w J, the discrete contact law of rodsnes).
    Unknowns (m(0), f_k, angle of e_k); residuals (m(L) - M, the 2K vector conditions)."""
    pairs = [(float(a), float(b)) for a, b in pairs]
    K = len(pairs)
    c = np.zeros(K) if compliance is None else np.asarray(compliance, float).reshape(K)

    def unpack(z):
        e = np.stack([np.cos(z[2::2]), np.sin(z[2::2])], -1)
        return z[0], z[1::2], e

    def resid(z):
        m0, f, e = unpack(z)
        try:
            _, yL, nodes = integrate(rod, pairs, f[:, None] * e, m0)
        except FloatingPointError:
            return np.full(1 + 2 * K, 1e3)
        out = [(yL[3] - rod.M) / rod.M]
        for k, (a, b) in enumerate(pairs):
            d = nodes[b][0:2] - nodes[a][0:2] - (2 * rod.eps - c[k] * f[k]) * e[k]
            out += [d[0] / rod.L, d[1] / rod.L]
        return np.array(out)

    if guess is None:
        # the blocked roll-up: ~3 EI/L^2 pushing the tip back along -x, shared by the pairs
        guess = [rod.M] + [3.0 * rod.EI / rod.L ** 2 / K, math.pi] * K
    res = root(resid, guess, method="hybr", options=dict(xtol=1e-14))
    if np.abs(res.fun).max() > 1e-10:
        raise RuntimeError(f"contact shooting failed: {res.message}, residual {res.fun}")
    m0, f, e = unpack(res.x)
    if np.any(f < 0):
        raise RuntimeError(f"contact forces {f}: a pair pulls (not an active contact)")
    segs, _, _ = integrate(rod, pairs, f[:, None] * e, m0, dense=True)
    return Solution(rod, kind, pairs, f[:, None] * e, float(m0), segs)


def solve_end_contact(rod, s_c=0.0, s_t=None, compliance=0.0, guess=None):
    """One contact pair (s_c, s_t): by default the clamped end (s_c = 0) against the free end
    (s_t = L), the hard-contact limit of the continuum problem."""
    s_t = rod.L if s_t is None else s_t
    return solve_contacts(rod, [(s_c, s_t)], [compliance], guess, kind="end")


def solve_end_contact_penalty(rod, mu, guess=None):
    """Clamped end against free end under the continuum penalty law (module docstring): the ends
    at distance 2 eps - d0 with f = mu d0^2 (1/c1 + 1/c2) / 2, c1 = -t(0).e, c2 = -t(L).e; f is
    the total force int mu <d> ds over both strands (rodsnes' total_force)."""
    def parts(z):
        m0, f, a = z
        e = np.array([math.cos(a), math.sin(a)])
        return m0, f, e

    def resid(z):
        m0, f, e = parts(z)
        try:
            _, yL, _ = integrate(rod, [(0.0, rod.L)], [f * e], m0)
        except FloatingPointError:
            return np.full(3, 1e3)
        c1 = -e[0]
        c2 = -(math.cos(yL[2]) * e[0] + math.sin(yL[2]) * e[1])
        if f < 0 or c1 <= 0 or c2 <= 0:
            return np.full(3, 1e3)
        d0 = math.sqrt(2 * f / (mu * (1 / c1 + 1 / c2)))
        d = yL[0:2] - (2 * rod.eps - d0) * e
        return [(yL[3] - rod.M) / rod.M, d[0] / rod.L, d[1] / rod.L]

    if guess is None:
        h = solve_end_contact(rod)
        guess = [h.m0, h.f, math.atan2(h.F[1], h.F[0])]
    res = root(resid, guess, method="hybr", options=dict(xtol=1e-14))
    if np.abs(res.fun).max() > 1e-10:
        raise RuntimeError(f"penalty end-contact shooting failed: {res.message}, residual {res.fun}")
    m0, f, e = parts(res.x)
    segs, yL, _ = integrate(rod, [(0.0, rod.L)], [f * e], m0, dense=True)
    sol = Solution(rod, f"end, penalty mu={mu:g}", [(0.0, rod.L)], (f * e)[None, :], float(m0), segs)
    c1, c2 = -e[0], -(math.cos(yL[2]) * e[0] + math.sin(yL[2]) * e[1])
    sol.d0 = math.sqrt(2 * f / (mu * (1 / c1 + 1 / c2)))
    sol.penalty_energy = mu / 6 * sol.d0 ** 3 * (1 / c1 + 1 / c2)   # (mu/2) int <d>^2 ds
    return sol


def solve_point_contact(rod, side=+1, guess=None):
    """Free end against an INTERIOR point P = r(s_P) of the first turn, P the closest point
    (r(L) - r(P) normal to the first turn at P; side +1: the end inside the first turn, toward
    its centre of curvature, -1: outside).  Unknowns (m(0), f, s_P).  Its solutions fail the
    clearance check (the tip strand passes through the cap of the clamped end): not a branch."""
    def parts(z):
        m0, f, sP = z
        thP = m0 / rod.EI * sP                          # n = 0 on [0, s_P]: circle arc
        nu = side * np.array([-math.sin(thP), math.cos(thP)])
        return m0, f, sP, nu

    def resid(z):
        m0, f, sP, nu = parts(z)
        if not 0.0 < sP < rod.L:
            return np.full(3, 1e3)
        try:
            _, yL, nodes = integrate(rod, [(sP, rod.L)], [f * nu], m0)
        except FloatingPointError:
            return np.full(3, 1e3)
        d = yL[0:2] - nodes[sP][0:2] - 2 * rod.eps * nu
        return [(yL[3] - rod.M) / rod.M, d[0] / rod.L, d[1] / rod.L]

    if guess is None:
        guess = [rod.M, 1.0, 0.5 * (rod.L - 2 * math.pi * rod.EI / rod.M)]
    res = root(resid, guess, method="hybr", options=dict(xtol=1e-14))
    if np.abs(res.fun).max() > 1e-10:
        raise RuntimeError(f"point-contact shooting failed: {res.message}, residual {res.fun}")
    m0, f, sP, nu = parts(res.x)
    segs, _, _ = integrate(rod, [(sP, rod.L)], [f * nu], m0, dense=True)
    return Solution(rod, f"point(side={side:+d})", [(float(sP), rod.L)], (f * nu)[None, :], float(m0), segs)


# ------------------------------------------------------------------------------------------------
# solver output (h5py only) and comparison
# ------------------------------------------------------------------------------------------------
def read_solver(outdir):
    """Last complete step of a rodsnes run (h5py): node and quadrature-point fields, summary."""
    import h5py
    with h5py.File(os.path.join(outdir, "result.h5"), "r") as fh:
        g = fh["steps"][f"{int(fh.attrs['last_step']):05d}"]
        d = {k: g[k][()] for k in g}
        d["attrs"] = dict(g.attrs)
        d["nelem"] = int(fh.attrs["nelem"])
        d["order"] = int(fh.attrs["order"])
        d["length"] = float(fh.attrs["length"])
    with open(os.path.join(outdir, "summary.json")) as fh:
        d["summary"] = json.load(fh)
    return d


def active_pairs(d):
    """Fixed Gauss points only: the solver's active contact points as reference pairs.  A slave
    Gauss point s near the clamped end (s < L/2) is pressed by the free end (its closest point is
    the end itself), one near the free end by the clamped end; the penalty law there is
    F = mu d w J (w J = Gauss weight x h/2): the compliance 1/(mu w J).
    Returns [(a, b)], compliances, slave arclengths, slave forces."""
    L, ne = d["length"], d["nelem"]
    s, fc = np.asarray(d["qp_s"]), np.asarray(d["contact_force"])
    nq = len(s) // ne
    h = L / ne
    xg, wg = np.polynomial.legendre.leggauss(nq)
    mu = d["summary"]["contact"]["penalty"]
    pairs, comp, slaves, forces = [], [], [], []
    for q in np.nonzero(fc > 0)[0]:
        e = min(int(s[q] // h), ne - 1)
        xi = 2 * (s[q] - e * h) / h - 1
        w = wg[np.argmin(np.abs(xg - xi))] * 0.5 * h
        pair = (float(s[q]), L) if s[q] < 0.5 * L else (0.0, float(s[q]))
        slaves.append(float(s[q]))
        forces.append(float(fc[q] * w))
        if pair in pairs:            # the same pair seen from both ends: springs in parallel
            k = pairs.index(pair)
            comp[k] = 1.0 / (1.0 / comp[k] + mu * w)
        else:
            pairs.append(pair)
            comp.append(1.0 / (mu * w))
    return pairs, comp, slaves, forces


def solver_curvature(d):
    """Signed planar curvature at the nodes: e_z . R u (the spatial curvature vector)."""
    return np.einsum("nij,nj->ni", d["directors"], d["strain_u"])[:, 2]


def compare(rod, outdir, hard=None):
    """A solver run against the hard contact, the continuum penalty contact at the run's mu
    and, for fixed Gauss points (no contact zones), the exact solution of the discrete law."""
    d = read_solver(outdir)
    c = d["summary"]["contact"]
    mu = c["penalty"]
    hard = hard or solve_end_contact(rod)
    refs = [("hard", hard, 0.0), ]
    # fixed Gauss points (-contact_zones 0) iff the total force is the sum over the reported
    # Gauss points; with zone integration it is the integral over the zones
    pairs, comp, _, gforces = active_pairs(d)
    zones = not pairs or abs(sum(gforces) - c["total_force"]) > 1e-9 * c["total_force"]
    if zones:
        pen = solve_end_contact_penalty(rod, mu)
        refs.append(("penalty", pen, pen.penalty_energy))
    else:
        if pairs:
            g = [hard.m0, hard.f, math.atan2(hard.F[1], hard.F[0])] if len(pairs) == 1 else None
            law = solve_contacts(rod, pairs, comp, g, kind="Gauss-point law")
            fk = np.hypot(law.forces[:, 0], law.forces[:, 1])
            refs.append(("gauss", law, float(np.sum(0.5 * np.asarray(comp) * fk ** 2))))
    nodes_s = np.linspace(0.0, rod.L, len(d["positions"]))
    kap = solver_curvature(d)
    tip = d["positions"][-1, :2]
    out = dict(outdir=outdir, nelem=d["nelem"], order=d["order"], mu=mu, zones=zones,
               total_force=c["total_force"], penetration=-c["min_gap"], tip=tip.tolist(),
               energy=d["summary"]["energy"], newton_iterations=d["summary"]["newton_iterations"],
               load_steps=d["summary"]["load_steps"], wall_time_s=d["summary"].get("wall_time_s"),
               converged=d["summary"].get("converged"))
    for name, ref, e_pen in refs:
        fsum = float(np.hypot(ref.forces[:, 0], ref.forces[:, 1]).sum())
        out[name] = dict(f=fsum, tip=ref.tip.tolist(), m0=ref.m0, pairs=ref.pairs,
                         d0=getattr(ref, "d0", 0.0), energy=ref.strain_energy() + e_pen,
                         tip_err=float(np.linalg.norm(tip - ref.tip)),
                         force_err=abs(c["total_force"] - fsum) / fsum,
                         curvature_err=float(np.abs(kap - ref.curvature(nodes_s)).max()))
    return out


def report(ref, label):
    tip = ref.tip
    cl = ref.clearance()
    pr = ", ".join(f"({a:.6g}, {b:.6g})" for a, b in ref.pairs)
    print(f"{label}: pairs {pr}  |F| = {ref.f:.9f}  F = ({ref.F[0]:.9f}, {ref.F[1]:.9f})")
    print(f"    tip = ({tip[0]:.9f}, {tip[1]:.9f})  tip angle = {ref.tip_angle:.9f}  "
          f"m(0) = {ref.m0:.9f} (M = {ref.rod.M:.9f})  strain energy = {ref.strain_energy():.9f}")
    print(f"    clearance = {cl[0]:.3e} at (s, sigma) = ({cl[1]:.6f}, {cl[2]:.6f})")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    ap.add_argument("--case", default=os.path.join(here, "cases", "rollup_contact.opts"))
    ap.add_argument("--branches", action="store_true",
                    help="also solve the tip-on-first-turn branches (inside and outside)")
    ap.add_argument("--compare", nargs="*", default=[], help="solver output directories")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    rod = PlanarRod.from_opts(a.case)
    ref = solve_end_contact(rod)
    if not a.json:
        print(f"rod: L={rod.L} EI={rod.EI} EA={rod.EA} GA={rod.GA} M={rod.M} eps={rod.eps} "
              f"exclusion={rod.exclusion:.6f}  (free: {rod.M * rod.L / (2 * math.pi * rod.EI):.4f} turns)")
        report(ref, "end contact (hard)")
    if a.branches and not a.json:
        for side in (+1, -1):
            try:
                report(solve_point_contact(rod, side), f"tip on first turn, side {side:+d}")
            except RuntimeError as exc:
                print(f"tip on first turn, side {side:+d}: {exc}")
    rows = []
    for outdir in a.compare:
        o = compare(rod, outdir, ref)
        rows.append(o)
        if not a.json:
            print(f"{outdir}: nelem={o['nelem']} mu={o['mu']:.3g} zones={o['zones']} "
                  f"total_force={o['total_force']:.9f} penetration={o['penetration']:.4e} "
                  f"tip=({o['tip'][0]:.9f}, {o['tip'][1]:.9f})  {o['load_steps']} steps "
                  f"{o['newton_iterations']} its {o['wall_time_s']:.1f} s")
            for name in ("hard", "penalty", "gauss"):
                if name in o:
                    r = o[name]
                    print(f"    vs {name:7s}: |F| {r['f']:.9f} err {r['force_err']:.2e}  tip err "
                          f"{r['tip_err']:.2e}  curvature err {r['curvature_err']:.2e}  d0 {r['d0']:.4e}"
                          f"  energy {r['energy']:.7f} (solver {o['energy']:.7f})")
    if a.json:
        json.dump(rows, sys.stdout, indent=1)
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
