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


def _matrix(n, rng, scale=0.0, base=None):
    """A dense-ish nonsymmetric well-conditioned AIJ matrix; with base, base + scale * noise."""
    if base is None:
        M = np.eye(n) * 4.0 + rng.standard_normal((n, n)) / np.sqrt(n)
    else:
        M = base + scale * rng.standard_normal((n, n)) / np.sqrt(n)
    A = PETSc.Mat().createDense((n, n), array=M.copy(), comm=PETSc.COMM_SELF)
    A.convert(PETSc.Mat.Type.SEQAIJ)
    return A, M


class System:
    """A random system A x = b of n unknowns, the preonly + LU KSP on A and its KeptFactor;
    ``refill(M)`` puts the entries M into the same Mat object (a Jacobian reassembled in
    place)."""

    def __init__(self, n, seed):
        self.rng = np.random.default_rng(seed)
        self.n = n
        self.A, self.M = _matrix(n, self.rng)
        self.ksp = PETSc.KSP().create(comm=PETSc.COMM_SELF)
        self.ksp.setType(PETSc.KSP.Type.PREONLY)
        self.ksp.getPC().setType(PETSc.PC.Type.LU)
        self.ksp.setOperators(self.A)
        self.kf = KeptFactor(self.ksp)
        self.b = self.A.createVecLeft()
        self.b.setArray(self.rng.standard_normal(n))
        self.x = self.b.duplicate()

    def refill(self, M):
        self.A.setValues(range(self.n), range(self.n), M.ravel())
        self.A.assemble()

    def exact(self, M):
        return np.linalg.solve(M, self.b.getArray())

    def destroy(self):
        self.kf.destroy()
        for obj in (self.ksp, self.A, self.b, self.x):
            obj.destroy()


def test_krylov_direction_equals_the_fresh_factor_to_rtol():
    """The second solve on a slightly changed matrix (the same Mat object, as a Jacobian
    reassembled in place) goes through GMRES on the old factor, no new factorisation, and its
    solution satisfies the new system to RTOL relative; a fresh LU's differs from it by
    less than RTOL times the condition number."""
    S = System(60, 3)
    assert S.kf.solve(S.A, S.b, S.x) == (True, True)
    M2 = S.M + 1e-3 * S.rng.standard_normal((S.n, S.n)) / np.sqrt(S.n)
    S.refill(M2)
    assert S.kf.solve(S.A, S.b, S.x) == (True, False)
    assert S.kf.krylov_solves == 1 and 0 < S.kf.krylov_its <= kept_factor.MAX_ITS
    xa = S.x.getArray()
    assert np.linalg.norm(M2 @ xa - S.b.getArray()) <= 1.01 * kept_factor.RTOL * S.b.norm()
    exact = S.exact(M2)
    assert np.linalg.norm(xa - exact) <= 1e-4 * np.linalg.norm(exact)
    S.destroy()


def test_a_tangent_too_far_gets_a_fresh_factorisation():
    """A matrix changed beyond what MAX_ITS Krylov iterations of the old factor resolve: the
    solve falls back to a fresh LU (counted), and its solution is the exact one."""
    S = System(80, 4)
    S.kf.solve(S.A, S.b, S.x)
    M2 = np.eye(S.n) * 4.0 + 3.0 * S.rng.standard_normal((S.n, S.n)) / np.sqrt(S.n)
    S.refill(M2)
    assert S.kf.solve(S.A, S.b, S.x) == (True, True) and S.kf.fallbacks == 1
    exact = S.exact(M2)
    assert np.linalg.norm(S.x.getArray() - exact) <= 1e-10 * np.linalg.norm(exact)
    S.destroy()


def test_a_new_matrix_or_a_users_krylov_method_factors_afresh():
    """A different Mat object (a new contact pattern) is factored afresh; with a KSP that is
    not preonly (the user's -ksp_type) no solve is replaced by the kept factor's GMRES."""
    S = System(40, 5)
    B, _ = _matrix(S.n, S.rng, 1e-3, S.M)
    assert S.kf.solve(S.A, S.b, S.x) == (True, True)
    assert S.kf.solve(B, S.b, S.x) == (True, True)
    S.ksp.setType(PETSc.KSP.Type.GMRES)
    assert not S.kf.eligible()
    assert S.kf.solve(B, S.b, S.x)[1]
    assert S.kf.krylov_solves == 0
    B.destroy()
    S.destroy()


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
