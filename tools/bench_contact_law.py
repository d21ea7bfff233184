"""Cost of the contact term, serial, CPU time (time.process_time: the 2-core machine is shared,
wall time is not), least of the repeats:

    .venv/bin/python tools/bench_contact_law.py [laws] [term] [search]

laws    one kernel evaluation under the two contact laws, on the plectoneme's strands in line
        contact at 9.72 turns (tests/data/plectoneme_9.72_line_contact.npy, 60 cubic elements):
        the closest-point law with contact zones (-contact_model projection) with its tangent,
        and the pair potential (-contact_model potential) with tangent and report, residual
        alone, tangent and report made afterwards (PotentialKernel.add_tangent, add_report);
term    the contact term of the assembled problem (ContactTerm) at the stored 10-turn state
        (tests/data/plectoneme_10 read by -restart, as tests/test_plectoneme.py does)
        with the case's pair potential: a residual at new positions (a Newton iterate or a
        line-search trial), the Jacobian after it, the pattern check of a Newton step, the
        report of a converged step; the candidate searches made and reused;
search  the candidate search (contact.element_bounds + candidate_pairs) on a helix whose turns
        touch, 1e3, 1e4 and 1e5 elements (positions built with numpy).
"""
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EPS, MU = 0.025, 5.754172062186161e7        # the plectoneme's contact radius and penalty at 9.72


def cpu_ms(f, reps=7):
    """Least CPU time of f() over reps calls, ms."""
    best = np.inf
    for _ in range(reps):
        t = time.process_time()
        f()
        best = min(best, time.process_time() - t)
    return 1e3 * best


def laws():
    from rodsnes.contact import search as C
    from rodsnes.contact.projection import ContactKernel
    from rodsnes.contact.potential import PotentialKernel
    X = np.load(os.path.join(ROOT, "tests", "data", "plectoneme_9.72_line_contact.npy"))
    order, delta = 3, np.pi * EPS
    nelem = (len(X) - 1) // order
    ids = np.arange(nelem)
    conn = C.element_node_ids(ids, order, nelem, False)
    kp = ContactKernel(order, 5, EPS, MU, delta, 1.0, nelem, False, segments=True)
    kq = PotentialKernel(order, 5, EPS, MU, delta, 1.0, nelem, False)
    xe = X[conn]
    cen, rad = C.element_bounds(xe)
    pairs = C.candidate_pairs(ids, cen, rad, ids, cen, rad, 2.5 * EPS, 1.0, 1.0 / nelem, False,
                              delta)
    args = (ids, xe, ids, xe, pairs)
    t = {"projection, with tangent": cpu_ms(lambda: kp.evaluate(*args, tangent=True), 3),
         "potential, with tangent and report": cpu_ms(lambda: kq.evaluate(*args)),
         "potential, residual alone": cpu_ms(lambda: kq.evaluate(*args, tangent=False,
                                                                  report=False))}
    alone = [kq.evaluate(*args, tangent=False, report=False) for _ in range(14)]
    t["potential, tangent made afterwards"] = cpu_ms(lambda: kq.add_tangent(alone.pop()))
    t["potential, report made afterwards"] = cpu_ms(lambda: kq.add_report(alone.pop()))
    out = kq.evaluate(*args)
    print(f"laws: {len(pairs)} candidate pairs, {len(out['_near']['oi'])} near, "
          f"{len(out['active'])} active, nqp {kq.nqp}")
    for k, v in t.items():
        print(f"  {k:40s} {v:9.2f} ms")
    print(f"  projection / potential (both full)       "
          f"{t['projection, with tangent'] / t['potential, with tangent and report']:9.1f}")


def term():
    import tempfile

    from petsc4py import PETSc

    from rodsnes.model.partition import NDOF
    from rodsnes.run import Run
    from rodsnes.io.scene import read_scene
    opts = PETSc.Options()
    with open(os.path.join(ROOT, "cases", "plectoneme.opts")) as fh:   # the case's options
        for line in fh:
            tok = line.split("#", 1)[0].split()
            if tok:
                opts.setValue(tok[0].lstrip("-"), " ".join(tok[1:]))
    for k, v in (("restart", os.path.join(ROOT, "tests", "data", "plectoneme_10")),
                 ("output_dir", tempfile.mkdtemp(prefix="bench_contact_law_")), ("quiet", "")):
        opts.setValue(k, v)
    run = Run(read_scene(["rodsnes"], opts), PETSc.COMM_WORLD)
    p, c = run.problem, run.contact
    r0, q0 = p.state.local_config()
    rng = np.random.default_rng(0)
    Floc = np.zeros((len(r0), NDOF))
    moved = []

    def new():
        moved.append(r0 + 1e-9 * rng.standard_normal(r0.shape))
        return moved[-1]

    def jacobian_after_residual():
        c.add_residual(p.lam, new(), q0, Floc)
        t = time.process_time()
        c.add_jacobian(p.lam, moved[-1], q0, p.J)
        dt = time.process_time() - t
        p.J.assemble()
        p.J.zeroEntries()
        return dt

    t = {"residual at new positions": cpu_ms(lambda: c.add_residual(p.lam, new(), q0, Floc)),
         "Jacobian after the residual": 1e3 * min(jacobian_after_residual() for _ in range(7)),
         "line-search trial (energy, depth)": cpu_ms(
             lambda: c.deepest_local(c.evaluate(new()))),
         "pattern check (ensure_pattern)": cpu_ms(p.ensure_pattern),
         "report (summary) after a residual": cpu_ms(
             lambda: (c.add_residual(p.lam, new(), q0, Floc), c.summary())) - cpu_ms(
             lambda: c.add_residual(p.lam, new(), q0, Floc))}
    print(f"term (plectoneme 10 turns, {c.model}): searches {c.searches}, reused "
          f"{c.search_reuses}, cache hits {c.cache_hits}")
    for k, v in t.items():
        print(f"  {k:40s} {v:9.2f} ms")


def helix(nelem, p=3, h=1.0 / 60, R=0.1):
    """Nodes of a helix of radius R whose turns press 1 % of the diameter 2 EPS into each other,
    elements of length h."""
    pitch = 2 * EPS * 0.99
    s = np.linspace(0.0, nelem * h, nelem * p + 1)
    t = 2 * np.pi * s / np.hypot(2 * np.pi * R, pitch)
    return np.stack([R * np.cos(t), R * np.sin(t), pitch * t / (2 * np.pi)], axis=1)


def search():
    from rodsnes.contact import search as ck
    print("search (helix, reach 2.5 eps):")
    for n in (1000, 10000, 100000):
        ids = np.arange(n)
        xe = helix(n)[ck.element_node_ids(ids, 3, n, False)]
        reps = 3 if n < 100000 else 2
        tb = cpu_ms(lambda: ck.element_bounds(xe), reps)
        c, r = ck.element_bounds(xe)
        pairs = []
        tc = cpu_ms(lambda: pairs.append(ck.candidate_pairs(
            ids, c, r, ids, c, r, 2.5 * EPS, n / 60, 1 / 60, False, np.pi * EPS)), reps)
        print(f"  {n:7d} elements: bounds {tb:8.1f} ms, candidate_pairs {tc:8.1f} ms, "
              f"{len(pairs[-1]) / n:.1f} pairs per element, {1e3 * (tb + tc) / n:.2f} us "
              f"per element")


if __name__ == "__main__":
    for what in sys.argv[1:] or ["laws", "term", "search"]:
        {"laws": laws, "term": term, "search": search}[what]()
