"""``cochlea-identify``: a robot's base parameters from its own logs, with their statistics,
figures and (optionally) the values written back into a description.

User mistakes -- a bad option, a missing or bad log, a robot that was not excited -- print one
line and exit with EXIT_USER_ERROR, before any output file exists; the same log given twice,
an output that cannot take its file, and a write that fails (full disk, read-only) have their
own codes (docs/identification.md, "Files and exit codes"). Outputs are checked before the
logs are read and written all together, atomically, after the fit (cochlea.ident.files).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import sys
from pathlib import Path

import numpy as np

from ..errors import EXIT_USER_ERROR, CochleaError
from ..ident import current as current_fit
from ..ident import estimate, files, writeback
from ..ident.cli import OneLineParser, Terminated, sigterm_unwinds
from ..ident.cli import exit_code as terminated_code
from ..ident.logs import read_run
from ..ident.physical import physically_consistent_fit
from ..robots import ROBOTS, model, robot
from ..text import number_argument, whole_argument

#: Exit codes (docs/identification.md, "Exit codes"). EXIT_USER_ERROR (2): a wrong option,
#: description or log (unreadable, damaged, cut short, columns or units not the
#: description's, empty, non-finite, too short, not excited).
#: The same log given twice (a copy or a link), or a validation log that is a fitted one.
EXIT_DUPLICATE_LOG = 4
#: An output (--out, its figures, the write-back target) refused before anything was read.
EXIT_OUTPUT_REFUSED = 5
#: Writing the outputs failed (full disk, read-only file system, I/O error): nothing partial
#: is left and every previous output is kept.
EXIT_WRITE_FAILED = 6
EXIT_INTERRUPTED = 130


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _number_or_off(text: str, option: str, valid, expected: str) -> float | None:
    """An option that takes a number or ``off`` (None)."""
    if text.strip().lower() == "off":
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and valid(value)):
        raise CochleaError(f"{option}: expected {expected} or 'off', got {text!r}")
    return value


def _parallel_cutoff(text: str) -> float | None:
    """``--parallel-cutoff-hz``: a frequency (Hz) or ``off``."""
    return _number_or_off(text, "--parallel-cutoff-hz",
                          lambda v: v >= estimate.MIN_PARALLEL_CUTOFF_HZ,
                          f"a frequency of at least {estimate.MIN_PARALLEL_CUTOFF_HZ:g} Hz")


def _max_bus(text: str) -> float | None:
    """``--max-bus-periods``: a number of periods above 1, or ``off``."""
    return _number_or_off(text, "--max-bus-periods", lambda v: v >= 1,
                          "a number of control periods of at least 1")


def _effort_lag(text: str) -> float | str:
    """``--effort-lag``: control periods in [0, 10], or ``auto``."""
    if text.strip().lower() == estimate.AUTO:
        return estimate.AUTO
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and 0 <= value <= 10):
        raise CochleaError(f"--effort-lag: expected a number of control periods in [0, 10] or "
                           f"'auto', got {text!r}")
    return value


def _unit(args) -> str:
    adapter = robot(args.robot)
    return adapter.unit(adapter.load(args.description), args.arm)


def _physical(m, result: estimate.Identification):
    return physically_consistent_fit(m, result.W, result.y, result.weights,
                                     prior_full=m.full_parameters.nominal)


def _report(args, m, unit, logs, validate, result, physical) -> dict:
    p = m.parameters
    params = []
    for i, name in enumerate(p.names):
        entry = {"name": name, "meaning": p.meanings[i], "si_unit": p.si_units[i],
                 "nominal": float(p.nominal[i]), "ols": float(result.ols.beta[i]),
                 "ols_std_error": float(result.ols.std_error[i]),
                 "wls": float(result.wls.beta[i]),
                 "wls_std_error": float(result.wls.std_error[i]),
                 "wls_relative_std_error_percent": _finite(result.wls.relative_std_error[i])}
        if physical is not None:
            entry["physical"] = float(physical.base[i])
        params.append(entry)
    joints = list(m.joint_names)
    doc = {
        "format": "cochlea-identification/1",
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "robot": args.robot, "unit": unit, "model": m.name,
        "description": str(m.source),
        "logs": [{"folder": str(log.folder), "sha256": log.sha256, "rows": log.rows}
                 for log in logs],
        "validation_logs": [{"folder": str(log.folder), "sha256": log.sha256,
                             "rows": log.rows} for log in validate],
        "held_out": result.held_out,
        "settings": {"cutoff_hz": result.settings.cutoff_hz,
                     "filter": f"Butterworth order {estimate.FILTER_ORDER}, zero-phase",
                     "decimate": result.settings.decimate,
                     "min_speed_rad_s": result.settings.min_speed,
                     "effort_lag_periods": result.settings.effort_lag,
                     "effort_lag_option": args.effort_lag,
                     "sample_times_option": args.sample_times,
                     "max_bus_periods": result.settings.max_bus_periods,
                     "parallel_cutoff_hz": result.settings.parallel_cutoff_hz,
                     "guard_s": result.settings.guard_s,
                     "holdout": result.settings.holdout,
                     "max_condition": result.settings.max_condition},
        "fit_rows": result.fit_rows, "fit_samples": result.fit_samples,
        "condition_number": _finite(result.condition),
        "condition_number_scaled": _finite(result.condition_scaled),
        "parameters": params,
        "prediction_nrms_percent": {
            "joints": joints,
            "wls": [_finite(x) for x in result.prediction_nrms()],
            "ols": [_finite(x) for x in result.prediction_nrms(result.ols.beta)],
            "wls_all_samples": [_finite(x) for x in result.prediction_nrms(moving=False)]},
        "residual_rms_wls": dict(zip(joints, map(float, result.wls.residual_rms))),
        "current_fits": _line_report(result),
        "timing": _timing_report(result, logs + validate),
    }
    if physical is not None:
        doc["physical"] = {"full_names": list(m.full_parameters.names),
                           "full": [float(x) for x in physical.full],
                           "cost": float(physical.cost), "iterations": int(physical.iterations),
                           "prediction_nrms_percent":
                               [_finite(x) for x in result.prediction_nrms(physical.base)]}
    return doc


def _check_finite(doc, where: str = "") -> None:
    """Refuse a report holding a NaN or an infinity (JSON has no such number; a reader would
    take the token, or fail on it): every number it holds is finite, or null where the
    report says what null means. Named by its place in the report."""
    if isinstance(doc, dict):
        for key, value in doc.items():
            _check_finite(value, f"{where}.{key}" if where else str(key))
    elif isinstance(doc, (list, tuple)):
        for i, value in enumerate(doc):
            _check_finite(value, f"{where}[{i}]")
    elif isinstance(doc, float) and not math.isfinite(doc):
        raise estimate.NumericalError(f"the report's {where} is {doc}, not a finite number: "
                                      "the logs' numbers are out of the range the fit can "
                                      "take; check their units")


def _timing_report(result: estimate.Identification, logs) -> dict:
    """How the logs were placed in time and, with --effort-lag auto, the lag search."""
    out = {"logs": [{"folder": str(log.folder), "logged_times": logged,
                     "timing_lag_periods": estimate.timing_lag(log)}
                    for log, logged in zip(logs, result.logged_times)],
           "effort_lag_periods": result.settings.effort_lag, "lag_search": None}
    search = result.lag_search
    if search is not None:
        out["lag_search"] = {"lag_periods": search.lag,
                             "residual_rise_percent_at_quarter_period": search.rise_percent,
                             "grid_periods": [float(x) for x in search.grid],
                             "residual_rms_ratio": [float(x) for x in search.rms_ratio]}
    return out


def _line_report(result: estimate.Identification) -> list[dict]:
    """Each fitted current-to-torque line: SI at the motor and in the description's units."""
    out = []
    for k, ln in enumerate(result.lines):
        fa, fb = ln.scale_to_description()
        a, b = result.line_wls[k]
        sa, sb = result.line_wls_std[k]
        a0, b0 = ln.in_description_units(ln.a0, ln.b0)
        out.append({
            "joint": ln.name, "motor_id": ln.motor_id, "source_before": ln.source,
            "si": {"a_Nm_per_A": float(a), "a_std_error": float(sa), "b_Nm": float(b),
                   "b_std_error": float(sb),
                   "a_ols": float(result.line_ols[k][0]), "b_ols": float(result.line_ols[k][1]),
                   "knee_A": float(result.knees[ln.joint])},
            "description_units": {"x": ln.x, "y": ln.y, "a": a * fa, "a_std_error": sa * fa,
                                  "b": b * fb, "b_std_error": sb * fb,
                                  "a_before": a0, "b_before": b0},
            "a_relative_std_error_percent": _finite(100.0 * sa / abs(a)) if a else None})
    return out


