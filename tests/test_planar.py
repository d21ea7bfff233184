"""Planar scenes on their in-plane unknowns (rodsnes/solve/planar.py, -rod_planar): detection,
the in-plane blocks against the full matrices, planar = 3-D on every planar case, refusals,
the guard, and lateral-torsional buckling (a planar solution that is unstable out of plane)."""
import numpy as np
import pytest
from petsc4py import PETSc

from conftest import build_run, gathered_positions, run_case
from rodsnes.errors import SceneError
from rodsnes.model.partition import NDOF

# lateral-torsional buckling of a cantilever under a tip force at the centroid in its stiff
# plane (cases/ltb.opts: EI1 = GJ = 1 out of plane, EI2 = 1000 in plane, L = 1)
P_CR = 4.0126


def _ltb_force(factor):
    return "0,%r,0" % (-factor * P_CR)


def _same_answer(a, b, its_margin=0):
    """Run a (planar) and b (3-D) end on the same state: positions to 1e-8 L, energy to
    1e-10 of its scale, load steps equal, Newton iterations no more than b's (+ its_margin)."""
    sa, sb = a.summary(a.ok), b.summary(b.ok)
    assert a.ok and b.ok
    L = a.mesh.length
    assert np.max(np.abs(gathered_positions(a) - gathered_positions(b))) <= 1e-8 * L
    assert abs(sa["energy"] - sb["energy"]) <= 1e-10 * (abs(sb["energy"]) + a.force_scale * L)
    assert sa["load_steps"] == sb["load_steps"]
    assert sa["newton_iterations"] <= sb["newton_iterations"] + its_margin
    return sa, sb


PLANAR = ["mattiasson", "euler", "rollup", "rollup_two_turns"]


@pytest.mark.parametrize("case", PLANAR)
def test_planar_equals_3d(case):
    """On every planar case auto detects the x-y plane and ends where -rod_planar off does.
    (euler's imperfection lies along d1 = e_y: in the plane.)"""
    a = run_case(case, rod_error_estimate="off")
    b = run_case(case, rod_error_estimate="off", rod_planar="off")
    sa, sb = _same_answer(a, b)
    assert sa["model"] == "planar (x, y, theta per node)"
    assert sb["model"] == "3-D"
    assert a.problem.planar.stats["planar_solves"] > 0
    assert gathered_positions(a)[:, 2].max() == 0.0 == gathered_positions(a)[:, 2].min()


@pytest.mark.slow
def test_planar_contact_equals_3d():
    """rollup_contact: contact keeps the reduction.  The iterates agree to round-off, which at
    the convergence test (|F| ~ rtol x force scale) may flip one iteration of a step either
    way (here 64 against 63 of 17 steps): a margin of 3 iterations."""
    a = run_case("rollup_contact", rod_error_estimate="off")
    b = run_case("rollup_contact", rod_error_estimate="off", rod_planar="off")
    sa, _ = _same_answer(a, b, its_margin=3)
    assert sa["model"] == "planar (x, y, theta per node)"


def test_force_out_of_the_x_y_plane_gives_the_x_z_plane():
    """A tip force along -z on the straight rod: the x-z plane (d1 = e_y normal to it), the
    in-plane unknowns x, z and theta_y; the same answer as in 3-D."""
    a = run_case("mattiasson", load_end_force="0,0,-10", rod_error_estimate="off")
    b = run_case("mattiasson", load_end_force="0,0,-10", rod_error_estimate="off",
                 rod_planar="off")
    sa, _ = _same_answer(a, b)
    assert sa["model"] == "planar (x, z, theta per node)"
    assert list(a.plane.inplane) == [0, 2, 4]


@pytest.mark.parametrize("case, part", [("helix", "-rod_shape helix"),
                                        ("michell", "-load_twist_turns"),
                                        ("plectoneme", "-bc_end_turns"),
                                        ("mattiasson", "-load_end_force")])
