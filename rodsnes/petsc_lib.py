"""The PETSc library petsc4py runs on, reached through ctypes for the few functions petsc4py
3.18 does not wrap: the options nobody read (options_left), MUMPS's Schur complement
(solve/schur.py), a block matrix's value array and nonzero state (model/assembly.py).
"""
import contextlib
import ctypes
import ctypes.util
import functools

_INT = ctypes.c_int


def release_garbage(comm):
    """Destroy now, on every rank of ``comm`` together, the PETSc objects whose Python handles
    went without destroy(): petsc4py 3.18 does not destroy them but parks them in their
    communicator's garbage until PetscFinalize (a vector of a 10^4-element rod, 1.4 MB, stayed
    for the rest of the run: a run's memory grew by 6 MB a load step at 10^4 elements from
    its output fields alone, 28 MB at 10^5).  Those of COMM_SELF too (the ranks' own
    objects).  Collective: where every rank is at the same point of the run (a load step's
    end)."""
    from petsc4py import PETSc
    PETSc.garbage_cleanup(comm)
    PETSc.garbage_cleanup(PETSc.COMM_SELF)


@functools.lru_cache(maxsize=None)
def library():
    """ctypes.CDLL of the PETSc shared library loaded in this process (found in
    /proc/self/maps; else the one the linker finds), or None."""
    paths = []
    try:
        with open("/proc/self/maps") as maps:
            paths = sorted({line.split()[-1] for line in maps
                            if "/libpetsc" in line and ".so" in line})
    except OSError:
        pass
    for name in ("petsc_real", "petsc"):
        found = ctypes.util.find_library(name)
        if found:
            paths.append(found)
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
            lib.PetscInitialized        # noqa: B018 - probes that it is PETSc
            return lib
        except (OSError, AttributeError):
            continue
    return None


@functools.lru_cache(maxsize=None)
def function(name, *argtypes):
    """PETSc's C function ``name`` with those argument types (returning its error code), or
    None where the library or the function cannot be reached."""
    lib = library()
    try:
        # lib[name]: a function object of its own (getattr's is shared by every caller of the
        # name, whose argument types the last one set)
        fn = lib[name] if lib is not None else None
    except AttributeError:
        fn = None
    if fn is not None:
        fn.argtypes, fn.restype = list(argtypes), _INT
    return fn


def call(name, *args, argtypes=None):
    """function(name, argtypes...)(args), raising PETSc.Error on a nonzero error code and
    RuntimeError where the function cannot be reached."""
    from petsc4py import PETSc
    fn = function(name, *(argtypes or [ctypes.c_void_p] * len(args)))
    if fn is None:
        raise RuntimeError(f"PETSc's {name} cannot be reached through ctypes")
    code = fn(*args)
    if code:
        raise PETSc.Error(code)


_ARRAY = {"seqbaij": ("MatSeqBAIJGetArray", "MatSeqBAIJRestoreArray"),
          "seqsbaij": ("MatSeqSBAIJGetArray", "MatSeqSBAIJRestoreArray")}


def has_value_array(mat):
    """Whether values_of works on ``mat`` (a sequential BAIJ or SBAIJ matrix) here."""
    names = _ARRAY.get(mat.getType())
    return bool(names) and all(function(n, ctypes.c_void_p, ctypes.c_void_p) for n in names)


@contextlib.contextmanager
def values_of(mat):
    """The address of the value array of the sequential BAIJ or SBAIJ matrix ``mat`` (its
    blocks in the order of its block CSR, each bs x bs column by column), for the with
    block (MatSeqBAIJGetArray ... RestoreArray).  The caller assembles the matrix after."""
    with values_at(mat.handle, mat.getType()) as ptr:
        yield ptr


@contextlib.contextmanager
def values_at(handle, kind):
    """values_of for the matrix of PETSc handle ``handle`` and type ``kind``: for an object
    kept in the matrix's own attributes (setAttr), which must not hold a petsc4py wrapper of
    it - the cyclic garbage collector sees the attributes' dict through every wrapper (petsc4py
    traverses it) and, in a collection that leaves out the older wrapper that keeps the matrix,
    takes the dict, the object and the wrapper for an unreachable cycle and clears the dict:
    every attribute of the matrix gone (a split matrix taken for a block-6 one: a traceback in
    the bench coil, 1000 elements)."""
    get, restore = _ARRAY[kind]
    ptr = ctypes.c_void_p()
    call(get, handle, ctypes.byref(ptr))
    try:
        yield ptr.value
    finally:
        call(restore, handle, ctypes.byref(ptr))


def nonzero_state(mat):
    """PETSc's nonzero state of ``mat`` (MatGetNonzeroState): it changes when the matrix's
    pattern does."""
    state = ctypes.c_int64()
    call("MatGetNonzeroState", mat.handle, ctypes.byref(state))
    return state.value


PC_FACTOR_NUMERIC_ZEROPIVOT = 2     # PCFailedReason (PETSc's petscpctypes.h)


def set_pc_failed(pc, failed):
    """PCSetFailedReason(pc, a zero pivot if ``failed``, else none), which petsc4py 3.18
    lacks: a python PC's failed factorisation then fails its KSP (DIVERGED_PCSETUP_FAILED,
    -11, the solution Inf) as PETSc's LU's zero pivot does; the reason stays until set again.
    Where the C function cannot be reached nothing happens (the PC's NaN fails the step)."""
    try:
        call("PCSetFailedReason", ctypes.c_void_p(pc.handle),
             ctypes.c_int(PC_FACTOR_NUMERIC_ZEROPIVOT if failed else 0),
             argtypes=[ctypes.c_void_p, ctypes.c_int])
    except RuntimeError:
        pass


def options_left():
    """(name, value) of every option in PETSc's database that nothing has read yet
    (PetscOptionsLeftGet, as -options_left reports at the end); None where PETSc's library
    cannot be reached."""
    import numpy as np
    from petsc4py import PETSc
    lib = library()
    if lib is None or not hasattr(lib, "PetscOptionsLeftGet"):
        return None
    pint = ctypes.c_int64 if np.dtype(PETSc.IntType).itemsize == 8 else ctypes.c_int32
    n = pint(0)
    names = ctypes.POINTER(ctypes.c_char_p)()
    values = ctypes.POINTER(ctypes.c_char_p)()
    if lib.PetscOptionsLeftGet(None, ctypes.byref(n), ctypes.byref(names), ctypes.byref(values)):
        return None
    out = [(names[i].decode(), values[i].decode() if values[i] else None) for i in range(n.value)]
    lib.PetscOptionsLeftRestore(None, ctypes.byref(n), ctypes.byref(names), ctypes.byref(values))
    return out
