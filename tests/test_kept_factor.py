"""The minimiser's Newton directions through a kept factorisation (rodsnes/solve/kept_factor.py):
GMRES on the new tangent, preconditioned by an earlier iterate's LU, gives the fresh LU's
direction to RTOL; a tangent too far from the factored one falls back to a fresh LU; a new
matrix, a user's -ksp_type and every new load step factor afresh."""
import numpy as np
import pytest
from petsc4py import PETSc

from conftest import gathered_positions, run_case
from rodsnes.solve import kept_factor
from rodsnes.solve.kept_factor import KeptFactor


def _direct(A):
    ksp = PETSc.KSP().create(comm=A.getComm())
    ksp.setType(PETSc.KSP.Type.PREONLY)
    ksp.getPC().setType(PETSc.PC.Type.LU)
    ksp.setOperators(A)
    return ksp


def _matrix(n, rng, scale=0.0, base=None):
    """A dense-ish nonsymmetric well-conditioned AIJ matrix; with base, base + scale * noise."""
    if base is None:
        M = np.eye(n) * 4.0 + rng.standard_normal((n, n)) / np.sqrt(n)
    else:
        M = base + scale * rng.standard_normal((n, n)) / np.sqrt(n)
    A = PETSc.Mat().createDense((n, n), array=M.copy(), comm=PETSc.COMM_SELF)
    A.convert(PETSc.Mat.Type.SEQAIJ)
    return A, M


def test_krylov_direction_equals_the_fresh_factor_to_rtol():
    """The second solve on a slightly changed matrix (the same Mat object, as a Jacobian
    reassembled in place) goes through GMRES on the old factor, no new factorisation, and its
    solution satisfies the new system to RTOL relative; a fresh LU's differs from it by
    less than RTOL times the condition number."""
    rng = np.random.default_rng(3)
    n = 60
    A, M = _matrix(n, rng)
    ksp = _direct(A)
    kf = KeptFactor(ksp)
    b = A.createVecLeft()
    b.setArray(rng.standard_normal(n))
    x = b.duplicate()
    ok, fresh = kf.solve(A, b, x)
    assert ok and fresh
    M2 = M + 1e-3 * rng.standard_normal((n, n)) / np.sqrt(n)
    A.setValues(range(n), range(n), M2.ravel())
    A.assemble()
    ok, fresh = kf.solve(A, b, x)
    assert ok and not fresh and kf.krylov_solves == 1 and 0 < kf.krylov_its <= kept_factor.MAX_ITS
    xa = x.getArray()
    assert np.linalg.norm(M2 @ xa - b.getArray()) <= 1.01 * kept_factor.RTOL * b.norm()
    exact = np.linalg.solve(M2, b.getArray())
    assert np.linalg.norm(xa - exact) <= 1e-4 * np.linalg.norm(exact)
    kf.destroy()
    ksp.destroy()
    A.destroy()


def test_a_tangent_too_far_gets_a_fresh_factorisation():
    """A matrix changed beyond what MAX_ITS Krylov iterations of the old factor resolve: the
    solve falls back to a fresh LU (counted), and its solution is the exact one."""
    rng = np.random.default_rng(4)
    n = 80
    A, M = _matrix(n, rng)
    ksp = _direct(A)
    kf = KeptFactor(ksp)
    b = A.createVecLeft()
    b.setArray(rng.standard_normal(n))
    x = b.duplicate()
    kf.solve(A, b, x)
    M2 = np.eye(n) * 4.0 + 3.0 * rng.standard_normal((n, n)) / np.sqrt(n)
    A.setValues(range(n), range(n), M2.ravel())
    A.assemble()
    ok, fresh = kf.solve(A, b, x)
    assert ok and fresh and kf.fallbacks == 1
    exact = np.linalg.solve(M2, b.getArray())
    assert np.linalg.norm(x.getArray() - exact) <= 1e-10 * np.linalg.norm(exact)
    kf.destroy()
    ksp.destroy()
    A.destroy()


def test_a_new_matrix_or_a_users_krylov_method_factors_afresh():
    """A different Mat object (a new contact pattern) is factored afresh; with a KSP that is
    not preonly (the user's -ksp_type) no solve is replaced by the kept factor's GMRES."""
    rng = np.random.default_rng(5)
    n = 40
    A, M = _matrix(n, rng)
    B, _ = _matrix(n, rng, 1e-3, M)
    ksp = _direct(A)
    kf = KeptFactor(ksp)
    b = A.createVecLeft()
    b.setArray(rng.standard_normal(n))
    x = b.duplicate()
    assert kf.solve(A, b, x) == (True, True)
    assert kf.solve(B, b, x) == (True, True)
    ksp.setType(PETSc.KSP.Type.GMRES)
    assert not kf.eligible()
    assert kf.solve(B, b, x)[1]
    assert kf.krylov_solves == 0
    kf.destroy()
    ksp.destroy()
    A.destroy()
    B.destroy()


@pytest.mark.mpi
@pytest.mark.parametrize("case,kw", [
    ("mattiasson", dict(load_steps=1, rod_planar="off")),
    (None, dict(rod_length=1, rod_radius=0.025, rod_youngs=1e6, rod_shear=666666.6666666666,
                bc_start="clamped", bc_end="sliding", rod_nelem=12, rod_imperfection=1e-3,
                bc_end_turns=1.5, load_end_force="3,0,0", load_steps=4)),
])
def test_minimiser_ends_where_it_ends_without_the_kept_factor(monkeypatch, case, kw):
    """Mattiasson's whole load in one step (solved in 3-D), and a twisted rod through its loop formation
    (12 cubic elements, 1.5 turns): with kept factorisations some Newton directions come from
    GMRES on the kept LU, and the run ends on the same stable equilibrium as the run that
    factors at every Newton step (positions to 1e-7 L, energy to 1e-9)."""
    runs = {}
    for on in (False, True):
        monkeypatch.setattr(kept_factor, "ENABLED", on)
        run = run_case(case, **kw)
        assert run.ok and all(h["negative_eigenvalues"] == 0 for h in run.history)
        runs[on] = run
    assert runs[True].solver.minimizer.kept.krylov_solves > 0
    e0, e1 = runs[False].last_energy, runs[True].last_energy
    assert abs(e0 - e1) <= 1e-9 * abs(e0)
    x0, x1 = gathered_positions(runs[False]), gathered_positions(runs[True])
    assert np.abs(x0 - x1).max() <= 1e-7 * runs[True].mesh.length
