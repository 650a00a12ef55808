"""The embedded C codec (``embedded/core/dxl.c``) against its Python twin and the official SDK.

- It builds freestanding (C99, no libc: ``nm -u`` lists nothing) without a warning.
- Its builders give the bytes of ``cochlea.dynamixel.protocol`` and of ``dynamixel_sdk`` (the
  latter only for frames that need no stuffing: the SDK's transmit path does not stuff).
- Its parser gives the results of ``protocol.PacketParser`` call for call on the same streams,
  and a sanitizer fuzz (ASan+UBSan, in a subprocess with the ASan runtime preloaded) of more
  than 10^5 random and corrupted frames finds no bad access, no hang, no difference.

The lock-step machinery and the fuzz itself live in ``tests/dxl_codec.py``.
"""

from __future__ import annotations

import ctypes
import json
import re
import subprocess
import sys

import numpy as np
import pytest

from cochlea.dynamixel import protocol as proto

from . import dxl_codec as dxl
from .embedded_build import ROOT, SANITIZE, compiler, sanitizer_environment
from .test_dynamixel_sdk import CapturePort  # the SDK's transmit path, captured

pytestmark = pytest.mark.skipif(compiler() is None, reason="no C compiler")

FREESTANDING = ["-std=c99", "-pedantic", "-ffreestanding", "-fno-builtin", "-Wall", "-Wextra",
                "-Werror", "-Wconversion", "-c"]


@pytest.fixture(scope="module")
def lib():
    return dxl.load(dxl.build(("-O2",)))


@pytest.fixture(scope="module")
def asan_lib():
    libasan = subprocess.run([compiler(), "-print-file-name=libasan.so"], capture_output=True,
                             text=True).stdout.strip()
    if not libasan.startswith("/"):
        pytest.skip("the compiler has no ASan runtime")
    return dxl.build(SANITIZE, name="dxl_asan")


def run_sanitized(args: list[str], timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], env=sanitizer_environment(), cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


