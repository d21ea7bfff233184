"""Self-contact in the parallel problem, at a constructed penetrating state (no solve needed):
the assembled tangent against finite differences of the assembled residual, one rank against
two (contact pairs across ranks: the SF halo exchange and the reaction sent back), and the KKT
report.  The converged contact scenes are run by tools/contact_study.py (slow: minutes)."""
from mpi4py import MPI
import numpy as np
import pytest
from petsc4py import PETSc

from conftest import (coiled_rollup as coiled, natural_residuals, run_case,
                      tangent_against_finite_differences)
from rodsnes.contact import search
from rodsnes.model.partition import NDOF


@pytest.mark.mpi
def test_assembled_tangent_matches_finite_differences_in_contact():
    run = coiled()
    p = run.problem
    X = p.state.X
    F = X.duplicate()
    p.residual(None, X, F)
    assert run.contact.summary()["active_points"] > 0
    J = p.layout.create_matrix(run.contact.extra_pattern(p.state.local_config()[0]))
    p.jacobian(None, X, J, J)
    fd, Jv, _ = tangent_against_finite_differences(p, J, seed=3)
    assert (fd - Jv).norm() / Jv.norm() < 1e-6


@pytest.mark.mpi
def test_two_ranks_give_the_serial_residual_energy_and_contact_forces():
    par = coiled()
    ser = coiled(comm=PETSc.COMM_SELF, outdir=par.outdir + f"_s{PETSc.COMM_WORLD.getRank()}")
    nat1, nat2 = natural_residuals(par, ser)
    assert np.abs(nat1 - nat2).max() < 1e-9 * np.abs(nat2).max()
    assert par.problem.energy() == pytest.approx(ser.problem.energy(), rel=1e-12)
    c1, c2 = par.contact.summary(), ser.contact.summary()
    assert c1["total_force"] == pytest.approx(c2["total_force"], rel=1e-12)
    assert c1["active_points"] == c2["active_points"] > 0
    if PETSc.COMM_WORLD.getSize() > 1:     # the contact really crosses ranks: clamp end and tip
        owners = par.layout.elem_owner
        assert owners[0] != owners[-1]


@pytest.mark.mpi
def test_the_pattern_pairs_when_one_rank_alone_has_candidates(monkeypatch):
    """ContactTerm.pattern_pairs where only rank 0 has candidate pairs: every rank meets the
    same collectives (a rank without candidates had taken the next allgather, of the pairs,
    for the elements' positions: ValueError on 3 ranks at rollup_contact's step 9), and all
    ranks hold rank 0's pairs that touch."""
    run = coiled()
    term = run.contact
    r = run.problem.state.local_config()[0]
    every = term.pattern_pairs(r)
    search_pairs = type(term).search_pairs
    rank = PETSc.COMM_WORLD.getRank()

    def rank0_only(self, *args, **kw):
        pairs, cen, rad = search_pairs(self, *args, **kw)
        return (pairs if rank == 0 else pairs[:0]), cen, rad
    monkeypatch.setattr(type(term), "search_pairs", rank0_only)
    got = term.pattern_pairs(r)
    mine = PETSc.COMM_WORLD.tompi4py().bcast(got)
    assert np.array_equal(got, mine)                    # the same on every rank
    keys = set(map(tuple, every))
    assert len(got) and all(tuple(p) in keys for p in got)
    if PETSc.COMM_WORLD.getSize() == 1:
        assert np.array_equal(got, every)


def test_kkt_report_and_action_reaction():
    run = coiled()
    p = run.problem
    F = p.F.duplicate()
    r, q = p.state.local_config()
    Floc = np.zeros((len(r), NDOF))
    run.contact.add_residual(p.lam, r, q, Floc)
    c = run.contact.summary()
    assert c["active_points"] > 0 and c["total_force"] > 0
    assert c["min_gap"] < 0 and c["max_penetration"] == pytest.approx(-c["min_gap"] / (2 * run.contact.radius))
    assert c["complementarity"] > 0
    # contact forces are internal: they sum to zero force and zero moment
    assert np.abs(Floc[:, 0:3].sum(axis=0)).max() < 1e-9 * np.abs(Floc).max()
    assert np.abs(np.cross(r, Floc[:, 0:3]).sum(axis=0)).max() < 1e-9 * np.abs(Floc).max() * 10
    del F


