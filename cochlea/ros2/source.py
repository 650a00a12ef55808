"""Where the bridge's rows come from, without ROS: the raw ``log.bin`` of a real-time run as
its log writer appends it (``follow``), or a finished run's ``log.csv`` (``replay``, through
:mod:`cochlea.export.run_log`). Both give float64 rows and, per unit, the column indices of
``q``, ``qd`` and ``tau`` (:class:`~cochlea.export.run_log.UnitColumns`), so the frames are
computed by the same code ``cochlea-mcap`` uses
(:func:`cochlea.export.to_mcap.frame_transforms`).
"""

from __future__ import annotations

import errno
import math
import os
import stat
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import files
from ..errors import CochleaError
from ..export.run_log import (
    MAX_TIME_S,
    Group,
    RunFolderError,
    UnitColumns,
    by_joint,
    model_joints,
    read_json,
    time_steps,
)
from ..export.to_mcap import frame_transforms
from ..robots import robot
from ..robots.urdf import export_urdf  # the public face of the serial kind's URDF
from ..sim.scenario import load as load_scenario

#: The raw log's groups the bridge needs (their elements' units: run_log.JOINT_GROUP_UNITS).
RAW_GROUPS = ("q", "qd", "tau")


@dataclass
class Described:
    """The robot of a run: adapter, description (system) and its units' columns."""

    adapter: object
    system: object
    units: list[UnitColumns]

    def joint_names(self) -> list[str]:
        """``UNIT/JOINT`` of every joint, the units in turn (the names on /joint_states and
        in the URDF)."""
        return [f"{u.name}/{j}" for u in self.units for j in u.joints()]

    def columns(self, group: str) -> list[int]:
        return [c for u in self.units for c in u.groups[group].columns]

    def transforms(self, rows: np.ndarray) -> list[list]:
        """Per row, ``(child, parent, translation, quaternion)`` of every frame: cochlea-mcap's
        own computation (:func:`cochlea.export.to_mcap.frame_transforms`), on these columns."""
        frames = {u.name: self.adapter.link_frames(self.system, u.name) for u in self.units}
        return frame_transforms(self.units, frames, rows)


def check_rate(rate: float) -> float:
    if not isinstance(rate, (int, float)) or not math.isfinite(rate) or rate <= 0:
        raise CochleaError(f"--rate {rate}: a publishing rate in Hz, finite and > 0")
    if rate > 1000:
        raise CochleaError(f"--rate {rate:g}: at most 1000 Hz (the control rate; the bridge "
                           "publishes the newest row at its own rate)")
    return float(rate)


def describe_scenario(scenario_name: str) -> tuple[object, object]:
    """The adapter and description of a scenario (a shipped name or a .toml)."""
    try:
        scenario = load_scenario(scenario_name)
    except CochleaError as exc:
        raise CochleaError(f"--scenario: {exc}") from None
    return robot(scenario.robot), scenario.system


def raw_units(adapter, system, names: list[str], where: Path) -> list[UnitColumns]:
    """Per unit, the ``q``, ``qd``, ``tau`` columns of ``log.bin`` from ``log.columns.json``'s
    names: ``UNIT.GROUP.JOINT_UNIT`` (``arm1.q.joint1_rad``, the one schema of every log,
    docs/logs.md), or a version-1 log's ``GROUP.UNIT.JOINT_UNIT``."""
    units = []
    for unit in adapter.layout(system, "joint").units:
        joints = model_joints(adapter, system, unit)
        n = len(joints)
        groups = {}
        for group in RAW_GROUPS:
            g = Group(group)
            for prefix in (f"{unit}.{group}.", f"{group}.{unit}."):  # version 2, then 1
                for index, name in enumerate(names):
                    if name.startswith(prefix):
                        g.columns.append(index)
                        g.elements.append(name[len(prefix):])
                if g.columns:
                    break
            if len(g.columns) != n:
                raise RunFolderError(f"{where} is not this robot's log: unit {unit} has {n} "
                                     f"joints but the log has {len(g.columns)} {group} columns")
            # By the joints' names and units, in the model's order; never by position.
            groups[group] = by_joint(g, unit, joints, where)
        units.append(UnitColumns(unit, groups))
    return units


