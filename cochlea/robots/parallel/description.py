"""The parallel mechanism's description: two pantographs sharing a vertical slider.

Read from a TOML file with ``kind = "parallel"`` (the shipped one: ``models/robots/
parallel.toml``); the geometry and coordinates are explained in
:mod:`cochlea.robots.parallel.model`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import parameters as params_mod
from ..description import (
    MAX_INERTIA_KGM2,
    MAX_LENGTH_M,
    MAX_MASS_KG,
    MIN_INERTIA_KGM2,
    MIN_MASS_KG,
    Actuator,
    Motor,
    Table,
    check_unique_motor_ids,
    open_description,
    read_actuator,
    read_limits,
    read_motor,
    resolve_path,
)
from ..model import JointInfo, full_inertial, with_armatures

#: Bodies of one side, in the order their parameters appear (proximal links first, so that the
#: base-parameter elimination groups distal masses into proximal inertias).
SIDE_BODIES = ("link1", "link4", "link2", "link3", "link5", "link7")

#: What each body is, and where its body frame sits (origin, x axis).
BODY_FRAMES = {
    "link1": "pantograph link 1: origin at the base B, x along the link (angle th1)",
    "link2": "pantograph link 2: origin at link 1's tip, x along the link (angle th2)",
    "link3": "pantograph link 3: origin at link 4's tip, x along the link (angle th1)",
    "link4": "pantograph link 4: origin at the base B, x along the link (angle th2)",
    "link5": "end-effector body (magnet): origin at C, x along the rod from S to C (angle phi)",
    "link7": "rod: origin at the slider pivot S, x along the rod towards C (angle phi)",
}

#: The sides: name, sign of the base's u coordinate (B = (sign * d2, 0)).
SIDES = (("left", 1.0), ("right", -1.0))

#: Parameters of a planar body, in its body frame.
PLANAR_NAMES = ("m", "mx", "my", "Izz")
PLANAR_MEANING = {
    "m": ("mass", "kg"),
    "mx": ("first moment of mass m*c_x in the body frame", "kg m"),
    "my": ("first moment of mass m*c_y in the body frame", "kg m"),
    "Izz": ("inertia about the body-frame origin, plane normal", "kg m^2"),
}
SLIDER_MEANING = {"m": ("mass (it only translates: nothing else of it enters the dynamics)",
                        "kg")}

#: Order of the generalised coordinates: (side, joint key in the description).
JOINT_ORDER = (("left", "th1"), ("left", "th2"), ("slider", "d1"), ("right", "th1"),
               ("right", "th2"))

#: Kinds of slider transmission a description may name, and the key of their size.
TRANSMISSIONS = {"pinion": "radius_m", "lead_screw": "lead_m"}


# --------------------------------------------------------------------------------------------
# Description dataclasses (SI units)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlanarBody:
    """A rigid body moving in the (u, v) plane, its inertial data in its body frame (SI)."""

    name: str
    mass: float  # kg
    com: np.ndarray  # m, (x, y) in the body frame
    inertia_com: float  # kg m^2, about the centre of mass and the plane normal

    def inertial_parameters(self) -> np.ndarray:
        """``[m, mx, my, Izz]``: first moments ``m c`` and inertia about the body-frame origin."""
        m, c = self.mass, self.com
        return np.array([m, m * c[0], m * c[1], self.inertia_com + m * float(c @ c)])


@dataclass(frozen=True)
class Transmission:
    """How the slider's motor moves it: a pinion on a rack or a lead screw, ideal (lossless)."""

    kind: str  # "pinion" | "lead_screw"
    size: float  # m: the pinion's pitch radius, or the screw's lead (travel per revolution)

    @property
    def ratio(self) -> float:
        """Slider travel per motor angle, m/rad."""
        return self.size if self.kind == "pinion" else self.size / (2.0 * math.pi)

    def motor_torque(self, force):
        """Motor torque (N m) that exerts ``force`` (N) on the slider."""
        return np.asarray(force) * self.ratio

    def motor_angle(self, d1):
        """Motor angle (rad) at slider height ``d1`` (m), zero at ``d1 = 0``."""
        return np.asarray(d1) / self.ratio


@dataclass(frozen=True)
class ParallelJoint:
    name: str  # e.g. "left.th1", "slider.d1"
    type: str  # "revolute" | "prismatic"
    position_limits: tuple[float, float]  # rad or m
    velocity_limit: float  # rad/s or m/s
    effort_limit: float  # N m or N
    motor: Motor
    transmission: Transmission | None = None  # the prismatic joint's drive
    #: What the joint's drive adds to the rigid links: armature and friction.
    actuator: Actuator = Actuator()

    def info(self) -> JointInfo:
        return JointInfo(self.name, self.type, self.position_limits, self.velocity_limit,
                         self.effort_limit)


@dataclass(frozen=True)
class Side:
    """One pantograph with its end-effector body and rod."""

    name: str  # "left" | "right"
    sign: float  # +1: base at (+d2, 0); -1: base at (-d2, 0)
    bodies: tuple[PlanarBody, ...]  # in SIDE_BODIES order
    th1: ParallelJoint
    th2: ParallelJoint

    def body(self, name: str) -> PlanarBody:
        return self.bodies[SIDE_BODIES.index(name)]


