"""One schema for every log (issue 29, item 2; docs/logs.md, "Column names and units").

Every writer (cochlea-run as fast as possible and on the sim backend in real time, on the
Dynamixel backend over the emulator, the embedded program) leaves ``log.csv`` and
``log.columns.json`` whose names are exactly :func:`cochlea.log_schema.run_columns` /
``raw_columns`` of the run, each of the pattern and units docs/logs.md documents; the two files
of one run name the same quantity alike; ``schema_version`` is in ``log.columns.json`` and
``summary.json``; the readers (cochlea-mcap's and cochlea-view's run folder, identification)
read logs of this version and of the one before it."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import cochlea
from cochlea import log_schema
from cochlea.export import run_log
from cochlea.ident import logs as ident_logs
from cochlea.robots import ROBOTS
from cochlea.sim import load_scenario, unit_setups

ROOT = Path(__file__).resolve().parent.parent
DOC = (ROOT / "docs" / "logs.md").read_text()
STUDIES = [("serial", "task"), ("parallel", "joint")]


# --------------------------------------------------------------------------------------------
# What docs/logs.md documents
# --------------------------------------------------------------------------------------------


def _section() -> str:
    start = DOC.index("## Column names and units: the one schema of every log")
    return DOC[start:DOC.index("\n## ", start + 1)]


def documented_units() -> set[str]:
    line = next(ln for ln in _section().splitlines() if ln.startswith("units: "))
    para = _section()[_section().index(line):].split("\n\n")[0]
    return set(re.findall(r"`([^`]+)`", para))


def documented_groups() -> set[str]:
    groups = set()
    for line in _section().splitlines():
        if line.startswith("| `"):
            groups |= set(re.findall(r"`([^`]+)`", line.split("|")[1]))
    return groups


def documented_timing() -> list[str]:
    para = next(p for p in _section().split("\n\n") if p.startswith("Run-level columns"))
    return [c for c in re.findall(r"`([^`]+)`", para) if c.endswith("_s")]


def assert_documented(names: list[str], units: list[str]) -> None:
    """Every name is ``time_s``, a documented timing column or ``UNIT.GROUP.ELEMENT_UNIT``
    with a documented group and unit; none twice."""
    assert len(set(names)) == len(names)
    assert names[0] == "time_s"
    groups, suffixes, timing = documented_groups(), documented_units(), documented_timing()
    assert timing == list(log_schema.TIMING_COLUMNS)
    for name in names[1:]:
        if name in timing:
            continue
        unit, group, rest = name.split(".", 2)
        assert unit in units, name
        assert group in groups, name
        assert any(rest.endswith("_" + s) and len(rest) > len(s) + 1 for s in suffixes), name
        assert not rest.endswith("_SI"), name  # every shipped parameter's unit is known


def schema_units(robot: str, space: str) -> list[log_schema.LogUnit]:
    sc = load_scenario(f"{robot}_{space}")
    return [log_schema.LogUnit.of_setup(u, space) for u in unit_setups(sc)]


def header(path: Path) -> list[str]:
    return path.read_text().split("\n", 1)[0].split(",")


def cochlea_run(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_run", *args],
                          capture_output=True, text=True, cwd=cwd, timeout=600)


def assert_same_quantities(csv: list[str], raw: list[str], first_errors: set[str]) -> None:
    """log.bin names each quantity as log.csv does: every raw column is a csv column, but the
    controller's own first error (log.csv logs the wrapped ``error`` instead)."""
    for name in raw:
        if name.split(".")[1:2] and name.split(".")[1] in first_errors:
            continue
        assert name in csv, name


# --------------------------------------------------------------------------------------------
# The schema itself
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("robot,space", STUDIES)
def test_the_schema_names_only_documented_groups_and_units(robot, space):
    units = schema_units(robot, space)
    names = [u.name for u in units]
    for current in (False, True):
        for truth in (False, True):
            csv = log_schema.run_columns(units, timing=True, current=current,
                                         true_state=truth)
            raw = log_schema.raw_columns(units, current=current, true_state=truth)
            assert_documented(csv, names)
            assert_documented(raw, names)
            assert_same_quantities(csv, raw, {u.error_names[0] for u in units})
            assert any(".current." in c for c in csv + raw) == current


