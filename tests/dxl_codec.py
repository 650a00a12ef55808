"""ctypes bindings of the embedded C codec (``embedded/core/dxl.c``) for its tests, and the
sanitizer fuzz that ``test_embedded_codec.py`` runs in a subprocess::

    python -m tests.dxl_codec --library build/.../libdxl_asan.so --frames 100000 --seed 1

The fuzz drives the C parser and ``cochlea.dynamixel.protocol.PacketParser`` in lock step on
the same streams (random bytes; good frames flipped, truncated, with wrong lengths or IDs,
unstuffed, with garbage between; fed in random pieces) and stops at the first call where
anything differs: result code, fields, buffer indices, parameters. It also checks that every
call makes progress, that good frames among FF-free garbage come out intact and in order, and
that the builders match protocol.py byte for byte without writing past an exactly-sized
buffer. Under ASan+UBSan a bad access ends the process with a report, so a clean exit with the
summary line means none happened.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import sys
import time
from ctypes import POINTER, byref, c_int, c_int32, c_size_t, c_uint8, c_uint16, c_uint32
from pathlib import Path

import numpy as np

from cochlea.dynamixel import protocol as proto

from .embedded_build import EMBEDDED, build_library

CORE = EMBEDDED / "core"
SOURCE = CORE / "dxl.c"
CAPACITY = 2 * 1024  # DXL_PARSER_CAPACITY
E_SPACE, E_ARG = -1, -2

#: Compiled next to the codec so that the tests check the ctypes mirror of struct dxl_parser
#: against the compiler's layout instead of trusting it.
LAYOUT_HARNESS = ("dxl_layout.c", """\
#include <stddef.h>
#include "dxl.h"
size_t dxl_test_layout(size_t *out);
size_t dxl_test_layout(size_t *out)
{
    out[0] = sizeof(dxl_parser);
    out[1] = offsetof(dxl_parser, start);
    out[2] = offsetof(dxl_parser, end);
    out[3] = offsetof(dxl_parser, params);
    out[4] = offsetof(dxl_parser, params_len);
    out[5] = offsetof(dxl_parser, frame_len);
    out[6] = offsetof(dxl_parser, dropped);
    out[7] = offsetof(dxl_parser, status_mode);
    out[8] = offsetof(dxl_parser, id);
    out[9] = offsetof(dxl_parser, instruction);
    out[10] = offsetof(dxl_parser, error);
    out[11] = offsetof(dxl_parser, buf);
    out[12] = DXL_PARSER_CAPACITY;
    return 13;
}
""")


class ParserStruct(ctypes.Structure):
    _fields_ = [("start", c_size_t), ("end", c_size_t), ("params", POINTER(c_uint8)),
                ("params_len", c_size_t), ("frame_len", c_size_t), ("dropped", c_uint32),
                ("status_mode", c_uint8), ("id", c_uint8), ("instruction", c_uint8),
                ("error", c_uint8), ("buf", c_uint8 * CAPACITY)]


def build(flags=("-O2",), name="dxl") -> Path:
    return build_library(name, [SOURCE, LAYOUT_HARNESS], flags, include=[CORE])


def load(path: Path | str) -> ctypes.CDLL:
    """The library with every signature declared once."""
    lib = ctypes.CDLL(str(path))
    u8p = POINTER(c_uint8)
    sigs = {
        "dxl_crc16": (c_uint16, [c_uint16, ctypes.c_char_p, c_size_t]),
        "dxl_instruction": (c_int32, [u8p, c_size_t, c_uint8, c_uint8, ctypes.c_char_p,
                                      c_size_t]),
        "dxl_status": (c_int32, [u8p, c_size_t, c_uint8, c_uint8, ctypes.c_char_p, c_size_t]),
        "dxl_ping": (c_int32, [u8p, c_size_t, c_uint8]),
        "dxl_reboot": (c_int32, [u8p, c_size_t, c_uint8]),
        "dxl_read": (c_int32, [u8p, c_size_t, c_uint8, c_uint16, c_uint16]),
        "dxl_write": (c_int32, [u8p, c_size_t, c_uint8, c_uint16, ctypes.c_char_p, c_size_t]),
        "dxl_sync_read": (c_int32, [u8p, c_size_t, c_uint16, c_uint16, ctypes.c_char_p,
                                    c_size_t]),
        "dxl_sync_write": (c_int32, [u8p, c_size_t, c_uint16, c_uint16, ctypes.c_char_p,
                                     ctypes.c_char_p, c_size_t]),
        "dxl_put_u16": (None, [u8p, c_uint16]),
        "dxl_put_u32": (None, [u8p, c_uint32]),
        "dxl_get_u16": (c_uint16, [ctypes.c_char_p]),
        "dxl_get_u32": (c_uint32, [ctypes.c_char_p]),
        "dxl_get_i16": (ctypes.c_int16, [ctypes.c_char_p]),
        "dxl_get_i32": (c_int32, [ctypes.c_char_p]),
        "dxl_parser_init": (None, [POINTER(ParserStruct), c_int]),
        "dxl_parser_reset": (None, [POINTER(ParserStruct)]),
        "dxl_parser_pending": (c_size_t, [POINTER(ParserStruct)]),
        "dxl_parser_space": (u8p, [POINTER(ParserStruct), POINTER(c_size_t)]),
        "dxl_parser_commit": (None, [POINTER(ParserStruct), c_size_t]),
        "dxl_parser_feed": (c_size_t, [POINTER(ParserStruct), ctypes.c_char_p, c_size_t]),
        "dxl_parser_parse": (c_int, [POINTER(ParserStruct)]),
        "dxl_test_layout": (c_size_t, [POINTER(c_size_t)]),
    }
    for name, (restype, argtypes) in sigs.items():
        fn = getattr(lib, name)
        fn.restype = restype
        fn.argtypes = argtypes
    return lib


def layout(lib) -> list[int]:
    out = (c_size_t * 16)()
    n = lib.dxl_test_layout(out)
    return list(out[:n])


def expected_layout() -> list[int]:
    fields = ["start", "end", "params", "params_len", "frame_len", "dropped", "status_mode",
              "id", "instruction", "error", "buf"]
    return ([ctypes.sizeof(ParserStruct)] + [getattr(ParserStruct, f).offset for f in fields]
            + [CAPACITY])


def call_builder(lib, name: str, cap: int, *args):
    """Run builder ``name`` into a buffer of exactly ``cap`` bytes that ends where its heap
    block ends (so ASan sees a write past it), and return the frame or the error code."""
    block = (c_uint8 * max(cap, 32))()  # > 16 bytes: ctypes then mallocs it (no inline copy)
    offset = len(block) - cap
    out = ctypes.cast(ctypes.addressof(block) + offset, POINTER(c_uint8))
    n = getattr(lib, name)(out, cap, *args)
    if n < 0:
        return n
    assert n <= cap, (name, n, cap)
    return bytes(block[offset:offset + n])


def frame_size(n_params: int) -> int:
    """DXL_FRAME_SIZE(n): room for any frame of n parameters."""
    return 7 + 2 * (1 + n_params) + 2


class CParser:
    """The C parser behind the interface of ``protocol.PacketParser``, for lock-step runs."""

    def __init__(self, lib, status: bool = True):
        self.lib = lib
        self.s = ParserStruct()
        self.ref = byref(self.s)
        lib.dxl_parser_init(self.ref, 1 if status else 0)
        self._room = c_size_t()

    start = property(lambda self: self.s.start)
    end = property(lambda self: self.s.end)
    id = property(lambda self: self.s.id)
    instruction = property(lambda self: self.s.instruction)
    error = property(lambda self: self.s.error)
    frame_len = property(lambda self: self.s.frame_len)
    dropped = property(lambda self: self.s.dropped)
    params_len = property(lambda self: self.s.params_len)

    @property
    def pending(self) -> int:
        return self.lib.dxl_parser_pending(self.ref)

    def feed(self, data: bytes) -> int:
        return self.lib.dxl_parser_feed(self.ref, data, len(data))

    def read_into(self, data: bytes) -> int:
        """The other way in: dxl_parser_space, a copy, dxl_parser_commit (as a UART driver)."""
        ptr = self.lib.dxl_parser_space(self.ref, byref(self._room))
        n = min(len(data), self._room.value)
        ctypes.memmove(ptr, data, n)
        self.lib.dxl_parser_commit(self.ref, n)
        return n

    def parse(self) -> int:
        return self.lib.dxl_parser_parse(self.ref)

    def params(self) -> bytes:
        s = self.s
        start = ctypes.addressof(s.params.contents) - ctypes.addressof(s.buf)
        assert 0 <= start and start + s.params_len <= CAPACITY, "params outside the buffer"
        return ctypes.string_at(s.params, s.params_len)


# --------------------------------------------------------------------------------------------
# Stream generation
# --------------------------------------------------------------------------------------------

#: Bytes that make stuffing and false headers likely.
SPECIAL = np.array([0xFF, 0xFD, 0x00, 0x55], dtype=np.uint8)


def random_bytes(rng, n: int, ff_free: bool = False) -> bytes:
    if ff_free:
        return rng.integers(0, 255, n, dtype=np.uint8).tobytes()  # 0..254
    data = rng.integers(0, 256, n, dtype=np.uint8)
    mask = rng.random(n) < 0.3
    data[mask] = rng.choice(SPECIAL, int(mask.sum()))
    return data.tobytes()


def param_count(rng) -> int:
    r = rng.random()
    if r < 0.85:
        return int(rng.integers(0, 17))
    if r < 0.98:
        return int(rng.integers(17, 300))
    return int(rng.integers(300, 1400))


def good_frame(rng, status: bool) -> tuple[bytes, tuple]:
    """A valid frame of the kind the parser expects, and what the parser must report."""
    params = random_bytes(rng, param_count(rng))
    if status:
        motor_id = int(rng.integers(0, 253))
        error = int(rng.integers(0, 256)) if rng.random() < 0.2 else 0
        return proto.status(motor_id, error, params), (motor_id, error, params)
    motor_id = int(rng.integers(0, 253)) if rng.random() < 0.9 else 0xFE
    code = int(rng.choice([0x01, 0x02, 0x03, 0x08, 0x82, 0x83, 0x92, int(rng.integers(0, 256))]))
    if code == 0x55:
        code = 0x03
    return proto.instruction(motor_id, code, params), (motor_id, 0, params)


def with_crc(body: bytes | bytearray) -> bytes:
    crc = proto.crc16(body)
    return bytes(body) + bytes([crc & 0xFF, crc >> 8])


def corrupt(rng, frame: bytes, status: bool) -> bytes:
    """One of the ways a frame goes wrong on a bus, or a sender gets it wrong."""
    kind = int(rng.integers(0, 9))
    b = bytearray(frame)
    if kind == 0:  # bit flips
        for _ in range(int(rng.integers(1, 4))):
            i = int(rng.integers(0, len(b)))
            b[i] ^= 1 << int(rng.integers(0, 8))
        return bytes(b)
    if kind == 1:  # truncated
        return bytes(b[:int(rng.integers(0, len(b)))])
    if kind == 2:  # a wrong length field, CRC left as it was
        b[5] = int(rng.integers(0, 256))
        b[6] = int(rng.integers(0, 256)) if rng.random() < 0.3 else 0
        return bytes(b)
    if kind == 3:  # a wrong length with a CRC that matches it (a buggy sender)
        length = max(0, len(b) - 7 + int(rng.integers(-4, 5)))
        body = bytearray(b[:7 + max(length - 2, 0)])
        body += bytes(max(0, 7 + length - 2 - len(body)))
        body[5], body[6] = length & 0xFF, length >> 8
        return with_crc(body)
    if kind == 4:  # an impossible ID with a good CRC
        b[4] = int(rng.choice([0xFD, 0xFF, 0xFE, int(rng.integers(253, 256))]))
        return with_crc(b[:-2])
    if kind == 5:  # the other kind of packet, well formed
        params = random_bytes(rng, int(rng.integers(0, 8)))
        return (proto.instruction(int(rng.integers(0, 253)), 0x02, params) if status
                else proto.status(int(rng.integers(0, 253)), 0, params))
    if kind == 6:  # stuffing missing (a sender that does not stuff) with a matching CRC
        body = bytes(b[7:-2]).replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")
        length = len(body) + 2
        return with_crc(b[:5] + bytes([length & 0xFF, length >> 8]) + body)
    if kind == 7:  # a doubled or partial header in front
        return proto.HEADER[:int(rng.integers(1, 5))] + bytes(b)
    # a length just over the parser's capacity, or the biggest one
    length = int(rng.choice([CAPACITY - 7 + 1, 0xFFFF, CAPACITY - 7]))
    b[5], b[6] = length & 0xFF, length >> 8
    return bytes(b)


def pieces(rng, total: int) -> list[int]:
    """Random read sizes: bytes one by one, UART-sized reads, whole bursts."""
    sizes = []
    scale = int(rng.choice([1, 4, 16, 64, 512, 4096], p=[0.05, 0.15, 0.2, 0.2, 0.2, 0.2]))
    left = total
    while left > 0:
        n = int(rng.integers(1, scale + 1))
        sizes.append(n)
        left -= n
    return sizes


# --------------------------------------------------------------------------------------------
# Lock-step runs
# --------------------------------------------------------------------------------------------

def state(p) -> tuple:
    return (p.start, p.end, p.id, p.instruction, p.error, p.frame_len, p.dropped & 0xFFFFFFFF)


def cstate(s: ParserStruct) -> tuple:
    """:func:`state` of a CParser's struct, read directly (the hot path of the fuzz)."""
    return (s.start, s.end, s.id, s.instruction, s.error, s.frame_len, s.dropped)


