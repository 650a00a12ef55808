"""cochlea-run --desired-topic: the desired joint path from one ROS 2 JointTrajectory, checked
before the run and refused in one line otherwise (docs/logs.md, "A desired trajectory from
ROS 2").

The checks run on real ``trajectory_msgs`` messages without a ROS graph (one test per class of
bad input, each naming the point or the time and the rule); a publisher in this test (its own
ROS_DOMAIN_ID, discovery on this machine only) then sends a good trajectory that a run follows,
a trajectory with a NaN that a run refuses, and nothing, which a run waits for and gives up on.
"""

from __future__ import annotations

import json
import math
import random
import sys
import threading
from pathlib import Path
from types import SimpleNamespace

import casadi as ca
import numpy as np
import pytest
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from cochlea.apps import cochlea_run
from cochlea.robots.adapter import desired_function
from cochlea.ros2 import desired as D
from cochlea.sim import load_scenario

TOPIC = "/cochlea/desired"
SIGNS = np.array([1, 1, 1, -1, -1, -1])


@pytest.fixture(scope="module")
def serial():
    sc = load_scenario("serial_joint")
    prepared = D.prepare(sc, TOPIC, 5.0)
    x0 = np.concatenate([u.x0[:3] for u in prepared.setups])
    return sc, prepared, x0


def message(names, times, positions, velocities=None, accelerations=None, effort=None,
            stamp=(12, 345)) -> JointTrajectory:
    msg = JointTrajectory()
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
    msg.joint_names = list(names)
    for k, t in enumerate(times):
        p = JointTrajectoryPoint()
        p.positions = [float(v) for v in positions[k]]
        if velocities is not None:
            p.velocities = [float(v) for v in velocities[k]]
        if accelerations is not None:
            p.accelerations = [float(v) for v in accelerations[k]]
        if effort is not None:
            p.effort = [float(v) for v in effort[k]]
        p.time_from_start.sec = math.floor(t)
        p.time_from_start.nanosec = int(round((t - math.floor(t)) * 1e9))
        msg.points.append(p)
    return msg


def wave(x0, times, amplitude=0.05):
    """A smooth path from x0 and back (rad): positions, velocities, accelerations."""
    t = np.asarray(times)[:, None]
    w = math.pi
    return (x0 + amplitude * SIGNS * np.sin(w * t), amplitude * SIGNS * w * np.cos(w * t),
            -amplitude * SIGNS * w * w * np.sin(w * t))


def good(x0, times=None):
    times = np.arange(21) * 0.1 if times is None else times
    return times, *wave(x0, times)


# ---- the path -------------------------------------------------------------------------------


def _evaluate(path, times):
    t = ca.SX.sym("t")
    f = desired_function("j", path.expression(t), t)
    return [np.array(v, float).ravel() for v in f.map(len(times))(np.asarray(times)[None, :])]


def test_quintic_meets_every_point_and_is_c2_and_holds_the_last(serial):
    _, prepared, x0 = serial
    times, P, V, A = good(x0, np.array([0.0, 0.13, 0.5, 0.61, 1.0]))
    tr = D.from_message(message(prepared.names, times, P, V, A), TOPIC)
    paths = D.splines(tr, D.check_numbers(tr, prepared.names), np.concatenate([x0, 0 * x0]))
    for i, path in enumerate(paths):
        q, qd, qdd = _evaluate(path, times[:-1])
        assert np.allclose(q, P[:-1, i], atol=1e-12) and np.allclose(qd, V[:-1, i], atol=1e-10)
        assert np.allclose(qdd, A[:-1, i], atol=1e-8)
        # Continuous acceleration across each inner point (from both sides).
        e = 1e-7
        left, right = (_evaluate(path, times[1:-1] + s)[2] for s in (-e, e))
        assert np.allclose(left, right, atol=1e-4)
        # Held at the last point after it.
        q, qd, qdd = _evaluate(path, [1.0, 1.5, 10.0])
        assert np.allclose(q, P[-1, i]) and not qd.any() and not qdd.any()


