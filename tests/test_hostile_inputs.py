"""Hostile input through ``cochlea-run``: every mistake a user can make in a file or an option
is one line on stderr naming the file, key or option, exit code 2, no traceback and no output
folder -- before anything moves (issue 13, classes 1, 2 and 7)."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest

from cochlea.apps import cochlea_run
from cochlea.errors import EXIT_USER_ERROR, CochleaError
from cochlea.resources import ROBOTS_DIR, SCENARIOS_DIR
from cochlea.sim import load_scenario, unit_setups

SERIAL_JOINT = (SCENARIOS_DIR / "serial_joint.toml").read_text()
SERIAL_TASK = (SCENARIOS_DIR / "serial_task.toml").read_text()
SERIAL_ROBOT = (ROBOTS_DIR / "serial.toml").read_text()
LEADER_1 = '"81.14 - 3.007*cos(0.632*t) - 0.129*sin(0.632*t) deg"'
FAST = ["--realtime", "off"]


@pytest.fixture
def refused(tmp_path, monkeypatch, capsys):
    """Run cochlea-run in-process in an empty folder; assert the refusal's shape and return
    its one line."""
    monkeypatch.chdir(tmp_path)

    def run(*argv, robot="serial", space="joint"):
        out = tmp_path / "out"
        try:
            code = cochlea_run.main(["--robot", robot, "--space", space, *FAST, "--out",
                                     str(out), *argv])
        except SystemExit as stop:  # the parser's own refusal (a number that is no number)
            code = stop.code
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert code == EXIT_USER_ERROR, err
        assert len(lines) == 1 and lines[0].startswith("cochlea-run: "), err
        assert "Traceback" not in err
        assert not out.exists() and not (tmp_path / "runs").exists()  # nothing created
        return lines[0]

    return run


def write(tmp_path, name, content) -> str:
    path = tmp_path / name
    (path.write_bytes if isinstance(content, bytes) else path.write_text)(content)
    return str(path)


def with_robot(tmp_path, robot_text: str, scenario_text: str = SERIAL_JOINT) -> str:
    """A scenario naming its own copy of the serial description."""
    robot = write(tmp_path, "robot.toml", robot_text)
    return write(tmp_path, "scenario.toml",
                 scenario_text.replace('format = "cochlea-scenario/1"',
                                       f'format = "cochlea-scenario/1"\ndescription = "{robot}"'))


# -- class 1: files that cannot be read as a description or a scenario ---------------------

@pytest.mark.parametrize("content, expected", [
    (("# caf\xe9\n" + SERIAL_JOINT).encode("latin-1"), "UTF-8"),
    (b"\xff\xfe\x00\x01" * 100, "UTF-8"),
    (SERIAL_JOINT + "\nx = " + "[" * 5000 + "]" * 5000 + "\n", "nested"),
    (SERIAL_JOINT + "\nx = " + "[" * 40 + "]" * 40 + "\n", "nested"),
    (SERIAL_JOINT + "\n[a" + ".b" * 3000 + "]\n", "nested"),
    ("format = \n", "valid TOML"),
    ("#" * (2 * 1024 * 1024), "KiB"),
], ids=["latin-1", "binary", "deep-list", "deep-40", "deep-tables", "syntax", "huge"])
def test_unreadable_scenario_names_the_file(refused, tmp_path, content, expected):
    path = write(tmp_path, "bad.toml", content)
    line = refused("--scenario", path)
    assert path in line and expected in line


def test_unreadable_description_names_the_description(refused, tmp_path):
    scenario = with_robot(tmp_path, "# \xe9\n" + SERIAL_ROBOT)
    (tmp_path / "robot.toml").write_bytes(("# \xe9\n" + SERIAL_ROBOT).encode("latin-1"))
    line = refused("--scenario", scenario)
    assert "robot.toml" in line and "UTF-8" in line


def test_missing_or_folder_scenario_is_called_a_scenario(refused, tmp_path):
    assert "an existing scenario file" in refused("--scenario", str(tmp_path / "nope.toml"))
    (tmp_path / "folder.toml").mkdir()
    assert "a scenario file, not a folder" in refused("--scenario",
                                                      str(tmp_path / "folder.toml"))
    missing_robot = SERIAL_JOINT.replace('format = "cochlea-scenario/1"',
                                         'format = "cochlea-scenario/1"\n'
                                         f'description = "{tmp_path / "gone.toml"}"')
    line = refused("--scenario", write(tmp_path, "s.toml", missing_robot))
    assert "gone.toml" in line and "an existing robot description file" in line


# -- class 2: trajectory formulas -------------------------------------------------------------

@pytest.mark.parametrize("formula, expected", [
    ('"1/0 + 81 deg"', "divides by zero"),
    ('"10**400 + t deg"', "overflows"),
    ('"exp(1000)*t deg"', "not a finite"),
    ('"81 + sin(t, 1) deg"', "takes 1 argument"),
    ('"atan2(t) deg"', "takes 2 arguments"),
    ('"81 + ' + "t+" * 1500 + 't deg"', "at most 2000 characters"),
    ('"81 + ' + "sin(" * 150 + "t" + ")" * 150 + ' deg"', "nested at most"),
    ('"1e400*t deg"', "not a finite"),
    ('"1/(t-t) deg"', "not a finite"),
    ('"81 + 0*t % 2 deg"', "unsupported"),
    ('"8_1 + t deg"', "without underscores"),  # Python's 8_1 is 81: a typo's tenfold value
], ids=["div0", "overflow", "exp", "arity1", "arity2", "long", "deep", "inf-literal", "t-t",
        "modulo", "underscore"])
def test_bad_formula_names_the_key(refused, tmp_path, formula, expected):
    path = write(tmp_path, "s.toml", SERIAL_JOINT.replace(LEADER_1, formula))
    line = refused("--scenario", path)
    assert path in line and "desired.leader[0]" in line and expected in line


@pytest.mark.parametrize("formula, when", [
    ('"81 + 10*sqrt(t - 0.5) deg"', "0"),  # NaN before t = 0.5
    ('"81 + 1/(t - 0.25) deg"', "0.25"),  # inf exactly at a period
    ('"81 + exp(100*t) deg"', "7.09"),  # overflows after about 7.1 s
    ('"81 + 10*sqrt(t) deg"', "0"),  # finite, but its velocity is infinite at t = 0
], ids=["nan", "pole", "overflow-later", "velocity"])
def test_formula_non_finite_during_the_run_is_refused_with_the_time(refused, tmp_path,
                                                                   formula, when):
    path = write(tmp_path, "s.toml", SERIAL_JOINT.replace(LEADER_1, formula))
    line = refused("--scenario", path)
    assert "desired.leader[0]" in line and f"t = {when}" in line and "finite" in line


def test_definitions_cannot_shadow_t_or_functions(refused, tmp_path):
    for name in ("t", "sin", "pi", "a b"):
        text = SERIAL_TASK.replace('define = { a1 =', f'define = {{ "{name}" = "1", a1 =')
        line = refused("--scenario", write(tmp_path, "s.toml", text), space="task")
        assert "desired.define" in line


# -- class 3: absurd but finite values --------------------------------------------------------

@pytest.mark.parametrize("old, new, key", [
    ("gravity_m_s2 = [0.0, 0.0, -9.81]", "gravity_m_s2 = [0.0, 0.0, -1e300]",
     "system.gravity_m_s2"),
    ("com_m = [0.0525, 0.0, 0.0]", "com_m = [1e200, 0.0, 0.0]", "arm[0].link[0].com_m"),
    ("mass_kg = 0.09518", "mass_kg = 1e30", "arm[0].link[0].mass_kg"),
    ("mass_kg = 0.09518", "mass_kg = 1e-300", "arm[0].link[0].mass_kg"),
    ("length_m = 0.105", "length_m = 1e100", "arm[0].link[0].length_m"),
    ("length_m = 0.105", "length_m = -0.1", "arm[0].link[0].length_m"),
    ("inertia_com_kgm2 = [1.18975e-06, 8.7446625e-05, 8.7446625e-05,",
     "inertia_com_kgm2 = [1e300, 1e300, 1e300,", "arm[0].link[0].inertia_com_kgm2"),
    ("position_limits_deg = [-170.0, 170.0]", "position_limits_deg = [-1e9, 1e9]",
     "arm[0].link[0].joint.position_limits_deg"),
    ("velocity_limit_rad_s = 6.0", "velocity_limit_rad_s = 1e200",
     "arm[0].link[0].joint.velocity_limit_rad_s"),
    ("torque_limit_Nm = 2.5", "torque_limit_Nm = 1e12", "arm[0].link[0].joint.torque_limit_Nm"),
    ("armature_kgm2 = 3.4e-3", "armature_kgm2 = 1e300", "arm[0].link[0].joint.armature_kgm2"),
    ("a = 108.2,", "a = 1e-300,", "arm[0].link[0].motor.fit.a"),
    ("base_yaw_deg = 0.0", "base_yaw_deg = 1e300", "arm[0].base_yaw_deg"),
    ("keep_out_radius_m = 0.02", "keep_out_radius_m = 1e9", "system.keep_out_radius_m"),
    # a circle smaller than the arms' positioning error protects nothing (MIN_KEEP_OUT_M)
    ("keep_out_radius_m = 0.02", "keep_out_radius_m = 1e-300", "system.keep_out_radius_m"),
    ("keep_out_radius_m = 0.02", "keep_out_radius_m = 0.0009", "system.keep_out_radius_m"),
    ('name = "arm1"', 'name = "../../etc"', "arm[0].name"),
], ids=lambda v: v if isinstance(v, str) and v.count(".") < 3 and "=" not in v else None)
def test_absurd_description_value_is_refused_with_key_and_range(refused, tmp_path, old, new,
                                                                key):
    assert old in SERIAL_ROBOT
    scenario = with_robot(tmp_path, SERIAL_ROBOT.replace(old, new, 1))
    line = refused("--scenario", scenario)
    assert f"robot.toml: {key}: expected" in line


@pytest.mark.parametrize("old, new, key", [
    ("K_e = [0.2, 0.2, 0.01] }", "K_e = [1e300, 0.2, 0.01] }", "unit[0].gains.K_e"),
    ("adaptation_gain = 1.0 ", "adaptation_gain = 1e300 ", "control.adaptation_gain"),
    ("estimate_bound = 10.0 ", "estimate_bound = 1e300 ", "control.estimate_bound"),
    ("mirror = \"desired\"", "mirror = \"desired\"\n[plant]\ndelay_periods = 1000000000000",
     "plant.delay_periods"),
    ("mirror = \"desired\"", "mirror = \"desired\"\n[plant]\nseed = -1", "plant.seed"),
    ("mirror = \"desired\"", "mirror = \"desired\"\n[plant]\npayload_kg = 1e200",
     "plant.payload_kg"),
])
def test_absurd_scenario_value_is_refused_with_key_and_range(refused, tmp_path, old, new, key):
    assert old in SERIAL_JOINT
    text = SERIAL_JOINT.replace(old, new, 1)
    if "[plant]" in new:  # the [plant] table must come after the [[unit]] tables
        text = SERIAL_JOINT + new.split("\n", 1)[1].replace("[plant]", "\n[plant]")
    line = refused("--scenario", write(tmp_path, "s.toml", text))
    assert f"{key}: expected" in line


# -- class 4: initial states ------------------------------------------------------------------

@pytest.mark.parametrize("old, new, expected", [
    ('initial_joint = ["73 deg"', 'initial_joint = ["sqrt(-1) deg"', "unit[0].initial_joint"),
    ('initial_joint = ["73 deg"', 'initial_joint = ["exp(800) deg"', "unit[0].initial_joint"),
    ('initial_joint = ["73 deg"', 'initial_joint = ["175 deg"', "outside its limits"),
    ('initial_joint = ["73 deg", "83 deg", "110 deg"]',
     'initial_joint = ["73 deg", "83 deg", "110 deg"]\n'
     'initial_velocity = ["1e3 deg", "0 deg", "0 deg"]', "exceeds its limit"),
    ('initial_joint = ["73 deg", "83 deg", "110 deg"]',
     'initial_joint = ["73 deg", "83 deg", "110 deg"]\n'
     'initial_velocity = ["0/0 deg", "0 deg", "0 deg"]', "unit[0].initial_velocity"),
])
def test_initial_state_refused_up_front(refused, tmp_path, old, new, expected):
    assert old in SERIAL_JOINT
    line = refused("--scenario", write(tmp_path, "s.toml", SERIAL_JOINT.replace(old, new, 1)))
    assert expected in line and "diverged" not in line


# -- class 5: degenerate run lengths ----------------------------------------------------------

@pytest.mark.parametrize("argv, expected", [
    (["--duration", "inf"], "--duration: 'inf': expected a plain decimal number"),
    (["--duration", "nan"], "--duration: 'nan': expected a plain decimal number"),
    (["--duration", "0_5"], "--duration: '0_5': expected a plain decimal number"),
    (["--duration", "-1"], "--duration must be positive and finite"),
    (["--duration", "1e12"], "split the session"),
    (["--duration", "1e-6"], "shorter than one control period"),
    (["--rate", "1", "--duration", "0.4"], "shorter than one control period"),
    (["--rate", "0"], "--rate must be between"),
    (["--rate", "nan"], "--rate: 'nan': expected a plain decimal number"),
    (["--duration", "7200"], "split the session"),  # as fast: every period kept in memory
])
def test_degenerate_duration_or_rate_option(refused, argv, expected):
    assert expected in refused(*argv)


@pytest.mark.parametrize("old, new, key", [
    ("duration_s = 20.0", "duration_s = 1e12", "duration_s"),
    ("duration_s = 20.0", "duration_s = 1e-9", "duration_s"),
    ("duration_s = 20.0", "duration_s = inf", "duration_s"),
    ("rate_Hz = 1000.0", "rate_Hz = 1e-9", "control.rate_Hz"),
    ("rate_Hz = 1000.0", "rate_Hz = 0.0", "control.rate_Hz"),
    ("plant_substeps = 1 ", "plant_substeps = 100000000 ", "control.plant_substeps"),
    ("plant_substeps = 1 ", "plant_substeps = 1001 ", "control.plant_substeps"),
])
def test_degenerate_run_length_in_the_scenario(refused, tmp_path, old, new, key):
    assert old in SERIAL_JOINT
    path = write(tmp_path, "s.toml", SERIAL_JOINT.replace(old, new, 1))
    line = refused("--scenario", path)
    assert f"{path}: {key}: expected" in line


# -- class 7: checks over the run's actual duration, both serial arms -------------------------

SHRINKING = SERIAL_TASK.replace('"0.03*cos(a1) m", "0.03*sin(a1) m"',
                                '"(0.03 - 0.001*t)*cos(a1) m", "(0.03 - 0.001*t)*sin(a1) m"')


@pytest.mark.slow
def test_the_path_check_samples_the_run_not_the_scenario(refused, tmp_path):
    """Arm 1's joint 1 limited to 83 deg: its path (3.19) stays below until t = 3.6 s."""
    robot = SERIAL_ROBOT.replace("position_limits_deg = [-170.0, 170.0]",
                                 "position_limits_deg = [-170.0, 83.0]", 1)
    short = with_robot(tmp_path, robot, SERIAL_JOINT.replace("duration_s = 20.0",
                                                             "duration_s = 3.0"))
    unit_setups(load_scenario(short))  # 3 s: inside the limits
    line = refused("--scenario", short, "--duration", "6")
    assert "arm1's desired path takes joint link1" in line and "outside its limits" in line
    assert "t = 3.6" in line
    # ... and a scenario too long for its path is fine when --duration stays inside it.
    long = with_robot(tmp_path, robot)
    with pytest.raises(CochleaError, match="outside its limits"):
        unit_setups(load_scenario(long))
    unit_setups(dataclasses.replace(load_scenario(long), duration=3.0))