@pytest.mark.mpi
def test_contact_blocks_zero_at_the_first_assembly_stay_in_the_matrix():
    """Regression (segfault on 2 ranks at first contact): a contact block absent from the first
    assembly was squeezed out of the pattern; inserting it later cost a malloc, MUMPS reused the
    old symbolic analysis (writing past its triples) and, on PETSc 3.18 MPIBAIJ, the block
    landed in a wrong column.  create_matrix makes every pattern entry present."""
    run = coiled()
    lay, m = run.layout, run.mesh
    last = m.n_nodes - 1
    group = np.array([[0, 1, last - 1, last]])
    J = lay.create_matrix(group)
    g = lay.gconn.astype(PETSc.IntType)
    ones = np.ones((len(g), g.shape[1] * NDOF, g.shape[1] * NDOF))
    for contact_on in (False, True):        # the contact blocks are zero at the first assembly
        J.zeroEntries()
        J.setValuesBlockedRCV(g, g, ones, addv=PETSc.InsertMode.ADD)
        if contact_on and PETSc.COMM_WORLD.getRank() == 0:
            rows = lay.nat2petsc[group].astype(PETSc.IntType)
            J.setValuesBlockedRCV(rows, rows, 10 * np.ones((1, 4 * NDOF, 4 * NDOF)),
                                  addv=PETSc.InsertMode.ADD)
        J.assemble()
    assert J.getInfo(PETSc.Mat.InfoType.GLOBAL_SUM)["mallocs"] == 0
    from rodsnes.solve.stability import gather_csr
    A = gather_csr(J, lay)
    if A is not None:
        A = A.toarray()
        assert np.abs(A - A.T).max() == 0
        assert A[0, NDOF * last] == 10 and A[NDOF * last, 0] == 10
        assert A[0, NDOF * (last - 2)] == 0          # nothing in a wrong column


@pytest.mark.mpi
@pytest.mark.slow
@pytest.mark.parametrize("steps", [20, 40])
def test_first_contact_solve_same_on_two_ranks(steps):
    """The solved rollup_contact (16 elements: the free end lands on the clamped end, contact
    across ranks): the same load steps, Newton iterations and tip on COMM_WORLD as serial.
    Under mpirun only: in a serial session both runs would be serial (tests/test_planar_contact.py
    solves this scene serially against the exact reference).  20 or 40 load steps instead of
    the case's 10 (five cut-backs at the first touch, Newton solves of up to 37 iterations):
    20 cut back three times, 40 not at all since the Newton path's secant keeps to the
    contact's move limits (newton.NewtonSolver._predict)."""
    if PETSc.COMM_WORLD.getSize() == 1:
        pytest.skip("compares 2 ranks with 1: runs under mpirun -n 2 (make test-mpi)")
    kw = dict(rod_nelem=16, load_steps=steps)
    par = run_case("rollup_contact", **kw)
    ser = run_case("rollup_contact", comm=PETSc.COMM_SELF,
                   outdir=par.outdir + f"_s{PETSc.COMM_WORLD.getRank()}", **kw)
    assert par.ok and ser.ok
    # the same load steps (cut-backs included); the Newton counts agree up to the last
    # iterate, which lands on the roundoff floor of the residual (1 and 2 ranks sum in
    # different orders, and 2 ranks solve by static condensation, solve/schur.py: one more
    # iteration may be needed to fall below the tolerance; measured 5 steps of 41)
    assert [h["load"] for h in par.history] == [h["load"] for h in ser.history]
    assert (len(par.history) > steps) == (steps == 20)        # cut-backs where expected
    its_p = np.array([h["newton_iterations"] for h in par.history])
    its_s = np.array([h["newton_iterations"] for h in ser.history])
    assert np.abs(its_p - its_s).max() <= 1
    assert np.abs(its_p - its_s).sum() <= 8
    sp, ss = par.summary(converged=True), ser.summary(converged=True)
    assert np.abs(np.subtract(sp["tip_position"], ss["tip_position"])).max() < 1e-9
    assert sp["contact"]["total_force"] == pytest.approx(ss["contact"]["total_force"], rel=1e-8)
    assert sp["contact"]["total_force"] > 3.0
    assert sp["contact"]["law"] == ss["contact"]["law"] == "projection"    # auto, 32 elements
    assert "closest-point projection (-contact_model auto)" in par.header()
    # the pre-check's scalings are counted, identically on both (rank-independent decisions)
    # where every solve converges; a solve cut back for stagnation (|F| not halved in 15
    # iterations) may take an iteration more or less on 2 ranks (its |F| hovers at the
    # threshold), and with it a scaling (20 steps: 68 and 52 against 70 and 54)
    keys = ("limited_steps", "penetration_limited_steps", "energy_limited_steps")
    cp = np.array([sp["contact"][k] for k in keys])
    cs = np.array([ss["contact"][k] for k in keys])
    assert np.abs(cp - cs).max() <= (0 if steps == 40 else 0.05 * cs.max())
    assert sp["contact"]["limited_steps"] > 0


