#!/usr/bin/env python
"""Planar against 3-D (-rod_planar auto against off): wall time per case and per Newton
iteration on planar scenes, each run as the rodsnes command (one process at a time, the best of
--repeat runs), written as a Markdown table between the markers of docs/planar.md (and printed).

    .venv/bin/python tools/bench_planar.py            # the table of docs/planar.md
    .venv/bin/python tools/bench_planar.py --quick    # mattiasson at 8 and 1000 elements only

The ratio planar / 3-D of each row comes from runs made one after the other on the same machine;
CPU time (user + system of the run's process), the least of --repeat runs (timings on a shared
machine are noisy: compare the ratios, not the seconds).
"""
import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOC = os.path.join(ROOT, "docs", "planar.md")
BEGIN, END = "<!-- bench_planar: begin -->", "<!-- bench_planar: end -->"

# (label, options file, extra options)
CASES = [
    ("mattiasson, 8 elements", "mattiasson", []),
    ("mattiasson, 1000 elements", "mattiasson", ["-rod_nelem", "1000"]),
    ("mattiasson, 10000 elements", "mattiasson", ["-rod_nelem", "10000"]),
    ("rollup_contact (32 elements, contact, Newton path)", "rollup_contact", []),
]


def run_once(case, extra, planar):
    """summary.json of one run of cases/<case>.opts with -rod_planar ``planar``, with the CPU
    seconds (user + system) of its process as "cpu_s"."""
    out = tempfile.mkdtemp(prefix="bench_planar_")
    cmd = [sys.executable, "-m", "rodsnes", "-options_file",
           os.path.join(ROOT, "cases", case + ".opts"), "-output_dir", out, "-quiet",
           "-rod_error_estimate", "off", "-rod_planar", planar] + extra
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(cmd, check=True, cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": "1"})
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    with open(os.path.join(out, "summary.json")) as fh:
        s = json.load(fh)
    s["cpu_s"] = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return s


def best(case, extra, planar, repeat):
    """The run of least CPU time of ``repeat``: (CPU seconds of the case, CPU seconds in the
    load steps, Newton iterations, energy, unknowns solved for).  The load steps' CPU time is
    the case's times the share of its wall time spent in them (summary.json steps' seconds):
    start-up, the first output and the Python import are left out.  CPU rather than wall time:
    the machine is shared, and CPU time is what contention disturbs least."""
    runs = [run_once(case, extra, planar) for _ in range(repeat)]
    s = min(runs, key=lambda r: r["cpu_s"])
    assert s["converged"], f"{case} {extra} -rod_planar {planar} did not converge"
    dofs = s["dofs"] // 2 if s["model"].startswith("planar") else s["dofs"]
    steps = s["cpu_s"] * sum(h["seconds"] for h in s["steps"]) / s["wall_time_s"]
    return s["cpu_s"], steps, s["newton_iterations"], s["energy"], dofs


def table(rows):
    """Per iteration: the CPU time of the load steps (the solves, not the start-up and output)
    over the Newton iterations; per case: the CPU time of the whole run."""
    lines = ["| case | unknowns planar / 3-D | Newton its planar / 3-D | CPU ms per iteration "
             "planar / 3-D | ratio | CPU s per case planar / 3-D | ratio |",
             "|---|---|---|---|---|---|---|"]
    for label, p, d in rows:
        per_p, per_d = 1e3 * p[1] / max(p[2], 1), 1e3 * d[1] / max(d[2], 1)
        lines.append(f"| {label} | {p[4]} / {d[4]} | {p[2]} / {d[2]} | {per_p:.1f} / {per_d:.1f} "
                     f"| {per_p / per_d:.2f} | {p[0]:.2f} / {d[0]:.2f} | {p[0] / d[0]:.2f} |")
    return "\n".join(lines)


def write_doc(text):
    with open(DOC) as fh:
        doc = fh.read()
    i, j = doc.index(BEGIN) + len(BEGIN), doc.index(END)
    with open(DOC, "w") as fh:
        fh.write(doc[:i] + "\n" + text + "\n" + doc[j:])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=2, help="runs per variant (the best is kept)")
    ap.add_argument("--quick", action="store_true", help="mattiasson at 8 and 1000 elements")
    ap.add_argument("--no-doc", action="store_true", help="print only")
    args = ap.parse_args()
    rows = []
    for label, case, extra in (CASES[:2] if args.quick else CASES):
        p = best(case, extra, "auto", args.repeat)
        d = best(case, extra, "off", args.repeat)
        rel = abs(p[3] - d[3]) / max(abs(d[3]), 1e-300)
        print(f"{label}: planar {p[0]:.2f} s ({p[2]} its), 3-D {d[0]:.2f} s ({d[2]} its), "
              f"energies differ by {rel:.1e}", flush=True)
        rows.append((label, p, d))
    text = table(rows)
    print(text)
    if not args.no_doc and not args.quick:
        write_doc(text)


if __name__ == "__main__":
    main()
