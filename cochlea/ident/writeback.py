"""Identified parameters written back into a robot description, in the description's own keys.

Base parameters are combinations of the full ones (``beta = from_full @ phi``), so a
description can only take a full vector. Without a physically consistent fit it is the full
vector closest to the description's nominal one that reproduces the identified base
parameters exactly, closest in a metric relative to each parameter's size::

    phi = phi_nom + S^2 A^T (A S^2 A^T)^-1 (beta - A phi_nom),   A = from_full,
    S = diag(max(|phi_nom_i|, 1e-3 max |phi_nom| of the same SI unit))

so a 3.4e-3 kg m^2 armature and a 4e-5 kg m^2 link inertia move by comparable fractions of
themselves (the plain pseudo-inverse would move both by the same kg m^2). Parameters that
never enter the dynamics (``A``'s zero columns: a planar arm's Ixx, Iyy) keep their values.

The file is edited line by line: each value is replaced on its own line, by key, keeping the
line's comment and every other line of the original; a comment naming the logs and the date
goes on top. The result is loaded with the description's own validation before it replaces
anything; a file that does not validate (a mass or an inertia about the centre of mass that
the combination made non-physical) is refused with a pointer to ``--physical``.
"""

from __future__ import annotations

import datetime
import os
import re
from pathlib import Path

import numpy as np

from ..errors import CochleaError
from ..robots import RobotModel, robot
from ..text import comment, toml_string
from . import files

_HEADER = re.compile(r"^\s*(\[\[?)\s*([A-Za-z0-9_.-]+)\s*\]\]?\s*(#.*)?$")
_KEY = re.compile(r"^(\s*)([A-Za-z0-9_-]+)(\s*=\s*)(.*?)(\s*#.*)?$")


class WriteBackError(CochleaError):
    """The identified values cannot be written into the description."""


class TargetExists(WriteBackError, files.OutputRefused):
    """The new description's name is taken: refused before fitting, never overwritten."""


def closest_full(model: RobotModel, beta: np.ndarray) -> np.ndarray:
    """The full parameter vector nearest the nominal one (relative metric, see the module
    docstring) whose base parameters are exactly ``beta``."""
    A = model.parameters.from_full
    full = model.full_parameters
    nominal = np.asarray(full.nominal, float)
    scale = np.abs(nominal).copy()
    for unit in set(full.si_units):
        same = np.array([u == unit for u in full.si_units])
        floor = 1e-3 * max(np.abs(nominal[same]).max(), 1e-12)
        scale[same] = np.maximum(scale[same], floor)
    AS = A * scale
    step = np.linalg.lstsq(AS, beta - A @ nominal, rcond=None)[0]  # min-norm in scaled space
    return nominal + scale * step


def key_lines(lines: list[str]) -> dict[tuple, int]:
    """Where each ``key = value`` of a TOML text sits: ``{path: line index}``, the path with
    the index of every array of tables (``("arm", 0, "link", 2, "joint", "armature_kgm2")``).
    Inline tables and multi-line values are not entered (they are never edited here)."""
    counts: dict[tuple, int] = {}
    current: dict[str, int] = {}
    table: tuple = ()
    where: dict[tuple, int] = {}
    for number, line in enumerate(lines):
        header = _HEADER.match(line)
        if header:
            is_array = header.group(1) == "[["
            parts = header.group(2).split(".")
            path: list = []
            for i, part in enumerate(parts):
                path.append(part)
                dotted = ".".join(parts[:i + 1])
                if is_array and i == len(parts) - 1:
                    key = tuple(path)
                    counts[key] = counts.get(key, -1) + 1
                    current[dotted] = counts[key]
                    path.append(counts[key])
                elif dotted in current:
                    path.append(current[dotted])
            table = tuple(path)
            continue
        match = _KEY.match(line)
        if match and not line.lstrip().startswith("#"):
            where[table + (match.group(2),)] = number
    return where


def fit_values(robot_name: str, unit: str, system, lines, ab: np.ndarray) -> dict[tuple, str]:
    """``{path of the motor's fit: inline table}`` for identified current-to-torque lines
    (:class:`cochlea.ident.current.Line`, ``ab`` their SI ``[a, b]``): in the description's
    own units, marked ``source = "identified"``; where each fit sits is the robot's
    adapter's ``fit_key``."""
    adapter = robot(robot_name)
    out = {}
    for ln, (a, b) in zip(lines, ab):
        a_d, b_d = ln.in_description_units(a, b)
        path = adapter.fit_key(system, unit, ln.joint, ln.name)
        out[path] = (f"{{ a = {a_d:.6g}, b = {b_d:.6g}, x = {toml_string(ln.x)}, "
                     f"y = {toml_string(ln.y)}, "
                     'source = "identified" }')
    return out


