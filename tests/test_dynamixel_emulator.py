"""The virtual chain: control-table semantics of the two models, Protocol 2.0 over the
pseudo-terminal (broadcast ping, CRC errors, unsupported instructions, Status Return Level),
the plant moving the joints, the event log and the command line's errors."""

from __future__ import annotations

import gc
import math
import os
import random
import select
import time
import weakref
from datetime import timedelta

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cochlea.dynamixel import control_table as ct
from cochlea.dynamixel import protocol as proto
from cochlea.dynamixel.emulator import Truth, VirtualChain, main
from cochlea.sim import unit_setups

# The virtual chain on a pseudo-terminal, in real time.
pytestmark = pytest.mark.hil

instruction_frames = st.builds(
    lambda i, c, p: proto.instruction(i, c, p), st.sampled_from([1, 2, 3, 0xFE, 252]),
    st.sampled_from([0x01, 0x02, 0x03, 0x08, 0x82, 0x83, 0x06, 0x77]), st.binary(max_size=40))


@pytest.fixture(scope="module")
def parallel_chain():
    return VirtualChain("parallel")  # not started: the motors are used directly


@pytest.fixture
def motor(parallel_chain):
    m = parallel_chain.by_id[1]  # the slider's XM540-W270
    m.table[:] = m.defaults  # as it came from the box
    yield m
    m.table[:] = m.defaults


def write(m, address, value, size):
    return m.write(address, proto.le(value, size))[0]


def test_the_control_table_of_each_model(parallel_chain):
    xm, mx = parallel_chain.by_id[1], parallel_chain.by_id[2]
    assert (xm.get(0), mx.get(0)) == (1120, 311)
    assert (xm.get(38), mx.get(38)) == (2047, 1941)  # Current Limit at its maximum
    assert (xm.spec.current_unit_mA, mx.spec.current_unit_mA) == (2.69, 3.36)
    for m in (xm, mx):
        assert (m.get(9), m.get(11), m.get(64), m.get(68)) == (250, 3, 0, 2)
        assert m.get(102) == m.get(38)  # Goal Current starts at the limit: write 0 first
        assert ct.BAUD_RATES[m.get(8)] == 4_000_000


def test_eeprom_is_locked_while_the_torque_is_on(motor):
    assert write(motor, 11, 0, 1) == 0
    assert write(motor, 64, 1, 1) == 0
    for address, size in ((11, 1), (9, 1), (38, 2)):
        assert write(motor, address, 0, size) == ct.ACCESS
    assert write(motor, 64, 0, 1) == 0
    assert write(motor, 9, 0, 1) == 0


def test_a_mode_change_resets_goal_current_to_the_limit(motor):
    assert write(motor, 38, 500, 2) == 0
    assert write(motor, 102, 0, 2) == 0
    assert write(motor, 11, 0, 1) == 0
    assert motor.get(102) == 500
    assert write(motor, 102, -501, 2) == ct.DATA_LIMIT
    assert write(motor, 102, -500, 2) == 0 and motor.get(102) == -500


def test_writes_are_checked_whole(motor):
    assert write(motor, 11, 2, 1) == ct.DATA_RANGE  # no such operating mode
    assert write(motor, 9, 255, 1) == ct.DATA_RANGE
    assert write(motor, 38, 2048, 2) == ct.DATA_RANGE
    assert write(motor, 102, 5, 1) == ct.DATA_LENGTH  # half of Goal Current
    assert write(motor, 103, 5, 1) == ct.ACCESS  # inside an item
    assert write(motor, 126, 5, 2) == ct.ACCESS  # read-only
    assert write(motor, 14, 1, 1) == ct.ACCESS  # a gap in the table
    # All or nothing: Return Delay fine, Drive Mode out of range -> neither is written.
    assert motor.write(9, bytes([7, 9]))[0] == ct.DATA_RANGE and motor.get(9) == 250
    assert motor.write(9, bytes([7, 1]))[0] == 0 and (motor.get(9), motor.get(10)) == (7, 1)
    assert motor.read(126, 10)[0] == 0 and motor.read(140, 20)[0] == ct.ACCESS


