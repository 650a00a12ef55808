"""What the generated closed-loop drivers gather while they run (issue 30 item 3): each measured
state column's extremes, each applied effort column's, the largest estimate row squares. The
verdict and the summary of an as-fast run read them instead of the logs, so they must be the
logs' own reductions: the extremes bit for bit, NaN where a column has one, and never read for
a log that no longer holds the arrays they describe."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from cochlea.apps import report
from cochlea.kernels import library as ckernels
from cochlea.robots import robot
from cochlea.runtime import build_supervisor
from cochlea.runtime import supervisor as sv
from cochlea.sim import compiled as csim
from cochlea.sim import load_scenario, simulate, unit_setups
from cochlea.sim.scenario import resolve

STUDIES = ("serial_joint", "serial_task", "parallel_joint", "parallel_task",
           "serial_joint_realistic", "parallel_task_realistic")
#: Measurements that are not the state: a delay, then everything at once.
OPTIONS = {
    "exact": {},
    "delay": dict(delay_periods=3),
    "everything": dict(position_encoder=True, velocity_register=True, delay_periods=1,
                       delay_jitter_periods=2, encoder_noise_counts=1, noise_q_std=1e-4,
                       noise_qd_std=1e-3, seed=9, current_quantisation=True),
}


def _scenario(name: str, options: str):
    sc = load_scenario(name)
    if options != "exact":
        # The realistic studies keep their rotors and gearbox (the gains are for them).
        sc = dataclasses.replace(sc, plant=dataclasses.replace(sc.plant, **OPTIONS[options]))
    return sc


def _python_reductions(u) -> tuple:
    """What the verdict and the summary read of a log without the driver's help."""
    state_low, state_high = sv.column_extremes(np.ascontiguousarray(np.hstack([u.q, u.qd])))
    tau_low, tau_high = sv.column_extremes(np.ascontiguousarray(u.tau))
    squares = sv.row_squares(np.ascontiguousarray(u.p_hat))
    later = squares[1:] if len(squares) > 1 else squares
    return state_low, state_high, tau_low, tau_high, squares.max(), later.max()


def _assert_gathered_is_the_logs(u) -> None:
    gathered = u.gathered.of(u)
    assert gathered is not None and gathered.rows == len(u.q)
    state_low, state_high, tau_low, tau_high, square_all, square_later = _python_reductions(u)
    for got, want in ((gathered.state_low, state_low), (gathered.state_high, state_high),
                      (gathered.tau_low, tau_low), (gathered.tau_high, tau_high)):
        np.testing.assert_array_equal(got, want)
    # The squares in column order: numpy's own order up to 8 columns, einsum's beyond.
    exact = u.p_hat.shape[1] <= sv._COLUMN_SUMS
    for got, want in ((gathered.square_all, square_all),
                      (gathered.square_later, square_later)):
        assert got == want if exact else abs(got - want) <= 1e-13 * want, (got, want)
    # The keep-out tool points' nearest approach over the true poses, as the gate sums it.
    s, nearest = u.setup, np.inf
    for _, (iu, iv) in s.tool_points:
        cu, cv = s.centre if s.moving_centre_joint is None else \
            (0.0, u.true_q[:, s.moving_centre_joint])
        du, dv = u.true_x[:, iu] - cu, u.true_x[:, iv] - cv
        nearest = min(nearest, (du * du + dv * dv).min())
    assert s.tool_points and np.isfinite(nearest)
    assert abs(gathered.keep_out_nearest - nearest) <= 1e-12 * nearest


@pytest.mark.parametrize("options", OPTIONS, ids=list(OPTIONS))
@pytest.mark.parametrize("name", STUDIES)
def test_the_driver_gathers_what_its_logs_reduce_to(name, options):
    sc = _scenario(name, options)
    result = csim.simulate_compiled(sc, 0.6, unit_setups(sc), threads=False)
    assert result.periods == 600
    for u in result.units:
        _assert_gathered_is_the_logs(u)
        reduced = sv.log_reductions(u)
        assert reduced.state_low is not None and reduced.describes(u)


