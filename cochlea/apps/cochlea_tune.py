"""``cochlea-tune``: a gain search over a sweep spec's perturbation sample, on Dask.

    cochlea-tune SPEC.toml --out DIR [--trials N] [--workers N] [--scheduler ADDRESS]
                 [--objective pNN|worst|mean] [--seed S] [--progress auto|on|off]

Every candidate (Optuna's TPE proposes them) runs the spec's whole perturbation sample, the
same draws for every candidate; the objective is a percentile (default p95), the worst or the
mean of the runs' convergence ratios, and a candidate with a run at a torque limit or stopped by
a supervisor rule is infeasible. DIR gets trials.csv, tuned.toml (the base scenario with the
best gains), summary.md and history.png. The same command on the same DIR resumes.
Exit codes (the table in docs/sweeps.md): 0 done; 1 done, but no candidate (the nominal gains
included) was feasible, so no tuned.toml; 2 the spec or an option is wrong; 3 --out cannot be
used; 4 --out is in use by another run; 5 the folder's files are damaged; 6 a write failed
while running (a full disk); 7 a sample failed on a worker; 130 interrupted (every finished
trial is kept).
"""

from __future__ import annotations

import io
import math
import os
import sys
from pathlib import Path

from matplotlib.figure import Figure

from ..console import OneLineParser, sigterm_interrupts, tolerate_closed_stdout
from ..errors import CochleaError
from ..sweep import results
from ..sweep import tune as tuning
from ..text import whole_argument
from . import cochlea_sweep

EXIT_NO_FEASIBLE = 1
EXIT_INTERRUPTED = 130
#: Trials listed in the summary.
LISTED = 10


def check_corners(tune: tuning.Tune) -> None:
    """Before any worker starts: with every searched gain at the low end of its range and then
    at the high end, the sample's first and last scenarios and every combination of the
    values the spec gives the keys of the loader's rules between ``[plant]`` keys
    (:func:`cochlea.apps.cochlea_sweep.check_samples`) through the scenario loader and the
    run's up-front checks."""
    for end, k in (("low", 0), ("high", 1)):
        gains = {d.name: d.corners()[k] for d in tune.dims}
        cochlea_sweep.check_samples(tune.candidate(gains),
                                    f" with the gains at the {end} end of their ranges")


