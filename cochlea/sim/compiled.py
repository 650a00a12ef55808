"""Closed-loop simulation on the generated C kernels: what ``simulate(kernels="c")`` runs.

Same scenario, same setups, same :class:`~cochlea.sim.result.SimulationResult` as the CasADi
reference (``simulate(..., kernels="casadi")``); the tests hold every log to 1e-10 of it. Per
unit:

* the desired samples of the whole run come first, in one call of the unit's ``desired``
  Function mapped over the time grid (the trajectory formulas are scenario-specific, the kernels
  are not);
* measurement noise, if the scenario has any, is drawn up front from the scenario's seed in the
  reference's order and passed as an array, whole encoder counts of noise (their own stream)
  added to it; a measurement delay is read from the state log, per period where it jitters
  (:func:`cochlea.sim.setup.delay_ages`, the driver's ``delays``);
* then either the generated driver ``<unit>_<kind>[_thesis]_closed_loop`` runs every period in C
  (``loop="c"``, the default; the units of a scenario run on parallel threads, since ctypes
  releases the GIL), or a Python loop calls the fused ``step``, ``plant_step`` and ``fk_world``
  kernels through :mod:`cochlea.kernels.library` once per period (``loop="python"``, for
  comparison).

Before anything runs, every kernel a unit needs is looked up in the library's manifest and its
source hash compared with the Function the setup really uses (controller step, plant step with
the scenario's RK4 sub-steps, pose): a missing library, a scenario outside what
``codegen/kernels.toml`` generates, or a stale library raises
:class:`CKernelsUnavailable`; with ``fallback=True`` (what ``simulate`` does) that becomes a
warning and the CasADi reference runs.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..control.controllers import ROBUST_INPUTS
from ..errors import CochleaError
from ..kernels import library as ckernels
from ..kernels.bind import BufferedFunction, BufferedKernel
from ..kernels.catalogue import UnitSpec
from ..kernels.naming import closed_loop_name, controller_kernel_name, source_hash, unit_prefix
from ..robots.plant import gear_plant_step, plant_step
from .reference import simulate_reference
from .result import SimulationResult, simulated_log, truncate
from .setup import (
    MeasurementGrid,
    UnitSetup,
    delay_ages,
    encoder_noise,
    measurements,
    mirror_stop,
    run_inputs,
    unit_setups,
)

LOOPS = ("c", "python")


class CKernelsUnavailable(CochleaError):
    """The generated C kernels cannot run this scenario (missing, not generated, or stale)."""


class CKernelsWarning(UserWarning):
    """The C kernels could not run a scenario: the CasADi reference ran instead."""


@dataclass(frozen=True)
class UnitKernels:
    """The kernels one unit runs on."""

    step: str
    plant: str
    pose: str
    closed_loop: str


#: Per-object caches of the checks (objects kept alive, so their ids stay theirs).
_HASHES: dict[int, tuple[object, str]] = {}
_PLANTS: dict[tuple[int, int], tuple[object, object]] = {}


def _hash(function) -> str:
    if id(function) not in _HASHES:
        _HASHES[id(function)] = (function, source_hash(function))
    return _HASHES[id(function)][1]


def _plant(u: UnitSetup, substeps: int):
    """The unit's plant Function (:meth:`UnitSetup.plant_function`), built once per model."""
    key = (id(u.plant_model), substeps, u.drive is not None, u.gearbox)
    if key not in _PLANTS:
        _PLANTS[key] = (u.plant_model, u.plant_function(substeps))
    return _PLANTS[key][1]


#: Units whose kernels :func:`unit_kernels` found and checked, by everything it reads (the
#: Functions by identity, kept alive with the entry, the names and options by value).
UNIT_KERNEL_CACHE_SIZE = 64
_UNIT_KERNELS: OrderedDict[tuple, tuple[tuple, UnitKernels]] = OrderedDict()


