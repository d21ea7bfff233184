"""tools/bench_scaling.py: its -log_view parsing and per-iteration split, on a real 4-element run
(cases/mattiasson.opts, started through the tool's child mode, serial) and on a synthetic log."""
import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tools"))
import bench_scaling as bs  # noqa: E402


@pytest.fixture(scope="module")
def mattiasson_run(tmp_path_factory):
    """A 4-element mattiasson run with -log_view: (parsed log, summary.json)."""
    d = tmp_path_factory.mktemp("bench_scaling")
    logfile = str(d / "log_view.txt")
    # the case's own 5 load steps (the benchmark's -load_steps 2 overridden: the last one counts)
    cmd = bs.command("cantilever", "-", 4, 1, str(d / "run"), logfile, extra=("-load_steps", "5"))
    subprocess.run(cmd, check=True, env=bs.run_env(), cwd=ROOT, timeout=120,
                   stdout=subprocess.DEVNULL)
    with open(logfile) as fh:
        log = bs.parse_log_view(fh.read())
    with open(d / "run" / "summary.json") as fh:
        summary = json.load(fh)
    return log, summary


def test_counts_match_the_run(mattiasson_run):
    log, s = mattiasson_run
    assert s["converged"] and s["load_steps"] == 5 and log["ranks"] == 1
    ev = log["events"]
    p = bs.iteration_parts(log)
    its = sum(step["newton_iterations"] for step in s["steps"])
    # every Newton iteration: one Jacobian, one numeric LU (the chain's, linear.use_chain_lu),
    # one solve; no failed tries here; plus the factorisation of the linear solver's check
    # before the run (cli.py) and the LUs of the node graph that measure the pattern's fill
    # (linear.pattern_fill, once per ordering: one pattern, AMD and the natural order of
    # linear.chain_ordering), PETSc's
    assert p["iterations"] == ev["SNESJacobianEval"]["count"] == its == s["newton_iterations"]
    assert ev["ChainFactor"]["count"] == ev["ChainSolve"]["count"] == its
    assert p["factorisations"] == its + 3 == its + ev["MatLUFactorNum"]["count"]
    assert p["snes_solves"] == s["load_steps"] == ev["SNESSolve"]["count"]
    # basic line search: one residual per iteration, plus the first of each solve
    assert p["residual_evals"] == its + s["load_steps"]
    # the elastic kernel runs once per residual and twice per Jacobian (child mode's event):
    # the tangents added into the matrix as they are made, and those of the element at the
    # clamp, which goes in through the matrix's insertion (its Dirichlet rows masked).  The
    # stability count of the path's end (a Newton path with an energy counts its end,
    # Run._execute) runs in the PathEnd stage, which the parser leaves out
    # and once per step written (the start and every load step: result.h5's force_n from
    # the elements' internal forces, RodProblem.force_resultants)
    assert ev["ElasticKernel"]["count"] == p["residual_evals"] + 2 * its + s["load_steps"] + 1
    # the in-plane matrix made and its chain LU planned in the solver's set-up, before the
    # path, in a stage of its own (tests/test_setup.py: the path makes neither again)
    assert 0.0 < p["setup"] == log["stages"]["SetUp"]


def test_parts_positive_and_nested(mattiasson_run):
    log, _ = mattiasson_run
    p = bs.iteration_parts(log)
    for key in ("total", "residual", "jacobian", "factor", "solve", "elastic"):
        assert p[key] > 0.0, key
    assert p["contact"] == 0.0 and p["rod_events"] == 1
    # disjoint parts of SNESSolve cannot add up to more than it; the elastic kernel runs
    # inside the residual and Jacobian evaluations
    assert p["residual"] + p["jacobian"] + p["factor"] + p["solve"] <= p["total"] * (1 + 1e-9)
    assert p["elastic"] <= p["residual"] + p["jacobian"]
    assert p["resjac_per_factor"] == pytest.approx((p["residual"] + p["jacobian"]) / p["factor"])


