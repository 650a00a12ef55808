"""What a run leaves behind: the CSV log, ``summary.json`` and the figures.

The log has one row per control period; every column name ends in its unit (``_s``, ``_rad``,
``_m``, ``_rad_s``, ``_m_s``, ``_N_m``, ``_N``, ``_A`` or the parameter's unit:
:mod:`cochlea.log_schema`). Figures show angles in
degrees (an edge of the program) with the unit on every axis.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from ..log_schema import SCHEMA_VERSION, TIMING_COLUMNS, LogUnit, run_columns
from ..runtime.supervisor import LogReductions, column_extremes, own_reductions
from ..runtime.supervisor import row_squares as _row_squares
from ..sim import result as run_result
from ..sim.result import SimulationResult, StreamedResult, UnitLog
from .outputs import ReportError, atomic_path, write_text_atomic

#: Convergence: the RMS tracking error over the last 20 % of the run must be at most this
#: fraction of the initial absolute error ...
CONVERGENCE_RATIO = 0.05
#: ... or below this floor (for coordinates that start on target), by unit; on a plant that
#: measures positions in encoder counts, below the resolution of a count (see
#: :func:`measurement_resolution`): no controller can resolve less.
CONVERGENCE_FLOOR = {"rad": 1e-5, "m": 1e-6}
TAIL_FRACTION = 0.2
#: Periods the figures plot at most (a long run is decimated evenly; a short one is whole).
FIGURE_POINTS = 5_000

_EFFORT_UNIT = {"rad": "Nm", "m": "N"}
_UNIT_TEXT = {"rad": "rad", "m": "m", "Nm": "N m", "N": "N"}


def columns(result: SimulationResult) -> tuple[list[str], np.ndarray]:
    """Column names (with units, :func:`cochlea.log_schema.run_columns`: the one schema of
    every log) and the data matrix of the log."""
    units = [LogUnit.of_setup(u.setup, u.space) for u in result.units]
    current = any(u.current is not None for u in result.units)
    truth = any(u.has_true_state for u in result.units)
    names = run_columns(units, timing=bool(result.timing), current=current,
                        true_state=truth)
    blocks = [result.time[:, None]]
    for u in result.units:
        n_track = u.setup.controller.n_desired
        blocks += [u.q, u.qd, u.desired, u.desired_dot, u.measured_tracking_error,
                   u.errors[:, n_track:], u.tau] + ([] if u.current is None else [u.current]) \
            + [u.p_hat, u.pose]
        if u.has_true_state:  # a simulated run: the plant's own state beside the measured one
            blocks += [u.true_q, u.true_qd, u.true_x, u.true_tracking_error]
    if result.timing:  # real-time runs: the timing of every period
        blocks += [result.timing[name][:, None] for name in TIMING_COLUMNS]
    data = np.hstack(blocks)
    if data.shape[1] != len(names):
        raise AssertionError(f"log.csv: {data.shape[1]} values a row, {len(names)} names")
    return names, data


def write_csv(result: SimulationResult, path: Path) -> None:
    """The log a chunk of periods at a time: memory bounded by the chunk, not the run."""
    names, _ = columns(result.rows(0, 0))
    with open(path, "w") as f:
        f.write(",".join(names) + "\n")
        for chunk in result.chunks():
            np.savetxt(f, columns(chunk)[1], delimiter=",", fmt="%.10g")


def measurement_resolution(u: UnitLog, position_quantum: np.ndarray | None = None
                           ) -> np.ndarray | None:
    """Per tracked coordinate, what one encoder count on every joint moves it at the run's
    last pose (rad or m): the joint's quantum in joint space, ``sum_j |fk(q + count_j) -
    fk(q)|`` in task space. The count is ``position_quantum`` (per joint, SI: the drives'
    encoders of a hardware run) or else the plant's grid; None when neither has one."""
    if position_quantum is None:
        quantum = u.setup.quantum
        if quantum is None or not len(u.q) or not np.any(quantum[:u.q.shape[1]] > 0):
            return None
        counts = quantum[:u.q.shape[1]]
    else:
        if not len(u.q):
            return None
        counts = np.abs(np.asarray(position_quantum, dtype=float))
    if u.setup.controller.space == "joint":
        return counts.copy()
    q = u.q[-1]
    pose = np.array(u.setup.fk_world(q)).ravel()
    moved = [np.abs(np.array(u.setup.fk_world(q + step)).ravel() - pose)
             for step in np.diag(counts)]
    return np.sum(moved, axis=0)


