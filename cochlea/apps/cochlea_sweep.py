"""``cochlea-sweep``: a scenario run for thousands of perturbed plants and gains, on Dask.

    cochlea-sweep SPEC.toml --out DIR [--workers N] [--scheduler ADDRESS] [--batch N]
    cochlea-sweep replay DIR SAMPLE [--out FILE.toml]
    cochlea-sweep report DIR

The run resumes: the same command on the same DIR runs only the samples not yet there.
Exit codes (the table in docs/sweeps.md): 0 done; 2 the spec or an option is wrong; 3 --out
cannot be used; 4 --out is in use by another run; 5 the folder's files are damaged; 6 a write
failed while running (a full disk); 7 a sample failed on a worker; 18 the report could not be
written; 130 interrupted (every finished batch is kept: run the same command to resume).
"""

from __future__ import annotations

import ctypes
import dataclasses
import functools
import math
import os
import sys
import tempfile
import time
from pathlib import Path

from .. import files
from ..console import OneLineParser, sigterm_interrupts, tolerate_closed_stdout
from ..errors import CochleaError, printable
from ..kernels import library as ckernels
from ..runtime import build_supervisor, verdict
from ..runtime.supervisor import log_reductions
from ..sim import KERNELS, GravityRefused, choose_kernels, load_scenario, simulate, unit_setups
from ..sim.setup import GRAVITY_RULE
from ..sweep import execute, results, sampling
from ..sweep import report as sweep_report
from ..sweep import spec as sweep_spec
from ..text import whole_argument
from . import report

EXIT_INTERRUPTED = 130
#: The samples are kept but the report failed (cochlea-run's code for a lost report part).
EXIT_REPORT_FAILED = 18
#: summary.json's effort unit -> the joint's position unit (which names the column's unit).
_POSITION_UNIT = {"N m": "rad", "N": "m"}


def measures(summary: dict, limits: dict[str, dict[str, float]]) -> dict:
    """A sample's result columns from its run's summary (summary.json's numbers, as they are):
    final RMS per coordinate, peak |effort| per joint and over its limit, the convergence
    ratio (the largest final RMS over its threshold: converged is ratio <= 1), the estimate
    bound, the supervisor's stop rule."""
    row: dict = {"converged": bool(summary["converged"]),
                 "diverged": bool(summary["diverged"])}
    ratio, bound_hit = 0.0, False
    for uname, u in summary["units"].items():
        for coord, c in u["tracked"].items():
            rms = c["final_rms_error"]
            rms = math.nan if rms is None else rms
            row[results.rms_column(uname, coord, c["unit"])] = rms
            floor = max(report.CONVERGENCE_FLOOR[c["unit"]], c.get("measurement_resolution", 0.0))
            initial = c["initial_abs_error"] or 0.0
            threshold = max(report.CONVERGENCE_RATIO * initial, floor)
            ratio = max(ratio, rms / threshold) if math.isfinite(rms) else math.inf
        for joint, t in u["torque"].items():
            row[results.peak_column(uname, joint, _POSITION_UNIT[t["unit"]])] = t["max_abs"]
            row[results.ratio_column(uname, joint)] = t["max_abs"] / limits[uname][joint]
        bound_hit = bound_hit or not u["estimates"]["bounded"]
    sup = summary["supervisor"]
    row.update({"convergence_ratio": ratio, "estimate_bound_hit": bound_hit,
                "stop_rule": sup["rule"], "stop_time_s": sup.get("time_s", math.nan),
                "saturated_periods": int(sup["saturated_periods"])})
    row["success"] = row["converged"] and not row["diverged"] and sup["rule"] == "none"
    return row


def refused(setups) -> dict:
    """The row of a sample refused before it ran (:class:`~cochlea.sim.GravityRefused`: its
    drives cannot hold the robot where it starts): the columns of a run of the same setups,
    nothing measured (NaN), stopped by :data:`~cochlea.sim.setup.GRAVITY_RULE`, no success."""
    row: dict = {"converged": False, "diverged": False}
    for u in setups:
        joint_space = u.controller.space == "joint"
        tracked = zip([j.name for j in u.controller_model.joints] if joint_space
                      else u.task_names, u.joint_units if joint_space else u.task_units)
        for coord, unit in tracked:
            row[results.rms_column(u.name, coord, unit)] = math.nan
        for j, unit in zip(u.controller_model.joints, u.joint_units):
            row[results.peak_column(u.name, j.name, unit)] = math.nan
            row[results.ratio_column(u.name, j.name)] = math.nan
    row.update({"convergence_ratio": math.inf, "estimate_bound_hit": False,
                "stop_rule": GRAVITY_RULE, "stop_time_s": 0.0, "saturated_periods": 0,
                "success": False})
    return row


