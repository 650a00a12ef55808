"""URDF in and out: a serial chain of a URDF file to a cochlea description, and back.

:func:`import_urdf` reads a URDF (standard library ``xml.etree`` only), takes the chain from a
base link to a tip link, merges the links that fixed joints attach into the moving link they
hang from (masses and centres of mass combined, inertias by the parallel-axis theorem, a fixed
joint's transform folded into the next moving joint's origin) and writes the description text
(``cochlea-robot/1``, one arm), a prismatic joint's transmission from the file's
``<transmission>`` (its ``mechanicalReduction``) or the ``--transmission`` option.
:func:`export_urdf` writes one arm of a description as a URDF.
:func:`starter_scenario` writes a gentle joint-space scenario for an imported arm.

Angles of the file (joint and inertial ``rpy``) within :data:`SNAP_TOLERANCE_RAD` of a multiple
of pi/12 are snapped to it, and each snap is reported: a URDF's pi written as 3.14159 tilts a
frame by 1.5e-4 deg, which changes the structure of the dynamics (36 base parameters become 38
on a 6-DoF arm, and identification refuses the rank-deficient regressor).

Everything that cannot be a serial chain is one :class:`UrdfError` (a
:class:`~cochlea.errors.CochleaError`: one line, exit code 2 in ``cochlea-urdf``).
"""

from __future__ import annotations

import math
import re
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ... import files
from ...dynamixel.control_table import MODELS as MOTOR_SPECS
from ...errors import CochleaError, DescriptionError
from ...text import comment, decimal, toml_string
from ..description import (
    MAX_LENGTH_M,
    MAX_MOTOR_ID,
    MIN_KEEP_OUT_M,
    NAME_PATTERN,
    TRANSMISSION_RANGE_M,
    TRANSMISSIONS,
    Transmission,
)
from .chain import tool_offset
from .description import MAX_JOINTS, Arm, SerialSystem, load_serial, rpy_matrix
from .model import build_model

#: A file angle this close to a multiple of pi/12 (15 deg) is snapped to it.
SNAP_TOLERANCE_RAD = 1e-5
#: Largest URDF read (meshes are referenced, not inlined: real URDFs are well below this).
MAX_URDF_BYTES = 16 * 1024 * 1024
#: Any number of a URDF beyond this is a mistake (SI units: no robot has a 1000 km link).
MAX_VALUE = 1e6
#: A continuous joint has no position limits; the description needs some: +-this many deg.
CONTINUOUS_LIMIT_DEG = 360.0
#: The motor a joint gets when ``--motor`` names none.
DEFAULT_MOTOR = "XM540-W270"
#: Datasheet figures for a placeholder torque fit (ROBOTIS e-Manual, each model's
#: specifications, at its nominal voltage: cochlea/dynamixel/models): stall torque (N m) and
#: stall current (A), for every model a description can use (current control, current unit
#: and limit sourced) whose stall figures are sourced. Their ratio is the torque constant the
#: placeholder fit ``torque_Ncm = a * current_A`` uses (b = 0): an upper bound of the real
#: slope (the thesis's MX-64 fits are 95-122 N cm/A, this gives 146).
DATASHEET_STALL = {m.name: (m.stall_torque_Nm, m.stall_current_A) for m in MOTOR_SPECS.values()
                   if m.current_control_problem() is None and m.stall_torque_Nm is not None
                   and m.stall_current_A is not None}

_STEP = math.pi / 12
_MOVING = ("revolute", "continuous", "prismatic")
_NOT_SERIAL = ("floating", "planar")


class UrdfError(CochleaError):
    """A URDF that cannot be read, or whose chain cannot be a cochlea serial arm."""


# --------------------------------------------------------------------------------------------
# Reading the file
# --------------------------------------------------------------------------------------------


@dataclass
class Inertial:
    mass: float
    com: np.ndarray  # in the owning frame
    inertia: np.ndarray  # 3x3 about the centre of mass, axes of the owning frame


@dataclass
class UJoint:
    name: str
    type: str
    parent: str
    child: str
    xyz: np.ndarray
    rpy: np.ndarray
    axis: np.ndarray
    limits: tuple[float, float, float, float] | None  # lower, upper, velocity, effort
    damping: float = 0.0
    friction: float = 0.0


@dataclass
class Urdf:
    name: str
    links: dict[str, Inertial | None]
    joints: dict[str, UJoint]
    snaps: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    #: joint name -> the ``mechanicalReduction`` of its ``<transmission>`` (motor rad per
    #: joint unit: rad/rad, or rad/m at a prismatic joint), where the file gives one.
    reductions: dict[str, float] = field(default_factory=dict)


def _fail(path, message: str) -> UrdfError:
    return UrdfError(f"{path}: {message}")


def _read_bytes(path: Path) -> bytes:
    try:
        raw = files.read_regular(path, MAX_URDF_BYTES)  # a FIFO or a device is refused
    except FileNotFoundError:
        raise _fail(path, "no such file") from None
    except IsADirectoryError:
        raise _fail(path, "a folder, not a URDF file") from None
    except OSError as exc:
        raise _fail(path, f"cannot read it: {exc.strerror or exc}") from None
    except ValueError:
        raise _fail(path, "a file name without NUL bytes is needed") from None
    if len(raw) > MAX_URDF_BYTES:
        raise _fail(path, f"larger than {MAX_URDF_BYTES // (1024 * 1024)} MiB: not a URDF")
    return raw


def _snap(value: float, what: str, snaps: list[str] | None) -> float:
    """``value`` (rad) snapped to a multiple of pi/12 when within the tolerance; a snap of a
    file value is reported in ``snaps``."""
    k = round(value / _STEP)
    exact = k * _STEP
    if value != exact and abs(value - exact) <= SNAP_TOLERANCE_RAD:
        if snaps is not None:
            snaps.append(f"{what}: {value!r} rad snapped to {k * 15} deg "
                         f"(moved by {abs(value - exact):.2g} rad)")
        return exact
    return value


def _numbers(path, element, attr: str, size: int, where: str, default=None) -> np.ndarray:
    text = element.get(attr) if element is not None else None
    if text is None:
        if default is None:
            raise _fail(path, f"{where}: the attribute {attr!r} is missing")
        return np.array(default, dtype=float)
    # Each token a plain ASCII decimal: float() alone would read "0_5" as 5.0 (a tenfold
    # mass), "nan", and other scripts' digits.
    values = [decimal(v) for v in text.split()]
    if None in values or len(values) != size or not all(math.isfinite(v) and abs(v) <= MAX_VALUE
                                      for v in values):
        raise _fail(path, f"{where}: {attr}={text[:80]!r}: expected {size} finite "
                    f"number{'s' if size > 1 else ''} within +-{MAX_VALUE:g}")
    return np.array(values, dtype=float)


