"""The bridge against the virtual chain over a real pseudo-terminal: the start-up sequence in
order, reads and writes through the plant, the shut-down, start-up refusals, and every injected
fault seen from the bridge as a reported failure (never an exception)."""

from __future__ import annotations

import gc
import math
import re
import time
from pathlib import Path

import numpy as np
import pytest

from cochlea.dynamixel import bridge as br
from cochlea.dynamixel.bridge import DynamixelBackend
from cochlea.dynamixel.emulator import Faults, VirtualChain
from cochlea.resources import ROBOTS_DIR, SCENARIOS_DIR
from cochlea.runtime.backend import BackendError
from cochlea.sim import unit_setups

# The bridge against the virtual chain on a pseudo-terminal, in real time.
pytestmark = pytest.mark.hil


def scenario_with(tmp_path: Path, robot: str, replace: list[tuple[str, str]] = ()) -> Path:
    """A copy of ROBOT_joint whose description is models/ROBOT.toml with some text replaced."""
    text = (ROBOTS_DIR / f"{robot}.toml").read_text()
    for old, new in replace:
        assert old in text, old
        text = text.replace(old, new, 1)
    description = tmp_path / f"{robot}.toml"
    description.write_text(text)
    scenario = (SCENARIOS_DIR / f"{robot}_joint.toml").read_text().replace(
        f'robot = "{robot}"', f'robot = "{robot}"\ndescription = "{description}"', 1)
    path = tmp_path / f"{robot}_joint.toml"
    path.write_text(scenario)
    return path


def connect(chain: VirtualChain, **options) -> DynamixelBackend:
    """A bridge on the chain's pseudo-terminal. The read timeout is generous (50 ms instead of
    the bus time plus 3 ms): the emulator is a Python thread on a machine that CI and other
    work share, and these tests are about behaviour, not timing."""
    options.setdefault("timeout_s", 0.05)
    return DynamixelBackend(chain.robot, chain.path, description=chain.scenario.description,
                            **options)


@pytest.fixture(autouse=True)
def no_gc():
    """The emulator runs in a thread of this process: a full garbage collection of the test
    process (pytest, hypothesis, CasADi hold many objects) can stall it past a read timeout.
    The real-time loop disables the collector too."""
    gc.collect()
    gc.disable()
    yield
    gc.enable()


@pytest.fixture
def serial_chain():
    chain = VirtualChain("serial").start()
    yield chain
    chain.close()


@pytest.fixture
def live(serial_chain):
    """The serial chain and an enabled bridge on it (disabled afterwards)."""
    backend = connect(serial_chain)
    backend.enable()
    yield serial_chain, backend
    backend.disable()


#: Start-up step 9 on the wire after the first nonzero Goal Current: two transactions, one
#: SYNC_WRITE of Torque Enable 1 to every motor, then one SYNC_READ of Torque Enable (1 byte)
#: confirming each; not a confirmed WRITE per motor (six round trips, during which the first
#: Goal Current was held: 2.3 ms idle, 5-8 ms and more under load).
TORQUE_ON_TRAFFIC = [("sync-write", i, 64, 1) for i in range(1, 7)] + [("sync-read", 254, 64, 1)]


def torque_on_traffic(chain: VirtualChain) -> list[tuple]:
    """``(kind, id, address, value)`` of what the motors heard after the Goal Current that
    preceded the first Torque Enable 1, up to the first instruction about another item (the
    next period's read, or the shut-down's Goal Current 0): the torque-on's transactions."""
    events = [tuple(e[1:]) for e in chain.events if e[1] not in ("fault", "watchdog")]
    first_on = next(i for i, e in enumerate(events) if e[2:] == (64, 1))
    goal = max(i for i, e in enumerate(events[:first_on]) if e[2] == 102)
    traffic = []
    for e in events[goal + 1:]:
        if e[2] != 64:
            break
        traffic.append(e)
    return traffic


