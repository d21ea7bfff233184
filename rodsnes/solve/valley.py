"""Walking a soft valley of the energy: predictor-corrector along the softest mode
(EnergyMinimizer calls it; docs/solver.md, "Soft valleys").

Where a ply lengthens or a loop slides, the minimum of a load step lies far along a valley
whose floor curves: one mode of K v = lambda M v is much softer than the rest (at 7.2 turns of
the plectoneme 5e-11 of the largest), the walls are the stiff modes (stretching, contact).
Newton's step is then almost all along the soft mode, the straight line leaves the curved
floor for a wall within a small fraction of it, and the line search takes the minimiser down
the valley by 1e-9 of the energy per iteration, for hundreds of iterations, each direction
turned by a tenth of a degree from the one before.

The follower walks the floor instead, as a continuation method traces a path:
1. the direction v: the softest mode of K v = lambda M v, by inverse iteration on the factor of
   the last Newton step (started from Newton's direction, which is nearly the mode), signed
   downhill, kept continuous from one point to the next;
2. the predictor x + s v + s^2/2 c, c = (v - v_before)/s_before the floor's curvature, within
   the line search's move limits, twice its contact limit (PREDICTOR_REACH), and no deeper
   into contact than the line search allows;
3. the corrector: the minimum of E on the hyperplane <M v, x - x_pred> = 0, by Newton with the
   bordered system [K, M v; (M v)^T, 0] (two solves with one factor of K), each step searched
   on the energy by the minimiser's line search, until the gradient's part in the hyperplane
   is a tenth of its part along M v;
4. a valley point is taken when its energy is lower than the last one's beyond the energy's
   round-off (EnergyMinimizer.descends: along a symmetry the energy changes by round-off alone,
   and the walk is declined where the linear model's descent at Newton's length is below it);
   s doubles after a corrector of at most two iterations and halves after one of
   CORRECTOR_ITS; a rejected point quarters s, and MISSES in a row end the walk;
5. where the slope along the floor, g . v, turns uphill, one last point where the slope,
   linear between the last two points, is zero.
It also ends where |g| is at tolerance, at a corrector that lowered the energy without
reaching the floor in CORRECTOR_ITS (its point is kept), or where the valley is lost (a
corrector that does not descend, a mode that turns by more than 60 degrees); the
minimiser then goes on from the last valley point with its own iterations, and only its own
test (|g| at tolerance and no negative pivot of H) ends the load step.
"""
import numpy as np
from petsc4py import PETSc

# iterations of a minimisation before it looks for a valley, and Newton directions in a row
# that must agree (cos >= ALIGNED in the metric M) before it walks one
VALLEY_AFTER = 6
ALIGNED_RUN = 3
ALIGNED = 0.99
# the least cos between Newton's direction and the softest mode for a walk (measured at 8.5
# turns: 0.976-0.988 where the crawl was along the softest mode, below 0.6 where it was not)
MODE = 0.9
# the predictor's move limit near contact, in multiples of the line search's (half the contact
# radius): a node moves at most one radius, so two strands cannot pass each other within one
# predictor without the predicted point showing the overlap (the depth allowance); the
# rotation limit and half the clearance elsewhere hold as in the line search
PREDICTOR_REACH = 2.0
CORRECTOR_ITS = 20
INVERSE_ITS = 2
MAX_POINTS = 200
# predictors rejected in a row before the follower gives up
MISSES = 2


class ValleyResult:
    """What one walk did: Newton iterations (corrector steps), valley points taken, rejected
    predictors, line-search cuts, and why it ended."""

    def __init__(self):
        self.its = self.points = self.rejected = self.cuts = 0
        # turned down before a predictor: Newton's direction is not the soft mode, or the valley
        # is flat (its descent below the energy's round-off: a symmetry)
        self.declined = False
        self.reason = ""