def unit_kernels(lib: ckernels.Library, u: UnitSetup, substeps: int) -> UnitKernels:
    """Find a unit's kernels in the library and check they compute what the setup does
    (source hashes; computed once per Function object). A unit found before in the same
    library, with the same Functions, names and plant options (a sweep's samples of one
    structure), is not looked up and checked again; a failure is never kept."""
    c, m, pm = u.controller, u.controller_model, u.plant_model
    key = (id(lib), id(c.step), c.kind, c.variant, m.name, m.actuators, id(pm), pm.actuators,
           pm.name, substeps, u.drive is not None, bool(u.gearbox), id(u.fk_world))
    hit = _UNIT_KERNELS.get(key)
    if hit is not None:
        with contextlib.suppress(KeyError):  # another thread may have let it go meanwhile
            _UNIT_KERNELS.move_to_end(key)
        return hit[1]
    found = _unit_kernels(lib, u, substeps)
    _UNIT_KERNELS[key] = ((lib, c.step, pm, u.fk_world), found)  # their ids stay theirs
    while len(_UNIT_KERNELS) > UNIT_KERNEL_CACHE_SIZE:
        with contextlib.suppress(KeyError):
            _UNIT_KERNELS.popitem(last=False)
    return found


def _unit_kernels(lib: ckernels.Library, u: UnitSetup, substeps: int) -> UnitKernels:
    """:func:`unit_kernels`, looked up and checked."""
    c = u.controller
    group = controller_kernel_name(unit_prefix(u.controller_model), c.kind, c.variant, "",
                                   u.controller_model.actuators)[:-1]
    plant = _plant(u, substeps)
    wanted = [(f"{group}_step", c.step, f"controller {c.kind} ({c.variant})"),
              (plant.name(), plant, f"the plant with {substeps} "
               f"{'gear' if u.gearbox else 'RK4'} sub-steps"),
              (u.fk_world.name(), u.fk_world, "the logged pose")]
    for name, function, what in wanted:
        if name not in lib.manifest["kernels"]:
            raise CKernelsUnavailable(
                f"{lib.path} has no kernel {name} ({what} of unit {u.name}): generate this "
                "scenario's with cochlea-codegen --scenario FILE --out DIR and run on "
                "--library DIR (a shipped robot: add it to codegen/kernels.toml, "
                "run cochlea-codegen and make lib), or use the CasADi kernels")
        if lib.source_hash(name) != _hash(function):
            raise CKernelsUnavailable(
                f"the C kernel {name} in {lib.path} computes something else than {what} of "
                f"unit {u.name} (a different description, parameterisation or option, or a "
                "stale library): run cochlea-codegen (--scenario FILE --out DIR for your "
                "own robot) and make lib, or use the CasADi kernels")
    loop = closed_loop_name(group, u.plant_model, u.drive is not None and not u.gearbox,
                            u.gearbox)
    meta = lib.manifest["closed_loops"].get(loop)
    if meta is None or (meta["step"], meta["plant"], meta["pose"]) != \
            (f"{group}_step", plant.name(), u.fk_world.name()):
        raise CKernelsUnavailable(f"{lib.path} has no closed loop {loop} on {plant.name()}: "
                                  "run cochlea-codegen and make lib")
    return UnitKernels(f"{group}_step", plant.name(), u.fk_world.name(), loop)


#: Desired samples kept per process (:func:`desired_samples`): a 20 s run at 1 kHz is about
#: 1.5 MB per unit; a sweep's worker meets one time grid per structure.
DESIRED_CACHE_SIZE = 16
_DESIRED: OrderedDict[tuple, tuple[object, np.ndarray, tuple[np.ndarray, ...]]] = \
    OrderedDict()


