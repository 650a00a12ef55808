"""Issue 27 items 3 and 4 on the C side: the embedded drive tables and the C bridge take a
P-series motor and a mixed X + P chain (tests/data/planar2_xp.toml: a PH42-020-S300-R shoulder,
an XM430-W350 elbow).

* the codec's BULK_READ (0x92) and BULK_WRITE (0x93) byte for byte the Python protocol's and
  the official SDK's (``dxl_bulk_read``, ``dxl_bulk_write``);
* the generated tables: each motor's items at its model's addresses, its units (counts per
  turn, velocity LSB, current unit) in its drive's constants, the Python drive's to the last
  bit, and the transfers ``choose_transfers`` chooses (BULK_READ + BULK_WRITE, cochlea-run's
  text);
* the C bridge against the Python bridge on a scripted line: every frame of a period, of the
  start-up's torque-on and its read-back and of the shut-down byte for byte, and every fault
  of a BULK_READ reply (a motor missing, a CRC error, a short packet, an error byte, an alert)
  the same failure kind and motor; a babbling line ends each wait at its deadline;
* ``cochlea-codegen --embedded`` of the mixed scenario, its program over ``cochlea-emulator``
  (``hil``): BULK_READ + BULK_WRITE and their budget in its summary, torque off confirmed on
  both motors, and tracking as ``cochlea-run`` tracks over the same emulator.
"""

from __future__ import annotations

import ctypes
import json
import math
import subprocess
import sys
from pathlib import Path

import dynamixel_sdk as sdk
import numpy as np
import pytest

from cochlea.dynamixel import protocol as proto
from cochlea.dynamixel.bridge import FAILURE_NAMES, DynamixelBackend
from cochlea.dynamixel.budget import bus_budget
from cochlea.dynamixel.control_table import ALERT_BIT, MODELS
from cochlea.dynamixel.drives import joint_drives
from cochlea.dynamixel.embedded_drives import (
    BUS_ITEMS,
    OPTIONAL_ITEMS,
    bus_choice,
    drives_header,
    joint_ampere_per_lsb,
)

from . import dxl_codec
from .embedded_build import build_library
from .test_dynamixel_fastsync import PH, CapturePort

ROOT = Path(__file__).resolve().parent.parent
CORE = ROOT / "embedded" / "core"
DATA = Path(__file__).resolve().parent / "data"
ARM = DATA / "planar2_xp.toml"
SCENARIO = DATA / "planar2_xp_joint.toml"
#: Each motor's per-period block (Realtime Tick .. Present Position): the PH42's, the XM430's.
READS = [(1, 568, 16), (2, 120, 16)]
#: embedded/core/bridge.h's failure kinds, in order (the Python bridge's names).
FAILURE_NAMES_C = ["timeout", "crc", "error-byte", "hardware-alert", "length", "port",
                   "late-traffic", "non-finite-command", "not-enabled", "stale-packet"]


# ---- the codec -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def codec():
    lib = dxl_codec.load(dxl_codec.build())
    u8p, u16p = ctypes.POINTER(ctypes.c_uint8), ctypes.POINTER(ctypes.c_uint16)
    lib.dxl_bulk_read.restype = ctypes.c_int32
    lib.dxl_bulk_read.argtypes = [u8p, ctypes.c_size_t, ctypes.c_char_p, u16p, u16p,
                                  ctypes.c_size_t]
    lib.dxl_bulk_write.restype = ctypes.c_int32
    lib.dxl_bulk_write.argtypes = [u8p, ctypes.c_size_t, ctypes.c_char_p, u16p, u16p,
                                   ctypes.c_char_p, ctypes.c_size_t]
    return lib


def _u16(values):
    return (ctypes.c_uint16 * max(1, len(values)))(*values)


def c_bulk_read(codec, reads, cap=None):
    ids, addresses, lengths = zip(*reads) if reads else ((), (), ())
    cap = dxl_codec.frame_size(5 * len(reads)) if cap is None else cap
    return dxl_codec.call_builder(codec, "dxl_bulk_read", cap, bytes(ids), _u16(addresses),
                                  _u16(lengths), len(reads))


def c_bulk_write(codec, writes, cap=None):
    ids = bytes(w[0] for w in writes)
    data = b"".join(w[2] for w in writes)
    cap = dxl_codec.frame_size(5 * len(writes) + len(data)) if cap is None else cap
    return dxl_codec.call_builder(codec, "dxl_bulk_write", cap, ids,
                                  _u16([w[1] for w in writes]),
                                  _u16([len(w[2]) for w in writes]), data, len(writes))