class ValleyFollower:
    """Predictor-corrector along the soft mode (module docstring) for one EnergyMinimizer."""

    def __init__(self, minimizer):
        self.m = minimizer
        self.prev = None        # the last Newton direction (M-normalised), for alignment
        self.run = 0            # Newton directions in a row aligned with the one before
        self.after = self.wait = VALLEY_AFTER

    def start(self):
        """A new minimisation: the first walk after VALLEY_AFTER iterations."""
        self.reset()
        self.after, self.wait = VALLEY_AFTER, VALLEY_AFTER

    def walked(self, its, walk):
        """After a walk that ended at iteration its: the next one as soon as Newton's
        directions agree again when it took valley points, or when it was declined before any
        predictor (Newton's direction not the soft mode, or a flat valley: two
        back-substitutions spent, again at the next 3 aligned directions); else no
        sooner than twice the last wait on (a fold or a snap is no valley: it is left to the
        minimiser).  Declined walks used to double the wait too: at 8.54 turns of the
        plectoneme, seven of them during a snap had pushed it to 192 iterations, and the
        crawl to the next minimum that followed, along the soft mode, waited 150 iterations
        for the walk that then took it there in 16."""
        self.reset()
        if walk.points:
            self.after, self.wait = its, VALLEY_AFTER
        elif walk.declined:
            self.after = its
        else:
            self.wait *= 2
            self.after = its + self.wait

    def reset(self):
        if self.prev is not None:
            self.prev.destroy()
        self.prev, self.run = None, 0

    def destroy(self):
        self.reset()

    def _unit(self, d):
        """A copy of d with its Dirichlet rows 0, M-normalised (the caller destroys it)."""
        u = d.copy()
        self.m.zero_fixed(u)
        self.m.metric_normalise(u)
        return u

    # -- when to follow --------------------------------------------------------------
    def wants(self, its, d):
        """Called with each Newton direction d: True when the minimisation has run
        VALLEY_AFTER iterations and its last ALIGNED_RUN directions agree (the crawl's
        signature).  Collective."""
        u = self._unit(d)
        if u.norm() == 0.0:
            u.destroy()
            self.reset()
            return False
        if self.prev is not None and abs(self.m.metric_dot(u, self.prev)) >= ALIGNED:
            self.run += 1
        else:
            self.run = 0
        if self.prev is not None:
            self.prev.destroy()
        self.prev = u
        return its >= self.after and self.run >= ALIGNED_RUN

    def _mode(self, ksp, v):
        """INVERSE_ITS inverse iterations of K v = lambda M v on the KSP's factor, from v (in
        place, M-normalised, Dirichlet rows 0)."""
        self.m.inverse_iterate(ksp.solve, v, INVERSE_ITS, self.m.metric_normalise)

    # -- the walk --------------------------------------------------------------------
    def follow(self, d):
        """Walk the valley from the current state, whose Newton direction d the minimiser's
        KSP has just solved for.  Returns a ValleyResult; the state is the last valley point
        (or unchanged).  Collective."""
        m = self.m
        p = m.problem
        X, g = p.state.X, p.F
        out = ValleyResult()
        u = self._unit(d)
        v = u.copy()
        self._mode(m.ksp, v)
        cos = abs(m.metric_dot(u, v))
        u.destroy()
        if cos < MODE:
            v.destroy()
            out.declined = True
            out.reason = "Newton's direction is not the soft mode"
            return out
        if m._same(g.dot(v)) > 0.0:
            v.scale(-1.0)
        # the first length: Newton's along the mode (the quadratic model's valley minimum)
        s = abs(m.metric_dot(d, v))
        E0, depth0 = m.energy_at(X)
        if not m.descends(E0, -s * m._same(g.dot(v))):
            # the linear model's descent along the mode at Newton's length is below the energy's
            # round-off: a symmetry (a ring turned about itself), not a valley to walk
            v.destroy()
            out.declined = True
            out.reason = "the valley is flat"
            return out
        Mv = v.duplicate()
        a, b, dc = v.duplicate(), v.duplicate(), v.duplicate()
        Xt = X.duplicate()
        bend = None             # the floor's curvature: (v - v_before) / s_before
        slope_before = m._same(g.dot(v))
        final = False           # the step back to the floor's minimum
        misses = 0              # predictors rejected in a row
        snap = None             # the state before this point's predictor
        try:
            while out.points < MAX_POINTS:
                cap = m._longest_step(v, most=PREDICTOR_REACH, reach=PREDICTOR_REACH)
                s = min(s, cap)
                if snap is not None:
                    snap[1].destroy()       # the last point's snapshot vector (not parked)
                snap = p.state.snapshot()
                # the predictor, no deeper into contact than the line search would go
                allow = p.depth_allowed(depth0) if depth0 is not None else None
                for _ in range(10):
                    X.copy(Xt)
                    Xt.axpy(s, v)
                    if bend is not None:
                        Xt.axpy(0.5 * s * s, bend)
                    Ep, depth = m.energy_at(Xt)
                    if np.isfinite(Ep) and (allow is None or depth <= allow):
                        break
                    s *= 0.5
                else:
                    out.reason = "no predictor within the contact allowance"
                    break
                X.axpy(s, v)
                if bend is not None:
                    X.axpy(0.5 * s * s, bend)
                ok, its, E1, depth1, gn = self._correct(v, Mv, a, b, dc, Xt, out)
                lower = m.descends(E0, E0 - E1)
                if not ok and lower and its > 0:
                    # short of the floor, but lower: the minimiser goes on from here
                    out.points += 1
                    out.reason = "the corrector stopped short of the floor"
                    break
                if not ok or not lower:
                    p.state.restore(snap)
                    out.rejected += 1
                    if final:
                        out.reason = "the floor turns uphill"
                        break
                    s *= 0.25
                    misses += 1
                    if misses >= MISSES or s < 1e-3 * cap or not ok and its == 0:
                        out.reason = "the corrector lost the valley"
                        break
                    continue
                out.points += 1
                misses = 0
                E0, depth0 = E1, depth1
                if gn <= m.tol:
                    out.reason = "gradient at tolerance"
                    break
                # the direction at the new point, continued from the last
                old = v.copy()
                self._mode(m.ksp, v)
                turn = m.metric_dot(v, old)
                if turn < 0.0:
                    v.scale(-1.0)
                if bend is None:
                    bend = v.duplicate()
                v.copy(bend)
                bend.axpy(-1.0, old)
                bend.scale(1.0 / s)
                old.destroy()
                if abs(turn) < 0.5:
                    out.reason = "the soft mode changed"
                    break
                if final:
                    out.reason = "at the floor's minimum"
                    break
                slope = m._same(g.dot(v))
                if slope >= 0.0:
                    # the minimum along the floor is behind: back to where the slope, linear
                    # between the last two points, is zero, and end there
                    back = s * slope / (slope - slope_before)
                    if back < 0.05 * s:
                        out.reason = "the floor turns uphill"
                        break
                    v.scale(-1.0)
                    s, final = back, True
                    continue
                slope_before = slope
                s *= 2.0 if its <= 2 else (0.5 if its >= CORRECTOR_ITS else 1.0)
            else:
                out.reason = "valley point limit"
        finally:
            for w in (Mv, a, b, dc, Xt, v, bend, snap and snap[1]):
                if w is None:
                    continue
                w.destroy()
        return out

    def _correct(self, v, Mv, a, b, dc, Xt, out):
        """Newton on E restricted to the hyperplane <M v, x - x_pred> = 0 from the predicted
        point (the state).  Returns (converged, iterations, E, depth, |g|) at the last iterate;
        the KSP keeps the factor of K at the last iterate it factored."""
        m = self.m
        p = m.problem
        X, g = p.state.X, p.F
        Mv.pointwiseMult(m.metric, v)
        m.zero_fixed(Mv)
        nn = m._same(Mv.dot(Mv))
        E, depth, gn = np.inf, None, np.inf
        accepted = None
        for k in range(CORRECTOR_ITS + 1):
            p.state.recentre()
            p.ensure_pattern()
            gn = m.gradient()
            if not np.isfinite(gn):
                return False, k, np.inf, None, gn
            gpar = m._same(g.dot(Mv)) / np.sqrt(nn)
            gperp = np.sqrt(max(gn * gn - gpar * gpar, 0.0))
            E, depth = accepted if accepted is not None else m.energy_at(X)
            if gperp <= max(m.tol, 0.1 * abs(gpar)) or gn <= m.tol:
                return True, k, E, depth, gn
            if k == CORRECTOR_ITS:
                return False, k, E, depth, gn
            # the bordered step: dc = -(a - mu b), K a = g, K b = M v, <M v, dc> = 0
            ksp = m.tangent()
            try:
                ksp.solve(g, a)
                ksp.solve(Mv, b)
            except PETSc.Error:
                return False, k, E, depth, gn
            if ksp.getConvergedReason() < 0:
                return False, k, E, depth, gn
            mu = m._same(Mv.dot(a)) / m._same(Mv.dot(b))
            a.axpy(-mu, b)
            a.copy(dc)
            dc.scale(-1.0)
            slope = m._same(g.dot(dc))
            out.its += 1
            if not (np.isfinite(slope) and slope < 0.0):
                return False, k + 1, E, depth, gn
            alpha = m._longest_step(dc)
            ok, alpha, tries = m._line_search(X, Xt, dc, slope, alpha, gn, E, depth)
            out.cuts += tries
            if ok is not True:
                return False, k + 1, E, depth, gn
            X.axpy(alpha, dc)
            accepted = m._trial
        return False, CORRECTOR_ITS, E, depth, gn
