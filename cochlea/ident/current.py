"""Motors' current-to-torque lines fitted from logs that carry the measured current.

A drive's fit (:class:`cochlea.robots.motor_fit.Fit`) turns the motor current ``I`` (A) into
the motor torque ``a I + b s(I)`` (N m) with the offset blended in over a ramp::

    s(I) = clip(I / I_knee, -1, 1),   I_knee = (ramp - b) / a

(the forward map of :class:`~cochlea.robots.motor_fit.Fit` written out: outside the knee
``sign(I) (a |I| + b)``, inside it the straight line through zero that meets it at the knee,
where the torque is the ramp: ``a I_knee + b = ramp``). At the joint the effort is that torque
over ``|ratio|`` (the slider's pinion radius), with the current logged at the joint's sign
(``<unit>.current.<joint>_A``, see :mod:`cochlea.runtime.backend`).

For a given knee, ``b = ramp - a I_knee`` and the torque ``a (I - I_knee s) + ramp s`` is
linear in ``a``: a joint whose line is unknown contributes ``Y_j beta - a_j (I_j - I_knee s_j)
/ r_j = ramp s_j / r_j`` instead of ``tau_j = Y_j beta``, and ``(beta, a_j)`` come out of one
least-squares problem; :func:`cochlea.ident.estimate.identify` searches the knees by the
fit's residual.

Only joints whose efforts are trusted fix the torque's scale: with every line unknown, ``beta``
and every line can be multiplied by one factor and still fit the logs (the ramp does not help:
it is the bridge's blending rule, the same for every line).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import CochleaError
from ..robots import RobotModel, robot
from ..robots.description import MotorFit
from ..robots.motor_fit import DEFAULT_RAMP_NM, Fit

#: ``--fit-current`` keywords: ``auto`` fits the lines the description marks as placeholders
#: (``source = "placeholder"``) when the logs carry the current; ``off`` fits none.
AUTO, OFF = "auto", "off"


class CurrentFitError(CochleaError):
    """The lines cannot be fitted from these logs or with this choice of joints."""


@dataclass(frozen=True)
class Line:
    """One drive's line to fit: where it sits and what the description says of it."""

    joint: int  # index in the model's joints (and the log's columns)
    name: str  # the model's joint name
    motor_id: int
    scale: float  # |ratio|: joint effort = motor torque / scale
    a0: float  # the description's slope, N m per A
    b0: float  # the description's offset, N m
    x: str  # the description's units ("current_A", "torque_Ncm")
    y: str
    source: str | None

    @property
    def ramp(self) -> float:
        """The torque (N m) at the knee: the offset's blending band (an offset ``b`` above
        half of it widens the band to ``2 b``: a current dead-band, not modelled here)."""
        return DEFAULT_RAMP_NM

    def knee(self, a: float, b: float) -> float:
        """The current (A) at which the offset is fully blended in, for slope ``a`` (N m/A)
        and offset ``b`` (N m): the ramp rule of :class:`~cochlea.robots.motor_fit.Fit`."""
        ramp = max(DEFAULT_RAMP_NM, 2.0 * b)
        return (ramp - b) / a if a > 0 else np.inf

    def in_description_units(self, a: float, b: float) -> tuple[float, float]:
        """``(a, b)`` from SI (N m/A, N m) into the description's fit units."""
        fa, fb = self.scale_to_description()
        return a * fa, b * fb

    def scale_to_description(self) -> tuple[float, float]:
        """Factors taking an SI ``(a, b)`` (and its standard errors) to the description's."""
        si = _si_per_unit(self.x, self.y)
        return 1.0 / si.a, 1.0 / si.b


def _si_per_unit(x: str, y: str) -> Fit:
    """The SI values of a fit ``y = 1 x + 1`` in units ``x``, ``y``: the conversion factors of
    the slope and the offset, from the motor-fit module's own rule."""
    return Fit.from_description(MotorFit(1.0, 1.0, x, y))


def offset_shape(current: np.ndarray, knee: float) -> np.ndarray:
    """``s(I) = clip(I / knee, -1, 1)``: how the drive applies its offset ``b``."""
    return np.clip(np.asarray(current, float) / knee, -1.0, 1.0)


def drive_lines(robot_name: str, model: RobotModel, unit: str, description=None) -> list[Line]:
    """Every joint of ``unit`` (an arm, or the parallel mechanism) with its drive's line, in the
    model's joint order."""
    adapter = robot(robot_name)
    system = adapter.load(description)
    units = list(adapter.layout(system, "joint").units)
    joints = adapter.actuated_joints(system)
    n = model.nq
    k = units.index(unit)
    mine = joints[k * n:(k + 1) * n]  # the loop's order: unit after unit
    lines = []
    for i, (j, mj) in enumerate(zip(mine, model.joints)):
        fit = j.motor.fit
        si = _si_per_unit(fit.x, fit.y)
        a, b = fit.a * si.a, fit.b * si.b
        lines.append(Line(i, mj.name, j.motor.id, abs(j.ratio), a, b, fit.x, fit.y,
                          fit.source))
    return lines


def choose(option: str, lines: list[Line], has_current: bool, where: str) -> list[Line]:
    """The lines ``--fit-current`` asks for: ``auto`` (the description's placeholders, when
    every log carries the current), ``off``, or joint names separated by commas (then the
    current is required). Refuses unknown names, and every joint at once (the torque's scale
    would not be observable)."""
    text = option.strip()
    if text.lower() == OFF:
        return []
    names = [ln.name for ln in lines]
    if text.lower() == AUTO:
        chosen = [ln for ln in lines if ln.source == "placeholder"] if has_current else []
    else:
        wanted = [w.strip() for w in text.split(",") if w.strip()]
        unknown = [w for w in wanted if w not in names]
        if not wanted or unknown:
            raise CurrentFitError(f"--fit-current {option!r}: expected auto, off or joint names "
                                  f"separated by commas from {', '.join(names)}"
                                  + (f" (no joint {unknown[0]!r})" if unknown else ""))
        if not has_current:
            raise CurrentFitError(f"--fit-current {option}: the logs ({where}) carry no "
                                  "measured current (columns <unit>.current.<joint>_A, written "
                                  "by cochlea-run over the motors or the emulator): record the "
                                  "run over the bus, or leave the fits out (--fit-current off)")
        chosen = [ln for ln in lines if ln.name in wanted]
    if chosen and len(chosen) == len(lines):
        raise CurrentFitError(
            f"--fit-current: every joint's current-to-torque line would be fitted "
            f"({', '.join(ln.name for ln in chosen)}): the torque's scale is then not "
            "observable (the base parameters and every line can be multiplied by one factor "
            "and still fit the logs). Calibrate one drive on the bench with cochlea-dxl "
            "calibrate --torque-fit, mark its fit source = \"measured\" in the description, "
            "and fit the others against it")
    return chosen