SYNTHETIC = """\
.venv/bin/rodsnes on a  named vm with 2 processors, by Unknown Thu Nov 26 01:02:35 2026

Summary of Stages:   ----- Time ------  ----- Flop ------  --- Messages ---  -- Message Lengths --  -- Reductions --
                        Avg     %Total     Avg     %Total    Count   %Total     Avg         %Total    Count   %Total
 0:      Main Stage: 8.0000e-01  80.0%  1.6581e+07  65.3%  0.000e+00   0.0%  0.000e+00        0.0%  0.000e+00   0.0%
 1:      Relaxation: 1.0000e-01  10.0%  0.0000e+00   0.0%  0.000e+00   0.0%  0.000e+00        0.0%  0.000e+00   0.0%
 2:           SetUp: 2.5000e-02   2.5%  0.0000e+00   0.0%  0.000e+00   0.0%  0.000e+00        0.0%  9.000e+00   5.3%

------------------------------------------------------------------------------------------------------------------------
Event                Count      Time (sec)     Flop                              --- Global ---  --- Stage ----  Total
                   Max Ratio  Max     Ratio   Max  Ratio  Mess   AvgLen  Reduct  %T %F %M %L %R  %T %F %M %L %R Mflop/s
------------------------------------------------------------------------------------------------------------------------

--- Event Stage 0: Main Stage

MatSolve               4 1.0 2.0000e-02 1.0 2.54e+06 1.0 0.0e+00 0.0e+00 0.0e+00  1 99  0  0  0   1 99  0  0  0   732
MatLUFactorNum         4 1.0 8.0000e-02 1.1 3.89e+03 1.0 0.0e+00 0.0e+00 0.0e+00  2  0  0  0  0   2  0  0  0  0     0
SNESSolve              1 1.0 4.0000e-01 1.0 2.57e+06 1.0 0.0e+00 0.0e+00 0.0e+00 48 100  0  0  0  48 100  0  0  0    10
SNESFunctionEval       5 1.0 5.0000e-02 1.0 0.00e+00 0.0 0.0e+00 0.0e+00 0.0e+00  4  0  0  0  0   4  0  0  0  0     0
SNESJacobianEval       4 1.0 1.0000e-01 1.0 0.00e+00 0.0 0.0e+00 0.0e+00 0.0e+00 40  0  0  0  0  40  0  0  0  0     0
SNESLineSearch         4 1.0 6.0000e-02 1.0 1.95e+04 1.0 0.0e+00 0.0e+00 0.0e+00  3  1  0  0  0   3  1  0  0  0     1
ContactSearch         10 1.0 1.0000e-02 1.0 0.00e+00 0.0 0.0e+00 0.0e+00 0.0e+00  0  0  0  0  0   0  0  0  0  0     0

--- Event Stage 1: Relaxation

SNESSolve              1 1.0 4.0000e-01 1.0 2.57e+06 1.0 0.0e+00 0.0e+00 0.0e+00 48 100  0  0  0  48 100  0  0  0    10
SNESJacobianEval       4 1.0 1.0000e-01 1.0 0.00e+00 0.0 0.0e+00 0.0e+00 0.0e+00 40  0  0  0  0  40  0  0  0  0     0
ContactEval            8 1.0 3.0000e-02 1.0 0.00e+00 0.0 0.0e+00 0.0e+00 0.0e+00  0  0  0  0  0   0  0  0  0  0     0

--- Event Stage 2: SetUp

MatAssemblyEnd         1 1.0 2.8093e-04 1.3 0.00e+00 0.0 0.0e+00 0.0e+00 7.0e+00  0  0  0  0  4   0  0  0  0 78     0
MatLUFactorNum         1 1.0 9.0000e-03 1.0 3.89e+03 1.0 0.0e+00 0.0e+00 0.0e+00  2  0  0  0  0   2  0  0  0  0     0
------------------------------------------------------------------------------------------------------------------------

Object Type          Creations   Destructions. Reports information only for process 0.
              Vector    28             28
"""


def test_parse_synthetic_log():
    log = bs.parse_log_view(SYNTHETIC)
    ev = log["events"]
    assert log["ranks"] == 2
    assert ev["SNESJacobianEval"] == {"count": 8, "time": pytest.approx(0.2)}   # both stages
    assert ev["SNESSolve"]["count"] == 2 and "Vector" not in ev
    p = bs.iteration_parts(log)
    assert p["iterations"] == 8
    assert p["total"] == pytest.approx(0.8 / 8)
    assert p["factor"] == pytest.approx(0.08 / 8)
    assert p["linesearch"] == pytest.approx((0.06 - 4 * 0.05 / 5) / 8)
    assert p["contact"] == pytest.approx(0.04 / 8)
    assert p["contact_per_factor"] == pytest.approx(0.5)
    # the solver's set-up (profiling.SET_UP) is work done once: its stage's time, its events
    # in no iteration's part
    assert log["stages"] == {"Main Stage": 0.8, "Relaxation": 0.1, "SetUp": 0.025}
    assert p["setup"] == pytest.approx(0.025)
    assert ev["MatLUFactorNum"]["count"] == 4 and "MatAssemblyEnd" not in ev


