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
