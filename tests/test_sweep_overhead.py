"""A sweep sample's cost outside its closed loop (issue 30 item 3): the supervisor's verdict
and the summary judged on each unit's whole log (no stacked copies, the sums in the pieces the
chunks cut them into; the measured state's column extremes in one blocked pass, the rows'
squares a column at a time), the scenario read from the data its text reads as (no TOML
written or parsed), the supervisor's pose kernels bound once per process. What it must not
change: any sample's verdict, summary or row. The old path is kept here as it was (the log
stacked and screened row by row, the summary a chunk at a time) and every sample of each
shipped study, at its full length, is judged both ways, with the description's limits and
with limits tight enough to stop it (a velocity, a position, the keep-out circle)."""

from __future__ import annotations

import dataclasses
import math
import threading
from pathlib import Path

import numpy as np
import pytest

from cochlea.apps import cochlea_sweep, report
from cochlea.runtime import build_supervisor, first_violation, verdict
from cochlea.runtime import supervisor as sv
from cochlea.sim import load_scenario, simulate, unit_setups
from cochlea.sim.result import StreamedResult, UnitLog
from cochlea.sweep import sampling
from cochlea.sweep import spec as sweep_spec

STUDIES = ("serial_joint", "serial_task", "parallel_joint", "parallel_task")
#: Delays of 0 and 2 periods: the measured state is then the true one, or a delayed copy whose
#: pose the run did not log (the verdict's keep-out rule computes it, or bounds it).
SPEC = """format = "cochlea-sweep/1"
scenario = "{study}"
samples = 2
seed = 3

[perturb]
mass_scale = {{uniform = [0.7, 1.3]}}
payload_kg = {{uniform = [0.0, 0.05]}}
delay_periods = {{grid = [0, 2]}}
"""


# --------------------------------------------------------------------------------------------
# The old path, as it was before (cochlea 3ff008d)
# --------------------------------------------------------------------------------------------


def _old_first_violation(result, supervisor):
    """Every period screened on the stacked log, each flagged one checked by the supervisor."""
    logs = result.units
    if len(result.time) == 0:
        return None
    q, qd = (np.hstack([u.q for u in logs]), np.hstack([u.qd for u in logs]))
    tau = np.hstack([u.tau for u in logs])
    estimates = [np.vstack([u.p_hat[1:], u.p_hat[-1:]]) for u in logs]
    L = supervisor.limits
    with np.errstate(invalid="ignore", over="ignore"):
        flagged = ~np.isfinite(q).all(axis=1) | ~np.isfinite(qd).all(axis=1)
        flagged |= ((q < L.position_lo) | (q > L.position_hi)).any(axis=1)
        flagged |= (np.abs(qd) > L.velocity).any(axis=1)
        if L.keep_out_radius is not None:
            for u in logs:
                s = u.setup
                pose = u.pose
                for _, (iu, iv) in s.tool_points:
                    cu, cv = (s.centre if s.moving_centre_joint is None
                              else (0.0, u.q[:, s.moving_centre_joint]))
                    flagged |= np.hypot(pose[:, iu] - cu, pose[:, iv] - cv) < \
                        L.keep_out_radius + 1e-9
        flagged |= ~np.isfinite(tau).all(axis=1)
        for p, bound in zip(estimates, supervisor.bounds):
            square = np.einsum("ij,ij->i", p, p)
            flagged |= ~np.isfinite(square) | (square > (bound * (1 + 1e-9)) ** 2)
    n = q.shape[1]
    for k in np.flatnonzero(flagged):
        t = float(result.time[k])
        x = np.concatenate([q[k], qd[k]])
        stop = supervisor.check_state(t, x, x[:n], x[n:])
        if stop is None:
            stop = supervisor.check_command(t, tau[k].copy(), [p[k] for p in estimates])
        if stop is not None:
            return stop
    return None


class _OldErrorStats:
    def __init__(self, tail_start: int):
        self.tail_start = tail_start
        self.initial = None
        self.tail_sq = self.tail_n = 0

    def add(self, e: np.ndarray, start: int) -> None:
        if self.initial is None:
            rows = np.flatnonzero(np.isfinite(e).all(axis=1))
            if not len(rows):
                return
            self.initial = np.abs(e[rows[0]])
        first = max(self.tail_start - start, 0)
        if first < len(e):
            self.tail_sq = self.tail_sq + np.array([np.sum(e[first:, i] ** 2)
                                                    for i in range(e.shape[1])])
            self.tail_n += len(e) - first

    def final_rms(self, i: int) -> float:
        return float(np.sqrt(self.tail_sq[i] / self.tail_n))


