"""The virtual chain's per-period work stays small (issue 30, item 2): a period's status
packets reach the pseudo-terminal in one system call, with the same bytes in the same order,
and packets due at different times (wire timing) still go each at its own time; a request takes
one plant step; the faster CRC is the specification's. Not timed:
the system calls are counted, so the tests hold on a loaded machine
(``bench/emulator_speed.py`` measures the time)."""

from __future__ import annotations

import ctypes
import os
import select
import sys
import threading
import time
import tty

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cochlea.dynamixel import protocol as proto
from cochlea.dynamixel.emulator import VirtualChain, precise_timers


@pytest.fixture
def chain():
    chain = VirtualChain("serial", "serial_joint")  # served by hand: no thread
    chain.open()
    fd = os.open(chain.path, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    chain.client = fd
    yield chain
    os.close(fd)
    chain.close()


def serve(chain: VirtualChain, frame: bytes, now: float | None = None) -> None:
    """``frame`` written by the host, then one pass of the chain's loop (read, answer)."""
    os.write(chain.client, frame)
    assert select.select([chain.master], [], [], 5.0)[0], "the request did not arrive"
    chain._receive()
    chain._flush(time.perf_counter() if now is None else now)


def take(fd: int, n: int) -> bytes:
    got = b""
    while len(got) < n and select.select([fd], [], [], 5.0)[0]:
        got += os.read(fd, 4096)
    return got


def counting_writes(monkeypatch, chain) -> list[int]:
    """The sizes of the chain's writes to its pseudo-terminal, from now on."""
    sizes: list[int] = []
    real = os.write

    def write(fd, data):
        if fd == chain.master:
            sizes.append(len(data))
        return real(fd, data)

    monkeypatch.setattr(os, "write", write)
    return sizes


def expected_statuses(chain: VirtualChain, address: int, length: int) -> bytes:
    return b"".join(proto.status(m.id, 0, bytes(m.table[address:address + length]))
                    for m in chain.motors)


def test_a_sync_reads_replies_go_in_one_system_call(chain, monkeypatch):
    """Six motors answer a SYNC_READ: one write of their six status packets, in list order,
    each as the motor builds it alone (the loop reads them as before)."""
    ids = [m.id for m in chain.motors]
    sizes = counting_writes(monkeypatch, chain)
    serve(chain, proto.sync_read(120, 16, ids), now=float("inf"))
    expected = expected_statuses(chain, 120, 16)
    assert sizes == [len(expected)]
    assert take(chain.client, len(expected)) == expected
    # A broadcast PING: every motor's reply, in ID order, in one write too.
    sizes.clear()
    serve(chain, proto.ping(0xFE), now=float("inf"))
    pings = b"".join(proto.status(m.id, 0, bytes(m.table[0:2]) + bytes(m.table[6:7]))
                     for m in sorted(chain.motors, key=lambda m: m.id))
    assert sizes == [len(pings)]
    assert take(chain.client, len(pings)) == pings


def test_packets_due_at_different_times_still_go_at_their_own_time(chain, monkeypatch):
    """With the wire's timing each status packet is due when its last byte would have
    arrived: a flush at the first one's time writes that one only, the rest follow."""
    chain.wire_timing, chain.byte_time = True, 10.0 / 57600  # 174 us a byte
    ids = [m.id for m in chain.motors]
    sizes = counting_writes(monkeypatch, chain)
    os.write(chain.client, proto.sync_read(120, 16, ids))
    assert select.select([chain.master], [], [], 5.0)[0]
    chain._receive()
    due = sorted(t for t, _, _ in chain._queue)
    assert len(due) == len(ids) and due[0] < due[1]
    chain._flush(due[0])
    one = len(proto.status(ids[0], 0, bytes(16)))
    assert sizes == [one]
    chain._flush(due[-1])
    assert len(sizes) == 2 and sum(sizes) == len(ids) * one  # the other five at once
    assert take(chain.client, len(ids) * one) == expected_statuses(chain, 120, 16)


def test_a_request_takes_one_plant_step_not_two(monkeypatch):
    """Serving a request integrates the plant up to its arrival (one step), and nothing more
    until the next request or the next update is due: the loop used to take another step,
    publish the motors' registers and check their watchdogs right after each request, for no
    reader."""
    chain = VirtualChain("serial", "serial_joint", plant_period_s=0.05)  # next update: 50 ms
    chain.open()
    fd = os.open(chain.path, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    order: list[str] = []
    real_select, real_tick = select.select, chain._tick

    def counted_select(r, w, x, timeout=None):
        order.append("select")
        if len(order) > 1:  # the first pass is over: stop the loop
            chain._stop.set()
            return [], [], []
        return real_select(r, w, x, 5.0)  # the request below

    def counted_tick(now, **how):
        order.append("tick")
        real_tick(now, **how)

    monkeypatch.setattr(select, "select", counted_select)
    monkeypatch.setattr(chain, "_tick", counted_tick)
    try:
        os.write(fd, proto.sync_read(132, 4, [m.id for m in chain.motors]))
        chain.serve(duration=10)
        monkeypatch.undo()
        assert take(fd, 6 * 15) == b"".join(proto.status(m.id, 0, bytes(m.table[132:136]))
                                            for m in chain.motors)
    finally:
        os.close(fd)
        chain.close()
    # select (the request), its step to the arrival, then straight back to select
    assert order[:3] == ["select", "tick", "select"], order


def bitwise_crc16(data: bytes, crc: int = 0) -> int:
    """The specification's CRC-16, one bit at a time (polynomial 0x8005, no reflection)."""
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


@pytest.mark.slow
@settings(max_examples=400, database=None, derandomize=True)
@given(data=st.binary(max_size=64), start=st.integers(0, 64), stop=st.integers(0, 64),
       crc=st.integers(0, 0xFFFF))
def test_the_two_byte_crc_is_the_specifications(data, start, stop, crc):
    """crc16 steps two bytes at a time (CRC_TABLE2) for speed: the same CRC as the
    specification's bit-by-bit one, over any slice (odd and even lengths), from any start."""
    start, stop = min(start, len(data)), min(stop, len(data))
    expected = bitwise_crc16(data[start:stop], crc) if start < stop else crc
    assert proto.crc16(data, start, stop, crc) == expected
    assert proto.crc16(memoryview(bytearray(data)), start, stop, crc) == expected


# ---- the per-period frame code's fast paths (issue 30, item 2) ------------------------------
# Each fast path (nothing to stuff, a running CRC continued block by block, parameters copied
# in one piece) must give the bytes the byte-by-byte definition gives, stuffing or not.

def reference_fast_sync_status(blocks) -> bytes:
    """The combined FAST_SYNC_READ status, byte by byte: the body stuffed with its CRC slots
    zero, then each running CRC (bit by bit) over the frame from its header to that slot."""
    body, marks = bytearray([0x55]), []
    for k, (motor_id, error, data) in enumerate(blocks):
        body += bytes([error, motor_id]) + bytes(data)
        if k < len(blocks) - 1:
            marks.append(len(body))
            body += b"\0\0"
    stuffed, slots, last1, last2 = bytearray(), [], 0, 0
    for i, x in enumerate(body):
        stuffed.append(x)
        if x == 0xFD and last1 == 0xFF and last2 == 0xFF:
            stuffed.append(0xFD)
        last2, last1 = last1, x
        if i + 1 in marks:
            slots.append(len(stuffed))
    n = len(stuffed) + 2
    frame = bytearray(b"\xff\xff\xfd\x00\xfe") + bytes([n & 0xFF, n >> 8]) + stuffed
    for slot in slots:
        crc = bitwise_crc16(bytes(frame[:proto.PREFIX + slot]))
        frame[proto.PREFIX + slot:proto.PREFIX + slot + 2] = bytes([crc & 0xFF, crc >> 8])
    crc = bitwise_crc16(bytes(frame))
    return bytes(frame + bytes([crc & 0xFF, crc >> 8]))


def reference_frame(packet_id: int, first: int, params: bytes) -> bytes:
    body = proto.stuff(bytes([first]) + params)
    n = len(body) + 2
    frame = b"\xff\xff\xfd\x00" + bytes([packet_id, n & 0xFF, n >> 8]) + body
    crc = bitwise_crc16(frame)
    return frame + bytes([crc & 0xFF, crc >> 8])


# Bytes that make stuffing likely (FF FF FD) as well as any.
wire_bytes = st.lists(st.sampled_from([0xFF, 0xFD, 0x00]) | st.integers(0, 255),
                      max_size=20).map(bytes)


@pytest.mark.slow  # 300 examples, 0.7 s
@settings(max_examples=300, database=None, derandomize=True)
@given(length=st.integers(0, 12), n=st.integers(1, 7), seed=wire_bytes, errors=wire_bytes)
def test_the_combined_status_is_the_definitions_bytes(length, n, seed, errors):
    """fast_sync_status (no stuffing: the body as it is; running CRCs continued) gives the
    byte-by-byte definition's frame, and the bridge's check accepts it; a corrupted CRC of
    any motor but the last is found at that motor."""
    pool = (seed or b"\x00") * (length * n + 1)
    blocks = [(k + 1, (errors or b"\x00")[k % max(len(errors), 1)],
               pool[k * length:(k + 1) * length]) for k in range(n)]
    frame = proto.fast_sync_status(blocks)
    assert frame == reference_fast_sync_status(blocks)
    parser = proto.PacketParser(status=True)
    parser.feed(frame)
    assert parser.parse() == proto.OK
    ids = [b[0] for b in blocks]
    assert proto.check_fast_sync(parser, ids, length) == (0, -1)
    stuffed = len(frame) != 8 + n * (length + 4)
    for k in range(n - 1):
        if stuffed:
            break  # only the packet's own CRC is relied on then (check_fast_sync)
        bad = bytearray(frame)
        at = proto.PREFIX + 1 + k * (length + 4) + 2 + length  # motor k's CRC
        bad[at] ^= 0x01
        crc = bitwise_crc16(bytes(bad[:-2]))
        bad[-2:] = bytes([crc & 0xFF, crc >> 8])  # the packet's own CRC still right
        parser.reset()
        parser.feed(bytes(bad))
        if parser.parse() == proto.OK:  # (the flip may have made a stuffing pattern)
            assert proto.check_fast_sync(parser, ids, length) == (proto.FAST_BLOCK_CRC, k)


@pytest.mark.slow  # 400 examples, 0.8 s
@settings(max_examples=400, database=None, derandomize=True)
@given(first=st.sampled_from([0xFF, 0xFD, 0x55, 0x03, 0x83]), params=wire_bytes,
       packet_id=st.integers(0, 252), as_array=st.booleans())
def test_frames_are_the_definitions_bytes_and_parse_back(first, params, packet_id, as_array):
    """encode_into copies parameters with nothing to stuff in one piece (an FF FF FD across
    the first byte and the parameters counts too), and the parser skips unstuffing where
    there is no FF FF FD: a frame is the definition's bytes and parses back to its fields."""
    out = bytearray(proto.PREFIX + 2 * (1 + len(params)) + 2)
    source = bytearray(params) if as_array else params
    n = proto.encode_into(out, packet_id, first, source, len(params))
    assert bytes(out[:n]) == reference_frame(packet_id, first, params)
    parser = proto.PacketParser(status=first == 0x55)
    parser.feed(bytes(out[:n]))
    if first == 0x55 and not params:
        assert parser.parse() == proto.BAD_LENGTH  # a status without its error byte
        return
    assert parser.parse() == proto.OK
    assert (parser.id, parser.instruction) == (packet_id, first)
    got = bytes(parser.buf[parser.params_start - (first == 0x55):
                           parser.params_start + parser.params_len])
    assert got == params


# ---- the wire-timed reply goes out on time ---------------------------------------------------

def test_a_due_reply_goes_out_before_the_plants_update(monkeypatch):
    """With wire timing, a reply falls due while the loop sleeps: it is written at once, not
    after a plant update (a step, the publication, the watchdogs: tens of microseconds the
    transaction used to take on top of its wire time), and no update runs that is not due."""
    chain = VirtualChain("serial", "serial_joint", plant_period_s=0.05, wire_timing=True,
                         baud=57600)  # next update in 50 ms; the reply due in 5 ms
    chain.open()
    fd = os.open(chain.path, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    order: list[str] = []
    real_select, real_tick, real_write = select.select, chain._tick, os.write

    def counted_select(r, w, x, timeout=None):
        order.append("select")
        if order.count("select") > 2:  # the request, then the wait for its reply: stop
            chain._stop.set()
            return [], [], []
        return real_select(r, w, x, min(timeout, 5.0))

    def counted_tick(now, **how):
        order.append("tick")
        real_tick(now, **how)

    def counted_write(f, data):
        if f == chain.master:
            order.append("write")
        return real_write(f, data)

    monkeypatch.setattr(select, "select", counted_select)
    monkeypatch.setattr(chain, "_tick", counted_tick)
    monkeypatch.setattr(os, "write", counted_write)
    m = chain.motors[0]
    try:
        real_write(fd, proto.read(m.id, 132, 4))
        chain.serve(duration=10)
        monkeypatch.undo()
        assert take(fd, 15) == proto.status(m.id, 0, bytes(m.table[132:136]))
    finally:
        os.close(fd)
        chain.close()
    # the request (its step to the arrival), the sleep until the replies are due, the replies
    assert order[:4] == ["select", "tick", "select", "write"], order
    assert "tick" not in order[2:], order


def test_wire_timed_replies_are_not_early():
    """Sleeping until shortly before a reply is due and waiting out the rest on the clock
    (WIRE_SPIN_S) never sends it before its wire time: the request's and the replies' bytes
    at 57600 baud (182 bytes, 31.6 ms), timed from the request's write to the last byte."""
    chain = VirtualChain("serial", "serial_joint", wire_timing=True, baud=57600)
    ids = [m.id for m in chain.motors]
    request = proto.sync_read(132, 4, ids)
    wire_s = (len(request) + 6 * 15) * 10 / 57600
    with chain:
        fd = os.open(chain.path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(fd)
        try:
            for _ in range(3):
                t = time.perf_counter()
                os.write(fd, request)
                assert len(take(fd, 6 * 15)) == 6 * 15
                assert time.perf_counter() - t >= wire_s
        finally:
            os.close(fd)


def test_the_serving_thread_asks_for_precise_timers():
    """The emulator's thread asks the kernel for a 1 ns timer slack (a sleep then ends on
    time, not up to 50 us later): read back through prctl's PR_GET_TIMERSLACK in a thread
    of its own."""
    if not sys.platform.startswith("linux"):
        pytest.skip("timer slack is Linux's")
    libc = ctypes.CDLL(None)
    got = {}

    def probe():  # a thread inherits its creator's slack: start from the default's 50 us
        assert libc.prctl(29, 50_000, 0, 0, 0) == 0  # PR_SET_TIMERSLACK
        got["before"] = libc.prctl(30, 0, 0, 0, 0)  # PR_GET_TIMERSLACK
        got["ok"] = precise_timers()
        got["after"] = libc.prctl(30, 0, 0, 0, 0)

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    assert got["ok"] and got["before"] == 50_000 and got["after"] == 1, got


@pytest.mark.slow
@settings(max_examples=300, database=None, derandomize=True)
@given(error=st.sampled_from([0x00, 0xFF, 0x80, 0x07]), params=wire_bytes,
       packet_id=st.integers(0, 252), as_array=st.booleans())
def test_a_status_packet_is_the_definitions_bytes(error, params, packet_id, as_array):
    """status() builds a packet with nothing to stuff in one piece, its CRC continued from a
    remembered head's (an FF FF FD across the error byte and the data counts too): the
    definition's bytes either way, for any motor, error and data, and again from the head's
    cache."""
    expected = reference_frame(packet_id, 0x55, bytes([error]) + params)
    source = bytearray(params) if as_array else params
    assert proto.status(packet_id, error, source) == expected
    assert proto.status(packet_id, error, source) == expected


def test_a_one_item_write_is_the_loops_write():
    """A write of one whole item (a period's Goal Current) takes the short path: the same
    errors and the same table as the same item written beside another one, over the range,
    the limit, the sign, and with the torque on (an EEPROM item is refused)."""
    chain = VirtualChain("serial", "serial_joint")
    try:
        one, two = chain.motors[0], chain.motors[1]
        for m in (one, two):
            m.write(11, bytes([0]))  # current control
        goal, limit = one.a_goal_current, one.get(one.a_limit)
        before = one.a_goal_current - 2  # the item just below Goal Current (Goal PWM)
        assert one.items[before].size == 2
        pwm = proto.le(one.get(before), 2)
        for value in (0, 5, -5, limit, -limit, limit + 1, -limit - 1, 32767, -32768):
            data = proto.le(value, 2)
            alone = one.write(goal, data)
            beside = two.write(before, pwm + data)
            assert alone[0] == beside[0], value
            assert alone[1] == [w for w in beside[1] if w[0] == goal], value
            ram = slice(one.ram_from, one.a_tick)  # the writable RAM items (not their states)
            assert one.table[ram] == two.table[ram], value
        for m in (one, two):
            m.write(m.a_torque, bytes([1]))
        assert one.write(11, bytes([0]))[0] == two.write(10, bytes([0, 0]))[0] != 0
    finally:
        chain.close()


def test_a_write_request_leaves_the_registers_to_the_next_read(chain):
    """A request's update publishes the present registers only for an instruction that reads
    them: a SYNC_WRITE alone publishes nothing; a SYNC_READ after it in the same data reports
    the currents applied at the data's arrival (before the write), and the next request's
    read the new ones; the Realtime Tick is the update's."""
    ids = [m.id for m in chain.motors]
    for frame in [proto.write(i, 11, bytes([0])) for i in ids] + \
            [proto.write(i, 64, bytes([1])) for i in ids]:
        serve(chain, frame, now=float("inf"))
        take(chain.client, 11)
    published: list[int] = []
    real = chain._publish

    def counted(tick_ms, currents=None):
        published.append(tick_ms)
        real(tick_ms, currents)

    chain._publish = counted
    serve(chain, proto.sync_write(102, 2, [(i, proto.le(7, 2)) for i in ids]))
    assert published == []
    serve(chain, proto.sync_write(102, 2, [(i, proto.le(9, 2)) for i in ids])
          + proto.sync_read(126, 2, ids), now=float("inf"))
    assert len(published) == 1
    got = take(chain.client, len(ids) * 13)
    assert got == b"".join(proto.status(i, 0, proto.le(7, 2)) for i in ids)
    serve(chain, proto.sync_read(120, 8, ids), now=float("inf"))
    got = take(chain.client, len(ids) * 19)
    assert len(published) == 2
    assert got == expected_statuses(chain, 120, 8)
    assert all(m.get(126) == 9 for m in chain.motors)
    assert [m.get(120) for m in chain.motors] == [published[-1] % 32768] * len(ids)


@pytest.mark.parametrize("robot", ["serial", "parallel"])
def test_whole_plant_steps_taken_at_once_are_the_steps_one_by_one(robot):
    """Between two requests the realistic plant (50 us sub-steps) takes about ten whole steps
    per unit: with every motor driving they go in one call (two buffers, no copies), the same
    arithmetic as step after step: the same state to the bit, odd and even counts; a unit with
    a joint held takes them one by one."""
    chains = [VirtualChain(robot) for _ in range(2)]  # the realistic (geared) plant
    try:
        for chain in chains:
            for m in chain.motors:
                m.write(m.a_mode, bytes([0]))
                m.write(m.a_torque, bytes([1]))
                m.write(m.a_goal_current, proto.le(40 + m.id, 2))
        one, many = chains
        h = one.h
        for k in (2, 3, 10):
            for u in one.units:
                for _ in range(k):
                    assert u.advance(h)
            for u in many.units:
                assert u.batchable()
                assert u.advance_many(h, k)
            for a, b in zip(one.units, many.units):
                assert np.array_equal(a.x, b.x) and np.any(a.x[a.n:2 * a.n] != 0)
        many.motors[0].write(many.motors[0].a_torque, bytes([0]))
        assert not many.units[0].batchable()
    finally:
        for chain in chains:
            chain.close()


def test_steps_taken_at_once_keep_to_the_plants_budget():
    """A plant whose steps cost more than real time allows falls behind (counted) rather than
    hog the processor (MAX_PLANT_DUTY of the time since the last update), steps taken at once
    or not: a batch holds no more steps than the budget has room for at the measured cost of
    a step. Here 40 ms of 50 us steps of the parallel mechanism's geared plant (tens of us a
    step) after 1 ms of quiet: far fewer steps than 800, and one overrun."""
    chain = VirtualChain("parallel", plant_period_s=5e-5, plant="realistic")
    try:
        for m in chain.motors:
            m.write(m.a_mode, bytes([0]))
            m.write(m.a_torque, bytes([1]))
        assert all(u.batchable() for u in chain.units)
        chain._last_tick_end = time.perf_counter() - 1e-3
        chain._tick(chain._plant_time + 0.04)
        assert chain.counts["plant_overruns"] == 1
        assert 1 <= chain.counts["plant_steps"] < 400, chain.counts
    finally:
        chain.close()


@pytest.mark.parametrize("robot, batched", [("serial", True), ("serial", False),
                                            ("parallel", True), ("parallel", False)])
def test_a_plant_gone_non_finite_shuts_its_motors_down(robot, batched):
    """A unit's plant that goes non-finite (here a speed of 1e308, whose next step overflows)
    latches every one of its motors' overload error (Hardware Error Status bit 5), turns their
    torque off and keeps the last finite state with its speeds zeroed, whether the steps went
    one by one or at once; the chain's other unit drives on."""
    chain = VirtualChain(robot)  # the realistic (geared) plant, served by hand: no thread
    try:
        for m in chain.motors:
            m.write(m.a_mode, bytes([0]))
            m.write(m.a_torque, bytes([1]))
            m.write(m.a_goal_current, proto.le(40, 2))
        broken = chain.units[-1]
        n = broken.n
        broken.x[n] = 1e308
        q = broken.x[:n].copy()
        assert all(u.batchable() for u in chain.units)
        steps = 10 if batched else 1
        chain._last_tick_end = time.perf_counter() - 1.0  # budget for every step at once
        chain._step_cost = 1e-6  # as measured by earlier steps (unmeasured: one by one)
        chain._tick(chain._plant_time + steps * chain.h - 1e-9 * (not batched))
        assert chain.counts["plant_steps"] == steps
        for m in broken.motors:
            assert m.table[m.a_error] & (1 << 5) and m.table[m.a_torque] == 0, m.id
        assert np.isfinite(broken.x).all() and np.array_equal(broken.x[:n], q)
        assert not broken.x[n:2 * n].any() and not broken.x[3 * n:].any()
        assert not broken.batchable()  # its motors no longer drive
        for u in chain.units[:-1]:  # the other arm drives on
            assert all(m.table[m.a_error] == 0 and m.table[m.a_torque] == 1 for m in u.motors)
            assert np.isfinite(u.x).all() and np.any(u.x[u.n:2 * u.n] != 0)
    finally:
        chain.close()
