"""An RK4 period whose later stages take their sines and cosines from the first stage's
(cochlea/robots/stage_trig.py, the all-in-C simulation's plant): the angle sums within an ulp or
two of the exact values over the whole reach, the lifted forward dynamics the same operations,
the period the plain one's to rounding, and ``far`` counting exactly the offsets past reach."""

from __future__ import annotations

import math
from decimal import Decimal, localcontext

import casadi as ca
import numpy as np
import pytest

import cochlea
from cochlea.robots import stage_trig
from cochlea.robots.parallel.forward import forward_dynamics as block_form
from cochlea.robots.plant import plant_step

H = 1e-3  # s


def _exact_sincos(x: Decimal) -> tuple[Decimal, Decimal]:
    """sin x and cos x of a Decimal to about 50 digits (|x| <= 8: plain Taylor series)."""
    with localcontext() as ctx:
        ctx.prec = 70
        x2, s, c, term = x * x, x, Decimal(1), x
        for n in range(1, 60):
            term = -term * x2 / ((2 * n) * (2 * n + 1))
            s += term
        term = Decimal(1)
        for n in range(1, 60):
            term = -term * x2 / ((2 * n - 1) * (2 * n))
            c += term
        return s, c


def test_the_shifted_values_are_within_two_ulps_of_the_exact_ones():
    """sin and cos of ``q + delta`` (the exact sum) from libm's sin q and cos q through the
    series, for offsets over the whole reach, both signs and tiny ones: within 2 ulp of 1 of
    the 50-digit values (the error of the first stage's own libm values is in that)."""
    rng = np.random.default_rng(11)
    angles = np.concatenate([rng.uniform(-7.0, 7.0, 60),
                             [0.0, math.pi / 2, math.pi, -math.pi / 4, 3.0]])
    reach = stage_trig.REACH
    offsets = np.concatenate([rng.uniform(-reach, reach, 30),
                              [reach, -reach, reach / 2, 1e-3, -1e-9, 0.0, 5e-324]])
    worst = 0.0
    for q in angles:
        s, c = math.sin(q), math.cos(q)
        for d in offsets:
            got_s, got_c = stage_trig.shifted(s, c, float(d))
            exact_s, exact_c = _exact_sincos(Decimal(float(q)) + Decimal(float(d)))
            worst = max(worst, abs(Decimal(got_s) - exact_s) / Decimal(2.0 ** -52),
                        abs(Decimal(got_c) - exact_c) / Decimal(2.0 ** -52))
    assert worst <= 2, worst
    assert stage_trig.shifted(0.3, 0.7, 0.0) == (0.3, 0.7)  # no offset: the first stage's


@pytest.fixture(scope="module")
def parallel():
    return cochlea.model("parallel")


@pytest.fixture(scope="module")
def serial():
    return cochlea.model("serial", parameterisation="inertial")


def _trig_of_inputs(f: ca.Function) -> int:
    """How many sines and cosines ``f`` takes of an element of an input, as it is."""
    g = ca.Function("g", f.sx_in(), f.call(f.sx_in()), {"live_variables": False})
    inputs = {g.instruction_output(k)[0] for k in range(g.n_instructions())
              if g.instruction_id(k) == ca.OP_INPUT}
    return sum(1 for k in range(g.n_instructions())
               if g.instruction_id(k) in (ca.OP_SIN, ca.OP_COS)
               and g.instruction_input(k)[0] in inputs)


@pytest.mark.parametrize("which", ["parallel", "serial"])
def test_the_lifted_forward_dynamics_reads_the_given_sines(which, request):
    """Every sine and cosine of a joint angle is read from ``s`` and ``c`` (none left); given
    the angles' own, the result is the forward dynamics' bit for bit (the same operations); and
    the angles lifted are the revolute joints the dynamics takes them of."""
    model = request.getfixturevalue(which)
    n, n_p = model.nq, len(model.param_names)
    forward = block_form(model) if which == "parallel" else model.forward_dynamics_p
    lifted, angles = stage_trig.lifted(forward, n, n_p)
    q, qd, tau, p = (ca.SX.sym(k, size) for k, size in (("q", n), ("qd", n), ("tau", n),
                                                         ("p", n_p)))
    plain = ca.Function("plain", [q, qd, tau, p], [forward(q, qd, tau, p)])
    assert _trig_of_inputs(plain) > 0 and _trig_of_inputs(lifted) == 0
    assert angles == ((0, 1, 3, 4) if which == "parallel" else (1, 2))
    rng = np.random.default_rng(5)
    for _ in range(10):
        qv = rng.uniform(-2.0, 2.0, n)
        args = (qv, rng.normal(0.0, 1.0, n), rng.normal(0.0, 1.0, n), model.p_nominal)
        s, c = np.asarray(ca.sin(ca.DM(qv))).ravel(), np.asarray(ca.cos(ca.DM(qv))).ravel()
        np.testing.assert_array_equal(np.asarray(lifted(args[0], s, c, *args[1:])),
                                      np.asarray(plain(*args)))


