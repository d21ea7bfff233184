"""solve/schur.py at interpreter exit: a script that leaves a KSP with the RankSchur python PC
alive (never destroys it) ends with exit code 0 on 2 ranks.  petsc4py 3.18 destroys the PETSc
objects whose Python handles go during the interpreter's teardown in PetscFinalize, after the
interpreter: a python PC still there then took the GIL of a finalised interpreter (a
segmentation fault at exit, the results right); solve/petsc_exit.py's exit hook turns every
live python PC of rodsnes into a PC of type none first.  In a subprocess under its own mpirun (rank 0 starts it, under
make test-mpi too)."""
import os
import subprocess
import sys
import textwrap

import pytest
from petsc4py import PETSc

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tools"))
import bench_scaling as bs  # noqa: E402

# the condensed PC (MIN_NODES_PER_RANK 0: a short rod condenses) and the whole-matrix one
# (SCHUR_MAX 0), both left alive at exit; every rank writes its PCs' modes and solutions' norms
# to a file of its own (mpirun merges the ranks' output mid-line)
SCRIPT = textwrap.dedent("""\
    import sys
    sys.path.insert(0, {tests!r})
    from petsc4py import PETSc
    from conftest import build_run
    from rodsnes.solve import schur
    schur.MIN_NODES_PER_RANK = 0
    run = build_run("mattiasson", rod_nelem=40, rod_planar="off")
    p = run.problem
    p.set_load(0.3)
    p.residual(None, p.state.X, p.F)
    p.jacobian(None, p.state.X, p.J, p.J)
    A = p.J
    b = A.createVecLeft(); b.set(1.0)
    kept = []
    for max_sep in (schur.SCHUR_MAX, 0):
        schur.SCHUR_MAX = max_sep
        ksp = PETSc.KSP().create(comm=A.getComm()); ksp.setType("preonly")
        pc = ksp.getPC(); pc.setType("python"); ctx = schur.RankSchur(p); pc.setPythonContext(ctx)
        ksp.setOperators(A)
        y = b.duplicate(); ksp.solve(b, y)
        with open({out!r} + str(PETSc.COMM_WORLD.getRank()), "a") as fh:
            fh.write(f"{{ctx.mode}} {{y.norm()!r}}\\n")
        kept.append((ksp, pc, y))
    """)


def _mpirun_env():
    """bench_scaling's environment for mpirun, without the variables of an mpirun this test
    may run under itself (make test-mpi): the inner mpirun would take them for its own job."""
    keep = ("OMPI_ALLOW_RUN_AS_ROOT", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "OMPI_MCA_btl")
    env = bs.run_env()
    for k in list(env):
        if k.startswith(("OMPI_", "PMIX_", "PMI_")) and k not in keep:
            del env[k]
    env["OMPI_MCA_mpi_yield_when_idle"] = "1"      # the outer ranks wait on the same cores
    return env


@pytest.mark.mpi
def test_a_script_leaving_a_rank_schur_pc_alive_exits_cleanly(tmp_path):
    comm = PETSc.COMM_WORLD.tompi4py()
    result = None
    if comm.rank == 0:
        try:
            script = tmp_path / "leave_alive.py"
            out = str(tmp_path / "rank")
            script.write_text(SCRIPT.format(tests=os.path.join(ROOT, "tests"), out=out))
            p = subprocess.run(["mpirun", "-n", "2", "--bind-to", "none", "--oversubscribe",
                                sys.executable, str(script)], env=_mpirun_env(), cwd=ROOT,
                               capture_output=True, text=True, timeout=300)
            ranks = [open(out + str(r)).read().split() if os.path.exists(out + str(r)) else []
                     for r in range(2)]
            result = (p.returncode, ranks, p.stdout[-2000:] + p.stderr[-3000:])
        except BaseException as exc:    # report on every rank, never hang the others
            result = (None, [], repr(exc))
    rc, ranks, err = comm.bcast(result, root=0)
    assert rc == 0 and "SEGV" not in err, err
    # both ranks solved with both PCs, the condensed one and the whole-matrix one, alike
    assert [r[0::2] for r in ranks] == [["schur", "whole"]] * 2, (ranks, err)
    schur0, whole0 = map(float, ranks[0][1::2])
    assert ranks[0] == ranks[1] and schur0 > 0, ranks
    assert schur0 == pytest.approx(whole0, rel=1e-6)
