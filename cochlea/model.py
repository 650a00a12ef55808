"""The robot model object: CasADi Functions for dynamics, kinematics and the regressor.

``cochlea.model("serial")`` returns a :class:`RobotModel`. Every Function takes and returns SI
values (rad, m, rad/s, N m, N) and can be called with numbers (numpy arrays, lists) or with
CasADi symbols to build larger graphs (controllers, code generation).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from . import parameters as params_mod
from .description import Arm, SerialSystem, load_serial
from .errors import ModelError
from .lagrange import christoffel_coriolis, gravity_vector, mass_matrix
from .parameters import Parameterisation
from .serial_chain import (
    INERTIAL_MEANING,
    INERTIAL_NAMES,
    N_INERTIAL,
    energies,
    inertial_parameters,
    planar_orientation,
    rnea,
    tool_point,
)
from .spatial import rot_z

ROBOTS = ("serial", "parallel")
METHODS = ("newton-euler", "lagrange")


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
    * ``Y(q, qd, qd_r, qdd_r)``, the regressor: ``Y @ p == M qdd_r + C(q, qd) qd_r + G``.

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
    #: target consistency and workspace checks, a ``cochlea.parallel.ParallelGeometry``).
    geometry: Any = field(default=None, repr=False)

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
                lines.append(f"  joint {j.name}: revolute, {np.degrees(lo):.1f}..{np.degrees(hi):.1f}"
                             f" deg, |qd| <= {j.velocity_limit:g} rad/s, |tau| <= "
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
               parameterisation: Parameterisation) -> dict[str, ca.Function]:
    """Turn full-inertial-parameter expressions into the model's Functions."""
    n = q.shape[0]
    tau = ca.SX.sym("tau", n)
    qd_r = ca.SX.sym("qd_r", n)
    qdd_r = ca.SX.sym("qdd_r", n)
    p = ca.SX.sym("p", len(parameterisation.names))

    def at_p(expr):
        return ca.substitute(expr, phi, ca.DM(parameterisation.to_full) @ p)

    M, C, G, ID = at_p(M_full), at_p(C_full), at_p(G_full), at_p(tau_full)
    # Forward dynamics: M qdd = tau - bias, with the bias taken from the inverse dynamics at
    # qdd = 0. For a serial chain that is the Newton-Euler recursion, about half the operations
    # of C qd + G from Christoffel symbols (256 against 447 for the 3R arm): the plant step,
    # hence every simulation, runs on it. For a Lagrangian model it is C qd + G itself.
    bias = ca.substitute(ID, qdd, ca.SX.zeros(n))
    FD = ca.solve(M, tau - bias)
    Y = ca.jacobian(M @ qdd_r + C @ qd_r + G, p)

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
                   source: Path | None) -> RobotModel:
    """Build a :class:`RobotModel` from expressions in the full inertial parameters ``phi``.

    ``M, C, G, tau`` are the mass matrix, Christoffel Coriolis matrix, gravity vector and
    inverse dynamics (an expression in ``q, qd, qdd``); ``kinematics`` maps Function names to
    expressions in ``q``; ``bodies`` names each body's slice of ``phi`` (for the mass-only set).
    Any robot -- serial chain or closed chain -- goes through here, so all share one API.
    """
    n = q.shape[0]
    if parameterisation == "inertial":
        chosen = full
    elif parameterisation == "mass":
        chosen = params_mod.mass_only(full.names, full.nominal, bodies)
    else:
        full_functions = _functions(prefix, q, qd, qdd, phi, M, C, G, tau, {}, full)
        chosen = params_mod.base(full_functions["Y"], full.names, full.nominal, full.units,
                                 [n, n, n, n])
    functions = _functions(prefix, q, qd, qdd, phi, M, C, G, tau, kinematics, chosen)
    return RobotModel(name, joints, chosen, method, functions, full, source)


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