def _origin(path, element, where: str, snaps: list[str]) -> tuple[np.ndarray, np.ndarray]:
    origin = element.find("origin")
    xyz = _numbers(path, origin, "xyz", 3, f"{where} origin", (0.0, 0.0, 0.0))
    rpy = _numbers(path, origin, "rpy", 3, f"{where} origin", (0.0, 0.0, 0.0))
    rpy = np.array([_snap(float(a), f"{where} origin rpy[{i}]", snaps)
                    for i, a in enumerate(rpy)])
    return xyz, rpy


def _check_inertia(path, where: str, inertia: np.ndarray) -> None:
    moments = np.linalg.eigvalsh(inertia)
    a, b, c = moments
    if not a > 0:
        raise _fail(path, f"{where}: the inertia is not positive definite (principal moments "
                    f"{a:.3g}, {b:.3g}, {c:.3g} kg m^2): not a physical body")
    if a + b < c * (1 - 1e-9):
        raise _fail(path, f"{where}: the principal moments {a:.6g}, {b:.6g}, {c:.6g} kg m^2 "
                    "violate the triangle inequality (two must sum to at least the third): "
                    "not a physical body")


def _inertial(path, link, snaps: list[str]) -> Inertial | None:
    """The link's inertial in its frame; None when it has none, or declares an empty one
    (mass 0 and zero inertia: a frame without a body, as URDFs write a tool frame). A positive
    mass with zero inertia is a point mass; whatever a moving link ends up with after the merge
    must still be a positive definite inertia (the description's loader checks it)."""
    where = f"link {link.get('name')!r} inertial"
    el = link.find("inertial")
    if el is None:
        return None
    xyz, rpy = _origin(path, el, where, snaps)
    mass_el = el.find("mass")
    mass = float(_numbers(path, mass_el, "value", 1, f"{where} mass")[0]) \
        if mass_el is not None else None
    if mass is None:
        raise _fail(path, f"{where}: <mass value=...> is missing")
    inertia_el = el.find("inertia")
    if inertia_el is None:
        raise _fail(path, f"{where}: <inertia ixx=... iyy=... izz=... ixy=... ixz=... iyz=...> "
                    "is missing")
    six = [float(_numbers(path, inertia_el, k, 1, f"{where} inertia", (0.0,))[0])
           for k in ("ixx", "iyy", "izz", "ixy", "ixz", "iyz")]
    ixx, iyy, izz, ixy, ixz, iyz = six
    if mass == 0.0 and not any(six):
        return None
    if not mass > 0:
        raise _fail(path, f"{where}: mass {mass:g} kg: a body needs a positive mass")
    I = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    if any(six):  # all zero: a point mass (a tool frame's token mass), physical in the limit
        _check_inertia(path, where, I)
    R = rpy_matrix(rpy)
    return Inertial(mass, xyz, R @ I @ R.T)


def _limits(path, joint_el, name: str, jtype: str):
    el = joint_el.find("limit")
    where = f"joint {name!r} ({jtype})"
    if el is None:
        raise _fail(path, f"{where}: <limit> is missing; a {jtype} joint needs lower, upper "
                    "(except a continuous joint), velocity and effort")
    def value(attr, required=True):
        if el.get(attr) is None:
            if required:
                raise _fail(path, f"{where}: <limit {attr}=...> is missing")
            return None
        return float(_numbers(path, el, attr, 1, f"{where} limit")[0])
    velocity, effort = value("velocity"), value("effort")
    if not velocity > 0 or not effort > 0:
        raise _fail(path, f"{where}: limit velocity={velocity:g}, effort={effort:g}: both must "
                    "be positive")
    if jtype == "continuous":
        b = math.radians(CONTINUOUS_LIMIT_DEG)
        return -b, b, velocity, effort
    lower, upper = value("lower", False), value("upper", False)
    if lower is None or upper is None or not lower < upper:
        raise _fail(path, f"{where}: position limits lower={lower}, upper={upper}: both needed, "
                    "lower < upper")
    return lower, upper, velocity, effort


def read_urdf(path: str | Path) -> Urdf:
    """Parse a URDF file into links (with their inertials) and joints, every value checked."""
    path = Path(path)
    raw = _read_bytes(path)
    try:
        raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise _fail(path, f"line {line}: byte 0x{raw[exc.start]:02x} is not UTF-8 (save the "
                    "file as UTF-8)") from None
    if b"<!DOCTYPE" in raw or b"<!ENTITY" in raw:
        raise _fail(path, "a document type declaration (<!DOCTYPE ...>): a URDF has none, and "
                    "its entities are not expanded here")
    try:
        root = ET.fromstring(raw)
    except ET.ParseError as exc:
        raise _fail(path, f"not well-formed XML: {exc}") from None
    except (ValueError, LookupError, RecursionError) as exc:  # e.g. an unknown encoding
        raise _fail(path, f"not readable XML: {exc}") from None
    if root.tag != "robot":
        raise _fail(path, f"the root element is <{str(root.tag)[:40]}>, a URDF's is <robot>")
    snaps: list[str] = []
    notes: list[str] = []
    links: dict[str, Inertial | None] = {}
    for el in root.findall("link"):
        name = el.get("name")
        if not name:
            raise _fail(path, "a <link> without a name")
        if name in links:
            raise _fail(path, f"two links named {name!r}")
        links[name] = _inertial(path, el, snaps)
    if not links:
        raise _fail(path, "no <link> at all")
    joints: dict[str, UJoint] = {}
    for el in root.findall("joint"):
        name = el.get("name")
        if not name:
            raise _fail(path, "a <joint> without a name")
        if name in joints:
            raise _fail(path, f"two joints named {name!r}")
        jtype = el.get("type")
        if jtype in _NOT_SERIAL:
            raise _fail(path, f"joint {name!r} is {jtype}: a serial arm has revolute, "
                        "continuous, prismatic and fixed joints only")
        if jtype not in (*_MOVING, "fixed"):
            raise _fail(path, f"joint {name!r} has type {str(jtype)[:40]!r}; a URDF joint is "
                        "revolute, continuous, prismatic, fixed, floating or planar")
        if el.find("mimic") is not None:
            raise _fail(path, f"joint {name!r} mimics another joint: a coupled joint is not a "
                        "serial chain's independent coordinate")
        ends = []
        for tag in ("parent", "child"):
            e = el.find(tag)
            link = e.get("link") if e is not None else None
            if link is None:
                raise _fail(path, f"joint {name!r}: <{tag} link=...> is missing")
            if link not in links:
                raise _fail(path, f"joint {name!r}: its {tag} link {link!r} is not defined")
            ends.append(link)
        xyz, rpy = _origin(path, el, f"joint {name!r}", snaps)
        axis, limits = np.array([1.0, 0.0, 0.0]), None
        damping = friction = 0.0
        if jtype != "fixed":
            axis = _numbers(path, el.find("axis"), "xyz", 3, f"joint {name!r} axis",
                            (1.0, 0.0, 0.0))
            norm = float(np.linalg.norm(axis))
            if not 1e-9 < norm < 1e9:
                raise _fail(path, f"joint {name!r}: axis {axis.tolist()} is not a direction")
            axis = axis / norm
            limits = _limits(path, el, name, jtype)
            dyn = el.find("dynamics")
            if dyn is not None:
                damping = float(_numbers(path, dyn, "damping", 1, f"joint {name!r} dynamics",
                                         (0.0,))[0])
                friction = float(_numbers(path, dyn, "friction", 1,
                                          f"joint {name!r} dynamics", (0.0,))[0])
                if damping < 0 or friction < 0:
                    raise _fail(path, f"joint {name!r}: negative damping or friction")
            if jtype == "continuous":
                notes.append(f"joint {name!r} is continuous: given position limits "
                             f"+-{CONTINUOUS_LIMIT_DEG:g} deg")
        joints[name] = UJoint(name, jtype, ends[0], ends[1], xyz, rpy, axis, limits,
                              damping, friction)
    reductions = _transmissions(path, root, joints, notes)
    return Urdf(root.get("name") or path.stem, links, joints, snaps, notes, reductions)


