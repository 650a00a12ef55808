"""Issue 27, item 5, the C bridge's side: Fast Sync Read (0x8A) in ``embedded/core/``, and every
address and size of the C bridge from the model data.

* the C codec's FAST_SYNC_READ request byte for byte the Python protocol's and the official
  SDK's, and its check of the combined status packet ``protocol.check_fast_sync``'s, case for
  case (``dxl_fast_sync_check``);
* the generator's choice (``embedded_drives.bus_choice``: ``choose_transfers`` over the models'
  data, the Python bridge's rule and text), its refusals in one line (a table the C bridge
  does not speak, a model without current control; a chain that needs BULK_READ /
  BULK_WRITE is generated: tests/test_embedded_p_series.py);
* the C bridge's read over a scripted line against the Python bridge's on the same bytes:
  the good packet gives the same state, and every fault of the combined packet (a motor's
  block missing, a CRC error in the middle, a wrong running CRC, a short packet, an alert, an
  error byte, a motor refusing the instruction) the same failure kind and motor, the read
  path the loop's watchdog stops on;
* ``build/cochlea-embedded`` over the virtual chain (``hil``): the MX-64 chain (plain
  SYNC_READ) and a user's chain of XM540-W270s (``models/examples``) whose data is set to
  answer FAST_SYNC_READ, each stating its read in ``summary.json`` as ``cochlea-run`` states it;
  the emulator answering the instruction only where the data say so; a dropped block ending in
  the watchdog's safe stop.

No shipped model's data says ``fast_sync_read = true`` yet (docs/dynamixel.md, "Fast Sync Read
support is not sourced"): the Fast Sync Read chain here is the example's XM540-W270s with that
one field set to true in the generator's input, as a firmware whose data said so would be.
"""

from __future__ import annotations

import ctypes
import dataclasses
import gc
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import dynamixel_sdk as sdk
import numpy as np
import pytest

from cochlea.dynamixel import protocol as proto
from cochlea.dynamixel.bridge import FAILURE_NAMES, TICK_ITEMS, DynamixelBackend, choose_transfers
from cochlea.dynamixel.budget import bus_budget
from cochlea.dynamixel.control_table import ALERT_BIT, INSTRUCTION_ERROR, MODELS
from cochlea.dynamixel.drives import joint_drives
from cochlea.dynamixel.embedded_drives import bus_choice, drives_header
from cochlea.errors import CochleaError
from cochlea.runtime.backend import BackendError

from . import dxl_codec
from .embedded_build import build_library
from .test_dynamixel_fastsync import PH, CapturePort

ROOT = Path(__file__).resolve().parent.parent
CORE = ROOT / "embedded" / "core"
EXAMPLES = ROOT / "models" / "examples"
ARM = EXAMPLES / "planar2_xm540.toml"
ARM_SCENARIO = EXAMPLES / "planar2_xm540_joint.toml"
#: What the C program reads each period: Realtime Tick .. Present Position (X layout).
TICK_ADDRESS, TICK_LENGTH = 120, 16


def fast_drives(description: Path = ARM):
    """The description's drives with their models' data set to answer FAST_SYNC_READ."""
    return [dataclasses.replace(d, spec=dataclasses.replace(d.spec, fast_sync_read=True))
            for d in joint_drives("serial", description)]


# ---- the codec ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def codec():
    lib = dxl_codec.load(dxl_codec.build())
    u8p = ctypes.POINTER(ctypes.c_uint8)
    lib.dxl_fast_sync_read.restype = ctypes.c_int32
    lib.dxl_fast_sync_read.argtypes = [u8p, ctypes.c_size_t, ctypes.c_uint16, ctypes.c_uint16,
                                       ctypes.c_char_p, ctypes.c_size_t]
    lib.dxl_fast_sync_check.restype = ctypes.c_int
    lib.dxl_fast_sync_check.argtypes = [ctypes.POINTER(dxl_codec.ParserStruct),
                                        ctypes.c_char_p, ctypes.c_size_t, ctypes.c_size_t,
                                        ctypes.POINTER(ctypes.c_size_t)]
    lib.dxl_fast_block.restype = ctypes.c_void_p
    lib.dxl_fast_block.argtypes = [ctypes.POINTER(dxl_codec.ParserStruct), ctypes.c_size_t,
                                   ctypes.c_size_t]
    return lib


