"""The command line as a batch user meets it: exit codes, messages, files on disk."""
import json
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def rodsnes(*args, tmp):
    env = dict(os.environ)
    for k in list(env):          # a serial subprocess must not inherit mpirun's rank variables
        if k.startswith(("OMPI_COMM_WORLD", "PMIX_", "PMI_")):
            del env[k]
    return subprocess.run([sys.executable, "-m", "rodsnes", *args, "-output_dir", str(tmp)],
                          cwd=ROOT, capture_output=True, text=True, env=env, timeout=600)


def test_misspelled_option_names_the_closest_valid_one(tmp_path):
    p = rodsnes("-options_file", "cases/rollup.opts", "-rod_lenght", "3", tmp=tmp_path)
    assert p.returncode == 2
    assert "unknown option -rod_lenght: did you mean -rod_length?" in p.stderr
    assert not (tmp_path / "result.h5").exists()


def test_negative_radius_is_refused_with_the_option_name(tmp_path):
    p = rodsnes("-options_file", "cases/rollup.opts", "-rod_radius", "-1", tmp=tmp_path)
    assert p.returncode == 2 and "-rod_radius" in p.stderr and "> 0" in p.stderr


def test_converged_run_writes_summary_and_steps(tmp_path):
    p = rodsnes("-options_file", "cases/rollup.opts", tmp=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "step    1  load 1.000000" in p.stdout
    s = json.loads((tmp_path / "summary.json").read_text())
    for key in ("converged", "load", "energy", "tip_position", "newton_iterations", "load_steps",
                "wall_time_s", "dofs", "ranks"):
        assert key in s
    assert s["converged"] and s["load"] == 1.0 and s["dofs"] == 6 * 25
    assert np.linalg.norm(s["tip_position"]) < 1e-5
    with h5py.File(tmp_path / "result.h5", "r") as f:
        assert sorted(f["steps"]) == ["00000", "00001"]
        assert f["steps/00001"].attrs["load"] == 1.0
        assert f["steps/00001/directors"].shape == (25, 3, 3)


def test_failed_load_path_keeps_the_last_converged_step(tmp_path):
    # two Newton iterations are not enough for lambda = 10 in one step, even after one cut-back
    p = rodsnes("-options_file", "cases/mattiasson.opts", "-load_steps", "4", "-load_path", "newton", "-snes_max_it", "3",
                "-load_max_cutbacks", "1", tmp=tmp_path)
    assert p.returncode == 3
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["converged"] is False and "failure" in s
    with h5py.File(tmp_path / "result.h5", "r") as f:
        last = f.attrs["last_step"]
        assert f[f"steps/{last:05d}"].attrs["load"] == s["load"] < 1.0


def test_log_view_prints_the_profile_and_a_converged_run_exits_0(tmp_path):
    """-log_view is read only when PETSc starts, so PETSc must start with the command line:
    no module the command line imports before that may start it.  The profile holds rodsnes'
    own events beside PETSc's, and the run exits 0."""
    p = rodsnes("-options_file", "cases/mattiasson.opts", "-load_steps", "1", "-log_view",
                tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "ElasticKernel" in p.stdout and "MinStep" in p.stdout
    assert "PETSC ERROR" not in p.stderr


@pytest.mark.parametrize("env, want", [(None, False), ("1", True), ("0", False)])
def test_a_run_gives_numpy_small_pages_unless_numpy_madvise_hugepage_says(monkeypatch, env, want):
    """cli.small_pages_for_numpy: numpy's huge-page requests off for the run's process (first
    touches waited for the kernel's compaction), numpy's own NUMPY_MADVISE_HUGEPAGE followed
    where set (numpy reads it at import: here the setting it left stays)."""
    from rodsnes import cli
    core = getattr(np, "_core", None) or np.core
    get, set_ = core.multiarray._get_madvise_hugepage, core.multiarray._set_madvise_hugepage
    before = get()
    try:
        set_(want if env is not None else True)         # as numpy's import left it
        if env is None:
            monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
        else:
            monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", env)
        cli.small_pages_for_numpy()
        assert get() is want
    finally:
        set_(before)
