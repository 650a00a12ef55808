"""cochlea-embedded-host: the rows a board's firmware streams (embedded/ports/, stm32f4: USART3)
written as cochlea-run writes a run: log.bin, log.columns.json, log.csv, summary.json and the
figures, through cochlea-run's own code (the real-time loop's row layout and report).

    cochlea-embedded-host --port /dev/ttyUSB1 --out runs/board1 [--baud 921600] [--timeout 10]

It reads frames (cochlea.runtime.row_stream) until the firmware's end frame, Ctrl-C, SIGTERM
or SIGHUP, or a line silent for --timeout seconds; every frame is checked (CRC, sequence,
schema, row length, time) and what is wrong is counted in summary.json's ``stream``, never
raised. A run that did not reach its end frame is written all the same, ``stream.complete``
false and its stop ``stream-incomplete``. docs/embedded.md, "The row stream".
"""

from __future__ import annotations

import math
import os
import re
import signal
import socket
import sys
import time
from pathlib import Path

import numpy as np
import serial

from ..console import OneLineParser
from ..errors import EXIT_USER_ERROR, CochleaError, printable
from ..log_schema import SCHEMA_VERSION
from ..runtime import RealTimeLoop, build_supervisor, write_raw_columns
from ..runtime.loop import raw_columns
from ..runtime.row_stream import (
    END,
    HEADER,
    MAX_PAYLOAD,
    ROW,
    Decoder,
    Frame,
    chain_crc,
    parse_text,
)
from ..sim import choose_kernels, load_scenario, unit_setups
from ..sim.scenario import MAX_RATE_HZ, MIN_RATE_HZ
from ..text import number_argument, whole_argument
from . import report
from .outputs import ReportError

#: The header's bounds: counts (every, periods, watchdog_misses) within 32 bits (a log's
#: time_s below 2**31 s, the firmware's C int); the period of a control rate cochlea-run allows
#: (MIN_RATE_HZ .. MAX_RATE_HZ); a row no longer than a frame can carry.
MAX_COUNT = 2**31 - 1
MIN_PERIOD_NS = round(1e9 / MAX_RATE_HZ)
MAX_PERIOD_NS = round(1e9 / MIN_RATE_HZ)
MAX_ROW_LENGTH = (MAX_PAYLOAD - 8) // 8  # a row frame: its period (int64), then the row

PROG = "cochlea-embedded-host"
#: Exit codes: after the end frame, the firmware's own (cochlea-run's: 0 completed, 5 the
#: motors did not start, 10-15 a supervisor rule), the files written; 2 a usage error (nothing
#: written); 3 the stream ended without its end frame (silence, a signal, end of a file),
#: what came is written; 4 no header came, or one this host cannot write (another schema or
#: scenario; nothing written); 18 part of the report could not be written (the line names
#: what was lost and what is kept).
EXIT_INCOMPLETE, EXIT_NO_HEADER = 3, 4
#: Part of the report could not be written (a full disk): cochlea-run's code.
EXIT_REPORT_FAILED = 18
READ_SIZE = 4096


class _Backend:
    """The loop's view of the firmware's bus: it measures current (the rows carry it)."""

    joint_current_A = True


class HeaderError(CochleaError):
    """No header, or one this host cannot write a run from: nothing is written."""


#: The end frame's integer fields and the least each may be (the firmware prints them with
#: %ld / %lu; a stop's joint is -1 when no joint stopped it, a limit's values are signed).
END_INTEGERS = {
    **{k: 0 for k in ("exit", "rows", "kicks", "tick_overruns", "deadline_misses", "overruns",
                      "lateness_max_ns", "reads", "good_reads", "rx_overflows", "stop_time_us",
                      "rows_seen", "rows_queued", "rows_dropped", "rows_sent", "frames",
                      "rows_crc")},
    "stop_joint": -1, "stop_value_u": -2**63, "stop_limit_u": -2**63,
}


