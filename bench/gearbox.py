"""The realistic studies on the geared plant, each effect alone and all together (issue 24):
``python bench/gearbox.py [--factor 3] [--out FILE.md]`` prints (or writes) the table of
docs/robustness.md, "The gearbox".

Every case is one as-fast run on the C kernels (the CasADi reference gives the same log, bit
for bit: tests/test_gearbox.py) of ``factor`` times the study's length, judged as
``summary.json`` judges it (:func:`cochlea.apps.report.unit_summary`: final RMS error over the
last 20 % within 5 % of the initial error or one encoder count), with the supervisor's verdict
(the rule a real run would have stopped on). *Oscillation*: per joint, the peak-to-peak of the
position about its centred 0.1 s moving average over the last 20 % of the run, in the joint's
encoder counts (the studies' own motion, at most 0.63 rad/s, leaves under 0.02 counts there);
the worst joint of the study; not given for a run the supervisor would have stopped. The
controllers are the shipped realistic ones, with the robust options their scenarios set.
``--cases stress`` runs the realistic preset with issue 24's delay and encoder noise on top
(:data:`STRESS`) instead of each effect alone; ``--cases everything`` the issue's
everything-at-once case as ``tests/test_gearbox_survival.py`` sets it (:data:`EVERYTHING`).
``--settings NAME`` runs the studies with other controller settings than their scenario files'
(:data:`SETTINGS`: what docs/robustness.md, "The serial studies: not converged", measured).
The *worst floor* column is the worst tracked coordinate's final true RMS error over its
convergence floor (the rule's 5 % of the initial error or one encoder count): at most 1 is
converged.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np

from cochlea.apps.report import unit_summary
from cochlea.dynamixel.control_table import RAD_PER_COUNT
from cochlea.robots import robot
from cochlea.runtime.supervisor import build_supervisor, verdict
from cochlea.sim import load_scenario, simulate, unit_setups

STUDIES = ("serial_joint", "serial_task", "parallel_joint", "parallel_task")
#: The cases: the realistic preset's keys that differ from the preset as shipped.
BEFORE = dict(gearbox=False, static_friction_ratio=1.0, bridge_offset=False)
CASES = {
    "before the gearbox (rigid links, Coulomb friction)": BEFORE,
    "backlash alone": dict(BEFORE, gearbox=True),
    "static friction 1.5x Coulomb alone": dict(BEFORE, static_friction_ratio=1.5),
    "the bridge's offset alone (double compensation)": dict(BEFORE, bridge_offset=True),
    "all together (the realistic preset: no offset for these controllers)": {},
    "all together, and the bridge's offset": dict(bridge_offset=True),
}


#: The disturbances of issue 24, item 2, on top of the realistic preset: measurement delay of
#: 2 and 3 periods (the real chain jitters between 1 and 3) and Gaussian position noise of
#: about one encoder count (``noise_q_std_SI``, one number for every joint: the finest joint's
#: count, so no joint sees more than a count: 1.53 mrad on the serial arms; on the parallel
#: mechanism the slider's 31 um, 0.02 count at its revolute joints). ``"count"`` stands for it.
STRESS = {
    "the realistic preset": {},
    "2 periods of delay, a count of noise": dict(delay_periods=2, noise_q_std="count", seed=1),
    "3 periods of delay, a count of noise": dict(delay_periods=3, noise_q_std="count", seed=2),
    "3 periods of delay, a count of noise, the bridge's offset":
        dict(delay_periods=3, noise_q_std="count", seed=2, bridge_offset=True),
}


#: Issue 24's everything-at-once case, as tests/test_gearbox_survival.py sets it on the
#: realistic preset (whose bridge offset is "auto": off for the friction-compensating
#: realistic controllers): the delay jittering between 1 and 3 periods, +-1 encoder count of
#: noise, the torque constant 5 % strong or weak (every joint).
EVERYTHING = {
    f"everything at once, torque constant {sign}5 %":
        dict(delay_periods=1, delay_jitter_periods=2, encoder_noise_counts=1,
             torque_constant_error=value, seed=24)
    for sign, value in (("+", 0.05), ("-", -0.05))
}

#: Controller settings other than the scenario files' (``--settings``): ``robust`` replaces
#: fields of the scenario's :class:`cochlea.sim.scenario.RobustOptions`, ``gains`` (per
#: study) every unit's gain vector. "shipped": the scenario files as they are.
SETTINGS = {
    "shipped": {},
    # The robust options of docs/robustness.md's serial table (ramp, adaptation dead zone
    # sized to the rattle, box, physical signs) with e's softest gains that survive there.
    "robust": {
        "robust": dict(startup_ramp=0.5, deadzone=np.array([0.3, 0.3, 0.6]), box_relative=0.5,
                       sign="physical"),
        "gains": {"serial_joint": [20, 20, 20, 0.1, 0.1, 0.1, 10, 10, 10],
                  "serial_task": [20, 20, 20, 0.3, 0.2, 0.17, 100, 100, 1]},
    },
}


def finest_count(sc) -> float:
    """The finest joint's encoder count (SI at the joint) of the scenario's robot."""
    joints = robot(sc.robot).actuated_joints(sc.system)
    return min(abs(j.ratio) * RAD_PER_COUNT for j in joints)


def oscillation_counts(result, sc) -> float:
    """The worst joint's steady oscillation, peak to peak, in encoder counts (see above)."""
    joints = robot(sc.robot).actuated_joints(sc.system)
    window = max(1, int(round(0.1 * sc.rate_hz))) | 1  # odd: centred
    worst, first = 0.0, 0
    for u in result.units:
        n = u.q.shape[1]
        count = np.array([abs(j.ratio) * RAD_PER_COUNT for j in joints[first:first + n]])
        first += n
        half = window // 2
        q = u.q if getattr(u, "true_q", None) is None else u.true_q  # the true positions
        tail = q[int(0.8 * len(q)) - half:]
        kernel = np.ones(window) / window
        for i in range(n):
            smooth = np.convolve(tail[:, i], kernel, mode="valid")
            wiggle = tail[half:len(tail) - half, i] - smooth
            worst = max(worst, float(np.ptp(wiggle) / count[i]))
    return worst