def _energy_at(p, X):
    """Total energy at the vector X (all ranks), as RodProblem.precheck measures it."""
    r, q = p.state.local_config(X)
    shares, _ = p.trial(r, q)
    return p.layout.comm.tompi4py().allreduce(p.energy_local(r, q, shares))


@pytest.mark.mpi
def test_the_standoff_law_reports_against_the_tube():
    """-contact_standoff s: at the same positions the law is that of the tube of radius
    eps_l = a (1 + s) (deeper by the offset 2 (eps_l - a) = 2 a s, so more energy), while what is
    reported is against the tube of radius a: min_gap, max_penetration and the clamps' mounts
    (none here) are those of the law without a standoff; the raise that keeps the promise
    scales the law's depth to its own promise p_l 2 eps_l (docs/contact.md, The standoff)."""
    from rodsnes.contact.projection import default_penalty
    from rodsnes.io.scene import law_tube
    hard, soft = coiled(), coiled(contact_standoff=0.02)
    rod = soft.scene.rod
    assert soft.contact.mu == default_penalty(min(rod.EI1, rod.EI2), *soft.scene.contact_law)
    assert soft.contact.mu < hard.contact.mu / 3          # the law's promise p_l = 2.94 %
    a = hard.contact.radius
    assert (soft.contact.radius, soft.contact.eps) == (a, pytest.approx(1.02 * a, rel=1e-15))
    assert soft.contact.offset == pytest.approx(0.04 * a, rel=1e-12)
    assert soft.contact.law_penetration == pytest.approx(0.03 / 1.02, rel=1e-15)
    assert law_tube(a, 0.01, 0.0) == (a, 0.01)
    reports = []
    for run in (hard, soft):
        r, q = run.problem.state.local_config()
        assert np.allclose(r, hard.problem.state.local_config()[0])
        pen, mu1 = run.contact.promised_penalty(r)
        c = run.contact.summary()
        reports.append((c, pen, mu1, run.contact.deepest(), run.contact.energy_local(0.0, r, q)))
    (ch, penh, muh, dh, eh), (cs, pens, mus, ds, es) = reports
    # the per-point gap of result.h5 (qp_fields): against the tube too
    # (at points near contact: further out each law's report takes the nearest of its own
    # candidates, which differ with its reach)
    gh, gs = (run.contact.qp_fields()["fields"]["gap"] for run in (hard, soft))
    both = (gh > -0.5 * a) & (gs > -0.5 * a)          # this rank's points (over all: below)
    mpi = PETSc.COMM_WORLD.tompi4py()
    assert mpi.allreduce(int(both.sum())) >= 4 and mpi.allreduce(bool((gh[both] > 0).any()),
                                                                op=MPI.LOR)
    assert np.abs(gs[both] - gh[both]).max(initial=0.0) < 1e-6 * a
    # the same to the closest-point law's zone points (their zones end where the law's gap
    # vanishes, a standoff further out: 5e-7 apart here)
    assert cs["min_gap"] == pytest.approx(ch["min_gap"], rel=1e-5)
    assert cs["max_penetration"] == pytest.approx(ch["max_penetration"], rel=1e-5)
    assert pens == pytest.approx(penh, rel=1e-5) and pens > 0.01
    assert ds == pytest.approx(dh + soft.contact.offset, rel=1e-5)       # the law's depth
    assert mpi.allreduce(es) > 0 and mpi.allreduce(eh) > 0          # the ranks' shares
    c = soft.contact
    assert mus == pytest.approx(1.25 * c.mu * ds / (c.law_penetration * 2 * c.eps), rel=1e-12)
    assert (cs["standoff"], cs["law_radius"], cs["radius"]) == (0.02, c.eps, a)