@pytest.mark.slow
def test_serial_task_path_is_checked_against_the_keep_out_circle(refused, tmp_path):
    path = write(tmp_path, "shrink.toml", SHRINKING)
    line = refused("--scenario", path, space="task")
    assert "keep-out radius 20.0 mm" in line and "arm1" in line and "t = 10.0" in line
    unit_setups(dataclasses.replace(load_scenario(path), duration=5.0))  # 25 mm: allowed


@pytest.mark.slow
def test_serial_joint_path_is_checked_against_the_keep_out_circle(refused, tmp_path):
    """A joint-space run keeps the tools out of the circle as a task-space one does: the
    thesis's joint-space path (3.19) passes 27.5 mm from the cochlea centre, so a 30 mm circle
    refuses it before anything moves, and the shipped 20 mm one lets it run."""
    assert "keep_out_radius_m = 0.02" in SERIAL_ROBOT
    scenario = with_robot(tmp_path, SERIAL_ROBOT.replace("keep_out_radius_m = 0.02",
                                                         "keep_out_radius_m = 0.03"))
    line = refused("--scenario", scenario)
    assert "desired tool path passes" in line and "inside the keep-out radius 30.0 mm" in line
    assert "arm1" in line
    unit_setups(load_scenario(with_robot(tmp_path, SERIAL_ROBOT)))