def test_start_up_sequence_in_order(live):
    chain, backend = live
    events = list(chain.events)
    kinds = [e[1] for e in events]
    # Every motor pinged before anything is written.
    assert kinds.index("write") > max(i for i, k in enumerate(kinds) if k == "ping")
    assert sorted(e[2] for e in events if e[1] == "ping") == backend.ids
    writes = [(e[2], e[3], e[4]) for e in events if e[1] == "write"]
    limits = {d.id: d.current_limit_lsb for d in backend.drives}
    steps = [(64, 0), (98, 0), (11, 0), (9, 0), (38, None), (102, 0), (98, 5)]
    for motor_id in backend.ids:
        mine = [(a, v) for i, a, v in writes if i == motor_id]
        assert mine == [(a, limits[motor_id] if v is None else v) for a, v in steps]
    # Step by step over all motors: each step done on every motor before the next.
    assert [(a, v) for _, a, v in writes][::6] == [(a, v if v is not None else limits[1])
                                                    for a, v in steps]
    # A good read of the state after the watchdog; the torque still off.
    last_watchdog = max(i for i, e in enumerate(events) if e[1] == "write"
                        and e[3:] == (98, 5))
    assert any(i > last_watchdog for i, e in enumerate(events) if e[1] == "sync-read")
    for m in chain.motors:
        assert not m.torque_on and m.table[11] == 0 and m.table[9] == 0
        assert m.get(38) == limits[m.id] and m.get(102) == 0 and m.get(98) == 5
    # A zero command leaves the torque off; the first nonzero one is written, then the torque
    # goes on: no motor is powered at zero current waiting.
    assert backend.write(np.zeros(6))
    assert not any(m.torque_on for m in chain.motors)
    tau = np.array([0.02, -0.01, 0.0, 0.03, -0.002, 0.001])
    assert backend.write(tau)
    for m, lsb in zip(chain.motors, backend.goal_current_lsb):
        assert m.torque_on and m.get(102) == lsb
    assert torque_on_traffic(chain) == TORQUE_ON_TRAFFIC
    # Later commands are the SYNC_WRITE alone.
    assert backend.write(tau)
    assert [e[1:] for e in chain.events if e[3:] == (64, 1)] == TORQUE_ON_TRAFFIC


def test_reads_and_writes_go_through_the_plant(live):
    chain, backend = live
    x = np.zeros(12)
    assert backend.read(x)
    truth = chain.joint_state()
    assert np.allclose(x[:6], truth[:6], atol=math.radians(0.088))
    assert np.allclose(x[6:], 0.0)
    tau = np.array([0.02, -0.01, 0.0, 0.03, -0.002, 0.001])
    assert backend.write(tau)
    time.sleep(0.02)
    for m, lsb in zip(chain.motors, backend.goal_current_lsb):
        assert m.get(102) == lsb
        # The emulator's motor gives back the torque asked for, to one current LSB.
        one_lsb = float(m.drive.effort(abs(lsb) + 1) - m.drive.effort(abs(lsb)))
        assert abs(float(m.drive.effort(lsb)) - tau[m.drive.id - 1]) <= one_lsb
    assert backend.read(x)
    # Joint 1 accelerates the way its torque points (arm 1 starts at rest).
    assert x[6] > 0 and x[9] > 0
    assert backend.failures == [0] * len(br.FAILURE_NAMES)
    assert 0 < backend.last_io_time_s < 0.01


def test_shut_down_zero_current_torque_off_idempotent(live):
    chain, backend = live
    backend.write(np.full(6, 0.02))
    x = np.zeros(12)
    backend.read(x)
    before = len(chain.events)
    backend.disable()
    backend.disable()
    assert "torque off confirmed by all 6" in backend.shutdown_report
    for m in chain.motors:
        assert not m.torque_on and m.get(102) == 0
    tail = [(e[1], e[3], e[4]) for e in list(chain.events)[before:]]
    first_zero = tail.index(("sync-write", 102, 0))
    first_off = tail.index(("sync-write", 64, 0))
    assert first_zero < first_off
    # After the shut-down nothing is sent and nothing raises.
    count = len(chain.events)
    assert not backend.read(x) and not backend.write(np.zeros(6))
    assert backend.last_failure == br.NOT_ENABLED
    time.sleep(0.01)
    assert len(chain.events) == count


def test_a_non_finite_command_sends_zero_current(live):
    chain, backend = live
    backend.write(np.full(6, 0.05))
    assert not backend.write(np.array([0.01, math.nan, 0, 0, 0, 0]))
    assert backend.describe_last_failure() == "non-finite-command"
    time.sleep(0.02)
    assert [m.get(102) for m in chain.motors] == [0] * 6
    assert not backend.write(np.array([math.inf, -math.inf, 0, 0, 0, 0]))
    x = np.zeros(12)
    assert backend.read(x)  # a bad command does not spoil the next read


