"""``[control] mirror = "measured"`` (issue 25 item 2): the serial system's follower (arm 2)
mirrors its leader's *measured* pose, period by period, in every path ``cochlea-run`` uses --
the CasADi reference, the C kernels (the C driver and the Python loop over them) and the
real-time loop -- with its safe stop when that pose leaves arm 2's reach, and its refusals
where a path cannot run it (docs/controllers.md, "The dual-arm rule")."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys

import casadi as ca
import numpy as np
import pytest

from cochlea.apps import cochlea_codegen
from cochlea.errors import EXIT_USER_ERROR, CochleaError
from cochlea.robots.adapter import desired_function
from cochlea.robots.serial.ik import ik
from cochlea.runtime import STOP_CODES, RealTimeLoop, SimBackend, build_supervisor, verdict
from cochlea.sim import compiled as csim
from cochlea.sim import load_scenario, simulate, unit_setups
from cochlea.sim.embedded import embedded_units
from cochlea.sim.scenario import resolve

STUDIES = {"serial_joint": "e", "serial_task": "g"}
#: Measurements that are not the state. Joint space: 1-3 periods old, Gaussian noise, on the
#: encoder (a count of noise) and velocity-register grids. Task space: on the grids only: with
#: any delay the thesis's rigid-arm task study throws its leader's joint 3 past 500 rad/s in
#: either mode (docs/controllers.md), where rounding differences grow past any tolerance.
NOISY = ("delay_periods = 1\ndelay_jitter_periods = 2\nnoise_q_std_SI = 1e-4\n"
         "noise_qd_std_SI = 1e-3\nseed = 7\nposition_encoder = true\nvelocity_register = true\n"
         "encoder_noise_counts = 1")
GRIDS = "position_encoder = true\nvelocity_register = true\nencoder_noise_counts = 1\nseed = 7"
MEASURING = {"serial_joint": NOISY, "serial_task": GRIDS}
FLIP = np.array([-1.0, -1.0, 1.0])  # the dual-arm rule's linear part on (x, y, phi)


def variant(tmp_path, study: str, mirror: str = "measured", plant: str = "",
            arm1: str = "", duration: float | None = None, name: str | None = None):
    """The shipped study with ``mirror`` (and a ``[plant]`` table, lines added to arm 1's
    unit, another duration), written in ``tmp_path`` and loaded."""
    text = resolve(study).read_text()
    text, count = re.subn(r'^mirror = "desired".*$', f'mirror = "{mirror}"', text, flags=re.M)
    assert count == 1
    if arm1:
        text = text.replace('name = "arm1"\n', f'name = "arm1"\n{arm1}\n', 1)
    if duration is not None:
        text = re.sub(r"^duration_s = .*$", f"duration_s = {duration}", text, flags=re.M)
    if plant:
        text += f"\n[plant]\n{plant}\n"
    path = tmp_path / f"{name or study}_{mirror}.toml"
    path.write_text(text)
    return load_scenario(path)


def wrap(a):
    return np.arctan2(np.sin(a), np.cos(a))


def rule_of(lead_log, q, qd):
    """The dual-arm rule on the tool pose and velocity of arm 1's joints ``q``, ``qd`` (rows):
    computed here from arm 1's forward kinematics and Jacobian, independently of the code."""
    m = lead_log.setup.controller_model
    rows = len(q)
    pose = np.array(m.fk_world.map(rows)(q.T)).T
    jq = ca.SX.sym("q", 3)
    jqd = ca.SX.sym("qd", 3)
    velocity = ca.Function("v", [jq, jqd], [m.J_world(jq) @ jqd]).map(rows)
    tool_velocity = np.array(velocity(q.T, qd.T)).T
    mirrored = pose * FLIP
    mirrored[:, 2] += np.pi
    return mirrored, tool_velocity * FLIP


def mirror_error(result) -> np.ndarray:
    """Per period, how far the two tools are from mirror images (m): ``|p1 + p2|``."""
    p1, p2 = result.units[0].true_x, result.units[1].true_x
    return np.hypot(p1[:, 0] + p2[:, 0], p1[:, 1] + p2[:, 1])


