"""A-posteriori error estimate of a converged load step, and the mesh a tolerance asks for.

Estimate (docs/error_estimate.md).  The discrete equilibrium u_p of order p on N elements is
carried onto the mesh of order p+1 on the same elements (model/refine.py: positions by their
Lagrange interpolant, rotations by the elements' projection-based quaternion interpolation, so
the carried state is the same rod, node for node), and Newton's method on that enriched problem,
started there, gives u_{p+1}.  Its error is O(h^(p+2)) against O(h^(p+1)), so

    eta_tip = |x_{p+1}(L) - x_p(L)|,    eta_centreline = max_s |x_{p+1}(s) - x_p(s)|

(s: 8 points per element of the fine sampling, refine.sample_points) estimate the true errors
|x_p(L) - x(L)| and max_s |x_p(s) - x(s)| in length units, with
(1 - r) e <= eta <= (1 + r) e for r = e_{p+1} / e_p (within a factor 3 whenever r <= 2/3).
u_{p+1} is found from the carried state in two stages (EnrichedProblem): the new nodes alone
with the carried ones held (SNES, prefix -estimate_), then the whole problem: where the run
minimises the energy, the same minimisation as its load steps (minimize.EnergyMinimizer, its
Newton step's KSP under -estimate_, to the run's tolerance, on a stable equilibrium: it lands
in the order p+1 minimum of the carried state's basin, whatever the round-off); otherwise SNES
with full Newton steps until a correction is below 1 % of the distance travelled from the
carried state (the estimate is then good to ~1 %).
Why p+1 rather than h/2: h/2 doubles the unknowns (cost x2 per estimate) and its error ratio
2^-(p+1) is what p+1 gives at (p+1)/p times the unknowns; p+1 keeps the same elements, so the
contact pairs, the partition and the element turn limits of the run carry over unchanged.

Tolerance (-rod_tolerance TOL, to_tolerance): runs the whole load path on a coarse mesh, then
on meshes chosen from the estimate (eta ~ C h^(p+1), the rate measured between the last two
meshes when there are two) aiming at TOL/2, until eta_centreline <= TOL; without -rod_order the
order of the least predicted cost (tangent blocks N (p+1)^2) is picked from estimates of every
order 2..4 made on the coarse mesh's final state.  Every trial writes into the output directory
(the last one stays); summary.json ``tolerance`` lists them with their cost.
"""
import math
import time
from dataclasses import replace

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from rodsnes.errors import tell
from rodsnes.model import mesh as rodmesh
from rodsnes.model import partition, refine
from rodsnes.model.partition import NDOF
from rodsnes.model.problem import RodProblem
from rodsnes.model.scales import force_scale
from rodsnes.solve.minimize import EnergyMinimizer
from rodsnes.solve.load_path import leave_plane_if_unstable
from rodsnes.solve.planar import PlanarSystem
from rodsnes.terms import scene_terms
from rodsnes.solve.linear import LUChoice, direct_solver_defaults, option_default, solver_made

PREFIX = "estimate_"          # options prefix of the enriched problem's SNES (-estimate_snes_*)


def gathered_state(problem):
    """Natural-ordered positions (n,3) and unit quaternions (n,4) of the problem's state, on
    every rank (collective)."""
    r, q = problem.state.local_config()
    no = problem.layout.n_owned
    lay = problem.layout
    return lay.allgather_nodes(r[:no]), lay.allgather_nodes(q[:no])


