"""Errors a user sees: a scene that cannot be run, with the options it concerns."""


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
