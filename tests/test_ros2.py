"""cochlea-ros2 and cochlea-run --ros2: a run on ROS 2 topics from a process of its own
(docs/logs.md, "Live on ROS 2").

A subscriber in this test (rclpy, a random ROS_DOMAIN_ID per test, discovery on this machine
only) receives what the bridge publishes during a real-time run and compares it with the run's
``log.csv``; a subscriber that never spins and a bridge killed mid-run leave the run's summary
as a run without the bridge; each class of bad input is one line with its exit code.

``/tf`` needs ``tf2_msgs``, which ``make test`` builds (``cochlea.ros2.tf2_msgs_build``: no
wheel on the package index); without it the /tf tests fail, in one line that says so.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from cochlea.apps import cochlea_ros2
from cochlea.export.ros2_msgs import schema_text
from cochlea.export.run_log import Group, UnitColumns, open_run
from cochlea.ros2 import node as ros_node
from cochlea.ros2 import tf2_msgs_build
from cochlea.ros2.source import Described, RawTail, describe_scenario, raw_units, robot_description

RATE_HZ = cochlea_ros2.DEFAULT_RATE_HZ  # what cochlea-run --ros2 asks for


@pytest.fixture
def domain(monkeypatch) -> int:
    """A ROS domain of this test's own, for it and the processes it starts."""
    value = random.randint(1, 101)
    monkeypatch.setenv("ROS_DOMAIN_ID", str(value))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    return value


def tf_message():
    """tf2_msgs/msg/TFMessage, or this test failed in one line (not skipped: make test builds
    it, so its absence is a failure of that build)."""
    if ros_node.TFMessage is None:
        pytest.fail("tf2_msgs is not installed, so /tf is not tested: make test builds it "
                    "(python -m cochlea.ros2.tf2_msgs_build says why it failed)", pytrace=False)
    return ros_node.TFMessage


class Listener:
    """A node of its own context, spinning in a thread, keeping what it receives (the receipt
    time with each /joint_states and /tf message)."""

    def __init__(self, domain: int, spin: bool = True, tf=None):
        self.context = rclpy.context.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node("cochlea_test_listener", context=self.context)
        self.states: list[tuple[float, JointState]] = []
        self.descriptions: list[str] = []
        live = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.node.create_subscription(
            JointState, "/joint_states", lambda m: self.states.append((time.monotonic(), m)),
            live)
        self.node.create_subscription(String, "/robot_description",
                                      lambda m: self.descriptions.append(m.data), latched)
        self.tf: list[tuple[float, object]] = []
        if tf is not None:
            self.node.create_subscription(
                tf, "/tf", lambda m: self.tf.append((time.monotonic(), m)), live)
        self.executor = None
        if spin:  # a stalled subscriber: subscribed, never reading
            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
            self.thread = threading.Thread(target=self.executor.spin, daemon=True)
            self.thread.start()

    def close(self) -> None:
        if self.executor is not None:
            self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


