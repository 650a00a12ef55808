"""Where identified parameters go in a parallel description: the slider, each side's bodies
and the joints."""

from __future__ import annotations

import numpy as np

from ..identified import actuator_values
from ..identified import number as _fmt
from ..model import RobotModel
from .description import ParallelSystem


def identified_values(model: RobotModel, system: ParallelSystem, phi: np.ndarray) -> dict:
    value = dict(zip(model.full_parameters.names, phi))
    out = {("slider", "mass_kg"): _fmt(value["slider.m"])}
    for side in system.sides:
        for body in side.bodies:  # body.name is "<side>.<link>"
            m = value[f"{body.name}.m"]
            c = np.array([value[f"{body.name}.mx"], value[f"{body.name}.my"]]) / m
            izz = value[f"{body.name}.Izz"] - m * float(c @ c)
            base = tuple(body.name.split("."))
            out[base + ("mass_kg",)] = _fmt(m)
            out[base + ("com_m",)] = "[" + ", ".join(_fmt(x) for x in c) + "]"
            out[base + ("inertia_com_kgm2",)] = _fmt(izz)
    for joint in model.joints:  # "left.th1", "slider.d1"
        out.update(actuator_values(joint, value, tuple(joint.name.split("."))))
    return out


def fit_key(name: str) -> tuple:
    """The key path of the motor fit of joint ``name`` ("left.th1", "slider.d1")."""
    return tuple(name.split(".")) + ("motor", "fit")
