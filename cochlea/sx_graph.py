"""Walking and rebuilding CasADi SX expression graphs, node by node.

Two rewrites use it: the desired trajectory's time atoms (:func:`cochlea.kernels.embedded.
time_atoms`) and the RK4 stages' lifted sines (:func:`cochlea.robots.stage_trig.lifted`). Each
visits every node of some outputs after the nodes it depends on and builds a new graph with the
same operations, some nodes replaced.
"""

from __future__ import annotations

import casadi as ca


def post_order(elements: list[ca.SX]) -> tuple[dict[int, ca.SX], list[int]]:
    """Every node the scalar expressions ``elements`` depend on, by ``element_hash``, and their
    hashes in post-order (each node after its dependencies, once)."""
    nodes: dict[int, ca.SX] = {}
    order: list[int] = []
    done: set[int] = set()
    stack = [(e, False) for e in elements]
    while stack:
        e, expanded = stack.pop()
        h = e.element_hash()
        if expanded:
            if h not in done:
                done.add(h)
                order.append(h)
            continue
        if h in nodes:
            continue
        nodes[h] = e
        stack.append((e, True))
        stack += [(e.dep(i), False) for i in range(e.n_dep())]
    return nodes, order


def same_operation(e: ca.SX, deps: list[ca.SX]) -> ca.SX | None:
    """Node ``e``'s operation on new operands ``deps`` (None for more than two)."""
    if len(deps) == 1:
        return ca.SX.unary(e.op(), deps[0])
    if len(deps) == 2:
        return ca.SX.binary(e.op(), deps[0], deps[1])
    return None