def test_newton_step_may_not_raise_the_energy():
    """Line-search pre-check, limit 3: with conservative loads (here none: load 0) a step that
    raises the total energy is shortened until it does not: the Newton step from the coiled
    state, tripled, overshoots and is cut back to a descent (without the residual: halved; with
    it: Armijo and the quadratic model).  The check is off while a step moves a
    constrained dof, and for loads without a potential (tests/test_relax.py: follower force)."""
    run = coiled()
    p, c = run.problem, run.contact
    assert p.energy_descent                    # no end moment here (coiled_rollup): nothing without a potential
    X = p.state.X
    p.update(None, 0)
    p.residual(None, X, p.F)
    p.jacobian(None, X, p.J, p.J)
    ksp = PETSc.KSP().create(comm=p.layout.comm)
    ksp.setOperators(p.J)
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")
    Y = X.duplicate()
    ksp.solve(p.F, Y)                          # Newton: X_new = X - Y
    Y.scale(3.0)
    E0 = _energy_at(p, X)
    Xt = X.copy()
    Xt.axpy(-1.0, Y)
    assert _energy_at(p, Xt) > E0 + 1e-6 * abs(E0)   # the tripled step overshoots
    p.step_limit = 100.0                       # limit 1 off
    p.residual(None, X, p.F)                   # ContactTerm.last at X, as inside SNES
    n0 = Y.norm()
    assert p.precheck(X, Y)
    assert p.stats.get("energy_limited_steps", 0) + p.stats.get("penetration_limited_steps", 0) >= 1
    assert Y.norm() < n0
    X.copy(Xt)
    Xt.axpy(-1.0, Y)
    assert _energy_at(p, Xt) <= E0 + 1e-11 * abs(E0)
    # with the residual F at X (as SNES passes it), the energy has a slope along the step and
    # the step must decrease it by a tenth of that (Armijo); the shortened step is the minimiser
    # of the quadratic through E0, the slope and E(tripled step): near the Newton step itself
    ksp.solve(p.F, Y)
    Y.scale(3.0)
    slope = -p.F.dot(Y)
    assert slope < 0
    p.residual(None, X, p.F)
    assert p.precheck(X, Y, p.F)
    s = Y.norm() / n0
    # 1/3 for an exactly quadratic energy; with the contact the quadratic model's minimiser, kept
    # within [0.1, 0.5] of the trial (measured 0.1 at the default penalty, 0.242 at 5x it), and
    # not a halving
    assert 0.1 - 1e-12 <= s < 0.45 and abs(np.log2(s) - np.round(np.log2(s))) > 0.01, s
    X.copy(Xt)
    Xt.axpy(-1.0, Y)
    assert _energy_at(p, Xt) <= E0 + 0.1 * s * slope
    # the check is off while the step moves a constrained dof (the first iteration of a step)
    p.residual(None, X, p.F)
    Z = X.duplicate()
    Z.set(0.0)
    with Z as a:
        if len(p.constraints.rows_local):
            a[p.constraints.rows_local[0]] = 1e-3
    assert not p.energy_descent_applies(Z) and p.energy_descent_applies(Y)
    ksp.destroy()


