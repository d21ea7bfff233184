"""Scaling benchmark: time per Newton iteration, split into its parts, against the number of
cubic elements N, for a scene without contact and one with contact along the whole rod, on 1
and 2 ranks.

    .venv/bin/python tools/bench_scaling.py                    # 1e2 ... 1e5, ranks 1 and 2
    .venv/bin/python tools/bench_scaling.py --quick            # 1e2, 1e3, 3 iterations each:
                                                               # checks that the tool runs
    .venv/bin/python tools/bench_scaling.py --sizes 100,1000,10000 --ranks 1 --laws projection
    .venv/bin/python tools/bench_scaling.py --publish          # also docs/img/bench_scaling.png
                                                               # and docs/bench_scaling.md

Scenes (one rodsnes subprocess per scene, N, ranks, contact law):
  cantilever  cases/mattiasson.opts (the elastica under a tip load, lambda = 10, L = 1) with
              -rod_nelem N -load_steps 2: no contact.
  coil        cases/bench_coil.opts with -rod_nelem N -rod_length 0.02 N: a tight coil (radius
              3 r), both ends clamped, adjacent turns touching along their whole length (92-98 %
              of the elements in contact at N = 100), the element length kept at 2 r;
              -contact_model projection (the default law) and potential (the plectoneme's).
              Heavy: every element has candidates on 2-3 turns either side (the turns lie 2 r
              apart); measured at N = 1000 (26 Nov 2026): factorisation 1.2-1.5 s, contact 1.8 s
              (potential) and 20 s (projection) per iteration, peak memory 2.6 and 9.6 GB.
              With the potential's chunked passes and its pattern of pairs within reach: 0.38
              GB at N = 1000, 2.6 GB at N = 1e4 (MUMPS' factors most of it), so 1e5 needs ~26
              GB.  From N = 1e4 the scene needs a softer stretch (--extra "-rod_EA 3 -rod_GA 3":
              scene.py refuses the default one, whose residual roundoff exceeds 0.1 of EI/L^2),
              and --skip-topology saves the O(N^2) writhe (2 x 230 s at N = 1e4).

Every case runs --repeat times (3 by default) and the fastest run is kept, with all the runs'
times per iteration in the CSV's repeats column: on the shared 2-core VM the same case varies by
10-40 % from run to run (the planar cantilever at N = 1e4 took 47-69 ms per iteration serially
and 31-51 ms on 2 ranks over five single runs of 26 Nov 2026), and the least time is the one
least disturbed.  The rank counts of one case take turns (1, 2, 1, 2, ... ranks: interleaved),
so that the speed-up compares runs made in the same minutes.  The ranks of a run are bound
to cores as a plain ``mpirun -n 2`` binds them (``command``).  With --reuse the files of the
last run of each case are read.

Each run writes PETSc's -log_view (ASCII) and rodsnes' summary.json; the parts of an iteration
are the events of -log_view divided by the Newton iterations (SNESJacobianEval's count: every
iteration, those of failed and cut-back solves included), times the maximum over the ranks:

  residual    SNESFunctionEval          factor      MatLUFactorNum (+ MatCholFctrNum, ChainFactor)
  jacobian    SNESJacobianEval          factor_sym  MatLUFactorSym (+ MatCholFctrSym)
  solve       MatSolve (+ ChainSolve)   linesearch  SNESLineSearch without its residual
  total       SNESSolve                 other       total - the rest (updates, pattern checks)

and, from rodsnes' own log events (rodsnes/profiling.py; inside the SNES events above):
  elastic         ElasticKernel (element residuals and tangents of the rod)
  contact_search  ContactSearch (candidate pairs)   contact_eval  ContactEval + ContactTangent
  contact_halo    ContactHalo (PetscSF)             contact_assemble  ContactAssemble
  contact         contact_search + contact_eval + contact_halo (what the contact target counts)
and, once per run and not in any iteration's part, ``setup``: the time of rodsnes' SetUp
stage (profiling.SET_UP, the average over the ranks; the solver's set-up before the path: the
matrices of the present pattern made, their LU chosen and planned), which the table shows as
"set-up (once)".
Where rodsnes does not log these events itself, the run is started through this tool's child
mode (``--child``), which wraps the methods that do that work with the same events before it
calls rodsnes.cli.main (a method already decorated with rodsnes.profiling.logged is left alone);
it also leaves rod.xdmf to the end of the run (child(): rank 0's rewrites between load steps
would be counted in the other ranks' next residual).

Runs that cannot fit are not started: a case whose run at a smaller N timed out or failed, or
whose time or memory (the last size's, scaled by (N / N_before)^1.2, memory times the ranks)
would exceed --timeout or 85 % of the available memory; a 2-rank run whose 1-rank run at the
same N did not fit.  A run that did not converge (or was capped by --max-its) still times its
iterations, and the table says so.

Outputs in --out (default tools/out/bench_scaling/): bench_scaling.csv (one row per scene, law,
N, ranks), bench_scaling.png (log-log, per-iteration parts against N, an N^1 guide),
bench_scaling.md (machine, table, targets), and the runs' logs in runs/.  The targets of the
issue are reported, never asserted (PASS / MISS / n/a).  Timings on a shared machine are noisy.
"""
import argparse
import csv
import functools
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)
from rodsnes.profiling import PATH_END, SET_UP  # noqa: E402  (no PETSc import: stage names)

