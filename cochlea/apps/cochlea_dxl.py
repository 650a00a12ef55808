"""``cochlea-dxl``: bring-up of the real motors (issue 15), one command with subcommands.

Each subcommand is a module of :mod:`cochlea.dynamixel.bringup` with ``NAME``, ``HELP``,
``add_arguments(parser)`` and ``run(args) -> int``; adding one adds it to ``SUBCOMMANDS``.

Exit codes (see :mod:`cochlea.dynamixel.bringup.common` and docs/hardware.md): 0 done; 1 a
check found a difference; 2 the user's input is wrong (one line, nothing written); 5 the port
or a motor of the description (as ``cochlea-run``); 130 interrupted. Only ``home`` and
``calibrate --torque-fit`` turn a motor's torque on, and they turn it off again whatever ends
them (an error, Ctrl-C).
"""

from __future__ import annotations

import argparse
import sys

from ..console import sigterm_interrupts, tolerate_closed_stdout
from ..dynamixel.bringup import calibrate, configure, home, info, reboot, scan
from ..errors import EXIT_USER_ERROR, CochleaError

SUBCOMMANDS = [scan, info, configure, reboot, calibrate, home]

EXIT_INTERRUPTED = 130


class _Parser(argparse.ArgumentParser):
    """An option the parser cannot read is one line naming it, as every other mistake is."""

    def error(self, message: str):
        self.exit(EXIT_USER_ERROR, f"{self.prog}: {message} (--help lists the options)\n")


def parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="cochlea-dxl",
        description="Bring-up of the Dynamixel motors: find them, compare and write the "
                    "registers the runtime relies on, reboot a motor in alert. Works on a real "
                    "port and on cochlea-emulator's pseudo-terminal alike.",
        epilog="A new lab: scan, configure --dry-run, configure, info (docs/hardware.md). "
               "Exit codes: 0 done, 1 a difference found, 2 a wrong option or file, 5 the port "
               "or a motor, 130 interrupted (Ctrl-C, SIGTERM, SIGHUP). Only home and "
               "calibrate --torque-fit turn a torque on, and off again whatever ends them.")
    sub = p.add_subparsers(dest="subcommand", metavar="SUBCOMMAND", required=True,
                           parser_class=_Parser)
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
        # SIGTERM and a hang-up (SIGHUP) end a subcommand as Ctrl-C does: its torques off.
        with sigterm_interrupts():
            return args._run(args)
    except CochleaError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return getattr(exc, "exit_code", EXIT_USER_ERROR)
    except KeyboardInterrupt:
        print(f"{name}: interrupted (every torque is off)", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
