"""The desired joint trajectory of a run from a ROS 2 topic (``cochlea-run --desired-topic``).

Before anything moves, ``cochlea-run`` waits (``--desired-timeout``) for one
``trajectory_msgs/msg/JointTrajectory`` naming every joint the run controls as on
``/joint_states`` (``UNIT/JOINT``: ``arm1/joint1``, ``mechanism/slider.d1``), checks it, and
then runs it exactly as a scenario's own ``desired_joint`` path: every unit's path becomes a
CasADi expression in ``t`` (:class:`JointSpline`), so the simulation layer's own checks of a
scenario's desired path (:func:`cochlea.sim.setup.unit_setups`: finite at every period, the
adapters' joint limits and workspace) run on it, and the loop precomputes its samples as it
does a scenario's (through :func:`sampler`, at a formula's cost). Before that, the run's own
supervisor rules (:func:`cochlea.runtime.supervisor.build_supervisor`, with the keep-out
circle) are applied to every point and to every period of the interpolated path, and so is
the effort the plant needs to follow it (docs/logs.md, "A desired trajectory from ROS 2").

Nothing here imports ROS until :func:`receive` is called: the checks are plain numbers
(:class:`Trajectory`), tested without a ROS graph.
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..errors import CochleaError
from ..robots.adapter import sample_times
from ..runtime.supervisor import build_supervisor
from ..sim.setup import check_run_length, unit_setups

#: ``cochlea-run`` exit codes of ``--desired-topic`` (README, docs/logs.md).
EXIT_NO_ROS = 4  # rclpy or trajectory_msgs not installed (the ``ros`` extra)
EXIT_NO_TRAJECTORY = 8  # no message on the topic within --desired-timeout
EXIT_REFUSED = 9  # the message failed a check; nothing moved

MESSAGE_TYPE = "trajectory_msgs/msg/JointTrajectory"
DEFAULT_TIMEOUT_S = 30.0
MAX_TIMEOUT_S = 86_400.0
#: How far the first point may be from the measured initial state, per joint type (rad, m).
START_TOLERANCE = {"revolute": math.radians(2.0), "prismatic": 0.002}
#: Points one message may hold (a 100 s path at 1 kHz).
MAX_POINTS = 100_000


class TopicError(CochleaError):
    """``--desired-topic`` failed: ``code`` is cochlea-run's exit code."""

    def __init__(self, message: str, code: int):
        super().__init__(message)
        self.code = code


def refused(topic: str, what: str) -> TopicError:
    return TopicError(f"--desired-topic {topic}: trajectory refused, nothing moved: {what}",
                      EXIT_REFUSED)


@dataclass(frozen=True)
class Trajectory:
    """A JointTrajectory's content as numbers (SI): ``times`` (m,) s from the run's start,
    ``positions`` (m, n), ``velocities`` and ``accelerations`` (m, n) or None."""

    topic: str
    stamp: tuple[int, int]  # header.stamp (sec, nanosec)
    names: tuple[str, ...]
    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray | None
    accelerations: np.ndarray | None

    def interpolation(self) -> str:
        if self.accelerations is not None:
            return ("quintic Hermite through each point's positions, velocities and "
                    "accelerations (C2)")
        if self.velocities is not None:
            return "cubic Hermite through each point's positions and velocities (C1)"
        return "cubic spline through the positions, at rest at both ends (C2)"


def _point(k: int, t: float | None = None) -> str:
    return f"point {k}" + (f" (t = {t:.6g} s)" if t is not None and math.isfinite(t) else "")