class Mismatch(AssertionError):
    pass


def lockstep(lib, stream: bytes, sizes: list[int], status: bool, rng, counts: dict) -> list:
    """Feed ``stream`` to both parsers in pieces of ``sizes``, parsing after each piece until
    NEED_MORE; compare everything after every call. Returns the C parser's results."""
    py = proto.PacketParser(status=status)
    c = CParser(lib, status=status)
    cs = c.s
    results = []
    offset = 0
    feeds = 0
    calls = 0
    size_iter = iter(sizes)
    while offset < len(stream):
        size = next(size_iter, len(stream))
        chunk = stream[offset:offset + size]
        fed_py = py.feed(chunk)
        fed_c = c.feed(chunk) if rng.random() < 0.5 else c.read_into(chunk)
        if fed_py != fed_c:
            raise Mismatch(f"feed took {fed_c} bytes in C, {fed_py} in Python at {offset}")
        if fed_c == 0:
            raise Mismatch(f"the buffer is full and the parser still waits at {offset}")
        offset += fed_c
        feeds += 1
        while True:
            pending = cs.end - cs.start
            code_py = py.parse()
            code_c = c.parse()
            calls += 1
            counts[code_c] = counts.get(code_c, 0) + 1
            now = cstate(cs)
            if code_c != code_py or now != state(py):
                raise Mismatch(f"at byte {offset}: C {code_c} {now}, Python {code_py} "
                               f"{state(py)}")
            if code_c == proto.OK:
                if c.params() != py.params():
                    raise Mismatch(f"params differ at {offset}: {c.params()!r} "
                                   f"{py.params()!r}")
                results.append((c.id, c.error, c.params()))
            if code_c == proto.NEED_MORE:
                # Without new bytes, parsing again changes nothing: a loop of calls ends.
                if c.parse() != proto.NEED_MORE or cstate(cs) != now:
                    raise Mismatch(f"NEED_MORE is not a fixed point at {offset}")
                break
            if not cs.end - cs.start < pending:
                raise Mismatch(f"result {code_c} without consuming a byte at {offset}")
    # Each feed's loop ends on one NEED_MORE; every other call consumed at least one byte.
    if calls > len(stream) + feeds:
        raise Mismatch(f"{calls} parse calls for {len(stream)} bytes in {feeds} pieces")
    counts["calls"] = counts.get("calls", 0) + calls
    counts["bytes"] = counts.get("bytes", 0) + len(stream)
    return results


