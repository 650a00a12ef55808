"""Issue 13, the emulator and the bridge, and messages: every bad option of cochlea-emulator
refused in one line before anything is served, the emulator answering SIGINT, SIGTERM and
--duration in any valid configuration, baud rates the motors do not have refused by every
program, and the stop line of a motor's hardware alert naming the motor and the alert."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cochlea.dynamixel import protocol as proto
from cochlea.dynamixel.emulator import Faults, VirtualChain, check_faults
from cochlea.dynamixel.emulator import main as emulator_main
from cochlea.errors import EXIT_USER_ERROR, CochleaError

ROOT = Path(__file__).resolve().parents[1]


def refused(capsys, argv: list[str]) -> str:
    """Run cochlea-emulator in-process on ``argv``: it must refuse with exit 2 and one line."""
    try:
        code = emulator_main(argv)
    except SystemExit as exc:  # the parser's own refusals
        code = exc.code
    err = capsys.readouterr().err
    assert code == EXIT_USER_ERROR, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cochlea-emulator: "), err
    assert "Traceback" not in err
    return lines[0]


# ---- class 8: every option validated ---------------------------------------------------------

@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "-inf", "1e-6", "0.049", "51",
                                   "1e300"])
def test_plant_periods_outside_the_sane_range_are_refused(capsys, value):
    line = refused(capsys, ["--robot", "serial", f"--plant-period-ms={value}"])
    # a value that is no number is the parser's refusal, a number out of range the option's
    expected = "plain decimal number" if "n" in value else "expected 0.05 to 50 ms"
    assert "--plant-period-ms" in line and expected in line


@pytest.mark.parametrize("value", ["0", "-2", "nan", "inf", "-inf", "x"])
def test_durations_that_are_not_positive_and_finite_are_refused(capsys, value):
    assert "--duration" in refused(capsys, ["--robot", "parallel", f"--duration={value}"])


@pytest.mark.parametrize("option,value", [
    ("--drop-replies", "nan"), ("--corrupt-crc", "inf"), ("--late-replies", "-0.1"),
    ("--drop-replies", "1.0001"), ("--late-ms", "nan"), ("--late-ms", "-1"),
    ("--late-ms", "1e9"), ("--fault-delay", "inf"), ("--fault-delay", "nan"),
    ("--fault-delay", "-1")])
def test_fault_numbers_out_of_range_are_refused(capsys, option, value):
    assert option in refused(capsys, ["--robot", "serial", f"{option}={value}"])


@pytest.mark.parametrize("robot,option,value", [
    ("serial", "--silent-motor", "7"), ("serial", "--silent-motor", "-1"),
    ("serial", "--hardware-error", "42"), ("serial", "--hardware-error", "0:5"),
    ("serial", "--fault-ids", "1,77"), ("parallel", "--fault-ids", "6"),
    ("parallel", "--missing-motor", "6"), ("serial", "--model-number", "300:311"),
    ("parallel", "--hardware-error", "9:2")])
def test_faults_naming_motors_that_are_not_on_the_chain_are_refused(capsys, robot, option,
                                                                      value):
    line = refused(capsys, ["--robot", robot, option, value])
    assert option in line and "is not on this chain" in line


@pytest.mark.parametrize("option,value", [
    ("--model-number", "3:70000"), ("--model-number", "3:-1"), ("--fault-ids", ","),
    ("--hardware-error", "3:1"), ("--hardware-error", "3:x"), ("--fault-ids", "a,b"),
    ("--seed", "1.5"), ("--nonsense", "1")])
def test_malformed_fault_options_are_one_line(capsys, option, value):
    refused(capsys, ["--robot", "serial", f"{option}={value}"])


def test_the_library_checks_what_the_command_checks():
    ids = [1, 2, 3]
    for faults in (Faults(drop=float("nan")), Faults(late_s=-1.0), Faults(silent=9),
                   Faults(hardware_error=(1, 1)), Faults(delay_s=float("inf")),
                   Faults(model_number={1: 1 << 16}), Faults(ids=frozenset())):
        with pytest.raises(CochleaError):
            check_faults(faults, ids)
    check_faults(Faults(drop=1.0, ids=frozenset({3}), hardware_error=(2, 5), silent=1), ids)
    with pytest.raises(CochleaError, match="--plant-period-ms"):
        VirtualChain("serial", plant_period_s=0.0)


@pytest.mark.slow
def test_a_log_that_cannot_be_written_is_refused_and_nothing_is_left(tmp_path, capsys):
    plain = tmp_path / "plain"
    plain.write_text("")
    for log in (tmp_path, plain / "events.txt", tmp_path / "missing" / "events.txt"):
        line = refused(capsys, ["--robot", "serial", "--log", str(log)])
        assert f"--log {log}" in line and "expected a file in a writable folder" in line
    # A refused option leaves no log file behind, even when the log's path itself is fine.
    log = tmp_path / "events.txt"
    refused(capsys, ["--robot", "serial", "--log", str(log), "--silent-motor", "9"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plain"]


@pytest.mark.hil
def test_a_log_that_fails_while_serving_stops_the_chain_with_its_own_code():
    """/dev/full: every write fails with ENOSPC, as on a full disk."""
    proc, fd = _start("--robot", "serial", "--log", "/dev/full", "--duration", "30")
    try:
        for _ in range(400):  # more events than the log's buffer holds
            try:
                os.write(fd, proto.ping(1))
            except OSError:
                break  # the chain stopped and closed its end
            time.sleep(0.001)
        out, err = proc.communicate(timeout=60)
    finally:
        os.close(fd)
    lines = err.strip().splitlines()
    assert proc.returncode == 3, err
    assert len(lines) == 1 and "writing the event log /dev/full failed" in lines[0], err
    assert "--log" in lines[0] and "Traceback" not in err
    assert "cochlea-emulator: stopped (" in out


# ---- class 8: responsive to signals and --duration in any valid configuration --------------

def _start(*options: str) -> tuple[subprocess.Popen, int]:
    """The emulator with ``options``, every motor driven (current mode, Goal Current 0, torque
    on) so the plant integrates at every step: the heaviest work its options can ask for."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "cochlea.dynamixel.emulator", "--priority", "normal", *options],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    path = proc.stdout.readline().strip()
    assert path.startswith("/dev/"), proc.stderr.read() if proc.poll() is not None else path
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    for motor_id in range(1, 7):
        for address, value, size in ((11, 0, 1), (102, 0, 2), (64, 1, 1)):
            os.write(fd, proto.write(motor_id, address, proto.le(value, size)))
            time.sleep(0.005)
    return proc, fd


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