def from_message(msg, topic: str) -> Trajectory:
    """The numbers of a JointTrajectory message, its shape checked (one line naming the point
    and the field otherwise): at least one point and at most :data:`MAX_POINTS`, as many
    positions as names at every point, velocities and accelerations at every point or none,
    accelerations only with velocities, no efforts (cochlea's controllers make their own)."""
    names = tuple(str(n) for n in msg.joint_names)
    points = list(msg.points)
    if not names:
        raise refused(topic, "names: the message names no joint")
    if not points:
        raise refused(topic, "points: the message has no point")
    if len(points) > MAX_POINTS:
        raise refused(topic, f"points: {len(points)} points, at most {MAX_POINTS}")
    n = len(names)
    fields = {}
    for field in ("positions", "velocities", "accelerations", "effort"):
        sizes = [len(getattr(p, field)) for p in points]
        given = [s for s in sizes if s]
        if field == "positions" or given:
            for k, s in enumerate(sizes):
                if s != n:
                    raise refused(topic, f"{_point(k)}: sizes: {s} {field} for {n} joint names"
                                  + (" (give them at every point or at none)"
                                     if field != "positions" else ""))
            fields[field] = np.array([list(getattr(p, field)) for p in points], float)
    if "effort" in fields:
        raise refused(topic, "effort: the message gives efforts; cochlea's controller computes "
                      "its own, give positions (velocities, accelerations) only")
    if "accelerations" in fields and "velocities" not in fields:
        raise refused(topic, "accelerations without velocities: give both, or velocities "
                      "alone, or neither")
    times = np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec
                      for p in points], float)
    stamp = (int(msg.header.stamp.sec), int(msg.header.stamp.nanosec))
    return Trajectory(topic, stamp, names, times, fields["positions"],
                      fields.get("velocities"), fields.get("accelerations"))


def check_numbers(tr: Trajectory, joint_names: list[str]) -> np.ndarray:
    """Names that match the run's joints (each once, any order), finite numbers, times from
    0 on, strictly increasing. Returns the column of each run joint in the message."""
    topic = tr.topic
    seen = {}
    for i, name in enumerate(tr.names):
        if name in seen:
            raise refused(topic, f"names: {name!r} is named twice")
        seen[name] = i
    unknown = [n for n in tr.names if n not in joint_names]
    if unknown:
        raise refused(topic, f"names: {unknown[0]!r} is not a joint of this run (its joints: "
                      f"{', '.join(joint_names)})")
    missing = [n for n in joint_names if n not in seen]
    if missing:
        raise refused(topic, f"names: the message lacks {', '.join(missing)}: it must give "
                      "every joint of the run")
    for k, t in enumerate(tr.times):
        if not math.isfinite(t):
            raise refused(topic, f"{_point(k)}: finite: time_from_start is {t}")
    for field in ("positions", "velocities", "accelerations"):
        values = getattr(tr, field)
        if values is None:
            continue
        bad = np.argwhere(~np.isfinite(values))
        if bad.size:
            k, i = bad[0]
            raise refused(topic, f"{_point(k, tr.times[k])}: finite: {field} of "
                          f"{tr.names[i]} is {values[k, i]}")
    if tr.times[0] < 0:
        raise refused(topic, f"{_point(0)}: sorted times: time_from_start {tr.times[0]:g} s "
                      "is negative")
    step = np.diff(tr.times)
    if step.size and not (step > 0).all():
        k = int(np.argmax(~(step > 0))) + 1
        raise refused(topic, f"{_point(k)}: sorted times: time_from_start {tr.times[k]:.9g} s "
                      f"is not after point {k - 1}'s {tr.times[k - 1]:.9g} s")
    return np.array([seen[n] for n in joint_names])


# ----------------------------------------------------------------------------------------------
# The path as a scenario's desired_joint
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class JointSpline:
    """One joint's desired path, piecewise polynomial in ``t``: segment ``k`` starts at
    ``starts[k]`` and is ``sum_j coefs[k][j] (t - starts[k])^j`` (degree 5 at most); the last
    segment holds the last point. Behaves as a scenario's :class:`~cochlea.sim.scenario.
    Quantity` (``expression(t, definitions)``, SI), so a unit's ``desired_joint`` may hold it.

    The segment of ``t`` is found by CasADi's linear interpolants (a binary search), so a
    sample costs the same whatever the number of points; the segment index is a ``floor``,
    whose derivative is zero, so the exact derivatives of the expression are the
    polynomial's."""

    starts: tuple[float, ...]
    coefs: tuple[tuple[float, ...], ...]

    def expression(self, t: ca.SX, definitions=None) -> ca.SX:  # noqa: ARG002
        count = len(self.starts)
        grid = [*self.starts, self.starts[-1] + 1.0]
        index = ca.interpolant("desired_segment", "linear", [grid],
                               [float(i) for i in range(count + 1)])
        k = ca.floor(ca.fmin(ca.fmax(index(t), 0.0), count - 1))
        rows = [[s, *c] for s, c in zip(self.starts, self.coefs)]
        if count == 1:
            rows.append(rows[0])
        table = ca.interpolant("desired_coefficients", "linear",
                               [[float(i) for i in range(len(rows))]],
                               np.array(rows, float).ravel().tolist())
        row = table(k)
        s = t - row[0]
        value = row[6]
        for j in range(5, 0, -1):
            value = row[j] + s * value
        return value