def _print_table(doc: dict) -> None:
    print(f"{doc['model']}: {doc['fit_samples']} samples from {len(doc['logs'])} log(s), "
          f"{doc['fit_rows']} equations; condition number {doc['condition_number']:.4g} "
          f"(columns scaled: {doc['condition_number_scaled']:.4g})")
    width = max(len(p["name"]) for p in doc["parameters"])
    print(f"  {'':<{width}}  {'nominal':>12}  {'OLS':>12}  {'WLS':>12}  {'std err':>10}  "
          f"{'rel %':>8}  unit")
    for p in doc["parameters"]:
        rel = p["wls_relative_std_error_percent"]
        print(f"  {p['name']:<{width}}  {p['nominal']:>12.5g}  {p['ols']:>12.5g}  "
              f"{p['wls']:>12.5g}  {p['wls_std_error']:>10.3g}  "
              f"{'inf' if rel is None else f'{rel:.3g}':>8}  {p['si_unit']}")
    pred = doc["prediction_nrms_percent"]
    timing = doc["timing"]
    placed = sum(t["logged_times"] for t in timing["logs"])
    text = (f"  effort lag {timing['effort_lag_periods']:.3g} periods"
            + (" (each command held from its logged write plus the lag less half a period)"
               if placed else " (on the nominal grid)"))
    search = timing["lag_search"]
    if search is not None:
        text += (f" (auto: the residual's minimum; its RMS rises "
                 f"{search['residual_rise_percent_at_quarter_period']:.2g} % a quarter period "
                 "either side)")
    if placed:
        text += f"; {placed} of {len(timing['logs'])} log(s) at their logged sample times"
    print(text)
    for line in doc["current_fits"]:
        d = line["description_units"]
        print(f"  current-to-torque fit of {line['joint']} (ID {line['motor_id']}): "
              f"y = {d['a']:.5g} x + {d['b']:.5g} ({d['y']} over {d['x']}; std err "
              f"{d['a_std_error']:.2g}, {d['b_std_error']:.2g}); was {d['a_before']:.5g} x + "
              f"{d['b_before']:.5g} ({line['source_before'] or 'source not given'})")
    print(f"  held-out effort NRMS on {doc['held_out']} (moving samples), WLS: "
          + ", ".join(f"{j} {'inf' if v is None else f'{v:.2f}'} %"
                      for j, v in zip(pred["joints"], pred["wls"])))


