"""The direct linear solves rodsnes defaults to, as defaults in the PETSc options database (a
user's -ksp_type, -pc_type, -pc_factor_mat_solver_type, -mat_mumps_icntl_* win).

The Newton steps (the minimiser's and the Newton path's SNES) factor the Jacobian by PETSc's
own sparse LU (6 x 6 blocks, nested-dissection ordering); on more than one rank every rank
factors the whole matrix (PCREDUNDANT).  A rod's Jacobian is a chain of small blocks plus the
contact couplings, and on it PETSc's LU was 3-5 x faster than MUMPS at every size measured
(plectoneme, 60 elements: 1.8 ms against 4.2 ms per factorisation; cantilever, 1e4 elements:
50-75 ms against 256 ms; 2 ranks, 1e4 elements: 0.16 s against 0.94 s; tools/bench_scaling.py,
docs/bench_scaling.md).  MUMPS stays one option away (-pc_factor_mat_solver_type mumps, and on
several ranks -pc_type lu), and it factors the symmetric LDL^T whose inertia the stability
count and the minimiser's shifts read (solve/stability.py), where its pivoting is needed."""
from petsc4py import PETSc


def option_default(name, value):
    """Set -name value in the options database unless the user gave it."""
    opts = PETSc.Options()
    if not opts.hasName(name):
        opts.setValue(name, value)


def mumps_fill_room(problem, prefix=""):
    """With a term whose pattern follows the state (contact), room for the fill MUMPS's
    analysis did not see (contact pairs come and go between factorisations; without it
    INFOG(1) = -9): -<prefix>mat_mumps_icntl_14 100."""
    if problem.moving_pattern:
        option_default(prefix + "mat_mumps_icntl_14", "100")


def lu_defaults(comm, prefix=""):
    """preonly + LU for the KSP of options prefix ``prefix`` (module docstring): PETSc's LU on
    one rank, PETSc's LU of the whole matrix on every rank (redundant) on several, unless the
    user chose a preconditioner or a factorisation package (then LU by it, MUMPS if none)."""
    opts = PETSc.Options()
    option_default(prefix + "ksp_type", "preonly")
    chosen = opts.hasName(prefix + "pc_type") or opts.hasName(prefix + "pc_factor_mat_solver_type")
    if comm.getSize() == 1:
        option_default(prefix + "pc_type", "lu")
        option_default(prefix + "pc_factor_mat_solver_type", "petsc")
    elif chosen:
        option_default(prefix + "pc_type", "lu")
        option_default(prefix + "pc_factor_mat_solver_type", "mumps")
    else:
        option_default(prefix + "pc_type", "redundant")
        option_default(prefix + "redundant_pc_type", "lu")
        option_default(prefix + "redundant_pc_factor_mat_solver_type", "petsc")


def direct_solver_defaults(problem, prefix=""):
    """lu_defaults on the problem's communicator, with mumps_fill_room for MUMPS."""
    lu_defaults(problem.layout.comm, prefix)
    mumps_fill_room(problem, prefix)
