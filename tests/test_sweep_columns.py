"""A sweep's result columns follow the one log schema, ``UNIT.GROUP.ELEMENT_UNIT`` (issue 29,
item 2; docs/logs.md and docs/sweeps.md), and a folder written with the older names
(``final_rms.UNIT.COORD_UNIT``, ``peak_torque.UNIT.JOINT_Nm``, ``torque_ratio.UNIT.JOINT``)
is still read, by every reader (results.read for the report, tune's rows), as the new names.
"""

from __future__ import annotations

import math
import re
import shutil
from pathlib import Path
from types import SimpleNamespace

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from cochlea.apps import cochlea_sweep
from cochlea.sweep import report as sweep_report
from cochlea.sweep import results, tune

ROOT = Path(__file__).resolve().parent.parent
#: A result column of the schema: a unit (no dot), a result group, an element (joints and
#: coordinates may hold dots and primes) and its SI unit.
SCHEMA = re.compile(r"(?P<unit>[A-Za-z0-9_]+)\.(?P<group>final_rms|peak_torque|torque_ratio)\."
                    r"(?P<element>[A-Za-z0-9_.']+?)_(?P<si>rad|m|N_m|N|1)")
#: The SI unit each group may carry.
GROUP_UNITS = {"final_rms": {"rad", "m"}, "peak_torque": {"N_m", "N"}, "torque_ratio": {"1"}}


def summary() -> dict:
    """summary.json's numbers for a serial arm and the parallel mechanism's slider."""
    tracked = {"x": {"final_rms_error": 1e-4, "unit": "m", "initial_abs_error": 0.01},
               "phi": {"final_rms_error": 2e-3, "unit": "rad", "initial_abs_error": 0.1}}
    return {"converged": True, "diverged": False,
            "supervisor": {"rule": "none", "saturated_periods": 0},
            "units": {
                "arm1": {"tracked": tracked, "estimates": {"bounded": True},
                         "torque": {"joint1": {"unit": "N m", "max_abs": 0.5}}},
                "mechanism": {"tracked": {"left.th1": {"final_rms_error": 1e-5, "unit": "rad",
                                                       "initial_abs_error": 0.1}},
                              "estimates": {"bounded": True},
                              "torque": {"slider.d1": {"unit": "N", "max_abs": 20.0},
                                         "left.th1": {"unit": "N m", "max_abs": 1.0}}}}}


LIMITS = {"arm1": {"joint1": 2.5}, "mechanism": {"slider.d1": 100.0, "left.th1": 4.0}}


def result_columns(row: dict) -> list[str]:
    return [c for c in row if any(g in c for g in GROUP_UNITS)]


def check_schema(names: list[str]) -> None:
    assert names
    for name in names:
        m = SCHEMA.fullmatch(name)
        assert m, f"{name}: not UNIT.GROUP.ELEMENT_UNIT"
        assert m["si"] in GROUP_UNITS[m["group"]], name
        assert results.group(name) == m["group"]


def test_a_samples_row_names_its_results_by_the_log_schema():
    row = cochlea_sweep.measures(summary(), LIMITS)
    names = result_columns(row)
    check_schema(names)
    assert row["arm1.final_rms.x_m"] == 1e-4 and row["arm1.final_rms.phi_rad"] == 2e-3
    assert row["arm1.peak_torque.joint1_N_m"] == 0.5
    assert row["mechanism.peak_torque.slider.d1_N"] == 20.0
    assert row["mechanism.torque_ratio.slider.d1_1"] == 0.2
    assert row["mechanism.final_rms.left.th1_rad"] == 1e-5
    # A refused sample (never ran) has the same columns, NaN.
    joints = [SimpleNamespace(name="joint1")]
    unit = SimpleNamespace(name="arm1", controller=SimpleNamespace(space="task"),
                           controller_model=SimpleNamespace(joints=joints),
                           task_names=["x", "phi"], task_units=["m", "rad"],
                           joint_units=["rad"])
    refused = cochlea_sweep.refused([unit])
    assert set(result_columns(refused)) == {c for c in names if c.startswith("arm1.")}
    assert all(math.isnan(refused[c]) for c in result_columns(refused))