def sampler(name: str, paths: list[JointSpline]) -> ca.Function:
    """``t -> (x, x_dot, x_ddot)`` of a unit's joints (as :func:`cochlea.robots.adapter.
    desired_function` gives a scenario's), the derivatives written out from the polynomials
    instead of differentiated through the segment look-up: two look-ups a sample for the whole
    unit (the segment, then every joint's coefficients), so the loop's chunk of desired
    samples costs what a scenario formula's does. Equal to the expression's exact derivatives
    (``tests/test_ros2_desired.py``)."""
    starts = paths[0].starts
    count = len(starts)
    t = ca.SX.sym("t")
    index = ca.interpolant(f"{name}_segment", "linear", [[*starts, starts[-1] + 1.0]],
                           [float(i) for i in range(count + 1)])
    k = ca.floor(ca.fmin(ca.fmax(index(t), 0.0), count - 1))
    rows = [[s, *(c for p in paths for c in p.coefs[i])] for i, s in enumerate(starts)]
    if count == 1:
        rows.append(rows[0])
    table = ca.interpolant(f"{name}_coefficients", "linear",
                           [[float(i) for i in range(len(rows))]],
                           np.array(rows, float).ravel().tolist())
    row = table(k)
    s = t - row[0]
    x, xd, xdd = [], [], []
    for j in range(len(paths)):
        c = [row[1 + 6 * j + i] for i in range(6)]
        value, rate, curve = c[5], 5 * c[5], 20 * c[5]
        for i in range(4, -1, -1):
            value = c[i] + s * value
        for i in range(4, 0, -1):
            rate = i * c[i] + s * rate
        for i in range(4, 1, -1):
            curve = i * (i - 1) * c[i] + s * curve
        x.append(value)
        xd.append(rate)
        xdd.append(curve)
    return ca.Function(f"desired_{name}", [t], [ca.vertcat(*x), ca.vertcat(*xd),
                                                 ca.vertcat(*xdd)],
                       ["t"], ["x", "x_dot", "x_ddot"])


def _segments(times, p, v, a) -> tuple[list[float], list[list[float]]]:
    """Coefficients of each segment between consecutive knots (one joint), then the hold."""
    starts, coefs = [], []
    for k in range(len(times) - 1):
        h = times[k + 1] - times[k]
        p0, p1, v0, v1 = p[k], p[k + 1], v[k], v[k + 1]
        if a is not None:  # quintic Hermite
            a0, a1 = a[k], a[k + 1]
            c = [p0, v0, a0 / 2,
                 (20 * (p1 - p0) - (8 * v1 + 12 * v0) * h - (3 * a0 - a1) * h * h) / (2 * h**3),
                 (30 * (p0 - p1) + (14 * v1 + 16 * v0) * h + (3 * a0 - 2 * a1) * h * h)
                 / (2 * h**4),
                 (12 * (p1 - p0) - 6 * (v1 + v0) * h - (a0 - a1) * h * h) / (2 * h**5)]
        else:  # cubic Hermite
            c = [p0, v0, (3 * (p1 - p0) / h - 2 * v0 - v1) / h,
                 (2 * (p0 - p1) / h + v0 + v1) / (h * h), 0.0, 0.0]
        starts.append(float(times[k]))
        coefs.append([float(x) for x in c])
    starts.append(float(times[-1]))
    coefs.append([float(p[-1]), 0.0, 0.0, 0.0, 0.0, 0.0])
    return starts, coefs


def splines(tr: Trajectory, columns: np.ndarray, x0: np.ndarray) -> list[JointSpline]:
    """Every run joint's path (the run's joint order): the message's points, and when its
    first point comes after t = 0 the measured initial state (position, velocity, zero
    acceleration) as a knot at t = 0 before them."""
    n = len(columns)
    times = tr.times
    P = tr.positions[:, columns]
    V = None if tr.velocities is None else tr.velocities[:, columns]
    A = None if tr.accelerations is None else tr.accelerations[:, columns]
    if times[0] > 0:
        times = np.concatenate([[0.0], times])
        P = np.vstack([x0[:n], P])
        V = None if V is None else np.vstack([x0[n:], V])
        A = None if A is None else np.vstack([np.zeros(n), A])
    if V is None:  # positions only: the C2 cubic spline, clamped at rest at both ends
        if len(times) > 1:
            # scipy.interpolate would be 0.6 s of every cochlea-run start at the top.
            from scipy.interpolate import CubicSpline  # noqa: PLC0415

            V = CubicSpline(times, P, bc_type="clamped").derivative()(times)
        else:
            V = np.zeros_like(P)
    out = []
    for i in range(n):
        starts, coefs = _segments(times, P[:, i], V[:, i], None if A is None else A[:, i])
        out.append(JointSpline(tuple(starts), tuple(tuple(c) for c in coefs)))
    return out