def end_fields(end: dict[str, str]) -> tuple[dict[str, str], str | None]:
    """The end frame's fields, or ``({}, why)`` when one of its integers is not one (a
    firmware built from another checkout, or a frame whose CRC matched by chance): the rows
    are kept and the run is reported incomplete, never a traceback with the report lost."""
    for key, least in END_INTEGERS.items():
        if key not in end:
            continue
        text = end[key]
        value = int(text) if re.fullmatch(r"-?[0-9]{1,20}", text) else None
        top = 255 if key == "exit" else 2**64 - 1
        if value is None or not least <= value <= top:
            return {}, (f"the end frame's {key} is {printable(text[:40])!r}, not an integer "
                        f"from {least} to {top}")
    return end, None


class StreamRun:
    """The host's side of one firmware run: the header sets the loop (cochlea-run's row
    layout), the rows go to log.bin, the end frame closes it."""

    def __init__(self, out: Path, scenario_override: str | None,
                 decoder: Decoder | None = None):
        self.out, self.scenario_override = out, scenario_override
        self.decoder = decoder or Decoder()
        self.restart_ended = False  # the frames that began it held its end frame too
        self.header: dict | None = None
        self.end: dict | None = None
        self.end_problem: str | None = None  # the end frame came, but it cannot be read
        self.loop: RealTimeLoop | None = None
        self.file: int | None = None  # log.bin's descriptor: rows are written whole
        self.pending = bytearray()  # this feed's rows, written when it returns
        self.rows = 0  # rows in log.bin (received, and NaN fill for missing periods)
        self.disk_error: str | None = None  # log.bin could not take the rows (a full disk)
        self.received = 0
        self.missing = 0  # periods the stream skipped (lost frames, the firmware's drops)
        self.bad_rows = {"length": 0, "time": 0, "order": 0}
        self.before_header = 0
        self.crc = 0
        self.last_k: int | None = None
        #: A second header (the board restarted: a reset, a power cycle) ends this run; the
        #: header and the frames after it begin the next run, in its own folder.
        self.restart: list[Frame] | None = None

    # ---- frames ----------------------------------------------------------------------

    def feed(self, data: bytes) -> bool:
        """True once the end frame has come. The rows are in log.bin when it returns (a
        reader following the file, as cochlea-ros2 follows cochlea-run's, sees them)."""
        try:
            done = self._frames(data)
        finally:
            if self.file is not None and self.pending:
                self._write_pending()
        return done or self.disk_error is not None

    def following(self, out: Path) -> StreamRun:
        """The run the board began when it restarted, from the frames after this one's end
        (its header first), written to ``out``; the same decoder reads on."""
        run = StreamRun(out, self.scenario_override, self.decoder)
        try:
            run.restart_ended = run.frames(self.restart)
        finally:
            if run.file is not None and run.pending:
                run._write_pending()
        run.restart_ended = run.restart_ended or run.disk_error is not None
        return run

    def _write_pending(self) -> None:
        """The rows of this feed into log.bin. A write that fails (a full disk, a file too
        large) leaves log.bin with the whole rows that fit and ends the read: the report is
        then written from them, and the host exits 18 as cochlea-run does."""
        data, self.pending = bytes(self.pending), bytearray()
        try:
            done = 0
            while done < len(data):
                done += os.write(self.file, data[done:])
        except OSError as exc:
            width = 8 * self.row_length
            size = os.fstat(self.file).st_size
            kept = size // width
            try:
                os.ftruncate(self.file, kept * width)  # no torn row at the end
            except OSError:
                pass
            lost = self.rows - kept
            self.rows = kept
            self.disk_error = (f"log.bin could not be written ({exc.strerror or exc}): it "
                               f"keeps its first {kept} rows, {lost} more were lost, and the "
                               "read stopped there")

    def _frames(self, data: bytes) -> bool:
        return self.frames(self.decoder.feed(data))

    def frames(self, frames: list[Frame]) -> bool:
        for i, frame in enumerate(frames):
            if frame.kind == HEADER:
                if self.header is None:
                    self._start(parse_text(frame.payload))
                elif frame.sequence == 0 and (self.received or any(self.bad_rows.values())):
                    # numbered from 0 again after rows had come: the board restarted
                    self.restart = frames[i:]
                    self.end_problem = ("the board restarted (a new stream header) before the "
                                        "end frame")
                    return True
            elif frame.kind == ROW:
                if self.loop is None:
                    self.before_header += 1
                else:
                    self._row(frame)
            elif frame.kind == END and self.loop is not None:
                self.end, self.end_problem = end_fields(parse_text(frame.payload))
                return True
        return False

    def _start(self, header: dict) -> None:
        try:
            self.every = int(header["every"])
            self.period_ns = int(header["period_ns"])
            self.row_length = int(header["row_length"])
            self.periods = int(header["periods"])
            self.misses = int(header.get("watchdog_misses", 20))
            name = self.scenario_override or header["scenario"]
            columns = header["columns"].split(",")
        except (KeyError, ValueError) as exc:
            raise HeaderError(f"the stream's header is malformed (field {exc})") from None
        if self.every < 1 or self.period_ns <= 0 or self.row_length <= 0:
            raise HeaderError("the stream's header says no rows are streamed (row_length "
                               f"{self.row_length}, every {self.every}): nothing to write")
        # What the host's own readers (cochlea-mcap, cochlea-view, cochlea-ros2) and
        # cochlea-run accept, so that a run written here is read back: counts within 32 bits
        # (the firmware's C int; watchdog_misses too: a firmware built for QEMU tolerates
        # 100 000, more than cochlea-run's 500), a control rate cochlea-run allows.
        for field, value, low, high in (
                ("every", self.every, 1, MAX_COUNT), ("periods", self.periods, 0, MAX_COUNT),
                ("row_length", self.row_length, 1, MAX_ROW_LENGTH),
                ("period_ns", self.period_ns, MIN_PERIOD_NS, MAX_PERIOD_NS),
                ("watchdog_misses", self.misses, 1, MAX_COUNT)):
            if not low <= value <= high:
                raise HeaderError(f"the stream's header is malformed (field {field} = "
                                  f"{str(value)[:40]}, outside [{low}, {high}])")
        if header.get("schema_version") != str(SCHEMA_VERSION):
            raise HeaderError(f"the firmware's rows follow log schema version "
                              f"{header.get('schema_version')}, this host's is {SCHEMA_VERSION}: "
                              "rebuild the firmware from this checkout")
        try:
            self.scenario = load_scenario(name)
            setups = unit_setups(self.scenario, on_motors=True)
        except CochleaError as exc:
            raise HeaderError(f"the stream's scenario {name!r}: {exc}") from None
        kernels = choose_kernels(setups, self.scenario.plant_substeps, "auto", None).used
        supervisor = build_supervisor(setups, self.scenario.system.keep_out_radius,
                                      watchdog_misses=self.misses, kernels=kernels,
                                      substeps=self.scenario.plant_substeps)
        # The loop's rows are log.bin's; its period is the log's row spacing (every-th
        # period), so that the report's desired samples fall at the rows' times.
        self.h = self.period_ns * 1e-9
        loop = RealTimeLoop(setups, _Backend(), supervisor, self.h * self.every,
                            max(self.periods // self.every, 1), realtime=True,
                            kernels=kernels, substeps=self.scenario.plant_substeps)
        expected = raw_columns(loop)
        if columns != expected or loop.width != self.row_length:
            raise HeaderError(
                f"the firmware's rows ({self.row_length} values: {','.join(columns[:4])}...) "
                f"are not {name}'s log.bin rows here ({loop.width} values: "
                f"{','.join(expected[:4])}...): a firmware built from another scenario or "
                "schema; --scenario names the one it was built from")
        self.out.mkdir(parents=True, exist_ok=True)
        write_raw_columns(self.out / "log.columns.json", loop)
        self.file = os.open(self.out / "log.bin", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self.header, self.loop = header, loop  # last: the run has begun

    def _row(self, frame: Frame) -> None:
        payload = frame.payload
        if len(payload) != 8 + 8 * self.row_length:
            self.bad_rows["length"] += 1
            return
        k = int(np.frombuffer(payload, "<i8", 1)[0])
        row = np.frombuffer(payload, "<f8", self.row_length, offset=8)
        t = float(row[0])
        # time_s is never NaN and is k periods; rows come every every-th period, in order.
        if not math.isfinite(t) or abs(t - k * self.h) > 1e-9 * max(1.0, abs(t)) + 1e-12 \
                or k % self.every:
            self.bad_rows["time"] += 1
            return
        if self.last_k is not None and k <= self.last_k:
            self.bad_rows["order"] += 1
            return
        self.crc = chain_crc(self.crc, frame.crc)
        expected = 0 if self.last_k is None else self.last_k + self.every
        while expected < k:  # a hole: a NaN row at the missing period's time keeps the log's
            hole = np.full(self.row_length, np.nan)  # rows at their periods
            hole[0] = expected * self.h
            self.pending += hole.astype("<f8").tobytes()
            self.rows += 1
            self.missing += 1
            expected += self.every
        self.pending += row.astype("<f8").tobytes()
        self.rows += 1
        self.received += 1
        self.last_k = k

    # ---- the report ------------------------------------------------------------------

    def write(self, why_incomplete: str | None) -> dict:
        os.close(self.file)
        loop, end = self.loop, self.end or {}
        loop.log_path, loop.rows = self.out / "log.bin", self.rows
        result = loop.result(self.scenario)
        result.kernels = {"used": "c", "requested": "c",
                          "library": f"compiled in: cochlea-{self.header.get('board', 'board')} "
                                     f"({self.header.get('precision', '?')})",
                          "fallback_reason": None}
        if why_incomplete is None:
            rule = end.get("rule", "none")
            exit_code = int(end.get("exit", 5))
            stop_t = int(end.get("stop_time_us", 0)) * 1e-6
            joint = int(end.get("stop_joint", -1))
            detail = "" if rule in ("completed", "none") or joint < 0 else (
                f"joint {joint}: {int(end.get('stop_value_u', 0)) * 1e-6:g} past its limit "
                f"{int(end.get('stop_limit_u', 0)) * 1e-6:g} (SI)")
            result.stop = {"rule": rule, "time_s": stop_t, "detail": detail,
                           "exit_code": exit_code}
        else:
            last = (self.last_k or 0) * self.h
            result.stop = {"rule": "stream-incomplete", "time_s": last,
                           "detail": why_incomplete, "exit_code": None}
        timing = loop.timing_summary()
        # What only the firmware knows: its own overrun rule's counts, its lateness, the bus.
        for key, kind in (("deadline_misses", int), ("overruns", int),
                          ("tick_overruns", int)):
            if key in end:
                timing[key] = kind(end[key])
        if "lateness_max_ns" in end:
            timing["lateness_max"] = int(end["lateness_max_ns"]) * 1e-9
        timing["deadline_miss_fraction"] = timing["deadline_misses"] / max(
            int(end.get("rows", self.rows * self.every)), 1)
        timing["nominal_period"] = self.h
        timing["scheduling"] = (f"{self.header.get('board', 'board')} firmware: SysTick paces "
                                "the periods, the main context runs them")
        if end:
            timing["bus"] = {"reads": int(end.get("reads", 0)),
                             "good_reads": int(end.get("good_reads", 0)),
                             "failures": end.get("failures", "none"),
                             "rx_overflows": int(end.get("rx_overflows", 0)),
                             "shutdown": "confirmed " + end.get("confirmed_off", "?")}
        seen = int(end["rows_seen"]) if "rows_seen" in end else None
        firmware_crc = int(end["rows_crc"]) if "rows_crc" in end else None
        stream = {
            "complete": why_incomplete is None,
            "incomplete_reason": why_incomplete,
            "every": self.every,
            "control_rate_Hz": 1.0 / self.h,
            "log_rate_Hz": 1.0 / (self.h * self.every),
            "rows_received": self.received,
            "rows_missing": self.missing,
            "rows_rejected": dict(self.bad_rows),
            "rows_before_header": self.before_header,
            "firmware": {k: int(end[k]) for k in ("rows_seen", "rows_queued", "rows_dropped",
                                                  "rows_sent", "frames", "kicks")
                         if k in end},
            "rows_crc_match": None if firmware_crc is None else firmware_crc == self.crc,
            "decoder": self.decoder.counts.as_dict(),
            "header": {k: v for k, v in self.header.items() if k != "columns"},
        }
        # periods, rate_Hz and duration_s describe log.bin's rows, as cochlea-run's do and as
        # the loaders (cochlea-mcap, cochlea-view) check them: with every > 1 the rate is the
        # log's (the control rate and the firmware's periods are in stream).
        stream["firmware_periods"] = seen
        extra = {"rate_Hz": 1.0 / (self.h * self.every),
                 "duration_s": self.rows * self.h * self.every, "stream": stream}
        return report.write_all(result, self.out, None, timing, extra=extra)


class _Socket:
    """``socket://HOST:PORT`` read as a port (pyserial's own handler discards what arrived
    before it returned from opening, which may be the header)."""

    def __init__(self, address: str, timeout: float, stopped: list[str]):
        host, _, port = address.removeprefix("socket://").rpartition(":")
        deadline = time.monotonic() + timeout
        while True:  # QEMU's -serial tcp:...,server=on listens a moment after it starts
            try:
                self.sock = socket.create_connection((host or "127.0.0.1", int(port)), 1.0)
                break
            except (OSError, ValueError) as exc:
                if time.monotonic() > deadline or isinstance(exc, ValueError) or stopped:
                    raise CochleaError(f"cannot connect to --port {address}: {exc}") from None
                time.sleep(0.1)
        self.sock.settimeout(0.05)

    def read(self, n: int) -> bytes:
        try:
            data = self.sock.recv(n)
        except TimeoutError:
            return b""
        if not data:
            raise EOFError
        return data

    def close(self) -> None:
        self.sock.close()


def _source(port: str, baud: int, timeout: float, stopped: list[str]):
    """A serial port, ``socket://HOST:PORT`` (QEMU's ``-serial tcp:...``), or a file of
    captured bytes."""
    path = Path(port)
    if path.is_file():
        return open(path, "rb"), True
    if port.startswith("socket://"):
        return _Socket(port, timeout, stopped), False
    try:
        return serial.Serial(port, baud, timeout=0.05), False
    except (serial.SerialException, OSError, ValueError) as exc:
        raise CochleaError(f"cannot open --port {port}: {exc}") from None


#: The signals that end the read (what came is written): Ctrl-C, SIGTERM, a hang-up.
SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def run(port: str, out: Path, baud: int, timeout: float, scenario: str | None) -> int:
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise CochleaError(f"--out {out} exists and is not an empty folder: choose a new one")
    stream = StreamRun(out, scenario)
    stopped: list[str] = []

    def on_signal(signum, frame):  # noqa: ARG001 - noted; the read loop ends at its next turn
        stopped.append(signal.Signals(signum).name)

    # Installed before the port opens and kept until the report is written: a signal ends the
    # read within a read's timeout (50 ms) and never cuts a row or the report in half.
    previous = {s: signal.signal(s, on_signal) for s in SIGNALS}
    try:
        return _read_and_write(stream, port, out, baud, timeout, stopped)
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


#: A board that keeps restarting (a reset loop) stops the read after this many restarts.
MAX_RESTARTS = 20


def _read_and_write(stream: StreamRun, port: str, out: Path, baud: int, timeout: float,
                    stopped: list[str]) -> int:
    """Read the stream into ``out``; a board that restarts mid-stream (a second header) ends
    the run there (incomplete) and each run after it goes to ``out/restart-N``. The reports
    are written once the read ends, so that writing one does not hold up the line."""
    source, is_file = _source(port, baud, timeout, stopped)
    runs: list[tuple[StreamRun, str | None]] = []
    try:
        while True:
            why = None if stream.restart_ended else _read(stream, source, is_file, timeout,
                                                          stopped)
            runs.append((stream, stream.disk_error or why or stream.end_problem))
            if stream.restart is None or stream.disk_error is not None:
                break
            if len(runs) > MAX_RESTARTS:
                print(f"{PROG}: the board restarted {len(runs) - 1} times: the read stops "
                      "there", file=sys.stderr)
                break
            try:
                stream = stream.following(out / f"restart-{len(runs)}")
            except HeaderError as exc:
                print(f"{PROG}: the board restarted with a header this host cannot write "
                      f"({exc}): the read stops there", file=sys.stderr)
                break
    finally:
        source.close()
    codes = [_write_run(run, why) for run, why in runs]
    if EXIT_REPORT_FAILED in codes:
        return EXIT_REPORT_FAILED
    if len(runs) > 1:
        return EXIT_INCOMPLETE  # the first run was cut by the restart
    return codes[-1]


def _read(stream: StreamRun, source, is_file: bool, timeout: float,
          stopped: list[str]) -> str | None:
    """Feed the stream until its end frame (None) or another end, said in words."""
    last = time.monotonic()
    while True:
        if stopped:
            return f"stopped by {stopped[0]} before the end frame"
        try:
            data = source.read(READ_SIZE)
        except EOFError:  # the peer closed the connection (QEMU quit)
            stream.decoder.finish()
            return "the connection closed before the end frame"
        if data:
            last = time.monotonic()
            if stream.feed(data):
                return None
        elif is_file:
            stream.decoder.finish()
            return "the capture ended before the end frame"
        elif time.monotonic() - last > timeout:
            return f"the line was silent for {timeout:g} s before the end frame"


def _write_run(stream: StreamRun, why: str | None) -> int:
    out = stream.out
    if stream.loop is None:
        print(f"{PROG}: no stream header came ({why or 'no frame'}; decoder "
              f"{stream.decoder.counts.as_dict()}): nothing written", file=sys.stderr)
        return EXIT_NO_HEADER
    try:
        # Values near the float64 limit (1e308 rows) overflow in the summary's sums: the
        # summary says inf, the console stays one line.
        with np.errstate(over="ignore", invalid="ignore"):
            data = stream.write(why)
    except ReportError as exc:  # the runs after this one are still written
        print(f"{PROG}: " + (f"{stream.disk_error}; " if stream.disk_error else "") + str(exc),
              file=sys.stderr)
        return EXIT_REPORT_FAILED
    if stream.disk_error is not None:
        print(f"{PROG}: {stream.disk_error}; wrote the report of {out} from them",
              file=sys.stderr)
        return EXIT_REPORT_FAILED
    print(f"{PROG}: wrote {out}: {stream.rows} rows (one every {stream.every} periods), "
          f"stop {data['stop']['rule']}"
          + (f"; incomplete: {why}" if why else "")
          + (f"; {stream.missing} missing" if stream.missing else ""))
    if why is not None:
        return EXIT_INCOMPLETE
    return data["stop"]["exit_code"]


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("--port", required=True,
                        help="the serial port of the firmware's USART3 (or a file of captured "
                             "bytes)")
    parser.add_argument("--out", type=Path, required=True, help="a new or empty folder")
    parser.add_argument("--baud", type=whole_argument, default=921600,
                        help="the stream's rate (the firmware's STM32_STREAM_BAUD)")
    parser.add_argument("--timeout", type=number_argument, default=10.0, metavar="S",
                        help="a line silent this long ends the read (s; default 10)")
    parser.add_argument("--scenario", default=None,
                        help="the scenario the firmware was built from (default: the header's)")
    args = parser.parse_args(argv)
    if not (args.timeout > 0 and math.isfinite(args.timeout)) or args.baud <= 0:
        print(f"{PROG}: --timeout and --baud must be positive", file=sys.stderr)
        return EXIT_USER_ERROR
    try:
        return run(args.port, args.out, args.baud, args.timeout, args.scenario)
    except HeaderError as exc:
        print(f"{PROG}: {exc}: nothing written", file=sys.stderr)
        return EXIT_NO_HEADER
    except ReportError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_REPORT_FAILED
    except CochleaError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    except OSError as exc:
        print(f"{PROG}: {exc.strerror or exc}: {getattr(exc, 'filename', '')}",
              file=sys.stderr)
        return EXIT_USER_ERROR


__all__ = ["main", "run", "StreamRun"]

if __name__ == "__main__":
    sys.exit(main())