def edit(text: str, values: dict[tuple, str], source: Path,
         tables: dict[tuple, str] | None = None) -> str:
    """``text`` with each value of ``values`` replaced on its line, comments kept; each of
    ``tables`` (an inline table such as a motor's ``fit``) replaces the whole inline table."""
    lines = text.splitlines(keepends=True)
    where = key_lines(lines)
    for path, new in (tables or {}).items():
        if path not in where:
            shown = ".".join(str(p) for p in path)
            raise WriteBackError(f"{source}: cannot write the identified {shown}: expected it "
                                 "as `fit = { ... }` on a line of its own under its table")
        number = where[path]
        line = lines[number]
        ending = line[len(line.rstrip("\r\n")):]
        body = line.rstrip("\r\n")
        start, stop = body.find("{"), body.find("}")
        if start < 0 or stop < start:
            raise WriteBackError(f"{source}: line {number + 1}: expected an inline table "
                                 f"{{ a = ..., b = ..., x = ..., y = ... }}, got {body.strip()!r}")
        lines[number] = body[:start] + new + body[stop + 1:] + ending
    for path, new in values.items():
        if path not in where:
            shown = ".".join(str(p) for p in path)
            raise WriteBackError(f"{source}: cannot write the identified {shown}: the key is "
                                 "not on a line of its own in the description (write it as "
                                 "`key = value` under its table)")
        number = where[path]
        line = lines[number]
        ending = line[len(line.rstrip("\r\n")):]
        match = _KEY.match(line.rstrip("\r\n"))
        indent, key, equals, old, comment = match.groups()
        if '"' in old or "'" in old or "{" in old:
            raise WriteBackError(f"{source}: line {number + 1}: expected a number or a list "
                                 f"of numbers for {key}, got {old!r}")
        lines[number] = f"{indent}{key}{equals}{new}{comment or ''}{ending}"
    return "".join(lines)


def target_path(description: Path, in_place: bool) -> Path:
    """Where the identified description goes: ``<name>.identified.toml`` beside it, or the
    file itself with ``--in-place``; an existing new file is refused (never overwritten)."""
    if in_place:
        return description
    target = description.with_name(f"{description.stem}.identified{description.suffix}")
    if target.exists():
        raise TargetExists(f"{target}: already exists; remove it, or give --in-place to "
                             f"update {description} itself")
    return target


def check_writable(description: Path, in_place: bool, inputs: tuple[Path, ...] = ()) -> Path:
    """Everything about ``--update-description`` that can be checked before fitting: the
    description a regular file, the target a new name (or, ``in_place``, the description
    itself, not a symbolic link) in a folder this process may write, and no log."""
    if not description.is_file():
        raise WriteBackError(f"{description}: --update-description expects an existing robot "
                             "description TOML file")
    target = target_path(description, in_place)
    if in_place and description.is_symlink():
        raise files.OutputRefused(f"--update-description {description} --in-place: the "
                                  "description is a symbolic link (a link is never replaced): "
                                  "name the file it points to, or leave out --in-place")
    files.check_output(target, "--update-description" + (" --in-place" if in_place else ""),
                       inputs=inputs, replace=in_place)
    return target


def write_back(model: RobotModel, robot_name: str, unit: str, description: Path,
               phi: np.ndarray, logs: list[tuple[str, str]], in_place: bool = False,
               how: str = "the full vector nearest the nominal one", lines=(),
               line_ab: np.ndarray | None = None, stage: files.Staged | None = None) -> Path:
    """Write the full parameters ``phi`` of ``model`` into ``description`` (a new file beside
    it unless ``in_place``), headed by a comment naming ``logs`` (folder, sha256) and the
    date; validated by loading before it lands. ``lines`` and ``line_ab``: identified
    current-to-torque lines, written into their motors' fits. Returns the file written; with
    ``stage``, the file is only staged (written and validated under a temporary name beside
    the target) and lands when the stage is committed."""
    target = target_path(description, in_place)
    adapter = robot(robot_name)
    system = adapter.load(description)
    values = adapter.identified_values(model, system, unit, phi)
    text = description.read_text(encoding="utf-8")
    fits = fit_values(robot_name, unit, system, lines, line_ab) if len(lines) else None
    edited = edit(text, values, description, fits)
    today = datetime.date.today().isoformat()
    what = f" ({unit})" if adapter.units_are_arms else ""
    header = [f"# Dynamic parameters{what} identified by cochlea-identify on {today} "
              f"({comment(how)}),"]
    if fits:
        header += ["# and the current-to-torque fits of "
                   + ", ".join(f"{ln.name} (ID {ln.motor_id})" for ln in lines)
                   + " from the measured current (source = \"identified\"),"]
    header += ["# from the logs:"]
    header += [f"#   {comment(str(folder))} (log.csv sha256 {digest})" for folder, digest in logs]
    edited = "\n".join(header) + "\n" + edited
    own = stage is None
    stage = files.Staged() if own else stage
    try:
        temp = stage.path(target)
        with open(temp, "w", encoding="utf-8") as f:
            f.write(edited)
            f.flush()
            os.fsync(f.fileno())
        try:
            adapter.load(temp)
        except CochleaError as exc:
            message = str(exc).replace(str(temp), str(target))
            raise WriteBackError(f"the identified values do not make a valid description: "
                                 f"{message}; fit physically consistent parameters with "
                                 "--physical") from None
        if own:
            stage.commit()
    finally:
        if own:
            stage.discard()
    return target
