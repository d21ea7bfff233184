"""Load stepping by energy minimisation (-load_path minimize): LoadPath.

LoadPath steps the load from lam0 to the stop: each increment starts from the last
converged state, with the prescribed end turns spread along the rod as material twist
(twist predictor: a rotation increment of the end arrives at every node in proportion to its
arclength, so no element sees a relative rotation near half a turn and a step of many turns
stays on the right sheet of SO(3)); the increment grows when a step took few iterations and
shrinks when it took many, and is halved on genuine failure (iteration limit, line search
failure, a link that differs from the imposed turns).
Each step's minimisation is minimize.EnergyMinimizer.
"""
import numpy as np

from rodsnes.model import so3
from rodsnes.solve.minimize import EnergyMinimizer

# the largest prescribed end turn per load step once the twist predictor spreads it
MAX_TURN_STEP = 1.0
# Newton iterations a load step is aimed at: longer steps cost more iterations each but fewer
# per unit of load (the plectoneme: 8 its for 0.01 turn, 33 for 0.1, 75 for 0.5).  Measured
# with the soft-valley walk (Intel Xeon VM; the plectoneme, PyElastica's scene as posed and
# two other plectonemes, in all): 20 -> 11441 iterations, 131 s; 80 -> 7116, 93 s; 160 ->
# 6351, 93 s with 4 cut-backs on the plectoneme
TARGET_ITS = 80
PREDICTOR = True


def leave_plane_if_unstable(minimizer, res, why="the planar equilibrium"):
    """A minimisation ``res`` of a planar problem (problem.planar): the out-of-plane block of
    the Hessian factored (planar.PlanarSystem.out_of_plane_count), its negative eigenvalues
    added to the step's (res.out_of_plane_negative_eigenvalues).  A planar minimum that is a
    saddle out of the plane (lateral-torsional buckling) is not what the minimiser promises:
    the problem leaves the plane and minimises again at the same load in 3-D from that state,
    which leaves the saddle along its negative curvature (EnergyMinimizer._escape); res takes
    the iterations and the outcome.  The run's load steps (LoadPath.check_plane) and the error
    estimate's order p+1 solve (estimate.py: a planar estimate that stayed in the plane
    reported 5e-6 for an unbuckled answer 0.09 L from the buckled one).
    Once left, a state that is still in the plane keeps being counted out of it
    (_count_out_of_plane): the 3-D count's neutral band (the Hessian's round-off, ~ EA / h^2:
    ltb with EA = 1e12 took -16.8 EI/L^4 as neutral) can hide the saddle that the block's own
    count, with its narrower band, finds; the 3-D minimisation then stopped at once on the
    planar state, which the run called stable (exit 0, 0.28 L from the buckled answer).
    Collective."""
    planar = minimizer.problem.planar
    if planar is None or not res.converged:
        return
    if not planar.active:
        _count_out_of_plane(planar, res)
        return
    n_out = planar.out_of_plane_count()
    res.out_of_plane_negative_eigenvalues = n_out
    if n_out <= 0:          # stable out of the plane, or a count that failed (-1): no claim
        return
    res.negative_eigenvalues += n_out
    planar.leave("%s is UNSTABLE out of plane (%d negative eigenvalue%s of the out-of-plane "
                 "Hessian)" % (why, n_out, "" if n_out == 1 else "s"), "unstable out of plane")
    again = minimizer.solve_at(res.lam)
    res.its += again.its
    res.seconds += again.seconds
    res.history = np.concatenate([res.history, again.history])
    res.fnorm, res.negative_eigenvalues = again.fnorm, again.negative_eigenvalues
    res.escapes += again.escapes
    res.valley_points += again.valley_points
    res.shifts += again.shifts
    res.line_search_cuts += again.line_search_cuts
    if not again.converged:
        res.converged, res.reason = False, f"in 3-D after leaving the plane: {again.reason}"
        return
    _count_out_of_plane(planar, res)


def _count_out_of_plane(planar, res):
    """A converged 3-D minimisation of a scene that left its plane, whose state is still in it
    and counted stable: the out-of-plane block's count stands (leave_plane_if_unstable).
    Collective."""
    if res.negative_eigenvalues != 0 or not planar.in_plane():
        return
    n = planar.out_of_plane_count()
    if n > 0:
        res.negative_eigenvalues = res.out_of_plane_negative_eigenvalues = n


