#!/usr/bin/env python
"""The compiled kernels of a Newton iteration on their own, at the state of a real scene: the
numbers docs/speed.md quotes for the elastic kernel and the chain LU, measured again in one go.

    .venv/bin/python tools/bench_kernels.py                      # 10^4 elements, 30 calls each
    .venv/bin/python tools/bench_kernels.py --sizes 1000,100000 --repeat 10

The scene is Mattiasson's cantilever (cases/mattiasson.opts) with -rod_nelem N, cubic elements,
at its reference state bent a little (every node's rotation turned and its position moved in
the plane by a smooth field, so that no strain is zero); one rank.  Each row is the fastest of
--repeat calls (the median beside it) of:

    plane tangent (lanes L)   the planar Newton step's in-plane tangents, L elements at once
                              (elastic_compiled.plane_tangents; 4 only with AVX2)
    3-D tangent               the 24 x 24 tangents of every element (element_terms)
    residual                  the residual summed per node (node_residual)
    energy                    the energy (node_energy: the line searches' trials)
    plane tangents into J     the same tangents added into the in-plane Jacobian's values as
                              they are made, stored at each block's first addition, the
                              other blocks zeroed (ElasticRod.tangents_into, zero_rest: the
                              Newton step's way)
    in-plane Jacobian         the whole Jacobian of the planar Newton step (its zeroing, the
                              tangents into it, the elements at the clamp, the assembly)
    chain LU factor / solve   rodsnes' LU of the in-plane Jacobian (chain.ChainLU), one rank
    PETSc LU factor / solve   PETSc's LU of the same matrix in the same (natural) order

Timings on a shared machine vary by 10-30 %: compare rows of one run, name the machine.
"""
import argparse
import os
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def best_of(fn, repeat):
    """(fastest, median) seconds of ``repeat`` calls of fn()."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times), float(np.median(times))


def scene_problem(n):
    """The RodProblem of Mattiasson's cantilever at n elements, its state bent a little (module
    docstring), and its planar system, on one rank."""
    from petsc4py import PETSc
    from rodsnes.io.scene import read_scene
    from rodsnes.run import Run
    opts = PETSc.Options()
    for key in list(opts.getAll()):
        opts.delValue(key)
    with open(os.path.join(ROOT, "cases", "mattiasson.opts")) as fh:
        for line in fh:
            parts = line.split("#")[0].split()
            if parts:
                opts.setValue(parts[0], parts[1] if len(parts) > 1 else "")
    for key, value in (("rod_nelem", str(n)), ("quiet", ""),
                       ("output_dir", tempfile.mkdtemp(prefix="bench_kernels_"))):
        opts.setValue(key, value)
    run = Run(read_scene(["rodsnes"], opts), PETSc.COMM_SELF)
    p = run.problem
    with p.state.X as a:                    # a smooth in-plane bend: no strain zero
        x = a.reshape(-1, 6)
        s = np.linspace(0.0, 1.0, len(x))
        plane = p.planar.plane if p.planar is not None else None
        P, Q = (plane.inplane[0], plane.inplane[1]) if plane else (0, 1)
        axis = plane.axis if plane else 2
        x[:, P] += 0.01 * np.sin(3.0 * s)
        x[:, Q] += 0.02 * s * s
        x[:, 3 + axis] += 0.1 * np.sin(2.0 * s)
    return run, p


def kernel_rows(p, repeat):
    """(name, fastest, median) of the elastic kernels at the problem's state."""
    from rodsnes.model import elastic_compiled
    rod = p.elastic
    r, q = p.state.local_config()
    r, q = np.ascontiguousarray(r), np.ascontiguousarray(q)
    conn = p.lconn
    qe, xe = np.take(q, conn, axis=0), np.take(r, conn, axis=0)
    rows = []
    axis = p.planar.plane.axis if p.planar is not None else 2
    out = np.empty((len(conn), 3 * conn.shape[1], 3 * conn.shape[1]))
    for lanes in (2, 4):
        try:
            elastic_compiled.plane_tangents(rod, qe, xe, axis, rod.e0, out=out, lanes=lanes)
        except ValueError:
            continue                        # no AVX2
        rows.append((f"plane tangent (lanes {lanes})", *best_of(
            lambda: elastic_compiled.plane_tangents(rod, qe, xe, axis, rod.e0, out=out,
                                                    lanes=lanes), repeat)))
    rows.append(("3-D tangent", *best_of(
        lambda: rod.element_terms(qe, xe, rod.e0, tangent=True, reuse=True), repeat)))
    rows.append(("residual", *best_of(lambda: rod.node_residual(q, r, conn, rod.e0), repeat)))
    rows.append(("energy", *best_of(lambda: rod.node_energy(q, r, conn, rod.e0), repeat)))
    return rows


