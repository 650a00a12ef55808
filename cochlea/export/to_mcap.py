"""A run folder's log as an MCAP file of standard ROS 2 messages, CDR-encoded with ``ros2msg``
schemas (:mod:`cochlea.export.ros2_msgs`), which Foxglove and ``ros2 bag`` read. The topics
(docs/logs.md), each message stamped (header and MCAP log time) with the period's ``time_s``
in nanoseconds:

* ``/UNIT/joint_states`` (``sensor_msgs/msg/JointState``): what the controller measured,
  ``q``, ``qd`` and the applied effort ``tau``; ``/UNIT/true/joint_states`` the plant's true
  ``true_q``, ``true_qd`` (simulated runs) with the same effort; ``/UNIT/desired/joint_states``
  the desired joint path and its rate (joint-space runs);
* ``/tf`` (``tf2_msgs/msg/TFMessage``): every body frame of every unit at the measured joint
  position, by the robot's forward kinematics (``RobotAdapter.link_frames``);
* ``/UNIT/tool_pose/actual|true|desired`` (``geometry_msgs/msg/PoseStamped``): the planar tool
  poses of the log's ``pose``, ``true_pose`` and (task-space runs) ``desired`` columns; the
  model's ``fk_world`` at the desired joints in joint space, and at ``q`` for a log without
  ``pose`` (the embedded program's);
* ``/UNIT/GROUP`` (``std_msgs/msg/Float64MultiArray``) for every column group of the log
  (``p_hat``, ``tau``, ``error``, ...), its layout's one dimension labelled with the
  elements' names and units; ``/run/timing`` the run-level columns of a real-time run;
* ``/rosout`` (``rcl_interfaces/msg/Log``): the run's start, and how it stopped or what the
  supervisor's verdict was, from ``summary.json``.
"""

from __future__ import annotations

import json
import re

import numpy as np

from ..errors import CochleaError
from .ros2_msgs import schema_name, schema_text
from .run_log import JOINT_UNITS, Group, RunLog, UnitColumns, strip_unit

try:  # the optional extra ``mcap`` (pip install cochlea[mcap])
    from mcap_ros2.writer import Writer
except ImportError:  # pragma: no cover - the test extra installs it
    Writer = None

WORLD = "world"
LOG_INFO, LOG_WARN, LOG_ERROR = 20, 30, 40
#: Groups published as JointState (and still as Float64MultiArray).
STATE_GROUPS = ("q", "qd", "true_q", "true_qd")
#: Stop rules that are not a fault.
CLEAN_STOPS = ("completed", "user-stop", "none")


def topic_name(*parts: str) -> str:
    """A valid ROS 2 topic from parts (a unit's or group's characters other than letters,
    digits and ``_`` become ``_``)."""
    return "/" + "/".join(re.sub(r"[^A-Za-z0-9_]", "_", p) for p in parts)


def stamp(ns: int) -> dict:
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def quaternions(R: np.ndarray) -> np.ndarray:
    """``(..., 4)`` unit quaternions ``x, y, z, w`` (w >= 0) of rotation matrices
    ``(..., 3, 3)`` (Shepperd's method: the largest of the four as the pivot)."""
    R = np.asarray(R, float)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    trace = m00 + m11 + m22
    q = np.zeros(R.shape[:-2] + (4,))
    cases = np.argmax(np.stack([trace, m00, m11, m22], axis=-1), axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.sqrt(np.maximum(1.0 + np.stack([trace, m00 - m11 - m22, m11 - m00 - m22,
                                               m22 - m00 - m11], axis=-1), 0.0)) * 2
        cand = {
            0: (R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                R[..., 1, 0] - R[..., 0, 1], None),
            1: (None, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0],
                R[..., 2, 1] - R[..., 1, 2]),
            2: (R[..., 0, 1] + R[..., 1, 0], None, R[..., 1, 2] + R[..., 2, 1],
                R[..., 0, 2] - R[..., 2, 0]),
            3: (R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], None,
                R[..., 1, 0] - R[..., 0, 1]),
        }
        for case, (a, b, c, d) in cand.items():
            sel = cases == case
            sc = s[..., case]
            parts = [a, b, c, d]
            pivot = {0: 3, 1: 0, 2: 1, 3: 2}[case]
            for i in range(4):
                q[..., i] = np.where(sel, (0.25 * sc) if i == pivot else parts[i] / sc, q[..., i])
    q *= np.where(q[..., 3:4] < 0, -1.0, 1.0)
    return q