def _transmissions(path, root, joints: dict[str, UJoint], notes: list[str]) -> dict[str, float]:
    """Each joint's ``mechanicalReduction`` from the file's ``<transmission>`` elements
    (ros_control's ``<actuator><mechanicalReduction>``, or the older form directly under
    ``<transmission>``): the motor's angle per unit of joint travel. A transmission of several
    joints (a differential) is left out, with a note."""
    out: dict[str, float] = {}
    for el in root.findall("transmission"):
        name = el.get("name") or "(unnamed)"
        names = [j.get("name") for j in el.findall("joint")]
        if len(names) != 1:
            notes.append(f"transmission {name!r} couples {len(names)} joints: left out (a "
                         "serial arm's motor drives one joint)")
            continue
        joint = names[0]
        if joint not in joints:
            raise _fail(path, f"transmission {name!r}: its joint {joint!r} is not defined")
        found = el.findall("actuator/mechanicalReduction") + el.findall("mechanicalReduction")
        if not found:
            continue
        value = decimal(found[0].text or "")
        if value is None:
            value = math.nan
        if not (math.isfinite(value) and value != 0.0 and abs(value) <= MAX_VALUE):
            raise _fail(path, f"transmission {name!r}: mechanicalReduction "
                        f"{(found[0].text or '').strip()[:40]!r}: expected a finite number, "
                        f"not zero, within +-{MAX_VALUE:g}")
        out[joint] = value
    return out


# --------------------------------------------------------------------------------------------
# The chain
# --------------------------------------------------------------------------------------------


@dataclass
class ChainLink:
    """One moving joint and the body it moves (its URDF child link and what is fixed to it)."""

    name: str  # the URDF child link's name
    joint: UJoint
    xyz: np.ndarray  # the joint's origin in the previous chain link's frame (fixed folded in)
    R: np.ndarray  # the joint frame's rotation in the previous chain link's frame
    body: Inertial | None
    merged: list[str] = field(default_factory=list)


def _combine(bodies: list[Inertial]) -> Inertial | None:
    bodies = [b for b in bodies if b is not None]
    if not bodies:
        return None
    m = sum(b.mass for b in bodies)
    c = sum(b.mass * b.com for b in bodies) / m
    I = np.zeros((3, 3))
    for b in bodies:
        d = b.com - c
        I += b.inertia + b.mass * (float(d @ d) * np.eye(3) - np.outer(d, d))
    return Inertial(m, c, 0.5 * (I + I.T))


def _moved(body: Inertial | None, R: np.ndarray, p: np.ndarray) -> Inertial | None:
    """``body`` given in a frame at (R, p) of the target frame, expressed in the target."""
    if body is None:
        return None
    return Inertial(body.mass, p + R @ body.com, R @ body.inertia @ R.T)


def _tree(path, urdf: Urdf) -> tuple[str, dict[str, list[UJoint]], dict[str, UJoint]]:
    """The root link, each link's child joints and each link's parent joint."""
    parent_of: dict[str, UJoint] = {}
    children: dict[str, list[UJoint]] = {name: [] for name in urdf.links}
    for j in urdf.joints.values():
        if j.child == j.parent:
            raise _fail(path, f"joint {j.name!r} joins link {j.child!r} to itself: a closed "
                        "loop")
        if j.child in parent_of:
            raise _fail(path, f"link {j.child!r} has two parents (joints "
                        f"{parent_of[j.child].name!r} and {j.name!r}): a closed loop, not a "
                        "serial chain")
        parent_of[j.child] = j
        children[j.parent].append(j)
    roots = [name for name in urdf.links if name not in parent_of]
    if not roots:
        raise _fail(path, "every link has a parent: the joints form a closed loop")
    if len(roots) > 1:
        raise _fail(path, f"links {roots[0]!r} and {roots[1]!r} both have no parent: the file "
                    "is not one tree")
    seen, stack = {roots[0]}, [roots[0]]
    while stack:
        for j in children[stack.pop()]:
            seen.add(j.child)
            stack.append(j.child)
    if len(seen) != len(urdf.links):
        lost = next(name for name in urdf.links if name not in seen)
        raise _fail(path, f"link {lost!r} is not reachable from the root {roots[0]!r}: its "
                    "joints form a closed loop")
    return roots[0], children, parent_of


def _has_moving(link: str, children: dict[str, list[UJoint]]) -> bool:
    stack = [link]
    while stack:
        for j in children[stack.pop()]:
            if j.type != "fixed":
                return True
            stack.append(j.child)
    return False


def _path(path, urdf: Urdf, base: str, tip: str | None, children, parent_of) -> list[UJoint]:
    """The joints from ``base`` to ``tip`` (default: follow the only branch with moving
    joints until none is left)."""
    if tip is not None:
        joints = []
        link = tip
        while link != base:
            if link not in parent_of:
                raise _fail(path, f"--tip {tip!r} is not below --base {base!r}")
            joints.append(parent_of[link])
            link = parent_of[link].parent
        return joints[::-1]
    joints, link = [], base
    while True:
        moving = [j for j in children[link] if j.type != "fixed" or _has_moving(j.child,
                                                                                children)]
        if not moving:
            return joints
        if len(moving) > 1:
            raise _fail(path, f"the chain branches at link {link!r} (joints "
                        + ", ".join(repr(j.name) for j in moving[:4])
                        + "): a serial arm has one path; choose it with --tip LINK")
        joints.append(moving[0])
        link = moving[0].child


@dataclass
class Frames:
    """The arm's base pose (the fixed joints from ``--base`` to the first moving joint) and
    its tool frame (the fixed joints after the last moving joint, to ``--tip`` or to the one
    massless leaf link fixed to the last moving link), each as ``(R, p)`` in its parent's
    frame; ``tool`` None: none found (the tool point is the last link's origin)."""

    base: tuple[np.ndarray, np.ndarray]
    tool: tuple[np.ndarray, np.ndarray] | None = None
    tool_link: str | None = None