DEFAULT_OUT = os.path.join(ROOT, "tools", "out", "bench_scaling")
DOC_PNG = os.path.join(ROOT, "docs", "img", "bench_scaling.png")
DOC_MD = os.path.join(ROOT, "docs", "bench_scaling.md")
COIL_ELEMENT = 0.02         # element length of the coil scene (2 x rod radius)
ROD_EVENTS = ("ElasticKernel", "ContactSearch", "ContactEval", "ContactTangent", "ContactHalo",
              "ContactAssemble")

# -- the scenes ---------------------------------------------------------------------------


def scene_options(scene, n, law=None):
    """rodsnes options of ``scene`` at N = n elements (law: the coil's -contact_model)."""
    if scene == "cantilever":
        return ["-options_file", os.path.join(ROOT, "cases", "mattiasson.opts"),
                "-rod_nelem", str(n), "-load_steps", "2", "-load_path", "newton",
                "-rod_error_estimate", "off"]
    if scene == "coil":
        return ["-options_file", os.path.join(ROOT, "cases", "bench_coil.opts"),
                "-rod_nelem", str(n), "-rod_length", repr(COIL_ELEMENT * n),
                "-contact_model", law, "-load_path", "newton", "-rod_error_estimate", "off"]
    raise ValueError(f"unknown scene {scene!r}")


def cases(scenes, laws):
    """(scene, law) pairs; the cantilever has no contact law ('-')."""
    out = []
    for s in scenes:
        out += [(s, "-")] if s == "cantilever" else [(s, law) for law in laws]
    return out


# -- -log_view ----------------------------------------------------------------------------

_EVENT_LINE = re.compile(r"^(\S+)\s+(\d+)\s+\S+\s+([0-9.]+e[+-]?\d+)\s")


_STAGE_LINE = re.compile(r"^\s*\d+:\s+(\S.*?):\s+([0-9.]+e[+-]?\d+)\s")
ONCE = (SET_UP, PATH_END)       # rodsnes' stages of the work done once, no iteration's


def parse_log_view(text):
    """PETSc's ASCII -log_view -> {"ranks": int, "events": {name: {"count", "time"}},
    "stages": {name: seconds}}: per event the count and the time (seconds, maximum over
    ranks), summed over the stages but rodsnes' SetUp and PathEnd (ONCE, profiling.SET_UP and
    PATH_END: the work done once before and after the path, no iteration's: the solver's
    set-up, a Newton path's stability count of its end); per stage its time (PETSc's "Summary
    of Stages": the average over the ranks)."""
    m = re.search(r"with (\d+) processors?", text)
    if m is None:
        raise ValueError("not a PETSc -log_view: no 'with N processor(s)' line")
    events, stages, inside, summary = {}, {}, False, False
    for line in text.splitlines():
        if line.startswith("Summary of Stages"):
            summary = True
            continue
        if summary:
            st = _STAGE_LINE.match(line)
            if st:
                stages[st.group(1)] = float(st.group(2))
            elif stages and not line.strip():
                summary = False
            continue
        if line.startswith("--- Event Stage"):
            inside = not any(line.rstrip().endswith(": " + name) for name in ONCE)
            continue
        if inside and (line.startswith("----") or line.startswith("====")):
            inside = False
            continue
        if not inside:
            continue
        e = _EVENT_LINE.match(line)
        if e:
            rec = events.setdefault(e.group(1), {"count": 0, "time": 0.0})
            rec["count"] += int(e.group(2))
            rec["time"] += float(e.group(3))
    if "SNESSolve" not in events:
        raise ValueError("-log_view without a SNESSolve event: no Newton solve was logged")
    return {"ranks": int(m.group(1)), "events": events, "stages": stages}


def _t(ev, name):
    return ev.get(name, {}).get("time", 0.0)


def _n(ev, name):
    return ev.get(name, {}).get("count", 0)