def test_a_follower_s_run_gathers_too(tmp_path):
    """mirror = "measured": the units run one after the other, each its own driver."""
    text = re.sub(r'^mirror = "desired".*$', 'mirror = "measured"',
                  resolve("serial_joint").read_text(), flags=re.M)
    path = tmp_path / "serial_joint_measured.toml"
    path.write_text(text + "\n[plant]\nposition_encoder = true\ndelay_periods = 1\n")
    sc = load_scenario(path)
    result = csim.simulate_compiled(sc, 0.4, unit_setups(sc))
    for u in result.units:
        _assert_gathered_is_the_logs(u)


def _driver(name: str = "serial_joint"):
    sc = load_scenario(name)
    u = unit_setups(sc)[0]
    lib = ckernels.load()
    loop = lib.closed_loop(csim.unit_kernels(lib, u, sc.plant_substeps).closed_loop)
    xd, xd_dot, xd_ddot = csim.desired_samples(u, np.arange(50) * sc.period)
    inputs = dict(x0=u.plant_x0, p_hat0=u.p_hat0, xd=xd, xd_dot=xd_dot, xd_ddot=xd_ddot,
                  gains=u.gains, Gamma=u.gamma, bound=u.bound, h=sc.period,
                  plant_p=u.plant_params, friction=u.friction, robust=u.robust_inputs)
    return loop, inputs


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_value_that_is_not_finite_makes_its_reductions_so(bad):
    loop, inputs = _driver()
    nq = loop.nq
    # A measurement that is not finite at period 7: its column's extremes say so (a NaN both,
    # an infinity the one it is), and the run ends after it.
    noise = np.zeros((50, 2 * nq))
    noise[7, 1] = bad
    log = loop.run(50, **inputs, noise=noise, reductions=True)
    assert log.rows == 8
    g = log.reductions
    low, high = sv.column_extremes(np.ascontiguousarray(log.x[:8] + noise[:8]))
    np.testing.assert_array_equal(g.state_low, low)
    np.testing.assert_array_equal(g.state_high, high)
    assert not (np.isfinite(g.state_low[1]) and np.isfinite(g.state_high[1]))
    assert np.isfinite(g.state_low[[0, 2, 3, 4, 5]]).all()
    tau_low, tau_high = sv.column_extremes(log.tau[:8])
    np.testing.assert_array_equal(g.tau_low, tau_low)
    np.testing.assert_array_equal(g.tau_high, tau_high)
    # An estimate that is not finite from the start: one row, its square not finite both ways
    # (the first row alone is the rows after the first when it is the only one).
    p_hat0 = np.array(inputs["p_hat0"], dtype=float)
    p_hat0[-1] = bad
    log = loop.run(50, **{**inputs, "p_hat0": p_hat0}, reductions=True)
    assert log.rows == 1
    assert not np.isfinite(log.reductions.square_all)
    assert not np.isfinite(log.reductions.square_later)
    assert np.isnan(log.reductions.square_all) == np.isnan(bad)


def test_a_nan_is_kept_whatever_follows_it():
    """A NaN in a column's first row stays its extremes' (a comparison with NaN is false)."""
    loop, inputs = _driver()
    noise = np.zeros((50, 2 * loop.nq))
    noise[0, 0] = np.nan
    log = loop.run(50, **inputs, noise=noise, quantum=np.zeros(2 * loop.nq), reductions=True)
    assert log.rows == 1 and np.isnan(log.reductions.state_low[0])
    assert np.isnan(log.reductions.state_high[0])