def _default_tool(urdf: Urdf, last: str, children) -> UJoint | None:
    """The fixed joint to the one massless leaf link fixed to ``last``, if it is the only link
    fixed to it (a tool frame as URDFs write one, e.g. ``tool0``); otherwise None."""
    fixed = [j for j in children[last] if j.type == "fixed"]
    if len(fixed) == 1 and urdf.links[fixed[0].child] is None and not children[fixed[0].child]:
        return fixed[0]
    return None


def extract_chain(path, urdf: Urdf, base: str | None = None,
                  tip: str | None = None) -> tuple[list[ChainLink], list[str], Frames]:
    """The moving links from ``base`` to ``tip``, notes of what was merged or left out, and
    the base and tool frames (:class:`Frames`)."""
    root, children, parent_of = _tree(path, urdf)
    for option, link in (("--base", base), ("--tip", tip)):
        if link is not None and link not in urdf.links:
            raise _fail(path, f"{option} {link!r}: no such link")
    base = root if base is None else base
    joints = _path(path, urdf, base, tip, children, parent_of)
    notes: list[str] = []
    if not any(j.type != "fixed" for j in joints):
        raise _fail(path, f"no revolute, continuous or prismatic joint between {base!r} and "
                    f"{tip or 'the tip'!r}: nothing to move")
    on_path = {base, *(j.child for j in joints)}
    chain: list[ChainLink] = []
    # Transform from the current chain frame (the base, then the last moving link) to the
    # link being walked: fixed joints accumulate into it.
    R_acc, p_acc = np.eye(3), np.zeros(3)

    def attach(owner: list, link: str, R: np.ndarray, p: np.ndarray, merged: list[str]):
        """Merge the bodies fixed to ``link`` (at R, p in the owner's frame) into ``owner``,
        refusing a moving joint that hangs off the path."""
        stack = [(link, R, p)]
        while stack:
            name, Rn, pn = stack.pop()
            for j in children[name]:
                if j.child in on_path:
                    continue
                if j.type != "fixed":
                    if tip is None:  # _path followed every moving branch: not reached
                        raise _fail(path, f"joint {j.name!r} branches off the chain")
                    notes.append(f"left out: joint {j.name!r} and what it carries (it branches "
                                 f"off the chain at link {name!r}); its mass is not in the model")
                    continue
                Rj = Rn @ rpy_matrix(j.rpy)
                pj = pn + Rn @ j.xyz
                if urdf.links[j.child] is not None:
                    owner.append(_moved(urdf.links[j.child], Rj, pj))
                    merged.append(j.child)
                stack.append((j.child, Rj, pj))

    base_bodies: list = []
    attach(base_bodies, base, np.eye(3), np.zeros(3), [])
    base_frame = None
    for j in joints:
        if j.type != "fixed" and base_frame is None:
            # The fixed joints before the first moving one place the arm's base.
            base_frame, R_acc, p_acc = (R_acc, p_acc), np.eye(3), np.zeros(3)
        Rj = R_acc @ rpy_matrix(j.rpy)
        pj = p_acc + R_acc @ j.xyz
        if j.type == "fixed":
            R_acc, p_acc = Rj, pj
            if chain:
                body = urdf.links[j.child]
                if body is not None:
                    chain[-1].merged.append(j.child)
                    chain[-1].body = _combine([chain[-1].body, _moved(body, R_acc, p_acc)])
                extra: list = []
                attach(extra, j.child, R_acc, p_acc, chain[-1].merged)
                chain[-1].body = _combine([chain[-1].body, *extra])
            continue
        link = ChainLink(j.child, j, pj, Rj, urdf.links[j.child])
        extra = []
        attach(extra, j.child, np.eye(3), np.zeros(3), link.merged)
        link.body = _combine([link.body, *extra])
        chain.append(link)
        R_acc, p_acc = np.eye(3), np.zeros(3)
    frames = Frames(base_frame)
    if joints[-1].type == "fixed":  # --tip names a link fixed below the last moving one
        frames.tool, frames.tool_link = (R_acc, p_acc), joints[-1].child
    elif tip is None and (leaf := _default_tool(urdf, joints[-1].child, children)) is not None:
        frames.tool, frames.tool_link = (rpy_matrix(leaf.rpy), leaf.xyz.copy()), leaf.child
    if frames.tool is not None:
        notes.append(f"the tool frame is link {frames.tool_link!r} (tool_xyz_m, tool_rpy_deg)")
    for link in chain:
        if link.body is None:
            raise _fail(path, f"link {link.name!r} (moved by joint {link.joint.name!r}) has no "
                        "inertial, nor anything fixed to it that has one: every moving link "
                        "needs a mass")
        if link.merged:
            notes.append(f"merged into link {link.name!r} (fixed joints): "
                         + ", ".join(repr(n) for n in link.merged))
    return chain, notes, frames


# --------------------------------------------------------------------------------------------
# Writing the description
# --------------------------------------------------------------------------------------------


def rpy_of(R: np.ndarray) -> np.ndarray:
    """Fixed-axis roll-pitch-yaw (rad) of a rotation matrix, ``R = Rz(y) Ry(p) Rx(r)``."""
    p = math.atan2(-R[2, 0], math.hypot(R[0, 0], R[1, 0]))
    if abs(abs(p) - math.pi / 2) < 1e-9:
        return np.array([0.0, math.copysign(math.pi / 2, p), math.atan2(-R[0, 1], R[1, 1])])
    return np.array([math.atan2(R[2, 1], R[2, 2]), p, math.atan2(R[1, 0], R[0, 0])])


def _deg(angle: float) -> float:
    """An angle (rad) in degrees, a multiple of 15 deg written exactly: the file's angles were
    snapped already, and composing snapped frames leaves only rounding (1e-9 rad here)."""
    k = round(angle / _STEP)
    if abs(angle - k * _STEP) <= 1e-9:
        return float(k * 15)
    return math.degrees(angle)


def clean_name(name: str, used: set[str], prefix: str) -> str:
    """``name`` as a description name (:data:`NAME_PATTERN`: letters, digits and single
    underscores, starting with a letter, at most 64), unique among ``used``. Every other
    character becomes ``_``, runs of ``_`` one, and a leading or trailing ``_`` goes: URDF
    names such as ``base-link`` or ``bras articul\u00e9`` are common, CasADi names are not."""
    def tidy(text: str) -> str:
        return re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9]", "_", text)).strip("_")

    out = tidy(name)[:56]
    if not out or not out[0].isalpha():
        out = tidy(f"{prefix}_{out}")[:56]
    out = out.rstrip("_")
    candidate, k = out, 2
    while candidate in used:
        candidate = f"{out}_{k}"
        k += 1
    assert NAME_PATTERN.fullmatch(candidate), candidate
    used.add(candidate)
    return candidate


