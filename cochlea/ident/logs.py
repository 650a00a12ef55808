"""Run folders read back for identification: the positions, velocities and efforts of one unit.

A run folder is what ``cochlea-run`` (simulated, emulated or real motors) or the embedded
program (``build/cochlea-embedded``) leaves: ``log.csv`` with one row per control period, SI,
columns named ``<unit>.<signal>.<joint>_<unit of measure>`` (``arm1.q.joint1_rad``,
``mechanism.tau.slider.d1_N``: docs/logs.md, :mod:`cochlea.log_schema`; a log of schema version
1, whose efforts end in ``Nm``, is read too; a newer version is refused). Columns are picked by
name, never by position, so the pose columns the embedded program leaves out or the real-time
timing columns it adds change nothing. Every problem with a log is one :class:`LogError` naming
the file and what was expected, before anything is fitted.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import CochleaError
from ..files import read_regular
from ..log_schema import SCHEMA_VERSION
from ..robots import ROBOTS, RobotModel

#: Column suffix of each signal's SI unit, by joint type (cochlea.log_schema, version 2).
SIGNAL_UNITS = {
    "q": {"revolute": "rad", "prismatic": "m"},
    "qd": {"revolute": "rad_s", "prismatic": "m_s"},
    "tau": {"revolute": "N_m", "prismatic": "N"},
}
#: Logs written before the schema had a version (1) named N m ``Nm``: still read.
LEGACY_UNITS = {**SIGNAL_UNITS, "tau": {"revolute": "Nm", "prismatic": "N"}}
#: An optional column of measured motor current (A) per joint: fits the motor's line.
CURRENT = "current"
#: The loop's timing columns (s) read when the log has them: when each period started
#: relative to its deadline, how long its read, compute and write took, and how long the
#: bus transfers among them took (see cochlea/runtime/loop.py). They place a real-time
#: run's samples and commands in time.
TIMING = ("start_lateness_s", "compute_s", "backend_io_s")
#: Largest log.csv read (bytes): an hour at 1 kHz of the serial system is about 1.5 GB;
#: identification runs are minutes long.
MAX_LOG_BYTES = 2 * 1024**3
#: ``time_s`` is the control loop's nominal grid ``k h`` (every writer logs it so; the real
#: times of a real-time run are in the timing columns): the filters assume it uniform. A step
#: more than this factor above or below the median step (a gap where the run was paused or
#: two runs were spliced, a jittered or rounded clock) is refused, naming the row.
MAX_STEP_RATIO = 1.5
#: Positions are refused outside each joint's position limits (the description's) widened by
#: this fraction of the joint's range, at least :data:`MIN_POSITION_MARGIN` (rad or m): room
#: for an overshoot at a limit, none for degrees logged under a ``_rad`` column, millimetres
#: under ``_m`` or an encoder offset of whole turns.
POSITION_MARGIN = 0.1
MIN_POSITION_MARGIN = {"revolute": 0.1, "prismatic": 0.005}
#: Efforts are refused beyond this multiple of the joint's effort limit (the description's;
#: every command is clipped to it): a factor a drive cannot reach, so mN m logged as N m
#: (x1000) or a corrupt column is caught, a command at its limit is not.
MAX_EFFORT_MULTIPLE = 3.0
#: An effort column whose range over the log is at most this fraction of the joint's effort
#: limit carries no signal (all zero, or constant: efforts not recorded, or a column zeroed):
#: every estimate would be zero and the joint's weight 1/0.
FLAT_EFFORT = 1e-9


class LogError(CochleaError):
    """A run folder that cannot be identified from: names the file and what was expected."""


@dataclass(frozen=True)
class RunLog:
    """One unit's signals from one run folder, SI, one row per control period."""

    folder: Path
    file: Path
    sha256: str
    unit: str
    time: np.ndarray  # (N,) s
    q: np.ndarray  # (N, n) rad or m
    qd: np.ndarray  # (N, n) rad/s or m/s, as logged (not used by default: see estimate)
    tau: np.ndarray  # (N, n) N m or N, the commanded effort
    current: np.ndarray | None  # (N, n) A, when the log carries it
    #: (N, 3) s: each period's start lateness, read-compute-write and bus time (TIMING), when the
    #: log carries them; NaN where the loop did not record them (a stopped period).
    timing: np.ndarray | None = None

    @property
    def rows(self) -> int:
        return len(self.time)

    @property
    def rate_hz(self) -> float:
        return float(1.0 / np.median(np.diff(self.time)))


