"""A run folder as ``cochlea-mcap`` reads it: ``summary.json`` (which robot, which scenario,
how many periods, how the run stopped) and ``log.csv`` (one row per period), checked before
anything is written, then read a chunk of rows at a time (a run of hours does not fit in
memory as one array).

``log.csv``'s columns (docs/logs.md, :mod:`cochlea.log_schema`; logs of schema version 1, before
``schema_version`` was written, read alike): ``time_s``, then per unit ``UNIT.GROUP.ELEMENT_UNIT``
(``arm1.q.joint1_rad``, ``mechanism.p_hat.left.link1.m_kg``), then run-level columns without a
unit prefix (``start_lateness_s``, ...). Any folder ``cochlea-run`` (sim, real time,
Dynamixel) or the embedded C program leaves is read alike.
"""

from __future__ import annotations

import json
import math
import os
import stat
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import files
from ..errors import CochleaError
from ..log_schema import SCHEMA_VERSION
from ..robots import RobotAdapter, robot
from ..sim.scenario import load as load_scenario

#: How the embedded C program's summary.json names its scenario_file.
COMPILED_IN = "compiled in: "
#: Rows read (and exported) at a time.
CHUNK_ROWS = 8192
#: time_s of a row must lie in [0, MAX_TIME_S): an MCAP or ROS time stamp holds seconds in 32
#: bits (builtin_interfaces/Time's int32 sec), and no run lasts 68 years.
MAX_TIME_S = 2.0**31
#: The joint position groups and the units their elements end with.
JOINT_UNITS = ("_rad", "_m")



def time_steps(times: np.ndarray) -> np.ndarray:
    """The differences of ``times``, quietly (garbage times of 1e300 overflow to inf, which the
    caller refuses in one line)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return np.diff(times)


class RunFolderError(CochleaError):
    """The folder is not a run cochlea-mcap can read, or its log is damaged."""


@dataclass
class Group:
    """The columns of one group of a unit (``q``, ``tau``, ``p_hat``, ...): their indices in
    a row and their element names with units (``joint1_rad``)."""

    name: str
    columns: list[int] = field(default_factory=list)
    elements: list[str] = field(default_factory=list)


@dataclass
class UnitColumns:
    name: str
    groups: dict[str, Group]

    def joints(self) -> list[str]:
        """The joints' names: ``q``'s elements without their unit (``joint1``)."""
        return [strip_unit(e, JOINT_UNITS) for e in self.groups["q"].elements]


@dataclass
class RunLog:
    folder: Path
    summary: dict
    adapter: RobotAdapter
    system: object
    header: list[str]
    units: list[UnitColumns]
    run_level: Group  # columns of no unit (timing of a real-time run)

    @property
    def csv(self) -> Path:
        return self.folder / "log.csv"

    def end_time(self) -> float:
        """The latest time_s a row of this run may have: its length (summary.json's
        ``duration_s``, or ``periods`` at ``rate_Hz``, the larger) and one period more; inf
        where the summary gives neither. A row later than this is damage (a time of 1e9 s in
        the last row made cochlea-ros2 replay wait for it)."""
        s = self.summary

        def number(key):
            v = s.get(key)
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and \
                math.isfinite(v) and v > 0
            return float(v) if ok else None

        rate, duration, periods = number("rate_Hz"), number("duration_s"), number("periods")
        if rate is None:
            return duration if duration is not None else math.inf
        ends = [x for x in (duration, periods / rate if periods else None) if x is not None]
        return max(ends) + 1.0 / rate if ends else math.inf

    def chunks(self):
        """``log.csv``'s rows, :data:`CHUNK_ROWS` at a time, as float64 arrays; a row that is
        not the header's number of numbers, a time that is not finite or does not increase, or
        fewer rows than ``summary.json``'s ``periods`` raise :class:`RunFolderError`."""
        width, last_time, count = len(self.header), -math.inf, 0
        expected = self.summary.get("periods")
        limit = self.end_time()
        try:
            f = open(self.csv, encoding="utf-8", errors="strict")
        except OSError as exc:
            raise RunFolderError(f"{self.csv}: cannot read it ({exc.strerror})") from None
        with f:
            f.readline()
            while True:
                first_line = count + 2  # the file's line number of the chunk's first row
                try:
                    with warnings.catch_warnings():  # the end of a log that fills its chunks
                        warnings.filterwarnings("ignore", "loadtxt: input contained no data")
                        # A blank line is skipped (the row count then tells the log is
                        # damaged), quietly: numpy's 3-line warning is not one line.
                        warnings.filterwarnings("ignore", "Input line .* contained no data")
                        # comments=None: a '#' line is a damaged row, not a comment to skip.
                        rows = np.loadtxt(f, delimiter=",", max_rows=CHUNK_ROWS, ndmin=2,
                                          dtype=np.float64, comments=None)
                except (ValueError, UnicodeDecodeError) as exc:
                    raise RunFolderError(
                        f"{self.csv} is damaged: a row from line {first_line} on is not "
                        f"{width} numbers ({exc}): export an undamaged copy of the run"
                    ) from None
                if rows.size == 0:
                    break
                if rows.shape[1] != width:
                    raise RunFolderError(f"{self.csv} is damaged: rows from line {first_line} "
                                         f"have {rows.shape[1]} values, the header {width}")
                times = rows[:, 0]
                steps = time_steps(np.concatenate([[last_time], times]))
                for wrong, why in (
                        (~np.isfinite(times) | ~(steps > 0),
                         "is not finite or not after the row before"),
                        ((times < 0) | (times >= MAX_TIME_S),
                         "is outside [0, 2**31) s (a run's time from its first period; a ROS "
                         "time stamp holds no more)"),
                        (times > limit,
                         f"is after the run's end ({limit:g} s: summary.json's duration_s and "
                         "one period)")):
                    if wrong.any():
                        bad = int(np.argmax(wrong))
                        raise RunFolderError(
                            f"{self.csv} is damaged: line {first_line + bad}: time_s = "
                            f"{float(times[bad])!r} {why}")
                last_time = float(times[-1])
                count += len(rows)
                yield rows
                if len(rows) < CHUNK_ROWS:
                    break
        if count != expected:
            raise RunFolderError(f"{self.csv} is truncated or damaged: it holds {count} rows "
                                 f"but summary.json says the run logged {expected} periods")
        if count == 0:
            raise RunFolderError(f"{self.csv} holds no period: nothing to export")