def _period_args(model, x, tau, coulomb, viscous=0.01):
    n = model.nq
    args = [x, tau, model.p_nominal, np.full(n, viscous), H]
    if coulomb:
        args.append(np.concatenate([np.full(n, 0.02), np.full(n, 0.03), np.full(n, 0.01)]))
    return args


@pytest.mark.parametrize("which", ["parallel", "serial"])
@pytest.mark.parametrize("coulomb", [False, True])
def test_the_stage_period_is_the_plain_one_to_rounding(which, coulomb, request):
    """At states of several turns and joint speeds up to 10 rad/s (offsets within reach), with
    and without dry friction: ``far`` is 0 and the next state is the plain period's to 1e-13
    relative, not bit for bit (the shifted values run); two RK4 sub-steps too."""
    model = request.getfixturevalue(which)
    n = model.nq
    rng = np.random.default_rng(9)
    for substeps in (1, 2):
        plain = plant_step(model, substeps, coulomb=coulomb)
        stages = plant_step(model, substeps, coulomb=coulomb, stage_trig=True)
        assert stages.name_out() == ["x_next", "far"]
        assert stages.name() == plain.name() + "_stages"
        differs = False
        for _ in range(12):
            x = np.concatenate([rng.uniform(-6.0, 6.0, n), rng.uniform(-10.0, 10.0, n)])
            if which == "parallel":  # a configuration the closed chain can take
                x[:n] = model.geometry.random_configuration(rng)
            tau = rng.normal(0.0, 0.5, n)
            args = _period_args(model, x, tau, coulomb)
            a = np.asarray(plain(*args)).ravel()
            b, far = stages(*args)
            b = np.asarray(b).ravel()
            assert float(far) == 0.0
            assert np.max(np.abs(a - b)) <= 1e-13 * max(1.0, np.max(np.abs(a))), (a, b)
            differs = differs or not np.array_equal(a, b)
        assert differs


def test_an_arm_from_its_urdf_takes_the_stage_period(tmp_path):
    """A spatial arm imported from its URDF (tests/data/arm4.urdf, 4 joints, the
    articulated-body algorithm's forward dynamics): its joints' sines are lifted and its stage
    period is its plain one's to 1e-13 relative."""
    from cochlea.robots.urdf import import_urdf

    from .conftest import DATA

    description = tmp_path / "arm4.toml"
    description.write_text(import_urdf(DATA / "arm4.urdf").text, encoding="utf-8")
    arm = cochlea.model("serial", description=description, parameterisation="inertial")
    n = arm.nq
    _, angles = stage_trig.lifted(arm.forward_dynamics_p, n, len(arm.param_names))
    assert angles
    plain, stages = plant_step(arm, 1), plant_step(arm, 1, stage_trig=True)
    rng = np.random.default_rng(2)
    for _ in range(10):
        x = np.concatenate([rng.uniform(-3.0, 3.0, n), rng.uniform(-3.0, 3.0, n)])
        args = _period_args(arm, x, rng.normal(0.0, 1.0, n), False)
        a = np.asarray(plain(*args)).ravel()
        b, far = stages(*args)
        assert float(far) == 0.0
        assert np.max(np.abs(a - np.asarray(b).ravel())) <= 1e-13 * max(1.0, np.max(np.abs(a)))


def test_far_counts_the_offsets_past_reach(serial):
    """``far`` is the number of stage offsets (3 a sub-step per lifted joint) past REACH: 0 at
    rest, 3 for one joint at 2.5 REACH / h without friction (every later stage of it past: the
    others at rest, nothing slows it within the period), and a NaN velocity gives
    a NaN state and no count (the caller's plain period would give NaN too)."""
    stages = plant_step(serial, 1, stage_trig=True)
    n = serial.nq
    zero = np.zeros(n)

    def far(qd):
        x_next, count = stages(*_period_args(serial, np.concatenate([zero, qd]), zero, False,
                                             viscous=0.0))
        return float(count), np.asarray(x_next).ravel()

    assert far(zero)[0] == 0.0
    fast = zero.copy()
    fast[2] = 2.5 * stage_trig.REACH / H  # joint 3 (lifted): h/2 qd past reach, so all three
    assert far(fast)[0] == 3.0
    fast = zero.copy()
    fast[0] = 1e3  # joint 1 takes no sine (the base's angle): not lifted, not counted
    assert far(fast)[0] == 0.0
    count, x_next = far(np.array([0.0, np.nan, 0.0]))
    assert count == 0.0 and np.all(np.isnan(x_next[n:]))
