"""One load step as an energy minimisation: inertia-controlled Newton on the total energy
(the load stepping around it: load_path.py).

For conservative loads (dead forces, gravity, prescribed end positions and rotations, an
intrinsic twist ramp, contact) an equilibrium a user wants is a local minimum of the total
energy E (elastic + loads + contact + supports).  Each load step minimises it, in the
exponential chart of the current state (x = (r, theta), the update (r + dr, exp(dtheta^x) R)):

1. g = dE/dx, the residual (RodProblem.residual: Dirichlet rows hold x - target = 0 once the
   load is set), and H = d2E/dx2, the symmetric chart Hessian (RodProblem.jacobian with
   symmetric=True), assembled into an SBAIJ matrix kept with its MUMPS analysis
   (stability.Inertia).
2. The direction: Newton's d = -K^-1 g with the consistent tangent K (LU), kept when it
   descends (g . d < 0); away from equilibrium K and H differ by O(|g|) and Newton with K
   converges far better (Mattiasson's whole load: 9 iterations against 112).  Otherwise
   LDL^T of H + sigma M, M the lumped metric (nodal length m_i for positions, m_i l^2 for
   rotations, l the element length), sigma = 0 first.  Its inertia comes with the
   factorisation (MUMPS INFOG(12), the negative pivots).  While it has negative pivots sigma is
   raised (from half the last shift that worked in this load step, or 1e-8 |H| / |M|, times 4
   per try), as MeshFEM's Newton optimiser does, so d = -(H + sigma M)^-1 g descends.
3. At a saddle (negative pivots and a step too short to leave it) the lowest mode of
   H v = lambda M v, from inverse iteration on the same factor, is added, signed downhill.
4. Backtracking line search on E (Armijo, quadratic interpolation), within move limits: no
   node near a contact moves more than half the contact radius, no node anywhere more than
   half the clearance between strands that have come back toward each other
   (ContactTerm.clearance), no rotation more than MAX_ROTATION (RodProblem.longest_step),
   and the deepest penetration grows at most to twice itself or 2 % of the diameter.  A watchdog lets the energy rise
   over WATCHDOG_STEPS full Newton steps (a linearised step that turns a stiff rod stretches
   it); if they have not paid off, the search goes back and backtracks, and the load step
   takes no more free steps (every step since the reference point counts).  A first trial
   that falls by less than INTERPOLATE of the linear prediction is interpolated too, a full
   step that falls as if linear is extrapolated (EXTRAPOLATE); a Newton step the move
   limits cut below LIMITED is replaced by the step of K + sigma M that fits them
   (_limited_step).  So no strand passes through
   another and no rotation wraps: the link is kept.  A step whose energy change is below the
   energy's round-off is accepted when it lowers |g|.
   Before it, a full Newton step is tried along its curve (_curved): x + d + a/2, a the
   residual's second-order departure along d corrected in the modes stiffer than the step.
5. Where Newton's steps crawl along one soft mode (a ply sliding), the minimiser walks the
   valley floor by predictor-corrector (valley.py) and goes on from the walk's last point.
6. Converged when |g| <= tolerance (relative to the force scale, or the round-off floor of
   the residual) AND H itself (sigma = 0, the neutral band tau M aside: stability.neutral_shift) factors
   with no negative pivot: every converged step is a stable equilibrium, its inertia known
   from the factorisation the iteration makes anyway.  A near-zero positive eigenvalue (a ply
   sliding, a ring turning) is not an instability: convergence is judged on |g| only.
"""
import time

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from rodsnes import petsc_lib
from rodsnes.model.assembly import set_diagonal
from rodsnes.profiling import logged, timed
from rodsnes.model.scales import residual_floor
from rodsnes.solve.linear import LUChoice, direct_solver_defaults, failed_solve, set_up_ahead
from rodsnes.solve.stability import inertia_of, lumped_metric
from rodsnes.solve.valley import ValleyFollower

ARMIJO = 1e-4
# full Newton steps the watchdog lets the energy rise over before it goes back and searches
WATCHDOG_STEPS = 4
FREE_STEPS = True
LINE_SEARCH_TRIES = 30
# past -load_max_it, a minimisation goes on while the energy still falls by more than PROGRESS
# of its scale per max_it / 4 iterations, up to MAX_IT_FACTOR x max_it (_descending)
PROGRESS = 1e-9
MAX_IT_FACTOR = 10
VALLEY = True
# a Newton step the move limits cut below LIMITED is replaced by the shifted step that fits them
# (_limited_step), found in at most LIMITED_TRIES factorisations
LIMITED = 0.1
LIMITED_TRIES = 3
# the longest extrapolated step, in multiples of Newton's (1: none)
EXTRAPOLATE = 8.0
# a first trial that falls by less than this share of the linear prediction is interpolated too
INTERPOLATE = 0.25
# a full Newton step is first tried along its curve (_curved): its second-order departure
# measured at CURVE_H of the step, corrected in the modes stiffer than the step (CURVED: on)
CURVED = True
CURVE_H = 0.1
# seconds between the progress lines of a long load step (not with -quiet): a step that crawls
# for minutes said nothing (michell_contact on 40 quadratic elements: 2000 iterations at load
# 0.99, 300 s)
HEARTBEAT = 10.0


