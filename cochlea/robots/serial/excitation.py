"""What an excitation of one serial arm must respect beyond its joint limits (``cochlea-excite``,
:mod:`cochlea.ident.excite`): every link segment outside the keep-out volumes, with a margin,
and clear of the other arms, which hold still at their working poses.

The keep-out volumes are the description's ``[[keep_out]]`` spheres where it has the key
(distances in 3-D); without it, the keep-out circle of radius ``keep_out_radius_m`` around the
world origin (the cochlea centre; distances in the x-y plane), for each arm whose base stands
outside that circle (an arm based inside it, as a user arm at the origin is, cannot keep its
links out of it: the circle is then the task-space supervisor's only)."""

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


def arm_segments(arm, dims: int = 2) -> ca.Function:
    """``q -> dims x (n + 1)`` points of an arm in the world (cochlea) frame: its base, the
    joints 2..n and the tool; consecutive points bound its n links. ``dims`` 2: their x, y;
    3: x, y, z."""
    q = ca.SX.sym("q", len(arm.links))
    poses = link_poses(arm, q)
    points = [p for _, p in poses] + [tool_point(arm, q)[0]]
    R = ca.DM(arm.base_rotation[:dims, :3])
    base = ca.DM(arm.base_xyz[:dims])
    world = [base + R @ p for p in points]
    return ca.Function(f"{arm.name}_points", [q], [ca.horzcat(*world)])


def point_segment(p, a, b):
    """Distance from point p to segment [a, b] (2- or 3-vectors; CasADi or numpy)."""
    dims = 3 if p.shape[0] == 3 else 2
    ab = b - a
    length2 = sum(ab[i] ** 2 for i in range(dims))
    s = sum((p[i] - a[i]) * ab[i] for i in range(dims)) / length2
    s = ca.fmin(ca.fmax(s, 0.0), 1.0)
    return ca.sqrt(sum((p[i] - a[i] - s * ab[i]) ** 2 for i in range(dims)) + 1e-12)


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
    arm = arms[arm_name]
    centre = np.asarray(study_pose, float)
    n_seg = len(arm.links)
    points = arm_segments(arm)
    held_points = [np.array(arm_segments(arms[n])(q)) for n, q in held.items()]
    volumes = system.keep_out_volumes
    if volumes is None:  # the keep-out circle around the origin, where the base is outside it
        keep_out = system.keep_out_radius or 0.0  # none in the description: no circle
        circle = (system.keep_out_radius is not None
                  and float(np.hypot(*arm.base_xyz[:2])) >= keep_out)
        spheres = []
    else:
        keep_out, circle = 0.0, False
        spheres = [(np.asarray(v.centre, float), v.radius, v.name) for v in volumes]
    points3 = arm_segments(arm, 3) if spheres else None

    q_sym = ca.SX.sym("q", n_seg)
    pts = points(q_sym)
    values = []
    if circle:  # every link outside the keep-out circle, not only the tool (the rods pass the head)
        origin = ca.DM([0.0, 0.0])
        values += [(point_segment(origin, pts[:, s], pts[:, s + 1]) - keep_out - KEEP_OUT_MARGIN)
                   / max(keep_out, 1e-3) for s in range(n_seg)]
    if spheres:
        pts3 = points3(q_sym)
        values += [(point_segment(ca.DM(c), pts3[:, s], pts3[:, s + 1]) - r - KEEP_OUT_MARGIN)
                   / max(r, 1e-3) for c, r, _ in spheres for s in range(n_seg)]
    if held_points:
        distances = []
        for other in held_points:
            for s in range(n_seg):
                for r in range(other.shape[1] - 1):
                    a1, b1 = pts[:, s], pts[:, s + 1]
                    a2, b2 = ca.DM(other[:, r]), ca.DM(other[:, r + 1])
                    distances += [point_segment(a1, a2, b2), point_segment(b1, a2, b2),
                                  point_segment(a2, a1, b1), point_segment(b2, a1, b1)]
        gap = _softmin(ca.vertcat(*distances), SOFTMIN_SHARPNESS)
        values.append((gap - clearance - CLEARANCE_MARGIN) / 0.01)
    constraints = ca.Function("serial_geometry", [q_sym],
                              [ca.vertcat(*values) if values else ca.SX(0, 1)])

    def distances_at(q):
        pts = np.array(points(q))
        keep = min((float(point_segment(np.zeros(2), pts[:, s], pts[:, s + 1]))
                    for s in range(n_seg)), default=math.inf) if circle else math.inf
        gap = min((segment_distance(pts[:, s], pts[:, s + 1], other[:, r], other[:, r + 1])
                   for other in held_points for s in range(n_seg)
                   for r in range(other.shape[1] - 1)),
                  default=math.inf)
        return keep, gap

    def sphere_gaps(q):
        """Per volume: the smallest distance of a link to its surface (m)."""
        pts3 = np.array(points3(q))
        return [min(float(point_segment(c, pts3[:, s], pts3[:, s + 1])) for s in range(n_seg))
                - r for c, r, _ in spheres]

    def check_start():
        keep, gap = distances_at(centre)
        if keep < keep_out + KEEP_OUT_MARGIN or gap < clearance + CLEARANCE_MARGIN:
            raise CochleaError(
                f"{arm_name}'s working pose is {keep * 1000:.1f} mm from the cochlea centre and "
                f"{gap * 1000:.1f} mm from the other arm: the excitation needs "
                f"{(keep_out + KEEP_OUT_MARGIN) * 1000:.1f} mm and --clearance-mm "
                f"{clearance * 1000:g} + {CLEARANCE_MARGIN * 1000:g} mm (lower it)")
        if spheres:
            for (_, _, name), g in zip(spheres, sphere_gaps(centre)):
                if g < KEEP_OUT_MARGIN:
                    raise CochleaError(
                        f"{arm_name}'s working pose comes {g * 1000:.1f} mm from the keep-out "
                        f"volume {name} of {system.path}: the excitation needs "
                        f"{KEEP_OUT_MARGIN * 1000:g} mm; give the arm a working_pose_deg "
                        "clear of it")

    def check_path(q, times):
        poses = [distances_at(q[:, k]) for k in range(q.shape[1])]
        keep = min(p[0] for p in poses)
        gap = min(p[1] for p in poses)
        problems = []
        if keep < keep_out:
            problems.append("a link enters the keep-out circle")
        if gap < clearance:
            problems.append("the arm comes closer to the other arm than --clearance-mm")
        found = {}
        if spheres:
            gaps = np.min([sphere_gaps(q[:, k]) for k in range(q.shape[1])], axis=0)
            for (_, _, name), g in zip(spheres, gaps):
                if g < 0:
                    problems.append(f"a link enters the keep-out volume {name}")
            found["keep_out_volume_distance"] = float(gaps.min())
        return problems, {"keep_out_distance": keep if circle else None,
                          "clearance_distance": gap if held_points else None, **found}

    return ExcitationGeometry(centre, arm_name, constraints, check_start, check_path)
