"""Task spaces of serial arms the package does not ship (issue 25): the tool coordinates against
Pinocchio, numeric inverse kinematics (round trips, refusals), the square-Jacobian rule of
controller g, and task-space runs of g that converge: a 2-DoF planar arm (tests/data/
planar2_tasks.toml, task "planar"), a 4-DoF spatial arm written by hand (tests/data/spatial4.toml,
"position_yaw") and the 6-DoF UR5 of example-robot-data (full "pose")."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from cochlea.errors import CochleaError, KinematicsError
from cochlea.resources import SCENARIOS_DIR
from cochlea.robots import robot
from cochlea.robots.serial import load_serial
from cochlea.robots.serial.chain import tool_offset
from cochlea.robots.serial.description import rpy_matrix
from cochlea.robots.serial.ik import (
    SingularTarget,
    TaskSizeError,
    UnreachableTarget,
    ik,
    solve_ik,
)
from cochlea.robots.serial.task import TASKS, task_space
from cochlea.robots.serial.urdf import import_urdf
from cochlea.sim import load_scenario, simulate
from cochlea.sim.setup import unit_setups

from .conftest import DATA
from .test_pinocchio_oracle import pinocchio_arm
from .test_urdf import UR5

PLANAR2 = DATA / "planar2_tasks.toml"
SPATIAL4 = DATA / "spatial4.toml"
needs_ur5 = pytest.mark.skipif(UR5 is None, reason="example-robot-data is not installed")


@pytest.fixture(scope="module")
def ur5_file(tmp_path_factory) -> Path:
    """The UR5 imported, gravity off (its imported XM540s could not hold it: the runs here
    are about the task space, not the drives)."""
    out = tmp_path_factory.mktemp("ur5") / "ur5.toml"
    text = import_urdf(UR5).text.replace("gravity_m_s2 = [0.0, 0.0, -9.81]",
                                         "gravity_m_s2 = [0.0, 0.0, 0.0]")
    out.write_text(text, encoding="utf-8")
    return out


def _random_q(arm, rng):
    lo = np.array([max(link.joint.position_limits[0], -3.0) for link in arm.links])
    hi = np.array([min(link.joint.position_limits[1], 3.0) for link in arm.links])
    return rng.uniform(0.8 * lo, 0.8 * hi)


def _pinocchio_tool(system, arm, q):
    """Tool point and tool rotation in the world frame, and the tool frame's Jacobian (world
    axes: linear, angular), by Pinocchio from the description's numbers."""
    model = pinocchio_arm(system, arm)
    last = model.njoints - 1
    R_tool = np.eye(3) if arm.tool_rpy is None else rpy_matrix(arm.tool_rpy)
    frame = model.addFrame(pin.Frame("tool", last, 0, pin.SE3(R_tool, tool_offset(arm)),
                                     pin.FrameType.OP_FRAME))
    data = model.createData()
    pin.computeJointJacobians(model, data, q)
    pin.updateFramePlacements(model, data)
    oMf = data.oMf[frame]
    J = pin.getFrameJacobian(model, data, frame, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
    Rb = arm.base_rotation
    p = arm.base_xyz + Rb @ oMf.translation
    return p, Rb @ oMf.rotation, Rb @ J[:3], Rb @ J[3:]


def _arms(ur5_file=None):
    out = [(PLANAR2, "planar"), (PLANAR2, "planar_yaw"), (SPATIAL4, "position"),
           (SPATIAL4, "position_yaw")]
    if ur5_file is not None:
        out += [(ur5_file, "position"), (ur5_file, "pose")]
    return out


def test_task_names_are_the_documented_ones():
    assert TASKS == ("planar", "planar_yaw", "position", "position_yaw", "pose")


@pytest.fixture(scope="module")
def tooled_file(tmp_path_factory) -> Path:
    """The 4-DoF arm with a tool offset and a turned tool frame."""
    out = tmp_path_factory.mktemp("tool") / "tooled.toml"
    out.write_text(SPATIAL4.read_text().replace(
        'base_rpy_deg = [3.0, -2.0, 80.0]\n', 'base_rpy_deg = [3.0, -2.0, 80.0]\n'
        'tool_xyz_m = [0.03, 0.01, -0.02]\ntool_rpy_deg = [10.0, -20.0, 30.0]\n'))
    return out


@pytest.mark.parametrize("which", ["planar2", "spatial4", "tooled", "ur5"])
def test_tool_coordinates_and_jacobians_agree_with_pinocchio(which, ur5_file, tooled_file,
                                                             rng):
    if which == "ur5" and UR5 is None:
        pytest.skip("example-robot-data is not installed")
    path = {"planar2": PLANAR2, "spatial4": SPATIAL4, "tooled": tooled_file,
            "ur5": ur5_file}[which]
    system = load_serial(path)
    arm = system.arms[0]
    assert (arm.tool_rpy is not None) == (which == "tooled")
    spaces = {t: task_space(arm, t) for t in TASKS}
    for _ in range(20):
        q = _random_q(arm, rng)
        p, R, Jv, Jw = _pinocchio_tool(system, arm, q)
        yaw = np.arctan2(R[1, 0], R[0, 0])
        wrap = lambda a: np.arctan2(np.sin(a), np.cos(a))  # noqa: E731
        x = {t: np.array(s.fk(q), float).ravel() for t, s in spaces.items()}
        J = {t: np.array(s.J(q), float) for t, s in spaces.items()}
        np.testing.assert_allclose(x["position"], p, atol=1e-12)
        np.testing.assert_allclose(x["planar"], p[:2], atol=1e-12)
        assert abs(wrap(x["planar_yaw"][2] - yaw)) < 1e-12
        assert abs(wrap(x["position_yaw"][3] - yaw)) < 1e-12
        np.testing.assert_allclose(J["position"], Jv, atol=1e-12)
        # d(yaw)/dq: the world z row of the angular Jacobian, scaled by the tool's tilt.
        d_first = np.cross(Jw.T, R[:, 0])  # d(R's first column)/dq_i = w_i x R[:, 0]
        dyaw = ((R[0, 0] * d_first[:, 1] - R[1, 0] * d_first[:, 0])
                / (R[0, 0] ** 2 + R[1, 0] ** 2))
        np.testing.assert_allclose(J["position_yaw"][3], dyaw, atol=1e-10)
        # The full pose: roll, pitch, yaw of R; at x_d = the current pose the error is zero
        # and its Jacobian is (linear; the angular velocity in the tool frame).
        roll, pitch, yaw_ = x["pose"][3:]
        Rz = np.array([[np.cos(yaw_), -np.sin(yaw_), 0], [np.sin(yaw_), np.cos(yaw_), 0],
                       [0, 0, 1]])
        Ry = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0],
                       [-np.sin(pitch), 0, np.cos(pitch)]])
        Rx = np.array([[1, 0, 0], [0, np.cos(roll), -np.sin(roll)],
                       [0, np.sin(roll), np.cos(roll)]])
        np.testing.assert_allclose(Rz @ Ry @ Rx, R, atol=1e-12)
        r, _, Je = (np.array(v, float) for v in spaces["pose"].residual()(q, x["pose"]))
        assert np.abs(r).max() < 1e-12
        assert np.abs(np.array(spaces["pose"].error(q, x["pose"]))).max() < 1e-12
        np.testing.assert_allclose(Je[:3], Jv, atol=1e-12)
        np.testing.assert_allclose(Je[3:], R.T @ Jw, atol=1e-12)


