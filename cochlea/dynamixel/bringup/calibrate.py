"""``cochlea-dxl calibrate``: measure each motor's ``zero_offset_deg`` and ``direction`` by hand,
torque off, and write them into a new description; or (``--torque-fit``) record current against
a known static torque and fit ``torque = a I + b`` for a placeholder fit.

Guided calibration, per joint (docs/hardware_calibration.md, "Calibration"):

1. the user puts the joint in its reference pose (:data:`REFERENCE`, or ``--reference``) and
   presses Enter: the motor's Present Position ``p0`` is read;
2. the user moves the joint a little in its positive sense and presses Enter: the sign of the
   motor's change is ``direction``;
3. ``zero_offset = theta0 - q_ref / (direction * ratio)`` with ``theta0 = p0 * 2 pi / N``, N
   the motor's counts per turn (its model's data: 4096 on the X series) (inverting
   ``q = direction * ratio * (theta - zero_offset)``, :mod:`..drives`).

Every motor of the description is pinged and its torque turned off before the first prompt; the
new description is the old text with only the two values of each calibrated motor replaced
(comments kept), loaded back and compared before it is renamed into place.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import math
import re
import sys
from datetime import datetime
from pathlib import Path

import numpy as np

from ... import files
from ...errors import CochleaError
from ...resources import ROBOTS_DIR, shipped_file
from ...robots import ROBOTS
from ...robots import robot as robot_adapter
from ...text import comment, decimal, number_argument
from ..control_table import baud_code
from ..drives import Fit, JointDrive, joint_drives
from . import common

NAME = "calibrate"
HELP = ("measure zero_offset_deg and direction of each motor by hand (torque off) and write a "
        "new description; --torque-fit: fit a motor's current-to-torque line")

#: Each robot's reference pose (joint coordinate, SI) and how to set it by hand: a pose a lab
#: can set with a ruler or a set square, inside the joint limits (the adapter's
#: ``calibration_reference``; ``"*"``: every joint not named). A description may give its own
#: (``calibration_pose_deg``, ``positive_direction`` of an arm); a user's description that
#: gives none gets the adapter's defaults (:meth:`~cochlea.robots.adapter.RobotAdapter.
#: calibration_references`).
REFERENCE = {name: r.calibration_reference for name, r in ROBOTS.items()}
#: The positive sense of each kind of joint, as the user sees it (``positive_direction``).
POSITIVE = {name: r.positive_direction for name, r in ROBOTS.items()}


#: A temporary name beside the file to write, renamed to it once written and synced, removed
#: on failure: a reader sees no file or the whole one (cochlea.files).
atomic_path = files.atomic_path


def write_atomic(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def ask(prompt: str) -> str:
    """One answer from the user (stdin): tests replace this function."""
    print(prompt, end=" ", flush=True)
    line = sys.stdin.readline()
    if not line:
        raise CochleaError("stdin closed before the calibration was finished: nothing written")
    return line.strip()


# ---- options ------------------------------------------------------------------------------------


def add_arguments(p: argparse.ArgumentParser) -> None:
    common.add_robot(p)  # --robot, and --description: the description to calibrate
    common.add_port(p)
    common.add_baud(p)
    p.add_argument("--out", type=Path, metavar="FILE", help="the new description (default: "
                   "NAME.calibrated.toml beside --description, or in the current folder for "
                   "the shipped one); never overwritten")
    p.add_argument("--in-place", action="store_true", help="replace --description itself")
    p.add_argument("--joints", metavar="NAMES", help="only these joints, e.g. arm1.link1,"
                   "arm1.link2 (default: all)")
    p.add_argument("--reference", action="append", default=[], metavar="JOINT=VALUE",
                   help="the reference pose of JOINT in deg (m for the slider) instead of the "
                        "documented one, e.g. for a jig (repeatable)")
    p.add_argument("--min-motion-deg", type=number_argument, default=5.0, metavar="DEG",
                   help="the smallest motor motion accepted when checking the direction "
                        "(default 5)")
    t = p.add_argument_group("torque fit (--torque-fit)")
    t.add_argument("--torque-fit", action="store_true", help="instead: hold --joint against a "
                   "lever on a scale, step the current, type the scale's force, fit the line")
    t.add_argument("--joint", help="the joint whose motor is fitted")
    t.add_argument("--lever-m", type=number_argument, metavar="M",
                   help="the lever: from the joint's "
                   "axis to where it presses on the scale, m")
    t.add_argument("--currents-mA", metavar="LIST", help="the current steps, mA (default: six "
                   "from 20 to 70 %% of the current the joint's torque limit needs)")
    t.add_argument("--csv", type=Path, metavar="FILE", help="the samples (required with "
                   "--torque-fit; never overwritten)")


def _finite(value: float, option: str, low: float = 0.0) -> float:
    if not (math.isfinite(value) and value > low):
        raise CochleaError(f"{option}: expected a finite number > {low:g}, got {value}")
    return value


def _new_file(path: Path, option: str) -> Path:
    """A new file the command may write: refused (exit 2) before anything moves if it exists,
    or its folder is missing, not a folder or not writable (:func:`common.check_output`)."""
    return common.check_output(path, option, new=True)


def _out_path(args: argparse.Namespace) -> Path:
    if args.in_place:
        if args.description is None:
            raise CochleaError("--in-place: expected --description FILE too (the shipped "
                               "description is the package's; calibrate a copy)")
        if args.out is not None:
            raise CochleaError("--in-place and --out: expected one of them")
        if not args.description.is_file():
            raise CochleaError(f"--description {args.description}: not a file")
        # Replaced by a rename in its folder: that folder must take a new file.
        return common.check_output(args.description, "--in-place --description")
    if args.out is not None:
        return _new_file(args.out, "--out")
    source = args.description if args.description is not None else Path(f"{args.robot}.toml")
    return _new_file(source.with_name(f"{source.stem}.calibrated.toml"), "--out (default)")


def _select(drives: list[JointDrive], names: str | None, option: str) -> list[JointDrive]:
    if names is None:
        return list(drives)
    by_name = {d.name: d for d in drives}
    chosen = []
    for name in (n.strip() for n in names.split(",")):
        if name not in by_name:
            raise CochleaError(f"{option}: no joint {name!r}; expected some of "
                               f"{', '.join(by_name)}")
        if by_name[name] not in chosen:
            chosen.append(by_name[name])
    if not chosen:
        raise CochleaError(f"{option}: expected at least one joint name")
    return chosen


def _references(args: argparse.Namespace, drives: list[JointDrive]) -> dict[str, tuple]:
    """Joint name -> (q_ref in SI, how to set it): the description's or the robot's
    documented pose, or --reference's."""
    adapter = robot_adapter(args.robot)
    system = adapter.load(args.description)
    every = adapter.calibration_references(system, _is_shipped(args))
    refs = {d.name: every[d.name] for d in drives}
    by_name = {d.name: d for d in drives}
    for text in args.reference:
        name, sep, value = text.partition("=")
        d = by_name.get(name.strip())
        if not sep or d is None:
            raise CochleaError(f"--reference {text!r}: expected JOINT=VALUE with JOINT one of "
                               f"{', '.join(by_name)}")
        number = decimal(value)  # float() would take 1_0 (10 deg) and other scripts' digits
        if number is None:
            number = math.nan
        if not math.isfinite(number):
            raise CochleaError(f"--reference {text!r}: expected a finite number of "
                               f"{'deg' if d.type == 'revolute' else 'm'}")
        q = math.radians(number) if d.type == "revolute" else number
        lo, hi = d.position_limits
        if not lo <= q <= hi:
            raise CochleaError(f"--reference {text!r}: outside the joint's limits")
        refs[d.name] = (q, f"your reference pose, {value.strip()} "
                           f"{'deg' if d.type == 'revolute' else 'm'}")
    return refs


