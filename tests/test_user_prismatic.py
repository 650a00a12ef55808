"""A serial arm's prismatic joint on a Dynamixel, end to end (issue 25, item 5): the
description's transmission, the drive's conversions, the model, a run in simulation and over
the virtual chain, cochlea-dxl calibrate and home, and cochlea-urdf's transmission.

The arm is tests/data/prismatic3.toml: a turret, a carriage lifted by a lead screw of 20 mm
lead on an XM430-W350, a forearm; its study tests/data/prismatic3_joint.toml.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import cochlea
from cochlea.apps import cochlea_model, cochlea_urdf
from cochlea.dynamixel.control_table import RAD_PER_COUNT, RAD_S_PER_VELOCITY_LSB
from cochlea.dynamixel.drives import joint_drives
from cochlea.errors import EXIT_USER_ERROR, DescriptionError
from cochlea.robots import robot
from cochlea.robots.serial import load_serial

from .conftest import DATA

PRISMATIC3 = DATA / "prismatic3.toml"
STUDY = DATA / "prismatic3_joint.toml"
ARM4 = DATA / "arm4.urdf"
LEAD = 0.02  # m per motor revolution, the carriage's lead screw
RUN = [sys.executable, "-m", "cochlea.apps.cochlea_run"]
TRANSMISSION = 'transmission = { kind = "lead_screw", lead_m = 0.02 }'


def _variant(tmp_path: Path, old: str, new: str, name: str = "variant.toml") -> Path:
    text = PRISMATIC3.read_text(encoding="utf-8")
    assert text.count(old) == 1, old
    path = tmp_path / name
    path.write_text(text.replace(old, new), encoding="utf-8")
    return path


def _carriage(description: Path = PRISMATIC3):
    return next(d for d in joint_drives("serial", description) if d.name == "arm.carriage")


# ---- the description ---------------------------------------------------------------------------


@pytest.mark.parametrize("table, ratio", [
    ('{ kind = "lead_screw", lead_m = 0.02 }', 0.02 / (2 * math.pi)),
    ('{ kind = "pinion", radius_m = 0.015 }', 0.015),
    ('{ kind = "belt", radius_m = 0.0127 }', 0.0127),
    ('{ kind = "ratio", m_per_rad = 0.004 }', 0.004),
])
def test_each_kind_of_transmission_gives_its_ratio(tmp_path, table, ratio):
    """m of travel per motor radian: a lead over 2 pi, a pitch radius, or the ratio itself;
    the actuated joint and the drive carry it, the revolute joints keep 1."""
    path = _variant(tmp_path, TRANSMISSION, f"transmission = {table}")
    joints = {j.name: j for j in robot("serial").actuated_joints(load_serial(path))}
    assert joints["arm.carriage"].ratio == pytest.approx(ratio, rel=1e-15)
    assert joints["arm.turret"].ratio == joints["arm.forearm"].ratio == 1.0
    assert _carriage(path).ratio == pytest.approx(ratio, rel=1e-15)


BAD = {
    "missing": (TRANSMISSION, "", "joint.transmission: expected a table (the key is missing)"),
    "zero lead": (TRANSMISSION, TRANSMISSION.replace("0.02", "0.0"), "lead_m"),
    "negative lead": (TRANSMISSION, TRANSMISSION.replace("0.02", "-0.02"), "lead_m"),
    "NaN lead": (TRANSMISSION, TRANSMISSION.replace("0.02", "nan"), "lead_m"),
    "infinite lead": (TRANSMISSION, TRANSMISSION.replace("0.02", "inf"), "lead_m"),
    "lead in mm": (TRANSMISSION, TRANSMISSION.replace("0.02", "20.0"), "within [0.0001, 1] m"),
    "lead as text": (TRANSMISSION, TRANSMISSION.replace("0.02", '"0.02"'), "lead_m"),
    "lead missing": (TRANSMISSION, 'transmission = { kind = "lead_screw" }', "lead_m"),
    "zero radius": (TRANSMISSION, 'transmission = { kind = "pinion", radius_m = 0.0 }',
                    "radius_m"),
    "radius of a lead screw": (TRANSMISSION, TRANSMISSION.replace("lead_m", "radius_m"),
                               "lead_m"),
    "unknown kind": (TRANSMISSION, TRANSMISSION.replace("lead_screw", "harmonic"), "kind"),
    "no kind": (TRANSMISSION, "transmission = { lead_m = 0.02 }", "kind"),
    "not a table": (TRANSMISSION, "transmission = 0.02", "transmission"),
    "unknown key": (TRANSMISSION, TRANSMISSION.replace(" }", ", efficiency = 0.4 }"),
                    "efficiency"),
    "on a revolute joint": ("  torque_limit_Nm = 1.5\n  armature_kgm2 = 0.0125   # estimate, "
                            "see the header\n  [arm.link.motor]\n  model = \"XM430-W350\"\n  "
                            "id = 1", "  torque_limit_Nm = 1.5\n  armature_kgm2 = 0.0125\n  "
                            f"{TRANSMISSION}\n  [arm.link.motor]\n  model = \"XM430-W350\"\n  "
                            "id = 1", "no transmission on a revolute joint"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_a_missing_or_non_physical_transmission_is_refused_in_one_line(tmp_path, capsys,
                                                                       case):
    """At load, naming the file and the key; through a command, one line and exit 2."""
    old, new, said = BAD[case]
    path = _variant(tmp_path, old, new)
    with pytest.raises(DescriptionError) as caught:
        load_serial(path)
    assert said in str(caught.value) and str(path) in str(caught.value)
    assert "transmission" in str(caught.value)
    assert cochlea_model.main(["serial", "--description", str(path)]) == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and said in err and "Traceback" not in err


# ---- the drive's conversions ------------------------------------------------------------------


@pytest.mark.parametrize("direction", [1, -1])
def test_the_drive_converts_metres_and_newtons_exactly(tmp_path, rng, direction):
    """q = direction * lead / 2 pi * (theta - zero_offset), the velocity likewise, and the
    motor torque direction * lead / 2 pi * force: each conversion and its inverse agree to
    rounding, and the counts round-trip to within half a count."""
    path = _variant(tmp_path, '  id = 2\n', f'  id = 2\n  direction = {direction}\n'
                    '  zero_offset_deg = 1234.5\n')
    d = _carriage(path)
    ratio = direction * LEAD / (2 * math.pi)
    assert d.unit == "m" and d.type == "prismatic"
    assert d.q_per_count == pytest.approx(direction * LEAD / 4096, rel=1e-15)  # 4.9 um a count
    assert d.qd_per_lsb == pytest.approx(ratio * RAD_S_PER_VELOCITY_LSB, rel=1e-15)
    assert d.torque_per_effort == pytest.approx(ratio, rel=1e-15)
    # Position: the motor angle of a whole number of counts gives the joint coordinate back.
    counts = rng.integers(-200_000, 200_000, 200).astype(float)
    theta = counts * RAD_PER_COUNT
    q = d.q(counts)
    np.testing.assert_allclose(q, ratio * (theta - math.radians(1234.5)), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(d.counts(q), counts)
    q_any = rng.uniform(0.0, 0.1, 200)  # the carriage's travel, anywhere between counts
    assert np.abs(d.q(d.counts(q_any)) - q_any).max() <= 0.5 * abs(d.q_per_count) * (1 + 1e-9)
    # Velocity: Present Velocity LSBs <-> m/s.
    lsb = rng.integers(-300, 300, 200).astype(float)
    np.testing.assert_array_equal(d.velocity_lsb(d.qd(lsb)), lsb)
    # Effort: N at the joint from N m at the motor, the fit's slope a (N m per A).
    current = rng.integers(-d.current_limit_lsb, d.current_limit_lsb, 200).astype(float)
    amps = current * d.spec.current_unit_mA * 1e-3
    force = d.effort(current, slope_only=True)
    np.testing.assert_allclose(force * ratio, d.fit.a * amps, rtol=1e-13, atol=1e-15)
    # and back: the Goal Current of a force is the current that gives it, to within one LSB
    # (the fit's offset is zero in this description).
    forces = rng.uniform(-90.0, 90.0, 200)
    goal = d.goal_current_lsb(forces)
    quantum = d.fit.a * d.spec.current_unit_mA * 1e-3 / abs(ratio)  # N per LSB
    assert np.abs(d.effort(goal) - forces).max() <= 0.5 * quantum * (1 + 1e-9)
    assert np.all(np.sign(goal) == direction * np.sign(forces) * (goal != 0))


def test_the_current_limit_comes_from_the_force_limit_through_the_lead(tmp_path):
    """100 N through 20 mm a turn is 0.318 N m at the motor: 0.178 A at 178.3 N cm/A, 67 LSB
    of 2.69 mA (rounded up); the revolute joints' 1.5 N m is 313 LSB."""
    drives = {d.name: d for d in joint_drives("serial", PRISMATIC3)}
    torque = 100.0 * LEAD / (2 * math.pi)
    assert drives["arm.carriage"].current_limit_lsb == math.ceil(torque / 1.783 / 2.69e-3)
    assert drives["arm.turret"].current_limit_lsb == math.ceil(1.5 / 1.783 / 2.69e-3)


