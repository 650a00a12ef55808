"""Exception types for mistakes a user can make and fix.

Command-line entry points catch :class:`CochleaError`, print its message and exit with
``EXIT_USER_ERROR``: a wrong description or option never ends in a traceback.
"""

from __future__ import annotations

from pathlib import Path

#: Exit code of every command-line tool when the user's input is wrong.
EXIT_USER_ERROR = 2

_MISSING = object()


#: Control characters (C0, DEL, C1) as they may come from a file name or a value in a file:
#: printed raw, a NUL or an escape sequence garbles the terminal and a newline splits the
#: one-line message.
_CONTROL = {c: f"\\x{c:02x}" for c in (*range(0x00, 0x20), *range(0x7f, 0xa0))}


def printable(text: str) -> str:
    """``text`` with its control characters shown as ``\\xNN`` escapes: one line, nothing the
    terminal would act on."""
    return text.translate(_CONTROL)


class CochleaError(Exception):
    """Base class of errors caused by the user's input, with a message that says what to do.

    Its text is always one printable line (:func:`printable`), whatever the file names and
    values it quotes hold."""

    def __str__(self) -> str:
        return printable(super().__str__())


class DescriptionError(CochleaError):
    """A robot description (TOML) is malformed: names the file, the key and what was expected."""

    def __init__(self, path: str | Path, key: str, expected: str, got: object = _MISSING):
        self.path = str(path)
        self.key = key
        self.expected = expected
        self.got = got
        message = f"{self.path}: {key}: expected {expected}"
        if got is not _MISSING:
            shown = repr(got)
            # One line of reasonable length, whatever the file held (a megabyte-long string).
            message += f", got {shown if len(shown) <= 200 else shown[:200] + '...'}"
        super().__init__(message)


class ModelError(CochleaError):
    """A model was asked for something it does not have (unknown robot, arm, option)."""


class KinematicsError(CochleaError):
    """A kinematic target the mechanism cannot reach (out of the workspace or inconsistent)."""