class EnrichedProblem:
    """The scene of a run on another discretisation (order, nelem), solved by Newton (PETSc SNES,
    options prefix -estimate_) from a state carried over from the run's mesh.  Built once and
    reused at every step.

    Two stages (docs/error_estimate.md "Why two stages"): first the new nodes alone, the carried
    nodes held (``interior``: element-local problems, stiff and well conditioned), then the whole
    problem (``whole``).  Newton on the whole problem straight from the carried state fails on
    slender rods: the carried state's residual sits in the stiff extension and shear of the new
    nodes (the helix on 32 quadratic elements: |F| = 23, 7.7e-3 once they are relaxed), and the
    quadratic part of that stiff correction, projected on the soft global bending modes (singular
    values 1e-5 of a tangent whose largest is 3e4), makes the first Newton step 100 times longer
    than the distance to the solution (2.2e-2 against 2.5e-4); no line search on |F| recovers."""

    MAX_IT_INTERIOR = 10
    # the whole stage (-estimate_snes_max_it; the minimiser goes on past it while the energy
    # still falls): the plectoneme's two-ply at 10 turns takes 51 iterations, 1.0 s
    MAX_IT = 200
    INTERIOR_SHARE = 1e-2       # the interior stage ends when its |F| < this x the whole |F|

    def __init__(self, scene, comm, order, nelem, minimize=False, plane=None):
        self.scene = replace(scene, rod=refine.enriched_rod(scene.rod, order, nelem))
        self.mesh = rodmesh.build_mesh(self.scene.rod, scene.bc)
        self.layout = partition.Layout(comm, self.mesh)
        terms = scene_terms(self.scene, self.mesh, self.layout)
        self.problem = RodProblem(self.scene, self.mesh, self.layout, terms)
        if plane is not None and minimize:
            # the run solves in this plane: the whole stage's minimisation takes its Newton
            # steps (its KSP under -estimate_, as in 3-D) and stability count
            # (-planar_stability_, as the run's) on the in-plane block (planar.py; its guard,
            # asked before every whole stage, goes on in 3-D, silently, when the carried state
            # is not planar)
            self.problem.planar = PlanarSystem(self.problem, plane, prefix=PREFIX)
        self.comm = comm.tompi4py()
        self.floor = 1e-13 * self.mesh.length
        self.stage = "whole"
        self.held_from = None           # the mesh whose nodes the interior stage holds
        self.X0 = self.problem.state.X.duplicate()     # the carried state
        self.snes = self._snes()
        if self.problem.planar is not None:
            # the interior stage's Newton steps on the in-plane block too, as the Newton
            # path's (planar.PlanarSystem.attach: the full 6-dof Jacobian, at 10^5 cubic
            # elements of order 4 a matrix of 0.8 GB and its factors as much, is made only
            # if the state is not planar)
            self.problem.planar.attach(self, jacobian=self._jacobian_in_plane)
        else:
            self.problem.on_pattern_change = self._set_matrix
        self.minimizer = None
        if minimize:        # the whole stage as the run's load steps: minimise the energy
            max_it = PETSc.Options().getInt(PREFIX + "snes_max_it", self.MAX_IT)
            self.minimizer = EnergyMinimizer(self.problem, force_scale(self.scene),
                                             rtol=self.scene.loads.rtol, max_it=max_it,
                                             prefix=PREFIX)

    # -- SNES --------------------------------------------------------------------------
    def _snes(self):
        """newtonls with full steps (-estimate_snes_linesearch_type basic: backtracking on |F|,
        bt, stalls on slender rods, whose |F| the stiff rows dominate: docs/error_estimate.md),
        the run's direct LU (solve/linear.py), at most MAX_IT iterations of the whole stage, defaults a user's -estimate_*
        options override; the problem's residual and tangent (masked in the interior stage), its
        rotation update before every step, and the convergence test _converged."""
        p = self.problem
        for name, value in (("snes_linesearch_type", "basic"), ("snes_max_it", str(self.MAX_IT))):
            option_default(PREFIX + name, value)
        # the LU as the Newton path's: MUMPS from a pattern that contact fills, on several
        # ranks each rank's stretch with the Schur complement where they meet (linear.LUChoice;
        # without it the whole matrix on every rank: 2 ranks took longer than one)
        self.lu = LUChoice(direct_solver_defaults(p, PREFIX))
        solver_made(PREFIX)
        snes = PETSc.SNES().create(comm=self.layout.comm)
        snes.setOptionsPrefix(PREFIX)
        snes.setType("newtonls")
        snes.setFunction(self._residual, p.F)
        snes.setJacobian(self._jacobian, p.J if p.planar is None else None)
        snes.setUpdate(self._update)
        snes.setConvergenceTest(self._converged)
        snes.setLineSearchPreCheck(self._precheck)
        snes.setFromOptions()
        return snes

    def _update(self, snes, its):
        """Before every Newton step: the problem's update (the rotations re-centred) and the
        LU's choice for a new pattern (linear.LUChoice)."""
        self.problem.update(snes, its)
        self.lu.check(snes.getKSP(), self.problem)

    def _set_matrix(self, J):
        """A new contact pattern (RodProblem._new_matrix): the new matrix, no old factorisation."""
        self.snes.setJacobian(None, J)
        self.snes.getKSP().reset()

    def _hold(self, mesh):
        """The rows the interior stage holds: every dof of this rank's nodes that are nodes of
        ``mesh`` (refine.kept_nodes), as local rows of F and a global IS."""
        if self.held_from is mesh:
            return
        lay = self.layout
        kept = refine.kept_nodes(mesh, self.mesh)[lay.owned_nodes]
        rows = (np.flatnonzero(kept)[:, None] * NDOF + np.arange(NDOF)).ravel()
        lo, _ = self.problem.F.getOwnershipRange()
        self.held_rows = rows
        self.held_is = PETSc.IS().createGeneral((lo + rows).astype(PETSc.IntType),
                                                comm=self.layout.comm)
        # the same nodes' rows of the in-plane block (3 a node; planar.PlanarSystem.J)
        lo3 = 3 * int(lay.starts[lay.comm.getRank()])
        rows3 = (np.flatnonzero(kept)[:, None] * 3 + np.arange(3)).ravel()
        self.held_is_plane = PETSc.IS().createGeneral((lo3 + rows3).astype(PETSc.IntType),
                                                      comm=self.layout.comm)
        self.held_from = mesh

    def _residual(self, snes, X, F):
        """The problem's residual; in the interior stage zero on the held rows (whose whole norm
        is kept: the interior stage's convergence test compares with it)."""
        self.problem.residual(snes, X, F)
        if self.stage == "interior":
            self.whole_fnorm = F.norm()
            with F as a:
                a[self.held_rows] = 0.0

    def _jacobian(self, snes, X, J, P):
        """The problem's tangent; in the interior stage the held rows and columns identity."""
        self.problem.jacobian(snes, X, J, P)
        if self.stage == "interior":
            P.zeroRowsColumns(self.held_is, 1.0)
        self.factorisations += 1

    def _jacobian_in_plane(self, snes, X, J, P):
        """The in-plane block's tangent (planar.PlanarSystem.snes_jacobian; the full one once
        the state has left the plane); in the interior stage the held rows and columns
        identity."""
        pl = self.problem.planar
        pl.snes_jacobian(snes, X, J, P)
        if self.stage == "interior":
            if pl.active:
                pl.J.zeroRowsColumns(self.held_is_plane, 1.0)
            else:
                self.problem.J.zeroRowsColumns(self.held_is, 1.0)
        self.factorisations += 1

    def _precheck(self, X, Y):
        """Keeps the length of the Newton correction (its largest position part) for the
        convergence test; in the whole stage of a contact scene the step limits of
        RodProblem.precheck."""
        self.newton_move = self.comm.allreduce(_largest_move(Y), op=MPI.MAX)
        p = self.problem
        if self.stage == "whole" and p.step_limit:
            return p.precheck(X, Y, self.snes.getFunction()[0])
        return False

    def _travelled(self):
        """max over the nodes of |x - x_carried| (collective)."""
        W = self.problem.state.X.copy()
        W.axpy(-1.0, self.X0)
        out = self.comm.allreduce(_largest_move(W), op=MPI.MAX)
        W.destroy()
        return out

    def _converged(self, snes, it, norms):
        """interior stage: |F| of the new nodes below INTERIOR_SHARE x the whole |F| (the rest is
        the whole stage's), or 1e-10 of its start; whole stage: the last Newton correction below
        rtol (1e-2) times the way travelled from the carried state, or below 1e-13 L (round-off):
        the state is then within about rtol of the error of the solution, and so the estimate.
        Not finite, or max_it (the interior stage at most MAX_IT_INTERIOR): diverged."""
        R = PETSc.SNES.ConvergedReason
        fnorm = norms[2]
        if not np.isfinite(fnorm):
            return R.DIVERGED_FNORM_NAN
        if it == 0:
            self.f0 = fnorm
            return R.CONVERGED_FNORM_ABS if fnorm == 0.0 else R.CONVERGED_ITERATING
        maxit = snes.getTolerances()[3]
        if self.stage == "interior":
            if (fnorm <= self.INTERIOR_SHARE * self.whole_fnorm or fnorm <= 1e-10 * self.f0
                    or self.newton_move <= self.floor):
                return R.CONVERGED_FNORM_RELATIVE
            maxit = min(maxit, self.MAX_IT_INTERIOR)
        elif self.newton_move <= max(self.rtol * self._travelled(), self.floor):
            return R.CONVERGED_SNORM_RELATIVE
        if it >= maxit:
            return R.DIVERGED_MAX_IT
        return R.CONVERGED_ITERATING

    def solve_stage(self, stage):
        """One solve of the stage from the current state: (iterations, converged).  The whole
        stage of a run that minimises is its minimisation (minimize.EnergyMinimizer), to the
        run's tolerance on a stable equilibrium; every other stage is an SNES solve."""
        self.stage = stage
        if stage == "whole" and self.minimizer is not None:
            n0 = self.minimizer.factorizations
            res = self.minimizer.solve_at(self.problem.lam)
            # in the plane, a stable minimum out of it too, as the run's steps are (the order
            # p+1 discretisation may buckle sideways where the run's did not); a state its
            # count finds unstable is no estimate
            leave_plane_if_unstable(self.minimizer, res, "the order p+1 solution")
            self.factorisations += self.minimizer.factorizations - n0
            return res.its, res.converged and res.negative_eigenvalues <= 0
        try:
            self.snes.solve(None, self.problem.state.X)
            ok = self.snes.getConvergedReason() > 0
        except PETSc.Error:               # e.g. MUMPS failing after a failed factorisation
            self.snes.getKSP().reset()
            ok = False
        return self.snes.getIterationNumber(), ok

    # -- the carried state and the solve ---------------------------------------------
    def place(self, mesh, x_nodes, q_nodes):
        """Put the state (x_nodes, q_nodes) of ``mesh`` (natural order, all nodes) onto this
        discretisation (refine.transfer), rotation increments zero."""
        x, q = refine.transfer(mesh, x_nodes, q_nodes, self.mesh)
        st, lay = self.problem.state, self.layout
        st.q_ref[:] = q[lay.local_nodes]
        with st.X as a:
            a = a.reshape(-1, NDOF)
            a[:, 0:3] = x[lay.owned_nodes]
            a[:, 3:6] = 0.0

    def solve_from(self, mesh, x_nodes, q_nodes, lam, terms=(), gauge=False, rtol=1e-2):
        """Newton on this discretisation at load lam from the carried state (place), each term
        adopting what the run's same term has adapted (``terms``, Term.adopt: the run's current
        penalty, so that the estimate measures the discretisation, not the penalty): the interior stage, the nodes of ``mesh`` held, then the whole
        problem (class docstring): minimised to the run's tolerance (``minimize``), or by Newton
        until a correction is below rtol times the way travelled from the carried state (the
        estimate is then good to about rtol).  An interior
        stage that fails is dropped (the whole stage starts from the carried state).  Returns
        (x (n,3), q (n,4), iterations, factorisations, converged).  Collective."""
        p = self.problem
        self.rtol, self.factorisations = rtol, 0
        self._hold(mesh)
        self.place(mesh, x_nodes, q_nodes)
        for mine, run_term in zip(p.terms, terms):
            mine.adopt(run_term)
        p.set_load(lam)
        if gauge:
            p.hold_sliding()
        p.state.X.copy(self.X0)
        # the plane's guard on the carried state before either stage: in the interior stage
        # the SNES's planar PC would take a state out of the plane to its unmasked 3-D
        # Jacobian, the held nodes free (they moved by 7.8 L from ltb's buckled state); the
        # minimiser asks it before a Newton step, not before a stability count at a state
        # already converged
        self._guard()
        its, ok = self.solve_stage("interior")
        if not ok:
            self.place(mesh, x_nodes, q_nodes)
        self._guard()
        more, converged = self.solve_stage("whole")
        x, q = gathered_state(p)
        return x, q, its + more, self.factorisations, converged

    def _guard(self):
        """planar.PlanarSystem.holds on the state's residual, where the plane is still held."""
        p = self.problem
        if p.planar is not None and p.planar.active:
            p.residual(None, p.state.X, p.F)
            p.planar.holds(p.F)

    def destroy(self):
        self.snes.destroy()
        self.X0.destroy()
        if self.minimizer is not None:
            self.minimizer.destroy()
        if self.problem.inertia is not None:
            self.problem.inertia.destroy()
            self.problem.inertia = None