def desired_samples(u: UnitSetup, time: np.ndarray) -> tuple[np.ndarray, ...]:
    """``(xd, xd_dot, xd_ddot)`` at every time of the grid, each ``(N, nd)``, in one call
    (CasADi's map on up to 4 threads; every sample is computed on its own).

    Computed once per process for each desired Function object and time grid (the Function
    kept alive with them, so its id stays its own): the set-ups of one structure share it
    (:func:`cochlea.sim.setup.unit_setups`). The arrays are read-only, since every run of the
    structure reads them."""
    time = np.asarray(time, dtype=float)
    key = (id(u.desired), len(time), float(time[0]) if len(time) else 0.0,
           float(time[-1]) if len(time) else 0.0)
    hit = _DESIRED.get(key)
    # The whole grid, bit for bit (not only its ends; -0.0 is not 0.0 to every formula): as
    # integers, without the two copies tobytes() made (0.1 ms a unit, every sweep sample).
    if hit is not None and np.array_equal(hit[1].view(np.int64), time.view(np.int64)):
        with contextlib.suppress(KeyError):  # a dask worker's other thread may evict it
            _DESIRED.move_to_end(key)
        return hit[2]
    n = len(time)
    t = ca.SX.sym("t")
    # Dense outputs: a constant coordinate's derivatives are structural zeros otherwise.
    dense = ca.Function("desired_dense", [t], [ca.densify(v) for v in u.desired(t)])
    mapped = BufferedFunction(dense.map(n, "thread", max(1, min(4, os.cpu_count() or 1))))
    mapped.inputs[0][:] = time
    mapped()  # straight into numpy buffers: no conversion of CasADi matrices afterwards
    # CasADi stores the (nd x n) outputs column by column: each row of the reshape is a sample.
    samples = tuple(out.reshape(n, -1) for out in mapped.outputs)
    for a in samples:
        a.flags.writeable = False
    grid = time.copy()
    grid.flags.writeable = False
    _DESIRED[key] = (u.desired, grid, samples)
    while len(_DESIRED) > DESIRED_CACHE_SIZE:
        with contextlib.suppress(KeyError):  # emptied by another thread meanwhile
            _DESIRED.popitem(last=False)
    return samples


def run_c(lib: ckernels.Library, kernels: UnitKernels, u: UnitSetup, h: float, delay,
           desired, noise) -> ckernels.ClosedLoopLog:
    """A unit's whole run in its generated driver, every plant option of the setup passed.
    ``delay``: whole periods, or each period's (:func:`cochlea.sim.setup.delay_ages`)."""
    loop = lib.closed_loop(kernels.closed_loop)
    xd, xd_dot, xd_ddot = desired
    grid = u.effort_grid
    jitter = np.ndim(delay) > 0
    # One delay: its rows in front of the state log, so the measured states are a view of it
    # (ClosedLoopLog.delayed), not a copy of the whole log.
    lead = 0 if jitter else min(int(delay), len(xd))
    return loop.run(len(xd), lead=lead, x0=u.plant_x0, p_hat0=u.p_hat0, xd=xd, xd_dot=xd_dot,
                    xd_ddot=xd_ddot, gains=u.gains, Gamma=u.gamma, bound=u.bound, h=h,
                    plant_p=u.plant_params, friction=u.friction, noise=noise,
                    delay=0 if jitter else delay, delays=delay if jitter else None,
                    quantum=u.quantum, offset=u.grid_offset, effort_limit=u.effort_limit,
                    coulomb=u.drive, effort_quantum=None if grid is None else grid.quantum,
                    effort_bound=None if grid is None else grid.bound,
                    effort_offset=None if grid is None else grid.offset,
                    effort_ramp=None if grid is None else grid.ramp,
                    robust=u.robust_inputs, torque_scale=u.torque_scale, reductions=True,
                    keep_out=keep_out_points(u))


def keep_out_points(u: UnitSetup) -> list[tuple]:
    """A unit's keep-out tool points as a closed-loop driver gathers their nearest approach
    (:meth:`cochlea.kernels.library.ClosedLoop.run`): each tool point's pose columns and its
    centre, fixed or on the moving joint (at u = 0, as the supervisor places it)."""
    cu, cv, joint = u.keep_out_reference()
    return [(iu, iv, joint, cu, cv) for _, (iu, iv) in u.tool_points]


def _shifted(log: ckernels.ClosedLoopLog, delay, rows: int) -> np.ndarray | None:
    """The first ``rows`` logged states ``delay`` periods earlier, a view of the log (one
    delay, a C driver's log with its rows in front), else None."""
    if np.ndim(delay) > 0 or not delay or not rows:
        return None
    return log.delayed(int(delay), rows)