def jacobian_rows(p, repeat):
    """(name, fastest, median) of the in-plane tangents added into the planar step's Jacobian
    and of that whole Jacobian."""
    from rodsnes.model import assembly
    from rodsnes.solve.planar import component_view
    pl = p.planar
    pl.assemble_tangent()
    view = component_view(pl, pl.J, pl.plane.inplane, p.constraints, pl.plane)
    r, q = p.state.local_config()
    r, q = np.ascontiguousarray(r), np.ascontiguousarray(q)
    blocks = assembly.element_blocks(pl.J, view.dirichlet, p._gconn, 3)
    rod = p.elastic
    def into():                             # as the Newton step's Jacobian does it
        blocks.zero_rest(pl.J)
        rod.tangents_into(q, r, p.lconn, blocks, rod.e0, plane=pl.plane, store_first=True)
    return [("plane tangents into J", *best_of(into, repeat)),
            ("in-plane Jacobian", *best_of(pl.assemble_tangent, repeat))]


def lu_rows(p, repeat):
    """(name, fastest, median) of the chain LU and PETSc's LU of the in-plane Jacobian."""
    from petsc4py import PETSc
    from rodsnes.solve import chain
    pl = p.planar
    pl.assemble_tangent()
    A = pl.J
    ai, aj = A.getRowIJ(compressed=True)
    lu = chain.ChainLU.plan(ai, aj, A.getBlockSize(), 1)
    b = A.createVecLeft()
    b.setRandom()
    x = b.duplicate()
    rows = [("chain LU factor", *best_of(lambda: lu.factor(A), repeat))]
    work = b.getArray().copy()
    rows.append(("chain LU solve", *best_of(lambda: lu.solve(work), repeat)))
    ksp = PETSc.KSP().create(PETSc.COMM_SELF)
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType("lu")
    pc.setFactorSolverType("petsc")
    pc.setFactorOrdering("natural")
    ksp.setOperators(A)
    ksp.setUp()
    diag = A.getValue(0, 0)

    def factor():                           # a new state of the same values: PCSetUp factors
        A.setValue(0, 0, diag)
        A.assemble()
        pc.setUp()
    rows.append(("PETSc LU factor", *best_of(factor, repeat)))
    rows.append(("PETSc LU solve", *best_of(lambda: ksp.solve(b, x), repeat)))
    ksp.destroy()
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="10000", help="element counts N (comma-separated)")
    ap.add_argument("--repeat", type=int, default=30, help="calls per row (the fastest kept)")
    args = ap.parse_args(argv)
    import petsc4py
    petsc4py.init([sys.argv[0]])
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from bench_scaling import machine       # '<cpu model>, <n> cores' (tools/, beside this)
    print(f"{machine()}; fastest (median) of {args.repeat} calls, milliseconds")
    print(f"| {'kernel':28s} | N | fastest | median |\n|---|---:|---:|---:|")
    for n in (int(v) for v in args.sizes.split(",")):
        run, p = scene_problem(n)
        rows = kernel_rows(p, args.repeat) + jacobian_rows(p, args.repeat) + \
            lu_rows(p, args.repeat)
        for name, fast, med in rows:
            print(f"| {name:28s} | {n} | {1e3 * fast:.3f} | {1e3 * med:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