def iteration_parts(log):
    """Seconds per Newton iteration of each part (module docstring) from a parsed -log_view."""
    ev = log["events"]
    its = _n(ev, "SNESJacobianEval")
    if its == 0:
        raise ValueError("no SNESJacobianEval in the log: no Newton iteration")
    f_mean = _t(ev, "SNESFunctionEval") / max(_n(ev, "SNESFunctionEval"), 1)
    ls = max(_t(ev, "SNESLineSearch") - _n(ev, "SNESLineSearch") * f_mean, 0.0)
    p = {"iterations": its,
         "residual_evals": _n(ev, "SNESFunctionEval"),
         "snes_solves": _n(ev, "SNESSolve"),
         "factorisations": (_n(ev, "MatLUFactorNum") + _n(ev, "MatCholFctrNum")
                            + _n(ev, "ChainFactor")),
         "analyses": _n(ev, "MatLUFactorSym") + _n(ev, "MatCholFctrSym"),
         "total": _t(ev, "SNESSolve") / its,
         "residual": _t(ev, "SNESFunctionEval") / its,
         "jacobian": _t(ev, "SNESJacobianEval") / its,
         "factor": (_t(ev, "MatLUFactorNum") + _t(ev, "MatCholFctrNum")
                    + _t(ev, "ChainFactor")) / its,
         "factor_sym": (_t(ev, "MatLUFactorSym") + _t(ev, "MatCholFctrSym")) / its,
         "solve": (_t(ev, "MatSolve") + _t(ev, "ChainSolve")) / its,
         "linesearch": ls / its,
         "elastic": _t(ev, "ElasticKernel") / its,
         "contact_search": _t(ev, "ContactSearch") / its,
         "contact_eval": (_t(ev, "ContactEval") + _t(ev, "ContactTangent")) / its,
         "contact_halo": _t(ev, "ContactHalo") / its,
         "contact_assemble": _t(ev, "ContactAssemble") / its,
         "rod_events": int(any(name in ev for name in ROD_EVENTS)),
         # once, not per iteration: the solver's set-up before the path (its stage's time)
         "setup": log.get("stages", {}).get(SET_UP, 0.0)}
    p["contact"] = p["contact_search"] + p["contact_eval"] + p["contact_halo"]
    pcsetup = _t(ev, "PCSetUp") / its
    ksp = _t(ev, "KSPSolve") / its
    p["other"] = max(p["total"] - p["residual"] - p["jacobian"] - pcsetup - ksp - p["linesearch"], 0.0)
    p["resjac_per_factor"] = (p["residual"] + p["jacobian"]) / p["factor"] if p["factor"] else math.nan
    p["contact_per_factor"] = p["contact"] / p["factor"] if p["factor"] else math.nan
    return p


# -- child mode: rodsnes with its work logged as events ----------------------------------

# (module, class, method, event): the first method found of each event's list is wrapped
_WRAP = (("rodsnes.model.elastic", "ElasticRod", "element_terms", "ElasticKernel"),
         ("rodsnes.contact.projection.term", "ContactTerm", "search_pairs", "ContactSearch"),
         ("rodsnes.contact.projection.term", "ContactTerm", "_pairs", "ContactSearch"),
         ("rodsnes.contact.projection.term", "ContactTerm", "_fetch", "ContactHalo"),
         ("rodsnes.contact.projection.term", "ContactTerm", "_send_back", "ContactHalo"),
         ("rodsnes.contact.projection.term", "ContactTerm", "_add_blocks", "ContactAssemble"),
         ("rodsnes.contact.projection.projection", "ContactKernel", "evaluate", "ContactEval"),
         ("rodsnes.contact.projection.projection", "ContactKernel", "add_tangent", "ContactTangent"),
         ("rodsnes.contact.projection.potential", "PotentialKernel", "evaluate", "ContactEval"),
         ("rodsnes.contact.projection.potential", "PotentialKernel", "add_tangent", "ContactTangent"))


def instrument():
    """Wrap the methods of _WRAP that exist (defined in the class itself, not yet logged) with
    rodsnes.profiling's events.  Returns the list of 'Class.method -> Event' wrapped."""
    import importlib
    from rodsnes import profiling
    done = []
    for mod, cls, meth, name in _WRAP:
        try:
            klass = getattr(importlib.import_module(mod), cls)
        except (ImportError, AttributeError):
            continue
        fun = klass.__dict__.get(meth)
        if fun is None or not callable(fun) or getattr(fun, "rod_event", None):
            continue
        setattr(klass, meth, profiling.logged(name)(fun))
        done.append(f"{cls}.{meth} -> {name}")
    return done


def child(argv, topology=True):
    """rodsnes.cli.main(argv) with the work of _WRAP logged (PETSc initialised first, with
    argv, so that -log_view is seen).  Without ``topology`` (--skip-topology) the run reports
    no link, twist and writhe (RodProblem.topology returns None, as for a rod without them):
    the writhe's Gauss integral is O(N^2), outside the Newton iterations, and took 2 x 230 s
    of a coil run at N = 1e4 (2 x 2.3 s at N = 1e3)."""
    import petsc4py
    petsc4py.init(argv)
    instrument()
    # the ParaView view (rod.xdmf) is written once, at the end: rank 0 rewrites it between load
    # steps (up to 2 % of a run, results.XDMF_SHARE) while the other ranks wait in the next
    # step's first residual, which the per-iteration events would count (the cantilever at
    # 10^4 on 2 ranks: 67.6 ms per iteration with the rewrites, 42.5 ms without)
    from rodsnes.io import results
    results.XDMF_SHARE = -1.0
    if not topology:
        from rodsnes.model.problem import RodProblem
        RodProblem.topology = lambda self: None
    from rodsnes import cli
    return cli.main(argv)


