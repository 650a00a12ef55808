"""``build/cochlea-embedded`` (``make embedded``, docs/embedded.md) against ``cochlea-emulator``:
the C program with no Python runs the four studies over the virtual chain and tracks like
``cochlea-run --backend dynamixel`` on the same emulator; every fault ends in the safe stop with
cochlea-run's exit code, torque off in the emulator's log and the log kept; bad options are
refused before anything opens."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from cochlea.apps.report import CONVERGENCE_FLOOR, CONVERGENCE_RATIO, TAIL_FRACTION
from cochlea.dynamixel.drives import joint_drives
from cochlea.runtime.supervisor import STOP_CODES
from cochlea.sim import load_scenario, unit_setups
from tests.test_dynamixel_hil import (
    FAULTS,
    FLOOR,
    LOOP_TRANSPORT,
    SHARED_MACHINE,
    assert_fault_stop,
    assert_log_complete,
    chain_scenario,
    last_commands,
    run,
    run_on_emulator,
)
from tests.test_dynamixel_hil import emulator as started_emulator

pytestmark = pytest.mark.hil

ROOT = Path(__file__).resolve().parent.parent
PROGRAM = ROOT / "build" / "cochlea-embedded"
STUDIES = [("serial", "joint"), ("serial", "task"), ("parallel", "joint"), ("parallel", "task")]
#: cochlea-emulator prints its port before it serves at full pace: talked to at once, it falls
#: behind by tens of milliseconds now and then in its first seconds (seen about one run in
#: three; enough for the read watchdog). cochlea-run takes about 2 s to import before it talks;
#: the C program starts in a millisecond, so its tests give the emulator that time.
EMULATOR_SETTLE_S = 2.0
#: Runs that are not about failed reads tolerate more of them: a late reply (the machine's
#: real-time wake-up latency, docs/dynamixel.md) then costs a few late periods, not the run
#: (as SHARED_MACHINE does for deadline misses).
PATIENT = (*SHARED_MACHINE, "--watchdog-errors", "100")


@contextmanager
def emulator(robot: str, scenario: str, log: Path, *options: str,
             transport: str = LOOP_TRANSPORT):
    """``cochlea-emulator`` settled; its socket by default (the timed runs: no retry needed),
    ``transport="pty"`` for what opens a serial device (cochlea-dxl's bus)."""
    with started_emulator(robot, scenario, log, *options, transport=transport) as port:
        time.sleep(EMULATOR_SETTLE_S)
        yield port


def on_emulator(program: Path, tmp_path: Path, emulator_args: tuple, *args: str
                ) -> tuple[subprocess.CompletedProcess, Path, Path]:
    """``build/cochlea-embedded ARGS --out DIR`` on a fresh emulator, over its socket, once.
    The result, the output folder and the emulator's log."""
    out, log = tmp_path / "c", tmp_path / "emulator.log"
    with emulator(*emulator_args[:2], log, *emulator_args[2:]) as port:
        done = embedded(program, "--port", port, "--out", str(out), *args)
    return done, out, log


def embedded(program: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([str(program), *args], capture_output=True, text=True,
                          timeout=timeout)


def read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    with path.open() as f:
        header = f.readline().strip().split(",")
    return header, np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def assert_current_is_the_goal_sent(robot: str, header: list[str], rows: np.ndarray) -> None:
    """The log's measured current (UNIT.current.JOINT_A, after each unit's efforts) is what
    cochlea-emulator reports as Present Current in current control: the Goal Current sent for
    the previous period's effort, times the LSB, at the joint's sign (tests/test_current_fit's
    check of cochlea-run's log, here on any log with the drives in the loop's order)."""
    tau_cols = [h for h in header if ".tau." in h]
    current_cols = [h for h in header if ".current." in h]
    drives = joint_drives(robot)
    assert len(tau_cols) == len(current_cols) == len(drives)
    moving = 0
    for d, tau_col, i_col in zip(drives, tau_cols, current_cols):
        joint_col = re.sub(r"_(N_m|N)$", "", tau_col)  # the effort's unit (N m, N) off
        assert i_col == joint_col.replace(".tau.", ".current.") + "_A"
        assert header.index(tau_col) < header.index(i_col)  # after the unit's efforts
        tau, logged = rows[:, header.index(tau_col)], rows[:, header.index(i_col)]
        assert np.isfinite(logged).all()
        expected = np.sign(d.torque_per_effort) * d.goal_current_lsb(tau) * \
            d.spec.current_unit_mA * 1e-3
        # A read can overtake a late write (jitter on a shared machine): most periods, not
        # all, see the previous period's command.
        same = np.isclose(logged[1:], expected[:-1], rtol=0, atol=1e-9)
        assert same.mean() > 0.8, (d.name, same.mean())
        nonzero = int((logged[1:][same] != 0).sum())
        assert nonzero > 0, d.name  # not a column of zeros
        moving += nonzero
    # Hundreds of periods of at least one LSB at the proximal joints, tens at the distal ones
    # (measured on a 3 s serial_joint run: 20..786 per joint, 2459 in all).
    assert moving >= 200, moving


def python_resolution(name: str, q: np.ndarray) -> dict:
    """Per unit, cochlea-run's measurement_resolution at joint positions ``q`` (the loop's
    order) with the drives' encoder counts: the count in joint space, one count on every joint
    through the kinematics in task space."""
    scenario = load_scenario(name)
    counts = np.abs([d.q_per_count for d in joint_drives(scenario.robot)])
    out, start = {}, 0
    for u in unit_setups(scenario):
        n = u.controller_model.nq
        q_u, c_u = q[start:start + n], counts[start:start + n]
        if u.controller.space == "joint":
            out[u.name] = c_u
        else:
            pose = np.array(u.fk_world(q_u)).ravel()
            out[u.name] = sum(np.abs(np.array(u.fk_world(q_u + step)).ravel() - pose)
                              for step in np.diag(c_u))
        start += n
    return out


@pytest.mark.parametrize("robot,space", STUDIES)
def test_each_study_tracks_like_cochlea_run_on_the_same_emulator(tmp_path, program, robot,
                                                                 space):
    name, duration = f"{robot}_{space}", 5.0
    (tmp_path / "py").mkdir()
    chain = chain_scenario(name, tmp_path)  # serial_task: the motors with their rotors
    done, c_out, c_log = on_emulator(program, tmp_path, (robot, chain), "--scenario", name,
                                     "--duration", str(duration), *PATIENT)
    assert done.returncode == 0, done.stderr
    reference, py_out, _ = run_on_emulator(robot, chain, tmp_path / "py", "--robot", robot,
                                           "--space", space, "--duration", str(duration))
    assert reference.returncode == 0, reference.stderr

    # The report is written under temporary names and renamed: none is left behind.
    assert sorted(p.name for p in c_out.iterdir()) == ["log.bin", "log.columns.json", "log.csv",
                                                       "summary.json"]
    summary = json.loads((c_out / "summary.json").read_text())
    python = json.loads((py_out / "summary.json").read_text())
    # cochlea-run's schema: every key it writes, at every level the two share, issue 15's
    # runtime hardening included.
    assert set(python) <= set(summary)
    assert set(python["timing"]) <= set(summary["timing"])
    assert set(python["timing"]["bus"]) <= set(summary["timing"]["bus"])
    assert summary["timing"]["bus"]["homing"] == python["timing"]["bus"]["homing"]
    # Friction compensated once, decided by the same rule (issue 24).
    assert summary["timing"]["bus"]["friction_compensated_by"] == \
        python["timing"]["bus"]["friction_compensated_by"]
    # The same overrun rule, its limits from --watchdog-misses as cochlea-run's; an overrun
    # ends after the next deadline, so it is a deadline miss too (not the other way round).
    timing = summary["timing"]
    assert timing["overrun_policy"] == python["timing"]["overrun_policy"]
    assert timing["stall_limit"] == pytest.approx(timing["watchdog_misses_allowed"] * 1e-3)
    assert timing["lateness_limit"] == pytest.approx(max(timing["stall_limit"], 0.1))
    assert timing["overruns"] <= timing["deadline_misses"]
    # The real-time settings, recorded as cochlea-run records them.
    for part in ("requested", "obtained"):
        assert set(summary["realtime"][part]) == set(python["realtime"][part])
    assert summary["realtime"]["requested"] == {"mlockall": True, "cpu": None,
                                                "policy": "fifo", "priority": 40}
    for unit, entry in python["units"].items():
        assert set(entry) == set(summary["units"][unit])
        assert set(entry["tracked"]) == set(summary["units"][unit]["tracked"])
        assert entry["estimates"]["names"] == summary["units"][unit]["estimates"]["names"]
    # The same rule, with the encoder-count floor of the same drives.
    assert summary["convergence_rule"] == python["convergence_rule"]
    for unit, entry in python["units"].items():
        assert summary["units"][unit]["position_quantum"] == entry["position_quantum"]
        for coord, c in entry["tracked"].items():
            assert set(summary["units"][unit]["tracked"][coord]) == set(c)
    assert summary["stop"] == {"rule": "completed", "time_s": pytest.approx(duration),
                               "detail": "", "exit_code": 0}
    assert summary["periods"] == python["periods"] == int(duration * 1000)
    assert_log_complete(c_out, summary)
    bus = summary["timing"]["bus"]
    n = 6 if robot == "serial" else 5
    assert bus["reads"] == summary["periods"]  # the start-up's are kept apart
    assert bus["good_reads"] >= 0.98 * bus["reads"]
    assert f"torque off confirmed by all {n}" in bus["shutdown"]
    tail = last_commands(c_log)[-4 * n:]
    assert tail == [("sync-write", a, v) for a, v in [(102, 0)] * n + [(64, 0)] * n] * 2

    # The same log layout as cochlea-run's on the same emulator: log.bin's columns, the
    # measured current's included, and log.csv's header but its pose columns (the C program
    # has no forward kinematics for them); the current is the Goal Current sent.
    assert json.loads((c_out / "log.columns.json").read_text()) == \
        json.loads((py_out / "log.columns.json").read_text())
    c_head, c_rows = read_csv(c_out / "log.csv")
    py_head, py_rows = read_csv(py_out / "log.csv")
    assert c_head == [h for h in py_head if ".pose." not in h]
    assert any(".current." in h for h in c_head)
    assert_current_is_the_goal_sent(robot, c_head, c_rows)

    # The logged joint trajectory is cochlea-run's, to the tolerance of a run over the motors:
    # FLOOR is what one run may stray from the ideal one (the distal links stick and slip by
    # several counts, differently each run), so two runs differ by up to twice that at an
    # instant, and by FLOOR in RMS.
    shared = [h for h in c_head if ".q." in h]
    assert shared and set(shared) <= set(py_head)
    for h in shared:
        unit = h.rsplit("_", 1)[1]
        gap = np.abs(c_rows[:, c_head.index(h)] - py_rows[:, py_head.index(h)])
        assert gap.max() <= 2 * FLOOR[unit], (h, gap.max())
        assert np.sqrt(np.mean(gap ** 2)) <= FLOOR[unit], (h, np.sqrt(np.mean(gap ** 2)))
    # One count on every joint at the run's last pose, as cochlea-run's report computes it.
    resolution = python_resolution(name, c_rows[-1, [c_head.index(h) for h in shared]])
    for unit, entry in summary["units"].items():
        for i, c in enumerate(entry["tracked"].values()):
            assert c["measurement_resolution"] == pytest.approx(resolution[unit][i], rel=1e-6)
            assert c["convergence_floor"] == max(c["measurement_resolution"],
                                                 CONVERGENCE_FLOOR[c["unit"]])
    # ... and it converges as cochlea-run's does: tracking within the HIL floor of the run.
    for unit, entry in summary["units"].items():
        for coord, c in entry["tracked"].items():
            py = python["units"][unit]["tracked"][coord]
            assert c["initial_abs_error"] == pytest.approx(py["initial_abs_error"], rel=0.05,
                                                           abs=2 * FLOOR["m"])
            bound = max(CONVERGENCE_RATIO * c["initial_abs_error"],
                        py["final_rms_error"] + FLOOR[c["unit"]])
            assert c["final_rms_error"] <= bound, (unit, coord, c, py)
            # The summary's numbers are the CSV's, by cochlea-run's own rule.
            column = c_head.index(f"{unit}.error.{coord}_{c['unit']}")
            error = c_rows[:, column]
            tail = error[int(len(error) * (1 - TAIL_FRACTION)):]
            assert c["initial_abs_error"] == pytest.approx(abs(error[0]), rel=1e-9)
            assert c["final_rms_error"] == pytest.approx(np.sqrt(np.mean(tail ** 2)), rel=1e-6)
            assert c["converged"] == bool(c["final_rms_error"] <= max(
                CONVERGENCE_RATIO * c["initial_abs_error"], c["convergence_floor"]))


@pytest.mark.parametrize("name", FAULTS)
def test_every_fault_ends_in_the_safe_stop(tmp_path, program, name):
    options = FAULTS[name][0]
    done, out, log = on_emulator(program, tmp_path,
                                 ("serial", "serial_joint", "--fault-delay", "0.3", *options),
                                 "--scenario", "serial_joint", "--duration", "3",
                                 *SHARED_MACHINE)
    assert STOP_CODES["watchdog"] == 15
    summary = assert_fault_stop(done, out, log, name)
    assert "consecutive backend read failures" in summary["stop"]["detail"]


def test_a_motor_repeating_its_status_packet_is_refused_by_its_realtime_tick(tmp_path, program):
    """Motor 3 repeats its last status packet from 0.3 s on: its Realtime Tick stops moving,
    every read after the first repeat (within a tick and a tenth) fails as stale-packet, and
    the read watchdog stops the run safely, naming the motor, as cochlea-run's would."""
    done, out, log = on_emulator(program, tmp_path,
                                 ("serial", "serial_joint", "--fault-delay", "0.3",
                                  "--stale-replies", "3:-1"),
                                 "--scenario", "serial_joint", "--duration", "3",
                                 *SHARED_MACHINE)
    assert done.returncode == STOP_CODES["watchdog"], done.stderr
    summary = json.loads((out / "summary.json").read_text())
    bus = summary["timing"]["bus"]
    assert bus["realtime_tick_check"] is True
    assert bus["failures"].get("stale-packet", 0) >= 6, bus
    assert bus["last_failure"] == "stale-packet (ID 3, arm1.link3)"
    assert summary["stop"]["detail"] == ("6 consecutive backend read failures: last failure "
                                         "stale-packet from ID 3 (arm1.link3, MX-64)")
    assert_log_complete(out, summary)
    assert "torque off confirmed by all 6" in bus["shutdown"]
    assert summary["stop"]["time_s"] < 2.0


def test_real_time_settings_are_applied_recorded_and_a_refusal_is_one_warning(tmp_path, program):
    cpu = max(os.sched_getaffinity(0))
    done, out, _ = on_emulator(program, tmp_path, ("serial", "serial_joint"), "--scenario",
                               "serial_joint", "--duration", "1", "--sched", "rr",
                               "--priority", "30", "--mlockall", "off", "--cpu", str(cpu),
                               *PATIENT)
    assert done.returncode == 0, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    realtime = summary["realtime"]
    assert realtime["requested"] == {"mlockall": False, "cpu": cpu, "policy": "rr",
                                     "priority": 30}
    obtained, problems = realtime["obtained"], realtime["problems"]
    warnings = [line for line in done.stderr.splitlines() if "warning: real-time" in line]
    assert len(warnings) == (1 if problems else 0)
    # Pinned to one CPU unless refused; rr 30 unless refused; memory left unlocked as asked.
    assert obtained["mlockall"] is False and summary["timing"]["memory"] == "not locked"
    assert (obtained["cpu"] == [cpu]) != any("CPU affinity" in p for p in problems)
    rr = (obtained["policy"], obtained["priority"]) == ("rr", 30)
    assert rr != any("SCHED_RR 30 not permitted" in p for p in problems)
    assert summary["timing"]["scheduling"] == ("SCHED_RR 30" if rr else
                                               "normal (SCHED_RR not permitted)")


def _slider():
    return next(d for d in joint_drives("parallel") if d.type == "prismatic")


def _hold_marker(port: str, marker: int) -> None:
    """Leave ``marker`` in the emulator's slider as cochlea-dxl home leaves its token (through
    its bus: the bridge's open_bus/close_bus are gone, cochlea-dxl's subcommands share one)."""
    from cochlea.dynamixel.bringup.common import Bus
    from cochlea.dynamixel.homing import marker_item

    with Bus(port, 4_000_000) as bus:
        bus.write(_slider().id, marker_item(_slider()), marker)


def _record(path: Path, marker: int, shift_m: float, *, legacy: bool = False) -> Path:
    """A homing record of the emulator's slider whose stop puts it ``shift_m`` beyond where the
    description's zero_offset_deg counts it: as cochlea-dxl home writes it (cochlea-homing/2,
    one entry), or ``legacy``, as it did before issue 25 (cochlea-homing/1, flat)."""
    from cochlea.dynamixel.homing import FORMAT, FORMAT_1

    d = _slider()
    entry = {"joint": d.name, "motor_id": d.id, "model": d.spec.name, "raw_counts": 0,
             "stop_m": d.q_offset + shift_m, "direction": d.direction,
             "ratio_m_per_rad": d.ratio, "marker_address": 88, "marker": marker}
    top = {"robot": "parallel", "description": "shipped", "date": "2026-11-23T10:00:00"}
    record = {"format": FORMAT_1, **top, **entry} if legacy else \
        {"format": FORMAT, **top, "port": "/dev/ttyUSB0", "joints": [entry]}
    path.write_text(json.dumps(record, indent=2))
    return path


def test_an_unhomed_slider_is_refused_before_any_write(tmp_path, program):
    """--homing required on the emulator's pseudo-terminal: without a record, and with a record
    whose token the motor no longer holds (power-cycled since), the start is refused before
    any write (exit 5, naming cochlea-dxl home) and nothing is left behind."""
    for case, record in (("none", tmp_path / "none.json"),
                         ("stale", _record(tmp_path / "stale.json", 4321, 0.0, legacy=True))):
        log, out = tmp_path / f"{case}.log", tmp_path / case
        with emulator("parallel", "parallel_joint", log, transport="pty") as port:
            done = embedded(program, "--scenario", "parallel_joint", "--port", port,
                            "--duration", "1", "--out", str(out), "--homing", "required",
                            "--homing-record", str(record))
        assert done.returncode == 5, done.stderr
        errors = [line for line in done.stderr.splitlines() if ": warning: " not in line]
        assert len(errors) == 1 and "cochlea-dxl home" in errors[0]  # one line
        expected = ("the slider is not homed: no homing record" if case == "none" else
                    f"the slider (ID {_slider().id}) was power-cycled or rebooted since it was "
                    "homed (2026-11-23T10:00:00)")
        assert expected in done.stderr, done.stderr
        if case == "none":  # a user description's record is elsewhere: the line says how
            assert "--description FILE" in errors[0]
        assert " write " not in log.read_text()  # refused before any write
        assert not out.exists()


@pytest.mark.parametrize("text, message", [
    ("{", "not a cochlea-homing/2 record (nor a cochlea-homing/1 one); run cochlea-dxl home "
          "again"),
    ('{"format": "cochlea-homing/1", "motor_id": 1}', "not a cochlea-homing/2 record"),
    ('{"format": "cochlea-homing/2", "robot": "parallel", "joints": [{"motor_id": 3}, '
     '{"motor_id": 4}]}', "holds 2 joints; this robot has one prismatic joint"),
    ('{"format": "cochlea-homing/2", "robot": "serial", "joints": [{"motor_id": 3}]}',
     "was made for the serial robot, not the parallel one"),
    ('{"format": "cochlea-homing/1", "motor_id": 1.5, "raw_counts": 0, "marker": 1, '
     '"stop_m": 0, "ratio_m_per_rad": 0.02, "direction": 1}', "not a cochlea-homing/2 record"),
    ('{"format": "cochlea-homing/1", "motor_id": 7, "raw_counts": 0, "marker": 1, '
     '"stop_m": 0, "ratio_m_per_rad": 0.02, "direction": 1}', "was made for motor ID 7"),
])
def test_a_wrong_homing_record_is_refused_before_the_port_opens(tmp_path, program, text,
                                                                 message):
    record = tmp_path / "record.json"
    record.write_text(text)
    done = embedded(program, "--scenario", "parallel_joint", "--port", "/dev/ttyUSB-none",
                    "--out", str(tmp_path / "run"), "--homing", "required", "--homing-record",
                    str(record))
    assert done.returncode == 5 and message in done.stderr, done.stderr
    assert "nothing moved" in done.stderr and not (tmp_path / "run").exists()


def test_a_homed_slider_is_counted_from_its_record(tmp_path, program):
    """The same start on the emulator, unchecked (auto on a pseudo-terminal) and checked
    against a record whose stop lies 1 mm beyond the description's zero: the second counts the
    slider 1 mm further, restores the token after the configuration, and reports the homing."""
    shift, marker = 1e-3, 1234
    first = {}
    for case in ("auto", "required"):
        log, out = tmp_path / f"{case}.log", tmp_path / case
        with emulator("parallel", "parallel_joint", log, transport="pty") as port:
            args = []
            if case == "required":
                _hold_marker(port, marker)
                args = ["--homing", "required", "--homing-record",
                        str(_record(tmp_path / "homed.json", marker, shift))]
            done = embedded(program, "--scenario", "parallel_joint", "--port", port,
                            "--duration", "0.2", "--out", str(out), *PATIENT, *args)
        assert done.returncode == 0, done.stderr
        head, rows = read_csv(out / "log.csv")
        first[case] = rows[0, next(i for i, h in enumerate(head) if ".q." in h and "d1" in h)]
        bus = json.loads((out / "summary.json").read_text())["timing"]["bus"]
        if case == "auto":
            assert bus["homing"] == "not checked (a pseudo-terminal: the virtual chain)"
        else:
            assert bus["homing"] == f"homed 2026-11-23T10:00:00 ({tmp_path / 'homed.json'})"
            events = log.read_text().splitlines()
            writes = [i for i, e in enumerate(events) if " write " in e]
            # The token written back after the configuration, the last unicast write; the
            # torque comes on after it (one SYNC_WRITE to the five motors).
            assert events[writes[-1]].split()[2:] == [f"id={_slider().id}", "address=88",
                                                      "value=1234"]
            ons = [i for i, e in enumerate(events)
                   if e.split()[1:2] == ["sync-write"] and e.split()[3:] == ["address=64",
                                                                            "value=1"]]
            assert len(ons) == 5 and min(ons) > writes[-1]
    quantum = abs(_slider().q_per_count)
    assert abs(first["required"] - first["auto"] - shift) <= 2 * quantum


def torque_on_window(log: Path) -> list[list[str]]:
    """``[kind, id=, address=, value=]`` of the instructions in an emulator's log after the
    Goal Current that preceded the first Torque Enable 1, up to the first one about another
    item: start-up step 9's transactions."""
    rows = [line.split()[1:] for line in log.read_text().splitlines()]
    rows = [r for r in rows if r[0] not in ("fault", "watchdog")]
    first_on = next(i for i, r in enumerate(rows) if r[2:] == ["address=64", "value=1"])
    goal = max(i for i, r in enumerate(rows[:first_on]) if r[2] == "address=102")
    window = []
    for r in rows[goal + 1:]:
        if r[2] != "address=64":
            break
        window.append(r)
    return window


def test_a_torque_that_does_not_take_stops_both_programs_alike(tmp_path, program):
    """``cochlea-emulator --ignore-write 3:64``: motor 3 acknowledges its Torque Enable 1 and
    stays unpowered (it reads back 0). cochlea-run and the C program refuse it at the first
    nonzero command (start-up step 9) the same way: the read watchdog's stop (exit 15) on
    not-enabled reads naming motor 3, torque off confirmed by every motor; and the emulator's
    logs of the two hold the same torque-on: one SYNC_WRITE of Torque Enable 1 to the six
    motors, one SYNC_READ of Torque Enable, nothing else in between."""
    windows = {}
    for side in ("cochlea-run", "c"):
        out, log = tmp_path / side, tmp_path / f"{side}.log"
        with emulator("serial", "serial_joint", log, "--ignore-write", "3:64") as port:
            if side == "c":
                done = embedded(program, "--scenario", "serial_joint", "--port", port,
                                "--duration", "3", "--out", str(out), *SHARED_MACHINE)
            else:
                done = run("--robot", "serial", "--space", "joint", "--backend", "dynamixel",
                           "--port", port, "--duration", "3", "--out", str(out), cwd=tmp_path)
        assert done.returncode == 15, done.stderr
        assert "stopped by rule watchdog" in done.stderr and "Traceback" not in done.stderr
        summary = json.loads((out / "summary.json").read_text())
        bus = summary["timing"]["bus"]
        assert summary["stop"]["time_s"] < 0.05, summary["stop"]
        assert bus["failures"]["not-enabled"] >= 6 and set(bus["failures"]) == {"not-enabled"}
        assert bus["last_failure"].startswith("not-enabled (ID 3, "), bus["last_failure"]
        assert bus["shutdown"].endswith("torque off confirmed by all 6"), bus["shutdown"]
        if side == "cochlea-run":
            assert ("consecutive backend read failures: the torque did not come on: ID 3 "
                    "(arm1.link3, MX-64) reads Torque Enable 0") in summary["stop"]["detail"]
        windows[side] = torque_on_window(log)
    ons = [["ignored-sync-write" if i == 3 else "sync-write", f"id={i}", "address=64",
            "value=1"] for i in range(1, 7)]
    assert windows["c"] == windows["cochlea-run"] == ons + [["sync-read", "id=254",
                                                             "address=64", "value=1"]]


@pytest.mark.parametrize("options, message", [
    (["--missing-motor", "3"], "ID 3 (arm1.link3, MX-64) did not answer PING"),
    (["--model-number", "5:1120"], "ID 5 (arm2.link2, MX-64) is model number 1120"),
])
def test_a_wrong_bus_stops_before_anything_moves(tmp_path, program, options, message):
    log = tmp_path / "emulator.log"
    with emulator("serial", "serial_joint", log, *options) as port:
        done = embedded(program, "--scenario", "serial_joint", "--port", port, "--duration",
                        "1", "--out", str(tmp_path / "c"))
    assert done.returncode == 5, done.stderr
    assert "the backend could not start, nothing moved" in done.stderr and message in done.stderr
    assert " write " not in log.read_text()  # nothing was configured, let alone enabled
    assert not (tmp_path / "c").exists()  # the start is undone: the identical retry can run


def test_a_robot_away_from_the_scenarios_start_stops_before_anything_moves(tmp_path, program):
    """serial_task's controller on a chain standing at serial_joint's initial pose: exit 5
    naming the first joint away (arm1.link1: 73 deg, the scenario's 83.5 deg), as cochlea-run
    refuses it (which names every joint away); the torque never on; a non-physical tolerance
    refused as a usage error."""
    log = tmp_path / "emulator.log"
    with emulator("serial", "serial_joint", log) as port:
        done = embedded(program, "--scenario", "serial_task", "--port", port, "--duration",
                        "1", "--out", str(tmp_path / "c"))
    assert done.returncode == 5, done.stderr
    assert re.search(r"the backend could not start, nothing moved: the robot is not at the "
                     r"scenario's initial pose: ID 1 \(arm1\.link1, MX-64\) is at 73\.0\d deg, "
                     r"the scenario starts it at 83\.5\d deg \(tolerance 5 deg, 5 mm\)",
                     done.stderr), done.stderr
    assert not [e for e in log.read_text().splitlines()
                if " write " in e and e.split()[3:] == ["address=64", "value=1"]]
    assert not (tmp_path / "c").exists()
    for bad in ("nan", "0", "-1", "inf"):
        done = embedded(program, "--scenario", "serial_task", "--port", "/dev/null",
                        "--out", str(tmp_path / "c"), "--start-tolerance-deg", bad)
        assert done.returncode == 2 and "--start-tolerance-deg must be a positive number" \
            in done.stderr, done.stderr


def _interrupted_run(program: Path, tmp_path: Path, interrupt) -> tuple:
    """serial_joint on a fresh emulator (its socket), ``interrupt(proc, log)`` 1.5 s after the
    start (the motors' start-up, then about a second of running)."""
    out, log = tmp_path / "c", tmp_path / "emulator.log"
    with emulator("serial", "serial_joint", log) as port:
        proc = subprocess.Popen([str(program), "--scenario", "serial_joint", "--port", port,
                                 "--duration", "10", "--out", str(out), *PATIENT],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(1.5)
        running = proc.poll() is None
        if running:
            interrupt(proc, log)
        _, stderr = proc.communicate(timeout=30)
    assert running, f"the run stopped before its interruption: {stderr}"
    return proc, stderr, out, log


def test_the_emulator_killed_mid_run_ends_in_the_safe_stop(tmp_path, program):
    def kill_emulator(proc, log):
        pids = subprocess.run(["pgrep", "-f", f"cochlea.dynamixel.emulator.*{log}"],
                              capture_output=True, text=True).stdout.split()
        assert pids
        for pid in pids:
            os.kill(int(pid), signal.SIGKILL)

    proc, stderr, out, _ = _interrupted_run(program, tmp_path, kill_emulator)
    assert proc.returncode == 15, stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stop"]["rule"] == "watchdog" and summary["stop"]["time_s"] < 9.9
    assert_log_complete(out, summary)
    bus = summary["timing"]["bus"]
    assert "port" in bus["failures"] or "timeout" in bus["failures"], bus
    assert "not confirmed by" in bus["shutdown"]


def test_sigint_is_the_users_stop(tmp_path, program):
    proc, stderr, out, _ = _interrupted_run(
        program, tmp_path, lambda proc, log: proc.send_signal(signal.SIGINT))
    assert proc.returncode == 0, stderr
    assert "stopped by the user" in stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stop"]["rule"] == "user-stop" and summary["stop"]["time_s"] < 9.0
    assert_log_complete(out, summary)
    assert "torque off confirmed by all 6" in summary["timing"]["bus"]["shutdown"]


@pytest.mark.parametrize("args, code, text", [
    (["--scenario", "serial_task"], 2, "--scenario, --port and --out are needed"),
    (["--scenario", "nope", "--port", "/dev/null", "--out", "X"], 2, "no scenario nope"),
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--duration", "-1"],
     2, "--duration must be positive"),
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--duration", "nan"],
     2, "--duration must be positive"),
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--duration", "inf"],
     2, "at most 86400 s"),
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--duration", "1e300"],
     2, "at most 86400 s"),
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--baud", "fast"],
     2, "--baud must be a whole number"),
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--watchdog-misses",
      "0"], 2, "--watchdog-misses must be between 1 and"),
    (["--scenario", "serial_task", "--port", "/dev/pts/999", "--out", "X", "--baud",
      "1000000"], 2, "the bus cannot meet the loop rate"),
    (["--scenario", "serial_task", "--port", "/dev/ttyUSB-none", "--out", "X"], 5,
     "cannot open the serial port /dev/ttyUSB-none"),
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--bogus", "1"], 2,
     "unknown option --bogus"),
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--watchdog-errors",
      "0"], 2, "--watchdog-errors must be between 1 and"),
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--rate", "50000"], 2,
     "--rate must be between 1 and 20000 Hz"),
    # cochlea-run's real-time options, refused as check_realtime_options refuses them.
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--sched", "other",
      "--priority", "3"], 2, "--priority goes with --sched fifo or rr"),
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--priority", "0"], 2,
     "--priority must be between 1 and 99 for --sched fifo, got 0"),
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--sched", "batch"], 2,
     "--sched: expected one of fifo, rr, other"),
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--cpu", "4096"], 2,
     "--cpu 4096 is not a CPU this process may use: expected one of"),
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--cpu", "-1"], 2,
     "--cpu -1 is not a CPU this process may use"),
    (["--scenario", "serial_task", "--port", "/dev/null", "--out", "X", "--mlockall", "yes"],
     2, "--mlockall: expected on or off, got yes"),
    # 1 Mbaud carries 6 motors at 400 Hz (1900 us of bus per 2500 us): past the budget, to
    # the port (which is missing).
    (["--scenario", "serial_task", "--port", "/dev/ttyUSB-none", "--out", "X", "--baud",
      "1000000", "--rate", "400"], 5, "cannot open the serial port /dev/ttyUSB-none"),
])
def test_bad_options_are_refused_with_a_message(tmp_path, program, args, code, text):
    done = subprocess.run([str(program), *args], capture_output=True, text=True, timeout=30,
                          cwd=tmp_path)
    assert done.returncode == code and text in done.stderr, done.stderr
    assert list(tmp_path.iterdir()) == []  # nothing left behind, not even an empty --out