def _serial_arm_model(system: SerialSystem, arm: Arm, parameterisation: str,
                      method: str) -> RobotModel:
    n = len(arm.links)
    q = ca.SX.sym("q", n)
    qd = ca.SX.sym("qd", n)
    qdd = ca.SX.sym("qdd", n)
    phi = ca.SX.sym("phi", N_INERTIAL * n)
    g_base = arm.base_rotation.T @ system.gravity

    if method == "newton-euler":
        tau = rnea(arm, q, qd, qdd, phi, g_base)
        M = ca.jacobian(rnea(arm, q, ca.SX.zeros(n), qdd, phi, np.zeros(3)), qdd)
        M = 0.5 * (M + M.T)  # symmetric by construction, not only up to rounding
        G = rnea(arm, q, ca.SX.zeros(n), ca.SX.zeros(n), phi, g_base)
        C = christoffel_coriolis(M, q, qd)
    else:
        K, U = energies(arm, q, qd, phi, g_base)
        M = mass_matrix(K, qd)
        G = gravity_vector(U, q)
        C = christoffel_coriolis(M, q, qd)
        tau = M @ qdd + C @ qd + G

    tip, _ = tool_point(arm, q)
    fk = ca.vertcat(tip[0], tip[1], planar_orientation(arm, q))
    Rb = rot_z(arm.base_yaw)
    tip_world = ca.DM(arm.base_xyz[:2]) + Rb[:2, :2] @ tip[:2]
    fk_world = ca.vertcat(tip_world, fk[2] + arm.base_yaw)
    kinematics = {"fk": fk, "J": ca.jacobian(fk, q), "fk_world": fk_world,
                  "J_world": ca.jacobian(fk_world, q)}

    full, blocks = full_inertial([(link.name, inertial_parameters(link)) for link in arm.links])
    joints = tuple(
        JointInfo(link.name.replace("link", "joint", 1) if link.name.startswith("link")
                  else f"{link.name}_joint",
                  link.joint.type, link.joint.position_limits, link.joint.velocity_limit,
                  link.joint.effort_limit)
        for link in arm.links
    )
    return assemble_model(f"{system.name}/{arm.name}", f"{system.name}_{arm.name}",
                          joints=joints, q=q, qd=qd, qdd=qdd, phi=phi, M=M, C=C, G=G, tau=tau,
                          kinematics=kinematics, full=full, bodies=blocks,
                          parameterisation=parameterisation, method=method, source=system.path)


def model(name: str = "serial", *, arm: str | None = None, parameterisation: str = "inertial",
          method: str = "newton-euler", description: str | Path | None = None) -> RobotModel:
    """Build the symbolic model of a robot.

    Parameters
    ----------
    name:
        ``"serial"`` (one planar 3R arm of the serial system) or ``"parallel"``.
    arm:
        For the serial system, which arm (default: the first in the description, ``"arm1"``).
    parameterisation:
        ``"inertial"`` (ten standard inertial parameters per link), ``"base"`` (the minimal
        identifiable combinations, see ``model.parameters.describe()``), or ``"mass"`` (one
        mass per link, geometry fixed: the thesis's choice).
    method:
        ``"newton-euler"`` (recursive, default) or ``"lagrange"`` (from the energies; the
        cross-check).
    description:
        A TOML description to use instead of ``models/<name>.toml``.
    """
    if name not in ROBOTS:
        raise ModelError(f"unknown robot {name!r}; choose one of {', '.join(ROBOTS)}")
    if parameterisation not in params_mod.PARAMETERISATIONS:
        raise ModelError(f"unknown parameterisation {parameterisation!r}; choose one of "
                         + ", ".join(params_mod.PARAMETERISATIONS))
    if method not in METHODS:
        raise ModelError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if name == "parallel":
        from .parallel import parallel_model  # here, not at the top: parallel imports this module

        return parallel_model(parameterisation, method, description)
    system = load_serial(description if description is not None else name)
    chosen_arm = system.arms[0] if arm is None else system.arm(arm)
    return _serial_arm_model(system, chosen_arm, parameterisation, method)
