#!/usr/bin/env python3
"""Penalty sweep: one scene at mu = factor x the default penalty, for several factors.

    .venv/bin/python tools/penalty_sweep.py cases/rollup_contact.opts --factors 1,10,100,1000 \
        --out docs/penalty_sweep_rollup_contact [-- -rod_nelem 24 ...extra rodsnes options]

Runs ``rodsnes`` once per factor (``-contact_penalty`` = factor x the default penalty,
docs/contact.md, read from the first run's summary) and writes OUT.csv and OUT.md: factor, mu, max penetration (fraction
of the tube's diameter), min gap, total contact force, complementarity, Newton iterations, load steps, wall
time, converged.  The penalty method promises penetration ~ 1/mu at a fixed contact force.
"""
import argparse
import csv
import os
import shutil
import subprocess
import sys

from rodsnes.io import results as output
from work_precision import solver_command      # tools/ is on sys.path when run as a script


def run(case, outdir, extra, mu=None, np_=1):
    """One rodsnes run into a fresh outdir (never a stale summary.json); its summary."""
    if os.path.isdir(outdir):
        shutil.rmtree(outdir)
    # a sweep holds mu fixed: no -contact_penalty_adapt (it would raise the soft ones)
    cmd = solver_command() + ["-options_file", case, "-output_dir", outdir, "-quiet",
                              "-contact_penalty_adapt", "0"] + list(extra)
    if mu is not None:
        cmd += ["-contact_penalty", repr(mu)]
    if np_ > 1:
        cmd = ["mpirun", "-n", str(np_), "--bind-to", "none"] + cmd
    subprocess.run(cmd, check=False)
    return output.read_summary(outdir)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case")
    ap.add_argument("--factors", default="1,10,100,1000")
    ap.add_argument("--out", default=None, help="output prefix (default out/penalty_sweep_<case>)")
    ap.add_argument("--np", type=int, default=1, help="MPI ranks per run (after it: -- extra rodsnes options)")
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    a = ap.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    name = os.path.splitext(os.path.basename(a.case))[0]
    out = a.out or os.path.join("out", "penalty_sweep_" + name)
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    rows, mu0 = [], None
    for f in [float(x) for x in a.factors.split(",")]:
        runs = os.path.join("out", os.path.basename(out) + "_runs", f"x{f:g}")      # run directories
        d = run(a.case, runs, extra, None if mu0 is None else f * mu0, a.np)
        c = d.get("contact", {})
        if mu0 is None:
            mu0 = c["penalty"] / f
        rows.append({"factor": f, "mu": c.get("penalty"), "max_penetration": c.get("max_penetration"),
                     "min_gap": c.get("min_gap"), "total_force": c.get("total_force"),
                     "complementarity": c.get("complementarity"),
                     "newton_iterations": d.get("newton_iterations"), "load_steps": d.get("load_steps"),
                     "wall_time_s": d.get("wall_time_s"), "converged": d.get("converged")})
        print(rows[-1], flush=True)
    with open(out + ".csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    with open(out + ".md", "w") as fh:
        fh.write("| mu / default | max penetration (of 2 eps) | total force | Newton its | load steps | wall s | converged |\n")
        fh.write("|---|---|---|---|---|---|---|\n")
        for r in rows:
            fh.write(f"| {r['factor']:g} | {r['max_penetration']:.3e} | {r['total_force']:.6f} | "
                     f"{r['newton_iterations']} | {r['load_steps']} | {r['wall_time_s']:.1f} | {r['converged']} |\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
