"""The virtual chain's C lane (``cochlea/dynamixel/lane.py``) against its Python path.

Two chains of the same robot take the same bytes at the same (fixed) time, one answering the
period's requests in C and one in Python (``_lane = None``); their replies (bytes and due
times), control tables, events, counts and contacts must be equal after every receive. The
plant is held still (its update is the chain's own, the same on both paths), so the present
registers are what the test puts there.
"""

from __future__ import annotations

import contextlib
import os
import random
import time

import numpy as np
import pytest

from cochlea.dynamixel import lane as c_lane
from cochlea.dynamixel import protocol as proto
from cochlea.dynamixel.emulator import Faults, VirtualChain

PERIOD_BLOCK = (120, 16)  # Realtime Tick .. Present Position (X series)


def _pair(robot: str = "serial", **options) -> list[VirtualChain]:
    chains = [VirtualChain(robot, f"{robot}_joint", **options) for _ in range(2)]
    assert chains[0]._lane is not None, \
        "build/libcochlea-lane.so missing or older than its sources: run make lib"
    chains[1]._lane = None
    for c in chains:
        c._tick = lambda now, publish=True: None  # the plant holds still
        c.lane_served = 0
        serve = c._lane_serve

        def counted(now, packets, c=c, serve=serve):
            c.lane_served += 1
            serve(now, packets)

        c._lane_serve = counted
    return chains


def _replies(chain: VirtualChain) -> list[tuple[float, bytes]]:
    """The queued status packets by due time, bytes in wire order (the lane may queue one
    entry where Python queues one per motor: the same bytes at the same time)."""
    due: dict[float, bytes] = {}
    for t, _, packet in sorted(chain._queue):
        due[t] = due.get(t, b"") + packet
    chain._queue.clear()
    return list(due.items())


def _state(chain: VirtualChain):
    return ([bytes(m.table) for m in chain.motors], [e[1:] for e in chain.events],
            dict(chain.counts), [m.last_contact for m in chain.motors],
            [m.answering for m in chain.motors], chain._bus_free)


def _both(chains, data: bytes, now: float) -> list[tuple[float, bytes]]:
    got = []
    for c in chains:
        c._received(data, now)
        got.append(_replies(c))
    assert got[0] == got[1]
    assert _state(chains[0]) == _state(chains[1])
    return got[0]


def _start(chains, now: float = 1.0) -> list[int]:
    ids = [m.id for m in chains[0].motors]
    for i in ids:  # current control, torque on (WRITEs: the Python path on both)
        _both(chains, proto.write(i, 11, bytes([0])) + proto.write(i, 64, bytes([1])), now)
    return ids


def test_a_period_is_answered_by_the_lane_as_python_answers_it():
    chains = _pair()
    ids = _start(chains)
    served = chains[0].lane_served
    now = 2.0
    for k in range(20):
        now += 1e-3
        for c in chains:  # a request's own update, not yet published (see VirtualChain._tick)
            c._unpublished, c._unpublished_currents = k, None
        period = proto.sync_write(102, 2, [(i, proto.le(10 * k - 50 + i, 2)) for i in ids]) + \
            proto.sync_read(*PERIOD_BLOCK, ids)
        replies = _both(chains, period, now)
        assert len(replies) == 1 and replies[0][1].count(b"\xff\xff\xfd\x00") == len(ids)
    assert chains[0].lane_served == served + 20
    assert chains[1].lane_served == 0
    # The goal currents written are in the tables, and logged as the Python path logs them.
    assert chains[0].writes()[-len(ids):] == [(i, 102, 190 - 50 + i) for i in ids]