def column_names(model: RobotModel, unit: str, legacy: bool = False
                 ) -> dict[str, list[str]]:
    """The columns identification needs of ``unit``: per signal, one name per joint
    (``legacy``: as logs of schema version 1 name them)."""
    return {signal: [f"{unit}.{signal}.{j.name}_{units[j.type]}" for j in model.joints]
            for signal, units in (LEGACY_UNITS if legacy else SIGNAL_UNITS).items()}


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _other_robot(header: list[str], robot: str) -> str | None:
    """The robot whose units name this log's columns, when it is not ``robot``."""
    for name, adapter in ROBOTS.items():
        if name == robot:
            continue
        units = adapter.layout(adapter.load(None), "joint").units
        if any(col.split(".", 1)[0] in units for col in header):
            return name
    return None


def _check_file(file: Path) -> None:
    """A regular file of reasonable size ending in a whole line: a FIFO or a device (which
    would block or never end), an empty file and a log cut short (a full disk, a copy
    interrupted) are refused before anything is parsed."""
    try:
        info = os.stat(file)
    except FileNotFoundError:
        raise LogError(f"{file}: no such file (a run folder holds the log.csv that "
                       "cochlea-run or cochlea-embedded writes)") from None
    except OSError as exc:
        raise LogError(f"{file}: cannot read it ({exc.strerror})") from None
    if not stat.S_ISREG(info.st_mode):
        kind = "a folder" if stat.S_ISDIR(info.st_mode) else "a pipe, device or socket"
        raise LogError(f"{file}: expected a regular file holding a CSV log, got {kind}")
    if info.st_size > MAX_LOG_BYTES:
        raise LogError(f"{file}: expected a log of at most {MAX_LOG_BYTES // 1024**3} GiB; "
                       "identify from shorter runs")
    if info.st_size == 0:
        raise LogError(f"{file}: the file is empty: expected a CSV log (a header naming the "
                       "columns, then one row per control period)")
    try:
        with open(file, "rb") as f:
            head = f.read(4096)
            f.seek(-1, os.SEEK_END)
            last = f.read(1)
    except OSError as exc:
        raise LogError(f"{file}: cannot read it ({exc.strerror})") from None
    if b"\0" in head:
        raise LogError(f"{file}: expected a text CSV log, got binary data (a NUL byte in its "
                       "first 4 KiB; log.bin is read by cochlea's runtime, not here)")
    if last != b"\n":
        raise LogError(f"{file}: the last line is cut short (no line end after it): expected "
                       "a complete log; the run or its copy was interrupted")