# -- runs ---------------------------------------------------------------------------------

def run_env():
    env = dict(os.environ)
    env.update(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_btl="self,vader", OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
               PYTHONPATH=ROOT + os.pathsep + env.get("PYTHONPATH", ""))
    return env


def run_name(scene, law, n, ranks):
    return f"{scene}{'' if law == '-' else '_' + law}_N{n}_np{ranks}"


def command(scene, law, n, ranks, rundir, logfile, extra=(), topology=True, cores=None):
    """The command line of one run: this file's child mode under mpirun for ranks > 1, each
    rank bound to a core as a plain ``mpirun -n 2`` binds them (Open MPI's default up to two
    ranks); more ranks than the ``cores`` (default: this machine's) run unbound.  On the 2-core
    VM of 28 Nov 2026 the cantilever at 10^4 elements, five alternating benches each way: 2
    ranks against 1 1.53-1.69 x bound (median 1.64), 1.51-1.61 x unbound (median 1.57), the
    bound run the faster in every pair; unbound, some runs' two ranks ran 1.5 x slower
    throughout (12 against 8 ms an iteration)."""
    cmd = [sys.executable, os.path.abspath(__file__), "--child",
           *(() if topology else ("--skip-topology",)), "rodsnes",
           *scene_options(scene, n, None if law == "-" else law),
           "-output_dir", rundir, "-quiet", "-log_view", ":" + logfile, *extra]
    if ranks > 1:
        cores = os.cpu_count() if cores is None else cores
        bind = ["--bind-to", "core"] if ranks <= cores else ["--bind-to", "none",
                                                              "--oversubscribe"]
        cmd = ["mpirun", "-n", str(ranks), *bind] + cmd
    return cmd


def wait_with_timeout(proc, timeout):
    """Wait for ``proc``; kill its process group (its own session) after ``timeout`` seconds.
    Returns (exit code or None on timeout, peak resident memory in GB of the largest process
    of its tree: wait4's ru_maxrss, which covers the waited-for descendants)."""
    t_end = time.monotonic() + timeout
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            proc.returncode = os.waitstatus_to_exitcode(status)
            return proc.returncode, usage.ru_maxrss / 2**20
        if time.monotonic() > t_end:
            os.killpg(proc.pid, signal.SIGKILL)          # the run's own process group only
            _, status, usage = os.wait4(proc.pid, 0)
            proc.returncode = os.waitstatus_to_exitcode(status)
            return None, usage.ru_maxrss / 2**20
        time.sleep(0.2)


def launch(cmd, stdout_path, timeout):
    """Run ``cmd`` (its own session), output to stdout_path; returns (exit code or None on
    timeout, peak memory GB, wall seconds)."""
    t0 = time.perf_counter()
    with open(stdout_path, "w") as fh:
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=run_env(),
                                cwd=ROOT, start_new_session=True)
        rc, rss = wait_with_timeout(proc, timeout)
    return rc, rss, time.perf_counter() - t0


def read_run(rundir, logfile, n):
    """Per-iteration parts (-log_view) and what summary.json and result.h5 say of one run."""
    with open(logfile) as fh:
        row = iteration_parts(parse_log_view(fh.read()))
    with open(os.path.join(rundir, "summary.json")) as fh:
        s = json.load(fh)
    row["converged"] = int(bool(s.get("converged")))
    row["dofs"] = s.get("dofs")
    row["iterations_converged"] = s.get("newton_iterations")
    row["wall_s"] = s.get("wall_time_s")
    c = s.get("contact") or {}
    if c:
        row["contact_zones"] = c.get("zones", "")
        row["contact_active_points"] = c.get("active_points", "")
        row["max_penetration"] = c.get("max_penetration", "")
        row["contact_elements"] = contact_elements(rundir, n)
    return row


def run_one(scene, law, n, ranks, out, timeout, extra=(), reuse=False, topology=True):
    """Run one case (with reuse: read the files of a finished run instead); returns the CSV
    row: status ok, not converged, timeout or failed, and the parts of read_run."""
    name = run_name(scene, law, n, ranks)
    base = os.path.join(out, "runs", name)
    rundir, logfile, res = base, base + "_log_view.txt", base + "_resources.json"
    row = {"scene": scene, "law": law, "N": n, "ranks": ranks, "status": "ok"}
    done = reuse and os.path.exists(logfile) and os.path.exists(os.path.join(rundir, "summary.json"))
    if not done:
        if os.path.exists(logfile):
            os.remove(logfile)
        shutil.rmtree(rundir, ignore_errors=True)
        os.makedirs(os.path.dirname(base), exist_ok=True)
        rc, rss, wall = launch(command(scene, law, n, ranks, rundir, logfile, extra, topology),
                               base + "_stdout.txt", timeout)
        with open(res, "w") as fh:
            json.dump({"wall_s": wall, "peak_rss_gb": rss, "exit": rc}, fh)
        row.update(wall_s=wall, peak_rss_gb=rss)
        if rc is None:
            return {**row, "status": f"timeout {timeout:g} s"}
        if rc not in (0, 3) or not os.path.exists(logfile):     # 3: the load path failed
            return {**row, "status": f"failed (exit {rc})"}
    row.update({k: v for k, v in read_run(rundir, logfile, n).items()
                if not (k == "wall_s" and "wall_s" in row)})
    if os.path.exists(res) and done:
        with open(res) as fh:
            r = json.load(fh)
        row.update(wall_s=r.get("wall_s"), peak_rss_gb=r.get("peak_rss_gb"))
    if not row["converged"]:
        row["status"] = "not converged"
    return row


