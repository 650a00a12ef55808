"""The command-line parser of ``cochlea-identify`` and ``cochlea-excite``: a malformed option
(an unknown one, ``--harmonics 1e9`` for a whole number) is one line on stderr and exit code 2,
like every other refusal, not argparse's usage block."""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import threading

from ..errors import EXIT_USER_ERROR, printable


class OneLineParser(argparse.ArgumentParser):
    def error(self, message: str):  # noqa: D102 (argparse's hook)
        print(printable(f"{self.prog}: {message} (see {self.prog} --help)"), file=sys.stderr)
        sys.exit(EXIT_USER_ERROR)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the program is, like Ctrl-C: staged files are removed on the way
    out (cochlea.ident.files.Staged) and the program exits with EXIT_TERMINATED."""


#: The shell's code for SIGTERM.
EXIT_TERMINATED = 128 + signal.SIGTERM


@contextlib.contextmanager
def sigterm_unwinds():
    """SIGTERM raises :class:`Terminated` for the life of the block (in the main thread; the
    previous handler is restored), so no temporary file outlives a terminated write."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _raise(signum, frame):
        raise Terminated(signum)

    previous = signal.signal(signal.SIGTERM, _raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
