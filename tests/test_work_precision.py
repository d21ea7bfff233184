"""tools/work_precision.py --case rollup_contact: the contact path of the work-precision study
(solver runs at fixed penalties, errors against tools/planar_contact_reference.py).

The end-to-end test runs the tool's command line on one coarse mesh at one penalty: 16 quadratic
elements, --penalties 10 (mu = 10 mu0 = 5e7, passed as -contact_penalty), -load_steps 40 (finer
load steps than the case's 10 skip most of the rejected attempts at the first touch: ~15 s instead
of ~27 s on the 2-core box).  Measured there: err_force 2.07e-4 (the penalty law's own deficit at
this mu is 1.85e-4), err_tip 2.55e-5 (d0 / L = 2.53e-5), err_force_law 2.16e-5, err_tip_law
1.05e-6 (the finite-element part).  The bounds are 10x those; the hard-contact errors must also
be the penalty law's (force deficit above half of it, tip error = d0 / L within 10 %): the
reference is the hard contact and the run's mu is the one asked for."""
import csv
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import load_tool

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # the package may not be pip-installed yet
    sys.path.insert(0, str(ROOT))




wp = load_tool("work_precision")
CASE = ROOT / "cases" / "rollup_contact.opts"


@pytest.fixture(scope="module")
def rod():
    return wp.planar_rod(wp.read_case_scene(CASE, []))


def test_default_penalty_is_the_solvers(rod):
    """mu0 = rodsnes.contact.default_penalty(EI, eps, 1 %) = 5 EI / eps^4 for the case, and a
    -contact_penalty given in the options wins."""
    assert wp.default_contact_penalty(CASE, []) == pytest.approx(5 * rod.EI / rod.eps ** 4, rel=1e-12)
    assert wp.default_contact_penalty(CASE, ["-contact_penalty", "123.5"]) == 123.5


def test_planar_rod_reads_the_scene_with_overrides(rod):
    assert (rod.L, rod.EI, rod.EA, rod.GA, rod.eps) == (10.0, 100.0, 1e4, 1e4, 0.1)
    assert rod.M == pytest.approx(1.1 * 2 * math.pi * rod.EI / rod.L, rel=1e-12)
    assert wp.planar_rod(wp.read_case_scene(CASE, ["-rod_EI", "50", "-rod_GJ", "50"])).EI == 50.0
    with pytest.raises(ValueError):
        wp.planar_rod(wp.read_case_scene(CASE, ["-load_end_moment", "1,0,69"]))


def test_reference_cache_round_trip(rod, tmp_path, monkeypatch):
    """Hard contact and penalty law solved once and cached; a second reference reads them back
    (same force and tip, no shooting); a cache that no longer meets its contact condition, or
    belongs to another rod, is solved again."""
    path = tmp_path / "ref.json"
    mu = 5e6
    a = wp.RollupContactReference(rod, str(path))
    h, p = a.hard(), a.penalty(mu)
    assert h.f == pytest.approx(3.2073, abs=1e-4)
    assert h.f - p.f == pytest.approx(h.f * 5.86e-4, rel=0.02)      # the penalty law's deficit
    cached = json.loads(path.read_text())
    assert set(cached["solutions"]) == {"hard", repr(mu)}

    def no_shooting(*args, **kw):
        raise AssertionError("solved again instead of read from the cache")

    with monkeypatch.context() as m:
        m.setattr(a.ref, "solve_end_contact", no_shooting)
        m.setattr(a.ref, "solve_end_contact_penalty", no_shooting)
        b = wp.RollupContactReference(rod, str(path))
        hb, pb = b.hard(), b.penalty(mu)
    assert hb.f == h.f and pb.f == p.f and pb.d0 == p.d0
    assert np.abs(hb.tip - h.tip).max() < 1e-12 and np.abs(pb.tip - p.tip).max() < 1e-12

    cached["solutions"]["hard"]["F"][0] *= 1.01                      # stale: fails |r(L) - r(0)| = 2 eps
    path.write_text(json.dumps(cached))
    c = wp.RollupContactReference(rod, str(path))
    assert c.hard().f == pytest.approx(h.f, rel=1e-10)
    other = wp.planar_reference_module().PlanarRod(**{**vars(rod), "EI": 90.0})
    assert wp.RollupContactReference(other, str(path))._cache["solutions"] == {}


def test_errors_vanish_on_the_reference_itself(rod):
    """The reference's own nodal positions (in the solver's 3-D frame, shifted and turned) give
    zero tip and force errors against the hard contact; the penalty law's shows exactly its
    penalty error."""
    a = wp.RollupContactReference(rod)
    mu = 5e7
    order, nelem = 3, 8
    s = np.linspace(0, rod.L, order * nelem + 1)
    x0, t0 = np.array([1.0, 2.0, 0.5]), np.array([0.6, 0.8, 0.0])
    basis = np.stack([t0, np.cross([0, 0, 1.0], t0)])
    for sol, zero in ((a.hard(), True), (a.penalty(mu), False)):
        P = x0 + sol.state(s)[0] @ basis
        E = a.strain_energy("hard")
        e = a.errors(P, x0, t0, sol.f, E, mu, order, nelem)
        if zero:
            assert e["err_tip"] < 1e-12 and e["err_force"] < 1e-12 and e["err_energy"] < 1e-12
            assert 1e-7 < e["err_l2"] < 1e-4    # cubic interpolation between the nodes: 2.1e-5
        else:
            assert e["err_tip_law"] < 1e-12 and e["err_force_law"] < 1e-12
            assert e["err_tip"] == pytest.approx(sol.d0 / rod.L, rel=0.02)
            assert e["err_force"] == pytest.approx((a.hard().f - sol.f) / a.hard().f, rel=1e-12)