class RawTail:
    """``log.bin`` of a real-time run, read while its writer appends whole float64 rows
    (``log.columns.json`` says how many values a row has). Reads only: never opens the file
    for writing, never locks it, so a tail that stalls or dies changes nothing in the run."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.bin = self.folder / "log.bin"
        spec_path = self.folder / "log.columns.json"
        try:
            # A regular file only (a FIFO would block), any JSON damage one line (nested too
            # deep included): run_log.read_json.
            spec = read_json(spec_path)
        except RunFolderError as exc:
            raise RunFolderError(f"{spec_path} is not a real-time run's column list ({exc})") \
                from None
        columns, width = (spec.get("columns"), spec.get("row_length")) \
            if isinstance(spec, dict) else (None, None)
        if not isinstance(columns, list) or not all(isinstance(c, str) for c in columns) \
                or not columns or columns[0] != "time_s" or isinstance(width, bool) \
                or not isinstance(width, int) or spec.get("dtype") != "float64" \
                or width != len(columns):
            raise RunFolderError(f"{spec_path} is not a real-time run's column list (float64 "
                                 "rows: dtype, row_length and its columns, names from time_s)")
        self.names, self.width = list(columns), width
        self.row_bytes = 8 * self.width
        #: time_s of the last row checked (rows are checked as they are read).
        self._last_time = -math.inf

    def _read(self, start: int, count: int) -> bytes:
        """``count`` rows from row ``start`` of log.bin, a regular file (a folder or a FIFO
        there is a damaged run folder, one line)."""
        try:
            with open(self.bin, "rb") as f:
                if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                    raise OSError(errno.EINVAL, "not a regular file")
                f.seek(start * self.row_bytes)
                data = f.read(count * self.row_bytes)
        except OSError as exc:
            raise RunFolderError(f"{self.bin} cannot be read ({exc.strerror or exc})") from None
        if len(data) != count * self.row_bytes:
            raise RunFolderError(f"{self.bin} shrank while it was read: not a growing run log")
        return data

    def rows_written(self) -> int:
        try:
            st = os.stat(self.bin)
        except FileNotFoundError:
            return 0
        except OSError as exc:
            raise RunFolderError(f"{self.bin} cannot be read ({exc.strerror})") from None
        if not stat.S_ISREG(st.st_mode):
            raise RunFolderError(f"{self.bin} is {files.kind(st.st_mode)}, not a regular file: "
                                 "not a run's raw log")
        return st.st_size // self.row_bytes

    def times(self, start: int, stop: int) -> np.ndarray:
        """``time_s`` of rows ``start`` to ``stop - 1`` (rows counted by :meth:`rows_written`),
        each checked: finite, in [0, 2**31) s (a ROS stamp's seconds) and after the row before
        (a NaN, an infinity or garbage there is damage, refused in one line; a NaN row of a
        lost period keeps its time)."""
        data = self._read(start, stop - start)
        times = np.frombuffer(data, dtype=np.float64).reshape(-1, self.width)[:, 0].copy()
        steps = time_steps(np.concatenate([[self._last_time], times]))
        bad = ~np.isfinite(times) | (times < 0) | (times >= MAX_TIME_S) | ~(steps > 0)
        if bad.any():
            k = int(np.argmax(bad))
            raise RunFolderError(f"{self.bin} is damaged: row {start + k + 1}: time_s = "
                                 f"{float(times[k])!r} is not finite, outside [0, 2**31) s or "
                                 "not after the row before")
        if len(times):
            self._last_time = float(times[-1])
        return times

    def row(self, index: int) -> np.ndarray:
        """Row ``index`` (0-based; a row counted by :meth:`rows_written`)."""
        return np.frombuffer(self._read(index, 1), dtype=np.float64).reshape(1, self.width)


def _rpy(R: np.ndarray) -> tuple[float, float, float]:
    """URDF's fixed-axis roll, pitch, yaw of a rotation matrix."""
    pitch = math.asin(max(-1.0, min(1.0, -float(R[2, 0]))))
    return (math.atan2(float(R[2, 1]), float(R[2, 2])), pitch,
            math.atan2(float(R[1, 0]), float(R[0, 0])))


def _rest_poses(adapter, system, unit: str):
    """Each frame of ``unit`` in its parent at ``q = 0``: ``(name, parent, xyz, rpy)``."""
    frames = adapter.link_frames(system, unit)
    n = int(frames.function.size1_in(0))
    values = np.array(frames.function(np.zeros(n)))
    out = []
    for k, (name, parent) in enumerate(zip(frames.names, frames.parents)):
        R = values[:9, k].reshape(3, 3, order="F")
        out.append((name, parent, values[9:, k], _rpy(R)))
    return out


def _vec(v) -> str:
    return " ".join(repr(float(x)) for x in v)


def robot_description(described: Described) -> str:
    """A URDF whose links are the frames published on ``/tf`` (``world``, ``UNIT/base``,
    ``UNIT/LINK``, ``UNIT/tool``, ...) and whose joints are named as on ``/joint_states``.

    A serial arm's is ``cochlea-urdf export``'s (:func:`cochlea.robots.urdf.export_urdf`:
    inertials, axes, limits), its names prefixed with the unit; the frames it lacks (a tool
    frame) are fixed joints at their pose. A closed chain (the parallel mechanism) is not a
    URDF tree: each body is a link on a ``floating`` joint from its frame's parent, which
    ``/tf`` poses."""
    adapter, system = described.adapter, described.system
    root = ET.Element("robot", name=f"cochlea_{adapter.name}")
    root.append(ET.Comment(" written by cochlea-ros2 from the run's robot description; "
                           "frames as on /tf, joints as on /joint_states "))
    ET.SubElement(root, "link", name="world")
    have = {"world"}
    for unit in described.units:
        rest = _rest_poses(adapter, system, unit.name)
        # A description of arms (a serial chain per unit) has cochlea-urdf export's URDF; a
        # closed chain has none (asked of the description, not of the robot's name).
        tree = None
        if callable(getattr(system, "arm", None)):
            arm = system.arm(unit.name)
            tree = ET.fromstring(export_urdf(system, arm))
        if tree is not None:
            links = [e.get("name") for e in tree.findall("link")]
            chain = [rest[0][0]] + [f"{unit.name}/{link.name}" for link in arm.links]
            rename = {links[1]: chain[0]}  # the arm's base link
            rename.update({link.name: f"{unit.name}/{link.name}" for link in arm.links})
            for e in tree.findall("link"):
                name = e.get("name")
                if name == links[0] or name not in rename:
                    continue  # its world (ours is shared) and its own tool link (ours below)
                e.set("name", rename[name])
                root.append(e)
                have.add(rename[name])
            for e in tree.findall("joint"):
                parent, child = e.find("parent"), e.find("child")
                if child.get("link") not in rename:
                    continue  # the tool: added below from /tf's own tool frame
                parent.set("link", "world" if parent.get("link") == links[0]
                           else rename[parent.get("link")])
                child.set("link", rename[child.get("link")])
                e.set("name", f"{unit.name}/{e.get('name')}")
                root.append(e)
        kind = "fixed" if tree is not None else "floating"
        for name, parent, xyz, rpy in rest:
            if name in have:
                continue
            ET.SubElement(root, "link", name=name)
            joint = ET.SubElement(root, "joint", name=f"{name}_joint", type=kind)
            ET.SubElement(joint, "parent", link=parent)
            ET.SubElement(joint, "child", link=name)
            ET.SubElement(joint, "origin", xyz=_vec(xyz), rpy=_vec(rpy))
            have.add(name)
    ET.indent(root)
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, "unicode") + "\n"
