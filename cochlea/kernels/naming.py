"""How kernels are named and identified, shared by the generator and every caller.

A kernel's C name is ``<unit prefix>_<Function>`` (``serial_arm1_M``, ``parallel_plant_step``)
or, for a controller, ``<unit prefix>_<kind>[_<variant>][_actuated]_<part>``; its identity is
the SHA-256 of the CasADi Function it was generated from, recorded in the library's manifest, so
a caller can tell a stale library from a fresh one.
"""

from __future__ import annotations

import hashlib

import casadi as ca

from ..robots.model import ACTUATOR_SUFFIX, RobotModel

#: The format tag of the manifest ``cochlea_manifest()`` returns (JSON).
#: 2: the closed-loop drivers take the measurement grid (quantum, offset) after the noise;
#: 3: and the joints' effort limits after the friction;
#: 4: and the Coulomb friction levels between them (drivers ``*_closed_loop_coulomb``);
#: 5: and the drives' effort grid (quantum, bound) after the effort limits;
#: 6: and the bridge's offset (effort_offset, effort_ramp) after them; the plant's state may be
#: larger than the logged [q, qd] (``nx``, the gear plant's 4 nq) and its 6th input, ``drive``,
#: has ``n_drive`` values (the dry-friction rows, or the gear plant's).
#: 7: and the per-period delays (after delay; NULL: the scalar) and the torque scale (after
#: effort_ramp; NULL: 1), the jittering delay and the motor's torque-constant error.
#: 8: and a last output, ``reductions`` (``n_reductions`` values; NULL: none), the column
#: extremes, largest estimate squares and nearest keep-out approach a verdict and a summary
#: read of the rows written, and the keep-out tool points (n_keep_out, keep_out_index,
#: keep_out_centre) after torque_scale.
MANIFEST_FORMAT = "cochlea-kernels/8"


def source_hash(function: ca.Function) -> str:
    """SHA-256 of a Function's CasADi serialisation: equal hashes, equal computations."""
    return hashlib.sha256(function.serialize().encode()).hexdigest()


def unit_prefix(m: RobotModel) -> str:
    """The C prefix of a unit's kernels: its model's name with ``/`` as ``_``."""
    return m.name.replace("/", "_")


def controller_kernel_name(prefix: str, kind: str, variant: str, part: str,
                           actuators: str = "none") -> str:
    """``<prefix>_<kind>[_<variant>][_<actuators>]_<part>``: the corrected variant has no
    suffix, nor a controller on the rigid-link model; one that models its drives (armature
    and friction, ``actuators="all"``) is ``_actuated``."""
    suffix = "" if variant == "corrected" else f"_{variant}"
    return f"{prefix}_{kind}{suffix}{ACTUATOR_SUFFIX[actuators]}_{part}"


def closed_loop_name(group: str, plant: RobotModel, coulomb: bool, gear: bool = False) -> str:
    """The driver of a controller's kernel group (``controller_kernel_name(...)`` without its
    part) on a plant: ``<group>_closed_loop[_armature][_coulomb]``, on the geared plant
    ``<group>_closed_loop_gear``."""
    if gear:
        return f"{group}_closed_loop_gear"
    return (f"{group}_closed_loop{ACTUATOR_SUFFIX[plant.actuators]}"
            + ("_coulomb" if coulomb else ""))


def computation_hash(function: ca.Function) -> str:
    """SHA-256 of what a Function computes, whatever its name: the same graph under a fixed
    name. Two kernels with equal computation hashes can share one C body."""
    inputs = function.sx_in() if function.is_a("SXFunction") else function.mx_in()
    renamed = ca.Function("kernel", inputs, function.call(inputs), function.name_in(),
                          function.name_out())
    return hashlib.sha256(renamed.serialize().encode()).hexdigest()
