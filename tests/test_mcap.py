"""cochlea-mcap: a run folder's log as MCAP of standard ROS 2 messages (docs/logs.md).

Each exported file is read back with the ``mcap`` reader and the ROS 2 (CDR) decoder of
``mcap-ros2-support``, message by message, and compared with the run's ``log.csv`` (every
sample, to 1e-12), its ``summary.json`` and the robot's forward kinematics; each class of bad
input is one line, exit code 2, and nothing under the output's name.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from cochlea.apps.cochlea_mcap import main
from cochlea.errors import EXIT_USER_ERROR
from cochlea.export.ros2_msgs import DEFINITIONS, dependencies, schema_text
from cochlea.export.to_mcap import quaternions
from cochlea.robots import robot

ROOT = Path(__file__).resolve().parent.parent
TOL = 1e-12


def cochlea_run(out: Path, *args: str) -> Path:
    done = subprocess.run(
        [sys.executable, "-m", "cochlea.apps.cochlea_run", *args, "--out", str(out),
         "--status", "off"], capture_output=True, text=True, timeout=300, cwd=out.parent)
    assert done.returncode == 0, done.stderr
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """Short runs of each kind a folder comes from: a real-time run on the sim backend (log.bin,
    timing columns, true state, task space), and as-fast runs (supervisor verdict, no timing)
    of the parallel mechanism in joint space and the serial arms in joint space."""
    base = tmp_path_factory.mktemp("runs")
    return {
        "serial_task_rt": cochlea_run(base / "serial_task_rt", "--robot", "serial", "--space",
                                      "task", "--duration", "0.3", "--watchdog-misses", "500"),
        "parallel_joint_fast": cochlea_run(base / "parallel_joint_fast", "--robot", "parallel",
                                           "--space", "joint", "--duration", "0.3",
                                           "--realtime", "off"),
        "serial_joint_fast": cochlea_run(base / "serial_joint_fast", "--robot", "serial",
                                         "--space", "joint", "--duration", "0.25",
                                         "--realtime", "off"),
    }


def read_mcap(path: Path) -> dict[str, list]:
    """topic -> [(log_time ns, publish_time ns, schema name, decoded message)] in file order,
    with the file's profile and the channels' encodings checked."""
    topics = defaultdict(list)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        assert header.profile == "ros2"
        for schema, channel, message, decoded in reader.iter_decoded_messages(
                log_time_order=False):
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            topics[channel.topic].append((message.log_time, message.publish_time, schema.name,
                                          decoded))
    return topics


def read_log(folder: Path) -> tuple[list[str], np.ndarray]:
    with open(folder / "log.csv") as f:
        header = f.readline().strip().split(",")
    return header, np.loadtxt(folder / "log.csv", delimiter=",", skiprows=1, ndmin=2)


def columns(header: list[str], prefix: str) -> list[int]:
    return [i for i, h in enumerate(header) if h.startswith(prefix)]


def export(folder: Path, tmp_path: Path, name: str = "out.mcap") -> dict[str, list]:
    out = tmp_path / name
    assert main([str(folder), "--out", str(out)]) == 0
    return read_mcap(out)


@pytest.fixture(scope="module")
def exported(runs, tmp_path_factory) -> dict[str, dict[str, list]]:
    out = tmp_path_factory.mktemp("mcap")
    return {name: export(folder, out, f"{name}.mcap") for name, folder in runs.items()}


# ---- every sample, every topic -----------------------------------------------------------------


@pytest.mark.parametrize("name", ["serial_task_rt", "parallel_joint_fast", "serial_joint_fast"])
@pytest.mark.slow
def test_joint_states_are_the_log_sample_for_sample(runs, exported, name):
    header, rows = read_log(runs[name])
    topics = exported[name]
    ns = np.rint(rows[:, 0] * 1e9).astype(np.int64)
    summary = json.loads((runs[name] / "summary.json").read_text())
    units = robot(summary["robot"]).layout(robot(summary["robot"]).load(None), "joint").units
    for unit in units:
        tau = columns(header, f"{unit}.tau.")
        kinds = [("joint_states", "q", "qd", tau), ("true/joint_states", "true_q", "true_qd",
                                                     tau)]
        if summary["space"] == "joint":
            kinds.append(("desired/joint_states", "desired", "desired_dot", []))
        else:
            assert f"/{unit}/desired/joint_states" not in topics  # task space: tool poses
        for topic, pos, vel, eff in kinds:
            messages = topics[f"/{unit}/{topic}"]
            assert len(messages) == len(rows), topic
            p, v = columns(header, f"{unit}.{pos}."), columns(header, f"{unit}.{vel}.")
            assert p and v
            names = [header[i].split(".", 2)[2].rsplit("_", 1)[0] for i in p]
            for k, (log_time, publish_time, schema, msg) in enumerate(messages):
                assert schema == "sensor_msgs/msg/JointState"
                assert log_time == publish_time == ns[k]
                assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == ns[k]
                assert list(msg.name) == names
                np.testing.assert_allclose(msg.position, rows[k, p], rtol=0, atol=TOL)
                np.testing.assert_allclose(msg.velocity, rows[k, v], rtol=0, atol=TOL)
                np.testing.assert_allclose(msg.effort, rows[k, eff], rtol=0, atol=TOL)


@pytest.mark.parametrize("name", ["serial_task_rt", "parallel_joint_fast"])
@pytest.mark.slow
def test_every_column_group_is_a_labelled_array(runs, exported, name):
    """Each unit's column groups (estimates, efforts, errors, ...) and the run-level timing are
    Float64MultiArrays whose layout names each element with its unit; together they carry
    every column of the log."""
    header, rows = read_log(runs[name])
    topics = exported[name]
    covered = {0}
    groups = defaultdict(list)
    for i, h in enumerate(header[1:], start=1):
        parts = h.split(".", 2)
        key = f"/{parts[0]}/{parts[1]}" if len(parts) == 3 else "/run/timing"
        groups[key].append(i)
    for topic, idx in groups.items():
        messages = topics[topic]
        assert len(messages) == len(rows), topic
        labels = [header[i].split(".", 2)[2] if topic != "/run/timing" else header[i]
                  for i in idx]
        for k, (log_time, _, schema, msg) in enumerate(messages):
            assert schema == "std_msgs/msg/Float64MultiArray"
            assert log_time == round(rows[k, 0] * 1e9)
            (dim,) = msg.layout.dim
            assert dim.label.split(",") == labels and dim.size == dim.stride == len(idx)
            np.testing.assert_allclose(msg.data, rows[k, idx], rtol=0, atol=TOL)
        covered |= set(idx)
    assert covered == set(range(len(header)))
    assert ("/run/timing" in topics) == (name == "serial_task_rt")  # real time only


@pytest.mark.slow
def test_message_counts_and_nothing_else(runs, exported):
    """Every topic has one message per period, except /rosout (start, stop or verdict, end)."""
    for name, topics in exported.items():
        _, rows = read_log(runs[name])
        for topic, messages in topics.items():
            if topic == "/rosout":
                assert len(messages) == 3, name
            else:
                assert len(messages) == len(rows), (name, topic)


@pytest.mark.slow
def test_tool_poses_are_the_logged_poses(runs, exported):
    header, rows = read_log(runs["serial_task_rt"])
    topics = exported["serial_task_rt"]
    for unit in ("arm1", "arm2"):
        for label, group in (("actual", "pose"), ("true", "true_pose"), ("desired", "desired")):
            x, y, phi = (header.index(f"{unit}.{group}.{c}") for c in ("x_m", "y_m", "phi_rad"))
            messages = topics[f"/{unit}/tool_pose/{label}"]
            assert len(messages) == len(rows)
            for k, (_, _, schema, msg) in enumerate(messages):
                assert schema == "geometry_msgs/msg/PoseStamped"
                assert msg.header.frame_id == "world"
                p, o = msg.pose.position, msg.pose.orientation
                np.testing.assert_allclose([p.x, p.y, p.z], [rows[k, x], rows[k, y], 0.0],
                                           rtol=0, atol=TOL)
                assert abs(np.arctan2(2 * o.w * o.z, 1 - 2 * o.z**2)
                           - np.angle(np.exp(1j * rows[k, phi]))) < 1e-9
    # The parallel mechanism's two end effectors, C (tool1) and C' (tool2).
    header, rows = read_log(runs["parallel_joint_fast"])
    topics = exported["parallel_joint_fast"]
    for tool, first in (("tool1", "C_u_m"), ("tool2", "C'_u_m")):
        i = header.index(f"mechanism.pose.{first}")
        msg = topics[f"/mechanism/{tool}_pose/actual"][-1][3]
        np.testing.assert_allclose([msg.pose.position.x, msg.pose.position.y],
                                   rows[-1, [i, i + 1]], rtol=0, atol=TOL)
    # Joint space: the desired tool poses are the model's fk_world at the desired joints.
    adapter = robot("parallel")
    fk = adapter.model(adapter.load(None), "mechanism").fk_world
    desired = columns(header, "mechanism.desired.")
    for k in (0, 150, len(rows) - 1):
        pose = np.array(fk(rows[k, desired])).ravel()
        for i, tool in enumerate(("tool1", "tool2")):
            msg = topics[f"/mechanism/{tool}_pose/desired"][k][3]
            np.testing.assert_allclose([msg.pose.position.x, msg.pose.position.y],
                                       pose[3 * i:3 * i + 2], rtol=0, atol=1e-15)
            o = msg.pose.orientation
            assert abs(np.angle(np.exp(1j * (2 * np.arctan2(o.z, o.w) - pose[3 * i + 2])))) \
                < 1e-12


def compose(transforms: list, frame: str) -> np.ndarray:
    """The 4x4 pose of ``frame`` in the world from one TFMessage."""
    by_child = {t.child_frame_id: t for t in transforms}
    T = np.eye(4)
    while frame != "world":
        t = by_child[frame]
        r, p = t.transform.rotation, t.transform.translation
        x, y, z, w = r.x, r.y, r.z, r.w
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        A = np.eye(4)
        A[:3, :3], A[:3, 3] = R, [p.x, p.y, p.z]
        T = A @ T
        frame = t.header.frame_id
    return T


@pytest.mark.parametrize("name", ["serial_task_rt", "parallel_joint_fast"])
@pytest.mark.slow
def test_tf_is_the_models_forward_kinematics(runs, exported, name):
    """At a few samples the tool frames composed from /tf are where the robot model's
    ``fk_world`` puts the tools at the logged q (position and heading), and every unit's
    frames are there."""
    header, rows = read_log(runs[name])
    summary = json.loads((runs[name] / "summary.json").read_text())
    adapter = robot(summary["robot"])
    system = adapter.load(None)
    messages = exported[name]["/tf"]
    assert len(messages) == len(rows)
    for k in (0, len(rows) // 2, len(rows) - 1):
        log_time, _, schema, msg = messages[k]
        assert schema == "tf2_msgs/msg/TFMessage" and log_time == round(rows[k, 0] * 1e9)
        for unit in adapter.layout(system, "joint").units:
            frames = adapter.link_frames(system, unit)
            assert {t.child_frame_id for t in msg.transforms} >= set(frames.names)
            q = rows[k, columns(header, f"{unit}.q.")]
            fk = np.array(adapter.model(system, unit).fk_world(q)).ravel()
            # The tool frames: a serial arm's UNIT/tool; the mechanism's link5 (C and C').
            tools = [n for n in frames.names if n.endswith("/tool") or n.endswith("/link5")]
            assert len(tools) == len(fk) // 3
            for i, frame in enumerate(tools):
                T = compose(msg.transforms, frame)
                np.testing.assert_allclose(T[:2, 3], fk[3 * i:3 * i + 2], rtol=0, atol=1e-12)
                heading = np.arctan2(T[1, 0], T[0, 0])
                assert abs(np.angle(np.exp(1j * (heading - fk[3 * i + 2])))) < 1e-9
                for t in msg.transforms:
                    assert t.header.stamp.sec * 10**9 + t.header.stamp.nanosec == log_time


@pytest.mark.parametrize("chunk", [37, 100])
@pytest.mark.slow
def test_chunked_reading_gives_the_same_messages(runs, exported, tmp_path, monkeypatch, chunk):
    """Long logs are read a chunk of rows at a time: with chunks that split the 300 rows
    unevenly (37) or evenly (100, then an empty read), every message is the same as read in
    one chunk."""
    import warnings

    import cochlea.export.run_log as run_log

    monkeypatch.setattr(run_log, "CHUNK_ROWS", chunk)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "empty input" warning at a chunk's end either
        topics = export(runs["serial_task_rt"], tmp_path)
    whole = exported["serial_task_rt"]
    assert topics.keys() == whole.keys()
    for topic, messages in whole.items():
        assert [(a, b, c, repr(d)) for a, b, c, d in topics[topic]] == \
            [(a, b, c, repr(d)) for a, b, c, d in messages], topic


def test_quaternions_of_rotations(rng):
    """All four branches of the matrix-to-quaternion conversion (rotations by angles near 0,
    and near pi about each axis) give back the matrix."""
    axes = rng.normal(size=(400, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(-np.pi, np.pi, 200), np.pi - rng.uniform(0, 1e-3, 200)])
    axes[200:203] = np.eye(3)
    K = np.zeros((400, 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axes[:, 2], axes[:, 1], -axes[:, 0]
    K -= K.transpose(0, 2, 1)
    s, c = np.sin(angles)[:, None, None], np.cos(angles)[:, None, None]
    R = np.eye(3) + s * K + (1 - c) * K @ K
    q = quaternions(R)
    x, y, z, w = q.T
    back = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                     2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                     2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
                    axis=1).reshape(-1, 3, 3)
    np.testing.assert_allclose(back, R, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    assert np.all(w >= 0)


@pytest.mark.slow
def test_events_say_how_the_run_ended(runs, exported):
    topics = exported["serial_task_rt"]
    summary = json.loads((runs["serial_task_rt"] / "summary.json").read_text())
    logs = [m for _, _, _, m in topics["/rosout"]]
    assert "run started" in logs[0].msg and logs[0].level == 20
    stop = summary["stop"]
    assert f"stop: rule {stop['rule']}" in logs[1].msg
    assert logs[1].stamp.sec * 10**9 + logs[1].stamp.nanosec == round(stop["time_s"] * 1e9) \
        or stop["time_s"] * 1e9 > topics["/tf"][-1][0]  # a stop after the last row: at it
    fast = [m for _, _, _, m in exported["parallel_joint_fast"]["/rosout"]]
    assert "supervisor verdict" in fast[1].msg and "saturated periods" in fast[1].msg


def test_schemas_are_the_standard_definitions():
    """Each type's schema text lists its dependencies once each (rosbag2's concatenation), and
    the fields are those of the standard messages (a subset checked by name)."""
    text = schema_text("sensor_msgs/JointState")
    assert text.splitlines()[:5] == ["std_msgs/Header header", "string[] name",
                                     "float64[] position", "float64[] velocity",
                                     "float64[] effort"]
    assert dependencies("tf2_msgs/TFMessage") == [
        "geometry_msgs/TransformStamped", "std_msgs/Header", "builtin_interfaces/Time",
        "geometry_msgs/Transform", "geometry_msgs/Vector3", "geometry_msgs/Quaternion"]
    for name in DEFINITIONS:
        body = schema_text(name)
        assert body.count("MSG: ") == len(dependencies(name))
        for dep in dependencies(name):
            assert f"MSG: {dep}\n" in body


# ---- bad input ---------------------------------------------------------------------------------


def refused(capsys, *argv: str) -> str:
    code = main(list(argv))
    err = capsys.readouterr().err
    assert code == EXIT_USER_ERROR, err
    assert err.count("\n") == 1 and err.startswith("cochlea-mcap: ") and "Traceback" not in err
    return err


def no_output(folder: Path) -> None:
    """Nothing of an export left in ``folder``: no MCAP and no hidden temporary file."""
    left = [p.name for p in folder.iterdir() if p.suffix == ".mcap" or ".tmp" in p.name]
    assert not left, left


def copy_run(runs, tmp_path: Path, name: str = "serial_task_rt") -> Path:
    return Path(shutil.copytree(runs[name], tmp_path / "run"))


@pytest.mark.slow
def test_not_a_run(capsys, tmp_path, runs):
    assert "is missing" in refused(capsys, str(tmp_path / "nothing"))
    (tmp_path / "file").write_text("x")
    assert "not a folder" in refused(capsys, str(tmp_path / "file"))
    (tmp_path / "empty").mkdir()
    assert "summary.json is missing" in refused(capsys, str(tmp_path / "empty"))
    run = copy_run(runs, tmp_path)
    (run / "log.csv").unlink()  # a run whose report was lost: log.bin only
    assert "log.bin holds the raw log" in refused(capsys, str(run))
    no_output(run)


@pytest.mark.parametrize("damage, message", [
    ("cut_mid_row", "is damaged"),
    ("cut_at_row", "truncated"),
    ("not_a_number", "is damaged"),
    ("time_backwards", "not after the row before"),
    ("header", "header"),
    ("summary_json", "not JSON"),
    ("summary_robot", "no robot"),
    ("missing_columns", "is not this run's log"),
    ("time_negative", "outside [0, 2**31) s"),
    ("time_beyond_ros", "outside [0, 2**31) s"),
    ("time_1e300", "outside [0, 2**31) s"),
    ("summary_deep", "nested too deep"),
    ("summary_fifo", "not a regular file"),
    ("periods_missing", "its periods is None"),
    ("periods_float", "its periods is 1000.0"),
    ("periods_text", "its periods is '1000'"),
    ("periods_bool", "its periods is True"),
    ("joint_in_degrees", "'joint1_deg' is in 'deg', not 'rad'"),
    ("joint_unknown", "'elbow_rad' names no joint of the unit"),
    ("late_row", "after the run's end"),
])
@pytest.mark.slow
def test_damaged_log_is_refused_and_leaves_nothing(capsys, tmp_path, runs, damage, message):
    run = copy_run(runs, tmp_path)
    csv = run / "log.csv"
    lines = csv.read_text().splitlines(keepends=True)
    if damage == "cut_mid_row":
        csv.write_text("".join(lines[:-1]) + lines[-1][: len(lines[-1]) // 2])
    elif damage == "cut_at_row":
        csv.write_text("".join(lines[:-5]))
    elif damage == "not_a_number":
        cells = lines[100].split(",")
        cells[3] = "0.1x"
        lines[100] = ",".join(cells)
        csv.write_text("".join(lines))
    elif damage == "time_backwards":
        lines[150], lines[151] = lines[151], lines[150]
        csv.write_text("".join(lines))
    elif damage == "header":
        csv.write_text("t," + "".join(lines)[len("time_s,"):])
    elif damage == "summary_json":
        (run / "summary.json").write_text((run / "summary.json").read_text()[:100])
    elif damage == "summary_robot":
        (run / "summary.json").write_text("{}")
    elif damage == "missing_columns":
        cells = [line.rstrip("\n").split(",") for line in lines]
        drop = cells[0].index("arm2.tau.joint3_N_m")
        csv.write_text("".join(",".join(c[:drop] + c[drop + 1:]) + "\n" for c in cells))
    elif damage.startswith("time_"):
        # every time shifted (-1 s; +3e9 s, beyond a ROS stamp's int32 seconds) or scaled
        # (1e300): struct.error, int32 'sec' tracebacks and overflow warnings before
        shift = {"time_negative": lambda t: t - 1, "time_beyond_ros": lambda t: t + 3e9,
                 "time_1e300": lambda t: (t + 1) * 1e300}[damage]
        cells = [line.rstrip("\n").split(",") for line in lines]
        for c in cells[1:]:
            c[0] = repr(shift(float(c[0])))
        csv.write_text("".join(",".join(c) + "\n" for c in cells))
    elif damage in ("joint_in_degrees", "joint_unknown"):
        # columns were taken by their position in the group: degrees read as radians
        new = {"joint_in_degrees": "arm1.q.joint1_deg", "joint_unknown": "arm1.q.elbow_rad"}
        old = {"joint_in_degrees": "arm1.q.joint1_rad", "joint_unknown": "arm1.q.joint2_rad"}
        csv.write_text("".join(lines).replace(old[damage], new[damage], 1))
    elif damage == "late_row":  # cochlea-ros2 replay waited for it (1e9 s)
        cells = lines[-1].split(",")
        cells[0] = "1e9"
        lines[-1] = ",".join(cells)
        csv.write_text("".join(lines))
    elif damage == "summary_deep":  # RecursionError in the parser before
        (run / "summary.json").write_text("[" * 200000 + "]" * 200000)
    elif damage == "summary_fifo":
        (run / "summary.json").unlink()
        os.mkfifo(run / "summary.json")
    elif damage.startswith("periods_"):
        # without a whole number of periods the truncation check was off (a log cut to 299
        # of 1000 rows was exported as whole)
        summary = json.loads((run / "summary.json").read_text())
        summary.pop("periods")
        value = {"periods_missing": None, "periods_float": 1000.0, "periods_text": "1000",
                 "periods_bool": True}[damage]
        if value is not None:
            summary["periods"] = value
        (run / "summary.json").write_text(json.dumps(summary))
    # An earlier export stays as it was when a new one fails.
    previous = run / "log.mcap"
    previous.write_bytes(b"previous export")
    assert message in refused(capsys, str(run))
    assert previous.read_bytes() == b"previous export"
    previous.unlink()
    no_output(run)


@pytest.mark.slow
@pytest.mark.parametrize("damage, message", [
    ("comment_row", "could not convert string '#"),
    ("blank_row", "truncated or damaged"),
    ("csv_fifo", "log.csv is not a regular file"),
    ("csv_folder", "log.csv is not a regular file"),
])
def test_a_damaged_log_says_one_line_and_no_more(capfd, tmp_path, runs, damage, message):
    """A '#' or blank row printed numpy's 3-line UserWarning before the one-line error (a '#'
    row was even skipped as a comment); log.csv a FIFO or a folder got the hint that log.bin
    holds the raw log of a run whose report was lost (it is not lost: something else is
    there). Now: one line, and the hint only where log.csv is missing."""
    run = copy_run(runs, tmp_path)
    csv = run / "log.csv"
    lines = csv.read_text().splitlines(keepends=True)
    if damage == "comment_row":
        lines[100] = "#" + lines[100]
    elif damage == "blank_row":
        lines[100] = "\n"
    else:
        csv.unlink()
        os.mkfifo(csv) if damage == "csv_fifo" else csv.mkdir()
    if damage.endswith("_row"):
        csv.write_text("".join(lines))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main([str(run)]) == EXIT_USER_ERROR
    err = capfd.readouterr().err
    assert err.count("\n") == 1 and message in err and "log.bin holds" not in err, err
    assert not [str(w.message) for w in caught]


@pytest.mark.slow
def test_an_infinite_pose_is_exported_without_warnings(capfd, tmp_path, runs):
    """An infinite pose angle (and q) in log.csv is exported as logged, and numpy's
    RuntimeWarnings (invalid value in sin, cos) no longer reach the console."""
    run = copy_run(runs, tmp_path)
    lines = (run / "log.csv").read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[50].split(",")
    cells[header.index("arm1.pose.phi_rad")] = "inf"
    cells[header.index("arm1.q.joint1_rad")] = "-inf"
    lines[50] = ",".join(cells)
    (run / "log.csv").write_text("\n".join(lines) + "\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main([str(run)]) == 0
    out = capfd.readouterr()
    assert out.err == "" and out.out.count("\n") == 1
    assert not [str(w.message) for w in caught]


@pytest.mark.slow
def test_bad_outputs(capsys, tmp_path, runs):
    run = copy_run(runs, tmp_path)
    (tmp_path / "folder.mcap").mkdir()
    assert "not a regular file" in refused(capsys, str(run), "--out", str(tmp_path / "folder.mcap"))
    assert "not a regular file" in refused(capsys, str(run), "--out", "/dev/null")
    os.mkfifo(tmp_path / "pipe.mcap")
    assert "not a regular file" in refused(capsys, str(run), "--out", str(tmp_path / "pipe.mcap"))
    (tmp_path / "afile").write_text("x")
    assert "does not exist" in refused(capsys, str(run), "--out",
                                       str(tmp_path / "afile" / "x.mcap"))
    assert "does not exist" in refused(capsys, str(run), "--out",
                                       str(tmp_path / "no" / "x.mcap"))
    os.symlink(tmp_path / "nowhere", tmp_path / "dangling.mcap")
    assert "cannot use it" in refused(capsys, str(run), "--out",
                                      str(tmp_path / "dangling.mcap"))
    no_output(run)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "afile", "dangling.mcap", "folder.mcap", "pipe.mcap", "run"]


@pytest.mark.slow
def test_the_runs_own_files_are_never_the_output(capsys, tmp_path, runs):
    """An --out that is one of the run's own files (its log, summary, raw log, column list, a
    figure), by its name, through a link or by another path to the folder, is refused before
    anything is written: the run's files are left byte for byte (a probe found log.csv and
    summary.json replaced by the MCAP, exit 0)."""
    run = copy_run(runs, tmp_path)
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    (tmp_path / "alias").symlink_to(run)
    (tmp_path / "link.mcap").symlink_to(run / "log.csv")
    for out in [run / name for name in ("log.csv", "summary.json", "log.bin",
                                        "log.columns.json", "paths.png")] + [
            tmp_path / "alias" / "summary.json", run / ".." / "run" / "log.bin",
            tmp_path / "link.mcap"]:
        assert "the run's own" in refused(capsys, str(run), "--out", str(out))
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before
    assert main([str(run), "--out", str(run / "log.mcap")]) == 0  # its export: allowed


@pytest.mark.slow
def test_unwritable_output_folder(capsys, tmp_path, runs):
    """A folder no one may create files in (/proc: even root cannot) and, for a user, a folder
    without write permission."""
    run = copy_run(runs, tmp_path)
    err = refused(capsys, str(run), "--out", "/proc/cochlea-test.mcap")
    assert "not writable" in err or "cannot write it" in err
    assert not os.path.lexists("/proc/cochlea-test.mcap")
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    if os.geteuid() != 0:  # root writes any folder whatever its mode
        assert "not writable" in refused(capsys, str(run), "--out", str(locked / "x.mcap"))
    assert not list(locked.iterdir())


@pytest.mark.slow
def test_write_failure_leaves_nothing(capsys, tmp_path, runs, monkeypatch):
    """A write that fails part way (a full disk: ENOSPC) is one line, and neither the output
    nor its temporary file is left."""
    import cochlea.export.to_mcap as to_mcap

    run = copy_run(runs, tmp_path)
    real = to_mcap.Exporter.write
    calls = {"n": 0}

    def failing(self, *args):
        calls["n"] += 1
        if calls["n"] == 2000:
            raise OSError(28, "No space left on device")
        return real(self, *args)

    monkeypatch.setattr(to_mcap.Exporter, "write", failing)
    assert "No space left on device" in refused(capsys, str(run))
    no_output(run)


@pytest.mark.slow
def test_interrupt_leaves_nothing(capsys, tmp_path, runs, monkeypatch):
    """Ctrl-C part way: exit 130, one line, neither the output nor its temporary file."""
    import cochlea.export.to_mcap as to_mcap

    run = copy_run(runs, tmp_path)
    real = to_mcap.Exporter.write
    calls = {"n": 0}

    def interrupted(self, *args):
        calls["n"] += 1
        if calls["n"] == 1500:
            raise KeyboardInterrupt
        return real(self, *args)

    monkeypatch.setattr(to_mcap.Exporter, "write", interrupted)
    assert main([str(run)]) == 130
    err = capsys.readouterr().err
    assert err == "cochlea-mcap: interrupted; nothing written\n"
    no_output(run)


TERMINATE_PART_WAY = """
import os, signal, sys
import cochlea.export.to_mcap as to_mcap
from cochlea.apps.cochlea_mcap import main
real, calls = to_mcap.Exporter.write, [0]
def write(self, *args):
    calls[0] += 1
    if calls[0] == 1500:
        os.kill(os.getpid(), getattr(signal, sys.argv[1]))
    return real(self, *args)
