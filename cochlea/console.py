"""What every command-line program shares: standard output that a departed reader cannot
crash, critical sections that an interrupt cannot cut in two, and option mistakes told in
one line (:class:`OneLineParser`).

``cochlea-run ... | head -1`` closes the pipe after the first line; the next ``print`` raises
BrokenPipeError, which would end a run mid-motion or before its report. A terminal or SSH
session that closes (a hang-up, SIGHUP) does the same to both standard output and standard
error: a write then fails with EIO (a pseudo-terminal whose other end is gone) or EPIPE (ssh's
pipes). Every command-line program calls :func:`tolerate_closed_stdout` first: from then on a
write to a closed pipe or terminal sends the rest of that stream to /dev/null and the program
goes on (a run finishes, stops its motors and keeps its log). :func:`stdout_was_closed` tells
the few programs whose only product is their output (``cochlea-model``) to exit with the
shell's code for SIGPIPE instead.

:data:`STOP_SIGNALS` are the signals every program treats as a request to stop: SIGINT
(Ctrl-C), SIGTERM (``kill``, a batch system) and SIGHUP (the terminal or session closed: a
hang-up is a stop like SIGTERM, never a death without the safe stop).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
import signal
import sys
from multiprocessing import resource_tracker

from .errors import EXIT_USER_ERROR, printable

#: Exit code when the reader of the output went away: 128 + SIGPIPE, as the shell reports a
#: program that signal ended (``yes | head -1`` under ``set -o pipefail``).
EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE

#: The signals that ask a program to stop (module docstring): SIGHUP is handled like SIGTERM.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

#: A write to a stream whose reader went away: a closed pipe (EPIPE), a terminal that hung up
#: (EIO).
_GONE = (errno.EPIPE, errno.EIO)


class OneLineParser(argparse.ArgumentParser):
    """An option the parser cannot read (unknown, missing, ``--force-N 0_5`` for a number:
    cochlea.text.number_argument) is one line on stderr naming it and exit code 2, like every
    other refusal, not argparse's usage block. Its subcommands' parsers are of this class too
    (argparse makes them of the parent's class)."""

    def error(self, message: str):  # noqa: D102 (argparse's hook)
        print(printable(f"{self.prog}: {message} (see {self.prog} --help)"), file=sys.stderr)
        sys.exit(EXIT_USER_ERROR)


def _reader_gone(exc: OSError) -> bool:
    return isinstance(exc, BrokenPipeError) or exc.errno in _GONE


class _ClosedPipeTolerantStream:
    """Delegates to the real stream; a write or flush that finds the reader gone (EPIPE, or EIO
    from a terminal that hung up) points the file descriptor at /dev/null (so the interpreter's
    own flush at exit succeeds too) and is swallowed; any other error is raised."""

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
        except OSError as exc:
            if not _reader_gone(exc):
                raise
            self._divert()
            return len(text)

    def flush(self) -> None:
        if self.closed_pipe:
            return
        try:
            self._stream.flush()
        except OSError as exc:
            if not _reader_gone(exc):
                raise
            self._divert()

    def __getattr__(self, name):
        return getattr(self._stream, name)


def tolerate_closed_stdout() -> None:
    """Make ``sys.stdout`` and ``sys.stderr`` survive a reader that went away: a closed pipe or
    a terminal that hung up (idempotent)."""
    if not isinstance(sys.stdout, _ClosedPipeTolerantStream) and sys.stdout is not None:
        sys.stdout = _ClosedPipeTolerantStream(sys.stdout)
    if not isinstance(sys.stderr, _ClosedPipeTolerantStream) and sys.stderr is not None:
        sys.stderr = _ClosedPipeTolerantStream(sys.stderr)


def stdout_was_closed() -> bool:
    """Whether a write found standard output's reader gone since
    :func:`tolerate_closed_stdout`."""
    return isinstance(sys.stdout, _ClosedPipeTolerantStream) and sys.stdout.closed_pipe


@contextlib.contextmanager
def signals_held(signals=STOP_SIGNALS):
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


def _start_resource_tracker_deaf_to_hangups() -> None:
    """multiprocessing's resource tracker (the process that removes the semaphores of a
    sweep's or a tune's worker pool) ignores SIGINT and SIGTERM but not SIGHUP: a terminal's
    hang-up, which goes to the whole process group, would kill it, leak what it tracks and
    print its tracebacks. Started here with SIGHUP ignored (a disposition that exec keeps), it
    outlives the hang-up and cleans up as the program ends. Nothing if it already runs."""
    try:
        previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    except ValueError:  # not the main thread
        return
    try:
        resource_tracker.ensure_running()
    except OSError:  # no tracker: the pool starts its own as before
        pass
    finally:
        signal.signal(signal.SIGHUP, previous)


@contextlib.contextmanager
def stop_signals_raise(exception):
    """For the section, SIGTERM and SIGHUP raise ``exception(signum)`` (a KeyboardInterrupt,
    as Ctrl-C's) in the main thread, so that the section unwinds through its ``finally``
    blocks; the previous handlers come back afterwards."""
    def unwind(signum, frame):
        raise exception(signum)

    previous = {s: signal.signal(s, unwind) for s in (signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


@contextlib.contextmanager
def sigterm_interrupts():
    """SIGTERM (a batch system's or a cluster's stop) and SIGHUP (the terminal or session
    closed) raise KeyboardInterrupt, as Ctrl-C does, for the section: the long-running programs
    that resume (cochlea-sweep, cochlea-tune) keep what finished and say so either way. The
    previous handlers come back afterwards."""
    _start_resource_tracker_deaf_to_hangups()
    with stop_signals_raise(lambda signum: KeyboardInterrupt()):
        yield