@pytest.mark.parametrize("faults, message", [
    (Faults(missing=frozenset({3})), "ID 3 (arm1.link3, MX-64) did not answer PING"),
    (Faults(model_number={5: 1120}), "ID 5 (arm2.link2, MX-64) is model number 1120 "
                                     "(XM540-W270), not the MX-64's 311"),
])
def test_start_up_refuses_a_missing_or_wrong_motor(faults, message):
    with VirtualChain("serial", faults=faults) as chain:
        backend = connect(chain, retries=1)
        with pytest.raises(BackendError, match=message.replace("(", r"\(").replace(")", r"\)")):
            backend.enable()
        assert not any(e[1] == "write" for e in chain.events)  # nothing was configured
        assert not backend.enabled


def test_start_up_refuses_a_joint_outside_its_limits(serial_chain, tmp_path):
    """arm1.link1 is at 73 deg; a bridge whose description puts the motor's zero at -107 deg
    reads 180 deg, in the 20 deg its limits (+-170 deg) leave out, whichever turn it takes."""
    chain = serial_chain
    wrong = tmp_path / "serial.toml"
    wrong.write_text((ROBOTS_DIR / "serial.toml").read_text().replace(
        "zero_offset_deg = 0.0", "zero_offset_deg = -107.0", 1))
    backend = DynamixelBackend("serial", chain.path, description=wrong)
    with pytest.raises(BackendError, match=r"arm1\.link1 \(ID 1\) reads -?180\.0 deg, outside "
                                           r"its limits \[-170, 170\] deg: check "
                                           r"zero_offset_deg and direction"):
        backend.enable()
    assert not any(m.torque_on for m in chain.motors)
    assert not any(e[1] in ("write", "sync-write") and e[3:] == (64, 1) for e in chain.events)
    # 193 deg is taken as -167 deg (single-turn encoder): inside the limits, accepted.
    wrong.write_text((ROBOTS_DIR / "serial.toml").read_text().replace(
        "zero_offset_deg = 0.0", "zero_offset_deg = -120.0", 1))
    backend = DynamixelBackend("serial", chain.path, description=wrong)
    backend.enable()
    x = np.zeros(12)
    assert backend.read(x)
    backend.disable()
    assert x[0] == pytest.approx(math.radians(193 - 360), abs=math.radians(0.1))


@pytest.mark.parametrize("joint, shift, unit", [(4, math.radians(6.0), "deg"),
                                                (1, -math.radians(40.0), "deg")])
def test_start_up_refuses_a_robot_away_from_the_scenarios_initial_pose(serial_chain, joint,
                                                                       shift, unit):
    """The chain stands at serial_joint's initial pose; a bridge told the run starts elsewhere
    (by more than the 5 deg tolerance, on any joint) refuses before the torque comes on,
    naming the joint and both angles; within the tolerance it starts."""
    chain = serial_chain
    start = np.concatenate([u.x0[:3] for u in unit_setups(chain.scenario)])
    away = start.copy()
    away[joint] += shift
    backend = connect(chain, expected_start=away)
    name = backend.drives[joint].name
    with pytest.raises(BackendError, match=rf"not at the scenario's initial pose: "
                                           rf"{re.escape(name)} \(ID {joint + 1}\) is at "
                                           rf"{math.degrees(start[joint]):.1f} deg, the scenario "
                                           rf"starts it at {math.degrees(away[joint]):.1f} deg"):
        backend.enable()
    assert not backend.enabled and not any(m.torque_on for m in chain.motors)
    assert not any(e[1] == "write" and e[3:] == (64, 1) for e in chain.events)
    near = start.copy()
    near[joint] += math.copysign(math.radians(4.0), shift)
    backend = connect(chain, expected_start=near)
    backend.enable()
    backend.disable()
    # A wider tolerance accepts the first pose; a non-physical one is refused at once.
    backend = connect(chain, expected_start=away, start_tolerance=(math.radians(50), 5e-3))
    backend.enable()
    backend.disable()
    for bad in [(0.0, 5e-3), (math.nan, 5e-3), (math.radians(5), -1.0)]:
        with pytest.raises(BackendError, match="start tolerance must be positive"):
            connect(chain, expected_start=start, start_tolerance=bad)


