"""Pseudo-arclength continuation: following the equilibrium branch around a fold of the load path.

Load stepping parametrises the branch by lambda and stops where lambda turns back (a fold,
lambda_max along the branch): no equilibrium exists just beyond it.  Pseudo-arclength
continuation (Keller 1977) parametrises the branch by its length s instead.  With u = (x, lambda)
and the unit tangent t of the branch at the converged point u_n, the next point solves

    F(x, lambda) = 0,      < t, u - u_n >_W = ds                           (1)

with Newton on the bordered system

    [ J        F_lambda ] [ dx      ]     [ F ]
    [ W t_x    w t_lam  ] [ dlambda ] = - [ 0 ]                            (2)

(the corrections are orthogonal to t; the predictor u_n + ds t meets the constraint, so the
accumulated increments keep < t, u - u_n > = ds).  The bordered matrix is regular at a
simple fold, where J is singular.  It is solved by bordering with J's factorisation:
J a = -F, J b = -F_lambda, then

    dlambda = -< t_x, a >_W / (< t_x, b >_W + w t_lam),    dx = a + dlambda b.        (3)

Rotations are updated on the manifold as in every Newton step (R <- exp(dtheta^x) R, re-centred
before the next iteration); the chart of the constraint is the accumulated increments.

Metric: < u, v >_W = sum over nodes (dr . dr + l^2 dtheta . dtheta) / n_nodes + L^2 dlambda^2,
l = L / 2 pi: ds is a length (the RMS nodal motion, a rotation counted as the motion at
distance l, plus L x the change of the load factor).

F_lambda = dF/dlambda at fixed x by central differences (h = 1e-5) of the residual without the
contact term: lambda enters through the prescribed end rotation, the ramped loads and the
intrinsic twist ramp; contact depends on positions only.  The first tangent is the exact one,
t ~ (b, 1) from J b = -F_lambda at the converged starting point (oriented to increasing
lambda: the branch as it arrives at the fold); the next ones are secants through the last two
points.  Each step counts the Hessian's negative eigenvalues with -stability: along a branch
through a simple fold, their number changes by one exactly where lambda turns.

The corrector is held to the load steps' convergence test (NewtonSolver.convergence_test), its
steps to the contact step limits of RodProblem.precheck (1: motion near contact, 2: penetration;
not the energy line search, which does not apply where lambda moves).
"""
import time

import numpy as np
from petsc4py import PETSc

from rodsnes.model import so3
from rodsnes.model.partition import NDOF
from rodsnes.solve.step import StepResult


# a converged corrector farther than this many step lengths ds from the last point (in the
# metric W) landed on another branch: the step is not accepted, ds halved (the corrector keeps
# <t, u - u_n> = ds, but nothing bounds its part across t: a snapping arch's continuation wrote
# one point 15 ds away, on the far side of the snap, and called it the branch past the fold)
MAX_DRIFT = 2.0


