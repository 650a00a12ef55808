"""Issue 26, a hang-up is not a stop: SIGHUP (the terminal or SSH session that started a program
closed) is treated like SIGTERM by every program. A run ends in the same safe stop (zero effort,
torque off, the log and summary written) with SIGTERM's exit code 16 and a stop detail naming
the hang-up; cochlea-emulator flushes and closes its --log; cochlea-sweep leaves a folder that
resumes; a standard output or error that closed with the terminal (EIO, EPIPE) fails its
writes, never the safe stop. The embedded program names only the report files it wrote."""

from __future__ import annotations

import contextlib
import json
import os
import pty
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cochlea import console
from cochlea.apps import cochlea_sweep, outputs
from cochlea.dynamixel import protocol as proto
from cochlea.dynamixel.drives import joint_drives
from cochlea.runtime.supervisor import SIGNAL_STOPS, STOP_CODES
from cochlea.sweep import results
from tests.test_dynamixel_hil import (
    LOOP_TRANSPORT,
    assert_log_complete,
    chain_scenario,
    last_commands,
)
from tests.test_dynamixel_hil import emulator as started_emulator
from tests.test_embedded_program import PATIENT, _interrupted_run, emulator
from tests.test_outputs import (
    test_signals_held_over_a_section_are_obeyed_after_it as held_over_a_section,
)
from tests.test_runtime import _cli, make_loop
from tests.test_sweep import BIN, write_spec

ROOT = Path(__file__).resolve().parents[1]

# ---- the rule: every stop signal, a hang-up among them --------------------------------------


def test_a_hangup_is_sigterms_stop_with_its_own_detail():
    """The one table the loop, cochlea-run's shield and the C program's words follow."""
    assert signal.SIGHUP in console.STOP_SIGNALS
    assert set(outputs.SignalShield.SIGNALS) == set(console.STOP_SIGNALS) == set(SIGNAL_STOPS)
    rule, detail = SIGNAL_STOPS[signal.SIGHUP]
    assert rule == SIGNAL_STOPS[signal.SIGTERM][0] and STOP_CODES[rule] == 16
    assert "SIGHUP" in detail and "hung up" in detail


def test_a_hangup_stops_the_loop_safely_at_its_next_period():
    _, loop, backend = make_loop(seconds=0.5)
    loop.on_signal(signal.SIGHUP, None)
    loop.on_signal(signal.SIGINT, None)  # a later signal does not rename the stop
    stop = loop.run()
    assert stop.rule == "terminated" and stop.code == 16 and "SIGHUP" in stop.detail
    assert np.array_equal(backend.commands[-1], np.zeros(loop.n))  # zero effort last ...
    assert backend.disabled == 1 and not backend.enabled  # ... then the drives off
    assert loop.rows < 5


@pytest.mark.slow  # a held section of 0.5 s
def test_a_hangup_inside_a_held_section_is_obeyed_after_it():
    """codegen's renames and cochlea-run's folder claim: not cut in two by a hang-up."""
    held_over_a_section(signal.SIGHUP)


def test_a_hangup_interrupts_what_sigterm_interrupts():
    """cochlea-sweep and cochlea-tune: a hang-up raises KeyboardInterrupt, as SIGTERM does,
    and the handler before the section is back after it."""
    before = signal.getsignal(signal.SIGHUP)
    with pytest.raises(KeyboardInterrupt):
        with console.sigterm_interrupts():
            os.kill(os.getpid(), signal.SIGHUP)
            time.sleep(1)  # the handler runs at the next bytecode; never reached
    assert signal.getsignal(signal.SIGHUP) is before


# ---- a terminal that hung up: writes fail with EIO ------------------------------------------


def _hung_up_terminal() -> int:
    """The slave end of a pseudo-terminal whose master (the terminal) is closed: every write
    to it fails with EIO, as to a closed SSH session's terminal."""
    master, slave = pty.openpty()
    os.close(master)
    with pytest.raises(OSError):
        os.write(slave, b"x")
    return slave


def test_console_writes_survive_a_terminal_that_hung_up(monkeypatch):
    slave = _hung_up_terminal()
    out = open(os.dup(slave), "w")  # noqa: SIM115 (closed below)
    err = open(slave, "w")  # noqa: SIM115
    try:
        monkeypatch.setattr(sys, "stdout", out)
        monkeypatch.setattr(sys, "stderr", err)
        console.tolerate_closed_stdout()
        print("the run's report line", flush=True)
        print("cochlea-run: stopped by rule terminated", file=sys.stderr, flush=True)
        print("more", flush=True)
        assert console.stdout_was_closed()
        assert sys.stderr.closed_pipe
    finally:
        monkeypatch.undo()
        out.close()
        err.close()


