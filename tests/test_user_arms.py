"""Issue 25's proof matrix on arms the package does not ship: a 2-DoF planar arm on XM540s
(tests/data/planar2*.toml), a 4-DoF spatial arm on XM430-W350s written by hand
(tests/data/spatial4.toml) and the 6-DoF UR5 imported from example-robot-data's URDF.

What is proved where (so nothing is duplicated):

(planar2 | spatial4 | UR5; "here" is this file)

- model against Pinocchio, dynamics: here | here | test_urdf; tool pose and Jacobians:
  test_task_spaces for all three;
- joint-space run on C kernels, equal to CasADi and converging: here | here | here (slow);
- task-space kernels equal to CasADi (1e-12), the C run to the CasADi run (1e-9), converging:
  here, planar | here, position_yaw (and position on its first three joints) | here, pose
  (slow);
- virtual chain (emulator + cochlea-run --backend dynamixel): test_user_robot_tools | here
  (hil) | here (hil);
- excitation + identification within 5 % on a perturbed plant: test_user_robot_tools | here
  (slow) | here (slow);
- small sweep: test_user_robot_tools | here | here.

The 6-DoF arm is the UR5, not the SO-101: see docs/extending.md ("A Dynamixel arm of your
own") for why the SO-101's identification on a perturbed plant fails without armature.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from cochlea.apps import cochlea_codegen
from cochlea.apps.cochlea_codegen import scenario_kernels
from cochlea.kernels.library import Library
from cochlea.robots.serial import load_serial
from cochlea.robots.serial.chain import tool_offset
from cochlea.robots.serial.description import rpy_matrix
from cochlea.robots.serial.task import task_space
from cochlea.robots.serial.urdf import import_urdf
from cochlea.sim import load_scenario, simulate
from cochlea.sim.setup import unit_setups

from .conftest import DATA
from .test_urdf import UR5

ROOT = Path(__file__).resolve().parent.parent
PLANAR2 = DATA / "planar2_tasks.toml"
SPATIAL4 = DATA / "spatial4.toml"
RUN = [sys.executable, "-m", "cochlea.apps.cochlea_run"]
FIELDS = ("q", "qd", "desired", "desired_dot", "errors", "tau", "p_hat", "pose", "true_q",
          "true_qd", "true_x")
needs_ur5 = pytest.mark.skipif(UR5 is None, reason="example-robot-data is not installed")


def _scenario(folder: Path, description: Path, task: str, leader: list[str], initial: str,
              gains: str, duration: float, space: str = "task", name: str = "s.toml") -> Path:
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
    path = folder / name
    path.write_text(text, encoding="utf-8")
    return path


def _spatial(folder: Path, task: str, duration: float = 3.0) -> Path:
    """spatial4 tracking a small circle in (x, z) with a heading swing (``position_yaw``), or
    its first three joints (``spatial3``, the hand cut off: ``position`` is square there)
    tracking the same circle; from a start a few degrees off the path."""
    text = SPATIAL4.read_text(encoding="utf-8")
    description = SPATIAL4
    if task == "position":
        description = folder / "spatial3.toml"
        cut = text.rindex("  [[arm.link]]")
        description.write_text(text[:cut].replace('name = "spatial4"', 'name = "spatial3"'),
                               encoding="utf-8")
    arm = load_serial(description).arms[0]
    q_ref = np.array([0.3, -0.6, 1.2, 0.8])[:len(arm.links)]
    x = np.array(task_space(arm, task).fk(q_ref), float).ravel().tolist()
    leader = [f"{x[0]!r} + 0.02*sin(t) m", f"{x[1]!r} m", f"{x[2]!r} + 0.02*(1 - cos(t)) m"]
    initial = ", ".join(f'"{float(v) + 0.02!r} rad"' for v in q_ref)
    if task == "position_yaw":
        leader.append(f"{float(np.degrees(x[3]))!r} + 10*sin(t) deg")
        gains = "{ G_g = [5.0, 5.0, 5.0, 5.0], G_a = [1.0, 1.0, 0.5, 0.05] }"
    else:
        gains = "{ G_g = [5.0, 5.0, 5.0], G_a = [1.0, 1.0, 0.5] }"
    return _scenario(folder, description, task, leader, f"initial_joint = [{initial}]", gains,
                     duration, name=f"{task}.toml")


@pytest.fixture(scope="module")
def ur5_file(tmp_path_factory) -> Path:
    """The UR5 imported, gravity off (its imported XM540s could not hold it: the runs here
    are about the task space and the kernels, not the drives)."""
    out = tmp_path_factory.mktemp("ur5") / "ur5.toml"
    text = import_urdf(UR5).text.replace("gravity_m_s2 = [0.0, 0.0, -9.81]",
                                         "gravity_m_s2 = [0.0, 0.0, 0.0]")
    out.write_text(text, encoding="utf-8")
    return out


def _ur5_pose(folder: Path, ur5: Path) -> Path:
    arm = load_serial(ur5).arms[0]
    q_ref = np.array([0.3, -1.2, 1.4, -1.8, -1.5, 0.4])
    x = np.array(task_space(arm, "pose").fk(q_ref), float).ravel().tolist()
    deg = np.degrees(x[3:]).tolist()
    initial = ", ".join(f'"{float(v) + 0.03!r} rad"' for v in q_ref)
    return _scenario(
        folder, ur5, "pose",
        [f"{x[0]!r} + 0.03*sin(t) m", f"{x[1]!r} + 0.03*(1 - cos(t)) m", f"{x[2]!r} m",
         f"{deg[0]!r} deg", f"{deg[1]!r} + 5*sin(t) deg", f"{deg[2]!r} deg"],
        f"initial_joint = [{initial}]",
        "{ G_g = [5.0, 5.0, 5.0, 5.0, 5.0, 5.0], G_a = [20.0, 20.0, 10.0, 2.0, 2.0, 2.0] }", 3.0,
        name="pose.toml")


def _generated(folder: Path, scenario: Path) -> Path:
    """``cochlea-codegen --scenario FILE --out DIR`` (ideal plant), the compiled folder."""
    out = folder / "kernels"
    assert cochlea_codegen.main(["--scenario", str(scenario), "--out", str(out),
                                 "--plant", "ideal"]) == 0
    return out


TASK_CASES = [
    pytest.param("planar", id="planar2-planar"),
    pytest.param("position", id="spatial3-position"),
    pytest.param("position_yaw", id="spatial4-position_yaw"),
    pytest.param("pose", id="ur5-pose", marks=[pytest.mark.slow, needs_ur5]),
]


@pytest.fixture(scope="module", params=TASK_CASES)
def task_kernels(request, tmp_path_factory):
    """Per task space: the scenario and its user kernels, generated and compiled."""
    folder = tmp_path_factory.mktemp(request.param)
    if request.param == "planar":
        scenario = DATA / "planar2_task.toml"
    elif request.param == "pose":
        scenario = _ur5_pose(folder, request.getfixturevalue("ur5_file"))
    else:
        scenario = _spatial(folder, request.param)
    return request.param, scenario, _generated(folder, scenario)


def _inputs(f, s, rng) -> list[np.ndarray]:
    """Random inputs of kernel ``f`` of unit setup ``s`` in the ranges a run feeds it:
    joints near the start, parameters +-20 % of the plant's and the estimate's, desired task
    coordinates near the path's, gains around the scenario's, the robust options on."""
    nq = s.controller_model.nq
    q = s.x0[:nq] + rng.uniform(-0.3, 0.3, nq)
    xd, xd_dot, xd_ddot = (np.array(v, float).ravel() for v in s.desired(rng.uniform(0, 3)))
    values = []
    for i in range(f.n_in()):
        name, size = f.name_in(i), f.numel_in(i)
        v = {
            "q": lambda n: q,
            "x": lambda n: np.concatenate([q, rng.uniform(-1, 1, nq)]),
            "p": lambda n: s.plant_params * rng.uniform(0.8, 1.2, n),
            "p_hat": lambda n: s.p_hat0 * rng.uniform(0.8, 1.2, n),
            "p_min": lambda n: -3 * np.abs(s.p_hat0) - 1,
            "p_max": lambda n: 3 * np.abs(s.p_hat0) + 1,
            "xd": lambda n: xd + rng.uniform(-0.01, 0.01, n),
            "xd_dot": lambda n: xd_dot + rng.uniform(-0.05, 0.05, n),
            "xd_ddot": lambda n: xd_ddot + rng.uniform(-0.05, 0.05, n),
            "gains": lambda n: s.gains * rng.uniform(0.5, 2.0, n),
            "Gamma": lambda n: s.gamma * rng.uniform(0.5, 2.0, n),
            "bound": lambda n: np.array([rng.choice([0.3, 10.0])]),  # projection on / off
            "h": lambda n: np.array([1e-3]),
            "deadzone": lambda n: rng.uniform(0, 1e-3, n),
            "static_excess": lambda n: rng.uniform(0, 0.05, n),
            "stribeck_velocity": lambda n: np.full(n, 0.02),
            "dry": lambda n: np.concatenate([fc := rng.uniform(0, 0.05, nq), 1.5 * fc,
                                           np.full(nq, 0.02)]),
            "tau": lambda n: rng.uniform(-0.5, 0.5, n),
            "friction": lambda n: rng.uniform(0, 0.05, n),
        }.get(name, lambda n: rng.uniform(-1, 1, n))(size)
        assert np.size(v) == size, (f.name(), name)
        values.append(np.asarray(v, float).reshape(-1))
    return values


@pytest.mark.slow
def test_task_space_kernels_equal_their_casadi_functions(task_kernels, rng):
    """Every kernel of the task-space scenario (model, task coordinates, plant steps, the
    controller's parts) at 20 random points: relative error <= 1e-12."""
    task, scenario, kernels = task_kernels
    setup = unit_setups(load_scenario(scenario))[0]
    assert setup.task_names and len(setup.task_names) == setup.controller_model.nq
    _, generated, _ = scenario_kernels(scenario, None, ["ideal"])
    lib = Library(kernels / "libcochlea.so")
    assert {k.name for k in generated} <= set(lib.names)
    assert any(k.role == "controller" and k.kind == "g" for k in generated)
    moved = set()
    for k in generated:
        bound = lib.kernel(k.name)
        for _ in range(20):
            args = _inputs(k.source, setup, rng)
            expected = [np.array(ca.densify(o)) for o in k.source.call(args)]
            got = bound.evaluate(*args)
            for a, e, g in zip(bound.signature.outputs, expected, got, strict=True):
                e = e.reshape(a.shape, order="F")
                scale = max(1.0, float(np.max(np.abs(e)))) if e.size else 1.0
                assert np.all(np.isfinite(g)), (k.name, a.name)
                assert np.max(np.abs(g - e), initial=0.0) <= 1e-12 * scale, (k.name, a.name)
                if np.any(g != 0):
                    moved.add(k.name)
    # Not a comparison of zeros (G is zero where gravity runs along the joint axes).
    assert {k.name for k in generated if k.role != "model"} <= moved, moved


def _assert_same_log(result, reference, tol):
    assert np.array_equal(result.time, reference.time)
    assert result.diverged == reference.diverged
    for u, r in zip(result.units, reference.units, strict=True):
        for key in FIELDS:
            np.testing.assert_allclose(getattr(u, key), getattr(r, key), rtol=tol, atol=tol,
                                       err_msg=f"{u.name}.{key}")


@pytest.mark.slow
def test_task_space_run_on_c_kernels_converges_and_equals_casadi(task_kernels):
    task, scenario, kernels = task_kernels
    sc = load_scenario(scenario)
    assert sc.space == "task" and sc.task == task and sc.controller == "g"
    setups = unit_setups(sc)
    result = simulate(sc, None, setups, kernels="c", library=kernels)
    assert result.kernels["used"] == "c", result.kernels
    reference = simulate(sc, None, setups, kernels="casadi")
    assert reference.kernels["used"] == "casadi"
    _assert_same_log(result, reference, 1e-9)
    assert not result.diverged
    e = result.units[0].tracking_error
    final, first = np.abs(e[-len(e) // 10:]).max(axis=0), np.abs(e[0])
    assert np.all(final < 0.05 * np.maximum(first, 1e-3)), (final, first)


# --------------------------------------------------------------------------------------------
# Papercuts: keep-out optional, URDF base and tool frames, excitation on a tilted base
# --------------------------------------------------------------------------------------------


def _without_keep_out(folder: Path, source: Path) -> Path:
    text = source.read_text(encoding="utf-8")
    assert "keep_out_radius_m = 0.01\n" in text
    out = folder / source.name
    out.write_text(text.replace("keep_out_radius_m = 0.01\n", ""), encoding="utf-8")
    return out


@pytest.mark.slow
def test_a_description_without_keep_out_radius_has_no_keep_out(tmp_path):
    """``keep_out_radius_m`` is optional: absent, no keep-out circle, neither in a task-space
    run's checks and supervisor nor in an excitation."""
    from cochlea.ident import excite
    from cochlea.runtime.supervisor import build_supervisor

    description = _without_keep_out(tmp_path, PLANAR2)
    assert load_serial(description).keep_out_radius is None
    assert load_serial(PLANAR2).keep_out_radius == 0.01
    # A line through the origin at t = 2 s: refused with the 10 mm keep-out, run without one.
    scenario = tmp_path / "through.toml"
    scenario.write_text((DATA / "planar2_task.toml").read_text().replace(
        'leader = ["0.03*cos(0.5*t) m", "0.15 + 0.03*sin(0.5*t) m"]',
        'leader = ["0.0 m", "0.04 - 0.02*t m"]').replace(
        'initial_task = ["0.04 m", "0.16 m"]', 'initial_task = ["0.003 m", "0.043 m"]').replace(
        'description = "planar2_tasks.toml"', f'description = "{PLANAR2}"'))
    with pytest.raises(Exception, match="keep-out radius 10.0 mm"):
        unit_setups(load_scenario(scenario))
    (tmp_path / "planar2_task.toml").write_text(scenario.read_text().replace(
        f'description = "{PLANAR2}"', f'description = "{description}"'))
    sc = load_scenario(tmp_path / "planar2_task.toml")
    assert sc.system.keep_out_radius is None
    setups = unit_setups(sc)
    supervisor = build_supervisor(setups, sc.system.keep_out_radius,
                                  kernels="casadi")
    assert supervisor.limits.keep_out_radius is None
    result = simulate(sc, 1.0, setups, kernels="casadi")
    assert not result.diverged
    # An excitation of the arm based at the origin: no circle either way (its base is inside).
    (tmp_path / "x").mkdir()
    plain = _without_keep_out(tmp_path / "x", DATA / "planar2.toml")
    fast = excite.ExcitationOptions(period=4.0, harmonics=3, starts=1, iterations=20, periods=4)
    assert excite.design("serial", None, fast, description=plain).keep_out_distance is None


def _round_trip(tmp_path: Path, description: Path) -> Path:
    from cochlea.apps.cochlea_urdf import main

    urdf = tmp_path / "out.urdf"
    assert main(["export", str(description), "--out", str(urdf)]) == 0
    again = tmp_path / "again.toml"
    assert main(["import", str(urdf), "--out", str(again), "--motor", "XM430-W350"]) == 0
    return again


@pytest.mark.parametrize("base, tool", [
    ("base_rpy_deg = [3.0, -2.0, 80.0]", "tool_xyz_m = [0.03, 0.01, -0.02]\n"
                                          "tool_rpy_deg = [10.0, -20.0, 30.0]\n"),
    ("base_rpy_deg = [0.0, 0.0, -30.0]", "tool_xyz_m = [0.0, 0.0, 0.07]\n"),
    ("base_rpy_deg = [0.0, 45.0, 0.0]", ""),
])
def test_urdf_import_reads_the_base_rotation_and_tool_frame_export_writes(tmp_path, rng,
                                                                          base, tool):
    """export writes the base pose and the tool frame as fixed joints; import reads them back
    as base_xyz_m / base_rpy_deg (base_yaw_deg for a level base) and tool_xyz_m /
    tool_rpy_deg: the same description, the same full tool pose."""
    source = tmp_path / "tooled.toml"
    source.write_text(SPATIAL4.read_text().replace(
        "base_rpy_deg = [3.0, -2.0, 80.0]\n", f"{base}\n{tool}"), encoding="utf-8")
    a = load_serial(source).arms[0]
    again = _round_trip(tmp_path, source)
    text = again.read_text()
    b = load_serial(again).arms[0]
    np.testing.assert_allclose(b.base_xyz, a.base_xyz, atol=1e-12)
    np.testing.assert_allclose(b.base_rotation, a.base_rotation, atol=1e-12)
    assert ("base_yaw_deg" in text) == a.base_is_level
    if tool:
        np.testing.assert_allclose(b.tool_xyz, a.tool_xyz, atol=1e-12)
        assert (b.tool_rpy is None) == (a.tool_rpy is None)
        if a.tool_rpy is not None:
            np.testing.assert_allclose(rpy_matrix(b.tool_rpy), rpy_matrix(a.tool_rpy),
                                       atol=1e-12)
    else:  # spatial4's hand has length 0.05: its tool point comes back as a tool frame
        np.testing.assert_allclose(tool_offset(b), tool_offset(a), atol=1e-12)
    pa, pb = task_space(a, "pose").fk, task_space(b, "pose").fk
    for _ in range(10):
        q = rng.uniform(-1.5, 1.5, 4)
        np.testing.assert_allclose(np.array(pb(q)), np.array(pa(q)), atol=1e-12)
    # The first joint keeps its own origin (the base is not folded into it).
    np.testing.assert_allclose(b.links[0].joint.origin_xyz, a.links[0].joint.origin_xyz,
                               atol=1e-12)


def test_urdf_tip_below_the_last_joint_is_the_tool_frame(tmp_path):
    """--tip naming a frame fixed below the last moving link: its pose is the tool frame, a
    turned one written as tool_rpy_deg (tests/data/arm4.urdf: tool0, then tool_tip)."""
    from cochlea.robots.serial.urdf import import_urdf

    imported = import_urdf(DATA / "arm4.urdf", tip="tool_tip")
    arm = imported.system.arms[0]
    np.testing.assert_allclose(arm.tool_xyz, [0.0, 0.0, 0.06], atol=1e-12)
    assert arm.tool_rpy is None
    # The mount (world -> base_link: 0.1, -0.05, 0.02 m, yaw 0.5 rad) is the arm's base.
    np.testing.assert_allclose(arm.base_xyz, [0.1, -0.05, 0.02], atol=1e-12)
    assert arm.base_is_level and arm.base_yaw == pytest.approx(0.5, abs=1e-12)


def test_excitation_segments_follow_a_pitched_base(tmp_path, rng):
    """The excitation's link points (robots/serial/excitation.py) use the full base rotation:
    on a pitched and rolled base they are Pinocchio's joint origins and tool point of the
    exported URDF (3-D), and their x-y projection (2-D)."""
    import pinocchio as pin

    from cochlea.robots.serial.excitation import arm_segments
    from cochlea.robots.serial.urdf import export_urdf

    source = tmp_path / "pitched.toml"
    source.write_text(SPATIAL4.read_text().replace(
        "base_rpy_deg = [3.0, -2.0, 80.0]\n", "base_rpy_deg = [20.0, 35.0, 80.0]\n"
        "tool_xyz_m = [0.05, 0.0, 0.0]\n"), encoding="utf-8")
    system = load_serial(source)
    arm = system.arms[0]
    urdf = tmp_path / "pitched.urdf"
    urdf.write_text(export_urdf(system), encoding="utf-8")
    model = pin.buildModelFromUrdf(str(urdf))
    data = model.createData()
    tool = model.getFrameId("tool")
    three, two = arm_segments(arm, 3), arm_segments(arm, 2)
    for _ in range(10):
        q = rng.uniform(-1.5, 1.5, 4)
        pin.framesForwardKinematics(model, data, q)
        expected = np.column_stack([arm.base_xyz] + [data.oMi[i].translation
                                                     for i in range(2, model.njoints)]
                                   + [data.oMf[tool].translation])
        points = np.array(three(q))
        np.testing.assert_allclose(points, expected, atol=1e-12)
        np.testing.assert_allclose(np.array(two(q)), expected[:2], atol=1e-12)


# --------------------------------------------------------------------------------------------
# The proof matrix: the 4-DoF spatial arm on XM430-W350s (and the dynamics of both user arms)
# --------------------------------------------------------------------------------------------

SPATIAL4_JOINT = DATA / "spatial4_joint.toml"


@pytest.mark.parametrize("description", [DATA / "planar2.toml", SPATIAL4],
                         ids=["planar2", "spatial4"])
def test_user_arm_dynamics_match_pinocchio(description, rng):
    """M (CRBA), the inverse dynamics (RNEA) and G of the user arms, gravity through the
    tilted base included, against Pinocchio built from the description's numbers."""
    import pinocchio as pin

    import cochlea

    from .conftest import ev, random_state
    from .test_pinocchio_oracle import pinocchio_arm

    system = load_serial(description)
    ours = cochlea.model("serial", description=description)
    theirs = pinocchio_arm(system, system.arms[0])
    data = theirs.createData()
    gravity = 0.0
    for _ in range(50):
        q, qd, qdd = random_state(rng, ours.nq)
        M = pin.crba(theirs, data, q)
        M = np.triu(M) + np.triu(M, 1).T
        assert np.abs(ev(ours.M, q) - M).max() < 1e-10
        assert np.abs(ev(ours.inverse_dynamics, q, qd, qdd)
                      - pin.rnea(theirs, data, q, qd, qdd)).max() < 1e-10
        G = pin.computeGeneralizedGravity(theirs, data, q)
        assert np.abs(ev(ours.G, q) - G).max() < 1e-10
        gravity = max(gravity, np.abs(G).max())
    if description == SPATIAL4:  # not vacuous: the tilted base loads every joint
        assert gravity > 0.1


@pytest.mark.parametrize("scenario, motor", [(DATA / "planar2_joint.toml", "XM540-W270"),
                                             (SPATIAL4_JOINT, "XM430-W350")],
                         ids=["planar2", "spatial4"])
@pytest.mark.slow
def test_user_arm_joint_space_run_on_c_kernels(tmp_path, scenario, motor):
    """cochlea-codegen --scenario on the joint-space study: the C run converges and gives the
    CasADi run's log."""
    sc = load_scenario(scenario)
    assert {link.motor.model for link in sc.system.arms[0].links} == {motor}
    kernels = _generated(tmp_path, scenario)
    setups = unit_setups(sc)
    result = simulate(sc, None, setups, kernels="c", library=kernels)
    assert result.kernels["used"] == "c", result.kernels
    _assert_same_log(result, simulate(sc, None, setups, kernels="casadi"), 1e-9)
    assert not result.diverged
    e = result.units[0].tracking_error
    final, first = np.abs(e[-len(e) // 10:]).max(axis=0), np.abs(e[0])
    assert np.all(final < 0.05 * first), (final, first)


@pytest.mark.hil
def test_spatial4_joint_space_run_over_the_virtual_chain(tmp_path):
    """cochlea-emulator emulates spatial4's four XM430-W350s from the scenario's description;
    cochlea-run --backend dynamixel tracks the joint-space study over the pseudo-terminal."""
    log, out = tmp_path / "emulator.log", tmp_path / "hil"
    proc = subprocess.Popen([sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot",
                             "serial", "--scenario", str(SPATIAL4_JOINT), "--log", str(log)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/"), proc.stderr.read() if proc.poll() is not None else port
        assert "XM430-W350" in proc.stdout.readline()
        done = subprocess.run(RUN + ["--robot", "serial", "--space", "joint", "--scenario",
                                     str(SPATIAL4_JOINT), "--backend", "dynamixel", "--port",
                                     port, "--duration", "3", "--out", str(out),
                                     "--watchdog-misses", "300"],
                              capture_output=True, text=True, timeout=180, cwd=tmp_path)
    finally:
        proc.terminate()
        proc.communicate(timeout=20)
    assert done.returncode == 0, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stop"]["rule"] == "completed"
    assert "torque off confirmed by all 4" in summary["timing"]["bus"]["shutdown"]
    for name, tracked in summary["units"]["arm"]["tracked"].items():
        assert tracked["final_rms_error"] < 0.2 * tracked["initial_abs_error"], (name, tracked)


@pytest.mark.parametrize("arm", ["spatial4", pytest.param("ur5", marks=needs_ur5)])
@pytest.mark.slow
def test_a_small_sweep_of_a_user_arm(arm, tmp_path, monkeypatch, request):
    """Three perturbed draws of the arm's joint-space study (spatial4_joint.toml, the UR5's
    imported starter), every run to its end."""
    from cochlea.apps import cochlea_sweep
    from cochlea.sweep import results

    if arm == "spatial4":
        for f in (SPATIAL4, SPATIAL4_JOINT):
            (tmp_path / f.name).write_text(f.read_text())
        scenario = SPATIAL4_JOINT.name
    else:
        description, starter = request.getfixturevalue("ur5_joint")
        scenario = str(starter)
    spec = tmp_path / "spec.toml"
    spec.write_text(f'''format = "cochlea-sweep/1"
scenario = "{scenario}"
samples = 3
seed = 11
duration_s = 0.4

[perturb]
mass_scale = {{uniform = [0.8, 1.2]}}
payload_kg = {{uniform = [0.0, 0.05]}}
''')
    monkeypatch.chdir(ROOT)
    out = tmp_path / "out"
    assert cochlea_sweep.main([str(spec), "--out", str(out), "--workers", "1",
                               "--progress", "off"]) == 0
    rows = results.read(out).to_pylist()
    assert len(rows) == 3
    assert all(r["stop_rule"] == "none" and not r["diverged"] for r in rows), rows


#: The perturbed plant of spatial4's identification: masses +-20 %, a 30 g payload, viscous
#: friction the description does not have, the drives' current quantisation, encoder and
#: velocity grids and one period of delay (tests/test_user_robot_tools.py's for planar2).
SPATIAL4_PLANT = """[plant]
plant = "ideal"
mass_scale = [1.2, 0.85, 1.1, 0.9]
payload_kg = 0.03
viscous_friction_SI = [0.02, 0.03, 0.015, 0.01]
current_quantisation = true
position_encoder = true
velocity_register = true
delay_periods = 1
"""


@pytest.mark.slow
def test_spatial4_excite_then_identify_a_perturbed_plant(tmp_path):
    """cochlea-excite --description on spatial4 (gravity through its tilted base), the
    excitation run on a perturbed plant, cochlea-identify predicting held-out torques
    within 5 %."""
    from cochlea.apps import cochlea_excite, cochlea_identify

    # The friction the model identifies is the friction the description declares: without a
    # viscous_friction_Nms_rad the regressor has no Fv column, and the plant's unmodelled
    # friction (larger than the light turret's and hand's inertial torques) leaves 22 % and
    # 72 % held-out NRMS there. A user declares an estimate, as planar2.toml does.
    description = tmp_path / "spatial4.toml"
    description.write_text(SPATIAL4.read_text().replace(
        "  torque_limit_Nm = 4.0\n",
        "  torque_limit_Nm = 4.0\n  viscous_friction_Nms_rad = 0.01\n"))
    (tmp_path / SPATIAL4_JOINT.name).write_text(SPATIAL4_JOINT.read_text())
    out = tmp_path / "excite.toml"
    assert cochlea_excite.main(["--robot", "serial", "--description", str(description),
                                "--scenario", str(tmp_path / SPATIAL4_JOINT.name),
                                "--out", str(out),
                                "--period", "4", "--harmonics", "3", "--starts", "2",
                                "--iterations", "60"]) == 0
    text = out.read_text()
    perturbed = tmp_path / "perturbed.toml"
    perturbed.write_text(text[:text.index("[plant]")] + SPATIAL4_PLANT)
    subprocess.run(RUN + ["--robot", "serial", "--space", "joint", "--scenario", str(perturbed),
                          "--out", str(tmp_path / "run"), "--realtime", "off"],
                   check=True, capture_output=True, cwd=ROOT)
    report = tmp_path / "ident.json"
    assert cochlea_identify.main([str(tmp_path / "run"), "--robot", "serial", "--description",
                                  str(description), "--out", str(report), "--min-speed", "0",
                                  "--no-figures"]) == 0
    doc = json.loads(report.read_text())
    assert max(doc["prediction_nrms_percent"]["wls"]) < 5.0, doc["prediction_nrms_percent"]
    from cochlea.robots import robot

    serial = robot("serial")
    m = serial.model(serial.load(description), "arm", "base", actuators="all")
    fv = [p["wls"] for name, p in zip(m.parameters.meanings, doc["parameters"])
          if name.endswith(".Fv")]
    assert fv == pytest.approx([0.02, 0.03, 0.015, 0.01], rel=0.05)


# --------------------------------------------------------------------------------------------
# The proof matrix: the 6-DoF UR5 imported from example-robot-data (slow: its kernels and
# excitation take minutes). Gravity off: its imported XM540s could not hold it.
# --------------------------------------------------------------------------------------------

#: UR5's perturbed plant (as spatial4's, with a payload sized for it).
UR5_PLANT = """[plant]
plant = "ideal"
mass_scale = [1.2, 0.85, 1.1, 0.9, 1.15, 0.9]
payload_kg = 0.2
viscous_friction_SI = [0.02, 0.03, 0.015, 0.01, 0.012, 0.008]
current_quantisation = true
position_encoder = true
velocity_register = true
delay_periods = 1
"""


@pytest.fixture(scope="module")
def ur5_joint(tmp_path_factory) -> tuple[Path, Path]:
    """``cochlea-urdf import`` of the UR5 with its starter scenario; gravity off and a viscous
    friction estimate declared per joint (the URDF's are zero, so none is imported)."""
    from cochlea.apps.cochlea_urdf import main

    folder = tmp_path_factory.mktemp("ur5_joint")
    description, starter = folder / "ur5.toml", folder / "starter.toml"
    assert main(["import", str(UR5), "--out", str(description), "--scenario-out",
                 str(starter)]) == 0
    text = description.read_text().replace("gravity_m_s2 = [0.0, 0.0, -9.81]",
                                           "gravity_m_s2 = [0.0, 0.0, 0.0]")
    description.write_text(text.replace("  torque_limit_Nm = ",
                                        "  viscous_friction_Nms_rad = 0.01\n  torque_limit_Nm = "))
    assert load_serial(description).arms[0].links[5].joint.actuator.viscous == 0.01
    return description, starter


@pytest.mark.slow
@needs_ur5
def test_ur5_joint_space_run_on_c_kernels(ur5_joint, tmp_path):
    _, starter = ur5_joint
    sc = load_scenario(starter)
    kernels = _generated(tmp_path, starter)
    setups = unit_setups(sc)
    result = simulate(sc, 3.0, setups, kernels="c", library=kernels)
    assert result.kernels["used"] == "c", result.kernels
    _assert_same_log(result, simulate(sc, 3.0, setups, kernels="casadi"), 1e-9)
    assert not result.diverged
    e = result.units[0].tracking_error
    final, first = np.abs(e[-len(e) // 10:]).max(axis=0), np.abs(e[0])
    assert np.all(final < 0.05 * first), (final, first)


@pytest.mark.slow
@needs_ur5
def test_ur5_excite_then_identify_a_perturbed_plant(ur5_joint, tmp_path):
    from cochlea.apps import cochlea_excite, cochlea_identify

    description, starter = ur5_joint
    out = tmp_path / "excite.toml"
    assert cochlea_excite.main(["--robot", "serial", "--description", str(description),
                                "--scenario", str(starter), "--out", str(out),
                                "--period", "4", "--harmonics", "3", "--starts", "2",
                                "--iterations", "60"]) == 0
    text = out.read_text()
    perturbed = tmp_path / "perturbed.toml"
    perturbed.write_text(text[:text.index("[plant]")] + UR5_PLANT)
    subprocess.run(RUN + ["--robot", "serial", "--space", "joint", "--scenario", str(perturbed),
                          "--out", str(tmp_path / "run"), "--realtime", "off"],
                   check=True, capture_output=True, cwd=ROOT)
    report = tmp_path / "ident.json"
    assert cochlea_identify.main([str(tmp_path / "run"), "--robot", "serial", "--description",
                                  str(description), "--out", str(report), "--min-speed", "0",
                                  "--no-figures"]) == 0
    doc = json.loads(report.read_text())
    assert max(doc["prediction_nrms_percent"]["wls"]) < 5.0, doc["prediction_nrms_percent"]


@pytest.mark.hil
@needs_ur5
def test_ur5_joint_space_run_over_the_virtual_chain(ur5_joint, tmp_path):
    """Six emulated XM540-W270s from the imported description; the starter tracked over the
    pseudo-terminal."""
    _, starter = ur5_joint
    log, out = tmp_path / "emulator.log", tmp_path / "hil"
    proc = subprocess.Popen([sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot",
                             "serial", "--scenario", str(starter), "--log", str(log)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/"), proc.stderr.read() if proc.poll() is not None else port
        assert "XM540-W270" in proc.stdout.readline()
        done = subprocess.run(RUN + ["--robot", "serial", "--space", "joint", "--scenario",
                                     str(starter), "--backend", "dynamixel", "--port", port,
                                     "--duration", "3", "--out", str(out),
                                     "--watchdog-misses", "300"],
                              capture_output=True, text=True, timeout=180, cwd=tmp_path)
    finally:
        proc.terminate()
        proc.communicate(timeout=20)
    assert done.returncode == 0, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stop"]["rule"] == "completed"
    assert "torque off confirmed by all 6" in summary["timing"]["bus"]["shutdown"]
    for name, tracked in summary["units"]["arm"]["tracked"].items():
        assert tracked["final_rms_error"] < 0.2 * tracked["initial_abs_error"], (name, tracked)
