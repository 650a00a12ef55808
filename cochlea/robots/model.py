"""The robot model object: CasADi Functions for dynamics, kinematics and the regressor.

``cochlea.model("serial")`` (:func:`cochlea.robots.model`) returns a :class:`RobotModel`. Every
Function takes and returns SI values (rad, m, rad/s, N m, N) and can be called with numbers
(numpy arrays, lists) or with
CasADi symbols to build larger graphs (controllers, code generation).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from ..errors import ModelError
from . import parameters as params_mod
from .parameters import Parameterisation

METHODS = ("newton-euler", "lagrange")
#: What a model carries of the joints' drives (see :class:`~cochlea.robots.description.Actuator`):
#: ``none``, the thesis's rigid links; ``armature``, each declared reflected rotor inertia on
#: the diagonal of ``M`` (the simulated plant: its friction is the plant step's own input);
#: ``all``, armature plus viscous and Coulomb friction as estimated parameters (a controller's
#: model: friction is compensated through the regressor).
ACTUATORS = ("none", "armature", "all")
#: How the generated C names what a model with each option computes: ``<unit>_plant_step``,
#: ``<unit>_armature_plant_step``; ``<unit>_e_step``, ``<unit>_e_actuated_step``.
ACTUATOR_SUFFIX = {"none": "", "armature": "_armature", "all": "_actuated"}
#: Velocity (rad/s at a revolute joint, m/s at a prismatic one) over which the model's Coulomb
#: friction ``Fc tanh(v / v_s)`` changes sign. The controllers evaluate it at their reference
#: velocity, which is smooth, so it can be sharp: 0.02 rad/s, under one count of the MX-64's
#: velocity register (0.024 rad/s); at the slider 4e-4 m/s. Wider, the
#: compensation fades over seconds of the studies' slow reversals and the joints stick there.
COULOMB_SMOOTHING = {"revolute": 0.02, "prismatic": 0.0004}

#: The ten standard inertial parameters of a rigid body, in its frame, and their meanings.
INERTIAL_NAMES = ("m", "mx", "my", "mz", "Ixx", "Iyy", "Izz", "Ixy", "Ixz", "Iyz")
INERTIAL_MEANING = {
    "m": ("mass", "kg"),
    "mx": ("first moment of mass m*c_x", "kg m"),
    "my": ("first moment of mass m*c_y", "kg m"),
    "mz": ("first moment of mass m*c_z", "kg m"),
    "Ixx": ("inertia about the link-frame origin", "kg m^2"),
    "Iyy": ("inertia about the link-frame origin", "kg m^2"),
    "Izz": ("inertia about the link-frame origin", "kg m^2"),
    "Ixy": ("product of inertia about the link-frame origin", "kg m^2"),
    "Ixz": ("product of inertia about the link-frame origin", "kg m^2"),
    "Iyz": ("product of inertia about the link-frame origin", "kg m^2"),
}


def check_options(parameterisation: str, method: str, actuators: str = "none") -> None:
    """Refuse an unknown parameterisation, derivation method or actuator option with the
    choices."""
    if parameterisation not in params_mod.PARAMETERISATIONS:
        raise ModelError(f"unknown parameterisation {parameterisation!r}; choose one of "
                         + ", ".join(params_mod.PARAMETERISATIONS))
    if method not in METHODS:
        raise ModelError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if actuators not in ACTUATORS:
        raise ModelError(f"unknown actuators option {actuators!r}; choose one of "
                         + ", ".join(ACTUATORS))


@dataclass(frozen=True)
class JointInfo:
    name: str
    type: str  # "revolute" | "prismatic"
    position_limits: tuple[float, float]  # rad or m
    velocity_limit: float  # rad/s or m/s
    effort_limit: float  # N m or N


@dataclass
class RobotModel:
    """Symbolic model of one robot (for "serial": one arm in its base frame).

    Functions evaluated at the nominal parameters:

    * ``M(q)`` mass matrix, ``C(q, qd)`` Christoffel Coriolis matrix, ``G(q)`` gravity torques;
    * ``inverse_dynamics(q, qd, qdd) -> tau`` and ``forward_dynamics(q, qd, tau) -> qdd``;
    * ``fk(q) -> [x, y, phi]`` of the tool in the base frame (m, m, rad), ``J(q) = dfk/dq``;
      ``fk_world`` / ``J_world`` the same in the world (cochlea-centred) frame;
    * ``Y(q, qd, qd_r, qdd_r)``, the regressor:
      ``Y @ p == M qdd_r + C(q, qd) qd_r + G + F(qd_r)`` with ``F`` the joints' friction when
      the model estimates it (``actuators="all"``), at the reference velocity;
    * ``friction_p(qd, p)``: that friction torque ``F`` (zero without friction parameters).

    The same dynamics for any parameter vector ``p`` of this model's parameterisation:
    ``M_p(q, p)``, ``C_p(q, qd, p)``, ``G_p(q, p)``, ``inverse_dynamics_p(q, qd, qdd, p)``,
    ``forward_dynamics_p(q, qd, tau, p)``.
    """

    name: str
    joints: tuple[JointInfo, ...]
    parameters: Parameterisation
    method: str
    functions: dict[str, ca.Function] = field(repr=False)
    full_parameters: Parameterisation = field(repr=False)
    source: Path | None = None
    #: Python-level helpers of the mechanism's geometry, or None (parallel: closed-form IK,
    #: target consistency and workspace checks, a
    #: :class:`~cochlea.robots.parallel.geometry.ParallelGeometry`).
    geometry: Any = field(default=None, repr=False)
    #: What the model carries of the joints' drives (one of :data:`ACTUATORS`).
    actuators: str = "none"

    def __getattr__(self, item):  # Functions as attributes: model.M, model.Y, ...
        functions = self.__dict__.get("functions", {})
        if item in functions:
            return functions[item]
        raise AttributeError(f"{type(self).__name__} has no attribute {item!r}")

    @property
    def nq(self) -> int:
        return len(self.joints)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.joints)

    @property
    def param_names(self) -> tuple[str, ...]:
        return self.parameters.names

    @property
    def p_nominal(self) -> np.ndarray:
        return self.parameters.nominal.copy()

    def describe(self) -> str:
        lines = [f"model {self.name!r}: {self.nq} joints, {self.method} dynamics"]
        if self.source:
            lines.append(f"  description: {self.source}")
        for j in self.joints:
            lo, hi = j.position_limits
            if j.type == "revolute":
                lines.append(f"  joint {j.name}: revolute, "
                             f"{np.degrees(lo):.1f}..{np.degrees(hi):.1f} deg, "
                             f"|qd| <= {j.velocity_limit:g} rad/s, |tau| <= "
                             f"{j.effort_limit:g} N m")
            else:
                lines.append(f"  joint {j.name}: prismatic, {lo:g}..{hi:g} m, |qd| <= "
                             f"{j.velocity_limit:g} m/s, |f| <= {j.effort_limit:g} N")
        lines.append(self.parameters.describe())
        return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Building
# --------------------------------------------------------------------------------------------


def _functions(prefix: str, q, qd, qdd, phi, M_full, C_full, G_full, tau_full, kinematics,
               parameterisation: Parameterisation, F_full,
               forward=None, regressand=None) -> dict[str, ca.Function]:
    """Turn full-parameter expressions into the model's Functions (``F_full``: the joints'
    friction torque, already part of ``tau_full``; ``forward``: None, or the model's own
    exact forward dynamics ``forward(q, qd, tau) -> qdd`` in ``phi``, without friction;
    ``regressand``: None, or ``M qdd_r + C(q, qd) qd_r + G`` (the Christoffel ``C``) computed
    another exact way, ``regressand(q, qd, qd_r, qdd_r)`` in ``phi``)."""
    n = q.shape[0]
    tau = ca.SX.sym("tau", n)
    qd_r = ca.SX.sym("qd_r", n)
    qdd_r = ca.SX.sym("qdd_r", n)
    p = ca.SX.sym("p", len(parameterisation.names))

    def at_p(expr):
        return ca.substitute(expr, phi, ca.DM(parameterisation.to_full) @ p)

    M, C, G, ID, F_fr = (at_p(M_full), at_p(C_full), at_p(G_full), at_p(tau_full),
                         at_p(F_full))
    # Forward dynamics, which the plant step, hence every simulation, runs on: the model's own
    # ``forward`` where it gives one (a Newton-Euler serial chain: the articulated-body
    # algorithm, O(n), no matrix solve, cochlea/robots/serial/aba.py), else M qdd = tau - bias
    # with the bias taken from the inverse dynamics at qdd = 0 (for a Lagrangian model, C qd + G
    # itself).
    if forward is None:
        bias = ca.substitute(ID, qdd, ca.SX.zeros(n))
        FD = ca.solve(M, tau - bias)
    else:
        FD = at_p(forward(q, qd, tau - F_full))
    # Friction at the reference velocity, not the measured one: the controllers then
    # compensate it ahead of a reversal instead of sticking there, the velocity quantisation
    # does not switch it, and the mismatch F(qd_r) - F(qd) only dissipates (F is monotone and
    # the sliding error is qd_r - qd), so every Lyapunov argument still holds.
    if regressand is None:
        f_r = M @ qdd_r + C @ qd_r + G
    else:
        f_r = at_p(regressand(q, qd, qd_r, qdd_r))
    Y = ca.jacobian(f_r + ca.substitute(F_fr, qd, qd_r), p)

    F = ca.Function
    out = {
        "M_p": F(f"{prefix}_M_p", [q, p], [M], ["q", "p"], ["M"]),
        "C_p": F(f"{prefix}_C_p", [q, qd, p], [C], ["q", "qd", "p"], ["C"]),
        "G_p": F(f"{prefix}_G_p", [q, p], [G], ["q", "p"], ["G"]),
        "inverse_dynamics_p": F(f"{prefix}_inverse_dynamics_p", [q, qd, qdd, p], [ID],
                                ["q", "qd", "qdd", "p"], ["tau"]),
        "forward_dynamics_p": F(f"{prefix}_forward_dynamics_p", [q, qd, tau, p], [FD],
                                ["q", "qd", "tau", "p"], ["qdd"]),
        "Y": F(f"{prefix}_Y", [q, qd, qd_r, qdd_r], [Y], ["q", "qd", "qd_r", "qdd_r"], ["Y"]),
        "friction_p": F(f"{prefix}_friction_p", [qd, p], [F_fr], ["qd", "p"], ["tau"]),
    }
    nominal = ca.DM(parameterisation.nominal)
    for key in ("M", "C", "G", "inverse_dynamics", "forward_dynamics"):
        f = out[f"{key}_p"]
        args = [ca.SX.sym(nm, f.size1_in(i)) for i, nm in enumerate(f.name_in()[:-1])]
        out[key] = F(f"{prefix}_{key}", args, [f(*args, nominal)], f.name_in()[:-1],
                     f.name_out())
    for key, expr in kinematics.items():
        out[key] = F(f"{prefix}_{key}", [q], [expr], ["q"], [key])
    return out


def assemble_model(name: str, prefix: str, *, joints: tuple[JointInfo, ...], q, qd, qdd, phi,
                   M, C, G, tau, kinematics: dict[str, ca.SX], full: Parameterisation,
                   bodies: list[tuple[str, slice]], parameterisation: str, method: str,
                   source: Path | None,
                   friction: list[tuple[float | None, float | None]] | None = None,
                   actuators: str = "none", forward=None, regressand=None) -> RobotModel:
    """Build a :class:`RobotModel` from expressions in the full inertial parameters ``phi``.

    ``M, C, G, tau`` are the mass matrix, Christoffel Coriolis matrix, gravity vector and
    inverse dynamics (an expression in ``q, qd, qdd``); ``kinematics`` maps Function names to
    expressions in ``q``; ``bodies`` names each body's slice of ``phi`` (for the mass-only set).
    Any robot -- serial chain or closed chain -- goes through here, so all share one API.

    ``friction``: per joint, its (viscous, Coulomb) friction or None each; every declared one
    becomes an estimated parameter (:func:`with_friction`) and its torque joins ``tau``.

    ``forward``: None (the forward dynamics solve ``M qdd = tau - bias``), or a callable
    ``forward(q, qd, tau) -> qdd`` in ``phi``, the same dynamics without friction computed
    another exact way (a serial chain's articulated-body algorithm); ``regressand``: None
    (the regressor ``Y`` differentiates ``M qdd_r + C qd_r + G``), or a callable
    ``(q, qd, qd_r, qdd_r) -> M qdd_r + C(q, qd) qd_r + G`` in ``phi`` (the Christoffel ``C``,
    without friction) computed another exact way (a serial chain's two Newton-Euler passes).
    """
    n = q.shape[0]
    full, bodies, phi, F_full = with_friction(full, bodies, phi, qd, joints, friction)
    tau = tau + F_full
    if parameterisation == "inertial":
        chosen = full
    elif parameterisation == "mass":
        chosen = params_mod.mass_only(full.names, full.nominal, bodies, full.si_units,
                                      full.meanings)
    else:
        full_functions = _functions(prefix, q, qd, qdd, phi, M, C, G, tau, {}, full, F_full)
        chosen = params_mod.base(full_functions["Y"], full.names, full.nominal, full.si_units,
                                 [n, n, n, n])
    functions = _functions(prefix, q, qd, qdd, phi, M, C, G, tau, kinematics, chosen, F_full,
                           forward, regressand)
    return RobotModel(name, joints, chosen, method, functions, full, source,
                      actuators=actuators)


#: The actuator parameter a joint may carry: its drive's reflected rotor inertia (armature).
ARMATURE = "Ia"


def with_armatures(full: Parameterisation, blocks: list[tuple[str, slice]],
                   joints: list[tuple[str, str, float | None]]
                   ) -> tuple[Parameterisation, list[tuple[str, slice]]]:
    """``full`` and its blocks, followed by one parameter ``<joint>.Ia`` per joint whose drive
    declares an armature (``joints``: name, type, armature or None), each its own block.

    The armature is inertia the joint's own coordinate drives: it adds ``Ia * qdd_i`` to the
    joint's torque and ``Ia * qd_i**2 / 2`` to the kinetic energy, i.e. ``Ia`` on the diagonal
    of ``M`` (the usual reduced model of a geared drive: the rotor's gyroscopic coupling with
    the link that carries it is left out). Linear in ``Ia``, so it is identifiable like any
    inertial parameter.
    """
    declared = [(name, jtype, value) for name, jtype, value in joints if value is not None]
    if not declared:
        return full, blocks
    n0 = len(full.names)
    names = [f"{name}.{ARMATURE}" for name, _, _ in declared]
    units = ["kg m^2" if jtype == "revolute" else "kg" for _, jtype, _ in declared]
    meanings = [f"reflected rotor inertia (armature) of {name}" for name, _, _ in declared]
    joined = params_mod.inertial(full.names + tuple(names),
                                 np.concatenate([full.nominal, [v for _, _, v in declared]]),
                                 full.si_units + tuple(units), full.meanings + tuple(meanings))
    return joined, blocks + [(name, slice(n0 + k, n0 + k + 1)) for k, name in enumerate(names)]


#: The friction parameters a joint may carry: viscous and Coulomb.
VISCOUS, COULOMB = "Fv", "Fc"


def with_friction(full: Parameterisation, blocks: list[tuple[str, slice]], phi: ca.SX,
                  qd: ca.SX, joints: tuple[JointInfo, ...],
                  friction: list[tuple[float | None, float | None]] | None):
    """``full``, its blocks and its symbol ``phi`` extended by one parameter per declared
    friction term of each joint, ``<joint>.Fv`` (viscous) and ``<joint>.Fc`` (Coulomb), each its
    own block; and the friction torque, ``Fv qd + Fc tanh(qd / v)`` per joint
    (:data:`COULOMB_SMOOTHING`), an expression in ``qd`` and the extended ``phi``.

    Linear in the parameters, so the regressor gains their columns (``qd`` and the smoothed
    sign) and an adaptive controller estimates and compensates them like the inertial ones.
    """
    n = qd.shape[0]
    if not friction:
        return full, blocks, phi, ca.SX.zeros(n)
    names, values, units, meanings, terms = [], [], [], [], []
    for i, (joint, (viscous, coulomb)) in enumerate(zip(joints, friction, strict=True)):
        revolute = joint.type == "revolute"
        if viscous is not None:
            names.append(f"{joint.name}.{VISCOUS}")
            values.append(viscous)
            units.append("N m s/rad" if revolute else "N s/m")
            meanings.append(f"viscous friction of {joint.name}")
            terms.append((i, qd[i]))
        if coulomb is not None:
            names.append(f"{joint.name}.{COULOMB}")
            values.append(coulomb)
            units.append("N m" if revolute else "N")
            meanings.append(f"Coulomb friction of {joint.name} (sign smoothed over "
                            f"{COULOMB_SMOOTHING[joint.type]:g} {'rad/s' if revolute else 'm/s'})")
            terms.append((i, ca.tanh(qd[i] / COULOMB_SMOOTHING[joint.type])))
    if not names:
        return full, blocks, phi, ca.SX.zeros(n)
    n0 = len(full.names)
    extra = ca.SX.sym("phi_friction", len(names))
    torque = ca.SX.zeros(n)
    for k, (i, column) in enumerate(terms):
        torque[i] = torque[i] + extra[k] * column
    joined = params_mod.inertial(full.names + tuple(names),
                                 np.concatenate([full.nominal, values]),
                                 full.si_units + tuple(units), full.meanings + tuple(meanings))
    blocks = blocks + [(name, slice(n0 + k, n0 + k + 1)) for k, name in enumerate(names)]
    return joined, blocks, ca.vertcat(phi, extra), torque


def full_inertial(bodies: list[tuple[str, np.ndarray]], names=INERTIAL_NAMES,
                  meanings=INERTIAL_MEANING) -> tuple[Parameterisation, list[tuple[str, slice]]]:
    """The full parameter set of named bodies, each with its block of nominal values."""
    full_names, full_units, full_meanings, blocks, nominal = [], [], [], [], []
    start = 0
    for body, values in bodies:
        blocks.append((body, slice(start, start + len(values))))
        start += len(values)
        nominal.append(values)
        for pname in names:
            meaning, unit = meanings[pname]
            full_names.append(f"{body}.{pname}")
            full_units.append(unit)
            full_meanings.append(f"{meaning} of {body}")
    full = params_mod.inertial(full_names, np.concatenate(nominal), full_units, full_meanings)
    return full, blocks