def test_refusals_errors_levels_and_stuffing_are_the_python_paths():
    chains = _pair(wire_timing=True, baud=1_000_000)
    ids = _start(chains)
    now = 3.0
    a, b, c, d = ids[:4]
    # Status Return Level 0 (no reply to a read) and 1 (replies to reads only).
    _both(chains, proto.write(a, 68, bytes([0])) + proto.write(b, 68, bytes([1])), now)
    for ch in chains:
        ch.by_id[c].latch_hardware_error(2)  # the alert bit in its replies, torque off
        ch.by_id[d].trip_watchdog()  # its goal values refused (Data Range)
        ch.by_id[ids[4]].answering = False
        # Present Position bytes that need stuffing in the status packet: FF FF FD.
        ch.by_id[ids[5]].table[132:136] = b"\xff\xff\xfd\x00"
    served = chains[0].lane_served
    limit = chains[0].by_id[a].get(chains[0].by_id[a].a_limit)
    requests = [
        # over the limit (Data Limit), an unknown ID, a duplicate, the extremes
        proto.sync_write(102, 2, [(a, proto.le(limit + 1, 2)), (99, proto.le(1, 2)),
                                  (b, proto.le(-limit, 2)), (b, proto.le(limit, 2)),
                                  (c, proto.le(-32768, 2)), (d, proto.le(1, 2))]
                         + [(i, proto.le(3, 2)) for i in ids[4:]]),
        proto.sync_read(*PERIOD_BLOCK, ids + [99, a]),  # unknown ID, a duplicate
        proto.sync_read(0, 4, ids),
        proto.sync_read(len(chains[0].motors[0].table) - 2, 4, ids),  # past the table: Access
        proto.sync_read(120, 0, ids),  # no data: Access
        proto.sync_read(*PERIOD_BLOCK, []),  # nobody
    ]
    for r in requests:
        now += 1e-3
        _both(chains, r, now)
    assert chains[0].lane_served == served + len(requests)
    errors = [e for e in chains[0].events if e[1] == "refused"]
    assert {e[2] for e in errors} >= {a, d}


def test_anything_else_takes_the_python_path_unchanged():
    chains = _pair()
    ids = _start(chains)
    now = 4.0
    good = proto.sync_read(*PERIOD_BLOCK, ids)
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    stuffed = proto.sync_read(0xFFFF, 0xFD, ids)  # FF FF FD in its parameters: stuffed
    assert len(stuffed) == len(proto.sync_read(0, 0, ids)) + 1
    cases = [
        good[:9],  # a request in pieces: the rest finds the parser holding the start
        bytes(bad_crc),  # a corrupted request
        b"\x00" + good,  # garbage before it
        stuffed,  # a parameter that needed stuffing
        proto.sync_write(116, 4, [(i, proto.le(0, 4)) for i in ids]),  # another item
        proto.sync_write(102, 2, [(ids[0], proto.le(1, 2))]) + proto.ping(ids[0]),
        proto.read(ids[0], 120, 16),
        # more than the lane's bounds (a hostile host): 300 motors listed, a 2000-byte read
        proto.sync_read(*PERIOD_BLOCK, (ids * 60)[:300]),
        proto.sync_write(102, 2, [(i, proto.le(1, 2)) for i in (ids * 60)[:300]]),
        proto.sync_read(0, 2000, ids),
    ]
    served = chains[0].lane_served
    for data in cases:
        now += 1e-3
        _both(chains, data, now)
        assert chains[0].lane_served == served, data  # none of them is the lane's
        if data == good[:9]:
            _both(chains, good[9:], now)
        for c in chains:
            assert c._parser.pending == 0 or data in (bytes(bad_crc), good[:9])
            c._parser.reset()
    assert chains[0].lane_served == served
    now += 1e-3
    _both(chains, good, now)
    assert chains[0].lane_served == served + 1


def test_a_chain_with_faults_on_its_replies_is_served_in_python():
    chains = _pair(faults=Faults(drop=0.5, seed=3))
    ids = _start(chains)
    chains[0]._received(proto.sync_read(*PERIOD_BLOCK, ids), 5.0)
    assert chains[0].lane_served == 0


