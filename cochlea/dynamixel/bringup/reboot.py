"""``cochlea-dxl reboot``: Protocol 2.0 REBOOT of motors in hardware alert, then whether each
came back without it.

A motor in alert (overload, overheating, ...) turns its torque off and keeps the alert until a
reboot or a power cycle; only the REBOOT instruction clears it without cutting the power to the
whole chain. Every motor named is pinged first (none is rebooted if one is missing); each is
then rebooted, pinged until it answers again (it restarts its firmware) and its Hardware Error
Status read. A reboot restores the RAM (torque off, Bus Watchdog off) and keeps the EEPROM; the
encoder restarts within one turn, so a multi-turn joint (the parallel robot's slider) must be
homed again.
"""

from __future__ import annotations

import argparse
import sys
import time

from .. import protocol as proto
from ..control_table import BRIDGE_LAYOUTS, MODELS_BY_NUMBER, MX64
from . import common
from .common import Bus, BusError

NAME = "reboot"
HELP = "reboot motors (clears a hardware alert), then check each came back without alert"

#: How long a motor may take to answer again after a REBOOT (its firmware restarts).
COME_BACK_S = 3.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    common.add_port(parser)
    common.add_baud(parser)
    parser.add_argument("--ids", type=common.id_list, required=True, metavar="IDS",
                        help="the motors to reboot, e.g. 3 or 1,2 or 1-6")


def run(args: argparse.Namespace) -> int:
    still, gone = [], []
    with Bus(args.port, args.baud) as bus:
        models = {}
        missing = []
        for motor_id in args.ids:
            answer = bus.ping(motor_id)
            if answer is None:
                missing.append(str(motor_id))
            else:
                models[motor_id] = MODELS_BY_NUMBER.get(answer[0], MX64)
                # Each model's Hardware Error Status (X 70, P 518); another table: refused.
                models[motor_id].require_layout("cochlea-dxl reboot", BRIDGE_LAYOUTS)
        if missing:
            raise BusError(f"ID {', '.join(missing)} did not answer PING on {args.port} at "
                           f"{args.baud} baud: nothing rebooted (cochlea-dxl scan lists what "
                           "answers)")
        for motor_id in args.ids:
            item = models[motor_id].item("Hardware Error Status")
            before = bus.read(motor_id, item)
            if bus.request(proto.reboot(motor_id), motor_id) is None:
                raise BusError(f"ID {motor_id} did not answer REBOOT on {args.port}")
            deadline = time.monotonic() + COME_BACK_S
            while bus.ping(motor_id, tries=1) is None:
                if time.monotonic() > deadline:
                    break
                time.sleep(0.05)
            else:
                after = bus.read(motor_id, item)
                was = common.value_text(item, before)
                if after or bus.alert(motor_id):
                    still.append(str(motor_id))
                    print(f"ID {motor_id}: rebooted, still in alert: "
                          f"{common.value_text(item, after)} (was {was})")
                else:
                    print(f"ID {motor_id}: rebooted, back without alert (was {was}); torque off")
                continue
            gone.append(str(motor_id))
            print(f"ID {motor_id}: rebooted, did not answer again within {COME_BACK_S:g} s")
    if still or gone:
        problems = ([f"ID {', '.join(still)} still in alert: remove the cause (load, "
                     "temperature, supply voltage) and reboot again"] if still else []) + \
            ([f"ID {', '.join(gone)} did not come back: check its power and cable"]
             if gone else [])
        print(f"cochlea-dxl reboot: {'; '.join(problems)}", file=sys.stderr)
        return common.EXIT_DIFFERS
    print(f"reboot: {len(args.ids)} motor{'s' if len(args.ids) != 1 else ''} back without alert; "
          "a multi-turn joint (the parallel robot's slider) must be homed again")
    return common.EXIT_OK