def _fmt(value) -> str:
    if isinstance(value, list):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def write_report(out: Path, tune: tuning.Tune, result: dict) -> Path:
    """summary.md and history.png in ``out``; tuned.toml when a candidate is feasible."""
    records = sorted(tuning.trial_records(tuning.open_study(out, tune), tune),
                     key=lambda r: r["trial"])
    s = tune.settings
    nominal, chosen = result["nominal"], result["chosen"]
    what = {"worst": "the worst", "mean": "the mean"}.get(s.objective,
                                                         f"the {s.objective[1:]}th percentile")
    perturbed = [e.name for e in tune.sample.entries if e.name.startswith("plant.")
                 and e.kind != "fixed"]
    lines = [f"# cochlea-tune: {tune.spec.path.name}", "",
             f"Scenario {tune.spec.scenario_path.name} (robot {tune.spec.robot}, space "
             f"{tune.spec.space}). Every candidate runs the same {tune.size} perturbed plants "
             f"(seed {tune.spec.seed}; varied: {', '.join(perturbed) or 'nothing'}). Objective: "
             f"{what} of the runs' convergence ratios (final RMS error over the convergence "
             "threshold, the largest over the tracked coordinates: 1 is converged), lower is "
             "better; a candidate with a run at a torque limit or stopped (supervisor rule, "
             "divergence) is infeasible.", "",
             f"{len(records)} trials finished ({s.trials} asked for), "
             f"{sum(1 for r in records if r['feasible'])} feasible (sampler seed {s.seed}).", ""]
    columns = [("objective", "objective"), ("feasible", "feasible"),
               ("successes", "runs converged"), ("median_ratio", "median convergence ratio"),
               ("worst_ratio", "worst convergence ratio"),
               ("max_torque_ratio", "peak effort / limit"),
               ("torque_limit_runs", "runs at a torque limit"), ("stopped_runs", "runs stopped")]
    label = "none feasible" if chosen is None else (
        "nominal (no trial beat it)" if chosen["trial"] == "nominal"
        else f"tuned (trial {chosen['trial']})")
    lines += [f"| | nominal | {label} |", "| --- | --- | --- |"]
    for key, name in columns:
        lines.append(f"| {name} | {_fmt(nominal[key]) if nominal else '-'} | "
                     f"{_fmt(chosen[key]) if chosen else '-'} |")
    for d in tune.dims:
        lines.append(f"| {d.name}{' (log scale)' if d.log else ''} | "
                     f"{_fmt(nominal['gains'][d.name]) if nominal else '-'} | "
                     f"{_fmt(chosen['gains'][d.name]) if chosen else '-'} |")
    lines.append("")
    if nominal and chosen and nominal["objective"] > 0:
        lines += [f"The objective goes from {nominal['objective']:.4g} to "
                  f"{chosen['objective']:.4g} ({chosen['objective'] / nominal['objective']:.1%}"
                  " of the nominal's) on the same sample.", ""]
    if chosen is not None:
        lines += [f"Run it: `cochlea-run --robot {tune.spec.robot} --space {tune.spec.space} "
                  f"--scenario {out / tuning.TUNED}`", ""]
    else:
        lines += ["No candidate was feasible: no tuned.toml. Widen the ranges, lower the "
                  "perturbations, or look at the trials' runs in samples/.", ""]
    lines += ["![history](history.png)", "", f"## The {LISTED} best trials", "",
              "| trial | objective | feasible | " + " | ".join(d.name for d in tune.dims) + " |",
              "| --- | --- | --- |" + " --- |" * len(tune.dims)]
    ranked = sorted(records, key=lambda r: (not r["feasible"], r["objective"], r["trial"]))
    for r in ranked[:LISTED]:
        lines.append(f"| {r['trial']} | {r['objective']:.4g} | {r['feasible']} | "
                     + " | ".join(_fmt(r["gains"][d.name]) for d in tune.dims) + " |")
    lines += ["", "Every trial: trials.csv; every run of a trial: samples/trial-NNNNNN.parquet "
              "(one row per run, the columns of cochlea-sweep's)."]
    _history(out / "history.png", records, nominal, s.objective)
    summary = out / "summary.md"
    tuning.write_atomic(summary, ("\n".join(lines) + "\n").encode("utf-8"))
    return summary