# --------------------------------------------------------------------------------------------
# Portability
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("opt", ["-O0", "-O2", "-Os", "-O3"])
@pytest.mark.slow
def test_compiles_freestanding_without_warnings_or_libc(tmp_path, opt):
    """No libc at all: not even the memcpy/memset a compiler may emit for a copy loop."""
    obj = tmp_path / "dxl.o"
    done = subprocess.run([compiler(), *FREESTANDING, opt, str(dxl.SOURCE), "-o", str(obj)],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""
    undefined = subprocess.run(["nm", "-u", str(obj)], capture_output=True, text=True,
                               check=True).stdout
    assert undefined.strip() == ""


def test_compiles_for_a_32_bit_target(tmp_path):
    """size_t of 32 bits (a Cortex-M's) is where -Wconversion finds size_t/uint32_t mixes."""
    obj = tmp_path / "dxl32.o"
    done = subprocess.run([compiler(), *FREESTANDING, "-m32", "-fno-pic", "-O2",
                           str(dxl.SOURCE), "-o", str(obj)], capture_output=True, text=True)
    if done.returncode != 0 and "-m32" in done.stderr:
        pytest.skip("the compiler has no 32-bit target")
    assert done.returncode == 0, done.stderr
    assert subprocess.run(["nm", "-u", str(obj)], capture_output=True, text=True,
                          check=True).stdout.strip() == ""


def test_includes_only_stddef_and_stdint():
    for path in (dxl.CORE / "dxl.h", dxl.SOURCE):
        includes = set(re.findall(r'#include\s*[<"]([^>"]+)[>"]', path.read_text()))
        assert includes <= {"stddef.h", "stdint.h", "dxl.h"}, (path.name, includes)


def test_the_ctypes_mirror_of_the_parser_matches_the_compiler(lib):
    assert dxl.layout(lib) == dxl.expected_layout()


# --------------------------------------------------------------------------------------------
# CRC, little-endian helpers
# --------------------------------------------------------------------------------------------

def test_crc16(lib, rng):
    assert lib.dxl_crc16(0, b"123456789", 9) == 0xFEE8
    for n in (0, 1, 10, 300):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert lib.dxl_crc16(0, data, n) == proto.crc16(data)
        # Chained over two pieces, as a receiver checking a frame in parts would.
        k = n // 3
        assert lib.dxl_crc16(lib.dxl_crc16(0, data[:k], k), data[k:], n - k) == proto.crc16(data)


@pytest.mark.parametrize("value", [0, 1, 731, 0x7FFF, 0x8000, 0xFFFF])
def test_u16_and_i16(lib, value):
    out = (ctypes.c_uint8 * 2)()
    lib.dxl_put_u16(out, value)
    assert bytes(out) == proto.le(value, 2)
    assert lib.dxl_get_u16(bytes(out)) == value
    assert lib.dxl_get_i16(bytes(out)) == proto.from_le(bytes(out), signed=True)


@pytest.mark.parametrize("value", [0, 2048, -1, -731, 2**31 - 1, -2**31, 0x12345678])
def test_u32_and_i32(lib, value):
    out = (ctypes.c_uint8 * 4)()
    lib.dxl_put_u32(out, value & 0xFFFFFFFF)
    assert bytes(out) == proto.le(value, 4)
    assert lib.dxl_get_u32(bytes(out)) == value & 0xFFFFFFFF
    assert lib.dxl_get_i32(bytes(out)) == value


# --------------------------------------------------------------------------------------------
# Builders
# --------------------------------------------------------------------------------------------

GOAL = [12, -40, 0, 731, -731, 5]
STUFFED = bytes([0xFF, 0xFF, 0xFD, 0x07])


def _sdk_ping(sdk, port, ph, motor_id):
    if motor_id == proto.BROADCAST_ID:
        ph.broadcastPing(port)
    else:
        ph.ping(port, motor_id)


def _sdk_sync_read(sdk, port, ph, address, length, ids):
    group = sdk.GroupSyncRead(port, ph, address, length)
    for i in ids:
        group.addParam(i)
    group.txPacket()


def _sdk_sync_write(sdk, port, ph, address, length, blocks):
    group = sdk.GroupSyncWrite(port, ph, address, length)
    for i, data in blocks:
        group.addParam(i, list(data))
    group.txPacket()


def _goal_blocks():
    return [(i, proto.le(v, 2)) for i, v in zip(range(1, 7), GOAL)]


#: (name, C builder and arguments, Python frame, SDK call or None when the frame needs stuffing).
PACKETS = [
    ("ping 1", ("dxl_ping", 1), proto.ping(1), lambda s, p, h: _sdk_ping(s, p, h, 1)),
    ("ping broadcast", ("dxl_ping", 0xFE), proto.ping(0xFE),
     lambda s, p, h: _sdk_ping(s, p, h, 0xFE)),
    ("read 4 at 132", ("dxl_read", 5, 132, 4), proto.read(5, 132, 4),
     lambda s, p, h: h.readTx(p, 5, 132, 4)),
    ("read 10 at 126", ("dxl_read", 6, 126, 10), proto.read(6, 126, 10),
     lambda s, p, h: h.readTx(p, 6, 126, 10)),
    ("write torque", ("dxl_write", 1, 64, b"\x01", 1), proto.write(1, 64, b"\x01"),
     lambda s, p, h: h.writeTxOnly(p, 1, 64, 1, [1])),
    ("write goal position", ("dxl_write", 3, 116, proto.le(2048, 4), 4),
     proto.write(3, 116, proto.le(2048, 4)),
     lambda s, p, h: h.writeTxOnly(p, 3, 116, 4, list(proto.le(2048, 4)))),
    ("write to broadcast", ("dxl_write", 0xFE, 64, b"\x00", 1), proto.write(0xFE, 64, b"\x00"),
     lambda s, p, h: h.writeTxOnly(p, 0xFE, 64, 1, [0])),
    ("reboot", ("dxl_reboot", 4), proto.reboot(4), lambda s, p, h: h.reboot(p, 4)),
    ("sync read 132", ("dxl_sync_read", 132, 4, b"\x01\x02", 2), proto.sync_read(132, 4, [1, 2]),
     lambda s, p, h: _sdk_sync_read(s, p, h, 132, 4, [1, 2])),
    ("sync read 126..135", ("dxl_sync_read", 126, 10, bytes(range(1, 7)), 6),
     proto.sync_read(126, 10, range(1, 7)),
     lambda s, p, h: _sdk_sync_read(s, p, h, 126, 10, range(1, 7))),
    ("sync write goal current", ("dxl_sync_write", 102, 2, bytes(range(1, 7)),
                                 b"".join(b for _, b in _goal_blocks()), 6),
     proto.sync_write(102, 2, _goal_blocks()),
     lambda s, p, h: _sdk_sync_write(s, p, h, 102, 2, _goal_blocks())),
    # Stuffing: FF FF FD inside the data, and made of the address and length bytes.
    ("write, stuffed", ("dxl_write", 1, 200, STUFFED, 4), proto.write(1, 200, STUFFED), None),
    ("read, stuffed", ("dxl_read", 1, 0xFFFF, 0xFD), proto.read(1, 0xFFFF, 0xFD), None),
    ("sync write, stuffed", ("dxl_sync_write", 116, 4, b"\x01\x02", STUFFED + STUFFED[::-1], 2),
     proto.sync_write(116, 4, [(1, STUFFED), (2, STUFFED[::-1])]), None),
    ("sync write, stuffed twice", ("dxl_sync_write", 116, 4, b"\x07", b"\xff\xff\xfd\xfd", 1),
     proto.sync_write(116, 4, [(7, b"\xff\xff\xfd\xfd")]), None),
]


@pytest.mark.parametrize("name, call, frame, sdk_call", PACKETS, ids=[p[0] for p in PACKETS])
def test_builders_match_python_and_the_sdk(lib, name, call, frame, sdk_call):
    builder, *args = call
    assert dxl.call_builder(lib, builder, len(frame), *args) == frame
    # The worst-case size macro is always enough, and a byte less than the frame never is.
    n_params = len(frame) - 10
    assert dxl.call_builder(lib, builder, dxl.frame_size(n_params), *args) == frame
    assert dxl.call_builder(lib, builder, len(frame) - 1, *args) == dxl.E_SPACE
    if sdk_call is None:
        assert proto.unstuff(frame[7:-2]) != frame[7:-2]  # really a stuffed frame
        return
    sdk = pytest.importorskip("dynamixel_sdk")
    port, ph = CapturePort(), sdk.PacketHandler(2.0)
    sdk_call(sdk, port, ph)
    assert port.sent == [frame]


def test_frames_from_the_e_manual(lib):
    assert dxl.call_builder(lib, "dxl_ping", 10, 1) == bytes.fromhex("FFFFFD0001030001194E")
    assert dxl.call_builder(lib, "dxl_sync_read", 16, 132, 4, b"\x01\x02", 2) == \
        bytes.fromhex("FFFFFD00FE090082840004000102CEFA")


def test_status_and_generic_instruction(lib, rng):
    for n in (0, 1, 5, 64):
        params = bytes(rng.integers(0, 256, n, dtype=np.uint8)) + STUFFED
        assert dxl.call_builder(lib, "dxl_status", dxl.frame_size(len(params) + 1), 7, 0x80,
                                params, len(params)) == proto.status(7, 0x80, params)
        assert dxl.call_builder(lib, "dxl_instruction", dxl.frame_size(len(params)), 3, 0x04,
                                params, len(params)) == proto.instruction(3, 0x04, params)


def test_builders_refuse_impossible_packets(lib):
    big = dxl.frame_size(70_000)
    for bad_id in (0xFD, 0xFF):
        assert dxl.call_builder(lib, "dxl_ping", 64, bad_id) == dxl.E_ARG
        assert dxl.call_builder(lib, "dxl_write", 64, bad_id, 1, b"\x00", 1) == dxl.E_ARG
    # Parameters given as NULL with a nonzero count.
    assert dxl.call_builder(lib, "dxl_write", 64, 1, 1, None, 3) == dxl.E_ARG
    assert dxl.call_builder(lib, "dxl_sync_read", 64, 1, 1, None, 3) == dxl.E_ARG
    # LEN is 16 bits: 70000 parameters cannot be framed, whatever the room.
    data = bytes(70_000)
    assert dxl.call_builder(lib, "dxl_instruction", big, 1, 3, data, len(data)) == dxl.E_ARG
    # The largest frame the parser takes back whole (2048 bytes) is built whole.
    data = bytes(2048 - 10)
    frame = dxl.call_builder(lib, "dxl_instruction", 2048, 1, 3, data, len(data))
    assert frame == proto.instruction(1, 3, data)


def test_every_capacity_short_of_the_frame_is_refused(lib):
    frame = proto.sync_write(116, 4, [(1, STUFFED), (2, STUFFED)])
    args = (116, 4, b"\x01\x02", STUFFED * 2, 2)
    for cap in range(len(frame)):
        assert dxl.call_builder(lib, "dxl_sync_write", cap, *args) == dxl.E_SPACE, cap


# --------------------------------------------------------------------------------------------
# Parser
# --------------------------------------------------------------------------------------------

def test_parser_reads_good_frames_like_protocol_py(lib, rng):
    frames = [proto.status(1, 0, proto.le(2048, 4)), proto.status(2, 0x80, STUFFED * 3),
              proto.status(252, 7), proto.status(0, 0, bytes(range(256)) * 3)]
    stream = b"".join(frames)
    expected = [(f[4], f[8], proto.unstuff(f[9:-2])) for f in frames]
    for sizes in ([len(stream)], [1] * len(stream), [7, 3, 900, 5, 2000]):
        counts: dict = {}
        got = dxl.lockstep(lib, stream, sizes, True, rng, counts)
        assert got == expected
        assert counts.get(proto.OK) == len(frames)


def test_parser_reads_instructions_in_instruction_mode(lib, rng):
    frames = [proto.ping(1), proto.sync_write(116, 4, [(1, STUFFED), (2, STUFFED)]),
              proto.read(0xFE, 0xFFFF, 0xFD), proto.reboot(4)]
    stream = b"\x00\xff\xff" + b"".join(frames)
    got = dxl.lockstep(lib, stream, [5] * len(stream), False, rng, {})
    assert got == [(f[4], 0, proto.unstuff(f[8:-2])) for f in frames]
    # A status packet where instructions are expected is reported, not returned as data.
    p = dxl.CParser(lib, status=False)
    p.feed(proto.status(1))
    assert p.parse() == proto.WRONG_KIND


def test_parser_results_for_damaged_frames(lib):
    good = proto.status(3, 0, b"\x10\x20")
    cases = [
        (good[:-1] + bytes([good[-1] ^ 1]), proto.CRC_FAILURE),
        (good[:4] + b"\xfd" + good[5:], proto.BAD_ID),
        (good[:5] + b"\x02\x00" + good[7:], proto.BAD_LENGTH),
        (good[:5] + b"\xff\xff" + good[7:], proto.BAD_LENGTH),
        (proto.read(3, 132, 4), proto.WRONG_KIND),
        (proto.ping(3), proto.BAD_LENGTH),  # 3 bytes after LEN cannot hold 0x55, ERR, CRC
    ]
    for stream, code in cases:
        p, py = dxl.CParser(lib), proto.PacketParser()
        p.feed(stream)
        py.feed(stream)
        assert p.parse() == py.parse() == code, stream.hex()


def test_space_commit_and_reset(lib):
    p = dxl.CParser(lib)
    room = ctypes.c_size_t()
    ptr = lib.dxl_parser_space(p.ref, ctypes.byref(room))
    assert room.value == dxl.CAPACITY
    frame = proto.status(9, 0, b"\x01\x02\x03")
    ctypes.memmove(ptr, frame, len(frame))
    lib.dxl_parser_commit(p.ref, len(frame))
    assert p.parse() == proto.OK and (p.id, p.params()) == (9, b"\x01\x02\x03")
    # A commit larger than the room is clamped rather than running the end off the buffer.
    lib.dxl_parser_space(p.ref, ctypes.byref(room))
    lib.dxl_parser_commit(p.ref, room.value + 100)
    assert p.end == dxl.CAPACITY
    lib.dxl_parser_reset(p.ref)
    assert p.pending == 0 and p.parse() == proto.NEED_MORE
    # A state no caller should make (start past end) is repaired, not followed off the buffer.
    p.s.start, p.s.end = 10, 5
    assert p.parse() == proto.NEED_MORE and p.pending == 0


@pytest.mark.slow
def test_a_small_lockstep_fuzz(lib):
    """The sanitizer fuzz's lock-step run, small and in process, for ``make test-fast``."""
    rng = np.random.default_rng(12)
    assert dxl.fuzz_builders(lib, rng, 300) == 300
    assert dxl.fuzz_parser(lib, rng, 3000)["frames"] >= 3000
    assert dxl.fuzz_clean(lib, rng, 500)["frames"] >= 500


# --------------------------------------------------------------------------------------------
# Sanitizers
# --------------------------------------------------------------------------------------------

OVERREAD = """
import ctypes, sys
from tests import dxl_codec as dxl
lib = dxl.load(sys.argv[1])
block = (ctypes.c_uint8 * 40)()
print("calling", flush=True)
lib.dxl_crc16(0, ctypes.cast(block, ctypes.c_char_p), 41)
print("no report")
"""


@pytest.mark.slow
def test_the_sanitizer_setup_sees_a_one_byte_overread(asan_lib):
    """Without this, a silent fuzz could mean ASan was never loaded."""
    done = run_sanitized(["-c", OVERREAD, str(asan_lib)])
    assert "calling" in done.stdout, done.stderr
    assert "no report" not in done.stdout
    assert done.returncode != 0
    assert "AddressSanitizer: heap-buffer-overflow" in done.stderr


@pytest.mark.slow
def test_sanitizer_fuzz_of_a_hundred_thousand_frames(asan_lib):
    done = run_sanitized(["-m", "tests.dxl_codec", "--library", str(asan_lib),
                          "--frames", "100000", "--clean-frames", "10000", "--seed", "20261122"])
    assert done.returncode == 0, done.stderr[-4000:]
    assert "Sanitizer" not in done.stderr and "runtime error" not in done.stderr, done.stderr
    line = next(x for x in done.stdout.splitlines() if x.startswith("DXL-FUZZ-OK "))
    summary = json.loads(line.removeprefix("DXL-FUZZ-OK "))
    corrupted = summary["corrupted"]
    assert corrupted["frames"] + summary["clean"]["frames"] >= 100_000
    # Every kind of result was exercised, not only the easy ones.
    for code in (proto.OK, proto.CRC_FAILURE, proto.BAD_LENGTH, proto.BAD_ID,
                 proto.WRONG_KIND):
        assert corrupted.get(str(code), 0) > 100, (code, corrupted)