def run_python(lib: ckernels.Library, kernels: UnitKernels, u: UnitSetup, h: float,
                delay, desired, noise) -> ckernels.ClosedLoopLog:
    """The same periods as the C driver, looping in Python over the ctypes kernels."""
    xd, xd_dot, xd_ddot = desired
    steps, n, n_p = len(xd), u.controller_model.nq, u.controller.n_params
    x = np.array(u.plant_x0, dtype=float)  # the plant's state; logged and measured: [q, qd]
    p_hat = np.array(u.p_hat0, dtype=float)
    meas = np.empty(2 * n)
    step = lib.kernel(kernels.step, q=meas[:n], qd=meas[n:], p_hat=p_hat)
    scale = u.torque_scale  # the motor's torque over the applied effort, or None
    torque = step["tau"] if scale is None else np.empty(n)
    plant = lib.kernel(kernels.plant, x=x, tau=torque)
    pose = lib.kernel(kernels.pose, q=x[:n])
    step["gains"][:] = u.gains
    step["Gamma"][:] = u.gamma
    step["bound"][...] = u.bound
    step["h"][...] = h
    for name, value in zip(ROBUST_INPUTS, u.robust_inputs):
        step[name][:] = value
    plant["p"][:] = u.plant_params
    plant["friction"][:] = u.friction
    plant["h"][...] = h
    if u.drive is not None:  # the plant's 6th input: dry friction, or the gear's drive
        plant.inputs[plant.signature.inputs[5].name][:] = u.drive
    b_xd, b_xd_dot, b_xd_ddot = step["xd"], step["xd_dot"], step["xd_ddot"]
    tau, p_next, errors = step["tau"], step["p_hat_next"], step["errors"]
    x_next, pose_out = plant["x_next"], pose.outputs[next(iter(pose.outputs))]
    call_step, call_plant, call_pose = step.call, plant.call, pose.call
    log = ckernels.ClosedLoopLog(steps, np.empty((steps, 2 * n)), np.empty((steps, n_p)),
                                 np.empty((steps, n)), np.empty((steps, len(errors))),
                                 np.empty((steps, len(pose_out))))
    X, P, TAU, E, POSE = log.x, log.p_hat, log.tau, log.errors, log.pose
    limit = u.effort_limit
    drive = None if u.effort_grid is None else u.effort_grid.apply
    grid = None if u.quantum is None else MeasurementGrid(u.quantum, u.grid_offset).apply
    isfinite = np.isfinite
    ages = np.broadcast_to(np.asarray(delay), (steps,))
    for k in range(steps):
        X[k] = x[:2 * n]
        age = ages[k]
        seen = X[k - age] if k >= age else X[0]
        if noise is None:
            meas[:] = seen
        else:
            np.add(seen, noise[k], out=meas)
        if grid is not None:
            grid(meas)
        P[k] = p_hat
        b_xd[:] = xd[k]
        b_xd_dot[:] = xd_dot[k]
        b_xd_ddot[:] = xd_ddot[k]
        failed = call_step()
        np.clip(tau, -limit, limit, out=tau)  # as the supervisor clips every command
        if drive is not None:  # as the drives apply it: whole current LSBs, saturated
            drive(tau)
        if scale is not None:  # the motor's torque-constant error
            np.multiply(scale, tau, out=torque)
        if failed or call_plant() or call_pose():
            raise ckernels.KernelError(f"a kernel of unit {u.name} returned a nonzero code")
        TAU[k] = tau
        E[k] = errors
        POSE[k] = pose_out
        x[:] = x_next
        p_hat[:] = p_next
        if not (isfinite(x).all() and isfinite(p_hat).all()):
            log.rows = k + 1
            break
    return log