# ---- the model ---------------------------------------------------------------------------------


def test_the_prismatic_arm_matches_pinocchio(rng):
    """M (CRBA), the inverse dynamics (RNEA) and G against Pinocchio built from the
    description's numbers, the carriage a prismatic joint; gravity loads the carriage with
    the weight it lifts (not vacuous)."""
    import pinocchio as pin

    from .conftest import ev, random_state
    from .test_pinocchio_oracle import pinocchio_arm

    system = load_serial(PRISMATIC3)
    ours = cochlea.model("serial", description=PRISMATIC3)
    theirs = pinocchio_arm(system, system.arms[0])
    data = theirs.createData()
    assert [j.type for j in ours.joints] == ["revolute", "prismatic", "revolute"]
    for _ in range(20):
        q, qd, qdd = random_state(rng, ours.nq)
        M = pin.crba(theirs, data, q)
        M = np.triu(M) + np.triu(M, 1).T
        assert np.abs(ev(ours.M, q) - M).max() < 1e-10
        assert np.abs(ev(ours.inverse_dynamics, q, qd, qdd)
                      - pin.rnea(theirs, data, q, qd, qdd)).max() < 1e-10
        assert np.abs(ev(ours.G, q) - pin.computeGeneralizedGravity(theirs, data, q)).max() \
            < 1e-10
    lifted = 0.25 + 0.15  # kg: the carriage and the forearm
    assert float(np.ravel(ev(ours.G, np.array([0.3, 0.05, 0.2])))[1]) == pytest.approx(
        lifted * 9.81, rel=1e-12)