def motor_fit(model: str) -> dict:
    """The placeholder fit of a motor model from its datasheet (:data:`DATASHEET_STALL`)."""
    torque, current = DATASHEET_STALL[model]
    return {"a": round(100.0 * torque / current, 3), "b": 0.0, "x": "current_A",
            "y": "torque_Ncm", "source": "placeholder"}


def _f(x: float) -> str:
    return repr(float(x)) if x != 0 else "0.0"


def _vec(v) -> str:
    return "[" + ", ".join(_f(x) for x in v) + "]"


def _frame_lines(frames: Frames | None) -> list[str]:
    """The arm's base pose and tool frame keys: ``base_yaw_deg`` for a level base (turned
    about z only), else ``base_rpy_deg``; ``tool_xyz_m`` (and ``tool_rpy_deg`` if turned)."""
    if frames is None:
        return ["base_xyz_m = [0.0, 0.0, 0.0]", "base_yaw_deg = 0.0"]
    R, p = frames.base
    rpy = [_deg(a) for a in rpy_of(R)]
    lines = [f"base_xyz_m = {_vec(p)}"]
    if rpy[0] == 0.0 and rpy[1] == 0.0:
        lines.append(f"base_yaw_deg = {_f(rpy[2])}")
    else:
        lines.append(f"base_rpy_deg = {_vec(rpy)}")
    if frames.tool is not None:
        R, p = frames.tool
        lines.append(f"tool_xyz_m = {_vec(p)}")
        rpy = [_deg(a) for a in rpy_of(R)]
        if any(a != 0.0 for a in rpy):
            lines.append(f"tool_rpy_deg = {_vec(rpy)}")
    return lines


def description_text(chain: list[ChainLink], source: Path, robot_name: str,
                     motors: list[str], ids: list[int], notes: list[str],
                     frames: Frames | None = None,
                     drives: list[JointTransmission] | None = None,
                     keep_out_radius: float | None = None) -> str:
    """The description (``cochlea-robot/1``, one arm) of an extracted chain: ``drives`` each
    joint's transmission (None: a revolute chain's, none anywhere), ``keep_out_radius`` (m)
    the ``keep_out_radius_m`` to write (None: none, no keep-out circle)."""
    drives = drives if drives is not None else [JointTransmission() for _ in chain]
    used_links: set[str] = set()
    used_joints: set[str] = set()
    fits = sorted({m: motor_fit(m) for m in motors}.items())
    lines = [
        f"# cochlea robot description imported from the URDF {comment(source.name)} by "
        "cochlea-urdf "
        "import.",
        "#",
        "# Units: every dimensional key names its unit in its suffix (_m, _kg, _kgm2, _deg, "
        "_rad_s, _Nm,",
        "# _m_s2); the loader turns degrees into radians. Frames: the URDF's base link is the "
        "arm's base",
        "# frame and the world frame; gravity is -z as in a URDF. Each link frame is its URDF "
        "link's",
        "# frame; a joint's origin_xyz_m / origin_rpy_deg is its URDF origin, with the "
        "transforms of",
        "# fixed joints before it folded in. Links attached by fixed joints are merged into "
        "the moving",
        "# link they hang from (mass, centre of mass, inertia by the parallel-axis theorem).",
        "#",
        "# From the URDF: joint names, types, axes, origins, position/velocity/effort limits, "
        "damping",
        "# and friction (as viscous_friction / coulomb_friction), the links' inertials.",
        "# length_m is 0 everywhere: every joint gives its origin; the tool point is the last "
        "link's",
        "# origin.",
        "#",
        "# ESTIMATES, not from the URDF (calibrate them on the robot):",
        "# * the motors: " + ", ".join(sorted(set(motors))) + " (cochlea-urdf import --motor), "
        "IDs " + ", ".join(str(i) for i in ids) + ";",
        "#   direction = 1 and zero_offset_deg = 0 are placeholders (cochlea-dxl calibrate).",
        "# * each fit is a PLACEHOLDER (source = \"placeholder\"): torque_Ncm = a * current_A "
        "with a the",
        "#   datasheet's stall torque over stall current (ROBOTIS e-Manual): "
        + "; ".join(f"{m} {DATASHEET_STALL[m][0]:g} N m / {DATASHEET_STALL[m][1]:g} A at "
                    f"{MOTOR_SPECS[m].stall_voltage_V:g} V = "
                    f"{f['a']:g} N cm/A" for m, f in fits) + ".",
        "#   Fit it on the robot (cochlea-dxl calibrate --torque-fit, or cochlea-identify).",
    ]
    for link, drive in zip(chain, drives, strict=True):
        if drive.transmission is not None:
            lines.append(f"# * the transmission of joint {comment(repr(link.joint.name))}: "
                         f"{comment(drive.source)}; "
                         "its sign is the motor's direction.")
    if keep_out_radius is None:
        lines += ["# No keep_out_radius_m: no keep-out circle around the world origin "
                  "(cochlea-urdf import", "# --keep-out-radius-m R writes one where a head "
                  "is near)."]
    else:
        lines.append(f"# keep_out_radius_m = {keep_out_radius!r} m: from cochlea-urdf import "
                     "--keep-out-radius-m.")
    if notes:
        lines += ["#", "# Import notes:"] + [f"# * {comment(n)}" for n in notes]
    lines += [
        "",
        'format = "cochlea-robot/1"',
        "",
        "[system]",
        f'name = {toml_string(clean_name(robot_name, set(), "robot"))}',
        'kind = "serial"',
        "gravity_m_s2 = [0.0, 0.0, -9.81]",
        *([] if keep_out_radius is None else [f"keep_out_radius_m = {keep_out_radius!r}"]),
        "",
        "[[arm]]",
        'name = "arm"',
        *_frame_lines(frames),
    ]
    for link, motor, motor_id, drive in zip(chain, motors, ids, drives, strict=True):
        j, body = link.joint, link.body
        I = body.inertia
        six = [I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]
        jtype = "prismatic" if j.type == "prismatic" else "revolute"
        lo, hi, velocity, effort = j.limits
        rpy = rpy_of(link.R)
        lines += [
            "",
            "  [[arm.link]]",
            f'  name = {toml_string(clean_name(link.name, used_links, "link"))}',
            "  length_m = 0.0",
            f"  mass_kg = {_f(body.mass)}",
            f"  com_m = {_vec(body.com)}",
            f"  inertia_com_kgm2 = {_vec(six)}  # [Ixx, Iyy, Izz, Ixy, Ixz, Iyz]",
            "",
            "  [arm.link.joint]",
            f'  name = {toml_string(clean_name(j.name, used_joints, "joint"))}',
            f'  type = "{jtype}"',
            f"  axis = {_vec(j.axis)}",
            f"  origin_xyz_m = {_vec(link.xyz)}",
            f"  origin_rpy_deg = {_vec([_deg(a) for a in rpy])}",
        ]
        if jtype == "revolute":
            lines += [f"  position_limits_deg = {_vec([math.degrees(lo), math.degrees(hi)])}",
                      f"  velocity_limit_rad_s = {_f(velocity)}",
                      f"  torque_limit_Nm = {_f(effort)}"]
            if j.damping > 0:
                lines.append(f"  viscous_friction_Nms_rad = {_f(j.damping)}")
            if j.friction > 0:
                lines.append(f"  coulomb_friction_Nm = {_f(j.friction)}")
        else:
            lines += [f"  position_limits_m = {_vec([lo, hi])}",
                      f"  velocity_limit_m_s = {_f(velocity)}",
                      f"  force_limit_N = {_f(effort)}"]
            if j.damping > 0:
                lines.append(f"  viscous_friction_Ns_m = {_f(j.damping)}")
            if j.friction > 0:
                lines.append(f"  coulomb_friction_N = {_f(j.friction)}")
            t = drive.transmission
            lines.append(f'  transmission = {{ kind = "{t.kind}", {TRANSMISSIONS[t.kind]} = '
                         f"{_f(t.size)} }}")
        fit = motor_fit(motor)
        direction = ("  direction = -1           # the URDF's mechanicalReduction is negative; "
                     "calibrate on the robot" if drive.direction < 0 else
                     "  direction = 1            # placeholder: calibrate on the robot")
        lines += [
            "",
            "  [arm.link.motor]",
            f'  model = "{motor}"',
            f"  id = {motor_id}",
            f'  fit = {{ a = {fit["a"]!r}, b = 0.0, x = "current_A", y = "torque_Ncm", '
            'source = "placeholder" }',
            direction,
            "  zero_offset_deg = 0.0    # placeholder: calibrate on the robot",
        ]
    return "\n".join(lines) + "\n"