@pytest.mark.parametrize("address,length,ids", [
    (132, 4, [1, 2]), (TICK_ADDRESS, TICK_LENGTH, [1, 2, 3, 4, 5, 6]), (126, 10, [7, 3, 200]),
    (0xFFFF, 0xFD, [1, 2]),  # the parameters FF FF FD: a stuffed frame
    (126, 10, [])])
def test_the_fast_sync_read_request_is_protocols_and_the_sdks(codec, address, length, ids):
    n = dxl_codec.frame_size(4 + len(ids))
    frame = dxl_codec.call_builder(codec, "dxl_fast_sync_read", n, address, length, bytes(ids),
                                   len(ids))
    assert frame == proto.fast_sync_read(address, length, ids)
    assert frame[7] == 0x8A
    # The SDK as a third opinion where it stuffs as the specification does: its addStuffing
    # leaves this request's FF FF FD unstuffed (its plain SYNC_READ's too), and it refuses an
    # empty group.
    if ids and b"\xff\xff\xfd" not in frame[7:]:
        port = CapturePort()
        group = sdk.GroupSyncRead(port, PH, address, length)
        for i in ids:
            assert group.addParam(i)
        assert group.fastSyncReadTxPacket() == sdk.COMM_SUCCESS
        assert port.sent == [frame]
    # Too little room: refused, not truncated.
    assert dxl_codec.call_builder(codec, "dxl_fast_sync_read", len(frame) - 1, address, length,
                                  bytes(ids), len(ids)) == dxl_codec.E_SPACE


def _combined(ids, length, rng, *, errors=None, data_len=None):
    errors = errors or {}
    return proto.fast_sync_status([
        (i, errors.get(i, 0), bytes(rng.integers(0, 256, (data_len or {}).get(i, length),
                                                 dtype=np.uint8))) for i in ids])


def _fix_crc(packet: bytearray) -> bytes:
    crc = proto.crc16(packet, 0, len(packet) - 2)
    packet[-2:] = bytes([crc & 0xFF, crc >> 8])
    return bytes(packet)


def _packets(rng):
    """(name, packet, the motors asked, block length): every kind of combined packet."""
    ids, length = [3, 7, 1], 6
    good = _combined(ids, length, rng)
    block = length + 4
    wrong_running = bytearray(good)
    wrong_running[8 + 2 * block - 2] ^= 0x5A  # motor 7's running CRC, packet CRC made right
    wire = bytearray(good)
    wire[8 + block - 2] ^= 0xFF  # motor 3's running CRC corrupted on the wire
    stuffed = proto.fast_sync_status([(i, 0, b"\xff\xff\xfd\x00\x01\x02") for i in ids])
    return [
        ("good", good, ids, length),
        ("stuffed", stuffed, ids, length),
        ("missing", _combined([3, 7], length, rng), ids, length),
        ("first-missing", _combined([7, 1], length, rng), ids, length),
        ("order", _combined([7, 3, 1], length, rng), ids, length),
        ("extra", _combined([3, 7, 1, 9], length, rng), ids, length),
        ("short-block", _combined(ids, length, rng, data_len={7: length - 1}), ids, length),
        ("running-crc", _fix_crc(wrong_running), ids, length),
        ("wire-crc", bytes(wire), ids, length),
        ("errors", _combined(ids, length, rng, errors={7: ALERT_BIT | 1, 1: 2}), ids, length),
        ("one", _combined([5], 1, rng), [5], 1),
        ("other-length", good, ids, length + 1),
    ]


