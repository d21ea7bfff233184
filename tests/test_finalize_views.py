"""A run on 2 ranks that asks PETSc for views at PetscFinalize (-log_view, -options_left)
ends: the bench coil (contact along the rod) used to hang at exit there, one rank waiting in
MPI_Comm_dup for a viewer while the other had finished (cli._release_petsc_objects).  In a
subprocess under its own mpirun (rank 0 starts it, under make test-mpi too)."""
import os
import subprocess
import sys

import pytest
from petsc4py import PETSc

from test_schur_exit import ROOT, _mpirun_env


@pytest.mark.mpi
@pytest.mark.parametrize("view", ["-log_view", "-options_left"])
def test_a_two_rank_contact_run_with_finalize_views_exits(tmp_path, view):
    comm = PETSc.COMM_WORLD.tompi4py()
    result = None
    if comm.rank == 0:
        try:
            log = str(tmp_path / "log.txt")
            extra = [view, ":" + log] if view == "-log_view" else [view]
            p = subprocess.run(["mpirun", "-n", "2", "--bind-to", "none", "--oversubscribe",
                                sys.executable, "-m", "rodsnes", "-options_file",
                                os.path.join(ROOT, "cases", "bench_coil.opts"), "-rod_nelem", "200",
                                "-rod_length", "4", "-load_path", "newton",
                                "-rod_error_estimate", "off", "-output_dir", str(tmp_path / "out"),
                                *extra], env=_mpirun_env(), cwd=ROOT, capture_output=True,
                               text=True, timeout=150)
            result = (p.returncode, view != "-log_view" or os.path.exists(log),
                      p.stdout[-1500:] + p.stderr[-1500:])
        except subprocess.TimeoutExpired as exc:
            result = (None, False, f"hung: {exc}")
        except BaseException as exc:    # report on every rank, never hang the others
            result = (None, False, repr(exc))
    rc, wrote, out = comm.bcast(result, root=0)
    assert rc == 0 and wrote, out