@pytest.mark.parametrize("reads", [
    READS, [(1, 144, 2), (2, 146, 1)],  # the e-Manual's example
    [(7, 0xFDFF, 0xFFFF), (3, 574, 10)],  # FF FF FD among the parameters: stuffed
    [(i, 120 + 448 * (i % 2), 16) for i in range(1, 17)], []])
def test_the_bulk_read_request_is_protocols_and_the_sdks(codec, reads):
    frame = c_bulk_read(codec, reads)
    assert frame == proto.bulk_read(reads)
    assert frame[7] == 0x92 and frame[4] == 0xFE
    if reads and b"\xff\xff\xfd" not in frame[7:]:  # the SDK does not stuff parameters
        port = CapturePort()
        group = sdk.GroupBulkRead(port, PH)
        for r in reads:
            assert group.addParam(*r)
        assert group.txPacket() == sdk.COMM_SUCCESS
        assert port.sent == [frame]
    if reads:  # too little room: refused, not truncated
        assert c_bulk_read(codec, reads, len(frame) - 1) == dxl_codec.E_SPACE


@pytest.mark.parametrize("writes", [
    [(1, 550, proto.le(-61, 2)), (2, 102, proto.le(-16, 2))],  # the mixed chain's Goal Current
    [(1, 512, b"\x01"), (2, 64, b"\x01")],  # its torque on
    [(1, 32, b"\xa0\x00"), (2, 31, b"\x50")],  # the e-Manual's example
    [(5, 0xFFFF, b"\xfd\x00"), (6, 102, b"\xff\xff\xfd\x01")],  # stuffed
    [(3, 100, b"")], []])
def test_the_bulk_write_is_protocols_and_the_sdks(codec, writes):
    frame = c_bulk_write(codec, writes)
    assert frame == proto.bulk_write(writes)
    assert frame[7] == 0x93
    if writes and all(w[2] for w in writes) and b"\xff\xff\xfd" not in frame[7:]:
        port = CapturePort()
        group = sdk.GroupBulkWrite(port, PH)
        for motor_id, address, data in writes:
            assert group.addParam(motor_id, address, len(data), list(data))
        assert group.txPacket() == sdk.COMM_SUCCESS
        assert port.sent == [frame]
    if writes:
        assert c_bulk_write(codec, writes, len(frame) - 1) == dxl_codec.E_SPACE
    # NULL data with a block to send: an impossible call, refused.
    if any(w[2] for w in writes):
        u8p = ctypes.POINTER(ctypes.c_uint8)
        out = (ctypes.c_uint8 * 64)()
        assert codec.dxl_bulk_write(ctypes.cast(out, u8p), 64, bytes(w[0] for w in writes),
                                    _u16([w[1] for w in writes]),
                                    _u16([len(w[2]) for w in writes]), None,
                                    len(writes)) == dxl_codec.E_ARG


# ---- the generated tables --------------------------------------------------------------------

def test_the_mixed_chain_s_tables_are_each_model_s_data():
    drives = joint_drives("serial", ARM)
    backend = DynamixelBackend("serial", "/dev/scripted", description=ARM, realtime_tick=True)
    read, write, why = bus_choice(drives)
    # The Python bridge's choice and text for the same chain, with the Realtime Tick.
    assert (read, write) == ("BULK_READ", "BULK_WRITE")
    assert (backend.read_instruction, backend.write_instruction) == ("bulk", "bulk")
    assert why == backend.read_choice
    header = drives_header("serial", ARM)
    assert "static const dxl_bus serial_bus = {DXL_BULK_READ, DXL_BULK_WRITE," in header
    for d in drives:  # each motor's items at its model's address and size
        spec = MODELS[d.spec.name]
        row = ", ".join("{0xFFFF, 0}" if name in OPTIONAL_ITEMS and name not in
                        {it.name for it in spec.items} else
                        f"{{{spec.item(name).address}, {spec.item(name).size}}}"
                        for name in BUS_ITEMS)
        assert f'{{"{spec.name}", {{{row}}}, 0}}' in header
    ph42, xm430 = drives
    assert ph42.spec.item("Goal Current").address == 550
    assert xm430.spec.item("Goal Current").address == 102
    # Each drive's units are its model's: counts per turn, velocity LSB, current unit.
    assert ph42.q_per_count == 2 * math.pi / 607500
    assert xm430.q_per_count == 2 * math.pi / 4096
    assert ph42.qd_per_lsb == pytest.approx(0.01 * 2 * math.pi / 60, rel=1e-15)
    assert xm430.qd_per_lsb == pytest.approx(0.229 * 2 * math.pi / 60, rel=1e-15)
    assert (ph42.lsb_per_ampere, joint_ampere_per_lsb(ph42)) == (1000.0, 1e-3)
    assert joint_ampere_per_lsb(xm430) == pytest.approx(2.69e-3, rel=1e-15)
    for d in drives:  # printed so that C reads back the very doubles
        line = next(t for t in header.splitlines() if t.startswith(f'    {{"{d.name}"'))
        cells = line.strip().strip("{},").split(", ")
        assert int(cells[2]) == d.spec.number and int(cells[13]) == d.current_limit_lsb
        assert [float(cells[k]) for k in (4, 6, 11, 12)] == [
            d.q_per_count, d.qd_per_lsb, d.lsb_per_ampere, joint_ampere_per_lsb(d)], line


