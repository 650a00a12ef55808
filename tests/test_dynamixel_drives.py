"""Joint <-> motor conversions round-trip; the fit rule (sign, offset, continuity, inverse); the
current limits; the bridge's vectorised per-period conversions agree with the scalar ones; the
bus budget's numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cochlea.dynamixel.bridge import DynamixelBackend
from cochlea.dynamixel.budget import bus_budget
from cochlea.dynamixel.control_table import MX64, XM540_W270
from cochlea.dynamixel.drives import DEFAULT_RAMP_NM, Fit, joint_drives
from cochlea.robots.description import MotorFit
from tests.conftest import assert_periods_allocate_nothing


@pytest.fixture(scope="module")
def drives():
    return joint_drives("serial") + joint_drives("parallel")


def test_position_velocity_and_current_round_trip(drives, rng):
    for d in drives:
        span = d.position_limits
        q = rng.uniform(*span, 200)
        counts = d.counts(q)
        assert np.all(np.abs(d.q(counts) - q) <= abs(d.q_per_count) / 2 + 1e-12)
        assert np.array_equal(d.counts(d.q(counts)), counts)
        qd = rng.uniform(-d.ratio * 5, d.ratio * 5, 200)
        lsb = d.velocity_lsb(qd)
        assert np.all(np.abs(d.qd(lsb) - qd) <= abs(d.qd_per_lsb) / 2 + 1e-12)
    mx, xm = drives[0], drives[8]
    assert mx.spec is MX64 and xm.spec is XM540_W270
    assert mx.current_mA(100) == pytest.approx(336.0)
    assert xm.current_mA(-100) == pytest.approx(-269.0)
    # 0.229 rpm per LSB, 4096 counts per turn.
    assert mx.qd(1) == pytest.approx(0.229 * 2 * math.pi / 60)
    assert mx.q(4096) - mx.q(0) == pytest.approx(2 * math.pi)


def test_the_slider_goes_through_its_transmission(drives):
    slider = next(d for d in drives if d.name == "slider.d1")
    assert slider.type == "prismatic" and slider.ratio == pytest.approx(0.02)  # pinion radius
    assert slider.q(4096) - slider.q(0) == pytest.approx(2 * math.pi * 0.02)  # m per turn
    force = 30.0  # N -> 0.6 N m at the pinion
    assert slider.goal_current_lsb(force) == np.rint(
        slider.fit.current(0.6) * 1000 / 2.69)


def test_fit_units_are_read_from_the_description():
    reference = Fit.from_description(MotorFit(108.2, -15.47, "current_A", "torque_Ncm"))
    assert (reference.a, reference.b) == pytest.approx((1.082, -0.1547))  # N m/A, N m
    for fit in (MotorFit(1.082, -0.1547, "current_A", "torque_Nm"),
                MotorFit(0.1082, -15.47, "current_mA", "torque_Ncm"),
                MotorFit(0.001082, -0.1547, "current_mA", "torque_Nm")):
        converted = Fit.from_description(fit)
        assert (converted.a, converted.b) == pytest.approx((reference.a, reference.b))


def test_fit_rule_sign_offset_and_inverse():
    fit = Fit.from_description(MotorFit(108.2, -15.47, "current_A", "torque_Ncm"))
    i0 = 0.1547 / 1.082  # A: the offset's current
    assert fit.offset_current == pytest.approx(i0)
    assert fit.current(0.0) == 0.0
    # Beyond the ramp: |I| = (|tau| - b) / a with the sign of tau.
    for tau in (0.05, 0.3, 2.5):
        assert fit.current(tau) == pytest.approx((tau + 0.1547) / 1.082)
        assert fit.current(-tau) == pytest.approx(-(tau + 0.1547) / 1.082)
    # Inside the ramp the offset is blended in linearly: continuous, odd, increasing.
    assert fit.current(0.025) == pytest.approx(0.025 / 1.082 + i0 / 2)
    taus = np.linspace(-1.0, 1.0, 20001)
    currents = fit.current(taus)
    assert np.all(np.diff(currents) > 0)
    assert np.allclose(currents, -fit.current(-taus))
    assert np.max(np.abs(np.diff(currents))) < 1e-3  # no jump anywhere, at 0 or +-ramp
    # The forward map (what the emulator's motor does) is the exact inverse.
    assert np.allclose(fit.torque(currents), taus, atol=1e-12)
    amps = np.linspace(-3, 3, 6001)
    assert np.allclose(fit.current(fit.torque(amps)), amps, atol=1e-12)
    # Forward: the fit's own line outside the ramp.
    assert fit.torque(1.0) == pytest.approx(1.082 - 0.1547)
    assert fit.ramp == DEFAULT_RAMP_NM


def test_a_positive_offset_stays_invertible():
    fit = Fit.from_description(MotorFit(100.0, 8.0, "current_A", "torque_Ncm"))  # b = 0.08 N m
    assert fit.ramp == pytest.approx(0.16)
    taus = np.linspace(-1, 1, 4001)
    assert np.all(np.diff(fit.current(taus)) > 0)
    assert np.allclose(fit.torque(fit.current(taus)), taus)
    assert fit.current(0.5) == pytest.approx((0.5 - 0.08) / 1.0)  # a current dead-band


def test_current_limits(drives):
    arm1_link1 = drives[0]
    amps = 2.5 / 1.082 + 0.1547 / 1.082  # torque limit 2.5 N m through the fit
    assert arm1_link1.current_limit_lsb == math.ceil(amps * 1000 / 3.36)
    slider = next(d for d in drives if d.name == "slider.d1")
    amps = (100.0 * 0.02 + 0.00567) / 0.972  # 100 N through the 20 mm pinion
    assert slider.current_limit_lsb == math.ceil(amps * 1000 / 2.69)
    for d in drives:
        assert 0 < d.current_limit_lsb <= d.spec.current_limit_max
        # Commands saturate at the limit, both signs.
        assert d.goal_current_lsb(1e6) == d.current_limit_lsb
        assert d.goal_current_lsb(-1e6) == -d.current_limit_lsb


class ScriptedPort:
    """A port that answers every SYNC_READ with given registers (no emulator, no threads)."""

    low_latency = False

    def __init__(self, backend: DynamixelBackend):
        from cochlea.dynamixel import protocol as proto

        self.proto = proto
        self.backend = backend
        self.registers = {i: (0, 0, 0) for i in backend.ids}
        self.pending = b""
        self.sent: list[bytes] = []

    def discard_input(self):
        self.pending = b""
        return True

    def write(self, view, n, deadline):
        frame = bytes(view[:n])
        self.sent.append(frame)
        if frame[7] == 0x82:
            self.pending = b"".join(
                self.proto.status(i, 0, self.proto.le(c, 2) + self.proto.le(v, 4)
                                  + self.proto.le(p, 4))
                for i, (c, v, p) in self.registers.items())
        return True

    def read_into(self, view, deadline):
        n = min(len(view), len(self.pending))
        view[:n] = self.pending[:n]
        self.pending = self.pending[n:]
        return n

    def close(self):
        pass


def _scripted(robot: str, **options):
    backend = DynamixelBackend(robot, "/dev/scripted", **options)
    port = ScriptedPort(backend)
    backend._port, backend._active = port, True
    return backend, port


@pytest.mark.parametrize("robot", ["serial", "parallel"])
def test_the_per_period_conversions_match_the_scalar_ones(robot, rng):
    backend, port = _scripted(robot)
    n = backend.nq
    for _ in range(20):
        tau = rng.uniform(-1, 1, n) * np.array([d.effort_limit for d in backend.drives]) * 1.2
        tau[rng.integers(n)] = 0.0
        assert backend.write(tau)
        expected = [d.goal_current_lsb(t) for d, t in zip(backend.drives, tau)]
        assert list(backend.goal_current_lsb) == expected
        registers = {i: (int(rng.integers(-2000, 2000)), int(rng.integers(-500, 500)),
                         int(rng.integers(-10**6, 10**6))) for i in backend.ids}
        port.registers = registers
        x = np.zeros(2 * n)
        assert backend.read(x)
        for j, d in enumerate(backend.drives):
            c, v, p = registers[d.id]
            assert x[j] == pytest.approx(float(d.q(p)))
            assert x[n + j] == pytest.approx(float(d.qd(v)))
            assert backend.present_current_mA[j] == pytest.approx(float(d.current_mA(c)))


@pytest.mark.slow
def test_the_per_period_path_does_not_grow_memory(rng):
    """No buffer, list or array is made per period: the allocated blocks stay put."""
    from cochlea.dynamixel import protocol as proto

    backend, port = _scripted("serial")
    port.write = lambda view, n, deadline: True  # answer from a fixed, prebuilt reply
    reply = b"".join(proto.status(i, 0, bytes(10)) for i in backend.ids)
    view = memoryview(reply)

    def read_into(target, deadline):
        target[:len(reply)] = view
        return len(reply)

    port.read_into = read_into
    assert_periods_allocate_nothing(backend, np.zeros(12), rng.uniform(-0.1, 0.1, 6))


def test_bus_budget_numbers():
    for baud, wire_us in ((1_000_000, 1780), (2_000_000, 890), (4_000_000, 445)):
        b = bus_budget(6, baud)
        assert (b.sync_write_bytes, b.sync_read_bytes, b.reply_bytes) == (32, 20, 21)
        assert b.total_bytes == 178
        assert b.wire_s * 1e6 == pytest.approx(wire_us)
    assert bus_budget(6, 1_000_000).check(1000).level == "refuse"
    assert bus_budget(6, 2_000_000).check(1000).level == "refuse"  # 0.89 + 0.12 ms > 1 ms
    assert bus_budget(6, 2_000_000).check(500).level == "warn"  # 1.01 + 1 ms latency > 2 ms
    assert bus_budget(6, 2_000_000).check(400).level == "ok"
    verdict = bus_budget(6, 4_000_000).check(1000)  # fits, but not with a 1 ms adapter latency
    assert verdict.level == "warn" and "1565 us" in verdict.message
    assert bus_budget(6, 4_000_000, adapter_latency_s=0.0).check(1000).level == "ok"
    assert bus_budget(5, 4_000_000).total_bytes == 29 + 19 + 5 * 21


@pytest.mark.parametrize("robot", ["serial", "parallel"])
def test_without_the_offset_current_the_bridge_commands_the_slope_alone(robot, rng):
    """A controller that compensates friction gets a bridge that does not (issue 24): the
    Goal Current is tau / a, with none of the fit's offset current on top."""
    backend, port = _scripted(robot, offset_current=False)
    assert not backend.offset_current
    n = backend.nq
    limits = np.array([d.effort_limit for d in backend.drives])
    for _ in range(20):
        tau = rng.uniform(-0.3, 0.3, n) * limits
        assert backend.write(tau)
        slope = [np.clip(np.rint(d.torque_per_effort * t / d.fit.a * d.lsb_per_ampere),
                         -d.current_limit_lsb, d.current_limit_lsb)
                 for d, t in zip(backend.drives, tau)]
        assert list(backend.goal_current_lsb) == slope
        with_offset = [d.goal_current_lsb(t) for d, t in zip(backend.drives, tau)]
        # Outside the blending band and below the Current Limit every command differs from
        # the bridge's with the offset by the offset current (0.14-0.22 A on the MX-64s).
        for d, t, a, b in zip(backend.drives, tau, slope, with_offset):
            if abs(t * d.torque_per_effort) >= d.fit.ramp and abs(b) < d.current_limit_lsb:
                assert abs(b - a) == pytest.approx(d.fit.offset_current * d.lsb_per_ampere,
                                                   abs=1)


@pytest.mark.slow  # 1.7 s
def test_friction_is_compensated_once():
    """One rule decides it: the bridge adds the offset current unless the controller's model
    carries friction (and so compensates it)."""
    from cochlea.robots.model import ACTUATORS
    from cochlea.robots.motor_fit import bridge_compensates_friction
    from cochlea.sim import load_scenario
    assert set(ACTUATORS) == {"none", "armature", "all"}
    assert bridge_compensates_friction("none") and bridge_compensates_friction("armature")
    assert not bridge_compensates_friction("all")
    # The shipped studies: the thesis's rigid controllers get the bridge's compensation, the
    # realistic ones (friction in their model) compensate it themselves.
    # The embedded program's scenarios carry the same decision to its C bridge.
    from cochlea.sim.embedded import embedded_scenario
    for name in ("serial_joint", "serial_task", "parallel_joint", "parallel_task"):
        assert bridge_compensates_friction(load_scenario(name).controller_actuators)
        assert embedded_scenario(load_scenario(name)).bridge_offset_current
        realistic = load_scenario(f"{name}_realistic")
        assert not bridge_compensates_friction(realistic.controller_actuators)
        assert not embedded_scenario(realistic).bridge_offset_current