@pytest.mark.slow
def test_parallel_joint_path_is_checked_against_the_keep_out_circle(refused, tmp_path):
    """The parallel mechanism's joint-space path: its end effectors stay at least 133 mm from
    the slider point S (the shipped circle is 60 mm); a 140 mm circle refuses it."""
    robot = (ROBOTS_DIR / "parallel.toml").read_text()
    assert "keep_out_radius_m = 0.06" in robot
    robot = write(tmp_path, "parallel.toml",
                  robot.replace("keep_out_radius_m = 0.06", "keep_out_radius_m = 0.14"))
    scenario = (SCENARIOS_DIR / "parallel_joint.toml").read_text().replace(
        'format = "cochlea-scenario/1"', f'format = "cochlea-scenario/1"\ndescription = "{robot}"')
    path = write(tmp_path, "near.toml", scenario)
    line = refused("--scenario", path, robot="parallel", space="joint")
    assert "desired joint path takes an end effector" in line and "slider point S" in line
    assert "inside the keep-out radius 140.0 mm" in line


def test_serial_follower_joint_limits_are_checked(tmp_path):
    """Arm 2 follows arm 1 through inverse kinematics: a limit its own joints leave is found
    before the run too (here its joint 3, starting at 100 deg, is limited to 105 deg; its
    path reaches 108 deg)."""
    arms = SERIAL_ROBOT.split("[[arm]]")
    links = arms[2].split("[[arm.link]]")
    links[3] = links[3].replace("position_limits_deg = [-170.0, 170.0]",
                                "position_limits_deg = [-170.0, 105.0]")
    arms[2] = "[[arm.link]]".join(links)
    scenario = with_robot(tmp_path, "[[arm]]".join(arms))
    with pytest.raises(CochleaError, match="arm2's desired path takes joint link3"):
        unit_setups(load_scenario(scenario))


