#!/usr/bin/env python3
"""A checkpoint of a long run: the last steps of ``DIR/result.h5``, enough to resume it.

    .venv/bin/python tools/checkpoint.py DIR OUT [--steps 2]

Writes ``OUT/result.h5`` (format ``rodsnes-result-1``: the root attributes of DIR's file and
its last ``--steps`` complete steps, 2 by default: the last state, and the step before for the
secant predictor).  ``rodsnes ... -restart OUT -output_dir NEW`` then takes the steps the run
in DIR would have taken next (its stored next increment, penalty and eigenvalue count), and
``NEW/result.h5`` goes on with the step numbers of DIR.  A long path (the plectoneme: hours of
load steps) can be kept this way between machines (about 50 kB a step, against megabytes for
the whole path); tests/data/plectoneme_10 is the 10-turn plectoneme's last step.
"""
import argparse
import os
import sys

import h5py

from rodsnes.io import results as output


def checkpoint(src_dir, dst_dir, nsteps=2):
    """Copy the root attributes and the last ``nsteps`` complete steps; returns their indices."""
    steps = output.read_steps(src_dir)
    if not steps:
        raise SystemExit(f"{src_dir}/result.h5 holds no complete step")
    keep = steps[-max(1, int(nsteps)):]
    os.makedirs(dst_dir, exist_ok=True)
    dst = os.path.join(dst_dir, "result.h5")
    tmp = dst + ".tmp"
    with h5py.File(os.path.join(src_dir, "result.h5"), "r") as f, h5py.File(tmp, "w") as g:
        for k, v in f.attrs.items():
            g.attrs[k] = v
        grp = g.create_group("steps")
        for k in keep:
            name = output._step_name(k)
            f.copy(f["steps"][name], grp, name=name)
        g.attrs["last_step"] = keep[-1]
        g.attrs["checkpoint_of"] = os.path.abspath(src_dir)
    os.replace(tmp, dst)
    return keep


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dir", help="run directory holding result.h5")
    ap.add_argument("out", help="checkpoint directory (OUT/result.h5 is written)")
    ap.add_argument("--steps", type=int, default=2, help="complete steps kept (default 2)")
    a = ap.parse_args(argv)
    keep = checkpoint(a.dir, a.out, a.steps)
    last = output.read_step(a.out, -1)
    print(f"{a.out}/result.h5: steps {keep[0]}..{keep[-1]}, load {last['attrs']['load']:.6f}, "
          f"{os.path.getsize(os.path.join(a.out, 'result.h5')) / 1e3:.0f} kB")


if __name__ == "__main__":
    sys.exit(main())
