"""``cochlea-dxl configure``: write what the runtime needs into the motors, then read it back.

1. Every motor of the description answers PING as its model, none in hardware alert, and every
   register is read: all checked before anything is written (exit 5 otherwise).
2. The plan: per motor, Torque Enable 0 if it is on (EEPROM accepts writes only with the torque
   off), then each register of :func:`~cochlea.dynamixel.bringup.common.runtime_settings` that
   differs; ``--baud-to`` last, on every motor. ``--dry-run`` prints it and writes nothing; a
   chain already configured gets no write at all ("already configured").
3. The writes, each confirmed by its status packet (a motor at Status Return Level below 2
   does not answer a WRITE: that one register is written unconfirmed and read back).
   Every status packet is watched: a hardware alert, a motor that stops answering or answers
   a garbled or stale packet stops the writes (torque off on every motor; exit 6 or 7).
4. The verify pass reads every register back: one that did not take is exit 1, naming the
   motor and the register.
5. ``--baud-to``: the Baud Rate of every motor, the port reopened at the new rate, and the
   chain checked and verified again there.

The torque is never turned on.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

from ...console import signals_held
from ..control_table import Item, baud_code
from ..drives import JointDrive
from . import common
from .common import Bus, BusError

NAME = "configure"
HELP = ("write what the runtime needs (return delay 0, current control, current limit, ...), "
        "then verify by reading back")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    common.add_robot(parser)
    common.add_port(parser)
    common.add_baud(parser)
    parser.add_argument("--baud-to", type=common.baud_rate, metavar="B",
                        help="change the motors' baud rate to B, last, and verify there (the "
                             "runtime's default is 4000000)")
    parser.add_argument("--dry-run", action="store_true",
                        help="print every write (motor, register, address, value) and write "
                             "nothing")


@dataclass(frozen=True)
class Write:
    drive: JointDrive
    item: Item
    present: int
    value: int
    why: str
    confirmed: bool = True  # a status packet answers it

    def text(self) -> str:
        spec = self.drive.spec
        return (f"ID {self.drive.id} ({self.drive.name}, {spec.name}): {self.item.name} "
                f"({self.item.address}) {common.value_text(self.item, self.present, spec)} -> "
                f"{common.value_text(self.item, self.value, spec)}: {self.why}")


def _plan(bus: Bus, drives: list[JointDrive], baud_to: int | None) -> tuple[list[Write],
                                                                            list[Write]]:
    """``(register writes, baud writes)`` from what the motors hold now; refuses a motor in
    hardware alert before anything is written."""
    writes, bauds, alerts = [], [], []
    for d in drives:
        spec = d.spec
        status = bus.read(d.id, spec.item("Hardware Error Status"))
        if status:
            alerts.append((d.id, f"{bus.who(d.id)}: "
                          f"{common.value_text(spec.item('Hardware Error Status'), status)}"))
            continue
        torque = spec.item("Torque Enable")
        if bus.read(d.id, torque):
            writes.append(Write(d, torque, 1, 0, "EEPROM takes writes only with the torque off"))
        level = bus.read(d.id, spec.item("Status Return Level"))
        for s in common.runtime_settings(d):
            present = bus.read(d.id, s.item)
            if present != s.value:
                # A motor below Status Return Level 2 does not answer the WRITE of the level.
                writes.append(Write(d, s.item, present, s.value, s.why,
                                    confirmed=level == 2
                                    or s.item.name != "Status Return Level"))
        if baud_to is not None:
            item = spec.item("Baud Rate")
            present = bus.read(d.id, item)
            if present != baud_code(baud_to):
                bauds.append(Write(d, item, present, baud_code(baud_to),
                                   f"the bus at {baud_to} baud, changed last"))
    if alerts:
        raise BusError("; ".join(text for _, text in alerts) + ": remove the cause, then "
                       "cochlea-dxl reboot --ids " + ",".join(str(i) for i, _ in alerts)
                       + f" --port {bus.path} --baud {bus.baud}; nothing was written")
    return writes, bauds


def _verify(bus: Bus, drives: list[JointDrive], baud_to: int | None) -> list[str]:
    """Every register the runtime needs, read back: what did not take."""
    wrong = []
    for d in drives:
        spec = d.spec
        checks = [(s.item, s.value) for s in common.runtime_settings(d)]
        checks.append((spec.item("Torque Enable"), 0))
        if baud_to is not None:
            checks.append((spec.item("Baud Rate"), baud_code(baud_to)))
        for item, value in checks:
            present = bus.read(d.id, item)
            if present != value:
                wrong.append(f"{bus.who(d.id)}: {item.name} ({item.address}) reads "
                             f"{common.value_text(item, present, spec)}, expected "
                             f"{common.value_text(item, value, spec)}")
    return wrong


def run(args: argparse.Namespace) -> int:
    drives = common.load_drives(args)
    baud_to = None if args.baud_to in (None, args.baud) else args.baud_to
    with Bus(args.port, args.baud) as bus:
        common.check_chain(bus, drives)
        writes, bauds = _plan(bus, drives, baud_to)
        if not writes and not bauds:
            print(f"configure: already configured: all {len(drives)} motors as the runtime "
                  "needs; nothing written")
            return common.EXIT_OK
        verb = "would write" if args.dry_run else "writing"
        for w in writes + bauds:
            print(f"{verb} {w.text()}")
        if args.dry_run:
            print(f"configure: dry run: {len(writes) + len(bauds)} writes listed, nothing "
                  "written")
            return common.EXIT_OK
        # Every status packet watched: an alert or a lost motor stops the writes (exit 6/7).
        with common.motion(bus, [], drives, "configure"):
            for w in writes:
                bus.write(w.drive.id, w.item, w.value, reply=w.confirmed)
        wrong = _verify(bus, drives, None)
        if wrong:
            return _failed(wrong, bus)
        if bauds:
            # All or none: a stop (Ctrl-C, SIGTERM, a hang-up) that comes between two motors'
            # writes would leave the chain at two rates, which no single --baud then reaches;
            # it waits the few milliseconds until every motor has its new rate.
            with signals_held():
                for w in bauds:
                    bus.write(w.drive.id, w.item, w.value)  # answered at the old rate
            bus.open(baud_to)
            try:
                common.check_chain(bus, drives)
            except BusError as exc:
                print(f"cochlea-dxl configure: verify at {baud_to} baud: {exc}",
                      file=sys.stderr)
                return common.EXIT_DIFFERS
            wrong = _verify(bus, drives, baud_to)
            if wrong:
                return _failed(wrong, bus)
    rate = f" at {bus.baud} baud" if bauds else ""
    print(f"configure: {len(writes) + len(bauds)} writes, verified by reading back{rate}; "
          "torque off on every motor")
    return common.EXIT_OK


def _failed(wrong: list[str], bus: Bus) -> int:
    for line in wrong:
        print(f"verify: {line} (the write did not take)")
    print(f"cochlea-dxl configure: verify failed on {len(wrong)} "
          f"register{'s' if len(wrong) != 1 else ''} at {bus.baud} baud (listed above): check "
          "the motor's firmware and that nothing else writes to the bus, then run configure "
          "again", file=sys.stderr)
    return common.EXIT_DIFFERS