def test_cochlea_model_takes_metres_at_a_prismatic_joint(capsys):
    """--at-deg is deg at a revolute joint and m at a prismatic one (as the description's
    poses), and the printout says each unit and the transmission."""
    assert cochlea_model.main(["serial", "--description", str(PRISMATIC3), "--at-deg", "10",
                               "0.05", "-20"]) == 0
    out = capsys.readouterr().out
    assert "at q = [10 deg, 0.05 m, -20 deg]:" in out
    assert "transmission carriage: lead screw 0.02 m: 0.0031831 m per motor rad" in out
    assert "G(q) [N m; N at a prismatic joint] =  0.000e+00   3.924e+00" in out
    # The carriage 0.05 m up from 0.1 m: the forearm's tool (0.15 m, pitched -20 deg) higher.
    z = 0.1 + 0.05 + 0.15 * math.sin(math.radians(20.0))
    assert f"{z:.6f} m" in out


@pytest.mark.slow
def test_the_prismatic_study_converges_in_simulation():
    from cochlea.apps import report
    from cochlea.sim import load_scenario, simulate

    result = simulate(load_scenario(STUDY), kernels="casadi")
    summary = report.summary(result)
    assert summary["converged"] and not summary["diverged"], summary
    assert summary["units"]["arm"]["tracked"]["carriage_joint"]["unit"] == "m"


# ---- over the virtual chain, and the bring-up tools ------------------------------------------