def test_direction_and_zero_offset_map_joint_to_motor(tmp_path):
    edits = [("direction = 1", "direction = -1"),
             ("zero_offset_deg = 0.0", "zero_offset_deg = 30.0")]
    with VirtualChain("serial", scenario_with(tmp_path, "serial", edits)) as chain:
        m = chain.motors[0]
        # q = direction (theta - zero): theta = zero + q / direction = 30 - 73 deg.
        assert m.get(132) == round(math.radians(30 - 73) / (2 * math.pi / 4096))
        backend = connect(chain)
        backend.enable()
        try:
            x = np.zeros(12)
            assert backend.read(x)
            assert np.allclose(x[:6], chain.joint_state()[:6], atol=math.radians(0.088))
            tau = np.array([0.05, 0, 0, 0, 0, 0])
            backend.write(tau)
            time.sleep(0.02)
            assert m.get(102) < 0  # a positive joint torque is a negative motor current
            assert backend.read(x) and x[6] > 0  # and the joint still goes the positive way
        finally:
            backend.disable()


def _run(backend: DynamixelBackend, seconds: float) -> tuple[list[bool], set]:
    """Read and write for a while; the results and the failures seen (kind, motor ID)."""
    x, tau = np.zeros(backend.nq * 2), np.zeros(backend.nq)
    results, seen = [], set()
    # One small command first: the torque comes on with the first nonzero one (start-up step
    # 9), and the emulator's faults count from there.
    assert backend.read(x) and backend.write(np.full(backend.nq, 0.01))
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        ok = backend.read(x)  # raises nothing, whatever happens
        results.append(ok)
        if not ok:
            seen.add((backend.last_failure, backend.last_failure_id))
        backend.write(tau)
        time.sleep(0.001)
    return results, seen


def _consecutive_failures(results: list[bool]) -> int:
    best = run = 0
    for ok in results:
        run = 0 if ok else run + 1
        best = max(best, run)
    return best


FAULTS = {
    "dropped replies": (Faults(drop=1.0, ids=frozenset({3})), br.TIMEOUT),
    "corrupted CRC": (Faults(crc=1.0, ids=frozenset({3})), br.CRC),
    "late replies": (Faults(late=1.0, late_s=0.03, ids=frozenset({3})), br.TIMEOUT),
    "hardware error": (Faults(hardware_error=(3, 5)), br.ALERT),
    "motor stops answering": (Faults(silent=3), br.TIMEOUT),
}


@pytest.mark.parametrize("name", FAULTS)
def test_every_fault_is_a_reported_failure(name):
    faults, kind = FAULTS[name]
    faults.delay_s = 0.1  # after the start-up
    with VirtualChain("serial", faults=faults) as chain:
        backend = connect(chain, timeout_s=0.02)  # a late reply is 30 ms late
        backend.enable()
        try:
            results, seen = _run(backend, 0.5)
        finally:
            backend.disable()
        assert results[0] is True
        assert (kind, 3) in seen, (seen, backend.summary())  # the fault, and the motor it hit
        # Failing reads in a row: the loop's watchdog (5 in a row by default) stops the run.
        assert _consecutive_failures(results) >= 6, backend.summary()
        summary = backend.summary()
        assert br.FAILURE_NAMES[kind] in summary["failures"]
    if name == "hardware error":
        assert "ID 3 (arm1.link3, MX-64): hardware error (overload)" in backend.shutdown_report
        assert 3 in backend.alert_ids
    if name == "motor stops answering":
        # Its Bus Watchdog stopped it by itself, and the shut-down says it could not confirm.
        assert any(e[1] == "watchdog" and e[2] == 3 for e in chain.events)
        assert "not confirmed by ID 3" in backend.shutdown_report


def test_the_bus_watchdog_stops_the_motors_when_the_loop_stops(serial_chain):
    chain = serial_chain
    backend = connect(chain, watchdog_s=0.04)
    backend.enable()
    try:
        backend.write(np.full(6, 0.01))
        time.sleep(0.15)  # the loop "hangs": no instruction for 150 ms > 40 ms
        for _ in range(100):  # (the emulator's thread may itself be late on a busy machine)
            trips = {e[2] for e in chain.events if e[1] == "watchdog"}
            if trips == set(backend.ids):
                break
            time.sleep(0.01)
        assert trips == set(backend.ids)
        assert all(not m.driving and m.applied_current == 0 for m in chain.motors)
    finally:
        backend.disable()