class LoadPath:
    """Load stepping by minimisation (module docstring): the same contract as
    newton.NewtonSolver.run."""

    def __init__(self, problem, force_scale, rtol=1e-10, max_it=200, quiet=True,
                 max_increment=None):
        self.problem = problem
        self.minimizer = EnergyMinimizer(problem, force_scale, rtol=rtol, max_it=max_it,
                                         quiet=quiet)
        self.quiet = quiet
        c = problem.constraints
        self.turn_cap = c.max_load_increment(MAX_TURN_STEP)
        self.max_increment = max_increment
        self.fail_reason = None
        self.results = []
        self.link0 = None
        self.lam_link0 = 0.0
        self.floor = self.minimizer.floor

    def setup(self):
        """Before the path: the minimiser's (EnergyMinimizer.setup).  Collective."""
        self.minimizer.setup()

    def tolerance(self):
        """The gradient norm every step is held to: max(rtol x force scale, round-off floor)."""
        return max(self.minimizer.tol, self.floor)

    def solve_at(self, lam):
        """Minimise at load lam from the current state (one step, no predictor)."""
        return self.minimizer.solve_at(lam)

    @property
    def total_its(self):
        return self.minimizer.total_its

    def _say(self, text):
        if not self.quiet and self.problem.layout.comm.getRank() == 0:
            print(text, flush=True)

    def twist_angles(self, dlam):
        """The end rotation's increment 2 pi T dlam (-bc_end_turns T) spread along the rod as
        material twist: phi_i = 2 pi T dlam s_i / L on the local nodes (None without end
        turns or on a ring)."""
        p = self.problem
        T = p.constraints.end_turns
        if not T or p.mesh.closed:
            return None
        return 2.0 * np.pi * T * dlam * p.mesh.s_nodes[p.layout.local_nodes] / p.mesh.length

    def twist_predictor(self, dlam):
        """Spread the end rotation's increment along the rod as material twist (twist_angles):
        R_i <- R_i exp(phi_i e3^x)."""
        phi = self.twist_angles(dlam)
        if phi is not None:
            q = self.problem.state.q_ref
            q[:] = so3.twisted(q, phi)

    def keep_promise(self, res, max_raises=4):
        """-contact_penalty_adapt: while the converged state's deepest penetration exceeds the
        promise p* (-contact_penetration, a fraction of the diameter), raise the penalty
        (ContactTerm.promised_penalty) and minimise again at the same load (mu never falls along a
        path).  res takes the iterations; a re-solve that fails fails the step.  Collective."""
        for term in self.problem.adaptive_terms():
            if not self._keep_promise_of(term, res, max_raises):
                return

    def _keep_promise_of(self, ct, res, max_raises):
        """keep_promise for one term; False when a re-solve failed (the step fails)."""
        p = self.problem
        for _ in range(max_raises):
            pen, mu1 = ct.promised_penalty(p.state.local_config()[0])
            if mu1 is None:
                return True
            mu0 = ct.mu
            ct.set_penalty(mu1)
            again = self.minimizer.solve_at(res.lam)
            res.its += again.its
            res.seconds += again.seconds
            res.history = np.concatenate([res.history, again.history])
            res.fnorm, res.negative_eigenvalues = again.fnorm, again.negative_eigenvalues
            ct.penalty_raises += 1
            self._say(f"  load {res.lam:.6f}: penetration {pen:.2%} of the diameter > "
                      f"-contact_penetration {ct.penetration:g}: penalty {mu0:.4g} -> "
                      f"{ct.mu:.4g}, minimised again in {again.its} its")
            if not again.converged:
                res.converged, res.reason = False, f"after a penalty raise: {again.reason}"
                ct.set_penalty(mu0)
                return False
        return True

    def check_plane(self, res):
        """A planar run's converged step: unstable out of the plane (lateral-torsional
        buckling), it leaves the plane and minimises again at the same load in 3-D
        (leave_plane_if_unstable).  Collective."""
        leave_plane_if_unstable(self.minimizer, res)

    def predict(self, prev, lam, dl):
        """The start of the step lam -> lam + dl: the secant through the last two converged
        states (positions and rotations, problem.RodState.predict) when there is a step before,
        as far along as the minimiser's move limits let any node move (the rest of the end's
        turn spread as twist, which moves no node), and kept when it penetrates no deeper than
        the line search allows; else the last state with the end turns spread as twist
        (twist_predictor).  Unlimited, a long step's secant once carried a strand through
        another (the plectoneme at 2.22 turns, +0.6: the step converged with the link off by
        2 and was cut back).  Collective."""
        p = self.problem
        if prev is not None and PREDICTOR:
            m = self.minimizer
            depth0 = p.deepest(p.state.local_config()[0], report=False)   # None: no such term
            if depth0 is not None:
                allow = p.depth_allowed(m._same(depth0))
            snap = p.state.snapshot()
            ratio = dl / (lam - prev[1])
            twist = self.twist_angles(lam - prev[1])     # the last step's, factored out
            share = p.predict_within_limits(snap, prev[0], ratio, twist)
            p.state.recentre()
            if share < 1.0:
                self.twist_predictor((1.0 - share) * dl)
            if depth0 is None:
                return
            if m._same(p.deepest(p.state.local_config()[0], report=False)) <= allow:
                return
            p.state.restore(snap)
        self.twist_predictor(dl)

    def link_error(self, lam):
        """|link - the link the load imposes| (the link at the first load, plus the end turns
        since), or None where the rod has no link (topology) or is too long to count it."""
        p = self.problem
        if p.mesh.n_nodes > 20000:
            return None
        topo = p.topology()
        if topo is None or not np.isfinite(topo["link"]):
            return None
        if self.link0 is None:
            self.link0, self.lam_link0 = topo["link"], lam
            return 0.0
        want = self.link0 + p.constraints.end_turns * (lam - self.lam_link0)
        return abs(topo["link"] - want)

    def link_kept(self, err):
        """The link is what the load imposes (to 0.01): with contact exactly, without contact up
        to an even number (a phantom rod may pass through itself, each crossing changes the
        link by 2; an odd change is a rotation taken the short way round)."""
        if self.problem.keeps_link:
            return err <= 1e-2
        return abs(err - 2.0 * np.round(err / 2.0)) <= 1e-2

    def run(self, lam0, steps, max_cutbacks, min_step, on_step=None, on_fail=None, dlam0=None,
            prev0=None, stop=1.0, **ignored):
        p = self.problem
        st = p.state
        nominal = 1.0 / steps
        dlam = min(dlam0 or nominal, self.turn_cap)
        largest = min(self.max_increment or 1.0, self.turn_cap)
        lam = lam0
        p.set_load(lam)
        self.link_error(lam)                 # the link at the start
        # a ring of uniform stress-free strains may slide along itself: hold that symmetry
        # (it carries no force; problem.hold_sliding) so that no valley of equal energy is left
        p.hold_sliding()
        cutbacks = 0
        prev = prev0                         # (snapshot, load) of the step before
        p.ease_walls(lam, stop, self._say)   # a restart from a state pressing into a wall
        while lam < stop - 1e-14:
            dl = min(dlam, stop - lam)
            snap = st.snapshot()
            self.predict(prev, lam, dl)
            res = self.minimizer.solve_at(lam + dl)
            if res.converged:
                self.keep_promise(res)
            if res.converged:
                self.check_plane(res)
            err = self.link_error(lam + dl) if res.converged else None
            if res.converged and err is not None and not self.link_kept(err):
                res.converged, res.reason = False, f"link off by {err:.3g}"
            if res.converged:
                prev = (snap, lam)
                lam += dl
                cutbacks = 0
                res.link_error = err
                # the next increment from the work this one took (Crisfield's rule: a step
                # of I iterations is scaled by sqrt(I_target / I), between x1/2 and x2)
                work = max(res.its + res.line_search_cuts / 4.0, 1.0)
                dlam = min(dl * min(max(np.sqrt(TARGET_ITS / work), 0.5), 2.0), largest)
                res.next_increment = dlam
                self.results.append(res)
                if on_step is not None:
                    on_step(res)
                p.ease_walls(lam, stop, self._say)
                continue
            st.restore(snap)
            prev = None
            p.set_load(lam)
            pl = p.planar
            if pl is not None and pl.left is not None and pl.left[0] > lam:
                # the plane was left in the try that failed: 3-D from the last converged load
                # (summary.json's model named the rejected trial's load)
                pl.left = (lam, pl.left[1])
            if on_fail is not None:
                on_fail(res, dl)
            cutbacks += 1
            dlam = 0.5 * dl
            if cutbacks > max_cutbacks or dlam < min_step:
                self.fail_reason = (f"load path stopped at load {lam:.6f}: the minimisation at "
                                    f"{lam + dl:.6f} failed ({res.reason}) after {cutbacks - 1} "
                                    f"cut-backs; the last converged step is in result.h5")
                return self.results, False
        return self.results, True
