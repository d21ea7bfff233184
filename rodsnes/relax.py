"""Relaxation of an unstable equilibrium onto a stable one (branch switching), in parallel.

Newton converges to the nearest stationary point, stable or not.  Past a subcritical
instability the load path can only go on along an unstable equilibrium; NewtonSolver (with
-stability -stability_switch) then perturbs the state along the lowest eigenvector of the
energy Hessian (stability.lowest_eigenpair) and calls :func:`relax`, an implicit gradient flow
(pseudo-transient continuation) on R^3 x SO(3) that decreases the energy to a stable minimum.

Pseudo-time step k (anchor (a_i, A_i) = the state after step k-1):

    minimise   E(x, R) + E_c(x, R),
    E_c = sum_i M_i [ c/2 |x_i - a_i|^2 + c_rot/2 |psi_i|^2 ],   psi_i = log(R_i A_i^T)

with the existing SNES (the term :class:`RelaxationTerm` sits in problem.extra_terms), then
move the anchor to the result.  M_i = int N_i ds is the lumped (row-sum) length weight of node
i, c = 1/dt a stiffness per length^2 and c_rot = c l^2 (l = L / 2 pi).  Every accepted step
satisfies E(x_k) + E_c(x_k) <= E(x_{k-1}) when x_k is the minimiser of the damped energy near
the anchor, so the energy decreases along the relaxation (checked: a step that raises E is
rejected and retried with a larger c).  c adapts by switched evolution relaxation
(c <- c |F_k| / |F_{k-1}|, |F| the undamped residual; bounded), grows after a failed damped
solve and shrinks further when the damped solve converges in a few Newton steps: the flow
becomes full Newton as the minimum is approached.  A pseudo-time step may move no node by more
than max_move (L/10; with contact, a quarter of the free space between non-neighbouring
strands but no less than half the contact radius, so the flow cannot tunnel through the rod).
It stops when the undamped residual is at the solver's tolerance; the caller then removes the
term and finishes with an undamped solve.

Two callers in NewtonSolver: switch_branch (a converged but unstable equilibrium: push along the
lowest eigenvector, relax) and jump_branch (a fold: no equilibrium near the last one at the next
load, however short the step; relax from the last converged state at that load).

Energy is the merit function, so the loads must be conservative: dead forces, gravity, the
twist load, prescribed end rotations and contact are; follower forces and (3-D) end moments are
not, and branch switching is refused with them (NewtonSolver).
"""
import numpy as np
from petsc4py import PETSc

from . import fe, so3
from .partition import NDOF


# Newton iterations of the damped problem per Levenberg-Marquardt step: the second corrects the
# first's linearisation error (a second-order correction).  A linearised step that turns a rod
# by da stretches it by ~da^2/2, which the stiff axial term prices at ~EA da^4/8, so one
# iteration is kept only for tiny da: Mattiasson's cantilever (EA = 1e6 EI/L^2), first of 10
# load steps: 97 LM steps (12 rejected, 109 iterations) with 1, 14 (none rejected, 28) with 2.
LM_ITS = 2
# kept flow steps over which the energy must fall by more than 1000 x its roundoff, else the
# flow is pinned and relax() hands over to Levenberg-Marquardt
PINNED_WINDOW = 25
# with contact a kept step may not press the strands deeper than this x -contact_penetration
PENETRATION_GUARD = 10.0
# Levenberg-Marquardt steps in a row, kept but idle (energy not lower beyond roundoff, |F| not
# 10 % lower), after which c is raised by grow^3 and held there by the floor
IDLE_STEPS = 3


def _MAX():
    from mpi4py import MPI
    return MPI.MAX


def _gamma(phi):
    """1/phi^2 - (1 + cos phi) / (2 phi sin phi) = 1/phi^2 - 1 / (2 phi tan(phi/2)), the
    psi^x psi^x coefficient of J_l^{-1}; finite on [0, pi] (1/pi^2 at pi)."""
    phi = np.asarray(phi, dtype=float)
    small = phi < 1e-3
    ps = np.where(small, 1.0, phi)
    exact = 1.0 / ps**2 - 1.0 / (2.0 * ps * np.tan(0.5 * ps))
    return np.where(small, 1.0 / 12.0 + phi**2 / 720.0, exact)


