"""The 5-DoF parallel mechanism: two pantographs on a prismatic slider (description, geometry
and closed-form kinematics, Lagrange model, scenario adapter)."""

from .adapter import ROBOT, ParallelRobot
from .description import ParallelJoint, ParallelSystem, Side, load_parallel
from .geometry import SCENARIO_START, ParallelGeometry
from .model import build_model

__all__ = ["ROBOT", "ParallelRobot", "ParallelJoint", "ParallelSystem", "Side",
           "load_parallel", "SCENARIO_START", "ParallelGeometry", "build_model"]
