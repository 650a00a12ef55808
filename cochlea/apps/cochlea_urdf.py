"""``cochlea-urdf``: a URDF's serial chain to a cochlea description (``import``), and a
description's arm back to a URDF (``export``). User mistakes -- a file that cannot be a serial
chain, an unknown motor, a missing file -- print one line and exit with EXIT_USER_ERROR.

From a URDF to a running controller (docs/models.md, "URDF in and out")::

    cochlea-urdf import arm.urdf --out arm.toml --scenario-out starter.toml
    cochlea-run --robot serial --space joint --scenario starter.toml --realtime off
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from ..console import OneLineParser
from ..errors import EXIT_USER_ERROR, CochleaError
from ..robots.urdf import export_urdf, import_urdf, load_chain, starter_scenario
from ..text import decimal, integer, toml_string
from . import outputs


def _ids(text: str | None) -> list[int] | None:
    if text is None:
        return None
    ids = [integer(x) for x in text.split(",")]  # ASCII digits only ("1_0": no), none empty
    if None in ids:
        raise CochleaError(f"--ids {text!r}: comma-separated integers, e.g. 1,2,3")
    return ids


def _metres(text: str | None, option: str) -> float | None:
    if text is None:
        return None
    value = decimal(text)  # float() would take "1_0" (10 m), "nan" and other scripts' digits
    if value is None:
        raise CochleaError(f"{option} {text!r}: a decimal number of metres, e.g. 0.05")
    return value


def _check(path: Path, option: str, suffix: str) -> None:
    """Before anything is written: an output whose folder is missing or not writable, or that
    exists as anything but a regular file, is refused (one line, exit 2)."""
    outputs.check_output_file(path, option, suffix)


def _write(path: Path, text: str) -> None:
    """Atomically: a reader (or a crash) sees the old file or the whole new one."""
    try:
        outputs.write_text_atomic(path, text)
    except OSError as exc:
        raise CochleaError(f"cannot write {path}: {exc.strerror or exc}") from None


def _relative(target: Path, start: Path) -> str:
    """``target`` relative to the folder ``start`` (as a scenario names its description)."""
    try:
        return Path(os.path.relpath(target.resolve(), start.resolve())).as_posix()
    except ValueError:  # another drive (Windows)
        return target.resolve().as_posix()


def _import(args: argparse.Namespace) -> None:
    if args.out.suffix != ".toml":  # a bare name means a shipped description to the loaders
        raise CochleaError(f"--out {args.out}: a description file name ending in .toml")
    _check(args.out, "--out", ".toml")
    if args.scenario_out is not None:
        _check(args.scenario_out, "--scenario-out", ".toml")
    if args.scenario_out is not None:  # the starter names the description: a TOML string
        try:
            toml_string(_relative(args.out, args.scenario_out.parent))
        except ValueError as exc:
            raise CochleaError(f"--out {args.out}: {exc}") from None
    outputs.refuse_overlap([("--out", args.out)]
                           + ([("--scenario-out", args.scenario_out)]
                              if args.scenario_out is not None else []),
                           [("URDF", args.urdf)])
    # Parsed here, not by argparse, so that a mistake is one line like every other refusal.
    ids, radius = _ids(args.ids), _metres(args.keep_out_radius_m, "--keep-out-radius-m")
    result = import_urdf(args.urdf, base=args.base, tip=args.tip, motors=args.motor,
                         ids=ids, transmissions=args.transmission, keep_out_radius=radius)
    for snap in result.snaps:
        print(f"snapped: {snap}")
    for note in result.notes:
        print(f"note: {note}")
    _write(args.out, result.text)
    arm = result.system.arms[0]
    print(f"wrote {args.out}: {len(arm.links)} joints ("
          + ", ".join(link.joint.name or link.name for link in arm.links) + ")")
    if args.scenario_out is not None:
        scenario = args.scenario_out
        system = load_chain(args.out)
        _write(scenario, starter_scenario(system, _relative(args.out, scenario.parent)))
        print(f"wrote {scenario}: run it with cochlea-run --robot serial --space joint "
              f"--scenario {scenario}")


def _export(args: argparse.Namespace) -> None:
    system = load_chain(args.description)
    arm = system.arm(args.arm) if args.arm else system.arms[0]
    _check(args.out, "--out", ".urdf")
    outputs.refuse_overlap([("--out", args.out)], [("description", system.path)])
    _write(args.out, export_urdf(system, arm))
    print(f"wrote {args.out}: arm {arm.name!r}, {len(arm.links)} joints")


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(
        prog="cochlea-urdf",
        description="Import a URDF's serial chain as a cochlea robot description, or export a "
                    "description's arm as a URDF (docs/models.md, \"URDF in and out\").")
    sub = parser.add_subparsers(dest="command", required=True)
    imp = sub.add_parser("import", help="URDF -> description (and a starter scenario)")
    imp.add_argument("urdf", type=Path, help="the URDF file")
    imp.add_argument("--out", type=Path, required=True, help="the description to write (.toml)")
    imp.add_argument("--base", metavar="LINK", help="the chain's base link (default: the root)")
    imp.add_argument("--tip", metavar="LINK",
                     help="the chain's tip link (default: follow the only branch that moves; "
                          "needed where the tree branches)")
    imp.add_argument("--motor", action="append", metavar="MODEL|JOINT=MODEL",
                     help="the Dynamixel of every joint (MODEL) or of one joint (JOINT=MODEL, "
                          "the URDF joint name); repeatable; default XM540-W270")
    imp.add_argument("--ids", metavar="1,2,..",
                     help="the motors' Dynamixel IDs from base to tip (default: 1..n)")
    imp.add_argument("--transmission", action="append", metavar="JOINT=KIND:SIZE",
                     help="a prismatic joint's transmission (required where the URDF has no "
                          "<transmission> with a mechanicalReduction for it): KIND lead_screw "
                          "(SIZE: the lead, m per motor turn), pinion or belt (SIZE: the pitch "
                          "radius, m), ratio (SIZE: m per motor rad); repeatable")
    imp.add_argument("--keep-out-radius-m", metavar="R",
                     help="write keep_out_radius_m = R (m), the keep-out circle around the "
                          "world origin (default: none written, no keep-out circle)")
    imp.add_argument("--scenario-out", type=Path, metavar="FILE",
                     help="also write a gentle joint-space starter scenario for cochlea-run")
    exp = sub.add_parser("export", help="description -> URDF")
    exp.add_argument("description", help="the description (a .toml path, or a shipped name)")
    exp.add_argument("--out", type=Path, required=True, help="the URDF to write")
    exp.add_argument("--arm", help="which arm (default: the first)")
    args = parser.parse_args(argv)
    try:
        (_import if args.command == "import" else _export)(args)
    except CochleaError as exc:
        print(f"cochlea-urdf: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("cochlea-urdf: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