def with_path(sc, paths: list[JointSpline], sizes: list[int]):
    """The scenario with every unit following its slice of ``paths`` (its ``desired_joint``)."""
    units, first = [], 0
    for unit, size in zip(sc.units, sizes, strict=True):
        units.append(dataclasses.replace(unit, desired_joint=tuple(paths[first:first + size])))
        first += size
    return dataclasses.replace(sc, units=tuple(units))


# ----------------------------------------------------------------------------------------------
# Receiving the message
# ----------------------------------------------------------------------------------------------


def check_timeout(timeout: float) -> float:
    if not (isinstance(timeout, (int, float)) and math.isfinite(timeout)
            and 0 < timeout <= MAX_TIMEOUT_S):
        raise CochleaError(f"--desired-timeout {timeout}: seconds to wait, finite, > 0 and at "
                           f"most {MAX_TIMEOUT_S:g}")
    return float(timeout)


def check_topic(topic: str) -> str:
    """A ROS 2 topic name (absolute or relative: letters, digits, ``_`` and ``/``)."""
    if not re.fullmatch(r"/?[A-Za-z_~][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*", topic or ""):
        raise CochleaError(f"--desired-topic {topic!r}: a ROS 2 topic name such as "
                           "/cochlea/desired (letters, digits, _ and /)")
    return topic


def receive(topic: str, timeout: float):
    """The first JointTrajectory published on ``topic`` (reliable, volatile, depth 1) within
    ``timeout`` s, from a node of its own (``cochlea_desired``) that is gone on return."""
    # The optional extra ``ros``, imported only when a run waits on a topic; ``node`` first:
    # it sets the middleware and the discovery range before rclpy starts.
    from . import node  # noqa: PLC0415
    try:
        import rclpy  # noqa: PLC0415
        from rclpy.executors import SingleThreadedExecutor  # noqa: PLC0415
        from rclpy.qos import (  # noqa: PLC0415
            DurabilityPolicy,
            HistoryPolicy,
            QoSProfile,
            ReliabilityPolicy,
        )
        from rclpy.signals import SignalHandlerOptions  # noqa: PLC0415
        from trajectory_msgs.msg import JointTrajectory  # noqa: PLC0415
    except ImportError as exc:
        raise TopicError(f"--desired-topic needs ROS 2's rclpy and trajectory_msgs ({exc}): "
                         "pip install 'cochlea[ros]'", EXIT_NO_ROS) from None
    del node
    context = rclpy.context.Context()
    # No signal handlers of rclpy's: Ctrl-C stays cochlea-run's (exit 130, nothing moved).
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    got = []
    try:
        n = rclpy.create_node("cochlea_desired", context=context)
        qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
        n.create_subscription(JointTrajectory, topic, got.append, qos)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(n)
        deadline = time.monotonic() + timeout
        while not got and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=min(0.1, max(deadline - time.monotonic(), 0.0)))
        executor.shutdown()
        n.destroy_node()
    finally:
        rclpy.shutdown(context=context)
    if not got:
        raise TopicError(f"--desired-topic {topic}: no {MESSAGE_TYPE} within {timeout:g} s "
                         "(--desired-timeout); nothing moved", EXIT_NO_TRAJECTORY)
    return got[0]


# ----------------------------------------------------------------------------------------------
# The checks and the run's scenario
# ----------------------------------------------------------------------------------------------


@dataclass
class Desired:
    """What ``cochlea-run --desired-topic`` prepared before waiting: the run's start."""

    topic: str
    timeout: float
    setups: list  # the scenario's own: the run's start, limits and models
    names: list[str]  # the run's joints, UNIT/JOINT
    sizes: list[int]


