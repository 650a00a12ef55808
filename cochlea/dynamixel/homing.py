"""The slider's homing record and the rule that says whether it still holds (issue 15).

``cochlea-dxl home`` (:mod:`cochlea.dynamixel.bringup.home`) writes the record; the bridge's
start-up (:meth:`cochlea.dynamixel.bridge.DynamixelBackend._check_homing`) applies the rule: the
record is valid while the motor still holds the random token written into
:data:`MARKER_ADDRESS` when it was homed. That register is RAM, unused in current control, and
returns to its default (0) at power-on and after a REBOOT, exactly when the single-turn encoder
loses its turn count. A valid record counts the slider from the stop:
``d1 = stop_m + direction * ratio * (counts - raw_counts) * 2 pi / 4096``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from ..runtime.backend import BackendError

FORMAT = "cochlea-homing/1"
#: Feedforward 2nd Gain: RAM (reset at power-on and by REBOOT), unused in current control.
MARKER_ADDRESS = 88
MARKER_RANGE = (1, 16383)  # its default is 0: a motor fresh from power-on never matches


def default_record(robot: str) -> Path:
    """Where ``home`` writes and the runtime looks: ``~/.cochlea/homing/ROBOT.json``."""
    return Path.home() / ".cochlea" / "homing" / f"{robot}.json"


def load_record(path: Path) -> dict:
    """The record at ``path``; a missing or malformed one is a BackendError naming what to do."""
    try:
        text = Path(path).read_text()
    except FileNotFoundError:
        raise BackendError(f"the slider is not homed: no homing record {path}; run cochlea-dxl "
                           "home --robot ROBOT [--description FILE] --port PORT first") from None
    except OSError as exc:
        raise BackendError(f"homing record {path}: cannot read it ({exc.strerror}); run "
                           "cochlea-dxl home again") from None
    try:
        record = json.loads(text)
        if record.get("format") != FORMAT:
            raise ValueError
        for key in ("motor_id", "raw_counts", "marker"):
            if not isinstance(record[key], int) or isinstance(record[key], bool):
                raise ValueError
        for key in ("stop_m", "ratio_m_per_rad"):
            if not math.isfinite(float(record[key])):
                raise ValueError
        if record["direction"] not in (1, -1):
            raise ValueError
    except (ValueError, KeyError, TypeError, AttributeError):
        raise BackendError(f"homing record {path}: not a {FORMAT} record; run cochlea-dxl home "
                           "again") from None
    return record


def _options(record: dict) -> str:
    """The ``--robot`` (and ``--description``) a record was made with, as options."""
    described = record.get("description")
    return (f" --robot {record.get('robot', 'ROBOT')}"
            + (f" --description {described}" if described and described != "shipped" else ""))


def reference_offset(record: dict, path: Path, drive, marker: int) -> float:
    """The slider's ``q_offset`` (``q = q_per_count * counts + q_offset``) from a valid
    ``record``, given the value the motor holds in :data:`MARKER_ADDRESS`; a BackendError
    naming ``cochlea-dxl home`` when the record does not belong to this motor and power
    cycle."""
    if record["motor_id"] != drive.id or record["direction"] != drive.direction or \
            abs(record["ratio_m_per_rad"] - drive.ratio) > 1e-12:
        raise BackendError(f"homing record {path} was made for motor ID {record['motor_id']}, "
                           f"direction {record['direction']:+d}, ratio "
                           f"{record['ratio_m_per_rad']:g} m/rad; the description has ID "
                           f"{drive.id}, {drive.direction:+d}, {drive.ratio:g}: run cochlea-dxl "
                           "home again")
    if marker != record["marker"]:
        raise BackendError(f"the slider (ID {drive.id}) was power-cycled or rebooted since it "
                           f"was homed ({record.get('date', 'date unknown')}): its encoder lost "
                           f"its turns; run cochlea-dxl home{_options(record)} --port PORT "
                           "again")
    return float(record["stop_m"]) - drive.q_per_count * record["raw_counts"]