@dataclass
class JointTransmission:
    """What drives one joint of the chain besides its motor: the prismatic joint's
    :class:`~cochlea.robots.description.Transmission` (None at a revolute joint), the motor's
    direction it implies (-1 for a negative ``mechanicalReduction``) and where it came from."""

    transmission: Transmission | None = None
    direction: int = 1
    source: str = ""


def assign_transmissions(path, urdf: Urdf, chain: list[ChainLink],
                         options: list[str] | None) -> tuple[list[JointTransmission], list[str]]:
    """Each joint's transmission: ``--transmission JOINT=KIND:SIZE`` (SIZE in m, m/rad for
    ``ratio``) first, else the URDF's ``mechanicalReduction`` R of a prismatic joint (motor
    rad per m: a ``ratio`` of 1/|R| m/rad, the motor's direction the sign of R). A prismatic
    joint with neither is refused: its motor's radians cannot be turned into metres. Returns
    the transmissions and notes (a revolute joint's reduction that is not carried)."""
    by_name = {link.joint.name: link for link in chain}
    given: dict[str, Transmission] = {}
    kinds = ", ".join(TRANSMISSIONS)
    for option in options or []:
        joint, sep, rest = option.partition("=")
        kind, colon, size_text = rest.partition(":")
        if not sep or not colon:
            raise UrdfError(f"--transmission {option!r}: expected JOINT=KIND:SIZE, e.g. "
                            "extend=lead_screw:0.008 (m of travel per motor turn)")
        link = by_name.get(joint)
        if link is None:
            raise UrdfError(f"--transmission {_short(option)}: the chain has no joint "
                            f"{_short(joint)}; its joints: " + _listed(list(by_name)))
        if link.joint.type != "prismatic":
            raise UrdfError(f"--transmission {option!r}: joint {joint!r} is {link.joint.type}: "
                            "only a prismatic joint has a transmission (a revolute joint is "
                            "its motor's output shaft)")
        if kind not in TRANSMISSIONS:
            raise UrdfError(f"--transmission {option!r}: unknown kind {kind!r}; known: {kinds}")
        size = decimal(size_text)
        if size is None:
            size = math.nan
        lo, hi = TRANSMISSION_RANGE_M
        if not lo <= size <= hi:  # NaN fails too
            unit = "m/rad" if kind == "ratio" else "m"
            raise UrdfError(f"--transmission {option!r}: expected SIZE a number in "
                            f"[{lo:g}, {hi:g}] {unit} ({TRANSMISSIONS[kind]})")
        given[joint] = Transmission(kind, size)
    out, notes = [], []
    for link in chain:
        name, reduction = link.joint.name, urdf.reductions.get(link.joint.name)
        if link.joint.type != "prismatic":
            if reduction is not None and reduction != 1.0:
                notes.append(f"joint {name!r}: the URDF's mechanicalReduction {reduction:g} is "
                             "not carried (a revolute joint is its motor's output shaft)")
            out.append(JointTransmission())
        elif name in given:
            t = given[name]
            out.append(JointTransmission(t, 1, f"--transmission {t.kind} "
                                         f"{TRANSMISSIONS[t.kind]} = {t.size:g}"))
        elif reduction is not None:
            out.append(JointTransmission(Transmission("ratio", 1.0 / abs(reduction)),
                                         1 if reduction > 0 else -1,
                                         f"the URDF's mechanicalReduction {reduction:g} rad/m, "
                                         f"1/|R| = {1.0 / abs(reduction):.6g} m/rad"))
        else:
            raise UrdfError(f"{path}: joint {name!r} is prismatic and the URDF gives no "
                            "<transmission> with a mechanicalReduction for it: give it with "
                            f"--transmission {name}=lead_screw:LEAD_M (m per motor turn), "
                            f"{name}=pinion:RADIUS_M or {name}=belt:RADIUS_M (m), or "
                            f"{name}=ratio:M_PER_RAD")
    return out, notes


def _short(text: str, size: int = 40) -> str:
    """A name from the file or an option as a message shows it: quoted, at most ``size``
    characters."""
    return repr(text if len(text) <= size else text[:size] + "...")


def _listed(names: list[str], most: int = MAX_JOINTS) -> str:
    """Names for a one-line message: each shortened, at most ``most`` of them."""
    shown = ", ".join(_short(n)[1:-1] for n in names[:most])
    return shown + (f", ... ({len(names)} in all)" if len(names) > most else "")


def assign_motors(path, chain: list[ChainLink], motor_options: list[str] | None,
                  ids: list[int] | None) -> tuple[list[str], list[int]]:
    """Each joint's motor model (``MODEL`` for all, ``JOINT=MODEL`` for one) and ID."""
    if len(chain) > MAX_JOINTS:  # before any message lists the joints
        raise UrdfError(f"{path}: the chain has {len(chain)} moving joints; a cochlea arm has "
                        f"at most {MAX_JOINTS} (choose a shorter one with --base and --tip)")
    known = ", ".join(sorted(DATASHEET_STALL))
    default, per_joint = DEFAULT_MOTOR, {}
    joint_names = [link.joint.name for link in chain]
    for option in motor_options or []:
        joint, sep, model = option.rpartition("=")
        if model not in MOTOR_SPECS or model not in DATASHEET_STALL:
            raise UrdfError(f"--motor {option!r}: unknown motor model {model!r}; known: {known}")
        if not sep:
            default = model
        elif joint not in joint_names:
            raise UrdfError(f"--motor {_short(option)}: the chain has no joint {_short(joint)}; "
                            "its joints: " + _listed(joint_names))
        else:
            per_joint[joint] = model
    motors = [per_joint.get(name, default) for name in joint_names]
    if ids is None:
        ids = list(range(1, len(chain) + 1))
    if len(ids) != len(chain):
        raise UrdfError(f"--ids gives {len(ids)} IDs for the chain's {len(chain)} joints ("
                        + _listed(joint_names) + ")")
    if len(set(ids)) != len(ids) or not all(0 <= i <= MAX_MOTOR_ID for i in ids):
        raise UrdfError(f"--ids {ids}: distinct integers in 0..{MAX_MOTOR_ID} are needed")
    return motors, ids


