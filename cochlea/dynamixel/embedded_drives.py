"""The C tables of a robot's drives for the embedded runtime: ``<robot>_drives.h``.

One :c:type:`cochlea_drive` (``embedded/core/drives.h``) per joint of the whole system in the
loop's order, from the robot description through the same :class:`~cochlea.dynamixel.drives.
JointDrive` the Python bridge uses, every constant printed to 17 significant digits so the C
conversions equal the bridge's bit for bit; the supervisor's limit arrays; and the chain's bus
(``dxl_bus``, ``embedded/core/dxl.h``): each motor's control-table items (address and size,
from the model data, ``cochlea/dynamixel/models``) and the per-period transfers, chosen by the
Python bridge's own rule (:func:`cochlea.dynamixel.bridge.choose_transfers`, with the Realtime
Tick the C program always reads): SYNC_READ, FAST_SYNC_READ or BULK_READ, SYNC_WRITE or
BULK_WRITE (a mixed chain, e.g. an X-series arm with a P-series joint, whose models place the
period's items at different addresses). Each motor's units are its model's, in its drive's
constants (``q_per_count`` from its counts per turn, ``qd_per_lsb`` from its velocity unit,
``lsb_per_ampere`` / ``ampere_per_lsb`` from its current unit). A model whose control table
the C bridge does not speak is refused here in one line naming it
(:data:`~cochlea.dynamixel.control_table.EMBEDDED_LAYOUTS`: the X and P series'; the XL320's
is not), and a chain no single state layout reads (:func:`choose_transfers`' refusal).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

from ..errors import CochleaError
from ..robots import ROBOTS
from ..robots import robot as robot_adapter
from ..robots.model import JointInfo
from ..runtime.backend import BackendError
from .bridge import TICK_ITEMS, choose_transfers
from .control_table import CURRENT_MODE, EMBEDDED_LAYOUTS
from .drives import JointDrive, drive_item, joint_drives

#: The items of ``dxl_table`` (``embedded/core/dxl.h``, enum dxl_item_name), in its order: the
#: model data's item names. The bridge needs every one but the homing marker (a slider's).
BUS_ITEMS = ("Return Delay Time", "Operating Mode", "Current Limit", "Torque Enable",
             "Hardware Error Status", "Bus Watchdog", "Goal Current", "Feedforward 2nd Gain",
             "Realtime Tick", "Present Current", "Present Velocity", "Present Position")
OPTIONAL_ITEMS = ("Feedforward 2nd Gain",)
#: The names ``cochlea-run`` writes (``read_instruction``, ``write_instruction``) of the
#: transfers the C bridge sends.
_READ_NAMES = {"sync": "SYNC_READ", "fast": "FAST_SYNC_READ", "bulk": "BULK_READ"}
_WRITE_NAMES = {"sync": "SYNC_WRITE", "bulk": "BULK_WRITE"}
#: ``dxl.h``'s code of each instruction choose_transfers can name.
_C_INSTRUCTIONS = {"SYNC_READ": "DXL_SYNC_READ", "FAST_SYNC_READ": "DXL_FAST_SYNC_READ",
                   "BULK_READ": "DXL_BULK_READ", "SYNC_WRITE": "DXL_SYNC_WRITE",
                   "BULK_WRITE": "DXL_BULK_WRITE"}


def _real(value: float) -> str:
    """A double literal that reads back as exactly ``value``."""
    if not math.isfinite(value):
        raise ValueError(f"a drive constant is not finite: {value!r}")
    text = f"{value:.17g}"
    return text if re.search(r"[.eE]", text) else text + ".0"


def _identifier(name: str) -> str:
    ident = re.sub(r"\W", "_", name)
    return ident if ident[:1].isalpha() else f"robot_{ident}"


def _c_string(text: str) -> str:
    """``text`` as a C string literal: printable ASCII as is, the rest as octal escapes."""
    out = []
    for byte in text.encode():
        ch = chr(byte)
        if ch in ('"', "\\"):
            out.append("\\" + ch)
        elif 32 <= byte < 127:
            out.append(ch)
        else:
            out.append(f"\\{byte:03o}")
    return '"' + "".join(out) + '"'


def bus_choice(drives: list[JointDrive]) -> tuple[str, str, str]:
    """The C bridge's per-period transfers for ``drives``: ``(read, write, why)`` with read
    ``"SYNC_READ"``, ``"FAST_SYNC_READ"`` or ``"BULK_READ"``, write ``"SYNC_WRITE"`` or
    ``"BULK_WRITE"``, and why the text ``cochlea-run`` writes as ``read_choice``:
    :func:`choose_transfers` over the models' data with the items the C program reads (the
    Realtime Tick first), the Python bridge's choice for the same chain. A model whose table
    the C bridge does not speak raises :class:`BackendError` in one line naming it."""
    for d in drives:
        try:
            d.spec.require_layout("the embedded drive tables and the C bridge",
                                  EMBEDDED_LAYOUTS)
        except CochleaError as exc:
            raise BackendError(f"joint {d.name}: {exc}") from None
    read, write, why = choose_transfers([d.spec for d in drives], TICK_ITEMS)
    return _READ_NAMES[read], _WRITE_NAMES[write], why


def _table_row(d: JointDrive) -> str:
    cells = []
    for name in BUS_ITEMS:
        if name in OPTIONAL_ITEMS and name not in {it.name for it in d.spec.items}:
            cells.append("{0xFFFF, 0}")
            continue
        it = drive_item(d, name, "the embedded bridge")  # the Python bridge's lookup
        cells.append(f"{{{it.address}, {it.size}}}")
    return f'{{{_c_string(d.spec.name)}, {{{", ".join(cells)}}}, {CURRENT_MODE}}}'


def drives_header(robot: str, description: str | Path | None = None, *, system=None,
                  drives: list[JointDrive] | None = None) -> str:
    """The text of ``<robot>_drives.h`` for the robot's description."""
    adapter = robot_adapter(robot)
    system = system if system is not None else adapter.load(description)
    drives = drives if drives is not None else joint_drives(robot, system=system)
    joints = supervised_joints(robot, system)
    if len(joints) != len(drives):
        raise ValueError(f"{robot}: {len(drives)} drives for {len(joints)} joints")
    read, write, why = bus_choice(drives)
    prefix = _identifier(robot)
    upper = prefix.upper()
    lines = [
        f"/* The drives of the {robot} system for the embedded runtime, joint by joint in the",
        " * loop's order: Dynamixel ID, model, conversions and limits (SI: rad or m, rad/s or m/s,",
        " * N m or N; currents in A and LSB). Generated by cochlea-codegen from the robot",
        " * description: do not edit; run cochlea-codegen. */",
        f"#ifndef {upper}_DRIVES_H",
        f"#define {upper}_DRIVES_H",
        "",
        '#include "drives.h"',
        '#include "dxl.h"',
        "",
        f"#define {upper}_N_DRIVES {len(drives)}",
        "",
        "/* Each motor's control-table items (address, size) in dxl.h's order, from the model",
        " * data; then the chain's per-period transfers, chosen from the same data by the",
        " * Python bridge's rule (cochlea.dynamixel.bridge.choose_transfers). */",
        f"static const dxl_table {prefix}_tables[{upper}_N_DRIVES] = {{",
    ]
    for d in drives:
        lines.append(f"    /* {d.name}: ID {d.id}, {d.spec.name} */")
        lines.append("    " + _table_row(d) + ",")
    lines += [
        "};",
        f"static const dxl_bus {prefix}_bus = {{{_C_INSTRUCTIONS[read]}, "
        f"{_C_INSTRUCTIONS[write]},",
        f"    {_c_string(why)},",
        f"    {upper}_N_DRIVES, {prefix}_tables}};",
        "",
        f"static const cochlea_drive {prefix}_drives[{upper}_N_DRIVES] = {{",
    ]
    for d, j in zip(drives, joints):
        lo, hi = j.position_limits
        fields = [
            f'"{d.name}"', str(d.id), str(d.spec.number), "1" if d.type == "revolute" else "0",
            _real(d.q_per_count), _real(d.q_offset), _real(d.qd_per_lsb),
            _real(d.torque_per_effort), _real(1.0 / d.fit.a), _real(1.0 / d.fit.ramp),
            _real(d.fit.offset_current), _real(d.lsb_per_ampere),
            _real(joint_ampere_per_lsb(d)), str(d.current_limit_lsb),
            _real(lo), _real(hi), _real(j.velocity_limit), _real(j.effort_limit),
            f"&{prefix}_bus",
        ]
        lines.append(f"    /* {d.name}: ID {d.id}, {d.spec.name} */")
        lines.append("    {" + ", ".join(fields) + "},")
    lines.append("};")
    lines.append("")
    lines.append("/* The supervisor's limits (cochlea_limits), the Python supervisor's: from the")
    lines.append(" * controllers' models of the description. */")
    for field, values in (("position_lo", [j.position_limits[0] for j in joints]),
                          ("position_hi", [j.position_limits[1] for j in joints]),
                          ("velocity", [j.velocity_limit for j in joints]),
                          ("effort", [j.effort_limit for j in joints])):
        lines.append(f"static const double {prefix}_{field}[{upper}_N_DRIVES] = {{"
                     + ", ".join(_real(v) for v in values) + "};")
    lines += ["", f"#endif /* {upper}_DRIVES_H */", ""]
    return "\n".join(lines)


def joint_ampere_per_lsb(d: JointDrive) -> float:
    """A per Present Current LSB at the joint's sign: the Python bridge's factor from the
    register to ``joint_current_A`` (``cochlea/dynamixel/bridge.py``), the same expression so
    the C program logs the same current bit for bit."""
    return d.spec.current_unit_mA * 1e-3 * math.copysign(1.0, d.torque_per_effort)


def supervised_joints(robot: str, system) -> list[JointInfo]:
    """Every unit's joints in the loop's order, as the supervisor takes its limits
    (``cochlea.runtime.supervisor.build_supervisor``: the controllers' models)."""
    adapter = robot_adapter(robot)
    arms = getattr(system, "arms", None)
    models = ([adapter.model(system, arm) for arm in arms] if arms is not None
              else [adapter.model(system)])
    return [j for m in models for j in m.joints]


def write_drive_tables(folder: str | Path) -> list[Path]:
    """``<robot>_drives.h`` of every robot's shipped description into ``folder``; the paths."""
    written = []
    for robot in ROBOTS:
        path = Path(folder) / f"{robot}_drives.h"
        path.write_text(drives_header(robot))
        written.append(path)
    return written