@pytest.mark.parametrize("k", range(6))
@pytest.mark.slow
def test_inverse_kinematics_round_trips(k, ur5_file, rng):
    cases = _arms(ur5_file if UR5 is not None else None)
    if k >= len(cases):
        pytest.skip("example-robot-data is not installed")
    path, task = cases[k]
    arm = load_serial(path).arms[0]
    space = task_space(arm, task)
    if len(arm.links) < space.size:  # the 2-DoF arm in (x, y, phi)
        with pytest.raises(TaskSizeError, match=r"deficient arm"):
            solve_ik(arm, space, np.zeros(space.size))
        return
    for _ in range(5):
        q = _random_q(arm, rng)
        target = np.array(space.fk(q), float).ravel()
        q_ik = solve_ik(arm, space, target)
        e = space.residual()(q_ik, target)[0]
        assert np.abs(np.array(e)).max() < 1e-9
        lo, hi = np.array([link.joint.position_limits for link in arm.links]).T
        assert np.all(lo <= q_ik) and np.all(q_ik <= hi)


@pytest.mark.slow
def test_numeric_inverse_kinematics_finds_the_closed_forms_branch():
    """The shipped planar 3R arm: the numeric solver seeded on a branch gives the closed form's
    answer on it."""
    arm = robot("serial").load().arms[0]
    space = task_space(arm, "planar_yaw")
    pose = np.array([0.028, 0.01, np.radians(-103)])
    q_closed, elbow, _ = ik(arm, pose, np.array([0.0, 1.0, 0.0]))
    q_numeric = solve_ik(arm, space, pose, seeds=(q_closed + 0.05,))
    np.testing.assert_allclose(q_numeric, q_closed, atol=1e-9)
    np.testing.assert_allclose(solve_ik(arm, space, pose, elbow=elbow), q_closed, atol=1e-9)


