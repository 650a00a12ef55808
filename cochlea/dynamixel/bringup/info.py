"""``cochlea-dxl info``: the registers the project relies on, per motor of the description,
against what the description and the runtime expect. Nothing is written.

Compared (a difference makes the exit code 1): the model number, the registers ``configure``
writes (:func:`~cochlea.dynamixel.bringup.common.runtime_settings`), Torque Enable 0 (nothing
should drive a motor during bring-up) and Hardware Error Status 0. Shown for the record: the
firmware, the baud rate, the position limits (unused in current control), and the Homing
Offset and Drive Mode, which the description's ``zero_offset_deg`` and ``direction`` were
calibrated with and must keep.
"""

from __future__ import annotations

import argparse

from . import common
from .common import Bus

NAME = "info"
HELP = ("compare the motors' registers with what the description and the runtime expect "
        "(exit 1 if one differs)")

#: Shown, never a difference (see the module docstring).
RECORD = ("Baud Rate", "Homing Offset", "Drive Mode", "Max Position Limit", "Min Position Limit")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    common.add_robot(parser)
    common.add_port(parser)
    common.add_baud(parser)


def run(args: argparse.Namespace) -> int:
    drives = common.load_drives(args)
    differences = 0
    alerted: list[str] = []
    with Bus(args.port, args.baud) as bus:
        common.check_chain(bus, drives)
        for d in drives:
            spec = d.spec
            rows = []
            firmware = bus.ping(d.id)[1]
            rows.append(("Model Number", "0", f"{spec.number} ({spec.name})",
                         f"{spec.number} ({spec.name})", ""))
            rows.append(("Firmware Version", "6", str(firmware), "-", ""))
            for s in common.runtime_settings(d):
                value = bus.read(d.id, s.item)
                ok = s.acceptable(value)
                rows.append((s.item.name, str(s.item.address),
                             common.value_text(s.item, value, spec),
                             common.value_text(s.item, s.value, spec) +
                             (" or the runtime's" if s.accept is not None else ""),
                             "" if ok else "DIFFERS"))
                differences += not ok
            for name, what in (("Torque Enable", "0 (off) during bring-up"),
                               ("Hardware Error Status", "0 (none)")):
                item = spec.item(name)
                value = bus.read(d.id, item)
                rows.append((name, str(item.address), common.value_text(item, value, spec),
                             what, "" if value == 0 else "DIFFERS"))
                differences += value != 0
                if name == "Hardware Error Status" and value:
                    alerted.append(str(d.id))
            for name in RECORD:
                item = spec.item(name)
                value = bus.read(d.id, item)
                rows.append((name, str(item.address), common.value_text(item, value, spec),
                             "as calibrated" if name in ("Homing Offset", "Drive Mode")
                             else f"{args.baud} baud" if name == "Baud Rate" else "-", ""))
            print(f"{bus.who(d.id)}")
            header = ("register", "address", "value", "expected", "")
            widths = [max(len(r[k]) for r in [header, *rows]) for k in range(5)]
            for r in [header, *rows]:
                print("  " + "  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip())
    if differences:
        print(f"info: {differences} register{'s differ' if differences != 1 else ' differs'} "
              f"from what the runtime expects (marked DIFFERS): cochlea-dxl configure writes "
              "them"
              + (f"; the hardware alert of ID {', '.join(alerted)} needs cochlea-dxl reboot "
                 f"--ids {','.join(alerted)} --port {args.port} --baud {args.baud}"
                 if alerted else ""))
        return common.EXIT_DIFFERS
    print(f"info: all {len(drives)} motors as the description and the runtime expect")
    return common.EXIT_OK
