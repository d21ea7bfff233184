"""Stability of an equilibrium: the inertia of the energy Hessian.

At an equilibrium the consistent tangent equals the (symmetric) Hessian of the total energy in
the exponential chart (elastic.py).  Its number of negative eigenvalues, from a MUMPS LDL^T
(Cholesky-type) factorisation (-mat_mumps_icntl_13 1 for a parallel-correct count), is the
number of independent directions in which the energy decreases: 0 means a stable (local
minimum) equilibrium.  Dirichlet rows hold 1 on the diagonal and count as positive.
"""
import numpy as np
from petsc4py import PETSc


def negative_eigenvalues(problem):
    """Number of negative eigenvalues of the symmetric tangent at the current state."""
    H = problem.layout.create_matrix(problem.contact.extra_pattern() if problem.contact else None)
    problem.jacobian(None, problem.state.X, H, H, symmetric=True)
    A = H.convert(PETSc.Mat.Type.AIJ, PETSc.Mat())
    A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    # a shift tau = 1000 eps max|diag(A)| (above the roundoff of an exact zero eigenvalue)
    # keeps exact zero modes (symmetries of isotropic rods, e.g. turning a buckled isotropic
    # column about its load axis) from counting as negative
    tau = 1e3 * np.finfo(float).eps * A.getDiagonal().norm(PETSc.NormType.INFINITY)
    A.shift(tau)
    # symmetric Jacobi scaling D^-1/2 A D^-1/2 is a congruence, so it keeps the inertia
    # (Sylvester) while bringing axial (EA/h) and bending (EI/h) pivots to one scale, so that
    # MUMPS's null-pivot test does not swallow soft negative directions
    d = A.getDiagonal()
    d.abs()
    d.sqrtabs()
    d.reciprocal()
    A.diagonalScale(d, d)
    pc = PETSc.PC().create(comm=problem.layout.comm)
    pc.setOptionsPrefix("stability_")
    pc.setOperators(A)
    pc.setType(PETSc.PC.Type.CHOLESKY)
    pc.setFactorSolverType("mumps")
    opts = PETSc.Options()
    for icntl in ("13", "24"):     # 13: inertia over all ranks; 24: null pivots (MatGetInertia needs it)
        if not opts.hasName("stability_mat_mumps_icntl_" + icntl):
            opts.setValue("stability_mat_mumps_icntl_" + icntl, "1")
    pc.setFromOptions()
    pc.setUp()
    nneg, nzero, npos = pc.getFactorMatrix().getInertia()
    pc.destroy()
    A.destroy()
    H.destroy()
    return int(nneg)