class _OldUnitStats:
    def __init__(self, periods: int):
        tail_start = int(periods * (1 - report.TAIL_FRACTION))
        self.judged = _OldErrorStats(tail_start)
        self.measured = _OldErrorStats(tail_start)
        self.tau_max = None
        self.max_norm = np.zeros(())
        self.finite = True
        self.last = None

    def add(self, u: UnitLog, start: int) -> None:
        if not len(u.q):
            return
        measured = u.measured_tracking_error
        self.measured.add(measured, start)
        self.judged.add(u.true_tracking_error if u.has_true_state else measured, start)
        peaks = np.array([np.max(np.abs(u.tau[:, i]), initial=0.0)
                          for i in range(u.tau.shape[1])])
        self.tau_max = peaks if self.tau_max is None else np.maximum(self.tau_max, peaks)
        self.max_norm = np.maximum(self.max_norm, np.max(np.linalg.norm(u.p_hat, axis=1)))
        self.finite = self.finite and bool(np.isfinite(u.p_hat).all())
        self.last = dataclasses.replace(u, **{name: getattr(u, name)[-1:] for name in (
            "q", "qd", "desired", "desired_dot", "errors", "tau", "p_hat", "x", "true_q",
            "true_qd", "true_x") if getattr(u, name) is not None})


def _old_units(result) -> dict:
    """summary.json's ``units``, read a chunk at a time."""
    stats = [_OldUnitStats(result.periods) for _ in result.units]
    start = 0
    for chunk in result.chunks():
        for s, u in zip(stats, chunk.units):
            s.add(u, start)
        start += chunk.periods
    return {u.name: report._unit_summary(u, s) for u, s in zip(result.units, stats)}


# --------------------------------------------------------------------------------------------


def _plain(value):
    """Floats as their exact text (NaN equals NaN), for comparisons bit for bit."""
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _stop(stop) -> tuple | None:
    return None if stop is None else (stop.rule, stop.time, stop.detail)


def _nearest(result) -> float:
    """How near any measured tool point comes to its keep-out centre (m), its pose computed
    aside (the log's own is left as the run left it)."""
    nearest = math.inf
    for u in result.units:
        s = u.setup
        pose = u.x if u.x is not None else np.array(s.fk_world.map(len(u.q))(u.q.T)).T
        for _, (iu, iv) in s.tool_points:
            cu, cv = (s.centre if s.moving_centre_joint is None
                      else (0.0, u.q[:, s.moving_centre_joint]))
            nearest = min(nearest, np.hypot(pose[:, iu] - cu, pose[:, iv] - cv).min())
    return nearest


def _tightened(supervisor, kind: str, nearest: float):
    L = supervisor.limits
    if kind == "velocity":
        L.velocity[:] = 0.3 * L.velocity
    elif kind == "position":
        L.position_hi[:] = L.position_lo + 0.6 * (L.position_hi - L.position_lo)
    elif kind == "keep-out":
        L.keep_out_radius = 3 * L.keep_out_radius  # the tools' paths pass inside it
    elif kind == "keep-out-edge":  # a tool grazes the circle: one period or a few inside
        L.keep_out_radius = nearest + 1e-7
    elif kind == "keep-out-clear":  # and just clear of it
        L.keep_out_radius = nearest - 1e-7
    return supervisor


