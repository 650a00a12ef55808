"""cochlea-tune: a small search on local Dask processes that does at least as well as the nominal
gains on the same sample, the same trials from the same seed (another worker count, a separately
started scheduler and worker, a resume after a kill), a tuned.toml that cochlea-run runs, and
the class of bad specs refused in one line with exit 2 and nothing written."""

from __future__ import annotations

import csv
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import optuna
import pyarrow.parquet as pq
import pytest

from cochlea.apps import cochlea_run, cochlea_sweep, cochlea_tune
from cochlea.sweep import execute, sampling
from cochlea.sweep import tune as tuning

BIN = Path(sys.executable).parent
TRIALS = 6
SPEC = """format = "cochlea-sweep/1"
scenario = "serial_task"
samples = 2
seed = 7
duration_s = 0.3

[perturb]
mass_scale = {{uniform = [0.7, 1.3]}}
payload_kg = {{uniform = [0.0, 0.05]}}
delay_periods = {{choice = [0, 1, 2]}}

[gains.arm1]
G_g = {{uniform = [1.0, 50.0]}}
G_a = [0.06, 0.06, 0.007]

[gains.arm2]
G_g = {{uniform = [1.0, 50.0], each = true}}

[tune]
trials = {trials}
parallel_candidates = 2
startup_trials = 3
{extra}"""


def write_spec(folder: Path, text: str | None = None, **kw) -> Path:
    path = folder / "spec.toml"
    fields = {"trials": TRIALS, "extra": ""} | kw
    path.write_text(text if text is not None else SPEC.format(**fields))
    return path


def trials_of(out: Path) -> list[dict]:
    with open(out / tuning.TRIALS_CSV, newline="") as f:
        return list(csv.DictReader(f))


def comparable(row: dict) -> dict:
    """A run's row but its timing, NaN as None (NaN equals nothing, itself included)."""
    return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in row.items()
            if k != "wall_s"}


@pytest.fixture(scope="module")
def local_tune(tmp_path_factory):
    """A small search (6 trials of 2 runs, 2 candidates a round) on a LocalCluster of 2."""
    folder = tmp_path_factory.mktemp("tune")
    spec = write_spec(folder)
    out = folder / "out"
    assert cochlea_tune.main([str(spec), "--out", str(out), "--workers", "2",
                              "--progress", "off"]) == 0
    return spec, out


# --------------------------------------------------------------------------------------------
# The objective and the search space (no runs)
# --------------------------------------------------------------------------------------------


def _row(ratio, torque=0.5, rule="none", diverged=False):
    return {"convergence_ratio": ratio, "arm1.torque_ratio.q1_1": torque,
            "arm1.torque_ratio.q2_1": 0.1, "stop_rule": rule, "diverged": diverged,
            "success": ratio <= 1}


def _run_rows(*rows: dict) -> list[dict]:
    """``rows`` as a candidate's run file holds them: samples 0, 1, ... with every row column
    (results.ROW_COLUMNS)."""
    return [{"sample": i, "grid": 0, "draw": i, "converged": r["success"],
             "estimate_bound_hit": False, "stop_time_s": math.nan, "saturated_periods": 0,
             "wall_s": 0.1, **r} for i, r in enumerate(rows)]


def test_the_objective_is_a_percentile_of_the_runs_and_limits_make_a_candidate_infeasible():
    rows = [_row(r) for r in (0.5, 4.0, 1.0, 2.0, 3.0)]
    # The smallest value that at least NN % of the runs do not exceed: a run's own value.
    assert tuning.judge(rows, "p60")["objective"] == 2.0
    assert tuning.judge(rows, "p61")["objective"] == 3.0
    assert tuning.judge(rows, "p100")["objective"] == tuning.judge(rows, "worst")["objective"]
    assert tuning.judge(rows, "mean")["objective"] == pytest.approx(2.1)
    ok = tuning.judge(rows, "p95")
    assert ok["feasible"] and ok["successes"] == 2 and ok["max_torque_ratio"] == 0.5
    for bad, what in ((_row(0.5, torque=1.0), "torque_limit_runs"),
                      (_row(0.5, rule="velocity"), "stopped_runs"),
                      (_row(0.5, diverged=True), "stopped_runs"),
                      (_row(float("nan")), "stopped_runs")):
        verdict = tuning.judge(rows + [bad], "p95")
        assert not verdict["feasible"] and verdict[what] == 1
    assert tuning.judge(rows + [_row(float("nan"))], "worst")["objective"] == float("inf")


