"""``make bench`` runs to its end (issue 30, item 0): a section that cannot run says why in its
place in results.md and the others still run; the embedded program's rows ask it only for rates
its own bus budget carries, and a run it refuses is reported, not repeated."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))

import embedded_program  # noqa: E402  (bench/, as bench/run.py imports it)
import run as bench_run  # noqa: E402  (bench/run.py)

#: The last full run's rows (bench/results.json) stand in for the sections that run; a sweep
#: row of its shape (bench/sweep_bench.py's serial()) where that file has none, and likewise
#: a MuJoCo row (bench/mujoco_compare.py's bench()).
LAST = json.loads((ROOT / "bench" / "results.json").read_text())
LAST.setdefault("sweep", [{"study": "serial_joint", "duration_s": 20.0, "per_s_core": 40.0,
                           "cpu_s": 0.025, "uncached_cpu_s": 0.1,
                           "parts": {"setup": 0.001, "simulate": 0.02}}])
LAST.setdefault("mujoco", {
    "scenario": "serial_joint", "unit": "arm1", "period_s": 1e-3, "plant_substeps": 1,
    "plant_kernel": "serial_arm1_plant_step", "plant_operations": 840, "mujoco": "4.0.0",
    "states": 50, "tolerance": 1e-9, "xml": "build/bench/serial_joint_arm1.xml",
    "load_before": 1.0, "load_after": 1.0, "qacc_max_rel": 2e-14, "step_max_rel": 2e-14,
    "same_arm": True, "plant_c_s": 2.7e-7, "mujoco_c_s": 3.7e-6, "mujoco_c_version": "4.0.0",
    "mujoco_rollout_s": 6.2e-6, "mujoco_python_s": 7e-6, "ratio": 13.7})


def fake_sections(monkeypatch, failing: dict[str, Exception]) -> None:
    """Every section returns the last run's rows at once, but those in ``failing`` raise."""
    def section(name):
        def run(*_args):
            if name in failing:
                raise failing[name]
            return LAST.get(name, [])
        return run

    lib = object()
    monkeypatch.setattr(bench_run.ckernels, "load", lambda: lib)
    monkeypatch.setattr(bench_run, "compile_helpers", lambda: (Path("floor"), Path("harness")))
    for name, attribute in (("build", "bench_build"), ("steps", "bench_steps"),
                            ("closed_loops", "bench_closed_loops"), ("sweep", "sweep_section")):
        monkeypatch.setattr(bench_run, attribute, section(name))
    monkeypatch.setattr(bench_run.embedded_bench, "bench_embedded_steps",
                        section("embedded_steps"))
    monkeypatch.setattr(bench_run.embedded_bench, "bench_embedded_sims",
                        section("embedded_sims"))
    monkeypatch.setattr(bench_run.embedded_program, "bench", section("embedded_program"))
    monkeypatch.setattr(bench_run.mujoco_compare, "bench", section("mujoco"))


def sections(markdown: str) -> dict[str, str]:
    """results.md's level-2 sections by heading."""
    parts = re.split(r"^## ", markdown, flags=re.M)[1:]
    return {p.split("\n", 1)[0]: p.split("\n", 1)[1] for p in parts}


@pytest.mark.parametrize("failing", sorted(bench_run.SECTIONS))
def test_a_section_that_cannot_run_says_why_and_the_others_run(monkeypatch, tmp_path, failing):
    error = subprocess.CalledProcessError(2, ["make", "embedded"],
                                          stderr=b"cc: error: no such file\n")
    fake_sections(monkeypatch, {failing: error})
    assert bench_run.main(["--out", str(tmp_path)]) == 0
    results = json.loads((tmp_path / "results.json").read_text())
    assert list(results["not_run"]) == [failing]
    assert "cc: error: no such file" in results["not_run"][failing]
    for name in set(bench_run.SECTIONS) - {failing}:
        assert name in results, name
    text = (tmp_path / "results.md").read_text()
    said = [h for h, body in sections(text).items() if "Not measured in this run:" in body]
    assert len(said) == 1, said  # in the failing section's own place, and nowhere else
    assert f"- **not measured**: {bench_run.SECTIONS[failing]}: " in text
    assert not list(tmp_path.glob(".*"))  # no partial file left beside the results


def test_every_section_failing_still_writes_the_results(monkeypatch, tmp_path):
    fake_sections(monkeypatch, {n: RuntimeError(f"{n} broke") for n in bench_run.SECTIONS})
    assert bench_run.main(["--out", str(tmp_path)]) == 0
    text = (tmp_path / "results.md").read_text()
    for name in bench_run.SECTIONS:
        assert f"RuntimeError: {name} broke" in text