@pytest.mark.slow
def test_units_are_written_as_documented():
    assert log_schema.unit_suffix("kg m^2") == "kg_m2"
    assert log_schema.unit_suffix("N m s/rad") == "N_m_s_rad"
    assert log_schema.unit_suffix("kg") == "kg"
    assert log_schema.unit_suffix("") == "SI"
    for robot in ROBOTS:  # every shipped parameterisation's unit is known
        for space in ("joint", "task"):
            for u in unit_setups(load_scenario(f"{robot}_{space}")):
                for unit in u.controller_model.parameters.si_units:
                    assert log_schema.unit_suffix(unit) in documented_units(), unit


# --------------------------------------------------------------------------------------------
# The writers
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("robot,space", STUDIES)
@pytest.mark.slow
def test_an_as_fast_run_writes_the_schema(tmp_path, robot, space):
    out = tmp_path / "run"
    done = cochlea_run("--robot", robot, "--space", space, "--duration", "0.05",
                       "--realtime", "off", "--out", str(out))
    assert done.returncode == 0, done.stderr
    units = schema_units(robot, space)
    csv = header(out / "log.csv")
    assert csv == log_schema.run_columns(units, timing=False, current=False, true_state=True)
    assert_documented(csv, [u.name for u in units])
    assert json.loads((out / "summary.json").read_text())["schema_version"] == \
        log_schema.SCHEMA_VERSION


@pytest.mark.parametrize("robot,space", STUDIES)
@pytest.mark.slow
def test_a_sim_backend_run_writes_the_schema_in_both_files(tmp_path, robot, space):
    out = tmp_path / "run"
    done = cochlea_run("--robot", robot, "--space", space, "--duration", "0.1",
                       "--watchdog-misses", "300", "--out", str(out))
    # The names do not depend on how the run ended (a loaded machine may stop it early).
    assert (out / "log.csv").is_file() and (out / "summary.json").is_file(), done.stderr
    units = schema_units(robot, space)
    csv = header(out / "log.csv")
    columns = json.loads((out / "log.columns.json").read_text())
    assert csv == log_schema.run_columns(units, timing=True, current=False, true_state=True)
    assert columns["schema_version"] == log_schema.SCHEMA_VERSION
    assert columns["columns"] == log_schema.raw_columns(units, current=False, true_state=True)
    assert len(columns["columns"]) == columns["row_length"]
    # The sim backend measures no current: neither file has the columns (log.bin had NaN
    # ones before).
    assert not [c for c in csv + columns["columns"] if ".current." in c]
    assert_same_quantities(csv, columns["columns"], {u.error_names[0] for u in units})
    rows = np.fromfile(out / "log.bin").reshape(-1, columns["row_length"])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["schema_version"] == log_schema.SCHEMA_VERSION
    assert len(rows) == summary["periods"]
    # log.bin's q is log.csv's q, by name.
    data = np.loadtxt(out / "log.csv", delimiter=",", skiprows=1, ndmin=2)
    for name in [c for c in columns["columns"] if ".q." in c]:
        np.testing.assert_allclose(data[:, csv.index(name)],
                                   rows[:, columns["columns"].index(name)], rtol=1e-9)


@pytest.mark.hil
@pytest.mark.parametrize("robot,space", STUDIES)
def test_a_dynamixel_run_and_the_embedded_program_write_the_schema(tmp_path, robot, space):
    from tests.test_dynamixel_hil import emulator, run
    from tests.test_embedded_program import PATIENT, embedded

    make = subprocess.run(["make", "--no-print-directory", "embedded"], cwd=ROOT,
                          capture_output=True, text=True, timeout=900)
    assert make.returncode == 0, make.stderr[-3000:]
    units = schema_units(robot, space)
    name = f"{robot}_{space}"
    py_out, c_out = tmp_path / "py", tmp_path / "c"
    with emulator(robot, name, tmp_path / "py.log") as port:
        run("--robot", robot, "--space", space, "--backend", "dynamixel", "--port", port,
            "--duration", "0.3", "--out", str(py_out), cwd=tmp_path)
    with emulator(robot, name, tmp_path / "c.log") as port:
        embedded(ROOT / "build" / "cochlea-embedded", "--port", port, "--out", str(c_out),
                 "--scenario", name, "--duration", "0.3", *PATIENT)
    raw = log_schema.raw_columns(units, current=True, true_state=False)
    for out, pose in ((py_out, True), (c_out, False)):
        csv = header(out / "log.csv")
        assert csv == log_schema.run_columns(units, timing=True, current=True, pose=pose)
        assert_documented(csv, [u.name for u in units])
        columns = json.loads((out / "log.columns.json").read_text())
        assert columns["columns"] == raw and columns["row_length"] == len(raw)
        assert columns["schema_version"] == log_schema.SCHEMA_VERSION
        assert json.loads((out / "summary.json").read_text())["schema_version"] == \
            log_schema.SCHEMA_VERSION