def _largest_move(V):
    """max over this rank's nodes of |position part| of the vector V (r, theta per node)."""
    d = V.getArray(readonly=True).reshape(-1, NDOF)[:, 0:3]
    return float(np.sqrt((d * d).sum(axis=1)).max()) if len(d) else 0.0


def differences(mesh_a, xa, qa, mesh_b, xb, qb):
    """(tip, centreline): |x_b(L) - x_a(L)| (None for a closed rod) and max over the fine
    sampling of the finer mesh (refine.sample_points) of |x_b(s) - x_a(s)|, length units."""
    fine = mesh_a if mesh_a.nelem * mesh_a.order >= mesh_b.nelem * mesh_b.order else mesh_b
    s = refine.sample_points(fine)
    d = refine.positions_at(mesh_b, xb, s) - refine.positions_at(mesh_a, xa, s)
    tip = None if mesh_a.closed else float(np.linalg.norm(xb[-1] - xa[-1]))
    return tip, float(np.sqrt((d * d).sum(axis=1)).max())


class ErrorEstimator:
    """The estimate of every converged step of a run (module docstring): the order p+1 problem
    on the run's elements, made at the first step and kept."""

    @classmethod
    def of(cls, scene, comm, minimize=False):
        """The estimator a scene asks for (-rod_error_estimate), None for off; ``minimize``:
        the run's load steps minimise the energy, and so does the estimate's whole stage."""
        return None if scene.rod.error_estimate == "off" else cls(scene, comm, minimize)

    def __init__(self, scene, comm, minimize=False):
        self.scene, self.comm, self.minimize = scene, comm, minimize
        self.enriched = None
        self.seconds = 0.0              # spent estimating, all steps
        self.count = 0

    def estimate(self, problem):
        """{tip, centreline, order, nelem, newton_iterations, factorisations, seconds} of the
        problem's current (converged) state.  Collective."""
        t0 = time.perf_counter()
        rod = self.scene.rod
        pl = problem.planar
        planar = pl is not None and pl.active
        if self.enriched is None:
            self.enriched = EnrichedProblem(self.scene, self.comm, rod.order + 1, rod.nelem,
                                            minimize=self.minimize,
                                            plane=pl.plane if planar else None)
        mine = self.enriched.problem.planar
        if mine is not None and mine.active and not planar:     # the run has left the plane
            mine.leave("the run left the plane", "the run left the plane")
        x, q = gathered_state(problem)
        e = self.enriched
        xe, qe, its, nf, ok = e.solve_from(problem.mesh, x, q, problem.lam, terms=problem.terms,
                                           gauge=problem.gauge is not None)
        tip, line = differences(problem.mesh, x, q, e.mesh, xe, qe)
        dt = time.perf_counter() - t0
        self.seconds += dt
        self.count += 1
        # a non-finite difference is no estimate, whatever the solve said
        ok = bool(ok) and all(np.isfinite(v) for v in (line, tip if tip is not None else 0.0))
        # the run in its plane, its order p+1 solution out of it (solve_stage): buckled
        left = bool(planar and mine is not None and not mine.active and not mine.in_plane())
        return {"tip": tip, "centreline": line, "order": rod.order + 1, "nelem": rod.nelem,
                "load": problem.lam, "left_plane": left,
                "newton_iterations": its, "factorisations": nf, "converged": ok, "seconds": dt}


