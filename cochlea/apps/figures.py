"""Figures the project draws from its own models (matplotlib, Agg backend: no display needed).

``python -m cochlea.apps.figures`` regenerates the committed figures in ``docs/``.
"""

from __future__ import annotations

from pathlib import Path

from ..resources import checkout
from ..robots import robot

#: Where the committed figures live (the checkout's docs/; installed: ./docs).
DOCS_DIR = (checkout() or Path.cwd()) / "docs"


def draw(robot_name: str, q=None, path: str | Path | None = None, *, description=None,
         title: str | None = None):
    """Draw robot ``robot_name`` at q (default: its adapter's working pose) with its adapter's
    :meth:`~cochlea.robots.RobotAdapter.draw`.

    Returns the matplotlib Figure; with ``path`` it is also saved there (PNG by the suffix).
    """
    adapter = robot(robot_name)
    return adapter.draw(adapter.load(description), q, path, title)


def draw_parallel(q=None, path: str | Path | None = None, *, description=None,
                  title: str | None = None):
    """Draw the parallel mechanism at q (default: the joint-space scenario's start)."""
    return draw("parallel", q, path, description=description, title=title)


def main() -> None:
    import matplotlib.pyplot as plt

    DOCS_DIR.mkdir(exist_ok=True)
    target = DOCS_DIR / "parallel_geometry.png"
    plt.close(draw_parallel(path=target))
    print(f"wrote {target}")


if __name__ == "__main__":
    main()
