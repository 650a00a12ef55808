"""Measured motor current in the logs, and the current-to-torque lines fitted from them.

* the column: cochlea-run over the (emulated) motors logs each joint's Present Current at the
  joint's sign, in A; a simulated run's log.csv has no such column (log.bin keeps NaN there);
* cochlea-emulator --true-fit: the plant's torque follows the true line, checked as a fit;
* cochlea-identify --fit-current: a placeholder line recovered from a simulated excitation
  whose log carries the current the true line needs, quantised as the drives report it; the
  refusals (every joint fitted, a log without the current, an unknown joint).
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from cochlea.apps.cochlea_identify import main
from cochlea.dynamixel.drives import joint_drives
from cochlea.dynamixel.emulator import Truth, true_drives
from cochlea.errors import EXIT_USER_ERROR, CochleaError
from cochlea.resources import ROBOTS_DIR, SCENARIOS_DIR
from cochlea.robots.description import MotorFit
from cochlea.robots.motor_fit import Fit
from tests.test_identify import _simulate, measured, serial_scenario

ROOT = Path(__file__).resolve().parent.parent
#: Present Current's LSB on the MX-64(2.0) (A).
MX64_LSB_A = 3.36e-3
#: Joint 1's line in the shipped serial description (Table C.1): the truth of the fit test.
TRUE_FIT = (108.2, -15.47)
#: The placeholder the test description gives joint 1 instead: the parallel robot's.
PLACEHOLDER = (112.68, -19.96)


def _description_with(tmp: Path, old: str, new: str, name: str = "serial.toml") -> Path:
    text = (ROBOTS_DIR / "serial.toml").read_text()
    assert old in text
    path = tmp / name
    path.write_text(text.replace(old, new, 1))
    return path


def _shipped_fit(a: float, b: float, extra: str = "") -> str:
    return f'fit = {{ a = {a}, b = {b}, x = "current_A", y = "torque_Ncm"{extra} }}'


def _header(path: Path) -> list[str]:
    return path.read_text().splitlines()[0].split(",")


# --------------------------------------------------------------------------------------------
# The column
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_a_simulated_run_logs_no_current_in_log_csv_nor_in_log_bin(tmp_path):
    """The sim backend measures no current: neither file has the columns (one schema for
    every log, docs/logs.md; log.bin had NaN ones before schema version 2)."""
    out = tmp_path / "run"
    subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial",
                    "--space", "joint", "--duration", "0.2", "--out",
                    str(out)], check=True, capture_output=True, cwd=ROOT)
    assert not [c for c in _header(out / "log.csv") if ".current." in c]
    columns = json.loads((out / "log.columns.json").read_text())
    names = columns["columns"]
    assert not [c for c in names if ".current." in c]
    # After the timing columns, the simulated plant's true state (a simulated run only), 12
    # columns.
    after = names[names.index("backend_io_s") + 1:]
    assert len(after) == 12
    assert all(c.split(".")[1] in ("true_q", "true_qd") for c in after)
    rows = np.fromfile(out / "log.bin").reshape(-1, columns["row_length"])
    assert len(rows) == 200 and np.isfinite(rows[:, names.index(after[0])]).all()
    assert np.isfinite(rows[:, names.index("backend_io_s")]).all()


@pytest.mark.hil
def test_the_bridge_logs_present_current_at_the_joints_sign(tmp_path):
    """Over the emulated bus, with arm 1's second motor mounted against its joint
    (direction -1 in the description and the emulator alike): the current logged at period
    k + 1 is the Goal Current the bridge sent for the effort of period k (what the emulator
    reports as Present Current in current control), times the LSB, signed so that it has the
    effort's sign."""
    from tests.test_dynamixel_hil import LOOP_TRANSPORT, emulator, run

    old = "id = 2\n  " + _shipped_fit(122.3, -23.7) + "\n  direction = 1"
    description = _description_with(tmp_path, old, old.replace("direction = 1",
                                                                "direction = -1"))
    scenario = tmp_path / "serial_joint.toml"
    scenario.write_text((SCENARIOS_DIR / "serial_joint.toml").read_text().replace(
        'space = "joint"\n', f'space = "joint"\ndescription = "{description}"\n', 1))
    out = tmp_path / "run"
    with emulator("serial", str(scenario), tmp_path / "emulator.log",
                  transport=LOOP_TRANSPORT) as port:
        done = run("--robot", "serial", "--space", "joint", "--scenario", str(scenario),
                   "--backend", "dynamixel", "--port", port, "--duration", "2", "--out",
                   str(out), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    header = _header(out / "log.csv")
    data = np.loadtxt(out / "log.csv", delimiter=",", skiprows=1)
    drives = joint_drives("serial", description)
    assert drives[1].direction == -1
    for d in drives:
        arm, link = d.name.split(".")
        joint = link.replace("link", "joint")
        i_col = header.index(f"{arm}.current.{joint}_A")
        assert header.index(f"{arm}.tau.{joint}_N_m") < i_col  # after the unit's efforts
        tau = data[:, header.index(f"{arm}.tau.{joint}_N_m")]
        logged = data[:, i_col]
        sign = np.sign(d.torque_per_effort)
        expected = sign * d.goal_current_lsb(tau) * d.spec.current_unit_mA * 1e-3
        # A read can overtake a late write (the loop's jitter on a shared machine): most
        # periods, not all, see the previous period's command.
        same = np.isclose(logged[1:], expected[:-1], rtol=0, atol=1e-9)
        assert same.mean() > 0.8, (d.name, same.mean())
        # The sign convention: a positive current drives the joint positively, whatever the
        # mounting (here direction -1 on arm1.link2).
        # (The motor's own current has the opposite sign where direction is -1: expected
        # above is the emulator's Present Current register times the mounting's sign.)
        moving = same & (logged[1:] != 0)
        # Periods with a current of at least one LSB: hundreds at arm 1's proximal joints,
        # tens at the distal ones (their efforts stay within a few mN m, a few LSB).
        assert moving.sum() >= (200 if d.direction < 0 else 10), (d.name, moving.sum())
        assert (np.sign(logged[1:][moving]) == np.sign(tau[:-1][moving])).all()


# --------------------------------------------------------------------------------------------
# The emulator's true line
# --------------------------------------------------------------------------------------------


def test_the_emulators_true_fit_replaces_the_line_and_is_checked():
    drives = joint_drives("serial")
    true = true_drives(drives, Truth(fit={1: (98.0, -12.0)}))
    expected = Fit.from_description(MotorFit(98.0, -12.0, "current_A", "torque_Ncm"))
    lsb = np.arange(-300, 301, 7)
    amps = lsb * MX64_LSB_A
    assert np.allclose(true[0].effort(lsb), expected.torque(amps) / true[0].torque_per_effort)
    assert not np.allclose(true[0].effort(lsb), drives[0].effort(lsb))
    assert true[1:] == drives[1:]  # the others as described
    for bad, what in [({1: (0.0, -12.0)}, "positive slope"), ({1: (np.nan, 1.0)}, "positive"),
                      ({1: (98.0, np.inf)}, "finite offset"), ({9: (98.0, -12.0)}, "not on")]:
        with pytest.raises(CochleaError, match=what):
            true_drives(drives, Truth(fit=bad))


@pytest.mark.slow
def test_the_emulator_refuses_a_malformed_true_fit_in_one_line():
    done = subprocess.run([sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot",
                           "serial", "--true-fit", "1:100"], capture_output=True, text=True,
                          cwd=ROOT, timeout=60)
    assert done.returncode == EXIT_USER_ERROR
    assert done.stderr.count("\n") == 1 and "ID:A,B" in done.stderr


def test_a_fit_source_is_validated_by_the_description_loader(tmp_path):
    from cochlea.robots import robot

    shipped = _shipped_fit(*TRUE_FIT)
    good = _description_with(tmp_path, shipped, _shipped_fit(*TRUE_FIT, ', source = "measured"'))
    assert robot("serial").load(good).arms[0].links[0].motor.fit.source == "measured"
    bad = _description_with(tmp_path, shipped, _shipped_fit(*TRUE_FIT, ', source = "guess"'),
                            "bad.toml")
    with pytest.raises(CochleaError, match="source"):
        robot("serial").load(bad)
    parallel = robot("parallel").load(None)
    sources = [j.motor.fit.source for j in robot("parallel").actuated_joints(parallel)]
    assert sources == ["placeholder", "placeholder", None, "placeholder", "placeholder"]


# --------------------------------------------------------------------------------------------
# The fit
# --------------------------------------------------------------------------------------------


def with_current(run: Path, out: Path, fits: list[Fit], unit: str = "arm1") -> Path:
    """A copy of the run folder that carries what the drives would have measured: for each
    joint the current its true line needs for the effort the plant was given, on the
    Present Current grid (3.36 mA), read at the start of the next period (the bridge reads
    before it writes)."""
    header = _header(run / "log.csv")
    data = np.loadtxt(run / "log.csv", delimiter=",", skiprows=1)
    columns = []
    for j, fit in enumerate(fits, start=1):
        tau = data[:, header.index(f"{unit}.tau.joint{j}_N_m")]
        amps = np.rint(fit.current(tau) / MX64_LSB_A) * MX64_LSB_A
        columns.append(np.concatenate([[0.0], amps[:-1]]))
    out.mkdir()
    names = header + [f"{unit}.current.joint{j}_A" for j in range(1, len(fits) + 1)]
    np.savetxt(out / "log.csv", np.column_stack([data] + columns), delimiter=",",
               header=",".join(names), comments="", fmt="%.17g")
    return out


@pytest.fixture(scope="module")
def current_run(tmp_path_factory):
    """The identification tests' simulated excitation (perturbed plant, measured positions),
    with the current the shipped description's lines (Table C.1) need; and a description
    whose joint 1 line is a placeholder."""
    tmp = tmp_path_factory.mktemp("current")
    scenario = serial_scenario(tmp)
    _simulate("serial", scenario, tmp / "run")
    measured(tmp / "run", scenario, "arm1", tmp / "measured")
    shipped = [(108.2, -15.47), (122.3, -23.7), (122.3, -23.7)]
    fits = [Fit.from_description(MotorFit(a, b, "current_A", "torque_Ncm")) for a, b in shipped]
    with_current(tmp / "measured", tmp / "logs", fits)
    description = _description_with(tmp, _shipped_fit(*TRUE_FIT),
                                     _shipped_fit(*PLACEHOLDER, ', source = "placeholder"'))
    return tmp, description


@pytest.mark.slow
def test_a_placeholder_line_is_recovered_from_the_measured_current(current_run, capsys):
    tmp, description = current_run
    report = tmp / "ident.json"
    assert main([str(tmp / "logs"), "--robot", "serial", "--description", str(description),
                 "--out", str(report), "--min-speed", "0", "--no-figures", "--physical",
                 "--update-description", str(description)]) == 0
    doc = json.loads(report.read_text())
    [line] = doc["current_fits"]  # auto: the one placeholder
    assert line["joint"] == "joint1" and line["source_before"] == "placeholder"
    got = line["description_units"]
    a, b = got["a"], got["b"]
    # Measured: a 1.2 % and b 1.8 % from the truth. The bias is the base parameters' own
    # (encoder counts twice differentiated, through the 3 Hz parallel filter: up to 1.6 % on
    # the well-excited ones, docs/identification.md) seen through the coupling terms that
    # fix joint 1's scale; the 3.36 mA current LSB adds at most 0.4 mN m a sample inside the
    # knee (0.35 % of joint 1's RMS effort), averaged by the filters. Bounds: 3 % and 5 %,
    # where the placeholder is 4 % and 29 % away.
    assert abs(a - TRUE_FIT[0]) < 0.03 * TRUE_FIT[0], a
    assert abs(b - TRUE_FIT[1]) < 0.05 * abs(TRUE_FIT[1]), b
    assert abs(a - TRUE_FIT[0]) < abs(PLACEHOLDER[0] - TRUE_FIT[0])
    assert abs(b - TRUE_FIT[1]) < 0.2 * abs(PLACEHOLDER[1] - TRUE_FIT[1])
    assert got["a_std_error"] > 0 and got["b_std_error"] > 0
    assert max(doc["prediction_nrms_percent"]["wls"]) < 5.0
    assert "current-to-torque fit of joint1 (ID 1)" in capsys.readouterr().out
    # Written back into the motor's fit, in its units, marked identified; the file loads
    # (--physical: this plant has no dry friction, and the nearest full vector to the WLS
    # estimate gives a Coulomb level of -5e-5 N m, which the description refuses).
    written = Path(doc["description_written"])
    motor = tomllib.loads(written.read_text())["arm"][0]["link"][0]["motor"]
    assert motor["fit"]["source"] == "identified"
    assert motor["fit"]["a"] == pytest.approx(a, rel=1e-5)
    assert motor["fit"]["b"] == pytest.approx(b, rel=1e-5)
    assert "current-to-torque fits of joint1 (ID 1)" in written.read_text()
    # Its joint 1 line is no placeholder any more: auto fits nothing from it.
    again = tmp / "again.json"
    assert main([str(tmp / "logs"), "--robot", "serial", "--description", str(written),
                 "--out", str(again), "--min-speed", "0", "--no-figures"]) == 0
    assert json.loads(again.read_text())["current_fits"] == []


def _refused(args: list[str], capsys, out: Path, *expected: str) -> None:
    assert main(args + ["--out", str(out), "--no-figures"]) == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    for text in expected:
        assert re.search(text, err), (text, err)
    assert not out.exists()


@pytest.mark.slow
def test_fitting_every_joints_line_is_refused(current_run, capsys):
    tmp, _ = current_run
    every = tmp / "every.toml"
    text = (ROBOTS_DIR / "serial.toml").read_text()
    every.write_text(re.sub(r'y = "torque_Ncm" \}', 'y = "torque_Ncm", source = "placeholder" }',
                            text))
    for option in ("auto", "joint1,joint2,joint3"):
        _refused([str(tmp / "logs"), "--robot", "serial", "--description", str(every),
                  "--fit-current", option], capsys, tmp / "every.json",
                 "not observable", "cochlea-dxl calibrate --torque-fit")


@pytest.mark.slow
def test_a_named_joint_needs_the_current_in_every_log(current_run, capsys):
    tmp, description = current_run
    _refused([str(tmp / "measured"), "--robot", "serial", "--fit-current", "joint2"], capsys,
             tmp / "none.json", "--fit-current joint2", "no measured current",
             "--fit-current off")
    _refused([str(tmp / "logs"), "--robot", "serial", "--fit-current", "joint4"], capsys,
             tmp / "none.json", "no joint 'joint4'", "joint1, joint2, joint3")
    # auto on a log without current fits nothing, and says so in the report.
    report = tmp / "plain.json"
    assert main([str(tmp / "measured"), "--robot", "serial", "--description", str(description),
                 "--out", str(report), "--min-speed", "0", "--no-figures"]) == 0
    assert json.loads(report.read_text())["current_fits"] == []
    capsys.readouterr()


@pytest.mark.hil
def test_a_line_is_recovered_from_a_log_recorded_against_the_emulator(tmp_path):
    """Over the emulated bus: the emulator's joint 1 follows the true line 98 x - 12
    (--true-fit) while the description, whose line says placeholder, has 108.2 x - 15.47.
    The bridge logs the Present Current; cochlea-identify places the log's samples and
    commands at their logged times (--sample-times auto) and fits the line with the base
    parameters."""
    from tests.test_dynamixel_hil import ALWAYS_OFFSET, LOOP_TRANSPORT, emulator, run
    from tests.test_identify import SERIAL_PLANT, _excitation, fourier_leader

    description = _description_with(tmp_path, _shipped_fit(*TRUE_FIT),
                                     _shipped_fit(*TRUE_FIT, ', source = "placeholder"'))
    # The identification tests' excitation at a 1 s period (harmonics to 3 Hz): efforts of
    # about 0.1 N m RMS, so that joint 1's current passes its knee often enough.
    lead = fourier_leader([81.14, 71.02, 117.8], [25, 25, 25], 1.0, 3, seed=1)
    scenario = _excitation("serial_joint_realistic.toml", lead,
                           ('initial_joint = ["73 deg", "83 deg", "110 deg"]',
                            'initial_joint = ["81.14 deg", "71.02 deg", "117.8 deg"]'),
                           8.0, SERIAL_PLANT, tmp_path)
    text = scenario.read_text()
    scenario.write_text(text.replace('space = "joint"\n',
                                     f'space = "joint"\ndescription = "{description}"\n', 1))
    # The line's offset b reaches the wire only where the bridge adds the offset current and
    # the motors take their true one off: the pairing of the thesis's controllers. This
    # excitation's controller compensates friction itself, so the bridge would command the
    # slope alone (issue 24) and a frictionless plant would never show b: the rule is patched
    # in both processes.
    out, report = tmp_path / "run", tmp_path / "ident.json"
    with emulator("serial", str(scenario), tmp_path / "emulator.log", "--true-fit", "1:98,-12",
                  prefix=ALWAYS_OFFSET, transport=LOOP_TRANSPORT) as port:
        done = run("--robot", "serial", "--space", "joint", "--scenario", str(scenario),
                   "--backend", "dynamixel", "--port", port, "--out", str(out),
                   cwd=tmp_path, prefix=ALWAYS_OFFSET)
    assert done.returncode == 0, done.stderr
    assert main([str(out), "--robot", "serial", "--description", str(description),
                 "--out", str(report), "--min-speed", "0", "--no-figures",
                 "--parallel-cutoff-hz", "4"]) == 0
    doc = json.loads(report.read_text())
    [line] = doc["current_fits"]
    got = line["description_units"]
    # The fit's accuracy rides on the run's timing (the excitation is read back at its logged
    # times): quiet runs gave a = 97-99, CI once 89.6 (8.6 % low) over the pseudo-terminal,
    # whose fit off the bounds was repeated; over the emulator's socket the run misses few
    # deadlines (issue 30: under 0.5 % beside make test-fast) and runs once.
    # Measured in three runs: a 93.3, 97.9, 96.7 and b -11.46, -11.92, -11.80 (within 4.8 %
    # and 4.5 %), held-out NRMS 0.1-0.4 %; on the nominal grid (--sample-times nominal) the
    # same kind of log gave a = 48.8 and b = -7.4. Bounds: 8 % on each (the placeholder is
    # 10 % and 29 % away), and nearer the truth than the placeholder.
    assert abs(got["a"] - 98.0) < 0.08 * 98.0, got
    assert abs(got["b"] + 12.0) < 0.08 * 12.0, got
    assert abs(got["a"] - 98.0) < abs(TRUE_FIT[0] - 98.0)
    assert max(doc["prediction_nrms_percent"]["wls"]) < 5.0
