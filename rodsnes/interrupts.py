"""SIGINT and SIGTERM during a run (cli.py installs ``handler`` while the run is on).

The handler raises Interrupted where the run is, except inside the writing of its output
(``deferred``): there the signal is kept and raised when the writing is done, so that a step is
written whole or not at all and no library's own clean-up is cut through.  A SIGTERM that landed
inside h5py's attribute creation (result.h5's commit) made h5py's clean-up fail in turn
(KeyError) and the run end with a traceback and exit 1 instead of its message and 128 + signal;
under MPI a rank interrupted inside a collective write would leave the others waiting."""
import contextlib
import signal


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM during a run (raised by ``handler``)."""

    def __init__(self, signum):
        super().__init__(signum)
        self.signum = signum
        self.name = signal.Signals(signum).name


_STATE = {"depth": 0, "pending": None}      # deferred() nesting, the signal kept meanwhile


def handler(signum, frame):
    """The signal handler: Interrupted now, or when the writing under way is done."""
    if _STATE["depth"]:
        _STATE["pending"] = signum
        return
    raise Interrupted(signum)


@contextlib.contextmanager
def deferred(keep=True):
    """A section the handler does not cut: a signal arriving inside is raised as Interrupted
    when it ends normally (with ``keep`` False it is dropped: the run is ending for it
    already)."""
    _STATE["depth"] += 1
    try:
        yield
    finally:
        _STATE["depth"] -= 1
        if not keep and _STATE["depth"] == 0:
            _STATE["pending"] = None
    if _STATE["depth"] == 0 and _STATE["pending"] is not None:
        signum, _STATE["pending"] = _STATE["pending"], None
        raise Interrupted(signum)