@pytest.mark.parametrize("seed", [1, 2])
def test_random_requests_agree(seed):
    """Random receives of period requests, refused values, other instructions, torn packets
    and register changes behind the instructions' back."""
    rng = random.Random(seed)
    chains = _pair("parallel" if seed == 2 else "serial")
    ids = _start(chains)
    table_size = len(chains[0].motors[0].table)
    now = 5.0

    def packet() -> bytes:
        kind = rng.random()
        some = rng.sample(ids + [77], rng.randint(0, len(ids) + 1))
        if kind < 0.35:
            return proto.sync_write(102, 2, [(i, proto.le(rng.choice(
                [rng.randint(-1500, 1500), rng.randint(-32768, 32767), 0]), 2)) for i in some])
        if kind < 0.7:
            return proto.sync_read(rng.choice([120, 126, rng.randrange(table_size)]),
                                   rng.choice([16, 10, 1, rng.randint(0, 40)]), some)
        if kind < 0.8:
            return proto.write(rng.choice(ids), rng.choice([68, 64, 98]),
                               bytes([rng.choice([0, 1, 2])]))
        if kind < 0.85:
            return proto.instruction(proto.BROADCAST_ID, proto.REBOOT) if rng.random() < 0.2 \
                else proto.reboot(rng.choice(ids))
        if kind < 0.9:
            return proto.ping(rng.choice(ids))
        return bytes(rng.randrange(256) for _ in range(rng.randint(1, 12)))

    served = 0
    for _ in range(300):
        now += rng.choice([1e-4, 1e-3, 0.05])
        r = rng.random()
        for c in chains:  # behind the instructions' back, the same on both
            m = c.motors[int(r * 1000) % len(ids)]
            if r < 0.03:
                m.latch_hardware_error(random.Random(r).randrange(6))
            elif r < 0.05:
                m.trip_watchdog()
            elif r < 0.08:
                m.answering = not m.answering
            elif r < 0.15:
                m.table[132:136] = random.Random(r).choice([b"\xff\xff\xfd\x00",
                                                            b"\x01\x02\x03\x04"])
            elif r < 0.3:
                c._unpublished, c._unpublished_currents = int(r * 1e4), None
        data = b"".join(packet() for _ in range(rng.randint(1, 3)))
        if rng.random() < 0.1:
            data = data[:rng.randint(0, len(data))]  # torn: the rest is lost
        _both(chains, data, now)
        served = chains[0].lane_served
    assert served > 50  # the lane took a good share of them


def test_a_library_older_than_its_sources_is_not_used(tmp_path, monkeypatch):
    """A checkout whose lane.c changed after ``make lib`` (edited, pulled) answers in Python
    until the library is rebuilt: an old library may not do what the source now says."""
    root = tmp_path / "checkout"
    for name in c_lane.SOURCES:
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text("/* source */\n")
    built = root / "build" / c_lane.LIBRARY_NAME
    built.parent.mkdir()
    built.write_bytes(c_lane.library_path().read_bytes())
    monkeypatch.setattr(c_lane, "checkout", lambda: root)
    os.utime(built, (2e9, 2e9))  # built after its sources
    assert c_lane.load() is not None
    os.utime(root / c_lane.SOURCES[0], (2e9 + 1, 2e9 + 1))  # lane.c edited since
    assert c_lane.load() is None


def test_the_lane_can_be_switched_off(monkeypatch):
    """``COCHLEA_EMULATOR_LANE=0``: no lane, the chain answers the period in Python."""
    assert c_lane.load() is not None
    monkeypatch.setenv(c_lane.ENVIRONMENT, "0")
    assert c_lane.load() is None
    chain = VirtualChain("serial", "serial_joint")
    assert chain._lane is None
    ids = [m.id for m in chain.motors]
    chain._received(proto.sync_read(*PERIOD_BLOCK, ids), 1.0)
    assert len(_replies(chain)[0][1]) == len(ids) * (11 + PERIOD_BLOCK[1])


class _ScriptedLine:
    """A port whose replies are scripted: the chunks of ``replies`` arrive after the next
    request is written, one per read; otherwise a read gets nothing until its deadline."""

    low_latency = None

    def __init__(self):
        self.replies: list[bytes] = []
        self.chunks: list[bytes] = []

    def discard_input(self) -> bool:
        return True

    def write(self, view, n, deadline) -> bool:
        self.chunks, self.replies = self.replies, []
        return True

    def read_into(self, view, deadline: float) -> int:
        if not self.chunks:
            time.sleep(max(0.0, min(deadline - time.perf_counter(), 0.05)))
            return 0
        chunk = self.chunks.pop(0)
        view[:len(chunk)] = chunk
        return len(chunk)


