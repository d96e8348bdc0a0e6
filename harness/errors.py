"""The one exception type the project raises for bad input."""

from __future__ import annotations


class MpeError(Exception):
    """A user-facing error: its message is one line that names the culprit.

    ``key`` is the configuration key at fault, when there is one, so that a
    caller who read the key from a file can say where it stands.
    The CLI prints the message to stderr and exits with code 2, without a
    traceback.
    """

    def __init__(self, message: str, key: str | None = None):
        super().__init__(message)
        self.key = key