EXTREME = [
    ("--robot", "parallel", "--plant", "realistic", "--plant-period-ms", "0.05"),
    ("--robot", "serial", "--plant-period-ms", "0.05", "--wire-timing", "--baud", "9600",
     "--late-replies", "1", "--late-ms", "10000"),
    ("--robot", "serial", "--plant-period-ms", "50", "--drop-replies", "1"),
]


@pytest.mark.hil
@pytest.mark.parametrize("options", EXTREME)
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_extreme_options_still_answer_signals(options, signum):
    proc, fd = _start(*options)
    try:
        # The plant's smallest step costs more than real time allows on this machine: the
        # emulator must fall behind (and count it), never spin: a spin under SCHED_FIFO would
        # starve the machine. Only a spin can use the whole of a processor.
        before, start = _cpu_seconds(proc.pid), time.monotonic()
        time.sleep(1.5)
        share = (_cpu_seconds(proc.pid) - before) / (time.monotonic() - start)
        assert share < 0.95, share
        proc.send_signal(signum)
        out, err = proc.communicate(timeout=30)
    finally:
        os.close(fd)
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert "cochlea-emulator: stopped (" in out and "Traceback" not in err


@pytest.mark.hil
def test_duration_ends_the_most_demanding_configuration():
    proc, fd = _start(*EXTREME[0], "--duration", "1")
    try:
        out, err = proc.communicate(timeout=60)
    finally:
        os.close(fd)
    assert proc.returncode == 0, err
    assert "plant_overruns" in out and "Traceback" not in err


# ---- class 8: baud rates the motors do not have, in every program --------------------------

BAD_BAUDS = ["0", "-5", "12345", "4000001", "1"]


@pytest.mark.parametrize("baud", BAD_BAUDS)
def test_the_emulator_refuses_rates_the_motors_do_not_have(capsys, baud):
    line = refused(capsys, ["--robot", "serial", f"--baud={baud}"])
    assert f"--baud {baud} is not a Dynamixel rate" in line and "4500000" in line


@pytest.mark.parametrize("baud", [0, -5, 12345, 4_000_001, True, 4e6])
def test_the_bridge_refuses_them_as_the_user_s_mistake_before_the_port(baud):
    from cochlea.dynamixel.bridge import DynamixelBackend  # noqa: PLC0415
    from cochlea.runtime import BackendError  # noqa: PLC0415

    with pytest.raises(CochleaError, match="is not a Dynamixel rate") as caught:
        DynamixelBackend("serial", "/dev/null-never-opened", baud)
    assert not isinstance(caught.value, BackendError)  # exit 2, not "could not start"