def test_other_write_errors_are_not_swallowed(monkeypatch):
    """Only a reader that went away is tolerated: a full disk under a redirected stdout is
    still an error."""
    stream = open("/dev/full", "w")  # noqa: SIM115 (closed below)
    try:
        monkeypatch.setattr(sys, "stdout", stream)
        console.tolerate_closed_stdout()
        with pytest.raises(OSError):
            print("x" * 10, flush=True)
        assert not console.stdout_was_closed()
    finally:
        monkeypatch.undo()
        with contextlib.suppress(OSError):  # its buffer cannot be written either
            stream.close()


# ---- cochlea-run in real time on the simulated robot ----------------------------------------


def _wait_for_rows(proc: subprocess.Popen, out: Path, timeout: float = 60) -> None:
    deadline = time.time() + timeout
    while not (out / "log.bin").exists() or (out / "log.bin").stat().st_size == 0:
        assert time.time() < deadline and proc.poll() is None
        time.sleep(0.05)


def _assert_run_stopped_by_the_hangup(out: Path) -> dict:
    summary = json.loads((out / "summary.json").read_text())
    stop = summary["stop"]
    assert stop["rule"] == "terminated" and stop["exit_code"] == 16, stop
    assert "SIGHUP" in stop["detail"]
    assert 0 < summary["periods"] < 20000
    rows = np.loadtxt(out / "log.csv", delimiter=",", skiprows=1, ndmin=2).shape[0]
    assert rows == summary["periods"]
    columns = json.loads((out / "log.columns.json").read_text())
    assert np.fromfile(out / "log.bin").size == rows * columns["row_length"]
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # no temporary left
    return summary


@pytest.mark.realtime
def test_cochlea_run_hung_up_stops_safely_and_keeps_the_log(tmp_path):
    out = tmp_path / "run"
    proc = _cli(["--robot", "serial", "--space", "task", "--out", str(out),
                 "--watchdog-misses", "300"], tmp_path)
    _wait_for_rows(proc, out)
    proc.send_signal(signal.SIGHUP)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 16, stderr
    assert "stopped by rule terminated" in stderr and "SIGHUP" in stderr
    assert "zero effort commanded, drives disabled, log complete" in stderr
    assert "Traceback" not in stderr
    _assert_run_stopped_by_the_hangup(out)


@pytest.mark.realtime
def test_cochlea_run_on_a_terminal_that_hung_up_still_stops_safely(tmp_path):
    """Its stdout and stderr on the terminal (the live status line on), the terminal closed,
    then SIGHUP: every write fails with EIO, and the run still stops, writes its report and
    exits with 16 (before the fix: a traceback on the first write, and exit 1)."""
    out = tmp_path / "run"
    master, slave = pty.openpty()
    proc = subprocess.Popen(
        [sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial", "--space",
         "task", "--out", str(out), "--watchdog-misses", "300", "--status", "on"],
        cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=slave, stderr=slave)
    os.close(slave)
    try:
        _wait_for_rows(proc, out)
        os.close(master)  # the terminal goes ...
        master = -1
        time.sleep(0.5)  # ... and the status line's writes find it gone
        proc.send_signal(signal.SIGHUP)  # ... then the hang-up
        assert proc.wait(timeout=120) == 16
    finally:
        if master >= 0:
            os.close(master)
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    _assert_run_stopped_by_the_hangup(out)


# ---- over the virtual chain: cochlea-run, the embedded program, the emulator ----------------


@pytest.mark.hil
def test_cochlea_run_over_the_chain_hung_up_turns_the_torque_off(tmp_path):
    out, log = tmp_path / "hil", tmp_path / "emulator.log"
    # The chain's motors with their rotors: on the thesis's rigid links a late first period
    # lets joint 3 (6e-6 kg m^2) pass its speed limit at once (CI of stop 41: velocity-limit at
    # t = 0.002 s, exit 11), and this test is about the hang-up, not the host's scheduling.
    served = chain_scenario("serial_joint", tmp_path, rotors=True)
    with started_emulator("serial", served, log, transport=LOOP_TRANSPORT) as port:
        proc = _cli(["--robot", "serial", "--space", "joint", "--backend", "dynamixel",
                     "--port", port, "--duration", "20", "--out", str(out), "--watchdog-misses",
                     "300"], tmp_path)
        _wait_for_rows(proc, out)
        time.sleep(0.5)
        proc.send_signal(signal.SIGHUP)
        _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 16, stderr
    assert "stopped by rule terminated" in stderr and "Traceback" not in stderr
    summary = _assert_run_stopped_by_the_hangup(out)
    # Sent, and in the emulator's log: zero current, then torque off, for every motor, last.
    # (Their confirmation is the bus's: a read lost to the shared machine's lag leaves one
    # unconfirmed, as the shut-down line then says.)
    assert "goal current 0 and torque off sent" in summary["timing"]["bus"]["shutdown"]
    tail = [(a, v) for _, a, v in last_commands(log)[-12:]]
    assert tail == [(102, 0)] * 6 + [(64, 0)] * 6


