"""The one schema of every run log's columns (docs/logs.md, "Column names and units").

Every log a run leaves names its columns the same way: ``log.csv`` (cochlea-run on any
backend, and the embedded program), ``log.bin``'s ``log.columns.json`` (the loop's raw period
buffer, and the embedded program's) and the sweeps' per-sample columns where they name logged
quantities. :func:`run_columns` produces them all, from one description of the run's units.

A column is ``time_s``, a run-level timing column (``start_lateness_s``, ... in s), or
``UNIT.GROUP.ELEMENT_UNIT``: ``arm1.q.joint1_rad``, ``arm1.tau.joint1_N_m``,
``mechanism.p_hat.left.link1.m_kg``. The unit suffix is the SI unit written with ``_`` between
its factors and ``/`` (``rad_s`` is rad/s, ``N_m`` is N m, ``kg_m2`` is kg m^2); ``1`` is
dimensionless. An estimate carries its parameter's unit; ``SI`` only where the
parameterisation names none (a user's model whose parameter units are unknown).

Version history (``schema_version`` in ``log.columns.json`` and ``summary.json``):

1. (no ``schema_version``) ``log.csv`` as today's but with ``Nm`` for N m and units squeezed
   (``kgm2``); ``log.columns.json`` named ``q.UNIT.JOINT_rad`` (group first), the controller's
   state ``UNIT.e[0]_SI`` and the estimates ``UNIT.p_hat.PARAM_SI``.
2. this module.
"""

from __future__ import annotations

from dataclasses import dataclass

#: The version of the column names below; written in log.columns.json and summary.json.
SCHEMA_VERSION = 2

#: The run-level timing columns (s) of a real-time run, in this order.
TIMING_COLUMNS = ("start_lateness_s", "wall_period_s", "compute_s", "backend_io_s")

#: A joint's (or coordinate's) position unit -> the unit of its rate and of its effort.
RATE_UNIT = {"rad": "rad_s", "m": "m_s"}
EFFORT_UNIT = {"rad": "N_m", "m": "N"}
#: Written where a parameter's unit is not known.
UNKNOWN_UNIT = "SI"


def unit_suffix(unit: str) -> str:
    """A unit as text (``kg m^2``, ``N m s/rad``) as a column's suffix (``kg_m2``,
    ``N_m_s_rad``); an empty unit is not known (``SI``)."""
    text = unit.strip().replace("^", "").replace("*", " ").replace("/", " ")
    return "_".join(text.split()) or UNKNOWN_UNIT


@dataclass(frozen=True)
class LogUnit:
    """What the schema needs of one controlled unit."""

    name: str  # arm1, mechanism
    joints: tuple[str, ...]
    joint_units: tuple[str, ...]  # rad | m
    tracked: tuple[str, ...]  # the coordinates the controller tracks (joints or task)
    tracked_units: tuple[str, ...]  # rad | m
    error_names: tuple[str, str]  # the controller's two errors: ("e", "r"), ("e_g", "e_v")
    params: tuple[str, ...]
    param_units: tuple[str, ...]  # as text: kg, kg m^2
    task: tuple[str, ...] = ()  # the tool pose's coordinates
    task_units: tuple[str, ...] = ()

    @classmethod
    def of_setup(cls, u, space: str) -> LogUnit:
        """From a :class:`cochlea.sim.setup.UnitSetup` run in ``space``."""
        joints = tuple(j.name for j in u.controller_model.joints)
        params = u.controller_model.parameters
        return cls(u.name, joints, tuple(u.joint_units),
                   joints if space == "joint" else tuple(u.task_names),
                   tuple(u.joint_units) if space == "joint" else tuple(u.task_units),
                   tuple(u.controller.error_names), tuple(params.names),
                   tuple(params.si_units), tuple(u.task_names), tuple(u.task_units))

    @classmethod
    def of_embedded(cls, u) -> LogUnit:
        """From a :class:`cochlea.kernels.embedded.EmbeddedUnit` (it has no pose)."""
        return cls(u.name, tuple(u.joint_names), tuple(u.joint_units), tuple(u.tracked_names),
                   tuple(u.tracked_units), tuple(u.error_names), tuple(u.param_names),
                   tuple(u.param_units))


