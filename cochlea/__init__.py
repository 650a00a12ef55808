"""cochlea: symbolic models, adaptive controllers and C code for the cochlear-microrobot robots.

Entry point::

    import cochlea
    arm = cochlea.model("serial")          # one planar 3R arm, CasADi Functions
    arm.M([0.1, 0.2, 0.3])                  # mass matrix at q (rad), kg m^2

See README.md for the whole API.
"""

from .description import load_serial
from .errors import CochleaError, DescriptionError, KinematicsError, ModelError
from .model import RobotModel, model

__all__ = ["model", "RobotModel", "load_serial", "CochleaError", "DescriptionError",
           "KinematicsError", "ModelError"]
__version__ = "0.1.0"
