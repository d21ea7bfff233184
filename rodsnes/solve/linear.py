"""The direct linear solves rodsnes defaults to, as defaults in the PETSc options database (a
user's -ksp_type, -pc_type, -pc_factor_mat_solver_type, -mat_mumps_icntl_* win)."""
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


def direct_solver_defaults(problem):
    """preonly + LU by MUMPS for the unprefixed KSP (the Newton path's SNES and the
    minimiser's Newton step), with mumps_fill_room."""
    option_default("ksp_type", "preonly")
    option_default("pc_type", "lu")
    option_default("pc_factor_mat_solver_type", "mumps")
    mumps_fill_room(problem)
