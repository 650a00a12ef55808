"""Task spaces of a serial arm: the tool coordinates a scenario tracks (``[control] task``).

=============  ==============================  =====================================
 task           coordinates (world frame)        error the controller drives to zero
=============  ==============================  =====================================
 planar         x, y (m)                        x - x_d
 planar_yaw     x, y (m), phi (rad, about z)    x - x_d, phi's wrapped to (-pi, pi]
 position       x, y, z (m)                     x - x_d
 position_yaw   x, y, z (m), phi (rad)          x - x_d, phi's wrapped to (-pi, pi]
 pose           x, y, z (m), roll, pitch,       position: p - p_d; orientation:
                yaw (rad, fixed-axis)           e_o = vee(R_d' R - R' R_d) / 2
=============  ==============================  =====================================

``planar_yaw`` is the default and what the shipped planar arms track (the thesis's study):
for an arm whose base only turns about z it is exactly the model's ``fk_world``.

The orientation error of ``pose`` is the vector part of the rotation error ``R_e = R_d' R``
(the desired frame to the tool frame), ``e_o = sin(theta) u`` for ``R_e`` a rotation by
``theta`` about ``u``, expressed in the desired frame: smooth everywhere (unlike the rotation
vector ``theta u``, whose derivative is 0/0 at zero error), equal to the rotation vector to
first order, and zero only at ``theta = 0`` or ``theta = pi``. Its Jacobian in ``q`` is
singular at ``theta = 90 deg``, so a run must start and stay within 90 deg of the desired
orientation (the adapter refuses an initial error beyond :data:`MAX_ORIENTATION_ERROR`).
The desired orientation is given in the scenario as fixed-axis roll, pitch, yaw
(``R_d = Rz(yaw) Ry(pitch) Rx(roll)``); the logged pose is the tool's roll, pitch, yaw
(``atan2`` forms, exact away from pitch = +-90 deg).

The tool point is the arm's ``tool_xyz_m`` in the last link's frame (default ``[length_m, 0,
0]``), the tool frame the last link's turned by ``tool_rpy_deg`` (default: none).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ...errors import ModelError
from ..model import RobotModel
from .chain import is_planar, tool_point
from .description import Arm

TASKS = ("planar", "planar_yaw", "position", "position_yaw", "pose")
DEFAULT_TASK = "planar_yaw"
_NAMES = {"planar": ("x", "y"), "planar_yaw": ("x", "y", "phi"), "position": ("x", "y", "z"),
          "position_yaw": ("x", "y", "z", "phi"), "pose": ("x", "y", "z", "roll", "pitch", "yaw")}
_ANGLES = {"planar": (), "planar_yaw": (2,), "position": (), "position_yaw": (3,),
           "pose": (3, 4, 5)}
#: rad: the largest initial orientation error a ``pose`` run may start with (below the 90 deg
#: where the error's Jacobian is singular, with a margin).
MAX_ORIENTATION_ERROR = math.radians(80.0)


def task_kinds(task: str) -> tuple[str, ...]:
    """``"length"`` | ``"angle"`` per coordinate of a task space."""
    check_task(task)
    return tuple("angle" if i in _ANGLES[task] else "length" for i in range(len(_NAMES[task])))


def check_task(task: str) -> None:
    if task not in TASKS:
        raise ModelError(f"unknown task space {task!r}; choose one of " + ", ".join(TASKS))


@dataclass(frozen=True)
class TaskSpace:
    """One arm's task coordinates: ``fk`` (q -> the logged task pose), ``J`` (its Jacobian),
    and for ``pose`` the controller's ``error`` ((q, x_d) -> e, see the module's table)."""

    task: str
    names: tuple[str, ...]
    units: tuple[str, ...]
    angles: tuple[int, ...]
    fk: ca.Function = field(repr=False)
    J: ca.Function = field(repr=False)
    error: ca.Function | None = field(default=None, repr=False)
    #: True when ``fk`` and ``J`` are the model's own ``fk_world`` and ``J_world``.
    model_pose: bool = False
    #: ``q -> (p, R)``: the tool point and rotation in the world frame (``pose`` only).
    _tool: ca.Function | None = field(default=None, repr=False)

    @property
    def size(self) -> int:
        return len(self.names)

    def residual(self) -> ca.Function:
        """``(q, x_d) -> (r, dr/dq, de/dq)``: what inverse kinematics drives to zero (angles
        wrapped), its Jacobian, and the Jacobian of the controller's error ``e`` (square for
        controller g: its singular values tell a singular target). For ``pose``, ``r`` is the
        position error and ``R_d' R - I`` (zero only at the target; ``e``'s orientation part
        ``sin(theta) u`` also vanishes at theta = 180 deg)."""
        n = self.fk.size1_in(0)
        q, xd = ca.SX.sym("q", n), ca.SX.sym("xd", self.size)
        if self.error is not None:
            e = self.error(q, xd)
            p, R = self._tool(q)
            r = ca.vertcat(p - xd[0:3], ca.vec(rpy_sx(xd[3:6]).T @ R - ca.DM.eye(3)))
        else:
            d = self.fk(q) - xd
            e = r = ca.vertcat(*[ca.atan2(ca.sin(d[i]), ca.cos(d[i])) if i in self.angles
                                 else d[i] for i in range(self.size)])
        return ca.Function(f"{self.fk.name()}_residual", [q, xd],
                           [r, ca.jacobian(r, q), ca.jacobian(e, q)])


def rpy_sx(rpy) -> ca.SX:
    """Fixed-axis roll-pitch-yaw to a rotation matrix, ``Rz(yaw) Ry(pitch) Rx(roll)``
    (symbolic)."""
    r, p, y = rpy[0], rpy[1], rpy[2]
    cr, sr, cp, sp, cy, sy = ca.cos(r), ca.sin(r), ca.cos(p), ca.sin(p), ca.cos(y), ca.sin(y)
    return ca.vertcat(
        ca.horzcat(cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
        ca.horzcat(sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
        ca.horzcat(-sp, cp * sr, cp * cr))


def rpy_of_matrix(R) -> ca.SX:
    """Fixed-axis roll, pitch, yaw of a rotation matrix (exact away from pitch = +-90 deg)."""
    return ca.vertcat(ca.atan2(R[2, 1], R[2, 2]),
                      ca.atan2(-R[2, 0], ca.sqrt(R[2, 1] ** 2 + R[2, 2] ** 2)),
                      ca.atan2(R[1, 0], R[0, 0]))


def orientation_error(R, R_d) -> ca.SX:
    """``vee(R_d' R - R' R_d) / 2 = sin(theta) u`` of the rotation error ``R_d' R``."""
    E = R_d.T @ R
    return 0.5 * ca.vertcat(E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1])


