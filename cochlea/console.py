"""What every command-line program shares: standard output that a departed reader cannot
crash, and critical sections that an interrupt cannot cut in two.

``cochlea-run ... | head -1`` closes the pipe after the first line; the next ``print`` raises
BrokenPipeError, which would end a run mid-motion or before its report. Every command-line
program calls :func:`tolerate_closed_stdout` first: from then on a write to a closed pipe sends
the rest of the output to /dev/null and the program goes on (a run finishes, stops its motors
and keeps its log). :func:`stdout_was_closed` tells the few programs whose only product is their
output (``cochlea-model``) to exit with the shell's code for SIGPIPE instead.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys

#: Exit code when the reader of the output went away: 128 + SIGPIPE, as the shell reports a
#: program that signal ended (``yes | head -1`` under ``set -o pipefail``).
EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE


class _ClosedPipeTolerantStream:
    """Delegates to the real stream; a BrokenPipeError on write or flush points the file
    descriptor at /dev/null (so the interpreter's own flush at exit succeeds too) and is
    swallowed."""

    def __init__(self, stream):
        self._stream = stream
        self.closed_pipe = False

    def _divert(self) -> None:
        self.closed_pipe = True
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, self._stream.fileno())
            os.close(devnull)
        except (OSError, ValueError):  # no descriptor (a captured stream): nothing to divert
            pass

    def write(self, text: str) -> int:
        if self.closed_pipe:
            return len(text)
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._divert()
            return len(text)

    def flush(self) -> None:
        if self.closed_pipe:
            return
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._divert()

    def __getattr__(self, name):
        return getattr(self._stream, name)


def tolerate_closed_stdout() -> None:
    """Make ``sys.stdout`` survive a reader that went away (idempotent)."""
    if not isinstance(sys.stdout, _ClosedPipeTolerantStream) and sys.stdout is not None:
        sys.stdout = _ClosedPipeTolerantStream(sys.stdout)


def stdout_was_closed() -> bool:
    """Whether a write found standard output's reader gone since
    :func:`tolerate_closed_stdout`."""
    return isinstance(sys.stdout, _ClosedPipeTolerantStream) and sys.stdout.closed_pipe


@contextlib.contextmanager
def signals_held(signals=(signal.SIGINT, signal.SIGTERM)):
    """Hold ``signals`` off for a few steps that must happen together (create a folder and
    record it for clean-up; rename a set of files into place): one that arrives meanwhile is
    recorded and raised again as the section ends, so the program's own handler runs after the
    section, never inside it.

    Python-level handlers, not a signal mask: a mask covers only the calling thread, and a
    process-directed signal (Ctrl-C, ``kill``) goes to any thread that does not block it
    (numpy's, CasADi's), whose C handler then wakes the main thread's Python handler all the
    same. Only the main thread may set handlers: elsewhere the section is not held.
    """
    arrived: list[int] = []
    try:
        previous = {s: signal.signal(s, lambda signum, frame: arrived.append(signum))
                    for s in signals}
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)
        for signum in dict.fromkeys(arrived):  # each kind once, in order of arrival
            signal.raise_signal(signum)


@contextlib.contextmanager
def sigterm_interrupts():
    """SIGTERM (a batch system's or a cluster's stop) raises KeyboardInterrupt, as Ctrl-C does,
    for the section: the long-running programs that resume (cochlea-sweep, cochlea-tune) keep
    what finished and say so either way. The previous handler comes back afterwards."""
    def terminate(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
