"""The virtual chain's per-period work stays small (issue 30, item 2): a period's status
packets reach the pseudo-terminal in one system call, with the same bytes in the same order,
and packets due at different times (wire timing) still go each at its own time; a request takes
one plant step; the faster CRC is the specification's. Not timed:
the system calls are counted, so the tests hold on a loaded machine
(``bench/emulator_speed.py`` measures the time)."""

from __future__ import annotations

import os
import select
import time
import tty

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cochlea.dynamixel import protocol as proto
from cochlea.dynamixel.emulator import VirtualChain


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

    def counted_tick(now):
        order.append("tick")
        real_tick(now)

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