class _ErrorStats:
    """One tracking error's initial absolute value and the sum of its squares over the tail."""

    def __init__(self, tail_start: int):
        self.tail_start = tail_start
        self.initial = None  # |e| of the first period
        self.tail_sq = self.tail_n = 0

    def add(self, error, rows: int, start: int) -> None:
        """``rows`` periods from period ``start`` (a chunk of a streamed run, or a whole run
        in memory); ``error(part)``: their error on the rows ``part`` (a slice), computed only
        where it is read: the first period and the tail."""
        skip, chunk = 0, run_result.CHUNK_ROWS  # the size SimulationResult.chunks() reads in
        if self.initial is None:
            # The first period with a measured state: a run whose first reads failed logs NaN
            # until its first good read (the loop commands nothing before it).
            e = error(slice(0, 1))
            if not np.isfinite(e).all():
                e = error(slice(0, rows))
                found = np.flatnonzero(np.isfinite(e).all(axis=1))
                if not len(found):
                    return
                e = e[found[0]:]
                # As a run read a chunk at a time: the tail in the chunks before that period's
                # is not summed.
                skip = (start + int(found[0])) // chunk * chunk - start
            self.initial = np.abs(e[0])
        first = max(self.tail_start - start, skip, 0)
        if first < rows:
            e = error(slice(first, rows))
            # Column by column, as np.mean sums a column: a one-chunk run's numbers are exact.
            # Summed in the pieces the chunks of a streamed run cut it into, so a run read
            # whole and one read a chunk at a time have the same numbers, bit for bit.
            cuts = [c - start - first for c in range((start + first) // chunk * chunk + chunk,
                                                     start + rows, chunk)]
            for a, b in zip([0, *cuts], [*cuts, len(e)]):
                self.tail_sq = self.tail_sq + _column_square_sums(e[a:b])
            self.tail_n += rows - first

    def final_rms(self, i: int) -> float:
        return float(np.sqrt(self.tail_sq[i] / self.tail_n))


#: The fields a tracking error reads (:func:`_rows`).
_ERROR_FIELDS = ("q", "errors", "desired", "true_q", "true_x")
#: The fields of a unit's last period the summary keeps.
_LAST_FIELDS = ("q", "qd", "desired", "desired_dot", "errors", "tau", "p_hat", "x", "true_q",
                "true_qd", "true_x")


def _column_square_sums(e: np.ndarray) -> np.ndarray:
    """Each column's sum of squares, as ``np.sum(e[:, i] ** 2)`` sums it (pairwise, in the
    same order, so bit for bit): the columns squared into the rows of one C-ordered array,
    each row reduced along its memory; two calls for every column instead of two a column."""
    return np.add.reduce(np.square(e.T, order="C"), axis=1)


def _rows(u: UnitLog, part: slice, fields: tuple[str, ...] = _ERROR_FIELDS) -> UnitLog:
    """``u``'s periods ``part``, as far as ``fields`` (default: what a tracking error reads):
    what ``dataclasses.replace`` makes of it (a UnitLog's fields are only stored), without
    calling its ``__init__`` (a third of the time; the summary asks for five a unit)."""
    rows = object.__new__(UnitLog)
    rows.__dict__.update(u.__dict__)
    for k in fields:
        value = getattr(u, k)
        if value is not None:
            setattr(rows, k, value[part])
    return rows


def _measured_error(u: UnitLog, part: slice) -> np.ndarray:
    """:attr:`UnitLog.measured_tracking_error` of ``u``'s periods ``part``."""
    return _rows(u, part).measured_tracking_error


def _judged_error(u: UnitLog, part: slice) -> np.ndarray:
    """:attr:`UnitLog.tracking_error` of ``u``'s periods ``part`` (the true one where the log
    has the true state)."""
    return _rows(u, part).tracking_error


