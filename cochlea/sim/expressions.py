"""Parse the trajectory formulas of a scenario file into CasADi expressions of time.

A scenario writes the thesis's trajectories as they are printed, e.g.
``"81.14 - 3.007*cos(0.632*t) - 0.129*sin(0.632*t)"``. Only arithmetic, the time ``t`` (s),
``pi`` and a few functions are allowed; anything else is rejected with a message (no ``eval``).
Derivatives are then exact: ``ca.jacobian`` of the parsed expression with respect to ``t``.
"""

from __future__ import annotations

import ast

import casadi as ca

FUNCTIONS = {
    "sin": ca.sin, "cos": ca.cos, "tan": ca.tan, "exp": ca.exp, "sqrt": ca.sqrt,
    "atan2": ca.atan2, "min": ca.fmin, "max": ca.fmax, "abs": ca.fabs,
}
CONSTANTS = {"pi": ca.pi}


class ExpressionError(ValueError):
    """The formula is not one this parser accepts; the message says why."""


def parse(text: str, t: ca.SX, definitions: dict[str, ca.SX] | None = None) -> ca.SX:
    """Turn ``text`` into an SX expression in the symbol ``t``; ``definitions`` names
    sub-expressions the formula may use (e.g. ``a1`` of the thesis's (3.46))."""
    if not isinstance(text, str) or not text.strip():
        raise ExpressionError("expected a formula in t, e.g. \"0.5*sin(2*t)\"")
    try:
        tree = ast.parse(text, mode="eval")
    except SyntaxError as exc:
        raise ExpressionError(f"not a formula: {exc.msg} in {text!r}") from None
    return ca.SX(_build(tree.body, t, text, definitions or {}))


def _build(node, t, text, definitions):
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) \
            and not isinstance(node.value, bool):
        return float(node.value)
    if isinstance(node, ast.Name):
        if node.id == "t":
            return t
        if node.id in CONSTANTS:
            return CONSTANTS[node.id]
        if node.id in definitions:
            return definitions[node.id]
        known = ", ".join(["t", "pi", *definitions])
        raise ExpressionError(f"unknown name {node.id!r} in {text!r} (known: {known})")
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        value = _build(node.operand, t, text, definitions)
        return -value if isinstance(node.op, ast.USub) else value
    if isinstance(node, ast.BinOp):
        left, right = (_build(node.left, t, text, definitions),
                       _build(node.right, t, text, definitions))
        ops = {ast.Add: lambda a, b: a + b, ast.Sub: lambda a, b: a - b,
               ast.Mult: lambda a, b: a * b, ast.Div: lambda a, b: a / b,
               ast.Pow: lambda a, b: a ** b}
        for kind, op in ops.items():
            if isinstance(node.op, kind):
                return op(left, right)
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and not node.keywords:
        if node.func.id not in FUNCTIONS:
            raise ExpressionError(f"unknown function {node.func.id!r} in {text!r} (allowed: "
                                  + ", ".join(FUNCTIONS) + ")")
        return FUNCTIONS[node.func.id](*[_build(a, t, text, definitions) for a in node.args])
    raise ExpressionError(f"unsupported element {ast.dump(node)[:40]}... in {text!r}")