def test_wire_timing_shows_the_bus_budget():
    """At 1 Mbaud the 6 replies alone take 1.26 ms of wire: the measured read shows it."""
    with VirtualChain("serial", baud=1_000_000, wire_timing=True) as chain:
        backend = connect(chain, baud=1_000_000, timeout_s=None)  # the default: bus + 3 ms
        backend.enable()
        try:
            x, tau = np.zeros(12), np.zeros(6)
            io = []
            for _ in range(60):
                if backend.read(x):  # a busy host may make one late now and then
                    backend.write(tau)
                    io.append(backend.last_io_time_s)
                time.sleep(0.002)
        finally:
            backend.disable()
    assert len(io) >= 30  # most reads make the 4.9 ms timeout, even on a busy machine
    budget = backend.budget
    read_wire = (budget.sync_read_bytes + 6 * budget.reply_bytes) * budget.byte_time_s
    assert read_wire == pytest.approx(1.46e-3)
    assert read_wire <= min(io)  # no read is quicker than its bytes on the wire
    assert float(np.median(io)) < budget.bus_s + backend.timeout_s
    assert backend.check_rate(1000).level == "refuse"


def test_the_realistic_plant_holds_a_joint_below_breakaway():
    """``plant="realistic"`` (``cochlea-emulator --plant realistic``): the gearboxes' friction
    from the description (static 1.5x Coulomb) holds every joint against torques below
    breakaway, the rotors behind their gears; a torque past breakaway moves the joint. The
    bridge leaves out the fit's offset current (which compensates that friction), so the motors
    give what is commanded."""
    with VirtualChain("serial", plant="realistic") as chain:
        unit = chain.scenario.system.arms[0].links
        coulomb = [link.joint.actuator.coulomb for link in unit] * 2
        assert chain.scenario.plant.gearbox and all(m.slope_only for m in chain.motors)
        backend = connect(chain, offset_current=False)
        backend.enable()
        try:
            def hold(tau, seconds=0.1):  # keep the bus busy: its watchdog would trip
                for _ in range(int(seconds / 0.002)):
                    assert backend.write(tau)
                    time.sleep(0.002)

            start = chain.joint_state()[:6].copy()
            below = 0.5 * np.array(coulomb)  # a third of each joint's breakaway
            below[1::2] *= -1
            hold(below)
            assert np.array_equal(chain.joint_state()[:6], start)  # stuck, exactly
            above = np.zeros(6)
            above[0] = 2.0 * coulomb[0]
            hold(above)
            moved = chain.joint_state()[:6] - start
            # Joint 1 slides (and its reaction drags the links it carries); arm 2 stays.
            assert moved[0] > 1e-4 and np.all(moved[3:] == 0.0)
        finally:
            backend.disable()


def test_the_bridges_offset_current_overcomes_the_realistic_gearbox():
    """With the fit's offset current (the bridge's friction compensation, what a controller
    without a friction model gets), half of a joint's breakaway torque commanded moves it on the
    realistic emulator: the motor gives ``a I``, the offset's share is the Coulomb friction the
    gearbox takes, so the joint sees the command plus that much: 0.75 + 1 of the Coulomb level,
    past its static 1.5."""
    with VirtualChain("serial", plant="realistic") as chain:
        coulomb = [link.joint.actuator.coulomb for link in chain.scenario.system.arms[0].links]
        backend = connect(chain)
        assert backend.offset_current
        backend.enable()
        try:
            start = chain.joint_state()[:6].copy()
            tau = np.zeros(6)
            tau[0] = 0.75 * coulomb[0]  # half of the breakaway, 1.5x Coulomb
            for _ in range(50):
                assert backend.write(tau)
                time.sleep(0.002)
            moved = chain.joint_state()[:6] - start
            assert moved[0] > 1e-4 and np.all(moved[3:] == 0.0)
        finally:
            backend.disable()