def wanted(estimator, scene, lam):
    """Whether the step converged at load lam gets an estimate: every step with
    -rod_error_estimate every, the step at -load_stop with last, none with off."""
    if estimator is None:
        return False
    return scene.rod.error_estimate == "every" or lam >= scene.loads.stop - 1e-12


def step_attrs(est):
    """The estimate as result.h5 step attributes (error_estimate_tip, _centreline)."""
    if est is None:
        return {}
    out = {"error_estimate_centreline": est["centreline"]}
    if est["tip"] is not None:
        out["error_estimate_tip"] = est["tip"]
    return out


def summary_entry(est, estimator, wall_time):
    """summary.json ``error_estimate``: the last step's estimate, how it was made, and the time
    all the steps' estimates took (seconds and share of the run)."""
    if est is None:
        return None
    return {"tip": est["tip"], "centreline": est["centreline"], "units": "length",
            "method": f"order {est['order']} on the same {est['nelem']} elements",
            "converged": est["converged"], "load": est["load"],
            "left_plane": est.get("left_plane", False), "steps_estimated": estimator.count,
            "seconds": estimator.seconds,
            "share_of_run": estimator.seconds / wall_time if wall_time > 0 else None}


def progress_text(est, penetration=None):
    """The estimate for the last progress line; with contact in touch (``penetration``: the
    deepest, in length units) what it does not count, the penalty's: an estimate of 3.6e-7 on
    rollup_contact stood 8e-4 from the hard contact's answer."""
    if est is None:
        return ""
    tip = "" if est["tip"] is None else f"tip {est['tip']:.1e}, "
    warn = "" if est["converged"] else (" (unreliable: the order p+1 solve did not converge "
                                        "to a stable state)")
    pen = "" if not penetration else (f" (the mesh's, at this penalty; the contact sinks up "
                                      f"to {penetration:.1e} deep)")
    # the order p+1 solution buckled out of the plane where the run's did not (estimate())
    side = ("; its order p+1 solution buckles out of the plane, this one does not: the mesh is "
            "too stiff out of plane" if est.get("left_plane") else "")
    return f"; estimated error {tip}centreline {est['centreline']:.1e}{warn}{pen}{side}"