@pytest.mark.slow
def test_newton_step_may_not_deepen_the_penetration_beyond_the_limit():
    """Line-search pre-check (RodProblem.precheck): a step that would push the free end into the
    clamped end far beyond the current penetration is halved until the deepest penetration at
    the trial point is within max(2 d_max, 2 % of the diameter); a step that does not deepen
    it is left alone."""
    run = coiled()
    p, c = run.problem, run.contact
    X = p.state.X
    p.residual(None, X, p.F)
    d_now = c.deepest()
    assert d_now > 0
    r, _ = p.state.local_config()
    allow = max(2 * d_now, 0.02 * 2 * c.eps)
    # push every free-end node 3 eps toward the clamped start (X_new = X - Y)
    Y = X.duplicate()
    Y.set(0.0)
    lay, m = p.layout, run.mesh
    with Y as a:
        a = a.reshape(-1, NDOF)
        tip = m.n_nodes - 1
        for node in range(tip - 3, tip + 1):
            li = lay.nat2local[node]
            if 0 <= li < lay.n_owned:
                a[li, 0:3] = 3 * c.eps * (r[li] - 0.0) / np.linalg.norm(r[li])
    n0 = Y.norm()
    p.step_limit = 10.0 * c.eps            # the move limit off: the penetration limit alone
    before = p.stats.get("penetration_limited_steps", 0)
    assert p.precheck(X, Y)
    assert p.stats.get("penetration_limited_steps", 0) == before + 1
    assert Y.norm() < n0
    dr = lay.to_local(Y)[:, 0:3]
    assert c.deepest(r - dr) <= allow
    # the opposite step (pulling the end out of contact) is not limited by penetration
    Z = X.duplicate()
    Z.set(0.0)
    p.residual(None, X, p.F)
    assert not p.precheck(X, Z)


# ------------------------------------------------------------------------------------------
# each caller pays for what it needs (ContactTerm.evaluate): residual alone, tangent and report
# made later at the same positions, the candidate search kept within its skin
# ------------------------------------------------------------------------------------------
LAW = {"projection": {},    # the coiled rod's overlap is deeper than the potential's wall
       "potential": dict(contact_model="potential", contact_quadrature=24, contact_wall=0)}
@pytest.mark.mpi
@pytest.mark.parametrize("model", ["projection", "potential"])
def test_residual_alone_is_the_residual_of_the_full_evaluation(model):
    """The residual-only evaluation (line search, residual) gives the energy, residual rows and
    assembled residual of the evaluation with tangent and report, bit for bit; its tangent and
    report, made later from what it kept, are those of the full evaluation, bit for bit; and
    the Jacobian after the residual at the same positions makes no new evaluation."""
    run = coiled(**LAW[model])
    c, p = run.contact, run.problem
    r, q = p.state.local_config()

    def fresh(**kw):
        c.kept_evaluation = None
        return c.evaluate(r, **kw)

    def assembled():
        Floc = np.zeros((len(r), NDOF))
        c.add_residual(p.lam, r, q, Floc)
        return Floc

    alone = fresh()
    assert alone["mat"] is None and alone["reported"] == (model == "projection")
    F_alone = assembled()
    full = fresh(tangent=True, report=True)
    F_full = assembled()
    assert full["energy"] == alone["energy"] and np.array_equal(F_full, F_alone)
    assert np.array_equal(full["active"], alone["active"])
    assert PETSc.COMM_WORLD.tompi4py().allreduce(len(full["active"])) > 0   # on some rank
    assert np.array_equal(full["vec"], alone["vec"])
    later = fresh()
    hits = c.cache_hits
    c.evaluate(r, tangent=True)
    c.evaluate(r, report=True)
    assert c.cache_hits == hits + 2
    for key in ("mat", "switch", "switch_mat", "gap", "force", "sbar", "d_active"):
        assert np.array_equal(later[key], full[key]), key
    for key in ("total_force", "complementarity", "zones", "depth"):
        assert later[key] == full[key], key
    if model == "potential":
        # its guard depth (the point couples) sees the report's penetration here
        deep = PETSc.COMM_WORLD.tompi4py().allreduce(later["depth"], op=MPI.MAX)   # any rank's
        assert deep > 0 and c.deepest(report=False) == pytest.approx(c.deepest(), rel=0.1)


