"""``cochlea-dxl home``: the homing of a robot's prismatic joints (the parallel robot's slider, a
user arm's carriages), and the record the runtime checks before it starts.

A slider's motor has a single-turn absolute encoder on a multi-turn travel: its Present
Position counts turns while it is powered, but after a power cycle (or a REBOOT) it starts
again within one turn, so the joint coordinate is no longer known. Homing finds it again:

1. torque off, current control, Bus Watchdog on; then a slow move towards the lower hard stop
   under a velocity loop whose force never exceeds ``--force-N`` (a PI loop on the slider's
   speed, ``--speed-mm-s``, in current control);
2. the stop is where the slider has not moved (within ``STILL_COUNTS``) for ``--dwell-s``
   while the loop pushes with its full force: the raw (multi-turn) position there is the
   reference, the joint coordinate there is ``--stop-m`` (default the description's lower
   limit);
3. a random token is written into a RAM register the current-control mode does not use
   (:data:`~..homing.MARKER_ITEM_NAME`, Feedforward 2nd Gain, its address from the model's
   data): RAM returns to its defaults at power-on and after a REBOOT, exactly when the turn
   count is lost;
4. goal current 0 and torque off, whatever happened.

With several prismatic joints, each is homed in turn, in the description's order, by steps 1-4
(a joint already homed rests torque-off on its lower stop meanwhile). Then one record holds one
entry per joint (JSON, :mod:`cochlea.dynamixel.homing`, at :func:`default_record`: one file per
robot description), written atomically to a path checked writable before anything moved.

Every status packet of the move is watched (:func:`common.motion`): a hardware alert, a motor
that stops answering or answers a garbled or stale packet, a signal stop the move at once
(goal current 0, torque off on every motor that answers), and nothing is recorded, not even the
joints already homed.

The rule the runtime applies to each joint (:func:`reference_offset`): its entry is valid
while its motor still holds the token, i.e. it has not been power-cycled or rebooted since it
was homed; then ``d = stop_m + direction * ratio * (counts - raw_counts) * 2 pi / N``
(N: the model's counts per turn, 4096 on the X series),
whatever the description's ``zero_offset_deg`` says.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import random
import time
from datetime import datetime
from pathlib import Path

from ...errors import CochleaError
from ...text import number_argument
from .. import homing
from ..control_table import baud_code
from ..drives import JointDrive
from ..homing import FORMAT, MARKER_RANGE, default_record, marker_item
from . import common
from .calibrate import write_atomic

NAME = "home"
HELP = ("home every prismatic joint (the parallel robot's slider) on its lower hard stop and "
        "record it, so the runtime knows its position (until the next power cycle)")

#: The slider has stopped when its position stays within this many counts over the dwell.
STILL_COUNTS = 2
#: The homing loop's period (s): slow enough for a pseudo-terminal, fast for a 5 mm/s move.
LOOP_PERIOD_S = 0.01


# ---- the command --------------------------------------------------------------------------------


def add_arguments(p: argparse.ArgumentParser) -> None:
    common.add_robot(p)
    common.add_port(p)
    common.add_baud(p)
    p.add_argument("--record", type=Path, metavar="FILE", help="where to write the homing "
                   "record (default ~/.cochlea/homing/ROBOT.json for the shipped description, "
                   "ROBOT-STEM-HASH.json for a user's, where the runtime looks; replaced at "
                   "each homing)")
    p.add_argument("--stop-m", type=number_argument, action="append", metavar="M", help="the "
                   "prismatic joint's coordinate at its lower hard stop (default: the "
                   "description's lower limit); with several prismatic joints, once per joint "
                   "in the description's order")
    p.add_argument("--speed-mm-s", type=number_argument, default=5.0, metavar="V",
                   help="the approach speed (default 5 mm/s)")
    p.add_argument("--force-N", type=number_argument, default=10.0, metavar="F",
                   help="the most force the motor may push with (default 10 N)")
    p.add_argument("--dwell-s", type=number_argument, default=0.3, metavar="S",
                   help="how long the slider must stay still under the full force (default 0.3)")
    p.add_argument("--timeout-s", type=number_argument, metavar="S", help="give up after S seconds "
                   "(default: twice the stroke at --speed-mm-s, plus 5 s)")


def _check(args: argparse.Namespace, d, stop_m: float | None) -> tuple[float, float, float]:
    lo, hi = d.position_limits
    for option, value in (("--speed-mm-s", args.speed_mm_s), ("--force-N", args.force_N),
                          ("--dwell-s", args.dwell_s)):
        if not (math.isfinite(value) and value > 0):
            raise CochleaError(f"{option}: expected a finite number > 0, got {value}")
    speed = args.speed_mm_s * 1e-3
    if speed > 0.06:
        raise CochleaError(f"--speed-mm-s {args.speed_mm_s}: expected at most 60 mm/s (the "
                           "slider's velocity limit); homing is slow")
    if args.force_N > d.effort_limit:
        raise CochleaError(f"--force-N {args.force_N}: expected at most {d.name}'s force "
                           f"limit, {d.effort_limit:g} N")
    stop = lo if stop_m is None else stop_m
    if not (math.isfinite(stop) and lo - 0.05 <= stop <= hi):
        raise CochleaError(f"--stop-m {stop_m}: expected a coordinate near {d.name}'s travel "
                           f"[{lo:g}, {hi:g}] m")
    timeout = args.timeout_s
    if timeout is None:
        timeout = 2.0 * (hi - lo) / speed + 5.0
    elif not (math.isfinite(timeout) and timeout > 0):
        raise CochleaError(f"--timeout-s: expected a finite number > 0, got {timeout}")
    return stop, speed, timeout


def run(args: argparse.Namespace) -> int:
    baud_code(args.baud)
    drives = common.load_drives(args)
    sliders = [d for d in drives if d.type == "prismatic"]
    if not sliders:
        raise CochleaError(f"--robot {args.robot}: it has no slider to home (the parallel "
                           "robot has; a serial arm has one where a joint is prismatic)")
    stops = args.stop_m if args.stop_m is not None else [None] * len(sliders)
    if len(stops) != len(sliders):
        raise CochleaError(f"--stop-m: given {len(stops)} time(s) for {len(sliders)} prismatic "
                           "joint(s) (" + ", ".join(d.name for d in sliders) + "): give it once "
                           "per joint, in that order, or leave it out (each joint's lower limit)")
    # Every joint's options checked before the port opens.
    checked = [(d, *_check(args, d, stop)) for d, stop in zip(sliders, stops)]
    record_path = _record_path(args)  # before anything moves: a move is 10 s or more
    made_for = homing.description_id(args.robot, args.description)
    tokens = random.SystemRandom()
    entries = []
    with common.Bus(args.port, args.baud) as bus:
        common.check_chain(bus, sliders, torque=True)  # nothing written yet
        bus.names = {x.id: x for x in drives}
        # One joint after the other, each with its own watched, force-limited move; any stop:
        # torque off on every motor and no record at all (an older one no longer matches the
        # markers of the joints already homed, so the runtime refuses it).
        for d, stop, speed, timeout in checked:
            marker = tokens.randint(*MARKER_RANGE)
            try:
                with common.motion(bus, [d], drives, f"the homing of {d.name}"):
                    result = _seek_stop(bus, d, args, speed, timeout, marker)
            finally:
                with contextlib.suppress(common.BusError):
                    bus.write(d.id, d.spec.item("Bus Watchdog"), 0)
            entries.append({"joint": d.name, "motor_id": d.id, "model": d.spec.name,
                            "raw_counts": int(result), "stop_m": stop,
                            "direction": d.direction, "ratio_m_per_rad": d.ratio,
                            "marker_address": marker_item(d).address, "marker": marker})
            if len(checked) > 1:
                print(f"  {d.name} (ID {d.id}) on its stop at raw position {result} counts = "
                      f"{stop:g} m; torque off", flush=True)
    record = {"format": FORMAT, "robot": args.robot, "description": made_for,
              "port": args.port, "date": datetime.now().isoformat(timespec="seconds"),
              "joints": entries}
    with common.finishing():  # a signal now would not stop the record half-reported
        _write_record(record_path, record)
        said = "; ".join(f"{e['joint']} (ID {e['motor_id']}) on its stop at raw position "
                         f"{e['raw_counts']} counts = {e['stop_m']:g} m" for e in entries)
        print(f"homed: {said}; record {record_path}; torque off", flush=True)
    return 0


def _record_path(args: argparse.Namespace) -> Path:
    """Where the record goes, checked writable (:func:`common.check_output`) before anything
    moves; the default's folder (~/.cochlea/homing) is created, a --record's must exist."""
    if args.record is not None:
        return common.check_output(args.record, "--record")
    path = default_record(args.robot, args.description)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CochleaError(f"--record (default) {path}: cannot create its folder "
                           f"({exc.strerror or exc}); give --record FILE; nothing moved") from None
    return common.check_output(path, "--record (default)")


def _write_record(path: Path, record: dict) -> None:
    try:
        common.check_output(path, "--record", then="")  # again: it may have changed meanwhile
        write_atomic(path, json.dumps(record, indent=2) + "\n")
    except (OSError, CochleaError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise CochleaError(f"--record {path}: cannot write it ({why}); the slider was homed "
                           "but nothing records it: home again with another --record") from None


def _window_said(d: JointDrive, window: list, start_counts: int, counts: int,
                 args: argparse.Namespace) -> str:
    """What the last dwell's samples showed, for the error of a homing that found no stop: how
    far the slider went, how still it stayed, whether the loop pushed with its full force, and
    how often it sampled (a loaded host's loop samples rarely)."""
    moved_mm = (counts - start_counts) * d.q_per_count * 1e3
    if not window:
        return f"moved {moved_mm:.1f} mm, no sample"
    positions = [c for _, c, _ in window]
    full = sum(1 for _, _, f in window if f)
    span = window[-1][0] - window[0][0]
    return (f"moved {moved_mm:.1f} mm; over its last {span:.2f} s: {len(window)} samples, "
            f"positions within {max(positions) - min(positions)} counts (still: at most "
            f"{STILL_COUNTS} over --dwell-s {args.dwell_s:g}), {full} of them at the full "
            f"{args.force_N:g} N")


def _seek_stop(bus: common.Bus, d: JointDrive, args: argparse.Namespace, speed: float,
               timeout: float, marker: int) -> int:
    """Drive the slider down at ``speed`` (m/s) under a force limit until it rests on its
    stop; leave ``marker`` in the motor and return the stop's raw position (counts)."""
    limit = abs(float(d.goal_current_lsb(args.force_N)))
    # Towards the stop: the joint's negative sense (the lower limit).
    kp = 0.25 * args.force_N / speed  # N per m/s: a quarter of the force at rest
    ki = args.force_N / (0.5 * speed)  # N per m: the full force after 0.5 s at rest
    bus.current_mode_at_rest(d)
    bus.write(d.id, d.spec.item("Bus Watchdog"), 5)  # 100 ms: the motor stops if we do
    start_counts = bus.position(d)
    bus.write(d.id, d.spec.item("Torque Enable"), 1)
    print(f"homing {d.name} (ID {d.id}): down at {speed * 1e3:g} mm/s, at most "
          f"{args.force_N:g} N", flush=True)
    integral, window = 0.0, []
    t0 = last = time.perf_counter()
    stroke = d.position_limits[1] - d.position_limits[0] + 0.01
    goal_current = d.spec.item("Goal Current")
    counts = start_counts
    while True:
        now = time.perf_counter()
        if now - t0 > timeout:
            raise common.BusError(f"no hard stop found in {timeout:g} s "
                                  f"({_window_said(d, window, start_counts, counts, args)}): "
                                  "check that the slider moves down, its direction in the "
                                  "description, and --stop-m")
        _, lsb, counts = bus.present(d)  # one READ, its Realtime Tick checked for staleness
        if abs((counts - start_counts) * d.q_per_count) > stroke:
            raise common.BusError(f"the slider travelled more than its stroke ({stroke:g} m) "
                                  "without meeting a stop: check its direction and the stop")
        v = float(d.qd(lsb))
        error = -speed - v
        dt = min(now - last, 0.1)
        last = now
        integral = min(max(integral + ki * error * dt, -args.force_N), args.force_N)
        force = min(max(kp * error + integral, -args.force_N), args.force_N)
        goal = int(min(max(float(d.goal_current_lsb(force)), -limit), limit))
        bus.write(d.id, goal_current, goal)
        window.append((now, counts, force <= -0.99 * args.force_N))
        # The window spans the dwell from its first sample: the newest sample at or before
        # now - dwell stays as its start, so a loop slowed by a loaded host (samples 30 ms or
        # more apart) still sees a whole dwell rather than never enough of one.
        while len(window) > 1 and window[1][0] <= now - args.dwell_s:
            window.pop(0)
        positions = [c for _, c, _ in window]
        if (len(window) >= 3 and window[-1][0] - window[0][0] >= args.dwell_s
                and max(positions) - min(positions) <= STILL_COUNTS
                and all(full for _, _, full in window)):
            bus.write(d.id, marker_item(d), marker)
            return sorted(positions)[len(positions) // 2]
        time.sleep(max(0.0, LOOP_PERIOD_S - (time.perf_counter() - now)))