def test_the_combined_packet_check_is_protocols_case_for_case(codec):
    rng = np.random.default_rng(27)
    for name, packet, ids, length in _packets(rng):
        py, c = proto.PacketParser(status=True), dxl_codec.CParser(codec)
        py.feed(packet)
        c.feed(packet)
        code = py.parse()
        assert c.parse() == code, name
        if code != proto.OK:
            assert name == "wire-crc" and code == proto.CRC_FAILURE
            continue
        expect = proto.check_fast_sync(py, ids, length)
        at = ctypes.c_size_t()
        got = codec.dxl_fast_sync_check(ctypes.byref(c.s), bytes(ids), len(ids), length,
                                        ctypes.byref(at))
        assert (got, at.value if got else -1) == expect, name
        if got == 0:  # each block where fast_block says: error byte, ID, data
            for k in range(len(ids)):
                at_py = proto.fast_block(py, k, length)
                block = ctypes.string_at(codec.dxl_fast_block(ctypes.byref(c.s), k, length),
                                         length + 2)
                assert block == bytes(py.buf[at_py:at_py + 2 + length]), (name, k)
    # every kind above was seen: the cases are not all the good one
    kinds = set()
    for _name, packet, ids, length in _packets(np.random.default_rng(27)):
        p = proto.PacketParser(status=True)
        p.feed(packet)
        kinds.add(proto.check_fast_sync(p, ids, length)[0] if p.parse() == proto.OK else "crc")
    assert kinds == {0, proto.FAST_MISSING, proto.FAST_WRONG_ID, proto.FAST_BLOCK_CRC, "crc"}


# ---- the generator's choice and refusals ------------------------------------------------------

def test_the_generator_chooses_the_read_as_the_python_bridge():
    """The drive table's bus: the Python bridge's choice and text for the same data (with the
    Realtime Tick, as cochlea-run reads), and each motor's items at its model's addresses."""
    for drives in (joint_drives("serial"), joint_drives("parallel"), joint_drives("serial", ARM),
                   fast_drives()):
        read, write, why = bus_choice(drives)
        expect = choose_transfers([d.spec for d in drives], TICK_ITEMS)
        assert (read, write, why) == ({"sync": "SYNC_READ", "fast": "FAST_SYNC_READ"}[expect[0]],
                                      "SYNC_WRITE", expect[2])
    assert bus_choice(joint_drives("serial"))[0] == "SYNC_READ"  # MX-64: no
    assert bus_choice(joint_drives("serial", ARM))[0] == "FAST_SYNC_READ"  # XM540s: the SDK
    assert bus_choice(fast_drives())[0] == "FAST_SYNC_READ"
    # The text cochlea-run writes as read_choice, word for word.
    backend = DynamixelBackend("serial", "/dev/scripted", realtime_tick=True)
    assert bus_choice(joint_drives("serial"))[2] == backend.read_choice
    header = drives_header("serial", ARM, drives=fast_drives())
    assert "DXL_FAST_SYNC_READ, DXL_SYNC_WRITE" in header
    assert '"every model answers FAST_SYNC_READ (its data)"' in header
    spec = MODELS["XM540-W270"]
    row = ", ".join(f"{{{spec.item(n).address}, {spec.item(n).size}}}" for n in (
        "Return Delay Time", "Operating Mode", "Current Limit", "Torque Enable",
        "Hardware Error Status", "Bus Watchdog", "Goal Current", "Feedforward 2nd Gain",
        "Realtime Tick", "Present Current", "Present Velocity", "Present Position"))
    assert f'{{"XM540-W270", {{{row}}}, 0}}' in header


def _moved(spec, names, shift):
    items = tuple(dataclasses.replace(it, address=it.address + shift) if it.name in names
                  else it for it in spec.items)
    return dataclasses.replace(spec, name=spec.name + "*", items=items)


def test_what_the_c_bridge_cannot_drive_is_refused_in_one_line(tmp_path):
    drives = joint_drives("serial", ARM)
    # A mixed chain whose state block lies elsewhere on one motor is BULK_READ now, Goal
    # Current elsewhere BULK_WRITE: the C bridge sends both (tests/test_embedded_p_series.py).
    state = ("Realtime Tick", "Moving", "Moving Status", "Present PWM", "Present Current",
             "Present Velocity", "Present Position")
    for names, what in ((state, "DXL_BULK_READ, DXL_SYNC_WRITE"),
                        (("Goal Current",), "DXL_FAST_SYNC_READ, DXL_BULK_WRITE")):
        mixed = [drives[0], dataclasses.replace(drives[1], spec=_moved(drives[1].spec, names,
                                                                       256))]
        assert what in drives_header("serial", ARM, drives=mixed)
    # A model whose control table the C bridge does not speak (none with current control
    # ships: the XL320's layout stands in), and a model without current control: refused
    # before any table, in one line naming the model.
    odd = [dataclasses.replace(drives[0], spec=dataclasses.replace(drives[0].spec,
                                                                   layout="xl320")), drives[1]]
    with pytest.raises(BackendError) as info:
        drives_header("serial", ARM, drives=odd)
    assert "\n" not in str(info.value) and "not supported by the embedded drive tables" in \
        str(info.value) and "XM540-W270" in str(info.value)
    text = ARM.read_text()
    for model, why in (("XL430-W250", "no Current Control mode"),):
        path = tmp_path / f"{model}.toml"
        path.write_text(text.replace('model = "XM540-W270"', f'model = "{model}"', 1))
        with pytest.raises(CochleaError) as info:
            drives_header("serial", path)
        assert "\n" not in str(info.value) and why in str(info.value) and model in \
            str(info.value)


