"""Errors a user sees: a scene that cannot be run, with the options it concerns, and the
lines that tell of errors, failures and warnings."""
import sys


def tell(kind, text):
    """``rodsnes: <kind>: <line>`` on stderr, one per line of text (the caller's rank decides
    who tells)."""
    for line in str(text).splitlines() or [""]:
        print(f"rodsnes: {kind}: {line}", file=sys.stderr, flush=True)


class SceneError(Exception):
    """A user-facing problem with the scene options.

    ``str(err)`` is the message to print (one problem per line); ``err.options``
    is the tuple of option names (with dash) it concerns.
    """

    def __init__(self, message, options=()):
        super().__init__(message)
        self.options = tuple(options)

    def __reduce__(self):
        """Pickled with its options (sent from one rank to the others)."""
        return type(self), (str(self), self.options)
