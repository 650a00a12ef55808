"""``build/cochlea-embedded`` in long runs (issue 13, docs/embedded.md "Memory in long runs"):
its memory does not grow with the run's length, its summary's timing percentiles are numpy's
on its own log.bin, a log that cannot be written (a failed write, a hung writer, a file-size
limit) ends in the safe stop with the log-failure rule (exit 17) and the log kept up to the
failure, and a disk too small for the run's log is refused before anything moves.

The failures are injected by a test build (``-DCOCHLEA_TEST_HOOKS``, environment variables
read by the writer); the product build has none of it (checked below), and the file-size limit
case runs on the product build with a real failing write."""

from __future__ import annotations

import json
import os
import re
import resource
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from cochlea.runtime.supervisor import STOP_CODES
from tests.test_dynamixel_hil import assert_log_complete, last_commands
from tests.test_embedded_program import ROOT, emulator, read_csv

pytestmark = pytest.mark.hil

HOOKED = ROOT / "build" / "test-hooks" / "cochlea-embedded"
SCENARIO = ("serial", "serial_joint")
#: These runs are about the log, not tracking: they ride through an emulator that falls behind
#: on a loaded machine (its late replies cost failed reads and late periods, each still logged)
#: with the most of both the watchdogs allow, rather than stop (test_embedded_program.py's runs
#: stop and are repeated).
TOLERANT = ("--watchdog-misses", "1000", "--watchdog-errors", "1000")
#: The log's ring in the program (RING_SECONDS) at the scenario's 1 kHz, in periods.
RING_PERIODS = 4000
#: The resolution stated for a percentile that stands for its histogram bin (HIST_BINS
#: logarithmic bins over 1e-9..1e3 s): half a bin, relative.
BIN_RESOLUTION = 0.5 * np.log(1e3 / 1e-9) / 65536