def run(args: argparse.Namespace) -> int:
    baud_code(args.baud)
    if args.torque_fit:
        return _torque_fit(args)
    if args.joint is not None or args.lever_m is not None or args.csv is not None:
        raise CochleaError("--joint, --lever-m and --csv belong to --torque-fit")
    _finite(args.min_motion_deg, "--min-motion-deg")
    out = _out_path(args)
    drives = common.load_drives(args)
    chosen = _select(drives, args.joints, "--joints")
    refs = _references(args, chosen)
    text = (args.description.read_text() if args.description is not None
            else _shipped(args.robot).read_text())
    with common.Bus(args.port, args.baud) as bus:
        # No motor in alert (docs/hardware.md); nothing written yet: nothing to undo.
        common.check_chain(bus, drives, torque=True)
        bus.names = {d.id: d for d in drives}
        try:
            failed = bus.torque_off(drives)
            if failed:
                raise common.BusError(f"torque off not confirmed by {', '.join(failed)}: "
                                      "calibrate only with every motor free")
            # Every status packet watched: an alert, a lost or garbled motor stops it.
            with common.motion(bus, [], drives, "the calibration"):
                results = {d.id: _calibrate_joint(bus, d, refs[d.name], args) for d in chosen}
        finally:
            bus.torque_off(drives)
    note = (f"calibrated {datetime.now().isoformat(timespec='seconds')} on {args.port} "
            "(cochlea-dxl calibrate)")
    new = edit_description(text, results, note, path=out)
    # Again: the path may have changed while the user calibrated (never replace a non-file).
    common.check_output(out, "--in-place --description" if args.in_place else "--out",
                        new=not args.in_place, then="")
    with common.finishing():  # a signal now would not stop the file half-reported
        _write_checked(new, out, args.robot, drives, results)
        for d in chosen:
            direction, offset = results[d.id]
            print(f"{d.name} (ID {d.id}): direction {direction:+d}, zero_offset_deg "
                  f"{offset:.4f}")
        print(f"written: {out}", flush=True)
    return 0


