"""The simulation layer: scenarios, the setups they make, and the as-fast closed loop on either
kernels -- the generated C (default) or the CasADi reference they are checked against.

    from cochlea.sim import load_scenario, simulate
    result = simulate(load_scenario("serial_task"))             # C kernels
    reference = simulate(load_scenario("serial_task"), kernels="casadi")
"""

from __future__ import annotations

from pathlib import Path

from ..errors import CochleaError
from .compiled import CKernelsUnavailable, CKernelsWarning, simulate_compiled
from .reference import simulate_reference
from .result import SimulationResult, UnitLog
from .scenario import Scenario
from .scenario import load as _load
from .setup import GravityRefused, UnitSetup, perturbed_parameters, run_inputs, unit_setups

#: Which kernels ``simulate`` runs: the generated C (default) or the CasADi reference.
KERNELS = ("c", "casadi")


def load_scenario(name_or_path: str | Path, plant_preset: str | None = None) -> Scenario:
    """A shipped scenario by name (``"serial_task"``) or a scenario file, with its robot's
    description loaded once; ``plant_preset`` (e.g. ``"realistic"``) replaces the preset of
    its ``[plant]`` table."""
    return _load(name_or_path, plant_preset)


def simulate(sc: Scenario, duration: float | None = None,
             setups: list[UnitSetup] | None = None, kernels: str = "c", *,
             threads: bool = True) -> SimulationResult:
    """Run the scenario as fast as possible and return the log of every period.

    A unit whose state or estimate becomes non-finite stops the run: ``result.diverged`` names
    it with the time, and the log keeps every period up to that one.

    ``kernels``: ``"c"`` (default) runs the generated C kernels (:mod:`cochlea.sim.compiled`;
    if they cannot run this scenario it warns and falls back), ``"casadi"`` the CasADi
    reference (:mod:`cochlea.sim.reference`). ``threads``: the C kernels run the units
    (the serial system's two arms) on threads of their own; a sweep's worker, one process per
    core, runs them one after the other (``False``), which spares it a thread pool a sample.
    """
    if kernels not in KERNELS:
        raise CochleaError(f"unknown kernels {kernels!r}; choose one of {', '.join(KERNELS)}")
    duration, setups = run_inputs(sc, duration, setups)
    if kernels == "c":
        return simulate_compiled(sc, duration, setups, fallback=True, threads=threads)
    return simulate_reference(sc, duration, setups)


__all__ = ["KERNELS", "load_scenario", "simulate", "simulate_compiled", "simulate_reference",
           "SimulationResult", "UnitLog", "UnitSetup", "Scenario", "unit_setups", "GravityRefused",
           "perturbed_parameters", "CKernelsUnavailable", "CKernelsWarning"]
