"""Newton on R^3 x SO(3) with PETSc SNES, and load stepping in lambda with cut-back.

SNES (newtonls) sees X = (r, theta); SNES.setUpdate re-centres the rotations before every
Newton step (slides "Newton method on C_a": (r, R) <- (r + eta, exp(theta^x) R)).  Defaults
(each overridable from the options database): full Newton steps (-snes_linesearch_type basic),
a direct solve -ksp_type preonly -pc_type lu with MUMPS, -snes_max_it 40, and the convergence
test of _converged: |F| below rtol (1e-10) times the force scale EI/L^2 + |loads|, or below the
roundoff floor of the residual (3 eps x largest stiffness x L/h_node x sqrt(nodes)), or below
-snes_atol; a solve that has not halved its best |F| in -load_stagnation_its (15) iterations
fails early (near a fold Newton 2-cycles between two residual levels until -snes_max_it).
A load step that fails is cut back (halved) and retried from
the last converged state; successful steps grow the increment again (x1.5) up to the nominal one.
Each step starts from the secant predictor through the last two converged states
(-load_predictor 0: from the last state), which keeps Newton on the branch it was following
near limit and bifurcation points.  With -stability, every converged step also counts the
negative eigenvalues of the energy Hessian (stability.py); a step that arrives at a less stable
equilibrium than it left is cut back too, so the load path stays on the stable branch (a genuine
loss of stability that survives all cut-backs is accepted and reported per step).
Branch switching (-stability_switch, on by default with -stability): such an accepted unstable
step is pushed along the lowest eigenvector of the energy Hessian (-stability_perturbation x L)
and relaxed by an energy-decreasing implicit gradient flow (relax.py) onto a stable equilibrium
at the same load, from which the load path goes on (switch_branch; conservative loads only).
"""
import time

import numpy as np
from petsc4py import PETSc

from .loads import nonconservative as _nonconservative
from .partition import NDOF

# the smallest penalty raise keep_penetration cuts a failed one back to (x mu)
RAISE_MIN = 1.1
# the largest turn of a prescribed end rotation (-bc_end_turns) in one load step: the end's
# rotation is set as a point of SO(3), which knows it only modulo a full turn, and Newton
# starts from the neighbouring nodes' rotations, so a step of more than half a turn would be
# taken the short way round (3 turns in one step gave the untwisted rod, 0.6 turns link -0.4)
MAX_TURN_STEP = 0.25


def _default(opts, name, value):
    if not opts.hasName(name):
        opts.setValue(name, value)


class StepResult:
    def __init__(self, lam, converged, its, reason, fnorm, history, seconds):
        self.lam, self.converged, self.its, self.reason = lam, converged, its, reason
        self.fnorm, self.history, self.seconds = fnorm, history, seconds