def fastest(run, repeat):
    """The row of the fastest of ``repeat`` runs (least time per iteration, SNESSolve), with the
    spread of all of them (``repeats``: the totals in ms, comma separated): on a shared VM one
    run of the same case varies by 10-40 %, and the least time is the one least disturbed
    (as timeit takes the minimum).  A run that did not end ok, capped or not converged is
    returned at once."""
    rows = []
    for _ in range(max(1, repeat)):
        row = run()
        if not timed(row):
            return row
        rows.append(row)
    return best_of(rows)


def timed(row):
    """Whether a run's row has a time per iteration (it ended ok, capped or not converged)."""
    return str(row.get("status", "")).startswith(("ok", "capped", "not converged")) \
        and math.isfinite(row.get("total", math.nan))


def best_of(rows):
    """The fastest of the timed rows of one case, with all their totals (``repeats``)."""
    best = dict(min(rows, key=lambda r: r["total"]))
    best["repeats"] = ",".join(f"{1e3 * r['total']:.4g}" for r in rows)
    return best


def interleaved(runs, repeat):
    """fastest() of each of ``runs`` (a dict key -> run, in order: the rank counts of one
    case) with the rounds interleaved: the second run of every key after the first of all of
    them, and so on, so that the cases compared (1 and 2 ranks) see the same phases of a shared
    machine (a 2-core VM's speed drifts by 10-30 % within minutes; run one after the other the
    2-rank runs of the cantilever at 10^4 could fall into a slow phase the 1-rank ones had
    missed).  A key whose run is not timed stops there, with that row, and the keys after it
    stop too, with no row (what did not fit on fewer ranks); the keys before it go on.  Returns
    key -> row."""
    keys = list(runs)
    got = {key: [] for key in keys}
    out, dropped = {}, set()
    for _ in range(max(1, repeat)):
        for i, key in enumerate(keys):
            if key in out or key in dropped:
                continue
            row = runs[key]()
            if timed(row):
                got[key].append(row)
                continue
            out[key] = row
            for later in keys[i + 1:]:
                dropped.add(later)
                out.pop(later, None)
    for key in keys:
        if key not in out and key not in dropped and got[key]:
            out[key] = best_of(got[key])
    return out


def contact_elements(rundir, n):
    """Share of the elements with a contact point in contact (gap d > 0 at a report point:
    the 'gap' quadrature-point field of the last step in result.h5); '' if unreadable."""
    try:
        from rodsnes.io import results as output
        gap = output.read_step(rundir, -1)["gap"]
    except (OSError, KeyError, ValueError):
        return ""
    return float((gap.reshape(n, -1) > 0.0).any(axis=1).mean())