def test_the_loops_sampler_is_the_paths_exact_derivatives(serial):
    """The run samples each unit through :func:`D.sampler` (derivatives written out); the
    scenario's checks see the expression differentiated by CasADi: the same numbers."""
    _, prepared, x0 = serial
    times, P, V, A = good(x0, np.array([0.0, 0.13, 0.5, 0.61, 1.0]))
    tr = D.from_message(message(prepared.names, times, P, V, A), TOPIC)
    paths = D.splines(tr, D.check_numbers(tr, prepared.names), np.concatenate([x0, 0 * x0]))
    fast = D.sampler("arm2", paths[3:])
    t = ca.SX.sym("t")
    exact = desired_function("arm2", ca.vertcat(*[p.expression(t) for p in paths[3:]]), t)
    grid = np.concatenate([np.linspace(0, 1.2, 1201), np.random.default_rng(1).uniform(0, 1, 50)])
    for a, b in zip(fast.map(len(grid))(grid[None, :]), exact.map(len(grid))(grid[None, :])):
        assert np.allclose(np.array(a), np.array(b), rtol=1e-12, atol=1e-9)


def test_positions_only_is_a_c2_spline_at_rest_and_a_late_first_point_starts_at_x0(serial):
    _, prepared, x0 = serial
    times = np.array([0.2, 0.5, 0.9, 1.4])
    P = wave(x0, times)[0]
    tr = D.from_message(message(prepared.names, times, P), TOPIC)
    assert "cubic spline" in tr.interpolation()
    paths = D.splines(tr, D.check_numbers(tr, prepared.names), np.concatenate([x0, 0 * x0]))
    for i, path in enumerate(paths):
        q, qd, _ = _evaluate(path, [0.0, *times])
        assert q[0] == pytest.approx(x0[i]) and qd[0] == pytest.approx(0, abs=1e-12)
        assert np.allclose(q[1:], P[:, i], atol=1e-12)
        assert qd[-1] == pytest.approx(0, abs=1e-12)
        e = 1e-7
        left, right = (_evaluate(path, times[:-1] + s)[2] for s in (-e, e))
        assert np.allclose(left, right, atol=1e-4)


@pytest.mark.slow
def test_a_good_trajectory_is_the_run_path_and_its_record(serial):
    sc, prepared, x0 = serial
    times, P, V, A = good(x0)
    run_sc, source = D.take(prepared, sc, None, 1000.0, message(prepared.names, times, P, V, A))
    assert run_sc.duration == pytest.approx(2.0)
    assert source["topic"] == TOPIC and source["points"] == 21
    assert source["stamp"] == {"sec": 12, "nanosec": 345} and "quintic" in source["interpolation"]
    setups = D.checked_setups(run_sc, prepared)
    for u, sl in zip(setups, (slice(0, 3), slice(3, 6))):
        q = np.array(u.desired.map(len(times))(times[None, :])[0]).T
        assert np.allclose(q[:-1], P[:-1, sl], atol=1e-12)


# ---- refusals: one class of bad input each --------------------------------------------------


def _refused(serial, msg, expected, duration=None):
    sc, prepared, _ = serial
    with pytest.raises(D.TopicError) as info:
        D.take(prepared, sc, duration, 1000.0, msg)
    text = str(info.value)
    assert info.value.code == D.EXIT_REFUSED and "\n" not in text
    assert text.startswith(f"--desired-topic {TOPIC}: trajectory refused, nothing moved: ")
    for part in expected:
        assert part in text, text
    return text


def _case(name, x0, names):
    times, P, V, A = good(x0)
    P, V, A = P.copy(), V.copy(), A.copy()
    if name == "unknown name":
        return message([*names[:5], "arm2/elbow"], times, P), ["names: 'arm2/elbow' is not"]
    if name == "missing joints":
        return message(names[:3], times, P[:, :3]), ["names: the message lacks arm2/joint1"]
    if name == "a name twice":
        return message([*names[:5], names[0]], times, P), ["'arm1/joint1' is named twice"]
    if name == "sizes":
        msg = message(names, times, P)
        msg.points[2].positions = list(P[2, :5])
        return msg, ["point 2: sizes: 5 positions for 6 joint names"]
    if name == "velocities at some points only":
        msg = message(names, times, P, V)
        msg.points[4].velocities = []
        return msg, ["point 4: sizes: 0 velocities", "at every point or at none"]
    if name == "efforts":
        return message(names, times, P, effort=0 * P), ["effort: the message gives efforts"]
    if name == "accelerations without velocities":
        return message(names, times, P, accelerations=A), ["accelerations without velocities"]
    if name == "no point":
        return message(names, [], []), ["points: the message has no point"]
    if name == "NaN position":
        P[3, 1] = math.nan
        return message(names, times, P, V, A), ["point 3 (t = 0.3 s): finite: positions of "
                                               "arm1/joint2 is nan"]
    if name == "infinite acceleration":
        A[5, 4] = math.inf
        return message(names, times, P, V, A), ["point 5 (t = 0.5 s): finite: accelerations "
                                               "of arm2/joint2 is inf"]
    if name == "negative time":
        msg = message(names, times, P)
        msg.points[0].time_from_start.sec = -1
        return msg, ["point 0: sorted times: time_from_start -1 s is negative"]
    if name == "unsorted times":
        msg = message(names, times, P)
        msg.points[7].time_from_start = msg.points[6].time_from_start
        return msg, ["point 7: sorted times: time_from_start 0.6 s is not after point 6's"]
    if name == "start":
        P[:, 0] += math.radians(5)
        return message(names, times, P), ["point 0 (t = 0 s): start: arm1/joint1",
                                          "from the measured initial state", "at most 2 deg"]
    raise AssertionError(name)


