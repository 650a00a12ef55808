"""A sweep's spec (``cochlea-sweep SPEC.toml``): which scenario, how its plant and gains vary,
how many samples, from which seed. Validated like the scenarios: a wrong key or value is one
:class:`~cochlea.errors.DescriptionError` naming the spec file and the key.

    format = "cochlea-sweep/1"
    scenario = "serial_task"          # a shipped scenario's name, or a path (relative: to the spec)
    samples = 200                     # Monte Carlo draws (per point of the grids)
    seed = 1
    duration_s = 5.0                  # optional: overrides the scenario's

    [perturb]                         # any key of the scenario's [plant] table
    mass_scale = {uniform = [0.7, 1.3]}          # one factor for every body ...
    payload_kg = {uniform = [0.0, 0.05]}
    delay_periods = {choice = [0, 1, 2]}
    noise_q_std_SI = 1e-4                        # a fixed value

    [gains.arm1]                      # [gains.<unit>]: any gain of that unit
    G_g = {grid = [1.0, 2.0, [2.0, 2.0, 3.0]]}  # a number is every component

A distribution is ``{uniform = [lo, hi]}``, ``{normal = [mu, sigma]}`` (truncated to the key's
valid range), ``{choice = [...]}`` or ``{grid = [...]}``; ``each = true`` on a uniform or
normal of a vector key draws every component on its own instead of one shared factor.
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import DescriptionError
from ..robots import robot as robot_adapter
from ..robots.description import Table, read_toml
from ..sim import load_scenario
from ..sim import scenario as sc_mod
from ..sim.setup import MAX_FAST_PERIODS

FORMAT = "cochlea-sweep/1"
#: Samples one sweep may hold (grid points times draws): a row each in memory for the report
#: and the bookkeeping of which are done (about 1 GB at this size); refused up front beyond.
MAX_SAMPLES = 1_000_000
#: A normal's draws must land in the key's range at least this often (it is truncated there
#: by rejection, :data:`cochlea.sweep.sampling.MAX_REJECTIONS` draws at most): checked up front.
MIN_NORMAL_ACCEPTANCE = 0.01
DISTRIBUTIONS = ("uniform", "normal", "choice", "grid")


@dataclass(frozen=True)
class KeyRule:
    """What a varied key accepts: a kind ("float", "int", "bool", "preset"), its valid range
    (``lo_open``: the low end excluded) and its vector size (None: a scalar)."""

    kind: str
    lo: float = 0.0
    hi: float = 0.0
    lo_open: bool = False
    size: int | None = None

    def text(self) -> str:
        if self.kind == "bool":
            return "true or false"
        if self.kind == "preset":
            return "one of " + ", ".join(repr(p) for p in sc_mod.PLANT_PRESETS)
        what = "an integer" if self.kind == "int" else "a number"
        interval = self.interval()
        if self.size is None:
            return f"{what} in {interval}"
        return f"{what} in {interval} (every component), or a list of {self.size} of them"

    def interval(self) -> str:
        """The valid range of a number key, e.g. ``(0, 10]``."""
        return f"{'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}]"

    def acceptance(self, mu: float, sigma: float) -> float:
        """The probability that a draw of normal(mu, sigma) is in the key's range."""
        def cdf(x: float) -> float:
            return 0.5 * math.erfc(-(x - mu) / (sigma * math.sqrt(2.0)))
        return max(0.0, cdf(self.hi) - cdf(self.lo))

    def scalar_ok(self, v: Any) -> bool:
        if self.kind == "bool":
            return isinstance(v, bool)
        if self.kind == "preset":
            return isinstance(v, str) and v in sc_mod.PLANT_PRESETS
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return False
        if self.kind == "int" and not isinstance(v, int):
            return False
        low = v > self.lo if self.lo_open else v >= self.lo
        return bool(low and v <= self.hi)

    def normal(self, v: Any) -> Any:
        """``v`` (already checked) with a float key's integers as floats: ``0`` and ``0.0``
        are the same value, and a column of the rows must have one type (Parquet refuses to
        merge int64 with double: a grid of backlash lists written ``[0, 0, ...]`` and
        ``[0.0017, ...]`` failed the report)."""
        if self.kind != "float":
            return v
        return [float(x) for x in v] if isinstance(v, list) else float(v)

    def value_ok(self, v: Any) -> bool:
        if self.size is not None and isinstance(v, list):
            return len(v) == self.size and all(self.scalar_ok(x) for x in v)
        return self.scalar_ok(v)


