"""The scenarios' embedded controllers: what ``cochlea-codegen`` writes to
``generated_c/embedded/`` (the ``[embedded]`` table of ``cochlea/data/codegen/kernels.toml``).

Each scenario's units (:func:`~cochlea.sim.setup.unit_setups`: the same desired trajectory,
controller, gains, adaptation gain, projection bound, initial estimate and effort limits as the
simulation) become :class:`~cochlea.kernels.embedded.EmbeddedUnit` data, and
:func:`~cochlea.kernels.embedded.embedded_sources` writes the C. See ``docs/embedded.md``.
"""

from __future__ import annotations

from pathlib import Path

from ..kernels.catalogue import CodegenConfig, law_units
from ..kernels.embedded import EmbeddedUnit, embedded_sources
from .scenario import Scenario
from .scenario import load as load_scenario
from .setup import unit_setups

__all__ = ["embedded_units", "write_embedded"]


def embedded_units(sc: Scenario) -> list[EmbeddedUnit]:
    """Every controlled unit of the scenario, as its embedded controller runs it."""
    units = []
    for u in unit_setups(sc):
        c = u.controller
        units.append(EmbeddedUnit(
            u.name, u.desired, c.law, tuple(u.joint_units), c.gain_names, c.gain_sizes,
            c.error_names, tuple(u.controller_model.param_names),
            law_units(u.controller_model, c), u.gains, u.gamma, float(u.bound), u.p_hat0,
            u.effort_limit, controller=f"{c.kind} ({c.variant}), {c.space} space"))
    return units


def write_embedded(config: CodegenConfig, folder: str | Path) -> list[Path]:
    """Write ``<scenario>.h`` and ``<scenario>.c`` for every scenario of ``config.embedded``
    into ``folder`` (its other files are removed); return the paths written."""
    folder = Path(folder)
    sources = {}
    for name in config.embedded.scenarios:  # everything built before the folder is touched
        sc = load_scenario(name)
        title = (f"the embedded controller of scenario {name} ({sc.robot} robot, "
                 f"{sc.space} space, controller {sc.controller})")
        sources[name] = embedded_sources(name, title, sc.period, embedded_units(sc),
                                         config.embedded.function)
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.iterdir():
        if old.is_file():
            old.unlink()
    written = []
    for name, (header, source) in sources.items():
        for suffix, text in ((".h", header), (".c", source)):
            path = folder / f"{name}{suffix}"
            path.write_text(text)
            written.append(path)
    return sorted(written)