to_mcap.Exporter.write = write
sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.slow
@pytest.mark.parametrize("name, code", [("SIGTERM", 143), ("SIGHUP", 129)])
def test_sigterm_or_sighup_leaves_nothing(tmp_path, runs, name, code):
    """SIGTERM (timeout, a batch system) or SIGHUP part way unwinds as Ctrl-C does: one line,
    the shell's code, and no hidden temporary file left beside the output (it was, after a
    SIGTERM)."""
    run = copy_run(runs, tmp_path)
    done = subprocess.run([sys.executable, "-c", TERMINATE_PART_WAY, name, str(run)],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert done.returncode == code, done.stderr
    assert done.stderr == f"cochlea-mcap: {'terminated' if code == 143 else 'hung up (SIGHUP)'}" \
        "; nothing written\n"
    no_output(run)


@pytest.mark.slow
def test_columns_are_read_by_joint_name_not_position(tmp_path, runs, exported):
    """Two joints' q columns swapped, header and data alike (the same log written in another
    order), export exactly as the original: the columns are taken by the joints' names (they
    were taken by position: /tf and tool_pose then disagreed)."""
    run = copy_run(runs, tmp_path)
    lines = (run / "log.csv").read_text().splitlines()
    header = lines[0].split(",")
    a, b = header.index("arm1.q.joint1_rad"), header.index("arm1.q.joint3_rad")
    out = []
    for line in lines:
        cells = line.split(",")
        cells[a], cells[b] = cells[b], cells[a]
        out.append(",".join(cells))
    (run / "log.csv").write_text("\n".join(out) + "\n")
    topics = export(run, tmp_path)
    original = exported["serial_task_rt"]
    for topic in ("/arm1/joint_states", "/tf", "/arm1/tool_pose/actual"):
        assert [str(m) for _, _, _, m in topics[topic]] == \
            [str(m) for _, _, _, m in original[topic]]
    assert topics["/arm1/joint_states"][0][3].name == ["joint1", "joint2", "joint3"]


@pytest.mark.slow
def test_a_stop_time_no_nanosecond_count_holds_is_clamped(tmp_path, runs):
    """summary.json's stop and supervisor times of 1e308 s (an OverflowError in the event's
    stamp before) are stamped at the log's last row, the text keeping the summary's value."""
    run = copy_run(runs, tmp_path, "serial_joint_fast")
    summary = json.loads((run / "summary.json").read_text())
    summary["stop"] = {"rule": "keep-out", "time_s": 1e308, "detail": "x", "exit_code": 11}
    summary["supervisor"]["time_s"] = 1e308
    (run / "summary.json").write_text(json.dumps(summary))
    rosout = export(run, tmp_path)["/rosout"]
    last = max(t for t, _, _, _ in export(run, tmp_path, "again.mcap")["/tf"])
    assert [t for t, _, _, _ in rosout[1:3]] == [last, last]
    assert "1e+308" in rosout[1][3].msg


@pytest.mark.slow
def test_non_finite_rows_have_no_transforms(tmp_path, runs):
    """A row whose measured q is not finite (a run stopped by the rule non-finite) keeps its
    joint states (NaN as logged) but has no /tf message; every other row has one."""
    run = copy_run(runs, tmp_path, "parallel_joint_fast")
    csv = run / "log.csv"
    lines = csv.read_text().splitlines(keepends=True)
    column = lines[0].split(",").index("mechanism.q.left.th2_rad")
    cells = lines[120].split(",")
    cells[column] = "nan"
    lines[120] = ",".join(cells)
    csv.write_text("".join(lines))
    header, rows = read_log(run)
    topics = export(run, tmp_path)
    bad_ns = round(rows[119, 0] * 1e9)
    assert len(topics["/tf"]) == len(rows) - 1
    assert bad_ns not in {t for t, _, _, _ in topics["/tf"]}
    states = topics["/mechanism/joint_states"]
    assert len(states) == len(rows) and np.isnan(states[119][3].position[1])


@pytest.mark.slow
def test_a_relative_scenario_is_recorded_absolute(tmp_path):
    """cochlea-run --scenario my.toml (relative) stored "my.toml" in summary.json: exported
    from another folder it named no file (or another my.toml). It is stored absolute, and the
    run exports from anywhere."""
    shutil.copy(ROOT / "models" / "scenarios" / "serial_joint.toml", tmp_path / "my.toml")
    run = tmp_path / "run"
    done = subprocess.run(  # from the scenario's folder, this checkout's cochlea
        [sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial", "--space",
         "joint", "--scenario", "my.toml", "--duration", "0.05", "--realtime", "off",
         "--status", "off", "--out", "run"], capture_output=True, text=True, timeout=300,
        cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr
    summary = json.loads((run / "summary.json").read_text())
    assert summary["scenario_file"] == str(tmp_path / "my.toml")
    assert Path.cwd() != tmp_path and main([str(run)]) == 0


@pytest.mark.slow
def test_existing_output_file_is_replaced_whole(tmp_path, runs):
    run = copy_run(runs, tmp_path, "parallel_joint_fast")
    out = run / "log.mcap"
    out.write_bytes(b"old")
    assert main([str(run)]) == 0  # the default output
    assert len(read_mcap(out)["/tf"]) == len(read_log(run)[1])
    no_output_left = [p.name for p in run.iterdir() if ".tmp" in p.name]
    assert not no_output_left


@pytest.mark.slow
def test_command_line(tmp_path, runs):
    """The installed command's module: the default output, a one-line report, exit 0; and a
    bad input from the shell, exit 2 without a traceback."""
    run = copy_run(runs, tmp_path, "serial_joint_fast")
    done = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_mcap", str(run)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"cochlea-mcap: wrote {run / 'log.mcap'}: ")
    assert (run / "log.mcap").is_file()
    bad = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_mcap", str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1
    assert "Traceback" not in bad.stderr


# ---- folders of the hardware paths (the virtual Dynamixel chain) -------------------------------


@pytest.mark.hil
def test_embedded_program_and_dynamixel_runs_export(tmp_path):
    """The embedded C program's folder (no pose columns, its own summary) and cochlea-run's on
    the virtual chain (measured state only, currents) export like the others: joint states of
    every row, /tf on each, no true-state topic where the log has no true state."""
    from tests.test_dynamixel_hil import run as cochlea_run_dxl
    from tests.test_embedded_program import PATIENT, on_emulator
    from tests.test_embedded_program import emulator as settled_emulator

    done = subprocess.run(["make", "--no-print-directory", "embedded"], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    result, c_out, _ = on_emulator(ROOT / "build" / "cochlea-embedded", tmp_path,
                                   ("serial", "serial_joint"), "--scenario", "serial_joint",
                                   "--duration", "0.3", *PATIENT)
    assert result.returncode == 0, result.stderr
    py_out = tmp_path / "py"
    with settled_emulator("serial", "serial_joint", tmp_path / "py.log") as port:
        ran = cochlea_run_dxl("--robot", "serial", "--space", "joint", "--backend", "dynamixel",
                              "--port", port, "--duration", "0.3", "--out", str(py_out),
                              cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr
    for folder in (c_out, py_out):
        topics = export(folder, tmp_path, f"{folder.name}.mcap")
        header, rows = read_log(folder)
        for unit in ("arm1", "arm2"):
            messages = topics[f"/{unit}/joint_states"]
            assert len(messages) == len(rows)
            q, tau = columns(header, f"{unit}.q."), columns(header, f"{unit}.tau.")
            for k, (log_time, _, _, msg) in enumerate(messages):
                assert log_time == round(rows[k, 0] * 1e9)
                np.testing.assert_allclose(msg.position, rows[k, q], rtol=0, atol=TOL)
                np.testing.assert_allclose(msg.effort, rows[k, tau], rtol=0, atol=TOL)
            assert f"/{unit}/true/joint_states" not in topics
            assert len(topics[f"/{unit}/current"]) == len(rows)
            # cochlea-run logs the pose; the embedded program does not, and the actual tool
            # pose is then fk_world at q.
            fk = robot("serial").model(robot("serial").load(None), unit).fk_world
            pose = columns(header, f"{unit}.pose.")
            assert len(pose) == (0 if folder == c_out else 3)
            for k in (0, len(rows) - 1):
                msg = topics[f"/{unit}/tool_pose/actual"][k][3]
                expected = rows[k, pose[:2]] if pose else np.array(fk(rows[k, q])).ravel()[:2]
                np.testing.assert_allclose([msg.pose.position.x, msg.pose.position.y],
                                           expected, rtol=0, atol=TOL)
        assert len(topics["/tf"]) == len(rows)
