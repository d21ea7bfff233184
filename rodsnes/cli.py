"""rodsnes command line: scene -> mesh -> layout -> problem -> load stepping -> output.

    mpirun -n 2 rodsnes -options_file cases/rollup.opts -rod_nelem 64 -snes_monitor

Exit codes: 0 converged to load 1; 2 bad input (message names the option); 3 the load path
failed (the last converged step stays in DIR/result.h5 and DIR/summary.json says so).
"""
import os
import sys
import time


def _print0(comm, *args, **kw):
    if comm.getRank() == 0:
        print(*args, **kw, flush=True)


def main(argv=None):
    argv = list(sys.argv if argv is None else argv)
    import petsc4py
    petsc4py.init(argv)
    from petsc4py import PETSc
    from . import scene as scn
    comm = PETSc.COMM_WORLD
    opts = PETSc.Options()
    if opts.hasName("help") or opts.hasName("h"):
        _print0(comm, scn.help_text())
        _print0(comm, "PETSc's own options (-snes_*, -ksp_*, -pc_*, -mat_*, -log_view ...) work as usual;"
                      " run with -help -snes_view to list them.")
        return 0
    try:
        scn.check_unknown_options(opts)
        scene = scn.read_scene(argv, opts)
        from .run import Run
        run = Run(scene, comm)
    except scn.SceneError as err:
        _print0(comm, f"rodsnes: error: {err}", file=sys.stderr)
        return 2
    ok = run.execute()
    return 0 if ok else 3


if __name__ == "__main__":
    sys.exit(main())