# ------------------------------------------------------------------------------------------------
# -rod_tolerance
# ------------------------------------------------------------------------------------------------
ORDERS = (2, 3, 4)          # candidates when -rod_order is not given
MAX_NELEM = 4096
AIM = 0.5                   # refine towards AIM x TOL


def predicted_cost(order, nelem):
    """Work of a mesh, in tangent blocks: N (p+1)^2 (assembly, storage and the banded
    factorisation all grow with it)."""
    return nelem * (order + 1) ** 2


def elements_for(eta, nelem, rate, target, at_least):
    """Element count at which eta ~ C h^rate falls to target (at least at_least)."""
    if eta <= 0.0:
        return at_least
    need = nelem * (eta / target) ** (1.0 / rate)
    return max(at_least, int(math.ceil(need * 1.05)))


def order_estimates(run):
    """eta_centreline of every candidate order on the run's (coarse) elements at its final state:
    the order p and p+1 problems each solved from the run's state.  Collective."""
    x, q = gathered_state(run.problem)
    mesh, lam = run.mesh, run.problem.lam
    out = {}
    sols = {run.mesh.order: (mesh, x, q)}
    for p in sorted(set(ORDERS) | {o + 1 for o in ORDERS}):
        if p in sols:
            continue
        e = EnrichedProblem(run.scene, run.comm, p, mesh.nelem,
                            minimize=run.path == "minimize")
        xe, qe, _, _, _ = e.solve_from(mesh, x, q, lam, terms=run.problem.terms, gauge=run.problem.gauge is not None)
        sols[p] = (e.mesh, xe, qe)
        e.destroy()
    for p in ORDERS:
        out[p] = differences(*sols[p], *sols[p + 1])[1]
    return out