@pytest.mark.slow
def test_unreachable_and_singular_targets_are_refused_in_one_line():
    arm = load_serial(PLANAR2).arms[0]
    space = task_space(arm, "planar")
    with pytest.raises(UnreachableTarget, match=r"out of reach within the joint limits") as e:
        solve_ik(arm, space, [0.0, 0.5])  # 0.65 m from a base that reaches 0.4 m
    assert "\n" not in str(e.value)
    with pytest.raises(UnreachableTarget):  # the base itself: th2 = 180 deg, beyond 170
        solve_ik(arm, space, [0.0, -0.15])
    with pytest.raises(SingularTarget, match="singular configuration"):
        solve_ik(arm, space, [0.0, 0.25])  # the arm stretched straight
    with pytest.raises(TaskSizeError, match=r"2 joints and task 'position_yaw' has 4"):
        solve_ik(arm, task_space(arm, "position_yaw"), [0.0, 0.2, 0.0, 0.0])


def _scenario(tmp_path: Path, description: Path, task: str, leader: list[str],
              initial: str, gains: str, duration: float = 3.0, space: str = "task") -> Path:
    text = f"""format = "cochlea-scenario/1"
robot = "serial"
space = "{space}"
description = "{description}"
duration_s = {duration}

[control]
task = "{task}"
parameterisation = "base"
initial_estimate = "nominal"

[desired]
leader = [{", ".join(f'"{x}"' for x in leader)}]

[[unit]]
name = "arm"
{initial}
gains = {gains}
"""
    path = tmp_path / "s.toml"
    path.write_text(text, encoding="utf-8")
    return path