def _fresh_search_pairs(c, r):
    """The candidates within reach of a fresh search at r (what the evaluation must use)."""
    return c.search_pairs(*search.element_bounds(r[c.lconn]), c.reach)


@pytest.mark.mpi
@pytest.mark.parametrize("model", ["projection", "potential"])
def test_candidate_search_is_reused_within_its_skin_and_repeated_beyond(model):
    """Verlet list (contact_term, 2.): a state whose bounding spheres moved by less than half
    the skin reuses the last search, and the pairs it evaluates are those of a fresh search
    within reach, also where the move brought new pairs within reach; a move beyond half the
    skin searches again.  The same decisions and the same residual on every rank."""
    run = coiled(**LAW[model])
    c, p = run.contact, run.problem
    r0, q0 = p.state.local_config()
    c.evaluate(r0)
    n0, pairs0 = c.searches, c.kept_evaluation["pairs"]
    assert np.array_equal(pairs0, _fresh_search_pairs(c, r0))
    # slide the free end along x by 0.4 skin (a ramp over s/L in [0.6, 0.8]): element 10 comes
    # within reach of element 0 (sphere distance 0.282 at reach 0.25, skin 0.1)
    s = run.mesh.s_nodes[run.layout.local_nodes] / run.mesh.length
    r1 = r0 + 0.4 * c.skin * np.clip((s - 0.6) / 0.2, 0.0, 1.0)[:, None] * np.array([1.0, 0, 0])
    c.evaluate(r1)
    assert c.searches == n0                          # reused
    pairs1 = c.kept_evaluation["pairs"]
    assert np.array_equal(pairs1, _fresh_search_pairs(c, r1))
    grown = run.layout.comm.tompi4py().allreduce(len(pairs1) - len(pairs0))
    assert grown > 0                                 # new pairs within reach, none missed
    # the residual is the one of an evaluation with a search of its own
    Floc = np.zeros((len(r1), NDOF))
    c.add_residual(p.lam, r1, q0, Floc)
    c.verlet_list, c.kept_evaluation = None, None
    Fnew = np.zeros((len(r1), NDOF))
    c.add_residual(p.lam, r1, q0, Fnew)
    assert c.searches == n0 + 1 and np.array_equal(Floc, Fnew)
    # a rigid move by 0.6 skin: beyond half the skin, a new search
    r2 = r1 + np.array([0.6 * c.skin, 0.0, 0.0])
    c.evaluate(r2)
    assert c.searches == n0 + 2
    assert np.array_equal(c.kept_evaluation["pairs"], _fresh_search_pairs(c, r2))
    r3 = r2 + np.array([0.0, 0.4 * c.skin, 0.0])      # then within half the skin again
    c.evaluate(r3)
    assert c.searches == n0 + 2 and c.search_reuses >= 2


