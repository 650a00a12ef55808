"""The simulation layer: scenarios, the setups they make, and the as-fast closed loop on either
kernels -- the generated C (default) or the CasADi reference they are checked against.

    from cochlea.sim import load_scenario, simulate
    result = simulate(load_scenario("serial_task"))             # C kernels (auto)
    reference = simulate(load_scenario("serial_task"), kernels="casadi")
"""

from __future__ import annotations

from pathlib import Path

from ..errors import CochleaError
from .compiled import (
    KERNEL_CHOICES,
    CKernelsUnavailable,
    CKernelsWarning,
    KernelChoice,
    choose_kernels,
    simulate_compiled,
)
from .reference import simulate_reference
from .result import SimulationResult, UnitLog
from .scenario import Scenario
from .scenario import load as _load
from .setup import GravityRefused, UnitSetup, perturbed_parameters, run_inputs, unit_setups

#: Which kernels ``simulate`` runs: "auto" (default: the generated C when the library has this
#: scenario's kernels, else the CasADi reference with a :class:`CKernelsWarning`), "c" (the C
#: kernels or :class:`CKernelsUnavailable`) or "casadi" (the reference).
KERNELS = KERNEL_CHOICES


def load_scenario(name_or_path: str | Path, plant_preset: str | None = None, *,
                  text: str | None = None, data: dict | None = None) -> Scenario:
    """A shipped scenario by name (``"serial_task"``) or a scenario file, with its robot's
    description loaded once; ``plant_preset`` (e.g. ``"realistic"``) replaces the preset of
    its ``[plant]`` table; ``text``: the file's text, already read (the file is not);
    ``data``: the TOML data that text reads as (a sweep's sample), checked as the file's."""
    return _load(name_or_path, plant_preset, text=text, data=data)


def simulate(sc: Scenario, duration: float | None = None,
             setups: list[UnitSetup] | None = None, kernels: str = "auto", *,
             threads: bool = True, library: str | Path | None = None) -> SimulationResult:
    """Run the scenario as fast as possible and return the log of every period.

    A unit whose state or estimate becomes non-finite stops the run: ``result.diverged`` names
    it with the time, and the log keeps every period up to that one.

    ``kernels``: ``"auto"`` (default) runs the generated C kernels (:mod:`cochlea.sim.compiled`)
    and, if they cannot run this scenario, warns (:class:`CKernelsWarning`) and falls back to
    the CasADi reference (:mod:`cochlea.sim.reference`); ``"c"`` runs the C kernels or raises
    :class:`CKernelsUnavailable`; ``"casadi"`` runs the reference. ``result.kernels`` says
    which ran (and why not C). ``library``: the C library (a ``.so`` or the folder
    ``cochlea-codegen --scenario ... --out DIR`` wrote; default ``$COCHLEA_LIB``, else the
    shipped one). ``threads``: the C kernels run the units
    (the serial system's two arms) on threads of their own; a sweep's worker, one process per
    core, runs them one after the other (``False``), which spares it a thread pool a sample.
    """
    if kernels not in KERNELS:
        raise CochleaError(f"unknown kernels {kernels!r}; choose one of {', '.join(KERNELS)}")
    duration, setups = run_inputs(sc, duration, setups)
    if kernels != "casadi":
        return simulate_compiled(sc, duration, setups, fallback=kernels == "auto",
                                 threads=threads, library=library)
    result = simulate_reference(sc, duration, setups)
    result.kernels = KernelChoice("casadi", "casadi").summary()
    return result


__all__ = ["KERNELS", "load_scenario", "simulate", "simulate_compiled", "simulate_reference",
           "SimulationResult", "UnitLog", "UnitSetup", "Scenario", "unit_setups", "GravityRefused",
           "perturbed_parameters", "CKernelsUnavailable", "CKernelsWarning", "KernelChoice",
           "choose_kernels"]