def left_jacobian_inverse(psi):
    """J_l^{-1}(psi) = I - 1/2 psi^x + gamma(|psi|) psi^x psi^x (batched (n,3) -> (n,3,3)):
    exp(theta^x) exp(psi^x) = exp((psi + J_l^{-1}(psi) theta)^x) + O(theta^2)."""
    K = so3.hat(psi)
    g = _gamma(np.linalg.norm(psi, axis=-1))
    return np.eye(3) - 0.5 * K + g[..., None, None] * (K @ K)


def lumped_weights(mesh, layout):
    """M_i = int N_i ds for the owned nodes (row-sum lumping of the consistent mass matrix of
    a unit line density; positive for the equispaced Lagrange elements of order 1..4)."""
    xi, w = fe.gauss_legendre(mesh.order + 1)
    N, _, _ = fe.lagrange(mesh.order, xi)
    we = (w * mesh.h / 2.0) @ N                       # (p+1,) per element node
    loc = np.zeros((len(layout.local_nodes), NDOF))
    np.add.at(loc, layout.lconn, np.broadcast_to(we[None, :, None], layout.lconn.shape + (NDOF,)))
    V = layout.create_vec()
    layout.add_to_global(loc, V)
    M = V.getArray(readonly=True).reshape(-1, NDOF)[:, 0].copy()
    V.destroy()
    return M


class RelaxationTerm:
    """Pseudo-time regularisation c M (x - a) (force rows), c_rot M log(R A^T) (moment rows).

    Energy (owned nodes of this rank; RodProblem.energy allreduces it):

        E_c = sum_i M_i [ c/2 |x_i - a_i|^2 + c_rot/2 |psi_i|^2 ],  psi_i = log(R_i A_i^T)

    Residual (its exact gradient in the Newton unknowns (r, theta), R <- exp(theta^x) R):

        force row   c M_i (x_i - a_i)
        moment row  c_rot M_i psi_i      (J_l^{-T}(psi) psi = psi: no chart factor)

    Tangent: c M_i I on the position block and c_rot M_i J_l^{-1}(psi_i) on the rotation
    block (= c_rot M_i I at the anchor; the exact derivative of the moment row everywhere, not
    symmetric away from the anchor).  Only the owned rows are touched, so no node is counted
    twice across ranks.  Use: set_anchor(), then append to problem.extra_terms."""

    def __init__(self, mesh, layout, c=1.0, c_rot=None, rot_length=None):
        self.layout = layout
        self.no = layout.n_owned
        self.M = lumped_weights(mesh, layout)
        self.rot_length = mesh.length / (2 * np.pi) if rot_length is None else float(rot_length)
        self.set_stiffness(c, c_rot)
        self.rows = (layout.starts[layout.comm.getRank()] + np.arange(self.no)).astype(PETSc.IntType)
        self.a = None
        self.qa = None

    def set_stiffness(self, c, c_rot=None):
        self.c = float(c)
        self.c_rot = self.c * self.rot_length**2 if c_rot is None else float(c_rot)

    def roundoff(self, size, n_nodes):
        """Roundoff floor of the term's residual: c M_i (x_i - a_i) with x_i, a_i of size
        ``size`` carries an error of eps |x| c M_i per row, so over n_nodes rows

            3 eps c max(M) size sqrt(n_nodes)

        (the moment rows c l^2 M psi are smaller for l < size).  At c = 1.7e9 on the
        plectoneme this is 8e-8, above the elastic floor 3.2e-9: without it every damped solve
        with a large c failed at its iteration limit.  Collective (max over ranks)."""
        from mpi4py import MPI
        m = float(np.max(self.M, initial=0.0))
        m = self.layout.comm.tompi4py().allreduce(m, op=MPI.MAX)
        return 3 * np.finfo(float).eps * self.c * m * size * np.sqrt(n_nodes)

    def set_anchor(self, r_loc, q_loc):
        """Anchor at the local (owned + ghost) configuration, e.g. state.local_config()."""
        self.a = np.array(r_loc[:self.no], dtype=float)
        self.qa = np.array(q_loc[:self.no], dtype=float)

    def _psi(self, q_loc):
        return so3.log_relative(q_loc[:self.no], self.qa)

    def add_residual(self, r_loc, q_loc, Floc):
        no = self.no
        Floc[:no, 0:3] += self.c * self.M[:, None] * (r_loc[:no] - self.a)
        Floc[:no, 3:6] += self.c_rot * self.M[:, None] * self._psi(q_loc)

    def add_jacobian(self, r_loc, q_loc, P):
        B = np.zeros((self.no, NDOF, NDOF))
        B[:, 0:3, 0:3] = self.c * self.M[:, None, None] * np.eye(3)
        B[:, 3:6, 3:6] = self.c_rot * self.M[:, None, None] * left_jacobian_inverse(self._psi(q_loc))
        P.setValuesBlockedRCV(self.rows[:, None], self.rows[:, None], B, addv=PETSc.InsertMode.ADD)

    def energy(self, r_loc, q_loc):
        no = self.no
        dx = r_loc[:no] - self.a
        psi = self._psi(q_loc)
        return 0.5 * float(np.sum(self.M * (self.c * np.einsum("ij,ij->i", dx, dx)
                                             + self.c_rot * np.einsum("ij,ij->i", psi, psi))))