def test_cochlea_codegen_refuses_the_table_before_writing_anything(tmp_path, capsys):
    """``cochlea-codegen --scenario --embedded`` with a motor the drive tables refuse (a model
    without current control): one line, exit 2, no file written (it used to write the kernels
    first, then refuse the drive table)."""
    from cochlea.apps import cochlea_codegen
    from cochlea.errors import EXIT_USER_ERROR

    description = tmp_path / "p.toml"
    description.write_text(ARM.read_text().replace('model = "XM540-W270"',
                                                   'model = "XL430-W250"', 1))
    out = tmp_path / "out"
    assert cochlea_codegen.main(["--scenario", str(ARM_SCENARIO), "--description",
                                 str(description), "--embedded", "--no-build", "--out",
                                 str(out)]) == EXIT_USER_ERROR
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "XL430-W250" in err[0] and "no Current Control mode" in err[0]
    assert not out.exists() or not any(out.iterdir())


# ---- the C bridge's read against the Python bridge's, on the same bytes ------------------------

LINE = r"""
#include <string.h>
#include "bridge.h"
#include "serial_drives.h"

/* A scripted line: each request gets the reply set before it, once; then silence (the clock
 * jumps to the read's deadline). */
static struct {
    int64_t t;
    uint8_t reply[4096];
    size_t reply_len, given;
    uint8_t sent[512];
    size_t sent_len;
} L;
static cochlea_hal hal;
static cochlea_bridge b;

static int64_t now_ns(void *c) { (void)c; return L.t; }
static void wait_until_ns(void *c, int64_t d) { (void)c; if (d > L.t) { L.t = d; } }
static void discard(void *c) { (void)c; }
static long line_write(void *c, const uint8_t *d, size_t n)
{
    (void)c;
    if (n <= sizeof L.sent) {
        memcpy(L.sent, d, n);
        L.sent_len = n;
    }
    L.given = 0;
    L.t += 1000;
    return (long)n;
}
static long line_read(void *c, uint8_t *d, size_t n, int64_t timeout_ns)
{
    (void)c;
    if (L.given < L.reply_len) {
        size_t k = L.reply_len - L.given;
        k = k < n ? k : n;
        memcpy(d, L.reply + L.given, k);
        L.given += k;
        L.t += 2500;
        return (long)k;
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
int line_read_state(const uint8_t *reply, size_t n, double *q, double *qd)
{
    memcpy(L.reply, reply, n);
    L.reply_len = n;
    b.active = 1;  /* as after a good start */
    b.suspect = 0; /* each case on a quiet line */
    return cochlea_bridge_read(&b, q, qd);
}
int line_failure(int *id) { *id = b.last_failure_id; return b.last_failure; }
const uint8_t *line_sent(size_t *n) { *n = L.sent_len; return L.sent; }
int line_instruction(void) { return b.bus->read_instruction; }
const char *line_choice(void) { return b.bus->read_choice; }
int line_read_length(void) { return b.read_length; }
const char *line_problem(void) { return b.config_problem; }
"""


