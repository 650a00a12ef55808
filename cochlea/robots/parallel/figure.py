"""The parallel mechanism drawn at a configuration (matplotlib, Agg backend: no display
needed): ``cochlea.apps.figures`` draws it for docs/parallel_geometry.png."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .description import ParallelSystem
from .geometry import SCENARIO_START, ParallelGeometry


def _angle_arc(ax, centre, radius, start, stop, label, colour, label_radius=None):
    """An arc from angle ``start`` to ``stop`` (rad) about ``centre``, labelled at its middle."""
    t = np.linspace(start, stop, 40)
    ax.plot(centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t), color=colour, lw=0.9)
    mid = 0.5 * (start + stop)
    r = label_radius if label_radius is not None else radius * 1.25
    ax.text(centre[0] + r * math.cos(mid), centre[1] + r * math.sin(mid), label, color=colour,
            ha="center", va="center", fontsize=9)


def draw(system: ParallelSystem, q=None, path: str | Path | None = None,
         title: str | None = None):
    """Draw the parallel mechanism at q (default: the joint-space scenario's start).

    Returns the matplotlib Figure; with ``path`` it is also saved there (PNG by the suffix).
    """
    # matplotlib is imported where the figure is drawn (as in cochlea/apps/figures.py): it is
    # heavy, and its backend (Agg) must be chosen before pyplot is imported.
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415
    from matplotlib.patches import Polygon  # noqa: PLC0415

    geometry = ParallelGeometry(system)
    q = SCENARIO_START if q is None else np.asarray(q, float).ravel()
    p = geometry.points(q)
    x_p = geometry.fk(q)
    S = p["S"]

    fig, ax = plt.subplots(figsize=(8.0, 5.6), dpi=110)
    # The slider's rail (its stroke) and the slider itself.
    lo, hi = system.d1.position_limits
    ax.plot([0, 0], [lo, hi], color="0.55", lw=6, solid_capstyle="butt", zorder=1,
            label="slider rail (stroke)")
    ax.plot([0, 0], [-0.02, 0.2], color="0.6", lw=0.8, ls="--", zorder=0)
    ax.add_patch(plt.Rectangle((S[0] - 0.008, S[1] - 0.008), 0.016, 0.016, color="black",
                               zorder=5))
    ax.annotate("", xy=(-0.012, S[1]), xytext=(-0.012, 0.0),
                arrowprops=dict(arrowstyle="<->", color="tab:purple", lw=1.0))
    ax.text(-0.016, 0.5 * S[1], "$d_1$", color="tab:purple", fontsize=10, ha="right")
    ax.text(S[0] + 0.004, S[1] - 0.012, "S (link 6)", fontsize=9, va="top")

    colours = {"": ("tab:blue", "tab:cyan"), "'": ("tab:red", "tab:orange")}
    for side, mark, angles in ((system.left, "", q[0:2]), (system.right, "'", q[3:5])):
        strong, light = colours[mark]
        B, A1, A4, C, R = (p[f"{k}{mark}"] for k in ("B", "A1", "A4", "C", "R"))
        phi = x_p[2] if mark == "" else x_p[5]
        # Reach of the pantograph: |C - B| <= 2 l_p.
        t = np.linspace(0, 2 * np.pi, 200)
        ax.plot(B[0] + 2 * geometry.lp * np.cos(t), B[1] + 2 * geometry.lp * np.sin(t),
                color=strong, lw=0.5, ls=":", alpha=0.6)
        for (a, b), name, lw, col in (((B, A1), "1", 4, strong), ((B, A4), "4", 4, strong),
                                      ((A1, C), "2", 2.5, light), ((A4, C), "3", 2.5, light)):
            ax.plot([a[0], b[0]], [a[1], b[1]], color=col, lw=lw, solid_capstyle="round",
                    zorder=3)
            mid = 0.5 * (a + b)
            ax.text(mid[0], mid[1] + 0.006, f"{name}{mark}", color=col, fontsize=9,
                    ha="center", fontweight="bold")
        ax.plot([S[0], R[0]], [S[1], R[1]], color="0.25", lw=1.8, zorder=2)
        ax.text(*(S + 0.45 * (R - S) + np.array([0.0, 0.008])), f"7{mark}", fontsize=9,
                color="0.25", ha="center")
        # The magnet (link 5) at C, a block along the rod.
        e, n = np.array([math.cos(phi), math.sin(phi)]), np.array([-math.sin(phi), math.cos(phi)])
        corners = [C + sx * 0.016 * e + sy * 0.009 * n for sx, sy in
                   ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        ax.add_patch(Polygon(corners, closed=True, color="0.15", alpha=0.85, zorder=4))
        ax.plot(*B, marker="^", color="black", ms=11, zorder=5)
        ax.text(B[0], B[1] - 0.016, f"B{mark}", ha="center", va="top", fontsize=10)
        ax.text(C[0] + side.sign * 0.006, C[1] + 0.024, f"C{mark} (link 5{mark})", fontsize=10,
                ha="left" if side.sign > 0 else "right")
        # Angles from +u at the base, and phi at S.
        _angle_arc(ax, B, 0.028, 0.0, angles[0], rf"$\theta{mark}_1$", strong, 0.040)
        _angle_arc(ax, B, 0.044, 0.0, angles[1], rf"$\theta{mark}_2$", strong, 0.056)
        ax.plot([B[0], B[0] + 0.06], [B[1], B[1]], color="0.5", lw=0.6)
        _angle_arc(ax, S, 0.05 if mark == "" else 0.036, 0.0, phi, rf"$\phi{mark}$", "0.25",
                   0.064 if mark == "" else 0.026)
    ax.plot([S[0], S[0] + 0.07], [S[1], S[1]], color="0.5", lw=0.6)
    ax.annotate("", xy=(system.left.sign * geometry.d2, -0.045), xytext=(0.0, -0.045),
                arrowprops=dict(arrowstyle="<->", color="tab:purple", lw=1.0))
    ax.text(0.5 * geometry.d2, -0.052, "$d_2$", color="tab:purple", ha="center", va="top")
    g = system.gravity / max(np.linalg.norm(system.gravity), 1e-12)
    ax.annotate("", xy=(0.2 + 0.04 * g[0], 0.2 + 0.04 * g[1]), xytext=(0.2, 0.2),
                arrowprops=dict(arrowstyle="-|>", color="black"))
    ax.text(0.207, 0.185, "g", fontsize=10)

    if title is None:
        values = [f"{math.degrees(q[0]):g}", f"{math.degrees(q[1]):g}", f"{q[2]:g} m",
                  f"{math.degrees(q[3]):g}", f"{math.degrees(q[4]):g}"]
        title = ("parallel mechanism at q = [" + ", ".join(values) + "] (deg unless noted)\n"
                 f"C = ({x_p[0]:.4f}, {x_p[1]:.4f}) m, phi = {math.degrees(x_p[2]):.2f} deg;  "
                 f"C' = ({x_p[3]:.4f}, {x_p[4]:.4f}) m, phi' = {math.degrees(x_p[5]):.2f} deg")
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("u [m]")
    ax.set_ylabel("v [m] (up)")
    ax.set_aspect("equal")
    ax.set_xlim(-0.25, 0.25)
    ax.set_ylim(-0.08, 0.24)
    ax.grid(True, lw=0.3, alpha=0.5)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path)
    return fig
