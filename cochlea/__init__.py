"""cochlea: symbolic models, adaptive controllers and C code for the cochlear-microrobot robots.

Entry point::

    import cochlea
    arm = cochlea.model("serial")          # one planar 3R arm, CasADi Functions
    arm.M([0.1, 0.2, 0.3])                  # mass matrix at q (rad), kg m^2

The package is layered; each layer imports only the ones before it: ``robots`` (descriptions,
models, one adapter per robot) -> ``control`` -> ``kernels`` (C code generation and loading) ->
``sim`` -> ``runtime`` -> ``dynamixel`` -> ``apps``. See README.md and docs/.
"""

from .errors import CochleaError, DescriptionError, KinematicsError, ModelError
from .robots import model
from .robots.model import RobotModel
from .robots.serial import load_serial

__all__ = ["model", "RobotModel", "load_serial", "CochleaError", "DescriptionError",
           "KinematicsError", "ModelError"]
__version__ = "0.1.0"
