"""The homing record of a robot's prismatic joints and the rule that says whether it still holds
(issues 15 and 25).

``cochlea-dxl home`` (:mod:`cochlea.dynamixel.bringup.home`) writes the record; the bridge's
start-up (:meth:`cochlea.dynamixel.bridge.DynamixelBackend._check_homing`) applies the rule to
each homed joint: its entry is valid while its motor still holds the random token written into
:data:`MARKER_ITEM_NAME` (:func:`marker_item`: its address from the motor model's data) when it
was homed. That register is RAM, unused in current control, and returns to its default (0) at
power-on and after a REBOOT, exactly when the single-turn encoder loses its turn count. A
valid entry counts the joint from its stop:
``d = stop_m + direction * ratio * (counts - raw_counts) * 2 pi / N``
(N: the model's counts per turn, 4096 on the X series).

One record per robot description (:func:`default_record`): ``~/.cochlea/homing/ROBOT.json``
for the shipped description of the kind ROBOT (``serial``, ``parallel``), as before, and
``~/.cochlea/homing/ROBOT-STEM-HASH.json`` for a user's description, STEM its file name without
``.toml`` and HASH the first 8 hex digits of the SHA-256 of its resolved path: the record
follows the file (editing a gain keeps it; a moved or copied file is homed again). The record
names its description (:func:`description_id`) and the runtime refuses a record made for
another one, whatever path it was given.

Format ``cochlea-homing/2``: the robot, the description, the date, the port and ``joints``, one
entry per prismatic joint (name, motor ID and model, ``raw_counts``, ``stop_m``, ``direction``,
``ratio_m_per_rad``, ``marker_address``, ``marker``). A ``cochlea-homing/1`` record (one joint,
from before issue 25) is still read for the shipped description it was made for (the parallel
robot's slider); one made for a user's description is refused: run ``cochlea-dxl home`` again.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from pathlib import Path

from .. import files
from ..resources import ROBOTS_DIR, shipped, shipped_file
from ..runtime.backend import BackendError
from .control_table import Item
from .drives import drive_item

FORMAT = "cochlea-homing/2"
#: One joint, flat (issue 15): still read for a shipped description.
FORMAT_1 = "cochlea-homing/1"
#: The register that holds the homing token, by name: each model's address and size come from
#: its data (88 on the X series and MX(2.0), 536 on the P series). Feedforward 2nd Gain: RAM
#: (reset to 0 at power-on and by REBOOT), unused in current control.
MARKER_ITEM_NAME = "Feedforward 2nd Gain"
MARKER_RANGE = (1, 16383)  # its default is 0: a motor fresh from power-on never matches
#: The description of a record made for the shipped ``models/robots/ROBOT.toml``.
SHIPPED = "shipped"
_ENTRY_INTS = ("motor_id", "raw_counts", "marker")
_ENTRY_FLOATS = ("stop_m", "ratio_m_per_rad")


def description_id(robot: str, description: str | Path | None) -> str:
    """What a record says it was made for: :data:`SHIPPED` for the shipped description of the
    kind ``robot`` (None, its bare name, or its file), else the description's resolved path."""
    path = (shipped(ROBOTS_DIR, description) if description is not None
            else shipped_file(ROBOTS_DIR, robot))
    resolved = Path(path).expanduser().resolve()
    if resolved == shipped_file(ROBOTS_DIR, robot).resolve():
        return SHIPPED
    return str(resolved)


def default_record(robot: str, description: str | Path | None = None) -> Path:
    """Where ``home`` writes and the runtime looks: ``~/.cochlea/homing/ROBOT.json`` for the
    shipped description, ``~/.cochlea/homing/ROBOT-STEM-HASH.json`` for a user's (STEM its
    file name, HASH 8 hex digits of the SHA-256 of its resolved path)."""
    folder = Path.home() / ".cochlea" / "homing"
    which = description_id(robot, description)
    if which == SHIPPED:
        return folder / f"{robot}.json"
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(which).stem)[:40] or "description"
    digest = hashlib.sha256(which.encode("utf-8", "surrogateescape")).hexdigest()[:8]
    return folder / f"{robot}-{stem}-{digest}.json"