def _int64(text: str) -> int:
    """A summary's integer, within 64 bits as cochlea writes them: a longer one is damage
    (json reads any integer whole, and a reader taking it as a float would overflow)."""
    value = int(text)
    if not -2**63 <= value < 2**63:
        raise ValueError(f"an integer of {len(text)} digits")
    return value

#: The largest run-folder JSON file read (summary.json, log.columns.json): a few hundred kB.
MAX_JSON_BYTES = 64 * 2**20


def read_json(path: Path, **options):
    """A run folder's JSON file (summary.json, log.columns.json), read as a regular file only
    (a FIFO or a device is refused without blocking: :func:`cochlea.files.read_regular`);
    every way it can be unreadable -- missing, a folder, not UTF-8, not JSON, nested so deep
    that the parser recurses out (``[[[...`` 200 000 deep), larger than
    :data:`MAX_JSON_BYTES` -- is one :class:`RunFolderError`."""
    try:
        data = files.read_regular(path, MAX_JSON_BYTES)
        if len(data) > MAX_JSON_BYTES:
            raise ValueError(f"larger than {MAX_JSON_BYTES} bytes")
        return json.loads(data.decode("utf-8"), **options)
    except OSError as exc:
        raise RunFolderError(f"{path} cannot be read ({exc.strerror or exc})") from None
    except RecursionError:
        raise RunFolderError(f"{path} is damaged: not JSON (nested too deep)") from None
    except (UnicodeDecodeError, ValueError) as exc:
        raise RunFolderError(f"{path} is damaged: not JSON ({exc})") from None


