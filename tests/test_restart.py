"""-restart DIR resumes from the last complete step of DIR and ends where an uninterrupted run ends."""
import shutil

import h5py
import numpy as np

from conftest import gathered_positions, run_case


def test_restart_from_an_interrupted_run_matches_the_uninterrupted_one(tmp_path):
    full = run_case("mattiasson", outdir=str(tmp_path / "full"), load_steps=4)
    assert full.ok
    # an interrupted run: the same file, but only two steps were complete when it stopped
    cut = tmp_path / "cut"
    shutil.copytree(tmp_path / "full", cut)
    with h5py.File(cut / "result.h5", "r+") as f:
        f.attrs["last_step"] = 2
    resumed = run_case("mattiasson", outdir=str(cut), load_steps=4, restart=str(cut))
    assert resumed.ok
    assert [h["load"] for h in resumed.history] == [0.75, 1.0]
    assert np.abs(gathered_positions(resumed) - gathered_positions(full)).max() < 1e-9
    with h5py.File(cut / "result.h5", "r") as f:
        assert f.attrs["last_step"] == 4
        assert sorted(f["steps"]) == ["00000", "00001", "00002", "00003", "00004"]
        assert f["steps/00003"].attrs["load"] == 0.75



def test_restart_from_an_unstable_step_keeps_its_eigenvalue_count(tmp_path):
    """-stability without switching: the Michell ring near sqrt(3) turns stays on the circle,
    accepted with negative eigenvalues after the cut-backs.  A restart from such a step starts
    from that count (Run.nneg0; no new switch attempt until the instability grows), so it does
    not take its own state for a loss of stability and cut every step back."""
    kw = dict(load_twist_turns=2.5, stability=True, stability_switch="false", rod_nelem=8,
              load_steps=10, load_max_cutbacks=3)
    full = run_case("michell", outdir=str(tmp_path / "full"), **kw)
    assert full.ok
    neg = [i + 1 for i, h in enumerate(full.history) if h["negative_eigenvalues"] > 0]
    k = neg[-1]                                  # the last step (load 1), unstable
    cut = tmp_path / "cut"
    shutil.copytree(tmp_path / "full", cut)
    with h5py.File(cut / "result.h5", "r+") as f:
        f.attrs["last_step"] = k - 3
    resumed = run_case("michell", outdir=str(cut), restart=str(cut), **kw)
    n0 = full.history[k - 4]["negative_eigenvalues"]
    assert n0 > 0 and resumed.nneg0 == n0
    assert resumed.ok
    assert all(h["negative_eigenvalues"] >= n0 for h in resumed.history)
