"""Issue 27 (the Dynamixel lineup as data): the Python bridge takes every address and size it
writes or reads from the drives' model data (``cochlea/dynamixel/models``), not from X-series
constants.

* every frame the bridge sends for the shipped robots (MX-64 serial, MX-64 + XM540-W270
  parallel), start-up to shut-down with a hardware alert on the way, and with the forced
  BULK_* transfers and the Realtime Tick, is byte for byte the one recorded before the change
  (``tests/data/bridge_frames.json``, written by the bridge whose start-up and shut-down used
  the ``ADDR_*`` constants);
* a test-only model whose items sit at other addresses changes exactly those frames: the
  addresses come from the data;
* a SYNC_WRITE whose item differs between the chain's models, and a value its item cannot
  hold, are refused in one line before anything is sent.

The bus is :class:`TableBus`, a port that answers from one control table per motor at once and
records every frame: no pseudo-terminal, no thread, no timing, so the frames are exact.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from unittest import mock

import numpy as np
import pytest

from cochlea.dynamixel import bridge as br
from cochlea.dynamixel import protocol as proto
from cochlea.dynamixel.bridge import DynamixelBackend
from cochlea.dynamixel.control_table import ALERT_BIT
from cochlea.dynamixel.drives import joint_drives
from cochlea.runtime.backend import BackendError

GOLDEN = Path(__file__).parent / "data" / "bridge_frames.json"


class TableBus:
    """A serial port whose motors answer at once from their control tables (one 1024-byte
    table per ID, filled from the drives' model data) and that records every frame sent.

    It answers PING, READ, WRITE, SYNC_READ, SYNC_WRITE, BULK_READ, BULK_WRITE and
    FAST_SYNC_READ; each state read finds every Realtime Tick one further (never a stale
    packet, however slow the machine). ``alert``: IDs whose replies carry the hardware alert
    bit (their Hardware Error Status reads ``overload``)."""

    def __init__(self, drives):
        self.drives = {d.id: d for d in drives}
        self.tables = {d.id: bytearray(1024) for d in drives}
        self.sent: list[bytes] = []
        self.rx = bytearray()
        self.alert: set[int] = set()
        self.low_latency = False
        self.parser = proto.PacketParser(status=False)
        for d in drives:
            self.put(d.id, "Model Number", d.spec.number)
            self.put(d.id, "Firmware Version", d.spec.firmware)
            # Each joint in the middle of its limits (a revolute one: that turn).
            lo, hi = d.position_limits
            self.put(d.id, "Present Position", int(d.counts((lo + hi) / 2)))

    def put(self, motor_id: int, name: str, value: int) -> None:
        it = self.drives[motor_id].spec.item(name)
        self.tables[motor_id][it.address:it.address + it.size] = proto.le(value, it.size)

    def get(self, motor_id: int, name: str) -> int:
        it = self.drives[motor_id].spec.item(name)
        return proto.from_le(self.tables[motor_id][it.address:it.address + it.size], it.signed)

    # ---- the port's interface (cochlea.dynamixel.port.SerialPort) -------------------------

    def write(self, view, n: int, deadline: float) -> bool:
        frame = bytes(view[:n])
        self.sent.append(frame)
        self.parser.reset()
        self.parser.feed(frame)
        assert self.parser.parse() == proto.OK, frame.hex(" ")
        if self.parser.instruction in (proto.SYNC_READ, proto.FAST_SYNC_READ, proto.BULK_READ):
            # A millisecond or more since the last read, on every motor's clock: fresh data.
            for i in self.tables:
                self.put(i, "Realtime Tick", (self.get(i, "Realtime Tick") + 1) % 32768)
        self._answer(self.parser.id, self.parser.instruction, self.parser.params())
        return True

    def read_into(self, view, deadline: float) -> int:
        n = min(len(view), len(self.rx))
        view[:n] = self.rx[:n]
        del self.rx[:n]
        return n

    def discard_input(self) -> bool:
        self.rx.clear()
        return True

    def close(self) -> None:
        pass

    # ---- the motors ---------------------------------------------------------------------------

    def _error(self, motor_id: int) -> int:
        return ALERT_BIT if motor_id in self.alert else 0

    def _reply(self, motor_id: int, data: bytes = b"") -> None:
        if motor_id in self.tables:
            self.rx += proto.status(motor_id, self._error(motor_id), data)

    def _read(self, motor_id: int, address: int, length: int) -> bytes:
        if motor_id in self.alert and address == \
                self.drives[motor_id].spec.item("Hardware Error Status").address:
            return bytes([1 << 5]) + bytes(self.tables[motor_id][address + 1:address + length])
        return bytes(self.tables[motor_id][address:address + length])

    def _answer(self, motor_id: int, inst: int, p: bytes) -> None:
        u16 = lambda k: p[k] | (p[k + 1] << 8)  # noqa: E731
        if inst == proto.PING:
            d = self.drives.get(motor_id)
            if d is not None:
                self._reply(motor_id, proto.le(d.spec.number, 2) + bytes([d.spec.firmware]))
        elif inst == proto.READ:
            if motor_id in self.tables:
                self._reply(motor_id, self._read(motor_id, u16(0), u16(2)))
        elif inst == proto.WRITE:
            if motor_id in self.tables:
                self.tables[motor_id][u16(0):u16(0) + len(p) - 2] = p[2:]
                self._reply(motor_id)
        elif inst in (proto.SYNC_READ, proto.FAST_SYNC_READ):
            address, length, ids = u16(0), u16(2), p[4:]
            if inst == proto.SYNC_READ:
                for i in ids:
                    self._reply(i, self._read(i, address, length))
            else:
                self.rx += proto.fast_sync_status(
                    [(i, self._error(i), self._read(i, address, length)) for i in ids])
        elif inst == proto.SYNC_WRITE:
            address, length = u16(0), u16(2)
            for k in range(4, len(p), 1 + length):
                i = p[k]
                if i in self.tables:
                    self.tables[i][address:address + length] = p[k + 1:k + 1 + length]
        elif inst == proto.BULK_READ:
            for k in range(0, len(p), 5):
                self._reply(p[k], self._read(p[k], u16(k + 1), u16(k + 3)))
        elif inst == proto.BULK_WRITE:
            k = 0
            while k < len(p):
                i, address, length = p[k], u16(k + 1), u16(k + 3)
                if i in self.tables:
                    self.tables[i][address:address + length] = p[k + 5:k + 5 + length]
                k += 5 + length


#: The recorded runs: name -> (robot, bridge options).
RUNS = {
    "serial": ("serial", {}),
    "parallel": ("parallel", {}),
    "serial-tick-bulk": ("serial", {"realtime_tick": True, "read_instruction": "bulk",
                                    "write_instruction": "bulk"}),
    "parallel-fast": ("parallel", {"read_instruction": "fast"}),
}


def run(robot: str, drives=None, **options) -> tuple[DynamixelBackend, TableBus]:
    """A bridge on a :class:`TableBus` through one whole run: start-up, a zero command, a
    nonzero one (the torque comes on), a read, a hardware alert on the second motor (the
    failed read, the period that reads its Hardware Error Status), the shut-down."""
    drives = joint_drives(robot) if drives is None else drives
    bus = TableBus(drives)
    with mock.patch.object(br, "joint_drives", lambda *args, **kwargs: list(drives)):
        backend = DynamixelBackend(robot, "/dev/null", 4_000_000, open_port=lambda p, b: bus,
                                   adapter_latency_s=0.0, timeout_s=0.01, homing="off",
                                   **options)
    n = backend.nq
    x = np.zeros(2 * n)
    backend.enable()
    assert backend.write(np.zeros(n))
    tau = np.linspace(0.02, -0.02, n)
    assert backend.write(tau), backend.torque_on_error
    assert backend.read(x)
    bus.alert.add(backend.ids[1])
    assert not backend.read(x) and not backend.read(x)
    assert backend.alert_status == {backend.ids[1]: 1 << 5}
    backend.disable()
    return backend, bus


def record() -> dict[str, list[str]]:
    frames = {}
    for name, (robot, options) in RUNS.items():
        _, bus = run(robot, **options)
        frames[name] = [f.hex(" ") for f in bus.sent]
    return frames


@pytest.fixture(scope="module")
def frames():
    return record()


@pytest.mark.parametrize("name", RUNS)
def test_the_shipped_robots_frames_are_the_ones_recorded_before(frames, name):
    golden = json.loads(GOLDEN.read_text())
    assert frames[name] == golden[name]


# ---- the addresses come from the data ------------------------------------------------------

#: Every item the start-up, the torque-on, the alert path and the shut-down write or read.
ITEMS = ("Torque Enable", "Bus Watchdog", "Operating Mode", "Return Delay Time",
         "Current Limit", "Goal Current", "Hardware Error Status")
SHIFT = 400  # an address no X-layout item uses (the table is 1024 bytes)


def moved(drives, name: str, which=None):
    """``drives`` whose models (a test-only copy of each: ``MODEL*``) have item ``name``
    SHIFT bytes further on; ``which``: the motor indices moved (default all)."""
    out = []
    for k, d in enumerate(drives):
        if which is None or k in which:
            items = tuple(dataclasses.replace(it, address=it.address + SHIFT)
                          if it.name == name else it for it in d.spec.items)
            d = dataclasses.replace(d, spec=dataclasses.replace(d.spec, name=d.spec.name + "*",
                                                                items=items))
        out.append(d)
    return out


def relocated(frame: bytes, old: int, new: int, ids) -> bytes:
    """``frame`` with the item at ``old`` addressed at ``new`` for the motors ``ids``: what
    the bridge must send when the data move it."""
    parser = proto.PacketParser(status=False)
    parser.feed(frame)
    assert parser.parse() == proto.OK
    motor_id, inst, p = parser.id, parser.instruction, bytearray(parser.params())
    at = lambda k: p[k] | (p[k + 1] << 8)  # noqa: E731
    if inst in (proto.READ, proto.WRITE) and motor_id in ids and at(0) == old:
        p[0:2] = proto.le(new, 2)
    elif inst in (proto.SYNC_READ, proto.SYNC_WRITE, proto.FAST_SYNC_READ) and at(0) == old:
        p[0:2] = proto.le(new, 2)
    elif inst == proto.BULK_WRITE:
        k = 0
        while k < len(p):
            if p[k] in ids and at(k + 1) == old:
                p[k + 1:k + 3] = proto.le(new, 2)
            k += 5 + at(k + 3)
    else:
        return frame
    return proto.instruction(motor_id, inst, bytes(p))


@pytest.mark.parametrize("name", ITEMS)
@pytest.mark.parametrize("run_name", ["serial", "serial-tick-bulk"])
def test_an_item_moved_in_the_data_moves_in_every_frame(name, run_name):
    """A test-only model with one item SHIFT bytes further on: every frame that addressed it
    now addresses it there, every other frame is unchanged (the golden run's)."""
    robot, options = RUNS[run_name]
    drives = joint_drives(robot)
    old = drives[0].spec.item(name).address
    _, bus = run(robot, moved(drives, name), **options)
    golden = [bytes.fromhex(f) for f in json.loads(GOLDEN.read_text())[run_name]]
    ids = {d.id for d in drives}
    expected = [relocated(f, old, old + SHIFT, ids) for f in golden]
    assert expected != golden  # the item is addressed somewhere
    assert bus.sent == expected


@pytest.mark.parametrize("name", ["Operating Mode", "Return Delay Time", "Current Limit",
                                  "Hardware Error Status"])
def test_a_unicast_item_is_each_motors_own(name):
    """An item the bridge only writes or reads motor by motor, moved on one motor's model:
    that motor's frames address it there, the others' where their own data put it."""
    drives = joint_drives("serial")
    old = drives[0].spec.item(name).address
    _, bus = run("serial", moved(drives, name, which={2}))
    golden = [bytes.fromhex(f) for f in json.loads(GOLDEN.read_text())["serial"]]
    assert bus.sent == [relocated(f, old, old + SHIFT, {drives[2].id}) for f in golden]


def test_a_goal_current_placed_differently_is_refused_for_sync_write_in_one_line():
    """Goal Current by SYNC_WRITE when asked: a chain whose models place it differently cannot
    be written so, and is refused before the port is opened, naming the item."""
    drives = moved(joint_drives("serial"), "Goal Current", which={2})
    opened = []
    with mock.patch.object(br, "joint_drives", lambda *args, **kwargs: drives), \
            pytest.raises(BackendError) as caught:
        DynamixelBackend("serial", "/dev/null", write_instruction="sync",
                         open_port=lambda p, b: opened.append(p))
    message = str(caught.value)
    assert "\n" not in message and not opened and "Goal Current" in message


@pytest.mark.parametrize("write", ["auto", "bulk"])
def test_a_torque_enable_placed_differently_goes_by_bulk_frames(write):
    """Torque Enable at another address on one motor's model (an X-series arm with a P-series
    joint: 64 and 512): the torque goes on by one BULK_WRITE (each motor at its own address)
    read back by one BULK_READ, and off by one BULK_WRITE; it was refused before (issue 27
    item 4). Where every model places it alike the frames stay SYNC ones (the golden runs)."""
    drives = moved(joint_drives("serial"), "Torque Enable", which={2})
    with mock.patch.object(br, "joint_drives", lambda *args, **kwargs: drives):
        backend = DynamixelBackend("serial", "/dev/null", write_instruction=write)
    on, check, off = (backend._torque_on_frame, backend._torque_check_frame,
                      backend._torque_off_frame)
    assert (on[7], check[7], off[7]) == (0x93, 0x92, 0x93)  # BULK_WRITE, BULK_READ
    moved_id = drives[2].id
    entries = [(check[k], proto.from_le(check[k + 1:k + 3], False))
               for k in range(8, len(check) - 2, 5)]
    assert entries == [(d.id, 464 if d.id == moved_id else 64) for d in drives]
    assert "BULK_WRITE Torque Enable = 1 at 464 (MX-64*), 64 (MX-64)" in backend._torque_on_what
    same = DynamixelBackend("serial", "/dev/null", write_instruction=write)
    assert same._torque_on_frame[7] == 0x83 and same._torque_check_frame[7] == 0x82


def test_a_value_its_item_cannot_hold_is_refused_before_the_port_opens():
    """The Bus Watchdog's range in a test-only model's data (0..3, 20 ms steps): a 100 ms
    watchdog (5) does not fit it, and nothing is sent; a 1-byte Current Limit cannot hold
    the MX-64's 2-byte limit."""
    drives = joint_drives("serial")
    for name, change in (("Bus Watchdog", {"hi": 3}), ("Current Limit", {"size": 1})):
        small = [dataclasses.replace(d, spec=dataclasses.replace(d.spec, items=tuple(
            dataclasses.replace(it, **change) if it.name == name else it
            for it in d.spec.items))) for d in drives]
        opened = []
        with mock.patch.object(br, "joint_drives", return_value=small), \
                pytest.raises(BackendError, match=f"{name} = [0-9]+ does not fit"):
            DynamixelBackend("serial", "/dev/null",
                             open_port=lambda p, b, seen=opened: seen.append(p))
        assert not opened


def test_the_bridge_writes_with_no_x_series_constant():
    """The bridge's source names no ADDR_* constant (they stay in control_table for the
    emulator): its addresses are the data's."""
    assert "ADDR_" not in Path(br.__file__).read_text()


if __name__ == "__main__":  # rewrite the golden frames (only on purpose: they prove a refactor)
    GOLDEN.write_text(json.dumps(record(), indent=1) + "\n")
