"""The loop hardened like ros2_control's (issue 15): a lateness-based overrun rule, real-time
options applied and recorded, a convergence floor that knows the encoders, stale status packets
refused by their Realtime Tick.

The watchdog's rules are tested on a synthetic clock: the loop's clock only advances by what a
test injects (a period's work, a stall, the sleep to a deadline), so each case is exact whatever
the machine's own timing."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from cochlea.errors import CochleaError
from cochlea.runtime import (
    OVERRUN_POLICY,
    STOP_CODES,
    OverrunWatch,
    RealTimeLoop,
    RealtimeOptions,
    SimBackend,
    build_supervisor,
    check_realtime_options,
)
from cochlea.runtime import loop as loop_module
from cochlea.sim import load_scenario, unit_setups

MS = 1_000_000  # ns


class SyntheticClock:
    """Nanoseconds that pass only when the loop sleeps, a backend works, or a reading is taken
    (1 us each, so the loop's final spin to a deadline ends)."""

    def __init__(self):
        self.now = 10**12

    def clock(self) -> int:
        self.now += 1_000
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += int(seconds * 1e9)

    def work(self, ns: int) -> None:
        self.now += int(ns)


class TimedBackend(SimBackend):
    """The sim backend whose read takes ``work(k)`` ns of the synthetic clock in period k."""

    def __init__(self, setups, period, substeps, clock: SyntheticClock, work):
        super().__init__(setups, period, substeps)
        self.synthetic, self.work, self.k = clock, work, 0
        self.commands, self.disabled = [], 0

    def read(self, x):
        self.synthetic.work(self.work(self.k))
        self.k += 1
        return super().read(x)

    def write(self, tau):
        self.commands.append(tau.copy())
        return super().write(tau)

    def disable(self):
        self.disabled += 1
        super().disable()


def timed_loop(work, periods=200, misses=10, name="serial_joint", options=None, warn=None):
    sc = load_scenario(name)
    setups = unit_setups(sc)
    synthetic = SyntheticClock()
    backend = TimedBackend(setups, sc.period, sc.plant_substeps, synthetic, work)
    supervisor = build_supervisor(setups, None, substeps=sc.plant_substeps,
                                  watchdog_misses=misses)
    loop = RealTimeLoop(setups, backend, supervisor, sc.period, periods, realtime=True,
                        substeps=sc.plant_substeps, clock=synthetic.clock,
                        sleep=synthetic.sleep, options=options or RealtimeOptions(
                            policy="other"), warn=warn)
    return loop, backend


def deadline_misses_the_old_rule_counts(loop) -> int:
    """Consecutive periods that finished after the next one was due, the longest run of them:
    what the watchdog counted before issue 15."""
    timing = loop.result(load_scenario("serial_joint")).timing
    k = np.arange(len(timing["compute_s"]))
    late = (k * loop.h + timing["start_lateness_s"] + timing["compute_s"]) > (k + 1) * loop.h
    longest = run = 0
    for miss in late:
        run = run + 1 if miss else 0
        longest = max(longest, run)
    return longest


# ---- the overrun rule ---------------------------------------------------------------------


def test_one_stall_then_catch_up_is_one_overrun_not_a_string_of_misses():
    # 0.3 ms of work a period; period 50 stalls 9.5 ms, less than the 10 periods allowed.
    loop, backend = timed_loop(lambda k: 9.5 * MS if k == 50 else 0.3 * MS)
    stop = loop.run()
    assert stop.rule == "completed", stop.detail
    assert loop.watch.overruns == 1
    # The catch-up periods ran back to back, late, each within a period: the rule before
    # counted them as more consecutive misses than the 10 allowed and stopped the run.
    assert deadline_misses_the_old_rule_counts(loop) > 10
    timing = loop.timing_summary()
    assert timing["overruns"] == 1 and timing["overrun_policy"] == OVERRUN_POLICY
    assert 8.5e-3 < timing["lateness_max"] < 9.6e-3  # the period after the stall started late
    assert timing["deadline_misses"] > 10  # late periods are still reported as such


def test_a_stall_longer_than_n_periods_stops_at_once():
    loop, backend = timed_loop(lambda k: 12 * MS if k == 40 else 0.3 * MS)
    stop = loop.run()
    assert stop.rule == "watchdog" and stop.code == STOP_CODES["watchdog"]
    assert "the loop stalled: one period took 12.0 ms, more than 10 periods" in stop.detail
    assert stop.time == pytest.approx(40 * loop.h) and loop.rows == 41
    assert np.array_equal(backend.commands[-1], np.zeros(loop.n)) and backend.disabled == 1


def test_a_loop_slower_than_its_rate_stops_after_n_overruns():
    loop, backend = timed_loop(lambda k: 1.5 * MS if k >= 20 else 0.3 * MS)
    stop = loop.run()
    assert stop.rule == "watchdog"
    assert "11 consecutive deadline misses" in stop.detail
    assert loop.rows == 31 and loop.watch.overruns == 11
    assert np.array_equal(backend.commands[-1], np.zeros(loop.n))


def test_overruns_that_never_come_n_in_a_row_cannot_let_the_loop_drift():
    # Every other period stalls 8 ms: one overrun, then one quick catch-up period that resets
    # the count; the lateness grows 7 ms every two periods until the loop gives up.
    loop, backend = timed_loop(lambda k: 8 * MS if k % 2 else 0.2 * MS)
    stop = loop.run()
    assert stop.rule == "watchdog" and "behind its deadlines" in stop.detail
    assert "at most 100 ms" in stop.detail
    assert 20 < loop.rows < 40  # nothing commanded in the period that started too late
    assert len(backend.commands) == loop.rows + 1  # its rows' commands, then the zero
    assert np.array_equal(backend.commands[-1], np.zeros(loop.n))


def test_the_watch_counts_a_late_wake_up_as_the_period_overrunning():
    """Own work runs from the deadline (or the previous end, if later): a period the OS woke
    2 ms late overran, though its compute took 0.1 ms; the next one starts late but is quick."""
    watch = OverrunWatch(1 * MS, 3)
    assert watch.started(0, 2 * MS) is None
    assert watch.finished(0, 2 * MS + 100_000) is None and watch.consecutive == 1
    assert watch.started(1 * MS, 2 * MS + 150_000) is None  # catching up
    assert watch.finished(1 * MS, 2 * MS + 300_000) is None and watch.consecutive == 0
    assert watch.overruns == 1 and watch.worst_lateness_ns == 2 * MS
    assert watch.stall_ns == 3 * MS and watch.max_lateness_ns == 100 * MS
    # Long periods: the lateness allowed is the N periods when they are longer than 0.1 s.
    assert OverrunWatch(50 * MS, 3).max_lateness_ns == 150 * MS


# ---- real-time options ----------------------------------------------------------------------


def _observed():
    """The calling thread's policy, priority, CPUs and whether memory is locked, from the OS."""
    locked = 0
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmLck:"):
                locked = int(line.split()[1])
    return (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority,
            sorted(os.sched_getaffinity(0)), locked > 0)


class ObservingBackend(TimedBackend):
    def read(self, x):
        if self.k == 3:
            self.seen = _observed()
        return super().read(x)


def test_options_are_applied_in_the_loop_recorded_and_undone():
    before = _observed()
    cpu = max(os.sched_getaffinity(0))
    options = RealtimeOptions(mlockall=True, cpu=cpu, policy="rr", priority=10)
    sc = load_scenario("serial_joint")
    setups = unit_setups(sc)
    synthetic = SyntheticClock()
    backend = ObservingBackend(setups, sc.period, sc.plant_substeps, synthetic,
                               lambda k: 0.2 * MS)
    supervisor = build_supervisor(setups, None, substeps=sc.plant_substeps)
    warnings = []
    loop = RealTimeLoop(setups, backend, supervisor, sc.period, 20, realtime=True,
                        substeps=sc.plant_substeps, clock=synthetic.clock,
                        sleep=synthetic.sleep, options=options, warn=warnings.append)
    assert loop.run().rule == "completed"
    report = loop.realtime_report
    assert report["requested"] == {"mlockall": True, "cpu": cpu, "policy": "rr",
                                   "priority": 10}
    policy, priority, cpus, locked = backend.seen
    obtained = report["obtained"]
    # What the record says is what the OS had during the loop, permitted or not ...
    assert obtained["policy"] == {os.SCHED_RR: "rr", os.SCHED_FIFO: "fifo",
                                  os.SCHED_OTHER: "other"}[policy]
    assert obtained["priority"] == priority and obtained["cpu"] == cpus
    assert obtained["mlockall"] == locked
    # ... a refusal is one warning naming it, and without one everything was obtained.
    assert len(warnings) == (1 if report["problems"] else 0)
    if not report["problems"]:
        assert (policy, priority, cpus, locked) == (os.SCHED_RR, 10, [cpu], True)
    assert _observed() == before  # back to normal for the report


def test_refused_settings_are_one_warning_and_the_run_goes_on(monkeypatch):
    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")

    class NoLock:
        def mlockall(self, flags):
            return -1

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    monkeypatch.setattr(os, "sched_setaffinity", refuse)
    monkeypatch.setattr(loop_module, "_libc", NoLock)
    warnings = []
    loop, _ = timed_loop(lambda k: 0.2 * MS, periods=20, warn=warnings.append,
                         options=RealtimeOptions(mlockall=True, cpu=0, policy="fifo"))
    assert loop.run().rule == "completed"
    (line,) = warnings
    assert line.startswith("real-time settings not all obtained: mlockall failed")
    assert "SCHED_FIFO 40 not permitted" in line and "CPU affinity 0 refused" in line
    report = loop.realtime_report
    assert report["obtained"]["mlockall"] is False and len(report["problems"]) == 3
    assert loop.scheduling.startswith("normal")


@pytest.mark.parametrize("options, message", [
    (RealtimeOptions(policy="other", priority=5), "--priority goes with --sched fifo or rr"),
    (RealtimeOptions(policy="fifo", priority=0), "--priority must be between 1 and 99"),
    (RealtimeOptions(policy="rr", priority=100), "--priority must be between 1 and 99"),
    (RealtimeOptions(cpu=4096), "--cpu 4096 is not a CPU this process may use"),
    (RealtimeOptions(cpu=-1), "--cpu -1 is not a CPU this process may use"),
    (RealtimeOptions(policy="batch"), "--sched: expected one of fifo, rr, other"),
])
def test_wrong_options_are_the_users_mistake(options, message):
    with pytest.raises(CochleaError, match=message):
        check_realtime_options(options)


def _cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_run", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=180)


@pytest.mark.slow
def test_cli_refuses_wrong_options_before_anything_moves(tmp_path):
    for args, message in [
        (["--sched", "other", "--priority", "3"], "--priority goes with --sched fifo or rr"),
        (["--cpu", "4096"], "--cpu 4096 is not a CPU this process may use: expected one of"),
        (["--realtime", "off", "--mlockall", "on"], "--mlockall set the real-time loop's"),
        (["--realtime", "off", "--sched", "rr", "--cpu", "0"], "--cpu, --sched set the"),
    ]:
        done = _cli("--robot", "serial", "--space", "joint", "--out", str(tmp_path / "x"),
                    *args, cwd=tmp_path)
        assert done.returncode == 2 and message in done.stderr, done.stderr
        assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
        assert not (tmp_path / "x").exists()


@pytest.mark.realtime
def test_cli_records_the_settings_in_summary_json(tmp_path):
    out = tmp_path / "run"
    done = _cli("--robot", "parallel", "--space", "joint", "--duration", "0.2", "--out",
                str(out), "--sched", "rr", "--priority", "30", "--mlockall", "on",
                "--watchdog-misses", "500", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    realtime = summary["realtime"]
    assert realtime["requested"] == {"mlockall": True, "cpu": None, "policy": "rr",
                                     "priority": 30}
    assert set(realtime["obtained"]) == {"mlockall", "cpu", "policy", "priority"}
    assert ("warning: real-time settings not all obtained" in done.stderr) == \
        bool(realtime["problems"])
    timing = summary["timing"]
    assert timing["overrun_policy"] == OVERRUN_POLICY and "overruns" in timing
    assert timing["stall_limit"] == pytest.approx(0.5) and timing["lateness_limit"] == 0.5


# ---- the convergence floor --------------------------------------------------------------------


def _short_run(name="serial_joint", periods=300):
    sc = load_scenario(name)
    setups = unit_setups(sc)
    backend = SimBackend(setups, sc.period, sc.plant_substeps)
    supervisor = build_supervisor(setups, None, substeps=sc.plant_substeps)
    loop = RealTimeLoop(setups, backend, supervisor, sc.period, periods, realtime=False,
                        substeps=sc.plant_substeps)
    assert loop.run().rule == "completed"
    return sc, loop, loop.result(sc)


def test_errors_below_one_encoder_count_are_converged_on_hardware():
    """0.3 s is too short for the ratio rule: every joint's tail error is far above the
    numeric floor. Counts coarser than those errors make them converged; finer ones do not."""
    from cochlea.apps.report import CONVERGENCE_FLOOR, summary

    sc, loop, result = _short_run()
    plain = summary(result)
    rms = {(u, c): v["final_rms_error"] for u, unit in plain["units"].items()
           for c, v in unit["tracked"].items()}
    assert not plain["converged"] and all(v > 1e-4 for v in rms.values())
    for scale, expected in ((2.0, True), (0.5, False)):
        quantum = {}
        for u in result.units:
            errors = np.array([rms[(u.name, c)] for c in u.tracked_names])
            quantum[u.name] = -scale * errors  # a direction of -1 gives a negative count
        data = summary(result, position_quantum=quantum)
        assert data["converged"] is expected
        for u in result.units:
            unit = data["units"][u.name]
            assert unit["position_quantum"]["source"] == "drives"
            for c, j in zip(u.tracked_names, u.setup.controller_model.joints):
                one_count = scale * rms[(u.name, c)]
                entry = unit["tracked"][c]
                assert entry["measurement_resolution"] == pytest.approx(one_count)
                assert entry["convergence_floor"] == pytest.approx(
                    max(CONVERGENCE_FLOOR["rad"], one_count))
                assert unit["position_quantum"]["joints"][j.name]["value"] == \
                    pytest.approx(one_count)
                assert entry["converged"] is expected
    # Without encoders the floor used is the numeric one, and it is recorded.
    entry = plain["units"]["arm1"]["tracked"]["joint1"]
    assert entry["convergence_floor"] == CONVERGENCE_FLOOR["rad"]
    assert plain["units"]["arm1"]["position_quantum"] is None


def test_a_task_space_floor_is_one_count_on_every_joint_through_the_kinematics():
    from cochlea.apps.report import summary

    sc, loop, result = _short_run("parallel_task", periods=200)
    counts = np.full(5, 2 * np.pi / 4096)
    counts[2] = 1e-5  # the slider: metres per count through its pinion
    data = summary(result, position_quantum={"mechanism": counts})
    unit = data["units"]["mechanism"]
    u = result.units[0]
    q = u.q[-1]
    pose = np.array(u.setup.fk_world(q)).ravel()
    moved = sum(np.abs(np.array(u.setup.fk_world(q + step)).ravel() - pose)
                for step in np.diag(counts))
    for i, c in enumerate(u.tracked_names):
        assert unit["tracked"][c]["measurement_resolution"] == pytest.approx(moved[i])
    assert unit["position_quantum"]["joints"]["slider.d1"]["unit"] == "m"


# ---- the Realtime-Tick check (the virtual chain) ------------------------------------------------


def _tick_bridge(chain):
    from cochlea.dynamixel.bridge import DynamixelBackend

    # A generous read timeout: the emulator is a thread of this process on a shared machine.
    return DynamixelBackend(chain.robot, chain.path, description=chain.scenario.description,
                            timeout_s=0.05, realtime_tick=True)


@pytest.mark.hil
def test_a_repeated_status_packet_is_refused_by_its_realtime_tick():
    from cochlea.dynamixel import bridge as br
    from cochlea.dynamixel import protocol as proto
    from cochlea.dynamixel.emulator import Faults, VirtualChain

    faults = Faults(stale=(3, 5), delay_s=0.1)
    with VirtualChain("serial", faults=faults) as chain:
        backend = _tick_bridge(chain)
        # The tick, in the same packet as the state: one SYNC_READ of 120..135.
        assert backend._read_frame == proto.sync_read(120, 16, backend.ids)
        backend.enable()
        x, tau = np.zeros(12), np.zeros(6)
        # The torque comes on with the first nonzero command; the faults count from there.
        assert backend.read(x) and backend.write(np.full(6, 0.01))
        results = []
        try:
            end = time.perf_counter() + 0.6
            while time.perf_counter() < end:
                ok = backend.read(x)
                results.append((ok, backend.last_failure, backend.last_failure_id))
                backend.write(tau)
                time.sleep(0.004)  # 250 Hz: each repeat is more than a tick after the original
        finally:
            backend.disable()
        repeated = chain.counts["stale"]
    assert repeated == 5  # the emulator repeated its packet five times, then answered afresh
    stale = [i for i, (ok, kind, who) in enumerate(results) if not ok and kind == br.STALE]
    assert 1 <= len(stale) <= repeated and all(results[i][2] == 3 for i in stale)
    assert backend.failures[br.STALE] == len(stale)
    assert any(ok for ok, _, _ in results[stale[-1] + 1:])  # fresh packets are good again
    assert results[0][0] and "stale-packet" in backend.summary()["failures"]


def test_the_tick_rule_on_synthetic_times():
    """A tick that did not move is stale only when the request left more than 1.1 ms after a
    reply that carried it had arrived: sooner, both may be the same millisecond."""
    from cochlea.dynamixel import bridge as br
    from cochlea.dynamixel.bridge import DynamixelBackend

    backend = DynamixelBackend("serial", "/dev/null-not-opened", realtime_tick=True)
    ticks = backend._tick
    ticks[:] = [100, 200, 300, 400, 500, 32767]
    assert backend._fresh(asked=0.0095, arrived=0.0100)
    assert backend._fresh(asked=0.0108, arrived=0.0109)  # 0.8 ms on: may be the same ms
    ticks[:] = [101, 201, 301, 401, 501, 0]  # all moved on, through the wrap at 32768
    assert backend._fresh(asked=0.0111, arrived=0.0112)
    ticks[:] = [102, 202, 301, 402, 502, 1]  # the third motor's did not
    assert backend._fresh(asked=0.0120, arrived=0.0121)  # 0.8 ms after its reply came in
    assert not backend._fresh(asked=0.0124, arrived=0.0125)  # 1.2 ms after: stale
    assert backend.failures[br.STALE] == 1 and backend.last_failure_id == backend.ids[2]
    assert "stale-packet (ID 3, arm1.link3)" in backend.describe_last_failure()
    ticks[2] = 302
    assert backend._fresh(asked=0.0130, arrived=0.0131)
    # Without the option the bridge reads 126..135 alone, as before (and the C program does).
    plain = DynamixelBackend("serial", "/dev/null-not-opened")
    assert plain._tick is None and plain.budget.reply_bytes == 21
    assert backend.budget.reply_bytes == 27 and backend.summary()["realtime_tick_check"]


@pytest.mark.hil
def test_a_healthy_chain_is_never_taken_for_stale():
    from cochlea.dynamixel import bridge as br
    from cochlea.dynamixel.emulator import VirtualChain

    with VirtualChain("parallel") as chain:
        backend = _tick_bridge(chain)
        backend.enable()
        x, tau = np.zeros(10), np.zeros(5)
        good = 0
        try:
            for _ in range(300):  # back to back: as fast as the emulator answers
                good += backend.read(x)
                backend.write(tau)
        finally:
            backend.disable()
    assert backend.failures[br.STALE] == 0 and good > 50


def test_the_emulator_refuses_a_stale_fault_on_no_motor():
    from cochlea.dynamixel.emulator import Faults, check_faults

    with pytest.raises(CochleaError, match="--stale-replies: motor ID 9 is not on this chain"):
        check_faults(Faults(stale=(9, -1)), [1, 2, 3])
    with pytest.raises(CochleaError, match="expected a number of reads >= 1"):
        check_faults(Faults(stale=(1, 0)), [1, 2, 3])


@pytest.mark.hil
def test_cli_stale_packets_end_in_the_watchdog_and_the_floor_knows_the_encoders(tmp_path):
    """Over the virtual chain, as on a bench: cochlea-run reads the tick with the state, a
    motor that keeps repeating its packet stops the run with the motor named, and the summary
    judges convergence against the drives' encoder counts."""
    from cochlea.dynamixel.control_table import RAD_PER_COUNT

    log = tmp_path / "emulator.log"
    proc = subprocess.Popen(
        [sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot", "serial", "--scenario",
         "serial_joint", "--log", str(log), "--stale-replies", "3", "--fault-delay", "0.5"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/"), proc.stderr.read() if proc.poll() is not None else port
        out = tmp_path / "hil"
        done = _cli("--robot", "serial", "--space", "joint", "--backend", "dynamixel",
                    "--port", port, "--duration", "3", "--out", str(out),
                    "--watchdog-misses", "300", cwd=tmp_path)
    finally:
        proc.terminate()
        proc.communicate(timeout=20)
    assert done.returncode == 15, done.stderr
    assert ("consecutive backend read failures: last failure stale-packet from ID 3 "
            "(arm1.link3, MX-64)") in done.stderr
    summary = json.loads((out / "summary.json").read_text())
    bus = summary["timing"]["bus"]
    assert bus["realtime_tick_check"] is True and bus["failures"]["stale-packet"] >= 6
    assert bus["bus_budget"]["bytes_per_period"] == (14 + 3 * 6) + (14 + 6) + 27 * 6
    for unit in summary["units"].values():
        assert unit["position_quantum"]["source"] == "drives"
        for joint in unit["position_quantum"]["joints"].values():
            assert joint["value"] == pytest.approx(RAD_PER_COUNT) and joint["unit"] == "rad"
        for coordinate in unit["tracked"].values():
            assert coordinate["convergence_floor"] >= RAD_PER_COUNT
