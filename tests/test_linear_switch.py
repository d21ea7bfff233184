"""linear.use_mumps_when_filled on several ranks (a contact-filled pattern goes to MUMPS over the
ranks on that KSP alone): the error estimate's SNES and minimiser share the prefix -estimate_,
and the estimate's stages all still solve after the minimiser's switch; a user's
-redundant_pc_factor_mat_solver_type stays as given.  (A shared options-database switch to
PCREDUNDANT over MUMPS, tried and reverted, broke the first.)"""
import numpy as np
import pytest
from petsc4py import PETSc

from conftest import build_run, run_case


@pytest.mark.mpi
def test_the_estimate_snes_survives_the_minimisers_switch_to_mumps():
    from rodsnes.solve import estimate
    if PETSc.COMM_WORLD.getSize() == 1:
        pytest.skip("one rank: PCLU, no redundant PC")
    stages = []
    orig = estimate.EnrichedProblem.solve_stage

    def probe(self, stage):
        its, ok = orig(self, stage)
        stages.append((stage, ok))
        return its, ok

    estimate.EnrichedProblem.solve_stage = probe
    try:
        run = run_case("bench_coil", rod_error_estimate="every", load_steps=3)
    finally:
        estimate.EnrichedProblem.solve_stage = orig
    assert run.ok
    assert all(ok for _, ok in stages), stages


@pytest.mark.mpi
def test_a_users_redundant_package_is_kept():
    from rodsnes.solve import linear
    if PETSc.COMM_WORLD.getSize() == 1:
        pytest.skip("one rank: PCLU, the redundant option is not read")
    run = run_case("bench_coil", rod_nelem=200, rod_length=4.0, load_path="newton",
                   rod_error_estimate="off", redundant_pc_factor_mat_solver_type="petsc")
    assert run.ok
    assert PETSc.Options().getString("redundant_pc_factor_mat_solver_type") == "petsc"
    assert not linear.is_default("redundant_pc_factor_mat_solver_type")


@pytest.mark.mpi
def test_a_second_run_in_the_process_chooses_its_solvers_as_the_first():
    """The solver defaults a run puts into the options database (preonly, PETSc's LU, its
    ordering, MUMPS's ICNTL(14) ...) leave it when the run ends, so a second run in the same
    process (the meshes of -rod_tolerance, a script's next scene) does not take them for the
    user's: its Newton KSP is again rodsnes' choice (the filled pattern goes to MUMPS, as in
    the first run), and the user's own option stays."""
    from rodsnes.io.scene import read_scene
    from rodsnes.run import Run
    from rodsnes.solve import linear
    from conftest import set_options
    opts = set_options("bench_coil", load_steps=1, quiet=True, snes_max_it=50)
    given = set(opts.getAll())
    runs = []
    for _ in range(2):
        run = Run(read_scene(["rodsnes"], opts), PETSc.COMM_WORLD)
        assert run.execute()
        runs.append(run)
        assert set(opts.getAll()) == given          # the defaults left; the user's stayed
        assert not linear.DEFAULTED
    lu = [r.solver.minimizer.lu for r in runs]
    types = [r.solver.minimizer.ksp.getPC().getFactorSolverType() for r in runs]
    assert lu[0].auto == lu[1].auto and types[0] == types[1] == "mumps"
    assert runs[0].solver.total_its == runs[1].solver.total_its


@pytest.mark.parametrize("case, extra, natural", [
    ("mattiasson", {"rod_planar": "off"}, True),            # an open chain: banded in its order
    ("mattiasson", {}, True),                               # the planar step's KSP too
    ("michell", {"rod_nelem": 12}, False),                  # a ring: its closing element fills
    ("plectoneme", {"load_steps": 1}, False),               # contact: the pattern moves
    ("mattiasson", {"pc_factor_mat_ordering_type": "nd", "rod_planar": "off"}, False),  # the user's
])
def test_chains_are_factored_in_their_own_order(case, extra, natural):
    """linear.chain_ordering: PETSc's LU of a Jacobian whose pattern stays in the natural node
    order where that fills no more than AMD (an open rod: the LU then goes through the blocks
    in memory order), AMD for a ring and for a contact pattern, the user's ordering as given;
    the factorisation then uses that ordering."""
    if PETSc.COMM_WORLD.getSize() > 1:
        pytest.skip("one rank: PCLU's own ordering option")
    from rodsnes.solve import linear
    run = build_run(case, **extra)
    prefix = "planar_" if run.problem.planar is not None else ""
    p = run.problem
    fills = {o: linear.pattern_fill(p, o) for o in ("natural", "amd")}
    assert linear.chain_ordering(p, prefix) is False       # nothing set yet: not rodsnes' default
    linear.lu_defaults(p.layout.comm, prefix)
    chose = linear.chain_ordering(p, prefix)
    got = PETSc.Options().getString(prefix + "pc_factor_mat_ordering_type")
    assert chose == natural and got == ("natural" if natural else extra.get(
        "pc_factor_mat_ordering_type", "amd")), (chose, got, fills)
    if case == "michell":
        assert fills["natural"] > fills["amd"]
    if natural:
        assert fills["natural"] == fills["amd"] == 1.0
    linear.take_back_defaults()