def _largest_norm(p: np.ndarray, squares: np.ndarray | None = None) -> float:
    """``max(np.linalg.norm(p, axis=1))``, bit for bit, without a norm of every row: the rows'
    squares (:func:`~cochlea.runtime.supervisor.row_squares`, or ``squares`` when the caller
    has them; rounded in another order for many columns) find the few rows that can hold the
    largest, whose norms are then taken as np.linalg.norm takes them (its square root is
    monotonic, so the largest norm is the root of the largest sum). Non-finite rows: every
    norm, as before."""
    if squares is None:
        squares = _row_squares(p)
    top = squares.max(initial=0.0)
    if not np.isfinite(top):
        return np.max(np.linalg.norm(p, axis=1))
    # Two sums of the same squares differ by far less than this (n eps of the largest).
    near = p[squares >= top * (1 - 1e-9)]
    return np.max(np.linalg.norm(near, axis=1))


class _UnitStats:
    """What a unit's summary needs from every period, gathered a chunk at a time: the error
    the run is judged on (the true one where the run knows the true state) and the error the
    controller measured."""

    def __init__(self, periods: int, row: bool = False):
        tail_start = int(periods * (1 - TAIL_FRACTION))
        self.judged = _ErrorStats(tail_start)
        self.measured = None if row else _ErrorStats(tail_start)
        self.tau_max = None
        self.max_norm = np.zeros(())
        self.finite = True
        self.last = None  # the last period, as a one-row UnitLog
        #: Only what a sweep's row reads (:func:`summary`'s ``row``): no measured error, and
        #: the largest estimate norm left out (None) where the rows' squares settle that
        #: every estimate is inside its bound.
        self.row = row

    def add(self, u: UnitLog, start: int, reduced: LogReductions | None = None) -> None:
        """``reduced``: the reductions of this ``u`` (a whole run), when the caller has them."""
        rows = len(u.q)
        if not rows:
            return
        if self.measured is not None:
            self.measured.add(lambda part: _measured_error(u, part), rows, start)
        self.judged.add(lambda part: _judged_error(u, part), rows, start)
        # Each column's largest |effort| from its extremes, all columns in one blocked pass
        # (a NaN makes both NaN; np.abs makes a -0.0 the 0.0 it gave column by column).
        low, high = column_extremes(u.tau) if reduced is None else (reduced.tau_low,
                                                                   reduced.tau_high)
        peaks = np.abs(np.maximum(high, -low))
        self.tau_max = peaks if self.tau_max is None else np.maximum(self.tau_max, peaks)
        # (A row's summary is of a run in memory, one chunk: summary() gives streamed runs
        # no reductions.)
        if self.row and reduced is not None and _inside(reduced.square_all, u.setup.bound):
            self.max_norm = None  # every estimate finite and inside the bound: not needed
            self.last = _rows(u, slice(-1, None), _LAST_FIELDS)
            return
        largest = _largest_norm(u.p_hat)
        self.max_norm = np.maximum(self.max_norm, largest)
        # A finite largest norm: every estimate finite (a NaN or an infinity makes its norm so).
        self.finite = self.finite and bool(np.isfinite(largest)
                                           or np.isfinite(u.p_hat).all())
        self.last = _rows(u, slice(-1, None), _LAST_FIELDS)


def _inside(largest_square: float, bound: float) -> bool:
    """Whether every estimate row has a finite norm within ``bound`` as the summary judges it
    (``np.linalg.norm`` at most ``bound (1 + 1e-9)``), from the rows' largest sum of squares
    (:class:`~cochlea.runtime.supervisor.LogReductions`' ``square_all``, summed in any order):
    finite (no NaN, no infinity, no overflow) and below the bound's square with a slack far
    wider than two sums' rounding. False: undecided (the norm decides)."""
    limit = bound * (1 + 1e-9)
    return math.isfinite(largest_square) and \
        largest_square * (1 + 1e-12) <= limit * limit * (1 - 1e-12)


def unit_summary(u: UnitLog, position_quantum: np.ndarray | None = None) -> dict:
    """The summary of one unit's log held in memory."""
    stats = _UnitStats(len(u.q))
    stats.add(u, 0)
    return _unit_summary(u, stats, position_quantum)


