"""Python PCs released before the interpreter exits (schur.RankSchur, planar's PC).

petsc4py 3.18 runs PetscFinalize after the interpreter is gone (a C-level exit hook), and the
PETSc objects whose Python handles go during the interpreter's teardown are only put in
PETSc's garbage list, to be destroyed in PetscFinalize.  A python PC among them (a script
that never destroys its KSP) then calls its context's reset and destroy on a finalised
interpreter: a segmentation fault at exit, whatever the context holds, the results already
written.  So a python PC registers itself here (``live``: its handle, no reference held), and
an atexit hook, which runs while the interpreter and PETSc are whole, turns every PC still
alive into a PC of type none: its context's destroy runs then, and PETSc keeps no Python to
call.  Finalising PETSc itself at that point instead would also finalise MPI where PETSc
initialised it, before mpi4py's objects are freed (MPI_Type_free after MPI_Finalize).
The hook's set-type is collective: every rank holds the same python PCs, registered in the
same order (SPMD)."""
import atexit
import ctypes

from petsc4py import PETSc

_LIVE = {}          # handle -> None, in the order of registration


def live(pc):
    """Register the python PC ``pc`` (its context's create, setUp)."""
    _LIVE.setdefault(pc.handle, None)


def gone(pc):
    """Unregister it (its context's destroy)."""
    _LIVE.pop(pc.handle, None)


def _pc_of(handle):
    """A petsc4py PC (a new reference) for the PC at ``handle``: petsc4py 3.18 has no
    PC.fromHandle; its C API (PyPetscPC_New, exported in PETSc.__pyx_capi__) has."""
    api = ctypes.PyDLL(None)                # not ctypes.pythonapi, whose prototypes are shared
    api.PyCapsule_GetName.restype = ctypes.c_char_p
    api.PyCapsule_GetName.argtypes = [ctypes.py_object]
    api.PyCapsule_GetPointer.restype = ctypes.c_void_p
    api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    capsule = PETSc.__pyx_capi__["PyPetscPC_New"]
    new = ctypes.PYFUNCTYPE(ctypes.py_object, ctypes.c_void_p)(
        api.PyCapsule_GetPointer(capsule, api.PyCapsule_GetName(capsule)))
    return new(handle)


def _release_at_exit():
    if not _LIVE or PETSc.Sys.isFinalized():
        return
    for handle in list(_LIVE):
        pc = _pc_of(handle)
        pc.setType(PETSc.PC.Type.NONE)      # the context's destroy: gone(pc)
        _LIVE.pop(handle, None)
        del pc


# registered after petsc4py's import (above); atexit runs the last registered first, and
# petsc4py finalises PETSc after the interpreter anyway
atexit.register(_release_at_exit)