def _blocks(bridge):
    """``block(tick, j)``: motor j's bytes of the bridge's per-period read (its own layout:
    Present Current, Velocity, Position, and the Realtime Tick when it reads it)."""
    dtype = bridge._cur.base.dtype

    def block(tick: int, j: int) -> bytes:
        record = np.zeros(1, dtype)
        record["current"], record["velocity"], record["position"] = 10 * j - 20, -3 * j, \
            2048 + 100 * j
        if "tick" in dtype.names:
            record["tick"] = tick
        return record.tobytes()
    return block


@contextlib.contextmanager
def _bridge_pair(timeout_s: float):
    """Two enabled bridges of the serial chain on scripted lines: the first checks whole
    SYNC_READ replies in C (``taken``: what each of its C checks said), the second parses
    every reply in Python. Yields ``(bridges, lines, taken)``."""
    from cochlea.dynamixel.bridge import DynamixelBackend

    chains = [VirtualChain("serial").start() for _ in range(2)]
    bridges = [DynamixelBackend("serial", c.path, description=c.scenario.description,
                                timeout_s=timeout_s) for c in chains]
    try:
        for b in bridges:
            b.enable()
        block = bridges[0]._status_block
        assert block is not None
        taken = []

        class Counted:  # the C check, counting the replies it took whole
            total = block.total

            def __call__(self, start, n_bytes):
                taken.append(block(start, n_bytes))
                return taken[-1]

        bridges[0]._status_block = Counted()
        bridges[1]._status_block = None
        lines = [_ScriptedLine() for _ in bridges]
        for b, line in zip(bridges, lines):
            b._port = line
        yield bridges, lines, taken
    finally:
        for b in bridges:
            b._port = None
        for c in chains:
            c.close()


@pytest.mark.hil
def test_the_bridge_reads_a_sync_read_in_c_as_in_python():
    """The bridge's SYNC_READ replies checked in one C call (lane.StatusBlock) or parsed in
    Python: the same result, state, failures and counters for healthy and damaged replies."""
    with _bridge_pair(timeout_s=0.01) as (bridges, lines, taken):
        ids = bridges[0].ids
        n = len(ids)
        _block = _blocks(bridges[0])

        def replies(tick, change=None):
            packets = [proto.status(i, 0, _block(tick, j)) for j, i in enumerate(ids)]
            if change is not None:
                packets = change(packets)
            return b"".join(packets)

        def corrupt(k):
            def f(p):
                p = list(p)
                p[k] = p[k][:-1] + bytes([p[k][-1] ^ 0xFF])
                return p
            return f

        def replace(k, packet):
            def f(p):
                p = list(p)
                p[k] = packet
                return p
            return f

        cases = [
            lambda t: [replies(t)],
            lambda t: [replies(t)[:10], replies(t)[10:70], replies(t)[70:]],
            lambda t: [b"\x00\x01" + replies(t)],
            lambda t: [replies(t) + b"\xff\xff\xfd"],
            lambda t: [replies(t, corrupt(2))],
            lambda t: [replies(t, replace(1, proto.status(ids[1], 1, _block(t, 1))))],
            lambda t: [replies(t, lambda p: [p[1], p[0], *p[2:]])],
            lambda t: [replies(t, lambda p: p[:-1])],  # the last motor silent
            lambda t: [replies(t, replace(3, proto.status(ids[3], 0, b"\xff\xff\xfd"
                                                          + _block(t, 3)[3:])))],  # stuffed
            lambda t: [replies(t, replace(0, proto.status(ids[0], 0, _block(t, 0)[:-1])))],
            lambda t: [replies(t, lambda p: [p[0], *p])],  # a packet twice
            lambda t: [replies(t, replace(4, proto.status(ids[4], 0x80, _block(t, 4))))],
            lambda t: [replies(t)],
        ]
        good = 0
        for k, case in enumerate(cases):
            results = []
            for b, line in zip(bridges, lines):
                line.replies = case(100 + 7 * k)
                x = np.full(2 * n, np.nan)
                ok = b.read(x)
                good += ok
                results.append((ok, x.tobytes(), bytes(b._raw), list(b.failures),
                                b.garbage_packets, b.unexpected_packets, sorted(b.alert_ids),
                                b._alert_pending, b.describe_last_failure(), b.good_reads))
            assert results[0] == results[1], k
        assert good >= 2 * 5  # the healthy replies were read
        # In C: the healthy replies whole, in pieces, and with bytes after them; the rest (bytes
        # before them, another order, a stuffed byte, a packet twice) read in Python.
        assert sum(taken) == 3


