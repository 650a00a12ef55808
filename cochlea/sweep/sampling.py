"""Each sample's inputs, and the exact scenario file of a sample.

Sample ``i`` is grid point ``i // samples`` and draw ``k = i % samples``. Every random input of
draw ``k`` comes from ``SeedSequence(seed, spawn_key=(k, crc32(name)))`` alone (numpy's spawn
tree, addressed directly): a sample is replayed without drawing the ones before it, adding a
key to the spec leaves the other keys' draws as they were, and every grid point meets the same
perturbations (common random numbers: differences between gains are not sampling noise).
The plant's noise seed is drawn the same way unless the spec fixes ``[perturb] seed``.
"""

from __future__ import annotations

import functools
import itertools
import math
import tomllib
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from ..sim.scenario import CROSS_KEYS
from ..text import comment, toml_string
from .spec import Entry, Spec

#: Draws of a truncated normal before giving up (a mean far outside the range).
MAX_REJECTIONS = 10_000


def grid_point(spec: Spec, i: int) -> tuple[int, int]:
    """``(grid point, draw)`` of sample ``i``."""
    if not 0 <= i < spec.total:
        raise IndexError(i)
    return divmod(i, spec.samples)


@functools.lru_cache(maxsize=1024)
def _name_key(name: str) -> int:
    return zlib.crc32(name.encode())


def _rng(spec: Spec, k: int, name: str) -> np.random.Generator:
    # What np.random.default_rng makes of a SeedSequence, without its checks.
    return np.random.Generator(np.random.PCG64(
        np.random.SeedSequence(spec.seed, spawn_key=(k, _name_key(name)))))


def _draw(e: Entry, rng: np.random.Generator) -> Any:
    n = e.rule.size if e.each else None
    a, b = e.args
    if e.kind == "uniform":
        if e.rule.kind == "int":
            v = rng.integers(a, b, endpoint=True, size=n)
            return [int(x) for x in v] if n else int(v)
        while True:  # [lo, hi), and the loader may exclude lo (mass_scale > 0)
            v = rng.uniform(a, b, size=n)
            values = [float(x) for x in np.atleast_1d(v)]
            if all(e.rule.scalar_ok(x) for x in values):
                return values if n else values[0]
    for _ in range(MAX_REJECTIONS):  # normal, truncated to the key's valid range
        values = [float(x) for x in np.atleast_1d(rng.normal(a, b, size=n))]
        if all(e.rule.scalar_ok(x) for x in values):
            return values if n else values[0]
    raise ValueError(f"{e.name}: normal {e.args} is almost never inside the key's range")