class NewtonSolver:
    def __init__(self, problem, force_scale, check_stability=False):
        self.problem = problem
        comm = problem.layout.comm
        opts = PETSc.Options()
        _default(opts, "snes_linesearch_type", "basic")
        # |F| is judged against rtol x force_scale (_converged), so the tolerance scales with
        # the problem; -snes_atol is an absolute test the user may add (0 by default: PETSc's
        # 1e-50 would accept at once a problem whose forces are all below it)
        _default(opts, "snes_rtol", "1e-10")
        _default(opts, "snes_atol", "0")
        _default(opts, "snes_stol", "1e-16")
        _default(opts, "snes_max_it", "40")
        _default(opts, "ksp_type", "preonly")
        _default(opts, "pc_type", "lu")
        _default(opts, "pc_factor_mat_solver_type", "mumps")
        if problem.contact is not None:
            # contact pairs add fill the analysis did not see: room for it (else INFOG(1) = -9)
            _default(opts, "mat_mumps_icntl_14", "100")
        snes = PETSc.SNES().create(comm=comm)
        snes.setType("newtonls")
        snes.setFunction(problem.residual, problem.F)
        snes.setJacobian(problem.jacobian, problem.J)
        snes.setUpdate(problem.update)
        snes.setConvergenceHistory(length=1000, reset=True)
        snes.setConvergenceTest(self._converged)
        snes.setFromOptions()
        self.snes = snes
        problem.on_pattern_change = self.set_matrix
        rod = problem.scene.rod
        # roundoff floor of the residual: strains of size ~1 (v3 = 1), differentiated over a
        # node spacing, times the largest stiffness, summed over the nodes; a residual at this level is as converged as the
        # arithmetic allows (DIVERGED_MAX_IT there would reject a correct equilibrium).
        from .scene import residual_floor
        self.floor = residual_floor(rod)
        self.divtol = 1e12
        self.force_scale = force_scale
        self.predictor = PETSc.Options().getBool("load_predictor", True)
        # a Newton solve that has not halved its best residual in this many iterations has
        # stalled (at a fold it 2-cycles between two residual levels for ever): give up early
        self.stagnation_its = PETSc.Options().getInt("load_stagnation_its", 15)
        self.stagnated = False              # the last solve stopped at that test
        self.stagnations = 0                # solves stopped at it
        # -load_damped_its N: a failed step is solved again by Levenberg-Marquardt (solve_damped)
        # before it is cut back (conservative loads only: energy is its merit function)
        self.damped_its = PETSc.Options().getInt("load_damped_its", 0)
        self.damped_solves = 0
        self.check_stability = check_stability
        self.f0 = None
        self.total_its = 0
        # branch switching (-stability_switch, on by default with -stability): relax an unstable
        # converged step onto a stable equilibrium (switch_branch, relax.py)
        self.switch = bool(check_stability) and opts.getBool("stability_switch", True)
        # -stability_switch_restart: a restart from an unstable step relaxes it first
        self.switch_restart = self.switch and opts.getBool("stability_switch_restart", False)
        self.fail_reason = None             # why run() stopped early, when not a failed step
        self.perturbation = opts.getReal("stability_perturbation", 1e-2)
        self.relax_max_it = opts.getInt("stability_relax_max_it", 200)
        self.jump_overshoot = opts.getReal("stability_jump_overshoot", 0.0)
        # -load_arclength: at a fold, follow the branch around it (arclength.py) instead
        self.arclength = opts.getBool("load_arclength", False)
        self.nominal = None                 # the nominal load increment of run()
        self._folds = []                    # (load, positions) where continuations started
        self.switch_attempts = 3
        self.quiet = bool(getattr(getattr(problem.scene, "output", None), "quiet", False))
        self.switch_refused = _nonconservative(problem.scene.loads)
        self._refusal_shown = False
        if self.damped_its > 0 and self.switch_refused:
            from .scene import SceneError
            raise SceneError(f"-load_damped_its {self.damped_its}: Levenberg-Marquardt takes the "
                             f"energy as its merit function, and {self.switch_refused}; use "
                             f"-load_damped_its 0 with these loads")
        self._switch_failed_nneg = None     # skip new attempts until the instability grows
        self.switches = []                  # info dict of every attempted switch
        self.results = []                   # StepResults of the last run()
        self.predictor_retries = 0          # failed predicted steps tried again from the last state
        # on_relaxation(lam, info): keeps an unfinished relaxation's state (Run writes it to
        # DIR/relaxation; relax.relax's keep), info: phase, c, c_min, steps, fnorm, energy,
        # negative_eigenvalues (of the state relaxed from), final, ok (finished)
        self.on_relaxation = None
        self.relaxation_kept = None         # where on_relaxation wrote the last one (Run)

    def _converged(self, snes, it, norms):
        """Convergence relative to the problem's scale, so that a problem and its twin with every
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

    def solve_at(self, lam):
        """Solve at load factor lam from the current state; returns a StepResult."""
        p = self.problem
        t0 = time.perf_counter()
        p.set_load(lam)
        self.snes.setConvergenceHistory(length=1000, reset=True)
        try:
            self.snes.solve(None, p.state.X)
            reason = self.snes.getConvergedReason()
        except PETSc.Error:
            reason = -100
        hist, _ = self.snes.getConvergenceHistory()
        self.last_history = np.array(hist)
        its = self.snes.getIterationNumber()
        p.state.recentre()
        ok = reason > 0 and np.all(np.isfinite(hist))
        fnorm = float(hist[-1]) if len(hist) else float("nan")
        if not ok and self.stagnated:
            reason = "stagnation"
            self.stagnations += 1
        return StepResult(lam, ok, its, reason, fnorm, np.array(hist), time.perf_counter() - t0)

    def run(self, lam0, steps, max_cutbacks, min_step, on_step=None, on_fail=None, nneg0=0,
            dlam0=None, prev0=None, arc0=None, stop=1.0, resume=None):
        """Step lambda from lam0 to ``stop`` (-load_stop, 1 by default) on the grid of ``steps``
        nominal increments of 0 -> 1, with cut-back.

        on_step(result) is called after every converged step (write output there), on_fail(result,
        dlam) after every failed try (dlam = the increment about to be halved, or None when the
        step is solved again by Levenberg-Marquardt, -load_damped_its).  With
        -stability and -stability_switch, a step accepted with negative eigenvalues is relaxed
        onto a stable equilibrium first (switch_branch); its result then has branch_switch =
        True and the negative eigenvalues counted after the switch, and the next step starts
        from the new state with the nominal increment (no secant predictor across the switch).
        A predicted step that fails is tried once more from the last state before its first
        cut-back.
        A step that fails at every cut-back from a stable state (a fold: no equilibrium nearby)
        is relaxed at the load of its shortest try instead of ending the run (jump_branch; the
        result has branch_switch = jump = True).
        nneg0: negative eigenvalues of the starting state (a restart from an unstable step,
        where the uninterrupted run had stayed on the unstable branch: no new switch attempt
        until the instability grows, as there).
        dlam0, prev0: the first increment and the (snapshot, lambda) of the step before lam0,
        for a restart that takes the steps the interrupted run would have taken (every result
        carries next_increment, the increment its successor starts from).
        resume: the record of an unfinished relaxation (a restart from DIR/relaxation, with
        -stability_switch_restart): it goes on from the restart state before any step.
        With -load_arclength a fold is passed by pseudo-arclength continuation instead
        (arclength.Arclength.around: the branch followed around the fold, through its unstable
        part, until it goes on stable with the load increasing); arc0: a restart inside that
        continuation (the fold's load; dlam0 is then its next arclength increment)."""
        p = self.problem
        self.fail_reason = None
        # the same load grid when a run is restarted from lam0; no step turns a prescribed end
        # by more than MAX_TURN_STEP (a rotation is known only modulo a full turn on SO(3))
        nominal = self.nominal = min(1.0 / steps, p.constraints.max_load_increment(MAX_TURN_STEP))
        if nominal < 1.0 / steps:
            self._say(f"  -bc_end_turns {p.scene.bc.end_turns:g}: load steps of at most "
                      f"{MAX_TURN_STEP:g} turn ({int(np.ceil(1.0 / nominal - 1e-9))} steps from 0 to 1)")
        lam, dlam = lam0, (nominal if dlam0 is None else min(nominal, dlam0))
        cutbacks = 0
        results = self.results = []
        prev = prev0           # (snapshot, lambda) of the previous converged step
        nneg = int(nneg0)      # negative eigenvalues of the last converged step (-stability)
        if nneg > 0:
            self._switch_failed_nneg = nneg
        if resume is not None:
            # an unfinished relaxation: not an equilibrium, its inertia says nothing; go on
            nneg = max(nneg, 1)
        elif self.switch_restart and arc0 is None:
            # the restart state's inertia, counted afresh (a run without -stability stored none)
            from .stability import negative_eigenvalues
            p.set_load(lam)
            nneg = self._count_negative(negative_eigenvalues)
            if nneg == 0:
                self._say(f"  -stability_switch_restart: the restart state at load {lam:.6f} is "
                          f"stable (no negative eigenvalue): nothing to relax")
        if self.switch_restart and nneg > 0 and arc0 is None:
            # -stability_switch_restart: the restart state is unstable; relax it onto a stable
            # equilibrium at the same load before any step (a new step, branch_switch = True)
            self._switch_failed_nneg = None
            res = StepResult(lam, True, 0, "restart switch", np.nan, np.array([]), 0.0)
            res.negative_eigenvalues = nneg
            if not self._maybe_switch(res, resume=resume):
                what = (f"the resumed relaxation at load {lam:.6f}" if resume is not None else
                        f"the branch switch at load {lam:.6f} ({nneg} negative eigenvalues)")
                self.fail_reason = (f"-stability_switch_restart: {what} found no stable "
                                    f"equilibrium; the restart state is unchanged"
                                    + ("" if self.relaxation_kept is None else
                                       f"; the relaxation's last state is in "
                                       f"{self.relaxation_kept}"))
                return results, False
            res.its = res.switch_info["newton_its"]     # (already in total_its)
            self.keep_penetration(res)
            nneg = res.negative_eigenvalues
            prev, dlam = None, nominal
            res.next_increment = nominal
            results.append(res)
            if on_step is not None:
                on_step(res)
        if arc0 is not None:
            ok, prev, lam, nneg = self._around_fold(arc0, on_step, prev0, dlam0)
            if not ok:
                return self.results, False
            dlam = nominal
        while lam < stop - 1e-14:
            target = min(stop, lam + dlam)
            snap = p.state.snapshot()
            predicted = prev is not None and self.predictor
            if predicted:
                p.state.predict(prev[0], (target - lam) / (lam - prev[1]))
            res = self.solve_guarded(target)
            if not res.converged and predicted and cutbacks == 0:
                # the secant can carry a strand into another (contact) or past a turn of the
                # path: try the same step once from the last state before cutting it back
                # (once per step: near a fold every shorter step fails too)
                p.state.restore(snap)
                res = self.solve_guarded(target)
                self.predictor_retries += 1
            if not res.converged and self.damped_its > 0 and not self.switch_refused:
                # Newton failed: Levenberg-Marquardt from the last state, before a cut-back
                if on_fail is not None:
                    on_fail(res, None)
                p.state.restore(snap)
                res = self.solve_damped(target)
            if res.converged and self.check_stability:
                from .stability import negative_eigenvalues
                res.negative_eigenvalues = self._count_negative(negative_eigenvalues)
                if (res.negative_eigenvalues > nneg and cutbacks < max_cutbacks
                        and 0.5 * dlam >= min_step):
                    # the step landed on a less stable equilibrium than the one it left: the
                    # path turned near a limit/bifurcation point; retry with a shorter step
                    res.converged = False
                    res.reason = "stability"
            switched = False
            if res.converged and getattr(res, "negative_eigenvalues", 0) > 0 and self.switch:
                switched = self._maybe_switch(res)
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
                # (stable) path, where the rod must jump; with switching, relax at the load
                # of the shortest step tried (jump_branch), else give up
                # (-stability_jump_overshoot: at least that far beyond the last converged load;
                # just past a fold the rod creeps through the fold's ghost, the slower the
                # closer, and the branch it jumps to goes on continuously beyond)
                if self.arclength and not self._fold_seen_before():
                    ok, prev, lam, nneg = self._around_fold(target, on_step)
                    if not ok:
                        return self.results, False
                    dlam, cutbacks = nominal, 0
                    continue
                target = max(target, min(1.0, lam + self.jump_overshoot))
                res = self._maybe_jump(target) if (self.switch and nneg == 0) else None
                if res is None:
                    return results, False
                switched = True
            self.keep_penetration(res)
            nneg = getattr(res, "negative_eigenvalues", 0)
            prev = None if switched else (snap, lam)
            lam = target
            self.total_its += res.its
            cutbacks = 0
            # after a switch the steps start afresh from the nominal increment
            dlam = res.next_increment = nominal if switched else min(nominal, 1.5 * dlam)
            results.append(res)
            if on_step is not None:
                on_step(res)
        return results, True

    def _fold_seen_before(self):
        """True when the path stands at a fold that an earlier continuation started from:
        within 1e-4 of its load and, node by node, within the contact radius (0.01 L without
        contact) of its state (branches that differ by a soft mode were 0.04 - 0.1 apart at the
        plectoneme's 8.7 turns, with energies equal to 1e-6).  The branch around it came back to
        the path before the fold (a closed loop of equilibria: the plectoneme at 8.80 turns,
        where the branch through the fold's unstable side rejoins a stable path at 8.64 turns
        across a contact event), and going round again would repeat it: the fold is then
        jumped (-stability) or the run ends.  Collective (allgathered positions)."""
        p = self.problem
        r = p.layout.allgather_nodes(p.state.local_config()[0][:p.layout.n_owned])
        near = p.contact.eps if p.contact is not None else 0.01 * p.mesh.length
        seen = any(abs(p.lam - lam) <= 1e-4 and np.linalg.norm(r - r0, axis=1).max() <= near
                   for lam, r0 in self._folds)
        if seen:
            self._say(f"  the continuation around the fold at load {p.lam:.6f} came back to it "
                      "(a closed loop of equilibria): no second round")
        else:
            self._folds.append((p.lam, r))
        return seen

    def _around_fold(self, lam_fold, on_step, prev=None, ds=None):
        """-load_arclength: follow the branch from the current state around the fold beyond the
        last converged load (lam_fold: the shortest step tried); the points join the results.
        Returns (ok, (snapshot, lambda) of the point before the last: the secant predictor's,
        the load and the negative eigenvalues of the point it ends at, from which the load
        steps go on with the nominal increment)."""
        from .arclength import Arclength
        self._say(f"  no equilibrium beyond load {self.problem.lam:.6f} up to {lam_fold:.6f} "
                  "(a fold): pseudo-arclength continuation around it" if prev is None else
                  f"  resuming the pseudo-arclength continuation around the fold at {lam_fold:.6f}")
        arc = Arclength(self)
        rs, ok, before = arc.around(lam_fold, on_step, prev=prev, ds=ds)
        self.results += rs
        if not ok:
            self._say(f"  pseudo-arclength continuation FAILED after {arc.steps} steps at load "
                      f"{self.problem.lam:.6f}")
        nneg = getattr(self.results[-1], "negative_eigenvalues", 0) if self.results else 0
        return ok, before, self.problem.lam, nneg or 0

    def keep_penetration(self, res, max_raises=8):
        """-contact_penalty_adapt: keep the penalty's promise at every converged load step.

        While the deepest penetration max <d> / (2 eps) of the converged state exceeds
        -contact_penetration p*, raise mu <- 1.25 mu (pen / p*) (a line contact has d ~ 1/mu, so
        it lands near 0.8 p*; a crossing, d ~ mu^(-2/3), may need a second raise) and solve the
        same load again from that state (at most ``max_raises`` times).  mu never falls, so a
        load path sees a non-decreasing penalty; each step records the mu it was solved with
        (result.h5 ``contact_penalty``).  A Newton re-solve that fails is done again by
        Levenberg-Marquardt with -load_damped_its N (solve_damped); one that still fails is
        tried again with a smaller raise (the geometric mean of the two mu, down to
        RAISE_MIN x mu); below that the state and mu are put back and it is reported (the step
        stays, with its penetration).  Updates res (its, seconds, fnorm,
        negative eigenvalues) in place."""
        p = self.problem
        ct = p.contact
        if ct is None or not ct.adapt or not res.converged:
            return
        raised = False
        for _ in range(max_raises):
            r_loc, _ = p.state.local_config()
            pen = ct.deepest(r_loc) / (2.0 * ct.eps)
            if pen <= ct.penetration:
                break
            mu0, snap = ct.mu, p.state.snapshot()
            mu1 = 1.25 * mu0 * pen / ct.penetration
            while True:
                ct.set_penalty(mu1)
                r = self.solve_guarded(res.lam)
                res.its += r.its
                res.seconds += r.seconds
                if not r.converged and self.damped_its > 0 and not self.switch_refused:
                    # as a failed load step (-load_damped_its): Levenberg-Marquardt from the
                    # state the raise started at (the plectoneme's switch at 9.415 turns: 2.2 %
                    # at the start clamp's mount, the Newton re-solve at 2.8 x mu failed)
                    p.state.restore(snap)
                    r = self.solve_damped(res.lam)
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
                self._say(f"  load {res.lam:.6f}: the re-solve with mu = {mu1:.4g} failed (reason "
                          f"{r.reason}): a smaller raise")
                mu1 = max(np.sqrt(mu0 * mu1), RAISE_MIN * mu0)
            if not r.converged:
                ct.penalty_failures += 1
                self._say(f"  load {res.lam:.6f}: penetration {pen:.2%} of the diameter exceeds "
                          f"-contact_penetration {ct.penetration:g}; the re-solve with mu = "
                          f"{mu1:.4g} FAILED (reason {r.reason}): "
                          f"the step keeps mu = {mu0:.4g}")
                break
            ct.penalty_raises += 1
            raised = True
            res.fnorm = r.fnorm
            self._say(f"  load {res.lam:.6f}: penetration {pen:.2%} of the diameter > "
                      f"-contact_penetration {ct.penetration:g}: penalty {mu0:.4g} -> {mu1:.4g}, "
                      f"solved again in {r.its} its")
        if raised and self.check_stability:
            from .stability import negative_eigenvalues
            res.negative_eigenvalues = self._count_negative(negative_eigenvalues)

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
        self.stats_linear_resets = getattr(self, "stats_linear_resets", 0) + 1

    # -- branch switching -------------------------------------------------------------
    def _count_negative(self, counter):
        """counter(problem), the same on every rank (max over ranks)."""
        from mpi4py import MPI
        return int(self.problem.layout.comm.tompi4py().allreduce(int(counter(self.problem)), op=MPI.MAX))

    def _say(self, text):
        if not self.quiet and self.problem.layout.comm.getRank() == 0:
            print(text, flush=True)

    def _maybe_switch(self, res, resume=None):
        """Try switch_branch for the accepted step ``res`` (negative eigenvalues > 0); update res.
        Returns True when the state moved onto a stable equilibrium."""
        res.branch_switch = False
        n = res.negative_eigenvalues
        if self.switch_refused:
            if not self._refusal_shown:
                self._say(f"  branch switching refused at load {res.lam:.6f}: {self.switch_refused}; "
                          "the load path stays on the unstable branch")
                self._refusal_shown = True
            return False
        if self._switch_failed_nneg is not None and n <= self._switch_failed_nneg:
            return False
        info = self.switch_branch(res.lam, n, resume=resume)
        res.switch_info = info
        self.total_its += info["newton_its"]
        if info["switched"]:
            res.branch_switch = True
            res.negative_eigenvalues = info["negative_after"]
            res.fnorm = info["fnorm"]
            res.seconds += info["seconds"]
            self._switch_failed_nneg = None
            how = (info["eigen_method"] if resume is not None else
                   f"lowest {info['eigenvalue']:+.3e}, {info['eigen_method']} {info['dofs']} dofs "
                   f"{info['eigen_seconds']:.2f} s")
            self._say(f"  branch switch at load {res.lam:.6f}: {n} -> {info['negative_after']} negative "
                      f"eigenvalues ({how}); relaxation "
                      f"{info['relax_steps']} steps ({info['relax_rejected']} rejected, "
                      f"{info['newton_its']} Newton its); E {info['energy_before']:+.6e} -> "
                      f"{info['energy_after']:+.6e}; {info['seconds']:.2f} s")
            return True
        self._switch_failed_nneg = n
        self._say(f"  branch switch at load {res.lam:.6f} FAILED ({info['message']}): the load "
                  f"path stays on the unstable branch ({n} negative eigenvalues)")
        return False

    def _maybe_jump(self, lam):
        """After the load step to lam failed at every cut-back: jump_branch; a StepResult
        (branch_switch = jump = True) when it found a stable equilibrium at lam, else None."""
        if self.switch_refused:
            if not self._refusal_shown:
                self._say(f"  branch switching refused at load {lam:.6f}: {self.switch_refused}")
                self._refusal_shown = True
            return None
        info = self.jump_branch(lam)
        if not info["switched"]:
            self.total_its += info["newton_its"]
            self._say(f"  jump at load {lam:.6f} FAILED ({info['message']})")
            return None
        res = StepResult(lam, True, info["newton_its"], "jump", info["fnorm"], np.array([]),
                         info["seconds"])
        res.negative_eigenvalues = info["negative_after"]
        res.branch_switch = res.jump = True
        res.switch_info = info
        self._say(f"  jump at load {lam:.6f} (no equilibrium near the last one: a fold): relaxation "
                  f"{info['relax_steps']} steps ({info['relax_rejected']} rejected, "
                  f"{info['newton_its']} Newton its) to a stable equilibrium; E "
                  f"{info['energy_before']:+.6e} -> {info['energy_after']:+.6e}; {info['seconds']:.2f} s")
        return res

    def _push_along(self, v, M):
        """Move the state by s v along the mode v (destroyed here): the largest nodal
        displacement becomes -stability_perturbation x L (a rotation-only mode: the largest
        rotation becomes that x 2 pi; with contact at most max(eps/2, clearance/4), as a
        pseudo-time step of relax.py), with the sign of lower energy (+ on a tie).  Returns the
        lumped-metric norm v.M v (positions + l^2 rotations, l = L / 2 pi).  Collective; the
        decisions use rank 0's values."""
        from mpi4py import MPI
        p = self.problem
        comm = p.layout.comm.tompi4py()
        L = p.mesh.length
        ell = L / (2 * np.pi)

        def same(x):
            return comm.bcast(x, root=0)
        va = v.getArray(readonly=True).reshape(-1, NDOF)
        dr = comm.allreduce(float(np.linalg.norm(va[:, 0:3], axis=1).max(initial=0.0)), op=MPI.MAX)
        dth = comm.allreduce(float(np.linalg.norm(va[:, 3:6], axis=1).max(initial=0.0)), op=MPI.MAX)
        delta = self.perturbation * L
        if p.contact is not None:       # a push may not carry a strand through another
            r_loc, _ = p.state.local_config()
            delta = min(delta, max(0.5 * p.contact.eps, 0.25 * p.contact.clearance(r_loc)))
        s = same(delta / (dr if dr > 1e-2 * ell * dth else ell * dth))
        X0 = p.state.X.copy()
        energies = []
        for sign in (1.0, -1.0):
            p.state.X.axpy(sign * s, v)
            energies.append(p.energy())
            X0.copy(p.state.X)
        Ep, Em = same(energies)
        sign = -1.0 if Em < Ep - 1e-10 * (abs(Ep) + abs(Em)) else 1.0
        p.state.X.axpy(sign * s, v)
        X0.destroy()
        p.state.recentre()
        mv = comm.allreduce(float(np.sum(M * (np.einsum("ij,ij->i", va[:, 0:3], va[:, 0:3])
                                               + ell**2 * np.einsum("ij,ij->i", va[:, 3:6], va[:, 3:6])))))
        v.destroy()
        return mv

    def _keeper(self, lam, nneg):
        """relax.relax's keep for a relaxation at load lam from a state with nneg negative
        eigenvalues: hands the state's description to on_relaxation (None without one)."""
        if self.on_relaxation is None:
            return None

        def keep(rr, final):
            self.on_relaxation(lam, {"phase": rr.phase, "c": float(rr.c_last),
                                     "c_min": float(rr.c_min), "steps": int(rr.steps),
                                     "fnorm": float(rr.fnorm), "energy": float(rr.energies[-1]),
                                     "negative_eigenvalues": int(nneg), "final": bool(final),
                                     "ok": bool(rr.ok)})
        return keep

    def tolerance(self):
        """The |F| every load step is held to: max(atol, rtol x force scale, roundoff floor)."""
        rtol, atol, _, _ = self.snes.getTolerances()
        return max(atol, rtol * self.force_scale, self.floor)

    def _first_stiffness(self):
        """Pseudo-time stiffness c of a first damped step (relax.py) from the current state at
        the current load: the step (c M) dx = -F moves no node by more than about
        -stability_perturbation x L (positions) or that / l (rotations, l = L / 2 pi).
        Collective (rank 0's value)."""
        from mpi4py import MPI
        from .relax import lumped_weights
        p = self.problem
        comm = p.layout.comm.tompi4py()
        ell = p.mesh.length / (2 * np.pi)
        delta = self.perturbation * p.mesh.length
        M = lumped_weights(p.mesh, p.layout)
        F = p.layout.create_vec()
        p.residual(None, p.state.X, F)
        Fa = F.getArray(readonly=True).reshape(-1, NDOF)
        c0 = float(np.max(np.maximum(np.linalg.norm(Fa[:, 0:3], axis=1),
                                     np.linalg.norm(Fa[:, 3:6], axis=1) / ell) / (delta * M), initial=0.0))
        F.destroy()
        return max(comm.bcast(comm.allreduce(c0, op=MPI.MAX), root=0), 1e-300)

    def solve_damped(self, lam):
        """Levenberg-Marquardt at load factor lam from the current state (-load_damped_its N:
        the fallback of a load step whose Newton solve failed, before it is cut back): steps
        (K + c M) dx = -F kept while the energy falls, c / 3 after a kept step, x 4 after a
        rejected one (relax.relax_phase, single_step), from the c of _first_stiffness, for at
        most N steps, until the undamped |F| meets the step tolerance.  As c falls the steps
        become Newton's; a soft mode next to a contact edge, along which undamped Newton throws
        strands across the edge and 2-cycles, is bounded by c.  Returns a StepResult (reason
        "damped"; its = Newton steps taken).  Energy is the merit function: conservative loads
        only (the caller checks).  Collective."""
        from .relax import relax_phase
        p = self.problem
        t0 = time.perf_counter()
        p.set_load(lam)
        rr = relax_phase(self, lam, self._first_stiffness(), self.tolerance(),
                         max_steps=self.damped_its, single_step=True)
        res = StepResult(lam, rr.ok, rr.newton_its, "damped" if rr.ok else "damped: " + rr.message,
                         rr.fnorm, np.array([row[3] for row in rr.log]), time.perf_counter() - t0)
        res.damped = True
        self.damped_solves += 1
        return res

    def jump_branch(self, lam):
        """From the last converged state (at a lower load), relax at load factor lam by the
        implicit gradient flow of relax.py (no push along an eigenvector: at the plectoneme's
        fold the lowest eigenvector lowers the energy only for pushes below 1e-3 L, by 1e-8;
        the flow follows the curved path itself) to an equilibrium; if that one is unstable,
        switch_branch from it.  Success: an
        equilibrium at lam with 0 negative eigenvalues (then the state is there); else the
        last converged state and its load are restored.  Collective."""
        from .relax import relax
        from .stability import negative_eigenvalues
        p = self.problem
        comm = p.layout.comm.tompi4py()
        t0 = time.perf_counter()
        p.hold_sliding()          # a closed uniform ring: no creeping along its sliding symmetry
        snap0, lam0 = p.state.snapshot(), p.lam
        p.set_load(lam)
        E0 = comm.bcast(p.energy(), root=0)
        info = {"switched": False, "jump": True, "negative_before": None, "negative_after": None,
                "energy_before": E0, "energy_after": E0, "relax_steps": 0, "relax_rejected": 0,
                "newton_its": 0, "message": "", "fnorm": np.nan, "relax_energies": [],
                "relax_log": [], "energy_monotone": True}
        tol = self.tolerance()
        rr = relax(self, lam, self._first_stiffness(), tol, max_steps=self.relax_max_it,
                   keep=self._keeper(lam, 0))
        info.update(relax_steps=rr.steps, relax_rejected=rr.rejected, newton_its=rr.newton_its)
        info["relax_energies"].append(rr.energies)
        info["relax_log"].append(rr.log)
        dE = np.diff(rr.energies)
        info["energy_monotone"] = bool(np.all(dE <= 1e-12 * (np.abs(rr.energies[1:]) + abs(E0))))
        n = None
        if not rr.ok:
            info["message"] = "relaxation: " + rr.message
        else:
            res = self._polish(lam, tol, rr.fnorm)
            info["newton_its"] += res.its
            if not res.converged:
                info["message"] = f"the undamped solve after relaxation failed (SNES reason {res.reason})"
            else:
                info["fnorm"] = res.fnorm
                n = self._count_negative(negative_eigenvalues)
                info["negative_before"] = n
                if n > 0:
                    sub = self.switch_branch(lam, n)
                    for k in ("relax_steps", "relax_rejected", "newton_its"):
                        info[k] += sub[k]
                    info["relax_energies"] += sub["relax_energies"]
                    info["energy_monotone"] &= sub["energy_monotone"]
                    info["fnorm"] = sub["fnorm"] if sub["switched"] else info["fnorm"]
                    n = sub["negative_after"]
                    info["message"] = sub["message"]
        if n == 0:
            info["switched"] = True
            info["negative_after"] = 0
            info["energy_after"] = comm.bcast(p.energy(), root=0)
        else:
            p.state.restore(snap0)
            p.set_load(lam0)
            info["message"] = info["message"] or f"the equilibrium reached has {n} negative eigenvalues"
        info["seconds"] = time.perf_counter() - t0
        self.switches.append(info)
        return info

    def _polish(self, lam, tol, f_relaxed):
        """The undamped Newton solve that ends a relaxation, from its state with undamped |F|
        f_relaxed (relax.RelaxResult.fnorm).  Next to a contact edge on a soft mode, Newton can
        2-cycle away from a state that already meets the tolerance (the plectoneme at 8.57
        turns: the relaxed |F| 3.0e-9 <= tol 3.2e-9, then Newton between 3.38e-4 and 3.39e-4 as
        a contact zone appears and vanishes in turn); the relaxed state is then kept, with its
        residual, if that meets the tolerance every load step is held to.  Returns a StepResult."""
        p = self.problem
        snap = p.state.snapshot()
        res = self.solve_guarded(lam)
        if res.converged:
            return res
        p.state.restore(snap)
        p.set_load(lam)
        if f_relaxed <= tol:
            res.converged, res.fnorm, res.reason = True, f_relaxed, "relaxed"
        return res

    def switch_branch(self, lam, nneg, resume=None):
        """Leave the unstable equilibrium at load factor lam (nneg > 0 negative eigenvalues)
        for a stable one: (1) lowest eigenvector v of the energy Hessian
        (stability.lowest_eigenpair); (2) perturb the state by s v, |s v| = -stability_perturbation
        x L at the node that moves most, with the sign of lower energy; (3) relax (relax.relax:
        implicit gradient flow with the RelaxationTerm, energy decreasing) until the undamped
        residual is at tolerance, then an undamped Newton solve; (4) count the negative
        eigenvalues: 0 ends, else repeat from (1), at most switch_attempts times.  On failure the
        unstable equilibrium is restored.  resume: an unfinished relaxation's record (a restart
        from DIR/relaxation: phase, c, c_min): the first attempt goes on with it from the
        current state, without (1)-(2).  Returns an info dict (switched, negative_after,
        energies, eigen and relaxation statistics).  Collective; every branch decision uses
        broadcast or allreduced values."""
        from .relax import lumped_weights, relax
        from .stability import lowest_eigenpair, negative_eigenvalues
        p = self.problem
        comm = p.layout.comm.tompi4py()
        t0 = time.perf_counter()
        p.hold_sliding()          # a closed uniform ring: no creeping along its sliding symmetry
        snap0 = p.state.snapshot()
        p.set_load(lam)

        def same(x):       # rank 0's value everywhere: the decisions must agree bit for bit
            return comm.bcast(x, root=0)

        E_before = same(p.energy())
        tol = self.tolerance()
        info = {"switched": False, "negative_before": nneg, "negative_after": nneg,
                "energy_before": E_before, "energy_after": E_before, "attempts": 0,
                "relax_steps": 0, "relax_rejected": 0, "newton_its": 0, "eigen_seconds": 0.0,
                "message": "", "fnorm": np.nan, "energy_perturbed": [], "relax_energies": [],
                "relax_log": [], "energy_monotone": True}
        M = lumped_weights(p.mesh, p.layout)
        for attempt in range(1, self.switch_attempts + 1):
            info["attempts"] = attempt
            if attempt == 1 and resume is not None:
                # an unfinished relaxation goes on where it was kept, with its c and phase
                info.update(eigenvalue=np.nan, eigen_method="resumed relaxation", dofs=0)
                # its c, unless above that of a first damped step from here (a relaxation kept
                # as it stalled has grown c to where no step moves: 1.5e25 on the plectoneme)
                c_go = min(float(resume["c"]), self._first_stiffness())
                rr = relax(self, lam, c_go, tol, max_steps=self.relax_max_it,
                           lm_only=resume.get("phase") == "lm",
                           c_min=float(resume.get("c_min", 1e-12 * float(resume["c"]))),
                           keep=self._keeper(lam, nneg))
            else:
                ev, v, einfo = lowest_eigenpair(p, nneg)
                info["eigen_seconds"] += einfo["seconds"]
                info.update(eigenvalue=ev, eigen_method=einfo["method"], dofs=einfo["n"])
                if not ev < 0:
                    info["message"] = f"lowest eigenvalue {ev:.3e} is not negative"
                    break
                mv = self._push_along(v, M)
                p.set_load(lam)
                # initial pseudo-time stiffness: H + c M positive along v with margin |ev|
                # (c M v.v >= 2 |ev|), so the first damped step doubles the departure from the
                # saddle
                c0 = same(2.0 * abs(ev) / mv)
                rr = relax(self, lam, c0, tol, max_steps=self.relax_max_it,
                           keep=self._keeper(lam, nneg))
            info["relax_steps"] += rr.steps
            info["relax_rejected"] += rr.rejected
            info["newton_its"] += rr.newton_its
            info["energy_perturbed"].append(rr.energies[0])
            info["relax_energies"].append(rr.energies)
            info["relax_log"].append(rr.log)
            # the flow must go downhill (relax rejects uphill steps: a violation here is a bug)
            dE = np.diff(rr.energies)
            info["energy_monotone"] &= bool(np.all(dE <= 1e-12 * (np.abs(rr.energies[1:]) + abs(E_before))))
            if not rr.ok:
                info["message"] = "relaxation: " + rr.message
                break
            res = self._polish(lam, tol, rr.fnorm)
            info["newton_its"] += res.its
            if not res.converged:
                info["message"] = f"the undamped solve after relaxation failed (SNES reason {res.reason})"
                break
            info["fnorm"] = res.fnorm
            E_after = same(p.energy())
            if not E_after < E_before:
                info["message"] = f"relaxation did not lower the energy ({E_before:.6e} -> {E_after:.6e})"
                break
            n_after = self._count_negative(negative_eigenvalues)
            info.update(energy_after=E_after, negative_after=n_after)
            if n_after == 0:
                info["switched"] = True
                break
            nneg = n_after
            info["message"] = f"{n_after} negative eigenvalues after {attempt} relaxations"
        if not info["switched"]:
            p.state.restore(snap0)
            p.set_load(lam)
            info.update(energy_after=E_before, negative_after=info["negative_before"])
        info["seconds"] = time.perf_counter() - t0
        self.switches.append(info)
        return info
