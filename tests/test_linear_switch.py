"""linear.use_mumps_when_filled on several ranks (a contact-filled pattern goes to MUMPS over the
ranks on that KSP alone): the error estimate's SNES and minimiser share the prefix -estimate_,
and the estimate's stages all still solve after the minimiser's switch; a user's
-redundant_pc_factor_mat_solver_type stays as given.  (A shared options-database switch to
PCREDUNDANT over MUMPS, tried and reverted, broke the first.)"""
import pytest
from petsc4py import PETSc

from conftest import run_case


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
