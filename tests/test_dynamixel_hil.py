"""Hardware in the loop over the virtual chain: ``cochlea-run --backend dynamixel`` on
``cochlea-emulator``, two processes as on a bench, over the emulator's socket (``--listen``,
:data:`LOOP_TRANSPORT`; the start-up tests over its pseudo-terminal). Each scenario converges
like the simulation (to within the encoders' resolution) and its summary reports the bus and
the loop's timing; every injected fault ends in the runtime's safe stop with the log complete;
the bus budget refuses a rate the bus cannot carry."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from cochlea.apps.report import unit_summary
from cochlea.dynamixel.control_table import RAD_PER_COUNT
from cochlea.sim import load_scenario, simulate

# Two processes on a socket, the loop in real time against the virtual chain.
pytestmark = pytest.mark.hil

#: The line between a loop and ``cochlea-emulator`` in the runs that are timed: its Unix-domain
#: socket (``--listen unix:PATH``). A pseudo-terminal's bytes are moved by the kernel's workers
#: of ordinary priority, which a loaded machine delays by milliseconds whatever the two ends'
#: SCHED_FIFO (issue 30: 17-23 % deadline misses for cochlea-run, 7-13 % for the C program,
#: beside ``make test-fast``); the socket delivers them in the writer's own system call (0.1-0.4
#: %), so these runs no longer need a retry. The pseudo-terminal stays what needs a serial
#: device (cochlea-dxl, the firmware hosts) and the start-up tests below.
LOOP_TRANSPORT = "unix"

#: What a run over the motors can show beyond the ideal simulation. Angles are measured in
#: counts of 0.088 deg and efforts commanded in current LSBs of about 0.7 mN m (near zero torque;
#: 4 mN m beyond the fit's ramp); the serial arms' distal links (about 6e-6 kg m^2) need less
#: than one LSB, so they stick and slip by several counts (up to 9 counts RMS seen in 20 runs).
#: 0.02 rad (13 counts, 1.1 deg) for an angle, 2 mm for a task length.
FLOOR = {"rad": 0.02, "m": 2e-3}
assert FLOOR["rad"] > 13 * RAD_PER_COUNT


#: Python run before a program's module (``python -c``): the bridge's friction rule patched so
#: that the bridge always adds the fit's offset current and the emulator's motors always take
#: it back off, whatever the controller: the pairing of every run before issue 24, for the
#: tests whose subject needs the fit's offset on the wire (the current-to-torque line).
ALWAYS_OFFSET = ("import cochlea.robots.motor_fit as fit; "
                 "fit.bridge_compensates_friction = lambda actuators: True; ")


def _module(name: str, prefix: str) -> list[str]:
    if not prefix:
        return [sys.executable, "-m", name]
    return [sys.executable, "-c", f"{prefix}import runpy, sys; sys.argv[0] = {name!r}; "
            f"runpy.run_module({name!r}, run_name='__main__', alter_sys=True)"]


@contextmanager
def emulator(robot: str, scenario: str | None, log: Path, *options: str, prefix: str = "",
             transport: str = "pty"):
    """``cochlea-emulator`` serving ``scenario`` (None: its default); yields the ``--port`` to
    give a bridge: its pseudo-terminal (``transport="pty"``) or its Unix-domain socket
    (``"unix"``, in a short temporary folder: a socket's path has at most 107 bytes)."""
    folder = tempfile.mkdtemp(prefix="cochlea-emu-") if transport == "unix" else None
    listen = () if folder is None else ("--listen", f"unix:{folder}/chain.sock")
    chosen = () if scenario is None else ("--scenario", scenario)
    proc = subprocess.Popen(
        [*_module("cochlea.dynamixel.emulator", prefix), "--robot", robot, *chosen,
         "--log", str(log), *listen, *options],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        path = proc.stdout.readline().strip()
        assert path.startswith("/dev/" if folder is None else "unix:"), \
            proc.stderr.read() if proc.poll() is not None else path
        yield path
    finally:
        proc.terminate()
        proc.communicate(timeout=20)
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)


#: These tests are about tracking and faults over the bus, not timing: on the shared 2-core CI
#: machine three processes (pytest, emulator, loop) sometimes lose 20 ms at once, which the
#: default watchdog rightly stops. The deadline watchdog has its own test (test_runtime.py).
SHARED_MACHINE = ("--watchdog-misses", "300")


def run(*args: str, cwd: Path, prefix: str = "") -> subprocess.CompletedProcess:
    return subprocess.run(
        [*_module("cochlea.apps.cochlea_run", prefix), *args,
         *(SHARED_MACHINE if "--port" in args else ())],
        cwd=cwd, capture_output=True, text=True, timeout=180)


#: The studies whose thesis gains leave no margin for a late period on the thesis's rigid links,
#: so that over the chain in real time they test the host's scheduling, not the bus. serial_task:
#: its distal links weigh about 6e-6 kg m^2 (h G / M = 1.2), and one period of measurement delay
#: makes its simulation diverge (joint 3 past 500 rad/s within 3 s), where serial_joint takes
#: measurements 1 to 3 periods old (not 3 every period) and the parallel studies 3 periods
#: unchanged. Its run over the chain reads each state late by part of a period, more on a busy
#: machine: CI's stop 38 stopped it twice on the velocity limit (0.3 s and 2.7 s), and on the
#: same machine in a slow spell (deadline misses 8-25 %) 7 runs of 8 stopped, with the code
#: before and after session 17 alike. The chain then gives its motors their rotors (the
#: description's armature, as every Dynamixel has): the same thesis controller, no change to any
#: study, and its simulation with the rotors moves by at most 3e-5 (m, rad) in any final error
#: from none to five periods of delay.
ROTORS_ON_THE_CHAIN = {"serial_task"}


def chain_scenario(name: str, folder: Path, rotors: bool | None = None) -> str:
    """The scenario ``cochlea-emulator`` serves for study ``name``: the study itself, or for
    :data:`ROTORS_ON_THE_CHAIN` (``rotors``: whichever study it is told) a copy in ``folder``
    whose plant has the drives' armature. The controller's scenario stays the study; compare
    with ``simulate(load_scenario(this))``."""
    if not (name in ROTORS_ON_THE_CHAIN if rotors is None else rotors):
        return name
    from cochlea.resources import SCENARIOS_DIR
    text = (SCENARIOS_DIR / f"{name}.toml").read_text()
    assert "[plant]" not in text, name  # the table below would be a second one
    path = folder / f"{name}_with_rotors.toml"
    path.write_text(text + "\n[plant]\narmature = true\n")
    return str(path)


def run_on_emulator(robot: str, scenario: str, tmp_path: Path, *args: str
                    ) -> tuple[subprocess.CompletedProcess, Path, Path]:
    """``cochlea-run ARGS --backend dynamixel --port PORT --out DIR`` on a fresh emulator of
    ``scenario``, over its socket (:data:`LOOP_TRANSPORT`), once. The result, DIR and the
    emulator's log."""
    out, log = tmp_path / "hil", tmp_path / "emulator.log"
    with emulator(robot, scenario, log, transport=LOOP_TRANSPORT) as port:
        done = run(*args, "--backend", "dynamixel", "--port", port, "--out", str(out),
                   cwd=tmp_path)
    return done, out, log


def assert_log_complete(out: Path, summary: dict) -> None:
    rows = summary["periods"]
    assert np.loadtxt(out / "log.csv", delimiter=",", skiprows=1, ndmin=2).shape[0] == rows
    columns = json.loads((out / "log.columns.json").read_text())
    assert np.fromfile(out / "log.bin").size == rows * columns["row_length"]


def last_commands(log: Path) -> list[tuple[str, int, int]]:
    """The emulator's last SYNC_WRITEs: (address, value) per motor, in order."""
    events = [line.split() for line in log.read_text().splitlines()]
    return [(e[1], int(e[3].split("=")[1]), int(e[4].split("=")[1])) for e in events
            if e[1] == "sync-write"]


@pytest.mark.parametrize("robot,space", [("serial", "joint"), ("serial", "task"),
                                         ("parallel", "joint"), ("parallel", "task")])
def test_each_scenario_converges_over_the_virtual_chain(tmp_path, robot, space):
    duration = 3.0
    chain = chain_scenario(f"{robot}_{space}", tmp_path)
    done, out, log = run_on_emulator(robot, chain, tmp_path, "--robot", robot, "--space", space,
                                     "--duration", str(duration))
    assert done.returncode == 0, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stop"]["rule"] == "completed"
    assert_log_complete(out, summary)

    # The summary reports the bus and the loop's timing; the printout says them too.
    timing, bus = summary["timing"], summary["timing"]["bus"]
    n = 6 if robot == "serial" else 5
    # Each status packet: 11 bytes + 16 of data (120..135: Realtime Tick to Present Position).
    assert bus["bus_budget"]["bytes_per_period"] == (14 + 3 * n) + (14 + n) + 27 * n
    assert bus["reads"] == summary["periods"] and bus["good_reads"] >= 0.98 * bus["reads"]
    assert 0 < timing["backend_mean"] < 0.01 and "deadline_miss_fraction" in timing
    assert timing["watchdog_misses_allowed"] == int(SHARED_MACHINE[1])
    assert f"torque off confirmed by all {n}" in bus["shutdown"]
    assert "  bus: " in done.stdout and "  timing: period p50" in done.stdout
    # After the run: zero current, then torque off, on every motor.
    tail = last_commands(log)[-4 * n:]
    assert tail == [("sync-write", a, v) for a, v in [(102, 0)] * n + [(64, 0)] * n] * 2

    # Tracking like the simulation of the chain's scenario, over the same time.
    simulated = simulate(load_scenario(chain), duration)
    for u in simulated.units:
        reference = unit_summary(u)["tracked"]
        for name, hil in summary["units"][u.name]["tracked"].items():
            sim = reference[name]
            assert hil["initial_abs_error"] == pytest.approx(sim["initial_abs_error"],
                                                            rel=0.05, abs=2 * FLOOR["m"])
            bound = max(0.05 * hil["initial_abs_error"], sim["final_rms_error"]
                        + FLOOR[hil["unit"]])
            assert hil["final_rms_error"] <= bound, (u.name, name, hil, sim)


def test_a_robot_away_from_the_scenarios_start_is_refused_before_anything_moves(tmp_path):
    """serial_task's controller on a chain standing at serial_joint's initial pose (four joints
    10-30 deg away): exit code 5 naming each joint, no output folder, nothing enabled. On the
    emulator's pseudo-terminal (the start-up is not timed): the pty path's own test."""
    log = tmp_path / "emulator.log"
    with emulator("serial", "serial_joint", log, transport="pty") as port:
        done = run("--robot", "serial", "--space", "task", "--backend", "dynamixel", "--port",
                   port, "--duration", "1", "--out", str(tmp_path / "run"), cwd=tmp_path)
    assert done.returncode == 5, done.stderr
    assert "the backend could not start, nothing moved: the robot is not at the scenario's " \
           "initial pose: arm1.link1 (ID 1) is at 73.0 deg, the scenario starts it at " \
           "83.5 deg" in done.stderr and "(tolerance 5 deg, 5 mm)" in done.stderr
    assert "Traceback" not in done.stderr and not (tmp_path / "run").exists()
    assert not [c for c in last_commands(log) if c[1] == 64 and c[2] == 1]


FAULTS = {
    "dropped replies": (["--drop-replies", "1", "--fault-ids", "3"], "timeout"),
    "corrupted CRC": (["--corrupt-crc", "1", "--fault-ids", "3"], "crc"),
    "late replies": (["--late-replies", "1", "--fault-ids", "3", "--late-ms", "5"], "timeout"),
    "hardware error": (["--hardware-error", "3:5"], "hardware-alert"),
    "motor stops answering": (["--silent-motor", "3"], "timeout"),
}


@pytest.mark.parametrize("name", FAULTS)
def test_every_fault_ends_in_the_safe_stop(tmp_path, name):
    options = FAULTS[name][0]
    out, log = tmp_path / "hil", tmp_path / "emulator.log"
    with emulator("serial", "serial_joint", log, "--fault-delay", "0.3", *options,
                  transport=LOOP_TRANSPORT) as port:
        done = run("--robot", "serial", "--space", "joint", "--backend", "dynamixel", "--port",
                   port, "--duration", "3", "--out", str(out), cwd=tmp_path)
    assert_fault_stop(done, out, log, name)


def periods_before_fault(log: Path) -> int:
    """How many of the run's periods the emulator served before its first fault event, from
    its log: the distinct times of its SYNC_WRITEs of Goal Current (one packet a period)."""
    events = [line.split() for line in log.read_text().splitlines()]
    first_fault = next(i for i, e in enumerate(events) if e[1] == "fault")
    return len({e[0] for e in events[:first_fault]
                if e[1] == "sync-write" and e[3] == "address=102"})


def assert_fault_stop(done: subprocess.CompletedProcess, out: Path, log: Path, name: str
                      ) -> dict:
    """The safe stop of a run on the virtual chain with fault ``name`` of FAULTS injected at
    0.3 s (cochlea-run or build/cochlea-embedded): the watchdog's exit code and message, the
    log complete, the failure counted, the shut-down reported, and zero current then torque off
    in the emulator's log for every motor that hears the bus. The run's summary."""
    kind = FAULTS[name][1]
    assert done.returncode == 15, done.stderr  # the watchdog's safe stop
    assert "stopped by rule watchdog" in done.stderr
    assert "zero effort commanded, drives disabled, log complete" in done.stderr
    summary = json.loads((out / "summary.json").read_text())
    # The emulator starts the fault 0.3 s after the first Torque Enable 1. The stop follows it,
    # counted in the run's periods on the emulator's own clock (the run's time_s is its period
    # count, which lags the wall clock once the faulty reads' timeouts make periods late).
    assert summary["stop"]["rule"] == "watchdog" and summary["stop"]["time_s"] < 2.0
    before = periods_before_fault(log)
    assert 200 <= before < summary["periods"], (before, summary["periods"])
    assert_log_complete(out, summary)
    bus = summary["timing"]["bus"]
    assert bus["failures"].get(kind, 0) > 0, bus
    assert "goal current 0 and torque off sent" in bus["shutdown"]
    if name == "hardware error":
        assert "ID 3 (arm1.link3, MX-64): hardware error (overload)" in bus["shutdown"]
    elif name != "late replies":  # its answers to the confirming reads are lost too
        assert "not confirmed by ID 3 (arm1.link3, MX-64)" in bus["shutdown"]
    # The motors that hear the bus got zero current and torque off, in that order.
    tail = [(a, v) for kind_, a, v in last_commands(log)[-24:]]
    hearing = 5 if name == "motor stops answering" else 6
    assert tail[-2 * hearing:] == [(102, 0)] * hearing + [(64, 0)] * hearing
    return summary


@pytest.mark.parametrize("options, message", [
    (["--missing-motor", "3"], "ID 3 (arm1.link3, MX-64) did not answer PING"),
    (["--model-number", "5:1120"], "ID 5 (arm2.link2, MX-64) is model number 1120"),
])
def test_a_wrong_bus_stops_the_run_before_anything_moves(tmp_path, options, message):
    log = tmp_path / "emulator.log"
    with emulator("serial", "serial_joint", log, *options) as port:
        done = run("--robot", "serial", "--space", "joint", "--backend", "dynamixel", "--port",
                   port, "--duration", "1", "--out", str(tmp_path / "hil"), cwd=tmp_path)
    assert done.returncode == 5, done.stderr
    assert "the backend could not start, nothing moved" in done.stderr and message in done.stderr
    assert "Traceback" not in done.stderr
    assert " write " not in log.read_text()  # nothing was configured, let alone enabled


def test_the_bus_budget_refuses_or_warns_with_the_numbers(tmp_path):
    # 6 motors at 1 Mbaud: 2260 us of bus per 1000 us period. Nothing is opened.
    done = run("--robot", "serial", "--space", "joint", "--backend", "dynamixel", "--port",
               "/dev/pts/999", "--baud", "1000000", "--out", str(tmp_path / "a"), cwd=tmp_path)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "214 bytes per period" in done.stderr and "2260 us" in done.stderr
    assert "the bus cannot meet the loop rate" in done.stderr
    # At 4 Mbaud behind a USB adapter (1 ms latency): a warning, then the missing port.
    done = run("--robot", "serial", "--space", "joint", "--backend", "dynamixel", "--port",
               "/dev/ttyUSB-none", "--out", str(tmp_path / "b"), cwd=tmp_path)
    assert "warning: bus budget" in done.stderr and "1655 us" in done.stderr
    assert done.returncode == 5 and "cannot open the serial port /dev/ttyUSB-none" in done.stderr
    # And the options go together.
    for args, text in [(["--backend", "dynamixel"], "needs --port"),
                       (["--port", "/dev/ttyUSB0"], "go with --backend dynamixel")]:
        done = run("--robot", "serial", "--space", "joint", *args, cwd=tmp_path)
        assert done.returncode == 2 and text in done.stderr


def _worst_ratio(summary: dict) -> float:
    return max(c["final_rms_error"] / max(c["initial_abs_error"], 1e-12)
               for u in summary["units"].values() for c in u["tracked"].values())


def test_friction_is_compensated_once_over_the_virtual_chain(tmp_path):
    """Issue 24: the realistic controllers compensate the gearbox's friction themselves, and
    the bridge used to add the fit's offset current (the same friction) on top. On the
    realistic emulator, whose motors give ``a I`` and whose gearboxes lose the friction, the
    run with the bridge's offset left out converges; the same run with both compensations
    (the bridge's rule patched back to always compensating) either stops on a joint's speed
    limit (seen at 16 ms, as the issue saw on the motors' model) or tracks several times
    worse (3 s ended with arm 2's joint 2 at 1.28 of its initial error, against 0.11). The
    realistic preset without its gearbox (backlash and static friction, which the serial
    controllers do not survive yet: docs/robustness.md), so the friction is the one effect.
    Over the emulator's socket, once (a session-12 run on the pseudo-terminal, under load,
    stopped on the velocity limit and was repeated)."""
    from cochlea.resources import SCENARIOS_DIR
    scenario = tmp_path / "serial_joint_realistic_rigid.toml"
    scenario.write_text((SCENARIOS_DIR / "serial_joint_realistic.toml").read_text()
                        + "gearbox = false\nstatic_friction_ratio = 1.0\n")
    summaries = {}
    for case, patch in (("once", ""), ("twice", "r.bridge_compensates_friction = "
                                               "lambda actuators: True; ")):
        out, log = tmp_path / case, tmp_path / f"{case}.log"
        with emulator("serial", str(scenario), log, transport=LOOP_TRANSPORT) as port:
            done = subprocess.run(
                [sys.executable, "-c", "import sys; import cochlea.apps.cochlea_run as r; "
                 f"{patch}sys.exit(r.main(sys.argv[1:]))", "--robot", "serial", "--space",
                 "joint", "--scenario", str(scenario), "--backend", "dynamixel",
                 "--port", port, "--duration", "3", "--out", str(out), *SHARED_MACHINE],
                cwd=tmp_path, capture_output=True, text=True, timeout=180)
        assert done.returncode in (0, 11), done.stderr  # completed, or the velocity limit
        summaries[case] = json.loads((out / "summary.json").read_text())
    once, twice = summaries["once"], summaries["twice"]
    assert once["timing"]["bus"]["friction_compensated_by"] == "controller"
    assert twice["timing"]["bus"]["friction_compensated_by"] == "bridge"
    assert once["stop"]["rule"] == "completed" and once["converged"], once["units"]
    assert twice["stop"]["rule"] == "velocity-limit" or \
        _worst_ratio(twice) > 3 * _worst_ratio(once), (twice["stop"], twice["units"])


def documented_pairs() -> list[tuple[list[str], list[str]]]:
    """Every ``cochlea-emulator ...`` line of the README and docs/ followed, in the same code
    block, by ``cochlea-run ... --port /dev/pts/N`` lines: (emulator arguments, run arguments)
    for each such run, comments stripped."""
    import shlex
    root = Path(__file__).resolve().parent.parent
    pairs = []
    for page in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        for block in page.read_text().split("```")[1::2]:
            emulator_args = None
            for line in block.splitlines():
                if not line.startswith(("cochlea-emulator ", "cochlea-run ")):
                    continue
                words = shlex.split(line.split("#", 1)[0])
                if words[:1] == ["cochlea-emulator"]:
                    emulator_args = words[1:]
                elif words[:1] == ["cochlea-run"] and "/dev/pts/N" in words:
                    assert emulator_args is not None, (page, line)
                    pairs.append((emulator_args, words[1:]))
    return pairs


def test_the_documented_examples_are_found():
    pairs = documented_pairs()
    assert len(pairs) >= 2
    spaces = {(run[run.index("--robot") + 1], run[run.index("--space") + 1])
              for _, run in pairs}
    # Both of the parallel robot's controllers; the serial arms do not survive the geared
    # emulator yet, and docs/dynamixel.md says so instead of showing a pair that fails.
    assert spaces == {("parallel", "joint"), ("parallel", "task")}


@pytest.mark.parametrize("emulator_args,run_args", documented_pairs(),
                         ids=lambda a: "-".join(a[:4]) if isinstance(a, list) else str(a))
def test_every_documented_example_over_the_virtual_chain_converges(tmp_path, emulator_args,
                                                                   run_args):
    """Issue 24: each documented hardware-in-the-loop example, as written (its whole duration),
    completes and converges: no supervisor stop. Over the emulator's socket in place of the
    page's /dev/pts/N, as every timed run here (:data:`LOOP_TRANSPORT`): on the pseudo-terminal
    in a slow spell of the CI machine both examples' bus I/O took 0.8 ms in the median and
    1.4 ms at p90, the parallel loops fell 0.08 ms a period behind, and the watchdog stopped
    both at 3.7-4.0 s, 300 ms late (a fresh clone's make test, 2026-11-27; the pty keeps its
    start-up tests)."""
    out = tmp_path / "run"
    robot = emulator_args[emulator_args.index("--robot") + 1]
    options = emulator_args[emulator_args.index("--robot") + 2:]
    scenario = (options[options.index("--scenario") + 1] if "--scenario" in options else None)
    rest = [w for i, w in enumerate(options)
            if "--scenario" not in (w, options[i - 1] if i else "")]
    with emulator(robot, scenario, tmp_path / "emu.log", *rest,
                  transport=LOOP_TRANSPORT) as port:
        args = [port if w == "/dev/pts/N" else w for w in run_args]
        done = run(*args, "--out", str(out), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stop"]["rule"] == "completed" and summary["supervisor"] is None
    assert summary["converged"], summary["units"]