def inputs(spec: Spec, i: int) -> dict[str, Any]:
    """The inputs of sample ``i`` by entry name (``plant.<key>``, ``gains.<unit>.<key>``),
    plus ``plant.seed`` (the plant's noise seed)."""
    g, k = grid_point(spec, i)
    out: dict[str, Any] = {}
    for e in spec.entries:  # the grids in spec order, the first varying slowest
        if e.kind == "grid":
            stride = math.prod(len(x.args) for x in spec.grid[spec.grid.index(e) + 1:])
            out[e.name] = e.args[(g // stride) % len(e.args)]
        elif e.kind == "fixed":
            out[e.name] = e.args[0]
        elif e.kind == "choice":
            out[e.name] = e.args[int(_rng(spec, k, e.name).integers(len(e.args)))]
        else:
            out[e.name] = _draw(e, _rng(spec, k, e.name))
    if "plant.seed" not in out:
        state = np.random.SeedSequence(spec.seed, spawn_key=(k,)).generate_state(2, np.uint32)
        out["plant.seed"] = (int(state[0]) << 31) | (int(state[1]) >> 1)  # below 2**63
    return out


def cases(spec: Spec) -> list[dict[str, Any]]:
    """Inputs (as :func:`inputs` gives them) that together meet every rule between
    ``[plant]`` keys the scenario loader has, for every sample the spec can give: sample 0's
    inputs with the keys those rules read (:data:`cochlea.sim.scenario.CROSS_KEYS`) set to
    every combination of the values the spec gives them (a fixed value; each value of a
    choice or grid, drawn or not; both ends of an integer range), an integer key's smallest
    and largest value standing for the rest (the rules on integers are thresholds). The other
    keys meet no rule but their own range, which the spec's loader checks."""
    base = inputs(spec, 0)
    names, options = [], []
    for e in spec.entries:
        if not e.name.startswith("plant.") or e.name[len("plant."):] not in CROSS_KEYS:
            continue
        # Every such key is a flag, a preset or an integer: fixed, a choice, a grid or an
        # integer range (no normal), its values in args.
        values = list(dict.fromkeys(e.args))
        if e.rule.kind == "int":
            values = sorted({min(values), max(values)})
        names.append(e.name)
        options.append(values)
    return [{**base, **dict(zip(names, combo))} for combo in itertools.product(*options)]


def _vector(value: Any, size: int | None) -> Any:
    if size is not None and not isinstance(value, list):
        return [value] * size
    return value


@functools.lru_cache(maxsize=8)
def _base_data(text: str) -> dict:
    """A base scenario's TOML data, parsed once per process and text (never handed out
    itself: each sample gets a deep copy)."""
    return tomllib.loads(text)


def _copy(value: Any) -> Any:
    """A copy of TOML data (tables, arrays, scalars), nothing shared: what ``copy.deepcopy``
    gives for it, in a fraction of the time (a sweep copies its base scenario every sample)."""
    if isinstance(value, dict):
        return {k: _copy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_copy(v) for v in value]
    return value  # str, int, float, bool, dates: immutable


@functools.lru_cache(maxsize=64)
def _description_path(folder: Path, description: str) -> str:
    """A scenario's ``description`` as its samples name it: a user's description file by its
    absolute path (found from anywhere), a shipped robot's name as it is. Resolved once per
    process and absolute ``folder`` (every sample of a sweep names the same file)."""
    path = Path(description)
    if path.suffix == ".toml" or path.parent != Path("."):
        return str((folder / path).resolve() if not path.is_absolute() else path)
    return description


def scenario_data(spec: Spec, i: int, values: dict[str, Any] | None = None) -> dict:
    """The base scenario's TOML data with sample ``i``'s plant, gains and duration
    (``values``: its :func:`inputs`, when the caller has them already): what
    :func:`scenario_text` reads as (``tomllib.loads``), a new object every call."""
    data = _copy(_base_data(spec.scenario_text))
    description = data.get("description")
    if isinstance(description, str):  # a user's description file: found from anywhere
        folder = spec.scenario_path.parent
        data["description"] = _description_path(folder, description) if folder.is_absolute() \
            else _description_path.__wrapped__(folder, description)  # cwd may change
    if spec.duration is not None:
        data["duration_s"] = spec.duration
    plant = data.setdefault("plant", {})
    rules = {e.name: e.rule for e in spec.entries}
    units = {u["name"]: u for u in data.get("unit", [])}
    for name, value in (inputs(spec, i) if values is None else values).items():
        parts = name.split(".")
        if parts[0] == "plant":
            rule = rules.get(name)
            plant[parts[1]] = _vector(value, rule.size if rule else None)
        else:
            units[parts[1]].setdefault("gains", {})[parts[2]] = _vector(value, rules[name].size)
    return data


def scenario_text(spec: Spec, i: int, values: dict[str, Any] | None = None) -> str:
    """Sample ``i``'s scenario file: ``cochlea-run --scenario`` on it runs exactly the sample
    (``values``: its :func:`inputs`, when the caller has them already)."""
    g, k = grid_point(spec, i)
    head = (f"# Sample {i} (grid point {g}, draw {k}) of the sweep {comment(spec.path.name)} "
            f"(seed {spec.seed}), from {comment(spec.scenario_path.name)}.\n"
            f"# cochlea-run --robot {spec.robot} --space {spec.space} --scenario THIS_FILE "
            "--realtime off\n\n")
    return head + dumps(scenario_data(spec, i, values))


# --------------------------------------------------------------------------------------------
# A TOML writer for scenario data (strings, numbers, booleans, lists, tables)
# --------------------------------------------------------------------------------------------


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"{v} has no place in a scenario")
        return repr(v)  # the shortest text that reads back as the same double
    if isinstance(v, str):
        return toml_string(v)  # JSON's escapes are not all TOML's (non-BMP, DEL)
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _key(k: str) -> str:
    bare = k and all(c.isascii() and (c.isalnum() or c in "_-") for c in k)
    return k if bare else toml_string(k)


def _is_tables(v: Any) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def dumps(data: dict) -> str:
    """TOML text that ``tomllib.loads`` reads back equal to ``data`` (floats exactly)."""
    lines = [f"{_key(k)} = {_value(v)}" for k, v in data.items()
             if not isinstance(v, dict) and not _is_tables(v)]
    for k, v in data.items():
        if isinstance(v, dict):
            lines += ["", f"[{_key(k)}]"] + [f"{_key(a)} = {_value(b)}" for a, b in v.items()]
    for k, v in data.items():
        if _is_tables(v):
            for table in v:
                lines += ["", f"[[{_key(k)}]]"]
                lines += [f"{_key(a)} = {_value(b)}" for a, b in table.items()]
    return "\n".join(lines) + "\n"
