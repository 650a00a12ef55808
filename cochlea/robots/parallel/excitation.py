"""What an excitation of the parallel mechanism must respect beyond its joint limits
(``cochlea-excite``, :mod:`cochlea.ident.excite`): each rod in its sleeve (``min_pivot_distance
<= |C - S| <= d3``, with margins), each pantograph on its branch away from its folded and
stretched singularities; checked against the whole workspace at 1 kHz."""

from __future__ import annotations

import casadi as ca
import numpy as np

from ...errors import CochleaError
from ..adapter import ExcitationGeometry
from .geometry import SCENARIO_START

#: Margin (m) of the rod's travel in its sleeve inside the limits the result is checked against.
SLEEVE_MARGIN = 0.005
#: Each pantograph keeps |sin(th1 - th2)| above this: at 0 its links fold or stretch out and
#: the end point loses a direction of motion.
MIN_BRANCH_SINE = 0.3


def excitation_geometry(geometry) -> ExcitationGeometry:
    """The mechanism works around the joint-space scenario's start (:data:`SCENARIO_START`);
    ``geometry``: its model's :class:`~.geometry.ParallelGeometry`."""
    system = geometry.system
    centre = np.asarray(SCENARIO_START, float)
    branches = geometry.branches(centre)
    lp, d2, d3 = geometry.lp, geometry.d2, geometry.d3
    r_min = system.min_pivot_distance

    q_sym = ca.SX.sym("q", 5)
    values = []
    for (i, j), sign, branch in (((0, 1), 1.0, branches[0]), ((3, 4), -1.0, branches[1])):
        th1, th2, d1 = q_sym[i], q_sym[j], q_sym[2]
        cu = sign * d2 + lp * (ca.cos(th1) + ca.cos(th2))
        cv = lp * (ca.sin(th1) + ca.sin(th2))
        r = ca.sqrt(cu ** 2 + (cv - d1) ** 2)
        values += [(r - r_min - SLEEVE_MARGIN) / r_min, (d3 - SLEEVE_MARGIN - r) / r_min,
                   branch * ca.sin(th1 - th2) - MIN_BRANCH_SINE]
    constraints = ca.Function("parallel_geometry", [q_sym], [ca.vertcat(*values)])

    def problems_at(q):
        problems = geometry.violations(q)
        if tuple(geometry.branches(q)) != tuple(branches):
            problems.append("a pantograph changed branch")
        return problems

    def check_start():
        if problems_at(centre):
            raise CochleaError("the parallel mechanism's working pose is outside its "
                               "workspace: " + "; ".join(problems_at(centre)))

    def check_path(q, times):
        for k in range(q.shape[1]):
            found = problems_at(q[:, k])
            if found:
                return [f"at t = {times[k]:.3f} s: " + "; ".join(found)], {}
        return [], {}

    return ExcitationGeometry(centre, "the mechanism", constraints, check_start, check_path)