@dataclass(frozen=True)
class ParallelSystem:
    name: str
    path: Path
    gravity: np.ndarray  # m/s^2, (u, v)
    link_length: float  # m, l_p
    base_offset: float  # m, d2
    rod_length: float  # m, d3
    min_pivot_distance: float  # m, smallest |C - S| the sleeve allows
    slider_mass: float  # kg
    d1: ParallelJoint
    left: Side
    right: Side
    keep_out_radius: float = 0.0  # m, R_m: the end effectors stay this far from S (safety)

    @property
    def sides(self) -> tuple[Side, Side]:
        return (self.left, self.right)

    @property
    def joints(self) -> tuple[ParallelJoint, ...]:
        """The five joints in the order of q: th1, th2, d1, th1', th2'."""
        return (self.left.th1, self.left.th2, self.d1, self.right.th1, self.right.th2)


def full_parameters(system: ParallelSystem):
    """The full parameter set of the model and the block form (:mod:`.model`, :mod:`.forward`):
    the slider's mass, then ``[m, mx, my, Izz]`` per planar body (left side, then right side,
    proximal links first), then the armature of each joint whose drive declares one, with each
    body's slice."""
    slider, slider_blocks = full_inertial([("slider", np.array([system.slider_mass]))],
                                          names=("m",), meanings=SLIDER_MEANING)
    planar, planar_blocks = full_inertial(
        [(f"{side.name}.{b}", side.body(b).inertial_parameters()) for side in system.sides
         for b in SIDE_BODIES], names=PLANAR_NAMES, meanings=PLANAR_MEANING)
    n0 = len(slider.names)
    blocks = slider_blocks + [(body, slice(s.start + n0, s.stop + n0))
                              for body, s in planar_blocks]
    full = params_mod.inertial(slider.names + planar.names,
                               np.concatenate([slider.nominal, planar.nominal]),
                               slider.si_units + planar.si_units, slider.meanings + planar.meanings)
    return with_armatures(full, blocks, [(j.name, j.type, j.actuator.armature)
                                         for j in system.joints])


# --------------------------------------------------------------------------------------------
# Loader
# --------------------------------------------------------------------------------------------


def _read_transmission(t: Table) -> Transmission:
    kind = t.string("kind", tuple(TRANSMISSIONS))
    if kind == "pinion":
        size = t.bounded("radius_m", "a positive number (m, the pinion's pitch radius)",
                         lambda v: v > 0, 0, MAX_LENGTH_M, "m")
    else:
        size = t.bounded("lead_m", "a positive number (m of slider travel per motor "
                         "revolution)", lambda v: v > 0, 0, MAX_LENGTH_M, "m")
    t.done()
    return Transmission(kind, size)


def _read_joint(t: Table, name: str, jtype: str) -> ParallelJoint:
    lo, hi, velocity, effort = read_limits(t, jtype)
    actuator = read_actuator(t, jtype)
    motor = read_motor(t.table("motor"))
    transmission = _read_transmission(t.table("transmission")) if jtype == "prismatic" else None
    t.done()
    return ParallelJoint(name, jtype, (lo, hi), velocity, effort, motor, transmission,
                         actuator)


def _read_body(t: Table, name: str) -> PlanarBody:
    mass = t.bounded("mass_kg", "a positive number (kg)", lambda v: v > 0, MIN_MASS_KG,
                     MAX_MASS_KG, "kg")
    com = t.vector("com_m", 2, "m", check=lambda v: all(abs(x) <= MAX_LENGTH_M for x in v),
                   what=f"(x, y) in the body frame, each within +-{MAX_LENGTH_M:g} m")
    inertia = t.bounded("inertia_com_kgm2", "a positive number (kg m^2, about the centre of "
                        "mass and the plane normal)", lambda v: v > 0, MIN_INERTIA_KGM2,
                        MAX_INERTIA_KGM2, "kg m^2")
    t.done()
    return PlanarBody(name, mass, com, inertia)


def _read_side(t: Table, name: str, sign: float) -> Side:
    bodies = tuple(_read_body(t.table(b), f"{name}.{b}") for b in SIDE_BODIES)
    th1 = _read_joint(t.table("th1"), f"{name}.th1", "revolute")
    th2 = _read_joint(t.table("th2"), f"{name}.th2", "revolute")
    t.done()
    return Side(name, sign, bodies, th1, th2)


def load_parallel(name_or_path: str | Path = "parallel") -> ParallelSystem:
    """Load and validate a description of the parallel mechanism (``kind = "parallel"``)."""
    path = resolve_path(name_or_path)
    top, name, gravity, keep_out = open_description(
        path, "parallel", 2, "in the (u, v) plane, v up",
        "the slider pivot S that the end effectors")

    geo = top.table("geometry")
    positive = lambda v: v > 0  # noqa: E731
    lp = geo.bounded("link_length_m", "a positive number (m)", positive, 0, MAX_LENGTH_M, "m")
    d2 = geo.bounded("base_offset_m", "a positive number (m)", positive, 0, MAX_LENGTH_M, "m")
    d3 = geo.bounded("rod_length_m", "a positive number (m)", positive, 0, MAX_LENGTH_M, "m")
    r_min = geo.number("min_pivot_distance_m",
                       f"a positive number (m) below rod_length_m = {d3:g}",
                       lambda v: 0 < v < d3)
    geo.done()

    slider = top.table("slider")
    slider_mass = slider.bounded("mass_kg", "a positive number (kg)", positive, MIN_MASS_KG,
                                 MAX_MASS_KG, "kg")
    d1 = _read_joint(slider.table("d1"), "slider.d1", "prismatic")
    slider.done()
    left = _read_side(top.table("left"), "left", 1.0)
    right = _read_side(top.table("right"), "right", -1.0)
    top.done()

    check_unique_motor_ids(path, [(f"{j.name}.motor.id", j.name, j.motor)
                                  for j in (left.th1, left.th2, d1, right.th1, right.th2)])
    return ParallelSystem(name, path, gravity, lp, d2, d3, r_min, slider_mass, d1, left, right,
                          keep_out)


