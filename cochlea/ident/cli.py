"""The command-line parser of ``cochlea-identify`` and ``cochlea-excite``: a malformed option
(an unknown one, ``--harmonics 1e9`` for a whole number) is one line on stderr and exit code 2,
like every other refusal, not argparse's usage block."""

from __future__ import annotations

import contextlib
import signal
import threading

from ..console import OneLineParser  # noqa: F401 (the ident tools' parser; shared)


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP (a hang-up: the terminal or session closed), raised where the program
    is, like Ctrl-C: staged files are removed on the way out (cochlea.ident.files.Staged) and
    the program exits with :func:`exit_code`."""

    @property
    def signum(self) -> int:
        return self.args[0] if self.args else signal.SIGTERM


#: The shell's code for SIGTERM (129 for SIGHUP: :func:`exit_code`).
EXIT_TERMINATED = 128 + signal.SIGTERM

#: The stops other than Ctrl-C (which Python raises as KeyboardInterrupt itself).
_UNWINDING = (signal.SIGTERM, signal.SIGHUP)


def exit_code(exc: Terminated) -> int:
    """The shell's code for the signal that ended the program: 128 + its number."""
    return 128 + int(exc.signum)


@contextlib.contextmanager
def sigterm_unwinds():
    """SIGTERM and SIGHUP raise :class:`Terminated` for the life of the block (in the main
    thread; the previous handlers are restored), so no temporary file outlives a terminated or
    hung-up write."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _raise(signum, frame):
        raise Terminated(signum)

    previous = {s: signal.signal(s, _raise) for s in _UNWINDING}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