# --------------------------------------------------------------------------------------------
# (1) the follower's desired is the rule on the leader's measured pose, period by period
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("study", STUDIES)
@pytest.mark.slow
def test_the_follower_desired_is_the_rule_on_the_leaders_measured_pose(tmp_path, study):
    """Measured through a jittering delay, noise and the grids (task space: the grids): the
    leader's measured state is not its true one, and the follower's logged desired pose (task
    space; joint space: the tool pose of its desired joints) and velocity are the rule on the
    measured one, to 1e-12."""
    sc = variant(tmp_path, study, plant=MEASURING[study])
    result = simulate(sc, 2.0, kernels="casadi")
    assert result.mirror_stop is None and len(result.time) == 2000
    lead, follower = result.units
    pose, velocity = rule_of(lead, lead.q, lead.qd)
    if sc.space == "task":
        got, got_velocity = follower.desired, follower.desired_dot
    else:  # through arm 2's forward kinematics and Jacobian
        m2 = follower.setup.controller_model
        got = np.array(m2.fk_world.map(len(pose))(follower.desired.T)).T
        q, qd = ca.SX.sym("q", 3), ca.SX.sym("qd", 3)
        tool = ca.Function("v", [q, qd], [m2.J_world(q) @ qd]).map(len(pose))
        got_velocity = np.array(tool(follower.desired.T, follower.desired_dot.T)).T
    np.testing.assert_allclose(got[:, :2], pose[:, :2], rtol=0, atol=1e-12)
    assert np.abs(wrap(got[:, 2] - pose[:, 2])).max() < 1e-12
    np.testing.assert_allclose(got_velocity, velocity, rtol=0, atol=1e-10)
    # What the rule saw is the measurement: on the true state it would be another pose...
    true_pose, _ = rule_of(lead, lead.true_q, lead.true_qd)
    assert np.abs(true_pose[:, :2] - got[:, :2]).max() > 1e-5
    # ... and on the leader's desired pose (mirror = "desired") another path again.
    nominal = simulate(variant(tmp_path, study, mirror="desired"), 2.0, kernels="casadi")
    assert np.abs(nominal.units[1].desired - follower.desired).max() > 1e-3
    # The leader runs as it always did: the mode changes only the follower.
    np.testing.assert_array_equal(nominal.units[0].desired, lead.desired)


@pytest.mark.slow
def test_the_startup_ramp_blends_from_arm2s_start_onto_the_rule(tmp_path):
    """``startup_ramp_s = 1``: arm 2's desired starts at its initial joints at rest and is the
    rule on arm 1's measured pose from 1 s on, as a nominal path is blended."""
    sc = variant(tmp_path, "serial_joint")
    sc.path.write_text(sc.path.read_text().replace("[control]\n",
                                                   "[control]\nstartup_ramp_s = 1.0\n", 1))
    sc = load_scenario(sc.path)
    result = simulate(sc, 1.5, kernels="casadi")
    lead, follower = result.units
    np.testing.assert_allclose(follower.desired[0], follower.setup.x0[:3], rtol=0, atol=1e-15)
    np.testing.assert_allclose(follower.desired_dot[0], 0.0, rtol=0, atol=1e-15)
    after = slice(1001, None)
    pose, velocity = rule_of(lead, lead.q[after], lead.qd[after])
    m2 = follower.setup.controller_model
    got = np.array(m2.fk_world.map(len(pose))(follower.desired[after].T)).T
    np.testing.assert_allclose(got[:, :2], pose[:, :2], rtol=0, atol=1e-12)
    during = np.abs(np.diff(follower.desired[:1001], axis=0)).max()
    assert during < 2e-3  # no jump while it blends (rad per period, on the ideal plant)
    got_c = csim.simulate_compiled(sc, 1.5, loop="c")
    np.testing.assert_allclose(got_c.units[1].desired, follower.desired, rtol=0, atol=1e-12)


# --------------------------------------------------------------------------------------------
# (2) a leader exactly on its path gives mirror = "desired"
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("study", STUDIES)
def test_a_leader_on_its_path_gives_the_desired_modes_path(tmp_path, study):
    """The rule on the leader's desired state (its desired joints and velocities; in task space
    through arm 1's inverse kinematics) gives the nominal follower path, its velocity and
    acceleration, to 1e-9: the two modes agree wherever the leader tracks exactly."""
    sc = variant(tmp_path, study)
    setups = unit_setups(sc)
    lead, follower = setups
    m1 = lead.controller_model
    follow = follower.follow
    assert follow is not None and follow.leader == 0 and lead.follow is None
    q_ref = lead.x0[:3]
    for t in np.linspace(0.0, sc.duration, 9):
        x, x_dot, _ = (np.array(v, float).ravel() for v in lead.desired(t))
        if sc.space == "task":
            q, _, _ = ik(sc.system.arms[0], x, q_ref)
            qd = np.linalg.solve(np.array(m1.J_world(q), float), x_dot)
            q_ref = q
        else:
            q, qd = x, x_dot
        out = follow.step(np.concatenate([q, qd]), follow.timed(t))
        want = follower.desired(t)
        for got, expected in zip(out[:3], want):
            np.testing.assert_allclose(np.array(got, float).ravel(),
                                       np.array(ca.densify(expected), float).ravel(),
                                       rtol=0, atol=1e-9)
        assert float(out[3]) > 0.0  # within reach, with the margin