def _shipped(robot: str) -> Path:
    return shipped_file(ROBOTS_DIR, robot)


def _is_shipped(args: argparse.Namespace) -> bool:
    """Whether the calibrated description is the robot's shipped one or a copy of it (its
    documented reference pose and positive sense apply)."""
    adapter = robot_adapter(args.robot)
    return adapter.is_shipped(adapter.load(args.description))


def _positive(args: argparse.Namespace, joint: str) -> str:
    adapter = robot_adapter(args.robot)
    return adapter.calibration_positive(adapter.load(args.description), joint,
                                        _is_shipped(args))


def _calibrate_joint(bus: common.Bus, d: JointDrive, ref: tuple, args) -> tuple[int, float]:
    q_ref, how = ref
    unit = "deg" if d.type == "revolute" else "m"
    shown = math.degrees(q_ref) if d.type == "revolute" else q_ref
    answer = ask(f"{d.name} (ID {d.id}): move it to its reference pose, {how} "
                 f"({d.name} = {shown:g} {unit}); Enter when there (q quits):")
    if answer.lower() == "q":
        raise CochleaError("calibration stopped by the user: nothing written")
    p0 = bus.position(d)
    rad_per_count = d.spec.rad_per_count  # the model's (joint_drives refused it unsourced)
    need = args.min_motion_deg / math.degrees(rad_per_count)
    for _ in range(3):
        answer = ask(f"{d.name}: now move it a little in its positive sense ("
                     f"{_positive(args, d.name)}), at least {args.min_motion_deg:g} deg at the "
                     "motor, and hold it; Enter (q quits):")
        if answer.lower() == "q":
            raise CochleaError("calibration stopped by the user: nothing written")
        delta = bus.position(d) - p0
        if abs(delta) >= need:
            break
        print(f"{d.name}: the motor moved {delta * math.degrees(rad_per_count):.2f} deg only; "
              "move it further", flush=True)
    else:
        raise CochleaError(f"{d.name} (ID {d.id}): the motor did not move {args.min_motion_deg:g}"
                           " deg in three tries: is it the right joint, and free? Nothing "
                           "written")
    direction = 1 if delta > 0 else -1
    theta0 = p0 * rad_per_count
    offset = math.degrees(theta0 - q_ref / (direction * d.ratio))
    if d.type == "revolute":  # any turn will do: the bridge unwraps revolute joints
        offset = (offset + 180.0) % 360.0 - 180.0
    return direction, offset