def tool_world(arm: Arm, q) -> tuple[ca.SX, ca.SX]:
    """The tool point and the tool frame's rotation in the world frame."""
    p, R = tool_point(arm, q)
    Rb = ca.DM(arm.base_rotation)
    return ca.DM(arm.base_xyz) + Rb @ p, Rb @ R


def task_space(arm: Arm, task: str, model: RobotModel | None = None) -> TaskSpace:
    """The arm's task space ``task`` (:data:`TASKS`); with ``model`` (the arm's), the default
    task of an arm on a level base is the model's own ``fk_world`` and ``J_world``."""
    check_task(task)
    names, angles = _NAMES[task], _ANGLES[task]
    units = tuple("rad" if i in angles else "m" for i in range(len(names)))
    if task == "planar_yaw" and model is not None and arm.base_is_level:
        return TaskSpace(task, names, units, angles, model.fk_world, model.J_world,
                         model_pose=True)
    n = len(arm.links)
    q = ca.SX.sym("q", n)
    p, R = tool_world(arm, q)
    error = None
    if task == "planar":
        x = p[0:2]
    elif task in ("planar_yaw", "position_yaw"):
        if is_planar(arm) and arm.base_is_level:  # unwrapped, as the model's
            phi = ca.SX(arm.base_yaw + sum(float(link.joint.origin_rpy[2])
                                           for link in arm.links)
                        + (float(arm.tool_rpy[2]) if arm.tool_rpy is not None else 0.0))
            for i, link in enumerate(arm.links):
                if link.joint.type == "revolute":
                    phi = phi + float(np.sign(link.joint.axis[2])) * q[i]
        else:
            phi = ca.atan2(R[1, 0], R[0, 0])
        x = ca.vertcat(p[0], p[1], phi) if task == "planar_yaw" else ca.vertcat(p, phi)
    elif task == "position":
        x = p
    else:
        x = ca.vertcat(p, rpy_of_matrix(R))
        xd = ca.SX.sym("xd", 6)
        e = ca.vertcat(p - xd[0:3], orientation_error(R, rpy_sx(xd[3:6])))
        error = ca.Function(f"{arm.name}_{task}_error", [q, xd], [e], ["q", "xd"], ["e"])
    fk = ca.Function(f"{arm.name}_{task}_fk", [q], [x], ["q"], ["x"])
    J = ca.Function(f"{arm.name}_{task}_J", [q], [ca.jacobian(x, q)], ["q"], ["J"])
    tool = ca.Function(f"{arm.name}_tool", [q], [p, R]) if error is not None else None
    return TaskSpace(task, names, units, angles, fk, J, error, _tool=tool)


def mirrored(task: str, pose) -> ca.SX:
    """The dual-arm rule on a task pose (world frame): the pose turned by 180 deg about the
    world z axis through the cochlea centre (a point reflection in the plane, the tool facing
    the other's)."""
    if task == "planar":
        return ca.vertcat(-pose[0], -pose[1])
    if task == "planar_yaw":
        return ca.vertcat(-pose[0], -pose[1], pose[2] + np.pi)
    if task == "position":
        return ca.vertcat(-pose[0], -pose[1], pose[2])
    if task == "position_yaw":
        return ca.vertcat(-pose[0], -pose[1], pose[2], pose[3] + np.pi)
    return ca.vertcat(-pose[0], -pose[1], pose[2], pose[3], pose[4], pose[5] + np.pi)