def _unit_summary(u: UnitLog, stats: _UnitStats,
                  position_quantum: np.ndarray | None = None) -> dict:
    """``u`` describes the unit (its rows are not read); ``stats`` holds every period's;
    ``position_quantum`` the drives' encoder count per joint of a hardware run (SI)."""
    resolution = measurement_resolution(stats.last, position_quantum) \
        if stats.last is not None else None
    tracked = {}
    for i, (name, unit) in enumerate(zip(u.tracked_names, u.tracked_units)):
        # The same floor for the true and the measured error: where the positions are measured
        # in encoder counts, a controller that sees counts cannot hold the true state closer
        # than about a count either, though the true state itself is not on the grid.
        floor = CONVERGENCE_FLOOR[unit] if resolution is None else \
            max(CONVERGENCE_FLOOR[unit], float(resolution[i]))
        if stats.judged.initial is None:  # a run stopped before its first period
            tracked[name] = {"unit": unit, "initial_abs_error": None, "final_rms_error": None,
                             "converged": False, "convergence_floor": floor,
                             "measured_initial_abs_error": None,
                             "measured_final_rms_error": None, "measured_converged": False}
            continue

        def judge(errors: _ErrorStats, i=i, floor=floor) -> tuple[float, float, bool]:
            initial, final_rms = float(errors.initial[i]), errors.final_rms(i)
            return initial, final_rms, bool(np.isfinite(final_rms) and (
                final_rms <= CONVERGENCE_RATIO * initial or final_rms <= floor))

        initial, final_rms, converged = judge(stats.judged)
        m_initial, m_final_rms, m_converged = (None, None, None) if stats.measured is None \
            else judge(stats.measured)
        tracked[name] = {
            "unit": unit,
            # Judged: of the true state where the run has it (summary's judged_error).
            "initial_abs_error": initial,
            "final_rms_error": final_rms,
            "converged": converged,
            # The floor this coordinate was judged on: the numeric one, or one encoder count
            # on every joint where the positions are measured in counts.
            "convergence_floor": floor,
            # The error the controller computed from what it measured (delayed, noisy, on the
            # grids), judged by the same rule; the same numbers on hardware.
            "measured_initial_abs_error": m_initial,
            "measured_final_rms_error": m_final_rms,
            "measured_converged": m_converged,
        }
        if resolution is not None:
            tracked[name]["measurement_resolution"] = float(resolution[i])
    torque = {}
    for i, (j, unit) in enumerate(zip(u.setup.controller_model.joints, u.setup.joint_units)):
        peak = 0.0 if stats.tau_max is None else float(stats.tau_max[i])
        torque[j.name] = {"unit": _UNIT_TEXT[_EFFORT_UNIT[unit]], "max_abs": peak}
    max_norm = None if stats.max_norm is None else float(stats.max_norm)
    params = u.setup.controller_model.parameters
    return {
        "tracked": tracked,
        "position_quantum": _position_quantum(u, position_quantum),
        "torque": torque,
        "estimates": {
            "names": list(params.names),
            "units": list(params.si_units),
            "bound_norm": u.setup.bound,
            "max_norm": max_norm,
            "bounded": max_norm is None or bool(stats.finite
                                                and max_norm <= u.setup.bound * (1 + 1e-9)),
            "final": [float(v) for v in stats.last.p_hat[-1]] if stats.last is not None
            else None,
            "nominal": [float(v) for v in u.setup.controller_model.p_nominal],
        },
    }


def _position_quantum(u: UnitLog, position_quantum: np.ndarray | None) -> dict | None:
    """Per joint, the count its position is measured in (SI) and where it comes from."""
    joints = [j.name for j in u.setup.controller_model.joints]
    if position_quantum is not None:
        source, values = "drives", np.abs(np.asarray(position_quantum, dtype=float))
    elif u.setup.quantum is not None and np.any(u.setup.quantum[:len(joints)] > 0):
        source, values = "plant", u.setup.quantum[:len(joints)]
    else:
        return None
    return {"source": source,
            "joints": {j: {"value": float(v), "unit": un}
                       for j, v, un in zip(joints, values, u.setup.joint_units)}}


