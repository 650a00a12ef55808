"""Issue 28, item 1: the STM32F4 firmware's row stream (embedded/ports/stm32f4/stream.c, USART3)
and ``cochlea-embedded-host``, which writes it as cochlea-run writes a run (log.bin,
log.columns.json, summary.json) through cochlea-run's own code. docs/embedded.md, "The row
stream".

The frame codec in pure Python first, against what a serial line does (a corrupted byte,
dropped bytes, a duplicated frame, a stream cut short, noise before the first sync); then the
host on captured and served streams (holes, rejected rows, a wrong schema, silence, SIGTERM);
then the firmware on QEMU's netduinoplus2 with its stream on a TCP socket (QEMU's third
``-serial``) read by the host, the rows checked against the firmware's own count and CRC-32."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from cochlea.runtime.row_stream import (
    END,
    HEADER,
    ROW,
    Decoder,
    chain_crc,
    encode,
    parse_text,
    row_payload,
)

ROOT = Path(__file__).resolve().parent.parent
H = 1e-3


def frames_of(stream: bytes, chunk: int | None = None) -> tuple[list, Decoder]:
    d = Decoder()
    out = []
    step = chunk or max(len(stream), 1)
    for i in range(0, len(stream), step):
        out += d.feed(stream[i:i + step])
    d.finish()
    return out, d


def sample(n_rows: int = 5, width: int = 4) -> list[bytes]:
    rng = np.random.default_rng(1)
    frames = [encode(HEADER, 0, b"scenario=x every=1 columns=a,b")]
    for k in range(n_rows):
        frames.append(encode(ROW, k + 1, row_payload(k, [k * H, *rng.normal(size=width - 1)])))
    frames.append(encode(END, n_rows + 1, b"rule=completed exit=0"))
    return frames


def test_frames_round_trip_whole_and_a_byte_at_a_time():
    frames = sample()
    for chunk in (None, 1, 7):
        got, d = frames_of(b"".join(frames), chunk)
        assert [f.kind for f in got] == [HEADER] + [ROW] * 5 + [END]
        assert [f.sequence for f in got] == list(range(7))
        assert parse_text(got[0].payload) == {"scenario": "x", "every": "1", "columns": "a,b"}
        assert got[3].payload == frames[3][10:-4]
        assert d.counts.as_dict() == {"frames": 7, "bad_crc": 0, "bad_length": 0,
                                      "skipped_bytes": 0, "lost_frames": 0, "duplicates": 0,
                                      "truncated_bytes": 0}


def test_a_corrupted_byte_loses_that_frame_only():
    frames = sample()
    bad = bytearray(frames[2])
    bad[20] ^= 0x10  # inside the row's values
    got, d = frames_of(b"".join(frames[:2]) + bytes(bad) + b"".join(frames[3:]))
    assert [f.sequence for f in got] == [0, 1, 3, 4, 5, 6]
    assert d.counts.bad_crc == 1 and d.counts.lost_frames == 1
    assert d.counts.skipped_bytes == len(bad)


def test_dropped_bytes_and_a_corrupted_length_resynchronise():
    frames = sample()
    torn = frames[2][:15] + frames[2][25:]  # ten bytes lost in the middle
    worse = bytearray(frames[4])
    worse[4:6] = (60000).to_bytes(2, "little")  # a length no frame has
    got, d = frames_of(b"".join(frames[:2]) + torn + frames[3] + bytes(worse)
                       + b"".join(frames[5:]))
    assert [f.sequence for f in got] == [0, 1, 3, 5, 6]
    assert d.counts.lost_frames == 2
    assert d.counts.bad_crc + d.counts.bad_length >= 2


def test_a_duplicated_frame_is_dropped_and_counted():
    frames = sample()
    got, d = frames_of(b"".join(frames[:3]) + frames[2] + b"".join(frames[3:]))
    assert [f.sequence for f in got] == list(range(7))
    assert d.counts.duplicates == 1 and d.counts.lost_frames == 0


def test_the_header_names_its_board():
    """The firmware's header begins with ``cochlea-<board>-stream``: the host's summary names
    that board (the OpenCR port's runs were said to come from an STM32F4)."""
    assert parse_text(b"cochlea-opencr-stream version=1 every=2 columns=t,a")["board"] == \
        "opencr"
    assert parse_text(b"cochlea-stm32f4-stream version=1 columns=t")["board"] == "stm32f4"
    assert "board" not in parse_text(b"something-else version=1")


def test_garbage_before_the_first_sync_and_a_truncated_end():
    frames = sample()
    noise = bytes(range(256)) + b"\xc5\x7eR\x00\xff\xff" + b"\xc5"  # a fake head, half a sync
    got, d = frames_of(noise + b"".join(frames)[:-9])
    assert [f.sequence for f in got] == [0, 1, 2, 3, 4, 5]
    assert d.counts.skipped_bytes >= 256
    assert d.counts.truncated_bytes == len(frames[-1]) - 9


def test_the_encoder_refuses_what_the_firmware_cannot_frame():
    with pytest.raises(ValueError):
        encode(ROW, 1, bytes(5000))
    with pytest.raises(ValueError):
        encode(ord("X"), 1, b"")


# ---- the host, on streams made here ---------------------------------------------------------


@pytest.fixture(scope="module")
def columns() -> list[str]:
    from cochlea.log_schema import LogUnit, raw_columns
    from cochlea.sim import load_scenario, unit_setups

    setups = unit_setups(load_scenario("serial_joint"), on_motors=True)
    return raw_columns([LogUnit.of_setup(u, u.controller.space) for u in setups],
                       current=True, true_state=False)


def header(columns, every=1, periods=40, scenario="serial_joint") -> bytes:
    return (f"cochlea-stm32f4-stream version=1 scenario={scenario} precision=float "
            f"period_ns=1000000 periods={periods} every={every} row_length={len(columns)} "
            f"schema_version=2 watchdog_misses=20 watchdog_errors=5 columns="
            + ",".join(columns)).encode()


def rows(columns, ks) -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    out = []
    for k in ks:
        row = rng.normal(scale=0.01, size=len(columns))
        row[0] = k * H
        out.append(row)
    return out


def end_text(n, crc, **more) -> bytes:
    fields = {"rule": "completed", "exit": 0, "rows": n, "kicks": n, "tick_overruns": 0,
              "deadline_misses": 0, "overruns": 0, "lateness_max_ns": 1000, "reads": n,
              "good_reads": n, "rx_overflows": 0, "failures": "none", "confirmed_off": "6/6",
              "stop_joint": -1, "stop_value_u": 0, "stop_limit_u": 0,
              "stop_time_us": int(n * H * 1e6), "rows_seen": n, "rows_dropped": 0,
              "rows_crc": crc, **more}
    return " ".join(f"{k}={v}" for k, v in fields.items()).encode()


def host(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_embedded_host", *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def header_and_rows(columns, sent: list[np.ndarray]) -> bytes:
    """A run's header (sequence 0) and its rows (sequence 1, 2, ...), as a firmware sends them."""
    return encode(HEADER, 0, header(columns)) + b"".join(
        encode(ROW, k + 1, row_payload(k, row)) for k, row in enumerate(sent))


def log_rows(out: Path) -> np.ndarray:
    spec = json.loads((out / "log.columns.json").read_text())
    return np.fromfile(out / "log.bin", "<f8").reshape(-1, spec["row_length"])


@pytest.mark.slow
def test_the_host_writes_cochlea_runs_files_and_counts_every_fault(tmp_path, columns):
    """40 periods, row 10 lost on the line (a corrupted byte), row 20 with a NaN time, row 30
    one value short, row 5 sent twice, noise in front: log.bin holds every period, NaN where
    a row is missing, the others bit for bit; summary.json counts each fault."""
    from cochlea.export.run_log import open_run

    data = rows(columns, range(40))
    frames, crc = [encode(HEADER, 0, header(columns))], 0
    for k, row in enumerate(data):
        payload = row_payload(k, row)
        if k == 20:
            payload = row_payload(k, [np.nan, *row[1:]])
        if k == 30:
            payload = row_payload(k, row[:-1])
        frame = encode(ROW, k + 1, payload)
        crc = chain_crc(crc, int.from_bytes(frame[-4:], "little"))
        if k == 10:
            frame = frame[:30] + bytes([frame[30] ^ 1]) + frame[31:]
        frames.append(frame)
        if k == 5:
            frames.append(frame)
    frames.append(encode(END, 41, end_text(40, crc)))
    capture = tmp_path / "stream.bin"
    capture.write_bytes(b"\x00\xc5\x13" * 50 + b"".join(frames))
    out = tmp_path / "run"
    run = host("--port", str(capture), "--out", str(out))
    assert run.returncode == 0, run.stderr
    assert run.stderr == ""
    got = log_rows(out)
    # Rows 10, 20 and 30 did not arrive whole: the first is a hole at its period, the
    # rejected two as well (the next good row fills back to its period).
    assert got.shape == (40, len(columns))
    good = [k for k in range(40) if k not in (10, 20, 30)]
    assert np.array_equal(got[good], np.array([data[k] for k in good]))
    for k in (10, 20, 30):
        assert got[k, 0] == k * H and np.isnan(got[k, 1:]).all()
    summary = json.loads((out / "summary.json").read_text())
    s = summary["stream"]
    assert s["complete"] and s["rows_received"] == 37 and s["rows_missing"] == 3
    assert s["rows_rejected"] == {"length": 1, "time": 1, "order": 0}
    assert s["decoder"]["bad_crc"] >= 1 and s["decoder"]["duplicates"] == 1
    assert s["decoder"]["lost_frames"] == 1 and s["decoder"]["skipped_bytes"] >= 150
    assert s["rows_crc_match"] is False  # the firmware sent rows the host did not keep
    assert summary["stop"] == {"rule": "completed", "time_s": 0.04, "detail": "",
                               "exit_code": 0}
    assert summary["periods"] == 40 and summary["rate_Hz"] == 1000.0
    assert summary["schema_version"] == 2 and summary["scenario"] == "serial_joint"
    assert summary["kernels"]["library"] == "compiled in: cochlea-stm32f4 (float)"
    # the same files cochlea-run leaves, readable by cochlea-mcap's and cochlea-view's loader
    assert {"log.bin", "log.columns.json", "log.csv", "summary.json"} <= \
        {p.name for p in out.iterdir()}
    log = open_run(out)
    assert log.summary["stream"]["every"] == 1


@pytest.mark.slow
def test_a_decimated_stream_keeps_its_rows_at_their_periods(tmp_path, columns):
    data = rows(columns, range(0, 60, 3))
    frames, crc = [encode(HEADER, 0, header(columns, every=3, periods=60))], 0
    for i, row in enumerate(data):
        frames.append(encode(ROW, i + 1, row_payload(3 * i, row)))
        crc = chain_crc(crc, int.from_bytes(frames[-1][-4:], "little"))
    frames.append(encode(END, len(data) + 1, end_text(60, crc)))
    capture = tmp_path / "stream.bin"
    capture.write_bytes(b"".join(frames))
    run = host("--port", str(capture), "--out", str(tmp_path / "run"))
    assert run.returncode == 0, run.stderr
    assert np.array_equal(log_rows(tmp_path / "run"), np.array(data))
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["stream"]["rows_crc_match"] is True
    assert summary["stream"]["every"] == 3 and summary["stream"]["log_rate_Hz"] == 1000 / 3
    # periods, rate and duration are the log's (20 rows, one every 3 ms), as the loaders
    # check them; the firmware's periods and control rate are in stream
    assert summary["periods"] == 20 and summary["rate_Hz"] == pytest.approx(1000 / 3)
    assert summary["duration_s"] == pytest.approx(0.06)
    assert summary["stream"]["firmware_periods"] == 60
    assert summary["stream"]["control_rate_Hz"] == 1000


@pytest.mark.slow
def test_a_wrong_schema_or_no_header_is_one_line_and_nothing_written(tmp_path, columns):
    capture = tmp_path / "stream.bin"
    capture.write_bytes(encode(HEADER, 0, header(columns[:-1] + ["other_A"])))
    run = host("--port", str(capture), "--out", str(tmp_path / "run"))
    assert run.returncode == 4
    assert len(run.stderr.strip().splitlines()) == 1 and "Traceback" not in run.stderr
    assert "another scenario or schema" in run.stderr
    assert not (tmp_path / "run" / "log.bin").exists()
    capture.write_bytes(b"noise" * 100)
    run = host("--port", str(capture), "--out", str(tmp_path / "run2"))
    assert run.returncode == 4 and "no stream header came" in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1
    capture.write_bytes(encode(HEADER, 0, header(columns, scenario="no_such_scenario")))
    run = host("--port", str(capture), "--out", str(tmp_path / "run3"))
    assert run.returncode == 4 and "no_such_scenario" in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1 and not (tmp_path / "run3").exists()
    run = host("--port", str(capture), "--out", str(tmp_path / "x"), "--timeout", "-1")
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("field, value", [
    ("every", 10**30), ("periods", 2**31), ("period_ns", 10**30), ("period_ns", 10),
    ("watchdog_misses", -1), ("watchdog_misses", 10**30)])
def test_a_header_its_own_readers_would_refuse_is_refused(tmp_path, columns, capsys, field,
                                                          value):
    """Header values the host accepted and its readers then refused (every = 10**30: 'summary
    .json damaged' from cochlea-mcap; period_ns = 10**30: times beyond a ROS stamp) or that
    no firmware's C int holds (watchdog_misses -1, 10**30; a QEMU build's 100 000 is
    accepted): one line, exit 4, nothing written."""
    from cochlea.apps import cochlea_embedded_host

    defaults = {"every": "1", "periods": "40", "period_ns": "1000000", "watchdog_misses": "20"}
    text = header(columns).replace(f" {field}={defaults[field]} ".encode(),
                                   f" {field}={value} ".encode())
    assert f"{field}={value}".encode() in text
    capture = tmp_path / "stream.bin"
    capture.write_bytes(encode(HEADER, 0, text) + encode(END, 1, end_text(0, 0)))
    out = tmp_path / "run"
    assert cochlea_embedded_host.main(["--port", str(capture), "--out", str(out)]) == 4
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and f"field {field} = " in err, err
    assert not out.exists()


@pytest.mark.slow
def test_a_firmware_that_refused_to_start_leaves_an_empty_log_and_its_exit_code(tmp_path,
                                                                                   columns):
    """A refusal before the bus starts (or a failed start) sends the header and the end
    frame, no row: the host writes the empty log and exits with the firmware's code, 5."""
    capture = tmp_path / "stream.bin"
    capture.write_bytes(encode(HEADER, 0, header(columns))
                        + encode(END, 1, end_text(0, 0, rule="none", exit=5, stop_time_us=0)))
    run = host("--port", str(capture), "--out", str(tmp_path / "run"))
    assert run.returncode == 5, run.stderr
    assert log_rows(tmp_path / "run").shape == (0, len(columns))
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["stop"]["rule"] == "none" and summary["stop"]["exit_code"] == 5
    assert summary["stream"]["complete"] and not summary["converged"]


@pytest.mark.slow
@pytest.mark.parametrize("field", [{"exit": "nan"}, {"rows": "1.5"}, {"exit": "999"},
                                   {"stop_time_us": "1e309"}, {"rows_crc": "x=y"},
                                   {"stop_joint": "-2"}, {"reads": "9" * 30}])
def test_an_end_frame_that_cannot_be_read_keeps_the_rows_and_says_so(tmp_path, columns,
                                                                      field, capsys):
    """An end frame whose integers are not integers (a firmware from another checkout, a
    CRC matched by chance) ended in a traceback with the report lost: the rows are written,
    the run is incomplete (exit 3), the reason names the field."""
    from cochlea.apps import cochlea_embedded_host

    data = rows(columns, range(3))
    capture = tmp_path / "stream.bin"
    capture.write_bytes(encode(HEADER, 0, header(columns))
                        + b"".join(encode(ROW, k + 1, row_payload(k, row))
                                   for k, row in enumerate(data))
                        + encode(END, 4, end_text(3, 0, **field)))
    out = tmp_path / "run"
    code = cochlea_embedded_host.main(["--port", str(capture), "--out", str(out)])
    said = capsys.readouterr()
    assert code == 3 and said.err == ""
    (key, value), = field.items()
    assert f"incomplete: the end frame's {key} is {value[:40]!r}, not an integer" in said.out
    assert np.array_equal(log_rows(out), np.array(data))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stop"]["rule"] == "stream-incomplete"
    assert summary["stream"]["incomplete_reason"].startswith(f"the end frame's {key} ")


@pytest.mark.slow
def test_a_report_that_cannot_be_written_is_one_line_and_exit_18(tmp_path, columns, monkeypatch,
                                                                   capsys):
    """The figures fail to write (as on a full disk): cochlea-run's ReportError, said in one
    line naming what was lost and kept, exit 18; log.bin and summary.json are kept."""
    from cochlea.apps import cochlea_embedded_host, report

    def full_disk(*_):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(report, "figures", full_disk)
    capture = tmp_path / "stream.bin"
    capture.write_bytes(encode(HEADER, 0, header(columns))
                        + b"".join(encode(ROW, k + 1, row_payload(k, row))
                                   for k, row in enumerate(rows(columns, range(3))))
                        + encode(END, 4, end_text(3, 0)))
    code = cochlea_embedded_host.main(["--port", str(capture), "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == 18 and len(err.strip().splitlines()) == 1, err
    assert "lost figures" in err and "log.bin" in err
    assert (tmp_path / "run" / "summary.json").exists()


@pytest.mark.slow
def test_rows_no_figure_can_draw_lose_the_figures_only(tmp_path, columns, capsys):
    """Rows of 1e308 (a valid header, then values matplotlib cannot scale: its ValueError
    'arange: cannot compute length') ended in a traceback and no summary.json: now the
    figures alone are lost, summary.json is written and says so (report_lost), and the exit
    (18) says so in one line."""
    from cochlea.apps import cochlea_embedded_host

    sent = [np.full(len(columns), 1e308) for _ in range(10)]
    for k, row in enumerate(sent):
        row[0] = k * H
    capture = tmp_path / "stream.bin"
    capture.write_bytes(header_and_rows(columns, sent) + encode(END, 11, end_text(10, 0)))
    out = tmp_path / "run"
    code = cochlea_embedded_host.main(["--port", str(capture), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 18 and len(err.strip().splitlines()) == 1, err
    assert "lost figures" in err and "a figure could not be drawn" in err
    assert "Free some space" not in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["report_lost"] == ["figures"]
    assert np.array_equal(log_rows(out), np.array(sent))


def serve(payload: bytes) -> tuple[int, threading.Event]:
    """A TCP server that sends ``payload`` to its one client and then holds the line open
    and silent until ``done`` is set."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    done = threading.Event()

    def talk():
        conn, _ = server.accept()
        conn.sendall(payload)
        done.wait(60)
        conn.close()
        server.close()

    threading.Thread(target=talk, daemon=True).start()
    return server.getsockname()[1], done


@pytest.mark.slow
@pytest.mark.parametrize("how", ["silence", "sigterm", "sigint"])
def test_silence_or_sigterm_writes_what_came_marked_incomplete(tmp_path, columns, how):
    data = rows(columns, range(12))
    stream = encode(HEADER, 0, header(columns)) + b"".join(
        encode(ROW, k + 1, row_payload(k, row)) for k, row in enumerate(data))
    port, done = serve(stream)
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "cochlea.apps.cochlea_embedded_host", "--port",
           f"socket://127.0.0.1:{port}", "--out", str(out),
           "--timeout", "3" if how == "silence" else "60"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        if how != "silence":
            deadline = time.monotonic() + 60
            while not (out / "log.bin").exists() or (out / "log.bin").stat().st_size < \
                    12 * 8 * len(columns):
                assert time.monotonic() < deadline and proc.poll() is None
                time.sleep(0.1)
            proc.send_signal(signal.SIGTERM if how == "sigterm" else signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        done.set()
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 3, stderr
    assert "Traceback" not in stderr
    assert np.array_equal(log_rows(out), np.array(data))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stream"]["complete"] is False
    assert summary["stop"]["rule"] == "stream-incomplete" and not summary["converged"]
    reason = summary["stream"]["incomplete_reason"]
    assert {"silence": "silent for 3 s", "sigterm": "SIGTERM", "sigint": "SIGINT"}[how] in reason
    assert "incomplete" in stdout


# ---- the firmware on QEMU, its stream read by the host --------------------------------------

#: Every third row (100 of the 300 periods), the test build's watchdogs and timeouts.
EVERY = 3


@pytest.fixture(scope="module")
def stream_firmware(tmp_path_factory) -> Path:
    from tests.test_embedded_qemu import ensure_tools
    from tests.test_embedded_stm32 import BUILD_OPTIONS

    ensure_tools()
    build = tmp_path_factory.mktemp("stm32-stream-build")
    run = subprocess.run(["make", "--no-print-directory", "stm32-firmware", f"BUILD={build}",
                          *BUILD_OPTIONS, f"STM32_STREAM_EVERY={EVERY}"], cwd=ROOT,
                         capture_output=True, text=True, timeout=900)
    if run.returncode != 0:
        pytest.fail(f"make stm32-firmware failed:\n{run.stderr[-4000:]}", pytrace=False)
    assert "warning" not in run.stderr.lower(), run.stderr[-4000:]
    return build / "stm32f4"


@pytest.mark.hil
def test_the_firmwares_rows_reach_the_host_whole(stream_firmware, tmp_path):
    """serial_joint's 300 periods on netduinoplus2 (its plant held still, as in
    test_embedded_stm32), USART3 on a TCP socket that QEMU waits on until the host connects:
    the host writes every third row, exactly what the firmware sent (its count and CRC-32 in
    the end frame), none dropped, and the summary of a completed run."""
    from cochlea.dynamixel.drives import joint_drives
    from cochlea.export.run_log import open_run
    from tests.test_dynamixel_hil import emulator
    from tests.test_embedded_stm32 import EMULATOR_SETTLE_S, PERIODS, SCENARIO, fields

    ids = [d.id for d in joint_drives("serial")]
    still = [a for i in ids for a in ("--true-fit", f"{i}:1e-6,0")]
    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    console, out = tmp_path / "console.txt", tmp_path / "run"
    with emulator("serial", SCENARIO, tmp_path / "emulator.log", *still) as pty:
        time.sleep(EMULATOR_SETTLE_S)
        qemu = subprocess.Popen(
            ["qemu-system-arm", "-M", "netduinoplus2", "-nographic", "-monitor", "none",
             "-serial", pty, "-serial", f"file:{console}",
             "-serial", f"tcp:127.0.0.1:{port},server=on,wait=on",
             "-kernel", str(stream_firmware / "float" / "cochlea-stm32f4.elf")],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        try:
            run = host("--port", f"socket://127.0.0.1:{port}", "--out", str(out),
                       "--timeout", "60")
        finally:
            qemu.terminate()
            qemu.communicate(timeout=20)
    assert run.returncode == 0, run.stdout + run.stderr
    end = fields(console.read_text().replace("\r", "").splitlines()[-1])
    assert end["rule"] == "completed" and end["rows"] == str(PERIODS)
    assert (end["rows_seen"], end["rows_sent"], end["rows_dropped"]) == (
        str(PERIODS), str(PERIODS // EVERY), "0")

    got = log_rows(out)
    assert got.shape[0] == PERIODS // EVERY
    assert np.array_equal(got[:, 0], np.arange(0, PERIODS, EVERY) * H)
    crc = 0  # the row frames' CRCs chained (header 0, rows 1..100): the firmware's rows_crc
    for i, row in enumerate(got):
        crc = chain_crc(crc, int.from_bytes(encode(ROW, i + 1, row_payload(EVERY * i, row))[-4:],
                                            "little"))
    assert crc == int(end["rows_crc"])  # the firmware's own rows, bit for bit
    summary = json.loads((out / "summary.json").read_text())
    s = summary["stream"]
    assert s["complete"] and s["rows_crc_match"] and s["rows_missing"] == 0
    assert s["decoder"]["bad_crc"] == 0 and s["decoder"]["lost_frames"] == 0
    assert s["firmware"]["rows_dropped"] == 0 and s["every"] == EVERY
    assert summary["stop"]["rule"] == "completed" and summary["periods"] == PERIODS // EVERY
    assert s["firmware_periods"] == PERIODS and summary["duration_s"] == pytest.approx(0.3)
    assert summary["timing"]["bus"]["shutdown"] == "confirmed 6/6"
    assert summary["timing"]["overruns"] == int(end["overruns"])
    # The controller commanded currents (tau) every streamed period, and the drives' measured
    # currents are in the rows (the current columns the host's schema expects).
    spec = json.loads((out / "log.columns.json").read_text())
    tau = [i for i, c in enumerate(spec["columns"]) if ".tau." in c]
    assert len(tau) == 6 and np.count_nonzero(got[1:, tau]) > 0
    assert sum(".current." in c for c in spec["columns"]) == 6
    assert open_run(out).summary["scenario"] == SCENARIO
    # cochlea-mcap and cochlea-view take the folder as they take cochlea-run's
    for tool, args in (("cochlea_mcap", ["--out", str(tmp_path / "run.mcap")]),
                       ("cochlea_view", ["--html-out", str(tmp_path / "run.html"), "--no-open"])):
        done = subprocess.run([sys.executable, "-m", f"cochlea.apps.{tool}", str(out), *args],
                              cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0 and "wrote" in done.stdout, done.stderr


@pytest.mark.slow
def test_a_refusal_before_the_bus_streams_its_header_and_end(tmp_path):
    """parallel_joint (a slider: the firmware refuses before the bus starts): the stream, into
    a file here, still carries the header and the end frame, and the host writes the empty
    run with the firmware's exit code 5 and its refusal's rule."""
    from tests.test_embedded_qemu import ensure_tools
    from tests.test_embedded_stm32 import console_lines, ended

    ensure_tools()
    build = tmp_path / "build"
    made = subprocess.run(["make", "--no-print-directory", "-s", "stm32-firmware",
                           f"BUILD={build}", "STM32_SCENARIO=parallel_joint"], cwd=ROOT,
                          capture_output=True, text=True, timeout=900)
    assert made.returncode == 0, made.stderr[-3000:]
    console, captured = tmp_path / "console.txt", tmp_path / "stream.bin"
    qemu = subprocess.Popen(
        ["qemu-system-arm", "-M", "netduinoplus2", "-nographic", "-monitor", "none",
         "-serial", f"file:{tmp_path / 'bus.bin'}", "-serial", f"file:{console}",
         "-serial", f"file:{captured}",
         "-kernel", str(build / "stm32f4" / "float" / "cochlea-stm32f4.elf")],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        start = time.monotonic()
        while time.monotonic() - start < 30 and not (
                console.exists() and ended(console.read_bytes().decode())):
            time.sleep(0.05)
    finally:
        qemu.terminate()
        qemu.wait(timeout=20)
    assert console_lines(console.read_bytes().decode())[1].startswith("refused what=homing")
    run = host("--port", str(captured), "--out", str(tmp_path / "run"))
    assert run.returncode == 5, run.stderr
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["scenario"] == "parallel_joint" and summary["periods"] == 0
    assert summary["stop"]["rule"] == "none" and summary["stop"]["exit_code"] == 5
    assert summary["stream"]["complete"] and summary["stream"]["firmware"]["rows_seen"] == 0
    assert summary["stream"]["header"]["every"] == "10"  # the default decimation


@pytest.mark.slow
def test_log_bin_that_cannot_take_more_rows_keeps_whole_rows_and_exits_18(tmp_path, columns):
    """A full disk while the rows stream (here a file-size limit, EFBIG): log.bin keeps the
    whole rows that fit, the read stops, the report is written from them as far as it can be,
    and the host says so in one line with exit 18. It used to end with exit 2 and no report."""
    import resource

    sent = rows(columns, range(40))
    capture = tmp_path / "stream.bin"
    capture.write_bytes(header_and_rows(columns, sent) + encode(END, 41, end_text(40, 0)))
    row_bytes = 8 * len(columns)
    limit = 12 * row_bytes + row_bytes // 2  # the 13th row is torn by the limit

    def limited():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past it fails with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_embedded_host", "--port",
                           str(capture), "--out", str(out)], cwd=ROOT, capture_output=True,
                          text=True, timeout=180, preexec_fn=limited)
    assert done.returncode == 18, done.stderr
    assert "Traceback" not in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert "log.bin could not be written" in done.stderr and "first 12 rows" in done.stderr
    kept = log_rows(out)
    assert kept.shape[0] == 12
    np.testing.assert_array_equal(kept, np.array(sent[:12]))


@pytest.mark.slow
def test_a_board_that_restarts_mid_stream_leaves_each_run_in_its_own_folder(tmp_path, columns):
    """A reset or power cycle mid-run: the board sends its header again, numbered from 0. The
    first run ends there, incomplete, in DIR; the restarted one goes to DIR/restart-1 with its
    own end frame; exit 3. The second header used to be ignored, its rows rejected as out of
    order and its end frame taken as the first run's."""
    first, second = rows(columns, range(10)), rows(columns, range(5))
    capture = tmp_path / "stream.bin"
    capture.write_bytes(header_and_rows(columns, first) + header_and_rows(columns, second)
                        + encode(END, 6, end_text(5, 0)))
    out = tmp_path / "run"
    done = host("--port", str(capture), "--out", str(out))
    assert done.returncode == 3, done.stderr
    assert "Traceback" not in done.stderr
    np.testing.assert_array_equal(log_rows(out), np.array(first))
    np.testing.assert_array_equal(log_rows(out / "restart-1"), np.array(second))
    cut = json.loads((out / "summary.json").read_text())
    assert cut["stream"]["incomplete_reason"].startswith("the board restarted")
    assert cut["stop"]["rule"] == "stream-incomplete"
    restarted = json.loads((out / "restart-1" / "summary.json").read_text())
    assert restarted["stream"]["complete"] and restarted["stop"]["rule"] == "completed"
    assert done.stdout.count("wrote ") == 2


@pytest.mark.slow
def test_a_header_repeated_before_any_row_is_not_a_restart(tmp_path, columns):
    """The same header twice before the first row (a board reset during its start-up, or a
    repeat on the line) is one run: nothing was lost."""
    sent = rows(columns, range(4))
    capture = tmp_path / "stream.bin"
    capture.write_bytes(encode(HEADER, 0, header(columns)) + header_and_rows(columns, sent)
                        + encode(END, 5, end_text(4, 0)))
    out = tmp_path / "run"
    done = host("--port", str(capture), "--out", str(out))
    assert done.returncode == 0, done.stderr
    np.testing.assert_array_equal(log_rows(out), np.array(sent))
    assert not (out / "restart-1").exists()