def available_memory_gb():
    """MemAvailable of /proc/meminfo in GB (inf if unknown)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 2**20
    except OSError:
        pass
    return math.inf


def too_big(prev, n, timeout, memory):
    """Why the run at N = n is not started, from the run of the same case at the size before
    (None: start it): that run failed or timed out, or its wall time or its peak memory (the
    largest process times the ranks) scaled by (n / N_before)^1.2 exceeds the timeout or 85 %
    of the memory available at the start."""
    if prev is None:
        return None
    st = prev.get("status", "")
    if st.startswith(("timeout", "failed", "skipped")):
        return f"N={prev['N']} {st.split(' (')[0]}"
    grow = (n / prev["N"]) ** 1.2
    if prev.get("wall_s") and prev["wall_s"] * grow > timeout:
        return f"predicted {prev['wall_s'] * grow:.0f} s > timeout {timeout:g} s"
    rss = (prev.get("peak_rss_gb") or 0.0) * prev["ranks"] * grow     # per process x ranks
    if rss > 0.85 * memory:
        return f"predicted {rss:.1f} GB > 85 % of {memory:.1f} GB available"
    return None


# -- targets ------------------------------------------------------------------------------

def timed(r):
    """A row with per-iteration times: the run finished, converged or not (a solve that did
    not converge, or was capped by --max-its, still times its iterations)."""
    return isinstance(r.get("total"), float) and r["total"] > 0


def _find(rows, **key):
    for r in rows:
        if all(r.get(k) == v for k, v in key.items()) and timed(r):
            return r
    return None


def fitted_exponent(rows, scene, law, ranks=1, lo=1000, hi=100000):
    """Least-squares slope of log(total per iteration) against log N over lo <= N <= hi
    (None with fewer than two sizes)."""
    pts = [(math.log(r["N"]), math.log(r["total"])) for r in rows
           if r["scene"] == scene and r["law"] == law and r["ranks"] == ranks
           and timed(r) and lo <= r["N"] <= hi]
    if len(pts) < 2:
        return None, []
    mx = sum(p[0] for p in pts) / len(pts)
    my = sum(p[1] for p in pts) / len(pts)
    sxx = sum((p[0] - mx) ** 2 for p in pts)
    slope = sum((p[0] - mx) * (p[1] - my) for p in pts) / sxx
    return slope, sorted(round(math.exp(p[0])) for p in pts)


def targets(rows):
    """The issue's targets: list of (target, where, measured, limit, verdict)."""
    out = []

    def verdict(value, limit, le=True):
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return "n/a"
        return "PASS" if (value <= limit if le else value >= limit) else "MISS"

    for n in (10000, 100000):
        r = _find(rows, scene="cantilever", N=n, ranks=1)
        v = r["resjac_per_factor"] if r else None
        out.append(("(residual + Jacobian) / factorisation", f"cantilever, N={n}, 1 rank", v,
                    "<= 0.5", verdict(v, 0.5)))
    for scene, law in cases(["coil"], sorted({r["law"] for r in rows if r["scene"] == "coil"})):
        r = _find(rows, scene=scene, law=law, N=10000, ranks=1)
        v = r["contact_per_factor"] if r and r.get("rod_events") else None
        out.append(("contact (search + evaluation + tangent) / factorisation",
                    f"{scene} ({law}), N=10000, 1 rank", v, "<= 1", verdict(v, 1.0)))
    for scene, law in sorted({(r["scene"], r["law"]) for r in rows}):
        e, ns = fitted_exponent(rows, scene, law)
        where = f"{scene}{'' if law == '-' else ' (' + law + ')'}, 1 rank, N = " + \
            (",".join(f"{x:g}" for x in ns) if ns else "1e3..1e5")
        out.append(("exponent of time per iteration ~ N^e", where, e, "<= 1.1", verdict(e, 1.1)))
    for scene, law in sorted({(r["scene"], r["law"]) for r in rows}):
        r1 = _find(rows, scene=scene, law=law, N=10000, ranks=1)
        r2 = _find(rows, scene=scene, law=law, N=10000, ranks=2)
        v = r1["total"] / r2["total"] if r1 and r2 else None
        out.append(("speed-up 2 ranks / 1 rank, per iteration",
                    f"{scene}{'' if law == '-' else ' (' + law + ')'}, N=10000", v, ">= 1.7",
                    verdict(v, 1.7, le=False)))
    return out


# -- outputs ------------------------------------------------------------------------------

COLUMNS = ("scene", "law", "N", "ranks", "status", "dofs", "iterations", "iterations_converged",
           "snes_solves", "residual_evals", "factorisations", "analyses", "wall_s", "peak_rss_gb",
           "setup", "total",
           "residual", "jacobian", "factor", "factor_sym", "solve", "linesearch", "other",
           "elastic", "contact", "contact_search", "contact_eval", "contact_halo",
           "contact_assemble", "resjac_per_factor", "contact_per_factor", "rod_events",
           "contact_elements", "contact_zones", "contact_active_points", "max_penetration",
           "repeats")


def write_csv(rows, path):
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})


def read_csv(path):
    rows = []
    with open(path) as fh:
        for r in csv.DictReader(fh):
            for k, v in list(r.items()):
                if k in ("N", "ranks", "iterations", "rod_events") and v not in ("", None):
                    r[k] = int(float(v))
                elif k not in ("scene", "law", "status") and v not in ("", None):
                    try:
                        r[k] = float(v)
                    except ValueError:
                        pass
            rows.append(r)
    return rows


def machine():
    """'<cpu model>, <n> cores' from /proc/cpuinfo."""
    model = "unknown CPU"
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} cores"


def _ms(v):
    return "" if v in ("", None) or (isinstance(v, float) and math.isnan(v)) else f"{1e3 * v:.4g}"


def _ratio(v):
    return "" if v in ("", None) or (isinstance(v, float) and math.isnan(v)) else f"{v:.3g}"


def _pct(v):
    return "" if v in ("", None) or (isinstance(v, float) and math.isnan(v)) else f"{100 * v:.0f} %"


