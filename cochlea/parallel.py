"""The parallel system: one 5-DoF mechanism of two pantographs sharing a vertical slider.

Geometry (thesis section 2.3 and Appendix A, reconstructed in model-notes section 2). Everything
lies in one vertical plane with coordinates ``(u, v)``, ``v`` up; the world frame of this robot
is that plane, origin on the slider axis at the height of the pantograph bases.

* Generalised coordinates ``q = [th1, th2, d1, th1', th2']`` (thesis 2.27): the two motor angles
  of the left pantograph, the slider height, the two motor angles of the right pantograph. All
  angles are measured from +u, counter-clockwise.
* Slider (link 6): translates on the vertical axis ``u = 0``; its pivot is ``S = (0, d1)``.
* Left pantograph (unprimed), base ``B = (+d2, 0)``: a parallelogram of four links of length
  ``l_p``. Links 1 (angle th1) and 4 (angle th2) are driven at B; link 2 hangs from link 1's tip
  with angle th2, link 3 from link 4's tip with angle th1. Its end point is
  ``C = B + l_p (cos th1 + cos th2, sin th1 + sin th2)``, where the end-effector body (link 5,
  the magnet) sits.
* Rod 7 pivots at S and slides through a sleeve on link 5, so it and link 5 both turn with
  ``phi = atan2(C_v - d1, C_u)``: the magnet always points at S.
* Right pantograph (primed): the mirror image, base ``B' = (-d2, 0)``, its own links 1'..5', 7'
  and ``phi' = atan2(C'_v - d1, C'_u)``. Only the slider couples the two sides.

Every body's pose is an explicit function of q (the closed loops are closed by construction), so
the Lagrangian needs no multipliers: ``K`` and ``U`` are sums over the bodies, ``M = hess(K, qd)``,
Christoffel ``C`` and ``G = dU/dq`` (:mod:`cochlea.lagrange`). Each planar body carries four
parameters in its body frame, ``[m, mx, my, Izz]`` (mass, first moments ``m c``, inertia about the
body-frame origin and the plane normal), on which K and U are linear; the slider only translates,
so its mass is its only parameter.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from pathlib import Path

import casadi as ca
import numpy as np

from . import parameters as params_mod
from .description import Motor, _read_motor, _Table, open_description, resolve_path
from .errors import DescriptionError, KinematicsError, ModelError
from .lagrange import christoffel_coriolis, gravity_vector, mass_matrix, time_derivative
from .model import METHODS, JointInfo, RobotModel, assemble_model, full_inertial

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


# --------------------------------------------------------------------------------------------
# Loader
# --------------------------------------------------------------------------------------------


def _read_transmission(t: _Table) -> Transmission:
    kind = t.string("kind", tuple(TRANSMISSIONS))
    if kind == "pinion":
        size = t.number("radius_m", "a positive number (m, the pinion's pitch radius)",
                        lambda v: v > 0)
    else:
        size = t.number("lead_m", "a positive number (m of slider travel per motor revolution)",
                        lambda v: v > 0)
    t.done()
    return Transmission(kind, size)


def _read_joint(t: _Table, name: str, jtype: str) -> ParallelJoint:
    ordered = lambda v: v[0] < v[1]  # noqa: E731
    what = "as [lower, upper] with lower < upper"
    if jtype == "revolute":
        lo, hi = np.radians(t.vector("position_limits_deg", 2, "deg", check=ordered, what=what))
        velocity = t.number("velocity_limit_rad_s", "a positive number (rad/s)", lambda v: v > 0)
        effort = t.number("torque_limit_Nm", "a positive number (N m)", lambda v: v > 0)
    else:
        lo, hi = t.vector("position_limits_m", 2, "m", check=ordered, what=what)
        velocity = t.number("velocity_limit_m_s", "a positive number (m/s)", lambda v: v > 0)
        effort = t.number("force_limit_N", "a positive number (N)", lambda v: v > 0)
    motor = _read_motor(t.table("motor"))
    transmission = _read_transmission(t.table("transmission")) if jtype == "prismatic" else None
    t.done()
    return ParallelJoint(name, jtype, (float(lo), float(hi)), velocity, effort, motor,
                         transmission)


def _read_body(t: _Table, name: str) -> PlanarBody:
    mass = t.number("mass_kg", "a positive number (kg)", lambda v: v > 0)
    com = t.vector("com_m", 2, "m", what="(x, y) in the body frame")
    inertia = t.number("inertia_com_kgm2",
                       "a positive number (kg m^2, about the centre of mass and the plane "
                       "normal)", lambda v: v > 0)
    t.done()
    return PlanarBody(name, mass, com, inertia)


def _read_side(t: _Table, name: str, sign: float) -> Side:
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
    lp = geo.number("link_length_m", "a positive number (m)", positive)
    d2 = geo.number("base_offset_m", "a positive number (m)", positive)
    d3 = geo.number("rod_length_m", "a positive number (m)", positive)
    r_min = geo.number("min_pivot_distance_m",
                       f"a positive number (m) below rod_length_m = {d3:g}",
                       lambda v: 0 < v < d3)
    geo.done()

    slider = top.table("slider")
    slider_mass = slider.number("mass_kg", "a positive number (kg)", positive)
    d1 = _read_joint(slider.table("d1"), "slider.d1", "prismatic")
    slider.done()
    left = _read_side(top.table("left"), "left", 1.0)
    right = _read_side(top.table("right"), "right", -1.0)
    top.done()

    seen: dict[int, str] = {}
    for joint in (left.th1, left.th2, d1, right.th1, right.th2):
        if joint.motor.id in seen:
            raise DescriptionError(path, f"{joint.name}.motor.id",
                                   f"a motor ID not already used (by {seen[joint.motor.id]})",
                                   joint.motor.id)
        seen[joint.motor.id] = joint.name
    return ParallelSystem(name, path, gravity, lp, d2, d3, r_min, slider_mass, d1, left, right,
                          keep_out)


# --------------------------------------------------------------------------------------------
# Numerical geometry: forward and inverse kinematics, workspace, drawing points
# --------------------------------------------------------------------------------------------


def _unit(angle: float) -> np.ndarray:
    return np.array([math.cos(angle), math.sin(angle)])


def _fmt(point) -> str:
    return "(" + ", ".join(f"{v:.4f}" for v in point) + ") m"


class ParallelGeometry:
    """Closed-form kinematics of the mechanism in numbers (SI), for targets and drawings.

    ``branch`` of a pantograph: its end point C determines the two link directions up to a swap,
    ``{th1, th2} = {psi + delta, psi - delta}`` with ``psi`` the direction of ``C - B`` and
    ``cos(delta) = |C - B| / (2 l_p)``; ``branch = +1`` takes ``th1 = psi + delta`` (so
    ``th1 > th2``), ``-1`` the other. The default is ``+1`` on the left and ``-1`` on the right,
    the mirror image of each other, as in the thesis's configurations (left ``[142, 32.25] deg``,
    right ``[43, 150] deg``).
    """

    def __init__(self, system: ParallelSystem):
        self.system = system
        self.lp = system.link_length
        self.d2 = system.base_offset
        self.d3 = system.rod_length

    # ---- forward ---------------------------------------------------------------------------

    def base(self, side: Side) -> np.ndarray:
        return np.array([side.sign * self.d2, 0.0])

    def _side_q(self, q) -> dict[str, tuple[float, float]]:
        q = np.asarray(q, float).ravel()
        return {"left": (q[0], q[1]), "right": (q[3], q[4])}

    def points(self, q) -> dict[str, np.ndarray]:
        """Named points of the mechanism at q: per side ``B, A1`` (link 1's tip), ``A4`` (link 4's
        tip), ``C``, ``R`` (the rod's free end, ``S + d3 e(phi)``), and ``S``; right-side names
        carry a prime, e.g. ``"C'"``."""
        q = np.asarray(q, float).ravel()
        S = np.array([0.0, q[2]])
        out = {"S": S}
        for side in self.system.sides:
            th1, th2 = self._side_q(q)[side.name]
            mark = "" if side.name == "left" else "'"
            B = self.base(side)
            A1, A4 = B + self.lp * _unit(th1), B + self.lp * _unit(th2)
            C = A1 + self.lp * _unit(th2)
            w = C - S
            out.update({f"B{mark}": B, f"A1{mark}": A1, f"A4{mark}": A4, f"C{mark}": C,
                        f"R{mark}": S + self.d3 * w / max(np.linalg.norm(w), 1e-300)})
        return out

    def fk(self, q) -> np.ndarray:
        """``x_p = [C_u, C_v, phi, C'_u, C'_v, phi']`` (m, m, rad, m, m, rad)."""
        p = self.points(q)
        S = p["S"]
        out = []
        for mark in ("", "'"):
            C = p[f"C{mark}"]
            out += [C[0], C[1], math.atan2(C[1] - S[1], C[0])]
        return np.array(out)

    @staticmethod
    def branches(q) -> tuple[int, int]:
        """The branch of each pantograph at q (see the class docstring)."""
        q = np.asarray(q, float).ravel()
        return (1 if math.sin(q[0] - q[1]) >= 0 else -1, 1 if math.sin(q[3] - q[4]) >= 0 else -1)

    # ---- workspace -------------------------------------------------------------------------

    def violations(self, q) -> list[str]:
        """Why q is outside the workspace (empty when inside): joint limits, and on each side
        ``min_pivot_distance <= |C - S| <= d3`` (the rod must stay in the sleeve, which cannot
        reach the slider's pivot)."""
        q = np.asarray(q, float).ravel()
        problems = []
        for value, joint in zip(q, self.system.joints):
            lo, hi = joint.position_limits
            if not lo <= value <= hi:
                if joint.type == "revolute":
                    problems.append(f"{joint.name} = {math.degrees(value):.3f} deg is outside "
                                    f"[{math.degrees(lo):g}, {math.degrees(hi):g}] deg")
                else:
                    problems.append(f"{joint.name} = {value:.5f} m is outside [{lo:g}, {hi:g}] m")
        p = self.points(q)
        for side, mark in zip(self.system.sides, ("", "'")):
            r = float(np.linalg.norm(p[f"C{mark}"] - p["S"]))
            if not self.system.min_pivot_distance <= r <= self.d3:
                problems.append(f"{side.name}: |C{mark} - S| = {r:.4f} m is outside "
                                f"[{self.system.min_pivot_distance:g}, {self.d3:g}] m")
        return problems

    def in_workspace(self, q) -> bool:
        return not self.violations(q)

    def random_configuration(self, rng: np.random.Generator, tries: int = 10_000) -> np.ndarray:
        """A configuration drawn uniformly from the workspace (rejection sampling in the box of
        joint limits)."""
        lo, hi = np.array([j.position_limits for j in self.system.joints]).T
        for _ in range(tries):
            q = rng.uniform(lo, hi)
            if self.in_workspace(q):
                return q
        raise KinematicsError(f"no configuration in the workspace after {tries} random draws "
                              "within the joint limits: check the description's limits")

    # ---- inverse ---------------------------------------------------------------------------

    def slider_height(self, C, phi: float) -> float:
        """The consistency rule: the slider height ``d1`` for which the rod through ``C`` has
        angle ``phi``, ``d1 = C_v - C_u tan(phi)``.

        Raises :class:`KinematicsError` when no slider height fits: the ray from S at angle
        ``phi`` reaches C only if ``C_u cos(phi) > 0``.
        """
        Cu, Cv = (float(v) for v in np.asarray(C, float).ravel())
        c = math.cos(phi)
        if not (Cu * c > 0.0 and abs(c) > 1e-9):
            raise KinematicsError(
                f"target C = {_fmt((Cu, Cv))}, phi = {math.degrees(phi):.3f} deg is "
                "inconsistent: the rod from the slider (on u = 0) at angle phi reaches C only if "
                "C_u and cos(phi) have the same sign and neither is zero")
        return Cv - Cu * math.tan(phi)

    @staticmethod
    def mirror(C, phi: float) -> tuple[np.ndarray, float]:
        """The mirror rule: the right side's target from the left's, ``C' = (-C_u, C_v)``,
        ``phi' = pi - phi`` (wrapped into (-pi, pi] like the FK's angles)."""
        C = np.asarray(C, float).ravel()
        return np.array([-C[0], C[1]]), math.atan2(math.sin(phi), -math.cos(phi))

    def target(self, C, phi: float) -> np.ndarray:
        """A consistent task-space target ``x_p`` from the left side's ``(C, phi)``, the right
        side by the mirror rule."""
        Cr, phir = self.mirror(C, phi)
        return np.array([*np.asarray(C, float).ravel(), phi, *Cr, phir])

    def _wrap(self, angle: float, joint: ParallelJoint, check: bool) -> float:
        lo, hi = joint.position_limits
        k = math.ceil((lo - angle) / (2 * math.pi) - 1e-12)
        wrapped = angle + 2 * math.pi * k
        if wrapped <= hi + 1e-12:
            return min(max(wrapped, lo), hi) if check else wrapped
        if not check:
            return math.atan2(math.sin(angle), math.cos(angle))
        raise KinematicsError(
            f"{joint.name} = {math.degrees(angle) % 360:.3f} deg (mod 360) needed for this "
            f"target is outside its limits [{math.degrees(lo):g}, {math.degrees(hi):g}] deg")

    def side_ik(self, side: str, C, branch: int | None = None, *,
                check_limits: bool = True) -> tuple[float, float]:
        """Motor angles ``(th1, th2)`` (rad) of one pantograph that put its end point at C (m).

        Raises :class:`KinematicsError` if C is out of reach (``0 < |C - B| <= 2 l_p``) or, with
        ``check_limits``, if the angles fall outside the joint limits.
        """
        if side not in ("left", "right"):
            raise KinematicsError(f"unknown side {side!r}: choose 'left' or 'right'")
        s = self.system.left if side == "left" else self.system.right
        branch = int(s.sign) if branch is None else branch
        if branch not in (1, -1):
            raise KinematicsError(f"branch must be +1 or -1, got {branch!r}")
        C = np.asarray(C, float).ravel()
        if C.shape != (2,) or not np.all(np.isfinite(C)):
            raise KinematicsError(f"target C must be two finite numbers (m), got {C!r}")
        B = self.base(s)
        w = C - B
        r = float(np.hypot(*w))
        reach = 2.0 * self.lp
        if r > reach * (1 + 1e-12) or r < 1e-9 * reach:
            raise KinematicsError(
                f"target C = {_fmt(C)} is out of reach of the {side} pantograph: |C - B| = "
                f"{r:.4f} m from its base B = {_fmt(B)}, but the links reach "
                f"0 < |C - B| <= 2 l_p = {reach:g} m")
        psi = math.atan2(w[1], w[0])
        delta = math.acos(min(1.0, r / reach))
        th1, th2 = psi + branch * delta, psi - branch * delta
        return self._wrap(th1, s.th1, check_limits), self._wrap(th2, s.th2, check_limits)

    def side_ik_symbolic(self, side: str, C, branch: int, offsets=(0.0, 0.0)) -> ca.SX:
        """:meth:`side_ik` as an expression of a symbolic C, on a fixed branch, for desired
        trajectories whose derivatives must be exact. ``offsets`` adds whole turns chosen once.
        Valid only where C is in reach; callers check the trajectory numerically first."""
        s = self.system.left if side == "left" else self.system.right
        B = self.base(s)
        wu, wv = C[0] - B[0], C[1] - B[1]
        psi = ca.atan2(wv, wu)
        delta = ca.acos(ca.sqrt(wu ** 2 + wv ** 2) / (2.0 * self.lp))
        return ca.vertcat(psi + branch * delta + offsets[0], psi - branch * delta + offsets[1])

    def ik(self, x_p, branches: tuple[int, int] | None = None, *, check_limits: bool = True,
           tol: float = 1e-9) -> np.ndarray:
        """Joint coordinates q for a task-space target ``x_p = [C_u, C_v, phi, C'_u, C'_v,
        phi']``.

        The target must be consistent (both sides imply the same slider height, to ``tol`` m;
        build one with :meth:`target`). Raises :class:`KinematicsError`, naming the target and
        the reachable range, when it is inconsistent or outside the workspace (out of reach,
        outside the joint limits or the slider stroke, the rod out of its sleeve); never returns
        NaN.
        """
        x = np.asarray(x_p, float).ravel()
        if x.shape != (6,) or not np.all(np.isfinite(x)):
            raise KinematicsError(f"x_p must be six finite numbers [C_u, C_v, phi, C'_u, C'_v, "
                                  f"phi'] (m, m, rad, ...), got {x_p!r}")
        b_left, b_right = (None, None) if branches is None else branches
        d1 = self.slider_height(x[0:2], x[2])
        d1_right = self.slider_height(x[3:5], x[5])
        if abs(d1 - d1_right) > tol:
            raise KinematicsError(
                f"target x_p is inconsistent: the left side (C = {_fmt(x[0:2])}, phi = "
                f"{math.degrees(x[2]):.3f} deg) needs the slider at d1 = {d1:.6f} m, the right "
                f"side (C' = {_fmt(x[3:5])}, phi' = {math.degrees(x[5]):.3f} deg) at "
                f"{d1_right:.6f} m; see ParallelGeometry.target for the mirror rule")
        lo, hi = self.system.d1.position_limits
        if check_limits and not lo - 1e-12 <= d1 <= hi + 1e-12:
            raise KinematicsError(f"target needs the slider at d1 = {d1:.5f} m, outside its "
                                  f"stroke [{lo:g}, {hi:g}] m")
        th = self.side_ik("left", x[0:2], b_left, check_limits=check_limits)
        th_r = self.side_ik("right", x[3:5], b_right, check_limits=check_limits)
        q = np.array([th[0], th[1], d1, th_r[0], th_r[1]])
        if check_limits:
            r_min = self.system.min_pivot_distance
            for mark, C in (("", x[0:2]), ("'", x[3:5])):
                r = float(np.hypot(C[0], C[1] - d1))
                if not r_min <= r <= self.d3 * (1 + 1e-12):
                    raise KinematicsError(
                        f"target C{mark} = {_fmt(C)} is {r:.4f} m from the slider pivot S = "
                        f"(0, {d1:.4f}) m; the rod reaches {r_min:g} m <= |C - S| <= "
                        f"d3 = {self.d3:g} m")
        return q

    def mirrored(self, q) -> np.ndarray:
        """q with the right side replaced by the mirror rule applied to the left side's pose, on
        the mirror image of the left's branch (joint limits not checked): ``th' = pi - th``."""
        q = np.asarray(q, float).ravel().copy()
        x = self.fk(q)
        Cr, _ = self.mirror(x[0:2], x[2])
        q[3:5] = self.side_ik("right", Cr, -self.branches(q)[0], check_limits=False)
        return q


#: A named configuration: the desired start of the joint-space scenario (thesis 3.67 at t = 0),
#: the right side by the mirror rule ``th' = 180 deg - th``.
SCENARIO_START = np.array([math.radians(142.0), math.radians(32.25), 0.07075,
                           math.radians(180.0 - 142.0), math.radians(180.0 - 32.25)])


# --------------------------------------------------------------------------------------------
# Symbolic model
# --------------------------------------------------------------------------------------------


def _planar_energies(origin, cos, sin, omega, params, q, qd, gravity):
    """Kinetic and potential energy of a planar body, linear in ``params = [m, mx, my, Izz]``.

    The body frame sits at ``origin`` (an expression in q) turned by the angle whose cosine and
    sine are given, turning at ``omega``. A point at ``r`` in the body frame moves at
    ``o_dot + omega E r`` with ``E = R(angle + 90 deg)``, so
    ``K = m |o_dot|^2 / 2 + omega o_dot . (E h) + Izz omega^2 / 2`` and
    ``U = -g . (m o + R h)`` with ``h = (mx, my)``.
    """
    m, hx, hy, izz = params[0], params[1], params[2], params[3]
    v = ca.jacobian(origin, q) @ qd
    Eh = ca.vertcat(-sin * hx - cos * hy, cos * hx - sin * hy)
    Rh = ca.vertcat(cos * hx - sin * hy, sin * hx + cos * hy)
    K = 0.5 * m * ca.dot(v, v) + omega * ca.dot(v, Eh) + 0.5 * izz * omega**2
    U = -ca.dot(ca.DM(gravity), m * origin + Rh)
    return K, U


def _side_expressions(system: ParallelSystem, side: Side, th1, th2, d1, q, qd, phi_of):
    """Energies of one side's bodies, its end point C and rod angle phi, as expressions."""
    lp = system.link_length
    e = lambda a: ca.vertcat(ca.cos(a), ca.sin(a))  # noqa: E731
    B = ca.DM([side.sign * system.base_offset, 0.0])
    A1, A4 = B + lp * e(th1), B + lp * e(th2)
    C = A1 + lp * e(th2)
    S = ca.vertcat(0, d1)
    w = C - S
    r2 = ca.dot(w, w)
    r = ca.sqrt(r2)
    w_dot = ca.jacobian(w, q) @ qd
    phi_rate = (w[0] * w_dot[1] - w[1] * w_dot[0]) / r2  # d/dt atan2(w_v, w_u)
    th1_dot, th2_dot = ca.jacobian(th1, q) @ qd, ca.jacobian(th2, q) @ qd
    frames = {  # body: origin, cos, sin, angular rate
        "link1": (B + ca.SX.zeros(2), ca.cos(th1), ca.sin(th1), th1_dot),
        "link4": (B + ca.SX.zeros(2), ca.cos(th2), ca.sin(th2), th2_dot),
        "link2": (A1, ca.cos(th2), ca.sin(th2), th2_dot),
        "link3": (A4, ca.cos(th1), ca.sin(th1), th1_dot),
        "link5": (C, w[0] / r, w[1] / r, phi_rate),
        "link7": (S, w[0] / r, w[1] / r, phi_rate),
    }
    K, U = 0, 0
    for body in SIDE_BODIES:
        k, u = _planar_energies(*frames[body], phi_of(f"{side.name}.{body}"), q, qd,
                                system.gravity)
        K, U = K + k, U + u
    return K, U, C, ca.atan2(w[1], w[0])


def _full_parameters(system: ParallelSystem):
    """The full parameter set: the slider's mass, then ``[m, mx, my, Izz]`` per planar body
    (left side, then right side, proximal links first), with each body's slice."""
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
                               slider.units + planar.units, slider.meanings + planar.meanings)
    return full, blocks


def _left_pseudo_inverse(J: ca.SX) -> ca.SX:
    """``(J^T J)^-1 J^T`` of a tall J of full column rank, as ``R^-1 Q^T`` from the QR
    factorisation of J (CasADi's modified Gram-Schmidt) and back substitution.

    Solving the normal equations symbolically instead squares J's condition number and, with
    CasADi's symbolic solve, lost all accuracy near the pantographs' singular configurations
    (relative error 0.2 where ``cond(J) ~ 6e5``; QR: 2e-11).
    """
    Q, R = ca.qr(J)
    rows = [None] * R.shape[0]
    for i in reversed(range(R.shape[0])):
        acc = Q.T[i, :]
        for j in range(i + 1, R.shape[0]):
            acc = acc - R[i, j] * rows[j]
        rows[i] = acc / R[i, i]
    return ca.vertcat(*rows)


def _symbolic(system: ParallelSystem):
    """Expressions of the model in the full parameters: returns a dict of SX."""
    q = ca.SX.sym("q", 5)
    qd = ca.SX.sym("qd", 5)
    qdd = ca.SX.sym("qdd", 5)
    full, blocks = _full_parameters(system)
    phi = ca.SX.sym("phi", len(full.names))
    block_of = dict(blocks)

    def phi_of(body):
        return phi[block_of[body]]

    d1 = q[2]
    K = 0.5 * phi_of("slider")[0] * qd[2] ** 2
    U = -phi_of("slider")[0] * float(system.gravity[1]) * d1  # S = (0, d1)
    task = []
    for side, (i1, i2) in zip(system.sides, ((0, 1), (3, 4))):
        k, u, C, angle = _side_expressions(system, side, q[i1], q[i2], d1, q, qd, phi_of)
        K, U = K + k, U + u
        task += [C[0], C[1], angle]
    M = mass_matrix(K, qd)
    G = gravity_vector(U, q)
    Cor = christoffel_coriolis(M, q, qd)
    x_p = ca.vertcat(*task)
    J = ca.jacobian(x_p, q)
    A = _left_pseudo_inverse(J)
    J_dot = time_derivative(J, q, qd)
    # d/dt of (J^T J)^-1 J^T for J of full column rank, with (J^T J)^-1 = A A^T:
    A_dot = -A @ J_dot @ A + A @ A.T @ J_dot.T @ (ca.DM.eye(J.shape[0]) - J @ A)
    return dict(q=q, qd=qd, qdd=qdd, phi=phi, full=full, blocks=blocks, K=K, U=U, M=M, C=Cor,
                G=G, tau=M @ qdd + Cor @ qd + G, x_p=x_p, J=J, A=A, J_dot=J_dot, A_dot=A_dot)


def _function_prefix(name: str) -> str:
    prefix = re.sub(r"\W", "_", name)
    return prefix if prefix[:1].isalpha() else f"robot_{prefix}"


def parallel_model(parameterisation: str = "inertial", method: str = "lagrange",
                   description: str | Path | None = None) -> RobotModel:
    """The symbolic model of the parallel mechanism as a :class:`~cochlea.model.RobotModel`.

    ``method`` is recorded but has one meaning here: the closed chain's model comes from its
    energies (Lagrange); ``"newton-euler"`` (the default of :func:`cochlea.model`, made for the
    serial chain) also yields it, and ``model.method`` says ``"lagrange"``.

    Besides the Functions every model has, this one has ``A(q)`` (5x6, ``(J^T J)^-1 J^T``),
    ``A_dot(q, qd)``, ``J_dot(q, qd)`` and ``energy(q, qd) -> [K, U]`` (J, at the nominal full
    parameters; U is zero with every mass at the world origin); ``model.geometry`` is the
    :class:`ParallelGeometry` (closed-form IK, target consistency, workspace check).
    """
    if parameterisation not in params_mod.PARAMETERISATIONS:
        raise ModelError(f"unknown parameterisation {parameterisation!r}; choose one of "
                         + ", ".join(params_mod.PARAMETERISATIONS))
    if method not in METHODS:
        raise ModelError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    system = load_parallel(description if description is not None else "parallel")
    x = _symbolic(system)
    q, qd = x["q"], x["qd"]
    prefix = _function_prefix(system.name)
    kinematics = {"fk": x["x_p"], "J": x["J"], "fk_world": x["x_p"], "J_world": x["J"],
                  "A": x["A"]}
    joints = tuple(j.info() for j in system.joints)
    model = assemble_model(system.name, prefix, joints=joints, q=q, qd=qd, qdd=x["qdd"],
                           phi=x["phi"], M=x["M"], C=x["C"], G=x["G"], tau=x["tau"],
                           kinematics=kinematics, full=x["full"], bodies=x["blocks"],
                           parameterisation=parameterisation, method="lagrange",
                           source=system.path)
    nominal = ca.DM(x["full"].nominal)
    energy = ca.substitute(ca.vertcat(x["K"], x["U"]), x["phi"], nominal)
    F = ca.Function
    model.functions.update({
        "A_dot": F(f"{prefix}_A_dot", [q, qd], [x["A_dot"]], ["q", "qd"], ["A_dot"]),
        "J_dot": F(f"{prefix}_J_dot", [q, qd], [x["J_dot"]], ["q", "qd"], ["J_dot"]),
        "energy": F(f"{prefix}_energy", [q, qd], [energy], ["q", "qd"], ["energy"]),
    })
    return replace(model, geometry=ParallelGeometry(system))
