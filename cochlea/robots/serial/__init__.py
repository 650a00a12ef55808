"""The serial system: two planar 3R arms (description, Newton-Euler chain, closed-form IK, model,
scenario adapter)."""

from .adapter import ROBOT, SerialRobot
from .description import Arm, Joint, Link, SerialSystem, load_serial
from .ik import UnreachableTarget
from .model import build_model

__all__ = ["ROBOT", "SerialRobot", "Arm", "Joint", "Link", "SerialSystem", "load_serial",
           "UnreachableTarget", "build_model"]
