"""Each angle's sin and cos from one inline ``cochlea_sincos`` in chosen generated kernels.

CasADi's C calls libm for every ``sin(a)`` and ``cos(a)``. In the ideal plants' RK4 steps (the
kernels a study's and a sweep's closed loop spend most of their time in) :func:`inline_trig`
takes each ``sin(a)`` and ``cos(a)`` of one value of ``a`` -- a variable between two of its
assignments: CasADi reuses its variables -- from one ``cochlea_sincos(a, &s, &c)`` at the
first of them (the others, a repeated ``sin(a)`` of the same value among them, copy ``s`` or
``c``; a lone ``sin(a)`` costs what the pair does, so it takes the pair too). ``cochlea_trig.h``
(``codegen/cochlea_trig.h``, written beside the generated files) defines them: inline, within
an ulp of libm, not always libm's last bit, so the kernels' results move by rounding.
"""

from __future__ import annotations

import re

from ..resources import CODEGEN_DIR
from .catalogue import CodegenError

#: The header's source (copied into every folder whose kernels use it) and its name there.
HEADER = CODEGEN_DIR / "cochlea_trig.h"
HEADER_NAME = "cochlea_trig.h"

_ASSIGN = re.compile(r"^\s*(a\d+)=(.*);$")
_TRIG = re.compile(r"^(\s*)(a\d+)=(sin|cos)\((a\d+)\);$")
_ANY_TRIG = re.compile(r"\b(sin|cos|sincos)\(")
_BODY = re.compile(r"^static int (casadi_f\d+)\(")
_MATH = "#include <math.h>\n"


def bodies(text: str, names: list[str]) -> dict[str, str]:
    """The CasADi body (``casadi_fN``) each exported kernel of ``names`` calls, by name."""
    found = {}
    for name in names:
        match = re.search(rf"^CASADI_SYMBOL_EXPORT int {re.escape(name)}\(const casadi_real\*\* "
                          r"arg.*?\{\n  return (casadi_f\d+)\(", text, flags=re.M | re.S)
        if match is None:
            raise CodegenError(f"inline trig: no exported function {name} in the generated C")
        found[name] = match.group(1)
    return found


def _rewrite(lines: list[str], start: int, end: int) -> int:
    """Rewrite the body ``lines[start:end]`` in place; return how many sincos it computes."""
    version: dict[str, int] = {}
    pairs: dict[tuple[str, int], tuple[int, str, str, str]] = {}  # (arg, version) -> first use
    count = 0
    for i in range(start, end):
        line = lines[i]
        trig = _TRIG.match(line)
        if trig:
            indent, target, kind, arg = trig.groups()
            key = (arg, version.get(arg, 0))
            first = pairs.get(key)
            if first is None:
                s, c = f"trig_s{count}", f"trig_c{count}"
                count += 1
                pairs[key] = (i, indent, s, c)
                lines[i] = (f"{indent}casadi_real {s}, {c}; cochlea_sincos({arg}, &{s}, &{c}); "
                            f"{target}={s if kind == 'sin' else c};")
            else:
                if first[1] != indent:  # a block between them: the pair is out of scope
                    raise CodegenError(f"inline trig: {kind}({arg}) in another block")
                lines[i] = f"{indent}{target}={first[2] if kind == 'sin' else first[3]};"
        elif _ANY_TRIG.search(line):
            raise CodegenError(f"inline trig: a sin or cos of other than a variable: "
                               f"{line.strip()}")
        assign = _ASSIGN.match(line)
        if assign:
            version[assign.group(1)] = version.get(assign.group(1), 0) + 1
    return count


def inline_trig(text: str, names: list[str]) -> tuple[str, int]:
    """``text`` (one generated C file) with the kernels ``names`` taking sin and cos from
    ``cochlea_trig.h``, which it then includes; return it and how many sincos the rewritten
    bodies compute. Nothing else in the file changes."""
    if not names:
        return text, 0
    wanted = set(bodies(text, names).values())
    lines = text.split("\n")
    total = 0
    i = 0
    while i < len(lines):
        match = _BODY.match(lines[i])
        if match and match.group(1) in wanted:
            end = lines.index("}", i)
            total += _rewrite(lines, i + 1, end)
            i = end
        i += 1
    out = "\n".join(lines)
    if total:
        if _MATH not in out:
            raise CodegenError("inline trig: no #include <math.h> in the generated C")
        out = out.replace(_MATH, _MATH + f'#include "{HEADER_NAME}" /* cochlea_sincos: the '
                          "ideal plant steps' sin and cos, inline */\n", 1)
    return out, total
