#!/usr/bin/env python3
"""Plot a twisted rod's load path from result.h5: link, twist and writhe against the imposed
turns (load x -bc_end_turns, or the link where no turns are imposed), and the total contact
force.

    .venv/bin/python tools/path_plot.py DIR [--turns T] [--out FILE.png] [--pyelastica PE.npz]

T: the turns at load 1 (default: read from the scene stored in result.h5, else the link of the
last step divided by its load).
PE.npz: snapshots of PyElastica's run of the same scene (tools/pyelastica_path.py); its writhe,
computed here by the same closure along the clamping axis, is drawn beside rodsnes's against
its own link (in PyElastica's example the end turns at 0.9 of the nominal rate while it twists,
its damping slowing the imposed spin, and is set to the full 10 turns when the twisting ends),
and its end state after the relaxation as a circle.
"""
import argparse

import numpy as np

from rodsnes.io import results as output


def path_table(rdir):
    """(load, link, twist, writhe, contact force, negative eigenvalues) per complete step."""
    rows = []
    for k in output.read_steps(rdir):
        a = output.read_step(rdir, k)["attrs"]
        rows.append((float(a["load"]), float(a.get("link", np.nan)), float(a.get("twist", np.nan)),
                     float(a.get("writhe", np.nan)), float(a.get("contact_total_force", 0.0)),
                     int(a.get("negative_eigenvalues", -1))))
    return np.array(rows)


def pyelastica_table(path):
    """(imposed turns, link, twist, writhe, time) per snapshot of tools/pyelastica_path.py's
    output, by rodsnes's closure along the end-to-end axis (topology.topology).  d1 at a node is
    the mean of its elements' (the end elements' at the ends)."""
    from rodsnes.model.topology import topology
    z = np.load(path)
    rows = []
    for turns, t, x, D in zip(z["turns"], z["time"], z["positions"], z["directors"]):
        d1 = D[0].T                                  # (n, 3): d1 of every element
        d1n = np.vstack([d1[:1], 0.5 * (d1[:-1] + d1[1:]), d1[-1:]])
        top = topology(x, d1n, closed=False)
        rows.append((turns, top["link"], top["twist"], top["writhe"], t))
    return np.array(rows)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir")
    ap.add_argument("--turns", type=float, default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--pyelastica", default=None, help="PyElastica snapshots (.npz)")
    args = ap.parse_args(argv)
    t = path_table(args.dir)
    turns = args.turns
    if turns is None:
        last = t[-1]
        turns = last[1] / last[0] if last[0] > 0 else 1.0
    x = t[:, 0] * turns
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
    a1.plot(x, t[:, 1], "k-", label="link")
    a1.plot(x, t[:, 2], "b-", label="twist")
    a1.plot(x, t[:, 3], "r-", label="writhe")
    if args.pyelastica:
        pe = pyelastica_table(args.pyelastica)
        twisting = np.r_[True, np.diff(pe[:, 0]) > 0]
        a1.plot(pe[twisting, 1], pe[twisting, 3], "r:", label="writhe, PyElastica (against its link)")
        a1.plot([pe[-1, 1]], [pe[-1, 3]], "ro", mfc="none", label="PyElastica after relaxing")
    unstable = t[:, 5] > 0
    if unstable.any():
        a1.plot(x[unstable], t[unstable, 3], "rx", label="unstable step")
    a1.set_ylabel("turns")
    a1.legend()
    a1.grid(alpha=0.3)
    a2.plot(x, t[:, 4], "g-")
    a2.set_ylabel("total contact force")
    a2.set_xlabel("turns between the clamps (link)")
    a2.grid(alpha=0.3)
    fig.tight_layout()
    out = args.out or f"{args.dir}/path.png"
    fig.savefig(out, dpi=110)
    print(out)


if __name__ == "__main__":
    main()
