"""Newton on R^3 x SO(3) with PETSc SNES, and load stepping in lambda with cut-back
(-load_path newton: loads without a potential, or a zero of the residual asked for).

SNES (newtonls) sees X = (r, theta); SNES.setUpdate re-centres the rotations before every
Newton step (slides "Newton method on C_a": (r, R) <- (r + eta, exp(theta^x) R)).  Defaults
(each overridable from the options database): full Newton steps (-snes_linesearch_type basic),
a direct solve -ksp_type preonly -pc_type lu with MUMPS, -snes_max_it 40, and the convergence
test of convergence_test: |F| below rtol (1e-10) times the force scale EI/L^2 + |loads|, or
below the roundoff floor of the residual (3 eps x largest stiffness x L/h_node x sqrt(nodes)),
or below -snes_atol; a solve that has not halved its best |F| in -load_stagnation_its (15)
iterations fails early (near a fold Newton 2-cycles between two residual levels until
-snes_max_it).
A load step that fails is cut back (halved) and retried from the last converged state;
successful steps grow the increment again (x1.5) up to the nominal one.  Each step starts from
the secant predictor through the last two converged states (-load_predictor 0: from the last
state), which keeps Newton on the branch it was following near limit and bifurcation points.
With -stability, every converged step also counts the negative eigenvalues of the energy
Hessian (stability.py); a step that arrives at a less stable equilibrium than it left is cut
back too, so an imperfect buckling path stays on its stable branch (a loss of stability that
survives all cut-backs is accepted and reported per step).  Where every cut-back fails (a fold
of the load path) the run ends there, or with -load_arclength the branch is followed around
the fold by pseudo-arclength continuation (arclength.py).
"""
import time

import numpy as np
from petsc4py import PETSc

from rodsnes.model.retraction import Retraction
from rodsnes.solve.arclength import Arclength
from rodsnes.solve.linear import (LUChoice, direct_solver_defaults, failed_solve,
                                  option_default, peek, set_up_ahead)
from rodsnes.solve.step import StepResult
from rodsnes.model.scales import residual_floor
from rodsnes.solve.stability import inertia_of, negative_eigenvalues

# the smallest penalty raise keep_penetration cuts a failed one back to (x mu)
RAISE_MIN = 1.1
# the largest turn of a prescribed end rotation (-bc_end_turns) in one load step: the end's
# rotation is set as a point of SO(3), which knows it only modulo a full turn, and Newton
# starts from the neighbouring nodes' rotations, so a step of more than half a turn would be
# taken the short way round (3 turns in one step gave the untwisted rod, 0.6 turns link -0.4)
MAX_TURN_STEP = 0.25

__all__ = ["NewtonSolver", "StepResult", "MAX_TURN_STEP"]


