"""A motor's calibration fit in SI, and what it means at the joint: pure conversions, no I/O.

The bridge (:mod:`cochlea.dynamixel.drives`) turns joint efforts into Goal Currents with it, the
emulator turns currents back into torques, and the simulation (:mod:`cochlea.sim.setup`) takes
from it the effort resolution and saturation of each joint's drive (:func:`effort_grid`).

The fit (thesis Table C.1, ``y = a x + b`` with the units its ``x`` and ``y`` name) maps current
to torque. The rule, :class:`Fit`:

* Forward (current -> torque, what the motor does): odd in the current. For ``|tau| >=
  ramp``, ``|tau| = a |I| + b``: with the thesis's negative ``b`` (all seven fits) the first
  ``I0 = -b / a`` of current is lost to friction before any torque comes out (0.14-0.22 A for
  the MX-64s). Below ``ramp`` the offset is scaled down linearly, so the map stays continuous
  and strictly increasing through zero instead of jumping by ``2 I0`` at ``tau = 0``.
* Inverse (torque -> current, what the bridge commands)::

      I = tau / a + I0 * clip(tau / ramp, -1, 1)          (SI: A, N m)

  i.e. ``|I| = (|tau| - b) / a`` with the sign of ``tau`` once ``|tau| >= ramp``, zero current
  for zero torque, and a linear blend in between (Coulomb-friction compensation without
  chattering around zero torque). ``ramp`` is 0.05 N m by default, and at least ``2 b`` when
  a re-fit gives a positive ``b`` (then the rule is a current dead-band), so the map is always
  invertible: the emulator turns commanded currents back into exactly the torque the
  controller asked for, up to the current's quantisation.

At the joint, the motor torque is ``direction * ratio * effort`` with ``ratio`` the joint travel
per motor radian (1 for a revolute joint driven by the motor's output shaft; the pinion radius,
m/rad, for the slider), so an effort is the motor torque over ``|ratio|``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..dynamixel.control_table import MODELS, ModelSpec
from ..errors import CochleaError
from .description import Motor, MotorFit

#: Default width of the torque band over which the fit's offset is blended in (N m).
DEFAULT_RAMP_NM = 0.05

_X_TO_A = {"current_A": 1.0, "current_mA": 1e-3}
_Y_TO_NM = {"torque_Nm": 1.0, "torque_Ncm": 1e-2}


class MotorFitError(CochleaError):
    """A motor's fit cannot drive it (e.g. less torque for more current)."""


@dataclass(frozen=True)
class Fit:
    """A motor's torque/current relation in SI (A, N m): see the module docstring."""

    a: float  # N m per A
    b: float  # N m
    ramp: float  # N m

    @classmethod
    def from_description(cls, fit: MotorFit, ramp: float = DEFAULT_RAMP_NM) -> Fit:
        a = fit.a * _Y_TO_NM[fit.y] / _X_TO_A[fit.x]
        b = fit.b * _Y_TO_NM[fit.y]
        if not a > 0:
            raise MotorFitError(f"the fit y = {fit.a:g} x + {fit.b:g} gives less torque for "
                                "more current (a <= 0): the bridge needs a positive slope")
        return cls(a, b, max(ramp, 2.0 * b))

    @property
    def offset_current(self) -> float:
        """``I0 = -b / a`` (A): the current the offset takes (positive for Table C.1)."""
        return -self.b / self.a

    def current(self, torque, offset: bool = True):
        """Current (A) for a motor torque (N m); works on numbers and arrays. ``offset=False``:
        the slope alone, ``tau / a``, when the controller compensates the friction the offset
        stands for (:func:`bridge_compensates_friction`)."""
        t = np.asarray(torque, dtype=float)
        if not offset:
            return t / self.a
        return t / self.a + self.offset_current * np.clip(t / self.ramp, -1.0, 1.0)

    def torque(self, current):
        """Motor torque (N m) a current (A) gives: the exact inverse of :meth:`current`."""
        i = np.asarray(current, dtype=float)
        knee = self.ramp / self.a + self.offset_current  # current at |torque| = ramp
        slope = 1.0 / (1.0 / self.a + self.offset_current / self.ramp)
        outer = np.sign(i) * (self.a * np.abs(i) + self.b)
        return np.where(np.abs(i) <= knee, slope * i, outer)


#: What the controller's model carries of the drives (``[control] actuators``) when it
#: estimates and compensates the joints' friction itself (:data:`cochlea.robots.model.ACTUATORS`).
FRICTION_COMPENSATING_ACTUATORS = ("all",)


def bridge_compensates_friction(controller_actuators: str) -> bool:
    """Whether the bridge adds the fit's offset current ``I0 clip(tau / ramp, -1, 1)`` to every
    command: the one place that decides who compensates the gearbox's friction.

    The offset is the current the gearbox's Coulomb friction takes before the output moves (the
    description's ``coulomb_friction_Nm`` is the same ``|b|``). A controller whose model carries
    friction (``actuators = "all"``) already commands it, so the bridge must not add it again:
    on the motors both together push every joint with twice its friction, which the realistic
    studies turn into a velocity-limit stop within 20 ms (issue 24). Every other controller gets
    the bridge's compensation, as on the thesis's robot. Friction is compensated once."""
    return controller_actuators not in FRICTION_COMPENSATING_ACTUATORS


def current_limit_lsb(motor: Motor, spec: ModelSpec, fit: Fit, effort_limit: float,
                      ratio: float) -> int:
    """The Current Limit (38) of a joint: ``current_limit_mA`` if the description gives it,
    otherwise the current the fit needs for the joint's effort limit; never above the model's
    maximum."""
    if motor.current_limit_mA is not None:
        milliamps = motor.current_limit_mA
    else:
        milliamps = 1000.0 * float(fit.current(effort_limit * ratio))
    lsb = int(math.ceil(milliamps / spec.current_unit_mA - 1e-9))
    return max(1, min(lsb, spec.current_limit_max))


def effort_grid(motor: Motor, ratio: float, effort_limit: float,
                ramp: float = DEFAULT_RAMP_NM) -> tuple[float, float]:
    """A joint's effort resolution and saturation through its drive, ``(quantum, saturation)``
    in N m (revolute) or N (prismatic):

    * ``quantum = a * LSB / |ratio|``: one Goal Current LSB (3.36 mA on the MX-64(2.0), 2.69 mA
      on the XM540-W270) through the fit's slope, at the joint. It is the fit's slope outside
      the ramp band; inside it (``|torque| < ramp``) the bridge's blended inverse makes the real
      steps finer, and outside it the real grid is shifted by the offset ``b``: a model of the
      resolution, not of every level.
    * ``saturation``: the effort the fit gives at the joint's Current Limit
      (:func:`current_limit_lsb`), offset included: ``(a I_lim + b) / |ratio|``, the most the
      motor produces (the offset current is lost to friction at the limit too). Without
      ``current_limit_mA`` the limit is the current the joint's effort limit needs, rounded up
      to a whole LSB, so the saturation is then the effort limit or up to one quantum above.
    """
    spec = MODELS[motor.model]
    fit = Fit.from_description(motor.fit, ramp)
    amperes_per_lsb = spec.current_unit_mA * 1e-3
    scale = abs(ratio)
    limit = current_limit_lsb(motor, spec, fit, effort_limit, ratio)
    return (fit.a * amperes_per_lsb / scale,
            float(fit.torque(limit * amperes_per_lsb)) / scale)
