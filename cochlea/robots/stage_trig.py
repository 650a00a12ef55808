"""An RK4 period's later stages take their joints' sines and cosines from its first stage's.

A plant period's RK4 evaluates the forward dynamics four times, at ``q``, ``q + dt/2 k1``,
``q + dt/2 k2`` and ``q + dt k3``, and each evaluation takes the sine and cosine of every
revolute joint angle it uses (the parallel mechanism's four motor angles, a serial arm's
angles after the first): 16 of libm's ``sincos`` a period of the parallel plant, a fifth of
the all-in-C simulation's instructions (callgrind). The stages' offsets ``delta = a dt k`` are
small (1e-3 rad at 1 rad/s and 1 kHz), so the later stages' values follow from the first's by
the angle sums

    sin(q + delta) = s + (s (cos delta - 1) + c sin delta)
    cos(q + delta) = c + (c (cos delta - 1) - s sin delta)

with ``sin delta`` and ``cos delta - 1`` from their Taylor series, a few multiplications and
additions each. For ``|delta| <= REACH`` (1/16 rad) the series' first omitted terms are below
2e-21 (``delta^11 / 11!``, ``delta^12 / 12!``), so each value is within an ulp or two of
``sin`` and ``cos`` of the stage's angle: the period equals the plain one to rounding (1e-12
relative, tests/test_stage_trig.py), not bit for bit. A stage angle differs from ``q + delta``
by the rounding of that sum, as the plain period's does.

Past ``REACH`` (a joint faster than 62 rad/s at 1 kHz: a diverging run) the series are not
exact enough: the period then says so (its ``far`` output, the number of offsets past
``REACH``) and its caller takes the plain period instead (the all-in-C simulation's plant,
bench/embedded_bench.py). A NaN offset propagates into the result as the plain period's would.
"""

from __future__ import annotations

from collections.abc import Callable

import casadi as ca

from ..sx_graph import post_order, same_operation

#: rad: the largest RK4 stage offset whose sine and cosine the series give to rounding.
REACH = 2.0 ** -4

# sin(d) = d + d z SIN[0] + d z^2 SIN[1] + ..., cos(d) - 1 = z COS[0] + z^2 COS[1] + ...
# (z = d^2), to d^9 and d^10: the next terms are below 2e-21 for |d| <= REACH.
_SIN = (-1 / 6, 1 / 120, -1 / 5040, 1 / 362880)
_COS = (-1 / 2, 1 / 24, -1 / 720, 1 / 40320, -1 / 3628800)


def _horner(z, coefficients):
    value = coefficients[-1]
    for c in reversed(coefficients[:-1]):
        value = c + z * value
    return value


def shifted(s, c, delta):
    """``(sin(q + delta), cos(q + delta))`` from ``s = sin q``, ``c = cos q`` (``|delta| <=
    REACH``)."""
    z = delta * delta
    sin_d = delta + delta * (z * _horner(z, _SIN))
    cos_d_minus_1 = z * _horner(z, _COS)
    return s + (s * cos_d_minus_1 + c * sin_d), c + (c * cos_d_minus_1 - s * sin_d)


def lifted(forward: Callable, n: int, n_params: int) -> tuple[ca.Function, tuple[int, ...]]:
    """``forward`` (``(q, qd, tau, p) -> qdd``) as ``(q, s, c, qd, tau, p) -> qdd`` where every
    ``sin(q[i])`` and ``cos(q[i])`` it takes is read from ``s[i]`` and ``c[i]`` instead; and
    the joints ``i`` it takes them of. Every other operation is the same node for node (the
    expression graph rebuilt, each sine or cosine of a joint angle replaced)."""
    q, qd, tau = ca.SX.sym("q", n), ca.SX.sym("qd", n), ca.SX.sym("tau", n)
    p = ca.SX.sym("p", n_params)
    s, c = ca.SX.sym("s", n), ca.SX.sym("c", n)
    out = ca.SX(forward(q, qd, tau, p))
    joint = {q[i].element_hash(): i for i in range(n)}
    replace = {ca.OP_SIN: s, ca.OP_COS: c}
    new: dict[int, ca.SX] = {}
    used: set[int] = set()
    nodes, order = post_order([out[k] for k in range(out.numel())])
    for h in order:
        e = nodes[h]
        if e.n_dep() == 0:
            new[h] = e
            continue
        if e.op() in replace and e.dep(0).element_hash() in joint:
            i = joint[e.dep(0).element_hash()]
            new[h] = replace[e.op()][i]
            used.add(i)
            continue
        new[h] = same_operation(e, [new[e.dep(i).element_hash()] for i in range(e.n_dep())])
    rebuilt = ca.vertcat(*[new[out[k].element_hash()] for k in range(out.numel())])
    f = ca.Function("forward_lifted", [q, s, c, qd, tau, p], [rebuilt],
                    ["q", "s", "c", "qd", "tau", "p"], ["qdd"])
    return f, tuple(sorted(used))