def run(study: str, changes: dict, factor: float, settings: str = "shipped") -> dict:
    sc = load_scenario(f"{study}_realistic")
    if changes.get("noise_q_std") == "count":
        changes = dict(changes, noise_q_std=finest_count(sc))
    if np.isscalar(changes.get("torque_constant_error")):
        n = robot(sc.robot).layout(sc.system, sc.space).n_joint
        changes = dict(changes, torque_constant_error=np.full(n, changes["torque_constant_error"]))
    sc = dataclasses.replace(sc, plant=dataclasses.replace(sc.plant, **changes))
    chosen = SETTINGS[settings]
    if "robust" in chosen:
        sc = dataclasses.replace(sc, robust=dataclasses.replace(sc.robust, **chosen["robust"]))
    duration = factor * sc.duration
    setups = unit_setups(dataclasses.replace(sc, duration=duration))
    if study in chosen.get("gains", {}):
        gains = np.asarray(chosen["gains"][study], float)
        setups = [dataclasses.replace(u, gains=gains) for u in setups]
    result = simulate(sc, duration, setups)
    supervisor = build_supervisor(setups, sc.system.keep_out_radius)
    rule = verdict(result, supervisor)
    tracked = [t for u in result.units for t in unit_summary(u)["tracked"].values()]
    # (With a start-up ramp the initial error is rounding, ~1e-16: no ratio to speak of.)
    ratios = [t["final_rms_error"] / t["initial_abs_error"] for t in tracked
              if t["initial_abs_error"] > 1e-9]
    floors = [t["final_rms_error"] / t["convergence_floor"] for t in tracked]
    return {"converged": sum(t["converged"] for t in tracked), "tracked": len(tracked),
            "worst_ratio": max(ratios, default=float("nan")), "worst_floor": max(floors),
            "oscillation": oscillation_counts(result, sc),
            "rule": rule["rule"], "time": rule.get("time_s"), "diverged": bool(result.diverged)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--factor", type=float, default=3.0)
    parser.add_argument("--studies", nargs="*", default=list(STUDIES))
    parser.add_argument("--cases", choices=("effects", "stress", "everything"),
                        default="effects",
                        help="each effect alone and together (default), the preset with "
                             "issue 24's delay and noise on top, or the issue's "
                             "everything-at-once case")
    parser.add_argument("--settings", choices=tuple(SETTINGS), default="shipped",
                        help="the controllers' settings (default: the scenario files')")
    parser.add_argument("--out")
    args = parser.parse_args(argv)
    cases = {"effects": CASES, "stress": STRESS, "everything": EVERYTHING}[args.cases]
    floor = args.cases == "everything"
    lines = []
    for study in args.studies:
        lines += [f"### {study}_realistic" + ("" if args.settings == "shipped"
                                                else f", settings {args.settings!r}"), "",
                  "| case | converged | worst ratio | " + ("worst floor | " if floor else "")
                  + "oscillation (counts) | supervisor |",
                  "|---|---|---|---|---|" + ("---|" if floor else "")]
        for case, changes in cases.items():
            t0 = time.perf_counter()
            r = run(study, changes, args.factor, args.settings)
            stopped = r["rule"] != "none"
            stop = f"{r['rule']} at {r['time']:.3f} s" if stopped else "none"
            wiggle = "-" if stopped else f"{r['oscillation']:.1f}"
            lines.append(f"| {case} | {r['converged']}/{r['tracked']} | "
                         + (f"{r['worst_ratio']:.3g} | " if np.isfinite(r["worst_ratio"])
                            else "- | ")
                         + (f"{r['worst_floor']:.3g} | " if floor else "")
                         + f"{wiggle} | {stop} |")
            print(lines[-1], f"({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
        lines.append("")
    text = "\n".join(lines)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