def test_parse_rejects_other_text():
    with pytest.raises(ValueError):
        bs.parse_log_view("no PETSc here\n")
    with pytest.raises(ValueError):       # a log without a Newton solve
        bs.parse_log_view(SYNTHETIC.replace("SNESSolve", "KSPSolve"))


def test_lu_with_much_fill_hands_over_to_mumps():
    """solve/linear.py: PETSc's LU factors the rod's Jacobian; where contact couples much of
    the rod (the bench coil, fill 2.95 at 200 elements with AMD) the pattern's fill exceeds
    FILL_MUMPS and MUMPS factors from the first Newton step on, ordered by AMD; a chain
    (Mattiasson, no fill) stays with rodsnes' own LU of the chain, and with PETSc's LU under the
    user's ordering; a package the user chose is never changed."""
    from conftest import run_case
    from petsc4py import PETSc
    from rodsnes.solve.linear import FILL_MUMPS, ORDERING, pattern_fill
    coil = run_case("bench_coil", rod_nelem=200, rod_length=4.0, load_path="newton",
                    rod_error_estimate="off")
    pc = coil.solver.snes.getKSP().getPC()
    assert coil.ok and pc.getFactorSolverType() == "mumps" and not coil.solver.lu.auto
    # MUMPS ordered by minimum degree, which fills the coil's pattern less than nested
    # dissection (INFOG(7) = 0: AMD), by rodsnes' default, gone with the run
    assert pattern_fill(coil.problem, "amd") < pattern_fill(coil.problem, "nd")
    assert pc.getFactorMatrix().getMumpsInfog(7) == 0
    assert not PETSc.Options().hasName("mat_mumps_icntl_7")
    chain = run_case("mattiasson", rod_nelem=200, load_path="newton", rod_error_estimate="off",
                     rod_planar="off")
    pc = chain.solver.snes.getKSP().getPC()
    # no fill at all: rodsnes' own LU of the chain (linear.use_chain_lu: its plan refuses
    # fill), still rodsnes' choice; the default ordering left the options database with the
    # run (linear.take_back_defaults)
    assert pattern_fill(chain.problem, ORDERING) == 1.0 < FILL_MUMPS and chain.solver.lu.auto
    assert pc.getType() == "python" and type(pc.getPythonContext()).__name__ == "ChainPC"
    assert not PETSc.Options().hasName("pc_factor_mat_ordering_type")
    # with the user's AMD ordering PETSc's LU, whose fill is as predicted
    chain = run_case("mattiasson", rod_nelem=200, load_path="newton", rod_error_estimate="off",
                     rod_planar="off", pc_factor_mat_ordering_type=ORDERING)
    pc = chain.solver.snes.getKSP().getPC()
    assert pc.getFactorSolverType() == "petsc" and chain.solver.lu.auto
    fill = pc.getFactorMatrix().getInfo()["fill_ratio_needed"]
    assert fill == pytest.approx(pattern_fill(chain.problem, "amd"), rel=1e-12)
    assert fill != pytest.approx(pattern_fill(chain.problem, "nd"), rel=1e-3)
    chosen = run_case("bench_coil", rod_nelem=200, rod_length=4.0, load_path="newton",
                      rod_error_estimate="off", pc_factor_mat_solver_type="petsc")
    assert chosen.solver.snes.getKSP().getPC().getFactorSolverType() == "petsc"