def plant_rules(n_bodies: int, n_joint: int) -> dict[str, KeyRule]:
    """Every key of a scenario's ``[plant]`` table, with the loader's own bounds."""
    friction = KeyRule("float", 0.0, sc_mod.MAX_FRICTION, size=n_joint)
    return {
        "plant": KeyRule("preset"),
        "mass_scale": KeyRule("float", 0.0, sc_mod.MAX_MASS_SCALE, True, n_bodies),
        "payload_kg": KeyRule("float", 0.0, sc_mod.MAX_PAYLOAD_KG),
        "viscous_friction_SI": friction,
        "coulomb_friction_SI": friction,
        "noise_q_std_SI": KeyRule("float", 0.0, sc_mod.MAX_NOISE_Q),
        "noise_qd_std_SI": KeyRule("float", 0.0, sc_mod.MAX_NOISE_QD),
        "delay_periods": KeyRule("int", 0, sc_mod.MAX_DELAY_PERIODS),
        "seed": KeyRule("int", 0, 2**63 - 1),
        "position_encoder": KeyRule("bool"),
        "velocity_register": KeyRule("bool"),
        "current_quantisation": KeyRule("bool"),
        "armature": KeyRule("bool"),
        # The gearbox (issue 24): backlash (rad or m at each joint), the gear's stiffness and
        # damping, static over Coulomb friction and its Stribeck velocity.
        "gearbox": KeyRule("bool"),
        "backlash_SI": KeyRule("float", 0.0, sc_mod.MAX_BACKLASH, size=n_joint),
        "gear_stiffness_SI": KeyRule("float", 0.0, sc_mod.MAX_GEAR_STIFFNESS, True, n_joint),
        "gear_damping_SI": KeyRule("float", 0.0, sc_mod.MAX_FRICTION, size=n_joint),
        "static_friction_ratio": KeyRule("float", 1.0, sc_mod.MAX_STATIC_FRICTION_RATIO),
        "stribeck_velocity_SI": KeyRule("float", 0.0, sc_mod.MAX_STRIBECK_VELOCITY, True,
                                        n_joint),
        # Issue 24's other disturbances: delay jitter, encoder noise in counts, Kt error.
        "delay_jitter_periods": KeyRule("int", 0, sc_mod.MAX_DELAY_PERIODS),
        "encoder_noise_counts": KeyRule("int", 0, sc_mod.MAX_ENCODER_NOISE_COUNTS),
        "torque_constant_error": KeyRule("float", -sc_mod.MAX_TORQUE_CONSTANT_ERROR,
                                         sc_mod.MAX_TORQUE_CONSTANT_ERROR, size=n_joint),
    }


@dataclass(frozen=True)
class Entry:
    """One varied input: ``name`` is ``plant.<key>`` or ``gains.<unit>.<key>``."""

    name: str
    rule: KeyRule
    kind: str  # "fixed" or one of DISTRIBUTIONS
    args: tuple  # fixed: (value,); uniform/normal: (a, b); choice/grid: the values
    each: bool = False

    @property
    def vector(self) -> bool:
        """Whether a sample's value is a list (else one scalar, broadcast to a vector key)."""
        if self.each:
            return True
        values = self.args if self.kind in ("fixed", "choice", "grid") else ()
        return any(isinstance(v, list) for v in values)