def test_no_x_series_constant_in_the_c_paths_a_p_motor_reaches():
    """Every conversion of the C bridge and program comes from the drive table: no 4096
    counts a turn or 0.229 rpm LSB in a C statement (comments may name them)."""
    import re

    for path in [*sorted((ROOT / "embedded" / "core").glob("*.[ch]")),
                 ROOT / "embedded" / "posix" / "main.c"]:
        code = re.sub(r"/\*.*?\*/", "", path.read_text(), flags=re.S)
        code = re.sub(r"char \w+\[4096\]", "", code)  # a path's buffer, not a resolution
        assert not re.search(r"\b4096(\.0)?\b|0\.229|\b2048\.0\b", code), path.name


# ---- the C bridge against the Python bridge, on a scripted line --------------------------------

LINE = r"""
#include <string.h>
#include "bridge.h"
#include "serial_drives.h"

/* A scripted line: the k-th frame written gets replies[k] (may be empty), once; then silence
 * (the clock jumps to the wait's deadline). babble: every read returns bytes at once. */
static struct {
    int64_t t;
    uint8_t replies[8192];
    size_t offsets[65], n_replies;
    size_t given, current;
    uint8_t sent[8192];
    size_t sent_len, sent_ends[64], n_sent;
    int babble;
} L;
static cochlea_hal hal;
static cochlea_bridge b;

static int64_t now_ns(void *c) { (void)c; return L.t; }
static void wait_until_ns(void *c, int64_t d) { (void)c; if (d > L.t) { L.t = d; } }
static void discard(void *c) { (void)c; }
static long line_write(void *c, const uint8_t *d, size_t n)
{
    (void)c;
    if (L.sent_len + n <= sizeof L.sent && L.n_sent < 64) {
        memcpy(L.sent + L.sent_len, d, n);
        L.sent_len += n;
        L.sent_ends[L.n_sent] = L.sent_len;
    }
    L.current = L.n_sent < L.n_replies ? L.n_sent : L.n_replies;
    L.given = 0;
    L.n_sent += 1;
    L.t += 1000;
    return (long)n;
}
static long line_read(void *c, uint8_t *d, size_t n, int64_t timeout_ns)
{
    (void)c;
    if (L.babble) { /* a line that always has a byte ready */
        size_t k = n < 7 ? n : 7;
        memset(d, 0xFF, k);
        L.t += 10000;
        return (long)k;
    }
    if (L.current < L.n_replies) {
        const size_t len = L.offsets[L.current + 1] - L.offsets[L.current];
        if (L.given < len) {
            size_t k = len - L.given;
            k = k < n ? k : n;
            memcpy(d, L.replies + L.offsets[L.current] + L.given, k);
            L.given += k;
            L.t += 2500;
            return (long)k;
        }
    }
    L.t += timeout_ns > 0 ? timeout_ns : 0;
    return 0;
}

int line_init(void)
{
    hal.ctx = 0;
    hal.serial_write = line_write;
    hal.serial_read = line_read;
    hal.serial_discard_input = discard;
    hal.rs485_direction = 0;
    hal.now_ns = now_ns;
    hal.wait_until_ns = wait_until_ns;
    L.t = 1000000000LL;
    if (cochlea_bridge_init(&b, &hal, serial_drives, SERIAL_N_DRIVES, 5000000LL, 0.1) != 0) {
        return -1;
    }
    return cochlea_bridge_use_realtime_tick(&b);
}
/* The replies for the next frames (n of them, lengths[k] bytes each), the log emptied. */
void line_script(const uint8_t *replies, const size_t *lengths, size_t n, int babble)
{
    size_t k, at = 0;
    for (k = 0; k < n && k < 64; ++k) {
        L.offsets[k] = at;
        at += lengths[k];
    }
    L.offsets[k] = at;
    memcpy(L.replies, replies, at);
    L.n_replies = k;
    L.sent_len = L.n_sent = 0;
    L.given = 0;
    L.current = 0;
    L.babble = babble;
}
int line_read_state(double *q, double *qd)
{
    b.active = 1;  /* as after a good start */
    b.suspect = 0; /* each case on a quiet line */
    return cochlea_bridge_read(&b, q, qd);
}
int line_write_tau(const double *tau, int torque_pending)
{
    b.active = 1;
    b.torque_pending = torque_pending;
    b.torque_failed_id = -1;
    return cochlea_bridge_write(&b, tau);
}
int line_torque_failed(void) { return b.torque_failed_id; }
int line_stop(void) { return cochlea_bridge_stop(&b); }
int64_t line_now(void) { return L.t; }
int line_failure(int *id) { *id = b.last_failure_id; return b.last_failure; }
const uint8_t *line_sent(size_t *n, const size_t **ends, size_t *n_frames)
{
    *n = L.sent_len;
    *ends = L.sent_ends;
    *n_frames = L.n_sent;
    return L.sent;
}
int line_instructions(void) { return b.bus->read_instruction << 8 | b.bus->write_instruction; }
const char *line_problem(void) { return b.config_problem; }
"""