def _recrc(packet: bytes) -> bytes:
    """``packet`` with its last two bytes made its CRC again (a damage a CRC cannot see)."""
    crc = proto.crc16(packet, 0, len(packet) - 2)
    return packet[:-2] + bytes((crc & 0xFF, crc >> 8))


@pytest.mark.hil
@pytest.mark.parametrize("seed", [1, 2])
def test_the_bridges_c_check_agrees_with_python_on_random_damage(seed):
    """Hostile replies to the period's SYNC_READ, a class, not a list: a healthy reply damaged
    at random -- bytes flipped, dropped, inserted, repeated or cut, packets swapped, left out or
    doubled, bytes changed under a CRC made good again (another ID, length, instruction,
    error or value that no CRC catches), values that make the motor stuff a byte -- and split
    into random pieces, read by the bridge that checks whole replies in C and by the one that
    parses them in Python: the same verdict, state, raw blocks, failures, counters and alerts
    every period. A wrong parse here would hand the controller a wrong state. (Removing the C
    check's stuffing test survives this: a stuffed packet's length field differs already.)"""
    rng = random.Random(seed)
    with _bridge_pair(timeout_s=0.002) as (bridges, lines, taken):
        ids = bridges[0].ids
        _block = _blocks(bridges[0])

        def damaged(tick: int) -> list[bytes]:
            packets = [proto.status(i, 0, _block(tick, j)) for j, i in enumerate(ids)]
            kind = rng.randrange(11)
            k = rng.randrange(len(packets))
            p = bytearray(packets[k])
            if kind == 0:  # healthy (the C path's, and a fresh tick after damage)
                pass
            elif kind == 1:
                p[rng.randrange(len(p))] ^= 1 << rng.randrange(8)
            elif kind == 2:
                del p[rng.randrange(len(p))]
            elif kind == 3:
                p.insert(rng.randrange(len(p) + 1), rng.randrange(256))
            elif kind == 4:  # under a good CRC: the ID, length, instruction, error or a value
                p[rng.choice([4, 5, 6, 7, 8, rng.randrange(9, len(p) - 2)])] = rng.randrange(256)
                p = bytearray(_recrc(bytes(p)))
            elif kind == 5:
                packets = [packets[i] for i in rng.sample(range(len(packets)), len(packets))]
            elif kind == 6:
                del packets[k]
                p = None
            elif kind == 7:
                packets.insert(k, packets[k])
            elif kind == 8:  # an error byte with the alert bit or a status error
                p = bytearray(proto.status(ids[k], rng.choice([0x80, 0x01, 0x07, 0x81]),
                                           _block(tick, k)))
            elif kind == 10:  # FF FF FD among the values: the motor stuffs a byte
                values = bytearray(_block(tick, k))
                at = rng.randrange(len(values) - 2)
                values[at:at + 3] = b"\xff\xff\xfd"
                p = bytearray(proto.status(ids[k], 0, bytes(values)))
            if p is not None and kind not in (5, 7):
                packets[k] = bytes(p)
            data = b"".join(packets)
            if kind == 9:
                data = data[:rng.randrange(len(data))] if rng.random() < 0.5 else \
                    bytes(rng.randrange(256) for _ in range(rng.randrange(1, 4))) + data
            if not data:
                return []  # nothing arrives
            cuts = sorted(rng.sample(range(1, len(data)), min(rng.randrange(3), len(data) - 1)))
            return [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)])]

        n = len(ids)
        for k in range(150):
            chunks = damaged(1000 + 3 * k)
            results = []
            for b, line in zip(bridges, lines):
                b._alert_pending = -1  # the next period reads the state, not an alert's cause
                line.replies = list(chunks)
                x = np.full(2 * n, np.nan)
                ok = b.read(x)
                results.append((ok, x.tobytes(), bytes(b._raw), list(b.failures),
                                b.garbage_packets, b.unexpected_packets, sorted(b.alert_ids),
                                b.describe_last_failure(), b.good_reads, b.reads))
            assert results[0] == results[1], (k, chunks)
        assert 10 <= sum(taken) < 150  # both paths were exercised
