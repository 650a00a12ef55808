"""Property-based fuzz of the packet parser (``hypothesis``, a test-only dependency): more than
10^4 random and corrupted frames (2000 random byte strings, then 2000 streams of at least 4
frames with random corruptions, then 1200 streams of at least 4 good frames in garbage: at least
14800 frames), fed in random pieces. No exception escapes, every parse call consumes bytes or
asks for more (so a loop of calls ends: no hang) within a bounded time, and good frames among
FF-free garbage all come out, in order, intact. (The emulator's own fuzz, random instructions
with valid CRCs, is in test_dynamixel_emulator.py.)"""

from __future__ import annotations

import time
from datetime import timedelta

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cochlea.dynamixel import protocol as proto

# Hypothesis feeds the parser thousands of streams.
pytestmark = pytest.mark.slow


def fuzz(examples: int):
    return settings(max_examples=examples, deadline=timedelta(milliseconds=500), database=None,
                    derandomize=True, suppress_health_check=[HealthCheck.too_slow])

#: The slowest single parse() call allowed (s): a few hundred bytes of CRC at most.
PARSE_BOUND_S = 0.05


def drain(parser: proto.PacketParser, stream: bytes, pieces: list[int]) -> list[tuple]:
    """Feed ``stream`` in pieces of the given sizes, parsing after each; return the results."""
    results = []
    offset = 0
    calls = 0
    sizes = iter(pieces)
    while offset < len(stream) or calls == 0:
        size = next(sizes, len(stream))
        chunk = stream[offset:offset + max(size, 1)]
        fed = parser.feed(chunk)
        assert fed > 0 or not chunk, "the parser's buffer is full and it still waits"
        offset += fed
        while True:
            before = (parser.start, parser.end)
            t0 = time.perf_counter()
            code = parser.parse()
            assert time.perf_counter() - t0 < PARSE_BOUND_S
            calls += 1
            assert calls <= 4 * len(stream) + 8, "the parser does not make progress"
            if code == proto.NEED_MORE:
                break
            assert (parser.start, parser.end) != before, "a result without consuming bytes"
            results.append((code, parser.id, parser.error,
                            parser.params() if code == proto.OK else None))
        if not chunk:
            break
    return results


status_frames = st.builds(
    lambda i, e, p: proto.status(i, e, p), st.integers(0, 252), st.integers(0, 255),
    st.one_of(st.binary(max_size=40),
              st.lists(st.sampled_from([0xFF, 0xFD, 0x00, 0x55]), max_size=24).map(bytes)))
instruction_frames = st.builds(
    lambda i, c, p: proto.instruction(i, c, p), st.sampled_from([1, 2, 3, 0xFE, 252]),
    st.sampled_from([0x01, 0x02, 0x03, 0x08, 0x82, 0x83, 0x06, 0x77]), st.binary(max_size=40))
pieces = st.lists(st.integers(1, 64), max_size=40)


@fuzz(2000)
@given(stream=st.binary(max_size=600), sizes=pieces, status=st.booleans())
def test_random_bytes(stream, sizes, status):
    drain(proto.PacketParser(status=status), stream, sizes)


@st.composite
def corrupted_streams(draw):
    frames = draw(st.lists(st.one_of(status_frames, instruction_frames), min_size=4,
                           max_size=8))
    stream = bytearray(b"".join(frames))
    for _ in range(draw(st.integers(0, 6))):
        kind = draw(st.sampled_from(["flip", "insert", "delete", "header", "truncate"]))
        at = draw(st.integers(0, max(len(stream) - 1, 0)))
        if kind == "flip" and stream:
            stream[at] ^= 1 << draw(st.integers(0, 7))
        elif kind == "insert":
            stream[at:at] = draw(st.binary(min_size=1, max_size=8))
        elif kind == "delete" and stream:
            del stream[at:at + draw(st.integers(1, 4))]
        elif kind == "header":  # a fake header with a random length field
            stream[at:at] = proto.HEADER + draw(st.binary(min_size=3, max_size=3))
        elif kind == "truncate":
            del stream[at:]
    return bytes(stream)


@fuzz(2000)
@given(stream=corrupted_streams(), sizes=pieces, status=st.booleans())
def test_corrupted_frames(stream, sizes, status):
    parser = proto.PacketParser(status=status)
    for code, *_ in drain(parser, stream, sizes):
        assert code in proto.RESULT_NAMES


@st.composite
def frames_in_garbage(draw):
    frames = draw(st.lists(status_frames, min_size=4, max_size=8))
    garbage = st.binary(max_size=12).map(lambda b: bytes(x for x in b if x != 0xFF))
    stream = b"".join(draw(garbage) + f for f in frames) + draw(garbage)
    return frames, stream


@fuzz(1200)
@given(case=frames_in_garbage(), sizes=pieces)
def test_good_frames_in_garbage_all_come_out(case, sizes):
    frames, stream = case
    results = drain(proto.PacketParser(status=True), stream, sizes)
    good = [(i, e, p) for code, i, e, p in results if code == proto.OK]
    expected = []
    for frame in frames:
        parser = proto.PacketParser()
        parser.feed(frame)
        assert parser.parse() == proto.OK
        expected.append((parser.id, parser.error, parser.params()))
    assert good == expected
    assert all(code == proto.OK for code, *_ in results)
