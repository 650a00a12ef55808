"""cochlea-sweep: samples that replay alone and exactly, a sweep on local Dask processes and on
a separately started scheduler and worker with the same rows, resume after a kill without
duplicates or gaps, and the class of bad specs refused in one line with exit 2."""

from __future__ import annotations

import json
import math
import os
import re
import signal
import socket
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from cochlea.apps import cochlea_run, cochlea_sweep, cochlea_tune
from cochlea.errors import DescriptionError
from cochlea.resources import SCENARIOS_DIR
from cochlea.sweep import results, sampling
from cochlea.sweep import spec as sweep_spec

BIN = Path(sys.executable).parent
SPEC = """format = "cochlea-sweep/1"
scenario = "serial_task"
samples = {samples}
seed = {seed}
duration_s = 0.2

[perturb]
mass_scale = {{uniform = [0.7, 1.3]}}
payload_kg = {{uniform = [0.0, 0.05]}}
delay_periods = {{choice = [0, 1, 2]}}
noise_q_std_SI = {{uniform = [0.0, 1e-4]}}

[gains.arm1]
G_g = {{grid = [2.0, [2.0, 2.0, 3.0]]}}
"""
#: Columns that are measured, not computed: they differ from run to run.
TIMING = {"wall_s"}


def write_spec(folder: Path, samples: int = 4, seed: int = 7, text: str | None = None) -> Path:
    path = folder / "spec.toml"
    path.write_text(text if text is not None else SPEC.format(samples=samples, seed=seed))
    return path


def rows_of(out: Path) -> list[dict]:
    """Every row but its timing, NaN as None (NaN equals nothing, itself included)."""
    return [{k: None if isinstance(v, float) and math.isnan(v) else v
             for k, v in r.items() if k not in TIMING}
            for r in results.read(out).to_pylist()]


@pytest.fixture(scope="module")
def local_sweep(tmp_path_factory):
    """A small sweep (4 draws x 2 grid points) on a LocalCluster of 2 processes."""
    folder = tmp_path_factory.mktemp("sweep")
    spec = write_spec(folder)
    out = folder / "out"
    code = cochlea_sweep.main([str(spec), "--out", str(out), "--workers", "2",
                               "--progress", "off"])
    assert code == 0
    return spec, out


# --------------------------------------------------------------------------------------------
# Sampling and the scenario files
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(p.stem for p in SCENARIOS_DIR.glob("*.toml")))
def test_scenario_writer_reads_back_every_shipped_scenario(name):
    data = tomllib.loads((SCENARIOS_DIR / f"{name}.toml").read_text())
    assert tomllib.loads(sampling.dumps(data)) == data


def test_writer_keeps_awkward_values():
    data = {"s": 'quote " back \\ tab \t nl \n é', "f": [1e-300, 0.1 + 0.2, -0.0, 5e17, 1.0],
            # json.dumps wrote DEL raw and this as a surrogate pair: neither is TOML
            "beyond": "del \x7f smile \U0001F600 esc \x1b",
            "\U0001F600 key": 1,
            "t": {"odd key": {"x": [True, False]}}, "u": [{"name": "a", "g": {"k": [1, 2]}}]}
    assert tomllib.loads(sampling.dumps(data)) == data


def test_a_sample_depends_only_on_the_seed_and_its_index(tmp_path):
    spec = sweep_spec.load(write_spec(tmp_path, samples=5))
    assert spec.total == 10
    forward = [sampling.inputs(spec, i) for i in range(spec.total)]
    backward = [sampling.inputs(spec, i) for i in reversed(range(spec.total))][::-1]
    assert forward == backward
    # Every grid point meets the same perturbations (common random numbers) ...
    for k in range(spec.samples):
        a, b = forward[k], forward[spec.samples + k]
        assert a["gains.arm1.G_g"] == 2.0 and b["gains.arm1.G_g"] == [2.0, 2.0, 3.0]
        assert {n: v for n, v in a.items() if n.startswith("plant.")} == \
            {n: v for n, v in b.items() if n.startswith("plant.")}
    # ... every draw differs, inside the spec's ranges, and another seed draws others.
    masses = [forward[k]["plant.mass_scale"] for k in range(spec.samples)]
    assert len(set(masses)) == spec.samples and all(0.7 <= m < 1.3 for m in masses)
    assert all(forward[k]["plant.delay_periods"] in (0, 1, 2) for k in range(spec.samples))
    other = sweep_spec.load(write_spec(tmp_path, samples=5, seed=8))
    assert sampling.inputs(other, 0)["plant.mass_scale"] != masses[0]
    # A key added to the spec leaves the other keys' draws alone.
    text = SPEC.format(samples=5, seed=7).replace("[perturb]\n", "[perturb]\narmature = "
                                                  "{choice = [true, false]}\n")
    more = sweep_spec.load(write_spec(tmp_path, text=text))
    assert sampling.inputs(more, 3)["plant.mass_scale"] == masses[3]