def simulate_compiled(sc, duration: float | None = None, setups: list[UnitSetup] | None = None,
                      *, loop: str = "c", library=None, fallback: bool = False,
                      threads: bool = True) -> SimulationResult:
    """Run the scenario on the C kernels; the result equals ``simulate(kernels="casadi")``'s.

    ``loop``: ``"c"`` (every period in the generated C driver) or ``"python"`` (a Python loop
    over the ctypes kernels). ``library``: the ``.so`` to use (default: ``ckernels.load()``'s).
    ``fallback``: run the CasADi reference, with a :class:`CKernelsWarning`, when the C kernels
    cannot run this scenario, instead of raising :class:`CKernelsUnavailable`.
    ``threads``: the units (the C loop releases the GIL) on a thread each; the same logs either
    way, since the units do not interact.
    """
    if loop not in LOOPS:
        raise CochleaError(f"unknown loop {loop!r}; choose one of {', '.join(LOOPS)}")
    duration, setups = run_inputs(sc, duration, setups)
    try:
        lib = ckernels.load(library)
        plans = [unit_kernels(lib, u, sc.plant_substeps) for u in setups]
    except CochleaError as exc:
        if not fallback:
            raise CKernelsUnavailable(str(exc)) from exc
        warnings.warn(f"{exc}. Simulating on the CasADi kernels instead.", CKernelsWarning,
                      stacklevel=3)
        result = simulate_reference(sc, duration, setups)
        result.kernels = KernelChoice("casadi", "auto", reason=str(exc)).summary()
        return result

    h = sc.period
    steps = int(round(duration / h))
    time = np.arange(steps) * h
    ages = delay_ages(sc.plant, steps)  # each period's delay where it jitters
    delay = sc.plant.delay_periods if ages is None else ages
    run = run_c if loop == "c" else run_python
    if any(u.follow is not None for u in setups):  # mirror = "measured": one after the other
        return _simulate_following(sc, setups, lib, plans, run, time, delay, fallback)
    desired = [desired_samples(u, time) for u in setups]
    noisy = [np.concatenate([np.full(u.controller_model.nq, sc.plant.noise_q_std),
                             np.full(u.controller_model.nq, sc.plant.noise_qd_std)])
             for u in setups]
    # Each unit's measurement noise, kept for its log: whole encoder counts (their own stream,
    # drawn up front) added to the Gaussian draws, as the reference adds them.
    noises = encoder_noise(sc.plant, steps, setups)
    for i, (u, counts) in enumerate(zip(setups, noises)):
        if counts is not None:
            noises[i] = np.zeros((steps, 2 * u.controller_model.nq))
            noises[i][:, :u.controller_model.nq] += counts
    if any(std.any() for std in noisy):
        # The reference draws 2n normals per period, unit after unit, until a unit stops.
        rng = np.random.default_rng(sc.plant.seed)
        runs = []
        for i, (u, plan, d, std) in enumerate(zip(setups, plans, desired, noisy)):
            if std.any():
                state = rng.bit_generator.state
                gauss = std * rng.standard_normal((steps, len(std)))
                if noises[i] is not None:
                    gauss[:, :u.controller_model.nq] += noises[i][:, :u.controller_model.nq]
                noises[i] = gauss
            runs.append(run(lib, plan, u, h, delay, d, noises[i]))
            if std.any() and runs[-1].rows < steps:
                rng.bit_generator.state = state
                rng.standard_normal((runs[-1].rows, len(std)))
    elif loop == "c" and len(setups) > 1 and threads:
        with ThreadPoolExecutor(max_workers=len(setups)) as pool:
            runs = list(pool.map(lambda a: run(lib, a[0], a[1], h, delay, a[2], a[3]),
                                 list(zip(plans, setups, desired, noises))))
    else:
        runs = [run(lib, p, u, h, delay, d, noise)
                for p, u, d, noise in zip(plans, setups, desired, noises)]

    logs, diverged = [], {}
    for u, d, r, noise in zip(setups, desired, runs, noises):
        rows = r.rows
        if rows < steps:
            diverged[u.name] = float(time[rows - 1])
        X = r.x[:rows]
        # What the controller saw, from the true states as the driver measured them.
        seen = measurements(X, delay, noise, u.quantum, u.grid_offset, _shifted(r, delay, rows))
        logs.append(simulated_log(u, sc.space, X, seen, r.pose[:rows], d[0][:rows],
                                  d[1][:rows], r.errors[:rows], r.tau[:rows], r.p_hat[:rows],
                                  r.reductions))
    rows = min(len(u.q) for u in logs)
    if rows < steps:  # every unit's log ends where the first one diverged (as the reference)
        truncate(logs, rows)
    return SimulationResult(sc, time[:rows], logs, diverged,
                            kernels=KernelChoice("c", "auto" if fallback else "c",
                                                 str(lib.path)).summary())