def prepare(scenario, topic: str, timeout: float) -> Desired:
    """The scenario checked as usual (its own path, initial state, gravity) before the wait,
    and the names the message must give."""
    check_topic(topic)
    check_timeout(timeout)
    if scenario.space != "joint":
        raise CochleaError("--desired-topic takes a joint trajectory and goes with --space joint")
    # The scenario's own checks (its path, the initial state, gravity) and the run's start,
    # limits and models: none of them depends on the path the topic will give.
    setups = unit_setups(scenario)
    sizes = [u.controller_model.nq for u in setups]
    names = [f"{u.name}/{j.name}" for u in setups for j in u.controller_model.joints]
    return Desired(topic, timeout, setups, names, sizes)


def take(prepared: Desired, scenario, duration: float | None, rate_hz: float, msg):
    """Check the message and make the run's scenario (duration: ``duration`` or the last
    point's time). Returns ``(scenario, source)``: ``source`` is summary.json's
    ``desired_source``. Raises :class:`TopicError` (:data:`EXIT_REFUSED`) naming the point or
    the time and the rule."""
    topic = prepared.topic
    tr = from_message(msg, topic)
    columns = check_numbers(tr, prepared.names)
    setups = prepared.setups
    x0 = np.concatenate([u.x0[:u.controller_model.nq] for u in setups])
    qd0 = np.concatenate([u.x0[u.controller_model.nq:] for u in setups])
    joints = [j for u in setups for j in u.controller_model.joints]
    # The first point near the measured initial state.
    first = tr.positions[0, columns]
    for i, j in enumerate(joints):
        if abs(first[i] - x0[i]) > START_TOLERANCE[j.type]:
            deg = j.type == "revolute"
            scale, unit = (180 / math.pi, "deg") if deg else (1.0, "m")
            raise refused(topic, f"{_point(0, tr.times[0])}: start: {prepared.names[i]} = "
                          f"{first[i] * scale:.4g} {unit}, {abs(first[i] - x0[i]) * scale:.3g} "
                          f"{unit} from the measured initial state {x0[i] * scale:.4g} {unit} "
                          f"(at most {START_TOLERANCE[j.type] * scale:g} {unit})")
    # Every point under the run's own supervisor rules, the keep-out circle included.
    supervisor = build_supervisor(setups, scenario.system.keep_out_radius,
                                  kernels="casadi")
    n = len(joints)
    for k in range(len(tr.times)):
        q = tr.positions[k, columns]
        qd = np.zeros(n) if tr.velocities is None else tr.velocities[k, columns]
        x = np.concatenate([q, qd])
        stop = supervisor.check_state(float(tr.times[k]), x, x[:n], x[n:])
        if stop is not None:
            raise refused(topic, f"{_point(k, tr.times[k])}: {stop.rule}: {stop.detail}")
    end = float(tr.times[-1])
    run_s = end if duration is None else float(duration)
    if duration is None:  # the run is the path: at least one period, at most a run's periods
        try:
            check_run_length(run_s, rate_hz, "the last point's time_from_start")
        except CochleaError as exc:
            raise refused(topic, f"{_point(len(tr.times) - 1, end)}: duration: {exc}") \
                from None
    if run_s > end:  # held after its last point: only at rest
        for field in ("velocities", "accelerations"):
            values = getattr(tr, field)
            if values is not None and np.any(values[-1] != 0):
                raise refused(topic, f"{_point(len(tr.times) - 1, end)}: held: its {field} are "
                              f"not zero, yet the run ({run_s:g} s, --duration) goes on after "
                              "it; end at rest or shorten --duration")
    paths = splines(tr, columns, np.concatenate([x0, qd0]))
    period = 1.0 / rate_hz
    _check_periods(tr, paths, setups, supervisor, run_s, period, prepared.names)
    run_sc = with_path(dataclasses.replace(scenario, duration=run_s), paths, prepared.sizes)
    source = {"source": "ros2-topic", "topic": topic, "type": MESSAGE_TYPE,
              "stamp": {"sec": tr.stamp[0], "nanosec": tr.stamp[1]},
              "stamp_s": tr.stamp[0] + 1e-9 * tr.stamp[1], "points": int(len(tr.times)),
              "joint_names": list(tr.names), "last_point_s": end,
              "held_from_s": end if run_s > end else None,
              "interpolation": tr.interpolation()
              + ("; from the initial state at t = 0 to the first point" if tr.times[0] > 0
                 else "")}
    return run_sc, source


def _between(tr: Trajectory, t: float) -> str:
    k = int(np.searchsorted(tr.times, t, side="right"))
    if k == 0:
        return f"before point 0, at t = {t:.6g} s"
    if k >= len(tr.times):
        return f"after the last point, at t = {t:.6g} s"
    return f"between points {k - 1} and {k}, at t = {t:.6g} s"


