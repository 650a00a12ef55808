"""What an excitation of one serial arm must respect beyond its joint limits (``cochlea-excite``,
:mod:`cochlea.ident.excite`): every link segment outside the cochlea keep-out circle, with a
margin, and clear of the other arm, which holds still at its working pose."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from ...errors import CochleaError
from ..adapter import ExcitationGeometry
from .chain import link_poses, tool_point
from .description import SerialSystem

#: Margins of the design inside the limits the result is checked against (m): the keep-out
#: circle and the clearance between the arms.
KEEP_OUT_MARGIN = 0.002
CLEARANCE_MARGIN = 0.005
#: Sharpness (1/m) of the soft minimum over the arms' segment distances: it undershoots the
#: true minimum by at most log(count) / SOFTMIN_SHARPNESS (~4 mm), on the safe side.
SOFTMIN_SHARPNESS = 1000.0


def arm_segments(arm) -> ca.Function:
    """``q -> 2 x 4`` points of an arm in the world (cochlea) frame: its base, the joints
    2..n and the tool; consecutive points bound its links."""
    q = ca.SX.sym("q", len(arm.links))
    poses = link_poses(arm, q)
    points = [p for _, p in poses] + [tool_point(arm, q)[0]]
    yaw = arm.base_yaw
    R = ca.DM([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    base = ca.DM(arm.base_xyz[:2])
    world = [base + R @ p[:2] for p in points]
    return ca.Function(f"{arm.name}_points", [q], [ca.horzcat(*world)])


def point_segment(p, a, b):
    """Distance from point p to segment [a, b] (2-vectors; CasADi or numpy)."""
    ab = b - a
    length2 = ab[0] ** 2 + ab[1] ** 2
    s = ((p[0] - a[0]) * ab[0] + (p[1] - a[1]) * ab[1]) / length2
    s = ca.fmin(ca.fmax(s, 0.0), 1.0)
    dx, dy = p[0] - a[0] - s * ab[0], p[1] - a[1] - s * ab[1]
    return ca.sqrt(dx ** 2 + dy ** 2 + 1e-12)


def segment_distance(a1, b1, a2, b2) -> float:
    """Distance between two segments of the plane (numbers): zero when they cross."""
    a1, b1, a2, b2 = (np.asarray(v, float) for v in (a1, b1, a2, b2))

    def cross(o, p, r):
        return (p[0] - o[0]) * (r[1] - o[1]) - (p[1] - o[1]) * (r[0] - o[0])

    d1, d2 = cross(a2, b2, a1), cross(a2, b2, b1)
    d3, d4 = cross(a1, b1, a2), cross(a1, b1, b2)
    if d1 * d2 < 0 and d3 * d4 < 0:
        return 0.0
    return float(min(point_segment(a1, a2, b2), point_segment(b1, a2, b2),
                     point_segment(a2, a1, b1), point_segment(b2, a1, b1)))


def _softmin(values, sharpness: float):
    """A smooth lower bound of min(values) (a CasADi column), within log(len)/sharpness."""
    m = ca.mmin(values)
    return m - ca.log(ca.sum1(ca.exp(-sharpness * (values - m)))) / sharpness


def excitation_geometry(system: SerialSystem, arm_name: str, study_pose: np.ndarray,
                        held: dict[str, np.ndarray], clearance: float) -> ExcitationGeometry:
    """The excited arm works around its pose in the study; the others hold theirs."""
    arms = {a.name: a for a in system.arms}
    centre = np.asarray(study_pose, float)
    points = arm_segments(arms[arm_name])
    held_points = [np.array(arm_segments(arms[n])(q)) for n, q in held.items()]
    keep_out = system.keep_out_radius

    q_sym = ca.SX.sym("q", len(arms[arm_name].links))
    pts = points(q_sym)
    origin = ca.DM([0.0, 0.0])
    # Every link outside the keep-out circle, not only the tool (the rods pass the head).
    values = [(point_segment(origin, pts[:, s], pts[:, s + 1]) - keep_out - KEEP_OUT_MARGIN)
              / max(keep_out, 1e-3) for s in range(3)]
    if held_points:
        distances = []
        for other in held_points:
            for s in range(3):
                for r in range(3):
                    a1, b1 = pts[:, s], pts[:, s + 1]
                    a2, b2 = ca.DM(other[:, r]), ca.DM(other[:, r + 1])
                    distances += [point_segment(a1, a2, b2), point_segment(b1, a2, b2),
                                  point_segment(a2, a1, b1), point_segment(b2, a1, b1)]
        gap = _softmin(ca.vertcat(*distances), SOFTMIN_SHARPNESS)
        values.append((gap - clearance - CLEARANCE_MARGIN) / 0.01)
    constraints = ca.Function("serial_geometry", [q_sym], [ca.vertcat(*values)])

    def distances_at(q):
        pts = np.array(points(q))
        keep = min(float(point_segment(np.zeros(2), pts[:, s], pts[:, s + 1]))
                   for s in range(3))
        gap = min((segment_distance(pts[:, s], pts[:, s + 1], other[:, r], other[:, r + 1])
                   for other in held_points for s in range(3) for r in range(3)),
                  default=math.inf)
        return keep, gap

    def check_start():
        keep, gap = distances_at(centre)
        if keep < keep_out + KEEP_OUT_MARGIN or gap < clearance + CLEARANCE_MARGIN:
            raise CochleaError(
                f"{arm_name}'s working pose is {keep * 1000:.1f} mm from the cochlea centre and "
                f"{gap * 1000:.1f} mm from the other arm: the excitation needs "
                f"{(keep_out + KEEP_OUT_MARGIN) * 1000:.1f} mm and --clearance-mm "
                f"{clearance * 1000:g} + {CLEARANCE_MARGIN * 1000:g} mm (lower it)")

    def check_path(q, times):
        poses = [distances_at(q[:, k]) for k in range(q.shape[1])]
        keep = min(p[0] for p in poses)
        gap = min(p[1] for p in poses)
        problems = []
        if keep < keep_out:
            problems.append("a link enters the keep-out circle")
        if gap < clearance:
            problems.append("the arm comes closer to the other arm than --clearance-mm")
        return problems, {"keep_out_distance": keep, "clearance_distance": gap}

    return ExcitationGeometry(centre, arm_name, constraints, check_start, check_path)
