"""Newton on R^3 x SO(3) with PETSc SNES, and load stepping in lambda with cut-back.

SNES (newtonls) sees X = (r, theta); SNES.setUpdate re-centres the rotations before every
Newton step (slides "Newton method on C_a": (r, R) <- (r + eta, exp(theta^x) R)).  Defaults
(each overridable from the options database): full Newton steps (-snes_linesearch_type basic),
a direct solve -ksp_type preonly -pc_type lu with MUMPS, -snes_max_it 40, and the convergence
test of _converged: |F| below rtol (1e-10) times the force scale EI/L^2 + |loads|, or below the
roundoff floor of the residual (3 eps x largest stiffness x L/h_node x sqrt(nodes)), or below -snes_atol.  A load step that fails is cut back (halved) and retried from
the last converged state; successful steps grow the increment again (x1.5) up to the nominal one.
Each step starts from the secant predictor through the last two converged states
(-load_predictor 0: from the last state), which keeps Newton on the branch it was following
near limit and bifurcation points.  With -stability, every converged step also counts the
negative eigenvalues of the energy Hessian (stability.py); a step that arrives at a less stable
equilibrium than it left is cut back too, so the load path stays on the stable branch (a genuine
loss of stability that survives all cut-backs is accepted and reported per step).
"""
import time

import numpy as np
from petsc4py import PETSc

from .partition import NDOF


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
        _default(opts, "snes_rtol", "1e-10")
        _default(opts, "snes_atol", repr(1e-11 * force_scale))
        _default(opts, "snes_stol", "1e-16")
        _default(opts, "snes_max_it", "40")
        _default(opts, "ksp_type", "preonly")
        _default(opts, "pc_type", "lu")
        if "mumps" in PETSc.Sys.getVersionInfo().get("version", "") or True:
            _default(opts, "pc_factor_mat_solver_type", "mumps")
        snes = PETSc.SNES().create(comm=comm)
        snes.setType("newtonls")
        snes.setFunction(problem.residual, problem.F)
        snes.setJacobian(problem.jacobian, problem.J)
        snes.setUpdate(problem.update)
        snes.setConvergenceHistory(length=1000, reset=True)
        snes.setConvergenceTest(self._converged)
        snes.setFromOptions()
        self.snes = snes
        rod = problem.scene.rod
        # roundoff floor of the residual: strains of size ~1 (v3 = 1), differentiated over a
        # node spacing, times the largest stiffness, summed over the nodes; a residual at this level is as converged as the
        # arithmetic allows (DIVERGED_MAX_IT there would reject a correct equilibrium).
        stiff = max(rod.EA, rod.GA1, rod.GA2) + max(rod.EI1, rod.EI2, rod.GJ) / rod.length
        m = problem.mesh
        nodes_per_length = m.nelem * m.order
        self.floor = 3 * np.finfo(float).eps * stiff * nodes_per_length * np.sqrt(m.n_nodes)
        self.divtol = 1e12
        self.force_scale = force_scale
        self.predictor = PETSc.Options().getBool("load_predictor", True)
        self.check_stability = check_stability
        self.f0 = None
        self.total_its = 0

    def _converged(self, snes, it, norms):
        """|F| <= atol, or |F| <= roundoff floor once Newton stagnates -> CONVERGED_FNORM_ABS; |F| <= rtol F_scale ->
        CONVERGED_FNORM_RELATIVE (relative to the problem's force scale, not to |F_0|, which the
        load-step predictor can inflate by orders of magnitude); NaN, blow-up beyond 1e12 |F_0|, or max_it -> diverged."""
        fnorm = norms[2]
        R = PETSc.SNES.ConvergedReason
        if not np.isfinite(fnorm):
            return R.DIVERGED_FNORM_NAN
        if it == 0:
            self.f0 = fnorm
            self.fprev = np.inf
        atol, rtol, _, maxit = snes.getTolerances()
        fprev, self.fprev = self.fprev, fnorm
        if fnorm <= atol:
            return R.CONVERGED_FNORM_ABS
        # below the roundoff floor, accept only once Newton has stopped gaining (|F| no longer
        # falls tenfold): an iterate that merely crossed the floor on its way down is not yet
        # the most accurate state the arithmetic allows
        if fnorm <= self.floor and (fnorm > 0.1 * fprev or fnorm <= 1e-3 * self.floor):
            return R.CONVERGED_FNORM_ABS
        if it > 0 and fnorm <= rtol * self.force_scale:
            return R.CONVERGED_FNORM_RELATIVE
        if fnorm > self.divtol * self.f0:
            return R.DIVERGED_DTOL
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
        return StepResult(lam, ok, its, reason, fnorm, np.array(hist), time.perf_counter() - t0)

    def run(self, lam0, steps, max_cutbacks, min_step, on_step=None, on_fail=None):
        """Step lambda from lam0 to 1 in ``steps`` nominal increments with cut-back.

        on_step(result) is called after every converged step (write output there)."""
        p = self.problem
        nominal = 1.0 / steps      # the same load grid when a run is restarted from lam0
        lam, dlam = lam0, nominal
        cutbacks = 0
        results = []
        prev = None            # (snapshot, lambda) of the previous converged step
        nneg = 0               # negative eigenvalues of the last converged step (-stability)
        while lam < 1.0 - 1e-14:
            target = min(1.0, lam + dlam)
            snap = p.state.snapshot()
            if prev is not None and self.predictor:
                p.state.predict(prev[0], (target - lam) / (lam - prev[1]))
            res = self.solve_at(target)
            if res.converged and self.check_stability:
                from .stability import negative_eigenvalues
                res.negative_eigenvalues = negative_eigenvalues(p)
                if (res.negative_eigenvalues > nneg and cutbacks < max_cutbacks
                        and 0.5 * dlam >= min_step):
                    # the step landed on a less stable equilibrium than the one it left: the
                    # path turned near a limit/bifurcation point; retry with a shorter step
                    res.converged = False
                    res.reason = "stability"
            if res.converged:
                nneg = getattr(res, "negative_eigenvalues", 0)
                prev = (snap, lam)
                lam = target
                self.total_its += res.its
                results.append(res)
                if on_step is not None:
                    on_step(res)
                cutbacks = 0
                dlam = min(nominal, 1.5 * dlam)
            else:
                p.state.restore(snap)
                p.set_load(lam)
                cutbacks += 1
                if on_fail is not None:
                    on_fail(res, dlam)
                dlam *= 0.5
                if cutbacks > max_cutbacks or dlam < min_step:
                    return results, False
        return results, True
