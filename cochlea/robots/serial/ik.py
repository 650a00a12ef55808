"""Inverse kinematics: the closed form of a planar 3R arm, symbolic (for trajectories) and
numeric, and a numeric solver for any chain and task space (:func:`solve_ik`, below).

The tool pose ``[x, y, phi]`` fixes the wrist point ``w = p - l3 (cos phi, sin phi)``; the first
two links reach ``w`` with the elbow on one of two sides, ``elbow = +1`` (``th2 >= 0``) or
``elbow = -1`` (``th2 <= 0``). The branch is always an explicit choice: numerically it is taken
nearest to a reference configuration, then kept fixed along a trajectory.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from ...errors import KinematicsError, ModelError
from .description import Arm


class UnreachableTarget(KinematicsError):
    """A task-space target lies outside the arm's workspace."""


def planar_3r_lengths(arm: Arm) -> tuple[float, float, float]:
    """Link lengths of a planar 3R arm; refuses chains the closed form does not describe."""
    ok = len(arm.links) == 3 and arm.tool_xyz is None and arm.tool_rpy is None
    for i, link in enumerate(arm.links if ok else ()):
        j = link.joint
        parent_length = arm.links[i - 1].length if i else 0.0
        ok &= (j.type == "revolute" and np.allclose(j.axis, [0, 0, 1])
               and np.allclose(j.origin_rpy, 0) and np.allclose(j.origin_xyz,
                                                               [parent_length, 0, 0]))
    if not ok:
        raise ModelError(f"arm {arm.name!r}: closed-form inverse kinematics needs a planar 3R "
                         "arm (revolute z axes, each joint at the previous link's tip)")
    return tuple(link.length for link in arm.links)


def world_to_base(arm: Arm, pose_world):
    """A tool pose ``[x, y, phi]`` (m, m, rad) from the cochlea frame into the arm's base frame."""
    c, s = np.cos(arm.base_yaw), np.sin(arm.base_yaw)
    dx = pose_world[0] - arm.base_xyz[0]
    dy = pose_world[1] - arm.base_xyz[1]
    return [c * dx + s * dy, -s * dx + c * dy, pose_world[2] - arm.base_yaw]


def elbow_cosine(arm: Arm, pose_base):
    """``cos th2`` of the pose; the pose is reachable iff it lies in [-1, 1]."""
    l1, l2, l3 = planar_3r_lengths(arm)
    x, y, phi = pose_base[0], pose_base[1], pose_base[2]
    wx, wy = x - l3 * ca.cos(phi), y - l3 * ca.sin(phi)
    return (wx**2 + wy**2 - l1**2 - l2**2) / (2 * l1 * l2)


def ik_symbolic(arm: Arm, pose_base, elbow: int, offsets=(0.0, 0.0, 0.0)) -> ca.SX:
    """Joint angles (rad) reaching ``pose_base`` on the given elbow branch, as an expression.

    ``offsets`` adds whole turns (2 pi k) chosen once so the solution is continuous with a
    reference configuration. Valid only where :func:`elbow_cosine` is inside [-1, 1]; callers
    check reachability over the whole trajectory before using it.
    """
    l1, l2, l3 = planar_3r_lengths(arm)
    x, y, phi = pose_base[0], pose_base[1], pose_base[2]
    wx, wy = x - l3 * ca.cos(phi), y - l3 * ca.sin(phi)
    c2 = (wx**2 + wy**2 - l1**2 - l2**2) / (2 * l1 * l2)
    th2 = elbow * ca.acos(c2)
    th1 = ca.atan2(wy, wx) - ca.atan2(l2 * ca.sin(th2), l1 + l2 * ca.cos(th2))
    th3 = phi - th1 - th2
    return ca.vertcat(th1 + offsets[0], th2 + offsets[1], th3 + offsets[2])