def test_a_sample_written_in_place_does_not_reach_the_base_or_the_next(tmp_path):
    """The base scenario is parsed once per process (sampling._base_data); every sample gets
    its own copy, so what one sample (or its caller) writes into its data reaches no other."""
    spec = sweep_spec.load(write_spec(tmp_path, text=SPEC.format(samples=3, seed=7)))
    before = [sampling.scenario_text(spec, i) for i in range(spec.total)]
    data = sampling.scenario_data(spec, 0)
    data["plant"]["mass_scale"] = [123.0] * 3
    data["unit"][0]["gains"].clear()
    data["desired"]["leader"].append("x")
    assert [sampling.scenario_text(spec, i) for i in range(spec.total)] == before
    assert "123.0" not in before[1] and sampling.scenario_data(spec, 0) != data


def test_each_draws_every_component_and_normal_stays_in_range(tmp_path):
    text = SPEC.format(samples=50, seed=1).replace(
        "mass_scale = {uniform = [0.7, 1.3]}", "mass_scale = {normal = [0.05, 0.1], each = true}")
    spec = sweep_spec.load(write_spec(tmp_path, text=text))
    for i in range(spec.samples):
        data = sampling.scenario_data(spec, i)
        scales = data["plant"]["mass_scale"]
        assert len(scales) == 3 and len(set(scales)) == 3
        assert all(s > 0 for s in scales)  # the loader's range: truncated, never clipped to 0


# --------------------------------------------------------------------------------------------
# Bad specs
# --------------------------------------------------------------------------------------------