def next_mesh(trials, tol, order_fixed, run):
    """(order, nelem) of the next trial, or None when the prediction passes MAX_NELEM."""
    last = trials[-1]
    p, n, eta = last["order"], last["nelem"], last["estimate_centreline"]
    target = AIM * tol
    if not order_fixed and len(trials) == 1:
        etas = order_estimates(run)
        last["order_estimates"] = {str(k): v for k, v in etas.items()}
        picks = {o: elements_for(etas[o], n, o + 1, target, n) for o in ORDERS}
        p = min(ORDERS, key=lambda o: predicted_cost(o, picks[o]))
        nelem = picks[p] if p != last["order"] else elements_for(eta, n, p + 1, target, n + 1)
    else:
        same = [t for t in trials[:-1] if t["order"] == p and t["nelem"] != n
                and t["estimate_centreline"] > 0]
        rate = p + 1
        if same:
            t = same[-1]
            observed = math.log(t["estimate_centreline"] / eta) / math.log(n / t["nelem"])
            # an estimate that did not fall by a rate of 1/2 on the finer mesh measures no
            # rate (two trials on two branches: ltb on 4 linear elements unbuckled, on 10
            # buckled, gave -3.3, and at the rate 1 it was clamped to, 1e-5 asked for more
            # than MAX_NELEM): the nominal one
            rate = min(max(observed, 1.0), p + 2) if observed >= 0.5 else p + 1
        nelem = elements_for(eta, n, rate, target, n + 1)
    return None if nelem > MAX_NELEM else (p, nelem)


