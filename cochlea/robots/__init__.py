"""The robots layer: descriptions, parameters, the symbolic models, and one adapter per robot.

``robot(name)`` is the registry every layer above asks instead of branching on a robot's name
(see :mod:`cochlea.robots.adapter` for the interface); ``model(...)`` is ``cochlea.model``.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import ModelError
from .adapter import (
    ActuatedJoint,
    ExcitationGeometry,
    Layout,
    LinkFrames,
    RobotAdapter,
    UnitPlan,
)
from .model import RobotModel
from .parallel import ROBOT as _PARALLEL_ROBOT
from .serial import ROBOT as _SERIAL_ROBOT

#: Every robot cochlea knows, by name.
ROBOTS: dict[str, RobotAdapter] = {r.name: r for r in (_SERIAL_ROBOT, _PARALLEL_ROBOT)}


def robot(name: str) -> RobotAdapter:
    """The adapter of robot ``name`` (``"serial"`` or ``"parallel"``)."""
    try:
        return ROBOTS[name]
    except KeyError:
        raise ModelError(f"unknown robot {name!r}; choose one of {', '.join(ROBOTS)}") from None


def model(name: str = "serial", *, arm: str | None = None, parameterisation: str = "inertial",
          method: str = "newton-euler", description: str | Path | None = None,
          actuators: str = "none") -> RobotModel:
    """Build the symbolic model of a robot.

    Parameters
    ----------
    name:
        ``"serial"`` (one planar 3R arm of the serial system) or ``"parallel"``.
    arm:
        For the serial system, which arm (default: the first in the description, ``"arm1"``).
    parameterisation:
        ``"inertial"`` (ten standard inertial parameters per link), ``"base"`` (the minimal
        identifiable combinations, see ``model.parameters.describe()``), or ``"mass"`` (one
        mass per link, geometry fixed: the thesis's choice).
    method:
        ``"newton-euler"`` (recursive, default) or ``"lagrange"`` (from the energies; the
        cross-check). The parallel mechanism's closed chain has one model, from its energies.
    description:
        A TOML description to use instead of the shipped ``models/robots/<name>.toml``.
    actuators:
        What the model carries of the joints' drives, as the description gives them:
        ``"none"`` (default: the thesis's rigid links), ``"armature"`` (reflected rotor
        inertia on the diagonal of ``M``) or ``"all"`` (armature, viscous and Coulomb friction
        as parameters, in the regressor too).
    """
    adapter = robot(name)
    return adapter.model(adapter.load(description), arm, parameterisation, method, actuators)


__all__ = ["ROBOTS", "robot", "model", "RobotModel", "RobotAdapter", "Layout", "UnitPlan",
           "ActuatedJoint", "ExcitationGeometry", "LinkFrames"]