MESSAGE_CASES = ["unknown name", "missing joints", "a name twice", "sizes",
                 "velocities at some points only", "efforts",
                 "accelerations without velocities", "no point", "NaN position",
                 "infinite acceleration", "negative time", "unsorted times", "start"]


@pytest.mark.parametrize("case", MESSAGE_CASES)
def test_a_bad_message_is_refused_naming_the_point_and_the_rule(serial, case):
    _, prepared, x0 = serial
    msg, expected = _case(case, x0, prepared.names)
    _refused(serial, msg, expected)


def _near_centre(setup, x0):
    """A pose of arm 1 with its tool 0.5 mm from the cochlea centre (inside the keep-out)."""
    from scipy.optimize import minimize
    fk = setup.fk_world
    best = minimize(lambda q: float(np.sum(np.array(fk(q)).ravel()[:2] ** 2)), x0)
    assert math.hypot(*np.array(fk(best.x)).ravel()[:2]) < 5e-4
    return best.x


def test_a_point_beyond_a_supervisor_rule_is_refused(serial):
    _, prepared, x0 = serial
    names = prepared.names
    times = np.array([0.0, 1.0, 2.0, 3.0])
    # Position limit (170 deg) at point 2.
    P = np.tile(x0, (4, 1))
    P[2, 2] = math.radians(175)
    _refused(serial, message(names, times, P),
             ["point 2 (t = 2 s): position-limit: arm1.joint3 = 175.00 deg outside"])
    # Velocity limit (6 rad/s) at point 1.
    V = np.zeros((4, 6))
    V[1, 4] = 7.0
    _refused(serial, message(names, times, np.tile(x0, (4, 1)), V),
             ["point 1 (t = 1 s): velocity-limit: arm2.joint2 speed = 7 rad/s, limit 6"])
    # The keep-out circle at point 3 (a joint path: the circle is checked all the same).
    P = np.tile(x0, (4, 1))
    P[3, :3] = _near_centre(prepared.setups[0], x0[:3])
    _refused(serial, message(names, times, P),
             ["point 3 (t = 3 s): keep-out: arm1 tool", "inside the keep-out radius 20.0 mm"])


@pytest.mark.slow
def test_the_interpolated_path_is_checked_between_the_points(serial):
    _, prepared, x0 = serial
    names = prepared.names
    # Every point inside the limits; the C2 spline through them overshoots 170 deg.
    times = np.array([0.0, 2.0, 2.5, 4.5])
    P = np.tile(x0, (4, 1))
    P[1:3, 2] = math.radians(169.5)
    _refused(serial, message(names, times, P),
             ["between points 1 and 2, at t = ", "position-limit: arm1.joint3 = 170"])
    # Every point at rest; between two of them the path is faster than 6 rad/s.
    P = np.tile(x0, (3, 1))
    P[1, 3] += 0.5
    _refused(serial, message(names, [0.0, 0.1, 1.0], P),
             ["between points 0 and 1, at t = ", "velocity-limit: arm2.joint1 speed"])
    # An acceleration the drive cannot give (2.5 N m on joint 1, 1.8e-3 kg m^2).
    times, P, V, A = good(x0, np.array([0.0, 0.001, 0.5]))
    A[1, 0] = 5000.0
    _refused(serial, message(names, times, P, V, A),
             ["at t = 0.001 s: effort: arm1/joint1 needs", "more than the 2.5 N m"])