def to_tolerance(run):
    """-rod_tolerance: trials from the run's coarse mesh until eta_centreline <= TOL (module
    docstring).  Every trial is a whole run into the output directory; returns whether the last
    one converged and met the tolerance, and leaves summary.json with ``tolerance``."""
    scene, tol = run.scene, run.scene.rod.tolerance
    order_fixed = "rod_order" in scene.given
    t0 = time.perf_counter()
    trials, cur, reason = [], run, None
    while True:
        cur.tolerance_trial = True
        ok = cur.execute()
        est = cur.last_estimate
        trials.append({"order": cur.mesh.order, "nelem": cur.mesh.nelem, "dofs": cur.dofs,
                       "converged": bool(ok), "wall_time_s": time.perf_counter() - cur.t_start,
                       "newton_iterations": cur.solver.total_its,
                       "estimate_tip": None if est is None else est["tip"],
                       "estimate_centreline": None if est is None else est["centreline"]})
        if not ok or est is None:
            reason = f"the trial on {cur.mesh.nelem} elements of order {cur.mesh.order} failed"
            break
        if est["centreline"] <= tol and est["converged"]:
            break
        # an estimate whose order p+1 solve did not converge: too coarse to tell, twice the elements
        nxt = (next_mesh(trials, tol, order_fixed, cur) if est["converged"]
               else (cur.mesh.order, 2 * cur.mesh.nelem))
        if nxt is None:
            reason = (f"-rod_tolerance {tol:g}: the estimate {est['centreline']:.2e} on "
                      f"{cur.mesh.nelem} elements asks for more than {MAX_NELEM}; raise "
                      f"-rod_tolerance")
            break
        p, n = nxt
        cur = type(run)(replace(scene, rod=refine.enriched_rod(scene.rod, p, n)), run.comm)
        cur.record_scene()
        run.live_trial = cur        # an interruption or an error now describes this trial
    met = reason is None
    last = trials[-1]
    # from the first trial's start (the run itself, begun before this loop: its share of a
    # total counted from here read 142 %)
    total = time.perf_counter() - min(t0, getattr(run, "t_start", t0))
    block = {"tolerance": tol, "met": met, "order": last["order"], "nelem": last["nelem"],
             "estimate_centreline": last["estimate_centreline"],
             "estimate_tip": last["estimate_tip"], "trials": trials,
             "wall_time_s": total,
             "last_trial_share": min(1.0, last["wall_time_s"] / max(total, 1e-300))}
    s = cur.summary(converged=met, failed_reason=reason)
    s["tolerance"] = block
    s["wall_time_s"] = block["wall_time_s"]
    cur.write_summary(s)
    run.tolerance_result = (cur, block)
    if cur.rank == 0 and cur.quiet and not met:
        # -quiet leaves out the progress, not a failure
        tell("failed", reason)
    if cur.rank == 0 and not cur.quiet:
        pen = cur.penetration_length()
        what = (f"{last['nelem']} elements of order {last['order']}: estimated error "
                f"{last['estimate_centreline']:.1e} <= {tol:g}" if met else "FAILED: " + reason)
        if met and pen:
            what += (f" (the mesh's error at the contact penalty; the contact sinks up to "
                     f"{pen:.1e} deep, which it does not count)")
        print(f"-rod_tolerance {tol:g}: {what} after {len(trials)} mesh(es), "
              f"{block['wall_time_s']:.1f} s in all ({100 * block['last_trial_share']:.0f} % "
              f"in the last)", flush=True)
    return met
