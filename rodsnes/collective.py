"""Work that rank 0 alone does, met by every rank: its result sent to all, or its exception
raised on all, so that no rank is left waiting in a collective that rank 0 never reaches
(docs/parallel.md, What is collective).  Plain mpi4py: no PETSc (io/results.py uses it)."""
import pickle


def on_root(comm, fn, *args):
    """fn(*args) on rank 0 of the mpi4py communicator ``comm``; every rank returns its result,
    or raises its exception (one that cannot be pickled as a RuntimeError naming it).  On one
    rank fn(*args) itself.  Collective."""
    if comm.size == 1:
        return fn(*args)
    got = None
    if comm.rank == 0:
        try:
            got = (True, fn(*args))
        except Exception as exc:  # noqa: BLE001 - raised on every rank below
            try:
                pickle.dumps(exc)
            except Exception:  # noqa: BLE001 - an exception not to be sent as it is
                exc = RuntimeError(f"{type(exc).__name__}: {exc}")
            got = (False, exc)
    ok, value = comm.bcast(got, root=0)
    if not ok:
        raise value
    return value