@pytest.mark.hil
def test_the_prismatic_study_runs_over_the_virtual_chain(tmp_path):
    """cochlea-emulator moves the carriage through its lead screw (the counts of a turn and a
    half of the motor), cochlea-run --backend dynamixel tracks the study over the
    pseudo-terminal, and stops the motors."""
    log, out = tmp_path / "emulator.log", tmp_path / "hil"
    proc = subprocess.Popen([sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot",
                             "serial", "--scenario", str(STUDY), "--log", str(log)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/"), proc.stderr.read() if proc.poll() is not None else port
        assert "2 (arm.carriage, XM430-W350)" in proc.stdout.readline()
        done = subprocess.run(RUN + ["--robot", "serial", "--space", "joint", "--scenario",
                                     str(STUDY), "--backend", "dynamixel", "--port", port,
                                     "--duration", "3", "--out", str(out),
                                     "--watchdog-misses", "300"],
                              capture_output=True, text=True, timeout=180, cwd=tmp_path)
    finally:
        proc.terminate()
        proc.communicate(timeout=20)
    assert done.returncode == 0, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stop"]["rule"] == "completed"
    assert "torque off confirmed by all 3" in summary["timing"]["bus"]["shutdown"]
    tracked = summary["units"]["arm"]["tracked"]
    assert tracked["carriage_joint"]["unit"] == "m"
    # Absolute bounds: the first row of a run over a loaded machine may be a failed read.
    assert tracked["carriage_joint"]["final_rms_error"] < 2e-4  # m
    for name in ("turret_joint", "forearm_joint"):
        assert tracked[name]["final_rms_error"] < math.radians(0.5), (name, tracked[name])
    import csv

    with open(out / "log.csv", newline="") as f:
        carriage = np.array([float(r["arm.q.carriage_joint_m"]) for r in csv.DictReader(f)][1:])
    assert carriage.max() - carriage.min() > 0.015  # it rode its path: 40 to 60 mm


def parse(module, *argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog=f"cochlea-dxl {module.NAME}")
    module.add_arguments(parser)
    return parser.parse_args(list(argv))


@pytest.fixture
def no_gc():
    gc.collect()
    gc.disable()
    yield
    gc.enable()


@pytest.mark.hil
def test_calibrate_and_the_limits_check_in_metres(tmp_path, monkeypatch, no_gc):
    """Mounted otherwise than the description says (the carriage's motor -1000 deg off and
    turning against it), the bridge refuses to start, the carriage read in metres outside its
    limits; cochlea-dxl calibrate recovers its offset and direction within one count (no
    modulo: a lead screw's turns are positions), and the calibrated description starts."""
    from cochlea.dynamixel.bridge import DynamixelBackend
    from cochlea.dynamixel.bringup import calibrate
    from cochlea.dynamixel.emulator import Truth, VirtualChain
    from cochlea.runtime.backend import BackendError

    description = tmp_path / "prismatic3.toml"
    description.write_text(PRISMATIC3.read_text(encoding="utf-8"), encoding="utf-8")
    scenario = tmp_path / "study.toml"
    scenario.write_text(STUDY.read_text(encoding="utf-8"), encoding="utf-8")
    truth = Truth(offset_deg={2: -1000.0, 3: 45.0}, direction={2: -1})
    chain = VirtualChain("serial", scenario, truth=truth).start()
    out = tmp_path / "calibrated.toml"
    try:
        bridge = DynamixelBackend("serial", chain.path, description=description, timeout_s=0.05)
        with pytest.raises(BackendError, match=r"arm\.carriage \(ID 2\) reads -?\d+\.\d{4} m, "
                           r"outside its limits \[0, 0\.1\] m"):
            bridge.enable()
        refs = {"arm.turret": 0.0, "arm.carriage": 0.0, "arm.forearm": 0.0}

        def answer(prompt):
            name = prompt.split(" ")[0].rstrip(":")
            step = 0.005 if name == "arm.carriage" else 0.2  # 5 mm: 1.6 motor rad
            chain.move_joint(name, refs[name] + (0.0 if "reference pose" in prompt else step))
            return ""

        monkeypatch.setattr(calibrate, "ask", answer)
        code = calibrate.run(parse(calibrate, "--robot", "serial", "--port", chain.path,
                                   "--description", str(description), "--out", str(out)))
        assert code == 0 and not any(m.torque_on for m in chain.motors)
        calibrated = {d.id: d for d in joint_drives("serial", out)}
        assert calibrated[2].direction == -1
        assert abs(math.degrees(calibrated[2].zero_offset) + 1000.0) <= math.degrees(
            RAD_PER_COUNT)
        bridge = DynamixelBackend("serial", chain.path, description=out, timeout_s=0.05)
        bridge.enable()
        try:
            x = np.zeros(6)
            assert bridge.read(x)
            assert abs(x[1] - chain.joint_state()[1]) <= 2 * calibrated[2].ratio * RAD_PER_COUNT
        finally:
            bridge.disable()
    finally:
        chain.close()


@pytest.mark.hil
def test_home_finds_the_carriages_stop(tmp_path, no_gc):
    """cochlea-dxl home drives the carriage down its lead screw onto a hard stop, records it,
    and the bridge then counts the carriage from the stop (a real port's rule, required)."""
    from cochlea.dynamixel.bridge import DynamixelBackend
    from cochlea.dynamixel.bringup import home
    from cochlea.dynamixel.emulator import Truth, VirtualChain

    stop = 0.03
    chain = VirtualChain("serial", STUDY, truth=Truth(offset_deg={2: 500.0},
                                                      hard_stop_m=stop)).start()
    record = tmp_path / "homing.json"
    try:
        code = home.run(parse(home, "--robot", "serial", "--description", str(PRISMATIC3),
                              "--port", chain.path, "--record", str(record), "--stop-m",
                              str(stop), "--speed-mm-s", "10", "--force-N", "20"))
        assert code == 0 and not any(m.torque_on for m in chain.motors)
        saved = json.loads(record.read_text())
        assert saved["description"] == str(PRISMATIC3.resolve())
        (entry,) = saved["joints"]
        assert entry["joint"] == "arm.carriage" and entry["motor_id"] == 2
        assert entry["ratio_m_per_rad"] == pytest.approx(LEAD / (2 * math.pi), rel=1e-15)
        bridge = DynamixelBackend("serial", chain.path, description=PRISMATIC3,
                                  timeout_s=0.05, homing="required", homing_record=record)
        bridge.enable()
        try:
            x = np.zeros(6)
            assert bridge.read(x)
            assert abs(x[1] - chain.joint_state()[1]) <= 3 * LEAD / 4096
            assert abs(x[1] - stop) < 1e-3
        finally:
            bridge.disable()
    finally:
        chain.close()


def test_home_wants_one_stop_per_prismatic_joint_in_one_line(tmp_path):
    """Two prismatic joints are homed in turn (tests/test_homing_records.py); a --stop-m given
    once for both is refused in one line before any port is opened."""
    from cochlea.dynamixel.bringup import home
    from cochlea.errors import CochleaError

    path = DATA / "prismatic3_two.toml"
    with pytest.raises(CochleaError, match=r"--stop-m: given 1 time\(s\) for 2 prismatic "
                       r"joint\(s\) \(arm\.carriage, arm\.forearm\)") as caught:
        home.run(parse(home, "--robot", "serial", "--description", str(path), "--port",
                       str(tmp_path / "no-such-port"), "--stop-m", "0.03"))
    assert "\n" not in str(caught.value)


# ---- cochlea-urdf ------------------------------------------------------------------------------


def _import(tmp_path: Path, capsys, urdf: Path, *options: str) -> tuple[int, str, Path]:
    out = tmp_path / "robot.toml"
    code = cochlea_urdf.main(["import", str(urdf), "--out", str(out), *options])
    return code, capsys.readouterr().err, out


def test_urdf_import_reads_the_transmission_and_export_writes_it(tmp_path, capsys):
    """The fixture's <transmission> (100 rad per m) becomes 0.01 m/rad; --transmission
    overrides it; export writes it back (signed by the motor's direction) and import reads
    the same ratio again."""
    code, _, out = _import(tmp_path, capsys, ARM4)
    assert code == 0
    assert _drive(out).ratio == pytest.approx(0.01, rel=1e-15)
    code, _, out = _import(tmp_path, capsys, ARM4, "--transmission", "extend=lead_screw:0.008")
    assert code == 0
    assert 'transmission = { kind = "lead_screw", lead_m = 0.008 }' in out.read_text()
    assert _drive(out).ratio == pytest.approx(0.008 / (2 * math.pi), rel=1e-15)
    urdf = tmp_path / "back.urdf"
    assert cochlea_urdf.main(["export", str(out), "--out", str(urdf)]) == 0
    assert "<mechanicalReduction>" in urdf.read_text()
    code, _, again = _import(tmp_path, capsys, urdf)
    assert code == 0
    assert _drive(again).ratio == pytest.approx(0.008 / (2 * math.pi), rel=1e-12)
    assert _drive(again).direction == 1


def test_urdf_export_signs_the_reduction_by_the_motors_direction(tmp_path, capsys):
    code, _, out = _import(tmp_path, capsys, ARM4)
    text = out.read_text()
    head, sep, tail = text.partition('  transmission = { kind = "ratio"')
    assert sep
    tail = tail.replace("  direction = 1 ", "  direction = -1", 1)  # the slider's motor
    flipped = tmp_path / "flipped.toml"
    flipped.write_text(head + sep + tail, encoding="utf-8")
    urdf = tmp_path / "flipped.urdf"
    assert cochlea_urdf.main(["export", str(flipped), "--out", str(urdf)]) == 0
    assert "<mechanicalReduction>-100.0</mechanicalReduction>" in urdf.read_text()
    code, _, again = _import(tmp_path, capsys, urdf)
    assert code == 0 and _drive(again).direction == -1
    assert _drive(again).ratio == pytest.approx(0.01, rel=1e-12)


def _drive(description: Path):
    return next(d for d in joint_drives("serial", description) if d.type == "prismatic")


def _without_transmission(tmp_path: Path) -> Path:
    text = ARM4.read_text(encoding="utf-8")
    start, end = text.index("  <transmission"), text.index("</transmission>") + len(
        "</transmission>\n")
    path = tmp_path / "bare.urdf"
    path.write_text(text[:start] + text[end:], encoding="utf-8")
    return path


BAD_OPTIONS = {
    "no transmission": ([], "joint 'extend' is prismatic and the URDF gives no <transmission>"),
    "zero lead": (["--transmission", "extend=lead_screw:0"], "expected SIZE a number"),
    "negative radius": (["--transmission", "extend=pinion:-0.01"], "expected SIZE a number"),
    "NaN lead": (["--transmission", "extend=lead_screw:nan"], "expected SIZE a number"),
    "lead in mm": (["--transmission", "extend=lead_screw:8"], "expected SIZE a number"),
    "not a number": (["--transmission", "extend=belt:wide"], "expected SIZE a number"),
    "unknown kind": (["--transmission", "extend=chain:0.01"], "unknown kind 'chain'"),
    "no size": (["--transmission", "extend=belt"], "expected JOINT=KIND:SIZE"),
    "unknown joint": (["--transmission", "elbow=belt:0.01"], "no joint 'elbow'"),
    "revolute joint": (["--transmission", "pan=belt:0.01"], "joint 'pan' is revolute"),
    "zero keep-out": (["--keep-out-radius-m", "0"], "--keep-out-radius-m"),
    "NaN keep-out": (["--keep-out-radius-m", "nan"], "--keep-out-radius-m"),
    "vanishing keep-out": (["--keep-out-radius-m", "1e-300"], "--keep-out-radius-m"),
}


@pytest.mark.parametrize("case", list(BAD_OPTIONS))
def test_urdf_import_refuses_a_missing_or_bad_transmission_in_one_line(tmp_path, capsys,
                                                                       case):
    options, said = BAD_OPTIONS[case]
    code, err, out = _import(tmp_path, capsys, _without_transmission(tmp_path), *options)
    assert code == EXIT_USER_ERROR and said in err, err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["bare.urdf"]


def test_urdf_refuses_a_bad_mechanical_reduction(tmp_path, capsys):
    for value in ("0", "nan", "abc", "1e300"):
        bad = tmp_path / f"bad_{value}.urdf"
        bad.write_text(ARM4.read_text(encoding="utf-8").replace(
            "<mechanicalReduction>100<", f"<mechanicalReduction>{value}<"), encoding="utf-8")
        code, err, out = _import(tmp_path, capsys, bad)
        assert code == EXIT_USER_ERROR and "mechanicalReduction" in err, (value, err)
        assert err.count("\n") == 1 and not out.exists()
    # 1 rad per metre: 1 m/rad is beyond any real transmission (the description's bound).
    far = tmp_path / "far.urdf"
    far.write_text(ARM4.read_text(encoding="utf-8").replace(
        "<mechanicalReduction>100<", "<mechanicalReduction>0.5<"), encoding="utf-8")
    code, err, out = _import(tmp_path, capsys, far)
    assert code == EXIT_USER_ERROR and "m_per_rad" in err and err.count("\n") == 1


def test_urdf_import_writes_no_keep_out_unless_asked(tmp_path, capsys):
    """keep_out_radius_m is optional: none written (no keep-out circle) by default, the
    option's value when given."""
    code, _, out = _import(tmp_path, capsys, ARM4)
    assert code == 0 and "keep_out_radius_m =" not in out.read_text()
    assert load_serial(out).keep_out_radius is None
    code, _, out = _import(tmp_path, capsys, ARM4, "--keep-out-radius-m", "0.045")
    assert code == 0 and "\nkeep_out_radius_m = 0.045\n" in out.read_text()
    assert load_serial(out).keep_out_radius == 0.045