# ---- the description's text ---------------------------------------------------------------------

_HEADER = re.compile(r"^\s*\[\[?\s*([^\]]+?)\s*\]\]?\s*(#.*)?$")
_KEY = re.compile(r"^(\s*)(id|direction|zero_offset_deg)(\s*=\s*)([^#]*?)(\s*)(#.*)?$")


def edit_description(text: str, results: dict[int, tuple[int, float]], note: str,
                     path: Path | str = "the description") -> str:
    """``text`` with ``direction`` and ``zero_offset_deg`` of each motor ID in ``results``
    replaced (``(direction, zero_offset_deg)``), found by key in its ``[..motor]`` table,
    everything else kept; the changed lines carry ``note`` as their comment."""
    note = comment(note)  # one line, whatever --port held
    lines = text.splitlines(keepends=True)
    tables, current = {}, None
    for i, line in enumerate(lines):
        header = _HEADER.match(line)
        if header:
            current = {"line": i} if header.group(1).split(".")[-1].strip() == "motor" else None
            continue
        key = _KEY.match(line)
        if current is not None and key:
            current[key.group(2)] = i
            if key.group(2) == "id":
                try:
                    tables[int(key.group(4))] = current
                except ValueError:
                    pass
    inserts = []
    for motor_id, (direction, offset) in results.items():
        table = tables.get(motor_id)
        if table is None:
            raise CochleaError(f"{path}: no [..motor] table with 'id = {motor_id}' written as "
                               "its own line; expected one per motor to edit")
        for key, value in (("direction", f"{direction}"), ("zero_offset_deg", f"{offset:.6f}")):
            if key in table:
                m = _KEY.match(lines[table[key]])
                end = "\r\n" if lines[table[key]].endswith("\r\n") else "\n"
                lines[table[key]] = (f"{m.group(1)}{key}{m.group(3)}{value}"
                                     f"{m.group(5) or '  '}# {note}{end}")
            else:
                indent = _KEY.match(lines[table["id"]]).group(1)
                inserts.append((table["id"] + 1, f"{indent}{key} = {value}  # {note}\n"))
    for at, line in sorted(inserts, reverse=True):
        lines.insert(at, line)
    ids = ", ".join(str(i) for i in sorted(results))
    return f"# direction and zero_offset_deg of motor IDs {ids} {note}\n" + "".join(lines)


def _write_checked(text: str, out: Path, robot: str, old: list[JointDrive],
                   results: dict[int, tuple[int, float]]) -> None:
    """Write ``text`` to ``out`` only once it loads back with exactly the new values and every
    other motor as it was."""
    with atomic_path(out) as tmp:
        tmp.write_text(text)
        try:
            new = joint_drives(robot, tmp)
        except CochleaError as exc:
            raise CochleaError(f"the edited description does not load ({exc}): nothing "
                               "written") from None
        for a, b in zip(old, new):
            want = results.get(a.id)
            direction = want[0] if want else a.direction
            offset = math.radians(want[1]) if want else a.zero_offset
            if (b.id, b.direction) != (a.id, direction) or abs(b.zero_offset - offset) > 1e-7:
                raise CochleaError(f"the edited description reads {b.name} back wrongly: "
                                   "nothing written")


# ---- torque fit ---------------------------------------------------------------------------------