@pytest.mark.parametrize("study", STUDIES)
@pytest.mark.slow
def test_on_an_ideal_plant_the_measured_mode_follows_the_desired_one(tmp_path, study):
    """Ideal plant, no delay, the leader started on its path with its nominal estimate: the
    follower's desired differs from mirror = "desired"'s by no more than the leader's own
    tracking error (the rule is an isometry in the plane) -- micrometres here."""
    start = {"serial_joint": 'initial_joint = ["78.133 deg", "63.938 deg", "113.726 deg"]\n'
                             'initial_velocity = ["-0.0815 deg", "0.0605 deg", "0.019 deg"]',
             "serial_task": 'initial_task = ["0.03*cos(0.0038) m", "0.03*sin(0.0038) m", '
                            '"-90 deg"]'}[study]
    runs = {}
    for mirror in ("desired", "measured"):
        path = resolve(study).read_text()
        path = re.sub(r'^mirror = "desired".*$', f'mirror = "{mirror}"', path, flags=re.M)
        path = path.replace('initial_estimate = "zero"', 'initial_estimate = "nominal"')
        path = re.sub(r'(name = "arm1"\n)initial_(joint|task) = \[[^\]]*\]\n',
                      lambda m: m.group(1) + start + "\n", path)
        file = tmp_path / f"on_path_{mirror}.toml"
        file.write_text(path)
        runs[mirror] = simulate(load_scenario(file), 3.0, kernels="c")
    a, b = runs["desired"], runs["measured"]
    travel = np.ptp(a.units[0].true_x[:, :2], axis=0).max()
    difference = np.abs(b.units[1].desired - a.units[1].desired)
    leader = np.abs(b.units[0].measured_tracking_error).max()
    assert leader < 1e-4 and travel > 0.002  # on its path, and really moving
    if study == "serial_task":  # the rule is an isometry: the difference is the leader's error
        e = b.units[0].measured_tracking_error
        np.testing.assert_allclose(np.hypot(*difference[:, :2].T), np.hypot(*e[:, :2].T),
                                   rtol=0, atol=1e-12)
    assert difference.max() < 10 * leader + 1e-9


# --------------------------------------------------------------------------------------------
# (3) a disturbed leader: the arms stay mirrored closer
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("study", STUDIES)
@pytest.mark.slow
def test_a_disturbed_leader_keeps_the_tools_mirrored_closer(tmp_path, study):
    """Arm 1's plant three times as heavy (arm 2's as described): the leader lags its path;
    following its measured pose, arm 2 keeps the tools mirror images several times closer
    from 4 s on (measured: e 7.2e-6 m against 5.3e-5 m RMS, g 1.7e-5 m against 8.0e-5 m)."""
    rms = {}
    for mirror in ("desired", "measured"):
        sc = variant(tmp_path, study, mirror=mirror)
        setups = unit_setups(sc)
        setups[0] = dataclasses.replace(setups[0], plant_params=3.0 * setups[0].plant_params)
        result = simulate(sc, 10.0, setups, kernels="c")
        assert result.kernels["used"] == "c" and len(result.time) == 10_000
        rms[mirror] = float(np.sqrt(np.mean(mirror_error(result)[4000:] ** 2)))
        lead_lag = np.hypot(*result.units[0].true_tracking_error[4000:, :2].T).max()
    assert lead_lag > 1e-4  # the disturbance is real: the leader is off its path
    assert rms["measured"] < 0.4 * rms["desired"], rms


# --------------------------------------------------------------------------------------------
# (4) the C kernels and the real-time loop give the reference's log
# --------------------------------------------------------------------------------------------

FIELDS = ("q", "qd", "desired", "desired_dot", "errors", "tau", "p_hat", "true_q", "true_qd")