@pytest.mark.parametrize("baud", ["0", "-5", "12345"])
@pytest.mark.slow
def test_cochlea_run_refuses_them_in_one_line(tmp_path, baud):
    done = subprocess.run(
        [sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial", "--space",
         "joint", "--backend", "dynamixel", "--port", "/dev/null-never-opened",
         f"--baud={baud}", "--out", str(tmp_path / "run")],
        capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == EXIT_USER_ERROR, done.stderr
    assert done.stderr.strip().splitlines() == [
        f"cochlea-run: --baud {baud} is not a Dynamixel rate: expected one of 9600, 57600, "
        "115200, 1000000, 2000000, 3000000, 4000000, 4500000"]
    assert sorted(tmp_path.iterdir()) == []  # refused before any folder was made



@pytest.mark.parametrize("baud", [*BAD_BAUDS, "nan", "4e6x", "115200.5"])
@pytest.mark.slow
def test_the_c_program_refuses_them_in_one_line(tmp_path, program, baud):
    out = tmp_path / "run"
    done = subprocess.run([str(program), "--scenario", "serial_joint", "--port",
                           "/dev/null-never-opened", "--baud", baud, "--out", str(out)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == EXIT_USER_ERROR, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "--baud must be a whole number of baud the motors have" in \
        lines[0] and lines[0].endswith(f"got {baud}")
    assert not out.exists()


# ---- class 9: the stop line of a motor's alert names the motor and the alert --------------

@pytest.mark.hil
@pytest.mark.parametrize("fault,expected", [
    ("3:2", "ID 3 (arm1.link3, MX-64): hardware error (overheating)"),
    ("5:4", "ID 5 (arm2.link2, MX-64): hardware error (electrical shock)"),
    (None, "last failure timeout from ID 3 (arm1.link3, MX-64)")])
def test_cochlea_run_s_stop_line_names_the_motor_and_its_alert(tmp_path, fault, expected):
    from tests.test_dynamixel_hil import LOOP_TRANSPORT, emulator, run  # noqa: PLC0415

    options = ["--hardware-error", fault] if fault else ["--silent-motor", "3"]
    out = tmp_path / "run"
    with emulator("serial", "serial_joint", tmp_path / "emulator.log", "--fault-delay", "0.3",
                  *options, transport=LOOP_TRANSPORT) as port:
        done = run("--robot", "serial", "--space", "joint", "--backend", "dynamixel", "--port",
                   port, "--duration", "3", "--out", str(out), cwd=tmp_path)
    assert done.returncode == 15, done.stderr
    (line,) = [x for x in done.stderr.splitlines() if "stopped by rule watchdog" in x]
    assert "consecutive backend read failures: " + expected in line, line
    summary = json.loads((out / "summary.json").read_text())
    assert expected in summary["stop"]["detail"]


@pytest.mark.hil
@pytest.mark.parametrize("fault,expected", [
    ("3:0", "ID 3 (arm1.link3, MX-64): hardware error (input voltage)"),
    ("2:5", "ID 2 (arm1.link2, MX-64): hardware error (overload)"),
    # Which motor a timed-out read blames first depends on where the emulator was: any of them.
    (None, "last failure timeout from ID ")])
def test_the_c_program_s_stop_line_names_the_motor_and_its_alert(tmp_path, program, fault,
                                                                expected):
    from tests.test_embedded_program import PATIENT, emulator  # noqa: PLC0415

    options = ["--hardware-error", fault] if fault else ["--silent-motor", "3"]
    out = tmp_path / "run"
    with emulator("serial", "serial_joint", tmp_path / "emulator.log", "--fault-delay", "0.3",
                  *options) as port:
        done = subprocess.run(
            [str(program), "--scenario", "serial_joint", "--port", port, "--duration", "3",
             "--out", str(out), *PATIENT[:2]], capture_output=True, text=True, timeout=120)
    assert done.returncode == 15, done.stderr
    (line,) = [x for x in done.stderr.splitlines() if "stopped by rule watchdog" in x]
    assert "consecutive backend read failures: " + expected in line, line
    summary = json.loads((out / "summary.json").read_text())
    assert expected in summary["stop"]["detail"]


# ---- class 9: a reader that goes away, a full output ------------------------------------------

def _closed_pipe() -> int:
    """The write end of a pipe whose reader is already gone: the first write fails (EPIPE),
    whatever the timing, as in ``| head -1`` once head has exited."""
    r, w = os.pipe()
    os.close(r)
    return w


@pytest.mark.parametrize("argv", [["serial"], ["parallel"], ["serial", "--arm", "arm2"]])
@pytest.mark.slow
def test_cochlea_model_ends_quietly_when_its_reader_goes_away(argv):
    w = _closed_pipe()
    try:
        done = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_model", *argv],
                              stdout=w, stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(w)
    assert done.stderr == "" and done.returncode == 128 + signal.SIGPIPE


@pytest.mark.slow
def test_cochlea_model_through_head_prints_its_first_line_only():
    done = subprocess.run(f"{sys.executable} -u -m cochlea.apps.cochlea_model parallel | head -1",
                          shell=True, capture_output=True, text=True, timeout=120)
    assert done.stdout.startswith("model 'parallel'") and done.stdout.count("\n") == 1
    assert done.stderr == ""


@pytest.mark.slow
def test_cochlea_model_on_a_full_disk_says_so_in_one_line():
    with open("/dev/full", "w") as full:
        done = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_model"], stdout=full,
                              stderr=subprocess.PIPE, text=True, timeout=120)
    assert done.returncode == 1
    assert done.stderr.splitlines() == ["cochlea-model: cannot write the output: No space left "
                                        "on device"]


@pytest.mark.hil
def test_the_emulator_keeps_serving_when_the_reader_of_its_path_goes_away():
    w = _closed_pipe()
    try:
        proc = subprocess.Popen([sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot",
                                 "serial", "--priority", "normal", "--duration", "1"],
                                stdout=w, stderr=subprocess.PIPE, text=True)
    finally:
        os.close(w)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0 and err == ""
