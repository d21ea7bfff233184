"""The twisted clamped rod of cases/plectoneme.opts (the PyElastica plectoneme scene: L = 1,
radius 0.025, E = 1e6, G = E/1.5, end clamped in rotation and sliding along the axis under a
small tension), here to 1.5 turns instead of 10 with 40 elements so that it fits the test budget (~3 min): the
straight rod's loop formation is a fold of the stable path, which -stability passes by
relaxation (jump_branch) into a loop in self-contact.  The full 10 turns are a batch run
(README, "Plectoneme")."""
import numpy as np

from conftest import run_case


def test_twisted_rod_snaps_into_a_loop_in_self_contact():
    """Converged at every step with the residual at tolerance; one jump (the loop formation);
    at the end: stable, Lk = imposed turns within 1e-2 (and Lk = Tw + Wr), a loop (writhe
    about 1), contact active with a penetration within the penalty's promise (about 1 % of the
    diameter)."""
    turns = 1.5
    # 40 elements instead of 60 and 8 cut-backs at the fold instead of 12: the same path (the
    # jump at 1.2075 turns, writhe 0.949 at 1.5 turns, as with 60) in 60 % of the time
    run = run_case("plectoneme", stability=True, bc_end_turns=turns, load_steps=30,
                   rod_nelem=40, load_max_cutbacks=8)
    assert run.ok
    # the SNES's tolerance, or the roundoff floor of the residual (stiff axial terms; solver.py)
    tol = max(1e-10 * run.force_scale, run.solver.floor)
    assert run.solver.floor < 1e-8
    assert all(h["residual_norm"] <= tol for h in run.history)
    jumps = [sw for sw in run.solver.switches if sw.get("jump")]
    assert len(jumps) == 1 and jumps[0]["energy_after"] < jumps[0]["energy_before"] - 1.0
    topo = run.last_topology
    assert abs(topo["link"] - turns) < 1e-2
    assert abs(topo["twist"] + topo["writhe"] - topo["link"]) < 1e-9
    assert 0.7 < topo["writhe"] < 1.2
    c = run.summary(converged=True)["contact"]
    assert c["zones"] >= 1 and c["total_force"] > 1.0 and c["active_points"] > 0
    assert 0.0 < c["max_penetration"] < 0.01
    assert run.history[-1]["negative_eigenvalues"] == 0
    assert np.isfinite(run.last_energy)