BAD = {
    "unknown top key": ('seed = 7\n', 'seed = 7\nsamplez = 3\n', "samplez"),
    "unknown plant key": ("payload_kg =", "payload_g =", "perturb.payload_g"),
    "unknown unit": ("[gains.arm1]", "[gains.arm9]", "gains.arm9"),
    "unknown gain": ("G_g = {grid", "G_x = {grid", "gains.arm1.G_x"),
    "zero samples": ("samples = 4", "samples = 0", "samples"),
    "negative samples": ("samples = 4", "samples = -3", "samples"),
    "samples a float": ("samples = 4", "samples = 4.0", "samples"),
    "empty range": ("uniform = [0.7, 1.3]", "uniform = [1.3, 1.3]", "perturb.mass_scale.uniform"),
    "reversed range": ("uniform = [0.7, 1.3]", "uniform = [1.3, 0.7]",
                       "perturb.mass_scale.uniform"),
    "range outside the loader's": ("uniform = [0.0, 0.05]", "uniform = [-0.1, 0.05]",
                                   "perturb.payload_kg.uniform"),
    "empty choice": ("choice = [0, 1, 2]", "choice = []", "perturb.delay_periods.choice"),
    "choice the loader refuses": ("choice = [0, 1, 2]", "choice = [0, 1.5]",
                                  "perturb.delay_periods.choice[1]"),
    "empty grid": ("grid = [2.0, [2.0, 2.0, 3.0]]", "grid = []", "gains.arm1.G_g.grid"),
    "gain of the wrong size": ("[2.0, 2.0, 3.0]", "[2.0, 3.0]", "gains.arm1.G_g.grid[1]"),
    "zero gain": ("grid = [2.0,", "grid = [0.0,", "gains.arm1.G_g.grid[0]"),
    "two distributions": ("{choice = [0, 1, 2]}", "{choice = [0, 1], grid = [0]}",
                          "perturb.delay_periods"),
    "unknown distribution": ("{choice = [0, 1, 2]}", "{poisson = [1, 2]}",
                             "perturb.delay_periods.poisson"),
    "zero sigma": ("uniform = [0.7, 1.3]", "normal = [1.0, 0.0]", "perturb.mass_scale.normal"),
    "fixed value refused": ("payload_kg = {uniform = [0.0, 0.05]}", "payload_kg = 1000.0",
                            "perturb.payload_kg"),
    "wrong format": ('cochlea-sweep/1', 'cochlea-sweep/9', "format"),
    "unknown scenario": ('"serial_task"', '"no_such_study"', "no_such_study"),
    "zero duration": ("duration_s = 0.2", "duration_s = 0.0", "duration_s"),
    "duration under one period": ("duration_s = 0.2", "duration_s = 0.0001", "duration_s"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_a_bad_spec_is_one_line_exit_2_and_leaves_nothing(case, tmp_path, capsys):
    old, new, named = BAD[case]
    text = SPEC.format(samples=4, seed=7)
    assert old in text
    spec = write_spec(tmp_path, text=text.replace(old, new, 1))
    out = tmp_path / "out"
    code = cochlea_sweep.main([str(spec), "--out", str(out), "--progress", "off"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("cochlea-sweep: ") and named in err
    assert "Traceback" not in err
    assert not out.exists()


@pytest.mark.slow
def test_a_folder_of_another_spec_or_other_files_is_refused(local_sweep, tmp_path, capsys):
    _, out = local_sweep
    other = write_spec(tmp_path, seed=8)
    before = sorted(p.name for p in (out / "parts").iterdir())
    assert cochlea_sweep.main([str(other), "--out", str(out), "--progress", "off"]) == 3
    err = capsys.readouterr().err
    assert "different spec" in err and err.count("\n") == 1
    assert sorted(p.name for p in (out / "parts").iterdir()) == before
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    assert cochlea_sweep.main([str(other), "--out", str(busy), "--progress", "off"]) == 3
    assert "other files" in capsys.readouterr().err
    assert sorted(p.name for p in busy.iterdir()) == ["notes.txt"]


# --------------------------------------------------------------------------------------------
# Sweeps
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_local_sweep_has_one_row_per_sample_and_a_report(local_sweep, capsys):
    spec_path, out = local_sweep
    rows = rows_of(out)
    assert [r["sample"] for r in rows] == list(range(8))
    spec = sweep_spec.load(spec_path)
    # A grid of a number and a list: a list in every row, the same columns in every part.
    assert [[r[f"gains.arm1.G_g[{j}]"] for j in range(3)] for r in rows] == \
        [[2.0] * 3] * 4 + [[2.0, 2.0, 3.0]] * 4
    assert {tuple(pq.read_schema(p).names) for p in (out / "parts").iterdir()} == \
        {tuple(results.read(out).column_names)}
    for r in rows:
        for name, value in sampling.inputs(spec, r["sample"]).items():
            if name != "gains.arm1.G_g":
                assert results.flatten(name, value).items() <= r.items()
        assert r["success"] == (r["converged"] and not r["diverged"] and r["stop_rule"] == "none")
        assert r["converged"] == (r["convergence_ratio"] <= 1)
        ratios = [c for c in r if re.fullmatch(r"arm[12]\.torque_ratio\.joint[123]_1", c)]
        assert len(ratios) == 6 and all(0 <= r[c] <= 1 for c in ratios)
    summary = (out / "summary.md").read_text()
    assert "## Robustness map" in summary and "cochlea-sweep replay" in summary
    assert (out / "robustness_map.png").stat().st_size > 0
    # The same command again runs nothing and writes no part.
    parts = sorted((out / "parts").iterdir())
    assert cochlea_sweep.main([str(spec_path), "--out", str(out), "--progress", "off"]) == 0
    assert "already" in capsys.readouterr().out
    assert sorted((out / "parts").iterdir()) == parts


@pytest.mark.slow
def test_replay_reproduces_a_row_exactly(local_sweep, tmp_path):
    _, out = local_sweep
    row = next(r for r in rows_of(out) if r["sample"] == 5)
    scenario = tmp_path / "sample5.toml"
    assert cochlea_sweep.main(["replay", str(out), "5", "--out", str(scenario)]) == 0
    run = tmp_path / "run"
    code = cochlea_run.main(["--robot", "serial", "--space", "task", "--scenario",
                             str(scenario), "--realtime", "off", "--out", str(run)])
    summary = json.loads((run / "summary.json").read_text())
    assert code in (0, 10, 11, 12, 13, 14)
    assert summary["converged"] == row["converged"]
    assert summary["supervisor"]["rule"] == row["stop_rule"]
    assert summary["supervisor"].get("time_s") == row["stop_time_s"]  # None: no rule
    checked = 0
    for uname, u in summary["units"].items():
        for coord, c in u["tracked"].items():
            assert c["final_rms_error"] == row[f"{uname}.final_rms.{coord}_{c['unit']}"]
            checked += 1
        for joint, t in u["torque"].items():
            unit = t["unit"].replace(" ", "_")  # N m -> N_m: the log schema's unit
            assert t["max_abs"] == row[f"{uname}.peak_torque.{joint}_{unit}"]
            checked += 1
        assert (not u["estimates"]["bounded"]) <= row["estimate_bound_hit"]
    assert checked == 12
    # The file says which sample it is and what to run; stdout gives the same text.
    assert "Sample 5 " in scenario.read_text()


@pytest.mark.slow
def test_replay_of_a_sample_out_of_range_is_refused(local_sweep, capsys):
    _, out = local_sweep
    assert cochlea_sweep.main(["replay", str(out), "8"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "between 0 and 7" in err


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_a_separate_scheduler_and_worker_give_the_same_rows(local_sweep, tmp_path):
    spec_path, local_out = local_sweep
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    procs = [subprocess.Popen([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port",
                               str(port), "--no-dashboard"], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, env=env, start_new_session=True)]
    try:
        procs.append(subprocess.Popen([str(BIN / "dask"), "worker", address, "--nthreads", "1",
                                       "--no-dashboard"], stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL, env=env,
                                      start_new_session=True))
        out = tmp_path / "out"
        code = cochlea_sweep.main([str(spec_path), "--out", str(out), "--scheduler", address,
                                   "--progress", "off"])
        assert code == 0
        assert rows_of(out) == rows_of(local_out)
    finally:
        for p in reversed(procs):
            os.killpg(p.pid, signal.SIGTERM)
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


@pytest.mark.slow
def test_an_unreachable_scheduler_is_one_line_exit_2(tmp_path, capsys, monkeypatch):
    from cochlea.sweep import execute

    monkeypatch.setattr(execute, "CONNECT_TIMEOUT_S", 1)
    spec_path = write_spec(tmp_path)
    code = cochlea_sweep.main([str(spec_path), "--out", str(tmp_path / "out"), "--scheduler",
                               f"tcp://127.0.0.1:{_free_port()}", "--progress", "off"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "--scheduler" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("address", ["tls://127.0.0.1:1", "ucx://192.0.2.1:5"])
@pytest.mark.parametrize("program", ["sweep", "tune"])
@pytest.mark.slow  # distributed's import
def test_a_scheduler_dask_cannot_connect_to_is_one_line_exit_2(address, program, tmp_path,
                                                                capsys):
    # tls:// without a certificate raised TypeError, ucx:// without UCX a TypeError of an
    # abstract class: tracebacks (only OSError, TimeoutError and ValueError were caught).
    spec_path = write_spec(tmp_path)
    if program == "tune":
        spec_path.write_text(spec_path.read_text() + "\n[tune]\ntrials = 1\n")
    main = cochlea_sweep.main if program == "sweep" else cochlea_tune.main
    code = main([str(spec_path), "--out", str(tmp_path / "out"), "--scheduler", address,
                 "--progress", "off"])
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    assert code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"cochlea-{program}: --scheduler {address}: cannot reach"), err
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_a_killed_sweep_resumes_without_duplicates_or_gaps(local_sweep, tmp_path):
    spec_path, local_out = local_sweep
    out = tmp_path / "out"
    proc = subprocess.Popen([str(BIN / "cochlea-sweep"), str(spec_path), "--out", str(out),
                             "--workers", "2", "--batch", "1", "--progress", "off"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 120  # a bound on a hung start, not a timed assertion
        while len(list((out / "parts").glob("*.parquet"))) < 2 and proc.poll() is None:
            assert time.monotonic() < deadline, "no part file appeared"
            time.sleep(0.05)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the sweep and its workers, at once
        proc.wait()
    kept = {p.name: p.read_bytes() for p in (out / "parts").glob("*.parquet")}
    assert len(kept) >= 2
    killed_rows = len(results.done(out))
    code = cochlea_sweep.main([str(spec_path), "--out", str(out), "--workers", "2",
                               "--progress", "off"])
    assert code == 0
    samples = [r["sample"] for r in results.read(out).to_pylist()]
    assert samples == list(range(8)), f"after a kill at {killed_rows} rows"
    for name, data in kept.items():  # finished batches are never rewritten
        assert (out / "parts" / name).read_bytes() == data
    assert rows_of(out) == rows_of(local_out)
    assert not list((out / "parts").glob("*.tmp"))


@pytest.mark.slow
def test_part_files_are_plain_parquet(local_sweep):
    _, out = local_sweep
    table = pq.read_table(out / "parts")
    assert sorted(table["sample"].to_pylist()) == list(range(8))
    assert json.loads((out / "sweep.json").read_text())["total"] == 8


def test_every_wilson_interval_holds_its_estimate():
    """A robustness map's error bars are p - lo and hi - p: the interval must hold p exactly,
    also where every sample or none succeeded (rounding once put hi a few ulps below 1 and
    the 400-sample report failed on a negative error bar)."""
    from cochlea.sweep.report import wilson

    for n in range(1, 1201):
        for s in {0, 1, n // 3, n // 2, n - 1, n}:
            lo, hi = wilson(s, n)
            assert 0.0 <= lo <= s / n <= hi <= 1.0, (s, n, lo, hi)
    assert wilson(0, 0) == (0.0, 1.0)


def test_a_report_that_fails_is_one_line_and_keeps_the_samples(tmp_path, monkeypatch, capsys):
    """The samples are the result: a report that cannot be written (a full disk, a figure)
    ends in one line naming the command that writes it again, exit 18, no traceback."""
    from cochlea.sweep import report as sweep_report

    def full_disk(out):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(sweep_report, "write", full_disk)
    assert cochlea_sweep.main(["report", str(tmp_path)]) == cochlea_sweep.EXIT_REPORT_FAILED
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "No space left on device" in err
    assert f"cochlea-sweep report {tmp_path}" in err


@pytest.mark.slow
def test_a_second_sweep_on_a_running_folder_is_refused(local_sweep, tmp_path, capsys):
    """Two sweeps on one folder would run the same missing samples and write each twice (it
    happened: 650 rows for 400 samples). The running one holds a lock; the second is one line,
    exit 2, and writes nothing; once the first is gone the same command resumes."""
    spec_path, local_out = local_sweep
    out = tmp_path / "out"
    spec = sweep_spec.load(spec_path)
    results.prepare(out, spec)
    fd = results.hold(out)  # a sweep running on the folder (flock: any other open file waits)
    try:
        code = cochlea_sweep.main([str(spec_path), "--out", str(out), "--workers", "1",
                                   "--progress", "off"])
        assert code == 4
        assert "another cochlea-sweep is running on this folder" in capsys.readouterr().err
        assert not list((out / "parts").iterdir())
    finally:
        results.release(fd)
    assert cochlea_sweep.main([str(spec_path), "--out", str(out), "--workers", "2",
                               "--progress", "off"]) == 0
    assert [r["sample"] for r in results.read(out).to_pylist()] == list(range(8))
    assert rows_of(out) == rows_of(local_out)


@pytest.mark.slow
def test_replay_of_a_spec_named_after_its_scenario(tmp_path):
    """docs/robustness/serial_task.toml sweeps serial_task.toml: replay rebuilt both files in
    one temporary folder under their own names, so the spec overwrote the scenario and every
    replay of such a sweep was refused."""
    spec_path = tmp_path / "serial_task.toml"
    spec_path.write_text(SPEC.format(samples=1, seed=3))
    out = tmp_path / "out"
    assert cochlea_sweep.main([str(spec_path), "--out", str(out), "--workers", "1",
                               "--progress", "off"]) == 0
    scenario = tmp_path / "sample1.toml"
    assert cochlea_sweep.main(["replay", str(out), "1", "--out", str(scenario)]) == 0
    assert "Sample 1 " in scenario.read_text()
    assert 'format = "cochlea-scenario/1"' in scenario.read_text()


def test_a_map_over_the_gearbox_varies_backlash_and_static_friction(tmp_path):
    """Issue 24's robustness map: the gearbox's keys vary like any other [plant] key, a number
    standing for every joint, and each sample's scenario loads with them."""
    from cochlea.sim import load_scenario
    text = ('format = "cochlea-sweep/1"\nscenario = "serial_joint_realistic"\nsamples = 1\n'
            'seed = 1\nduration_s = 0.1\n[perturb]\n'
            'backlash_SI = {grid = [0.0, 0.0087]}\n'
            'static_friction_ratio = {grid = [1, 2.0]}\n')
    spec = sweep_spec.load(write_spec(tmp_path, text=text))
    seen = set()
    for i in range(4):
        path = tmp_path / f"sample{i}.toml"
        path.write_text(sampling.scenario_text(spec, i))
        plant = load_scenario(path).plant
        assert plant.gearbox and len(set(plant.backlash)) == 1
        seen.add((float(plant.backlash[0]), plant.static_friction_ratio))
    assert seen == {(0.0, 1.0), (0.0, 2.0), (0.0087, 1.0), (0.0087, 2.0)}
    # A float key's integers are floats in the rows (one column type for Parquet).
    assert sampling.inputs(spec, 0)["plant.backlash_SI"] == 0.0
    assert isinstance(sampling.inputs(spec, 0)["plant.backlash_SI"], float)
    assert isinstance(sampling.inputs(spec, 0)["plant.static_friction_ratio"], float)
    bad = text.replace("2.0]}", "0.5]}")  # static below Coulomb
    with pytest.raises(DescriptionError, match="static_friction_ratio"):
        sweep_spec.load(write_spec(tmp_path, text=bad))