def _simulate_following(sc, setups: list[UnitSetup], lib, plans, run, time: np.ndarray, delay,
                        fallback: bool) -> SimulationResult:
    """:func:`simulate_compiled` with a follower (``mirror = "measured"``): the units run one
    after the other, the leader first, so that a follower's desired samples come from what its
    leader's controller saw in each period (:meth:`cochlea.sim.setup.Follow.samples`, as the
    reference computes them); its run ends at the period its rule fails, the safe stop
    (``result.mirror_stop``). Noise is drawn as the reference draws it, unit after unit."""
    steps = len(time)
    rng = np.random.default_rng(sc.plant.seed)
    counts = encoder_noise(sc.plant, steps, setups)
    logs, seen_by, diverged, stopped = [], [], {}, None
    for u, plan, encoder in zip(setups, plans, counts):
        n = u.controller_model.nq
        if u.follow is None:
            desired = desired_samples(u, time)
        else:
            desired, failure = u.follow.samples(seen_by[u.follow.leader], time)
            if failure is not None and (stopped is None or failure.row < stopped.row):
                stopped = failure
        rows = len(desired[0])
        std = np.concatenate([np.full(n, sc.plant.noise_q_std), np.full(n, sc.plant.noise_qd_std)])
        noise = None
        if std.any() or encoder is not None:
            noise = np.zeros((rows, 2 * n))
            if std.any():  # the reference's draws: 2n normals a period, up to where it stops
                state = rng.bit_generator.state
                noise = std * rng.standard_normal((rows, 2 * n))
            if encoder is not None:
                noise[:, :n] += encoder[:rows]
        ages = delay if np.ndim(delay) == 0 else delay[:rows]
        r = run(lib, plan, u, sc.period, ages, desired, noise)
        if std.any() and r.rows < rows:
            rng.bit_generator.state = state
            rng.standard_normal((r.rows, 2 * n))
        if r.rows < rows:
            diverged[u.name] = float(time[r.rows - 1])
        X = r.x[:r.rows]
        seen = measurements(X, ages, noise, u.quantum, u.grid_offset, _shifted(r, ages, r.rows))
        seen_by.append(seen)
        logs.append(simulated_log(u, sc.space, X, seen, r.pose[:r.rows], desired[0][:r.rows],
                                  desired[1][:r.rows], r.errors[:r.rows], r.tau[:r.rows],
                                  r.p_hat[:r.rows], r.reductions))
    rows = min(len(u.q) for u in logs)
    if rows < steps:
        truncate(logs, rows)
    choice = KernelChoice("c", "auto" if fallback else "c", str(lib.path))
    return SimulationResult(sc, time[:rows], logs, diverged,
                            mirror_stop=mirror_stop(stopped, rows), kernels=choice.summary())


#: Where a unit's kernels come from: the generated C library or CasADi.
KERNEL_SOURCES = ("c", "casadi")


def period_kernels(u: UnitSetup, substeps: int, source: str = "c"):
    """A unit's ``(step, plant_step, pose)`` kernels, each called through bound buffers, and
    where they come from.

    ``source="c"``: the generated C kernels, checked against the Functions the setup uses (a
    missing or stale library falls back to CasADi with a warning); ``"casadi"``: CasADi
    Functions called through preallocated buffers.
    """
    if source == "c":
        try:
            lib = ckernels.load()
            names = unit_kernels(lib, u, substeps)
            return (BufferedKernel(lib.kernel(names.step)), BufferedKernel(lib.kernel(names.plant)),
                    BufferedKernel(lib.kernel(names.pose)), "c")
        except CochleaError as exc:
            warnings.warn(f"{exc}; running on the CasADi kernels", CKernelsWarning, stacklevel=2)
    return (BufferedFunction(u.controller.step), BufferedFunction(_plant(u, substeps)),
            BufferedFunction(u.fk_world), "casadi")