def yaw_quaternion(phi: float) -> dict:
    return {"x": 0.0, "y": 0.0, "z": float(np.sin(0.5 * phi)), "w": float(np.cos(0.5 * phi))}


def planar_poses(group: Group | None) -> list[tuple[int, int, int]] | None:
    """The ``(x, y, angle)`` column triples of a pose group whose elements are planar poses
    (``_m``, ``_m``, ``_rad`` in turn), or None."""
    if group is None or not group.elements or len(group.elements) % 3:
        return None
    triples = []
    for k in range(0, len(group.elements), 3):
        a, b, c = group.elements[k:k + 3]
        if not (a.endswith("_m") and b.endswith("_m") and c.endswith("_rad")):
            return None
        triples.append(tuple(group.columns[k:k + 3]))
    return triples


def frame_transforms(units: list[UnitColumns], frames: dict, rows: np.ndarray,
               maps: dict | None = None) -> list[list]:
    """Per row, ``(child, parent, translation, quaternion)`` of every frame of every unit at
    the measured ``q`` (``frames``: each unit's ``adapter.link_frames``); an empty list (no
    ``/tf`` message) for a row where a unit's ``q`` is not finite (a run stopped by the rule
    non-finite). ``maps`` caches the frames' functions mapped over a number of rows (CasADi
    ``map``), per unit and row count, between calls. cochlea-mcap's ``/tf`` and the ROS 2
    bridge's (cochlea.ros2.source) are this one computation."""
    maps = {} if maps is None else maps
    n = len(rows)
    finite = np.ones(n, bool)
    per_unit = []
    for unit in units:
        unit_frames = frames[unit.name]
        q = rows[:, unit.groups["q"].columns]
        finite &= np.isfinite(q).all(axis=1)
        if n not in maps.setdefault(unit.name, {}):
            maps[unit.name][n] = unit_frames.function.map(n)
        k = len(unit_frames.names)
        # map(n) puts row r's 12 x k block at columns r k .. r k + k - 1.
        values = np.array(maps[unit.name][n](q.T)).reshape(12, n, k)
        # Each rotation's 9 entries are column-major: entry 3 c + r is R[r, c].
        R = values[:9].reshape(3, 3, n, k).transpose(2, 3, 1, 0)
        p = values[9:].transpose(1, 2, 0)
        per_unit.append((unit_frames, p, quaternions(R)))
    out = []
    for r in range(n):
        out.append([] if not finite[r] else [
            (child, parent, p[r, f].tolist(), quat[r, f].tolist())
            for unit_frames, p, quat in per_unit
            for f, (child, parent) in enumerate(zip(unit_frames.names, unit_frames.parents))])
    return out