def summary(result: SimulationResult, wall_time_s: float | None = None,
            timing: dict | None = None, realtime: dict | None = None,
            position_quantum: dict | None = None,
            reductions: list[LogReductions] | None = None, row: bool = False) -> dict:
    """``position_quantum``: per unit name, its joints' encoder counts (SI) when the run
    measured real drives (a hardware run); the convergence floor then knows them.
    ``reductions``: each unit's :func:`~cochlea.runtime.supervisor.log_reductions` of this
    result held in memory, when the caller has them (a sweep's worker: the verdict read them
    too); the same summary either way.

    ``row``: only what a sweep's row reads (:func:`cochlea.apps.cochlea_sweep.measures`),
    for a worker that writes no summary.json: every coordinate's ``measured_*`` entries are
    None (the measured error is not computed), and so is an estimate's ``max_norm`` where
    the shared reductions' row squares settle that it is ``bounded``; every other entry as
    without it, bit for bit."""
    sc = result.scenario
    stats = [_UnitStats(result.periods, row) for _ in result.units]
    start = 0
    # A run in memory is read whole (its sums in the same pieces as a streamed run's chunks:
    # _ErrorStats.add), a streamed one a chunk at a time.
    streamed = isinstance(result, StreamedResult)
    reductions = own_reductions(None if streamed else reductions, result.units)
    for chunk in result.chunks() if streamed else [result]:
        for s, u, reduced in zip(stats, chunk.units, reductions):
            s.add(u, start, reduced)
        start += chunk.periods
    quanta = position_quantum or {}
    units = {u.name: _unit_summary(u, s, quanta.get(u.name))
             for u, s in zip(result.units, stats)}
    converged = all(c["converged"] for s in units.values() for c in s["tracked"].values())
    # The true state where every unit's log has it (simulation), else what was measured.
    truth = bool(result.units) and all(u.has_true_state for u in result.units)
    # Stopped: a real-time run by its supervisor (or the user, a fault), an as-fast run by
    # the rule its supervisor's after-the-fact verdict would have stopped a real run on.
    stopped = (result.stop is not None and result.stop["rule"] != "completed") or \
        (result.supervisor is not None and result.supervisor.get("rule", "none") != "none")
    return {
        # The column names of log.csv and log.columns.json (cochlea.log_schema).
        "schema_version": SCHEMA_VERSION,
        "scenario": sc.name,
        # Absolute: a relative --scenario (my.toml) stored as given would name another file,
        # or none, from wherever the run is read (cochlea-mcap, cochlea-view, cochlea-ros2).
        "scenario_file": os.path.abspath(sc.path),
        "robot": sc.robot,
        "space": sc.space,
        "controller": sc.controller,
        "variant": sc.variant,
        "parameterisation": sc.parameterisation,
        # What a following unit's rule is applied to: its leader's "desired" or "measured"
        # pose ([control] mirror; docs/controllers.md, "The dual-arm rule").
        "mirror": sc.mirror,
        # Which kernels ran: "c" with the library's path, or "casadi" (and why not C).
        "kernels": result.kernels,
        "rate_Hz": sc.rate_hz,
        "duration_s": float(result.periods / sc.rate_hz),
        "periods": int(result.periods),
        "convergence_rule": f"final RMS over the last {TAIL_FRACTION:.0%} <= "
                            f"{CONVERGENCE_RATIO:.0%} of the initial absolute error, or below "
                            + ", ".join(f"{v:g} {k}" for k, v in CONVERGENCE_FLOOR.items())
                            + " (with encoder counts, of the plant or of a hardware run's "
                              "drives: below the coordinate's measurement_resolution, one "
                              "count on every joint; each coordinate's convergence_floor), "
                              "on the tracking error judged_error names; converged overall "
                              "only if every coordinate converged, nothing diverged and no "
                              "supervisor rule stopped the run (real time) or would have (as "
                              "fast as possible: supervisor)",
        # Which tracking error the coordinates' initial_abs_error, final_rms_error and
        # converged are of: "true" (the plant's state, a simulated run) or "measured" (a
        # hardware run); the measured one is beside it as measured_* in every case.
        "judged_error": "true" if truth else "measured",
        "logged_state": ("true and measured: log.csv's true_q, true_qd, true_pose, "
                         "true_error beside the measured q, qd, pose, error") if truth else
                        ("measured only: a hardware run knows the robot only through its "
                         "encoders and velocity registers (q, qd, pose, error)"),
        "converged": bool(converged and not result.diverged and not stopped),
        "diverged": result.diverged,
        "stop": result.stop,
        "supervisor": result.supervisor,
        "timing": timing,
        # The loop thread's settings, asked for and obtained (real-time runs; see
        # cochlea.runtime.loop.RealtimeOptions).
        "realtime": realtime,
        "wall_time_s": wall_time_s,
        "units": units,
        # Only where the desired path is not the scenario's formulas (--desired-topic).
        **({"desired_source": result.desired_source} if result.desired_source else {}),
    }


# --------------------------------------------------------------------------------------------
# Figures
# --------------------------------------------------------------------------------------------


