"""Shared test helpers: run a scene from a cases/*.opts file with overrides, in-process."""
import os
import shlex
import tempfile

import numpy as np
import pytest
from petsc4py import PETSc

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load_tool(name):
    """The module tools/<name>.py (tools are scripts, not a package)."""
    import importlib.util
    spec = importlib.util.spec_from_file_location(f"tool_{name}", os.path.join(ROOT, "tools", f"{name}.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def read_opts_file(path):
    """Options file -> list of (name, value) pairs (PETSc syntax: '-name value', '#' comments)."""
    pairs = []
    with open(path) as fh:
        for line in fh:
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            tok = shlex.split(line)
            name = tok[0].lstrip("-")
            pairs.append((name, " ".join(tok[1:]) if len(tok) > 1 else None))
    return pairs


def clear_options():
    opts = PETSc.Options()
    for k in list(opts.getAll().keys()):
        opts.delValue(k)


# options every run of the current test module gets unless it says otherwise (newton_path)
DEFAULT_OVERRIDES = {}


@pytest.fixture(scope="module")
def newton_path():
    """The test's runs take -load_path newton (the Newton path's own machinery: cut-back,
    secant predictor, stability count, pseudo-arclength continuation) unless they say
    otherwise.  Use with pytestmark = pytest.mark.usefixtures("newton_path")."""
    DEFAULT_OVERRIDES["load_path"] = "newton"
    yield
    DEFAULT_OVERRIDES.pop("load_path", None)


def set_options(case=None, **overrides):
    """Fill the options database from cases/<case>.opts and keyword overrides
    (rod_nelem=8; a value of True means a bare flag)."""
    clear_options()
    opts = PETSc.Options()
    for k, v in DEFAULT_OVERRIDES.items():
        overrides.setdefault(k, v)
    pairs = read_opts_file(os.path.join(ROOT, "cases", case + ".opts")) if case else []
    for k, v in pairs:
        opts.setValue(k, v if v is not None else "")
    for k, v in overrides.items():
        if v is True:
            opts.setValue(k, "")
        elif v is False or v is None:
            if opts.hasName(k):
                opts.delValue(k)
        else:
            opts.setValue(k, str(v))
    return opts


def build_run(case=None, comm=None, outdir=None, **overrides):
    """A Run of a scene on ``comm`` (default COMM_WORLD), not executed, writing into outdir
    (rank 0's, the same directory on every rank; a fresh temporary one if None)."""
    from rodsnes.run import Run
    from rodsnes.io.scene import read_scene, check_unknown_options
    comm = PETSc.COMM_WORLD if comm is None else comm
    mpi = comm.tompi4py()
    if mpi.rank == 0:
        outdir = tempfile.mkdtemp(prefix="rodsnes_test_") if outdir is None else str(outdir)
    outdir = mpi.bcast(outdir)
    overrides.setdefault("output_dir", outdir)
    overrides.setdefault("quiet", True)
    opts = set_options(case, **overrides)
    check_unknown_options(opts)
    return Run(read_scene(["rodsnes"], opts), comm)


def run_case(case=None, comm=None, outdir=None, **overrides):
    """Run a scene in-process on ``comm`` (default COMM_WORLD); returns the finished Run."""
    run = build_run(case, comm, outdir, **overrides)
    run.ok = run.execute()
    return run


def gathered_positions(run):
    return run.layout.allgather_nodes(run.last_fields["positions"])


def place(run, x, t):
    """Put the rod of a built run on the natural-ordered node positions x (n, 3) with unit
    tangents t (n, 3) (frames from the tangent, rotation increments zero)."""
    from rodsnes.model import so3
    from rodsnes.model.partition import NDOF
    p, lay = run.problem, run.layout
    p.state.q_ref[:] = so3.quat_from_rot(so3.frame_from_tangent(t))[lay.local_nodes]
    with p.state.X as a:
        a = a.reshape(-1, NDOF)
        a[:, 0:3] = x[lay.owned_nodes]
        a[:, 3:6] = 0.0


def coiled_rollup(comm=None, outdir=None, **extra):
    """The rollup_contact rod (12 elements) with no load, put on a circle of 1.05 turns whose
    free end overlaps the clamped start by a fraction of the contact diameter (``extra``: more
    options)."""
    run = run_case("rollup_contact", comm=comm, outdir=outdir,
                   **{**dict(rod_nelem=12, load_steps=1, load_end_moment="0,0,0"), **extra})
    m = run.mesh
    R = m.length / (2 * np.pi * 1.05)
    ph = m.s_nodes / R
    x = np.stack([R * np.sin(ph), R * (1 - np.cos(ph)) - 0.12 * m.s_nodes / m.length, 0 * ph], 1)
    place(run, x, np.stack([np.cos(ph), np.sin(ph), 0 * ph], 1))
    return run


def tangent_against_finite_differences(p, J, seed, h=1e-7):
    """Central differences of the assembled residual of problem p at its state along a random
    direction v (zero on the constrained rows): returns (fd, J v, v) as PETSc vectors."""
    X = p.state.X
    rng = np.random.default_rng(seed + PETSc.COMM_WORLD.getRank())
    v = X.duplicate()
    with v as a:
        a[:] = rng.normal(size=a.shape)
        a[p.constraints.rows_local] = 0.0
    Fp, Fm, Jv = X.duplicate(), X.duplicate(), X.duplicate()
    Xp, Xm = X.copy(), X.copy()
    Xp.axpy(h, v)
    Xm.axpy(-h, v)
    p.residual(None, Xp, Fp)
    p.residual(None, Xm, Fm)
    J.mult(v, Jv)
    fd = Fp - Fm
    fd.scale(1 / (2 * h))
    return fd, Jv, v


def perturb_state(p, scale=1e-3, seed=3):
    """Move every unconstrained dof of problem ``p`` by a deterministic small amount (the same
    on any number of ranks: drawn for the global dofs, each rank takes its own)."""
    X = p.state.X
    lo, hi = X.getOwnershipRange()
    d = np.random.default_rng(seed).normal(size=X.getSize()) * scale
    with X as a:
        free = np.ones(hi - lo, dtype=bool)
        free[p.constraints.rows_local] = False
        a[free] += d[lo:hi][free]


def inertia_solve(inertia, backward):
    """(b, x): x = (H + shift)^-1 b by the last factor of ``inertia`` (stability.Inertia or a
    subclass) for the smooth b_i = sin(0.37 i), checked to a backward error |H x - b| <=
    ``backward`` |H| |x| (H holds the factored diagonal)."""
    H = inertia.H
    b = H.createVecRight()
    lo, hi = b.getOwnershipRange()
    b.setArray(np.sin(0.37 * np.arange(lo, hi)))
    x = b.duplicate()
    inertia.solve(b, x)
    r = b.duplicate()
    H.mult(x, r)
    r.axpy(-1.0, b)
    assert r.norm() <= backward * H.norm(PETSc.NormType.INFINITY) * x.norm()
    r.destroy()
    return b, x


def natural_residuals(*runs):
    """Each run's assembled residual at its state, natural-ordered (n, NDOF) on every rank."""
    from rodsnes.model.partition import NDOF
    out = []
    for run in runs:
        F = run.problem.F.duplicate()
        run.problem.residual(None, run.problem.state.X, F)
        out.append(run.layout.allgather_nodes(F.getArray(readonly=True).reshape(-1, NDOF)))
    return out


@pytest.fixture(autouse=True)
def _fresh_options():
    clear_options()
    yield
    clear_options()


def pytest_collection_modifyitems(config, items):
    """Files by their expected time, longest first, each file's tests together and in their
    order (module fixtures are made once): under pytest-xdist (--dist loadfile) the longest
    files start at once instead of last, when one worker would run them alone (longest
    processing time first).  A test marked slow counts its ``seconds`` (measured on the 2-core
    machine; 10 when not given), any other 0.5."""
    def seconds(item):
        mark = item.get_closest_marker("slow")
        return 0.5 if mark is None else float(mark.kwargs.get("seconds", 10.0))
    weight = {}
    for item in items:
        weight[item.fspath] = weight.get(item.fspath, 0.0) + seconds(item)
    first = {f: i for i, f in enumerate(dict.fromkeys(item.fspath for item in items))}
    items.sort(key=lambda item: (-weight[item.fspath], first[item.fspath]))