def fuzz_parser(lib, rng, frames: int) -> dict:
    """Corrupted streams until ``frames`` frames (good, corrupted or random blobs) are done."""
    counts: dict = {}
    done = 0
    streams = 0
    while done < frames:
        status = bool(rng.random() < 0.7)
        parts = []
        n = int(rng.integers(20, 200))
        for _ in range(n):
            r = rng.random()
            if r < 0.25:
                parts.append(random_bytes(rng, int(rng.integers(0, 48))))
            elif r < 0.5:
                parts.append(good_frame(rng, status)[0])
            else:
                parts.append(corrupt(rng, good_frame(rng, status)[0], status))
            if rng.random() < 0.3:
                parts.append(random_bytes(rng, int(rng.integers(0, 8))))
        stream = b"".join(parts)
        lockstep(lib, stream, pieces(rng, len(stream)), status, rng, counts)
        done += n
        streams += 1
    counts["frames"] = done
    counts["streams"] = streams
    return counts


def fuzz_clean(lib, rng, frames: int) -> dict:
    """Good frames among FF-free garbage: every one comes out, in order, intact."""
    counts: dict = {}
    done = 0
    while done < frames:
        status = bool(rng.random() < 0.7)
        parts, expected = [], []
        for _ in range(int(rng.integers(5, 60))):
            parts.append(random_bytes(rng, int(rng.integers(0, 24)), ff_free=True))
            frame, fields = good_frame(rng, status)
            parts.append(frame)
            expected.append(fields)
        parts.append(random_bytes(rng, int(rng.integers(0, 24)), ff_free=True))
        stream = b"".join(parts)
        got = lockstep(lib, stream, pieces(rng, len(stream)), status, rng, counts)
        if got != expected:
            raise Mismatch(f"{len(got)} of {len(expected)} good frames came out, or changed")
        extra = sum(v for k, v in counts.items() if k not in (proto.OK, proto.NEED_MORE,
                                                               "calls", "bytes"))
        if extra:
            raise Mismatch(f"{extra} error results among good frames and FF-free garbage")
        done += len(expected)
    counts["frames"] = done
    return counts