# --------------------------------------------------------------------------------------------
# Which kernels a run uses, decided once, before it starts
# --------------------------------------------------------------------------------------------

#: What a run may ask for: "auto" (the C kernels when the library has this scenario's, else
#: CasADi, saying so), "c" (the C kernels or a refusal) and "casadi" (the reference).
KERNEL_CHOICES = ("auto", "c", "casadi")


@dataclass(frozen=True)
class KernelChoice:
    """The kernels a run uses: ``used`` ("c" or "casadi"), what was ``requested``, the
    ``library`` the C kernels come from, and why the C kernels could not run it (``reason``:
    set when "auto" fell back)."""

    used: str
    requested: str
    library: str | None = None
    reason: str | None = None

    def summary(self) -> dict:
        """The ``kernels`` entry of summary.json."""
        return {"used": self.used, "requested": self.requested, "library": self.library,
                "fallback_reason": self.reason}

    def line(self) -> str:
        """One line for the console: which kernels, from where, and why not C."""
        if self.used == "c":
            return f"C kernels from {self.library}"
        if self.reason is None:
            return "CasADi (asked for)"
        return f"CasADi (the C kernels cannot run this scenario: {self.reason})"


def choose_kernels(setups: list[UnitSetup], substeps: int, kernels: str = "auto",
                   library=None) -> KernelChoice:
    """Decide, before anything runs, which kernels run ``setups``: the library (``library``,
    else ``$COCHLEA_LIB``, else the shipped one; a folder ``cochlea-codegen --out`` wrote
    names its ``libcochlea.so``) is loaded and every unit's kernels checked against the
    Functions the setups use (:func:`unit_kernels`: names and source hashes).

    ``kernels="c"``: a library that lacks or mismatches a kernel raises
    :class:`CKernelsUnavailable` (one line, naming the kernel); ``"auto"``: that falls back to
    CasADi, the reason kept in the choice; ``"casadi"``: the reference, nothing checked."""
    if kernels not in KERNEL_CHOICES:
        raise CochleaError(f"unknown kernels {kernels!r}; choose one of "
                           + ", ".join(KERNEL_CHOICES))
    if kernels == "casadi":
        return KernelChoice("casadi", "casadi")
    try:
        lib = ckernels.load(library)
        for u in setups:
            unit_kernels(lib, u, substeps)
    except CochleaError as exc:
        if kernels == "c":
            raise CKernelsUnavailable(f"--kernels c: {exc}") from None
        return KernelChoice("casadi", "auto", reason=str(exc))
    return KernelChoice("c", kernels, str(lib.path))


# --------------------------------------------------------------------------------------------
# What a user's scenario needs generated (cochlea-codegen --scenario)
# --------------------------------------------------------------------------------------------


def scenario_units(sc, setups: list[UnitSetup] | None = None) -> list[UnitSpec]:
    """What to generate for scenario ``sc`` (:func:`cochlea.kernels.catalogue.collect_units`):
    per unit the Functions its run checks -- the controller, the logged pose, the plant step the
    scenario's ``[plant]`` needs -- and that plant's sibling with or without dry friction (so a
    sweep that turns the scenario's Coulomb friction on or off stays on C). The geared plant
    (``gearbox``, the realistic preset) has one step, friction included."""
    setups = setups if setups is not None else unit_setups(sc, gravity=False)
    units = []
    for u in setups:
        if u.gearbox:
            plants = ((u.plant_model, gear_plant_step(u.plant_model, sc.plant_substeps)),)
        else:
            plants = tuple((u.plant_model, plant_step(u.plant_model, sc.plant_substeps,
                                                      coulomb=coulomb))
                           for coulomb in (False, True))
        units.append(UnitSpec(sc.robot, u.controller_model, u.controller, u.fk_world,
                              u.plant_model, plants))
    return units