#: The name a sample's scenario goes by on a worker (in a refusal's message): it is read from
#: its text, never from a file.
SAMPLE_FILE = Path("sample.toml")


def evaluate(sample: str | dict, cache: bool = True, kernels: str = "auto",
             library: str | None = None) -> dict:
    """One sample on a worker: exactly what ``cochlea-run --scenario FILE --realtime off``
    computes for its summary.json, from the sample's scenario file: its text
    (:func:`cochlea.sweep.sampling.scenario_text`), or the data that text reads as
    (:func:`cochlea.sweep.sampling.scenario_data`: what a sweep's worker passes, which spares
    writing the text and parsing it again; the same row, bit for bit).

    ``cache``: the set-ups' symbolic part (models, controllers, checked desired path) comes
    from the worker's cache when an earlier sample had the same structure
    (:func:`cochlea.sim.setup.unit_setups`), and so do the supervisor's bound pose kernels;
    ``False`` builds everything again, with the same row, bit for bit. ``kernels``,
    ``library``: as :func:`cochlea.sim.simulate` takes them (the library also every other
    kernel's on this worker: ``$COCHLEA_LIB``). Several samples at once: :func:`evaluate_many`
    (a batch's, as :func:`cochlea.sweep.execute.run_batch` runs them)."""
    return evaluate_many([sample], cache, kernels, library)[0][0]


#: The most periods (times units) of the samples :func:`evaluate_many` holds run at once: their
#: logs (about 250 bytes a unit and period: 80 MB) stay in memory until their rows are made.
GROUP_PERIODS = 320_000
#: ... and the most samples.
GROUP_SAMPLES = 16


def unit_periods(scenario, units: int) -> int:
    """The periods a sample's log holds, times its units: what :data:`GROUP_PERIODS` counts."""
    return round(float(scenario.duration) / scenario.period) * units


@dataclasses.dataclass
class _Sample:
    """A sample through :func:`evaluate_many`: its scenario and set-ups (or its row already:
    refused before it ran), its log, and the seconds of its own work so far."""

    scenario: object
    setups: list
    row: dict | None = None
    result: object = None
    wall: float = 0.0
    seconds: float = 0.0


def _prepare(sample: str | dict, cache: bool) -> _Sample:
    # Read as the file would be, without writing one (a temporary folder a sample cost more
    # than the summary); the sample's description path is absolute (sampling.scenario_data).
    scenario = load_scenario(SAMPLE_FILE, data=sample) if isinstance(sample, dict) else \
        load_scenario(SAMPLE_FILE, text=sample)
    try:
        return _Sample(scenario, unit_setups(scenario, cache=cache))
    except GravityRefused:  # a sample the robot cannot start: counted, not an error
        setups = unit_setups(scenario, cache=cache, gravity=False)
        return _Sample(scenario, setups, row=refused(setups))


def _run(s: _Sample, kernels: str, library: str | None) -> None:
    start = time.perf_counter()
    # One worker per core: the arms one after the other, no thread pool a sample.
    s.result = simulate(s.scenario, None, s.setups, kernels, threads=False, library=library)
    s.wall = time.perf_counter() - start


def _judge(s: _Sample, cache: bool, kernels: str) -> dict:
    result, setups = s.result, s.setups
    supervisor = build_supervisor(setups, s.scenario.system.keep_out_radius,
                                  kernels="casadi" if kernels == "casadi" else "c",
                                  substeps=s.scenario.plant_substeps, cache=cache)
    # The reductions the verdict and the summary both read (the efforts' extremes, the
    # estimates' squares), each log read once for them; the same verdict and summary.
    reductions = [log_reductions(u) for u in result.units]
    result.supervisor = verdict(result, supervisor, reductions)
    limits = {u.name: {j.name: float(lim) for j, lim in zip(u.controller_model.joints,
                                                           u.effort_limit)} for u in setups}
    # Only what the row reads (no summary.json is written): the same row, bit for bit.
    return measures(report.summary(result, s.wall, reductions=reductions, row=True), limits)