@pytest.mark.slow
def test_the_scenario_checks_of_a_desired_path_run_on_it():
    """What only the simulation layer checks (here the mechanism's workspace) refuses the
    topic's path as it refuses a scenario's, in one line with exit 9."""
    sc = load_scenario("parallel_joint")
    prepared = D.prepare(sc, TOPIC, 5.0)
    assert prepared.names[2] == "mechanism/slider.d1"
    x0 = prepared.setups[0].x0[:5]
    P = np.tile(x0, (3, 1))
    P[1, 3] += 0.8  # right.th1, inside its limits; the right side's end out of reach
    run_sc, _ = D.take(prepared, sc, None, 1000.0, message(prepared.names, [0.0, 3.0, 6.0], P))
    with pytest.raises(D.TopicError) as info:
        D.checked_setups(run_sc, prepared)
    text = str(info.value)
    assert info.value.code == D.EXIT_REFUSED and "\n" not in text
    assert "trajectory refused, nothing moved: " in text
    assert "the desired configuration leaves the workspace at t = " in text


def test_a_last_point_that_moves_is_not_held_and_a_run_needs_a_period(serial):
    _, prepared, x0 = serial
    times, P, V, A = good(x0, np.arange(16) * 0.1)  # ends moving (t = 1.5 s)
    msg = message(prepared.names, times, P, V, A)
    _refused(serial, msg, ["point 15 (t = 1.5 s): held: its velocities are not zero"],
             duration=3.0)
    _refused(serial, message(prepared.names, [0.0], [x0]),
             ["point 0 (t = 0 s): duration: the last point's time_from_start must be "
              "positive"])


def test_without_ros_the_wait_is_exit_4(monkeypatch):
    monkeypatch.setitem(sys.modules, "trajectory_msgs.msg", None)
    with pytest.raises(D.TopicError) as info:
        D.receive(TOPIC, 1.0)
    assert info.value.code == D.EXIT_NO_ROS and "pip install 'cochlea[ros]'" in str(info.value)


