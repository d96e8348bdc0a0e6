"""The one exception type the project raises for bad input, and the checks
that phrase its messages (shared by run keys and solver options)."""

from __future__ import annotations

import difflib
from typing import Any


class MpeError(ValueError):
    """A user-facing error: its message is one line that names the culprit.

    ``key`` is the configuration key at fault, when there is one, so that a
    caller who read the key from a file can say where it stands; ``hint`` is a
    trailing suggestion such as `` (did you mean 'views'?)``, kept apart so the
    location goes before it. The CLI prints the message to stderr and exits
    with ``exit_code`` (2, bad input), without a traceback.
    """

    exit_code = 2

    def __init__(self, message: str, key: str | None = None, hint: str = ""):
        super().__init__(message + hint)
        self.message, self.key, self.hint = message, key, hint

    def located(self, where: str) -> "MpeError":
        """The same error, saying where it stands: ``... at file.yaml:7 (did you mean ...)``."""
        return MpeError(f"{self.message} at {where}", key=self.key, hint=self.hint)


class MachineError(MpeError):
    """The machine, not the input, is at fault: no space left in a scratch
    folder, a folder that cannot be written (exit code 3)."""

    exit_code = 3


class StoreError(MachineError):
    """The tracking store failed or cannot be reached: not the user's input
    (exit code 3). Results computed meanwhile stay in the local journal."""


class DiskFull(StoreError):
    """No space left where the store, its artifacts or the journal are written
    (exit code 3); ``path`` is where the write failed."""

    def __init__(self, message: str, path: str):
        super().__init__(message)
        self.path = path


class Unregistered(MpeError):
    """A structure-from-motion method registered fewer than two views.

    The method's own honest outcome on its input, not a failure: a run that
    ends so is a finished run with no cloud (``registered_views`` 0), where
    any other error makes the run FAILED, for every method alike.
    """


def first_line(exc: BaseException, limit: int = 300) -> str:
    """An exception's first line of text (its type's name when it has none)."""
    lines = str(exc).strip().splitlines()
    return lines[0][:limit] if lines else type(exc).__name__


def suggest(name: str, candidates) -> str:
    """`` (did you mean 'x'?)`` for the closest candidate, or an empty string."""
    match = difflib.get_close_matches(name, list(candidates), n=1, cutoff=0.5)
    return f" (did you mean '{match[0]}'?)" if match else ""


_WANTED = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


def coerce(key: str, value: Any, kind: type) -> Any:
    """``value`` as ``kind`` (ints are accepted as floats, bools never as numbers)."""
    is_number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind is bool and isinstance(value, bool):
        return value
    if kind is int and is_number and isinstance(value, int):
        return int(value)
    if kind is float and is_number:
        return float(value)
    if kind is float and isinstance(value, str):  # YAML 1.1 reads 1e-12 (no dot) as text
        try:
            number = float(value)
        except ValueError:
            number = float("nan")
        if number == number and abs(number) != float("inf"):
            return number
    if kind is str and isinstance(value, str):
        return value
    if kind not in _WANTED:  # an option without a typed default takes anything
        return value
    raise MpeError(f"{key}: expected {_WANTED[kind]}, got {value!r}", key=key)