def test_no_reductions_asked_for_gives_the_same_logs():
    loop, inputs = _driver("parallel_task")
    plain = loop.run(50, **inputs)
    gathered = loop.run(50, **inputs, reductions=True)
    assert plain.reductions is None and gathered.reductions.rows == plain.rows == 50
    for key in ("x", "p_hat", "tau", "errors", "pose"):
        assert getattr(plain, key).tobytes() == getattr(gathered, key).tobytes(), key
    # The estimates' squares before any update: row 0 alone, and over every row at least it.
    first = 0.0
    for value in inputs["p_hat0"]:  # in column order, as the driver adds them
        first += value * value
    one = {**inputs, **{k: inputs[k][:1] for k in ("xd", "xd_dot", "xd_ddot")}}
    assert loop.run(1, **one, reductions=True).reductions.square_later == first
    assert gathered.reductions.square_all >= first


def test_reductions_are_read_only_for_the_arrays_they_describe():
    sc = load_scenario("serial_task")
    setups = unit_setups(sc)
    sup = build_supervisor(setups, sc.system.keep_out_radius, substeps=sc.plant_substeps)
    result = simulate(sc, 0.5, setups, threads=False)
    u = result.units[0]
    for name in ("q", "qd", "tau", "p_hat", "true_q", "true_qd"):
        with pytest.raises(ValueError, match="read-only"):
            getattr(u, name)[0, 0] = 1.0
    # An array put in the place of one they describe: the log is read again.
    judged = sv.verdict(result, sup, [sv.log_reductions(v) for v in result.units])
    assert judged["rule"] == "none"
    tau = u.tau.copy()
    tau[100, 0] = np.nan
    u.tau = tau
    assert u.gathered.of(u) is None
    reduced = sv.log_reductions(u)
    assert reduced.state_low is None and np.isnan(reduced.tau_high[0])
    assert sv.verdict(result, sup, [sv.log_reductions(v) for v in result.units])["rule"] \
        == "non-finite"
    # A part of a run is read again too.
    part = result.rows(0, 200)
    assert all(v.gathered is None for v in part.units)
    assert sv.log_reductions(part.units[1]).rows == 200


def test_a_summary_from_gathered_reductions_is_the_summary_from_the_logs():
    sc = load_scenario("parallel_joint")
    setups = unit_setups(sc)
    sup = build_supervisor(setups, sc.system.keep_out_radius, substeps=sc.plant_substeps)
    result = simulate(sc, 1.0, setups, threads=False)
    gathered = [sv.log_reductions(u) for u in result.units]
    assert all(r.state_low is not None for r in gathered)
    result.supervisor = sv.verdict(result, sup, gathered)
    assert result.supervisor == sv.verdict(result, sup)
    # Against the reductions read from the same arrays (a log the driver did not gather).
    read = [sv.log_reductions(dataclasses.replace(u, gathered=None)) for u in result.units]
    assert all(r.state_low is None for r in read)
    for row in (False, True):
        a = report.summary(result, 0.0, reductions=gathered, row=row)
        assert repr(a) == repr(report.summary(result, 0.0, reductions=read, row=row))
        if not row:
            assert repr(a) == repr(report.summary(result, 0.0))


@pytest.mark.parametrize("point, message", [
    ((0, 99, None, 0.0, 0.0), "v must be a whole index below"),
    ((-1, 1, None, 0.0, 0.0), "u must be a whole index below"),
    ((0, 1, 3, 0.0, 0.0), "joint must be a whole index below 3"),
    ((0, 1, -2, 0.0, 0.0), "joint must be"),
    ((0.0, 1, None, 0.0, 0.0), "u must be a whole index"),
    ((True, 1, None, 0.0, 0.0), "u must be a whole index"),
    ((0, 1, None), "a keep-out point is"),
    (None, "a keep-out point is"),
])
def test_keep_out_points_the_driver_cannot_read_are_refused(point, message):
    """The driver reads the pose and the state at the points' indices: each is checked."""
    loop, inputs = _driver()
    with pytest.raises(ckernels.KernelError, match=message):
        loop.run(50, **inputs, reductions=True, keep_out=[point])