@pytest.mark.mpi
def test_several_ranks_hand_a_filled_pattern_to_mumps(monkeypatch):
    """On several ranks the Newton steps of a chain solve by static condensation (every rank
    factors its own stretch by PETSc's LU: solve/schur.py, tests/test_schur.py), whose factors
    petsc4py does not reach: the fill is that of the Jacobian's node graph (linear.pattern_fill,
    equal to the serial LU's: 3.355 for the coil at 1000 elements), and above FILL_MUMPS the
    Newton steps factor by MUMPS: each rank its own stretch with the Schur complement where the
    stretches meet (schur.RankSchur with package mumps), over the ranks on a short rod."""
    from conftest import run_case
    from petsc4py import PETSc
    from rodsnes.solve.linear import FILL_MUMPS, pattern_fill
    coil = run_case("bench_coil", rod_nelem=200, rod_length=4.0, load_path="newton",
                    rod_error_estimate="off")
    pc = coil.solver.snes.getKSP().getPC()
    assert coil.ok and pattern_fill(coil.problem) > FILL_MUMPS
    size = coil.comm.getSize()
    if size > 1:
        # 601 nodes: too short for the condensation (schur.MIN_NODES_PER_RANK_MUMPS)
        assert pc.getType() == "lu" and pc.getFactorSolverType() == "mumps"
        # long enough: every rank factors its stretch by MUMPS, the ranks share the Schur
        # complement; the run is the serial run's
        n = 150 * size
        kw = dict(rod_nelem=n, rod_length=0.02 * n, load_path="newton", rod_error_estimate="off")
        long = run_case("bench_coil", **kw)
        ser = run_case("bench_coil", comm=PETSc.COMM_SELF, **kw,
                       outdir=long.outdir + f"_s{PETSc.COMM_WORLD.getRank()}")
        ctx = long.solver.snes.getKSP().getPC().getPythonContext()
        assert long.ok and ser.ok
        assert ctx.package == "mumps" and ctx.setups["schur"] > 0 and ctx.setups["whole"] == 0
        # linear.py's MUMPS defaults reach the stretches' factors: room for the fill, AMD
        F = ctx.kept["ksp"].getPC().getFactorMatrix()
        assert F.getMumpsIcntl(14) == 100 and F.getMumpsIcntl(7) == 0
        sl, ss = long.summary(converged=True), ser.summary(converged=True)
        assert sl["newton_iterations"] == ss["newton_iterations"]
        assert sl["energy"] == pytest.approx(ss["energy"], rel=1e-9)
        # a separator too large to condense: MUMPS over the ranks, ordered by AMD as serially
        # (INFOG(7) = 0)
        from rodsnes.solve import schur
        monkeypatch.setattr(schur, "SCHUR_MAX", 0)
        over = run_case("bench_coil", **kw)
        ctx = over.solver.snes.getKSP().getPC().getPythonContext()
        assert over.ok and ctx.mode == "whole" and ctx.setups["schur"] == 0
        assert ctx.whole.getPC().getFactorMatrix().getMumpsInfog(7) == 0
        assert over.summary(converged=True)["energy"] == pytest.approx(ss["energy"], rel=1e-9)
    chain = run_case("mattiasson", rod_nelem=200, load_path="newton", rod_error_estimate="off",
                     rod_planar="off")
    pc = chain.solver.snes.getKSP().getPC()
    assert pattern_fill(chain.problem) < FILL_MUMPS
    if chain.comm.getSize() > 1:
        # 601 nodes: too short for the condensation to pay (schur.MIN_NODES_PER_RANK), the
        # whole matrix on every rank
        assert pc.getType() == "redundant"
    else:                   # one rank: rodsnes' own LU of the chain (linear.use_chain_lu)
        assert pc.getType() == "python" and type(pc.getPythonContext()).__name__ == "ChainPC"


def test_fastest_keeps_the_least_time_and_the_spread():
    totals = iter([0.050, 0.031, 0.042])
    calls = []

    def run():
        calls.append(1)
        t = next(totals)
        return {"status": "ok", "total": t, "factor": t / 10}

    row = bs.fastest(run, 3)
    assert len(calls) == 3
    assert row["total"] == pytest.approx(0.031) and row["factor"] == pytest.approx(0.0031)
    assert row["repeats"] == "50,31,42"
    # a failed run ends the repeats and is what the case reports
    seq = iter([{"status": "ok", "total": 0.02}, {"status": "failed (exit 1)"}])
    assert bs.fastest(lambda: next(seq), 3)["status"] == "failed (exit 1)"
    # one run: its own row
    assert bs.fastest(lambda: {"status": "capped", "total": 0.5}, 1)["repeats"] == "500"