def _check_periods(tr, paths, setups, supervisor, run_s, period, names) -> None:
    """Every period of the run on the interpolated path: the supervisor's rules, and the effort
    the plant needs to follow it (its inverse dynamics) within each joint's effort limit and
    drive (the description gives no acceleration limit: this is what bounds acceleration)."""
    functions, first = [], 0
    for u in setups:
        m = u.controller_model.nq
        functions.append(sampler(u.name, paths[first:first + m]))
        first += m
    n = first
    units = [un for u in setups for un in u.joint_units]
    for times in sample_times(run_s, period):
        qs, qds, taus, caps = [], [], [], []
        for u, f in zip(setups, functions):
            q, qd, qdd = (np.array(v, float) for v in f.map(len(times))(times.reshape(1, -1)))
            qs.append(q)
            qds.append(qd)
            tau = u.plant_model.inverse_dynamics_p.map(len(times))(
                q, qd, qdd, np.tile(u.plant_params[:, None], (1, len(times))))
            taus.append(np.abs(np.array(tau, float)))
            cap = u.effort_limit
            if u.effort_grid is not None:
                cap = np.minimum(cap, u.effort_grid.saturation)
            caps.append(cap)
        Q, QD, TAU = np.vstack(qs), np.vstack(qds), np.vstack(taus)
        cap = np.concatenate(caps)
        for k in range(len(times)):
            x = np.concatenate([Q[:, k], QD[:, k]])
            stop = supervisor.check_state(float(times[k]), x, x[:n], x[n:])
            if stop is not None:
                raise refused(tr.topic, f"{_between(tr, times[k])}: {stop.rule}: {stop.detail}")
            over = np.flatnonzero(~(TAU[:, k] <= cap * (1 + 1e-9)))
            if over.size:
                i = over[0]
                unit = "N m" if units[i] == "rad" else "N"
                raise refused(tr.topic, f"{_between(tr, times[k])}: effort: {names[i]} needs "
                              f"{TAU[i, k]:.4g} {unit} to follow the path, more than the "
                              f"{cap[i]:.4g} {unit} its drive gives (too fast an acceleration)")


def checked_setups(scenario, prepared: Desired, on_motors: bool = False):
    """The run's setups (:func:`cochlea.sim.setup.unit_setups`: the simulation layer's checks
    of a scenario's desired path), a refusal there worded as the topic's; each unit's
    ``desired`` then its :func:`sampler` (the same path, sampled at a scenario formula's
    cost)."""
    try:
        setups = unit_setups(scenario, on_motors=on_motors)
    except CochleaError as exc:
        raise refused(prepared.topic, str(exc)) from None
    for u, unit in zip(setups, scenario.units, strict=True):
        u.desired = sampler(u.name, list(unit.desired_joint))
    return setups


@dataclass
class FromTopic:
    """A run's desired path from a topic: the run's scenario (each unit's ``desired_joint``
    the message's path), summary.json's ``desired_source``, what was prepared."""

    scenario: object
    source: dict
    prepared: Desired

    def setups(self) -> list:
        """The run's setups (:func:`checked_setups`)."""
        return checked_setups(self.scenario, self.prepared)


def from_topic(args, scenario) -> FromTopic:
    """``cochlea-run --desired-topic``: the scenario checked, the message awaited, checked and
    made the run's path. Prints where it waits and what it got (stdout)."""
    if args.backend != "sim":
        raise CochleaError("--desired-topic goes with --backend sim: the first point is checked "
                           "against the measured initial state, which on the motors is read "
                           "only once the run starts")
    timeout = check_timeout(DEFAULT_TIMEOUT_S if args.desired_timeout is None
                            else args.desired_timeout)
    prepared = prepare(scenario, args.desired_topic, timeout)
    print(f"cochlea-run: waiting up to {timeout:g} s for a {MESSAGE_TYPE} on "
          f"{prepared.topic} (joints {', '.join(prepared.names)})", flush=True)
    msg = receive(prepared.topic, timeout)
    rate = scenario.rate_hz if args.rate is None else args.rate
    run_sc, source = take(prepared, scenario, args.duration, rate, msg)
    print(f"cochlea-run: desired path from {prepared.topic}: {source['points']} points to "
          f"t = {source['last_point_s']:g} s, {source['interpolation']}", flush=True)
    return FromTopic(run_sc, source, prepared)