#: Motor 3 at the torque-on, each a class of refusal: the write does not take (it reads back 0,
#: as ``cochlea-emulator --ignore-write 3:64``), it stops answering the moment its torque came
#: on, or it raises its alert then (overload: its torque goes off). What the refusal says after
#: "ID 3 (arm1.link3, MX-64) ".
TORQUE_ON_FAULTS = {
    "ignores the write": "reads Torque Enable 0 after torque on (SYNC_WRITE 64 = 1, read back by "
                         "SYNC_READ): the write did not take",
    "stops answering": "did not answer torque on (SYNC_WRITE 64 = 1, read back by SYNC_READ)",
    "raises its alert": "reports a hardware error (overload): remove the cause and reboot",
}


def torque_on_chain(fault: str | None) -> VirtualChain:
    """The serial chain, started, with motor 3's TORQUE_ON_FAULTS ``fault`` (None: none). The
    last two come from a hook on the motor's Torque Enable 1, so they strike between the
    torque-on's SYNC_WRITE and its SYNC_READ whatever the timing (the emulator's own
    ``--silent-motor`` and ``--hardware-error`` strike at its next tick, which may come after a
    SYNC_READ sent right behind the SYNC_WRITE)."""
    chain = VirtualChain("serial", ignore_writes=[(3, 64)] if fault == "ignores the write"
                         else ())
    motor = chain.by_id[3]
    chained = motor.on_torque

    def strike(m) -> None:
        chained(m)
        if fault == "stops answering":
            m.answering = False
        elif fault == "raises its alert":
            m.latch_hardware_error(5)

    motor.on_torque = strike
    return chain.start()


def expected_torque_on_traffic(fault: str | None, tries: int) -> list[tuple]:
    """TORQUE_ON_TRAFFIC with motor 3's fault: its write acknowledged but not applied, and the
    SYNC_READ asked ``tries`` times in all while a reply is missing."""
    ons = [("ignored-sync-write" if fault == "ignores the write" and i == 3 else "sync-write",
            i, 64, 1) for i in range(1, 7)]
    return ons + [("sync-read", 254, 64, 1)] * (tries if fault == "stops answering" else 1)


@pytest.mark.parametrize("fault", TORQUE_ON_FAULTS)
def test_a_torque_that_does_not_come_on_stops_the_run(fault):
    """Start-up step 9 at the first nonzero command: a motor that does not confirm its Torque
    Enable (reads back 0, does not answer, answers with its alert) fails that write, and every
    read after it fails as not-enabled, naming the motor, without a byte on the bus, so the
    loop's read watchdog stops the run instead of running on unpowered motors; on the wire,
    the torque-on's two transactions (the SYNC_READ asked again only for a missing reply), and
    the shut-down then reaches every motor that hears the bus."""
    chain = torque_on_chain(fault)
    try:
        backend = connect(chain, retries=2)
        backend.enable()
        try:
            x = np.zeros(12)
            assert backend.read(x)
            assert not backend.write(np.full(6, 0.01))
            assert backend.torque_on_error.startswith(
                "ID 3 (arm1.link3, MX-64) " + TORQUE_ON_FAULTS[fault]), backend.torque_on_error
            heard = len(chain.events)
            for _ in range(6):
                assert not backend.read(x)
                assert (backend.last_failure, backend.last_failure_id) == (br.NOT_ENABLED, 3)
            assert len(chain.events) == heard
            assert backend.failure_detail() == ("the torque did not come on: "
                                                + backend.torque_on_error)
        finally:
            backend.disable()
        assert torque_on_traffic(chain) == expected_torque_on_traffic(fault, 2)
        assert not any(m.torque_on for m in chain.motors if m.id != 3)
        if fault == "stops answering":  # its torque came on; its Bus Watchdog stops it
            assert "not confirmed by ID 3 (arm1.link3, MX-64)" in backend.shutdown_report
            for _ in range(100):
                if any(e[1] == "watchdog" and e[2] == 3 for e in chain.events):
                    break
                time.sleep(0.01)
            assert not chain.by_id[3].driving
        else:
            assert not chain.by_id[3].torque_on
            assert "torque off confirmed by all 6" in backend.shutdown_report
        if fault == "raises its alert":
            assert "ID 3 (arm1.link3, MX-64): hardware error (overload)" in \
                backend.shutdown_report
    finally:
        chain.close()