class Line:
    """The C bridge of the mixed chain's generated table over the scripted line (ctypes)."""

    def __init__(self, tmp: Path, header: str | None = None):
        (tmp / "serial_drives.h").write_text(header or drives_header("serial", ARM))
        lib = build_library("p_series_line", [CORE / "dxl.c", CORE / "drives.c",
                                              CORE / "bridge.c", ("line.c", LINE)],
                            include=[CORE, tmp])
        self.c = ctypes.CDLL(str(lib), mode=ctypes.RTLD_LOCAL)
        dp = ctypes.POINTER(ctypes.c_double)
        self.c.line_script.argtypes = [ctypes.c_char_p, ctypes.POINTER(ctypes.c_size_t),
                                       ctypes.c_size_t, ctypes.c_int]
        self.c.line_read_state.argtypes = [dp, dp]
        self.c.line_write_tau.argtypes = [dp, ctypes.c_int]
        self.c.line_now.restype = ctypes.c_int64
        self.c.line_sent.restype = ctypes.POINTER(ctypes.c_uint8)
        self.c.line_problem.restype = ctypes.c_char_p
        self.init = self.c.line_init()
        self.n = 2

    def script(self, replies=(), babble=False):
        lengths = (ctypes.c_size_t * 64)(*[len(r) for r in replies])
        self.c.line_script(b"".join(replies), lengths, len(replies), int(babble))

    def read(self, reply: bytes, babble=False):
        self.script([reply], babble)
        q, qd = np.zeros(self.n), np.zeros(self.n)
        dp = ctypes.POINTER(ctypes.c_double)
        ok = self.c.line_read_state(q.ctypes.data_as(dp), qd.ctypes.data_as(dp))
        return bool(ok), q, qd, self.failure(ok)

    def failure(self, ok):
        motor = ctypes.c_int()
        kind = self.c.line_failure(ctypes.byref(motor))
        return (FAILURE_NAMES_C[kind] if not ok else None, motor.value)

    def write(self, tau, torque_pending=False, replies=()):
        self.script(replies)
        tau = np.asarray(tau, dtype=float)
        return bool(self.c.line_write_tau(tau.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
                                          int(torque_pending)))

    def sent(self) -> list[bytes]:
        n, frames = ctypes.c_size_t(), ctypes.c_size_t()
        ends = ctypes.POINTER(ctypes.c_size_t)()
        p = self.c.line_sent(ctypes.byref(n), ctypes.byref(ends), ctypes.byref(frames))
        data = bytes(p[:n.value])
        bounds = [0] + [ends[k] for k in range(frames.value)]
        return [data[a:b] for a, b in zip(bounds, bounds[1:])]


class ScriptedPort:
    """The Python bridge's port with the same script: the k-th frame written gets the k-th
    reply, once; every frame written is kept."""

    low_latency = None

    def __init__(self, replies=()):
        self.replies, self.sent, self.current, self.given = list(replies), [], -1, True

    def write(self, view, n, deadline):
        self.sent.append(bytes(view[:n]))
        self.current, self.given = len(self.sent) - 1, False
        return True

    def read_into(self, target, deadline):
        if self.given or self.current >= len(self.replies) or not self.replies[self.current]:
            return 0
        self.given = True
        reply = self.replies[self.current]
        target[:len(reply)] = reply
        return len(reply)

    def discard_input(self):
        pass

    def close(self):
        pass