class NewtonSolver:
    def __init__(self, problem, force_scale, check_stability=False, conservative=True):
        self.problem = problem
        comm = problem.layout.comm
        option_default("snes_linesearch_type", "basic")
        # |F| is judged against rtol x force_scale (convergence_test), so the tolerance scales
        # with the problem; -snes_atol is an absolute test the user may add (0 by default:
        # PETSc's 1e-50 would accept at once a problem whose forces are all below it)
        option_default("snes_rtol", "1e-10")
        option_default("snes_atol", "0")
        option_default("snes_stol", "1e-16")
        option_default("snes_max_it", "40")
        self.lu = LUChoice(direct_solver_defaults(problem))
        snes = PETSc.SNES().create(comm=comm)
        snes.setType("newtonls")
        snes.setFunction(problem.residual, problem.F)
        # a run in its plane hands the SNES its in-plane operator (planar.attach, below): the
        # full Jacobian is made only if the run leaves the plane
        snes.setJacobian(problem.jacobian, problem.J if problem.planar is None else None)
        snes.setUpdate(self._update)
        snes.setConvergenceHistory(length=1000, reset=True)
        snes.setConvergenceTest(self.convergence_test)
        snes.setFromOptions()
        self.snes = snes
        problem.on_pattern_change = self.set_matrix
        if problem.planar is not None:      # linear solves on the in-plane block (planar.py)
            problem.planar.attach(self)
        # every full Newton step along the rod's retraction (model/retraction.py), where the
        # line search takes the step as it is (basic, its damping the step) and no term limits
        # the step's move: contact's limits bound the straight move, and the retraction's
        # correction, summed along the rod, moves the strands of a ply relative to each other
        # against the contact's stiffness (the 10-turn plectoneme's re-solve at a raised
        # penalty stagnated with it, converged in 37 iterations without)
        self.retraction = None
        kind, damping = _line_search(snes)
        if problem.scene.loads.retraction and kind == "basic" and not problem.step_limit:
            self.retraction = Retraction(problem)
            self.damping = damping
        if self.retraction is not None or problem.step_limit:
            snes.setLineSearchPreCheck(self._precheck)
        rod = problem.scene.rod
        # roundoff floor of the residual: strains of size ~1 (v3 = 1), differentiated over a
        # node spacing, times the largest stiffness, summed over the nodes; a residual at this
        # level is as converged as the arithmetic allows (DIVERGED_MAX_IT there would reject a
        # correct equilibrium).
        self.floor = residual_floor(rod)
        self.divtol = 1e12
        self.force_scale = force_scale
        ld = problem.scene.loads
        self.predictor = ld.predictor
        # a Newton solve that has not halved its best residual in this many iterations has
        # stalled (at a fold it 2-cycles between two residual levels for ever): give up early
        self.stagnation_its = ld.stagnation_its
        self.stagnated = False              # the last solve stopped at that test
        self.stagnations = 0                # solves stopped at it
        self.check_stability = check_stability
        # the inertia decides stability only where the loads have an energy (a step that lands
        # on more negative eigenvalues is cut back there alone: the 3-D helix's end moment
        # converged in 3 iterations and was cut back to a failure, exit 3)
        self.conservative = conservative
        self.f0 = None
        self.total_its = 0
        self.fail_reason = None             # why run() stopped early, when not a failed step
        # -load_arclength: at a fold, follow the branch around it (arclength.py)
        self.arclength = ld.arclength
        self.nominal = None                 # the nominal load increment of run()
        self._folds = []                    # (load, positions) where continuations started
        self.quiet = bool(getattr(getattr(problem.scene, "output", None), "quiet", False))
        self.results = []                   # StepResults of the last run()
        self.predictor_retries = 0          # failed predicted steps tried again from the last state

    def setup(self):
        """Before the path (Run, in the log stage profiling.SET_UP): PETSc's SNESSetUp, and the
        matrix the Newton step factors with its LU's choice and plan for the present pattern
        (linear.set_up_ahead; planar.PlanarSystem.setup for a run in its plane), and where
        every step is counted (-stability) the Hessian's for its count, which the first
        iteration and count then find made.  Collective."""
        p = self.problem
        self.snes.setSolution(p.state.X)    # the SNES's work vectors are made like it
        try:
            self.snes.setUp()
        except PETSc.Error:
            pass            # a -snes_type that cannot be set up so: its solve says it, a step
        if p.planar is not None and p.planar.active:
            p.planar.setup(counts=self.check_stability)
            return
        set_up_ahead(self.snes.getKSP(), self.lu, p, p.J)
        if self.check_stability:
            inertia_of(p).setup()

    def convergence_test(self, snes, it, norms):
        """SNES's convergence test (also the continuation corrector's): convergence relative to
        the problem's scale, so that a problem and its twin with every
        stiffness and load scaled by s take the same Newton path:
          |F| <= rtol F_scale (rtol = -snes_rtol, 1e-10; F_scale = the force scale EI/L^2 +
          |loads|; at iteration 0 a tenth of it; never above tolerance()) ->
          CONVERGED_FNORM_RELATIVE (relative to the force scale, not to |F_0|, which the
          load-step predictor can inflate by orders of magnitude);
          |F| <= -snes_atol (absolute, off unless given) -> CONVERGED_FNORM_ABS;
          |F| <= roundoff floor (proportional to the stiffness) once Newton stops gaining, or
          below a tenth of it -> CONVERGED_FNORM_ABS;
          NaN, blow-up beyond 1e12 |F_0|, no halving of |F| in -load_stagnation_its
          iterations, or max_it -> diverged."""
        fnorm = norms[2]
        R = PETSc.SNES.ConvergedReason
        if not np.isfinite(fnorm):
            return R.DIVERGED_FNORM_NAN
        if it == 0:
            self.f0 = fnorm
            self.fprev = np.inf
            self.fbest, self.best_it = fnorm, 0
            self.stagnated = False
        rtol, atol, _, maxit = snes.getTolerances()       # petsc4py's order: rtol first
        fprev, self.fprev = self.fprev, fnorm
        if fnorm <= atol:
            return R.CONVERGED_FNORM_ABS
        # never above tolerance(), the |F| the rest of the solver holds a step to
        if fnorm <= min((rtol if it > 0 else 0.1 * rtol) * self.force_scale, self.tolerance()):
            return R.CONVERGED_FNORM_RELATIVE
        # below the roundoff floor, accept once Newton has stopped gaining (|F| no longer falls
        # tenfold: an iterate that merely crossed the floor on its way down is not yet the most
        # accurate state the arithmetic allows), or an order of magnitude below it: there
        # Newton may only cycle (the perfect Michell ring on 16 elements: 1e-12 <-> 1e-10,
        # floor 2e-11, while the relative tolerance asks for 5e-14)
        if fnorm <= self.floor and (fnorm > 0.1 * fprev or fnorm <= 0.1 * self.floor):
            return R.CONVERGED_FNORM_ABS
        if fnorm > self.divtol * self.f0:
            return R.DIVERGED_DTOL
        if fnorm < 0.5 * self.fbest:
            self.fbest, self.best_it = fnorm, it
        elif self.stagnation_its and it - self.best_it >= self.stagnation_its:
            self.stagnated = True              # -load_stagnation_its: no progress, a failed step
            return R.DIVERGED_MAX_IT
        if it >= maxit:
            return R.DIVERGED_MAX_IT
        return R.CONVERGED_ITERATING

    def _precheck(self, X, Y):
        """SNES's line-search pre-check (its iterate X - Y): the step along the retraction,
        then the contact's step limits (RodProblem.precheck).  True when Y was changed."""
        changed = False
        if self.retraction is not None:
            self.retraction.retract_direction(X, Y, self.damping)
            changed = True
        if self.problem.step_limit:
            changed = self.problem.precheck(X, Y, self.snes.getFunction()[0]) or changed
        return changed

    def _update(self, snes, its):
        """Before every Newton step: the problem's update (the rotations re-centred), and for a
        new pattern whose LU fills much, MUMPS from now (linear.py)."""
        self.problem.update(snes, its)
        self.lu.check(snes.getKSP(), self.problem)

    def solve_at(self, lam):
        """Solve at load factor lam from the current state; returns a StepResult."""
        p = self.problem
        t0 = time.perf_counter()
        p.set_load(lam)
        self.snes.setConvergenceHistory(length=1000, reset=True)
        if p.planar is not None:
            p.planar.failure = None         # set by its solves that fail (the SNES's PC's)
        try:
            self.snes.solve(None, p.state.X)
            reason = self.snes.getConvergedReason()
        except PETSc.Error:
            reason = -100
        hist, _ = self.snes.getConvergenceHistory()
        self.last_history = np.array(hist)
        its = self.snes.getIterationNumber()
        ok = reason > 0 and np.all(np.isfinite(hist))
        fnorm = float(hist[-1]) if len(hist) else float("nan")
        R = PETSc.SNES.ConvergedReason
        if ok and not (reason in (R.CONVERGED_FNORM_ABS, R.CONVERGED_FNORM_RELATIVE)
                       and self.snes.getType() == PETSc.SNES.Type.NEWTONLS):
            # whatever the SNES (-snes_type) and the reason it gives, a step is converged only
            # where the residual at its state meets the tolerance: ksponly stops after one
            # linear solve and says CONVERGED_ITS (the roll-up left at the wrong tip, |F| NaN,
            # exit 0), a step test (-snes_stol) may stop short of it.  (Newton's line search
            # ending on convergence_test's own |F| test needs no second look.)
            p.residual(None, p.state.X, p.F)
            fnorm = float(p.F.norm())
            if not (np.isfinite(fnorm) and fnorm <= self.tolerance()):
                ok, reason = False, "residual above the tolerance"
        p.state.recentre()
        if not ok and self.stagnated:
            reason = "stagnation"
            self.stagnations += 1
        failure = None
        if reason == PETSc.SNES.ConvergedReason.DIVERGED_LINEAR_SOLVE:
            # the linear solve of a Newton step failed: why, in the user's options' words (an
            # iterative solve that did not converge said only "SNES reason -3")
            reason = "linear solve"
            failure = getattr(p.planar, "failure", None) or failed_solve(self.snes.getKSP())
        res = StepResult(lam, ok, its, reason, fnorm, np.array(hist), time.perf_counter() - t0)
        res.linear_failure = failure
        return res

    def run(self, lam0, steps, max_cutbacks, min_step, on_step=None, on_fail=None, nneg0=0,
            dlam0=None, prev0=None, arc0=None, stop=1.0):
        """Step lambda from lam0 to ``stop`` (-load_stop, 1 by default) on the grid of ``steps``
        nominal increments of 0 -> 1, with cut-back.  Returns (results, ok).

        on_step(result) is called after every converged step (write output there), on_fail(result,
        dlam) after every failed try (dlam = the increment about to be halved).  A predicted step
        that fails is tried once more from the last state before its first cut-back.
        nneg0: negative eigenvalues of the starting state (-stability: a restart from an
        unstable step does not take its own state for a loss of stability).
        dlam0, prev0: the first increment and the (snapshot, lambda) of the step before lam0,
        for a restart that takes the steps the interrupted run would have taken (every result
        carries next_increment, the increment its successor starts from).
        A step that fails at every cut-back (a fold: no equilibrium near the last one) ends the
        run, or with -load_arclength is passed by pseudo-arclength continuation
        (arclength.Arclength.around: the branch followed around the fold, through its unstable
        part, until it goes on stable with the load increasing); arc0: a restart inside that
        continuation (the fold's load; dlam0 is then its next arclength increment)."""
        p = self.problem
        self.fail_reason = None
        # the same load grid when a run is restarted from lam0; no step turns a prescribed end
        # by more than MAX_TURN_STEP (a rotation is known only modulo a full turn on SO(3))
        nominal = self.nominal = min(1.0 / steps, p.constraints.max_load_increment(MAX_TURN_STEP))
        if nominal < 1.0 / steps:
            n = int(np.ceil(1.0 / nominal - 1e-9))
            self.say(f"  -bc_end_turns {p.scene.bc.end_turns:g}: load steps of at most "
                     f"{MAX_TURN_STEP:g} turn ({n} steps from 0 to 1)")
        lam, dlam = lam0, (nominal if dlam0 is None else min(nominal, dlam0))
        cutbacks = 0
        results = self.results = []
        prev = prev0           # (snapshot, lambda) of the previous converged step
        nneg = int(nneg0)      # negative eigenvalues of the last converged step (-stability)
        p.ease_walls(lam, stop, self.say)    # a restart from a state pressing into a wall
        if arc0 is not None:
            ok, prev, lam, nneg = self._around_fold(arc0, on_step, prev0, dlam0, stop=stop)
            if not ok:
                return results, False
            dlam = nominal
            p.ease_walls(lam, stop, self.say)
        while lam < stop - 1e-14:
            target = min(stop, lam + dlam)
            snap = p.state.snapshot()
            predicted = prev is not None and self.predictor
            if predicted:
                predicted = self._predict(snap, prev, (target - lam) / (lam - prev[1]))
            res = self.solve_guarded(target)
            if not res.converged and predicted and cutbacks == 0:
                # the secant can carry a strand into another (contact) or past a turn of the
                # path: try the same step once from the last state before cutting it back
                # (once per step: near a fold every shorter step fails too)
                p.state.restore(snap)
                res = self.solve_guarded(target)
                self.predictor_retries += 1
            if res.converged and self.check_stability:
                res.negative_eigenvalues = self.negative_eigenvalues()
                if (self.conservative and res.negative_eigenvalues > nneg
                        and cutbacks < max_cutbacks and 0.5 * dlam >= min_step):
                    # the step landed on a less stable equilibrium than the one it left: the
                    # path turned near a limit/bifurcation point; retry with a shorter step
                    res.converged = False
                    res.reason = "stability"
            if not res.converged:
                p.state.restore(snap)
                p.set_load(lam)
                cutbacks += 1
                if on_fail is not None:
                    on_fail(res, dlam)
                dlam *= 0.5
                if cutbacks <= max_cutbacks and dlam >= min_step:
                    continue
                # no equilibrium near the last one, however short the step: a fold of the
                # path; -load_arclength follows the branch around it, else the run ends here
                if not self.arclength:
                    if dlam < min_step:         # the step shrank to nothing: a fold, or a jump
                        self.fail_reason = self._no_equilibrium(lam, 2.0 * dlam)
                    return results, False
                if self._fold_seen_before():
                    self.fail_reason = (f"load path stopped at load {lam:.6f}: the continuation "
                                        f"around this fold came back to it (a closed loop of "
                                        f"equilibria); the last converged step is in result.h5")
                    return results, False
                ok, prev, lam, nneg = self._around_fold(target, on_step, stop=stop)
                if not ok:
                    return results, False
                p.ease_walls(lam, stop, self.say)   # load stepping goes on from the last point
                dlam, cutbacks = nominal, 0
                continue
            self.keep_penetration(res)
            nneg = getattr(res, "negative_eigenvalues", 0)
            prev = (snap, lam)
            lam = target
            self.total_its += res.its
            cutbacks = 0
            dlam = res.next_increment = min(nominal, 1.5 * dlam)
            results.append(res)
            if on_step is not None:
                on_step(res)
            p.ease_walls(lam, stop, self.say)
        return results, True

    def _no_equilibrium(self, lam, dlam):
        """Why the path stopped where no step, however short, found an equilibrium, and what
        goes on from there (-load_arclength; for loads with an energy the minimiser)."""
        hint = "-load_arclength follows the branch around a fold"
        if self.conservative:
            hint += ", and the default -load_path minimize descends past it"
        return (f"load path stopped at load {lam:.6f}: Newton found no equilibrium near the last "
                f"one however short the step (the last increment {dlam:.1e}: a fold, where the "
                f"path turns back, or a jump): {hint}; the last converged step is in result.h5")

    def _predict(self, snap, prev, ratio):
        """The secant predictor ``ratio`` times the last step from the state (``snap``), as
        far along as the move limits let any node move (RodProblem.longest_step: contact, half
        its radius near a possible contact), and only where it penetrates no deeper than a
        line search may (else the step starts from the state): the minimiser path's predictor
        (load_path.LoadPath.predict) without the twist.  Unlimited, the secant of a step 1.5 x
        the last carried rollup_contact's free end past the clamped end's cap (12 or 20 load
        steps: the tip landed outside the first turn, another equilibrium, exit 0).  Returns
        whether the step starts from a prediction (a failed one is tried again from the
        state).  Collective."""
        p = self.problem
        if not p.step_limit:
            p.state.predict(prev[0], ratio)
            return True
        depth0 = p.deepest(p.state.local_config()[0], report=False)
        p.predict_within_limits(snap, prev[0], ratio)
        if depth0 is not None and \
                p.deepest(p.state.local_config()[0], report=False) > p.depth_allowed(depth0):
            p.state.restore(snap)
            return False
        return True

    def _fold_seen_before(self):
        """True when the path stands at a fold that an earlier continuation started from:
        within 1e-4 of its load and, node by node, within the contact radius (0.01 L without
        contact) of its state (branches that differ by a soft mode were 0.04 - 0.1 apart at the
        plectoneme's 8.7 turns, with energies equal to 1e-6).  The branch around it came back to
        the path before the fold (a closed loop of equilibria: the plectoneme at 8.80 turns,
        where the branch through the fold's unstable side rejoins a stable path at 8.64 turns
        across a contact event), and going round again would repeat it: the run ends there.
        Collective (allgathered positions)."""
        p = self.problem
        r = p.layout.allgather_nodes(p.state.local_config()[0][:p.layout.n_owned])
        near = p.length_scale if p.length_scale is not None else 0.01 * p.mesh.length
        seen = any(abs(p.lam - lam) <= 1e-4 and np.linalg.norm(r - r0, axis=1).max() <= near
                   for lam, r0 in self._folds)
        if seen:
            self.say(f"  the continuation around the fold at load {p.lam:.6f} came back to it "
                     "(a closed loop of equilibria): no second round")
        else:
            self._folds.append((p.lam, r))
        return seen

    def _around_fold(self, lam_fold, on_step, prev=None, ds=None, stop=1.0):
        """-load_arclength: follow the branch from the current state around the fold beyond the
        last converged load (lam_fold: the shortest step tried); the points join the results.
        Returns (ok, (snapshot, lambda) of the point before the last: the secant predictor's,
        the load and the negative eigenvalues of the point it ends at, from which the load
        steps go on with the nominal increment)."""
        self.say(f"  no equilibrium beyond load {self.problem.lam:.6f} up to {lam_fold:.6f} "
                 "(a fold): pseudo-arclength continuation around it" if prev is None else
                 f"  resuming the pseudo-arclength continuation around the fold at {lam_fold:.6f}")
        arc = Arclength(self)
        rs, ok, before = arc.around(lam_fold, on_step, prev=prev, ds=ds, stop=stop)
        self.results += rs
        if not ok:
            self.say(f"  pseudo-arclength continuation FAILED after {arc.steps} steps at load "
                     f"{self.problem.lam:.6f}")
            why = (f"it reached -load_arclength_max_steps ({arc.max_steps} points)"
                   if arc.steps >= arc.max_steps else "its step shrank to nothing")
            self.fail_reason = (f"load path stopped at load {self.problem.lam:.6f}: the "
                                f"pseudo-arclength continuation around the fold at load "
                                f"{lam_fold:.6f} found no point past it ({why}); the last "
                                f"converged point is in result.h5")
        nneg = getattr(self.results[-1], "negative_eigenvalues", 0) if self.results else 0
        return ok, before, self.problem.lam, nneg or 0

    def keep_penetration(self, res, max_raises=8):
        """-contact_penalty_adapt: keep the penalty's promise at every converged load step.

        While the deepest penetration max <d> / (2 eps) of the converged state exceeds
        -contact_penetration p*, raise mu (ContactTerm.promised_penalty) and solve the
        same load again from that state (at most ``max_raises`` times).  mu never falls, so a
        load path sees a non-decreasing penalty; each step records the mu it was solved with
        (result.h5 ``contact_penalty``).  A re-solve that fails is tried again with a smaller
        raise (the geometric mean of the two mu, down to RAISE_MIN x mu); below that the state
        and mu are put back and it is reported (the step stays, with its penetration).
        Updates res (its, seconds, fnorm, negative eigenvalues) in place."""
        if not res.converged:
            return
        raised = False
        for term in self.problem.adaptive_terms():
            raised = self._keep_penetration_of(term, res, max_raises) or raised
        if raised and self.check_stability:
            res.negative_eigenvalues = self.negative_eigenvalues()

    def _keep_penetration_of(self, ct, res, max_raises):
        """keep_penetration for one term; True when its penalty was raised."""
        p = self.problem
        raised = False
        for _ in range(max_raises):
            pen, mu1 = ct.promised_penalty(p.state.local_config()[0])
            if mu1 is None:
                break
            mu0, snap = ct.mu, p.state.snapshot()
            while True:
                ct.set_penalty(mu1)
                r = self.solve_guarded(res.lam)
                res.its += r.its
                res.seconds += r.seconds
                if r.converged:
                    break
                p.state.restore(snap)
                ct.set_penalty(mu0)
                p.set_load(res.lam)
                if mu1 <= RAISE_MIN * mu0 * (1 + 1e-12):
                    break
                # a smaller raise: the penalty continued in steps Newton can follow (there, x 2.8
                # failed in 20 its; x 1.25 converged in 22)
                self.say(f"  load {res.lam:.6f}: the re-solve with mu = {mu1:.4g} failed (reason "
                         f"{r.reason}): a smaller raise")
                mu1 = max(np.sqrt(mu0 * mu1), RAISE_MIN * mu0)
            if not r.converged:
                ct.penalty_failures += 1
                self.say(f"  load {res.lam:.6f}: penetration {pen:.2%} of the diameter exceeds "
                         f"-contact_penetration {ct.penetration:g}; the re-solve with mu = "
                         f"{mu1:.4g} FAILED (reason {r.reason}): "
                         f"the step keeps mu = {mu0:.4g}")
                break
            ct.penalty_raises += 1
            raised = True
            res.fnorm = r.fnorm
            self.say(f"  load {res.lam:.6f}: penetration {pen:.2%} of the diameter > "
                     f"-contact_penetration {ct.penetration:g}: penalty {mu0:.4g} -> {mu1:.4g}, "
                     f"solved again in {r.its} its")
        return raised

    def solve_guarded(self, lam):
        """solve_at(lam); after a PETSc error inside the solve (e.g. MUMPS failing in its solve
        phase after a failed factorisation, reason -100) the linear solver is replaced by a
        fresh one: the error unwinds past PCPostSolve and would leave the old PC refusing every
        later solve ("Cannot embed PCPreSolve() more than twice")."""
        res = self.solve_at(lam)
        if res.reason == -100:
            self.reset_linear_solver()
        return res

    def set_matrix(self, J):
        """Take a new Jacobian matrix (a new contact pattern, RodProblem._new_matrix) and drop
        the factorisation: its symbolic analysis belongs to the old pattern, and a new matrix
        object of a lower nonzero state would be taken for the same pattern."""
        self.snes.setJacobian(None, J)
        self.snes.getKSP().reset()

    def reset_linear_solver(self):
        """Give the SNES's KSP a new PC of the same prefix and options (SNES sets its operators
        again at the next Newton step)."""
        ksp = self.snes.getKSP()
        old = ksp.getPC()
        pc = PETSc.PC().create(comm=ksp.getComm())
        prefix = old.getOptionsPrefix()
        if prefix:
            pc.setOptionsPrefix(prefix)
        ksp.setPC(pc)
        ksp.setFromOptions()
        if self.problem.planar is not None:
            self.problem.planar.attach_pc(ksp)
        self.stats_linear_resets = getattr(self, "stats_linear_resets", 0) + 1

    def tolerance(self):
        """The |F| every load step is held to: max(atol, rtol x force scale, roundoff floor)."""
        rtol, atol, _, _ = self.snes.getTolerances()
        return max(atol, rtol * self.force_scale, self.floor)

    def negative_eigenvalues(self):
        """The negative eigenvalues of the energy Hessian at the current state
        (stability.negative_eigenvalues), the same on every rank (max over ranks).  Collective."""
        from mpi4py import MPI
        planar = self.problem.planar
        if planar is not None and planar.active:
            # a planar state: the in-plane and the out-of-plane blocks, each of half the size
            n_in, n_out = planar.negative_eigenvalues()
            if n_out:
                self.say(f"  load {self.problem.lam:.6f}: the planar equilibrium is UNSTABLE out "
                         f"of plane ({n_out} negative eigenvalues of the out-of-plane Hessian)")
            return n_in + n_out
        n = int(negative_eigenvalues(self.problem))
        return int(self.problem.layout.comm.tompi4py().allreduce(n, op=MPI.MAX))

    def say(self, text):
        """A progress line on rank 0 (nothing with -quiet)."""
        if not self.quiet and self.problem.layout.comm.getRank() == 0:
            print(text, flush=True)


def _line_search(snes):
    """(type, damping) of ``snes``'s line search as the options database sets them (PETSc's
    basic and 1.0 where none is given), read without marking the options used."""
    prefix = snes.getOptionsPrefix() or ""
    kind = str(peek(prefix + "snes_linesearch_type", "basic"))
    try:
        damping = float(peek(prefix + "snes_linesearch_damping", 1.0))
    except (TypeError, ValueError):
        damping = 1.0
    return kind, (damping if damping > 0.0 else 1.0)