def _history(path: Path, records: list[dict], nominal: dict | None, objective: str) -> None:
    fig = Figure(figsize=(7, 4))
    ax = fig.subplots()
    ok = [r for r in records if r["feasible"]]
    bad = [r for r in records if not r["feasible"]]
    ax.plot([r["trial"] for r in ok], [r["objective"] for r in ok], "o", ms=4, color="C0",
            label="feasible")
    ax.plot([r["trial"] for r in bad], [min(r["objective"], 1e6) for r in bad], "x", ms=5,
            color="C3", label="infeasible (torque limit or stop)")
    best, xs, ys = math.inf, [], []
    for r in ok:
        best = min(best, r["objective"])
        xs.append(r["trial"])
        ys.append(best)
    if xs:
        ax.step(xs, ys, where="post", color="C0", lw=1.2, label="best so far")
    if nominal is not None:
        ax.axhline(nominal["objective"], color="k", ls="--", lw=1, label="nominal gains")
    values = [r["objective"] for r in records if 0 < r["objective"] < 1e6]
    if values and max(values) / min(values) > 20:
        ax.set_yscale("log")
    ax.axhline(1.0, color="0.6", lw=0.8, label="1: converged")
    ax.set_xlabel("trial")
    ax.set_ylabel(f"objective ({objective} of convergence ratio)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    sink = io.BytesIO()
    fig.savefig(sink, dpi=110, format="png")
    tuning.write_atomic(path, sink.getvalue())


def _tune(argv: list[str]) -> int:
    p = OneLineParser(
        prog="cochlea-tune",
        description="Search a scenario's gains (the spec's [gains] ranges) for the best "
                    "objective over the spec's perturbation sample, on Dask workers; writes "
                    "DIR/tuned.toml, DIR/trials.csv and DIR/summary.md.",
        epilog="The same command on the same DIR resumes an interrupted search (a larger "
               "--trials continues a finished one). See docs/sweeps.md.")
    p.add_argument("spec", type=Path, metavar="SPEC.toml")
    p.add_argument("--out", type=Path, required=True, metavar="DIR")
    p.add_argument("--trials", type=whole_argument, metavar="N",
                   help=f"candidates to evaluate (default: [tune] trials, else "
                        f"{tuning.DEFAULTS['trials']})")
    p.add_argument("--workers", type=whole_argument, metavar="N",
                   help=f"local worker processes (default: the cores, {os.cpu_count()})")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="an existing Dask scheduler, e.g. tcp://10.0.0.5:8786, whose workers "
                        "run the samples (instead of local processes)")
    p.add_argument("--objective", metavar="pNN|worst|mean",
                   help="over the sample's convergence ratios (default: [tune] objective, else "
                        "p95)")
    p.add_argument("--seed", type=whole_argument, metavar="S",
                   help="the sampler's seed (default: [tune] seed, else the spec's seed)")
    p.add_argument("--progress", default="auto", choices=["auto", "on", "off"],
                   help="progress bar on stderr (auto: when stderr is a terminal)")
    args = p.parse_args(argv)
    if args.trials is not None and not 1 <= args.trials <= tuning.MAX_TRIALS:
        raise CochleaError(f"--trials must be between 1 and {tuning.MAX_TRIALS:,}, got "
                           f"{args.trials}")
    if args.workers is not None and not 1 <= args.workers <= 4096:
        raise CochleaError(f"--workers must be between 1 and 4096, got {args.workers}")
    if args.workers is not None and args.scheduler is not None:
        raise CochleaError("--workers starts local workers; with --scheduler the scheduler's "
                           "workers run the samples: give one or the other")
    if args.objective is not None and not tuning.objective_ok(args.objective):
        raise CochleaError(f"--objective must be {tuning.OBJECTIVE_TEXT}, got "
                           f"{args.objective!r}")
    if args.seed is not None and not 0 <= args.seed < 2**32:
        raise CochleaError(f"--seed must be between 0 and 2**32 - 1, got {args.seed}")
    tune = tuning.load(args.spec, trials=args.trials, objective=args.objective, seed=args.seed)
    check_corners(tune)
    progress = args.progress == "on" or (args.progress == "auto" and sys.stderr.isatty())
    try:
        info = tuning.run(tune, args.out, cochlea_sweep.evaluate,
                          workers=args.workers or os.cpu_count(), scheduler=args.scheduler,
                          progress=progress, warm=cochlea_sweep.warm,
                          log=lambda m: print(f"cochlea-tune: {m}", flush=True))
    except KeyboardInterrupt:
        print(f"cochlea-tune: interrupted; the finished trials are in {args.out}: run the same "
              "command to resume", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as exc:  # the journal (Optuna's writes) on a full disk, say
        raise results.WriteFailed(f"--out {args.out}: a write failed ({exc.strerror or exc}); "
                                  "every finished trial is kept: free some space and run the "
                                  "same command to resume") from None
    result = info["result"]
    chosen = result["chosen"]
    try:
        tuned = tuning.write_tuned(args.out, tune, chosen)
        summary = write_report(args.out, tune, result)
    except OSError as exc:
        raise results.WriteFailed(f"--out {args.out}: the report could not be written "
                                  f"({exc.strerror or exc}); every trial is kept: free some "
                                  "space and run the same command") from None
    nominal = result["nominal"]
    ran = (f"{info['trials_run']} run now on {info['workers']} worker(s)" if info["workers"]
           else f"all already in {args.out}")
    print(f"cochlea-tune: {result['trials']} trials ({ran}), {result['feasible_trials']} "
          f"feasible; objective "
          f"{tune.settings.objective}: nominal {nominal['objective']:.4g}"
          + (f", tuned {chosen['objective']:.4g} -> {tuned}" if chosen else
             ", no feasible candidate"), flush=True)
    print(f"cochlea-tune: report {summary}", flush=True)
    return 0 if chosen is not None else EXIT_NO_FEASIBLE


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    tolerate_closed_stdout()
    with sigterm_interrupts():  # SIGTERM (a batch system's stop) is an interrupt too
        try:
            return _tune(argv)
        except CochleaError as exc:
            print(f"cochlea-tune: {exc}", file=sys.stderr)
            return results.exit_code(exc)
        except KeyboardInterrupt:
            print("cochlea-tune: interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