def test_non_planar_scenes_are_3d_and_on_is_refused_by_name(case, part):
    """auto says 3-D (and why); -rod_planar on is refused naming the option that leaves the
    plane (the 4th: a force with components along y and z)."""
    extra = {"load_end_force": "0,-1,1"} if case == "mattiasson" else {}
    run = build_run(case, **extra)
    assert run.plane is None and run.model() == "3-D" and part in run.planar_why
    with pytest.raises(SceneError) as err:
        build_run(case, rod_planar="on", **extra)
    assert "-rod_planar" in err.value.options and part in str(err.value)
    from rodsnes.io import scene as scn
    from conftest import set_options
    opts = set_options(case, rod_planar="on", **extra)
    with pytest.raises(SceneError, match="-rod_planar on: the scene is not planar") as err:
        scn.check_solvable(scn.read_scene(["rodsnes"], opts), memory=None)
    assert "-rod_planar" in err.value.options


def test_michell_imperfection_leaves_the_plane():
    """The ring's imperfection is out of plane (along d2 = e_z): without the twist load it is
    still 3-D, for the imperfection."""
    run = build_run("michell", load_twist_turns=0)
    assert run.plane is None and "-rod_imperfection" in run.planar_why


@pytest.mark.mpi
def test_blocks_are_the_full_matrices_blocks():
    """At a converged planar Mattiasson state: the assembled in-plane tangent J_ii and the
    out-of-plane Hessian H_oo are the (i, i) and (o, o) blocks of the full matrices (with the
    Dirichlet rows), and the full tangent has no (o, i) coupling (block diagonal)."""
    run = run_case("mattiasson", load_stop=0.6, load_steps=2, rod_error_estimate="off")
    p, pl = run.problem, run.problem.planar
    assert pl.active
    rng = np.random.default_rng(3 + PETSc.COMM_WORLD.getRank())
    v = p.F.duplicate()
    with v as a:
        a[:] = rng.standard_normal(a.shape)
    sel, out = pl.plane.inplane, pl.plane.outplane
    for symmetric, block, comps in ((False, None, sel), (True, pl.out_inertia, out)):
        p.jacobian(None, p.state.X, p.J, p.J, symmetric=symmetric)
        if block is None:
            pl.assemble_tangent()
            A = pl.J
        else:
            A = block.assemble()
            full = p.layout.create_matrix(p.node_groups(p.patterns_at()), symmetric=True)
            p.jacobian(None, p.state.X, full, full, symmetric=True)
        w = v.copy()
        with w as a:                                # v on the block's components only
            a.reshape(-1, NDOF)[:, [c for c in range(NDOF) if c not in comps]] = 0.0
        Jw = v.duplicate()
        (p.J if block is None else full).mult(w, Jw)
        wb = pl.restrict(w)                          # a vector of the block's layout
        wb.setArray(np.ascontiguousarray(w.getArray(readonly=True).reshape(-1, NDOF)[:, comps]))
        Aw = wb.duplicate()
        A.mult(wb, Aw)
        Jwb = Jw.getArray(readonly=True).reshape(-1, NDOF)
        err = np.abs(Aw.getArray(readonly=True).reshape(-1, 3) - Jwb[:, comps]).max()
        scale = np.abs(Jwb).max()
        from mpi4py import MPI
        comm = PETSc.COMM_WORLD.tompi4py()
        assert comm.allreduce(err, op=MPI.MAX) <= 1e-12 * comm.allreduce(scale, op=MPI.MAX)
        other = [c for c in range(NDOF) if c not in comps]
        cross = comm.allreduce(np.abs(Jwb[:, other]).max(), op=MPI.MAX)
        assert cross <= 1e-10 * comm.allreduce(scale, op=MPI.MAX)