@pytest.mark.hil
def test_the_embedded_program_hung_up_stops_safely(tmp_path, program):  # noqa: F811
    proc, stderr, out, log = _interrupted_run(
        program, tmp_path, lambda proc, log: proc.send_signal(signal.SIGHUP))
    assert proc.returncode == 16, stderr
    assert "stopped by rule terminated" in stderr and "SIGHUP" in stderr
    assert "zero effort commanded, drives disabled, log complete" in stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stop"]["rule"] == "terminated" and summary["stop"]["exit_code"] == 16
    assert "SIGHUP" in summary["stop"]["detail"] and summary["stop"]["time_s"] < 9.0
    assert_log_complete(out, summary)
    assert "goal current 0 and torque off sent" in summary["timing"]["bus"]["shutdown"]
    tail = [(a, v) for _, a, v in last_commands(log)[-12:]]
    assert tail == [(102, 0)] * 6 + [(64, 0)] * 6


@pytest.mark.hil
@pytest.mark.parametrize("blocked", [("log.csv",), ("summary.json",),
                                     ("log.csv", "summary.json")])
def test_the_embedded_program_names_only_the_report_files_it_wrote(tmp_path, program,  # noqa: F811
                                                                   blocked):
    """The report's temporary files cannot be created (a directory in their place, as a full
    disk refuses them): the program says which files were not written and names none of them
    as if it had, on stdout or stderr."""
    out, log = tmp_path / "c", tmp_path / "emulator.log"
    with emulator("serial", "serial_joint", log) as port:
        proc = subprocess.Popen([str(program), "--scenario", "serial_joint", "--port", port,
                                 "--duration", "10", "--out", str(out), *PATIENT],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        _wait_for_rows(proc, out)
        for name in blocked:
            (out / f".{name}.tmp").mkdir()
        time.sleep(0.5)
        proc.send_signal(signal.SIGHUP)
        stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 16, stderr
    assert "writing the report to" in stderr
    for name in ("log.csv", "summary.json"):
        written = name not in blocked
        assert (out / name).exists() == written
        assert (f"{out}/{name}" in stdout) == written, stdout
        assert (f"{name} not written" in stdout) == (not written), stdout
    if len(blocked) == 2:
        assert "neither log.csv nor summary.json was written" in stderr
    tail = [(a, v) for _, a, v in last_commands(log)[-12:]]
    assert tail == [(102, 0)] * 6 + [(64, 0)] * 6  # the safe stop all the same


@pytest.mark.hil
def test_the_emulators_log_is_complete_after_a_hangup(tmp_path):
    """Every item written before the hang-up is in the --log, each line whole (before the fix:
    the process died with its buffered log unwritten)."""
    log = tmp_path / "emulator.log"
    proc = subprocess.Popen(
        [sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot", "serial", "--priority",
         "normal", "--log", str(log)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    fd = -1
    try:
        path = proc.stdout.readline().strip()
        assert path.startswith("/dev/"), proc.stderr.read() if proc.poll() is not None else path
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        sent = []
        for motor_id in range(1, 7):
            for address, value, size in ((11, 0, 1), (102, 0, 2), (64, 1, 1)):
                os.write(fd, proto.write(motor_id, address, proto.le(value, size)))
                sent.append((motor_id, address, value))
                time.sleep(0.01)
        time.sleep(0.3)
        proc.send_signal(signal.SIGHUP)
        out, err = proc.communicate(timeout=30)
    finally:
        if fd >= 0:
            os.close(fd)
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert "cochlea-emulator: stopped (" in out and "Traceback" not in err
    text = log.read_text()
    assert text.endswith("\n")
    events = [line.split() for line in text.splitlines()]
    written = [(int(e[2].split("=")[1]), int(e[3].split("=")[1]), int(e[4].split("=")[1]))
               for e in events if e[1] == "write"]
    assert written == sent


# ---- a sweep hung up resumes -----------------------------------------------------------------


@pytest.mark.slow
def test_a_sweep_hung_up_says_so_and_resumes(tmp_path):
    """The hang-up goes to the whole process group, as a closed terminal sends it: the sweep
    says it was interrupted (no traceback), keeps its finished parts and resumes to the same
    samples, each once."""
    spec_path = write_spec(tmp_path)
    out = tmp_path / "out"
    proc = subprocess.Popen([str(BIN / "cochlea-sweep"), str(spec_path), "--out", str(out),
                             "--workers", "2", "--batch", "1", "--progress", "off"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 120  # a bound on a hung start, not a timed assertion
        while len(list((out / "parts").glob("*.parquet"))) < 2 and proc.poll() is None:
            assert time.monotonic() < deadline, "no part file appeared"
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGHUP)
        _, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == cochlea_sweep.EXIT_INTERRUPTED, stderr
    assert "cochlea-sweep: interrupted" in stderr
    assert "Traceback" not in stderr, stderr[stderr.find("Traceback") - 300:]
    kept = {p.name: p.read_bytes() for p in (out / "parts").glob("*.parquet")}
    assert len(kept) >= 2
    assert cochlea_sweep.main([str(spec_path), "--out", str(out), "--workers", "2",
                               "--progress", "off"]) == 0
    samples = [r["sample"] for r in results.read(out).to_pylist()]
    assert samples == list(range(8))
    for name, data in kept.items():  # finished batches are never rewritten
        assert (out / "parts" / name).read_bytes() == data


# ---- cochlea-dxl: a torque on while homing ---------------------------------------------------


@pytest.mark.hil
def test_cochlea_dxl_home_hung_up_turns_the_torque_off(tmp_path):
    """``cochlea-dxl home`` pushes the slider onto its stop with its torque on and, asked to
    dwell there for a minute, keeps pushing: a hang-up meanwhile ends it as Ctrl-C does,
    torque off (before the fix: killed with the torque on)."""
    slider = next(d for d in joint_drives("parallel") if d.type == "prismatic")
    log, record = tmp_path / "emulator.log", tmp_path / "parallel.json"
    with started_emulator("parallel", "parallel_joint", log, "--hard-stop-m", "0.01") as port:
        proc = subprocess.Popen(
            [sys.executable, "-m", "cochlea.apps.cochlea_dxl", "home", "--robot", "parallel",
             "--port", port, "--record", str(record), "--stop-m", "0.01", "--dwell-s", "60"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(6)  # its imports, the checks, then the torque on and the slow approach
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGHUP)
        _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 129, stderr  # 128 + SIGHUP (docs/hardware.md)
    assert "interrupted by SIGHUP (every torque is off)" in stderr and "Traceback" not in stderr
    torque = [int(e[4].split("=")[1]) for e in (line.split() for line in
                                               log.read_text().splitlines())
              if e[1] in ("write", "sync-write") and e[2] == f"id={slider.id}"
              and e[3] == "address=64"]
    assert 1 in torque and torque[-1] == 0, torque  # on while homing, off at the end
    assert not record.exists()


def test_dask_errors_print_one_line_without_a_traceback():
    # What the hang-up above once printed beside "cochlea-sweep: interrupted" (CI, with other
    # tests on both cores): distributed.batched's "Error in batched write" with its traceback.
    # As in cochlea-sweep's process: distributed's own handler, which its records stop at.
    import io
    import logging

    from cochlea.sweep import execute

    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    dask_logger = logging.getLogger("distributed")
    saved = dask_logger.propagate
    dask_logger.addHandler(handler)
    dask_logger.propagate = False
    try:
        execute.one_line_logs()
        execute.one_line_logs()  # idempotent: one filter
        try:
            raise OSError("Stream is closed")
        except OSError:
            logging.getLogger("distributed.batched").exception("Error in batched %s", "write")
        logging.getLogger("distributed.batched").error("plain %d", 7)
    finally:
        dask_logger.removeHandler(handler)
        dask_logger.propagate = saved
    lines = stream.getvalue().splitlines()
    assert lines == ["Error in batched write (OSError: Stream is closed)", "plain 7"]
    assert sum(isinstance(f, execute._OneLineErrors) for f in handler.filters) == 1
    # Another logger's record keeps its traceback, through the same handler.
    record = logging.LogRecord("cochlea", logging.ERROR, __file__, 1, "x", None,
                               (OSError, OSError("kept"), None))
    assert execute._OneLineErrors().filter(record) and record.exc_info is not None