def fuzz_builders(lib, rng, n: int) -> int:
    """Random builder calls against protocol.py, into exact and one-byte-short buffers."""
    for _ in range(n):
        k = int(rng.integers(0, 6))
        motor_id = int(rng.integers(0, 253)) if rng.random() < 0.9 else 0xFE
        address = int(rng.choice([int(rng.integers(0, 0x10000)), 0xFDFF, 0xFFFF, 0xFFFD]))
        data = random_bytes(rng, int(rng.integers(0, 40)))
        ids = random_bytes(rng, int(rng.integers(0, 12)))
        length = int(rng.integers(0, 9))
        if k == 0:
            args, ref = ("dxl_ping", motor_id), proto.ping(motor_id)
        elif k == 1:
            args, ref = ("dxl_reboot", motor_id), proto.reboot(motor_id)
        elif k == 2:
            args, ref = ("dxl_read", motor_id, address, length), proto.read(motor_id, address,
                                                                           length)
        elif k == 3:
            args, ref = ("dxl_write", motor_id, address, data, len(data)), \
                proto.write(motor_id, address, data)
        elif k == 4:
            args, ref = ("dxl_sync_read", address, length, ids, len(ids)), \
                proto.sync_read(address, length, ids)
        else:
            blocks = random_bytes(rng, length * len(ids))
            args = ("dxl_sync_write", address, length, ids, blocks, len(ids))
            ref = proto.sync_write(address, length, [(i, blocks[j * length:(j + 1) * length])
                                                     for j, i in enumerate(ids)])
        name, *rest = args
        got = call_builder(lib, name, len(ref), *rest)
        if got != ref:
            raise Mismatch(f"{name}{tuple(rest)}: {got!r} != {ref!r}")
        short = call_builder(lib, name, len(ref) - 1, *rest)
        if short != E_SPACE:
            raise Mismatch(f"{name} into {len(ref) - 1} bytes returned {short!r}")
    return n


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--library", required=True)
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--clean-frames", type=int, default=10_000)
    ap.add_argument("--builders", type=int, default=5_000)
    ap.add_argument("--seed", type=int, default=20261122)
    args = ap.parse_args(argv)
    lib = load(args.library)
    if layout(lib) != expected_layout():
        print(f"struct layout {layout(lib)} != ctypes {expected_layout()}", file=sys.stderr)
        return 2
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    summary = {"builders": fuzz_builders(lib, rng, args.builders),
               "corrupted": fuzz_parser(lib, rng, args.frames),
               "clean": fuzz_clean(lib, rng, args.clean_frames)}
    summary["seconds"] = round(time.perf_counter() - t0, 2)
    print("DXL-FUZZ-OK " + json.dumps(summary, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
