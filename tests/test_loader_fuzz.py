"""Fuzz of the description and scenario loaders (issue 13): files built from the shipped ones
with hostile values put in -- wrong types, NaN and infinities, huge and negative numbers,
unicode, deep nesting, missing and extra keys, bad formulas, broken bytes. Loading either
succeeds or raises :class:`~cochlea.errors.CochleaError`; nothing else may escape.

10 000 generated files in all (four tests of 2 500), derandomized so every run tries the same
ones; the loaders are called directly (no subprocess, no model built)."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path  # noqa: F401  (annotations)

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cochlea.errors import CochleaError
from cochlea.resources import ROBOTS_DIR, SCENARIOS_DIR
from cochlea.robots.parallel.description import load_parallel
from cochlea.robots.serial.description import load_serial
from cochlea.sim.scenario import load as load_scenario

EXAMPLES = int(__import__("os").environ.get("FUZZ_N", 2500))  # per test; four tests
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                suppress_health_check=list(HealthCheck))

SHIPPED = {
    "serial": tomllib.loads((ROBOTS_DIR / "serial.toml").read_text()),
    "parallel": tomllib.loads((ROBOTS_DIR / "parallel.toml").read_text()),
    "serial_joint": tomllib.loads((SCENARIOS_DIR / "serial_joint.toml").read_text()),
    "serial_task": tomllib.loads((SCENARIOS_DIR / "serial_task.toml").read_text()),
    "parallel_joint_realistic": tomllib.loads(
        (SCENARIOS_DIR / "parallel_joint_realistic.toml").read_text()),
    "parallel_task": tomllib.loads((SCENARIOS_DIR / "parallel_task.toml").read_text()),
}
LOADERS = {"serial": load_serial, "parallel": load_parallel}

# -- writing TOML (tomllib only reads) --------------------------------------------------------


class Deep:
    """A list nested ``depth`` deep, written out as text (no recursion in the test itself)."""

    def __init__(self, depth: int):
        self.depth = depth


def _value(v) -> str:
    if isinstance(v, Deep):
        return "[" * v.depth + "1.0" + "]" * v.depth
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string (a lone surrogate makes it invalid TOML)
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {_value(x)}" for k, x in v.items()) + "}"
    return json.dumps(str(v))


def to_toml(data: dict) -> str:
    """Every top-level key on its line, everything below it inline (arrays of inline tables
    are TOML too)."""
    return "".join(f"{json.dumps(str(k))} = {_value(v)}\n" for k, v in data.items())


# -- hostile values ---------------------------------------------------------------------------

FORMULAS = st.sampled_from([
    "1/0 deg", "10**400 m", "sin(t, 1) deg", "atan2(t) rad", "t" + "+t" * 1200 + " m",
    "sqrt(-1) deg", "exp(1000) m", "1e400 deg", "sin(" * 120 + "t" + ")" * 120 + " rad",
    "__import__('os') m", "t % 2 deg", "lambda: 1 deg", "1/(t-t) m", "x deg", "t deg furlong",
    "", " ", "deg", "\x00 m", "(" * 300 + "t" + ")" * 300 + " deg", "1/(t - 0.5) deg",
    "exp(100*t) deg", "sqrt(t - 1) deg", "0.01*t m", "81 deg", "-1e308*t*t deg",
])
NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.sampled_from([0, -1, 1e300, -1e300, 1e-300, 5e-324, 2**63, -(2**63) - 1, 1e12, 1e6]),
)
SCALARS = st.one_of(
    NUMBERS, st.booleans(), FORMULAS,
    st.text(max_size=30),
    st.sampled_from(["nan", "inf", "-inf", "1e999", "NaN deg", "\u00e9\u4e2d\U0001f600", "\ud800",
                     "serial", "parallel", "joint", "task", "/dev/zero", "/", "..", "a" * 5000,
                     "cochlea-robot/1", "cochlea-scenario/1", "MX-64"]),
)
HOSTILE = st.recursive(SCALARS, lambda inner: st.one_of(
    st.lists(inner, max_size=6), st.dictionaries(st.text(max_size=10), inner, max_size=4)),
    max_leaves=12)


def _containers(data, path=()):
    """Every (path, container) inside ``data``, the top level first."""
    yield path, data
    items = data.items() if isinstance(data, dict) else enumerate(data)
    for k, v in items:
        if isinstance(v, (dict, list)):
            yield from _containers(v, (*path, k))


@st.composite
def mutated(draw, name: str) -> bytes:
    """The shipped file ``name`` with one to four mutations, written out as bytes."""
    data = json.loads(json.dumps(SHIPPED[name]))  # a deep copy
    for _ in range(draw(st.integers(1, 4))):
        places = list(_containers(data))
        _, where = places[draw(st.integers(0, len(places) - 1))]
        keys = list(where.keys()) if isinstance(where, dict) else list(range(len(where)))
        action = draw(st.sampled_from(["replace", "replace", "replace", "delete", "add",
                                       "deep", "number"]))
        if not keys and action != "add":
            action = "add"
        key = draw(st.sampled_from(keys)) if keys else None
        if action == "replace":
            where[key] = draw(HOSTILE)
        elif action == "number":
            where[key] = draw(NUMBERS)
        elif action == "deep":
            where[key] = Deep(draw(st.sampled_from([5, 33, 200, 3000])))
        elif action == "delete":
            del where[key]
        elif isinstance(where, dict):
            where[draw(st.text(max_size=12))] = draw(HOSTILE)
        else:
            where.append(draw(HOSTILE))
    text = to_toml(data)
    encoding = draw(st.sampled_from(["utf-8"] * 8 + ["latin-1", "utf-16", "cut"]))
    if encoding == "cut":  # a file cut at an arbitrary byte
        raw = text.encode("utf-8", "surrogatepass")
        return raw[:draw(st.integers(0, len(raw)))]
    return text.encode(encoding, "surrogatepass" if encoding == "utf-8" else "replace")


def _load_or_refuse(loader, path: Path) -> None:
    try:
        loader(path)
    except CochleaError as exc:
        message = str(exc)
        assert message and "\n" not in message, message


@pytest.mark.parametrize("robot", ["serial", "parallel"])
@pytest.mark.slow
def test_description_loader_refuses_or_loads(robot, tmp_path):
    target = tmp_path / f"{robot}.toml"

    @FUZZ
    @given(mutated(robot))
    def fuzz(raw):
        target.write_bytes(raw)
        _load_or_refuse(LOADERS[robot], target)

    fuzz()


@pytest.mark.parametrize("pair", [("serial_joint", "serial_task"),
                                  ("parallel_joint_realistic", "parallel_task")])
@pytest.mark.slow
def test_scenario_loader_refuses_or_loads(pair, tmp_path):
    target = tmp_path / "scenario.toml"

    @FUZZ
    @given(st.sampled_from(pair).flatmap(mutated))
    def fuzz(raw):
        target.write_bytes(raw)
        _load_or_refuse(load_scenario, target)

    fuzz()


def test_the_generator_keeps_valid_structure_often_enough(tmp_path):
    """The fuzz is worth its count only if many files get past the first keys: the unmutated
    files written by to_toml load, and a deleted optional key still loads."""
    for name in ("serial", "parallel"):
        path = tmp_path / f"{name}.toml"
        path.write_text(to_toml(SHIPPED[name]))
        LOADERS[name](path)
    for name in ("serial_joint", "parallel_task"):
        data = json.loads(json.dumps(SHIPPED[name]))
        del data["control"]["variant"]
        path = tmp_path / f"{name}.toml"
        path.write_text(to_toml(data))
        assert load_scenario(path).variant == "corrected"