@dataclass
class Imported:
    text: str
    chain: list[ChainLink]
    snaps: list[str]
    notes: list[str]
    system: SerialSystem


def effort_notes(chain: list[ChainLink], motors: list[str], drives) -> list[str]:
    """A note per revolute joint driven directly (no transmission) whose URDF effort limit is
    above its motor's stall torque: the limit carries over as the URDF says, but the drive
    saturates first, so a run's torque limit there would never be the one that stops it."""
    out = []
    for link, motor, drive in zip(chain, motors, drives, strict=True):
        stall = MOTOR_SPECS[motor].stall_torque_Nm
        effort = link.joint.limits[3]
        if (link.joint.type != "prismatic" and drive.transmission is None
                and stall is not None and effort > stall):
            out.append(f"joint {link.joint.name!r}: the URDF's effort limit {effort:g} N m is "
                       f"above the {motor}'s stall torque {stall:g} N m (the drive saturates "
                       f"first): consider torque_limit_Nm <= {stall:g}")
    return out


def import_urdf(path: str | Path, base: str | None = None, tip: str | None = None,
                motors: list[str] | None = None, ids: list[int] | None = None,
                transmissions: list[str] | None = None,
                keep_out_radius: float | None = None) -> Imported:
    """The description text of the chain of a URDF file, with the snaps and notes.
    ``transmissions``: ``JOINT=KIND:SIZE`` options (:func:`assign_transmissions`);
    ``keep_out_radius`` (m): the ``keep_out_radius_m`` to write, None for none."""
    path = Path(path)
    if keep_out_radius is not None and not MIN_KEEP_OUT_M <= keep_out_radius <= MAX_LENGTH_M:
        raise UrdfError(f"--keep-out-radius-m {keep_out_radius}: expected a number of metres "
                        f"within [{MIN_KEEP_OUT_M:g}, {MAX_LENGTH_M:g}] (less than a millimetre "
                        "protects nothing; leave the option out for no circle)")
    urdf = read_urdf(path)
    chain, notes, frames = extract_chain(path, urdf, base, tip)
    motor_models, motor_ids = assign_motors(path, chain, motors, ids)
    drives, drive_notes = assign_transmissions(path, urdf, chain, transmissions)
    notes = urdf.notes + notes + drive_notes + effort_notes(chain, motor_models, drives)
    text = description_text(chain, path, urdf.name, motor_models, motor_ids,
                            notes + urdf.snaps, frames, drives, keep_out_radius)
    system = load_text(text, path)
    return Imported(text, chain, urdf.snaps, notes, system)