def cochlea_run(out: Path, *args: str, during=None, duration: float = 4
                ) -> subprocess.CompletedProcess:
    """A real-time run of the serial arms on the sim backend; ``during(process)`` is called
    while it runs."""
    process = subprocess.Popen(
        [sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial", "--space",
         "joint", "--duration", str(duration), "--watchdog-misses", "500", "--status", "off",
         "--out", str(out), *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=out.parent)
    if during is not None:
        during(process)
    stdout, stderr = process.communicate(timeout=300)
    assert process.returncode == 0, stderr
    return subprocess.CompletedProcess(process.args, 0, stdout, stderr)


def read_log(folder: Path) -> tuple[list[str], np.ndarray]:
    with open(folder / "log.csv") as f:
        header = f.readline().strip().split(",")
    return header, np.loadtxt(folder / "log.csv", delimiter=",", skiprows=1, ndmin=2)


def column(header: list[str], name: str, group: str) -> int:
    unit, joint = name.split("/")
    found = [i for i, c in enumerate(header) if c.startswith(f"{unit}.{group}.{joint}_")]
    assert len(found) == 1, (name, group, found)
    return found[0]


@pytest.mark.realtime
def test_a_run_on_ros2_is_its_log(tmp_path, domain):
    """/joint_states at the configured rate, every message a row of log.csv (names, position,
    velocity, effort to log.csv's 10 digits; stamps spaced as the rows' time_s);
    /robot_description a URDF of every /tf frame and /joint_states joint, to a subscriber
    that comes after it was published; /tf where tf2_msgs is installed, said otherwise."""
    listener = Listener(domain)
    late_descriptions = []

    def join_late(process):
        """A second subscriber, once the bridge has published (so after its description)."""
        end = time.monotonic() + 20
        while not listener.states and time.monotonic() < end:
            time.sleep(0.05)
        late = Listener(domain)
        try:
            while not late.descriptions and time.monotonic() < end:
                time.sleep(0.05)
            late_descriptions.extend(late.descriptions)
        finally:
            late.close()

    try:
        # communicate() returns once the bridge, which shares the run's stderr, has ended too.
        done = cochlea_run(tmp_path / "run", "--ros2", during=join_late, duration=6)
    finally:
        listener.close()
    folder = tmp_path / "run"
    header, rows = read_log(folder)
    states = listener.states
    # The bridge starts (imports, description; at nice 10) in 2 to 4 s of the 6 s run on a
    # loaded machine: at least a second of messages.
    assert len(states) > RATE_HZ, (f"{len(states)} /joint_states messages in a 6 s run: "
                                       f"{done.stderr}")
    # Rate: as received, over the messages of the run (the follower starts up to ~2 s late).
    received = np.array([t for t, _ in states])
    rate = (len(received) - 1) / (received[-1] - received[0])
    assert abs(rate - RATE_HZ) < 0.2 * RATE_HZ, f"received at {rate:.1f} Hz"
    # Values: each message is one row of log.csv; the first one found by value, the others by
    # their stamps' distance from it (the row's time_s).
    names = list(states[0][1].name)
    assert names == [f"arm{a}/joint{j}" for a in (1, 2) for j in (1, 2, 3)]
    cols = {g: [column(header, n, g) for n in names] for g in ("q", "qd", "tau")}

    def ns(m: JointState) -> int:
        return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec

    first = states[0][1]
    k0 = int(np.argmin(np.abs(rows[:, cols["q"]] - np.array(first.position)).sum(axis=1)))
    times = rows[:, 0]
    for _, m in states:
        t = times[k0] + (ns(m) - ns(first)) * 1e-9
        k = int(np.argmin(np.abs(times - t)))
        assert abs(times[k] - t) < 1e-6, f"a stamp at {t} s is no row's time_s"
        assert list(m.name) == names
        for group, values in (("q", m.position), ("qd", m.velocity), ("tau", m.effort)):
            np.testing.assert_allclose(values, rows[k, cols[group]], rtol=1e-9, atol=1e-12,
                                       err_msg=f"{group} at t = {times[k]} s")
    # The description: a URDF whose links are every frame the bridge poses on /tf, whose
    # joints include every /joint_states name; delivered to the late subscriber too.
    assert listener.descriptions and late_descriptions == listener.descriptions[:1]
    urdf = ET.fromstring(listener.descriptions[0])
    links = {e.get("name") for e in urdf.findall("link")}
    joints = {e.get("name") for e in urdf.findall("joint")}
    run = open_run(folder)
    for unit in run.units:
        frames = run.adapter.link_frames(run.system, unit.name)
        assert set(frames.names) <= links and set(frames.parents) <= links
    assert set(names) <= joints
    if ros_node.TFMessage is None:  # pragma: no cover - make test builds tf2_msgs
        assert "no /tf" in done.stderr
    else:
        assert "no /tf" not in done.stderr


def stamp_ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


@pytest.mark.realtime
def test_a_run_on_ros2_has_every_frame_on_tf(tmp_path, domain):
    """/tf during a run, at the configured rate: each message every frame of every unit
    (parent, child) at one row of log.csv, stamped as that row on /joint_states, its
    translations (m) and rotations those cochlea-mcap computes from the row; the publisher as a
    ROS installation sees it: tf2_msgs/msg/TFMessage with Jazzy's type hash."""
    listener = Listener(domain, tf=tf_message())
    endpoints = []

    def discover(process):
        """The bridge's /tf publisher as discovery shows it (DDS type name and type hash)."""
        end = time.monotonic() + 20
        while not listener.tf and time.monotonic() < end:
            time.sleep(0.05)
        endpoints.extend(listener.node.get_publishers_info_by_topic("/tf"))

    try:
        done = cochlea_run(tmp_path / "run", "--ros2", during=discover, duration=6)
    finally:
        listener.close()
    assert "no /tf" not in done.stderr
    assert [(e.topic_type, str(e.topic_type_hash)) for e in endpoints] == [
        ("tf2_msgs/msg/TFMessage", tf2_msgs_build.JAZZY_HASH)]
    messages = listener.tf
    assert len(messages) > RATE_HZ, f"{len(messages)} /tf messages in a 6 s run: {done.stderr}"
    received = np.array([t for t, _ in messages])
    rate = (len(received) - 1) / (received[-1] - received[0])
    assert abs(rate - RATE_HZ) < 0.2 * RATE_HZ, f"/tf received at {rate:.1f} Hz"
    # The row of each message: its stamp's distance from the first /joint_states message, whose
    # row is found by value (as in test_a_run_on_ros2_is_its_log).
    folder = tmp_path / "run"
    header, rows = read_log(folder)
    first = listener.states[0][1]
    q_cols = [column(header, n, "q") for n in first.name]
    k0 = int(np.argmin(np.abs(rows[:, q_cols] - np.array(first.position)).sum(axis=1)))
    times = rows[:, 0]
    picked = []
    for _, m in messages:
        stamps = {stamp_ns(t.header.stamp) for t in m.transforms}
        assert len(stamps) == 1, "one /tf message, one stamp"
        t = times[k0] + (stamps.pop() - stamp_ns(first.header.stamp)) * 1e-9
        k = int(np.argmin(np.abs(times - t)))
        assert abs(times[k] - t) < 1e-6, f"a /tf stamp at {t} s is no row's time_s"
        picked.append(k)
    run = open_run(folder)
    expected = Described(run.adapter, run.system, run.units).transforms(rows[picked])
    frames = {f for unit in run.units
              for f in run.adapter.link_frames(run.system, unit.name).names}
    for (_, m), want in zip(messages, expected):
        got = [(t.child_frame_id, t.header.frame_id) for t in m.transforms]
        assert got == [f[:2] for f in want] and frames <= {child for child, _ in got}
        values = [[t.transform.translation.x, t.transform.translation.y,
                   t.transform.translation.z, t.transform.rotation.x, t.transform.rotation.y,
                   t.transform.rotation.z, t.transform.rotation.w] for t in m.transforms]
        # The bridge reads log.bin's float64, log.csv has 10 digits.
        np.testing.assert_allclose(values, [list(f[2]) + list(f[3]) for f in want], atol=1e-8)


def test_tf2_msgs_is_tfmessage_on_the_wire():
    """The built TFMessage's CDR (rclpy through Fast DDS's type support) and cochlea-mcap's own
    encoding of the standard definition (mcap_ros2, no ROS) decode into each other, field for
    field."""
    from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic
    from rclpy.serialization import deserialize_message, serialize_message

    TFMessage = tf_message()
    TransformStamped = ros_node.TransformStamped
    text = schema_text("tf2_msgs/TFMessage")
    encode = serialize_dynamic("tf2_msgs/msg/TFMessage", text)["tf2_msgs/msg/TFMessage"]
    decode = generate_dynamic("tf2_msgs/msg/TFMessage", text)["tf2_msgs/msg/TFMessage"]
    fields = []
    message = TFMessage()
    for i, (parent, child) in enumerate([("world", "arm1/base"), ("arm1/base", "arm1/link1"),
                                         ("arm1/link1", "arm1/tool")]):
        p, q = (0.1 * i, -2.5, 1e-3 * i), (0.5, -0.5 * i, 0.25, 0.75)
        t = TransformStamped()
        t.header.stamp.sec, t.header.stamp.nanosec = 1_700_000_000 + i, 123_456_789 - i
        t.header.frame_id, t.child_frame_id = parent, child
        (t.transform.translation.x, t.transform.translation.y,
         t.transform.translation.z) = p
        (t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
         t.transform.rotation.w) = q
        message.transforms.append(t)
        fields.append({"header": {"stamp": {"sec": 1_700_000_000 + i,
                                            "nanosec": 123_456_789 - i}, "frame_id": parent},
                       "child_frame_id": child,
                       "transform": {"translation": dict(zip("xyz", p)),
                                     "rotation": dict(zip("xyzw", q))}})
    assert deserialize_message(encode({"transforms": fields}), TFMessage) == message
    decoded = decode(serialize_message(message))
    assert [(t.header.stamp.sec, t.header.stamp.nanosec, t.header.frame_id, t.child_frame_id,
             t.transform.translation.x, t.transform.translation.y, t.transform.translation.z,
             t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
             t.transform.rotation.w) for t in decoded.transforms] == [
        (f["header"]["stamp"]["sec"], f["header"]["stamp"]["nanosec"], f["header"]["frame_id"],
         f["child_frame_id"], *f["transform"]["translation"].values(),
         *f["transform"]["rotation"].values()) for f in fields]


@pytest.mark.realtime
def test_frames_of_log_bin_are_those_of_log_csv(tmp_path, domain):
    """The follower's columns of log.bin (log.columns.json's names) give every frame as
    cochlea-mcap computes it from log.csv, row for row."""
    cochlea_run(tmp_path / "run")
    folder = tmp_path / "run"
    run = open_run(folder)
    tail = RawTail(folder)
    raw = Described(run.adapter, run.system, raw_units(run.adapter, run.system, tail.names,
                                                       tail.bin))
    csv = Described(run.adapter, run.system, run.units)
    picked = range(0, 4000, 397)
    rows_csv = next(run.chunks())[list(picked)]
    rows_raw = np.vstack([tail.row(k) for k in picked])
    np.testing.assert_allclose(rows_raw[:, 0], rows_csv[:, 0], atol=1e-12)
    for a, b in zip(raw.transforms(rows_raw), csv.transforms(rows_csv)):
        assert [f[:2] for f in a] == [f[:2] for f in b] and a
        np.testing.assert_allclose([f[2] + f[3] for f in a], [f[2] + f[3] for f in b],
                                   atol=1e-8)
    assert raw.joint_names() == csv.joint_names()


def verdict(folder: Path) -> dict:
    """summary.json without what depends on the wall clock (timing, wall time)."""
    summary = json.loads((folder / "summary.json").read_text())
    for key in ("timing", "wall_time_s"):
        summary.pop(key)
    return summary


def follower_pids(folder: Path) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                cmd = (entry / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"cochlea.apps.cochlea_ros2" in cmd and str(folder).encode() in cmd:
                found.append(int(entry.name))
    return found


@pytest.mark.realtime
def test_a_stalled_subscriber_or_a_dead_bridge_changes_nothing(tmp_path, domain):
    """A subscriber that never spins, and the bridge killed mid-run: the run's summary (every
    verdict, stop, error, estimate) is that of a run without the bridge."""
    without = tmp_path / "without"
    cochlea_run(without)
    stalled = Listener(domain, spin=False)
    killed = []

    def kill_the_bridge(process):
        end = time.monotonic() + 20
        while time.monotonic() < end and not killed:
            for pid in follower_pids(tmp_path / "with"):
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
            time.sleep(0.2)

    try:
        cochlea_run(tmp_path / "with", "--ros2", during=kill_the_bridge)
    finally:
        stalled.close()
    assert killed, "the bridge was never seen running"
    assert verdict(tmp_path / "with") == verdict(without)


@pytest.mark.parametrize("scenario", ["serial_task", "parallel_joint"])
def test_robot_description_is_a_tree_of_the_tf_frames(scenario):
    """The URDF: a tree rooted at world (each other link the child of exactly one joint, every
    parent a link), whose links are every frame of every unit; a serial arm's joints named as
    on /joint_states, with cochlea-urdf export's axes and limits."""
    adapter, system = describe_scenario(scenario)
    units = []
    for name in adapter.layout(system, "joint").units:
        joints = [j.name for j in adapter.model(system, name).joints]
        units.append(UnitColumns(name, {"q": Group("q", list(range(len(joints))),
                                                   [f"{j}_rad" for j in joints])}))
    described = Described(adapter, system, units)
    urdf = ET.fromstring(robot_description(described))
    links = [e.get("name") for e in urdf.findall("link")]
    assert len(set(links)) == len(links)
    children = [j.find("child").get("link") for j in urdf.findall("joint")]
    assert sorted(children) == sorted(set(links) - {"world"})
    assert {j.find("parent").get("link") for j in urdf.findall("joint")} <= set(links)
    frames = {f for unit in units for f in adapter.link_frames(system, unit.name).names}
    assert set(links) == frames | {"world"}
    if adapter.name == "serial":
        moving = {j.get("name"): j for j in urdf.findall("joint") if j.get("type") == "revolute"}
        assert set(described.joint_names()) == set(moving)
        assert all(j.find("limit") is not None and j.find("axis") is not None
                   for j in moving.values())


# ---- bad input: one line, its exit code ---------------------------------------------------

def refused(capsys, code: int, *argv: str) -> str:
    assert cochlea_ros2.main(list(argv)) == code
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cochlea-ros2: "), err
    assert "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize("command", ["follow", "replay"])
def test_not_a_run_folder(capsys, tmp_path, command):
    assert "missing" in refused(capsys, 2, command, str(tmp_path / "nothing"))
    (tmp_path / "file").write_text("x")
    assert "not a folder" in refused(capsys, 2, command, str(tmp_path / "file"))


def test_a_folder_that_never_becomes_a_run(capsys, tmp_path):
    assert "no log.columns.json" in refused(capsys, 3, "follow", str(tmp_path), "--wait",
                                             "0.2")
    assert "not a finished run" in refused(capsys, 2, "replay", str(tmp_path))


@pytest.mark.parametrize("columns, message", [
    ("{not json", "not a real-time run's column list"),
    ('{"dtype": "float32", "row_length": 1, "columns": ["time_s"]}',
     "not a real-time run's column list"),
    ('{"dtype": "float64", "row_length": 2, "columns": ["time_s", "q.arm1.joint1_rad"]}',
     "not this robot's log"),
])
def test_a_damaged_or_foreign_log(capsys, tmp_path, columns, message):
    """log.columns.json that is not JSON, not float64 rows, or not the named robot's."""
    (tmp_path / "log.columns.json").write_text(columns)
    assert message in refused(capsys, 2, "follow", str(tmp_path), "--scenario", "serial_joint")


def serial_joint_columns() -> list[str]:
    """log.columns.json's names of a serial_joint run on the sim backend (the one schema)."""
    from cochlea.log_schema import LogUnit, raw_columns
    from cochlea.sim import load_scenario, unit_setups

    setups = unit_setups(load_scenario("serial_joint"))
    return raw_columns([LogUnit.of_setup(u, u.controller.space) for u in setups],
                       current=False, true_state=True)


def write_columns(folder: Path, names: list[str]) -> None:
    (folder / "log.columns.json").write_text(json.dumps(
        {"schema_version": 2, "dtype": "float64", "row_length": len(names), "columns": names}))


@pytest.mark.parametrize("damage, message", [
    ("columns_ints", "not a real-time run's column list"),
    ("columns_deep", "nested too deep"),
    ("columns_fifo", "not a regular file"),
    ("bin_folder", "not a regular file"),
    ("time_nan", "time_s = nan"),
    ("time_inf", "time_s = inf"),
    ("time_backwards", "not after the row before"),
    ("time_garbage", "is damaged"),
    ("finished_without_bin", "finished run without log.bin"),
    ("finished_empty_bin", "finished run without log.bin"),
])
def test_a_damaged_raw_log_is_one_line(capsys, tmp_path, damage, message):
    """follow on damaged log.columns.json or log.bin: columns as ints (AttributeError), JSON
    nested 200 000 deep (RecursionError), a FIFO (a hang), log.bin a folder
    (IsADirectoryError), a NaN, infinite, backwards or garbage time (ValueError,
    OverflowError, SystemError in the publisher), and a finished run without rows (exit 0,
    'published 0 rows of 0'): each one line, exit 2, before or without publishing."""
    names = serial_joint_columns()
    write_columns(tmp_path, names)
    rows = np.zeros((5, len(names)))
    rows[:, 0] = np.arange(5) * 1e-3
    if damage == "columns_ints":
        (tmp_path / "log.columns.json").write_text(
            '{"dtype": "float64", "row_length": 2, "columns": [1, 2]}')
    elif damage == "columns_deep":
        (tmp_path / "log.columns.json").write_text("[" * 200000 + "]" * 200000)
    elif damage == "columns_fifo":
        (tmp_path / "log.columns.json").unlink()
        os.mkfifo(tmp_path / "log.columns.json")
    elif damage == "bin_folder":
        (tmp_path / "log.bin").mkdir()
    elif damage.startswith("time_"):
        rows[3, 0] = {"time_nan": np.nan, "time_inf": np.inf, "time_backwards": 0.0,
                      "time_garbage": -6.28e161}[damage]
    elif damage.startswith("finished_"):
        (tmp_path / "summary.json").write_text("{}")
        if damage == "finished_empty_bin":
            (tmp_path / "log.bin").write_bytes(b"")
    if damage.startswith("time_"):
        rows.tofile(tmp_path / "log.bin")
    assert message in refused(capsys, 2, "follow", str(tmp_path), "--scenario",
                              "serial_joint", "--idle", "5")


def test_raw_columns_are_taken_by_joint_name_and_unit(tmp_path):
    """log.bin's q columns in another order map to the model's joints by name (they were
    taken by position); a joint in degrees or a name no joint has is refused."""
    from cochlea.export.run_log import RunFolderError

    adapter, system = describe_scenario("serial_joint")
    names = serial_joint_columns()
    a, b = names.index("arm1.q.joint1_rad"), names.index("arm1.q.joint2_rad")
    swapped = list(names)
    swapped[a], swapped[b] = swapped[b], swapped[a]
    units = raw_units(adapter, system, swapped, tmp_path / "log.bin")
    assert units[0].groups["q"].columns[:2] == [b, a]
    assert units[0].joints() == ["joint1", "joint2", "joint3"]
    for wrong in ("arm1.q.joint1_deg", "arm1.q.elbow_rad"):
        bad = [wrong if n == "arm1.q.joint1_rad" else n for n in names]
        with pytest.raises(RunFolderError, match="not this run.s log"):
            raw_units(adapter, system, bad, tmp_path / "log.bin")


def test_an_unknown_scenario(capsys, tmp_path):
    (tmp_path / "log.columns.json").write_text(
        '{"dtype": "float64", "row_length": 1, "columns": ["time_s"]}')
    assert "--scenario" in refused(capsys, 2, "follow", str(tmp_path), "--scenario",
                                   str(tmp_path / "none.toml"))


@pytest.mark.parametrize("command", ["follow", "replay"])
@pytest.mark.parametrize("rate", ["0", "-5", "nan", "inf", "fast", "1e9"])
def test_bad_rate(capsys, tmp_path, command, rate):
    assert "--rate" in refused(capsys, 2, command, str(tmp_path), "--rate", rate)


@pytest.mark.parametrize("option", ["--wait", "--idle"])
def test_bad_wait(capsys, tmp_path, option):
    assert option in refused(capsys, 2, "follow", str(tmp_path), option, "-1")


@pytest.mark.slow
def test_ros2_is_for_real_time_runs(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial", "--space",
         "joint", "--realtime", "off", "--ros2", "--out", str(tmp_path / "run")],
        capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert done.stderr.strip().count("\n") == 0 and "cochlea-ros2 replay" in done.stderr
    assert not (tmp_path / "run").exists()