def test_search_space_scales_and_the_sample_is_the_same_for_every_candidate(tmp_path):
    extra = 'log = ["gains.arm2.G_g"]\n'
    text = SPEC.format(trials=3, extra=extra).replace("G_g = {uniform = [1.0, 50.0]}",
                                                      "G_g = {uniform = [1.0, 5.0]}", 1)
    tune = tuning.load(write_spec(tmp_path, text))
    scales = {d.name: d.log for d in tune.dims}
    assert scales == {"gains.arm1.G_g": False, "gains.arm2.G_g": True}  # fixed G_a: not searched
    assert sorted(tune.distributions()) == ["gains.arm1.G_g", "gains.arm2.G_g[0]",
                                            "gains.arm2.G_g[1]", "gains.arm2.G_g[2]"]
    # A range over a decade is searched on a log scale unless the spec says linear.
    auto = tuning.load(write_spec(tmp_path, extra='linear = ["gains.arm1.G_g"]\n'))
    assert {d.name: d.log for d in auto.dims} == {"gains.arm1.G_g": False,
                                                  "gains.arm2.G_g": True}
    # Two candidates: the same plants (common random numbers), their own gains, G_a fixed.
    a = tune.candidate({"gains.arm1.G_g": 2.0, "gains.arm2.G_g": [1.0, 2.0, 3.0]})
    b = tune.candidate({"gains.arm1.G_g": 4.0, "gains.arm2.G_g": [5.0, 5.0, 5.0]})
    for i in range(tune.size):
        da, db = sampling.scenario_data(a, i), sampling.scenario_data(b, i)
        assert da["plant"] == db["plant"]
        units_a = {u["name"]: u["gains"] for u in da["unit"]}
        units_b = {u["name"]: u["gains"] for u in db["unit"]}
        assert units_a["arm1"]["G_g"] == [2.0] * 3 and units_b["arm1"]["G_g"] == [4.0] * 3
        assert units_a["arm2"]["G_g"] == [1.0, 2.0, 3.0]
        assert units_a["arm1"]["G_a"] == units_b["arm1"]["G_a"] == [0.06, 0.06, 0.007]
    assert len({sampling.inputs(a, i)["plant.mass_scale"] for i in range(tune.size)}) == 2


# --------------------------------------------------------------------------------------------
# A search
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_a_local_tune_does_at_least_as_well_as_the_nominal_gains(local_tune):
    spec_path, out = local_tune
    tune = tuning.load(spec_path)
    trials = trials_of(out)
    assert [int(t["trial"]) for t in trials] == list(range(TRIALS))
    result = json.loads((out / tuning.RESULT).read_text())
    nominal, chosen = result["nominal"], result["chosen"]
    assert chosen is not None and chosen["objective"] <= nominal["objective"]
    assert result["best_trial"]["objective"] == min(float(t["objective"]) for t in trials
                                                    if t["feasible"] == "True")
    # Every trial's objective is its own runs' verdict; every candidate met the same plants.
    nominal_rows = pq.read_table(tuning.rows_path(out, "nominal")).to_pylist()
    plants = [{k: v for k, v in r.items() if k.startswith("plant.")} for r in nominal_rows]
    assert len(plants) == tune.size and plants[0] != plants[1]
    for t in trials:
        rows = pq.read_table(tuning.rows_path(out, int(t["trial"]))).to_pylist()
        assert float(t["objective"]) == tuning.judge(rows, tune.settings.objective)["objective"]
        assert [{k: v for k, v in r.items() if k.startswith("plant.")} for r in rows] == plants
        assert rows[0]["gains.arm1.G_g"] == float(t["gains.arm1.G_g"])
        assert [rows[0][f"gains.arm2.G_g[{j}]"] for j in range(3)] == \
            [float(t[f"gains.arm2.G_g[{j}]"]) for j in range(3)]
        assert rows[0]["gains.arm1.G_a[2]"] == 0.007
    assert nominal["objective"] == tuning.judge(nominal_rows, "p95")["objective"]
    assert nominal["gains"]["gains.arm1.G_g"] == [2.0, 2.0, 3.0]  # the scenario's own
    summary = (out / "summary.md").read_text()
    assert "nominal" in summary and "cochlea-run" in summary and "history.png" in summary
    assert (out / "history.png").stat().st_size > 0
    # The study holds exactly the trials, each finished once.
    study = tuning.open_study(out, tune)
    assert [t.number for t in study.get_trials()] == list(range(TRIALS))
    assert all(t.state == optuna.trial.TrialState.COMPLETE for t in study.get_trials())


