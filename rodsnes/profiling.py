"""PETSc log events for rodsnes' own work, so that ``-log_view`` splits a Newton iteration's
residual and Jacobian into the elastic kernel and the parts of self-contact
(tools/bench_scaling.py reads them):

    ElasticKernel    element energy gradient and tangent of the rod (elastic.py)
    ContactSearch    candidate pairs: bounding spheres, their allgather, the cKDTree
    ContactEval      the contact kernel's energy and residual (closest points / pair potential)
    ContactTangent   the contact kernel's tangent blocks
    ContactHalo      positions of remote master elements in, their forces back (PetscSF)
    ContactAssemble  the contact tangent blocks into the global matrix
    MinStep          one load step of the minimiser (minimize.py; the events below inside it)
    MinGradient      the minimiser's gradient (the residual)
    MinNewton        the consistent tangent, its LU and the Newton direction
    MinHessian       the symmetric Hessian and its LDL^T factorisations (shifts, certificate)
    MinLineSearch    the energy line search (trial energies)
    MinCurved        the curved trial of a full Newton step (a residual, a factorisation, a trial)
    ChainFactor      a rank's stretch factored by its own LU without fill (solve/chain.py)
    ChainSolve       its substitutions (whole, or over the stretch's last rows)

Work done once before or after the path, not in its iterations, runs in a log stage of its
own (the bench leaves both out of its per-iteration parts and reports the set-up apart):
``with stage(SET_UP):`` (-log_view's "Event Stage 2: SetUp"), the solver's set-up, as PETSc's
SNESSetUp before a solve: the Newton step's matrix preallocated, its LU chosen and planned
for the pattern (Run._execute: the solver's setup()); ``with stage(PATH_END):`` ("PathEnd"),
the stability count at the end of a Newton path.

A call site is either a ``with timed("ContactSearch"):`` block or a method decorated with
``@logged("ContactSearch")``.  Events nest in PETSc's log: the time of one counts inside the
SNES events around it (SNESFunctionEval, SNESJacobianEval, SNESLineSearch), and an event
entered again inside itself is counted once.  Events are registered at first use, after
PETSc is initialised (rodsnes.cli initialises it with the command line, so -log_view is seen).
"""
import contextlib
import functools

NAMES = ("ElasticKernel", "ContactSearch", "ContactEval", "ContactTangent", "ContactHalo",
         "ContactAssemble", "MinStep", "MinGradient", "MinNewton", "MinHessian", "MinLineSearch",
         "MinCurved", "ChainFactor", "ChainSolve")

_events = {}
_stages = {}

# the log stages of the work done once before and at the end of the path (module docstring)
SET_UP = "SetUp"
PATH_END = "PathEnd"


def event(name):
    """The PETSc.Log.Event called ``name`` (one of NAMES), registered at first use."""
    if name not in NAMES:
        raise KeyError(f"unknown rodsnes log event {name!r} (one of {', '.join(NAMES)})")
    ev = _events.get(name)
    if ev is None:
        from petsc4py import PETSc
        ev = _events[name] = PETSc.Log.Event(name)
    return ev


@contextlib.contextmanager
def timed(name):
    """Log the block as event ``name``."""
    ev = event(name)
    ev.begin()
    try:
        yield
    finally:
        ev.end()


def logged(name):
    """Decorator: log every call of the function as event ``name``.  The wrapper carries
    ``rod_event = name`` (tools/bench_scaling.py does not wrap a method twice)."""
    def wrap(fun):
        @functools.wraps(fun)
        def inner(*args, **kw):
            ev = event(name)
            ev.begin()
            try:
                return fun(*args, **kw)
            finally:
                ev.end()
        inner.rod_event = name
        return inner
    return wrap


@contextlib.contextmanager
def stage(name):
    """Log the block in PETSc's log stage ``name`` (registered at first use)."""
    st = _stages.get(name)
    if st is None:
        from petsc4py import PETSc
        st = _stages[name] = PETSc.Log.Stage(name)
    st.push()
    try:
        yield
    finally:
        st.pop()