@pytest.mark.mpi
@pytest.mark.parametrize("strided", [True, False])
def test_restrict_expand_and_share_are_the_components(monkeypatch, strided):
    """The in-plane restriction and expansion and the out-of-plane share of a vector (PETSc's
    strided functions, or numpy's where they cannot be reached) against its components."""
    from rodsnes.solve import planar
    if not strided:
        monkeypatch.setattr(planar.petsc_lib, "function", lambda *a: None)
    run = build_run("rollup", rod_error_estimate="off")
    pl = run.problem.planar
    comm = PETSc.COMM_WORLD.tompi4py()
    v = run.problem.F.duplicate()
    rng = np.random.default_rng(5 + comm.rank)
    with v as a:
        a[:] = rng.standard_normal(a.shape)
    a = v.getArray(readonly=True).reshape(-1, NDOF).copy()
    vi = pl.restrict(v)
    assert np.array_equal(vi.getArray(readonly=True).reshape(-1, 3), a[:, pl.plane.inplane])
    w = v.duplicate()
    w.set(7.0)
    pl.expand(vi, w)
    b = w.getArray(readonly=True).reshape(-1, NDOF)
    assert np.array_equal(b[:, pl.plane.inplane], a[:, pl.plane.inplane])
    assert not b[:, pl.plane.outplane].any()
    # a vector of block size 1 (as a shell's may be): the numpy way, the same values
    flat = PETSc.Vec().createMPI((v.getLocalSize(), v.getSize()), comm=v.getComm())
    v.copy(flat)
    assert flat.getBlockSize() == 1
    assert np.array_equal(pl.restrict(flat).getArray(readonly=True), vi.getArray(readonly=True))
    pl.expand(vi, flat)
    assert np.array_equal(flat.getArray(readonly=True), w.getArray(readonly=True))
    go, gn = pl.out_of_plane_share(v)
    from mpi4py import MPI
    o2 = comm.allreduce(float((a[:, pl.plane.outplane] ** 2).sum()), op=MPI.SUM)
    n2 = comm.allreduce(float((a ** 2).sum()), op=MPI.SUM)
    assert go == pytest.approx(np.sqrt(o2), rel=1e-13) and gn == pytest.approx(np.sqrt(n2), rel=1e-13)


@pytest.mark.mpi
@pytest.mark.parametrize("case", ["mattiasson", "rollup"])
def test_planar_equals_3d_in_parallel(case):
    """The minimiser's and the Newton path's planar solves on any number of ranks (run under
    mpirun -n 2 too)."""
    a = run_case(case, rod_error_estimate="off")
    b = run_case(case, rod_error_estimate="off", rod_planar="off")
    sa, _ = _same_answer(a, b)
    assert sa["model"].startswith("planar")


@pytest.mark.parametrize("case", ["mattiasson", "rollup"])
def test_guard_leaves_the_plane_for_a_state_out_of_it(case):
    """A planar scene started from a state pushed out of its plane (as a 3-D restart state
    would be): the guard sees the out-of-plane residual, the run says so and goes on in 3-D
    (minimiser and Newton path), to the answer of the 3-D run from the same state."""
    runs = []
    for mode in ("auto", "off"):
        run = build_run(case, rod_planar=mode, rod_error_estimate="off")
        with run.problem.state.X as a:
            a = a.reshape(-1, NDOF)
            s = run.mesh.s_nodes[run.layout.owned_nodes]
            a[:, 2] += 1e-4 * s ** 2
        run.problem.constraints.apply(0.0, run.problem.state)
        run.ok = run.execute()
        runs.append(run)
    a, b = runs
    s = a.summary(a.ok)
    assert a.ok and "3-D from load" in s["model"] and "left the plane" in s["model"]
    assert np.max(np.abs(gathered_positions(a) - gathered_positions(b))) <= 1e-8 * a.mesh.length


def test_ltb_below_critical_stays_planar_and_stable():
    """0.9 P_cr: every step planar, no out-of-plane negative eigenvalue, stable."""
    run = run_case("ltb", load_end_force=_ltb_force(0.9), rod_error_estimate="off")
    s = run.summary(run.ok)
    assert run.ok and s["model"] == "planar (x, y, theta per node)" and s["stable"] is True
    assert all(h["out_of_plane_negative_eigenvalues"] == 0 for h in s["steps"])
    assert np.all(gathered_positions(run)[:, 2] == 0.0)