def test_bus_watchdog_and_hardware_error(motor):
    assert write(motor, 11, 0, 1) == 0 and write(motor, 102, 0, 2) == 0
    motor.trip_watchdog()
    assert motor.get(98) == -1 and not motor.driving
    assert write(motor, 102, 10, 2) == ct.DATA_RANGE  # goal values read-only
    assert write(motor, 98, 0, 1) == 0  # cleared
    assert write(motor, 102, 10, 2) == 0
    assert write(motor, 64, 1, 1) == 0 and motor.driving
    motor.latch_hardware_error(5)
    assert not motor.torque_on and not motor.driving
    assert write(motor, 64, 1, 1) == ct.RESULT_FAIL  # only a reboot re-enables
    motor.reboot()
    assert motor.hardware_error == 0 and write(motor, 64, 1, 1) == 0


class Client:
    """Our own frames on the slave side of the pseudo-terminal."""

    def __init__(self, path):
        import termios
        import tty

        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        termios.tcflush(self.fd, termios.TCIFLUSH)

    def ask(self, frame: bytes, replies: int = 1, timeout: float = 0.5) -> list[tuple]:
        parser = proto.PacketParser()
        os.write(self.fd, frame)
        out, end = [], time.perf_counter() + timeout
        while len(out) < replies and time.perf_counter() < end:
            if select.select([self.fd], [], [], 0.01)[0]:
                parser.feed(os.read(self.fd, 4096))
            while (code := parser.parse()) != proto.NEED_MORE:
                out.append((code, parser.id, parser.error, parser.params()))
        return out

    def close(self):
        os.close(self.fd)


@pytest.fixture
def client_chain():
    gc.disable()
    chain = VirtualChain("serial").start()
    client = Client(chain.path)
    yield client, chain
    client.close()
    chain.close()
    gc.enable()


def test_protocol_over_the_pseudo_terminal(client_chain):
    client, chain = client_chain
    # Broadcast ping: everyone, in ID order, with model number and firmware.
    answers = client.ask(proto.ping(0xFE), replies=6)
    assert [(a[0], a[1], a[3][:2]) for a in answers] == [(proto.OK, i, b"\x37\x01")
                                                         for i in range(1, 7)]
    # A corrupted instruction to ID 2: a status with the CRC error number.
    bad = bytearray(proto.read(2, 132, 4))
    bad[-1] ^= 1
    assert client.ask(bytes(bad)) == [(proto.OK, 2, ct.CRC_ERROR, b"")]
    # Unemulated instruction: Instruction Error. Unknown ID: silence.
    assert client.ask(proto.instruction(3, ct.REG_WRITE, b"\x40\x00\x01")) == \
        [(proto.OK, 3, ct.INSTRUCTION_ERROR, b"")]
    assert client.ask(proto.ping(42), timeout=0.05) == []
    # Status Return Level 1: READ answered, WRITE not (this one included: it is done first).
    assert client.ask(proto.write(4, 68, b"\x01"), timeout=0.05) == []
    assert client.ask(proto.write(4, 65, b"\x01"), timeout=0.05) == []
    assert client.ask(proto.read(4, 65, 1)) == [(proto.OK, 4, 0, b"\x01")]
    # SYNC_READ of 126..135 for IDs 6, 1: one status each, in the order asked.
    answers = client.ask(proto.sync_read(126, 10, [6, 1]), replies=2)
    assert [a[1] for a in answers] == [6, 1] and all(len(a[3]) == 10 for a in answers)
    kinds = {e[1] for e in chain.events}
    assert {"ping", "crc-error", "refused", "write", "read", "sync-read"} <= kinds


def test_the_plant_moves_a_driven_joint_and_holds_the_others(client_chain):
    client, chain = client_chain
    q0 = chain.joint_state()[:6].copy()
    for frame in (proto.write(1, 11, b"\x00"), proto.write(1, 102, proto.le(0, 2)),
                  proto.write(1, 64, b"\x01"), proto.write(1, 102, proto.le(200, 2))):
        assert client.ask(frame)[0][2] == 0
    time.sleep(0.05)
    motor = chain.by_id[1]
    with chain.paused():  # the state and the registers of one update (not one in between)
        state = chain.joint_state()
        present = motor.get(126), motor.get(132), motor.get(128)
    assert state[0] > q0[0] + 1e-3 and state[6] > 0  # 0.67 A -> about 0.57 N m, positive
    assert list(state[1:6]) == list(q0[1:6]) and not state[7:].any()  # torque off: held
    # The registers follow: Present Current, Position, Velocity.
    assert present[0] == 200
    assert present[1] == round(state[0] / ct.RAD_PER_COUNT)
    assert present[2] > 0