def ik(arm: Arm, pose_world, reference_q) -> tuple[np.ndarray, int, np.ndarray]:
    """Joint angles (rad) for a tool pose in the cochlea frame, nearest to ``reference_q``.

    Returns ``(q, elbow, offsets)``: the branch and whole-turn offsets used, so a trajectory can
    keep them. Raises :class:`UnreachableTarget` outside the workspace.
    """
    pose_base = world_to_base(arm, pose_world)
    c2 = float(elbow_cosine(arm, pose_base))
    if not -1.0 <= c2 <= 1.0:
        l1, l2, l3 = planar_3r_lengths(arm)
        raise UnreachableTarget(
            f"arm {arm.name!r}: the tool pose x = {pose_world[0]:.4f} m, y = {pose_world[1]:.4f} m,"
            f" phi = {np.degrees(pose_world[2]):.2f} deg (cochlea frame) is out of reach: its "
            f"wrist point must lie between {abs(l1 - l2):.4f} m and {l1 + l2:.4f} m from the base")
    reference_q = np.asarray(reference_q, float)
    best = None
    for elbow in (1, -1):
        q = np.array(ik_symbolic(arm, ca.DM(pose_base), elbow)).ravel()
        offsets = 2 * np.pi * np.round((reference_q - q) / (2 * np.pi))
        q = q + offsets
        distance = np.linalg.norm(q - reference_q)
        if best is None or distance < best[0]:
            best = (distance, q, elbow, offsets)
    return best[1], best[2], best[3]


# --------------------------------------------------------------------------------------------
# Numeric inverse kinematics: any chain, any task space (cochlea.robots.serial.task)
# --------------------------------------------------------------------------------------------


class SingularTarget(KinematicsError):
    """A task-space target is reached only at a singular configuration of the arm (its task
    Jacobian loses rank there): the task-space controller cannot be used there."""


class TaskSizeError(KinematicsError):
    """The arm's joints and the task's coordinates do not fit (a deficient arm for inverse
    kinematics, or a non-square task Jacobian for the task-space controller)."""


#: Numeric IK: a solution when the residual's norm (m and rad alike) is below this.
IK_TOLERANCE = 1e-10
#: Iterations of one Levenberg-Marquardt solve from one seed.
IK_ITERATIONS = 200
#: Seeds tried beyond the caller's: the limits' middle, then random ones within the limits
#: (a fixed generator: the same target gives the same answer).
IK_RANDOM_SEEDS = 24
#: A reached target is singular when the task Jacobian's smallest singular value is below
#: this fraction of its largest.
SINGULAR_RATIO = 1e-6


def joint_limits(arm: Arm) -> tuple[np.ndarray, np.ndarray]:
    lo = np.array([link.joint.position_limits[0] for link in arm.links], float)
    hi = np.array([link.joint.position_limits[1] for link in arm.links], float)
    return lo, hi


def _levenberg_marquardt(residual, target, q, lo, hi, iterations=IK_ITERATIONS):
    """Damped least squares from ``q``, each step projected into the limits; returns
    ``(q, |e|)``."""
    e, J, _ = (np.array(v, float) for v in residual(q, target))
    e = e.ravel()
    cost = float(e @ e)
    lam = 1e-3
    for _ in range(iterations):
        if cost < IK_TOLERANCE ** 2:
            break
        JtJ = J.T @ J
        step = np.linalg.solve(JtJ + lam * (np.trace(JtJ) / len(q) + 1e-12) * np.eye(len(q)),
                               J.T @ e)
        q_new = np.clip(q - step, lo, hi)
        e_new, J_new, _ = (np.array(v, float) for v in residual(q_new, target))
        e_new = e_new.ravel()
        cost_new = float(e_new @ e_new)
        if cost_new < cost:
            q, e, J, cost = q_new, e_new, J_new, cost_new
            lam = max(lam / 3.0, 1e-12)
        else:
            lam *= 4.0
            if lam > 1e8:
                break
    return q, math.sqrt(cost)


def _describe(space, target) -> str:
    parts = []
    for name, unit, value in zip(space.names, space.units, np.asarray(target, float)):
        parts.append(f"{name} = {math.degrees(value):.2f} deg" if unit == "rad"
                     else f"{name} = {value:.4f} m")
    return ", ".join(parts)


def check_sizes(arm: Arm, space, square: bool) -> None:
    """Refuse, in one line naming the sizes, a task the arm cannot serve: fewer joints than
    task coordinates (inverse kinematics), or (``square``: controller g) any other number."""
    n, m = len(arm.links), space.size
    if n < m or (square and n != m):
        kind = "deficient" if n < m else "redundant"
        need = ("a square task Jacobian (as many joints as task coordinates)" if square
                else "at least as many joints as task coordinates")
        raise TaskSizeError(
            f"arm {arm.name!r} has {n} joints and task {space.task!r} has {m} coordinates "
            f"({', '.join(space.names)}): a {kind} arm; this needs {need}; choose another "
            "[control] task")