def load_text(text: str, source: Path) -> SerialSystem:
    """The description ``text`` through cochlea's own loader: what it refuses (a value beyond
    its bounds, e.g. a mass under 1e-6 kg) is refused here, naming the URDF."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "imported.toml"
        path.write_text(text, encoding="utf-8")
        try:
            return load_serial(path)
        except DescriptionError as exc:
            raise _fail(source, "the imported chain is not a valid cochlea description: "
                        + str(exc)[len(exc.path) + 2:]) from None


# --------------------------------------------------------------------------------------------
# Writing a URDF
# --------------------------------------------------------------------------------------------


def _attr_vec(v) -> str:
    return " ".join(repr(float(x)) for x in v)


def export_urdf(system: SerialSystem, arm: Arm | None = None) -> str:
    """One arm of a description as URDF text: links with their inertials, joints with their
    origins, axes, limits and friction. The base pose in the world frame becomes a fixed joint
    from a massless ``world`` link."""
    arm = system.arms[0] if arm is None else arm
    names = [j.name for j in build_model(system, arm).joints]
    link_names = {link.name for link in arm.links}
    base = "base_link" if "base_link" not in link_names else f"{arm.name}_base_link"
    world = "world" if "world" not in link_names else f"{arm.name}_world"
    root = ET.Element("robot", name=f"{system.name}_{arm.name}")
    root.append(ET.Comment(
        f" written by cochlea-urdf export from {comment(system.path.name, xml=True)}, arm "
        f"{arm.name!r}. Not in "
        "a URDF, so not here: the motors (model, ID, fit, offset), the armature, "
        "a prismatic joint's kind of transmission (its <transmission> has the ratio only, "
        "signed by the motor's direction), gravity (a URDF assumes -z; the description's is "
        f"{np.asarray(system.gravity).tolist()} m/s^2) and the keep-out radius. "))
    ET.SubElement(root, "link", name=world)
    ET.SubElement(root, "link", name=base)
    joint_names = set(names)  # the fixed joints' names must avoid the arm's (URDF: unique)

    def fixed_name(stem: str) -> str:
        name = f"{stem}_fixed"
        while name in joint_names:
            name += "_frame"
        joint_names.add(name)
        return name

    fixed = ET.SubElement(root, "joint", name=fixed_name(base), type="fixed")
    ET.SubElement(fixed, "parent", link=world)
    ET.SubElement(fixed, "child", link=base)
    ET.SubElement(fixed, "origin", xyz=_attr_vec(arm.base_xyz),
                  rpy=_attr_vec(arm.base_rpy))
    parent = base
    transmissions: list[tuple[str, float]] = []
    for link, jname in zip(arm.links, names, strict=True):
        el = ET.SubElement(root, "link", name=link.name)
        inertial = ET.SubElement(el, "inertial")
        ET.SubElement(inertial, "origin", xyz=_attr_vec(link.com), rpy="0.0 0.0 0.0")
        ET.SubElement(inertial, "mass", value=repr(float(link.mass)))
        I = link.inertia_com
        ET.SubElement(inertial, "inertia", ixx=repr(float(I[0, 0])), iyy=repr(float(I[1, 1])),
                      izz=repr(float(I[2, 2])), ixy=repr(float(I[0, 1])),
                      ixz=repr(float(I[0, 2])), iyz=repr(float(I[1, 2])))
        j = link.joint
        je = ET.SubElement(root, "joint", name=jname, type=j.type)
        ET.SubElement(je, "parent", link=parent)
        ET.SubElement(je, "child", link=link.name)
        ET.SubElement(je, "origin", xyz=_attr_vec(j.origin_xyz), rpy=_attr_vec(j.origin_rpy))
        ET.SubElement(je, "axis", xyz=_attr_vec(j.axis))
        lo, hi = j.position_limits
        ET.SubElement(je, "limit", lower=repr(float(lo)), upper=repr(float(hi)),
                      velocity=repr(float(j.velocity_limit)), effort=repr(float(j.effort_limit)))
        a = j.actuator
        if a.viscous or a.coulomb:
            ET.SubElement(je, "dynamics", damping=repr(float(a.viscous or 0.0)),
                          friction=repr(float(a.coulomb or 0.0)))
        if j.transmission is not None:  # motor rad per m, signed by the motor's direction
            transmissions.append((jname, link.motor.direction / j.transmission.ratio))
        parent = link.name
    for jname, reduction in transmissions:  # ros_control's form, after the joints
        tr = ET.SubElement(root, "transmission", name=f"{jname}_transmission")
        ET.SubElement(tr, "type").text = "transmission_interface/SimpleTransmission"
        ET.SubElement(ET.SubElement(tr, "joint", name=jname), "hardwareInterface").text = \
            "hardware_interface/EffortJointInterface"
        ET.SubElement(ET.SubElement(tr, "actuator", name=f"{jname}_motor"),
                      "mechanicalReduction").text = repr(float(reduction))
    # The tool frame, massless: a tool_xyz_m/tool_rpy_deg, or the last link's length_m (the
    # tool point at its end), else import would put the tool point at the last joint.
    if arm.tool_xyz is not None or arm.tool_rpy is not None or np.any(tool_offset(arm) != 0):
        taken = {link.name for link in arm.links} | {world, base}
        name = "tool"
        while name in taken:
            name += "_frame"
        tool = ET.SubElement(root, "joint", name=fixed_name(name), type="fixed")
        ET.SubElement(root, "link", name=name)
        ET.SubElement(tool, "parent", link=parent)
        ET.SubElement(tool, "child", link=name)
        ET.SubElement(tool, "origin", xyz=_attr_vec(tool_offset(arm)),
                      rpy=_attr_vec(arm.tool_rpy if arm.tool_rpy is not None else np.zeros(3)))
    ET.indent(root)
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, "unicode") + "\n"


# --------------------------------------------------------------------------------------------
# A starter scenario
# --------------------------------------------------------------------------------------------

#: The starter's motion: each joint moves by at most this around its pose (deg, or m).
STARTER_AMPLITUDE = {"revolute": 5.0, "prismatic": 0.01}
STARTER_PERIOD_S = 10.0
STARTER_OFFSET = {"revolute": 2.0, "prismatic": 0.004}  # initial error, deg or m
STARTER_DURATION_S = 20.0


def _safe_pose(lo: float, hi: float) -> float:
    """Zero when it is well inside [lo, hi] (10 % of the range from each end), else the
    middle."""
    margin = 0.1 * (hi - lo)
    return 0.0 if lo + margin <= 0.0 <= hi - margin else 0.5 * (lo + hi)


def starter_scenario(system: SerialSystem, description_ref: str) -> str:
    """A joint-space scenario for the (first) arm of ``system``: each joint a slow sinusoid of
    a few degrees (or millimetres) around a pose inside its limits, starting a little off it,
    with gains scaled to the arm's own inertia at that pose."""
    arm = system.arms[0]
    # A description every joint of which declares its drive's armature (added by hand after
    # an import, or written so): the controller carries it and the gains scale with it, as
    # the plant moves it (a 12 g gripper behind a 350:1 gearbox is mostly its rotor).
    geared = all(link.joint.actuator.armature is not None for link in arm.links)
    model = build_model(system, arm, actuators="armature" if geared else "none")
    centres, amps, starts, units = [], [], [], []
    for link in arm.links:
        j = link.joint
        lo, hi = j.position_limits
        unit = "deg" if j.type == "revolute" else "m"
        if j.type == "revolute":
            lo, hi = math.degrees(lo), math.degrees(hi)
        c = _safe_pose(lo, hi)
        a = min(STARTER_AMPLITUDE[j.type], 0.1 * (hi - lo))
        centres.append(c)
        amps.append(a)
        starts.append(c + min(STARTER_OFFSET[j.type], 0.5 * a))
        units.append(unit)
    q0 = np.array([math.radians(c) if u == "deg" else c for c, u in zip(centres, units)])
    d = np.diag(np.array(model.M(q0)))
    # Controller e: the sliding variable s = de + alpha e decays at about G_e / M_ii; with
    # G_e = 10 M_ii and K_e = 25 M_ii the loop is of the order of 5 rad/s, slow and damped.
    alpha = 5.0
    G_e = [float(f"{10.0 * x:.3g}") for x in d]
    K_e = [float(f"{25.0 * x:.3g}") for x in d]
    w = 2 * math.pi / STARTER_PERIOD_S
    # Centre and start with every digit (repr): .6g could round a pose of a tiny range onto
    # or past its limit.
    leader = [f'"{"" if c == 0 else f"{c!r} + "}{a:.6g}*sin({w:.6g}*t) {u}"'
              for c, a, u in zip(centres, amps, units)]
    start = [f'"{float(s)!r} {u}"' for s, u in zip(starts, units)]
    return "\n".join([
        f"# A starter joint-space scenario for {comment(system.path.name)}, written by "
        "cochlea-urdf "
        "import.",
        f"# Each joint moves {STARTER_AMPLITUDE['revolute']:g} deg "
        f"({STARTER_AMPLITUDE['prismatic']:g} m for a prismatic joint; at most a tenth of its "
        "range) around a pose inside its",
        f"# limits (zero where zero is well inside, else the middle), a {STARTER_PERIOD_S:g} s "
        "sinusoid, and starts",
        f"# {STARTER_OFFSET['revolute']:g} deg off it. Gains of controller e scaled to the "
        "arm's own inertia at that pose",
        "# (G_e = 10 M_ii, K_e = 25 M_ii, alpha = 5/s): conservative; tune them with "
        "cochlea-tune.",
        "# The description path is relative to this file.",
        "",
        'format = "cochlea-scenario/1"',
        'robot = "serial"',
        f"description = {toml_string(description_ref)}",
        'space = "joint"',
        f"duration_s = {STARTER_DURATION_S:g}",
        "",
        "[control]",
        "rate_Hz = 1000.0",
        'parameterisation = "base"',
        'initial_estimate = "nominal"',
        "adaptation_gain = 0.1",
        *(['actuators = "armature"'] if geared else []),
        "",
        *(["[plant]", "armature = true", ""] if geared else []),
        "[desired]",
        "leader = [" + ", ".join(leader) + "]",
        "",
        "[[unit]]",
        f"name = {toml_string(arm.name)}",
        "initial_joint = [" + ", ".join(start) + "]",
        f"gains = {{ alpha = {_vec([alpha] * len(d))}, G_e = {_vec(G_e)}, K_e = {_vec(K_e)} }}",
        "",
    ])