def test_fastest_edge_cases():
    """fastest: a run with no finite time (status ok) ends the repeats and is the case's row
    (no repeats column); a repeat count below 1 runs once; ties keep the first run; the kept
    row is a copy (the run's own dict is not given the repeats column)."""
    import math
    import os
    import sys
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tools"))
    import bench_scaling as bs
    seq = iter([{"status": "ok", "total": 0.02}, {"status": "ok", "total": math.nan}])
    row = bs.fastest(lambda: next(seq), 3)
    assert math.isnan(row["total"]) and "repeats" not in row
    calls = []
    bs.fastest(lambda: calls.append(1) or {"status": "ok", "total": 0.01}, 0)
    assert len(calls) == 1
    first, second = {"status": "ok", "total": 0.01, "k": 1}, {"status": "ok", "total": 0.01, "k": 2}
    seq = iter([first, second])
    row = bs.fastest(lambda: next(seq), 2)
    assert row["k"] == 1 and row["repeats"] == "10,10" and "repeats" not in first
    # not converged and capped runs are timed like ok ones
    seq = iter([{"status": "not converged", "total": 0.03}, {"status": "capped", "total": 0.02}])
    assert bs.fastest(lambda: next(seq), 2)["status"] == "capped"


def test_interleaved_rounds_and_a_failure_stops_more_ranks():
    """interleaved: the rounds alternate between the rank counts (1, 2, 1, 2, ...), each keeps
    its fastest run with its spread; a failed run is its key's row and stops the keys after it
    (no row: what did not fit on fewer ranks), not those before it."""
    order = []

    def runner(key, totals):
        it = iter(totals)

        def run():
            order.append(key)
            t = next(it)
            return {"status": "ok", "total": t} if isinstance(t, float) else {"status": t}
        return run

    out = bs.interleaved({1: runner(1, [0.03, 0.02, 0.04]), 2: runner(2, [0.02, 0.03, 0.01])}, 3)
    assert order == [1, 2, 1, 2, 1, 2]
    assert out[1]["total"] == 0.02 and out[1]["repeats"] == "30,20,40"
    assert out[2]["total"] == 0.01
    order.clear()
    out = bs.interleaved({1: runner(1, ["timeout"]), 2: runner(2, [0.01])}, 3)
    assert order == [1] and out == {1: {"status": "timeout"}}
    # a larger rank count failing does not cut the smaller one's repeats short
    order.clear()
    out = bs.interleaved({1: runner(1, [0.03, 0.02, 0.02]), 2: runner(2, ["timeout"])}, 3)
    assert order == [1, 2, 1, 1]
    assert out[2] == {"status": "timeout"} and out[1]["repeats"] == "30,20,20"
    order.clear()
    out = bs.interleaved({1: runner(1, [0.03, 0.02, 0.02]), 2: runner(2, [0.02, "failed (exit 1)"])}, 3)
    assert order == [1, 2, 1, 2, 1]
    assert out[2]["status"] == "failed (exit 1)" and out[1]["repeats"] == "30,20,20"
    # the smaller failing in a later round: the larger ones stop, with no row (as when it
    # failed at once: skipped by the caller)
    order.clear()
    out = bs.interleaved({1: runner(1, [0.03, "failed (exit 1)"]), 2: runner(2, [0.02, 0.01]),
                          4: runner(4, [0.01, 0.01])}, 3)
    assert order == [1, 2, 4, 1]
    assert out == {1: {"status": "failed (exit 1)"}}


def test_ranks_bound_to_cores_as_plain_mpirun_binds_them():
    """Up to the machine's cores each rank is bound to a core (what `mpirun -n 2` does by
    default); beyond them unbound and oversubscribed; one rank without mpirun."""
    def cmd(ranks, cores):
        return bs.command("cantilever", "-", 10, ranks, "d", "log", cores=cores)
    two = cmd(2, 2)
    assert two[:5] == ["mpirun", "-n", "2", "--bind-to", "core"] and "--oversubscribe" not in two
    three = cmd(3, 2)
    assert three[:6] == ["mpirun", "-n", "3", "--bind-to", "none", "--oversubscribe"]
    assert cmd(1, 2)[0] == sys.executable
