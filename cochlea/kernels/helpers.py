"""CasADi's runtime helpers in the generated C, made ``static`` and their min and max inline.

CasADi defines the helpers a file's kernels use (``casadi_sq``, ``casadi_fmax``, ``casadi_fmin``,
``casadi_fabs``, ``casadi_sign``, ...) as external functions. In a shared library built with
``-fPIC`` an external function may be interposed at load time, so the compiler calls each one
through the procedure linkage table and cannot inline it: the parallel plant step made 56 calls
to ``casadi_sq`` (``x*x``) a period, the parallel task law 67, each a call and the registers
saved around it. :func:`static_helpers` declares them ``static`` (each file's own, as CasADi's
prefix already makes them), so they inline wherever the file is compiled.

``casadi_fmax`` and ``casadi_fmin`` call libm's ``fmax``/``fmin``, which no compiler inlines
without ``-ffinite-math-only``; the laws clip with them 20-40 times a step. Their inline form
here takes the comparison where both are numbers and leaves NaN to libm:

    x > y ? x : y >= x ? y : fmax(x, y)

It returns libm's result for every pair of numbers and libm's own result whenever either is
NaN (signalling ones included), so the kernels' results are bit for bit those of the libm
calls, but for a tie of +0 and -0, where it returns ``y`` (glibc's ``fmax`` does too) and C
leaves the choice open: GCC, which takes ``fmax`` for commutative, may swap libm's operands
itself (``fmax(-0.0, +0.0)`` is -0 at -O2 and +0 at -O0 with the same glibc). Only the sign of
a zero can differ, where a compiler chose otherwise. :func:`min_max_functions` writes the same
form for the embedded laws (``CFMIN``/``CFMAX``), in float too.
"""

from __future__ import annotations

import re

from .catalogue import CodegenError

#: A helper CasADi defines at the start of a line, not yet static or exported.
_HELPER = re.compile(r"^casadi_real (casadi_\w+)\((casadi_real x(?:, casadi_real y)?)\) \{",
                     re.M)
_MIN_MAX = {"fmax": ("  return fmax(x, y);", "  return x > y ? x : y >= x ? y : fmax(x, y);"),
            "fmin": ("  return fmin(x, y);", "  return x < y ? x : y <= x ? y : fmin(x, y);")}


def static_helpers(text: str) -> str:
    """``text`` (one file of CasADi's C) with its helpers ``static`` and ``casadi_fmax`` and
    ``casadi_fmin`` inline for numbers (see the module). Raises :class:`CodegenError` where a
    min or max helper is not in the form this module knows (another CasADi version's)."""
    for kind, (libm, inline) in _MIN_MAX.items():
        start = re.search(rf"^casadi_real casadi_{kind}\(casadi_real x, casadi_real y\) \{{\n",
                          text, flags=re.M)
        if start is None:
            continue
        end = text.index("\n}\n", start.end())
        body = text[start.end():end]
        if body.count(libm) != 1:
            raise CodegenError(f"casadi_{kind} is not in the form cochlea-codegen rewrites "
                               f"(a different CasADi version?): {body!r}")
        text = text[:start.end()] + body.replace(libm, inline) + text[end:]
    return _HELPER.sub(r"static casadi_real \1(\2) {", text)


def min_max_functions(real: str, text: str) -> str:
    """The embedded laws' min and max (CasADi's ``fmin``/``fmax`` in
    :mod:`~cochlea.kernels.embedded`'s C) in :func:`static_helpers`' form, in the working
    precision ``real``
    (``CFMIN``, ``CFMAX``: ``CM(fmin)`` is its libm function) and in double (``CFMIND``,
    ``CFMAXD``: the desired trajectory's), those ``text`` calls (an unused static function is
    a warning, and warnings are errors)."""
    parts = [
        "/* CasADi's fmin/fmax by comparison where both are numbers, libm's where either is NaN:\n"
        " * libm's result for every pair (y on a tie of +0 and -0, which C leaves open), without\n"
        " * a call (a Cortex-M4 has no min/max instruction; -ffinite-math-only is refused). */\n"]
    for name, less, libm in (("CFMIN", "<", "fmin"), ("CFMAX", ">", "fmax")):
        for suffix, kind, call in (("", real, f"CM({libm})"), ("D", "double", libm)):
            if f"{name}{suffix}(" in text:
                parts.append(f"static {kind} {name}{suffix}({kind} x, {kind} y) {{\n"
                             f"  return x {less} y ? x : (y {less}= x ? y : {call}(x, y));\n}}\n")
    return "".join(parts) if len(parts) > 1 else ""