def test_ltb_above_critical_goes_on_in_3d_to_a_stable_buckled_state():
    """cases/ltb.opts, 1.1 P_cr: the planar solution of the last step has one negative
    out-of-plane eigenvalue; the run says so, goes on in 3-D and ends on a stable state bent
    out of plane and twisted."""
    run = run_case("ltb")
    s = run.summary(run.ok)
    assert run.ok and s["stable"] is True and s["negative_eigenvalues"] == 0
    assert "3-D from load 1.000000 (unstable out of plane)" in s["model"]
    assert s["steps"][-1]["out_of_plane_negative_eigenvalues"] == 1
    assert all(h["out_of_plane_negative_eigenvalues"] == 0 for h in s["steps"][:-1])
    tip = np.array(s["tip_position"])
    assert abs(tip[2]) > 0.1                       # sideways by > 10 % of L
    assert not run.problem.planar.in_plane()
    d = run.layout.allgather_nodes(run.last_fields["directors"])[-1]
    assert abs(d[2, 0]) > 0.1                      # d1 (e_y at rest) turned out of the x-y plane


def test_a_hidden_out_of_plane_saddle_is_not_called_stable():
    """ltb with EA = 1e12 EI/L^2: the planar minimum at 1.1 P_cr is a saddle out of the plane
    (the out-of-plane block's count, 1); in 3-D the count's neutral band (the Hessian's
    round-off, 16.8 EI/L^4, warned) hides it and the minimisation stops at once on the planar
    state, which the run called stable (exit 0; the buckled answer is 0.28 L away).  The
    out-of-plane count stands: an unstable end, said, exit 3."""
    run = run_case("ltb", rod_EA=1e12, rod_error_estimate="off")
    s = run.summary(run.ok)
    assert not run.ok and s["stable"] is False and s["negative_eigenvalues"] == 1, s
    assert s["steps"][-1]["out_of_plane_negative_eigenvalues"] == 1
    assert abs(s["tip_position"][2]) < 1e-9            # the planar state, not buckled
    assert run.problem.planar.in_plane() and not run.problem.planar.active
    # an error estimate whose order p+1 solution stops on such a saddle is no estimate (it
    # said 'converged', and that the p+1 solution buckled, while it stayed planar)
    run = run_case("ltb", rod_EA=1e12, rod_order=1, rod_nelem=4, load_end_force="0,-4.05,0")
    est = run.last_estimate
    assert not est["converged"] and not est["left_plane"], est


def _lowest_out_of_plane(run, factor):
    """The lowest eigenvalue of H_oo at the planar equilibrium under factor x P_cr (the
    minimiser at that load from the unloaded rod, no out-of-plane check)."""
    import scipy.linalg as sl
    from rodsnes.model.partition import NDOF  # noqa: F401
    m = run.solver.minimizer
    run.problem.set_load(0.0)
    assert m.solve_at(factor).converged and run.problem.planar.active
    H = run.problem.planar.out_inertia.assemble()
    B = H.convert(PETSc.Mat.Type.AIJ, PETSc.Mat())        # a copy: convert(type) is in place
    A = B.convert(PETSc.Mat.Type.DENSE, PETSc.Mat()).getDenseArray()
    A = np.triu(A) + np.triu(A, 1).T
    return float(sl.eigvalsh(A, subset_by_index=[0, 0])[0])


def test_ltb_critical_load_within_one_percent():
    """The load at which H_oo's lowest eigenvalue crosses zero (linear interpolation between
    0.99 and 1.01 P_cr) is P_cr = 4.0126 sqrt(EI1 GJ) / L^2 within 1 %, and the inertia count
    says 0 below and 1 above."""
    run = build_run("ltb", load_end_force=_ltb_force(1.0), rod_error_estimate="off")
    lo, hi = 0.99, 1.01
    mu_lo = _lowest_out_of_plane(run, lo)
    n_lo = run.problem.planar.out_of_plane_count()
    mu_hi = _lowest_out_of_plane(run, hi)
    n_hi = run.problem.planar.out_of_plane_count()
    assert mu_lo > 0 > mu_hi and (n_lo, n_hi) == (0, 1)
    crossing = lo + (hi - lo) * mu_lo / (mu_lo - mu_hi)
    assert abs(crossing - 1.0) < 0.01