#: The unit of a per-joint group's elements, from the joint's position unit (rad, m); the
#: groups whose elements are the joints (or, in joint space, the tracked coordinates).
JOINT_GROUP_UNITS = {
    **{g: {"rad": ("rad",), "m": ("m",)} for g in ("q", "true_q", "desired", "error",
                                                  "true_error", "e", "e_g", "e_p")},
    **{g: {"rad": ("rad_s",), "m": ("m_s",)} for g in ("qd", "true_qd", "desired_dot", "r",
                                                      "e_v", "e_d")},
    "tau": {"rad": ("N_m", "Nm"), "m": ("N",)},  # Nm: a version-1 log's
    "current": {"rad": ("A",), "m": ("A",)},
}


def model_joints(adapter, system, unit: str) -> list[tuple[str, str]]:
    """``(name, position unit)`` of the unit's joints in the model's order (the order of
    ``q`` in its kinematics): ``rad`` for a revolute joint, ``m`` for a prismatic one."""
    return [(j.name, "rad" if j.type == "revolute" else "m")
            for j in adapter.model(system, unit).joints]


def by_joint(group: Group, unit: str, joints: list[tuple[str, str]], where: Path,
             required: bool = True) -> Group:
    """``group``'s columns in the model's joint order, each element named by the
    description's joint and unit (``joint1_rad``): a log is read by its columns' names,
    never by their position (two joints' columns swapped were exported swapped). A
    ``required`` group (``q``, ``qd``, ``tau``) whose elements are not exactly the joints,
    each once, in the group's unit, is refused (an unknown joint, ``joint1_deg``); another
    group is reordered when its elements are the joints (a joint-space run's ``desired``) and
    kept as it is otherwise (a task-space run's ``x``, ``y``, ``phi``)."""
    units = JOINT_GROUP_UNITS.get(group.name)
    if units is None:
        return group
    names = sorted((j for j, _ in joints), key=len, reverse=True)  # longest name first
    found: dict[str, tuple[int, str, str]] = {}
    problem = None
    for column, element in zip(group.columns, group.elements):
        joint = next((j for j in names if element.startswith(j + "_")), None)
        if joint is None:
            problem = f"{element!r} names no joint of the unit ({', '.join(j for j, _ in joints)})"
            break
        if joint in found:
            problem = f"joint {joint} has two columns"
            break
        found[joint] = (column, element, element[len(joint) + 1:])
    if problem is None:
        for joint, kind in joints:
            if joint not in found:
                problem = f"joint {joint} has no column"
                break
            column, element, unit_text = found[joint]
            if unit_text not in units[kind]:
                problem = (f"{element!r} is in {unit_text!r}, not {units[kind][0]!r} (joint "
                           f"{joint} is {'revolute' if kind == 'rad' else 'prismatic'})")
                break
    if problem is not None:
        if not required:
            return group  # not the joints (a task's coordinates): as it is
        raise RunFolderError(f"{where} is not this run's log: {unit}.{group.name}: {problem}")
    return Group(group.name, [found[j][0] for j, _ in joints],
                 [found[j][1] for j, _ in joints])


def strip_unit(element: str, units: tuple[str, ...]) -> str:
    for unit in units:
        if element.endswith(unit):
            return element[: -len(unit)]
    return element


