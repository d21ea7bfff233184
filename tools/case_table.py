#!/usr/bin/env python3
"""Run every case of cases/ as a user would (its options file, nothing else) and tabulate what
each run took: load steps, Newton iterations, wall time, whether every step ended on a stable
equilibrium, and the run's end (converged, exit code).

    .venv/bin/python tools/case_table.py                    # every case, serially
    .venv/bin/python tools/case_table.py --ranks 2          # under mpirun -n 2
    .venv/bin/python tools/case_table.py --cases euler,helix --out docs/cases_table.md

One `rodsnes -options_file cases/<case>.opts` per case (in --workdir, default a temporary
directory), its summary.json read back.  "stable at every step": every step's
negative_eigenvalues is 0 (the minimiser certifies each step; a Newton-path case without
-stability has no count: "not counted").  Wall time is the run's own (summary.json wall_time_s,
from the start of the first load step to the last), on whatever machine this runs: time a table
on an otherwise idle machine, and say which.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

from bench_scaling import machine     # '<cpu model>, <n> cores' (tools/, beside this file)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
COLUMNS = ("case", "path", "load steps", "Newton iterations", "wall s", "stable at every step",
           "end")


def case_names(cases_dir):
    return sorted(f[:-5] for f in os.listdir(cases_dir) if f.endswith(".opts"))


def command(case, outdir, ranks):
    exe = [sys.executable, "-m", "rodsnes", "-options_file",
           os.path.join(ROOT, "cases", case + ".opts"), "-output_dir", outdir, "-quiet"]
    if ranks > 1:
        return ["mpirun", "-n", str(ranks), "--bind-to", "none"] + exe
    return exe


def stability(summary):
    counts = [s.get("negative_eigenvalues") for s in summary.get("steps", [])]
    if not counts or any(c is None or c < 0 for c in counts):
        return "not counted"
    bad = sum(1 for c in counts if c > 0)
    return "yes" if bad == 0 else f"no ({bad} of {len(counts)} steps unstable)"


def run_case(case, workdir, ranks, timeout):
    """One row: the run's summary, or what went wrong."""
    outdir = os.path.join(workdir, case)
    t0 = time.perf_counter()
    env = dict(os.environ, OMP_NUM_THREADS="1")
    try:
        proc = subprocess.run(command(case, outdir, ranks), cwd=ROOT, env=env, timeout=timeout,
                              capture_output=True, text=True)
        rc = proc.returncode
    except subprocess.TimeoutExpired:
        rc = None
    wall = time.perf_counter() - t0
    try:
        with open(os.path.join(outdir, "summary.json")) as fh:
            s = json.load(fh)
    except (OSError, ValueError):
        return {"case": case, "end": "timed out" if rc is None else f"no summary (exit {rc})",
                "wall s": f"{wall:.1f}"}
    end = "converged" if s.get("converged") else "failed"
    if s.get("stable") is False:
        end += ", UNSTABLE"
    end += f" (exit {rc})" if rc is not None else " (timed out)"
    return {"case": case, "path": s.get("path", "?"), "load steps": s.get("load_steps", "?"),
            "Newton iterations": s.get("newton_iterations", "?"),
            "wall s": f"{s.get('wall_time_s', wall):.1f}", "stable at every step": stability(s),
            "end": end}


def table(rows):
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        lines.append("| " + " | ".join(str(r.get(c, "")) for c in COLUMNS) + " |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=None, help="comma-separated case names (default: all)")
    ap.add_argument("--ranks", type=int, default=1)
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per case")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--out", default=None, help="also write the table (Markdown) here")
    args = ap.parse_args(argv)
    cases = args.cases.split(",") if args.cases else case_names(os.path.join(ROOT, "cases"))
    workdir = args.workdir or tempfile.mkdtemp(prefix="case_table_")
    rows = []
    for case in cases:
        rows.append(run_case(case, workdir, args.ranks, args.timeout))
        print(table(rows[-1:]).splitlines()[-1], flush=True)
    head = (f"Every case of cases/ as given, {args.ranks} rank(s), {machine()}, "
            f"{time.strftime('%Y-%m-%d %H:%M')} (tools/case_table.py)")
    text = head + "\n\n" + table(rows) + "\n"
    print("\n" + text)
    if args.out:
        with open(args.out, "w") as fh:
            fh.write(text)
    return 0 if all(r.get("end", "").startswith("converged") for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