def _unit(v):
    """v scaled to unit length; a zero or non-finite v (a factor that overflowed: loads
    1e100 times the stiffness scale divided by zero here) becomes zero: no mode, which the
    saddle's escape then does not add."""
    n = v.norm()
    if n > 0.0 and np.isfinite(n):
        v.scale(1.0 / n)
    else:
        v.set(0.0)


def _quadratic_min(E0, slope, alpha, E):
    """The minimiser of the quadratic through E(0) = E0, E'(0) = slope and E(alpha) = E."""
    return -slope * alpha ** 2 / (2.0 * (E - E0 - slope * alpha))


def _depth_cut(depth0, depth, allow):
    """The factor on alpha after a trial that went deeper than ``allow``: where the deepest
    penetration, taken as linear in alpha from ``depth0`` (the iterate's; 0 where nothing
    touches there), has gone 0.9 of the way to the allowance, within [0.01, 0.5]; 0.5 where
    the trial is not deeper than that base.  Measured on PyElastica's plectoneme scene (40
    elements, no imperfection): 17 % of the line searches met the allowance, halving took
    3-6 trials there, and the line search cost 4.3 ms an iteration against 3.1 ms with this
    cut (one trial)."""
    base = max(depth0, 0.0) if depth0 is not None and np.isfinite(depth0) else 0.0
    rise = depth - base
    if not rise > 0.0:
        return 0.5
    return float(min(max(0.9 * (allow - base) / rise, 0.01), 0.5))


class MinimizeResult:
    """One load step's minimisation: load, converged, iterations, reason, |g| history, seconds,
    negative eigenvalues (of H at the last iterate), shifts (factorisations with sigma > 0),
    line-search cuts, saddle escapes, soft-valley points, steps shifted to fit the move
    limits, Newton steps taken along their curve (EnergyMinimizer._curved)."""

    def __init__(self, lam, converged, its, reason, history, seconds, nneg, shifts, cuts,
                 escapes, factorizations, valley_points=0, limited_steps=0, curved_steps=0):
        self.lam, self.converged, self.its, self.reason = lam, converged, its, reason
        self.history = np.asarray(history)
        self.fnorm = float(history[-1]) if len(history) else float("nan")
        self.seconds = seconds
        self.negative_eigenvalues = nneg
        self.shifts, self.line_search_cuts, self.escapes = shifts, cuts, escapes
        self.factorizations = factorizations
        self.valley_points = valley_points      # points of the soft-valley walks (valley.py)
        self.limited_steps = limited_steps      # Newton steps shifted to fit the move limits
        self.curved_steps = curved_steps        # Newton steps taken along their curve