@pytest.mark.parametrize("steps", ["1 ms", "uneven"])
def test_a_slider_pushed_onto_its_hard_stop_stays_on_it(steps):
    """The realistic (geared) plant's slider, 0.5 mm above its hard stop, pushed down at its
    full homing force (10 N) with the plant's steps of 1 ms or of uneven lengths (a loaded
    machine's): once on the stop it stays there, within a micrometre (a count is 30), and comes
    to rest. Before the rotor went back with the link, each step's overshoot wound the gear's
    spring up further: the slider bounced 3.8 mm off its stop, and homing timed out in CI."""
    stop = 0.01
    chain = VirtualChain("parallel", plant="realistic",
                         truth=Truth(offset_deg={1: 100.0}, hard_stop_m=stop))
    slider = next(m for m in chain.motors if m.drive.type == "prismatic")
    unit = next(u for u in chain.units if slider in u.motors)
    j = unit.motors.index(slider)
    assert unit.gearbox
    chain.move_joint(slider.drive.name, stop + 5e-4)
    goal = int(slider.drive.goal_current_lsb(-10.0))  # down, as cochlea-dxl home pushes
    now = chain._plant_time  # the requests at the plant's own time: they step nothing
    for frame in (proto.write(slider.id, 11, b"\x00"), proto.write(slider.id, 64, b"\x01"),
                  proto.write(slider.id, 102, proto.le(goal & 0xFFFF, 2))):
        chain._received(frame, now)
    assert slider.state()[0] and slider.state()[2] < -9.0  # driving, about 10 N down
    rng = random.Random(3)
    t, touched, highest = 0.0, None, 0.0
    while t < 3.0:
        h = 1e-3 if steps == "1 ms" else rng.uniform(5e-5, 1e-3)
        assert unit.advance(h)
        t += h
        if touched is None and unit.x[j] <= stop:
            touched = t
        elif touched is not None:
            highest = max(highest, unit.x[j] - stop)
    assert touched is not None and touched < 0.5
    assert highest < 1e-6, f"{highest * 1e3:.3f} mm above the stop"
    assert abs(unit.x[unit.n + j]) < 1e-6  # at rest on it


def test_the_event_log_file(tmp_path):
    log = tmp_path / "events.txt"
    with VirtualChain("serial", log_path=log) as chain:
        client = Client(chain.path)
        client.ask(proto.write(5, 65, b"\x01"))
        client.close()
    lines = log.read_text().splitlines()
    assert any(" write id=5 address=65 value=1" in line for line in lines)


def test_an_in_process_chain_keeps_the_hosts_objects_out_of_the_collectors_way():
    """While a chain serves from a thread of this process, the objects alive before it started
    are frozen (a full collection triggered by its allocations would scan a long pytest
    session's whole heap); after the last chain stops they are the collector's again, so a
    cycle made before the chain is collected, and nested chains thaw only at the last stop."""
    class Cycle:
        pass

    from cochlea.dynamixel.emulator import serving_chains
    assert serving_chains() == 0, "an earlier test left a chain serving"
    before = gc.get_freeze_count()
    gc.disable()  # no automatic collection takes the cycle before the chain starts
    try:
        cycle = Cycle()
        cycle.self = cycle
        collected = []
        ref = weakref.ref(cycle, lambda _: collected.append(True))
        del cycle
        with VirtualChain("serial") as outer:
            frozen = gc.get_freeze_count()
            assert frozen > before
            gc.collect()
            assert ref() is not None  # frozen: the collector leaves it
            with VirtualChain("serial"):
                assert gc.get_freeze_count() >= frozen and serving_chains() == 2
            assert gc.get_freeze_count() >= frozen  # the outer chain still serves
            thread = outer._thread
            assert outer.start() is outer  # already serving: the same thread, one freeze
            assert outer._thread is thread and serving_chains() == 1
        assert gc.get_freeze_count() == 0 and serving_chains() == 0
        gc.collect()
    finally:
        gc.enable()
    assert ref() is None and collected == [True]


def test_command_line_errors(capsys):
    assert main(["--robot", "serial", "--baud", "12345"]) == 2
    assert "12345 is not a Dynamixel rate" in capsys.readouterr().err
    assert main(["--robot", "parallel", "--scenario", "serial_joint"]) == 2
    assert "is for the serial robot, not parallel" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--robot", "serial", "--drop-replies", "1.5"])
    with pytest.raises(SystemExit):
        main(["--robot", "serial", "--hardware-error", "3:1"])
    assert "BIT must be one of" in capsys.readouterr().err