def test_the_out_of_plane_count_is_of_its_metric_eigenvalues():
    """The out-of-plane block's count (planar.BlockInertia: the stability metric restricted to
    the block's components, Dirichlet rows 1) is Sylvester's on H_oo + tau M_oo: the number of
    eigenvalues of H_oo v = lambda M_oo v below -tau (dense LAPACK), below and above the
    lateral-torsional buckling load."""
    import scipy.linalg as sl
    from rodsnes.solve import stability
    if PETSc.COMM_WORLD.getSize() > 1:
        pytest.skip("one rank (the block's rows in the layout's order)")
    run = build_run("ltb", load_end_force=_ltb_force(1.0), rod_error_estimate="off")
    for factor, want in ((0.99, 0), (1.01, 1)):
        run.problem.set_load(0.0)
        assert run.solver.minimizer.solve_at(factor).converged
        inertia = run.problem.planar.out_inertia
        H = inertia.assemble()
        A = H.convert(PETSc.Mat.Type.AIJ, PETSc.Mat()).convert(PETSc.Mat.Type.DENSE,
                                                               PETSc.Mat()).getDenseArray()
        A = np.triu(A) + np.triu(A, 1).T
        M = stability.stability_metric(run.problem)[:, inertia.comps].ravel()
        lam = sl.eigh(A, np.diag(M), eigvals_only=True)
        n = inertia.factor()
        assert n == int(np.sum(lam < -inertia.tau)) == want, (factor, lam[:3], inertia.tau)


def test_newton_path_stability_count_from_the_two_blocks():
    """-load_path newton -stability on the perfect Euler column at 0.3 ... 1.2 P_cr (no
    cut-back): the last, straight state has two negative eigenvalues, buckling in the plane
    (in-plane block) and out of it (out-of-plane block); every step's count from the two blocks
    is the 3-D count."""
    kw = dict(load_path="newton", stability=True, rod_error_estimate="off", load_steps=4,
              rod_imperfection=0, load_max_cutbacks=0)
    a = run_case("euler", **kw)
    b = run_case("euler", rod_planar="off", **kw)
    assert a.summary(a.ok)["model"].startswith("planar")
    counts = [h["negative_eigenvalues"] for h in a.history]
    assert counts == [h["negative_eigenvalues"] for h in b.history] == [0, 0, 0, 2]
    assert np.max(np.abs(gathered_positions(a) - gathered_positions(b))) <= 1e-8


def test_a_failed_in_plane_solve_fails_the_newton_step(monkeypatch):
    """The planar Newton path's PC whose in-plane LU fails (a zero pivot): the SNES's linear
    solve fails (SNES_DIVERGED_LINEAR_SOLVE), not a NaN step taken into the line search; the
    next solve that succeeds goes on (the PC's failed reason cleared)."""
    from petsc4py import PETSc
    from rodsnes.solve import planar
    run = build_run("mattiasson", rod_nelem=8, load_path="newton", load_steps=1,
                    rod_error_estimate="off")
    fail = [True]
    real = planar.PlanarSystem.solve_block

    def solve_block(self, b, x):
        return False if fail[0] else real(self, b, x)
    monkeypatch.setattr(planar.PlanarSystem, "solve_block", solve_block)
    solver = run.solver
    res = solver.solve_at(0.5)
    assert not res.converged
    assert solver.snes.getConvergedReason() == PETSc.SNES.ConvergedReason.DIVERGED_LINEAR_SOLVE
    fail[0] = False
    assert solver.solve_at(0.5).converged


def test_a_run_in_its_plane_makes_no_full_jacobian():
    """The full Jacobian (block size 6; 0.43 GB at 10^5 cubic elements) is made only when a
    run needs it: not by a run that stays in its plane (either path), by one in 3-D."""
    for path in ("newton", "minimize"):
        run = run_case("mattiasson", rod_nelem=6, load_path=path, rod_error_estimate="off")
        assert run.ok and run.problem.planar is not None and run.problem.planar.active
        assert run.problem.J_made is None, path
    run = run_case("mattiasson", rod_nelem=6, load_path="newton", rod_error_estimate="off",
                   rod_planar="off")
    assert run.ok and run.problem.J_made is not None