def test_the_embedded_tables_are_the_schemas():
    """The names compiled into the embedded program (generated_c/embedded/*_scenario.c) are
    the schema's, so its log.csv and log.columns.json are."""
    from cochlea.kernels.embedded import log_columns
    from cochlea.sim.embedded import embedded_units

    for robot, space in STUDIES:
        units = embedded_units(load_scenario(f"{robot}_{space}"))
        csv, raw = log_columns(units)
        text = (ROOT / "generated_c" / "embedded" / f"{robot}_{space}_scenario.c").read_text()
        for table, names in (("log_columns", csv), ("raw_columns", raw)):
            body = text.split(f"static const char *const {table}[{len(names)}] = {{")[1]
            assert re.findall(r'"([^"]*)"', body.split("};")[0]) == names
        assert csv == log_schema.run_columns(schema_units(robot, space), timing=True,
                                             current=True, pose=False)


# --------------------------------------------------------------------------------------------
# The readers: this version and the one before
# --------------------------------------------------------------------------------------------


def as_version_1(folder: Path, out: Path) -> Path:
    """The same run as a log of schema version 1 names it (``Nm``, squeezed units, no
    ``schema_version``)."""
    out.mkdir()
    csv = header(folder / "log.csv")
    old = [re.sub(r"_N_m$", "_Nm", c).replace("_kg_m2", "_kgm2").replace("_kg_m", "_kgm")
           for c in csv]
    body = (folder / "log.csv").read_text().split("\n", 1)[1]
    (out / "log.csv").write_text(",".join(old) + "\n" + body)
    summary = json.loads((folder / "summary.json").read_text())
    del summary["schema_version"]
    (out / "summary.json").write_text(json.dumps(summary))
    return out


@pytest.mark.parametrize("robot,space", STUDIES)
@pytest.mark.slow
def test_readers_read_this_version_and_the_one_before(tmp_path, robot, space):
    out = tmp_path / "run"
    done = cochlea_run("--robot", robot, "--space", space, "--duration", "0.05",
                       "--realtime", "off", "--out", str(out))
    assert done.returncode == 0, done.stderr
    old = as_version_1(out, tmp_path / "old")
    assert "_Nm" in (old / "log.csv").read_text().split("\n", 1)[0] or robot == "parallel"
    model = cochlea.model(robot)
    results = []
    for folder in (out, old):
        run = run_log.open_run(folder)
        rows = np.concatenate(list(run.chunks()))
        assert len(rows) == 50
        assert [u.name for u in run.units] == [u.name for u in schema_units(robot, space)]
        for u in run.units:
            assert {"q", "qd", "tau", "p_hat"} <= set(u.groups)
        per_unit = []
        for u in run.units:
            log = ident_logs.read_run(folder, model, robot, u.name)
            per_unit.append((log.q, log.qd, log.tau))
        results.append(per_unit)
    for new_unit, old_unit in zip(*results):
        for a, b in zip(new_unit, old_unit):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("version", [log_schema.SCHEMA_VERSION + 1, 0, "2", True])
@pytest.mark.slow
def test_a_log_of_an_unknown_schema_version_is_refused_in_one_line(tmp_path, version):
    out = tmp_path / "run"
    done = cochlea_run("--robot", "serial", "--space", "joint", "--duration", "0.05",
                       "--realtime", "off", "--out", str(out))
    assert done.returncode == 0, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    summary["schema_version"] = version
    (out / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(run_log.RunFolderError, match="schema_version"):
        run_log.open_run(out)
    with pytest.raises(ident_logs.LogError, match="schema_version"):
        ident_logs.read_run(out, cochlea.model("serial"), "serial", "arm1")
    mcap = tmp_path / "x.mcap"
    done = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_mcap", str(out),
                           "--out", str(mcap)], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "schema_version" in done.stderr and not mcap.exists()
    done = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_identify", str(out),
                           "--robot", "serial", "--out", str(tmp_path / "i.json")],
                          capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "schema_version" in done.stderr and not (tmp_path / "i.json").exists()