def test_the_gate_reads_the_gathered_keep_out_approach_only_for_the_true_poses():
    sc = load_scenario("parallel_task")  # its keep-out centre moves with the slider
    setups = unit_setups(sc)
    result = simulate(sc, 0.5, setups, threads=False)
    u = result.units[0]
    gathered = [sv.log_reductions(v) for v in result.units]
    nearest = gathered[0].keep_out_nearest
    radius = float(np.sqrt(nearest))
    for r, clear in ((radius * (1 - 1e-6), True), (radius * (1 + 1e-6), False)):
        assert sv._clear_of_keep_out(result, r, gathered) == clear
        assert sv._clear_of_keep_out(result, r) == clear
    # A pose array put in the true poses' place is read, not the driver's approach.
    u.true_x = u.true_x.copy()
    u.x = u.true_x if u.x is not None else None
    u.true_x[3, :] = np.nan
    assert not sv._clear_of_keep_out(result, radius * 0.5, [sv.log_reductions(v)
                                                             for v in result.units])


@pytest.mark.parametrize("name", ["serial_joint", "parallel_joint"])
def test_one_rule_places_the_keep_out_centre_for_the_driver_and_the_supervisor(name):
    # The driver's keep-out points, the supervisor's checks on a log and one position all
    # take the centre from UnitSetup.keep_out_centre: a fixed centre, or one riding on a joint.
    for u in unit_setups(load_scenario(name)):
        rows = np.random.default_rng(3).uniform(-0.5, 0.5, (7, u.controller_model.nq))
        cu, cv = u.keep_out_centre(rows)
        for k, q in enumerate(rows):
            assert u.keep_out_centre(q) == pytest.approx((float(np.broadcast_to(cu, 7)[k]),
                                                          float(np.broadcast_to(cv, 7)[k])))
        ru, rv, joint = u.keep_out_reference()
        assert joint == u.moving_centre_joint
        for _, _, j, pu, pv in csim.keep_out_points(u):
            assert (j, pu, pv) == (joint, ru, rv)
            moved = 0.0 if j is None else rows[:, j]
            assert np.array_equal(np.broadcast_to(cv, 7), np.broadcast_to(pv + moved, 7))
            assert np.array_equal(np.broadcast_to(cu, 7), np.broadcast_to(pu, 7))
        if name.startswith("parallel"):
            assert joint is not None  # the slider carries the cochlea
        else:
            assert joint is None and (cu, cv) == tuple(u.centre)
    # The robot adapter's plans state it (the replay draws the circle from them) and the
    # set-ups take it from there: the same centre at every row.
    sc = load_scenario(name)
    plans = robot(sc.robot).unit_plans(sc.system, sc)
    for plan, u in zip(plans, unit_setups(sc)):
        rows = np.random.default_rng(5).uniform(-0.5, 0.5, (7, u.controller_model.nq))
        for a, b in zip(plan.keep_out_centre(rows), u.keep_out_centre(rows)):
            assert np.array_equal(np.broadcast_to(a, 7), np.broadcast_to(b, 7))
    # The 1 kHz check's points (the whole system's q, units stacked) place it alike.
    sc = load_scenario(name)
    setups = unit_setups(sc)
    points = build_supervisor(setups, sc.system.keep_out_radius, kernels="c").keep_out_points
    q_all = np.random.default_rng(4).uniform(-0.5, 0.5, sum(u.controller_model.nq
                                                              for u in setups))
    row, start = 0, 0
    rows = points(q_all)
    for u in setups:
        q = q_all[start:start + u.controller_model.nq]
        for _ in u.tool_points:
            assert tuple(rows[row, 2:]) == tuple(map(float, u.keep_out_centre(q)))
            row += 1
        start += u.controller_model.nq
    assert row == len(rows)