def test_a_failed_start_removes_only_what_it_created(tmp_path, program):
    """The port does not open: the folders the run made go, with its log.bin and
    log.columns.json; a folder the user made stays (empty), so the same command can run again."""
    mine = tmp_path / "mine"
    mine.mkdir()
    for out in (tmp_path / "deep" / "er" / "run", mine):
        done = embedded(program, "--scenario", "serial_task", "--port", "/dev/ttyUSB-none",
                        "--out", str(out))
        assert done.returncode == 5, done.stderr
        assert [p.name for p in tmp_path.iterdir()] == ["mine"]
    assert list(mine.iterdir()) == []


def test_a_used_output_folder_is_refused(tmp_path, program):
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "log.csv").write_text("keep me\n")
    done = embedded(program, "--scenario", "serial_task", "--port", "/dev/null", "--out",
                    str(tmp_path / "used"))
    assert done.returncode == 2 and "is not empty" in done.stderr
    assert (tmp_path / "used" / "log.csv").read_text() == "keep me\n"


def test_cochlea_identify_reads_the_programs_log_with_its_current(tmp_path, program):
    """A log of the C program is one cochlea-identify reads (cochlea.ident.logs.read_run, as
    for cochlea-run's), the measured current included: present, finite, the CSV's columns,
    and the Goal Current the emulator was sent."""
    import cochlea
    from cochlea.ident.logs import read_run

    done, out, _ = on_emulator(program, tmp_path, ("serial", "serial_joint"), "--scenario",
                               "serial_joint", "--duration", "3", *PATIENT)
    assert done.returncode == 0, done.stderr
    model = cochlea.model("serial", parameterisation="base", actuators="all")
    header, rows = read_csv(out / "log.csv")
    for unit in ("arm1", "arm2"):
        log = read_run(out, model, "serial", unit)
        assert log.rows == len(rows) == 3000
        assert log.current is not None and log.current.shape == (3000, 3)
        assert np.isfinite(log.current).all() and np.abs(log.current).max() > 0
        columns = [header.index(f"{unit}.current.{j.name}_A") for j in model.joints]
        assert np.array_equal(log.current, rows[:, columns])
    assert_current_is_the_goal_sent("serial", header, rows)