def markdown(rows, note=""):
    """The Markdown table (README): machine, per-iteration parts, targets."""
    lines = [f"Machine: {machine()}.  Milliseconds per Newton iteration (the maximum over the "
             f"ranks), from PETSc's -log_view; tools/bench_scaling.py.{' ' + note if note else ''}",
             "",
             "| scene | law | N | ranks | set-up (once) | its | total | residual | Jacobian "
             "| factor (LU) | solve | line search | elastic | contact | (res+Jac)/factor "
             "| contact/factor | in contact | peak GB | status |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
             "---:|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['law']} | {r['N']} | {r['ranks']} | "
                     f"{_ms(r.get('setup'))} | {r.get('iterations', '')} | {_ms(r.get('total'))} | "
                     f"{_ms(r.get('residual'))} | {_ms(r.get('jacobian'))} | "
                     f"{_ms(r.get('factor'))} | {_ms(r.get('solve'))} | "
                     f"{_ms(r.get('linesearch'))} | {_ms(r.get('elastic'))} | "
                     f"{_ms(r.get('contact')) if r['scene'] != 'cantilever' else ''} | "
                     f"{_ratio(r.get('resjac_per_factor'))} | "
                     f"{_ratio(r.get('contact_per_factor')) if r['scene'] != 'cantilever' else ''} | "
                     f"{_pct(r.get('contact_elements'))} | {_ratio(r.get('peak_rss_gb'))} | "
                     f"{r.get('status', '')} |")
    lines += ["", "| target | where | measured | limit | verdict |", "|---|---|---:|---|---|"]
    for name, where, v, limit, ok in targets(rows):
        lines.append(f"| {name} | {where} | {'' if v is None else f'{v:.4g}'} | {limit} | {ok} |")
    return "\n".join(lines) + "\n"


def print_targets(rows):
    print(f"\n{'target':58s} {'where':46s} {'measured':>9s} {'limit':>7s}  verdict")
    for name, where, v, limit, ok in targets(rows):
        print(f"{name:58s} {where:46s} {'' if v is None else f'{v:9.4g}':>9s} {limit:>7s}  {ok}")


PARTS = (("total", "k", "o", "total"), ("residual", "tab:blue", "s", "residual"),
         ("jacobian", "tab:orange", "^", "Jacobian"), ("factor", "tab:red", "D", "factorisation (LU)"),
         ("solve", "tab:purple", "v", "solve"), ("linesearch", "tab:brown", "x", "line search"),
         ("elastic", "tab:olive", "*", "elastic kernel"), ("contact", "tab:green", "P", "contact"))