LEGACY = {"final_rms.arm1.x_m": "arm1.final_rms.x_m",
          "final_rms.mechanism.C'_u_m": "mechanism.final_rms.C'_u_m",
          "peak_torque.arm1.joint1_Nm": "arm1.peak_torque.joint1_N_m",
          "peak_torque.mechanism.slider.d1_N": "mechanism.peak_torque.slider.d1_N",
          "torque_ratio.mechanism.left.th1": "mechanism.torque_ratio.left.th1_1",
          "convergence_ratio": None, "plant.seed": None, "gains.arm1.G_g[0]": None}


def test_every_legacy_name_has_its_schema_name():
    for old, new in LEGACY.items():
        assert results.legacy_name(old) == new, old
    check_schema([n for n in LEGACY.values() if n])
    # A table already in the schema is never renamed (a unit could be named like a group).
    table = pa.table({"arm1.final_rms.x_m": [1.0], "final_rms.x": [2.0]})
    assert results.upgrade(table).column_names == table.column_names


#: A row's columns besides its results (results.ROW_COLUMNS, every part file has them).
ROW = {"converged": True, "diverged": False, "estimate_bound_hit": False, "stop_rule": "none",
       "stop_time_s": math.nan, "saturated_periods": 0, "wall_s": 0.1}


def legacy_part(samples: range) -> pa.Table:
    n = len(samples)
    return pa.table({"sample": list(samples), "grid": [0] * n, "draw": list(samples),
                     **{k: [v] * n for k, v in ROW.items()}, "success": [True] * n,
                     "convergence_ratio": [0.5] * n,
                     "final_rms.arm1.x_m": [1e-4] * n, "peak_torque.arm1.joint1_Nm": [0.5] * n,
                     "torque_ratio.arm1.joint1": [0.2 + 0.8 * (i == 1) for i in samples]})


def test_a_folder_of_legacy_and_new_part_files_reads_as_one_schema(tmp_path):
    (tmp_path / results.PARTS).mkdir()
    pq.write_table(legacy_part(range(0, 2)),
                   tmp_path / results.PARTS / "part-000000000-000000001.parquet")
    new = cochlea_sweep.measures(summary(), LIMITS)
    new_rows = [{"sample": 2, "grid": 0, "draw": 2, **ROW, "success": True,
                 "convergence_ratio": 0.5,
                 **{k: v for k, v in new.items() if k.startswith("arm1.")}}]
    results.write_part(tmp_path, new_rows)
    table = results.read(tmp_path, 3)
    assert table["sample"].to_pylist() == [0, 1, 2]
    check_schema(results.columns(table.column_names, results.RMS)
                 + results.columns(table.column_names, results.PEAK)
                 + results.columns(table.column_names, results.RATIO))
    assert not [c for c in table.column_names if results.legacy_name(c)]
    # One column per quantity, whole (no old/new pair with the other half null).
    assert table["arm1.torque_ratio.joint1_1"].null_count == 0
    assert table["arm1.peak_torque.joint1_N_m"].to_pylist() == [0.5, 0.5, 0.5]


def test_a_resumed_tune_reads_its_legacy_trial_rows_and_judges_their_limits(tmp_path):
    (tmp_path / tune.SAMPLES).mkdir()
    path = tune.rows_path(tmp_path, 3)
    rows = legacy_part(range(0, 2)).to_pylist()
    for r in rows:
        r.update(stop_rule="none", diverged=False)
    pq.write_table(pa.Table.from_pylist(rows), path)
    read = tune.read_rows(tmp_path, 3, 2)
    assert "arm1.torque_ratio.joint1_1" in read[0] and "torque_ratio.arm1.joint1" not in read[0]
    verdict = tune.judge(read, "worst")
    assert verdict["max_torque_ratio"] == 1.0 and not verdict["feasible"]
    assert verdict["torque_limit_runs"] == 1


@pytest.mark.slow
def test_the_report_of_a_published_legacy_folder_names_the_new_columns(tmp_path):
    """docs/robustness/serial_joint was written with the old names: its report, rewritten
    here on a copy, reads them and names the schema's."""
    folder = tmp_path / "serial_joint"
    shutil.copytree(ROOT / "docs" / "robustness" / "serial_joint", folder)
    old = pq.read_table(folder / results.PARTS).column_names
    assert "final_rms.arm1.joint1_rad" in old  # the published files keep their names
    text = sweep_report.write(folder).read_text()
    assert "| arm1.final_rms.joint1_rad |" in text
    assert "| arm2.torque_ratio.joint3_1 |" in text
    assert "final_rms.arm1" not in text and "torque_ratio.arm" not in text