@pytest.mark.parametrize("loop", csim.LOOPS)
@pytest.mark.parametrize("study", STUDIES)
@pytest.mark.slow
def test_the_c_kernels_give_the_reference_log(tmp_path, study, loop):
    """Measured through a jittering delay, Gaussian and encoder noise on the grids (task space:
    the grids): the C driver and the Python loop over the kernels log what the CasADi reference
    does, to 1e-10 (the follower's desired samples included); so does the realistic (geared)
    study."""
    for plant, name in ((MEASURING[study], "measuring"), (None, "realistic")):
        if plant is None:
            sc = variant(tmp_path, f"{study}_realistic", name=f"{study}_realistic")
        else:
            sc = variant(tmp_path, study, plant=plant, name=name)
        setups = unit_setups(sc)
        reference = simulate(sc, 0.5, setups, kernels="casadi")
        got = csim.simulate_compiled(sc, 0.5, setups, loop=loop)
        assert got.kernels["used"] == "c"
        assert np.array_equal(got.time, reference.time)
        for a, b in zip(got.units, reference.units):
            for key in FIELDS:
                np.testing.assert_allclose(getattr(a, key), getattr(b, key), rtol=1e-10,
                                           atol=1e-10, err_msg=f"{name} {a.name}.{key}")


@pytest.mark.parametrize("study", STUDIES)
@pytest.mark.slow
def test_the_real_time_loop_gives_the_as_fast_log(tmp_path, study):
    """The loop (back to back, on the sim backend) overwrites the follower's desired row from
    each fresh read: it commands, estimates and logs what the as-fast run does; the report's
    desired is the one the period used. Joint space with a jittering delay and noise; the
    task study on its ideal plant (with any delay its leader breaks the velocity limit)."""
    sc = variant(tmp_path, study, plant=NOISY if study == "serial_joint" else "")
    setups = unit_setups(sc)
    periods = 400
    backend = SimBackend(setups, sc.period, sc.plant_substeps, plant=sc.plant, steps=periods)
    loop = RealTimeLoop(setups, backend, build_supervisor(setups, None), sc.period, periods,
                        realtime=False)
    assert loop.run().rule == "completed"
    looped = loop.result(sc)
    fast = simulate(sc, periods * sc.period, setups)
    for a, b in zip(fast.units, looped.units):
        for key in ("tau", "errors", "p_hat", "desired", "desired_dot", "q", "qd"):
            np.testing.assert_allclose(getattr(b, key), getattr(a, key), rtol=0, atol=1e-12,
                                       err_msg=f"{a.name}.{key}")
    # Decimated (the figures' read) the same rows.
    every = loop.chunk_result(sc, loop.rows_source(), 0, periods, 7)
    np.testing.assert_allclose(every.units[1].desired, fast.units[1].desired[::7], rtol=0,
                               atol=1e-12)


# --------------------------------------------------------------------------------------------
# (5) refusals, one line each
# --------------------------------------------------------------------------------------------


def test_the_shipped_studies_keep_mirroring_the_desired_pose():
    for name in ("serial_joint", "serial_task", "serial_joint_realistic",
                 "serial_task_realistic"):
        assert load_scenario(name).mirror == "desired"


def test_a_robot_without_the_rule_refuses_it(tmp_path):
    text = resolve("parallel_task").read_text().replace("[control]\n",
                                                        '[control]\nmirror = "measured"\n', 1)
    (tmp_path / "p.toml").write_text(text)
    with pytest.raises(CochleaError, match="mirror") as info:
        load_scenario(tmp_path / "p.toml")
    assert "\n" not in str(info.value) and "desired" in str(info.value)


def test_a_task_without_the_closed_form_refuses_it(tmp_path):
    sc = variant(tmp_path, "serial_task")
    text = sc.path.read_text().replace("[control]\n", '[control]\ntask = "planar"\n', 1)
    text = re.sub(r'(initial_task = \["[^"]*", "[^"]*"), "[^"]*"\]', r"\1]", text)
    text = re.sub(r'leader = \[("[^"]*"), ("[^"]*"), "[^"]*"\]', r"leader = [\1, \2]", text)
    text = re.sub(r"(G_g|K_c) = \[([^,\]]*), ([^,\]]*), [^\]]*\]", r"\1 = [\2, \3]", text)
    (tmp_path / "planar.toml").write_text(text)
    with pytest.raises(CochleaError, match='mirror = "measured" needs the closed-form') as info:
        unit_setups(load_scenario(tmp_path / "planar.toml"))
    assert "\n" not in str(info.value)


