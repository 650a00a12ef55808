"""``cochlea-dxl scan``: which motors answer on a port, at which baud rate, and in what state.

At each baud rate (default: every Dynamixel rate, the runtime's 4 Mbaud and the factory 57600
first) one broadcast PING finds the motors in the ID range; when it comes back garbled (two
motors sharing an ID collide) or with ``--per-id``, each ID is pinged on its own. Each motor
found is then read: Operating Mode, Torque Enable, Hardware Error Status, each at the address
its model's data gives (X series 11, 64, 70; P series 11, 512, 518). Nothing is written.
"""

from __future__ import annotations

import argparse
import sys

from ..control_table import BAUD_RATES, BRIDGE_LAYOUTS, MAX_ID, MODELS_BY_NUMBER, MX64
from . import common
from .common import Bus, BusError

NAME = "scan"
HELP = "list every motor that answers, at every baud rate: model, firmware, mode, alerts"

#: The runtime's rate and the motors' factory rate first: where a motor most likely is.
DEFAULT_BAUDS = [4_000_000, 57_600] + [b for b in BAUD_RATES.values()
                                        if b not in (4_000_000, 57_600)]
#: A per-ID PING waits one try of the adapter's latency timer (16 ms by default) plus the wire
#: time of the request and the reply: 253 IDs must stay a matter of seconds.
PER_ID_TIMEOUT_S = 0.02


def add_arguments(parser: argparse.ArgumentParser) -> None:
    common.add_port(parser)
    parser.add_argument("--baud", type=common.baud_rate, action="append", metavar="B",
                        help="a baud rate to scan (repeatable; default: all Dynamixel rates, "
                             "4000000 and 57600 first)")
    parser.add_argument("--ids", type=common.id_list, default=list(range(MAX_ID + 1)),
                        metavar="A-B", help=f"the IDs to look for, e.g. 1-6 or 1,3 (default "
                        f"0-{MAX_ID})")
    parser.add_argument("--per-id", action="store_true",
                        help="ping each ID on its own instead of one broadcast PING (slower; "
                             "for firmware that does not answer a broadcast)")


def _find(bus: Bus, ids: list[int], per_id: bool) -> tuple[dict[int, tuple[int, int]], str]:
    """The motors in ``ids`` answering at the bus's rate, and a note on how they were found."""
    wanted = set(ids)
    if not per_id:
        found, corrupted = bus.broadcast_ping(max(ids))
        found = {i: v for i, v in found.items() if i in wanted}
        if not corrupted:
            return found, ""
        note = (f"{corrupted} garbled replies to the broadcast PING (two motors with one ID?); "
                "pinged each ID")
    else:
        note = ""
    found = {}
    timeout, bus.timeout_s = bus.timeout_s, PER_ID_TIMEOUT_S + 24 * 10.0 / bus.baud
    try:
        for motor_id in ids:
            answer = bus.ping(motor_id, tries=1)
            if answer is not None:
                found[motor_id] = answer
    finally:
        bus.timeout_s = timeout
    return found, note


def _row(bus: Bus, motor_id: int, model: int, firmware: int) -> list[str]:
    # An unknown model number: the X series' addresses (X and MX(2.0) share them).
    spec = MODELS_BY_NUMBER.get(model, MX64)
    cells = []
    names = ("Operating Mode", "Torque Enable", "Hardware Error Status")
    if spec.layout not in BRIDGE_LAYOUTS:  # another table (XL320): never read at X addresses
        cells = [f"not read ({spec.layout} layout: not supported by cochlea-dxl yet)"] * 3
        names = ()
    for name in names:
        item = spec.item(name)
        try:
            value = bus.read(motor_id, item)
        except BusError:
            cells.append("? (no reply to READ)")
            continue
        cells.append(common.value_text(item, value, spec))
    name = MODELS_BY_NUMBER[model].name if model in MODELS_BY_NUMBER else f"unknown ({model})"
    return [str(bus.baud), str(motor_id), name, str(firmware), *cells]


def run(args: argparse.Namespace) -> int:
    bauds = list(dict.fromkeys(args.baud or DEFAULT_BAUDS))
    rows: list[list[str]] = []
    notes: list[str] = []
    bus: Bus | None = None
    try:
        for baud in bauds:
            if bus is None:
                bus = Bus(args.port, baud)
            else:
                bus.open(baud)
            found, note = _find(bus, args.ids, args.per_id)
            if note:
                notes.append(f"{baud} baud: {note}")
            for motor_id in sorted(found):
                rows.append(_row(bus, motor_id, *found[motor_id]))
    finally:
        if bus is not None:
            bus.close()
    ids = _ranges(args.ids)
    if not rows:
        print(f"cochlea-dxl scan: no motor answered on {args.port} at "
              f"{', '.join(str(b) for b in bauds)} baud (IDs {ids}): check the power supply, "
              "the cable and the adapter, and that the motors speak Protocol 2.0",
              file=sys.stderr)
        return common.EXIT_DIFFERS
    header = ["baud", "ID", "model", "firmware", "operating mode", "torque",
              "hardware error"]
    widths = [max(len(r[k]) for r in [header, *rows]) for k in range(len(header))]
    for r in [header, *rows]:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip())
    for note in notes:
        print(f"note: {note}")
    by_baud: dict[str, int] = {}
    for r in rows:
        by_baud[r[0]] = by_baud.get(r[0], 0) + 1
    print(f"found {len(rows)} motor{'s' if len(rows) != 1 else ''} ("
          + ", ".join(f"{n} at {b} baud" for b, n in by_baud.items()) + f"; IDs {ids} scanned)")
    alerts: dict[str, list[str]] = {}
    for r in rows:
        if not r[6].endswith("(none)") and not r[6].startswith("?"):
            alerts.setdefault(r[0], []).append(r[1])
    for baud, motors in alerts.items():
        print(f"hardware alert on ID {', '.join(motors)}: remove the cause, then cochlea-dxl "
              f"reboot --port {args.port} --baud {baud} --ids {','.join(motors)}")
    return common.EXIT_OK


def _ranges(ids: list[int]) -> str:
    """``[1, 2, 3, 5]`` as ``1-3,5``."""
    parts, start = [], None
    for k, i in enumerate(ids):
        if start is None:
            start = i
        if k + 1 == len(ids) or ids[k + 1] != i + 1:
            parts.append(str(start) if start == i else f"{start}-{i}")
            start = None
    return ",".join(parts)