class ScriptedLine:
    """The C bridge of a drive table over the scripted line (ctypes)."""

    def __init__(self, tmp: Path, drives, description: Path | None, header: str | None = None):
        (tmp / "serial_drives.h").write_text(header or drives_header("serial", description,
                                                                     drives=drives))
        lib = build_library("fastsync_line", [CORE / "dxl.c", CORE / "drives.c",
                                              CORE / "bridge.c", ("line.c", LINE)],
                            include=[CORE, tmp])
        self.c = ctypes.CDLL(str(lib), mode=ctypes.RTLD_LOCAL)
        self.n = len(drives)
        dp = ctypes.POINTER(ctypes.c_double)
        self.c.line_read_state.argtypes = [ctypes.c_char_p, ctypes.c_size_t, dp, dp]
        self.c.line_sent.restype = ctypes.POINTER(ctypes.c_uint8)
        self.c.line_choice.restype = ctypes.c_char_p
        self.c.line_problem.restype = ctypes.c_char_p
        self.init = self.c.line_init()
        if header is None:
            assert self.init == 0

    def read(self, reply: bytes):
        q, qd = np.zeros(self.n), np.zeros(self.n)
        dp = ctypes.POINTER(ctypes.c_double)
        ok = self.c.line_read_state(reply, len(reply), q.ctypes.data_as(dp),
                                    qd.ctypes.data_as(dp))
        motor = ctypes.c_int()
        kind = self.c.line_failure(ctypes.byref(motor))
        return bool(ok), q, qd, (FAILURE_NAMES_C[kind] if not ok else None, motor.value)

    def sent(self) -> bytes:
        n = ctypes.c_size_t()
        p = self.c.line_sent(ctypes.byref(n))
        return bytes(p[:n.value])


#: embedded/core/bridge.h's failure kinds, in order (the Python bridge's names).
FAILURE_NAMES_C = ["timeout", "crc", "error-byte", "hardware-alert", "length", "port",
                   "late-traffic", "non-finite-command", "not-enabled", "stale-packet"]


class OnceReply:
    """The Python bridge's port with the same script: the reply once per request."""

    low_latency = None

    def __init__(self):
        self.reply, self.given = b"", True

    def write(self, view, n, deadline):
        self.given = False
        return True

    def read_into(self, target, deadline):
        if self.given or not self.reply:
            return 0
        self.given = True
        target[:len(self.reply)] = self.reply
        return len(self.reply)

    def discard_input(self):
        pass

    def close(self):
        pass


def python_read(reply: bytes):
    backend = DynamixelBackend("serial", "/dev/scripted", description=ARM, timeout_s=0.005,
                               read_instruction="fast", realtime_tick=True)
    port = OnceReply()
    port.reply = reply
    backend._port, backend._active = port, True
    x = np.zeros(2 * backend.nq)
    ok = backend.read(x)
    backend._active, backend._port = False, None
    kind = None if ok else FAILURE_NAMES[backend.last_failure]
    return ok, x[:backend.nq], x[backend.nq:], (kind, backend.last_failure_id)


def _replies(rng):
    """(case, the combined reply) for the two motors (IDs 1, 2) of the example arm."""
    ids, length = [1, 2], TICK_LENGTH

    def block(i):
        tick = proto.le(int(rng.integers(0, 32768)), 2)
        state = (proto.le(int(rng.integers(-500, 500)), 2) + proto.le(int(rng.integers(
            -300, 300)), 4) + proto.le(int(rng.integers(0, 4096)), 4))
        return tick + b"\0\0\0\0" + state

    good = proto.fast_sync_status([(i, 0, block(i)) for i in ids])
    running = bytearray(good)
    running[8 + (length + 4) - 2] ^= 0x5A
    wire = bytearray(good)
    wire[8 + (length + 4) - 1] ^= 0xFF
    stuffed = proto.fast_sync_status([(1, 0, b"\0\0\0\0\0\0" + proto.le(-3, 2)
                                       + b"\xff\xff\xfd\x00" + proto.le(2048, 4)),
                                      (2, 0, block(2))])
    return [
        ("good", good), ("stuffed", stuffed), ("garbage-first", b"\x00\x12\x55" + good),
        ("stranger-first", proto.status(9, 0, b"\1\2") + good),
        ("missing", proto.fast_sync_status([(1, 0, block(1))])),
        ("order", proto.fast_sync_status([(2, 0, block(2)), (1, 0, block(1))])),
        ("extra", proto.fast_sync_status([(i, 0, block(i)) for i in (1, 2, 3)])),
        ("short-block", proto.fast_sync_status([(1, 0, block(1)), (2, 0, block(2)[:-1])])),
        ("short-packet", good[:-5]),
        ("wire-crc", bytes(wire)),
        ("running-crc", _fix_crc(running)),
        ("alert", proto.fast_sync_status([(1, 0, block(1)), (2, ALERT_BIT, block(2))])),
        ("alert-and-error", proto.fast_sync_status([(1, 1, block(1)),
                                                    (2, ALERT_BIT, block(2))])),
        ("error-byte", proto.fast_sync_status([(1, 0, block(1)), (2, 7, block(2))])),
        ("refused", proto.status(1, INSTRUCTION_ERROR, b"")),
        ("alone-alert", proto.status(2, ALERT_BIT, b"")),
        ("nothing", b""),
    ]


