"""A batch's samples through their phases in groups (cochlea_sweep.evaluate_many, which
cochlea.sweep.execute.run_batch calls): every scenario read and set up, then every closed loop,
then every verdict and row, so that the interpreter pays once a group, not once a sample, for
the caches the C loop took (issue 30 item 3). Each sample's row is the one evaluate() gives it
alone, bit for bit, refused samples included, whatever the grouping."""

from __future__ import annotations

import functools
import math

import pytest

from cochlea.apps import cochlea_sweep
from cochlea.sweep import execute, sampling
from cochlea.sweep import spec as sweep_spec

# payload_kg 2.0 is more than the mechanism's motors hold at its start (GravityRefused): a row
# made before the closed loop, in the middle of a group.
SPEC = """format = "cochlea-sweep/1"
scenario = "parallel_joint"
samples = 7
seed = 3
duration_s = 0.05

[perturb]
payload_kg = {choice = [0.0, 0.01, 2.0]}
mass_scale = {uniform = [0.9, 1.1]}
"""


@pytest.fixture(scope="module")
def spec(tmp_path_factory):
    path = tmp_path_factory.mktemp("groups") / "spec.toml"
    path.write_text(SPEC)
    return sweep_spec.load(path)


def _plain(row: dict) -> dict:
    return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in row.items()
            if k != "wall_s"}


@pytest.mark.parametrize("periods, samples", [(10**9, 16), (60, 16), (10**9, 2), (1, 1)])
def test_grouped_rows_are_each_sample_alone(spec, monkeypatch, periods, samples):
    alone = [_plain(cochlea_sweep.evaluate(sampling.scenario_data(spec, i)))
             for i in range(spec.total)]
    assert any(r["stop_rule"] == cochlea_sweep.GRAVITY_RULE for r in alone)
    assert any(r["stop_rule"] != cochlea_sweep.GRAVITY_RULE for r in alone)
    monkeypatch.setattr(cochlea_sweep, "GROUP_PERIODS", periods)
    monkeypatch.setattr(cochlea_sweep, "GROUP_SAMPLES", samples)
    for evaluate in (cochlea_sweep.evaluate,
                     functools.partial(cochlea_sweep.evaluate, kernels="c")):
        rows = execute.run_batch(spec, list(range(spec.total)), evaluate)
        assert [r["sample"] for r in rows] == list(range(spec.total))
        assert all(r["wall_s"] > 0 for r in rows)
        for row, want in zip(rows, alone, strict=True):
            got = _plain(row)
            assert {k: got[k] for k in want} == want


def test_the_phases_go_group_by_group(spec, monkeypatch):
    """With groups of three: three scenarios set up, their three loops, their three rows."""
    events = []
    for name in ("_prepare", "_run", "_judge"):
        original = getattr(cochlea_sweep, name)

        def spy(*args, _original=original, _name=name, **kw):
            events.append(_name[1])
            return _original(*args, **kw)

        monkeypatch.setattr(cochlea_sweep, name, spy)
    monkeypatch.setattr(cochlea_sweep, "GROUP_SAMPLES", 3)
    datas = [sampling.scenario_data(spec, i) for i in range(spec.total)]
    refused = [cochlea_sweep.evaluate_many([d])[0][0]["stop_rule"] == cochlea_sweep.GRAVITY_RULE
               for d in datas]
    events.clear()
    cochlea_sweep.evaluate_many(datas)
    expected = []
    for start in range(0, spec.total, 3):
        group = range(start, min(start + 3, spec.total))
        expected += ["p"] * len(group)
        expected += ["r" for i in group if not refused[i]]
        expected += ["j" for i in group if not refused[i]]
    assert "".join(events) == "".join(expected)


def test_a_partial_that_binds_the_sample_runs_one_sample_after_the_other(spec):
    assert execute._many(functools.partial(cochlea_sweep.evaluate, {})) is None
    assert execute._many(cochlea_sweep.evaluate) is cochlea_sweep.evaluate_many
    assert execute._many(lambda data: {}) is None