class RelaxResult:
    """Outcome of :func:`relax`: ok, pseudo-time steps (accepted / rejected), Newton
    iterations of the damped solves, energies (first, last), the undamped |F| of the state
    it ends at (fnorm) and the per-step log (c, Newton its, energy, undamped |F|)."""

    def __init__(self):
        self.ok, self.steps, self.rejected, self.newton_its = False, 0, 0, 0
        self.crossings = 0      # steps rejected because the link changed
        # rejected steps by cause: the damped solve failed, the energy rose, a node moved
        # beyond the move limit, the link changed, the strands pressed too deep
        self.causes = {"solve": 0, "uphill": 0, "too far": 0, "crossing": 0, "penetration": 0}
        self.idle_raises = 0    # LM's c raised after IDLE_STEPS idle kept steps
        self.energies, self.log, self.message = [], [], ""
        self.fnorm = np.nan
        self.phase = "flow"     # the phase it ended in: "flow" or "lm" (Levenberg-Marquardt)
        self.c_last = np.nan    # the pseudo-time stiffness it ended at
        self.c_min = np.nan     # the floor of c in that phase


def undamped_residual_norm(problem, skip, F=None):
    """|F| of the problem without the term ``skip`` at the current state (collective)."""
    terms = problem.extra_terms
    saved = list(terms)
    problem.extra_terms = [t for t in terms if t is not skip]
    own = F is None
    F = problem.layout.create_vec() if own else F
    try:
        problem.residual(None, problem.state.X, F)
        return F.norm()
    finally:
        problem.extra_terms = saved
        if own:
            F.destroy()


def undamped_energy(problem, skip):
    terms = problem.extra_terms
    saved = list(terms)
    problem.extra_terms = [t for t in terms if t is not skip]
    try:
        return problem.energy()
    finally:
        problem.extra_terms = saved