def _final_error(result) -> np.ndarray:
    e = result.units[0].tracking_error
    return np.abs(e[-len(e) // 10:]).max(axis=0), np.abs(e[0])


@pytest.mark.slow
def test_planar_two_joint_arm_tracks_a_circle_with_controller_g():
    sc = load_scenario(DATA / "planar2_task.toml")
    assert sc.task == "planar" and sc.controller == "g"
    result = simulate(sc, kernels="casadi")
    assert not result.diverged
    final, first = _final_error(result)
    assert np.all(first > 5e-3) and np.all(final < 0.02 * first), (final, first)


@pytest.mark.slow
def test_spatial_four_joint_arm_tracks_position_and_heading(tmp_path):
    arm = load_serial(SPATIAL4).arms[0]
    space = task_space(arm, "position_yaw")
    q_ref = np.array([0.3, -0.6, 1.2, 0.8])
    x = np.array(space.fk(q_ref), float).ravel().tolist()
    path = _scenario(
        tmp_path, SPATIAL4, "position_yaw",
        [f"{x[0]!r} + 0.02*sin(t) m", f"{x[1]!r} m", f"{x[2]!r} + 0.02*(1 - cos(t)) m",
         f"{float(np.degrees(x[3]))!r} + 10*sin(t) deg"],
        'initial_joint = ["0.32 rad", "-0.62 rad", "1.22 rad", "0.77 rad"]',
        "{ G_g = [5.0, 5.0, 5.0, 5.0], G_a = [1.0, 1.0, 0.5, 0.05] }")
    result = simulate(load_scenario(path), kernels="casadi")
    assert not result.diverged
    final, first = _final_error(result)
    assert np.all(final < 0.02 * first), (final, first)


@needs_ur5
@pytest.mark.slow
def test_ur5_tracks_a_full_pose_with_controller_g(tmp_path, ur5_file):
    arm = load_serial(ur5_file).arms[0]
    space = task_space(arm, "pose")
    q_ref = np.array([0.3, -1.2, 1.4, -1.8, -1.5, 0.4])
    x = np.array(space.fk(q_ref), float).ravel().tolist()
    deg = np.degrees(x[3:]).tolist()
    initial = ", ".join(f'"{float(v) + 0.03!r} rad"' for v in q_ref)
    path = _scenario(
        tmp_path, ur5_file, "pose",
        [f"{x[0]!r} + 0.03*sin(t) m", f"{x[1]!r} + 0.03*(1 - cos(t)) m", f"{x[2]!r} m",
         f"{deg[0]!r} deg", f"{deg[1]!r} + 5*sin(t) deg", f"{deg[2]!r} deg"],
        f"initial_joint = [{initial}]",
        "{ G_g = [5.0, 5.0, 5.0, 5.0, 5.0, 5.0], G_a = [20.0, 20.0, 10.0, 2.0, 2.0, 2.0] }")
    result = simulate(load_scenario(path), kernels="casadi")
    assert not result.diverged
    final, first = _final_error(result)
    assert np.all(final < 0.05 * first), (final, first)
    # The orientation error the controller drives (sin(theta) u) shrinks with the logged one.
    errors = result.units[0].errors
    assert np.abs(errors[-300:, 3:6]).max() < 0.05 * np.abs(errors[0, 3:6]).max()


@needs_ur5
@pytest.mark.slow
def test_a_task_the_jacobian_is_not_square_for_is_refused(tmp_path, ur5_file):
    """Controller g on the 6-joint UR5 in (x, y, z): a redundant arm, refused in one line
    naming the sizes; the default task (planar + yaw) likewise."""
    for task, m in (("position", 3), ("planar_yaw", 3)):
        path = _scenario(tmp_path, ur5_file, task, ["0.4 m", "0.1 m"] + (
            ["0.3 m"] if task == "position" else ["0 deg"]),
            'initial_joint = ["0 rad", "-1 rad", "1 rad", "0 rad", "1 rad", "0 rad"]',
            "{ G_g = [1.0, 1.0, 1.0], G_a = [1.0, 1.0, 1.0, 1.0, 1.0, 1.0] }")
        with pytest.raises(TaskSizeError, match=rf"6 joints and task '{task}' has {m} "
                           r"coordinates .*redundant"):
            unit_setups(load_scenario(path), cache=False)


@pytest.mark.slow
def test_an_initial_task_pose_is_solved_numerically_and_an_unreachable_one_refused(tmp_path):
    gains = "{ G_g = [5.0, 5.0], G_a = [0.5, 0.5] }"
    leader = ["0.03*cos(0.5*t) m", "0.15 + 0.03*sin(0.5*t) m"]
    sc = load_scenario(_scenario(tmp_path, PLANAR2, "planar", leader,
                                 'initial_task = ["0.04 m", "0.16 m"]\nelbow = -1', gains))
    (setup,) = unit_setups(sc, cache=False)
    q0 = setup.x0[:2]
    assert q0[1] < 0
    np.testing.assert_allclose(np.array(setup.fk_world(q0)).ravel(), [0.04, 0.16], atol=1e-9)
    sc = load_scenario(_scenario(tmp_path, PLANAR2, "planar", leader,
                                 'initial_task = ["0.3 m", "0.4 m"]', gains))
    with pytest.raises(UnreachableTarget, match="out of reach"):
        unit_setups(sc, cache=False)
    # A desired path that leaves the workspace is refused before anything runs.
    far = ["0.03*cos(0.5*t) m", "0.15 + 0.2*t m"]
    sc = load_scenario(_scenario(tmp_path, PLANAR2, "planar", far,
                                 'initial_task = ["0.04 m", "0.16 m"]', gains))
    with pytest.raises(KinematicsError, match=r"desired path: .*at t = "):
        unit_setups(sc, cache=False)


def test_the_task_key_is_checked_and_only_serial_robots_take_it(tmp_path):
    path = _scenario(tmp_path, PLANAR2, "spherical", ["0 m", "0 m"], 'initial_joint = '
                     '["0 rad", "1 rad"]', "{ G_g = [5.0, 5.0], G_a = [0.5, 0.5] }")
    with pytest.raises(CochleaError, match=re.escape("control.task")):
        load_scenario(path)
    text = (SCENARIOS_DIR / "parallel_task.toml").read_text().replace(
        "[control]", '[control]\ntask = "pose"')
    bad = tmp_path / "parallel.toml"
    bad.write_text(text)
    with pytest.raises(CochleaError, match="task"):
        load_scenario(bad)


@pytest.mark.slow
def test_the_shipped_studies_keep_their_default_task():
    for name in ("serial_task", "serial_joint"):
        sc = load_scenario(name)
        assert sc.task == "planar_yaw"
        (a1, a2) = unit_setups(sc)
        assert a1.task_names == ("x", "y", "phi") and a1.task_angles == (2,)


def test_base_rpy_and_its_yaw_shorthand(tmp_path):
    text = PLANAR2.read_text()
    rolled = tmp_path / "rolled.toml"
    rolled.write_text(text.replace("base_yaw_deg = 90.0", "base_rpy_deg = [0.0, 0.0, 90.0]"))
    a, b = load_serial(PLANAR2).arms[0], load_serial(rolled).arms[0]
    q = np.array([0.3, -0.4])
    np.testing.assert_allclose(np.array(task_space(a, "pose").fk(q)),
                               np.array(task_space(b, "pose").fk(q)), atol=1e-15)
    both = tmp_path / "both.toml"
    both.write_text(text.replace("base_yaw_deg = 90.0",
                                 "base_yaw_deg = 90.0\nbase_rpy_deg = [0.0, 0.0, 90.0]"))
    with pytest.raises(CochleaError, match="one of base_yaw_deg or base_rpy_deg"):
        load_serial(both)


@pytest.mark.slow
def test_cochlea_run_refuses_an_unreachable_path_in_one_line_with_exit_2(tmp_path, capsys):
    from cochlea.apps.cochlea_run import main

    far = ["0.03*cos(0.5*t) m", "0.15 + 0.2*t m"]
    path = _scenario(tmp_path, PLANAR2, "planar", far, 'initial_task = ["0.04 m", "0.16 m"]',
                     "{ G_g = [5.0, 5.0], G_a = [0.5, 0.5] }")
    code = main(["--robot", "serial", "--space", "task", "--scenario", str(path),
                 "--realtime", "off", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == 2
    assert "out of reach" in err and "Traceback" not in err
    assert len([line for line in err.splitlines() if line.strip()]) == 1


@pytest.mark.slow
def test_controller_e_runs_a_user_arm_from_a_task_space_initial_pose(tmp_path):
    """Joint space on the 4-DoF arm: the initial joint position from an initial (x, y, z,
    heading) by the numeric solver, then e tracks a joint path."""
    arm = load_serial(SPATIAL4).arms[0]
    x = np.array(task_space(arm, "position_yaw").fk([0.3, -0.6, 1.2, 0.8]), float).ravel()
    initial = ", ".join(f'"{v!r} m"' for v in x[:3].tolist()) + f', "{float(x[3])!r} rad"'
    path = _scenario(
        tmp_path, SPATIAL4, "position_yaw",
        ["0.3 + 0.1*sin(t) rad", "-0.6 rad", "1.2 - 0.1*sin(t) rad", "0.8 rad"],
        f"initial_task = [{initial}]",
        "{ alpha = [5.0, 5.0, 5.0, 5.0], G_e = [0.5, 0.5, 0.2, 0.02] }",
        duration=2.0, space="joint")
    sc = load_scenario(path)
    (setup,) = unit_setups(sc, cache=False)
    np.testing.assert_allclose(setup.x0[:4], [0.3, -0.6, 1.2, 0.8], atol=1e-8)
    result = simulate(sc, kernels="casadi")
    assert not result.diverged
    assert np.abs(result.units[0].tracking_error[-200:]).max() < 1e-3


@pytest.mark.slow
def test_a_user_dual_arm_system_mirrors_the_leader_in_the_planar_task(tmp_path):
    """Two copies of the 2-DoF arm facing each other across the cochlea centre: the second
    tracks the leader's desired point reflected through the centre, by controller g."""
    text = PLANAR2.read_text()
    second = text[text.index("[[arm]]"):]
    for old, new in (('name = "arm"', 'name = "arm2"'), ("[0.0, -0.15, 0.0]", "[0.0, 0.15, 0.0]"),
                     ("base_yaw_deg = 90.0", "base_yaw_deg = -90.0"), ("id = 1\n", "id = 3\n"),
                     ("id = 2\n", "id = 4\n")):
        second = second.replace(old, new)
    (tmp_path / "dual.toml").write_text(text + "\n" + second)
    gains = "{ G_g = [5.0, 5.0], G_a = [0.5, 0.5] }"
    path = _scenario(tmp_path, tmp_path / "dual.toml", "planar",
                     ["0.03*cos(0.5*t) m", "0.1 + 0.03*sin(0.5*t) m"],
                     'initial_task = ["0.04 m", "0.11 m"]', gains)
    path.write_text(path.read_text() + f'\n[[unit]]\nname = "arm2"\ninitial_task = '
                    f'["-0.04 m", "-0.09 m"]\ngains = {gains}\n')
    result = simulate(load_scenario(path), kernels="casadi")
    lead, follow = result.units
    np.testing.assert_allclose(follow.desired, -lead.desired, atol=1e-15)
    for unit in result.units:
        final = np.abs(unit.tracking_error[-300:]).max(axis=0)
        assert np.all(final < 0.01 * np.abs(unit.tracking_error[0])), (unit.setup.name, final)


@needs_ur5
@pytest.mark.slow
def test_a_full_pose_run_starting_beyond_80_degrees_is_refused(tmp_path, ur5_file):
    """The orientation error sin(theta) u loses rank at 90 deg and vanishes again at 180 deg:
    a run that starts 120 deg away is refused before it moves."""
    arm = load_serial(ur5_file).arms[0]
    q_ref = np.array([0.3, -1.2, 1.4, -1.8, -1.5, 0.4])
    x = np.array(task_space(arm, "pose").fk(q_ref), float).ravel().tolist()
    deg = np.degrees(x[3:]).tolist()
    initial = ", ".join(f'"{float(v)!r} rad"' for v in q_ref)
    path = _scenario(
        tmp_path, ur5_file, "pose",
        [f"{x[0]!r} m", f"{x[1]!r} m", f"{x[2]!r} m", f"{deg[0] + 120.0!r} deg",
         f"{deg[1]!r} deg", f"{deg[2]!r} deg"],
        f"initial_joint = [{initial}]",
        "{ G_g = [5.0, 5.0, 5.0, 5.0, 5.0, 5.0], G_a = [20.0, 20.0, 10.0, 2.0, 2.0, 2.0] }")
    with pytest.raises(UnreachableTarget, match=r"initial orientation is 120\.0 deg from the "
                       r"desired one"):
        unit_setups(load_scenario(path), cache=False)


def test_urdf_export_writes_the_tool_frame(tmp_path, tooled_file):
    """cochlea-urdf export adds a massless fixed frame ``tool``: Pinocchio's pose of it is
    the task space's full pose."""
    from cochlea.robots.serial.urdf import export_urdf

    system = load_serial(tooled_file)
    arm = system.arms[0]
    urdf = tmp_path / "tooled.urdf"
    urdf.write_text(export_urdf(system), encoding="utf-8")
    model = pin.buildModelFromUrdf(str(urdf))
    data = model.createData()
    q = np.array([0.2, -0.3, 0.5, 0.7])
    pin.framesForwardKinematics(model, data, q)
    tool = data.oMf[model.getFrameId("tool")]
    x = np.array(task_space(arm, "pose").fk(q), float).ravel()
    np.testing.assert_allclose(tool.translation, x[:3], atol=1e-12)
    np.testing.assert_allclose(tool.rotation, rpy_matrix(x[3:]), atol=1e-12)