def python_backend(port) -> DynamixelBackend:
    backend = DynamixelBackend("serial", "/dev/scripted", description=ARM, timeout_s=0.005,
                               realtime_tick=True)
    backend._port, backend._active = port, True
    return backend


def python_read(reply: bytes):
    backend = python_backend(ScriptedPort([reply]))
    x = np.zeros(2 * backend.nq)
    ok = backend.read(x)
    backend._active, backend._port = False, None
    kind = None if ok else FAILURE_NAMES[backend.last_failure]
    return ok, x[:backend.nq], x[backend.nq:], (kind, backend.last_failure_id)


@pytest.fixture
def line(tmp_path):
    line = Line(tmp_path)
    assert line.init == 0, line.c.line_problem()
    return line


def _block(rng, position_range):
    tick = proto.le(int(rng.integers(0, 32768)), 2)
    state = (proto.le(int(rng.integers(-500, 500)), 2)
             + proto.le(int(rng.integers(-3000, 3000)), 4)
             + proto.le(int(rng.integers(*position_range)), 4))
    return tick + b"\0\0\0\0" + state


def _replies(rng):
    """(case, the two status packets of a BULK_READ, as they come)."""
    ph42 = _block(rng, (-303750, 303750))  # multi-turn signed pulses, 607500 a turn
    xm = _block(rng, (0, 4096))
    good = proto.status(1, 0, ph42) + proto.status(2, 0, xm)
    wire = bytearray(good)
    wire[-3] ^= 0x40  # a bit flipped in the XM430's packet: its CRC fails
    stuffed = proto.status(1, 0, b"\0\0\0\0\0\0" + proto.le(-3, 2) + b"\xff\xff\xfd\x00"
                           + proto.le(-1000, 4)) + proto.status(2, 0, xm)
    return [
        ("good", good), ("other-order", proto.status(2, 0, xm) + proto.status(1, 0, ph42)),
        ("stuffed", stuffed), ("garbage-first", b"\x00\x12\x55" + good),
        ("stranger-first", proto.status(9, 0, b"\1\2") + good),
        ("twice", good + proto.status(1, 0, ph42)),
        ("missing", proto.status(1, 0, ph42)),
        ("first-missing", proto.status(2, 0, xm)),
        ("crc", bytes(wire)),
        ("short-packet", proto.status(1, 0, ph42[:-1]) + proto.status(2, 0, xm)),
        ("cut", good[:-4]),
        ("error-byte", proto.status(1, 0, ph42) + proto.status(2, 7, xm)),
        ("alert", proto.status(1, ALERT_BIT, ph42) + proto.status(2, 0, xm)),
        ("alert-and-error", proto.status(1, 1, ph42) + proto.status(2, ALERT_BIT, xm)),
        ("nothing", b""),
    ]


@pytest.mark.slow
def test_the_c_bulk_read_is_the_python_bridges_on_every_reply(line):
    """The same bytes through both bridges: the C request is the Python bridge's BULK_READ
    (each motor's block at its own address), and each reply gives the same state (the PH42's
    607500 counts a turn, 0.01 rpm and 1 mA; the XM430's), or the same failure kind and
    motor."""
    assert line.c.line_instructions() == 0x92 << 8 | 0x93
    rng = np.random.default_rng(27)
    seen = set()
    for case, reply in _replies(rng):
        c_ok, c_q, c_qd, c_fail = line.read(reply)
        assert line.sent() == [proto.bulk_read(READS)], case
        py_ok, py_q, py_qd, py_fail = python_read(reply)
        assert c_ok == py_ok, (case, c_fail, py_fail)
        if py_ok:
            assert c_q.tolist() == py_q.tolist() and c_qd.tolist() == py_qd.tolist(), case
        else:
            assert c_fail == py_fail, case
        seen.add(c_fail[0] if not c_ok else "ok")
    assert seen == {"ok", "timeout", "crc", "length", "error-byte", "hardware-alert"}


def _python_frames(tau, torque_replies, stop_replies):
    """The Python bridge's frames: the first nonzero write (Goal Current, the torque-on, its
    read-back), then the shut-down's."""
    port = ScriptedPort([b"", b""] + list(torque_replies))
    backend = python_backend(port)
    backend._torque_pending = True
    ok = backend.write(np.asarray(tau, dtype=float))
    on = port.sent
    port = ScriptedPort([b""] * 4 + list(stop_replies))
    backend._port = port
    backend.disable()
    return ok, backend.torque_on_error, on, port.sent, backend.shutdown_report