@pytest.fixture(scope="module")
def hooked() -> Path:
    """The test build: the same sources and flags through the Makefile, with the hooks."""
    cc = os.environ.get("CC", "cc")
    done = subprocess.run(["make", "--no-print-directory", "BUILD=build/test-hooks",
                           f"CC={cc} -DCOCHLEA_TEST_HOOKS", str(HOOKED.relative_to(ROOT))],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "warning" not in done.stderr
    return HOOKED


def peak_kib(pid: int) -> int:
    """The process's resident high-water mark so far (``VmHWM``, KiB; 0 once it has exited).
    Its own: ``VmHWM`` starts afresh at exec, where the child's rusage would count the
    Python process it was forked from."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def run_on_emulator(binary: Path, out: Path, duration: float, *args: str,
                    env: dict | None = None, preexec=None) -> tuple[int, str, int, Path]:
    """``binary`` for ``duration`` s of serial_task on a fresh emulator: exit code,
    stderr, peak resident KiB (polled every 10 ms until it exits) and the emulator's log."""
    log = out.parent / f"{out.name}.emulator.log"
    with emulator(*SCENARIO, log) as port:
        with open(out.parent / f"{out.name}.stderr", "w+") as err:
            proc = subprocess.Popen(
                [str(binary), "--scenario", SCENARIO[1], "--port", port, "--duration",
                 str(duration), "--out", str(out), *TOLERANT, *args],
                stdout=subprocess.DEVNULL, stderr=err, env={**os.environ, **(env or {})},
                preexec_fn=preexec)
            peak = 0
            while proc.poll() is None:
                peak = max(peak, peak_kib(proc.pid))
                time.sleep(0.01)
            err.seek(0)
            stderr = err.read()
    return proc.returncode, stderr, peak, log


def failing_run(binary: Path, tmp_path: Path, name: str, duration: float, **kw):
    """A run whose log fails (exit 17), on a fresh emulator's socket, once."""
    out = tmp_path / name
    code, stderr, _, log = run_on_emulator(binary, out, duration, **kw)
    return out, code, stderr, log


def complete_run(binary: Path, tmp_path: Path, name: str, duration: float):
    """A run that completes, on a fresh emulator's socket, once (on the pseudo-terminal a
    loaded machine delayed replies long enough for the watchdog, or for the reads after them
    to show a joint catching up faster than its velocity limit, and these runs were
    repeated: issue 30)."""
    out = tmp_path / name
    code, stderr, peak, log = run_on_emulator(binary, out, duration)
    assert code == 0, stderr
    return out, peak, log


def summary_of(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def log_rows(out: Path) -> np.ndarray:
    length = json.loads((out / "log.columns.json").read_text())["row_length"]
    return np.fromfile(out / "log.bin").reshape(-1, length)


def log_columns(out: Path) -> list[str]:
    return json.loads((out / "log.columns.json").read_text())["columns"]


def numpy_timing(rows: np.ndarray, columns: list[str]) -> dict:
    """summary.json's timing numbers as numpy computes them from log.bin (finite values; the
    first period has no wall period); ``columns``: log.columns.json's names."""
    def finite(c):
        return c[np.isfinite(c)]

    wall, compute, backend = (rows[:, columns.index(c)] for c in ("wall_period_s", "compute_s",
                                                                  "backend_io_s"))
    wall, compute, backend = finite(wall[1:]), finite(compute), finite(backend)
    return {"period_mean": wall.mean(), "period_std": wall.std(),
            "period_p50": np.percentile(wall, 50), "period_p99": np.percentile(wall, 99),
            "period_max": wall.max(), "compute_p50": np.percentile(compute, 50),
            "compute_p99": np.percentile(compute, 99), "compute_max": compute.max(),
            "backend_mean": backend.mean(), "backend_p99": np.percentile(backend, 99)}


def assert_safe_stop(log: Path) -> None:
    """The emulator's last commands: zero current, then torque off, to all six motors, twice."""
    assert last_commands(log)[-24:] == [("sync-write", a, v)
                                        for a, v in [(102, 0)] * 6 + [(64, 0)] * 6] * 2


@pytest.fixture(scope="module")
def short_and_long(program, tmp_path_factory):
    """serial_joint for 5 s and for 12 s (both longer than the 4 s ring): the output folders
    and peak resident memory of each."""
    tmp = tmp_path_factory.mktemp("flat")
    return {seconds: complete_run(program, tmp, f"run{seconds}", seconds)[:2]
            for seconds in (5.0, 12.0)}


def test_memory_does_not_grow_with_the_runs_length(short_and_long):
    (short, short_peak), (long, long_peak) = short_and_long[5.0], short_and_long[12.0]
    assert summary_of(short)["periods"] == 5000 and summary_of(long)["periods"] == 12000
    # 2.4 times the log (the whole-run buffer this replaced took 0.33 MB a second, locked,
    # on a peak of 5.3 MB now) ...
    assert 5 * (long / "log.bin").stat().st_size == 12 * (short / "log.bin").stat().st_size
    # ... in the same memory: the ring, the report's chunk and histogram are fixed in size.
    assert short_peak > 0 and long_peak <= 1.2 * short_peak, (short_peak, long_peak)


def test_the_report_read_back_from_log_bin_is_the_logs(short_and_long):
    for out, _ in short_and_long.values():
        summary = summary_of(out)
        assert_log_complete(out, summary)
        rows, columns = log_rows(out), log_columns(out)
        # The CSV is log.bin's rows, value for value (to its 10 significant digits): the
        # timing and the measured current (UNIT.current.JOINT_A in both: one schema).
        head, csv = read_csv(out / "log.csv")
        assert np.allclose(csv[:, 0], rows[:, 0], rtol=1e-9, atol=1e-12)
        current = [c for c in columns if ".current." in c]
        assert len(current) == 6
        pairs = [(c, c) for c in ("start_lateness_s", "wall_period_s", "compute_s",
                                  "backend_io_s")]
        pairs += [(c, c) for c in current]
        for binary, text in pairs:
            assert np.allclose(csv[:, head.index(text)], rows[:, columns.index(binary)],
                               rtol=1e-9, atol=1e-15, equal_nan=True), binary
        # Mean, spread, maxima exactly up to summation order; the percentiles exactly, since
        # every bin they fall in was gathered whole.
        timing = summary["timing"]
        for key, value in numpy_timing(rows, columns).items():
            assert timing[key] == pytest.approx(value, rel=1e-12), key
        # The convergence numbers are the CSV's, by cochlea-run's rule.
        for unit, entry in summary["units"].items():
            for coord, c in entry["tracked"].items():
                error = csv[:, head.index(f"{unit}.error.{coord}_{c['unit']}")]
                tail = error[int(len(error) * 0.8):]
                assert c["initial_abs_error"] == pytest.approx(abs(error[0]), rel=1e-9)
                assert c["final_rms_error"] == pytest.approx(np.sqrt(np.mean(tail ** 2)),
                                                             rel=1e-6)


def test_a_failed_write_stops_the_run_safely_and_keeps_the_log_up_to_it(hooked, tmp_path):
    """The writer's write fails (ENOSPC) once 1500 rows are in log.bin; the report is made with
    no gathering, so its percentiles are the histogram's, within the stated resolution."""
    out, code, stderr, log = failing_run(
        hooked, tmp_path, "full", 10.0, env={"COCHLEA_TEST_LOG_FAIL_AFTER": "1500",
                                             "COCHLEA_TEST_GATHER_MAX": "0"})
    assert code == STOP_CODES["log-failure"] == 17, stderr
    line = [s for s in stderr.splitlines() if "stopped by rule" in s]
    assert len(line) == 1 and "stopped by rule log-failure" in line[0], stderr
    assert os.strerror(28) in line[0] and "log.bin holds the first 1500 of" in line[0]
    assert line[0].endswith("drives disabled, log kept up to the failure")
    assert_safe_stop(log)
    summary = summary_of(out)
    assert summary["stop"]["rule"] == "log-failure" and summary["stop"]["exit_code"] == 17
    assert summary["periods"] == 1500 and summary["stop"]["time_s"] < 9.9  # long before the end
    assert_log_complete(out, summary)  # log.csv and log.bin: the 1500 rows, whole
    rows = log_rows(out)
    assert np.array_equal(rows[:, 0], np.arange(1500) * 1e-3)
    for key, value in numpy_timing(rows, log_columns(out)).items():
        assert summary["timing"][key] == pytest.approx(value, rel=BIN_RESOLUTION * 1.01), key


def test_a_writer_a_whole_ring_behind_stops_the_run(hooked, tmp_path):
    """The writer hangs after 500 rows (a disk that stops answering): the loop fills the ring
    and stops at the period that would overwrite row 500, never before and never after."""
    out, code, stderr, log = failing_run(hooked, tmp_path, "hung", 10.0,
                                         env={"COCHLEA_TEST_LOG_STALL_AFTER": "500"})
    assert code == 17, stderr
    assert (f"the log writer fell {RING_PERIODS} periods (4 s) behind the loop; log.bin holds "
            f"the first 500 of {500 + RING_PERIODS} periods") in stderr
    assert_safe_stop(log)
    summary = summary_of(out)
    assert summary["periods"] == 500 and summary["stop"]["rule"] == "log-failure"
    assert summary["stop"]["time_s"] == pytest.approx((500 + RING_PERIODS) * 1e-3)
    assert_log_complete(out, summary)


def test_a_file_size_limit_is_a_log_failure_in_the_product_build(program, tmp_path):
    """A real failing write: log.bin may not grow past 600 KiB (RLIMIT_FSIZE, SIGXFSZ ignored:
    the write fails with EFBIG, as on a full disk it fails with ENOSPC)."""
    limit = 600 * 1024

    def limited():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    out, code, stderr, log = failing_run(program, tmp_path, "limited", 10.0, preexec=limited)
    assert code == 17, stderr
    assert os.strerror(27) in stderr and "stopped by rule log-failure" in stderr
    assert_safe_stop(log)
    summary = summary_of(out)
    rows = log_rows(out)  # whole rows only: a row cut by the limit is cut off
    assert summary["periods"] == len(rows) > 0
    assert (out / "log.bin").stat().st_size <= limit
    assert f"log.bin holds the first {len(rows)} of" in summary["stop"]["detail"]


def test_a_disk_too_small_for_the_log_is_refused_before_anything_moves(hooked, tmp_path,
                                                                       short_and_long):
    out = tmp_path / "new" / "run"

    def attempt(free: float, duration: float, folder: Path = out):
        return subprocess.run([str(hooked), "--scenario", SCENARIO[1], "--port",
                               "/dev/ttyUSB-none", "--out", str(folder), "--duration",
                               str(duration)], capture_output=True, text=True, timeout=30,
                              env={**os.environ, "COCHLEA_TEST_FREE_BYTES": str(free)})

    done = attempt(1e6, 60)
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.splitlines()) == 1
    assert f"--out {out}: the run's log needs about" in done.stderr
    assert "976.6 KiB are free" in done.stderr and "shorter --duration" in done.stderr
    assert not (tmp_path / "new").exists()  # nothing created, the port never opened
    # Room enough: on to the port, which is missing.
    done = attempt(1e12, 60)
    assert done.returncode == 5 and "cannot open the serial port" in done.stderr
    # The estimate covers what a run writes, without being wildly above it.
    real, _ = short_and_long[5.0]
    written = sum((real / name).stat().st_size for name in ("log.bin", "log.csv"))
    need = re.search(r"needs about ([\d.]+) (KiB|MiB)",
                     attempt(1, 5.0, tmp_path / "other").stderr)
    need = float(need[1]) * {"KiB": 2**10, "MiB": 2**20}[need[2]]
    assert written <= need <= 2 * written + 2**21


def test_the_product_build_has_no_test_hooks(program, hooked):
    assert b"COCHLEA_TEST_" in hooked.read_bytes()
    assert b"COCHLEA_TEST_" not in program.read_bytes()
    usage = subprocess.run([str(program), "--help"], capture_output=True, text=True).stdout
    assert "17 log-failure" in usage and "memory does not grow" in usage