@pytest.mark.slow
def test_tuned_scenario_runs_with_cochlea_run_and_holds_the_chosen_gains(local_tune, tmp_path):
    spec_path, out = local_tune
    tune = tuning.load(spec_path)
    chosen = json.loads((out / tuning.RESULT).read_text())["chosen"]
    data = tomllib.loads((out / tuning.TUNED).read_text())
    units = {u["name"]: u["gains"] for u in data["unit"]}
    gains = chosen["gains"]
    arm1 = gains["gains.arm1.G_g"]
    assert units["arm1"]["G_g"] == (arm1 if isinstance(arm1, list) else [arm1] * 3)
    assert units["arm2"]["G_g"] == gains["gains.arm2.G_g"]
    base = tomllib.loads(tune.spec.scenario_text)
    assert data["duration_s"] == base["duration_s"] and "plant" not in data  # the scenario's own
    run = tmp_path / "run"
    code = cochlea_run.main(["--robot", "serial", "--space", "task", "--scenario",
                             str(out / tuning.TUNED), "--realtime", "off", "--duration", "0.3",
                             "--out", str(run)])
    assert code in (0, 10, 11, 12, 13, 14)
    summary = json.loads((run / "summary.json").read_text())
    assert set(summary["units"]) == {"arm1", "arm2"}
    # The chosen gains on the tuning sample give the chosen trial's runs, exactly.
    if chosen["trial"] != "nominal":
        rows = execute.run_batch(tune.candidate(gains), [0], cochlea_sweep.evaluate)
        stored = pq.read_table(tuning.rows_path(out, chosen["trial"])).to_pylist()[0]
        assert comparable(rows[0]) == comparable(stored)


@pytest.mark.slow
def test_the_same_command_again_runs_nothing_and_another_spec_is_refused(local_tune, tmp_path,
                                                                         capsys):
    spec_path, out = local_tune
    before = {p.name: p.read_bytes() for p in (out / tuning.SAMPLES).iterdir()}
    assert cochlea_tune.main([str(spec_path), "--out", str(out), "--progress", "off"]) == 0
    assert "all already in" in capsys.readouterr().out
    assert {p.name: p.read_bytes() for p in (out / tuning.SAMPLES).iterdir()} == before
    for args in (["--seed", "8"], ["--objective", "worst"]):
        assert cochlea_tune.main([str(spec_path), "--out", str(out), *args]) == 3
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "different spec" in err
    other = write_spec(tmp_path)
    other.write_text(other.read_text().replace("seed = 7", "seed = 9"))
    assert cochlea_tune.main([str(other), "--out", str(out)]) == 3
    assert "different spec" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in (out / tuning.SAMPLES).iterdir()} == before