def _torque_fit(args: argparse.Namespace) -> int:
    if args.joint is None or args.lever_m is None or args.csv is None:
        raise CochleaError("--torque-fit: expected --joint NAME, --lever-m M and --csv FILE")
    if args.out is not None or args.in_place or args.joints or args.reference:
        raise CochleaError("--torque-fit writes a CSV and prints the fit: --out, --in-place, "
                           "--joints and --reference belong to the calibration of offsets")
    lever = _finite(args.lever_m, "--lever-m")
    csv_path = _new_file(args.csv, "--csv")
    drives = common.load_drives(args)
    (d,) = _select(drives, args.joint, "--joint")
    if d.type != "revolute":
        raise CochleaError(f"--joint {d.name}: the torque fit is for a revolute joint's motor "
                           "(the lever on its output shaft)")
    limit_mA = d.current_limit_lsb * d.spec.current_unit_mA
    if args.currents_mA is None:
        top = 1000.0 * float(d.fit.current(d.effort_limit))
        currents = [top * k for k in np.linspace(0.2, 0.7, 6)]
    else:
        currents = [decimal(v) for v in args.currents_mA.split(",")]
        if None in currents:
            currents = [math.nan]
        if len(currents) < 2 or not all(math.isfinite(c) and 0 < c <= limit_mA
                                        for c in currents):
            raise CochleaError(f"--currents-mA {args.currents_mA!r}: expected two or more "
                               f"currents in (0, {limit_mA:.0f}] mA (the joint's Current "
                               "Limit), e.g. 200,400,600")
    samples = []
    with common.Bus(args.port, args.baud) as bus:
        common.check_chain(bus, [d], torque=True)  # nothing written yet: nothing to undo
        bus.names = {x.id: x for x in drives}
        # Every status packet watched; any stop: torque off on every motor, no CSV.
        with common.motion(bus, [d], drives, f"the torque fit of {d.name}"):
            _push_and_measure(bus, d, lever, currents, samples)
    common.check_output(csv_path, "--csv", new=True, then="")  # again: it may have changed
    if len(samples) < 2:
        raise CochleaError("the torque fit needs two samples or more: nothing written")
    amps = np.array([s[1] for s in samples]) * 1e-3  # the present current the motor measured
    torque = np.array([s[4] for s in samples])
    a, b = np.polyfit(amps, torque, 1)
    residual = float(np.sqrt(np.mean((a * amps + b - torque) ** 2)))
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["goal_current_mA", "present_current_mA", "force_N", "lever_m",
                     "torque_Nm"])
    writer.writerows(samples)
    with common.finishing():  # a signal now would not stop the CSV half-reported
        with atomic_path(csv_path) as tmp:
            tmp.write_text(buffer.getvalue())
        x, y = d.motor.fit.x, d.motor.fit.y
        # The description's units per SI unit, from the fit's own conversion (a = b = 1 there).
        unit = Fit.from_description(dataclasses.replace(d.motor.fit, a=1.0, b=1.0))
        a_d, b_d = a / unit.a, b / unit.b
        print(f"{d.name} (ID {d.id}): torque = {a:.4f} N m/A * I {b:+.4f} N m from {len(samples)} "
              f"samples (RMS residual {residual:.2e} N m); samples: {csv_path}")
        # source = "measured": cochlea-identify then trusts this line (it fits only placeholders).
        print(f"for the description: fit = {{ a = {a_d:.6g}, b = {b_d:.6g}, x = \"{x}\", "
              f"y = \"{y}\", source = \"measured\" }}")
    return 0


def _push_and_measure(bus: common.Bus, d: JointDrive, lever: float, currents: list[float],
                      samples: list[tuple]) -> None:
    """The torque fit's bench steps: each current held against the scale, the user's force
    read; ``samples`` keeps what was measured even when the user stops early."""
    # No Bus Watchdog: the current must hold while the user reads the scale.
    bus.current_mode_at_rest(d)
    ask(f"{d.name} (ID {d.id}): fix a lever of {lever:g} m on it pressing on a scale (the "
        "joint must not move); the motor will push with each current in turn. Enter:")
    bus.write(d.id, d.spec.item("Torque Enable"), 1)
    for milliamps in currents:
        lsb = int(round(milliamps / d.spec.current_unit_mA))
        bus.write(d.id, d.spec.item("Goal Current"), lsb)
        answer = ask(f"{d.name}: {lsb * d.spec.current_unit_mA:.0f} mA; the force on the "
                     "scale in N (q stops):")
        if answer.lower() == "q":
            break
        try:
            force = float(answer)
        except ValueError:
            force = math.nan
        if not math.isfinite(force):
            raise CochleaError(f"the force {answer!r}: expected a number of N; nothing "
                               "written")
        present = bus.present(d)[0] * d.spec.current_unit_mA  # its Realtime Tick checked
        samples.append((lsb * d.spec.current_unit_mA, present, force, lever, force * lever))