# -- through the real entry point -------------------------------------------------------------

@pytest.mark.parametrize("argv", [
    ["--duration", "inf"],
    ["--scenario", "LATIN1"],
])
@pytest.mark.slow
def test_entry_point_refuses_without_traceback(tmp_path, argv):
    latin1 = tmp_path / "latin1.toml"
    latin1.write_bytes(("# caf\xe9\n" + SERIAL_JOINT).encode("latin-1"))
    argv = [str(latin1) if a == "LATIN1" else a for a in argv]
    done = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial",
                           "--space", "joint", *argv], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == EXIT_USER_ERROR, done.stderr
    lines = [ln for ln in done.stderr.splitlines() if "Warning" not in ln and ln.strip()]
    assert len(lines) == 1 and "Traceback" not in done.stderr
    assert not (tmp_path / "runs").exists()


@pytest.mark.slow
def test_parallel_task_path_is_checked_against_the_keep_out_circle(refused, tmp_path):
    """The end effectors keep out of the circle around the slider point S = (0, d1) at every
    period, like the serial arms' tools: here C_u drifts inward, 5 mm/s, and the path crosses a
    140 mm keep-out radius at t = (0.16 - 0.14 cos(19.25 deg)) / 0.005 = 5.567 s."""
    robot = (ROBOTS_DIR / "parallel.toml").read_text()
    assert "keep_out_radius_m = 0.06" in robot
    robot = write(tmp_path, "parallel.toml",
                  robot.replace("keep_out_radius_m = 0.06", "keep_out_radius_m = 0.14"))
    scenario = (SCENARIOS_DIR / "parallel_task.toml").read_text()
    old = '"-0.000547*min(t, 5)**3 + 0.0041*min(t, 5)**2 + 0.1258 m"'
    assert old in scenario
    scenario = scenario.replace(old, '"0.16 - 0.005*t m"').replace(
        'format = "cochlea-scenario/1"', f'format = "cochlea-scenario/1"\ndescription = "{robot}"')
    path = write(tmp_path, "drift.toml", scenario)
    line = refused("--scenario", path, "--duration", "7", robot="parallel", space="task")
    assert "inside the keep-out radius 140.0 mm" in line and "slider point S" in line
    assert "t = 5.56" in line  # the first period inside: 5.566 s
    unit_setups(dataclasses.replace(load_scenario(path), duration=5.0))  # allowed up to 5.57 s