class Exporter:
    """Writes one run's messages to an open binary file."""

    def __init__(self, run: RunLog, stream):
        if Writer is None:
            raise CochleaError("cochlea-mcap needs the packages mcap and mcap-ros2-support: "
                               "pip install 'cochlea[mcap]'")
        self.run = run
        self.writer = Writer(stream)
        self.schemas = {}
        self.counts: dict[str, int] = {}
        self.frames = {u.name: run.adapter.link_frames(run.system, u.name) for u in run.units}
        self._maps = {}
        self._fk = {}

    def schema(self, name: str):
        if name not in self.schemas:
            self.schemas[name] = self.writer.register_msgdef(schema_name(name),
                                                             schema_text(name))
        return self.schemas[name]

    def write(self, topic: str, type_name: str, message: dict, ns: int) -> None:
        self.writer.write_message(topic, self.schema(type_name), message, log_time=ns,
                                  publish_time=ns, sequence=self.counts.get(topic, 0))
        self.counts[topic] = self.counts.get(topic, 0) + 1

    # ---- per unit ----------------------------------------------------------------------------

    def joint_states(self, unit: UnitColumns) -> list[tuple[str, str, str, str | None]]:
        """``(topic, position group, velocity group, effort group)`` of a unit."""
        g = unit.groups
        out = [(topic_name(unit.name, "joint_states"), "q", "qd", "tau")]
        if "true_q" in g and "true_qd" in g:
            out.append((topic_name(unit.name, "true", "joint_states"), "true_q", "true_qd",
                        "tau"))
        desired = g.get("desired")
        if desired is not None and "desired_dot" in g and desired.elements == g["q"].elements:
            out.append((topic_name(unit.name, "desired", "joint_states"), "desired",
                        "desired_dot", None))
        return out

    def poses(self, unit: UnitColumns) -> list[tuple[str, tuple]]:
        """``(topic, source)`` of a unit's tool poses: ``source`` the ``(x, y, angle)`` columns
        of a logged pose, or ``("fk", group, i)``: tool ``i`` of the robot model's
        ``fk_world`` at the joints of ``group`` (the desired pose of a joint-space run; the
        actual pose of a log without ``pose`` columns, the embedded program's)."""
        g = unit.groups
        joints = g["q"].elements
        n_tools = int(self.fk_world(unit.name).size1_out(0)) // 3
        out = []
        sources = [("actual", planar_poses(g.get("pose")) or
                    [("fk", "q", i) for i in range(n_tools)]),
                   ("true", planar_poses(g.get("true_pose")))]
        desired = g.get("desired")
        if desired is not None and "pose" in g and desired.elements == g["pose"].elements:
            sources.append(("desired", planar_poses(desired)))
        elif desired is not None and desired.elements == joints:
            sources.append(("desired", [("fk", "desired", i) for i in range(n_tools)]))
        for label, triples in sources:
            for i, source in enumerate(triples or ()):
                tool = "tool_pose" if len(triples) == 1 else f"tool{i + 1}_pose"
                out.append((topic_name(unit.name, tool, label), source))
        return out

    def fk_world(self, unit: str):
        """The unit's tool poses in the world, ``q -> (x, y, phi) per tool`` (the model's)."""
        if unit not in self._fk:
            self._fk[unit] = self.run.adapter.model(self.run.system, unit).fk_world
        return self._fk[unit]

    def pose_values(self, unit: UnitColumns, sources: list, rows: np.ndarray) -> list:
        """Per pose topic of ``unit``, the chunk's ``(n, 3)`` x (m), y (m), angle (rad)."""
        computed, out = {}, []
        for _, source in sources:
            if source[0] == "fk":
                _, group, i = source
                if group not in computed:
                    q = rows[:, unit.groups[group].columns]
                    computed[group] = np.array(
                        self.fk_world(unit.name).map(len(rows))(q.T)).T
                out.append(computed[group][:, 3 * i:3 * i + 3])
            else:
                out.append(rows[:, list(source)])
        return out

    def export(self) -> dict[str, int]:
        run = self.run
        self.writer.add_metadata("cochlea_run", {
            "folder": str(run.folder.resolve()), "robot": run.adapter.name,
            "scenario_file": str(run.summary.get("scenario_file")),
            "summary_json": json.dumps(run.summary, sort_keys=True)})
        first_ns = None
        last_ns = 0
        states = {u.name: self.joint_states(u) for u in run.units}
        poses = {u.name: self.poses(u) for u in run.units}
        arrays = [(topic_name(u.name, g.name), g) for u in run.units for g in u.groups.values()]
        if run.run_level.columns:
            arrays.append((topic_name("run", "timing"), run.run_level))
        for rows in run.chunks():
            ns_all = np.rint(rows[:, 0] * 1e9).astype(np.int64)
            if first_ns is None:
                first_ns = int(ns_all[0])
                self.events_at_start(first_ns)
            tf = self.transforms(rows)
            pose_values = {u.name: self.pose_values(u, poses[u.name], rows) for u in run.units}
            for k, row in enumerate(rows):
                ns = int(ns_all[k])
                header = {"stamp": stamp(ns), "frame_id": WORLD}
                joint_header = {"stamp": stamp(ns), "frame_id": ""}
                for unit in run.units:
                    g = unit.groups
                    names = unit.joints()
                    for topic, pos, vel, eff in states[unit.name]:
                        self.write(topic, "sensor_msgs/JointState", {
                            "header": joint_header, "name": names,
                            "position": row[g[pos].columns].tolist(),
                            "velocity": row[g[vel].columns].tolist(),
                            "effort": row[g[eff].columns].tolist() if eff else []}, ns)
                    for (topic, _), values in zip(poses[unit.name], pose_values[unit.name]):
                        x, y, angle = values[k].tolist()
                        self.write(topic, "geometry_msgs/PoseStamped", {
                            "header": header, "pose": {
                                "position": {"x": x, "y": y, "z": 0.0},
                                "orientation": yaw_quaternion(angle)}}, ns)
                for topic, group in arrays:
                    label = ",".join(group.elements)
                    self.write(topic, "std_msgs/Float64MultiArray", {
                        "layout": {"dim": [{"label": label, "size": len(group.columns),
                                            "stride": len(group.columns)}],
                                   "data_offset": 0},
                        "data": row[group.columns].tolist()}, ns)
                if tf[k]:
                    self.write("/tf", "tf2_msgs/TFMessage", {"transforms": [
                        {"header": {"stamp": stamp(ns), "frame_id": parent},
                         "child_frame_id": child,
                         "transform": {"translation": {"x": p[0], "y": p[1], "z": p[2]},
                                       "rotation": {"x": r[0], "y": r[1], "z": r[2],
                                                    "w": r[3]}}}
                        for child, parent, p, r in tf[k]]}, ns)
            last_ns = int(ns_all[-1])
        self.events_at_end(first_ns, last_ns)
        self.writer.finish()
        return dict(self.counts)

    def transforms(self, rows: np.ndarray) -> list[list]:
        """Per row, every frame of every unit at the measured ``q`` (:func:`frame_transforms`)."""
        return frame_transforms(self.run.units, self.frames, rows, self._maps)

    # ---- events ------------------------------------------------------------------------------

    def log(self, ns: int, level: int, text: str) -> None:
        self.write("/rosout", "rcl_interfaces/Log", {
            "stamp": stamp(ns), "level": level, "name": "cochlea", "msg": text,
            "file": "summary.json", "function": "", "line": 0}, ns)

    def events_at_start(self, ns: int) -> None:
        s = self.run.summary
        self.log(ns, LOG_INFO, f"run started: robot {s.get('robot')}, scenario "
                               f"{s.get('scenario')}, space {s.get('space')}, controller "
                               f"{s.get('controller')}, {s.get('periods')} periods at "
                               f"{s.get('rate_Hz')} Hz")

    def events_at_end(self, first_ns: int, last_ns: int) -> None:
        s = self.run.summary

        def at(entry) -> int:
            t = entry.get("time_s")
            if isinstance(t, (int, float)) and not isinstance(t, bool) and np.isfinite(t):
                # Clamped to the log's span as a float first: 1e308 s is no integer of ns.
                ns = min(max(float(t) * 1e9, float(first_ns)), float(last_ns))
                return min(max(int(round(ns)), first_ns), last_ns)
            return last_ns

        stop = s.get("stop")
        if isinstance(stop, dict) and stop.get("rule"):
            rule = stop["rule"]
            self.log(at(stop), LOG_INFO if rule in CLEAN_STOPS else LOG_ERROR,
                     f"stop: rule {rule} at t = {stop.get('time_s')} s, exit code "
                     f"{stop.get('exit_code')}" + (f": {stop['detail']}" if stop.get("detail")
                                                   else ""))
        sup = s.get("supervisor")
        if isinstance(sup, dict) and sup.get("rule"):
            rule = sup["rule"]
            text = ("supervisor verdict: no rule would have stopped this as-fast run"
                    if rule == "none" else
                    f"supervisor verdict: a real run would have stopped by rule {rule} at t = "
                    f"{sup.get('time_s')} s, exit code {sup.get('exit_code')}: "
                    f"{sup.get('detail', '')}")
            text += f"; saturated periods {sup.get('saturated_periods')}"
            self.log(at(sup), LOG_INFO if rule == "none" else LOG_WARN, text)
        self.log(last_ns, LOG_INFO if s.get("converged") else LOG_WARN,
                 f"run ended: converged {s.get('converged')}, judged on the "
                 f"{s.get('judged_error')} error")


__all__ = ["Exporter", "quaternions", "planar_poses", "strip_unit", "JOINT_UNITS"]
