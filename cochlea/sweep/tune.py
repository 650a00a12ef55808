"""A gain search over a sweep spec's perturbation sample (``cochlea-tune SPEC.toml``).

The spec is a sweep spec (:mod:`cochlea.sweep.spec`: same format, loader and checks) read
another way: its ``[gains]`` entries are the search space and its ``[perturb]`` entries the
Monte-Carlo sample every candidate is judged on -- the same samples, drawn from the same seeds,
for every candidate (common random numbers: two candidates differ by their gains, not by their
luck). An optional ``[tune]`` table sets the search:

    [tune]
    trials = 60                  # candidates to evaluate (--trials)
    objective = "p95"            # "pNN" (a percentile), "worst" or "mean" (--objective)
    seed = 3                     # the sampler's seed (--seed); default: the spec's seed
    parallel_candidates = 4      # candidates proposed at once and evaluated together
    startup_trials = 10          # random candidates before the TPE model takes over
    log = ["gains.arm1.G_a"]     # searched on a log scale (default: a range over a decade)
    linear = []                  # searched on a linear scale

The study (Optuna, TPE) lives in this process (ask and tell) with a journal file in the output
folder; the Dask workers only run samples (:func:`cochlea.sweep.execute.run_batch` with the
caller's ``evaluate``), as a sweep's workers do, so they need neither Optuna's storage nor a
shared file system. Every proposal depends only on the seed, the trial's number and the trials
finished before its round: a search gives the same trials whatever the workers, and an
interrupted search resumes (the trials asked but not finished are run again with the same
gains) to the same trials as one that was never stopped.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import math
import os
import re
import sys
import tomllib
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import optuna
import pyarrow as pa
import pyarrow.parquet as pq
from optuna.distributions import BaseDistribution, CategoricalDistribution, FloatDistribution
from optuna.storages import JournalStorage
from optuna.storages.journal import JournalFileBackend
from optuna.trial import TrialState
from tqdm import tqdm

from ..errors import CochleaError, DescriptionError
from ..robots.description import Table, read_toml
from ..sim import load_scenario
from ..text import comment
from . import execute, results, sampling
from . import spec as sweep_spec
from .spec import Entry, Spec

MANIFEST = "tune.json"
MANIFEST_FORMAT = "cochlea-tune-folder/1"
JOURNAL = "study.journal"
#: Held (flock) by the search running in a folder: the kernel drops it when the process dies.
LOCK = ".cochlea-tune.lock"
SAMPLES = "samples"
STUDY = "cochlea-tune"
TRIALS_CSV = "trials.csv"
RESULT = "result.json"
TUNED = "tuned.toml"
#: A gain range searched on a log scale by default: one spanning this factor or more.
LOG_SPAN = 10.0
#: Trials one search may hold (each a sample's worth of runs).
MAX_TRIALS = 1_000_000
#: What an objective that is not finite (a run that diverged) is told to the sampler as: the
#: candidate is infeasible anyway, and the sampler ranks by value.
NOT_FINITE = 1e12
DEFAULTS = {"trials": 50, "objective": "p95", "parallel_candidates": 4, "startup_trials": 10}
TUNE_KEYS = ("trials", "objective", "seed", "parallel_candidates", "startup_trials", "log",
             "linear")
OBJECTIVE_TEXT = ('"pNN" (the NN-th percentile of the sample, 0 < NN <= 100, e.g. "p95"), '
                  '"worst" or "mean"')


class TuneFolderError(results.SweepFolderError):
    """An output folder that cannot be used (another search's, not a search's)."""


def objective_ok(text: Any) -> bool:
    if not isinstance(text, str):
        return False
    if text in ("worst", "mean"):
        return True
    m = re.fullmatch(r"p(\d+(?:\.\d+)?)", text)
    return m is not None and 0 < float(m.group(1)) <= 100


# --------------------------------------------------------------------------------------------
# The search space
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Dim:
    """One searched gain: a ``[gains]`` entry of the spec. A uniform is a range (one value for
    every component, or with ``each = true`` one range per component); a choice or a grid is a
    list of candidates values (categorical)."""

    entry: Entry
    log: bool = False

    @property
    def name(self) -> str:
        return self.entry.name

    def _categorical_by_index(self) -> bool:
        return any(isinstance(v, list) for v in self.entry.args)

    def distributions(self) -> dict[str, BaseDistribution]:
        e = self.entry
        if e.kind == "uniform":
            lo, hi = (float(a) for a in e.args)
            if e.each:
                return {f"{e.name}[{j}]": FloatDistribution(lo, hi, log=self.log)
                        for j in range(e.rule.size)}
            return {e.name: FloatDistribution(lo, hi, log=self.log)}
        if self._categorical_by_index():  # Optuna's choices are scalars: a vector by its index
            return {e.name: CategoricalDistribution(tuple(range(len(e.args))))}
        return {e.name: CategoricalDistribution(tuple(e.args))}

    def value(self, params: dict[str, Any]) -> Any:
        """The gain's value (a number for every component, or a list) from a trial's params."""
        e = self.entry
        if e.kind == "uniform" and e.each:
            return [float(params[f"{e.name}[{j}]"]) for j in range(e.rule.size)]
        if e.kind == "uniform":
            return float(params[e.name])
        if self._categorical_by_index():
            value = e.args[int(params[e.name])]
            # A choice mixing numbers and vectors: a number is every component (the same
            # columns for every trial, in trials.csv as in the rows).
            return value if isinstance(value, list) else [value] * e.rule.size
        return params[e.name]

    def corners(self) -> tuple[Any, Any]:
        """The lowest and highest values the search can give (checked before anything runs)."""
        e = self.entry
        if e.kind == "uniform":
            lo, hi = (float(a) for a in e.args)
            return ([lo] * e.rule.size, [hi] * e.rule.size) if e.each else (lo, hi)
        return e.args[0], e.args[-1]


@dataclass(frozen=True)
class Settings:
    trials: int
    objective: str
    seed: int
    parallel: int  # candidates per round
    startup: int  # random candidates before TPE models


@dataclass(frozen=True)
class Tune:
    spec: Spec  # as loaded: its [gains] distributions are the search space
    sample: Spec  # the perturbation sample (and the spec's fixed gains): the nominal candidate
    dims: tuple[Dim, ...]
    settings: Settings

    @property
    def size(self) -> int:
        """Runs per candidate: the sample's size."""
        return self.sample.total

    @property
    def digest(self) -> str:
        """What makes two searches the same study: the spec (but its number of trials: more
        trials continue a study), the base scenario and the settings given on the command line
        (objective, seed)."""
        data = tomllib.loads(self.spec.text)
        if isinstance(data.get("tune"), dict):
            data["tune"].pop("trials", None)
        s = self.settings
        blob = json.dumps([data, self.spec.scenario_text, s.objective, s.seed, s.parallel,
                           s.startup, [(d.name, d.log) for d in self.dims]], sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()

    def distributions(self) -> dict[str, BaseDistribution]:
        out: dict[str, BaseDistribution] = {}
        for d in self.dims:
            out.update(d.distributions())
        return out

    def gains(self, params: dict[str, Any]) -> dict[str, Any]:
        """A trial's gains by entry name (``gains.<unit>.<key>``)."""
        return {d.name: d.value(params) for d in self.dims}

    def candidate(self, gains: dict[str, Any]) -> Spec:
        """The sample with a candidate's gains written in (fixed entries): the same draws."""
        rules = {d.name: d.entry.rule for d in self.dims}
        fixed = tuple(Entry(name, rules[name], "fixed", (value,)) for name, value in gains.items())
        return replace(self.sample, entries=self.sample.entries + fixed)


def _names(t: Table, key: str, searchable: dict[str, Dim]) -> set[str]:
    value = t.data.get(key, [])
    t.used.add(key)
    expected = ("a list of searched gains' names, each one of " + ", ".join(searchable)
                + " (a uniform range)")
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise t.error(key, expected, value)
    for j, v in enumerate(value):
        if v not in searchable:
            raise DescriptionError(t.path, f"{t.key(key)}[{j}]", expected, v)
    return set(value)


def load(path: str | Path, *, trials: int | None = None, objective: str | None = None,
         seed: int | None = None) -> Tune:
    """Read and check a tune spec (a sweep spec with an optional ``[tune]`` table); the
    keyword arguments (the command line's) override the ``[tune]`` table."""
    path = Path(path)
    spec = sweep_spec.load(path, own_tables=("tune",))
    data = read_toml(path, "sweep spec")
    top = Table(path, data, "")
    t = top.table("tune") if "tune" in data else Table(path, {}, "tune")

    def integer(key: str, lo: int, hi: int, what: str) -> int | None:
        return t.get(key, f"an integer in [{lo:,}, {hi:,}] ({what})",
                     lambda v: isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi,
                     required=False)

    n_trials = integer("trials", 1, MAX_TRIALS, "candidates to evaluate")
    chosen = t.get("objective", OBJECTIVE_TEXT, objective_ok, required=False)
    sampler_seed = integer("seed", 0, 2**32 - 1, "the sampler's seed")
    parallel = integer("parallel_candidates", 1, 4096, "candidates proposed at once")
    startup = integer("startup_trials", 0, MAX_TRIALS, "random candidates before TPE")
    dims = []
    for e in spec.entries:
        if not e.name.startswith("gains.") or e.kind == "fixed":
            continue
        if e.kind == "normal":
            unit, key = e.name.split(".")[1:]
            raise DescriptionError(path, f"{e.name}.normal", "a search range: {uniform = [lo, "
                                   "hi]}, {choice = [...]} or {grid = [...]} (cochlea-tune "
                                   "searches a gain; a normal draws it at random)", list(e.args))
        dims.append(Dim(e))
    if not dims:
        raise DescriptionError(path, "gains", "at least one gain to search: {uniform = [lo, "
                               "hi]}, {choice = [...]} or {grid = [...]} under [gains.<unit>] "
                               "(fixed values are not searched)")
    searchable = {d.name: d for d in dims if d.entry.kind == "uniform"}
    forced_log = _names(t, "log", searchable)
    forced_linear = _names(t, "linear", searchable)
    both = sorted(forced_log & forced_linear)
    if both:
        raise t.error("linear", "gains not also in tune.log", both[0])
    t.done()
    for j, d in enumerate(dims):
        if d.name in searchable:
            lo, hi = d.entry.args
            log = (d.name in forced_log
                   or (d.name not in forced_linear and hi / lo >= LOG_SPAN))
            if log and lo <= 0:  # the loader refuses gains <= 0 already; kept for the reader
                raise DescriptionError(path, f"{d.name}.uniform", "a positive range on a log "
                                       "scale", list(d.entry.args))
            dims[j] = Dim(d.entry, log)
    settings = Settings(
        trials=trials if trials is not None else (n_trials or DEFAULTS["trials"]),
        objective=objective if objective is not None else (chosen or DEFAULTS["objective"]),
        seed=seed if seed is not None else (sampler_seed if sampler_seed is not None
                                            else spec.seed % 2**32),
        parallel=parallel or DEFAULTS["parallel_candidates"],
        startup=startup if startup is not None else DEFAULTS["startup_trials"])
    searched = {d.name for d in dims}
    sample = replace(spec, entries=tuple(e for e in spec.entries if e.name not in searched))
    return Tune(spec, sample, tuple(dims), settings)


# --------------------------------------------------------------------------------------------
# The objective over a candidate's rows
# --------------------------------------------------------------------------------------------


def reduce(values: np.ndarray, objective: str) -> float:
    """The objective over the sample's convergence ratios. A percentile is the smallest value
    that at least NN % of the sample do not exceed (no interpolation: always a run's own value,
    and an infinite one stays infinite)."""
    if objective == "worst":
        return float(np.max(values))
    if objective == "mean":
        return float(np.mean(values))
    return float(np.percentile(values, float(objective[1:]), method="inverted_cdf"))


def judge(rows: list[dict], objective: str) -> dict:
    """A candidate's verdict on its sample: the objective (over each run's convergence ratio:
    its largest final RMS over the convergence threshold, 1 being converged), and the runs that
    make it infeasible: an effort at its limit (torque ratio >= 1: commands are clipped there),
    or a stop rule, a divergence or a non-finite error."""
    ratio = np.array([r["convergence_ratio"] for r in rows], float)
    ratio = np.where(np.isfinite(ratio), ratio, np.inf)
    # A sample refused before it ran (gravity above a drive's limit) has no torque (NaN); its
    # stop rule makes the candidate infeasible.
    torque = np.array([max((v for k, v in r.items() if results.group(k) == results.RATIO
                            and not math.isnan(v)), default=0.0) for r in rows], float)
    stopped = [r["stop_rule"] != "none" or bool(r["diverged"]) or not math.isfinite(x)
               for r, x in zip(rows, ratio)]
    value = reduce(ratio, objective)
    return {"objective": value, "feasible": bool(not np.any(torque >= 1) and not any(stopped)),
            "torque_limit_runs": int(np.sum(torque >= 1)), "stopped_runs": int(sum(stopped)),
            "successes": int(sum(bool(r["success"]) for r in rows)), "runs": len(rows),
            "median_ratio": float(np.median(ratio)), "worst_ratio": float(np.max(ratio)),
            "max_torque_ratio": float(np.max(torque))}


# --------------------------------------------------------------------------------------------
# The folder
# --------------------------------------------------------------------------------------------


def write_atomic(path: Path, data: bytes) -> None:
    """Whole or not at all, never over a path that is not a regular file
    (:func:`cochlea.sweep.results.write_atomic`)."""
    results.write_atomic(path, data)


def check(out: Path, tune: Tune) -> bool:
    """Whether ``out`` is this search's folder (to resume); False: new or empty. Any other
    folder is refused. Writes nothing."""
    results.check_out(out)
    if not (out.is_dir() and any(p.name != LOCK for p in out.iterdir())):
        return False
    path = out / MANIFEST
    if not os.path.lexists(path):
        raise TuneFolderError(f"--out {out}: expected a new or empty folder, or a cochlea-tune "
                              "folder to resume; it holds other files")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
            raise ValueError(f"format: expected {MANIFEST_FORMAT!r}")
        digest = manifest["digest"]
        if not isinstance(digest, str):
            raise ValueError(f"digest: expected a string, got {digest!r:.80}")
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise results.FolderDamaged(f"{path}: damaged cochlea-tune manifest "
                                    f"({getattr(exc, 'strerror', None) or exc})") from None
    if digest != tune.digest:
        raise TuneFolderError(f"--out {out}: made by a different spec, scenario, objective or "
                              f"seed (hash {digest[:12]}, this one {tune.digest[:12]}): give a "
                              "new --out, or the spec and options that made it to resume")
    return True


def prepare(out: Path, tune: Tune) -> None:
    """A new folder becomes this search's (:func:`check` first); what a killed run was writing
    is removed (``*.tmp``, a journal line cut short)."""
    if not check(out, tune):
        results.make_folder(out)  # made by results.claim already; a caller without it too
        s = tune.settings
        manifest = {"format": MANIFEST_FORMAT, "digest": tune.digest, "robot": tune.spec.robot,
                    "space": tune.spec.space, "spec_path": str(tune.spec.path.resolve()),
                    "scenario_path": str(tune.spec.scenario_path), "objective": s.objective,
                    "seed": s.seed, "spec_text": tune.spec.text,
                    "scenario_text": tune.spec.scenario_text}
        write_atomic(out / "spec.toml", tune.spec.text.encode("utf-8"))
        # The manifest last: a folder with it is a whole search folder.
        write_atomic(out / MANIFEST, (json.dumps(manifest, indent=1) + "\n").encode())
    samples = out / SAMPLES
    try:
        samples.mkdir(exist_ok=True)
    except OSError as exc:
        raise results.WriteFailed(f"{samples}: cannot create it ({exc.strerror})") from None
    if samples.is_symlink() or not samples.is_dir():
        raise results.FolderDamaged(f"{samples}: expected the search's folder of runs, got "
                                    "something else: move it away and run the same command")
    results.clean_temporary(out)
    results.clean_temporary(samples)
    journal = out / JOURNAL
    if os.path.lexists(journal):
        if journal.is_symlink() or not journal.is_file():
            raise results.FolderDamaged(f"{journal}: expected the search's journal (a file), "
                                        "got something else: move it away")
        data = journal.read_bytes()
        if data and not data.endswith(b"\n"):  # a write cut by a kill: never acknowledged
            with open(journal, "r+b") as f:
                f.truncate(data.rfind(b"\n") + 1)


def hold(out: Path) -> int:
    """Lock ``out`` for this process (a second search on the same folder is refused). Holding
    it, any lock Optuna's journal left is a killed run's: removed, or the next write would wait
    for its grace period."""
    fd = results.hold(out, LOCK, "cochlea-tune", TuneFolderError)
    results.remove_ours(out / (JOURNAL + ".lock"))
    return fd


def release(out: Path, fd: int | None) -> None:
    results.release(fd)


def rows_path(out: Path, key: int | str) -> Path:
    name = "nominal" if key == "nominal" else f"trial-{int(key):06d}"
    return out / SAMPLES / f"{name}.parquet"


def write_rows(out: Path, key: int | str, rows: list[dict]) -> None:
    sink = io.BytesIO()
    pq.write_table(pa.Table.from_pylist(sorted(rows, key=lambda r: r["sample"])), sink)
    write_atomic(rows_path(out, key), sink.getvalue())


def read_rows(out: Path, key: int | str, size: int) -> list[dict] | None:
    """A candidate's rows (``key``: a trial's number or "nominal"), None when its file is
    missing or unreadable (its runs are simply run again). A file that reads but is not a
    candidate's ``size`` runs -- a row column missing, ``sample`` other than 0 to size - 1,
    each once, in order -- is :class:`~cochlea.sweep.results.FolderDamaged` naming it (judged,
    it was a KeyError, or a verdict on rows that are not the sample's)."""
    path = rows_path(out, key)
    if not path.exists():
        return None
    try:
        table = results.upgrade(pq.read_table(path))
    except (OSError, pa.ArrowException):
        return None  # unreadable: its runs are simply run again
    missing = [c for c in results.ROW_COLUMNS if c not in table.column_names]
    samples = table["sample"] if "sample" in table.column_names else None
    if missing or samples is None or not pa.types.is_integer(samples.type) \
            or samples.to_pylist() != list(range(size)):
        why = (f"no column {missing[0]!r}" if missing else
               f"its samples are not the {size} runs of a candidate, 0 to {size - 1}")
        raise results.FolderDamaged(f"{path}: not a run file of this search ({why}); move it "
                                    "away and run the same command to run them again")
    return table.to_pylist()


def open_study(out: Path, tune: Tune) -> optuna.Study:
    """The folder's study, read from its journal; a damaged journal (a line that is not one of
    Optuna's records) is :class:`~cochlea.sweep.results.FolderDamaged`."""
    optuna.logging.set_verbosity(optuna.logging.WARNING)  # the report says what matters
    journal = out / JOURNAL
    try:
        storage = JournalStorage(JournalFileBackend(str(journal)))
        # Loaded when it is there: create_study(load_if_exists=True) appended a line to the
        # journal every time (a folder refused as damaged was changed).
        if any(s.study_name == STUDY for s in storage.get_all_studies()):
            study = optuna.load_study(study_name=STUDY, storage=storage,
                                      sampler=sampler(tune, 0))
        else:
            study = optuna.create_study(study_name=STUDY, storage=storage,
                                        direction="minimize", sampler=sampler(tune, 0))
        trials = study.get_trials(deepcopy=False)  # every line read now, not mid-search
    except OSError as exc:
        raise results.WriteFailed(f"{journal}: cannot read or write it ({exc.strerror or exc})"
                                  ) from None
    except (ValueError, KeyError, TypeError, AttributeError, IndexError) as exc:
        raise results.FolderDamaged(f"{journal}: damaged journal ({type(exc).__name__}: "
                                    f"{str(exc)[:200]}): a line was changed; move the folder "
                                    "away and start a new search") from None
    # A journal of another search (one that searched a gain on another range or as a
    # choice) read as this one's: its trials' values would be taken for this search's (a
    # choice's index 0 as a gain of 0, written into tuned.toml).
    ours = tune.distributions()
    for t in trials:
        for name, distribution in t.distributions.items():
            if ours.get(name) != distribution:
                theirs = ("not a parameter of this search" if name not in ours
                          else f"this search's is {ours[name]}")
                raise results.FolderDamaged(
                    f"{journal}: not this search's journal: trial {t.number}'s {name} is "
                    f"{distribution} ({theirs}); move the folder away and start a new search")
    return study


def sampler(tune: Tune, number: int) -> optuna.samplers.BaseSampler:
    """The sampler that proposes trial ``number``: seeded from the search's seed and the number
    alone, so a proposal does not depend on how many proposals this process made before (a
    resumed search proposes what an uninterrupted one would)."""
    state = np.random.SeedSequence(tune.settings.seed, spawn_key=(number,)).generate_state(1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.samplers.TPESampler(seed=int(state[0]),
                                          n_startup_trials=tune.settings.startup,
                                          constant_liar=True)


def complete_params(study: optuna.Study, tune: Tune, number: int,
                    distributions: dict[str, BaseDistribution]) -> None:
    """The params of a trial a killed search left half-asked: Optuna's journal records an ask's
    params one by one, so a kill between two leaves the trial without the rest. They are drawn
    again as the first ask drew them (the trial's own seeded sampler, the same order, every
    draw made, kept ones included, so the random stream is the same) and the missing ones
    recorded. Optuna has no public call for either step: the sampler's own draw and the study's
    storage are used directly."""
    frozen = study.get_trials(deepcopy=False)[number]
    draw = sampler(tune, number)
    for name, distribution in distributions.items():
        value = draw.sample_independent(study, frozen, name, distribution)
        if name not in frozen.params:
            study._storage.set_trial_param(frozen._trial_id, name,
                                           distribution.to_internal_repr(value), distribution)


def trial_records(study: optuna.Study, tune: Tune) -> list[dict]:
    """Every finished trial: number, objective, verdict, gains."""
    out = []
    for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
        verdict = t.user_attrs.get("verdict", {})
        out.append({"trial": t.number, **verdict, "gains": tune.gains(t.params)})
    return out


def write_trials_csv(out: Path, tune: Tune, records: list[dict]) -> None:
    """trials.csv, whole each time (from the study, the source of truth): written to a
    temporary file and renamed, so a reader never sees half a line."""
    columns = ["trial", "objective", "feasible", "torque_limit_runs", "stopped_runs",
               "successes", "runs", "median_ratio", "worst_ratio", "max_torque_ratio"]
    sink = io.StringIO()
    writer = csv.writer(sink, lineterminator="\n")
    flats = []
    gain_columns: dict[str, None] = {}  # every trial's, in order (a choice may mix shapes)
    for r in records:
        flat: dict[str, Any] = {}
        for name, value in r["gains"].items():
            flat.update(results.flatten(name, value))
        flats.append(flat)
        gain_columns.update(dict.fromkeys(flat))
    writer.writerow(columns + list(gain_columns))
    for r, flat in zip(records, flats):
        writer.writerow([repr(r[c]) if isinstance(r[c], float) else r[c] for c in columns]
                        + [repr(flat[c]) if isinstance(flat.get(c), float) else flat.get(c, "")
                           for c in gain_columns])
    write_atomic(out / TRIALS_CSV, sink.getvalue().encode())


def best(records: list[dict]) -> dict | None:
    """The feasible trial of the smallest objective (the earliest of equals); None: none is."""
    feasible = [r for r in records if r.get("feasible")]
    return min(feasible, key=lambda r: (r["objective"], r["trial"])) if feasible else None


# --------------------------------------------------------------------------------------------
# Running the search
# --------------------------------------------------------------------------------------------


def _evaluate(client, jobs: dict[Any, Spec], size: int, evaluate: Callable[[dict], dict],
              n_workers: int, done: Callable[[Any, list[dict]], None],
              progress: Callable[[int], None], out: Path = Path(".")) -> None:
    """Every job's sample on the workers, in chunks that keep every worker busy; ``done(key,
    rows)`` as soon as a job's rows are all back."""
    from distributed import as_completed  # noqa: PLC0415 (see execute.connect)

    if not jobs:
        return
    chunk = max(1, min(size, math.ceil(size * len(jobs) / (execute.IN_FLIGHT * n_workers))))
    keys = {}
    for key, spec in jobs.items():
        remote = client.scatter(spec)
        for start in range(0, size, chunk):
            f = client.submit(execute.run_batch, remote, list(range(start, min(size,
                                                                                start + chunk))),
                              evaluate, pure=False)
            keys[f] = key
    got: dict[Any, list[dict]] = {key: [] for key in jobs}
    for future in as_completed(list(keys)):
        key = keys[future]
        rows = execute.batch_rows(future, out)
        got[key] += rows
        progress(len(rows))
        if len(got[key]) == size:
            done(key, got.pop(key))


def run(tune: Tune, out: Path, evaluate: Callable[[dict], dict], *, workers: int | None = None,
        scheduler: str | None = None, progress: bool = True,
        warm: Callable[[], object] | None = None, log=None) -> dict:
    """Evaluate the nominal gains and every trial not yet finished in ``out``, then write
    trials.csv and result.json (the report is the caller's). An interrupt (KeyboardInterrupt)
    keeps every finished trial; the same call resumes."""
    s = tune.settings
    info = {"trials_run": 0, "workers": 0}
    lock: dict[str, int] = {}  # the folder's lock, once this process holds it
    try:
        if check(out, tune):  # before any worker starts; nothing written yet
            lock["fd"] = hold(out)
            prepare(out, tune)
            study = open_study(out, tune)
            finished = {t.number for t in study.get_trials(deepcopy=False,
                                                           states=(TrialState.COMPLETE,))}
            if finished >= set(range(s.trials)) and \
                    read_rows(out, "nominal", tune.size) is not None:
                info.update(write_result(out, tune, study))  # nothing to run: no workers
                return info
        return _run(tune, out, evaluate, workers, scheduler, progress, warm, log, info, lock)
    finally:
        release(out, lock.get("fd"))


def _run(tune: Tune, out: Path, evaluate, workers, scheduler, progress, warm, log, info: dict,
         lock: dict[str, int]) -> dict:
    """:func:`run` once workers are needed: a new folder is written only once they are up."""
    s = tune.settings
    client, cluster = execute.connect(workers, scheduler)
    bar = None
    created: list[Path] = []
    try:
        if "fd" not in lock:  # the lock first: then the folder is written
            lock["fd"], created = results.claim(out, LOCK, "cochlea-tune", TuneFolderError)
        prepare(out, tune)
        study = open_study(out, tune)
        n_workers = len(client.scheduler_info()["workers"])
        info["workers"] = n_workers
        if warm is not None:
            client.run(warm)
        finished = {t.number for t in study.get_trials(deepcopy=False,
                                                       states=(TrialState.COMPLETE,))}
        todo_trials = sum(1 for n in range(s.trials) if n not in finished)
        nominal_rows = read_rows(out, "nominal", tune.size)
        total = (s.trials + 1) * tune.size
        bar = tqdm(total=total, initial=total - (todo_trials + (nominal_rows is None))
                   * tune.size, unit="run", file=sys.stderr, disable=not progress,
                   smoothing=0.05, dynamic_ncols=True)
        if log:
            log(f"{todo_trials} of {s.trials} trials to run, {tune.size} runs each, on "
                f"{n_workers} worker(s)")
        distributions = tune.distributions()
        records = trial_records(study, tune)

        def finish(key, rows):
            if key != "nominal":
                # The rows first: a kill between the two leaves a trial that resumes from them.
                write_rows(out, key, rows)
                tell(study, key, judge(rows, s.objective))
                info["trials_run"] += 1
                records[:] = trial_records(study, tune)
                write_trials_csv(out, tune, records)
                b = best(records)
                bar.set_postfix_str(f"trials {len(records)}/{s.trials}" + (
                    f", best {b['objective']:.4g}" if b else ""), refresh=False)
            else:
                write_rows(out, key, rows)

        write_trials_csv(out, tune, records)
        while True:
            states = {t.number: t for t in study.get_trials(deepcopy=False)}
            open_numbers = [n for n in range(s.trials)
                            if n not in states or states[n].state != TrialState.COMPLETE]
            if not open_numbers:
                break
            first = open_numbers[0] // s.parallel * s.parallel
            numbers = range(first, min(first + s.parallel, s.trials))
            for n in numbers:  # ask the round's missing trials before any of it is told
                if n in states and states[n].state != TrialState.COMPLETE and \
                        not set(distributions) <= set(states[n].params):
                    complete_params(study, tune, n, distributions)
                    states[n] = study.get_trials(deepcopy=False)[n]
                if n not in states:
                    study.sampler = sampler(tune, n)
                    trial = study.ask(distributions)
                    if trial.number != n:
                        raise CochleaError(f"{out / JOURNAL}: trial {trial.number} asked where "
                                           f"{n} was expected; is another cochlea-tune running "
                                           "on this folder?")
                    states[n] = study.get_trials(deepcopy=False)[n]
            jobs: dict[Any, Spec] = {}
            if nominal_rows is None:
                jobs["nominal"] = tune.sample
                nominal_rows = []
            for n in numbers:
                if states[n].state == TrialState.COMPLETE:
                    continue
                rows = read_rows(out, n, tune.size)
                if rows is not None and len(rows) == tune.size:
                    finish_from_file(study, n, rows, s.objective)
                    records[:] = trial_records(study, tune)
                    write_trials_csv(out, tune, records)
                    bar.update(tune.size)
                    continue
                jobs[n] = tune.candidate(tune.gains(states[n].params))
            _evaluate(client, jobs, tune.size, evaluate, n_workers, finish, bar.update, out)
        if not nominal_rows:
            nominal_rows = read_rows(out, "nominal", tune.size)
        if nominal_rows is None:  # the trials were all done before: only the nominal runs
            _evaluate(client, {"nominal": tune.sample}, tune.size, evaluate, n_workers,
                      lambda key, rows: write_rows(out, key, rows), bar.update, out)
    except BaseException:
        if created and not any((out / SAMPLES).glob("*.parquet")):
            # A new folder that got no run: removed, as if the command had not run.
            for name in (JOURNAL, JOURNAL + ".lock", TRIALS_CSV, MANIFEST, "spec.toml"):
                results.remove_ours(out / name)
            with contextlib.suppress(OSError):
                (out / SAMPLES).rmdir()
            results.discard(out, created, LOCK)
        raise
    finally:
        if bar is not None:
            bar.close()
        client.close()
        if cluster is not None:
            cluster.close()
    info.update(write_result(out, tune, study))
    return info


def tell(study: optuna.Study, number: int, verdict: dict) -> None:
    """A trial's verdict into the study: the objective, and as Optuna constraints (feasible when
    both are 0) the runs at a torque limit and the runs stopped (rule, divergence)."""
    frozen = study.get_trials(deepcopy=False)[number]
    # Optuna has no public handle on a trial asked by another process (a resumed search's);
    # a Trial made from the frozen one's id is what study.ask returns for its own.
    trial = optuna.trial.Trial(study, frozen._trial_id)
    trial.set_user_attr("verdict", verdict)
    with warnings.catch_warnings():  # set already by a run killed before its tell: the same
        warnings.simplefilter("ignore")
        trial.set_constraint("torque_limit_runs", verdict["torque_limit_runs"])
        trial.set_constraint("stopped_runs", verdict["stopped_runs"])
    value = verdict["objective"]
    study.tell(number, value if math.isfinite(value) else NOT_FINITE)


def finish_from_file(study: optuna.Study, number: int, rows: list[dict], objective: str) -> None:
    """A trial whose rows a killed run wrote but did not tell: told from its file, not rerun."""
    tell(study, number, judge(rows, objective))


def write_result(out: Path, tune: Tune, study: optuna.Study | None = None) -> dict:
    """result.json: the nominal and the best candidate on the same sample. The nominal gains
    count as a candidate: when no trial beats them (a smaller objective; a tie does not),
    they are the result."""
    if study is None:
        study = open_study(out, tune)
    records = trial_records(study, tune)
    write_trials_csv(out, tune, records)
    nominal_rows = read_rows(out, "nominal", tune.size)
    nominal = judge(nominal_rows, tune.settings.objective) if nominal_rows else None
    b = best(records)
    chosen = b
    # A trial that only ties the nominal gains does not beat them: they stay the result.
    if nominal is not None and nominal["feasible"] and (b is None
                                                        or nominal["objective"] <= b["objective"]):
        chosen = {"trial": "nominal", **nominal, "gains": nominal_gains(tune)}
    result = {"objective": tune.settings.objective, "trials": len(records),
              "feasible_trials": sum(1 for r in records if r["feasible"]),
              "runs_per_candidate": tune.size,
              "nominal": None if nominal is None else {**nominal, "gains": nominal_gains(tune)},
              "best_trial": b, "chosen": chosen}
    write_atomic(out / RESULT, (json.dumps(result, indent=1) + "\n").encode())
    return {"result": result}


def nominal_gains(tune: Tune) -> dict[str, Any]:
    """The base scenario's own values of the searched gains (the nominal candidate's; a gain
    the scenario leaves out is its controller's default, as the loader fills it in)."""
    units = {u.name: u for u in load_scenario(tune.spec.scenario_path).units}
    out = {}
    for d in tune.dims:
        _, unit, key = d.name.split(".")
        out[d.name] = [float(x) for x in np.atleast_1d(units[unit].gains[key])]
    return out


def tuned_text(tune: Tune, gains: dict[str, Any], header: str) -> str:
    """The base scenario with ``gains`` written in, its own duration, and its own plant but
    for the spec's fixed ``[perturb]`` values (conditions the gains were tuned under, such as
    ``plant = "realistic"``); the random draws are the sample's, not the scenario's."""
    fixed = tuple(e for e in tune.sample.entries
                  if not e.name.startswith("plant.") or e.kind == "fixed")
    spec = replace(tune.candidate(gains), duration=None)
    data = sampling.scenario_data(replace(spec, entries=fixed + spec.entries[
        len(tune.sample.entries):]), 0)
    plant = dict(tomllib.loads(tune.spec.scenario_text).get("plant", {}))
    plant.update((e.name.split(".", 1)[1], data["plant"][e.name.split(".", 1)[1]])
                 for e in fixed if e.name.startswith("plant."))
    if plant:
        data["plant"] = plant
    else:
        data.pop("plant", None)
    return header + sampling.dumps(data)


def write_tuned(out: Path, tune: Tune, chosen: dict | None) -> Path:
    """DIR/tuned.toml from the chosen candidate (removed when none is feasible: a previous,
    shorter search's result is not this one's)."""
    path = out / TUNED
    if chosen is None:
        results.remove_ours(path)
        return path
    which = ("the nominal gains: no trial beat them" if chosen["trial"] == "nominal"
             else f"trial {chosen['trial']}")
    length = f"{tune.spec.duration:g} s" if tune.spec.duration else "the scenario's duration"
    header = (f"# Tuned by cochlea-tune from {comment(tune.spec.path.name)} ({which}): "
              f"{tune.settings.objective} of the convergence ratio {chosen['objective']:.6g} "
              f"over {tune.size} perturbed runs of {length}.\n"
              f"# cochlea-run --robot {tune.spec.robot} --space {tune.spec.space} --scenario "
              "THIS_FILE\n\n")
    write_atomic(path, tuned_text(tune, chosen["gains"], header).encode())
    return path