def _header(file: Path) -> list[str]:
    try:
        with open(file, encoding="utf-8") as f:
            first = f.readline()
    except FileNotFoundError:
        raise LogError(f"{file}: no such file (a run folder holds the log.csv that "
                       "cochlea-run or cochlea-embedded writes)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise LogError(f"{file}: expected a readable UTF-8 CSV log, got {exc}") from None
    header = [c.strip() for c in first.rstrip("\n").split(",")]
    if not first.strip() or not header or header[0] != "time_s":
        raise LogError(f"{file}: expected a CSV log whose first column is time_s, got "
                       f"{first[:80].rstrip()!r}")
    return header


def _check_version(summary: Path) -> None:
    """Refuse a log of a newer schema than this cochlea reads (its names may mean something
    else); a folder without summary.json, or a summary without ``schema_version`` (version 1),
    is read."""
    try:
        # A regular file only (a FIFO named summary.json would block), and a summary nested
        # too deep for the parser (RecursionError) is as unreadable as one that is not JSON.
        version = json.loads(read_regular(summary, 64 * 2**20).decode("utf-8")).get(
            "schema_version", 1)
    except (OSError, UnicodeDecodeError, ValueError, AttributeError, RecursionError):
        return  # the log itself is checked column by column
    if not isinstance(version, int) or isinstance(version, bool) or \
            not 1 <= version <= SCHEMA_VERSION:
        raise LogError(f"{summary}: its log's schema_version is {version!r}; this cochlea "
                       f"reads versions 1 to {SCHEMA_VERSION} (docs/logs.md): identify it "
                       "with the cochlea that wrote it")


def read_run(folder: str | Path, model: RobotModel, robot: str, unit: str) -> RunLog:
    """The signals of ``unit`` (an arm of the serial system, or ``mechanism``) in the run
    folder ``folder`` (or a log.csv itself), refused with one :class:`LogError` when the
    folder, the file or a column is missing, a value is not a number or not finite (the row
    is named), time does not increase on a uniform grid, a position lies outside its joint's
    limits or an effort far beyond its drive's (a unit mistake: the column, row and likely
    cause named), an effort column carries no signal, or the log belongs to the other
    robot."""
    folder = Path(folder)
    file = folder / "log.csv" if folder.is_dir() else folder
    if not folder.exists():
        raise LogError(f"{folder}: no such run folder")
    _check_file(file)
    _check_version(file.parent / "summary.json")
    header = _header(file)
    twice = sorted({c for c in header if header.count(c) > 1})
    if twice:
        raise LogError(f"{file}: column {twice[0]!r} appears {header.count(twice[0])} times in "
                       "the header: expected each column once (a damaged or hand-edited log)")
    wanted = column_names(model, unit)
    missing = [c for cols in wanted.values() for c in cols if c not in header]
    old = column_names(model, unit, legacy=True)
    if missing and all(c in header for cols in old.values() for c in cols):
        wanted, missing = old, []  # a log of schema version 1 (efforts in "Nm")
    if missing:
        other = _other_robot(header, robot)
        if other is not None:
            raise LogError(f"{file}: this is a log of the {other} robot, not of the {robot} "
                           f"robot (give --robot {other})")
        other_unit = [c for c in header
                      if any(c.startswith(f"{unit}.{signal}.{j.name}_") and
                             c not in wanted[signal]
                             for signal in SIGNAL_UNITS for j in model.joints
                             if missing[0].startswith(f"{unit}.{signal}.{j.name}_"))]
        if other_unit:
            raise LogError(f"{file}: column {other_unit[0]!r} where {missing[0]!r} was expected "
                           "(the signal in another unit or of another joint type than the "
                           "description's: identification reads SI columns of the "
                           "description's joints)")
        units = sorted({c.split(".", 1)[0] for c in header[1:] if "." in c})
        raise LogError(f"{file}: missing column {missing[0]!r} (expected q, qd and tau of "
                       f"unit {unit!r}; the log's units: {', '.join(units) or 'none'})")
    current = [f"{unit}.{CURRENT}.{j.name}_A" for j in model.joints]
    has_current = all(c in header for c in current)
    names = ["time_s"] + wanted["q"] + wanted["qd"] + wanted["tau"] + \
        (current if has_current else [])
    index = [header.index(c) for c in names]
    timing = None
    if all(c in header for c in TIMING):
        # Read apart from the signals: a stopped period leaves NaN here, which only means
        # that its times are unknown (see estimate.sample_times), not a bad row.
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                timing = np.loadtxt(file, delimiter=",", skiprows=1, ndmin=2,
                                    usecols=[header.index(c) for c in TIMING])
        except ValueError as exc:
            raise LogError(f"{file}: expected numbers in the timing columns "
                           f"{', '.join(TIMING)}, {str(exc).splitlines()[0]}") from None
    try:
        with warnings.catch_warnings():  # an empty body is refused below, in one line
            warnings.simplefilter("ignore", UserWarning)
            data = np.loadtxt(file, delimiter=",", skiprows=1, usecols=index, ndmin=2)
    except ValueError as exc:
        # numpy names the offending line ("... at row 12, column 3"): keep it, one line.
        raise LogError(f"{file}: expected numbers in every selected column, "
                       f"{str(exc).splitlines()[0]}") from None
    bad = np.flatnonzero(~np.isfinite(data).all(axis=1))
    if bad.size:
        row = int(bad[0])
        col = names[int(np.flatnonzero(~np.isfinite(data[row]))[0])]
        raise LogError(f"{file}: row {row + 1} of the data (line {row + 2}) holds a "
                       f"non-finite value in {col} ({bad.size} such rows): drop them or "
                       "re-record the run")
    if len(data) < 2:
        raise LogError(f"{file}: expected at least two rows of data under the header, got "
                       f"{len(data)}")
    _check_time(file, data[:, 0])
    n = model.nq
    _check_signals(file, model, names, data[:, 1:1 + n], data[:, 1 + 2 * n:1 + 3 * n])
    return RunLog(folder, file, _sha256(file), unit, data[:, 0], data[:, 1:1 + n],
                  data[:, 1 + n:1 + 2 * n], data[:, 1 + 2 * n:1 + 3 * n],
                  data[:, 1 + 3 * n:1 + 4 * n] if has_current else None, timing)


def _check_time(file: Path, time: np.ndarray) -> None:
    """``time_s`` strictly increasing on a uniform grid (:data:`MAX_STEP_RATIO`): the first
    row that breaks it is named."""
    step = np.diff(time)
    back = np.flatnonzero(~(step > 0))
    if back.size:
        row = int(back[0]) + 1
        raise LogError(f"{file}: expected time_s strictly increasing, but row {row + 1} of the "
                       f"data (line {row + 2}) is at {time[row]:.10g} s, not after the row "
                       f"before it ({time[row - 1]:.10g} s): a repeated or reordered row, or "
                       "times too large for their step to show")
    median = float(np.median(step))
    off = np.flatnonzero((step > MAX_STEP_RATIO * median) | (step < median / MAX_STEP_RATIO))
    if off.size:
        row = int(off[0]) + 1
        raise LogError(f"{file}: expected time_s on a uniform grid (the control period, "
                       f"{median:.4g} s here), but row {row + 1} of the data (line {row + 2}) "
                       f"comes {step[row - 1]:.4g} s after the row before it ({off.size} such "
                       f"step{'s' if off.size > 1 else ''}): a gap (a paused or spliced run) "
                       "or an irregular clock; the filters need one rate: identify the parts "
                       "on either side as separate logs")


def _joint_units(kind: str) -> tuple[str, str]:
    return ("rad", "N m") if kind == "revolute" else ("m", "N")


def _check_signals(file: Path, model: RobotModel, names: list[str], q: np.ndarray,
                   tau: np.ndarray) -> None:
    """Positions inside the joints' limits (:data:`POSITION_MARGIN`), efforts within
    :data:`MAX_EFFORT_MULTIPLE` of their limits and each effort column carrying a signal
    (:data:`FLAT_EFFORT`): a unit mistake (degrees, mN m) or a column that was not recorded,
    named with its first row and the likely cause, before anything is fitted."""
    n = model.nq
    for i, j in enumerate(model.joints):
        length = _joint_units(j.type)[0]
        lo, hi = j.position_limits
        margin = max(POSITION_MARGIN * (hi - lo), MIN_POSITION_MARGIN[j.type])
        column = q[:, i]
        out = np.flatnonzero((column < lo - margin) | (column > hi + margin))
        if out.size:
            row = int(out[0])
            if j.type == "revolute":
                scaled = np.radians(column)
                cause = "degrees logged under a _rad column?"
            else:
                scaled = column / 1000.0
                cause = "millimetres logged under a _m column?"
            if not ((scaled >= lo - margin) & (scaled <= hi + margin)).all():
                cause = ("an encoder offset, another description's joint or a corrupt "
                         "column?")
            raise LogError(f"{file}: {names[1 + i]} is {column[row]:.6g} {length} at row "
                           f"{row + 1} of the data (line {row + 2}), outside joint {j.name}'s "
                           f"limits [{lo:.4g}, {hi:.4g}] {length} by more than {margin:.3g} "
                           f"{length} ({out.size} such row{'s' if out.size > 1 else ''}): {cause}")
    for i, j in enumerate(model.joints):
        force = _joint_units(j.type)[1]
        name = names[1 + 2 * n + i]
        column = tau[:, i]
        limit = j.effort_limit
        big = np.flatnonzero(np.abs(column) > MAX_EFFORT_MULTIPLE * limit)
        if big.size:
            row = int(big[0])
            cause = ("efforts in mN m logged as N m?" if j.type == "revolute" else
                     "forces in mN logged as N?") \
                if (np.abs(column) / 1000.0 <= MAX_EFFORT_MULTIPLE * limit).all() else \
                "a scaled or corrupt column?"
            raise LogError(f"{file}: {name} is {column[row]:.6g} {force} at row {row + 1} of "
                           f"the data (line {row + 2}), beyond {MAX_EFFORT_MULTIPLE:g} times "
                           f"joint {j.name}'s effort limit {limit:g} {force} ({big.size} such "
                           f"row{'s' if big.size > 1 else ''}): {cause}")
        spread = float(np.ptp(column))
        if spread <= FLAT_EFFORT * limit:
            raise LogError(f"{file}: {name} carries no signal: "
                           + (f"{column[0]:.6g} {force} on every row" if spread == 0 else
                              f"it varies by {spread:.3g} {force} over the log")
                           + ": expected the commanded effort of a moving joint (efforts not "
                           "recorded, or a column zeroed)")
