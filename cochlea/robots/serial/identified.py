"""Where identified parameters go in a serial description: an arm's links and joints."""

from __future__ import annotations

import numpy as np

from ..description import MAX_INERTIA_KGM2, MIN_INERTIA_KGM2
from ..identified import actuator_values
from ..identified import number as _fmt
from ..model import RobotModel
from .description import SerialSystem


def identified_values(model: RobotModel, system: SerialSystem, arm_name: str,
                      phi: np.ndarray) -> dict:
    """``{path: TOML value text}`` for the arm's links and joints."""
    arm_index = [a.name for a in system.arms].index(arm_name)
    arm = system.arms[arm_index]
    names = list(model.full_parameters.names)
    value = dict(zip(names, phi))
    # Parameters that never enter the dynamics (a planar arm's mz, Ixx, Iyy, products): any
    # value reproduces the identified base parameters, so keep them where the description
    # has them about the centre of mass, not about the frame origin, which a moved centre
    # of mass would turn non-physical.
    free = {n for n, col in zip(names, model.parameters.from_full.T) if not col.any()}
    entries = {"Ixx": (0, 0), "Iyy": (1, 1), "Izz": (2, 2), "Ixy": (0, 1), "Ixz": (0, 2),
               "Iyz": (1, 2)}
    out = {}
    for i, link in enumerate(arm.links):
        b = link.name
        m = value[f"{b}.m"]
        own = np.array([value[f"{b}.mx"], value[f"{b}.my"], value[f"{b}.mz"]]) / m
        c = own.copy()
        for k, axis in enumerate(("mx", "my", "mz")):
            if f"{b}.{axis}" in free:
                c[k] = link.com[k]
        Io = np.array([[value[f"{b}.Ixx"], value[f"{b}.Ixy"], value[f"{b}.Ixz"]],
                       [value[f"{b}.Ixy"], value[f"{b}.Iyy"], value[f"{b}.Iyz"]],
                       [value[f"{b}.Ixz"], value[f"{b}.Iyz"], value[f"{b}.Izz"]]])
        Ic = Io - m * (float(c @ c) * np.eye(3) - np.outer(c, c))
        own_ic = Io - m * (float(own @ own) * np.eye(3) - np.outer(own, own))
        for key, (r, s) in entries.items():
            if f"{b}.{key}" in free:
                Ic[r, s] = Ic[s, r] = link.inertia_com[r, s]
        # A free principal moment grows, if needed, so the three obey the triangle inequality
        # (a rod whose identified Izz outgrew the nominal Iyy + Ixx).
        for k in range(3):
            key = ("Ixx", "Iyy", "Izz")[k]
            others = [x for x in range(3) if x != k]
            if f"{b}.{key}" in free:
                for o in others:
                    rest = [x for x in range(3) if x != o]
                    deficit = Ic[o, o] - sum(Ic[x, x] for x in rest)
                    if deficit > 0:
                        Ic[k, k] += deficit * (1 + 1e-9)
        if not _consistent(Ic) and _consistent(own_ic):
            # A physically consistent fit moves free parameters together with identified
            # ones (the prismatic arm's forearm: my with Ixy; the SO-101's base link: Ixx,
            # Iyy and the products with a small Izz): its body is consistent as a whole, the
            # description's values spliced into it need not be. Keep the fit's own body (the
            # same inertia about the frame origin: the same dynamics).
            c, Ic = own, own_ic
        base = ("arm", arm_index, "link", i)
        out[base + ("mass_kg",)] = _fmt(m)
        out[base + ("com_m",)] = "[" + ", ".join(_fmt(x) for x in c) + "]"
        six = [Ic[0, 0], Ic[1, 1], Ic[2, 2], Ic[0, 1], Ic[0, 2], Ic[1, 2]]
        out[base + ("inertia_com_kgm2",)] = "[" + ", ".join(_fmt(x) for x in six) + "]"
        out.update(actuator_values(model.joints[i], value, base + ("joint",)))
    return out


def _consistent(Ic: np.ndarray) -> bool:
    """Whether an inertia about the centre of mass is one the description's loader takes
    (``description._physical_inertia``): positive definite, principal moments obeying the
    triangle inequality, every entry and moment within the descriptions' bounds."""
    if not (np.abs(Ic) <= MAX_INERTIA_KGM2).all():
        return False
    a, b, c = np.linalg.eigvalsh(0.5 * (Ic + Ic.T))
    return bool(a >= MIN_INERTIA_KGM2 and a + b >= c - 1e-12 * c)


def fit_key(system: SerialSystem, arm_name: str, joint: str) -> tuple:
    """The key path of the motor fit of link ``joint`` (its index in the arm) of ``arm_name``."""
    arm = [x.name for x in system.arms].index(arm_name)
    return ("arm", arm, "link", joint, "motor", "fit")
