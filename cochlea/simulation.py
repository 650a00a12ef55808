"""Closed-loop simulation of a scenario: controller sampled and held at the control rate, plant
integrated with RK4 sub-steps, estimates integrated once per period.

The plant is the same symbolic model with its own parameters (the scenario may scale masses, add
a tip payload and viscous friction); measurements may carry Gaussian noise and a delay of whole
periods. Everything that can be is fused into one CasADi Function per unit and period; the
Python loop only adds noise, delays measurements and stores the log.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from . import scenario as scenario_mod
from .controllers import Controller, build
from .description import load_serial
from .errors import CochleaError
from .model import RobotModel, model
from .serial_ik import UnreachableTarget, elbow_cosine, ik, ik_symbolic, world_to_base


@dataclass
class UnitSetup:
    """Everything one controlled unit needs, in SI."""

    name: str
    controller_model: RobotModel
    plant_model: RobotModel  # full inertial parameterisation
    plant_params: np.ndarray
    controller: Controller
    desired: ca.Function  # t -> (xd, xd_dot, xd_ddot) in the controller's space
    x0: np.ndarray  # [q0, qd0]
    gains: np.ndarray
    gamma: np.ndarray
    bound: float
    p_hat0: np.ndarray
    friction: np.ndarray
    joint_units: tuple[str, ...]  # "rad" | "m" per joint
    task_names: tuple[str, ...]
    task_units: tuple[str, ...]
    task_angles: tuple[int, ...]
    fk_world: ca.Function = field(repr=False)
    #: Tool points drawn in the path figure: label -> indices of (u, v) in the task pose.
    tool_points: tuple[tuple[str, tuple[int, int]], ...] = (("tool", (0, 1)),)
    #: Centre of the cochlea-centred circle in the path figure (m, world frame).
    centre: tuple[float, float] = (0.0, 0.0)
    #: Index of the joint whose value moves the keep-out centre along v (the parallel
    #: mechanism's slider: S = (0, d1)), or None for a fixed centre at ``centre``.
    moving_centre_joint: int | None = None

    def keep_out_centre(self, q) -> tuple[float, float]:
        """Centre of the safety keep-out circle at joint position q (m, world frame)."""
        if self.moving_centre_joint is None:
            return self.centre
        return (0.0, float(q[self.moving_centre_joint]))


@dataclass
class UnitLog:
    """The log of one unit, one row per control period (SI)."""

    name: str
    space: str
    q: np.ndarray  # (N, n) true joint positions at the start of each period
    qd: np.ndarray
    desired: np.ndarray  # (N, nd) desired sample (joint or task space)
    desired_dot: np.ndarray
    errors: np.ndarray  # (N, 2 blocks) controller error signals
    tau: np.ndarray  # (N, n) commanded torque / force
    p_hat: np.ndarray  # (N, n_p) estimate used in the period
    x: np.ndarray  # (N, m) tool / task pose of the true state
    setup: UnitSetup = field(repr=False)

    @property
    def tracking_error(self) -> np.ndarray:
        """Desired minus actual on the tracked coordinates (angles wrapped), SI."""
        n = self.setup.controller.n_desired
        block = self.errors[:, :n]
        # g defines e_g = x - x_d; report every controller as desired - actual.
        return -block if self.setup.controller.kind == "g" else block

    @property
    def tracked_names(self) -> tuple[str, ...]:
        if self.space == "joint":
            return tuple(j.name for j in self.setup.controller_model.joints)
        return self.setup.task_names

    @property
    def tracked_units(self) -> tuple[str, ...]:
        return self.setup.joint_units if self.space == "joint" else self.setup.task_units


@dataclass
class SimulationResult:
    scenario: scenario_mod.Scenario
    time: np.ndarray  # (N,) s
    units: list[UnitLog]
    diverged: dict[str, float] = field(default_factory=dict)  # unit -> time (s) it diverged
    #: Real-time runs: per-period timing arrays (s) by name, and how the run stopped.
    timing: dict[str, np.ndarray] | None = None
    stop: dict | None = None

    def unit(self, name: str) -> UnitLog:
        return next(u for u in self.units if u.name == name)


# --------------------------------------------------------------------------------------------
# Robot adapters: how a scenario's units, leader and followers map onto models
# --------------------------------------------------------------------------------------------


def serial_layout(robot: str, space: str, description: str) -> dict:
    system = load_serial(description)
    n = len(system.arms[0].links)
    kinds = ("angle",) * n
    return {"leader": kinds if space == "joint" else ("length", "length", "angle"),
            "joint": kinds, "task": ("length", "length", "angle"),
            "units": tuple(a.name for a in system.arms), "n_joint": n, "n_task": 3,
            "n_bodies": n}


def layout(robot: str, space: str, description: str) -> dict:
    if robot == "serial":
        return serial_layout(robot, space, description)
    from .parallel_sim import parallel_layout  # noqa: PLC0415 (arrives with the parallel model)

    return parallel_layout(robot, space, description)


def load_scenario(name_or_path) -> scenario_mod.Scenario:
    return scenario_mod.load(name_or_path, layout)


def perturbed_parameters(full, plant: scenario_mod.Plant,
                         payload_points: dict[str, np.ndarray]) -> np.ndarray:
    """Full inertial parameters of the simulated robot: bodies scaled, payloads added.

    Works from the parameter names ``<body>.<m|mx|my|mz|Ixx|...>`` of any model: each body's
    parameters scale with ``plant.mass_scale`` (same shape, denser), and a point mass
    ``plant.payload_kg`` is added at ``payload_points[body]`` (m, body frame).
    """
    p = np.asarray(full.nominal, float).copy()
    bodies = list(dict.fromkeys(name.rsplit(".", 1)[0] for name in full.names))
    if plant.mass_scale is not None:
        for body, scale in zip(bodies, plant.mass_scale, strict=True):
            for i, name in enumerate(full.names):
                if name.rsplit(".", 1)[0] == body:
                    p[i] *= scale
    m = plant.payload_kg
    for body, point in payload_points.items():
        x, y, z = (list(point) + [0.0, 0.0])[:3]
        added = {"m": m, "mx": m * x, "my": m * y, "mz": m * z,
                 "Ixx": m * (y * y + z * z), "Iyy": m * (x * x + z * z),
                 "Izz": m * (x * x + y * y), "Ixy": -m * x * y, "Ixz": -m * x * z,
                 "Iyz": -m * y * z}
        for i, name in enumerate(full.names):
            owner, kind = name.rsplit(".", 1)
            if owner == body:
                p[i] += added[kind]
    return p


def _desired_function(name: str, expr_t: ca.SX, t: ca.SX) -> ca.Function:
    x_dot = ca.jacobian(expr_t, t)
    return ca.Function(f"desired_{name}", [t], [expr_t, x_dot, ca.jacobian(x_dot, t)],
                       ["t"], ["x", "x_dot", "x_ddot"])


def _check_reachable(arm, pose_base_t: ca.SX, t: ca.SX, sc: scenario_mod.Scenario) -> None:
    """Refuse a follower trajectory that leaves the workspace, before anything runs."""
    c2 = ca.Function("c2", [t], [elbow_cosine(arm, pose_base_t)])
    times = np.arange(0.0, sc.duration + 0.5 * sc.period, sc.period)
    values = np.array(c2.map(len(times))(times)).ravel()
    bad = np.flatnonzero(~(np.abs(values) <= 1.0))
    if bad.size:
        k = bad[0]
        raise UnreachableTarget(f"scenario {sc.name}: {arm.name}'s desired pose leaves the "
                                f"workspace at t = {times[k]:.3f} s (cos th2 = {values[k]:.4f})")


def serial_units(sc: scenario_mod.Scenario) -> list[UnitSetup]:
    system = load_serial(sc.description)
    t = ca.SX.sym("t")
    leader = sc.desired_leader()
    x_lead, _, _ = leader(t)
    models = {a.name: model("serial", arm=a.name, parameterisation=sc.parameterisation,
                            description=system.path) for a in system.arms}
    leader_arm = system.arms[0]
    # The leader's tool pose in the cochlea frame, as a function of t.
    lead_pose = x_lead if sc.space == "task" else models[leader_arm.name].fk_world(x_lead)
    setups = []
    for arm, unit in zip(system.arms, sc.units):
        m = models[arm.name]
        plant = model("serial", arm=arm.name, parameterisation="inertial",
                      description=system.path)
        # Initial joint state (the branch is explicit for task-space initial poses).
        if unit.initial_joint is not None:
            q0 = unit.initial_joint
        else:
            reference = np.array([0.0, unit.elbow or 1, 0.0])
            q0, _, _ = ik(arm, unit.initial_task, reference)
            if unit.elbow is not None and np.sign(q0[1]) != unit.elbow:
                raise UnreachableTarget(f"{arm.name}: the initial pose has no solution on "
                                        f"elbow branch {unit.elbow:+d}")
        qd0 = unit.initial_velocity if unit.initial_velocity is not None else np.zeros(len(q0))

        if arm is leader_arm:
            desired_expr = x_lead
        else:  # dual-arm rule: point reflection through the cochlea centre, facing the leader
            pose = ca.vertcat(-lead_pose[0], -lead_pose[1], lead_pose[2] + np.pi)
            if sc.space == "task":
                desired_expr = pose
            else:
                pose_base = world_to_base(arm, pose)
                _check_reachable(arm, pose_base, t, sc)
                pose0 = np.array(ca.evalf(ca.substitute(pose, t, 0.0))).ravel()
                q_ref, elbow, offsets = ik(arm, pose0, q0)
                if unit.elbow is not None:
                    elbow = unit.elbow
                    q_branch = np.array(ik_symbolic(arm, ca.DM(world_to_base(arm, pose0)),
                                                    elbow)).ravel()
                    offsets = 2 * np.pi * np.round((q0 - q_branch) / (2 * np.pi))
                desired_expr = ik_symbolic(arm, pose_base, elbow, offsets)
        if sc.space == "task":
            _check_reachable(arm, world_to_base(arm, desired_expr), t, sc)
        desired = _desired_function(arm.name, desired_expr, t)

        controller = build(m, sc.controller, variant=sc.variant, task_angles=(2,))
        gains = np.concatenate([unit.gains[k] for k in controller.gain_names])
        n_p = len(m.param_names)
        bound = sc.estimate_bound * max(np.linalg.norm(m.p_nominal), 1e-12)
        p_hat0 = np.zeros(n_p) if sc.initial_estimate == "zero" else m.p_nominal
        n = m.nq
        friction = (sc.plant.viscous_friction if sc.plant.viscous_friction is not None
                    else np.zeros(n))
        tool = {arm.links[-1].name: np.array([arm.links[-1].length, 0.0, 0.0])}
        setups.append(UnitSetup(
            arm.name, m, plant, perturbed_parameters(plant.parameters, sc.plant, tool),
            controller, desired,
            np.concatenate([q0, qd0]), gains, sc.adaptation_gain * np.ones(n_p), bound, p_hat0,
            friction, tuple("rad" if j.type == "revolute" else "m" for j in m.joints),
            ("x", "y", "phi"), ("m", "m", "rad"), (2,), m.fk_world))
    return setups


def unit_setups(sc: scenario_mod.Scenario) -> list[UnitSetup]:
    if sc.robot == "serial":
        return serial_units(sc)
    from .parallel_sim import parallel_units  # noqa: PLC0415

    return parallel_units(sc)


# --------------------------------------------------------------------------------------------
# The fused period and the loop
# --------------------------------------------------------------------------------------------


def plant_step(plant: RobotModel, substeps: int) -> ca.Function:
    """One control period of a plant, torque held: RK4 with ``substeps`` equal steps.

    ``(x, tau, p, friction, h) -> x_next`` with ``x = [q, qd]``, ``p`` the plant's full
    inertial parameters and ``friction`` its viscous coefficients (N m s/rad or N s/m). Generic
    in the parameters, so the same Function is the simulation's plant and a C kernel.
    """
    n = plant.nq
    x = ca.SX.sym("x", 2 * n)
    tau = ca.SX.sym("tau", n)
    p = ca.SX.sym("p", len(plant.param_names))
    friction = ca.SX.sym("friction", n)
    h = ca.SX.sym("h")

    def f(state):
        q, qd = state[:n], state[n:]
        return ca.vertcat(qd, plant.forward_dynamics_p(q, qd, tau - friction * qd, p))

    dt = h / substeps
    xk = x
    for _ in range(substeps):
        k1 = f(xk)
        k2 = f(xk + dt / 2 * k1)
        k3 = f(xk + dt / 2 * k2)
        k4 = f(xk + dt * k3)
        xk = xk + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    prefix = plant.name.replace("/", "_")
    return ca.Function(f"{prefix}_plant_step", [x, tau, p, friction, h], [xk],
                       ["x", "tau", "p", "friction", "h"], ["x_next"])


def period_function(u: UnitSetup, h: float, substeps: int) -> ca.Function:
    """``(t, x_true, x_measured, p_hat) -> (x_true_next, p_hat_next, tau, errors, xd, xd_dot)``."""
    n = u.controller_model.nq
    t = ca.SX.sym("t")
    x_true = ca.SX.sym("x_true", 2 * n)
    x_meas = ca.SX.sym("x_meas", 2 * n)
    p_hat = ca.SX.sym("p_hat", u.controller.n_params)
    xd, xd_dot, xd_ddot = u.desired(t)
    tau, p_next, errors = u.controller.step(
        x_meas[:n], x_meas[n:], xd, xd_dot, xd_ddot, p_hat, ca.DM(u.gains), ca.DM(u.gamma),
        u.bound, h)
    x_next = plant_step(u.plant_model, substeps)(x_true, tau, ca.DM(u.plant_params),
                                                 ca.DM(u.friction), h)
    return ca.Function(f"period_{u.name}", [t, x_true, x_meas, p_hat],
                       [x_next, p_next, tau, errors, xd, xd_dot],
                       ["t", "x_true", "x_meas", "p_hat"],
                       ["x_true_next", "p_hat_next", "tau", "errors", "xd", "xd_dot"])


#: ``simulate``'s backends: the generated C kernels (default) and the CasADi reference.
BACKENDS = ("c", "casadi")


def simulate(sc: scenario_mod.Scenario, duration: float | None = None,
             setups: list[UnitSetup] | None = None, backend: str = "c") -> SimulationResult:
    """Run the scenario as fast as possible and return the log of every period.

    A unit whose state or estimate becomes non-finite stops the run: ``result.diverged`` names
    it with the time, and the log keeps every period up to that one.

    ``backend``: ``"c"`` (default) runs the generated C kernels (``cochlea.csim``; if they
    cannot run this scenario it warns and falls back), ``"casadi"`` the CasADi reference below.
    """
    if backend not in BACKENDS:
        raise CochleaError(f"unknown backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    duration = sc.duration if duration is None else duration
    if not duration > 0:
        raise CochleaError(f"the duration must be positive, got {duration} s")
    setups = unit_setups(sc) if setups is None else setups
    if backend == "c":
        from .csim import simulate as simulate_c  # noqa: PLC0415 (csim imports this module)

        return simulate_c(sc, duration, setups, fallback=True)
    h = sc.period
    steps = int(round(duration / h))
    time = np.arange(steps) * h
    rng = np.random.default_rng(sc.plant.seed)
    logs = []
    diverged: dict[str, float] = {}
    for u in setups:
        n, n_p = u.controller_model.nq, u.controller.n_params
        nd, ne = u.controller.n_desired, u.controller.n_desired + n
        period = period_function(u, h, sc.plant_substeps)
        X = np.empty((steps, 2 * n))
        log = {k: np.empty((steps, s)) for k, s in
               [("tau", n), ("errors", ne), ("xd", nd), ("xd_dot", nd), ("p_hat", n_p)]}
        x = u.x0.astype(float).copy()
        p_hat = u.p_hat0.astype(float).copy()
        noise = np.concatenate([np.full(n, sc.plant.noise_q_std),
                                np.full(n, sc.plant.noise_qd_std)])
        delay = sc.plant.delay_periods
        rows = steps
        for k in range(steps):
            X[k] = x
            measured = X[max(k - delay, 0)]
            if noise.any():
                measured = measured + noise * rng.standard_normal(2 * n)
            log["p_hat"][k] = p_hat
            out = period(time[k], x, measured, p_hat)
            x = np.array(out[0]).ravel()
            p_hat = np.array(out[1]).ravel()
            log["tau"][k] = np.array(out[2]).ravel()
            log["errors"][k] = np.array(out[3]).ravel()
            log["xd"][k] = np.array(out[4]).ravel()
            log["xd_dot"][k] = np.array(out[5]).ravel()
            if not (np.isfinite(x).all() and np.isfinite(p_hat).all()):
                diverged[u.name] = float(time[k])  # keep the log up to and including row k
                rows = k + 1
                break
        X = X[:rows]
        log = {key: value[:rows] for key, value in log.items()}
        pose = np.array(u.fk_world.map(rows)(X[:, :n].T)).T
        logs.append(UnitLog(u.name, sc.space, X[:, :n], X[:, n:], log["xd"], log["xd_dot"],
                            log["errors"], log["tau"], log["p_hat"], pose, u))
    rows = min(len(u.q) for u in logs)
    if rows < steps:  # every unit's log ends where the first one diverged
        for u in logs:
            for key in ("q", "qd", "desired", "desired_dot", "errors", "tau", "p_hat", "x"):
                setattr(u, key, getattr(u, key)[:rows])
    return SimulationResult(sc, time[:rows], logs, diverged)