@pytest.mark.mpi
@pytest.mark.parametrize("nelem", [12, 100, 400])
def test_the_natural_order_is_the_matrix_order(nelem):
    """On several ranks PETSc's natural order is the ranks' stretches in rank order, each
    numbered toward the nodes it shares with the others (partition.stretch_descends), which a
    partition need not keep along the rod (METIS may number the pieces from either end).
    chain_ordering chooses it exactly where it does not fill, measured on the matrix's
    numbering; on two ranks it never does, whichever end METIS numbers first (at 12 elements it
    gives rank 1 the rod's first half)."""
    from rodsnes.solve import linear
    run = build_run("mattiasson", rod_nelem=nelem, rod_planar="off")
    p, lay = run.problem, run.layout
    linear.lu_defaults(lay.comm, "")
    chose = linear.chain_ordering(p, "")
    fill = linear.pattern_fill(p, "natural")
    assert chose == (fill == 1.0), (lay.elem_owner, fill)
    # each rank's nodes in PETSc's order: along the rod, the last next to the other rank's
    own = lay.owned_nodes
    assert np.all(np.diff(own) == 1) or np.all(np.diff(own) == -1)
    if lay.comm.getSize() == 2:
        assert fill == 1.0, (lay.elem_owner, fill)
        other = lay.node_owner != lay.comm.getRank()
        touching = np.isin(p.mesh.conn, own[-1]).any(axis=1)
        assert other[p.mesh.conn[touching]].any()
    linear.take_back_defaults()


@pytest.mark.parametrize("extra, chained", [
    ({}, True),                                             # the planar step's KSP
    ({"rod_planar": "off"}, True),                          # the 3-D step's
    ({"rod_planar": "off", "pc_factor_mat_ordering_type": "natural"}, False),    # the user's
    ({"rod_planar": "off", "pc_factor_mat_solver_type": "mumps"}, False),
    ({"rod_planar": "off", "pc_factor_shift_type": "nonzero"}, False),  # PETSc's LU's option
])
def test_an_open_chain_is_factored_by_the_chain_lu_on_one_rank(extra, chained):
    """linear.use_chain_lu: on one rank the Newton steps of an open rod without contact factor
    by chain.ChainPC where PETSc's LU in the rod's order is rodsnes' default (not where the
    user chose the ordering or the package), and the run is PETSc's LU's to round-off: the
    same iterations, the same state (the user's natural ordering is that LU)."""
    if PETSc.COMM_WORLD.getSize() > 1:
        pytest.skip("one rank: the chain LU of the whole matrix")
    from rodsnes.solve import chain
    run = run_case("mattiasson", rod_nelem=40, load_steps=3, rod_error_estimate="off", **extra)
    assert run.ok
    planar = run.problem.planar
    ksp = planar.ksp if planar is not None and planar.active else run.solver.minimizer.ksp
    pc = ksp.getPC()
    is_chain = pc.getType() == "python" and isinstance(pc.getPythonContext(), chain.ChainPC)
    assert is_chain == chained
    if extra.get("pc_factor_mat_ordering_type") == "natural":
        ref = run_case("mattiasson", rod_nelem=40, load_steps=3, rod_error_estimate="off",
                       rod_planar="off")
        assert ref.solver.total_its == run.solver.total_its
        x, y = ref.problem.state.X.getArray(), run.problem.state.X.getArray()
        assert np.abs(x - y).max() <= 1e-9 * np.abs(x).max()


@pytest.mark.parametrize("case, extra", [
    ("michell", {"rod_nelem": 12}),                         # a ring: its closing element fills
    ("plectoneme", {"load_steps": 1, "snes_max_it": 3}),    # contact: the pattern moves
])
def test_rings_and_contact_keep_petscs_lu(case, extra):
    if PETSc.COMM_WORLD.getSize() > 1:
        pytest.skip("one rank")
    from rodsnes.solve import linear
    run = build_run(case, **extra)
    p = run.problem
    ksp = PETSc.KSP().create(PETSc.COMM_SELF)
    linear.lu_defaults(p.layout.comm, "")
    linear.chain_ordering(p, "")
    ksp.setFromOptions()
    p.jacobian(None, p.state.X, p.J, p.J)
    ksp.setOperators(p.J)
    assert not linear.use_chain_lu(ksp, p)
    assert ksp.getPC().getType() == "lu"
    ksp.destroy()
    linear.take_back_defaults()
