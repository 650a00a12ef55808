"""The scenarios' embedded controllers: what ``cochlea-codegen`` writes to
``generated_c/embedded/`` (the ``[embedded]`` table of ``codegen/kernels.toml``).

Each scenario's units (:func:`~cochlea.sim.setup.unit_setups`: the same desired trajectory,
controller, gains, adaptation gain, projection bound, initial estimate and effort limits as the
simulation) become :class:`~cochlea.kernels.embedded.EmbeddedUnit` data, and
:func:`~cochlea.kernels.embedded.embedded_sources` writes the C. See ``docs/embedded.md``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import CochleaError
from ..kernels.catalogue import CodegenConfig, law_units
from ..kernels.embedded import (
    EmbeddedScenario,
    EmbeddedUnit,
    embedded_sources,
    scenario_source,
    scenario_table,
)
from ..robots.motor_fit import bridge_compensates_friction
from .scenario import Scenario
from .scenario import load as load_scenario
from .setup import unit_setups

__all__ = ["check_embeddable", "embedded_scenario", "embedded_units", "write_embedded",
           "scenario_sources"]


def check_embeddable(sc: Scenario) -> None:
    """Refuse, in one line, what the embedded controller cannot run: a follower of its
    leader's measured pose (``mirror = "measured"``: its C loop takes every unit's desired
    path as a function of t, ``embedded/core/loop.c``)."""
    if sc.mirror == "measured":
        raise CochleaError(
            f"scenario {sc.path}: mirror = \"measured\" is not supported by the embedded "
            "program and the all-C simulation (their desired paths are functions of t): use "
            "mirror = \"desired\" there, or run it with cochlea-run (docs/controllers.md, "
            "\"The dual-arm rule\")")


def embedded_units(sc: Scenario) -> list[EmbeddedUnit]:
    """Every controlled unit of the scenario, as its embedded controller runs it."""
    check_embeddable(sc)
    units = []
    for u in unit_setups(sc):
        c = u.controller
        units.append(EmbeddedUnit(
            u.name, u.desired, c.law, tuple(u.joint_units), c.gain_names, c.gain_sizes,
            c.error_names, tuple(u.controller_model.param_names),
            law_units(u.controller_model, c), u.gains, u.gamma, float(u.bound), u.p_hat0,
            u.effort_limit, controller=f"{c.kind} ({c.variant}), {c.space} space",
            fk=u.fk_world, tool_points=tuple(u.tool_points),
            keep_out_reference=u.keep_out_reference(),
            tracked_names=(tuple(j.name for j in u.controller_model.joints)
                           if c.space == "joint" else tuple(u.task_names)),
            tracked_units=(tuple(u.joint_units) if c.space == "joint"
                           else tuple(u.task_units)),
            joint_names=tuple(j.name for j in u.controller_model.joints),
            param_units=tuple(u.controller_model.parameters.si_units),
            p_nominal=np.asarray(u.controller_model.p_nominal, float),
            tracking_sign=-1 if c.kind == "g" else 1,
            robust=tuple(np.asarray(v, float) for v in u.robust_inputs)))
    return units


def embedded_scenario(sc: Scenario) -> EmbeddedScenario:
    """The scenario's facts the embedded runtime carries (names, period, keep-out radius)."""
    check_embeddable(sc)
    radius = sc.system.keep_out_radius  # every run: the circle does not depend on the space
    start = tuple(float(v) for u in unit_setups(sc) for v in u.x0[:u.controller_model.nq])
    return EmbeddedScenario(sc.name, sc.robot, sc.space, sc.controller, sc.variant,
                            sc.parameterisation, sc.period, float(sc.duration),
                            float(radius) if radius is not None else 0.0,
                            bridge_compensates_friction(sc.controller_actuators), start)


def scenario_sources(sc: Scenario, function: dict) -> dict[str, str]:
    """The embedded controller of one loaded scenario (a user's file too) and the table of
    scenarios holding it alone: file name -> text (``<name>.h``, ``<name>.c``,
    ``<name>_scenario.c``, ``scenarios.h``, ``scenarios.c``). The robot's drive table
    (``<robot>_drives.h``) is the caller's (:mod:`cochlea.dynamixel.embedded_drives`)."""
    name = sc.name
    if not re.fullmatch(r"[a-z][a-z0-9_]*", name):
        raise CochleaError(f"{sc.path}: the embedded controller is named after the scenario "
                           f"file, and {name!r} is not a C identifier in lower case: rename "
                           "the file (letters, digits, underscores)")
    title = (f"the embedded controller of scenario {name} ({sc.robot} robot, "
             f"{sc.space} space, controller {sc.controller})")
    units = embedded_units(sc)
    header, source = embedded_sources(name, title, sc.period, units, function)
    table_h, table_c = scenario_table([name])
    return {f"{name}.h": header, f"{name}.c": source,
            f"{name}_scenario.c": scenario_source(embedded_scenario(sc), units),
            "scenarios.h": table_h, "scenarios.c": table_c}


def write_embedded(config: CodegenConfig, folder: str | Path) -> list[Path]:
    """Write ``<scenario>.h`` and ``<scenario>.c`` for every scenario of ``config.embedded``
    into ``folder`` (its other files are removed); return the paths written."""
    folder = Path(folder)
    sources = {}
    for name in config.embedded.scenarios:  # everything built before the folder is touched
        sc = load_scenario(name)
        title = (f"the embedded controller of scenario {name} ({sc.robot} robot, "
                 f"{sc.space} space, controller {sc.controller})")
        units = embedded_units(sc)
        header, source = embedded_sources(name, title, sc.period, units,
                                          config.embedded.function)
        sources[name] = {".h": header, ".c": source,
                         "_scenario.c": scenario_source(embedded_scenario(sc), units)}
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.iterdir():
        if old.is_file():
            old.unlink()
    table_h, table_c = scenario_table(list(sources))
    sources["scenarios"] = {".h": table_h, ".c": table_c}
    written = []
    for name, files in sources.items():
        for suffix, text in files.items():
            path = folder / f"{name}{suffix}"
            path.write_text(text)
            written.append(path)
    return sorted(written)