@pytest.mark.slow
def test_a_killed_tune_resumes_to_the_same_trials(local_tune, tmp_path):
    spec_path, local_out = local_tune
    out = tmp_path / "out"
    proc = subprocess.Popen([str(BIN / "cochlea-tune"), str(spec_path), "--out", str(out),
                             "--workers", "1", "--progress", "off"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 120  # a bound on a hung start, not a timed assertion
        while not list((out / tuning.SAMPLES).glob("trial-*.parquet")) and proc.poll() is None:
            assert time.monotonic() < deadline, "no trial finished"
            time.sleep(0.02)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the search and its workers, at once
        proc.wait()
    kept = {p.name: p.read_bytes() for p in (out / tuning.SAMPLES).glob("*.parquet")}
    finished = [n for n in kept if n.startswith("trial-")]
    assert 1 <= len(finished) < TRIALS, "the kill came after the search had finished"
    code = cochlea_tune.main([str(spec_path), "--out", str(out), "--workers", "2",
                              "--progress", "off"])
    assert code == 0
    # The same trials as the search that was never stopped: none lost, none repeated ...
    assert trials_of(out) == trials_of(local_out)
    study = tuning.open_study(out, tuning.load(spec_path))
    assert [t.number for t in study.get_trials()] == list(range(TRIALS))
    # ... and the trials finished before the kill were not run again.
    for name, data in kept.items():
        assert (out / tuning.SAMPLES / name).read_bytes() == data
    assert not list(out.rglob("*.tmp"))
    assert json.loads((out / tuning.RESULT).read_text())["chosen"] == \
        json.loads((local_out / tuning.RESULT).read_text())["chosen"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_a_separate_scheduler_and_worker_give_the_same_trials(local_tune, tmp_path):
    spec_path, local_out = local_tune
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
        assert cochlea_tune.main([str(spec_path), "--out", str(out), "--scheduler", address,
                                  "--progress", "off"]) == 0
        assert trials_of(out) == trials_of(local_out)
        assert (out / tuning.TUNED).read_text() == (local_out / tuning.TUNED).read_text()
    finally:
        for p in reversed(procs):
            os.killpg(p.pid, signal.SIGTERM)
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------

BAD = {
    "unknown tune key": ("startup_trials = 3", "startup_trials = 3\ntrails = 4", "tune.trails"),
    "unknown top key": ("seed = 7", "seed = 7\nsamplez = 2", "samplez"),
    "unknown gain": ("G_a = [", "G_x = [", "gains.arm1.G_x"),
    "empty range": ("G_g = {uniform = [1.0, 50.0]}", "G_g = {uniform = [5.0, 5.0]}",
                    "gains.arm1.G_g.uniform"),
    "reversed range": ("G_g = {uniform = [1.0, 50.0]}", "G_g = {uniform = [50.0, 1.0]}",
                       "gains.arm1.G_g.uniform"),
    "non-positive range": ("G_g = {uniform = [1.0, 50.0]}", "G_g = {uniform = [0.0, 50.0]}",
                           "gains.arm1.G_g.uniform"),
    "negative range on a log scale": ("G_g = {uniform = [1.0, 50.0], each",
                                      "G_g = {uniform = [-1.0, 50.0], each",
                                      "gains.arm2.G_g.uniform"),
    "zero trials": ("trials = 6", "trials = 0", "tune.trials"),
    "trials a float": ("trials = 6", "trials = 6.0", "tune.trials"),
    "zero samples": ("samples = 2", "samples = 0", "samples"),
    "nothing to search": ([("G_g = {uniform = [1.0, 50.0]}\nG_a", "G_g = 2.0\nG_a"),
                           ("G_g = {uniform = [1.0, 50.0], each = true}", "G_g = [1.0, 2.0, 3.0]")],
                          "gains"),
    "no gains at all": ([("[gains.arm1]\nG_g = {uniform = [1.0, 50.0]}\nG_a = [0.06, 0.06, "
                          "0.007]\n", ""), ("[gains.arm2]\nG_g = {uniform = [1.0, 50.0], each "
                                            "= true}\n", "")], "gains"),
    "a normal is not a search range": ("G_g = {uniform = [1.0, 50.0]}",
                                       "G_g = {normal = [10.0, 1.0]}", "gains.arm1.G_g.normal"),
    "unknown objective": ("startup_trials = 3", 'startup_trials = 3\nobjective = "median"',
                          "tune.objective"),
    "percentile out of range": ("startup_trials = 3", 'startup_trials = 3\nobjective = "p0"',
                                "tune.objective"),
    "log names a fixed gain": ("startup_trials = 3",
                               'startup_trials = 3\nlog = ["gains.arm1.G_a"]', "tune.log[0]"),
    "log and linear both": ("startup_trials = 3", 'startup_trials = 3\nlog = ["gains.arm1.G_g"]'
                            '\nlinear = ["gains.arm1.G_g"]', "tune.linear"),
    "zero candidates a round": ("parallel_candidates = 2", "parallel_candidates = 0",
                                "tune.parallel_candidates"),
    "tune not a table": ([("[tune]\ntrials = 6\nparallel_candidates = 2\nstartup_trials = 3\n",
                           ""), ("seed = 7", "seed = 7\ntune = 3")], "tune"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_a_bad_spec_is_one_line_exit_2_and_leaves_nothing(case, tmp_path, capsys):
    change, *rest, named = BAD[case]
    text = SPEC.format(trials=TRIALS, extra="")
    for old, new in change if isinstance(change, list) else [(change, rest[0])]:
        assert old in text
        text = text.replace(old, new, 1)
    spec = write_spec(tmp_path, text)
    out = tmp_path / "out"
    code = cochlea_tune.main([str(spec), "--out", str(out), "--progress", "off"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("cochlea-tune: ") and named in err, err
    assert "Traceback" not in err
    assert not out.exists()


BAD_OPTIONS = {
    "zero trials": (["--trials", "0"], "--trials"),
    "negative seed": (["--seed", "-1"], "--seed"),
    "unknown objective": (["--objective", "best"], "--objective"),
    "zero workers": (["--workers", "0"], "--workers"),
    "workers and scheduler": (["--workers", "2", "--scheduler", "tcp://127.0.0.1:1"],
                              "--scheduler"),
}


@pytest.mark.parametrize("case", sorted(BAD_OPTIONS))
def test_a_bad_option_is_one_line_exit_2_and_leaves_nothing(case, tmp_path, capsys):
    args, named = BAD_OPTIONS[case]
    out = tmp_path / "out"
    code = cochlea_tune.main([str(write_spec(tmp_path)), "--out", str(out), *args])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and named in err, err
    assert not out.exists()


@pytest.mark.slow
def test_a_folder_with_other_files_or_an_unreachable_scheduler_is_refused(tmp_path, capsys,
                                                                          monkeypatch):
    spec = write_spec(tmp_path)
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    assert cochlea_tune.main([str(spec), "--out", str(busy)]) == 3
    assert "other files" in capsys.readouterr().err
    assert sorted(p.name for p in busy.iterdir()) == ["notes.txt"]
    monkeypatch.setattr(execute, "CONNECT_TIMEOUT_S", 1)
    code = cochlea_tune.main([str(spec), "--out", str(tmp_path / "out"), "--scheduler",
                              f"tcp://127.0.0.1:{_free_port()}", "--progress", "off"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "--scheduler" in err
    assert not (tmp_path / "out").exists()


def test_the_example_spec_loads_as_documented():
    example = Path(__file__).resolve().parent.parent / "examples" / "tune_serial_task.toml"
    tune = tuning.load(example)
    assert len(tune.distributions()) == 6 and all(d.log for d in tune.dims)
    assert tune.size == 8 and tune.settings.trials == 40 and tune.settings.objective == "p95"


@pytest.mark.slow
def test_the_nominal_gains_are_the_result_when_no_trial_beats_them(tmp_path):
    """The choice among finished trials and the nominal, on verdicts made up for the purpose
    (no runs): the feasible candidate of the smallest objective; none feasible, no tuned.toml."""
    tune = tuning.load(write_spec(tmp_path, trials=3))
    out = tmp_path / "out"
    tuning.prepare(out, tune)
    study = tuning.open_study(out, tune)
    ask = tune.distributions()

    def verdict(objective, feasible=True):
        return {"objective": objective, "feasible": feasible,
                "torque_limit_runs": 0 if feasible else 1, "stopped_runs": 0, "successes": 0,
                "runs": 2, "median_ratio": objective, "worst_ratio": objective,
                "max_torque_ratio": 0.5}

    for n, v in enumerate([verdict(3.0), verdict(0.5, feasible=False), verdict(2.0)]):
        assert study.ask(ask).number == n
        tuning.tell(study, n, v)
    nominal_rows = _run_rows(_row(1.0), _row(1.5))
    tuning.write_rows(out, "nominal", nominal_rows)
    result = tuning.write_result(out, tune, study)["result"]
    assert result["best_trial"]["trial"] == 2  # trial 1 is lower but infeasible
    assert result["chosen"]["trial"] == "nominal" and result["chosen"]["objective"] == 1.5
    assert tuning.write_tuned(out, tune, result["chosen"]).exists()
    assert "no trial beat them" in (out / tuning.TUNED).read_text()
    data = tomllib.loads((out / tuning.TUNED).read_text())
    assert {u["name"]: u["gains"]["G_g"] for u in data["unit"]} == \
        {"arm1": [2.0, 2.0, 3.0], "arm2": [1.5, 1.0, 1.0]}  # the scenario's own
    # Nothing feasible (every trial and the nominal at a torque limit): no tuned.toml, and a
    # previous search's is not left to be taken for this one's.
    other = tmp_path / "other"
    tuning.prepare(other, tune)
    study = tuning.open_study(other, tune)
    for n in range(3):
        study.ask(ask)
        tuning.tell(study, n, verdict(1.0 + n, feasible=False))
    tuning.write_rows(other, "nominal", _run_rows(_row(1.0, torque=1.0), _row(1.0)))
    result = tuning.write_result(other, tune, study)["result"]
    assert result["chosen"] is None and result["best_trial"] is None
    assert result["nominal"]["torque_limit_runs"] == 1
    (other / tuning.TUNED).write_text("stale")
    assert not tuning.write_tuned(other, tune, None).exists()
    summary = cochlea_tune.write_report(other, tune, result).read_text()
    assert "No candidate was feasible" in summary and "none feasible" in summary
    assert (other / "history.png").stat().st_size > 0
    # A trial that only ties the nominal gains does not beat them: they stay the result
    # (the earliest trial of the tie was chosen over them).
    tie = tmp_path / "tie"
    tuning.prepare(tie, tune)
    study = tuning.open_study(tie, tune)
    for n, objective in enumerate([1.5, 2.0, 1.5]):
        study.ask(ask)
        tuning.tell(study, n, verdict(objective))
    tuning.write_rows(tie, "nominal", nominal_rows)
    result = tuning.write_result(tie, tune, study)["result"]
    assert result["best_trial"]["trial"] == 0 and result["best_trial"]["objective"] == 1.5
    assert result["nominal"]["objective"] == 1.5
    assert result["chosen"]["trial"] == "nominal", result["chosen"]


@pytest.mark.slow
def test_a_second_search_on_a_running_folder_is_refused(local_tune, tmp_path, capsys):
    """The running search holds the folder's lock: a second one is one line, exit 2, and
    changes nothing in the folder (both would tell Optuna the same trials)."""
    import shutil

    spec, finished = local_tune
    out = tmp_path / "out"
    shutil.copytree(finished, out)
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    fd = tuning.hold(out)
    try:
        assert cochlea_tune.main([str(spec), "--out", str(out), "--workers", "1",
                                  "--progress", "off"]) == 4
    finally:
        tuning.release(out, fd)
    assert "another cochlea-tune is running on this folder" in capsys.readouterr().err
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before


@pytest.mark.parametrize("kept", [0, 1])
def test_a_half_asked_trial_gets_the_params_an_uninterrupted_ask_gives(tmp_path, kept):
    """Optuna's journal records an ask's params one by one: a search killed between two left a
    trial without the rest, and the resumed search failed on the missing key (CI saw it). The
    missing params are drawn again as the first ask drew them."""
    tune = tuning.load(write_spec(tmp_path))
    distributions = tune.distributions()
    assert len(distributions) >= 2
    whole = tmp_path / "whole"
    whole.mkdir()
    study = tuning.open_study(whole, tune)
    for n in range(2):  # trial 1 is drawn with trial 0 in the study, as in a round
        study.sampler = tuning.sampler(tune, n)
        expected = study.ask(distributions).params
    half = tmp_path / "half"
    half.mkdir()
    study = tuning.open_study(half, tune)
    study.sampler = tuning.sampler(tune, 0)
    study.ask(distributions)
    # What the kill leaves of trial 1: the trial and its first `kept` params only.
    storage = study._storage
    trial_id = storage.create_new_trial(study._study_id)
    for name in list(distributions)[:kept]:
        storage.set_trial_param(trial_id, name, distributions[name].to_internal_repr(
            expected[name]), distributions[name])
    tuning.complete_params(study, tune, 1, distributions)
    assert study.get_trials(deepcopy=False)[1].params == expected