def relax(solver, lam, c0, tol, max_steps=200, lm_only=False, **kw):
    """Relax at load factor lam to an equilibrium of lower energy: the implicit gradient flow
    (:func:`relax_phase`) for up to max_steps // 2 pseudo-time steps, then, if the undamped
    residual is not yet at ``tol``, Levenberg-Marquardt steps (single_step) from where the flow
    stopped, for up to max_steps more.  The flow is the robust way off a saddle and into
    contact; it converges only linearly, and a closed uniform ring has a nearly free mode
    (sliding along itself: a symmetry of the continuous problem that only the discretisation
    pins, lowest Hessian eigenvalue 2.8e-6 against 4.7e-5 next for the writhed Michell ring), along
    which the flow creeps and the undamped Newton step overshoots.  Levenberg-Marquardt
    bounds that step and ends quadratically (the Michell ring in contact: |F| 2.9e-5 ->
    1.4e-11 in 56 steps, where the undamped Newton solve diverged).  Returns a RelaxResult
    over both phases.

    lm_only: Levenberg-Marquardt alone for up to max_steps (a resumed relaxation that had
    reached it).  keep(result, final): called with the term removed, the state at the last kept
    step, every ``progress_every`` kept steps of either phase and once more at the end
    (final=True; result.ok tells whether it finished): Run writes an unfinished state to
    DIR/relaxation, from where -stability_switch_restart resumes it (hours of relaxation are
    not lost to a time limit or a stall), and removes it when the relaxation finished."""
    keep = kw.get("keep")
    if lm_only:
        # a resumed relaxation (a restart from DIR/relaxation) that had reached LM goes on with it
        out = relax_phase(solver, lam, c0, tol, max_steps=max_steps, single_step=True, **kw)
    else:
        out = relax_phase(solver, lam, c0, tol, max_steps=max(max_steps // 2, 1), **kw)
    if out.ok or out.steps == 0 or kw.get("single_step") or lm_only:
        if keep is not None:
            keep(out, final=True)
        return out
    # the LM phase starts at the flow's last c, but its floor stays that of the first c: after
    # failed damped solves the flow's c can have grown by 1e12 (the plectoneme's fold at 8.79
    # turns: 4e16), and a floor of 1e-12 x that pinned LM at c = 4e4 for 200 steps, nodes moving
    # < 2e-4 in all, |F| wandering between 0.5 and 3
    lm_kw = {k: v for k, v in kw.items() if k != "single_step"}
    lm_kw.setdefault("c_min", 1e-12 * c0)
    lm = relax_phase(solver, lam, out.c_last, tol, max_steps=max_steps, single_step=True, **lm_kw)
    out.ok, out.message, out.c_last, out.fnorm = lm.ok, lm.message, lm.c_last, lm.fnorm
    out.steps += lm.steps
    out.rejected += lm.rejected
    out.crossings += lm.crossings
    out.idle_raises += lm.idle_raises
    out.causes = {k: v + lm.causes[k] for k, v in out.causes.items()}
    out.newton_its += lm.newton_its
    out.energies += lm.energies[1:]
    out.log += lm.log[1:]
    out.phase, out.c_min = lm.phase, lm.c_min
    if keep is not None:
        keep(out, final=True)
    return out


def relax_phase(solver, lam, c0, tol, max_steps=200, c_min=None, grow=4.0, newton_max_it=12,
                max_move=None, single_step=False, progress_every=25, keep=None):
    """Implicit gradient flow at load factor lam from the current state to an equilibrium of
    lower energy (module docstring).  solver: NewtonSolver (solve_at, problem); c0: initial c;
    tol: undamped |F| to stop at; max_move: largest nodal displacement of one pseudo-time step
    (default L/10, with contact max(eps/2, clearance/4) from the anchor, so the flow cannot
    tunnel through the rod); a longer step is rejected like a failed one.  The term is removed
    again before returning; the state is the last accepted pseudo-time step.  Collective: every decision
    uses rank 0's values of energies, norms and displacements, and SNES reasons.

    single_step: Levenberg-Marquardt instead of the implicit flow: LM_ITS (2) Newton steps of the
    damped problem per pseudo-time step, (K + c M) dx = -F, then the same at the new point (a
    second-order correction, same anchor), kept when the energy falls (and the move limit holds), c / 3 after a kept step, c x grow after a rejected one.  As c falls the steps
    become Newton's, so the end game converges quadratically, while a soft mode (a closed
    uniform ring sliding along itself is a symmetry of the continuous problem; only the
    discretisation pins it) cannot throw the iterate far: its step is bounded by |F| / (c M).

    Every ``progress_every`` accepted steps rank 0 prints the energy, undamped |F| and c
    (NewtonSolver._say: silent with -quiet) and keep(result, final=False) is called, the term
    removed (the result's c_last, c_min, phase, fnorm describe the state: relax's keep)."""
    p = solver.problem
    comm = p.layout.comm.tompi4py()

    def same(*values):     # rank 0's values everywhere: reductions may round differently per rank
        return comm.bcast(values if len(values) > 1 else values[0], root=0)

    out = RelaxResult()
    out.phase = "lm" if single_step else "flow"
    fixed_move = max_move

    def move_limit():
        """max_move, else L/10, and with contact at most max(eps/2, clearance/4) (contact_term
        .clearance): far from contact the flow may take long steps, near it none can tunnel."""
        if fixed_move is not None:
            return fixed_move
        lim = 0.1 * p.mesh.length
        if p.contact is not None:
            r_loc, _ = p.state.local_config()
            lim = min(lim, max(0.5 * p.contact.eps, 0.25 * p.contact.clearance(r_loc)))
        return lim
    term = RelaxationTerm(p.mesh, p.layout, c0)
    c_min = 1e-12 * c0 if c_min is None else c_min
    out.c_min = c_min
    F = p.layout.create_vec()
    p.set_load(lam)
    E, f = same(undamped_energy(p, None), undamped_residual_norm(p, None, F))
    out.energies.append(E)
    out.log.append((np.nan, 0, E, f, ""))
    E_scale = abs(E) + solver.force_scale * p.mesh.length      # force scale x L: EI/L + ...

    def Etol(e):           # roundoff of an energy difference
        return 1e-11 * (abs(e) + E_scale)

    # with contact the link cannot change (without it a strand may pass through another: the
    # twisted rod without contact snaps into a loop through itself)
    topo = p.topology() if p.contact is not None else None
    link0 = None if topo is None else same(topo["link"])
    # with contact no kept step may press the strands deeper than PENETRATION_GUARD x the
    # promised penetration (or than the start, if deeper): contact must hold in large steps too
    pen_limit = None
    if p.contact is not None:
        p.contact.energy(p.state.local_config()[0])
        pen_limit = max(PENETRATION_GUARD * p.contact.penetration,
                        same(p.contact.deepest()) / (2.0 * p.contact.eps))
    p.extra_terms.append(term)
    c = float(c0)
    E_window = E            # energy PINNED_WINDOW kept steps ago (flow only)
    far_move = None         # the move of the last step rejected as too far, in a row
    cooldown = 0            # accepted steps after a rejection during which c may not fall
    c_floor = 0.0           # c may not fall below it: twice the last failed c, decaying 0.9x per step
    stuck = 0               # damped solves in a row that failed before any Newton step
    rejected_row = 0        # rejections in a row: beyond max_rejected_row the flow has stalled
    idle = 0                # kept LM steps in a row that went nowhere (IDLE_STEPS)
    max_rejected_row = 12   # c grown by >= grow^12 (1.7e7) without an acceptable step
    snes = solver.snes
    tols = snes.getTolerances()
    floor0 = solver.floor
    size = same(comm.allreduce(float(np.abs(p.state.local_config()[0]).max(initial=0.0)),
                               op=_MAX())) + p.mesh.length
    snes.setTolerances(max_it=LM_ITS if single_step else newton_max_it)  # more: c too small
    try:
        while out.steps + out.rejected < max_steps:
            if f <= tol:
                out.ok = True
                break
            term.set_stiffness(c)
            term.set_anchor(*p.state.local_config())
            solver.floor = max(floor0, term.roundoff(size, p.mesh.n_nodes))
            max_move = same(move_limit())
            snap = p.state.snapshot()
            res = solver.solve_guarded(lam)
            out.newton_its += res.its
            ok, fac, too_far = False, grow, False
            cause = "solve"         # why a step is rejected: RelaxResult.causes
            done = res.converged
            if single_step:      # LM_ITS Newton steps taken (or converged), finite: a candidate
                R = PETSc.SNES.ConvergedReason
                done = 1 <= res.its <= LM_ITS and res.reason in (R.DIVERGED_MAX_IT, R.CONVERGED_FNORM_ABS,
                                                        R.CONVERGED_FNORM_RELATIVE) \
                    and bool(np.all(np.isfinite(res.history)))
            if done:
                r_new, _ = p.state.local_config()
                move = float(np.linalg.norm(r_new[:term.no] - term.a, axis=1).max(initial=0.0))
                move = same(comm.allreduce(move, op=_MAX()))
                E_new = same(undamped_energy(p, term))
                ok = E_new <= E + Etol(E_new) and move <= max_move
                cause = "uphill" if E_new > E + Etol(E_new) else "too far"
                if ok and link0 is not None and not abs(same(p.topology()["link"]) - link0) < 0.5:
                    # the link changed: a strand went through another (where the exclusion
                    # hides a tight loop's neighbour, or through a penalty that long steps
                    # overcome): not a motion of the rod; a shorter step, and keep above this c
                    ok = False
                    out.crossings += 1
                    cause = "crossing"
                elif ok and pen_limit is not None and \
                        same(p.contact.deepest()) > pen_limit * 2.0 * p.contact.eps:
                    # the strands pressed into each other far beyond the penalty's promise: the
                    # Newton precheck lets each iteration double the deepest penetration, so over
                    # many steps they can sink into each other until the link changes (the
                    # plectoneme's switch at 9.415 turns: 21 crossings, then stalled at c = 4e26)
                    ok = False
                    cause = "penetration"
                elif move > max_move and E_new <= E + Etol(E_new):
                    # too long a step, but downhill: the move scales as 1/c, aim at 0.8 max_move
                    fac = max(1.25 * move / max_move, 1.5)
                    too_far = True
                    if far_move is not None and move > 0.7 * far_move:
                        # it did not: c is below K's stiffness along the step, which is then
                        # Newton's whatever c (the plectoneme's switch at 9.415 turns: c grew
                        # x 1.5 per rejection from 2e-3 to 3e2 until the phase stalled)
                        fac = max(fac, grow)
                    far_move = move
            if not too_far:
                far_move = None
            stuck = stuck + 1 if (not res.converged and res.its == 0) else 0
            rejected_row = 0 if ok else rejected_row + 1
            if not ok:
                # damped solve failed, went uphill (toward a saddle) or too far: smaller
                # pseudo-time step
                p.state.restore(snap)
                p.set_load(lam)
                out.rejected += 1
                out.causes[cause] += 1
                out.log.append((c, res.its, np.nan, np.nan, str(res.reason)))
                if stuck >= 3:      # fails at the anchor itself, whatever c: not a step size issue
                    out.message = (f"the damped solve fails at the state itself (SNES reason "
                                   f"{res.reason}) after {out.steps} pseudo-time steps")
                    break
                # stalled: rejected in a row even back at the phase's first c (a short gradient
                # step), or for ever.  Counting rejections alone declared the plectoneme's
                # 8.80-turn jump stalled after Levenberg-Marquardt had fallen to c = 7e-7 and
                # was descending (E -3e-3 per step): 12 rejections x 4 only brought c back to 3
                if rejected_row >= max_rejected_row and (c >= c0
                                                         or rejected_row >= 3 * max_rejected_row):
                    out.message = (f"stalled after {out.steps} pseudo-time steps: {rejected_row} "
                                   f"damped solves in a row rejected (last SNES reason "
                                   f"{res.reason}, c = {c:.3e}, undamped |F| = {f:.3e}; "
                                   f"rejected: " + ", ".join(f"{k} {v}" for k, v in
                                                             out.causes.items() if v) + ")")
                    break
                if not too_far:
                    # a c that failed fails again a few steps later: keep above it for a while
                    # (without this floor the flow falls back to it every third step)
                    c_floor = max(c_floor, 2.0 * c)
                c *= fac
                cooldown = 0 if too_far else 2
                continue
            f_new = same(undamped_residual_norm(p, term, F))
            out.steps += 1
            out.log.append((c, res.its, E_new, f_new, str(res.reason)))
            out.energies.append(E_new)
            # switched evolution relaxation: dt ~ 1/|F|, bounded; harder solves -> smaller dt.
            # While the energy falls, a growing |F| (the flow leaving a saddle) does not shorten
            # the step: that would stall the escape.
            ratio = min(max(f_new / f, 0.05), 2.0)
            if single_step:
                ratio = 1.0 / 3.0
            elif res.its > 8:
                ratio = max(ratio, 2.0)
            elif res.its <= 5:          # an easy damped solve: a longer pseudo-time step
                ratio = min(ratio, 0.25 if f_new < f else 0.5)
            else:
                ratio = min(ratio, 1.0)
            if cooldown > 0:
                ratio = max(ratio, 1.0)
                cooldown -= 1
            # the move scales as 1/c: a smaller c may not aim beyond 0.8 max_move (a step
            # rejected as too long costs a whole damped solve)
            ratio = max(ratio, min(move / (0.8 * max_move), 1.0))
            c_floor *= 0.9
            c = max(c * ratio, c_min, c_floor)
            if single_step:
                # kept steps that go nowhere: at c's floor the plectoneme's switch at 9.415
                # turns kept 150 LM steps with E equal to 1e-11 and |F| 8.613e-2 unchanged (two
                # Newton iterations that come back where they started: a cycle of the contact's
                # active set); a larger c shortens the step and makes it a contraction
                idle = idle + 1 if (E_new > E - Etol(E_new) and f_new > 0.9 * f) else 0
                if idle >= IDLE_STEPS:
                    c = c_floor = c * grow ** 3
                    idle = 0
                    out.idle_raises += 1
            E, f = E_new, f_new
            if out.steps % progress_every == 0:
                # a long relaxation (hundreds of steps, minutes each on a plectoneme) shows
                # that it is on its way: rank 0 prints, unless -quiet; and keeps its state
                if hasattr(solver, "_say"):
                    solver._say(f"  relaxation ({'Levenberg-Marquardt' if single_step else 'flow'})"
                                f": {out.steps} steps ({out.rejected} rejected), E {E:.9g}, "
                                f"undamped |F| {f:.3e}, c {c:.3e}; rejected: "
                                + ", ".join(f"{k} {v}" for k, v in out.causes.items() if v))
                if keep is not None:
                    out.c_last, out.fnorm = c, f
                    p.extra_terms = [t for t in p.extra_terms if t is not term]
                    try:
                        keep(out, final=False)
                    finally:
                        p.extra_terms.append(term)
            if not single_step and out.steps % PINNED_WINDOW == 0:
                # the flow pinned: its damped solves fail below some c, the floor keeps c above
                # it, and the kept steps no longer move (the plectoneme at 9.415 turns: c 1e11 -
                # 2e13, E equal to 1e-6 over 125 kept steps); Levenberg-Marquardt takes over
                if E_window - E <= 1000 * Etol(E):
                    out.message = (f"pinned after {out.steps} pseudo-time steps: the energy fell "
                                   f"by {E_window - E:.2e} over the last {PINNED_WINDOW} "
                                   f"(c = {c:.3e}, undamped |F| = {f:.3e})")
                    break
                E_window = E
        else:
            out.ok = f <= tol
        if not out.ok and not out.message:
            out.message = (f"no equilibrium after {out.steps} pseudo-time steps "
                           f"({out.rejected} rejected): undamped |F| = {f:.3e} > {tol:.3e}")
    finally:
        p.extra_terms = [t for t in p.extra_terms if t is not term]
        snes.setTolerances(max_it=tols[3])
        solver.floor = floor0
        F.destroy()
    out.c_last, out.fnorm = c, f
    return out