def test_a_leader_start_whose_mirror_arm2_cannot_reach_is_refused(tmp_path, capsys):
    """Arm 1 turned 45 deg at joint 1: the mirror of its tool lies beyond arm 2's reach at
    t = 0; cochlea-run refuses before anything moves (exit 2, one line)."""
    sc = variant(tmp_path, "serial_joint", arm1="")
    text = sc.path.read_text().replace('initial_joint = ["73 deg"', 'initial_joint = ["118 deg"',
                                       1)
    sc.path.write_text(text)
    with pytest.raises(CochleaError, match="mirror of arm1's initial pose"):
        unit_setups(load_scenario(sc.path))
    from cochlea.apps import cochlea_run

    code = cochlea_run.main(["--robot", "serial", "--space", "joint", "--scenario",
                             str(sc.path), "--realtime", "off", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == EXIT_USER_ERROR and len(err) == 1 and "arm2" in err[0]
    assert not (tmp_path / "run").exists()


def test_the_embedded_program_and_the_all_c_simulation_refuse_it(tmp_path, capsys):
    sc = variant(tmp_path, "serial_joint")
    with pytest.raises(CochleaError, match="not supported by the embedded program"):
        embedded_units(sc)
    out = tmp_path / "kernels"
    code = cochlea_codegen.main(["--scenario", str(sc.path), "--out", str(out), "--embedded",
                                 "--no-build"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == EXIT_USER_ERROR and len(err) == 1
    assert 'mirror = "measured" is not supported' in err[0] and not out.exists()


# --------------------------------------------------------------------------------------------
# (6) the safe stop: a leader pushed where arm 2 cannot follow
# --------------------------------------------------------------------------------------------

#: Arm 1 turned at joint 1 by 10 deg/s, its own path (joint space): its tool's mirror leaves
#: arm 2's reach at 3.576 s, arm 2 still below 3 rad/s (its velocity limit is 6).
PUSH = 'desired_joint = ["73 + 10*min(t, 6) deg", "83 deg", "110 deg"]'


def pushed(tmp_path):
    return variant(tmp_path, "serial_joint", arm1=PUSH, duration=6.0, name="pushed")


def test_the_stop_line_names_the_arm_and_the_measured_pose(tmp_path):
    sc = pushed(tmp_path)
    setups = unit_setups(sc)  # the nominal path (arm 1's [desired] leader, mirrored) passes
    follow = setups[1].follow
    x_lead = np.radians([115.0, 83.0, 110.0, 0.0, 0.0, 0.0])
    outputs = [np.array(v, float).ravel() for v in follow.step(x_lead, follow.timed(1.0))]
    assert not follow.ok(outputs)
    line = follow.failure(7, 0.007, x_lead, outputs).detail
    assert "\n" not in line and line.startswith("arm2's desired pose")
    assert "arm1's measured pose (q = [115.00, 83.00, 110.00] deg)" in line
    assert "within 10 deg of straight or folded" in line
    nan = [np.full(3, np.nan), np.zeros(3), np.zeros(3), np.array([0.5])]
    assert not follow.ok(nan) and "is not finite" in follow.failure(0, 0.0, x_lead, nan).detail


@pytest.mark.slow
def test_a_pushed_leader_stops_every_path_at_the_same_period(tmp_path):
    """Joint space (e): the reference, both C loops and the real-time loop stop at the period
    whose rule's pose is out of arm 2's reach: the as-fast logs end just before it, the loop
    commands zero effort and disables the drives there; before it every rule was kept."""
    sc = pushed(tmp_path)
    setups = unit_setups(sc)
    reference = simulate(sc, 6.0, setups, kernels="casadi")
    stop = reference.mirror_stop
    assert stop is not None and stop["rule"] == "mirror-reach"
    assert abs(stop["time_s"] - 3.576) < 1e-9 and len(reference.time) == 3576
    assert "arm2" in stop["detail"] and "arm1's measured pose" in stop["detail"]
    rule = verdict(reference, build_supervisor(setups, sc.system.keep_out_radius))
    assert rule["rule"] == "mirror-reach" and rule["exit_code"] == STOP_CODES["mirror-reach"]
    assert np.isfinite(reference.units[1].desired).all()
    assert np.abs(reference.units[1].qd).max() < 3.0  # arm 2 was never near its speed limit
    for loop in csim.LOOPS:
        got = csim.simulate_compiled(sc, 6.0, setups, loop=loop)
        assert got.mirror_stop == stop and np.array_equal(got.time, reference.time)
        np.testing.assert_allclose(got.units[1].tau, reference.units[1].tau, rtol=1e-10,
                                   atol=1e-10)

    class Recording(SimBackend):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.written = []

        def write(self, tau):
            self.written.append(tau.copy())
            return super().write(tau)

        def disable(self):
            self.written.append("disabled")
            super().disable()

    periods = 4000
    backend = Recording(setups, sc.period, sc.plant_substeps, plant=sc.plant, steps=periods)
    loop = RealTimeLoop(setups, backend, build_supervisor(setups, sc.system.keep_out_radius),
                        sc.period, periods, realtime=False)
    halt = loop.run()
    assert (halt.rule, halt.code) == ("mirror-reach", 19)
    assert abs(halt.time - stop["time_s"]) < 1e-12 and halt.detail == stop["detail"]
    assert loop.rows == 3577  # the stop's own row, its commands NaN: never written
    assert len(backend.written) == 3576 + 2  # every period before, then zero effort, drives off
    assert not backend.written[-2].any() and backend.written[-1] == "disabled"
    looped = loop.result(sc)
    assert np.isnan(looped.units[1].desired[-1]).all() and np.isnan(looped.units[0].tau[-1]).all()
    np.testing.assert_allclose(looped.units[1].desired[:-1], reference.units[1].desired,
                               rtol=0, atol=1e-12)


@pytest.mark.slow
def test_cochlea_run_reports_the_stop(tmp_path):
    """``cochlea-run --realtime off``: exit 19, one line naming the rule and the arm, the log
    up to there, summary.json with the mode and the verdict."""
    sc = pushed(tmp_path)
    out = tmp_path / "run"
    result = subprocess.run(
        [sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial", "--space",
         "joint", "--scenario", str(sc.path), "--realtime", "off", "--out", str(out)],
        capture_output=True, text=True)
    assert result.returncode == STOP_CODES["mirror-reach"] == 19, result.stderr
    assert "Traceback" not in result.stderr
    last = result.stderr.strip().splitlines()[-1]
    assert "stopped by rule mirror-reach at t = 3.576 s: arm2's desired pose" in last
    assert "the as-fast run ended there too" in last
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mirror"] == "measured" and summary["periods"] == 3576
    assert summary["supervisor"]["rule"] == "mirror-reach" and not summary["converged"]


@pytest.mark.slow
def test_a_task_space_leader_pushed_away_stops_the_run(tmp_path):
    """Task space (g): arm 1's tool taken along a line to a pose whose mirror arm 2 cannot
    reach (its setup's desired replaced, the follower's checked path left as it was): the
    safe stop, on the C kernels as in the reference."""
    sc = variant(tmp_path, "serial_task")
    setups = unit_setups(sc)
    lead = setups[0]
    start = np.array(lead.desired(0.0)[0], float).ravel()
    m = lead.controller_model
    target = np.array(m.fk_world(lead.x0[:3] + np.radians([45.0, 0.0, 0.0])), float).ravel()
    target[2] += 2 * np.pi * np.round((start[2] - target[2]) / (2 * np.pi))
    t = ca.SX.sym("t")
    path = ca.DM(start) + ca.DM(target - start) * ca.fmin(t / 6.0, 1.0)
    setups[0] = dataclasses.replace(lead, desired=desired_function("arm1", path, t))
    reference = simulate(sc, 6.0, setups, kernels="casadi")
    got = simulate(sc, 6.0, setups, kernels="c")
    assert reference.mirror_stop is not None and got.mirror_stop == reference.mirror_stop
    assert 4.5 < reference.mirror_stop["time_s"] < 5.5
    rule = verdict(got, build_supervisor(setups, sc.system.keep_out_radius))
    assert rule["rule"] == "mirror-reach"


@pytest.mark.slow
def test_a_sweep_sample_counts_the_stop(tmp_path):
    """``cochlea-sweep`` runs its samples through ``simulate()``: a pushed leader's sample
    records the rule and its time, and is not a success."""
    from cochlea.apps.cochlea_sweep import evaluate

    row = evaluate(pushed(tmp_path).path.read_text())
    assert row["stop_rule"] == "mirror-reach" and abs(row["stop_time_s"] - 3.576) < 1e-9
    assert row["success"] is False