def _home_command(robot: str, description: str) -> str:
    return ("cochlea-dxl home --robot " + robot
            + ("" if description == SHIPPED else f" --description {description}")
            + " --port PORT")


#: What each integer of an entry can be: a Protocol 2.0 ID, a 4-byte signed Present
#: Position, a 2-byte register. A record out of them was not written by cochlea-dxl home (a
#: raw count of 10**320 used to end the start-up in an OverflowError).
_ENTRY_INT_RANGES = {"motor_id": (0, 252), "raw_counts": (-2**31, 2**31 - 1),
                     "marker": (0, 65535)}


def _check_entry(entry) -> None:
    for key in _ENTRY_INTS:
        if not isinstance(entry[key], int) or isinstance(entry[key], bool):
            raise ValueError
        low, high = _ENTRY_INT_RANGES[key]
        if not low <= entry[key] <= high:
            raise ValueError
    for key in _ENTRY_FLOATS:  # a number: "0.02" (a string) would fail later, in arithmetic
        if not isinstance(entry[key], (int, float)) or isinstance(entry[key], bool) or \
                not math.isfinite(entry[key]):
            raise ValueError
    if entry["direction"] not in (1, -1) or isinstance(entry["direction"], bool):
        raise ValueError


#: A homing record is a few hundred bytes a joint; anything over this is not one.
MAX_RECORD_BYTES = 1 << 20


def load_record(path: Path, robot: str | None = None,
                description: str | Path | None = None) -> dict:
    """The record at ``path`` as a ``cochlea-homing/2`` dict (a ``/1`` one turned into one
    entry, ``legacy`` True); a missing or malformed one is a BackendError naming what to do
    (the ``cochlea-dxl home`` of ``robot`` and ``description`` when given)."""
    try:
        raw = files.read_regular(path, MAX_RECORD_BYTES)  # a FIFO or a device is refused
    except FileNotFoundError:
        command = "cochlea-dxl home --robot ROBOT [--description FILE] --port PORT" \
            if robot is None else _home_command(robot, description_id(robot, description))
        raise BackendError(f"the robot's prismatic joints are not homed: no homing record "
                           f"{path}; run {command} first") from None
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the name
        raise BackendError(f"homing record {path}: cannot read it "
                           f"({getattr(exc, 'strerror', None) or exc}); run cochlea-dxl home "
                           "again") from None
    try:
        if len(raw) > MAX_RECORD_BYTES:
            raise ValueError
        record = json.loads(raw.decode("utf-8"))
        if not isinstance(record, dict):
            raise ValueError
        if record.get("format") == FORMAT_1:
            _check_entry(record)
            entry = {k: record[k] for k in record if k not in ("format", "robot", "description",
                                                              "date", "port")}
            record = {"format": FORMAT, "legacy": True, "robot": record.get("robot"),
                      "description": record.get("description", SHIPPED),
                      "date": record.get("date"), "joints": [entry]}
        elif record.get("format") == FORMAT:
            if not isinstance(record["description"], str) or \
                    not isinstance(record["joints"], list) or not record["joints"]:
                raise ValueError
            for entry in record["joints"]:
                _check_entry(entry)
                if not isinstance(entry["joint"], str):
                    raise ValueError
        else:
            raise ValueError
    except (ValueError, KeyError, TypeError, AttributeError, RecursionError, OverflowError):
        raise BackendError(f"homing record {path}: not a {FORMAT} record (nor a {FORMAT_1} "
                           "one); run cochlea-dxl home again") from None
    return record