@pytest.mark.slow
def test_the_c_writes_torque_on_and_shut_down_are_the_python_bridges_frames(line):
    """Goal Current by BULK_WRITE (550 on the PH42, 102 on the XM430), the first nonzero one
    followed by BULK_WRITE Torque Enable 1 (512, 64) and its BULK_READ read-back; the
    shut-down's BULK_WRITEs of Goal Current 0 and Torque Enable 0, twice, then a READ of
    Torque Enable per motor: the Python bridge's bytes, frame for frame."""
    on = proto.status(1, 0, b"\x01") + proto.status(2, 0, b"\x01")
    off = [proto.status(1, 0, b"\x00"), proto.status(2, 0, b"\x00")]
    tau = [1.7, -0.4]
    assert line.write(tau, torque_pending=True, replies=[b"", b"", on])
    c_on = line.sent()
    py_ok, error, py_on, py_off, report = _python_frames(tau, [on], off)
    assert py_ok and error is None
    assert c_on == py_on
    goal = [drive.goal_current_lsb(t) for drive, t in zip(joint_drives("serial", ARM), tau)]
    assert c_on[0] == proto.bulk_write([(1, 550, proto.le(int(goal[0]), 2)),
                                        (2, 102, proto.le(int(goal[1]), 2))])
    assert c_on[1] == proto.bulk_write([(1, 512, b"\x01"), (2, 64, b"\x01")])
    assert c_on[2] == proto.bulk_read([(1, 512, 1), (2, 64, 1)])
    assert goal[0] != 0 and goal[1] != 0
    # A period's write after it: the one BULK_WRITE.
    assert line.write([0.5, 0.5])
    assert len(line.sent()) == 1 and line.sent()[0][7] == 0x93
    # The shut-down.
    line.script([b""] * 4 + off)
    assert line.c.line_stop() == 2
    c_off = line.sent()
    assert c_off == py_off
    zero = proto.bulk_write([(1, 550, b"\0\0"), (2, 102, b"\0\0")])
    torque_off = proto.bulk_write([(1, 512, b"\0"), (2, 64, b"\0")])
    assert c_off == [zero, torque_off] * 2 + [proto.read(1, 512, 1), proto.read(2, 64, 1)]
    assert "torque off confirmed by all 2" in report


@pytest.mark.slow
def test_a_torque_read_back_with_a_motor_missing_refuses_the_torque(line):
    """The XM430 does not answer the torque-on's BULK_READ: the write fails and every read
    after it (not-enabled, naming it), as in the Python bridge."""
    on = proto.status(1, 0, b"\x01")
    tau = [1.7, -0.4]
    assert not line.write(tau, torque_pending=True, replies=[b"", b"", on, on, on])
    assert line.c.line_torque_failed() == 2
    assert line.failure(0) == ("not-enabled", 2)
    ok, *_, fail = line.read(b"")
    assert not ok and fail == ("not-enabled", 2)
    py_ok, error, *_ = _python_frames(tau, [on, on, on], [])
    assert not py_ok and error.startswith("ID 2 (arm.forearm, XM430-W350) did not answer")


@pytest.mark.slow
def test_a_babbling_line_ends_every_bulk_wait_at_its_deadline(line):
    """A line that always has a byte ready (0xFF: never a whole packet): the period's
    BULK_READ fails as a timeout within its deadline, the torque-on's read-back fails within
    its retries' deadlines, and the shut-down ends: nothing hangs, whatever the line delivers."""
    t0 = line.c.line_now()
    ok, *_, fail = line.read(b"", babble=True)
    assert not ok and fail[0] == "timeout"
    assert line.c.line_now() - t0 <= 5_000_000 + 100_000  # the read timeout, 5 ms, and a read
    line.script(babble=True)
    t0 = line.c.line_now()
    assert not line.write([1.0, 1.0], torque_pending=True)
    assert line.c.line_torque_failed() == 1
    assert line.c.line_now() - t0 <= 3 * 20_000_000 + 1_000_000  # 3 tries of 20 ms at most
    line.script(babble=True)
    t0 = line.c.line_now()
    assert line.c.line_stop() == 0
    # a quiet line awaited first (the failed read: at most 2 read timeouts), then 2 motors x
    # 2 tries x 10 ms
    assert line.c.line_now() - t0 <= 2 * 5_000_000 + 4 * 10_000_000 + 1_000_000


