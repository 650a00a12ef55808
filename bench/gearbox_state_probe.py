"""Controller e with a state of its own, on issue 24's everything-at-once plant: a probe, not a
shipped controller (docs/robustness.md, "A controller state: a velocity filter, an integral,
dither").

``python bench/gearbox_state_probe.py [--seconds 60] [--torque-error 0.05]`` runs the shipped
serial_joint_realistic study (controller e, its scenario's gains) on the plant of
``tests/test_gearbox_survival.py`` (the realistic preset with the MX-64's 0.33 deg of backlash,
static friction 1.5x Coulomb, the bridge's conversion, the delay jittering between 1 and 3
periods, +-1 encoder count and the torque constant off by ``--torque-error``), once per
setting of :data:`SETTINGS`, and prints for each the converged coordinates, each joint's final
true RMS error in encoder counts (the last 20 %, as ``summary.json`` judges it) and the rule
the supervisor would have stopped a real run on.

The loop is :func:`cochlea.sim.reference.simulate_reference`'s, period by period, with the
shipped controller's own CasADi ``step`` in it. What the settings add around that step needs
a state carried from period to period, which the controllers' ``step`` Functions do not have
(they carry only the estimate ``p^``), so this probe keeps it in Python:

* ``friction_at_desired``: the Coulomb columns of the regressor boxed to zero and the friction
  compensated instead as a feedforward at the *desired* velocity, on the plant's Stribeck curve
  (``F_c tanh(v / 0.02) (1 + 0.5 exp(-(v / 0.02)^2))``, ``F_c`` the description's estimate): a
  compensation the position error and its count of noise cannot switch;
* ``velocity_filter_hz``: the measured velocity through a first-order low-pass before the
  controller (the link's rattle, 0.2-0.5 rad/s square waves, out of the damping term);
* ``integral``: ``K_i`` times the integral of the joint error added to the torque (N m/(rad s));
* ``dither``: a square wave of this fraction of each joint's Coulomb level added to the torque,
  ``dither_periods`` control periods long (4: 250 Hz), against the rotor's stick-slip;
* ``stiffness``: a factor on ``K_e``;
* ``ramp``: the scenario's ``startup_ramp_s`` (the controllers' own option): without it the
  start-up transient stops every setting on the velocity limit within 10-25 ms, and with it
  the initial error is zero, so every joint is judged on its one-count floor.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import casadi as ca
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cochlea.apps.report import summary  # noqa: E402
from cochlea.dynamixel.control_table import RAD_PER_COUNT  # noqa: E402
from cochlea.robots import robot  # noqa: E402
from cochlea.runtime.supervisor import build_supervisor, verdict  # noqa: E402
from cochlea.sim import load_scenario, unit_setups  # noqa: E402
from cochlea.sim.result import SimulationResult, simulated_log, truncate  # noqa: E402
from cochlea.sim.setup import delay_ages, encoder_noise, quantise  # noqa: E402

STUDY = "serial_joint_realistic"
#: The settings docs/robustness.md reports, in the order of its table.
RAMP = dict(ramp=0.5)  # s: the desired path ramped from the initial pose (startup_ramp_s)
FILTERED = dict(RAMP, friction_at_desired=True, velocity_filter_hz=20.0)
SETTINGS = {
    "shipped": {},
    "the start-up ramp, 0.5 s": RAMP,
    "... and the friction at the desired velocity": dict(RAMP, friction_at_desired=True),
    "... and a 20 Hz velocity filter": FILTERED,
    "... and an integral, K_i 150": dict(FILTERED, integral=150.0),
    "... and a 250 Hz dither of 0.2 F_c": dict(FILTERED, integral=150.0, dither=0.2,
                                               dither_periods=4),
    "... and K_e x 4": dict(FILTERED, integral=150.0, dither=0.2, dither_periods=4,
                            stiffness=4.0),
}
COULOMB_SMOOTHING = 0.02  # rad/s, the controllers' and the plant's (docs/models.md)
STATIC_RATIO = 1.5  # the plant's static friction over Coulomb


def everything(torque_error: float, preset_only: bool = False, **changes):
    """The study on issue 24's everything-at-once plant (tests/test_gearbox_survival.py), or
    (``preset_only``) on the realistic preset alone; ``changes``: other ``[plant]`` fields."""
    sc = load_scenario(STUDY)
    n = robot(sc.robot).layout(sc.system, sc.space).n_joint
    plant = sc.plant if preset_only else dataclasses.replace(
        sc.plant, delay_periods=1, delay_jitter_periods=2, encoder_noise_counts=1,
        torque_constant_error=np.full(n, torque_error), seed=24)
    return dataclasses.replace(sc, plant=dataclasses.replace(plant, **changes))


def plant_change(text: str) -> tuple[str, object]:
    """``KEY=VALUE`` of ``--plant``: a number, or true/false."""
    key, _, value = text.partition("=")
    if value.lower() in ("true", "false"):
        return key, value.lower() == "true"
    return key, float(value)


class ProbeController:
    """The shipped step of one unit with the probe's additions and their state."""

    def __init__(self, u, h: float, setting: dict):
        self.u, self.h, self.s = u, h, setting
        n = u.controller_model.nq
        robust = [np.array(v, float).copy() for v in u.robust_inputs]
        self.coulomb = {}
        if setting.get("friction_at_desired"):
            for k, name in enumerate(u.controller_model.param_names):
                owner, _, kind = name.rpartition(".")
                if kind == "Fc":
                    joint = [j.name for j in u.controller_model.joints].index(owner)
                    self.coulomb[joint] = float(u.p_hat0[k])
                    robust[1][k] = robust[2][k] = 0.0  # the box holds this estimate at zero
        self.robust = [ca.DM(v) for v in robust]
        self.box = robust[1], robust[2]
        gains = np.array(u.gains, float)
        gains[2 * n:] *= setting.get("stiffness", 1.0)
        self.gains, self.gamma = ca.DM(gains), ca.DM(u.gamma)
        self.velocity = None
        self.integral = np.zeros(n)
        self.level = np.array([self.coulomb.get(i, 0.2) for i in range(n)])

    def start(self, p_hat: np.ndarray) -> np.ndarray:
        return np.clip(p_hat, *self.box)

    def __call__(self, k: int, t: float, measured: np.ndarray, p_hat: np.ndarray):
        u, s, n = self.u, self.s, self.u.controller_model.nq
        q, qd = measured[:n], measured[n:]
        if s.get("velocity_filter_hz"):
            a = 1 - np.exp(-2 * np.pi * s["velocity_filter_hz"] * self.h)
            self.velocity = qd.copy() if self.velocity is None else \
                self.velocity + a * (qd - self.velocity)
            qd = self.velocity
        xd, xd_dot, xd_ddot = (ca.densify(v) for v in u.desired(t))
        tau, p_next, errors = u.controller.step(q, qd, xd, xd_dot, xd_ddot, p_hat, self.gains,
                                                self.gamma, u.bound, self.h, *self.robust)
        tau = np.array(tau).ravel()
        errors = np.array(errors).ravel()
        v_d = np.array(xd_dot).ravel()
        for i, level in self.coulomb.items():
            v = v_d[i]
            tau[i] += level * np.tanh(v / COULOMB_SMOOTHING) * (
                1 + (STATIC_RATIO - 1) * np.exp(-(v / COULOMB_SMOOTHING) ** 2))
        if s.get("dither"):
            period = s.get("dither_periods", 4)
            tau += (1 if k % period < period // 2 else -1) * s["dither"] * self.level
        if s.get("integral"):
            self.integral += errors[:n] * self.h
            tau += s["integral"] * self.integral
        tau = np.clip(tau, -u.effort_limit, u.effort_limit)
        return tau, np.array(p_next).ravel(), errors, np.array(xd).ravel(), v_d


def run(sc, setting: dict, seconds: float) -> SimulationResult:
    """:func:`cochlea.sim.reference.simulate_reference`'s loop with :class:`ProbeController`."""
    if setting.get("ramp"):
        sc = dataclasses.replace(sc, robust=dataclasses.replace(sc.robust,
                                                                startup_ramp=setting["ramp"]))
    setups = unit_setups(sc)
    h = sc.period
    steps = int(round(seconds / h))
    time = np.arange(steps) * h
    ages = delay_ages(sc.plant, steps)
    counts = encoder_noise(sc.plant, steps, setups)
    logs = []
    for u, encoder in zip(setups, counts):
        n = u.controller_model.nq
        control = ProbeController(u, h, setting)
        step = u.plant_function(sc.plant_substeps)
        numbers = [u.plant_params, u.friction, h] + ([] if u.drive is None else [u.drive])
        X, seen = np.empty((steps, 2 * n)), np.empty((steps, 2 * n))
        log = {k: np.empty((steps, s)) for k, s in [
            ("tau", n), ("errors", 2 * n), ("xd", n), ("xd_dot", n),
            ("p_hat", u.controller.n_params)]}
        x, p_hat = u.plant_x0.astype(float), control.start(u.p_hat0.astype(float))
        rows = steps
        for k in range(steps):
            X[k] = x[:2 * n]
            measured = X[max(k - (sc.plant.delay_periods if ages is None else ages[k]), 0)]
            if encoder is not None:
                measured = measured + np.concatenate([encoder[k], np.zeros(n)])
            if u.quantum is not None:
                measured = quantise(measured, u.quantum, u.grid_offset)
            seen[k] = measured
            log["p_hat"][k] = p_hat
            tau, p_hat, *rest = control(k, time[k], measured, p_hat)
            if u.effort_grid is not None:
                u.effort_grid.apply(tau)
            log["tau"][k] = tau
            log["errors"][k], log["xd"][k], log["xd_dot"][k] = rest
            applied = tau if u.torque_scale is None else np.multiply(tau, u.torque_scale)
            x = np.array(step(x, applied, *numbers)).ravel()
            if not (np.isfinite(x).all() and np.isfinite(p_hat).all()):
                rows = k + 1
                break
        pose = np.array(u.fk_world.map(rows)(X[:rows, :n].T)).T
        logs.append(simulated_log(u, sc.space, X[:rows], seen[:rows], pose, log["xd"][:rows],
                                  log["xd_dot"][:rows], log["errors"][:rows],
                                  log["tau"][:rows], log["p_hat"][:rows]))
    rows = min(len(unit.q) for unit in logs)
    if rows < steps:
        truncate(logs, rows)
    result = SimulationResult(sc, time[:rows], logs, {})
    supervisor = build_supervisor(setups, sc.system.keep_out_radius, kernels="casadi",
                                  substeps=sc.plant_substeps)
    result.supervisor = verdict(result, supervisor)
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="run length (s)")
    parser.add_argument("--torque-error", type=float, default=0.05,
                        help="the motors' torque-constant error (fraction)")
    parser.add_argument("--preset-only", action="store_true",
                        help="the realistic preset alone, without the issue's delay jitter, "
                             "encoder noise and torque-constant error")
    parser.add_argument("--plant", action="append", type=plant_change, default=[],
                        metavar="KEY=VALUE", help="another [plant] field, e.g. "
                        "static_friction_ratio=1.0 or current_quantisation=false")
    parser.add_argument("--settings", nargs="+", type=int, metavar="ROW",
                        help="only these rows of SETTINGS (0-based)")
    args = parser.parse_args(argv)
    sc = everything(args.torque_error, args.preset_only, **dict(args.plant))
    case = "the realistic preset" if args.preset_only else \
        f"everything at once, torque constant {args.torque_error:+.0%}"
    print(f"{STUDY}, {case}{''.join(f', {k} = {v}' for k, v in args.plant)}, "
          f"{args.seconds:g} s; final true RMS per joint in counts (arm1 | arm2)")
    rows = list(SETTINGS.items())
    for label, setting in (rows if args.settings is None else [rows[i] for i in args.settings]):
        judged = summary(run(sc, setting, args.seconds))
        coords = [c for s in judged["units"].values() for c in s["tracked"].values()]
        rms = " | ".join(" ".join(f"{c['final_rms_error'] / RAD_PER_COUNT:.2f}"
                                  for c in s["tracked"].values())
                         for s in judged["units"].values())
        rule = judged["supervisor"]
        stop = "none" if rule["rule"] == "none" else f"{rule['rule']} at {rule['time_s']:.3f} s"
        print(f"| {label} | {sum(c['converged'] for c in coords)}/{len(coords)} | {rms} | "
              f"{stop} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
