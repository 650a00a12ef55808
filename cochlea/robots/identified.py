"""Identified parameters as the text of a robot description's values (``cochlea-identify
--update-description``, :mod:`cochlea.ident.writeback`): what every robot's adapter shares."""

from __future__ import annotations

from .description import ACTUATOR_KEYS

#: The parameter name's suffix of each actuator term of a joint.
ACTUATOR_PARAMETERS = {"armature": "Ia", "viscous": "Fv", "coulomb": "Fc"}


def number(value: float) -> str:
    """A value as the description's text: every digit of the float."""
    return repr(float(value))


def actuator_values(joint, value: dict, path: tuple) -> dict[tuple, str]:
    """``{path + (key,): text}`` of ``joint``'s identified actuator terms found in ``value``
    (parameter name -> value), under its table ``path``."""
    out = {}
    for field, (key, _) in ACTUATOR_KEYS[joint.type].items():
        name = f"{joint.name}.{ACTUATOR_PARAMETERS[field]}"
        if name in value:
            out[path + (key,)] = number(value[name])
    return out