def evaluate_many(samples: list, cache: bool = True, kernels: str = "auto",
                  library: str | None = None) -> list[tuple[dict, float]]:
    """:func:`evaluate` of each sample, and the seconds of its own work: each sample's row
    is :func:`evaluate`'s, bit for bit. The samples go through in groups
    (:data:`GROUP_PERIODS`, :data:`GROUP_SAMPLES`), each phase once for the whole group: every
    scenario read and set up, then every closed loop in C, then every verdict and row. The
    first Python call after a C closed loop took 3-4x its time (0.18 against 0.05 ms for a
    sample's scenario data, 0.25 against 0.07 ms for its summary: the loop's generated code
    evicts the interpreter's from the caches and the branch predictors, which streaming as
    many bytes of data did not do), so sample after sample each of the six Python parts paid
    it: 11-14 % of the loop's time outside it on this project's 2-vCPU machine (issue 30 item 3:
    under 10 %). In groups a phase pays it once a group."""
    if library is not None:
        os.environ[ckernels.ENVIRONMENT] = library
    rows: list[tuple[dict, float]] = []
    group: list[_Sample] = []

    def finish():
        for s in group:
            if s.row is None:
                _run(s, kernels, library)
                s.seconds += s.wall
        for s in group:
            if s.row is None:
                start = time.perf_counter()
                s.row = _judge(s, cache, kernels)
                s.seconds += time.perf_counter() - start
            s.result = None  # its log freed as soon as its row is made
            rows.append((s.row, s.seconds))
        group.clear()

    held = 0
    for sample in samples:
        start = time.perf_counter()
        s = _prepare(sample, cache)
        s.seconds = time.perf_counter() - start
        group.append(s)
        held += unit_periods(s.scenario, len(s.setups))
        if held >= GROUP_PERIODS or len(group) >= GROUP_SAMPLES:
            finish()
            held = 0
    finish()
    return rows


evaluate.many = evaluate_many  # what execute.run_batch calls for a batch (see there)


#: glibc's mallopt() parameters (malloc.h) and what a worker sets them to: blocks up to 32 MiB
#: from the heap (not pages of their own), and up to 256 MiB of free heap kept.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD_BYTES, _TRIM_THRESHOLD_BYTES = 32 << 20, 256 << 20