def _display(values: np.ndarray, unit: str) -> tuple[np.ndarray, str]:
    return (np.degrees(values), "deg") if unit == "rad" else (values, unit)


def _grid(plt, rows: int, title: str):
    fig, axes = plt.subplots(rows, 1, figsize=(7, 1.9 * rows + 0.6), sharex=True, squeeze=False)
    fig.suptitle(title)
    return fig, axes[:, 0]


def figures(result: SimulationResult, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    try:
        return _figures(plt, result, out)
    finally:
        plt.close("all")  # a figure that failed part way is not left open


def _figures(plt, result: SimulationResult, out: Path) -> list[Path]:
    paths = []
    result = result.decimated(FIGURE_POINTS)  # figures of a long run read a sample of it
    t = result.time
    label_text = f"{result.scenario.name} (controller {result.scenario.controller})"

    def save(fig, name):
        fig.tight_layout()
        path = out / name
        try:
            with atomic_path(path) as tmp:
                fig.savefig(tmp, dpi=110)
        finally:
            plt.close(fig)
        paths.append(path)

    for u in result.units:
        # The plant's true state where the run has it (as the error the run is judged on).
        if u.has_true_state:
            actual = u.true_q if u.space == "joint" else u.true_x
        else:
            actual = u.q if u.space == "joint" else u.pose
        fig, axes = _grid(plt, len(u.tracked_names), f"{label_text}: {u.name}, desired vs actual")
        for i, (ax, name, unit) in enumerate(zip(axes, u.tracked_names, u.tracked_units)):
            d, shown = _display(u.desired[:, i], unit)
            a, _ = _display(actual[:, i], unit)
            if unit == "rad" and u.space == "task":
                a = d - np.degrees(u.tracking_error[:, i])  # unwrapped like the desired
            ax.plot(t, d, "--", label="desired")
            ax.plot(t, a, label="actual")
            ax.set_ylabel(f"{name} [{shown}]")
        axes[0].legend(loc="best", fontsize=8)
        axes[-1].set_xlabel("time [s]")
        save(fig, f"{u.name}_tracking.png")

        fig, axes = _grid(plt, len(u.tracked_names), f"{label_text}: {u.name}, tracking error "
                                                     "(desired - actual)")
        for i, (ax, name, unit) in enumerate(zip(axes, u.tracked_names, u.tracked_units)):
            v, shown = _display(u.tracking_error[:, i], unit)
            ax.plot(t, v)
            ax.axhline(0.0, color="0.6", lw=0.8)
            ax.set_ylabel(f"e {name} [{shown}]")
        axes[-1].set_xlabel("time [s]")
        save(fig, f"{u.name}_errors.png")

        fig, axes = _grid(plt, 1, f"{label_text}: {u.name}, commanded joint efforts")
        for i, (j, unit) in enumerate(zip(u.setup.controller_model.joints, u.setup.joint_units)):
            axes[0].plot(t, u.tau[:, i], label=f"{j.name} [{_UNIT_TEXT[_EFFORT_UNIT[unit]]}]")
        axes[0].set_ylabel("torque [N m] / force [N]")
        axes[0].legend(loc="best", fontsize=8)
        axes[-1].set_xlabel("time [s]")
        save(fig, f"{u.name}_torques.png")

        params = u.setup.controller_model.parameters
        fig, axes = _grid(plt, 1, f"{label_text}: {u.name}, parameter estimates")
        for i, (name, unit) in enumerate(zip(params.names, params.si_units)):
            axes[0].plot(t, u.p_hat[:, i], label=f"{name} [{unit}]")
        axes[0].set_ylabel("estimate [SI]")
        axes[0].legend(loc="best", fontsize=7, ncol=2)
        axes[-1].set_xlabel("time [s]")
        save(fig, f"{u.name}_estimates.png")

    save(paths_figure(plt, result, label_text), "paths.png")
    return paths


def paths_figure(plt, result: SimulationResult, label_text: str):
    """The tool paths in the plane, desired and actual, with the cochlea's centre and the
    circle about it through the first desired point. Where the centre rides on a joint (the
    parallel mechanism's slider: :func:`cochlea.robots.adapter.keep_out_centre`), it is drawn
    where it was at the start and at the end, with its track between: one circle at the start
    centre alone misplaced it by the slider's travel (18 mm over parallel_task)."""
    fig, ax = plt.subplots(figsize=(6, 6))
    first = result.units[0]
    q = first.true_q if first.has_true_state else first.q
    cu, cv = first.setup.keep_out_centre(q)
    track = np.column_stack(np.broadcast_arrays(np.asarray(cu, float), np.asarray(cv, float)))
    track = track.reshape(-1, 2)
    start, end = track[0], track[-1]
    radius = None
    for u in result.units:
        desired = _desired_poses(u)
        for label, (iu, iv) in u.setup.tool_points:
            name = u.name if len(u.setup.tool_points) == 1 else f"{u.name} {label}"
            ax.plot(desired[:, iu], desired[:, iv], "--", lw=1, label=f"{name} desired")
            pose = u.true_x if u.has_true_state else u.pose
            ax.plot(pose[:, iu], pose[:, iv], lw=1.2, label=f"{name} actual")
            ax.plot(pose[0, iu], pose[0, iv], "o", ms=4, color=ax.lines[-1].get_color())
            if radius is None:
                radius = float(np.hypot(*(desired[0, [iu, iv]] - start)))
    moves = first.setup.moving_centre_joint is not None
    when = " at the start" if moves else ""
    ax.add_patch(plt.Circle(start, radius, fill=False, color="0.5", lw=0.8, ls=":",
                            label=f"cochlea-centred circle{when}, r = {radius * 1000:.1f} mm"))
    ax.plot(*start, "k+", ms=10, label=f"cochlea centre{when}")
    if moves:
        joint = first.setup.controller_model.joints[first.setup.moving_centre_joint].name
        ax.plot(track[:, 0], track[:, 1], "k-", lw=0.8,
                label=f"cochlea centre's track (rides on {joint}: "
                      f"{(track[:, 1].max() - track[:, 1].min()) * 1000:.1f} mm)")
        ax.add_patch(plt.Circle(end, radius, fill=False, color="0.3", lw=0.8, ls="--",
                                label=f"the circle at the end (t = {result.time[-1]:.2f} s)"))
        ax.plot(*end, "kx", ms=8, label="cochlea centre at the end")
    ax.set_aspect("equal")
    ax.set_xlabel(f"{first.setup.task_names[0]} [m]")
    ax.set_ylabel(f"{first.setup.task_names[1]} [m]")
    ax.set_title(f"{label_text}: tool paths in the plane")
    ax.legend(loc="best", fontsize=7)
    return fig


def _desired_poses(u: UnitLog) -> np.ndarray:
    """The desired task pose of every period (through the FK for joint-space runs)."""
    if u.space == "task":
        return u.desired
    return np.array(u.setup.fk_world.map(len(u.desired))(u.desired.T)).T


def write_all(result: SimulationResult, out: Path, wall_time_s: float | None = None,
              timing: dict | None = None, realtime: dict | None = None,
              position_quantum: dict | None = None, extra: dict | None = None) -> dict:
    """log.csv, the figures, then summary.json, each to a temporary name and renamed: a reader
    never sees half a file, and a summary.json without ``report_lost`` means the report is
    whole. A part that fails to write (a full disk) does not stop the others; then
    :class:`ReportError` names what was lost. ``extra``: entries that replace or join the
    summary's (cochlea-embedded-host: the firmware's rate and periods, its ``stream``)."""
    out.mkdir(parents=True, exist_ok=True)
    lost, causes = [], []
    try:
        with atomic_path(out / "log.csv") as tmp:
            write_csv(result, tmp)
    except OSError as exc:
        lost.append("log.csv")
        causes.append(exc)
    data = summary(result, wall_time_s, timing, realtime, position_quantum)
    data.update(extra or {})
    try:
        data["figures"] = [str(p) for p in figures(result, out)] if result.periods > 1 else []
    except Exception as exc:  # noqa: BLE001 - a figure never costs the summary
        # A full disk (OSError), or values matplotlib cannot draw (1e308 in a row: ValueError,
        # OverflowError, ...): the figures are lost, summary.json is still written and says so.
        lost.append("figures")
        causes.append(exc)
        data["figures"] = []
    saved = {k: v for k, v in data.items() if k != "figures"}
    if lost:
        saved["report_lost"] = list(lost)
    try:
        write_text_atomic(out / "summary.json", json.dumps(saved, indent=2) + "\n")
    except OSError as exc:
        lost.append("summary.json")
        causes.append(exc)
    if lost:
        raise ReportError(out, lost, causes[0])
    return data