@pytest.mark.slow
def test_rollup_contact_study_end_to_end(rod, tmp_path):
    """The tool's command line: one solver run (16 quadratic elements, mu = 10 mu0), its CSV row,
    the cached reference and the plot."""
    out = tmp_path / "wp"
    rc = wp.main(["--case", "rollup_contact", "--orders", "2", "--nelem", "16", "--penalties", "10",
                  "--extra", "-load_steps 40", "--timeout", "300", "--out", str(out)])
    with open(out / "work_precision.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert rc == 0 and len(rows) == 1
    r = rows[0]
    assert set(wp.CSV_COLUMNS) <= set(r)
    assert r["converged"] == "True" and r["note"] == "", r["note"]
    mu = 10 * wp.default_contact_penalty(CASE, [])
    assert float(r["penalty_factor"]) == 10.0 and float(r["penalty"]) == pytest.approx(mu, rel=1e-12)
    err = {k: float(r[k]) for k in ("err_force", "err_tip", "err_force_law", "err_tip_law", "err_l2")}
    assert all(np.isfinite(v) for v in err.values()), err
    ref = json.loads((out / "reference_rollup_contact.json").read_text())
    hard, law = ref["solutions"]["hard"], ref["solutions"][repr(float(r["penalty"]))]
    f_hard, f_law = math.hypot(*hard["F"]), math.hypot(*law["F"])
    assert 0.5 * (f_hard - f_law) / f_hard < err["err_force"] < 2.1e-3     # 2.07e-4 (law: 1.85e-4)
    assert err["err_tip"] == pytest.approx(law["d0"] / rod.L, rel=0.1)     # 2.55e-5 (d0 / L 2.53e-5)
    assert err["err_tip"] < 2.5e-4
    assert err["err_force_law"] < 2.2e-4                                  # 2.16e-5
    assert err["err_tip_law"] < 1.1e-5                                    # 1.05e-6
    assert int(r["newton_iterations"]) > 0 and 0 < float(r["step_time_s"]) <= float(r["wall_time_s"])
    assert (out / "work_precision.png").stat().st_size > 10_000
    rates = json.loads((out / "rates.json").read_text())
    assert "penalty_slope_err_force" in rates


def test_rollup_study_reports_the_estimate_beside_the_true_error(tmp_path):
    """The tool's command line on the roll-up (2 quadratic meshes, ~3 s): each CSV row carries
    the solver's estimate (summary.json error_estimate, / L) beside the true tip and max centreline
    errors on the same sampling, within a factor 3 of them (measured 0.99 .. 1.00), and the plot
    draws it; a CSV without the estimate columns (an older study) still plots."""
    out = tmp_path / "wp"
    rc = wp.main(["--case", "rollup", "--orders", "2", "--nelem", "4,8", "--timeout", "120",
                  "--out", str(out)])
    assert rc == 0
    rows = wp.read_csv(out / "work_precision.csv")
    assert len(rows) == 2
    for r in rows:
        assert r["converged"] and r["est_converged"] is True, r["note"]
        for est, err in (("est_tip", "err_tip"), ("est_centreline", "err_max")):
            assert 1 / 3 < r[est] / r[err] < 3, (est, r[est], r[err])
        assert r["err_l2"] < r["err_max"]            # RMS below the maximum
    x, y = wp.estimate_series(rows, "dofs", "err_max")
    assert len(x) == 2 and y == sorted(y, reverse=True)
    assert wp.estimate_series(rows, "dofs", "err_energy") == ([], [])
    old = [{k: v for k, v in r.items() if not k.startswith("est_")} for r in rows]
    wp.write_csv(old, tmp_path / "old.csv")
    assert all(r["est_converged"] is not True for r in wp.read_csv(tmp_path / "old.csv"))
    assert wp.main(["--case", "rollup", "--from-csv", str(tmp_path / "old.csv"),
                    "--out", str(tmp_path / "replot")]) == 0
    assert (tmp_path / "replot" / "work_precision.png").stat().st_size > 10_000


def test_estimate_columns_of_a_summary():
    est = {"tip": 2e-4, "centreline": 4e-4, "converged": False, "units": "length"}
    assert wp.estimate_columns(est, 2.0) == {"est_converged": False, "est_tip": 1e-4,
                                             "est_centreline": 2e-4}
    assert wp.estimate_columns({"tip": None, "centreline": 1.0, "converged": True}, 1.0) == {
        "est_converged": True, "est_centreline": 1.0}
    assert wp.estimate_columns(None, 1.0) == {}