def test_wire_timing_delays_replies():
    """A PING at 57600 baud: 10 + 14 bytes of 10 bits -> 4.2 ms, plus 500 us return delay."""
    gc.disable()
    try:
        with VirtualChain("serial", baud=57600, wire_timing=True) as chain:
            client = Client(chain.path)
            t0 = time.perf_counter()
            assert client.ask(proto.ping(1))[0][:3] == (proto.OK, 1, 0)
            elapsed = time.perf_counter() - t0
            client.close()
    finally:
        gc.enable()
    expected = 24 * 10 / 57600 + 250 * 2e-6
    assert expected <= elapsed < expected + 0.05  # no sooner than the wire allows
    assert math.isclose(expected, 0.004667, rel_tol=1e-3)


@settings(max_examples=600, deadline=timedelta(milliseconds=500), database=None,
          derandomize=True)
@given(frame=instruction_frames, address=st.integers(0, 160), data=st.binary(max_size=12))
def test_the_emulator_survives_random_instructions(parallel_chain, frame, address, data):
    """Random instructions with valid CRCs, and random writes and reads of the table."""
    chain = parallel_chain
    for raw in (frame, proto.write(2, address, data), proto.read(3, address, len(data)),
                proto.sync_write(address, len(data), [(1, data), (4, data)])):
        chain._parser.reset()
        chain._parser.feed(raw)
        assert chain._parser.parse() == proto.OK
        chain._instruction(time.perf_counter())
    chain._queue.clear()
    for m in chain.motors:  # back to the factory state (a random write may change an ID)
        m.table[:] = m.defaults
    chain._index()


def test_the_commands_default_plant_is_the_realistic_one():
    """Issue 24: ``cochlea-emulator --robot R`` emulates the geared motors (the realistic
    joint-space study's plant); ``--plant ideal`` the thesis's rigid links."""
    from cochlea.dynamixel.emulator import default_scenario
    from cochlea.sim import load_scenario
    for robot in ("serial", "parallel"):
        for plant, preset in ((None, "realistic"), ("realistic", "realistic"),
                              ("ideal", "ideal")):
            sc = load_scenario(default_scenario(robot, plant), plant_preset=plant)
            assert sc.robot == robot and sc.plant.preset == preset
            assert sc.plant.armature == (preset == "realistic")


@pytest.mark.parametrize("scenario", ["parallel_joint_realistic", "parallel_joint",
                                      "serial_joint_realistic", "serial_task"])
def test_the_plant_runs_on_the_c_kernels_and_steps_as_its_function(scenario):
    """The chain steps its plant with the generated C kernel of the very Function the
    simulation uses (the geared parallel plant costs about 260 us per step in CasADi, 18 us in
    C: on a busy machine the slow one made the chain's replies miss the bridge's read
    timeout). One step from a moving state agrees with the Function's."""
    chain = VirtualChain(scenario.split("_")[0], scenario)
    assert chain.plant_source == "the C kernels"
    rng = np.random.default_rng(3)
    for u, s in zip(chain.units, unit_setups(chain.scenario)):
        assert u.plant_source == "c"
        x = u.x + 0.01 * rng.standard_normal(len(u.x))
        tau = 0.3 * rng.standard_normal(u.n)
        u._x[:], u._tau[:], u._h[0] = x, tau, chain.h
        u._call()
        numbers = [s.plant_params, s.friction, chain.h] + ([] if s.drive is None else [s.drive])
        expected = np.array(s.plant_function(1)(x, tau, *numbers)).ravel()
        assert not np.array_equal(expected, x)  # the step moved the state
        np.testing.assert_allclose(u._next, expected, rtol=1e-9, atol=1e-12)


def test_without_the_library_the_plant_runs_on_casadi(tmp_path, monkeypatch):
    monkeypatch.setenv("COCHLEA_LIB", str(tmp_path / "missing.so"))
    chain = VirtualChain("serial", "serial_joint")
    assert chain.plant_source == "CasADi"
    assert {u.plant_source for u in chain.units} == {"casadi"}
    u = chain.units[0]
    q0 = u.x.copy()
    u._x[:], u._tau[:] = q0, 0.2
    u._call()
    assert u._next[u.n:2 * u.n].any()  # a torque accelerated the joints