@dataclass(frozen=True)
class Spec:
    path: Path
    text: str  # the spec file as written
    scenario_path: Path
    scenario_text: str  # the base scenario file, kept so a sweep folder replays on its own
    robot: str
    space: str
    samples: int  # draws per grid point
    seed: int
    duration: float | None
    entries: tuple[Entry, ...]

    @property
    def grid(self) -> tuple[Entry, ...]:
        return tuple(e for e in self.entries if e.kind == "grid")

    @property
    def total(self) -> int:
        n = self.samples
        for e in self.grid:
            n *= len(e.args)
        return n

    @property
    def digest(self) -> str:
        """What makes two sweeps the same: the spec and the base scenario, as read."""
        blob = json.dumps([tomllib.loads(self.text), self.scenario_text], sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()


def _entry(t: Table, key: str, rule: KeyRule, name: str) -> Entry:
    value = t.data[key]
    t.used.add(key)
    where = t.key(key)
    expected = (f"{rule.text()}, or a distribution: " + ", ".join(f"{{{d} = [...]}}"
                                                                 for d in DISTRIBUTIONS))
    if not isinstance(value, dict):
        if not rule.value_ok(value):
            raise DescriptionError(t.path, where, expected, value)
        return Entry(name, rule, "fixed", (rule.normal(value),))
    kinds = [d for d in DISTRIBUTIONS if d in value]
    unknown = sorted(set(value) - set(DISTRIBUTIONS) - {"each"})
    if unknown or len(kinds) != 1:
        raise DescriptionError(t.path, f"{where}.{unknown[0]}" if unknown else where,
                               "exactly one of " + ", ".join(DISTRIBUTIONS)
                               + " (and each = true for a vector key)", value)
    kind = kinds[0]
    args = value[kind]
    each = value.get("each", False)
    if not isinstance(each, bool) or (each and (rule.size is None
                                                or kind not in ("uniform", "normal"))):
        raise DescriptionError(t.path, f"{where}.each", "true or false, and true only on a "
                               "uniform or normal of a vector key", each)
    at = f"{where}.{kind}"
    if kind in ("choice", "grid"):
        if not isinstance(args, list) or not args:
            raise DescriptionError(t.path, at, f"a non-empty list of values, each {rule.text()}",
                                   args)
        for i, v in enumerate(args):
            if not rule.value_ok(v):
                raise DescriptionError(t.path, f"{at}[{i}]", rule.text(), v)
        return Entry(name, rule, kind, tuple(rule.normal(v) for v in args))
    if rule.kind in ("bool", "preset"):
        raise DescriptionError(t.path, at, f"choice or grid ({rule.text()}): {kind} needs a "
                               "number", args)
    number = rule.kind == "int" and kind == "uniform"
    if not (isinstance(args, list) and len(args) == 2
            and all(isinstance(a, (int, float)) and not isinstance(a, bool)
                    and math.isfinite(a) for a in args)
            and (not number or all(isinstance(a, int) for a in args))):
        raise DescriptionError(t.path, at, "two finite " + ("integers" if number else "numbers")
                               + (" [lo, hi]" if kind == "uniform" else " [mu, sigma]"), args)
    a, b = args
    if kind == "uniform":
        if not a < b:
            raise DescriptionError(t.path, at, "a non-empty range [lo, hi] with lo < hi (a "
                                   "fixed value is written without a distribution)", args)
        if not (rule.scalar_ok(a) and rule.scalar_ok(b)):
            raise DescriptionError(t.path, at, f"a range inside the key's: {rule.text()}", args)
    else:
        if rule.kind == "int":
            raise DescriptionError(t.path, at, "uniform, choice or grid (an integer key)", args)
        if not (b > 0 and rule.scalar_ok(a)):
            raise DescriptionError(t.path, at, f"[mu, sigma] with sigma > 0 and mu in "
                                   f"{rule.interval()} (the key's range)", args)
        # each = true redraws the whole vector until every component is in range.
        p = rule.acceptance(float(a), float(b)) ** (rule.size if each else 1)
        if not p >= MIN_NORMAL_ACCEPTANCE:
            raise DescriptionError(t.path, at, f"[mu, sigma] whose draws fall in the key's "
                                   f"range {rule.interval()} at least "
                                   f"{MIN_NORMAL_ACCEPTANCE:.0%} of the time (the normal is "
                                   f"truncated there; this one: {p:.2g}): a smaller sigma",
                                   args)
    return Entry(name, rule, kind, (a, b), each)


def _scenario_path(spec_path: Path, name: str) -> Path:
    resolved = sc_mod.resolve(name)
    if resolved == Path(name) and not resolved.is_absolute():
        return (spec_path.parent / resolved).resolve()  # a user's path: next to the spec
    return resolved


def load(path: str | Path, scenario_file: Path | None = None, *,
         own_tables: tuple[str, ...] = ()) -> Spec:
    """Read and check a sweep spec; the scenario it names is loaded (and so checked) too.
    ``scenario_file``: read the base scenario from there instead (a sweep folder's copy).
    ``own_tables``: top-level keys the caller reads and checks itself (cochlea-tune's
    ``[tune]``); any other unknown key is refused."""
    path = Path(path)
    data = read_toml(path, "sweep spec")
    text = path.read_text(encoding="utf-8")
    top = Table(path, data, "")
    top.get("format", f"the string {FORMAT!r}", lambda v: v == FORMAT)
    name = top.string("scenario")
    samples = top.get("samples", f"a positive integer (draws per grid point, at most "
                      f"{MAX_SAMPLES:,} samples in all)", lambda v: isinstance(v, int)
                      and not isinstance(v, bool) and 0 < v <= MAX_SAMPLES)
    seed = top.get("seed", "a non-negative integer below 2**63", lambda v: isinstance(v, int)
                   and not isinstance(v, bool) and 0 <= v < 2**63)
    duration = top.number("duration_s", "a positive number (s)", lambda v: v > 0,
                          required=False)
    scenario_path = scenario_file or _scenario_path(path, name)
    base = load_scenario(scenario_path)
    # The workers run as fast as they can, every period in memory: their own bound, checked
    # here (else every sample fails on its worker after the folder is made).
    length = duration if duration is not None else base.duration
    periods = length * base.rate_hz
    if not periods <= MAX_FAST_PERIODS:
        where = "duration_s" if duration is not None else "scenario"
        raise top.error(where, f"a run of at most {MAX_FAST_PERIODS:,} control periods "
                        f"({MAX_FAST_PERIODS / base.rate_hz:g} s at the scenario's "
                        f"{base.rate_hz:g} Hz: a sweep's runs keep every period in memory)"
                        + ("" if duration is not None else
                           f"; the scenario's duration_s is {base.duration:g} s: give a "
                           "shorter duration_s in the spec"),
                        length if duration is not None else name)
    layout = robot_adapter(base.robot).layout(base.system, base.space)
    rules = plant_rules(layout.n_bodies, layout.n_joint)
    entries = []
    if "perturb" in data:
        p = top.table("perturb")
        for key in p.data:
            if key not in rules:
                raise p.error(key, "a key of the scenario's [plant] table: " + ", ".join(rules),
                              show_got=False)
            entries.append(_entry(p, key, rules[key], f"plant.{key}"))
    if "gains" in data:
        g = top.table("gains")
        units = {u.name: u for u in base.units}
        for unit_name in g.data:
            if unit_name not in units:
                raise g.error(unit_name, "a unit of the scenario: " + ", ".join(units),
                              show_got=False)
            u = g.table(unit_name)
            for key in u.data:
                gains = units[unit_name].gains
                if key not in gains:
                    raise u.error(key, f"a gain of unit {unit_name}: " + ", ".join(gains),
                                  show_got=False)
                rule = KeyRule("float", 0.0, sc_mod.MAX_GAIN, True, len(gains[key]))
                entries.append(_entry(u, key, rule, f"gains.{unit_name}.{key}"))
    top.used.update(own_tables)
    top.done()
    spec = Spec(path, text, scenario_path, scenario_path.read_text(encoding="utf-8"),
                base.robot, base.space, samples, seed, duration, tuple(entries))
    if spec.total > MAX_SAMPLES:
        raise top.error("samples", f"at most {MAX_SAMPLES:,} samples in all (samples times "
                        "the grid points)", spec.total)
    return spec