@pytest.mark.slow
def test_the_c_read_is_the_python_bridges_on_every_combined_packet(tmp_path):
    """The same bytes through both bridges: the same state, or the same failure kind and
    motor; the C bridge's request is the Python bridge's frame."""
    line = ScriptedLine(tmp_path, fast_drives(), ARM)
    assert line.c.line_instruction() == 0x8A and line.c.line_read_length() == TICK_LENGTH
    assert line.c.line_choice() == b"every model answers FAST_SYNC_READ (its data)"
    rng = np.random.default_rng(5)
    seen = set()
    for case, reply in _replies(rng):
        c_ok, c_q, c_qd, c_fail = line.read(reply)
        assert line.sent() == proto.fast_sync_read(TICK_ADDRESS, TICK_LENGTH, [1, 2]), case
        py_ok, py_q, py_qd, py_fail = python_read(reply)
        assert c_ok == py_ok, (case, c_fail, py_fail)
        if py_ok:
            np.testing.assert_allclose(c_q, py_q, rtol=0, atol=1e-12, err_msg=case)
            np.testing.assert_allclose(c_qd, py_qd, rtol=0, atol=1e-12, err_msg=case)
        else:
            assert c_fail == py_fail, case
        seen.add(c_fail[0] if not c_ok else "ok")
    assert seen == {"ok", "timeout", "crc", "length", "error-byte", "hardware-alert"}


@pytest.mark.slow
def test_the_mx64_chain_reads_with_sync_read_from_its_tables(tmp_path):
    """The shipped serial robot (MX-64s: no FAST_SYNC_READ in their data): the plain
    SYNC_READ of the tick block, its text cochlea-run's."""
    drives = joint_drives("serial")
    line = ScriptedLine(tmp_path, drives, None)
    assert line.c.line_instruction() == 0x82
    assert line.c.line_choice().decode() == DynamixelBackend(
        "serial", "/dev/scripted", realtime_tick=True).read_choice
    ids = [d.id for d in drives]
    replies = b"".join(proto.status(i, 0, bytes(TICK_LENGTH)) for i in ids)
    ok, *_ = line.read(replies)
    assert ok and line.sent() == proto.sync_read(TICK_ADDRESS, TICK_LENGTH, ids)


# ---- the program over the virtual chain ----------------------------------------------------------

@pytest.fixture(autouse=True)
def no_gc():
    """The in-process emulator is a thread of this process: no collector pause may stall it."""
    gc.collect()
    gc.disable()
    yield
    gc.enable()