def keep_freed_memory() -> bool:
    """Let this process's malloc keep the memory a sample frees for the next sample (glibc;
    elsewhere nothing happens: False). A sample's logs are some 10 MB of arrays of about
    1 MB; glibc hands such blocks back to the kernel when they are freed, and the next sample
    faults them in again page by page: some 2,500 page faults and 4 ms of system time a
    serial_joint sample of 20 s, a sixth of its CPU time. The process then holds its largest
    sample's memory (up to 256 MiB of it free) for as long as it lives: a sweep's worker."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_BYTES)) and \
        bool(mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD_BYTES))


def warm() -> None:
    """A worker process before its first batch: the C library bound once, and freed memory
    kept for the next sample (:func:`keep_freed_memory`)."""
    ckernels.load()
    keep_freed_memory()


def _choose_kernels(spec: sweep_spec.Spec, kernels: str, library: str | None):
    """The kernels of the sweep, decided on its first sample before any worker starts
    (:func:`cochlea.sim.choose_kernels`): ``--kernels c`` refuses here, ``auto`` says here
    that it falls back."""
    scenario = load_scenario(SAMPLE_FILE, text=sampling.scenario_text(spec, 0))
    setups = unit_setups(scenario, gravity=False)
    return choose_kernels(setups, scenario.plant_substeps, kernels, library)


def check_samples(spec: sweep_spec.Spec, gains: str = "") -> None:
    """Before any worker starts or a folder is made: the first and last samples' scenarios
    through the scenario loader and the run's up-front checks (reachability, a finite
    trajectory), and so every combination of the values the spec gives the keys of the
    loader's rules between ``[plant]`` keys (:func:`cochlea.sweep.sampling.cases`): such a
    rule refusing a sample in the middle stopped the sweep there, and every resume at the same
    sample. ``gains``: what the message says of the gains (cochlea-tune's ends of a range)."""
    checks = [(f"sample {i}'s scenario{gains}", sampling.scenario_data(spec, i))
              for i in sorted({0, spec.total - 1})]
    seen = set()
    for values in sampling.cases(spec):
        varied = tuple((k, values[k]) for k in values
                       if k.split(".", 1)[-1] in sampling.CROSS_KEYS and k.startswith("plant."))
        if varied in seen:
            continue
        seen.add(varied)
        shown = ", ".join(f"{k} = {sampling.dumps({'v': v})[4:].strip()}" for k, v in varied)
        checks.append((f"the scenario of a sample the spec can give ({shown}){gains}",
                       sampling.scenario_data(spec, 0, values)))
    for what, data in checks:
        try:
            unit_setups(load_scenario(SAMPLE_FILE, data=data))
        except GravityRefused:
            pass  # a perturbation the robot cannot start with: that sample's row says so
        except CochleaError as exc:
            raise CochleaError(f"{spec.path}: {what} is refused: {exc}") from None


def _sweep(argv: list[str]) -> int:
    p = OneLineParser(
        prog="cochlea-sweep",
        description="Run a scenario for every sample of a sweep spec (perturbed plants, gain "
                    "grids) on Dask workers; one Parquet row per sample in DIR/parts, a "
                    "robustness report in DIR/summary.md. Other forms: `cochlea-sweep replay "
                    "DIR SAMPLE [--out FILE]` and `cochlea-sweep report DIR`.",
        epilog="The same command on the same DIR resumes an interrupted sweep. See "
               "docs/sweeps.md.")
    p.add_argument("spec", type=Path, metavar="SPEC.toml")
    p.add_argument("--out", type=Path, required=True, metavar="DIR")
    p.add_argument("--workers", type=whole_argument, metavar="N",
                   help=f"local worker processes (default: the cores, {os.cpu_count()})")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="an existing Dask scheduler, e.g. tcp://10.0.0.5:8786, whose workers "
                        "run the samples (instead of local processes)")
    p.add_argument("--batch", type=whole_argument, metavar="N",
                   help="samples per batch (default: measured, see docs/sweeps.md)")
    p.add_argument("--progress", default="auto", choices=["auto", "on", "off"],
                   help="progress bar on stderr (auto: when stderr is a terminal)")
    p.add_argument("--kernels", default="auto", choices=list(KERNELS),
                   help="as cochlea-run's: auto (default) the C kernels when the library has "
                        "the scenario's, else casadi, saying so; c: those or exit 2; casadi")
    p.add_argument("--library", metavar="PATH",
                   help="the C kernels' library: a .so or the folder cochlea-codegen "
                        "--scenario FILE --out DIR wrote (default: $COCHLEA_LIB, else the "
                        "shipped one); with --scheduler, a path every worker can read")
    args = p.parse_args(argv)
    if args.workers is not None and not 1 <= args.workers <= 4096:
        raise CochleaError(f"--workers must be between 1 and 4096, got {args.workers}")
    if args.workers is not None and args.scheduler is not None:
        raise CochleaError("--workers starts local workers; with --scheduler the scheduler's "
                           "workers run the samples: give one or the other")
    if args.batch is not None and args.batch < 1:
        raise CochleaError(f"--batch must be a positive number of samples, got {args.batch}")
    spec = sweep_spec.load(args.spec)
    check_samples(spec)
    choice = _choose_kernels(spec, args.kernels, args.library)
    print(f"cochlea-sweep: kernels: {choice.line()}", flush=True)
    evaluate_sample = functools.partial(evaluate, kernels=choice.used, library=choice.library)
    progress = args.progress == "on" or (args.progress == "auto" and sys.stderr.isatty())
    try:
        info = execute.run(spec, args.out, evaluate_sample, workers=args.workers or os.cpu_count(),
                           scheduler=args.scheduler, batch=args.batch, progress=progress,
                           warm=warm, log=lambda m: print(f"cochlea-sweep: {m}", flush=True))
    except KeyboardInterrupt:
        try:
            finished = len(results.done(args.out, spec.total)) if args.out.is_dir() else 0
        except CochleaError:
            finished = 0
        print(f"cochlea-sweep: interrupted; {finished} of {spec.total} samples are in "
              f"{args.out}: run the same command to resume", file=sys.stderr)
        return EXIT_INTERRUPTED
    if info["samples"]:
        print(f"cochlea-sweep: {info['samples']} samples in {info['wall_s']:.1f} s on "
              f"{info['workers']} worker(s), {info['batches']} batches of up to "
              f"{info['batch']}", flush=True)
    else:
        print(f"cochlea-sweep: all {spec.total} samples were already in {args.out}", flush=True)
    return _report(args.out)


def _report(out: Path) -> int:
    """The report from the finished samples. The samples are the sweep's result and stay in
    ``out/parts`` whatever happens here: a report that fails (a full disk, a figure that
    cannot be drawn) is one line and :data:`EXIT_REPORT_FAILED`, not a traceback."""
    try:
        print(f"cochlea-sweep: report {sweep_report.write(out)}", flush=True)
    except (OSError, ValueError, ArithmeticError, TypeError, results.WriteFailed) as exc:
        print(f"cochlea-sweep: the report could not be written ({type(exc).__name__}: "
              f"{printable(str(exc))}); every finished sample is kept in {out}/parts: "
              f"`cochlea-sweep report {out}` writes it again", file=sys.stderr)
        return EXIT_REPORT_FAILED
    return 0


