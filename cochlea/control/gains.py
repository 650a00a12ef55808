"""The one registry of the four controllers: which robot and space each serves, and its gains.

A controller's gain vector stacks the diagonal gains in the order of ``names``; each gain has
one entry per task coordinate or per joint (``sizes``). ``weight`` is the weight of the position
error in the controller's Lyapunov function (``V = e' K e / 2 + ...``): any positive weight keeps
the analysis, ones reproduce the thesis, so a scenario may leave it out.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class GainSet:
    kind: str  # "e" | "g" | "f" | "d"
    robot: str  # "serial" | "parallel"
    space: str  # "joint" | "task"
    names: tuple[str, ...]  # in the order of the gain vector
    sizes: tuple[str, ...]  # per gain: "task" or "joint" (one entry per coordinate)
    weight: str | None = None  # the optional Lyapunov weight (defaults to ones)

    @property
    def required(self) -> tuple[str, ...]:
        """The gains a scenario must give."""
        return tuple(n for n in self.names if n != self.weight)

    def size(self, name: str, n_joint: int, n_task: int) -> int:
        return n_task if self.sizes[self.names.index(name)] == "task" else n_joint


CONTROLLERS: dict[str, GainSet] = {
    "e": GainSet("e", "serial", "joint", ("alpha", "G_e", "K_e"), ("joint",) * 3, "K_e"),
    "g": GainSet("g", "serial", "task", ("G_g", "G_a", "K_c"), ("task", "joint", "task"), "K_c"),
    "f": GainSet("f", "parallel", "joint", ("alpha", "G_f", "K_e"), ("joint",) * 3, "K_e"),
    "d": GainSet("d", "parallel", "task", ("K_p", "G_d"), ("task", "joint")),
}
#: Controller kind -> (robot, space).
KINDS = {kind: (c.robot, c.space) for kind, c in CONTROLLERS.items()}


def controller_of(robot: str, space: str) -> GainSet:
    """The controller of a robot in a space."""
    return next(c for c in CONTROLLERS.values() if (c.robot, c.space) == (robot, space))
