"""The control layer: the thesis's four robust adaptive controllers (``e, g`` for the serial
arms, ``f, d`` for the parallel mechanism) built on any model, and the registry of their gains."""

from .controllers import VARIANTS, Controller, build
from .gains import CONTROLLERS, KINDS, GainSet, controller_of

__all__ = ["VARIANTS", "Controller", "build", "CONTROLLERS", "KINDS", "GainSet",
           "controller_of"]
