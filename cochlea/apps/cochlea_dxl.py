"""``cochlea-dxl``: bring-up of the real motors (issue 15), one command with subcommands.

Each subcommand is a module of :mod:`cochlea.dynamixel.bringup` with ``NAME``, ``HELP``,
``add_arguments(parser)`` and ``run(args) -> int``; adding one adds it to ``SUBCOMMANDS``.

Exit codes (see :mod:`cochlea.dynamixel.bringup.common` and docs/hardware.md): 0 done; 1 a
check found a difference; 2 the user's input is wrong (one line, nothing written, nothing
moved: an output path that cannot be written included); 5 the port or a motor of the
description (as ``cochlea-run``); 6 a motor went into hardware alert during a move or a
configuration; 7 a motor stopped answering (or answered garbled or stale packets) during one;
128 + the signal's number when SIGHUP (129), SIGINT (130) or SIGTERM (143) stopped it. Only
``home`` and ``calibrate --torque-fit`` turn a motor's torque on, and they turn it off again
whatever ends them (an error, an alert, a signal); nothing is then written.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import threading

from ..console import OneLineParser, tolerate_closed_stdout
from ..dynamixel.bringup import calibrate, common, configure, home, info, reboot, scan
from ..errors import EXIT_USER_ERROR, CochleaError

SUBCOMMANDS = [scan, info, configure, reboot, calibrate, home]

EXIT_INTERRUPTED = 128 + signal.SIGINT  # 130
#: The signals that stop a command the safe way (torque off, nothing written), exit 128 + N.
STOP_SIGNALS = common.STOP_SIGNALS


class Interrupted(BaseException):
    """A stop signal arrived: raised in the main thread wherever it is, so that every
    ``finally`` and :func:`~cochlea.dynamixel.bringup.common.motion` runs its torque off (a
    BaseException, as KeyboardInterrupt, so that no ``except Exception`` swallows it)."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


@contextlib.contextmanager
def _stop_signals():
    """SIGINT, SIGTERM and SIGHUP raise :class:`Interrupted` once; later ones are ignored so
    that they cannot cut the clean-up short. The previous handlers come back at the end."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        for s in STOP_SIGNALS:
            signal.signal(s, signal.SIG_IGN)
        raise Interrupted(signum)

    previous = {s: signal.signal(s, handler) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="cochlea-dxl",
        description="Bring-up of the Dynamixel motors: find them, compare and write the "
                    "registers the runtime relies on, reboot a motor in alert. Works on a real "
                    "port and on cochlea-emulator's pseudo-terminal alike.",
        epilog="A new lab: scan, configure --dry-run, configure, info (docs/hardware.md). "
               "Exit codes: 0 done, 1 a difference found, 2 a wrong option or file (an "
               "output that cannot be written: checked before anything moves), 5 the port or "
               "a motor, 6 a hardware alert during a move, 7 a motor lost during a move, "
               "128+N stopped by signal N (129 SIGHUP, 130 SIGINT, 143 SIGTERM). Only home "
               "and calibrate --torque-fit turn a torque on, and off again whatever ends them.")
    sub = p.add_subparsers(dest="subcommand", metavar="SUBCOMMAND", required=True,
                           parser_class=OneLineParser)
    for module in SUBCOMMANDS:
        sp = sub.add_parser(module.NAME, help=module.HELP, description=module.HELP)
        module.add_arguments(sp)
        sp.set_defaults(_run=module.run)
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    tolerate_closed_stdout()
    name = f"cochlea-dxl {args.subcommand}"
    try:
        with _stop_signals():
            return args._run(args)
    except CochleaError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return getattr(exc, "exit_code", EXIT_USER_ERROR)
    except (Interrupted, KeyboardInterrupt) as exc:
        signum = getattr(exc, "signum", signal.SIGINT)
        failed = getattr(exc, "unconfirmed", None)
        torque = (f"torque off NOT confirmed by {', '.join(failed)}" if failed else
                  "every torque is off")
        with contextlib.suppress(OSError):  # SIGHUP: the terminal may be gone
            print(f"{name}: interrupted by {signal.Signals(signum).name} ({torque}); nothing "
                  "done, nothing written", file=sys.stderr)
        return 128 + signum


if __name__ == "__main__":
    sys.exit(main())