def solve_ik(arm: Arm, space, target, seeds=(), elbow: int | None = None,
             residual: ca.Function | None = None) -> np.ndarray:
    """Joint position (SI) within the joint limits whose task pose is ``target`` (world frame,
    in ``space``'s coordinates), by Levenberg-Marquardt from each seed: the caller's
    ``seeds`` first, then the limits' middle and :data:`IK_RANDOM_SEEDS` random ones. Of the
    solutions found, the one nearest the first seed (``elbow``: only those whose second joint
    has that sign). Raises :class:`UnreachableTarget` when no seed reaches the target and
    :class:`SingularTarget` when it is reached only at a singular configuration."""
    check_sizes(arm, space, square=False)
    residual = residual or space.residual()
    target = np.asarray(target, float)
    lo, hi = joint_limits(arm)
    mid = np.where(np.isfinite(lo + hi), 0.5 * (lo + hi), 0.0)
    rng = np.random.default_rng(0)
    span_lo, span_hi = np.maximum(lo, -np.pi), np.minimum(hi, np.pi)
    starts = [np.clip(np.asarray(s, float), lo, hi) for s in seeds] + [mid]
    starts += [rng.uniform(span_lo, span_hi) for _ in range(IK_RANDOM_SEEDS)]
    reference = starts[0]
    found, best = [], np.inf
    for k, start in enumerate(starts):
        q, r = _levenberg_marquardt(residual, target, start, lo, hi)
        best = min(best, r)
        if r < 1e-8 and (elbow is None or len(q) < 2 or np.sign(q[1]) == elbow):
            found.append(q)
            if k < len(seeds):  # a caller's seed reached it: the branch it asked for
                break
    if not found:
        branch = f" on elbow branch {elbow:+d}" if elbow is not None else ""
        raise UnreachableTarget(
            f"arm {arm.name!r}: the task target {_describe(space, target)} (task "
            f"{space.task!r}, world frame) is out of reach{branch} within the joint limits "
            f"(the closest of {len(starts)} starts is {best:.3g} away)")
    q = min(found, key=lambda x: float(np.linalg.norm(x - reference)))
    _, _, J = residual(q, target)
    s = np.linalg.svd(np.array(J, float), compute_uv=False)
    if s[-1] < SINGULAR_RATIO * max(s[0], 1e-300):
        raise SingularTarget(
            f"arm {arm.name!r}: the task target {_describe(space, target)} (task "
            f"{space.task!r}) is reached only at a singular configuration (the task Jacobian's "
            f"singular values range {s[-1]:.2g} to {s[0]:.2g}): move it inside the workspace")
    return q


def follow_path(arm: Arm, space, targets: np.ndarray, times: np.ndarray, q0: np.ndarray
                ) -> np.ndarray:
    """Joint positions along sampled task targets (``(m, N)``), each solved from the one
    before (continuation from ``q0``: the configuration the arm moves through), ``(n, N)``.
    :class:`UnreachableTarget` names the first time the continued solution is lost: out of
    reach within the limits, or (the message says so) reachable only on another branch, which
    the arm cannot jump to; :class:`SingularTarget` the first singular configuration."""
    residual = space.residual()
    lo, hi = joint_limits(arm)
    q = np.asarray(q0, float)
    out = np.empty((len(q), targets.shape[1]))
    for k in range(targets.shape[1]):
        q_new, r = _levenberg_marquardt(residual, targets[:, k], q, lo, hi)
        if r >= 1e-8:
            try:
                solve_ik(arm, space, targets[:, k], seeds=(q,), residual=residual)
            except KinematicsError as exc:
                raise type(exc)(f"at t = {times[k]:.3f} s: {exc}") from None
            raise UnreachableTarget(
                f"arm {arm.name!r}: at t = {times[k]:.3f} s the task target "
                f"{_describe(space, targets[:, k])} (task {space.task!r}) is reached only on "
                "another branch than the arm's configuration so far (the joints it moves "
                "through reach a limit or a singularity first)")
        _, _, J = residual(q_new, targets[:, k])
        s = np.linalg.svd(np.array(J, float), compute_uv=False)
        if s[-1] < SINGULAR_RATIO * max(s[0], 1e-300):
            raise SingularTarget(
                f"arm {arm.name!r}: at t = {times[k]:.3f} s the task target "
                f"{_describe(space, targets[:, k])} (task {space.task!r}) is reached only at a "
                "singular configuration of the arm")
        q = out[:, k] = q_new
    return out