@pytest.mark.slow
@pytest.mark.parametrize("edit,why", [
    # the table's read is not BULK_READ though the blocks lie at different addresses
    (("{DXL_BULK_READ, DXL_BULK_WRITE,", "{DXL_SYNC_READ, DXL_BULK_WRITE,"), "BULK_READ"),
    # its write is not BULK_WRITE though Goal Current lies at 550 and 102
    (("{DXL_BULK_READ, DXL_BULK_WRITE,", "{DXL_BULK_READ, DXL_SYNC_WRITE,"), "BULK_WRITE"),
    # the PH42's block one byte longer than the XM430's: no single read parses both
    (("{574, 2}, {576, 4}, {580, 4}}", "{574, 2}, {576, 4}, {581, 4}}"), "length")])
def test_the_c_bridge_refuses_a_mixed_table_it_cannot_drive(tmp_path, edit, why):
    """A drive table written by hand (the generator never writes these): cochlea_bridge_init
    returns -1 and says why in one line, before any byte is sent."""
    header = drives_header("serial", ARM)
    assert edit[0] in header
    line = Line(tmp_path, header.replace(edit[0], edit[1], 1))
    assert line.init == -1
    problem = line.c.line_problem().decode()
    assert why in problem and "\n" not in problem
    assert line.sent() == []


# ---- the program over the virtual chain ---------------------------------------------------------

