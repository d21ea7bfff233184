"""A run stopped by an error it did not expect (a defect of rodsnes, or a failure of one rank
alone): one line naming the error and the rank, its traceback in DIR/error_rank<r>.txt,
summary.json marked failed with the converged steps kept, exit code 4 (cli._failed).  Under
mpirun an error of one rank alone used to leave the other ranks waiting for ever in the
solver's next collective (a batch job hung until its wall time); now the rank that stopped
aborts the job once the others have not stopped within cli.AGREE_SECONDS.  The 2-rank runs
are subprocesses under their own mpirun (an abort would end the test's own job)."""
import json
import os
import subprocess
import sys
import textwrap
import time

import pytest

from conftest import ROOT, clear_options
from rodsnes import cli

MATT = ("-options_file", os.path.join(ROOT, "cases", "mattiasson.opts"), "-rod_nelem", "16",
        "-load_path", "newton")

# rodsnes.cli.main with RodProblem.residual raising at its 30th call on rank RANK (-1: every
# rank); the agreement's wait cut to 1 s
SCRIPT = textwrap.dedent("""\
    import sys
    import petsc4py
    petsc4py.init(sys.argv)
    from mpi4py import MPI
    from rodsnes import cli
    from rodsnes.model.problem import RodProblem
    cli.AGREE_SECONDS = 1.0
    rank, calls, residual = {rank}, [0], RodProblem.residual

    def failing(self, *args, **kw):
        calls[0] += 1
        if calls[0] == 30 and rank in (-1, MPI.COMM_WORLD.rank):
            raise ValueError("made to fail here")
        return residual(self, *args, **kw)
    RodProblem.residual = failing
    sys.exit(cli.main(sys.argv))
    """)


def _env():
    """This environment without an outer mpirun's variables (the test may run under one)."""
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_btl="self,vader", OMPI_MCA_mpi_yield_when_idle="1",
               PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    for k in list(env):
        if k.startswith(("OMPI_COMM_WORLD", "OMPI_MCA_ess", "OMPI_MCA_orte", "OMPI_MCA_pmix",
                         "PMIX_", "PMI_")):
            del env[k]
    return env


def _summary(d):
    with open(os.path.join(d, "summary.json")) as fh:
        return json.load(fh)


@pytest.mark.parametrize("rank", [1, -1], ids=["one-rank", "every-rank"])
def test_an_internal_error_on_two_ranks_ends_the_job(tmp_path, rank):
    script = tmp_path / "fail.py"
    script.write_text(SCRIPT.format(rank=rank))
    out = tmp_path / "out"
    t0 = time.monotonic()
    p = subprocess.run(["mpirun", "-n", "2", "--bind-to", "none", "--oversubscribe",
                        sys.executable, str(script), *MATT, "-output_dir", str(out)],
                       env=_env(), cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert time.monotonic() - t0 < 60                   # no hang (it hung for ever before)
    assert p.returncode == cli.EXIT_INTERNAL, p.stdout[-2000:] + p.stderr[-3000:]
    lines = [l for l in p.stderr.splitlines() if l.startswith("rodsnes: error: ")]
    alone = rank == 1
    where = "on rank 1 of 2" if alone else "on rank 0 of 2"
    assert f"internal error {where}: ValueError: made to fail here" in lines[0], p.stderr
    assert ("the job is aborted" in p.stderr) == alone, p.stderr
    assert "Traceback" not in p.stderr, p.stderr
    failing = [1] if alone else [0, 1]
    for r in failing:
        text = (out / f"error_rank{r}.txt").read_text()
        assert "Traceback" in text and "made to fail here" in text
    s = _summary(out)
    assert s["converged"] is False and "made to fail here" in s["failure"]
    assert s["load_steps"] >= 1                          # the converged steps are kept
    assert os.path.exists(out / "result.h5")


def test_an_internal_error_on_one_rank_says_so_and_keeps_the_steps(capsys, tmp_path,
                                                                     monkeypatch):
    from rodsnes.model.problem import RodProblem
    calls, residual = [0], RodProblem.residual

    def failing(self, *args, **kw):
        calls[0] += 1
        if calls[0] == 30:
            raise ValueError("made to fail here")
        return residual(self, *args, **kw)
    monkeypatch.setattr(RodProblem, "residual", failing)
    out = tmp_path / "out"
    try:
        rc = cli.main(["rodsnes", *MATT, "-output_dir", str(out)])
    finally:
        clear_options()
    err = capsys.readouterr().err
    assert rc == cli.EXIT_INTERNAL
    assert err.strip().splitlines()[-1].startswith(
        "rodsnes: error: internal error: ValueError: made to fail here"), err
    assert str(out / "error_rank0.txt") in err and "Traceback" not in err
    s = _summary(out)
    assert s["converged"] is False and "made to fail here" in s["failure"]
    assert s["load_steps"] >= 1


def test_an_internal_error_before_the_run_prints_its_traceback_after_the_line(capsys,
                                                                            monkeypatch):
    """No output directory yet: the traceback follows the error line on stderr."""
    from rodsnes.io import scene as scn

    def broken(scene):
        raise RuntimeError("made to fail before the run")
    monkeypatch.setattr(scn, "check_solvable", broken)
    try:
        rc = cli.main(["rodsnes", *MATT, "-output_dir", "/nonexistent/never/made"])
    finally:
        clear_options()
    err = capsys.readouterr().err
    assert rc == cli.EXIT_INTERNAL
    first, rest = err.split("\n", 1)
    assert first.startswith("rodsnes: error: internal error: RuntimeError: made to fail "
                            "before the run") and first.endswith("printed below)"), err
    assert rest.startswith("Traceback") and "broken" in rest, err