def _replay(argv: list[str]) -> int:
    p = OneLineParser(prog="cochlea-sweep replay",
                                description="Write the exact scenario of one sample: "
                                            "cochlea-run --scenario FILE --realtime off "
                                            "reproduces its row.")
    p.add_argument("dir", type=Path, metavar="DIR")
    p.add_argument("sample", type=whole_argument, metavar="SAMPLE")
    p.add_argument("--out", type=Path, metavar="FILE.toml",
                   help="where to write it (default: standard output)")
    args = p.parse_args(argv)
    spec = replay_spec(args.dir)
    if not 0 <= args.sample < spec.total:
        raise CochleaError(f"SAMPLE must be between 0 and {spec.total - 1} (the sweep in "
                           f"{args.dir} has {spec.total}), got {args.sample}")
    text = sampling.scenario_text(spec, args.sample)
    if args.out is None:
        sys.stdout.write(text)
    else:
        write_new(args.out, text)
        print(f"cochlea-sweep: sample {args.sample} -> {args.out}; run: cochlea-run --robot "
              f"{spec.robot} --space {spec.space} --scenario {args.out} --realtime off")
    return 0


def write_new(path: Path, text: str, option: str = "--out") -> None:
    """``text`` into a new file ``path``, whole or not at all; an existing path of any kind (a
    file, a FIFO, a device, a link, a folder) is refused and left as it is."""
    where = f"{option} {path}"
    if os.path.lexists(path):
        mode = os.lstat(path).st_mode
        raise results.SweepFolderError(f"{where} already exists ({results.kind_words(mode)}): "
                                       "replay writes a new file only: name another")
    parent = path.parent
    if not parent.is_dir():
        raise results.SweepFolderError(
            f"{where}: cannot create it, {parent} "
            + ("is not a folder" if os.path.lexists(parent) else "does not exist"))
    try:
        # Linked, not renamed: nothing that appeared there meanwhile is replaced.
        files.write_atomic(path, text, replace=False, keep_suffix=False)
    except FileExistsError:
        raise results.SweepFolderError(f"{where} appeared while it was written: name another"
                                       ) from None
    except OSError as exc:
        raise results.WriteFailed(f"{where}: cannot write it ({exc.strerror or exc})"
                                  ) from None


def replay_spec(folder: Path) -> sweep_spec.Spec:
    """The spec of a sweep folder, from its manifest alone (the spec and the base scenario as
    they were when the sweep started)."""
    m = results.read_manifest(folder)
    with tempfile.TemporaryDirectory(prefix="cochlea-sweep-") as tmp:
        # Each in a folder of its own: a spec is often named after its scenario
        # (docs/robustness/serial_task.toml sweeps serial_task.toml).
        scenario = Path(tmp) / "scenario" / Path(m.scenario_path).name
        spec_file = Path(tmp) / "spec" / Path(m.spec_path).name
        for path, text in ((scenario, m.scenario_text), (spec_file, m.spec_text)):
            path.parent.mkdir()
            path.write_text(text, encoding="utf-8")
        try:
            spec = sweep_spec.load(spec_file, scenario_file=scenario)
        except CochleaError as exc:
            shown = str(exc).replace(str(spec_file), "spec_text").replace(str(scenario),
                                                                         "scenario_text")
            raise results.FolderDamaged(f"{folder / results.MANIFEST}: damaged sweep "
                                        f"manifest: {shown}") from None
    spec = dataclasses.replace(spec, path=Path(m.spec_path), scenario_path=Path(m.scenario_path))
    if spec.digest != m.digest or spec.total != m.total:
        raise results.FolderDamaged(f"{folder / results.MANIFEST}: damaged sweep manifest: its "
                                    "texts do not match its hash")
    return spec


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    tolerate_closed_stdout()
    with sigterm_interrupts():  # SIGTERM (a batch system's stop) is an interrupt too
        try:
            if argv[:1] == ["replay"]:
                return _replay(argv[1:])
            if argv[:1] == ["report"]:
                p = OneLineParser(prog="cochlea-sweep report",
                                            description="Write DIR/summary.md and the figures "
                                                        "from the samples finished so far.")
                p.add_argument("dir", type=Path, metavar="DIR")
                args = p.parse_args(argv[1:])
                return _report(args.dir)
            return _sweep(argv)
        except CochleaError as exc:
            print(f"cochlea-sweep: {exc}", file=sys.stderr)
            return results.exit_code(exc)
        except KeyboardInterrupt:
            print("cochlea-sweep: interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