def _outputs(args, out: Path, inputs: tuple[Path, ...]) -> list[tuple[Path, str]]:
    """Every file the run will write, with the option that names it: checked before the fit."""
    files_ = [(out, "--out")]
    if not args.no_figures:
        stem = out.with_suffix("")
        files_ += [(Path(f"{stem}_torques.png"), "--out (its figure)"),
                   (Path(f"{stem}_parameters.png"), "--out (its figure)")]
    if args.update_description:
        target = writeback.target_path(Path(args.update_description), args.in_place) \
            if args.in_place else Path(args.update_description).with_name(
                f"{Path(args.update_description).stem}.identified"
                f"{Path(args.update_description).suffix}")
        files_.append((target, "--update-description"))
    seen: dict[str, str] = {}
    for path, option in files_:
        key = os.path.abspath(path)
        if key in seen:
            raise files.OutputRefused(f"{option} {path}: the same file as {seen[key]}'s: "
                                      "name another --out")
        seen[key] = option
    for path, option in files_:
        if option != "--update-description":  # checked by writeback.check_writable
            files.check_output(path, option, inputs=inputs)
    return files_


def run(args) -> int:
    # Every check that needs no fit, before anything is read at length or written.
    out = Path(args.out)
    descriptions = (Path(args.description),) if args.description else ()
    if args.update_description:
        descriptions += (Path(args.update_description),)
    inputs = tuple(p for f in args.logs + (args.validate or []) for p in files.run_inputs(f)) \
        + descriptions
    _outputs(args, out, inputs)
    target = None
    if args.update_description:
        target = writeback.check_writable(Path(args.update_description), args.in_place,
                                          inputs=tuple(files.log_file(f) for f in
                                                       args.logs + (args.validate or [])))
    if args.decimate is not None and not 1 <= args.decimate <= estimate.MAX_DECIMATE:
        raise CochleaError(f"--decimate must be a whole number from 1 to "
                           f"{estimate.MAX_DECIMATE}, got {args.decimate}")
    if not (math.isfinite(args.cutoff_hz) and args.cutoff_hz >= estimate.MIN_CUTOFF_HZ):
        raise CochleaError(f"--cutoff-hz must be a frequency of at least "
                           f"{estimate.MIN_CUTOFF_HZ:g} Hz (and below the log's Nyquist "
                           f"frequency), got {args.cutoff_hz:g}")
    if not args.validate and not (estimate.MIN_HOLDOUT <= args.holdout
                                  <= estimate.MAX_HOLDOUT):
        raise CochleaError(f"--holdout must lie between {estimate.MIN_HOLDOUT:g} and "
                           f"{estimate.MAX_HOLDOUT:g} (a fraction of each log), got "
                           f"{args.holdout:g}")
    if not (math.isfinite(args.max_condition) and args.max_condition > 1):
        raise CochleaError(f"--max-condition must be a finite number above 1, got "
                           f"{args.max_condition:g}")
    effort_lag = _effort_lag(args.effort_lag)
    max_bus = _max_bus(args.max_bus_periods)
    parallel = _parallel_cutoff(args.parallel_cutoff_hz)
    if not (math.isfinite(args.guard_s) and 0 <= args.guard_s <= 10):
        raise CochleaError(f"--guard-s must lie in [0, 10] seconds, got {args.guard_s:g}")
    unit = _unit(args)
    # A robot of one unit ignores ``arm``.
    m = model(args.robot, arm=unit, parameterisation="base", actuators="all",
              description=args.description)
    drive_lines = current_fit.drive_lines(args.robot, m, unit, args.description)
    # The option's names and the every-joint refusal need no log: checked before reading.
    if args.fit_current.strip().lower() not in (current_fit.AUTO, current_fit.OFF):
        current_fit.choose(args.fit_current, drive_lines, True, "")
    # The same log twice (a copy, a link) is refused before any log is parsed.
    files.check_distinct_logs(args.logs, args.validate or [])
    logs = [read_run(folder, m, args.robot, unit) for folder in args.logs]
    validate = [read_run(folder, m, args.robot, unit) for folder in (args.validate or [])]
    everything = logs + validate
    with_current = all(log.current is not None for log in everything)
    lines = current_fit.choose(
        args.fit_current, drive_lines, with_current,
        ", ".join(str(log.folder) for log in everything if log.current is None))
    settings = estimate.Settings(args.cutoff_hz, args.decimate, args.holdout,
                                 args.max_condition, args.min_speed, effort_lag,
                                 parallel, args.guard_s, args.sample_times, max_bus)
    result = estimate.identify(m, logs, validate or None, settings, lines)
    try:
        physical = _physical(m, result) if args.physical else None
    except np.linalg.LinAlgError as exc:
        raise estimate.NumericalError(f"--physical: the physically consistent fit failed "
                                      f"numerically ({exc})") from None
    doc = _report(args, m, unit, logs, validate, result, physical)
    _check_finite(doc)
    written = []
    # Every output is written under a temporary name beside its target and renamed only when
    # all are complete: a full disk or an I/O error leaves the previous files as they were.
    with files.Staged() as stage:
        if target is not None:
            if physical is not None:
                phi, how = physical.full, "physically consistent fit"
            else:
                phi = writeback.closest_full(m, result.beta)
                how = "WLS, the full vector nearest the nominal one"
            path = writeback.write_back(m, args.robot, unit, Path(args.update_description),
                                        phi, [(str(log.folder), log.sha256) for log in logs],
                                        args.in_place, how, result.lines, result.line_wls,
                                        stage=stage)
            doc["description_written"] = str(path)
            written.append(path)
        if not args.no_figures:
            from ..ident import figures  # noqa: PLC0415 (matplotlib only when drawing)

            stem = out.with_suffix("")
            torques = Path(f"{stem}_torques.png")
            parameters = Path(f"{stem}_parameters.png")
            figures.torque_figure(result, stage.path(torques))
            figures.parameter_figure(result, stage.path(parameters))
            doc["figures"] = [str(torques), str(parameters)]
        stage.write_text(out, json.dumps(doc, indent=2, allow_nan=False) + "\n")
        stage.commit()
    _print_table(doc)
    print(f"  wrote {out}" + "".join(f", {p}" for p in written + doc.get("figures", [])))
    return 0


def parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="cochlea-identify",
        description="Identify a robot's base dynamic parameters (inertial, armature, viscous "
                    "and Coulomb friction) from the logs of its runs (cochlea-run, "
                    "cochlea-embedded): zero-phase filtering, the stacked base regressor, "
                    "ordinary and weighted least squares with standard errors, and the "
                    "effort predicted on held-out data. See docs/identification.md.")
    p.add_argument("logs", nargs="+", metavar="LOG_DIR",
                   help="run folders (each with its log.csv) to fit")
    p.add_argument("--robot", required=True, choices=list(ROBOTS))
    p.add_argument("--arm", help="serial: which arm's columns to identify (default: arm1)")
    p.add_argument("--description", help="the robot description the logs' robot was run "
                   "with (default: the shipped one)")
    p.add_argument("--out", default="ident.json", help="the report (JSON; default "
                   "ident.json); figures go beside it as OUT_torques.png, OUT_parameters.png")
    p.add_argument("--validate", nargs="+", metavar="LOG_DIR", help="run folders held out "
                   "for validation (default: the last --holdout of every fitted log)")
    p.add_argument("--holdout", type=number_argument, default=estimate.DEFAULT_HOLDOUT,
                   help="fraction of each log held out when no --validate is given "
                        f"(default {estimate.DEFAULT_HOLDOUT:g})")
    p.add_argument("--cutoff-hz", type=number_argument, default=estimate.DEFAULT_CUTOFF_HZ,
                   help="cut-off of the zero-phase Butterworth filter (default "
                        f"{estimate.DEFAULT_CUTOFF_HZ:g} Hz)")
    p.add_argument("--decimate", type=whole_argument,
                   help="keep every N-th filtered sample (default: "
                   "the log's rate over ten times the cut-off)")
    p.add_argument("--min-speed", type=number_argument, default=estimate.DEFAULT_MIN_SPEED,
                   help="leave out samples where a joint moves slower than this (rad/s; a "
                        "prismatic joint: times 0.02 m/rad) (default "
                        f"{estimate.DEFAULT_MIN_SPEED:g})")
    p.add_argument("--effort-lag", default=f"{estimate.DEFAULT_EFFORT_LAG:g}",
                   metavar="P|auto",
                   help="control periods by which the logged effort lags the motion it "
                        f"causes (default {estimate.DEFAULT_EFFORT_LAG:g}: a held command; "
                        "with logged sample times each command is held from its logged write "
                        "plus P - 0.5 periods); auto: the lag that minimises the fit's "
                        "residual")
    p.add_argument("--sample-times", choices=estimate.SAMPLE_TIMES,
                   default=estimate.SAMPLE_TIMES[0],
                   help="place each period's state and command at the times the log's timing "
                        "columns record (logged) or on the nominal grid time_s (nominal); "
                        "auto (default): logged for logs recorded over the motors or the "
                        "emulator (they carry measured current), nominal otherwise")
    p.add_argument("--max-bus-periods", default=f"{estimate.DEFAULT_MAX_BUS_PERIODS:g}",
                   metavar="P|off",
                   help="with logged sample times, leave out the samples near a period whose "
                        "bus transfers took longer than P periods (the chain answered late: "
                        "its timing is unknown) (default "
                        f"{estimate.DEFAULT_MAX_BUS_PERIODS:g}; off: keep them)")
    p.add_argument("--parallel-cutoff-hz", default=f"{estimate.DEFAULT_PARALLEL_CUTOFF_HZ:g}",
                   metavar="F|off", help="low-pass of the regressor's columns and the "
                   "efforts (parallel filtering): just above the excitation's highest "
                   f"harmonic (default {estimate.DEFAULT_PARALLEL_CUTOFF_HZ:g} Hz; off: none)")
    p.add_argument("--guard-s", type=number_argument, default=estimate.DEFAULT_GUARD_S,
                   help="with parallel filtering, leave out samples this close (s) to one "
                        "where a joint moves slower than --min-speed (default "
                        f"{estimate.DEFAULT_GUARD_S:g})")
    p.add_argument("--max-condition", type=number_argument, default=estimate.DEFAULT_MAX_CONDITION,
                   help="largest condition number of the column-scaled regressor accepted "
                        f"(default {estimate.DEFAULT_MAX_CONDITION:g})")
    p.add_argument("--fit-current", default=current_fit.AUTO, metavar="auto|off|JOINT,...",
                   help="fit these joints' current-to-torque lines from the measured current "
                        "the logs carry, with the base parameters (auto, the default: the "
                        "joints whose fit the description marks source = \"placeholder\", "
                        "when every log carries the current; off: none)")
    p.add_argument("--physical", action="store_true",
                   help="also fit physically consistent parameters (and write those back)")
    p.add_argument("--update-description", metavar="TOML",
                   help="write the identified values into a copy of this description, "
                        "NAME.identified.toml beside it")
    p.add_argument("--in-place", action="store_true",
                   help="with --update-description: overwrite the description itself")
    p.add_argument("--no-figures", action="store_true", help="write no PNG figures")
    return p


def exit_code(exc: CochleaError) -> int:
    """The documented exit code of a refusal (docs/identification.md, "Exit codes")."""
    if isinstance(exc, files.DuplicateLog):
        return EXIT_DUPLICATE_LOG
    if isinstance(exc, files.OutputRefused):
        return EXIT_OUTPUT_REFUSED
    if isinstance(exc, files.WriteFailed):
        return EXIT_WRITE_FAILED
    return EXIT_USER_ERROR


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if args.in_place and not args.update_description:
        print("cochlea-identify: --in-place needs --update-description", file=sys.stderr)
        return EXIT_USER_ERROR
    try:
        with sigterm_unwinds():
            return run(args)
    except CochleaError as exc:
        print(f"cochlea-identify: {exc}", file=sys.stderr)
        return exit_code(exc)
    except BrokenPipeError:
        return 0
    except KeyboardInterrupt as exc:
        print("cochlea-identify: " + ("terminated" if isinstance(exc, Terminated) else
                                      "interrupted") + "; nothing written", file=sys.stderr)
        return terminated_code(exc) if isinstance(exc, Terminated) else EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())