class Arclength:
    """Pseudo-arclength steps from the current converged state (module docstring).  solver: the
    Newton path's solver (solver.NewtonSolver), whose SNES, linear solver, convergence test,
    inertia count and penalty promise the corrector uses."""

    def __init__(self, solver):
        self.solver = solver
        self.p = p = solver.problem
        ld = p.scene.loads
        self.max_steps = ld.arclength_max_steps
        self.target_its = ld.arclength_its
        L = p.mesh.length
        ell = L / (2 * np.pi)
        n = p.mesh.n_nodes
        self.w = p.layout.create_vec()
        with self.w as a:
            a = a.reshape(-1, NDOF)
            a[:, 0:3] = 1.0 / n
            a[:, 3:6] = ell ** 2 / n
        self.w_lam = L ** 2
        # a step moves no node by more than the contact radius (RMS), and first by a quarter
        self.ds_max = p.length_scale if p.length_scale is not None else 0.05 * L
        self.comm = p.layout.comm.tompi4py()
        self.steps = 0

    # -- pieces ------------------------------------------------------------------------
    def dot(self, ax, al, bx, bl):
        """< (ax, al), (bx, bl) >_W (collective)."""
        t = ax.copy()
        t.pointwiseMult(t, self.w)
        v = t.dot(bx) + self.w_lam * al * bl
        t.destroy()
        return v

    def dF_dlambda(self, h=1e-5):
        """F_lambda at the current X and lambda: central differences of the residual of the
        rod and the terms that depend on lambda (RodProblem.load_terms: not contact).  A new
        Vec."""
        p = self.p
        lam = p.lam
        terms = p.load_terms()
        Fp, Fm = p.layout.create_vec(), p.layout.create_vec()
        try:
            for sign, F in ((1.0, Fp), (-1.0, Fm)):
                p.set_load(lam + sign * h, refresh=False)
                p.residual(None, p.state.X, F, terms=terms)
        finally:
            p.set_load(lam, refresh=False)
        Fp.axpy(-1.0, Fm)
        Fp.scale(0.5 / h)
        Fm.destroy()
        return Fp

    def difference(self, snap_a, lam_a, snap_b, lam_b):
        """u_a - u_b for two re-centred states (snapshots): (dx Vec with dtheta = log(R_a R_b^T),
        dlambda)."""
        qa, Xa = snap_a
        qb, Xb = snap_b
        no = self.p.layout.n_owned
        d = Xa.copy()
        d.axpy(-1.0, Xb)
        with d as a:
            a.reshape(-1, NDOF)[:, 3:6] = so3.log_relative(qa[:no], qb[:no])
        return d, lam_a - lam_b

    def normalise(self, tx, tl):
        nrm = np.sqrt(self.dot(tx, tl, tx, tl))
        tx.scale(1.0 / nrm)
        return tx, tl / nrm, nrm

    def _linear_solver(self):
        ksp = self.solver.snes.getKSP()
        ksp.setOperators(self.p.J)
        return ksp

    def exact_tangent(self):
        """Unit tangent (t_x, t_lam) of the branch at the current equilibrium, oriented to
        increasing lambda: J b = -F_lambda, t ~ (b, 1)."""
        p = self.p
        p.update(None, 0)
        p.jacobian(None, p.state.X, p.J, p.J)
        Fl = self.dF_dlambda()
        Fl.scale(-1.0)
        b = p.layout.create_vec()
        self._linear_solver().solve(Fl, b)
        Fl.destroy()
        tx, tl, nrm = self.normalise(b, 1.0)
        return tx, tl, nrm

    # -- one step -----------------------------------------------------------------------
    def corrector(self, t, ds, snap_n, lam_n):
        """From u_n (snapshot, lambda) the predictor u_n + ds t, then Newton on (2).  Returns a
        StepResult (the state at the new point when converged)."""
        p, solver = self.p, self.solver
        t0 = time.perf_counter()
        tx, tl = t
        p.state.restore(snap_n)
        p.state.X.axpy(ds, tx)                 # r += ds t_r, theta = ds t_theta
        lam = lam_n + ds * tl
        p.set_load(lam)                        # prescribed values; the pattern follows
        snes = solver.snes
        maxit = snes.getTolerances()[3]
        hist, its, reason = [], 0, None
        a = p.layout.create_vec()
        b = p.layout.create_vec()
        Y = p.layout.create_vec()
        wt = tx.copy()                         # W t_x: the constraint row, fixed for the step
        wt.pointwiseMult(wt, self.w)
        energy_descent, p.energy_descent = p.energy_descent, False
        # <t, u - u_n>_W - ds: what the steps along the retraction added to the constraint (each
        # step is orthogonal to t, its correction not: fed back into the next load correction)
        g = 0.0
        try:
            while True:
                p.update(None, its)            # re-centre, contact pattern
                p.residual(None, p.state.X, p.F)
                f = p.F.norm()
                hist.append(f)
                reason = solver.convergence_test(snes, its, (0.0, 0.0, f))
                if reason != PETSc.SNES.ConvergedReason.CONVERGED_ITERATING or its >= maxit:
                    break
                p.jacobian(None, p.state.X, p.J, p.J)
                ksp = self._linear_solver()
                Fl = self.dF_dlambda()
                p.F.copy(Y)
                Y.scale(-1.0)
                ksp.solve(Y, a)
                Fl.scale(-1.0)
                ksp.solve(Fl, b)
                Fl.destroy()
                if ksp.getConvergedReason() < 0:
                    reason = "linear solve failed"
                    break
                dl = -(g + wt.dot(a)) / (wt.dot(b) + self.w_lam * tl)
                a.axpy(dl, b)                  # dx = a + dlambda b
                a.copy(Y)
                Y.scale(-1.0)                  # precheck's convention: X_new = X - Y
                y0 = Y.norm()
                if p.step_limit:
                    p.precheck(p.state.X, Y)
                s = Y.norm() / y0 if y0 > 0 else 1.0
                s = self.comm.bcast(s, root=0)
                if solver.retraction is not None:      # along the retraction, as newton.py
                    corr = solver.retraction.move(p.state.X, s, a)
                    wr = wt.getArray(readonly=True).reshape(-1, NDOF)[:, 0:3]
                    g = (1.0 - s) * g + self.comm.allreduce(float((wr * corr).sum()))
                else:
                    p.state.X.axpy(s, a)
                lam += s * dl
                p.set_load(lam, refresh=False)
                its += 1
        except PETSc.Error:
            reason = -100
            solver.reset_linear_solver()
        finally:
            p.energy_descent = energy_descent
            for v in (a, b, Y, wt):
                v.destroy()
        p.state.recentre()
        ok = isinstance(reason, int) and reason > 0 and bool(np.all(np.isfinite(hist)))
        res = StepResult(lam, ok, its, "arclength" if ok else reason, hist[-1] if hist else np.nan,
                         np.array(hist), time.perf_counter() - t0)
        res.arclength = True
        return res

    # -- around a fold -------------------------------------------------------------------
    def around(self, lam_fold, on_step=None, prev=None, ds=None, stop=1.0):
        """Follow the branch from the current equilibrium (at load <= lam_fold) until it is past
        the fold: a converged point with lambda increasing, beyond lam_fold or after lambda has
        fallen, and (-stability, loads with an energy) no negative eigenvalue; or lambda reaches
        ``stop`` (-load_stop, 1 by default; the last point then solved at lambda = stop by plain
        Newton from the point before).  A point the corrector found farther than MAX_DRIFT ds
        from the last is on another branch: not accepted, ds halved.  prev: (snapshot, lambda) of the point before the
        current one on the branch, to start from the secant (a restart inside the continuation);
        None: the exact tangent.  on_step(result) after every converged point (result.arclength,
        result.arclength_from = lam_fold, result.next_increment = the next ds).  Returns
        (results, ok, (snapshot, lambda) of the point before the last)."""
        p, solver = self.p, self.solver
        results = []
        snap, lam = p.state.snapshot(), p.lam
        if prev is None:
            tx, tl, nrm = self.exact_tangent()
            if ds is None:   # the nominal load step's length along the tangent, within limits
                ds = min(solver.nominal * nrm, 0.25 * self.ds_max)
        else:
            tx, tl = self.difference(snap, lam, prev[0], prev[1])
            tx, tl, nrm = self.normalise(tx, tl)
            ds = nrm if ds is None else ds
        ds_min = 1e-6 * self.ds_max
        went_back = False
        raise_wall = False          # a point was written: its wall raise before the next one
        while self.steps < self.max_steps:
            if raise_wall:          # (none after the last point: the caller's, when it goes on)
                self.p.ease_walls(lam, say=solver.say)
                raise_wall = False
            res = self.corrector((tx, tl), ds, snap, lam)
            if res.converged:
                new = p.state.snapshot()
                dx, dl = self.difference(new, res.lam, snap, lam)
                drift = np.sqrt(self.dot(dx, dl, dx, dl)) / ds
                dx.destroy()
                new[1].destroy()
                if drift > MAX_DRIFT:
                    res.converged = False
                    res.reason = (f"it landed {drift:.1f} steps from the last point: another "
                                  f"branch")
            if res.converged and res.lam > stop:
                # past the end of the load: the last point is solved at lambda = stop
                p.state.restore(snap)
                p.set_load(stop)
                res = solver.solve_guarded(stop)
                res.arclength, res.reason = True, "arclength: end"
                if not res.converged:
                    p.state.restore(snap)
                    p.set_load(lam)
                    ds *= 0.5
                    if ds < ds_min:
                        break
                    continue
            if res.converged and solver.check_stability:
                res.negative_eigenvalues = solver.negative_eigenvalues()
            if not res.converged:
                p.state.restore(snap)
                p.set_load(lam)
                ds *= 0.5
                solver.say(f"  arclength step ds {2 * ds:.3e} from load {lam:.6f} not accepted "
                           f"(reason {res.reason}, {res.its} its): ds halved")
                if ds < ds_min:
                    break
                continue
            self.steps += 1
            solver.keep_penetration(res)
            solver.total_its += res.its
            new = p.state.snapshot()
            dx, dl = self.difference(new, res.lam, snap, lam)
            if self.dot(dx, dl, tx, tl) < 0:          # never: the corrector keeps <t, du> = ds
                dx.scale(-1.0)
                dl = -dl
            prev, snap, lam = (snap, lam), new, res.lam
            tx.destroy()
            tx, tl, _ = self.normalise(dx, dl)       # secant tangent
            went_back |= tl < 0
            if res.its <= self.target_its // 2:
                ds = min(1.5 * ds, self.ds_max)
            elif res.its > self.target_its:
                ds *= 0.7
            res.arclength_from = lam_fold
            res.next_increment = ds
            results.append(res)
            if on_step is not None:
                on_step(res)
            raise_wall = True
            if lam >= stop - 1e-14:         # the end of the load, stable or not
                return results, True, prev
            past = tl > 0 and (went_back or lam > lam_fold)
            # a count decides stability only for loads with an energy (solver.conservative)
            stable = not solver.conservative or getattr(res, "negative_eigenvalues", 0) == 0
            if past and stable:
                return results, True, prev
        return results, False, prev