def test_only_runs_the_sections_named(monkeypatch, tmp_path):
    fake_sections(monkeypatch, {})
    assert bench_run.main(["--only", "sweep", "build", "--out", str(tmp_path)]) == 0
    results = json.loads((tmp_path / "results.json").read_text())
    assert set(results["not_run"]) == set(bench_run.SECTIONS) - {"sweep", "build"}
    assert "build" in results and "steps" not in results


@pytest.mark.parametrize("argv, message", [
    (["--only", "nosuch", "--out", "."], "unknown section nosuch"),
    (["--only", "sweep"], "--only needs --out"),
    (["--out", "/nonexistent/folder"], "not a folder"),
])
def test_bad_options_are_one_line_and_exit_2(monkeypatch, capsys, argv, message):
    fake_sections(monkeypatch, {n: AssertionError("must not run") for n in bench_run.SECTIONS})
    assert bench_run.main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def c_budget_bytes(motors: int) -> float:
    """The bytes of one period as the embedded program counts them for the MX-64 chain: the
    SYNC_WRITE of Goal Current (14 + 3 n), the SYNC_READ request (14 + n) and n status
    packets of 11 + 16 bytes (Realtime Tick to Present Position): what its warning and
    summary.json print (214 for six motors; tests/test_dynamixel_hil.py asserts the same sum
    from a run)."""
    return (14 + 3 * motors) + (14 + motors) + 27 * motors


@pytest.mark.parametrize("baud", [1_000_000, 2_000_000, 3_000_000, 4_000_000])
def test_the_wire_rows_ask_for_a_rate_the_programs_budget_carries(baud):
    """The program refuses a rate whose period is shorter than its bus time: the rate the
    bench picks is one it accepts (1 Mbaud: 400 Hz, not the 500 Hz it refused)."""
    rate = embedded_program.carried_rate(6, baud)
    bus_s = c_budget_bytes(6) * 10 / baud + 6 * 20e-6  # BITS_PER_BYTE, TURNAROUND_S
    assert bus_s <= 1.0 / rate
    faster = [r for r in (1000, 500, 400, 250, 200, 100) if r > rate]
    assert all(bus_s > 1.0 / r for r in faster)


class _Done:
    def __init__(self, returncode, stderr):
        self.returncode, self.stderr = returncode, stderr


def test_a_refused_run_is_not_repeated_and_its_row_says_why(monkeypatch, tmp_path):
    starts = []

    class FakeEmulator:
        def __init__(self, *args):
            starts.append(args)

        def __enter__(self):
            return "/dev/pts/fake"

        def __exit__(self, *exc):
            return False

    refusal = ("cochlea-embedded: bus budget for 6 motors at 1000000 baud: 214 bytes per "
               "period = 2260 us on the bus; the bus cannot meet the loop rate\n")
    monkeypatch.setattr(embedded_program, "emulator", FakeEmulator)
    monkeypatch.setattr(embedded_program.subprocess, "run",
                        lambda *a, **k: _Done(2, refusal))
    rows = embedded_program.wire_times(bauds=(1_000_000,), seconds=0.1)
    assert len(starts) == 1  # one attempt: a refusal is not the emulator's lag
    assert rows[0]["not_run"].startswith("cochlea-embedded refused the run: ")
    assert "cannot meet the loop rate" in rows[0]["not_run"]
    text = embedded_program.markdown({"loop_compute": [], "wire": rows,
                                      "deadline_misses": embedded_program.deadline_misses(0.1)})
    assert "| 1 M | 400 Hz | not measured: cochlea-embedded refused the run" in text
    assert "Deadline misses of the C program over 0.1 s (serial_task): not measured" in text


def test_a_run_that_stops_early_every_time_is_reported_after_three(monkeypatch):
    starts = []

    class FakeEmulator:
        def __init__(self, *args):
            starts.append(args)

        def __enter__(self):
            return "/dev/pts/fake"

        def __exit__(self, *exc):
            return False

    monkeypatch.setattr(embedded_program, "emulator", FakeEmulator)
    monkeypatch.setattr(embedded_program.subprocess, "run",
                        lambda *a, **k: _Done(15, "cochlea-embedded: watchdog: 6 failed reads"))
    result = embedded_program.deadline_misses(0.1)
    assert len(starts) == embedded_program.ATTEMPTS
    assert "stopped early 3 times" in result["not_run"] and "watchdog" in result["not_run"]
