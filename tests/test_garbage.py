"""PETSc objects a run drops are destroyed as it goes, not kept to its end: petsc4py 3.18 parks
an object whose Python handle goes without destroy() in its communicator's garbage until
PetscFinalize or a cleanup (petsc_lib.release_garbage), and a run's memory grew by a vector or
more a load step (6 MB a step at 10^4 elements from the output fields, 28 MB at 10^5) and by
the valley walks' snapshots within a step."""
import contextlib
import ctypes
import gc
import io
import os
import re
import sys
import tempfile

import pytest
from petsc4py import PETSc

from conftest import run_case
from rodsnes import petsc_lib


def _printed(fun):
    """What ``fun()`` prints, wherever PETSc's printing goes: petsc4py sends it through a
    Python sys.stdout where one was installed when it was imported (under pytest's capture),
    else to C's stdout; both are caught (the Python stream redirected, file descriptor 1 put
    on a file, every buffer flushed)."""
    libc = ctypes.CDLL(None)
    text = io.StringIO()
    with tempfile.TemporaryFile(mode="w+") as fh:
        for stream in (sys.stdout, sys.__stdout__):
            stream.flush()
        libc.fflush(None)
        saved = os.dup(1)
        try:
            os.dup2(fh.fileno(), 1)
            with contextlib.redirect_stdout(text):
                fun()
            for stream in (sys.stdout, sys.__stdout__):
                stream.flush()
            libc.fflush(None)
        finally:
            os.dup2(saved, 1)
            os.close(saved)
        fh.seek(0)
        return text.getvalue() + fh.read()


def parked():
    """The objects in petsc4py's garbage now (PETSc.garbage_view's count, COMM_WORLD's and
    COMM_SELF's), serially."""
    total = 0
    for comm in (PETSc.COMM_WORLD, PETSc.COMM_SELF):
        out = _printed(lambda: PETSc.garbage_view(comm))
        m = re.search(r"Total entries: (\d+)", out)
        if m is None:
            raise RuntimeError("PETSc.garbage_view printed no count: " + out)
        total += int(m.group(1))
    return total


@pytest.mark.parametrize("case,kw", [
    # the minimiser's steps, a buckling one of 71 iterations with shifts and escapes (it left
    # 39 objects before the cleanups, 17 with the escape's mode and the shifted factor's
    # restriction destroyed)
    ("ltb", {}),
    # the Newton path's twelve steps (every step's output fields left 2 vectors)
    ("mattiasson", dict(rod_nelem=40, load_steps=12, load_path="newton")),
    # the plectoneme's first loads: valley walks within its steps (94 objects in a step of
    # 110 iterations before the minimiser's own cleanup)
    ("plectoneme", dict(load_stop=0.3))])
def test_dropped_objects_do_not_pile_up(case, kw, monkeypatch):
    if PETSc.COMM_WORLD.getSize() > 1:
        pytest.skip("the count is read serially")
    counts = []
    release = petsc_lib.release_garbage

    def counted(comm):
        counts.append(parked())
        release(comm)
    monkeypatch.setattr(petsc_lib, "release_garbage", counted)
    # a clean slate: the objects of earlier tests' runs, parked when the cyclic collector
    # takes those runs, are not this run's (the collector off while it runs)
    gc.collect()
    release(PETSc.COMM_WORLD)
    gc.disable()
    try:
        run = run_case(case, rod_error_estimate="off", **kw)
    finally:
        gc.enable()
    assert run.ok and len(counts) >= len(run.history)
    assert max(counts) <= 3, (max(counts), counts)