@pytest.mark.mpi
@pytest.mark.parametrize("model", ["projection", "potential"])
def test_the_pattern_check_of_a_newton_step_reads_the_evaluation(model):
    """RodProblem.ensure_pattern asks ContactTerm.pattern_covers whether the pairs that the
    iterate's tangent couples (each rank its own) are preallocated: true for the pattern of
    the pairs that can touch there (which holds every coupled pair, on every rank), false
    for a pattern that misses one of them; and that pattern is tighter than the search's
    candidates (the Verlet list within reach + skin)."""
    run = coiled(**LAW[model])
    c, p = run.contact, run.problem
    r, _ = p.state.local_config()
    assert not c.pattern_covers(r, p.pattern_of(c))     # made for the straight rod
    p.refresh_pattern()                                   # as at the start of a load step
    need = np.concatenate(c.comm.allgather(c.coupled_pairs(r)))
    have = p.pattern_of(c)
    n = run.mesh.nelem
    assert len(need) and np.isin(need[:, 0] * n + need[:, 1], have[:, 0] * n + have[:, 1]).all()
    assert c.pattern_covers(r, have)
    wide = c.comm.allreduce(len(c.search_pairs(*search.element_bounds(r[c.lconn]),
                                                c.reach + c.skin)))
    assert len(have) < wide
    contact_pairs = need[need[:, 0] != need[:, 1]]
    # a pattern without one pair that the evaluation couples (the same on every rank)
    drop = contact_pairs[np.argmax(np.abs(contact_pairs[:, 0] - contact_pairs[:, 1]))]
    less = have[~((have[:, 0] == drop[0]) & (have[:, 1] == drop[1]))]
    assert len(less) == len(have) - 1
    assert not c.pattern_covers(r, less)
    p.ensure_pattern()                                     # and a step there gets a new one
    assert c.pattern_covers(r, p.pattern_of(c))


@pytest.mark.mpi
@pytest.mark.parametrize("model", ["projection", "potential"])
def test_a_new_pattern_is_the_iterates_own(model):
    """When an iterate couples a pair outside the Jacobian's pattern, the new pattern is the
    iterate's (ContactTerm.covering_pattern: the pairs that can touch there and those its
    tangent couples): a pair of the old pattern whose elements are far apart is not kept (a
    ply sliding over a long load step had grown a kept pattern to 2.3 x its nonzeros)."""
    run = coiled(**LAW[model])
    c, p = run.contact, run.problem
    r, _ = p.state.local_config()
    p.refresh_pattern()
    have = p.pattern_of(c)
    n = run.mesh.nelem
    key = have[:, 0] * n + have[:, 1]
    a, b = np.triu_indices(n, 2)
    free = ~np.isin(a * n + b, key)
    assert free.any()
    far = np.array([[a[free][0], b[free][0]]])         # a pair that cannot touch here
    need = np.concatenate(c.comm.allgather(c.coupled_pairs(r)))
    drop = need[np.argmax(np.abs(need[:, 0] - need[:, 1]))]
    stale = np.concatenate([have[key != drop[0] * n + drop[1]], far])
    p._new_matrix([stale if t is c else pat for t, pat in zip(p.terms, p.patterns)])
    assert not c.pattern_covers(r, p.pattern_of(c))
    p.ensure_pattern()
    now = p.pattern_of(c)
    assert c.pattern_covers(r, now) and np.array_equal(now, c.covering_pattern(r))
    assert not ((now[:, 0] == far[0, 0]) & (now[:, 1] == far[0, 1])).any()
    assert np.array_equal(now, have)          # the pattern made at the start of a load step


@pytest.mark.parametrize("model", ["projection", "potential"])
def test_a_penalty_change_drops_the_kept_evaluation(model):
    """mu is part of the kept evaluation's validity: set_penalty drops it, and a kernel whose
    mu changed is evaluated anew at the same positions (energy and tangent scale with mu)."""
    run = coiled(**LAW[model])
    c, p = run.contact, run.problem
    r, _ = p.state.local_config()
    out1 = c.evaluate(r, tangent=True)
    e1, k1 = out1["energy"], out1["mat"].copy()
    assert e1 > 0 and len(k1)
    c.set_penalty(2.0 * c.mu)
    hits = c.cache_hits
    out2 = c.evaluate(r, tangent=True)
    assert c.cache_hits == hits and out2["energy"] == pytest.approx(2.0 * e1, rel=1e-12)
    assert np.allclose(out2["mat"], 2.0 * k1, rtol=1e-12, atol=0)
    c.kernel.mu = 0.5 * c.kernel.mu                  # behind the term's back
    assert c.evaluate(r)["energy"] == pytest.approx(e1, rel=1e-12) and c.cache_hits == hits