@pytest.mark.parametrize("options, expected", [
    (["--desired-timeout", "nan"], "--desired-timeout: 'nan': expected a plain decimal number"),
    (["--desired-timeout", "0"], "--desired-timeout 0.0: seconds to wait"),
    (["--backend", "dynamixel", "--port", "/dev/null"], "--desired-topic goes with --backend sim"),
])
def test_bad_options_are_exit_2(capsys, tmp_path, options, expected):
    try:
        code = cochlea_run.main(["--robot", "serial", "--space", "joint", "--desired-topic",
                                 TOPIC, "--out", str(tmp_path / "run"), *options])
    except SystemExit as stop:  # the parser's own refusal (a number that is no number)
        code = stop.code
    err = capsys.readouterr().err.strip()
    assert code == 2 and expected in err and "\n" not in err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("args, expected", [
    (["--space", "task", "--desired-topic", TOPIC], "goes with --space joint"),
    (["--space", "joint", "--desired-topic", "not a topic"], "a ROS 2 topic name"),
    (["--space", "joint", "--desired-timeout", "5"], "--desired-timeout goes with --desired-topic"),
])
def test_a_task_space_run_or_a_bad_topic_name_is_exit_2(capsys, tmp_path, args, expected):
    code = cochlea_run.main(["--robot", "serial", *args, "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and expected in err and "\n" not in err


# ---- through ROS 2 --------------------------------------------------------------------------


@pytest.fixture
def domain(monkeypatch) -> int:
    value = random.randint(1, 101)
    monkeypatch.setenv("ROS_DOMAIN_ID", str(value))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    return value


class Talker:
    """A node of its own context publishing one message every 0.1 s (reliable, depth 1), as a
    researcher's script would, until closed."""

    def __init__(self, domain: int, msg: JointTrajectory):
        self.context = rclpy.context.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node("cochlea_test_talker", context=self.context)
        self.pub = self.node.create_publisher(
            JointTrajectory, TOPIC, QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, args=(msg,), daemon=True)
        self.thread.start()

    def _run(self, msg):
        while not self.stop.wait(0.1):
            self.pub.publish(msg)

    def close(self):
        self.stop.set()
        self.thread.join()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


def _run(tmp_path, *options):
    return cochlea_run.main(["--robot", "serial", "--space", "joint", "--desired-topic", TOPIC,
                             "--desired-timeout", "20", "--out", str(tmp_path / "run"),
                             *options])


@pytest.mark.slow
def test_a_run_follows_a_published_trajectory(capsys, tmp_path, domain, serial):
    _, prepared, x0 = serial
    times, P, V, A = good(x0)
    talker = Talker(domain, message(prepared.names, times, P, V, A, stamp=(7, 8)))
    try:
        code = _run(tmp_path, "--realtime", "off")
    finally:
        talker.close()
    out = capsys.readouterr().out
    assert code == 0, out
    assert f"desired path from {TOPIC}: 21 points to t = 2 s, quintic" in out
    run = tmp_path / "run"
    summary = json.loads((run / "summary.json").read_text())
    assert summary["desired_source"]["topic"] == TOPIC
    assert summary["desired_source"]["stamp"] == {"sec": 7, "nanosec": 8}
    assert summary["desired_source"]["points"] == 21
    assert summary["duration_s"] == pytest.approx(2.0) and summary["supervisor"]["rule"] == "none"
    log = np.genfromtxt(run / "log.csv", delimiter=",", names=True)
    rows = np.rint(times[:-1] * 1000).astype(int)  # the points' periods
    for a, unit in enumerate(("arm1", "arm2")):
        for j in range(3):
            desired = log[f"{unit}desiredjoint{j + 1}_rad"]
            assert np.allclose(desired[rows], P[:-1, 3 * a + j], atol=1e-9)
            # Tracked: the plant's true error stays small along the whole path.
            assert np.abs(log[f"{unit}true_errorjoint{j + 1}_rad"]).max() < math.radians(1)


@pytest.mark.slow
def test_a_published_trajectory_with_a_nan_is_refused_and_nothing_is_written(capsys, tmp_path,
                                                                              domain, serial):
    _, prepared, x0 = serial
    times, P, V, A = good(x0)
    P[3, 1] = math.nan
    talker = Talker(domain, message(prepared.names, times, P, V, A))
    try:
        code = _run(tmp_path, "--realtime", "off")
    finally:
        talker.close()
    err = capsys.readouterr().err.strip()
    assert code == D.EXIT_REFUSED and "\n" not in err
    assert err.endswith("point 3 (t = 0.3 s): finite: positions of arm1/joint2 is nan")
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_no_message_in_time_is_exit_8(capsys, tmp_path, domain):
    code = cochlea_run.main(["--robot", "serial", "--space", "joint", "--desired-topic", TOPIC,
                             "--desired-timeout", "1", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err.strip()
    assert code == D.EXIT_NO_TRAJECTORY and "\n" not in err
    assert err == (f"cochlea-run: --desired-topic {TOPIC}: no {D.MESSAGE_TYPE} within 1 s "
                   "(--desired-timeout); nothing moved")
    assert not (tmp_path / "run").exists()


@pytest.mark.realtime
def test_a_short_real_time_run_follows_it(capsys, tmp_path, domain, serial):
    _, prepared, x0 = serial
    times, P, V, A = good(x0)
    talker = Talker(domain, message(prepared.names, times, P, V, A))
    try:
        code = _run(tmp_path, "--duration", "1", "--status", "off")
    finally:
        talker.close()
    assert code == 0, capsys.readouterr().err
    summary = json.loads((Path(tmp_path) / "run" / "summary.json").read_text())
    assert summary["stop"]["rule"] == "completed" and summary["desired_source"]["points"] == 21


def test_the_plain_numbers_are_checked_without_ros():
    """The checks read a message's fields only: a plain object with them is checked alike."""
    point = SimpleNamespace(positions=[0.0], velocities=[], accelerations=[], effort=[],
                            time_from_start=SimpleNamespace(sec=0, nanosec=0))
    msg = SimpleNamespace(joint_names=["a/b"], points=[point],
                          header=SimpleNamespace(stamp=SimpleNamespace(sec=1, nanosec=2)))
    tr = D.from_message(msg, TOPIC)
    with pytest.raises(D.TopicError, match="names: 'a/b' is not a joint of this run"):
        D.check_numbers(tr, ["arm1/joint1"])