class EnergyMinimizer:
    """Inertia-controlled Newton on the total energy at one load factor (module docstring)."""

    def __init__(self, problem, force_scale, rtol=1e-10, max_it=200, quiet=True, prefix=""):
        self.problem = problem
        self.prefix = prefix        # options prefix of the Newton step's KSP
        self.comm = problem.layout.comm.tompi4py()
        full = inertia_of(problem)
        # a planar run factors the in-plane block (planar.PlanarInertia), 3-D once it left it
        self.factor = full if problem.planar is None else problem.planar.inertia
        self.force_scale = force_scale
        self.tol = rtol * force_scale
        self.floor = residual_floor(problem.scene.rod)
        self.max_it = max_it
        self.quiet = quiet
        m = problem.mesh
        self.energy_scale = force_scale * m.length
        self.roundoff = 1e-12 * np.sqrt(m.nelem)       # relative round-off of an energy sum
        self.metric = self._metric()
        self.sigma_last = 0.0
        self.total_its = 0
        self.factorizations = 0
        # Newton steps tried and those whose linear solve failed (the iteration then takes the
        # Hessian's step), with the first failure's reason: Run warns when most of them failed
        self.newton_tries = self.newton_failures = 0
        self.newton_failure = None
        self._mode = None
        self._trial = None          # (E, depth) of the line search's last evaluated trial
        self.last = None
        self.ksp = None
        self.lu = None              # linear.LUChoice of the Newton step's KSP
        self.by_ksp = False         # the last Newton direction came from self.ksp's factor
        self.by_plane = False       # ... from the in-plane block's (planar.PlanarSystem)
        self.valley = ValleyFollower(self) if VALLEY else None

    def destroy(self):
        """Free the PETSc objects this minimiser made (its KSP, metric, kept mode)."""
        for obj in (self.ksp, self.metric, self._mode, self.valley):
            if obj is not None:
                obj.destroy()
        self.ksp = self._mode = None

    # -- pieces -----------------------------------------------------------------------
    def _metric(self):
        """Lumped metric M (a Vec): m_i for position rows, m_i h^2 for rotation rows (m_i =
        int N_i ds, h the element length), 1 on the Dirichlet rows (stability.lumped_metric)."""
        p = self.problem
        h = p.mesh.length / p.mesh.nelem
        M = p.layout.create_vec()
        M.setArray(lumped_metric(p, h * h).ravel())
        return M

    def _same(self, *values):
        """Rank 0's values on every rank: the decisions must agree bit for bit."""
        return self.comm.bcast(values if len(values) > 1 else values[0], root=0)

    @logged("MinGradient")
    def gradient(self):
        p = self.problem
        p.residual(None, p.state.X, p.F)
        return self._same(p.F.norm())

    def energy_at(self, X):
        """(total energy, deepest penetration or None) at the chart point X.  Collective."""
        p = self.problem
        r, q = p.state.local_config(X)
        shares, depth = p.trial(r, q)
        E = self.comm.allreduce(p.energy_local(r, q, shares))
        return self._same(E, depth)

    @logged("MinHessian")
    def _shifted_factor(self, nneg):
        """Factor H + sigma M with the smallest sigma of the sequence that has no negative
        pivot; returns sigma (inf when none up to 1e8 |H| / |M| does, nan when every
        factorisation failed: a solver that cannot factor H, MUMPS out of the memory an option
        allowed it - not a state without a positive definite shift)."""
        if nneg == 0:
            return 0.0
        scale = self._same(self.factor.diagonal.norm(PETSc.NormType.INFINITY)
                           / self.metric.norm(PETSc.NormType.INFINITY))
        sigma = max(0.5 * self.sigma_last, 1e-8 * scale)
        shift = self.metric.duplicate()
        failed = nneg < 0
        while sigma < 1e8 * scale:
            self.metric.copy(shift)
            shift.scale(sigma)
            n = self._same(self.factor.factor(shift))
            self.factorizations += 1
            failed = failed and n < 0
            if n == 0:
                shift.destroy()
                self.sigma_last = sigma
                return sigma
            sigma *= 4.0
        shift.destroy()
        return np.nan if failed else np.inf

    def _energy_roundoff(self, E0):
        """The round-off of an energy near E0 (absolute)."""
        return self.roundoff * (abs(E0) + self.energy_scale)

    def _above_roundoff(self, E0, change):
        """Whether an energy change of this size near E0 lies far (1e3 x) above the energy's
        round-off: only there may a decision depend on energies, the same on every rank."""
        return change > 1e3 * self._energy_roundoff(E0)

    def descends(self, E0, decrease):
        """Whether an energy decrease from E0 lies beyond the energy's round-off (the valley
        follower's walks and points: along a symmetry the energy changes by round-off alone)."""
        return decrease > self._energy_roundoff(E0)

    def metric_dot(self, a, b):
        """<M a, b>, the same on every rank.  Collective."""
        w = a.duplicate()
        w.pointwiseMult(self.metric, a)
        val = self._same(w.dot(b))
        w.destroy()
        return val

    def metric_normalise(self, v):
        """v scaled to |v|_M = 1 (unless 0); returns its former M-norm.  Collective."""
        n = np.sqrt(self.metric_dot(v, v))
        if n > 0:
            v.scale(1.0 / n)
        return n

    def zero_fixed(self, v):
        """The Dirichlet rows of v set to 0."""
        with v as a:
            a[self.problem.constraints.rows_local] = 0.0

    def inverse_iterate(self, solve, v, its, normalise):
        """its inverse iterations of A v = lambda M v on v in place: v <- A^-1 M v with
        ``solve(b, x)`` (x = A^-1 b, a factorisation's), the Dirichlet rows 0, then
        ``normalise(v)``.  Collective."""
        w = v.duplicate()
        for _ in range(its):
            w.pointwiseMult(self.metric, v)
            self.zero_fixed(w)
            solve(w, v)
            self.zero_fixed(v)
            normalise(v)
        w.destroy()

    def _forget_mode(self):
        if self._mode is not None:
            self._mode.destroy()
        self._mode = None

    def _oriented(self, v):
        """v with the sign that makes its largest entry positive (the entry of lowest natural
        number among those within 1e-6 of the largest in size): the same on any number of
        ranks, where the sign inverse iteration leaves is round-off.  Collective."""
        va = v.getArray(readonly=True)
        a = np.abs(va)
        top = self.comm.allreduce(float(a.max()) if len(a) else 0.0, op=MPI.MAX)
        if top == 0.0:
            return v
        nat = self.problem.layout.natural_rows(len(a))
        near = np.flatnonzero(a >= (1.0 - 1e-6) * top)
        first = near[np.argmin(nat[near])] if len(near) else None
        mine = (int(nat[first]), float(va[first])) if first is not None \
            else (np.iinfo(np.int64).max, 0.0)
        first = min(self.comm.allgather(mine))
        if first[1] < 0.0:
            v.scale(-1.0)
        return v

    def _lowest_mode(self, its=6):
        """Lowest mode of H v = lambda M v by inverse iteration on the current factor of
        H + sigma M (rows of Dirichlet dofs zero).  Collective."""
        p = self.problem
        v = p.F.duplicate()
        if self._mode is not None and self._mode.getSize() == v.getSize():
            self._mode.copy(v)
        else:
            # a seed of the unknowns' natural numbers: the same on any number of ranks (the
            # mode's sign, which decides the branch at a symmetric saddle: _oriented)
            idx = p.layout.natural_rows(v.getLocalSize()).astype(float)
            v.setArray(np.sin(12.9898 * idx + 0.5) * 43758.5453 % 1.0 - 0.5)
        self.inverse_iterate(self.factor.solve, v, its, _unit)
        if self._mode is not None:
            self._mode.destroy()
        self._mode = v.copy()
        return v

    def _move(self, d, rows=None):
        """(largest translation, largest rotation) of the nodal step d (owned nodes ``rows``:
        all by default), over all ranks (RodProblem.largest_moves)."""
        return self.problem.largest_moves(d, rows)

    def _descending(self, energies, its):
        """Past -load_max_it iterations, whether the minimisation is still going somewhere:
        over the last quarter of max_it iterations the energy fell by more than PROGRESS of its
        scale (a jump past a fold: the minimum the step started near is gone, and the descent to
        the next one takes hundreds of iterations; cutting the increment back would only return
        to the fold).  Never beyond MAX_IT_FACTOR x max_it."""
        window = max(10, self.max_it // 4)
        if its >= MAX_IT_FACTOR * self.max_it or len(energies) <= window:
            return False
        drop = energies[-window - 1] - energies[-1]
        return bool(drop > PROGRESS * (abs(energies[-1]) + self.energy_scale))

    def _longest_step(self, d, most=1.0, reach=1.0):
        """The largest multiple (<= most) of d within the move limits (module docstring, 4.;
        RodProblem.longest_step), the contact's (half its radius) taken ``reach`` times."""
        return self.problem.longest_step(d, most, reach)

    # -- one load step ----------------------------------------------------------------
    @logged("MinStep")
    def solve_at(self, lam):
        """Minimise the energy at load factor lam from the current state (the Dirichlet values
        set first).  Returns a MinimizeResult; the state is the last iterate."""
        p = self.problem
        t0 = time.perf_counter()
        p.set_load(lam)
        X, g = p.state.X, p.F
        # a shift remembered from an earlier load step over-damps this one: a rotational
        # negative pivot (rotation rows of M are m h^2) needs sigma ~ the diagonal, which then
        # held the translations back step after step (the plectoneme crawled at 7.23 turns;
        # reset, it went on to 8 turns)
        self.sigma_last = 0.0
        # nor does a load step start from an earlier one's lowest mode (_lowest_mode): what a
        # step does depends on its start state alone, which result.h5 holds, so that a restart
        # takes the steps the run took
        self._forget_mode()
        free_ok = FREE_STEPS           # free steps, until the watchdog has once gone back
        d = X.duplicate()
        Xt = X.duplicate()
        hist = []
        energies = []               # E at every iterate: is the minimisation still descending?
        its = shifts = cuts = escapes = free_steps = valley_points = limited = curved = 0
        if self.valley is not None:
            self.valley.start()
        nneg, reason, prev = -1, "iteration limit", np.inf
        watch = None                # the watchdog's reference point (module docstring, 4.)
        accepted = None             # (E, depth) of the step just taken, at the new iterate
        beat = t0                   # the last progress line (HEARTBEAT)
        while True:
            # the PETSc objects the last iteration dropped (a valley walk's snapshots, a
            # watchdog's reference point), destroyed (petsc_lib.release_garbage: 10 us, 30 on
            # 2 ranks)
            petsc_lib.release_garbage(p.layout.comm)
            p.state.recentre()
            p.ensure_pattern()
            gnorm = self.gradient()
            hist.append(gnorm)
            if not self.quiet and time.perf_counter() - beat >= HEARTBEAT:
                beat = time.perf_counter()
                self._progress(lam, its, gnorm, energies, beat - t0)
            if not np.isfinite(gnorm):
                reason = "not finite"
                break
            small = gnorm <= self.tol or (gnorm <= self.floor and gnorm > 0.1 * prev)
            newton = not small and self._newton_step(g, d)
            if newton and self.by_ksp and watch is None and self.valley is not None \
                    and self.valley.wants(its, d):
                walk = self.valley.follow(d)
                its += walk.its
                self.valley.walked(its, walk)
                cuts += walk.cuts
                valley_points += walk.points
                accepted = None
                continue        # from the walk's last point, or the state it went back to
            if not newton:
                with timed("MinHessian"):
                    self.factor.assemble(p.patterns)
                    nneg = self._same(self.factor.factor())
                self.factorizations += 1
                if small and nneg == 0:
                    reason = "converged"
                    break
            if its >= self.max_it and not self._descending(energies, its):
                break
            prev = gnorm
            if not newton:
                sigma = self._shifted_factor(nneg) if nneg != 0 else 0.0
                if np.isnan(sigma):
                    reason = ("the Hessian's factorisation failed at every shift, see its "
                              "solver's -stability_* or -planar_stability_* options: MUMPS's "
                              "memory, mat_mumps_icntl_14 or 23")
                    break
                if not np.isfinite(sigma):
                    reason = "no positive definite shift"
                    break
                shifts += sigma > 0
                self.factor.solve(g, d)
                d.scale(-1.0)
                if nneg != 0:
                    d, escaped = self._escape(d, g)
                    escapes += escaped
            slope = self._same(g.dot(d))
            alpha = self._longest_step(d)
            if newton and self.by_ksp and alpha < LIMITED:
                slope, alpha = self._limited_step(g, d, slope, alpha)
                limited += 1
            # the energy here was the accepted trial's of the last iteration (the same chart
            # point; recentre moves it by round-off only): one evaluation fewer per iteration
            E0, depth0 = accepted if accepted is not None else self.energy_at(X)
            accepted = None
            energies.append(E0)
            if watch is not None and E0 <= watch["E"] + ARMIJO * watch["alpha"] * watch["slope"]:
                watch = None                    # the free steps have paid off
            if watch is not None and watch["steps"] >= WATCHDOG_STEPS:
                p.state.restore(watch["snap"])  # they have not: back, and search the line
                watch["d"].copy(d)
                X.copy(Xt)
                slope, alpha, E0, depth0 = watch["slope"], watch["alpha"], watch["E"], watch["depth"]
                watch["d"].destroy()
                watch, free, reverted = None, False, True
                free_ok = False                 # the same free step would come again
            else:
                free, reverted = free_ok, False
            if newton and (self.by_ksp or self.by_plane) and alpha == 1.0 and CURVED \
                    and not reverted and self._curved(X, Xt, d, slope, E0, depth0):
                curved += 1                     # d is the curved step now, Xt its point
                ok, alpha, tries = True, 1.0, 0
            else:
                ok, alpha, tries = self._line_search(X, Xt, d, slope, alpha, gnorm, E0, depth0,
                                                     free=free)
            cuts += tries
            if ok == "free":                    # a full step that has not lowered E (yet)
                if watch is None:
                    watch = {"snap": p.state.snapshot(), "d": d.copy(), "slope": slope,
                             "alpha": alpha, "E": E0, "depth": depth0, "steps": 0}
                free_steps += 1
            elif not ok:
                reason = "line search"
                break
            if watch is not None:
                # every step since the reference point counts, not only the free ones: a step
                # that lowers E from a risen E0 has not paid the rise off
                watch["steps"] += 1
            X.axpy(alpha, d)               # Xt, bit for bit: the trial's energy is the new E0
            accepted = self._trial
            its += 1
        if watch is not None:
            watch["d"].destroy()
        d.destroy()
        Xt.destroy()
        self.total_its += its
        res = MinimizeResult(lam, reason == "converged", its, reason, hist,
                             time.perf_counter() - t0, nneg, shifts, cuts, escapes,
                             self.factorizations, valley_points, limited, curved)
        self.last = res
        return res

    def _progress(self, lam, its, gnorm, energies, seconds):
        """A progress line of a long load step (HEARTBEAT), on the first rank."""
        if self.comm.Get_rank() == 0:
            energy = f", E {energies[-1]:+.6e}" if energies else ""
            print(f"  load {lam:.6f}: {its} iterations in {seconds:.0f} s, |g| {gnorm:.3e}"
                  f"{energy}", flush=True)

    @logged("MinNewton")
    def _newton_step(self, g, d):
        """d = -K^-1 g with the consistent tangent K (LU); True when d is a descent direction
        of the energy (g . d < 0), else the step comes from the symmetric Hessian."""
        p = self.problem
        self.by_ksp = self.by_plane = False
        self.newton_tries += 1
        if p.planar is not None and p.planar.holds(g):
            # the in-plane block of K (planar.py: the 3-D step, whose out-of-plane part is 0)
            self.factorizations += 1
            if not p.planar.tangent_solve(g, d):
                return self._newton_failed(f"the in-plane solve failed: {p.planar.failure}")
            self.by_plane = True
            d.scale(-1.0)
            slope = self._same(g.dot(d))
            return bool(np.isfinite(slope) and slope < 0.0)
        ksp = self.tangent()
        try:
            ksp.solve(g, d)
        except PETSc.Error as err:
            return self._newton_failed(failed_solve(ksp, err))
        if ksp.getConvergedReason() < 0:
            return self._newton_failed(failed_solve(ksp))
        self.by_ksp = True
        d.scale(-1.0)
        slope = self._same(g.dot(d))
        return bool(np.isfinite(slope) and slope < 0.0)

    def _newton_failed(self, reason):
        """A Newton step whose linear solve failed: counted, the first reason kept; False."""
        self.newton_failures += 1
        if self.newton_failure is None:
            self.newton_failure = reason
        return False

    def _limited_step(self, g, d, slope, alpha):
        """Newton's step d that the move limits cut to alpha < LIMITED replaced by the step
        of K + sigma M, d = -(K + sigma M)^-1 g, with sigma such that it fits them, as a trust
        region's step does: the cut Newton step corrects the stiff modes (stretching, contact)
        by the same fraction alpha as the soft ones whose length the limits cut, the shifted
        step corrects them whole and shortens only the modes softer than sigma.  sigma starts
        from d's Rayleigh quotient -g.d / d.M d times (1/alpha - 1) (Newton's length shrunk
        to the limit along one soft mode) and grows while the step is still cut below 1/2,
        at most LIMITED_TRIES factorisations.  Kept only when it descends and is cut less;
        returns (slope, alpha) of the step taken (in d).  Collective."""
        p = self.problem
        dMd = self.metric_dot(d, d)
        if not dMd > 0.0:
            return slope, alpha
        sigma = -slope / dMd * (1.0 / alpha - 1.0)
        trial = d.duplicate()
        try:
            for _ in range(LIMITED_TRIES):
                if not (np.isfinite(sigma) and sigma > 0.0):
                    break
                if not self._shifted_solve(sigma, g, trial):
                    break
                trial.scale(-1.0)
                s2 = self._same(g.dot(trial))
                a2 = self._longest_step(trial)
                if not (np.isfinite(s2) and s2 < 0.0) or a2 <= alpha:
                    break
                trial.copy(d)
                slope, alpha = s2, a2
                if a2 >= 0.5:
                    break
                sigma *= 1.0 / a2
        finally:
            trial.destroy()
            self.by_ksp = False         # the KSP's factor is no longer K's
        return slope, alpha

    @logged("MinCurved")
    def _curved(self, X, Xt, d, slope, E0, depth0):
        """Newton's full step d (K d = -g, the KSP holding K's factor) tried along its curve,
        x + d + a / 2: where strands slide along each other (or a stretched piece turns) the
        residual departs from Newton's linear prediction (1 - t) g along x + t d at second
        order, C t^2 with C = D^2 g[d, d] (the plectoneme's crawl: 27-30 x more from the
        contact than from the rod), and the stiff terms answer it with an energy that the
        straight step climbs: the line search then keeps a tenth to a third of it, iteration
        after iteration.  C from the residual at CURVE_H of the step, C = 2 (g(x + h d) -
        (1 - h) g) / h^2; a = -(K + sigma M)^-1 C corrects it in the modes stiffer than sigma
        only (the soft ones, along which the plain K^-1 C is 10-100 x the step, keep Newton's
        step): sigma = sqrt(lambda_d lambda_max), halfway on a log scale between the step's
        own curvature lambda_d = -g.d / d.M d and the stiffest diagonal lambda_max =
        max K_ii / M_ii.  Kept when it meets Armijo's condition within the move limits and
        the depth allowance: then d holds the curved step, Xt and self._trial its point.
        Costs a residual, a factorisation and a trial energy; measured on every load step of
        a plectoneme run from its stored start: 3154 -> 2455 iterations (70 % of the curved
        trials kept).  Collective."""
        p = self.problem
        if not self._above_roundoff(E0, -slope):
            return False
        h = CURVE_H
        c, a = X.duplicate(), X.duplicate()
        try:
            X.copy(Xt)
            Xt.axpy(h, d)
            p.residual(None, Xt, c)
            if not np.isfinite(c.norm()):               # beyond the contact's wall
                return False
            c.axpy(-(1.0 - h), p.F)
            c.scale(2.0 / (h * h))
            lam_max = self._stiffest()
            dMd = self.metric_dot(d, d)
            if not (dMd > 0.0 and lam_max > 0.0):
                return False
            sigma = np.sqrt(-slope / dMd * lam_max)
            if not self._shifted_solve(sigma, c, a):
                return False
            a.scale(-0.5)
            self.zero_fixed(a)
            a.axpy(1.0, d)                                  # the curved step d + a / 2
            if self._longest_step(a) < 1.0:
                return False
            X.copy(Xt)
            Xt.axpy(1.0, a)
            E, depth = self.energy_at(Xt)
            allow = p.depth_allowed(depth0) if depth0 is not None else None
            if not (np.isfinite(E) and E <= E0 + ARMIJO * slope
                    and (allow is None or depth <= allow)):
                return False
            a.copy(d)
            self._trial = (E, depth)
            return True
        finally:
            c.destroy()
            a.destroy()

    def _stiffest(self):
        """max K_ii / M_ii of the Newton step's matrix (K, or its in-plane block after a planar
        step): the stiffest scale.  Collective."""
        planar = self.problem.planar if self.by_plane else None
        K = self.problem.J if planar is None else planar.J
        M = self.metric if planar is None else planar.restrict(self.metric)
        ratio = K.getDiagonal()
        ratio.pointwiseDivide(ratio, M)
        out = self._same(ratio.max()[1])
        ratio.destroy()
        if planar is not None:
            M.destroy()
        return out

    def _shifted_solve(self, sigma, b, x):
        """x = (K + sigma M)^-1 b with the Newton step's matrix K (the KSP's, or the in-plane
        block's after a planar step; the Dirichlet rows unshifted), K restored after; its
        factor is then no longer K's.  True when the solve succeeded.  Collective."""
        p = self.problem
        planar = p.planar if self.by_plane else None
        shift = self.metric.duplicate()
        self.metric.copy(shift)
        shift.scale(sigma)
        self.zero_fixed(shift)
        if planar is not None:
            full, shift = shift, planar.restrict(shift)
            full.destroy()
        K = p.J if planar is None else planar.J
        set_diagonal(K, shift, add=True)
        self.factorizations += 1
        if planar is not None:
            ok = planar.solve_block(b, x)
        else:
            self.ksp.setOperators(K)
            try:
                self.ksp.solve(b, x)
                ok = self.ksp.getConvergedReason() >= 0
            except PETSc.Error:
                ok = False
        shift.scale(-1.0)
        set_diagonal(K, shift, add=True)                                 # K again
        shift.destroy()
        self.by_ksp = self.by_plane = False
        return ok

    def tangent(self):
        """The consistent tangent K at the state, set on the Newton step's KSP (the solver
        choice checked for its pattern): its next solve factors it.  Returns the KSP."""
        p = self.problem
        p.jacobian(None, p.state.X, p.J, p.J)
        ksp = self._ksp()
        ksp.setOperators(p.J)
        self.lu.check(ksp, p)
        self.factorizations += 1
        return ksp

    def _ksp(self):
        """The Newton step's KSP, made at the first call: the Newton path's linear solver
        (preonly + LU, solve/linear.py, unless -ksp_type, -pc_type,
        -pc_factor_mat_solver_type ... say otherwise)."""
        if self.ksp is None:
            self.lu = LUChoice(direct_solver_defaults(self.problem, self.prefix))
            ksp = self.ksp = PETSc.KSP().create(comm=self.problem.layout.comm)
            ksp.setOptionsPrefix(self.prefix)
            ksp.setFromOptions()
        return self.ksp

    def setup(self):
        """Before the path (Run, in the log stage profiling.SET_UP): the Newton step's matrix,
        its KSP, and its LU's choice and plan for the present pattern (linear.set_up_ahead),
        and the Hessian's matrix and LDL^T plan (stability.Inertia.setup); planar.
        PlanarSystem.setup for a run in its plane, its out-of-plane count's too.
        Collective."""
        p = self.problem
        if p.planar is not None and p.planar.active:
            p.planar.setup(counts=True)
            return
        set_up_ahead(self._ksp(), self.lu, p, p.J)
        self.factor.setup()

    def _escape(self, d, g):
        """At a saddle: add the lowest mode, signed downhill and scaled to move a node by
        1 % of the rod length (or half the contact radius), when the shifted Newton step moves
        no node by a tenth of that.  Returns (step, 1 if added)."""
        p = self.problem
        reach = 0.01 * p.mesh.length
        if p.step_limit:
            reach = min(reach, p.step_limit)
        t, _ = self._move(d)
        if t >= 0.1 * reach:
            return d, 0
        v = self._lowest_mode()
        try:
            return self._escape_along(d, g, v, reach)
        finally:
            v.destroy()

    def _escape_along(self, d, g, v, reach):
        """_escape's step along the lowest mode v (v signed by _oriented)."""
        tv, _ = self._move(v)
        if tv == 0.0:
            return d, 0
        # downhill; where g . v is below what it can tell (a symmetric saddle: either way is
        # a branch) the mode's own orientation, the same on any number of ranks
        v = self._oriented(v)
        gv = self._same(g.dot(v))
        # what g . v cannot tell: the dot product's round-off, 1e3 eps sum |g_i v_i|, and a
        # gradient at the tolerance (or the floor), whose direction is round-off itself
        ga, va = g.getArray(readonly=True), v.getArray(readonly=True)
        bound = (1e3 * np.finfo(float).eps * self._same(
            self.comm.allreduce(float(np.abs(ga * va).sum()), op=MPI.SUM))
            + max(self.tol, self.floor) * self._same(v.norm()))
        sign = -1.0 if gv > bound else 1.0
        d.axpy(sign * reach / tv, v)
        return d, 1

    def _extrapolate(self, X, Xt, d, slope, E1, E0, allow):
        """After a full step whose energy fell as if linear (by 0.9 of the slope or more: the
        quadratic model's curvature along d is too high, the step too short), the multiples
        2, 4, ... of d within the move limits, while the energy still falls.  Returns the
        accepted alpha (Xt and self._trial at it)."""
        best, E_best, trial = 1.0, E1, self._trial
        alpha = 2.0
        most = self._longest_step(d, most=EXTRAPOLATE)
        while alpha <= most:
            X.copy(Xt)
            Xt.axpy(alpha, d)
            E, depth = self.energy_at(Xt)
            if not (np.isfinite(E) and E < E_best and (allow is None or depth <= allow)):
                break
            best, E_best, trial = alpha, E, (E, depth)
            if E - E0 > 0.9 * alpha * slope:       # no longer linear: stop here
                break
            alpha *= 2.0
        if best != alpha:
            X.copy(Xt)
            Xt.axpy(best, d)
        self._trial = trial
        return best

    def _interpolate(self, X, Xt, d, slope, alpha, E1, E0, allow):
        """After a first trial that met Armijo's condition but fell by less than INTERPOLATE of
        the linear prediction (the step went past the minimum along d, and the next iterate's
        gradient bounces back), the minimiser of the quadratic through E0, the slope and E1
        too; the lower of the two is taken.  Returns alpha (Xt and self._trial at it)."""
        trial = self._trial
        aq = min(max(_quadratic_min(E0, slope, alpha, E1), 0.1 * alpha), 0.9 * alpha)
        X.copy(Xt)
        Xt.axpy(aq, d)
        E, depth = self.energy_at(Xt)
        if np.isfinite(E) and E < E1 and (allow is None or depth <= allow):
            self._trial = (E, depth)
            return aq
        X.copy(Xt)
        Xt.axpy(alpha, d)
        self._trial = trial
        return alpha

    @logged("MinLineSearch")
    def _line_search(self, X, Xt, d, slope, alpha, gnorm, E0, depth0, free=False):
        """Backtracking on the energy from X along d (module docstring, 4.); returns
        (accepted, alpha, tries), accepted = "free" for a full step taken on the watchdog's
        credit (``free``: allowed)."""
        p = self.problem
        allow = None
        if depth0 is not None:
            allow = p.depth_allowed(depth0)
        slack = self._energy_roundoff(E0)
        for k in range(LINE_SEARCH_TRIES):
            X.copy(Xt)
            Xt.axpy(alpha, d)
            E, depth = self.energy_at(Xt)
            if not np.isfinite(E):
                alpha *= 0.5
                free = False
                continue
            if allow is not None and depth > allow:
                # the step at which the depth, linear in alpha from depth0, has gone 0.9 of
                # the way to the allowance: one trial where halving took up to six
                alpha *= _depth_cut(depth0, depth, allow)
                free = False
                continue
            self._trial = (E, depth)
            if E <= E0 + ARMIJO * alpha * min(slope, 0.0):
                # (only where the predicted change is far above the energy's round-off: the
                # decision must not depend on it, nor differ between ranks)
                if k == 0 and self._above_roundoff(E0, -slope * alpha):
                    if EXTRAPOLATE and alpha == 1.0 and E - E0 <= 0.9 * slope:
                        alpha = self._extrapolate(X, Xt, d, slope, E, E0, allow)
                    elif INTERPOLATE and E - E0 > INTERPOLATE * alpha * slope:
                        alpha = self._interpolate(X, Xt, d, slope, alpha, E, E0, allow)
                return True, alpha, k
            if free:
                return "free", alpha, k
            if E <= E0 + slack:
                # a change at the energy's round-off: accept when the gradient falls
                p.residual(None, Xt, p.F)
                gt = self._same(p.F.norm())
                p.residual(None, X, p.F)
                if gt < gnorm:
                    return True, alpha, k
            if slope < 0.0:       # minimiser of the quadratic through E0, slope, E(alpha)
                alpha = min(max(_quadratic_min(E0, slope, alpha, E), 0.1 * alpha), 0.5 * alpha)
            else:
                alpha *= 0.5
        return False, alpha, LINE_SEARCH_TRIES