def unit_groups(u: LogUnit, *, current: bool, pose: bool, true_state: bool,
                controller_error: bool = False) -> list[tuple[str, list[str]]]:
    """``(group, column names)`` of one unit, in log.csv's order.

    ``controller_error``: the controller's own first error (``e``, ``e_g``, ``e_p``: the
    tracked coordinates, at the controller's sign) instead of log.csv's ``error`` (desired
    minus measured, angles wrapped, which log.csv computes after the run)."""
    rate, effort = RATE_UNIT, EFFORT_UNIT

    def cols(group, elements, units):
        return group, [f"{u.name}.{group}.{e}_{un}" for e, un in zip(elements, units)]

    first, second = u.error_names
    groups = [cols("q", u.joints, u.joint_units),
              cols("qd", u.joints, [rate[x] for x in u.joint_units]),
              cols("desired", u.tracked, u.tracked_units),
              cols("desired_dot", u.tracked, [rate[x] for x in u.tracked_units]),
              cols(first, u.tracked, u.tracked_units) if controller_error else
              cols("error", u.tracked, u.tracked_units),
              cols(second, u.joints, [rate[x] for x in u.joint_units]),
              cols("tau", u.joints, [effort[x] for x in u.joint_units])]
    if current:
        groups.append(cols("current", u.joints, ["A"] * len(u.joints)))
    groups.append(cols("p_hat", u.params, [unit_suffix(x) for x in u.param_units]))
    if pose:
        groups.append(cols("pose", u.task, u.task_units))
    if true_state:
        groups += [cols("true_q", u.joints, u.joint_units),
                   cols("true_qd", u.joints, [rate[x] for x in u.joint_units])]
        if pose:
            groups.append(cols("true_pose", u.task, u.task_units))
        groups.append(cols("true_error", u.tracked, u.tracked_units))
    return groups


def run_columns(units: list[LogUnit], *, timing: bool, current: bool, pose: bool = True,
                true_state: bool = False) -> list[str]:
    """``log.csv``'s header of a run: ``time_s``, each unit's groups, then (a real-time run)
    the timing columns. ``current``: the drives measured current (hardware, the embedded
    program); ``pose``: the tool pose is logged (cochlea-run, not the embedded program);
    ``true_state``: the plant's true state is known (simulated runs)."""
    names = ["time_s"]
    for u in units:
        for _, cols in unit_groups(u, current=current, pose=pose, true_state=true_state):
            names += cols
    return names + (list(TIMING_COLUMNS) if timing else [])


def raw_columns(units: list[LogUnit], *, current: bool, true_state: bool) -> list[str]:
    """``log.bin``'s columns (``log.columns.json``), in the loop's row layout: ``time_s``,
    every unit's ``q``, then every unit's ``qd``, every unit's ``tau``, per unit the
    controller's two errors and ``p_hat``, the timing columns, every unit's ``current`` (when
    measured), every unit's ``true_q`` and ``true_qd`` (when known). The same names as
    :func:`run_columns`'s; the controller's first error (``e``, ``e_g``, ``e_p``) stands
    where log.csv has ``error``."""
    per_unit = [dict(unit_groups(u, current=current, pose=False, true_state=true_state,
                                 controller_error=True)) for u in units]

    def every(group):
        return [c for g in per_unit for c in g.get(group, [])]

    names = ["time_s"] + every("q") + every("qd") + every("tau")
    for u, g in zip(units, per_unit):
        names += g[u.error_names[0]] + g[u.error_names[1]] + g["p_hat"]
    names += list(TIMING_COLUMNS) + every("current")
    return names + every("true_q") + every("true_qd")


def columns_document(units: list[LogUnit], *, current: bool, true_state: bool,
                     row_length: int) -> dict:
    """``log.columns.json``'s content."""
    names = raw_columns(units, current=current, true_state=true_state)
    if len(names) != row_length:
        raise AssertionError(f"log.bin rows hold {row_length} values but the schema names "
                             f"{len(names)}")
    return {"schema_version": SCHEMA_VERSION, "dtype": "float64", "row_length": row_length,
            "columns": names}
