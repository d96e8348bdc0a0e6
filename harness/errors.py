"""The one exception type the project raises for bad input."""


class MpeError(Exception):
    """A user-facing error: its message is one line that names the culprit.

    The CLI prints it to stderr and exits with code 2, without a traceback.
    """