@pytest.fixture(scope="module")
def mixed_program(tmp_path_factory) -> tuple[Path, str]:
    """``cochlea-codegen --scenario planar2_xp_joint.toml --embedded`` and ``make embedded``
    into a folder of its own, as docs/codegen.md tells a user: the program and the scenario's
    name."""
    tmp = tmp_path_factory.mktemp("mixed_program")
    gen = tmp / "gen"
    done = subprocess.run(
        [sys.executable, "-m", "cochlea.apps.cochlea_codegen", "--scenario", str(SCENARIO),
         "--embedded", "--no-build", "--out", str(gen)], cwd=ROOT, capture_output=True,
        text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "DXL_BULK_READ, DXL_BULK_WRITE" in (gen / "embedded" / "serial_drives.h").read_text()
    build = gen / "build"
    done = subprocess.run(["make", "-s", "embedded", f"GEN={gen}", f"BUILD={build}"], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    program = build / "cochlea-embedded"
    listed = subprocess.run([str(program), "--list"], capture_output=True, text=True,
                            check=True)
    return program, listed.stdout.split()[0]


def _bulk_writes(log: Path) -> list[tuple[int, int, int]]:
    """The emulator's BULK_WRITEs: (ID, address, value) per motor, in order."""
    events = [line.split() for line in log.read_text().splitlines()]
    return [(int(e[2].split("=")[1]), int(e[3].split("=")[1]), int(e[4].split("=")[1]))
            for e in events if e[1] == "bulk-write"]


@pytest.mark.slow
@pytest.mark.hil
def test_the_mixed_chain_program_tracks_like_cochlea_run_on_the_same_emulator(mixed_program,
                                                                              tmp_path):
    from tests.test_dynamixel_hil import FLOOR, run_on_emulator
    from tests.test_embedded_program import PATIENT, on_emulator

    program, name = mixed_program
    assert name == "planar2_xp_joint"
    duration = 2.0
    (tmp_path / "py").mkdir()
    done, c_out, c_log = on_emulator(program, tmp_path, ("serial", str(SCENARIO)), "--scenario",
                                     name, "--duration", str(duration), *PATIENT)
    assert done.returncode == 0, done.stderr
    reference, py_out, _ = run_on_emulator(
        "serial", str(SCENARIO), tmp_path / "py", "--robot", "serial", "--space", "joint",
        "--scenario", str(SCENARIO), "--duration", str(duration))
    assert reference.returncode == 0, reference.stderr

    # BULK_READ + BULK_WRITE, stated as cochlea-run states them, with the same budget: the
    # budget of the frames actually sent (98 bytes, 285 us at 4 Mbaud).
    assert ("cochlea-embedded: bus: BULK_READ + BULK_WRITE per period (the motors read "
            "Realtime Tick, Present Current, Present Velocity, Present Position at different "
            "addresses: BULK_READ)") in done.stdout
    summary = json.loads((c_out / "summary.json").read_text())
    python = json.loads((py_out / "summary.json").read_text())
    bus, py_bus = summary["timing"]["bus"], python["timing"]["bus"]
    budget = bus_budget(2, 4_000_000, read_length=16, read_instruction="bulk",
                        write_instruction="bulk")
    assert budget.total_bytes == (10 + 7 * 2) + (10 + 5 * 2) + 2 * (11 + 16) == 98
    assert set(bus["bus_budget"]) == set(py_bus["bus_budget"])
    for key in ("bytes_per_period", "read_instruction", "write_instruction", "read_choice"):
        assert bus["bus_budget"][key] == py_bus["bus_budget"][key], key
    assert bus["bus_budget"]["bytes_per_period"] == budget.total_bytes
    assert bus["bus_budget"]["bus_s"] == pytest.approx(budget.bus_s)
    assert (bus["bus_budget"]["read_instruction"],
            bus["bus_budget"]["write_instruction"]) == ("BULK_READ", "BULK_WRITE")
    assert bus["reads"] == summary["periods"] == int(duration * 1000)
    assert bus["good_reads"] >= 0.98 * bus["reads"]
    # Torque off confirmed on both motors; the last commands zero current, then torque off,
    # each motor at its own address, twice.
    assert "torque off confirmed by all 2" in bus["shutdown"]
    tail = _bulk_writes(c_log)[-8:]
    assert tail == [(1, 550, 0), (2, 102, 0), (1, 512, 0), (2, 64, 0)] * 2
    events = c_log.read_text()
    assert " sync-read " not in events and " sync-write " not in events
    assert " fast-sync-read " not in events

    # It tracks as cochlea-run does over the same emulator.
    assert summary["stop"]["rule"] == "completed"
    for unit, entry in summary["units"].items():
        for coord, c in entry["tracked"].items():
            py = python["units"][unit]["tracked"][coord]
            assert c["initial_abs_error"] == pytest.approx(py["initial_abs_error"], rel=0.05)
            assert c["final_rms_error"] <= py["final_rms_error"] + FLOOR[c["unit"]], \
                (unit, coord, c, py)
            assert c["converged"], (unit, coord, c)
    assert summary["converged"] is True and python["converged"] is True


@pytest.mark.slow
@pytest.mark.hil
def test_the_program_counts_a_p_carriage_from_the_record_home_writes(tmp_path):
    """tests/data/prismatic3 with a PH42-020-S300-R on its lead-screw carriage (a mixed chain:
    XM430, PH42, XM430): ``cochlea-dxl home`` records the carriage's stop (its token at 536),
    and the embedded program checks that record (direction and m/rad from the drive table,
    not from 4096 counts a turn: the PH42 has 607500), reads the token at the PH42's address
    and counts the carriage from its stop in the PH42's pulses, by BULK frames."""
    import argparse
    import time

    from cochlea.dynamixel.bringup import home
    from cochlea.dynamixel.emulator import Truth, VirtualChain
    from tests.test_dynamixel_p_series import _p_carriage
    from tests.test_embedded_program import EMULATOR_SETTLE_S, PATIENT

    description, scenario = _p_carriage(tmp_path)
    assert [d.spec.name for d in joint_drives("serial", description)] == [
        "XM430-W350", "PH42-020-S300-R", "XM430-W350"]
    gen, build = tmp_path / "gen", tmp_path / "build"
    done = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_codegen", "--scenario",
                           str(scenario), "--embedded", "--no-build", "--out", str(gen)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    program = build / "cochlea-embedded"
    done = subprocess.run(["make", "-s", f"GEN={gen}", f"BUILD={build}", str(program)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    stop, record, out = 0.03, tmp_path / "homing.json", tmp_path / "run"
    parser = argparse.ArgumentParser()
    home.add_arguments(parser)
    chain = VirtualChain("serial", scenario, truth=Truth(offset_deg={2: 500.0},
                                                        hard_stop_m=stop)).start()
    try:
        assert home.run(parser.parse_args([
            "--robot", "serial", "--description", str(description), "--port", chain.path,
            "--record", str(record), "--stop-m", str(stop), "--speed-mm-s", "8",
            "--force-N", "20"])) == 0
        chain.move_joint("arm.carriage", 0.0395)  # the scenario's initial pose, by hand
        time.sleep(min(EMULATOR_SETTLE_S, 0.5))
        done = subprocess.run([str(program), "--scenario", "prismatic3_joint", "--port",
                               chain.path, "--duration", "0.3", "--out", str(out), *PATIENT,
                               "--homing", "required", "--homing-record", str(record)],
                              capture_output=True, text=True, timeout=120)
        events = list(chain.events)
    finally:
        chain.close()
    assert done.returncode == 0, done.stderr
    assert "bus: BULK_READ + BULK_WRITE per period" in done.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["timing"]["bus"]["homing"].startswith("homed ")
    assert "torque off confirmed by all 3" in summary["timing"]["bus"]["shutdown"]
    assert any(e[1] == "read" and e[2] == 2 and e[3] == 536 for e in events)  # the token
    with open(out / "log.csv") as f:
        header = f.readline().strip().split(",")
        first = f.readline().strip().split(",")
    assert abs(float(first[header.index("arm.q.carriage_joint_m")]) - 0.0395) < 1e-3
