"""Exception types for mistakes a user can make and fix.

Command-line entry points catch :class:`CochleaError`, print its message and exit with
``EXIT_USER_ERROR``: a wrong description or option never ends in a traceback.
"""

from __future__ import annotations

from pathlib import Path

#: Exit code of every command-line tool when the user's input is wrong.
EXIT_USER_ERROR = 2

_MISSING = object()


class CochleaError(Exception):
    """Base class of errors caused by the user's input, with a message that says what to do."""


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