def _is_regular(path: Path) -> str | None:
    """None if ``path`` is a regular file, else what it is."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "missing"
    except OSError as exc:
        return f"unreadable ({exc.strerror})"
    return None if stat.S_ISREG(mode) else "not a regular file"


def open_run(folder: Path) -> RunLog:
    """Check ``folder`` is a run folder and read its summary and log header; nothing else."""
    folder = Path(folder)
    if not folder.is_dir():
        what = "missing" if not os.path.lexists(folder) else "not a folder"
        raise RunFolderError(f"RUN_DIR {folder} is {what}: name a run's output folder (one "
                             "holding summary.json and log.csv)")
    summary_path, csv_path = folder / "summary.json", folder / "log.csv"
    for path in (summary_path, csv_path):
        problem = _is_regular(path)
        if problem is not None:
            # The hint only where the report is missing, not where something else is there.
            hint = (" (log.bin holds the raw log of a run whose report was lost; this command "
                    "exports finished runs)") if problem == "missing" and \
                (folder / "log.bin").exists() else ""
            raise RunFolderError(f"{folder} is not a finished run: {path.name} is {problem}"
                                 f"{hint}")
    summary = read_json(summary_path, parse_int=_int64)
    if not isinstance(summary, dict) or not isinstance(summary.get("robot"), str) \
            or not isinstance(summary.get("scenario_file"), str):
        raise RunFolderError(f"{summary_path} is not a run's summary: it has no robot and "
                             "scenario_file")
    periods = summary.get("periods")
    if not isinstance(periods, int) or isinstance(periods, bool) or periods < 1:
        # The count every reader checks the log against (a log cut short is refused by it):
        # without a whole number of periods a truncated log would pass as whole.
        raise RunFolderError(f"{summary_path} is damaged: its periods is {periods!r}, not a "
                             "whole number >= 1 (the log's row count, which the log is "
                             "checked against)")
    version = summary.get("schema_version", 1)  # a log without one is of version 1
    if not isinstance(version, int) or isinstance(version, bool) or \
            not 1 <= version <= SCHEMA_VERSION:
        raise RunFolderError(f"{summary_path}: its log's schema_version is {version!r}; this "
                             f"cochlea reads versions 1 to {SCHEMA_VERSION} (docs/logs.md): "
                             "export it with the cochlea that wrote it")
    adapter = robot(summary["robot"])
    source = summary["scenario_file"]
    if source.startswith(COMPILED_IN) and isinstance(summary.get("scenario"), str):
        # The embedded program's scenarios are the shipped ones (kernels.toml's [embedded]),
        # compiled in: the shipped scenario of that name has the run's description.
        source = summary["scenario"]
    try:
        scenario = load_scenario(source)
    except CochleaError as exc:
        raise RunFolderError(f"{summary_path}: its scenario_file, which names the run's robot "
                             f"description, cannot be loaded: {exc}") from None
    if scenario.robot != adapter.name:
        raise RunFolderError(f"{summary_path}: its scenario {summary['scenario_file']} is for "
                             f"the {scenario.robot} robot, not the run's {adapter.name}")
    try:
        with open(csv_path, encoding="utf-8") as f:
            header = f.readline().rstrip("\r\n").split(",")
    except (OSError, UnicodeDecodeError) as exc:
        raise RunFolderError(f"{csv_path} is damaged: cannot read its header ({exc})") from None
    if header[0] != "time_s" or len(set(header)) != len(header):
        raise RunFolderError(f"{csv_path} is damaged: its header does not start with time_s "
                             "or repeats a column")
    names = adapter.layout(scenario.system, "joint").units
    units = {name: UnitColumns(name, {}) for name in names}
    run_level = Group("run")
    for index, column in enumerate(header[1:], start=1):
        unit, _, rest = column.partition(".")
        if unit in units and "." in rest:
            group, _, element = rest.partition(".")
            g = units[unit].groups.setdefault(group, Group(group))
            g.columns.append(index)
            g.elements.append(element)
        else:
            run_level.columns.append(index)
            run_level.elements.append(column)
    for unit in units.values():
        joints = model_joints(adapter, scenario.system, unit.name)
        for group in ("q", "qd", "tau"):
            found = len(unit.groups[group].columns) if group in unit.groups else 0
            if found != len(joints):
                raise RunFolderError(f"{csv_path} is not this run's log: unit {unit.name} of "
                                     f"the {adapter.name} robot has {len(joints)} joints but "
                                     f"the log has {found} {unit.name}.{group} columns")
        for name, group in unit.groups.items():
            unit.groups[name] = by_joint(group, unit.name, joints, csv_path,
                                         required=name in ("q", "qd", "tau"))
    return RunLog(folder, summary, adapter, scenario.system, header, list(units.values()),
                  run_level)