@pytest.mark.slow
@pytest.mark.parametrize("study", STUDIES)
def test_every_sample_is_judged_and_summarised_as_on_the_old_path(study, tmp_path):
    path = tmp_path / "spec.toml"
    path.write_text(SPEC.format(study=study))
    spec = sweep_spec.load(path)
    stops = set()
    for i in range(spec.total):
        text = sampling.scenario_text(spec, i)
        row = cochlea_sweep.evaluate(text)
        # What a worker hands evaluate: the data that text reads as (no TOML written or
        # parsed), the same row bit for bit.
        assert _plain(cochlea_sweep.evaluate(sampling.scenario_data(spec, i))) == _plain(row)
        # The old path: the sample's file written and read, a supervisor bound for it alone.
        file = tmp_path / "sample.toml"
        file.write_text(text)
        sc = load_scenario(file)
        setups = unit_setups(sc)
        result = simulate(sc, None, setups, threads=False)
        assert result.periods == round(sc.duration * sc.rate_hz) >= 10_000  # full length
        nearest = _nearest(result)
        reductions = [sv.log_reductions(u) for u in result.units]  # what a worker shares
        for kind in ("none", "velocity", "position", "keep-out", "keep-out-edge",
                     "keep-out-clear"):
            sup = _tightened(build_supervisor(setups, sc.system.keep_out_radius,
                                              substeps=sc.plant_substeps), kind, nearest)
            new = _stop(first_violation(result, sup))
            assert _stop(first_violation(result, sup, reductions)) == new, (i, kind)
            assert verdict(result, sup, reductions) == verdict(result, sup), (i, kind)
            logged = [u.x for u in result.units]
            old = _stop(_old_first_violation(result, sup))  # computes the measured poses
            for u, x in zip(result.units, logged):
                u.x = x  # as the run left it: the next verdict may bound what it did not log
            assert new == old, (i, kind)
            stops.add(old[0] if old else "none")
        sup = build_supervisor(setups, sc.system.keep_out_radius, substeps=sc.plant_substeps)
        judged = verdict(result, sup)
        result.supervisor = judged
        new = report.summary(result, 0.0)
        assert _plain(new["units"]) == _plain(_old_units(result)), i
        assert _plain(report.summary(result, 0.0, reductions=reductions)) == _plain(new), i
        # A run streamed to disk is read a chunk at a time: the same summary.
        streamed = StreamedResult(result.scenario, result.units, result.periods, result.rows)
        assert _plain(report.summary(streamed, 0.0)["units"]) == _plain(new["units"]), i
        # The sample's row through the worker's path (text, caches) is this summary's row.
        limits = {u.name: {j.name: float(lim) for j, lim in
                           zip(u.controller_model.joints, u.effort_limit)} for u in setups}
        assert _plain(row) == _plain(cochlea_sweep.measures(new, limits)), i
    # The limits above stopped every sample somewhere, by each rule the tightening asks for.
    assert {"velocity-limit", "position-limit", "keep-out"} <= stops


def test_keep_out_points_are_written_in_place_and_stop_as_before():
    """The keep-out rule's points: one array, the same each period, its rows named; a tool
    inside the circle stops the run with the message the loop always gave."""
    sc = load_scenario("parallel_task")
    setups = unit_setups(sc)
    sup = build_supervisor(setups, 0.2, substeps=sc.plant_substeps)
    q = setups[0].x0[:setups[0].controller_model.nq].copy()
    first = sup.keep_out_points(q)
    assert sup.keep_out_points(q + 0.01) is first  # written in place
    assert sup.keep_out_points.labels == ("mechanism C", "mechanism C'")
    assert first[0, 2] == 0.0 and first[0, 3] == q[2] + 0.01  # S = (0, d1) moves
    qd = np.zeros_like(q)
    stop = sup.check_state(0.5, np.concatenate([q, qd]), q, qd)
    assert stop.rule == "keep-out"
    (pu, pv), r = first[0, :2], math.hypot(first[0, 0], first[0, 1] - q[2])
    assert stop.detail == (f"mechanism C at ({pu:.4f}, {pv:.4f}) m is {r * 1000:.1f} mm from "
                           f"the centre (0.0000, {q[2]:.4f}) m, inside the keep-out radius "
                           "200.0 mm")


def test_the_pose_kernels_are_bound_once_per_process():
    sc = load_scenario("serial_task")
    setups = unit_setups(sc)
    a = build_supervisor(setups, 0.02, cache=True)
    b = build_supervisor(unit_setups(sc), 0.02, cache=True)
    assert a.keep_out_points._units[0][0] is b.keep_out_points._units[0][0]
    fresh = build_supervisor(setups, 0.02)
    assert fresh.keep_out_points._units[0][0] is not a.keep_out_points._units[0][0]
    q = np.concatenate([u.x0[:u.controller_model.nq] for u in setups])
    assert np.array_equal(a.keep_out_points(q), fresh.keep_out_points(q))
    assert sv._POSE_KERNELS  # kept, with their Functions
    # Another thread (a dask worker running two samples at once) binds its own: a kernel's
    # buffers are written and read around each call.
    other = []
    thread = threading.Thread(target=lambda: other.append(build_supervisor(setups, 0.02,
                                                                           cache=True)))
    thread.start()
    thread.join()
    assert other[0].keep_out_points._units[0][0] is not a.keep_out_points._units[0][0]