def check_record(record: dict, path: Path, robot: str, description: str | Path | None,
                 drives) -> list[dict]:
    """The entry of each of ``drives`` (the prismatic joints, in order) in a loaded
    ``record``; a BackendError in one line when the record was made for another robot or
    description, or holds other joints."""
    made_for = record.get("description")
    ours = description_id(robot, description)
    if record.get("robot") not in (None, robot):
        raise BackendError(f"homing record {path} was made for the {record['robot']} robot, "
                           f"not the {robot} one: run {_home_command(robot, ours)} again")
    if record.get("legacy"):
        if ours != SHIPPED or made_for not in (None, SHIPPED):
            raise BackendError(f"homing record {path} is a {FORMAT_1} record (from an older "
                               "cochlea) of a user's description, which it does not identify: "
                               f"run {_home_command(robot, ours)} again")
    elif made_for != ours:
        raise BackendError(f"homing record {path} was made for the description {made_for}, "
                           f"not {ours}: run {_home_command(robot, ours)} again")
    entries = {e.get("joint"): e for e in record["joints"]}
    if record.get("legacy") and len(drives) == 1:  # /1 records named the joint, or did not
        entries = {drives[0].name: record["joints"][0]}
    names = [d.name for d in drives]
    if sorted(entries) != sorted(names):
        raise BackendError(f"homing record {path} holds the joints "
                           f"{', '.join(sorted(map(str, entries)))}; the description's prismatic "
                           f"joints are {', '.join(names)}: run {_home_command(robot, ours)} "
                           "again")
    return [entries[n] for n in names]


def marker_item(drive) -> Item:
    """The homing token's register of ``drive``'s motor model (:data:`MARKER_ITEM_NAME`, its
    address and size from the model's data), refused in one line where the model has no such
    two-byte RAM register that holds :data:`MARKER_RANGE`."""
    it = drive_item(drive, MARKER_ITEM_NAME, "cochlea-dxl home and the bridge's homing check")
    if it.size != 2 or not it.writable or it.lo > MARKER_RANGE[0] or it.hi < MARKER_RANGE[1]:
        raise BackendError(f"joint {drive.name}: the {drive.spec.name}'s {MARKER_ITEM_NAME} "
                           f"(address {it.address}, {it.size} bytes, {it.lo}..{it.hi}) cannot "
                           f"hold a homing token ({MARKER_RANGE[0]}..{MARKER_RANGE[1]}, 2 "
                           "bytes, writable)")
    return it


def reference_offset(entry: dict, record: dict, path: Path, drive, marker: int) -> float:
    """The joint's ``q_offset`` (``q = q_per_count * counts + q_offset``) from its valid
    ``entry`` of ``record``, given the value its motor holds in its :func:`marker_item`; a
    BackendError naming ``cochlea-dxl home`` when the entry does not belong to this motor and
    power cycle."""
    if entry["motor_id"] != drive.id or entry["direction"] != drive.direction or \
            abs(entry["ratio_m_per_rad"] - drive.ratio) > 1e-12:
        raise BackendError(f"homing record {path} was made for {drive.name} on motor ID "
                           f"{entry['motor_id']}, direction {entry['direction']:+d}, ratio "
                           f"{entry['ratio_m_per_rad']:g} m/rad; the description has ID "
                           f"{drive.id}, {drive.direction:+d}, {drive.ratio:g}: run cochlea-dxl "
                           "home again")
    kept_at = marker_item(drive).address
    if entry.get("marker_address", kept_at) != kept_at:
        raise BackendError(f"homing record {path} keeps {drive.name}'s token at address "
                           f"{entry['marker_address']}; the {drive.spec.name} keeps it at "
                           f"{kept_at} ({MARKER_ITEM_NAME}): run cochlea-dxl home again")
    if marker != entry["marker"]:
        described = record.get("description") or SHIPPED
        robot = record.get("robot") or "ROBOT"
        raise BackendError(f"{drive.name} (ID {drive.id}) was power-cycled or rebooted (or "
                           "homed again, for another record) since it was homed "
                           f"({record.get('date') or 'date unknown'}): the record no longer "
                           f"counts its turns; run {_home_command(robot, described)} again")
    return float(entry["stop_m"]) - drive.q_per_count * entry["raw_counts"]
