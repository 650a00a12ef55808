"""URDF in and out, as the layers above the robots see it (``cochlea-urdf``).

A URDF describes a tree of links; cochlea reads and writes the serial chains in it, so the
serial kind does the work (:mod:`cochlea.robots.serial.urdf`) and this module is its public
face: nothing outside ``cochlea/robots/`` imports a robot kind's internals
(tests/test_architecture.py).
"""

from __future__ import annotations

from .serial import load_serial as load_chain
from .serial.urdf import export_urdf, import_urdf, starter_scenario

__all__ = ["export_urdf", "import_urdf", "load_chain", "starter_scenario"]