@pytest.mark.slow
def test_a_worker_keeps_the_memory_a_sample_frees():
    """A worker's samples free and allocate the same ~1 MB arrays again and again: after
    warm(), glibc keeps them instead of handing them back and faulting them in again page by
    page (in a process of its own: the setting lasts as long as the process)."""
    import subprocess
    import sys

    script = (
        "import resource, sys\n"
        "import numpy as np\n"
        "from cochlea.apps import cochlea_sweep\n"
        "def faults():\n"
        "    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
        "    for _ in range(20):  # a sample's logs: ten arrays of ~1 MB, freed together\n"
        "        logs = [np.ones((20000, 6)) for _ in range(10)]\n"
        "        del logs\n"
        "    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before\n"
        "plain = faults()\n"
        "kept = cochlea_sweep.keep_freed_memory()\n"
        "faults()\n"
        "print(plain, kept, faults())\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         check=True).stdout.split()
    plain, kept, after = int(out[0]), out[1] == "True", int(out[2])
    if not kept:
        pytest.skip("not glibc: the worker leaves malloc as it is")
    assert plain > 20 * 1000 and after < 100, (plain, after)  # 10 MB: 2,400 pages


@pytest.mark.parametrize("failed", [0, 1, 53, 120, 250, 265, 280])
def test_a_run_whose_first_reads_failed_is_summarised_as_chunk_by_chunk(monkeypatch, failed):
    """A hardware run logs NaN until its first good read: its initial error is that read's,
    and the chunks before it add nothing to the tail, whether the run is read whole or a
    chunk at a time (small chunks here: 300 periods in chunks of 53, the tail from 240)."""
    from cochlea.sim import result as result_module

    monkeypatch.setattr(result_module, "CHUNK_ROWS", 53)
    sc = dataclasses.replace(load_scenario("serial_task"), duration=0.3)
    result = simulate(sc, threads=False)
    for u in result.units[:1]:
        for name in ("q", "qd", "errors", "true_q", "true_x"):
            value = getattr(u, name).copy()
            value[:failed] = np.nan
            setattr(u, name, value)
    whole = report.summary(result, 0.0)["units"]
    assert _plain(whole) == _plain(_old_units(result))
    streamed = StreamedResult(result.scenario, result.units, result.periods, result.rows)
    assert _plain(report.summary(streamed, 0.0)["units"]) == _plain(whole)
    # The tail is summed from the chunk of the first good read on: its failed reads there
    # make the final RMS NaN; a first good read that starts a chunk leaves none (265 = 5 x 53).
    rms = whole["arm1"]["tracked"]["x"]["final_rms_error"]
    assert math.isnan(rms) == (max(240, failed // 53 * 53) < failed), rms


# --------------------------------------------------------------------------------------------
# The sample's scenario as data, and the whole-log reductions, against what they replace
# --------------------------------------------------------------------------------------------

#: Every kind of input a sample's data holds: a drawn float, a drawn integer, a choice, a
#: grid of vectors and numbers, a per-component draw, a fixed value, the duration.
DATA_SPEC = """format = "cochlea-sweep/1"
scenario = "serial_task"
samples = 3
seed = 5
duration_s = 0.05

[perturb]
mass_scale = {uniform = [0.7, 1.3]}
delay_periods = {uniform = [0, 2]}
position_encoder = {choice = [true, false]}
noise_q_std_SI = 1e-5

[gains.arm1]
G_g = {grid = [1.5, [2.0, 2.0, 3.0]]}
G_a = {uniform = [0.5, 2.0], each = true}
"""


def _typed(value):
    """TOML data with every scalar's type: 1 and 1.0 and True differ."""
    if isinstance(value, dict):
        return {k: _typed(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_typed(v) for v in value]
    return (type(value).__name__, repr(value))


@pytest.mark.parametrize("study", [*STUDIES, "data"])
def test_a_sample_s_data_is_what_its_replay_file_reads_as(study, tmp_path):
    import tomllib

    path = tmp_path / "spec.toml"
    path.write_text(DATA_SPEC if study == "data" else SPEC.format(study=study))
    spec = sweep_spec.load(path)
    for i in range(spec.total):
        data, text = sampling.scenario_data(spec, i), sampling.scenario_text(spec, i)
        assert _typed(tomllib.loads(text)) == _typed(data), i
        # A new object every call, nothing shared with the base's: a sample's loader may
        # keep parts of it.
        data["plant"]["mass_scale"] = -1.0
        data.setdefault("control", {})["rate_Hz"] = -1.0
        data["unit"][0].setdefault("gains", {})["extra"] = [0.0]
        assert _typed(sampling.scenario_data(spec, i)) == _typed(tomllib.loads(text)), i


def test_a_sample_read_from_its_data_runs_and_is_refused_as_from_its_text(tmp_path):
    import tomllib

    from cochlea.errors import CochleaError, DescriptionError

    path = tmp_path / "spec.toml"
    path.write_text(DATA_SPEC)
    spec = sweep_spec.load(path)
    for i in (0, spec.total - 1):
        text = sampling.scenario_text(spec, i)
        row = cochlea_sweep.evaluate(sampling.scenario_data(spec, i))
        assert _plain(row) == _plain(cochlea_sweep.evaluate(text)), i
    # A bad value is the same one line either way (the file's name, the key, the value).
    data = sampling.scenario_data(spec, 0)
    data["plant"]["mass_scale"] = -2.0
    text = sampling.dumps(data)
    messages = []
    for kind in ({"text": text}, {"data": data}):
        with pytest.raises(DescriptionError) as err:
            load_scenario(cochlea_sweep.SAMPLE_FILE, **kind)
        messages.append(str(err.value))
    assert messages[0] == messages[1] and "mass_scale" in messages[0], messages
    # Nesting no scenario needs is refused as the parsed file's would be.
    deep = tomllib.loads(sampling.scenario_text(spec, 0))
    deep["plant"]["extra"] = nested = []
    for _ in range(40):
        nested.append([])
        nested = nested[0]
    with pytest.raises(DescriptionError, match="nested at most"):
        load_scenario(cochlea_sweep.SAMPLE_FILE, data=deep)
    with pytest.raises(CochleaError, match="not both"):
        load_scenario(cochlea_sweep.SAMPLE_FILE, text=text, data=data)


def _same(a, b) -> bool:
    return np.array_equal(a, b, equal_nan=True)


@pytest.mark.parametrize("rows", [0, 1, 255, 256, 257, 1000, 20_001])
@pytest.mark.parametrize("columns", [1, 3, 6, 7])
def test_column_extremes_are_each_column_s_min_and_max(rows, columns):
    rng = np.random.default_rng(rows * 10 + columns)
    a = rng.normal(size=(rows, columns)) * 10.0 ** rng.integers(-3, 4, size=columns)
    low, high = sv.column_extremes(a)
    assert _same(low, a.min(axis=0, initial=np.inf)) and \
        _same(high, a.max(axis=0, initial=-np.inf))
    if rows:  # a NaN, an infinity, in a block or in the rows after the last block
        for r in {0, rows // 2, rows - 1}:
            b = a.copy()
            b[r, columns - 1] = np.nan
            b[rows - 1 - r, 0] = -np.inf
            low, high = sv.column_extremes(b)
            if columns > 1:  # the NaN's column: both NaN
                assert math.isnan(low[-1]) and math.isnan(high[-1])
            want = [np.min(b[:, j]) for j in range(columns)], [np.max(b[:, j])
                                                               for j in range(columns)]
            assert _same(low, want[0]) and _same(high, want[1])


def test_the_state_gate_reads_q_and_qd_together_only_where_they_share_rows():
    rng = np.random.default_rng(2)
    state = rng.uniform(-1, 1, size=(5000, 6))
    q, qd = state[:, :3], state[:, 3:]
    both = sv._side_by_side(q, qd)
    assert both is not None and not both.flags.writeable and _same(both, state)
    assert sv._side_by_side(q.copy(), qd) is None  # separate arrays
    assert sv._side_by_side(state[:, :2], state[:, 4:]) is None  # not adjacent
    assert sv._side_by_side(state[::2, :3], state[::2, 3:]) is None  # every other row
    lo, hi, speed = np.full(3, -1.0), np.full(3, 1.0), np.full(3, 1.0)
    for change in (None, (17, 1, 1.5), (4999, 4, -1.5), (256, 2, np.nan), (0, 5, np.inf),
                   (300, 0, -1.0), (301, 3, 1.0)):
        s = state.copy()
        if change is not None:
            s[change[0], change[1]] = change[2]
        q, qd = s[:, :3], s[:, 3:]
        want = sv._columns_within(q, lo, hi) and sv._columns_within(qd, -speed, speed)
        assert sv._state_within(q, qd, lo, hi, speed) == want, change
        # The same answer from the columns alone (q and qd apart).
        assert sv._state_within(q.copy(), qd.copy(), lo, hi, speed) == want, change
    assert not sv._state_within(q, qd, lo, np.full(3, 0.5), speed)


@pytest.mark.parametrize("columns", [1, 2, 3, 8, 9, 30])
def test_the_largest_estimate_norm_is_numpy_s_bit_for_bit(columns):
    for seed in range(30):
        rng = np.random.default_rng(seed)
        v = rng.normal(size=columns) * 10 ** rng.uniform(-2, 2, size=columns)
        # The largest row in many orders: sums whose roundings differ in the last bits (a
        # screen without its margin picks the wrong one for several of these seeds).
        rows = [np.roll(v, k) for k in range(columns)] + [rng.permutation(v) for _ in range(20)]
        p = np.vstack([rng.normal(size=(300, columns)) * 0.1 * np.abs(v).max(), *rows])
        p = p[rng.permutation(len(p))]
        assert report._largest_norm(p) == np.max(np.linalg.norm(p, axis=1)), seed
        assert np.allclose(report._row_squares(p), np.einsum("ij,ij->i", p, p), rtol=1e-15,
                           atol=0)
    for bad in (np.nan, np.inf, -np.inf):
        q = p.copy()
        q[7, 0] = bad
        assert _same(report._largest_norm(q), np.max(np.linalg.norm(q, axis=1)))


# --------------------------------------------------------------------------------------------
# The third pass (issue 30 item 3): fewer numpy calls a sample, the same numbers
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("rows", [1, 2, 7, 8, 9, 127, 128, 129, 1000, 3616, 8191, 8192])
def test_a_tail_s_column_sums_are_np_sum_s_bit_for_bit(rows):
    rng = np.random.default_rng(rows)
    e = rng.normal(size=(rows, 7)) * 10.0 ** rng.uniform(-9, 3, size=7)
    e = e[:, 1:6]  # a strided piece of a wider log, as the errors' first block is
    want = np.array([np.sum(e[:, i] ** 2) for i in range(e.shape[1])])
    got = report._column_square_sums(e)
    assert got.view(np.int64).tolist() == want.view(np.int64).tolist()
    for bad in (np.nan, np.inf):
        b = e.copy()
        b[rows // 2, 2] = bad
        assert _same(report._column_square_sums(b), [np.sum(b[:, i] ** 2) for i in range(5)])


def test_a_unit_s_rows_are_what_dataclasses_replace_makes_of_them():
    sc = dataclasses.replace(load_scenario("serial_task"), duration=0.05)
    u = simulate(sc, threads=False).units[0]
    for part, fields in ((slice(3, 9), report._ERROR_FIELDS),
                         (slice(-1, None), report._LAST_FIELDS)):
        got = report._rows(u, part, fields)
        want = dataclasses.replace(u, **{k: getattr(u, k)[part] for k in fields
                                         if getattr(u, k) is not None})
        assert type(got) is UnitLog and got is not u
        for f in dataclasses.fields(UnitLog):
            a, b = getattr(got, f.name), getattr(want, f.name)
            assert (_same(a, b) if isinstance(b, np.ndarray) else a is b), f.name
    assert len(u.q) == 50  # the log itself is left whole


def _old_saturated(result, supervisor) -> int:
    top = supervisor.limits.effort
    if any(u.setup.effort_grid is not None for u in result.units):
        top = np.minimum(top, np.concatenate([
            u.setup.effort_limit if u.setup.effort_grid is None else u.setup.effort_grid.top
            for u in result.units]))
    with np.errstate(invalid="ignore"):
        tau = np.hstack([u.tau for u in result.units])
        return int(np.sum((np.abs(tau) >= top).any(axis=1)))


@pytest.mark.parametrize("study", ["serial_task", "parallel_task"])
def test_clipped_periods_are_counted_as_on_the_stacked_log(study):
    sc = dataclasses.replace(load_scenario(study), duration=0.2)
    setups = unit_setups(sc)
    result = simulate(sc, None, setups, threads=False)
    sup = build_supervisor(setups, sc.system.keep_out_radius, substeps=sc.plant_substeps)
    assert sv.saturated_periods(result, sup) == _old_saturated(result, sup) == 0
    top = sup.limits.effort
    rng = np.random.default_rng(4)
    first = 0
    for u in result.units:
        n = u.tau.shape[1]
        tau = u.tau.copy()
        rows = rng.choice(len(tau), size=12, replace=False)
        tau[rows[:4], 0] = top[first]  # at the top: clipped
        tau[rows[4:8], n - 1] = -top[first + n - 1]  # at the bottom: clipped
        tau[rows[8], n - 1] = np.nextafter(top[first + n - 1], 0.0)  # just under: not
        tau[rows[9], 0] = np.nan  # not clipped (a NaN is the verdict's other rule)
        tau[rows[10:], :] = top[first:first + n]  # every joint at once: one period
        u.tau = tau
        first += n
    count = sv.saturated_periods(result, sup)
    assert count == _old_saturated(result, sup)
    # From the efforts' extremes a worker shares with the summary: the same count.
    assert sv.saturated_periods(result, sup, [sv.log_reductions(u) for u in result.units]) \
        == count
    assert len(result.units) * 10 >= count >= 10  # rows may coincide across the units


def test_the_gate_sends_an_estimate_over_its_bound_or_not_finite_to_the_screen():
    sc = dataclasses.replace(load_scenario("serial_task"), duration=0.3)
    setups = unit_setups(sc)
    sup = build_supervisor(setups, sc.system.keep_out_radius, substeps=sc.plant_substeps)
    result = simulate(sc, None, setups, threads=False)
    assert sv._nothing_flagged(result, sup) and first_violation(result, sup) is None
    p_hat = result.units[1].p_hat
    bound = sup.bounds[1]
    for row, value in ((150, np.nan), (299, -np.inf), (120, -1.01 * bound), (0, 2 * bound)):
        changed = p_hat.copy()
        changed[row, -1] = value
        result.units[1].p_hat = changed
        # Row 0 is no estimate a period hands on: nothing to stop, and none is made up.
        reductions = [sv.log_reductions(u) for u in result.units]
        assert sv._nothing_flagged(result, sup) == (row == 0), row
        assert sv._nothing_flagged(result, sup, reductions) == (row == 0), row
        old = _stop(_old_first_violation(result, sup))
        assert _stop(first_violation(result, sup)) == old
        assert _stop(first_violation(result, sup, reductions)) == old
        if row:
            assert first_violation(result, sup).rule in ("non-finite", "estimate-bound")
    result.units[1].p_hat = p_hat
    tau = result.units[0].tau.copy()
    tau[77, 1] = np.nan  # a command that is not finite: the gate sends it on either way
    result.units[0].tau = tau
    reductions = [sv.log_reductions(u) for u in result.units]
    assert not sv._nothing_flagged(result, sup) and not sv._nothing_flagged(result, sup,
                                                                             reductions)
    assert _stop(first_violation(result, sup, reductions)) == \
        _stop(_old_first_violation(result, sup)) == _stop(first_violation(result, sup))
    assert first_violation(result, sup).rule == "non-finite"
    # Reductions that cannot be this run's (another run's, one unit's only) are not read.
    other = simulate(dataclasses.replace(sc, duration=0.2), None, setups, threads=False)
    for wrong in ([sv.log_reductions(u) for u in other.units], reductions[:1]):
        assert not sv._nothing_flagged(result, sup, wrong)
        assert sv.verdict(result, sup, wrong) == sv.verdict(result, sup)
        assert _plain(report.summary(result, 0.0, reductions=wrong)) == \
            _plain(report.summary(result, 0.0))


def test_a_sample_s_random_inputs_are_default_rng_s_draws(tmp_path):
    import zlib

    path = tmp_path / "spec.toml"
    path.write_text(DATA_SPEC)
    spec = sweep_spec.load(path)
    for k in (0, 1, 7):
        for name in ("plant.mass_scale", "gains.arm1.G_a"):
            want = np.random.default_rng(np.random.SeedSequence(
                spec.seed, spawn_key=(k, zlib.crc32(name.encode())))).random(4)
            assert np.array_equal(sampling._rng(spec, k, name).random(4), want)


def test_a_user_description_is_named_by_its_absolute_path_in_every_sample(tmp_path,
                                                                           monkeypatch):
    import tomllib

    from cochlea.resources import ROBOTS_DIR, SCENARIOS_DIR

    (tmp_path / "robots").mkdir()
    (tmp_path / "robots" / "mine.toml").write_text(
        (ROBOTS_DIR / "serial.toml").read_text())
    base = tomllib.loads((SCENARIOS_DIR / "serial_task.toml").read_text())
    base["description"] = "robots/mine.toml"
    (tmp_path / "scenario.toml").write_text(sampling.dumps(base))
    (tmp_path / "spec.toml").write_text(DATA_SPEC.replace('"serial_task"', '"scenario.toml"'))
    want = str((tmp_path / "robots" / "mine.toml").resolve())
    spec = sweep_spec.load(tmp_path / "spec.toml")
    assert spec.scenario_path.is_absolute()
    for i in (0, 1):
        assert sampling.scenario_data(spec, i)["description"] == want
    monkeypatch.chdir(tmp_path / "robots")  # a worker's own folder: the same file
    assert sampling.scenario_data(spec, 2)["description"] == want
    relative = dataclasses.replace(spec, scenario_path=Path("scenario.toml"))
    monkeypatch.chdir(tmp_path)  # a scenario named relative to the folder: resolved there
    assert sampling.scenario_data(relative, 0)["description"] == want
    monkeypatch.chdir(tmp_path / "robots")  # and again from elsewhere: not what it was
    assert sampling.scenario_data(relative, 0)["description"] == \
        str((tmp_path / "robots" / "robots" / "mine.toml").resolve())


@pytest.fixture(scope="module")
def five_seconds():
    """serial_task, 5 s (5,000 periods: every block of the screen), its supervisor."""
    sc = dataclasses.replace(load_scenario("serial_task"), duration=5.0)
    setups = unit_setups(sc)
    return sc, setups, simulate(sc, None, setups, threads=False)


@pytest.mark.parametrize("row", [0, 1, 255, 256, 257, 4095, 4096, 4999, None])
@pytest.mark.parametrize("rule", ["velocity-limit", "estimate-bound"])
@pytest.mark.parametrize("keep_out", [False, True])
def test_the_screen_finds_the_first_stop_whichever_block_holds_it(five_seconds, row, rule,
                                                                  keep_out):
    """A run the gate sends on is screened a block of periods at a time (up to 256, 4,096,
    the rest): a speed over its limit, or an estimate handed on over its bound (the next
    period's row, across a block's end too), in any period, with or without a keep-out circle
    the tool grazes earlier or later, stops where the whole run stacked and screened stops."""
    sc, setups, result = five_seconds
    sup = build_supervisor(setups, sc.system.keep_out_radius, substeps=sc.plant_substeps)
    assert list(sv._screen_blocks(5000)) == [(0, 256), (256, 4096), (4096, 5000)]
    if keep_out:  # the tool grazes the circle in one period, around the middle block
        sup.limits.keep_out_radius = _nearest(result) + 1e-7
    u = result.units[1]
    # The module's log is read-only (its driver's reductions describe it): a copy is changed.
    name, at = ("qd", row) if rule == "velocity-limit" else ("p_hat", min((row or 0) + 1, 4999))
    saved = getattr(u, name)
    log = saved.copy()
    setattr(u, name, log)
    try:
        if row is not None:
            log[at, 1] = 1.5 * (sup.limits.velocity[4] if rule == "velocity-limit"
                                else sup.bounds[1])
        old = _stop(_old_first_violation(result, sup))
        assert _stop(first_violation(result, sup)) == old
        assert old is not None or (row is None and not keep_out)
        if row is not None:
            assert old[0] in (rule, "keep-out"), old
            assert old[0] == rule or keep_out
    finally:
        setattr(u, name, saved)  # the log is the module's: as it was