@pytest.mark.parametrize("formula, reason", [
    ("1/(1-1)", "'1/(1-1)' divides by zero"),
    ("sin(1, 2)", "sin() takes 1 argument, given 2"),
    ("foo(t)", "unknown function 'foo'"),
    ("t**", "not a formula: invalid syntax"),
    ("exp(1e5)", "'exp(1e5)' is not a finite real number"),
])
def test_a_bad_formula_is_quoted_once(refused, tmp_path, formula, reason):
    """The message gives the reason and the formula as the file has it, once."""
    old = '"81.14 - 3.007*cos(0.632*t) - 0.129*sin(0.632*t) deg"'
    assert old in SERIAL_JOINT
    path = write(tmp_path, "s.toml", SERIAL_JOINT.replace(old, f'"{formula} deg"'))
    line = refused("--scenario", path)
    assert f"desired.leader[0]: expected a valid formula ({reason}" in line
    assert line.count(formula) == 1 + reason.count(formula), line


@pytest.mark.parametrize("name", ["a\\u0000b", "red\\u001b[31m", "two\\nlines", "c1\\u009b"])
def test_control_characters_from_a_file_are_shown_escaped(refused, tmp_path, name):
    """A description name holding a NUL, a terminal escape or a newline: the one line says
    which file, with the characters shown as escapes the terminal does not act on."""
    text = SERIAL_JOINT.replace('format = "cochlea-scenario/1"',
                                f'format = "cochlea-scenario/1"\ndescription = "{name}"')
    line = refused("--scenario", write(tmp_path, "s.toml", text))
    assert line.isprintable(), repr(line)
    assert "\\x" in line
