#!/usr/bin/env python3
"""Report of a load path from result.h5: Newton work per range of the path, and the end state.

    .venv/bin/python tools/path_report.py DIR [--by link|load] [--edges 0,1,2,...] [--out FILE.md]
                                          [--summary OLD/summary.json ...]

Reads the step attributes of ``DIR/result.h5`` (every complete step, across restarts that
appended to DIR) and prints a markdown report:

* a table per range of the path (``--by link``: imposed turns, the default when the run has a
  topology; else ``--by load``), with the number of load steps, median and largest Newton
  iterations per step, median seconds per step (the ``seconds`` attribute; steps written before
  it existed are filled from ``--summary`` files, matched by load, else unknown) and the branch
  switches / jumps in the range;
* over the whole path: total steps, Newton iterations, wall seconds of the steps, the largest
  residual norm of a converged step, the largest penetration (fraction of the tube's diameter);
* the last step: load, energy, link / twist / writhe, negative eigenvalues, contact zones, total
  contact force int f_c ds, and the distribution of the contact force line density f_c = mu <d>
  over the contact quadrature points with f_c > 0 (median, 90th percentile, max) with the
  arclength intervals where it acts.
"""
import argparse
import sys

import numpy as np

from rodsnes.io import results as output


def intervals(s, active):
    """Arclength intervals [a, b] covered by consecutive active points of the sorted s."""
    order = np.argsort(s)
    s, active = np.asarray(s)[order], np.asarray(active)[order]
    runs, start = [], None
    for i, a in enumerate(active):
        if a and start is None:
            start = i
        if (not a or i == len(s) - 1) and start is not None:
            end = i if a else i - 1
            runs.append((float(s[start]), float(s[end])))
            start = None
    return runs


def contact_distribution(last):
    """Median, 90th percentile and max of the contact force line density at its active points."""
    if "contact_force" not in last:
        return None
    f = np.asarray(last["contact_force"], float)
    s = np.asarray(last["qp_s"], float)
    on = f > 0
    if not on.any():
        return {"active": 0}
    return {"active": int(on.sum()), "median": float(np.median(f[on])),
            "p90": float(np.percentile(f[on], 90)), "max": float(f.max()),
            "s_max": float(s[np.argmax(f)]), "intervals": intervals(s, on)}


def timings_from_summaries(files):
    """{load: seconds} from the per-step history of summary.json files (runs made before
    result.h5 recorded ``seconds``, or the earlier part of a restarted run)."""
    import json
    out = {}
    for fn in files:
        with open(fn) as fh:
            for st in json.load(fh).get("steps", []):
                out[round(float(st["load"]), 12)] = float(st["seconds"])
    return out


def report(outdir, by=None, edges=None, summaries=()):
    rows = output.read_step_attrs(outdir)
    timings = timings_from_summaries(summaries)
    for _, a in rows:
        if "seconds" not in a and round(float(a.get("load", -1)), 12) in timings:
            a["seconds"] = timings[round(float(a["load"]), 12)]
    meta = output.read_meta(outdir)
    path = [(k, a) for k, a in rows if k > 0]
    if not path:
        raise SystemExit(f"{outdir}: no converged load step")
    if by is None:
        by = "link" if "link" in path[-1][1] else "load"
    x = np.array([a[by] for _, a in path], float)
    its = np.array([a.get("newton_iterations", 0) for _, a in path], float)
    sec = np.array([a.get("seconds", np.nan) for _, a in path], float)
    if edges is None:
        hi = float(np.ceil(x.max() - 1e-9)) if by == "link" else 1.0
        edges = list(np.arange(0.0, hi + 0.5, 1.0 if by == "link" else 0.1))
    lines = [f"# {meta.get('case_name', '')}: {outdir}", "",
             f"| {by} | steps | median its / step | max its | median s / step | switches (jumps) |",
             "|---|---|---|---|---|---|"]
    for a, b in zip(edges[:-1], edges[1:]):
        m = (x > a + 1e-12) & (x <= b + 1e-12)
        if not m.any():
            continue
        sw = sum(1 for (k, at), mm in zip(path, m) if mm and at.get("branch_switch"))
        jp = sum(1 for (k, at), mm in zip(path, m) if mm and at.get("jump"))
        s_med = np.nanmedian(sec[m]) if np.isfinite(sec[m]).any() else float("nan")
        lines.append(f"| {a:g} - {b:g} | {int(m.sum())} | {np.median(its[m]):g} | {int(its[m].max())} "
                     f"| {s_med:.3g} | {sw} ({jp}) |")
    res = np.array([a.get("residual_norm", 0.0) for _, a in path], float)
    pen = np.array([a.get("contact_max_penetration", 0.0) for _, a in path], float)
    known = np.isfinite(sec)
    lines += ["", f"Whole path: {len(path)} load steps, {int(its.sum())} Newton iterations, "
              f"{np.nansum(sec):.0f} s in the steps ({int((~known).sum())} steps without timing), "
              f"largest residual of a converged step {res.max():.2e} (step {path[int(res.argmax())][0]}), "
              f"largest penetration {pen.max():.3%} of the diameter "
              f"(at {by} {x[int(pen.argmax())]:.4g})."]
    last = output.read_step(outdir, -1)
    at = last["attrs"]
    end = [f"load {at['load']:.6g}", f"energy {at['energy']:.6g}"]
    for key in ("link", "twist", "writhe", "negative_eigenvalues", "contact_zones",
                "contact_total_force", "contact_max_penetration", "contact_complementarity"):
        if key in at:
            end.append(f"{key} {at[key]:.6g}")
    lines += ["", f"Last step {last['step']}: " + ", ".join(end) + "."]
    dist = contact_distribution(last)
    if dist and dist.get("active"):
        iv = ", ".join(f"[{a:.3f}, {b:.3f}]" for a, b in dist["intervals"])
        lines.append(f"Contact force line density over its {dist['active']} active report points: "
                     f"median {dist['median']:.4g}, 90th percentile {dist['p90']:.4g}, max "
                     f"{dist['max']:.4g} (at s = {dist['s_max']:.3f}); acting over s in {iv}.")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir")
    ap.add_argument("--by", choices=("link", "load"), default=None)
    ap.add_argument("--edges", default=None, help="comma-separated range edges in the --by variable")
    ap.add_argument("--out", default=None, help="also write the report to this file")
    ap.add_argument("--summary", action="append", default=[],
                    help="summary.json whose per-step seconds fill steps without them (repeatable)")
    a = ap.parse_args(argv)
    edges = None if a.edges is None else [float(e) for e in a.edges.split(",")]
    text = report(a.dir, a.by, edges, a.summary)
    sys.stdout.write(text)
    if a.out:
        with open(a.out, "w") as fh:
            fh.write(text)


if __name__ == "__main__":
    main()
