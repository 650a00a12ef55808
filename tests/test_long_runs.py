"""Long runs: memory flat in the run's length (a ring of periods streamed to log.bin, the
report read back in chunks), and a loop that stops safely when its log cannot be written."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cochlea.apps import report
from cochlea.errors import CochleaError
from cochlea.runtime import STOP_CODES, log_writer
from cochlea.runtime import loop as loop_module
from cochlea.runtime.log_writer import LogWriter
from cochlea.sim import result as result_module
from tests.test_runtime import make_loop

BENCH = Path(__file__).resolve().parents[1] / "bench" / "memory_long_run.py"


@pytest.fixture
def small_chunks(monkeypatch):
    """A ring of 20 periods and chunks of tens of rows, so short runs wrap and chunk often."""
    monkeypatch.setattr(loop_module, "RING_SECONDS", 0.02)
    monkeypatch.setattr(loop_module, "READ_CHUNK", 37)
    monkeypatch.setattr(result_module, "CHUNK_ROWS", 53)


def _old_timing(rows: np.ndarray, first: int, h: float) -> dict:
    """The whole-run timing summary as the loop computed it before it streamed its log."""
    t = rows[:, first:first + 4]
    wall, compute, backend = t[1:, 1], t[:, 2], t[:, 3]
    finish = rows[:, 0] + t[:, 0] + compute
    misses = int(np.sum(finish > np.arange(1, len(rows) + 1) * h))
    return {"period_mean": wall.mean(), "period_std": wall.std(),
            "period_p50": np.percentile(wall, 50), "period_p99": np.percentile(wall, 99),
            "period_max": wall.max(), "deadline_misses": misses,
            "compute_p50": np.percentile(compute, 50), "compute_p99": np.percentile(compute, 99),
            "backend_mean": backend.mean(), "backend_p99": np.percentile(backend, 99)}


@pytest.mark.parametrize("name", ["serial_task", "parallel_joint"])
@pytest.mark.slow
def test_streamed_log_and_report_equal_the_in_memory_ones(tmp_path, small_chunks, name):
    sc, kept, _ = make_loop(name, seconds=0.6)
    assert kept.run().rule == "completed"  # no log file: every period kept in memory
    _, streamed, _ = make_loop(name, seconds=0.6)
    assert streamed.run(tmp_path / "log.bin").rule == "completed"
    assert len(streamed.buffer) == 20 < streamed.rows == kept.rows == 600

    raw = np.fromfile(tmp_path / "log.bin").reshape(-1, streamed.width)
    timing = int(streamed.offsets[-2])
    assert raw.shape == kept.buffer.shape  # every period, in order, through a wrapping ring
    assert np.array_equal(raw[:, :timing], kept.buffer[:, :timing])

    memory, disk = kept.result(sc), streamed.result(sc)
    assert len(disk.time) == 0 and disk.periods == memory.periods == 600  # nothing loaded
    report.write_csv(memory, tmp_path / "memory.csv")
    report.write_csv(disk, tmp_path / "disk.csv")
    a, b = (np.loadtxt(tmp_path / f, delimiter=",", skiprows=1) for f in
            ("memory.csv", "disk.csv"))
    header = (tmp_path / "disk.csv").read_text().splitlines()[0].split(",")
    assert header == (tmp_path / "memory.csv").read_text().splitlines()[0].split(",")
    logged = [i for i, c in enumerate(header) if c not in loop_module.TIMING_COLUMNS]
    assert a.shape == b.shape == (600, len(header))
    assert np.array_equal(a[:, logged], b[:, logged])  # desired and poses too, chunk by chunk

    s_memory, s_disk = report.summary(memory), report.summary(disk)
    assert s_disk["periods"] == 600
    assert json.dumps(s_disk["units"], sort_keys=True) == \
        json.dumps(s_memory["units"], sort_keys=True) or \
        s_disk["units"] == pytest.approx(s_memory["units"])

    got = streamed.timing_summary()
    expected = _old_timing(raw, timing, sc.period)
    for key, value in expected.items():
        assert got[key] == pytest.approx(value, rel=1e-12, abs=1e-15), key


@pytest.mark.slow
def test_figures_of_a_long_run_plot_a_bounded_sample(tmp_path, small_chunks, monkeypatch):
    sc, loop, _ = make_loop("serial_joint", seconds=0.3)
    loop.run(tmp_path / "log.bin")
    monkeypatch.setattr(report, "FIGURE_POINTS", 40)
    sample = loop.result(sc).decimated(report.FIGURE_POINTS)
    assert 30 <= sample.periods <= 40 and sample.time[0] == 0.0
    assert np.all(np.diff(sample.time) > 0)
    full = loop.result(sc).rows(0, 300)
    step = int(round((sample.time[1] - sample.time[0]) / sc.period))
    assert np.array_equal(sample.units[0].q, full.units[0].q[::step])


def _full_disk(monkeypatch, when):
    """The writer's file write raises ENOSPC from the ``when``-th block on (or only once the
    loop has finished, ``when="final"``)."""
    calls = []
    write = LogWriter._write

    def failing(self, f, rows):
        calls.append(len(rows))
        if (when == "final" and self.finished.is_set()) or \
                (when != "final" and len(calls) > when):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        write(self, f, rows)

    monkeypatch.setattr(LogWriter, "_write", failing)
    return calls


@pytest.mark.parametrize("when", [0, 3, "final"])
def test_a_full_disk_stops_the_run_safely_with_its_own_rule(tmp_path, small_chunks,
                                                           monkeypatch, when):
    sc, loop, backend = make_loop("serial_task", seconds=1.0)
    _full_disk(monkeypatch, when)
    stop = loop.run(tmp_path / "log.bin")
    assert stop.rule == "log-failure" and stop.code == STOP_CODES["log-failure"] == 17
    assert os.strerror(errno.ENOSPC) in stop.detail and "log.bin holds the first" in stop.detail
    assert np.array_equal(backend.commands[-1], np.zeros(loop.n))  # zero effort last ...
    assert backend.disabled == 1 and not backend.enabled  # ... then the drives off
    if when == "final":  # the loop finished; only the last rows were lost
        assert loop.rows == 1000
    else:  # the loop stopped at its next period, long before the end
        assert loop.rows < 1000
    source = loop.rows_source()
    assert source.rows <= loop.rows
    # What reached the disk is still reported, with the stop that explains the rest.
    result = loop.result(sc)
    result.stop = {"rule": stop.rule, "time_s": stop.time, "detail": stop.detail,
                   "exit_code": stop.code}
    data = report.summary(result, None, loop.timing_summary())
    assert data["periods"] == source.rows and not data["converged"]


@pytest.mark.slow
def test_a_writer_a_ring_behind_stops_a_realtime_run(tmp_path, small_chunks, monkeypatch):
    sc, loop, backend = make_loop("serial_joint", seconds=1.0, realtime=True)

    def stalled(self, f, rows):  # a disk that does not answer until the loop has stopped
        while loop.stop is None:
            time.sleep(0.002)

    monkeypatch.setattr(LogWriter, "_write", stalled)
    stop = loop.run(tmp_path / "log.bin")
    assert stop.rule == "log-failure" and "fell 20 periods" in stop.detail
    assert loop.rows < 1000 and backend.disabled == 1
    assert np.array_equal(backend.commands[-1], np.zeros(loop.n))


@pytest.mark.slow
def test_an_as_fast_run_waits_for_a_slow_writer_but_not_for_a_hung_one(tmp_path, small_chunks,
                                                                      monkeypatch):
    write = LogWriter._write

    def slow(self, f, rows):
        time.sleep(0.001)
        write(self, f, rows)

    monkeypatch.setattr(LogWriter, "_write", slow)
    _, loop, _ = make_loop("serial_joint", seconds=0.4)
    assert loop.run(tmp_path / "slow.bin").rule == "completed"
    assert loop.rows_source().rows == 400

    monkeypatch.setattr(log_writer, "WRITER_STALL_S", 0.2)
    _, loop, backend = make_loop("serial_joint", seconds=0.4)
    monkeypatch.setattr(LogWriter, "_write", lambda self, f, rows: time.sleep(0.5))
    stop = loop.run(tmp_path / "hung.bin")
    assert stop.rule == "log-failure" and "wrote nothing for 0.2 s" in stop.detail
    assert backend.disabled == 1


def test_a_log_that_cannot_be_created_is_refused_before_anything_moves(tmp_path):
    _, loop, backend = make_loop("serial_task")
    with pytest.raises(CochleaError, match=r"cannot create the log .*missing.*writable --out"):
        loop.run(tmp_path / "missing" / "log.bin")
    assert backend.commands == [] and backend.disabled == 0 and not backend.enabled


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.slow
def test_chunked_percentiles_equal_numpys(monkeypatch, seed):
    # Few bins and a small exact threshold, so every case narrows over several passes.
    monkeypatch.setattr(loop_module, "_BINS", 8)
    monkeypatch.setattr(loop_module, "_EXACT", 16)
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 3000))
    data = [rng.normal(1e-3, 1e-5, n), rng.exponential(1e-4, n) - 2e-5,
            np.round(rng.normal(0, 3, n)),  # heavy ties
            np.full(n, 7.25), np.concatenate([np.full(n, 1e-3), [5.0]]),
            rng.uniform(-1e300, 1e300, n)][seed]
    chunk = int(rng.integers(1, 200))

    def columns():
        return (data[i:i + chunk] for i in range(0, len(data), chunk))

    percents = (0, 1, 37.5, 50, 99, 99.9, 100)
    got = loop_module.chunked_percentiles(columns, percents)
    # The order statistics are exact; the interpolation between them to a rounding.
    assert got == pytest.approx([float(np.percentile(data, p)) for p in percents], rel=1e-14,
                                abs=0)
    with_nan = np.concatenate([data, [np.nan]])
    assert all(np.isnan(loop_module.chunked_percentiles(lambda: iter([with_nan]), (50,))))
    assert all(np.isnan(loop_module.chunked_percentiles(lambda: iter([]), (50,))))


def _peak_mb(seconds: float, tmp_path: Path) -> float:
    """Peak RSS (MB) of the loop, the summary and the figures of a run, in a fresh process."""
    done = subprocess.run([sys.executable, str(BENCH), "--case", "serial_task", str(seconds),
                           "figures", str(tmp_path / f"run{seconds:g}")],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    case = json.loads(done.stdout.strip().splitlines()[-1])
    assert case["rule"] == "completed" and case["periods"] == round(seconds * 1000)
    assert case["figures"] == 9
    return case["after_report_MB"]


@pytest.mark.slow
def test_memory_is_flat_in_the_runs_length(tmp_path):
    """Ten times the periods, the same peak: the loop, its log, the summary and the figures
    read back from it take memory bounded by the ring and the chunks (the whole-run buffer of
    100 s of a serial task run alone would add about 45 MB)."""
    short, long = _peak_mb(10, tmp_path), _peak_mb(100, tmp_path)
    assert long - short < 8.0, (short, long)