def plot(rows, path):
    """Log-log panels, one per scene and law: per-iteration parts against N (solid: 1 rank;
    the 2-rank total dashed), with an N^1 guide through the 1-rank total's first point."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    order = {"-": 0, "projection": 1, "potential": 2}
    keys = sorted({(r["scene"], r["law"]) for r in rows if timed(r)},
                  key=lambda k: (k[0] != "cantilever", k[0], order.get(k[1], 3), k[1]))
    if not keys:
        return False
    fig, axes = plt.subplots(1, len(keys), figsize=(5.2 * len(keys), 4.4), squeeze=False)
    for ax, (scene, law) in zip(axes[0], keys):
        one = sorted((r for r in rows if r["scene"] == scene and r["law"] == law
                      and r["ranks"] == 1 and timed(r)), key=lambda r: r["N"])
        for key, color, marker, label in PARTS:
            if key == "contact" and scene == "cantilever":
                continue
            pts = [(r["N"], r[key]) for r in one if r.get(key, 0) and r[key] > 0]
            if pts:
                ax.loglog(*zip(*pts), marker=marker, color=color, label=label,
                          lw=2.0 if key == "total" else 1.2)
        two = sorted((r for r in rows if r["scene"] == scene and r["law"] == law
                      and r["ranks"] == 2 and timed(r)), key=lambda r: r["N"])
        pts = [(r["N"], r["total"]) for r in two if r.get("total", 0) > 0]
        if pts:
            ax.loglog(*zip(*pts), "k--", marker="o", mfc="none", label="total, 2 ranks")
        if one:
            n0, t0 = one[0]["N"], one[0]["total"]
            ns = [n0, max(r["N"] for r in rows)]
            ax.loglog(ns, [t0 * n / n0 for n in ns], ":", color="gray", label="$\\propto N$")
        ax.set_title(scene + ("" if law == "-" else f", -contact_model {law}"))
        ax.set_xlabel("cubic elements N")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("seconds per Newton iteration")
    axes[0][-1].legend(fontsize=7, loc="upper left")
    fig.suptitle(f"Time per Newton iteration ({machine()})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


# -- main ---------------------------------------------------------------------------------

def _ints(text):
    return [int(float(x)) for x in text.split(",") if x.strip()]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="100,1000,10000,100000", help="element counts N")
    ap.add_argument("--ranks", default="1,2", help="MPI ranks")
    ap.add_argument("--scenes", default="cantilever,coil", help="cantilever, coil")
    ap.add_argument("--laws", default="projection,potential", help="the coil's contact laws")
    ap.add_argument("--out", default=DEFAULT_OUT, help="output directory")
    ap.add_argument("--quick", action="store_true",
                    help="N = 100, 1000 only, each run capped at 3 Newton iterations (--max-its "
                         "3 unless given): checks that the tool runs")
    ap.add_argument("--timeout", type=float, default=3600.0,
                    help="seconds per run; a run that times out skips the larger N of its case")
    ap.add_argument("--reuse", action="store_true",
                    help="read the runs already in --out instead of running them again")
    ap.add_argument("--report", action="store_true",
                    help="no runs: table, plot and targets from --out/bench_scaling.csv")
    ap.add_argument("--publish", action="store_true",
                    help=f"also write {os.path.relpath(DOC_PNG, ROOT)} and {os.path.relpath(DOC_MD, ROOT)}")
    ap.add_argument("--max-its", type=int, default=0,
                    help="cap each run at this many Newton iterations (one solve, no cut-backs): "
                         "per-iteration times without waiting for convergence (status 'capped')")
    ap.add_argument("--repeat", type=int, default=3,
                    help="runs of every case; the fastest is kept, the others' times are in the "
                         "CSV's repeats column (default 3)")
    ap.add_argument("--extra", default="", help="more rodsnes options for every run (quoted)")
    ap.add_argument("--skip-topology", action="store_true",
                    help="no link, twist and writhe in the runs: the writhe is O(N^2), outside "
                         "the Newton iterations (2 x 230 s of a coil run at N = 1e4)")
    ap.add_argument("--note", default="", help="a sentence for the Markdown table's heading")
    args = ap.parse_args(argv)
    extra = args.extra.split()
    if args.quick and not args.max_its:
        args.max_its = 3
    if args.max_its:
        extra += ["-snes_max_it", str(args.max_its), "-load_max_cutbacks", "0",
                  "-load_stagnation_its", "0"]
    sizes = [100, 1000] if args.quick else _ints(args.sizes)
    ranks = _ints(args.ranks)
    # the runs' own output directories go below it, and the runs' working directory is the
    # repository: a relative --out is the caller's, made absolute here
    args.out = os.path.abspath(args.out)
    os.makedirs(args.out, exist_ok=True)
    csv_path = os.path.join(args.out, "bench_scaling.csv")
    if args.report:
        rows = read_csv(csv_path)
    else:
        rows, last, memory = [], {}, available_memory_gb()
        for n in sorted(sizes):
            for scene, law in cases(args.scenes.split(","), args.laws.split(",")):
                runs, skipped = {}, {}
                for np_ in ranks:
                    why = too_big(last.get((scene, law, np_)), n, args.timeout, memory)
                    if skipped and not why:         # what did not fit on fewer ranks
                        first = skipped[min(skipped)]
                        why = f"{first['ranks']} rank(s): {first['status'].split(' (')[0]}"
                    if why:
                        skipped[np_] = {"scene": scene, "law": law, "N": n, "ranks": np_,
                                        "status": f"skipped ({why})"}
                        continue
                    runs[np_] = functools.partial(run_one, scene, law, n, np_, args.out,
                                                  args.timeout, extra=extra, reuse=args.reuse,
                                                  topology=not args.skip_topology)
                done = {**skipped, **interleaved(runs, 1 if args.reuse else args.repeat)}
                failed = None               # the first rank count whose run did not end ok
                for np_ in ranks:
                    row = done.get(np_)
                    if row is None:         # what did not fit on fewer ranks
                        row = {"scene": scene, "law": law, "N": n, "ranks": np_,
                               "status": f"skipped ({failed['ranks']} rank(s): "
                                         f"{failed['status'].split(' (')[0]})"}
                    elif failed is None and not timed(row) and np_ not in skipped:
                        failed = row
                    if args.max_its and row["status"] == "not converged":
                        row["status"] = "capped"
                    rows.append(row)
                    last[(scene, law, np_)] = row
                    print(f"{run_name(scene, law, n, np_):40s} {row['status']:14s} its "
                          f"{row.get('iterations', '-')!s:>4s}  "
                          f"{1e3 * row.get('total', math.nan):10.4g} ms/it  "
                          f"factor {1e3 * row.get('factor', math.nan):9.4g} ms  "
                          f"wall {row.get('wall_s', math.nan):7.1f} s", flush=True)
                write_csv(rows, csv_path)
    write_csv(rows, csv_path)
    md = markdown(rows, args.note)
    with open(os.path.join(args.out, "bench_scaling.md"), "w") as fh:
        fh.write(md)
    png = os.path.join(args.out, "bench_scaling.png")
    plotted = plot(rows, png)
    print_targets(rows)
    print(f"\n{csv_path}\n{os.path.join(args.out, 'bench_scaling.md')}" + (f"\n{png}" if plotted else ""))
    if args.publish:
        os.makedirs(os.path.dirname(DOC_PNG), exist_ok=True)
        if plotted:
            shutil.copyfile(png, DOC_PNG)
        with open(DOC_MD, "w") as fh:
            fh.write(md)
        print(f"{DOC_PNG}\n{DOC_MD}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        skip = len(sys.argv) > 2 and sys.argv[2] == "--skip-topology"
        sys.exit(child(sys.argv[2 + skip:], topology=not skip))
    sys.exit(main())