@pytest.fixture(scope="module")
def fast_program(tmp_path_factory) -> tuple[Path, str]:
    """``build/cochlea-embedded`` of the example arm's scenario (cochlea-codegen --embedded, as
    a user builds it), its drive table generated from the data with FAST_SYNC_READ: the
    program and the scenario's name."""
    tmp = tmp_path_factory.mktemp("fast_program")
    gen = tmp / "gen"
    done = subprocess.run(
        [sys.executable, "-m", "cochlea.apps.cochlea_codegen", "--scenario", str(ARM_SCENARIO),
         "--embedded", "--no-build", "--out", str(gen)], cwd=ROOT, capture_output=True,
        text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    (gen / "embedded" / "serial_drives.h").write_text(
        drives_header("serial", ARM, drives=fast_drives()))
    program = tmp / "build" / "cochlea-embedded"
    done = subprocess.run(["make", "-s", f"GEN={gen}", f"BUILD={tmp / 'build'}", str(program)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    listed = subprocess.run([str(program), "--list"], capture_output=True, text=True,
                            check=True)
    return program, listed.stdout.split()[0]


def _on_chain(program: Path, name: str, out: Path, *, fast: bool | None, faults=None,
              duration: float = 1.0, patient: bool = True):
    """The program on an in-process virtual chain of the example arm, over its socket, the
    serving thread under SCHED_FIFO 30 where permitted (as the command's): the result and the
    chain's events. ``fast``: VirtualChain.fast_sync_read (None: as the models' data say)."""
    import tempfile

    from cochlea.dynamixel.emulator import EMULATOR_FIFO_PRIORITY, VirtualChain
    from tests.test_embedded_program import EMULATOR_SETTLE_S, PATIENT

    folder = tempfile.TemporaryDirectory(prefix="cochlea-emu-")  # a socket's path is short
    chain = VirtualChain("serial", ARM_SCENARIO, faults=faults,
                         listen=f"unix:{folder.name}/chain.sock")
    chain.fast_sync_read = fast
    with folder, chain:
        try:
            os.sched_setscheduler(chain._thread.native_id, os.SCHED_FIFO,
                                  os.sched_param(EMULATOR_FIFO_PRIORITY))
        except (AttributeError, PermissionError, OSError):
            pass  # an ordinary thread, as before
        time.sleep(min(EMULATOR_SETTLE_S, 0.5))
        done = subprocess.run(
            [str(program), "--scenario", name, "--port", chain.path, "--duration",
             str(duration), "--out", str(out),
             *(PATIENT if patient else ("--watchdog-misses", "300"))],
            capture_output=True, text=True, timeout=120)
    return done, list(chain.events)


@pytest.mark.hil
def test_the_fast_sync_read_chain_runs_and_states_its_read(fast_program, tmp_path):
    program, name = fast_program
    out = tmp_path / "run"
    done, events = _on_chain(program, name, out, fast=True)
    assert done.returncode == 0, done.stderr
    assert "bus: FAST_SYNC_READ + SYNC_WRITE per period (every model answers FAST_SYNC_READ " \
           "(its data))" in done.stdout
    summary = json.loads((out / "summary.json").read_text())
    bus = summary["timing"]["bus"]
    budget = bus_budget(2, 4_000_000, read_length=TICK_LENGTH, read_instruction="fast")
    assert bus["bus_budget"]["read_instruction"] == "FAST_SYNC_READ"
    assert bus["bus_budget"]["write_instruction"] == "SYNC_WRITE"
    assert bus["bus_budget"]["read_choice"] == "every model answers FAST_SYNC_READ (its data)"
    assert bus["bus_budget"]["bytes_per_period"] == budget.total_bytes
    assert bus["bus_budget"]["bus_s"] == pytest.approx(budget.bus_s)
    assert bus["good_reads"] >= 0.9 * bus["reads"] and bus["reads"] == summary["periods"]
    assert summary["timing"]["tick_overruns"] == 0
    kinds = {e[1] for e in events}
    # Every period's read is the fast one; the only plain SYNC_READs left are the torque-on's
    # confirmation of Torque Enable (address 64, one byte: start-up step 9).
    assert "fast-sync-read" in kinds
    assert {tuple(e[3:5]) for e in events if e[1] == "sync-read"} <= {(64, 1)}
    assert "torque off confirmed by all 2" in bus["shutdown"]


@pytest.mark.hil
def test_a_firmware_without_fast_sync_read_stops_the_start_up(fast_program, tmp_path):
    """Motors whose firmware does not answer FAST_SYNC_READ (the data give no first version
    for the X series: the emulator told to refuse it): each motor refuses the instruction; the
    program's start-up stops in one line, exit 5, nothing moved, torque off."""
    program, name = fast_program
    out = tmp_path / "run"
    done, events = _on_chain(program, name, out, fast=False)
    assert done.returncode == 5, done.stderr
    # one line (besides the bus budget's warning about the adapter's latency, which a
    # pseudo-terminal does not have: the program assumes a USB adapter)
    lines = [t for t in done.stderr.strip().splitlines() if ": warning: " not in t]
    assert len(lines) == 1 and "no good FAST_SYNC_READ" in lines[0]
    assert "error-byte (ID 1)" in lines[0]
    assert any(e[1] == "refused" and "FAST_SYNC_READ" in str(e[4]) for e in events)
    assert not any(e[1] == "write" and e[3] == 64 and e[4] == 1 for e in events)
    assert not out.exists()


@pytest.mark.hil
def test_a_block_missing_from_the_combined_packet_ends_in_the_safe_stop(fast_program,
                                                                        tmp_path):
    """Motor 2's block dropped from every combined packet after 0.3 s: the reads fail as
    ``length`` naming it, the read watchdog stops the run (exit 15) through the safe stop."""
    from cochlea.dynamixel.emulator import Faults

    program, name = fast_program
    out = tmp_path / "run"
    done, events = _on_chain(program, name, out, fast=True, duration=3.0, patient=False,
                             faults=Faults(drop=1.0, ids=frozenset({2}), delay_s=0.3))
    assert done.returncode == 15, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    bus = summary["timing"]["bus"]
    # Five failed reads in a row stop the run; on a loaded machine one of them may be the
    # emulator's lag (a timeout) rather than the dropped block (seen once at load 6: 4 + 1).
    assert sum(bus["failures"].values()) >= 5 and bus["failures"].get("length", 0) >= 3
    assert "length" in bus["last_failure"] and "ID 2" in bus["last_failure"]
    assert summary["stop"]["rule"] == "watchdog"
    writes = [e for e in events if e[1] == "sync-write"]
    assert writes and writes[-1][3] == 64 and writes[-1][4] == 0  # torque off, last


@pytest.fixture(scope="module")
def shipped_program() -> Path:
    """``make embedded`` in this checkout (the shipped scenarios: MX-64 chains)."""
    done = subprocess.run(["make", "--no-print-directory", "embedded"], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return ROOT / "build" / "cochlea-embedded"


@pytest.mark.hil
def test_the_mx64_chain_states_its_sync_read_as_cochlea_run(shipped_program, tmp_path):
    """The shipped serial robot on cochlea-emulator: the plain SYNC_READ (the MX-64's data
    say no FAST_SYNC_READ), stated with cochlea-run's keys, text and budget; tick_overruns
    beside the timing keys."""
    from tests.test_embedded_program import PATIENT, on_emulator

    done, out, log = on_emulator(shipped_program, tmp_path, ("serial", "serial_joint"),
                                 "--scenario", "serial_joint", "--duration", "1", *PATIENT)
    assert done.returncode == 0, done.stderr
    backend = DynamixelBackend("serial", "/dev/scripted", realtime_tick=True)
    python = backend.summary()["bus_budget"]
    assert f"bus: SYNC_READ + SYNC_WRITE per period ({backend.read_choice})" in done.stdout
    summary = json.loads((out / "summary.json").read_text())
    budget = summary["timing"]["bus"]["bus_budget"]
    assert set(budget) == set(python)
    for key in ("bytes_per_period", "read_instruction", "write_instruction", "read_choice"):
        assert budget[key] == python[key], key
    assert budget["bus_s"] == pytest.approx(python["bus_s"])
    assert summary["timing"]["tick_overruns"] == 0
    events = log.read_text()
    assert " sync-read " in events and "fast-sync-read" not in events


@pytest.mark.slow
@pytest.mark.parametrize("edit,why", [
    # motor 2's Present Position 256 further on: the block differs (it would need BULK_READ)
    (("{132, 4}}, 0},\n};", "{388, 4}}, 0},\n};"), "BULK_READ"),
    # motor 2's Goal Current elsewhere: BULK_WRITE
    (("{98, 1}, {102, 2}, {88, 2}, {120, 2}, {126, 2}, {128, 4}, {132, 4}}, 0},\n};",
      "{98, 1}, {358, 2}, {88, 2}, {120, 2}, {126, 2}, {128, 4}, {132, 4}}, 0},\n};"),
     "BULK_WRITE"),
    # a drive of another chain (here: of none)
    (("&serial_bus}", "0}"), "not of one chain")])
def test_the_c_bridge_refuses_a_table_it_cannot_drive(tmp_path, edit, why):
    """A drive table written by hand (the generator refuses these first): cochlea_bridge_init
    returns -1 and says why in one line, before any byte is sent."""
    header = drives_header("serial", ARM, drives=fast_drives())
    assert edit[0] in header
    header = header[::-1].replace(edit[0][::-1], edit[1][::-1], 1)[::-1]  # the last one
    line = ScriptedLine(tmp_path, fast_drives(), ARM, header=header)
    assert line.init == -1
    problem = line.c.line_problem().decode()
    assert why in problem and "\n" not in problem
    assert line.sent() == b""
