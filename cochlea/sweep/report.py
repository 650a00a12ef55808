"""A sweep's report (``cochlea-sweep report DIR``, also written at the end of a sweep):
``summary.md`` and PNG figures in DIR.

A sample *succeeds* when its run converged (cochlea-run's rule, summary.json's ``converged``),
did not diverge and no supervisor rule would have stopped a real run. The robustness map is the
success probability against each input that varies, in bins, with a 95 % Wilson interval; the
distributions are the final RMS error per coordinate and the peak effort per joint as a
fraction of its limit; the worst samples are listed with the commands that replay them.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pyarrow as pa

from . import results

#: Bins of a continuous input in the robustness map; an input with this many values or fewer
#: is shown value by value.
BINS = 8
WORST = 10
INFO_COLUMNS = ("sample", "grid", "draw", "plant.seed")


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a success probability."""
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    # The interval always holds p; rounding can put an end a few ulps past it when every
    # sample (or none) succeeded, which a figure's error bar refuses as a negative length.
    return (min(p, max(0.0, centre - half)), max(p, min(1.0, centre + half)))


def varied_inputs(table: pa.Table) -> list[str]:
    """Input columns (plant.*, gains.*) that take more than one value in the sweep."""
    names = []
    for name in table.column_names:
        if not name.startswith(("plant.", "gains.")) or name in INFO_COLUMNS:
            continue
        if len(set(table[name].to_pylist())) > 1:
            names.append(name)
    return names


def binned(values: list, success: np.ndarray) -> list[tuple[str, float, int, int]]:
    """``(label, centre, successes, n)`` per bin of an input's values."""
    distinct = sorted(set(values), key=lambda v: (str(type(v)), v))
    numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in distinct)
    out = []
    if len(distinct) <= BINS or not numeric:
        for j, v in enumerate(distinct):
            mask = np.array([x == v for x in values])
            label = f"{v:.4g}" if isinstance(v, float) else str(v)
            out.append((label, float(v) if numeric else float(j), int(success[mask].sum()),
                        int(mask.sum())))
        return out
    x = np.array(values, float)
    edges = np.linspace(x.min(), x.max(), BINS + 1)
    which = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, BINS - 1)
    for b in range(BINS):
        mask = which == b
        out.append((f"{edges[b]:.4g}..{edges[b + 1]:.4g}", float((edges[b] + edges[b + 1]) / 2),
                    int(success[mask].sum()), int(mask.sum())))
    return out


def replay_command(out: Path, sample: int, robot: str, space: str) -> str:
    return (f"cochlea-sweep replay {out} {sample} --out sample{sample}.toml && cochlea-run "
            f"--robot {robot} --space {space} --scenario sample{sample}.toml --realtime off")


def _badness(table: pa.Table) -> np.ndarray:
    """Failures first, then the largest convergence ratio (final RMS over its threshold)."""
    ratio = np.nan_to_num(np.array(table["convergence_ratio"].to_pylist(), float), nan=np.inf)
    ok = np.array(table["success"].to_pylist(), bool)
    return np.where(ok, 0.0, 1.0) * 1e300 + np.minimum(ratio, 1e299)


def _save(fig, path: Path) -> None:
    """A figure as PNG, whole or not at all (:func:`cochlea.sweep.results.write_atomic`)."""
    sink = io.BytesIO()
    fig.savefig(sink, dpi=100, format="png")
    results.write_atomic(path, sink.getvalue())


def write(out: Path) -> Path:
    """summary.md and the figures from every finished sample in ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    manifest = results.read_manifest(out)
    table = results.read(out, manifest.total)
    n = table.num_rows
    lines = [f"# Sweep report: {out}", "",
             f"{n} of {manifest.total} samples finished; robot {manifest.robot}, space "
             f"{manifest.space}; scenario {manifest.scenario_path}.", ""]
    if n == 0:
        lines.append("No sample has finished yet.")
        path = out / "summary.md"
        results.write_atomic(path, ("\n".join(lines) + "\n").encode("utf-8"))
        return path
    success = np.array(table["success"].to_pylist(), bool)
    lo, hi = wilson(int(success.sum()), n)
    rules = table["stop_rule"].to_pylist()
    lines += [f"**Success: {success.sum()} of {n} ({success.mean():.1%}; 95 % interval "
              f"{lo:.1%}-{hi:.1%}).** A success converged (cochlea-run's rule), did not "
              "diverge, and no supervisor rule would have stopped a real run.", "",
              "| outcome | samples |", "| --- | --- |",
              f"| converged | {sum(table['converged'].to_pylist())} |",
              f"| diverged | {sum(table['diverged'].to_pylist())} |",
              f"| estimate bound hit | {sum(table['estimate_bound_hit'].to_pylist())} |"]
    for rule in sorted(set(rules) - {"none"}):
        lines.append(f"| stopped by rule {rule} | {rules.count(rule)} |")
    lines.append("")

    inputs = varied_inputs(table)
    figures = []
    if inputs:
        lines += ["## Robustness map", "", "Success probability against each input that "
                  "varies (![map](robustness_map.png)).", ""]
        cols = min(3, len(inputs))
        rows = math.ceil(len(inputs) / cols)
        fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), squeeze=False)
        for ax, name in zip(axes.ravel(), inputs):
            bins = binned(table[name].to_pylist(), success)
            lines += [f"**{name}**", "", "| value | success | samples | 95 % interval |",
                      "| --- | --- | --- | --- |"]
            centres, p, err_lo, err_hi = [], [], [], []
            for label, centre, s, m in bins:
                if m == 0:
                    continue
                a, b = wilson(s, m)
                lines.append(f"| {label} | {s / m:.1%} | {m} | {a:.1%}-{b:.1%} |")
                centres.append(centre)
                p.append(s / m)
                err_lo.append(s / m - a)
                err_hi.append(b - s / m)
            lines.append("")
            ax.errorbar(centres, p, yerr=[err_lo, err_hi], fmt="o-", capsize=3)
            ax.set_ylim(-0.05, 1.05)
            ax.set_xlabel(name)
            ax.set_ylabel("success probability")
            ax.grid(alpha=0.3)
        for ax in axes.ravel()[len(inputs):]:
            ax.set_visible(False)
        fig.suptitle("Robustness map (95 % Wilson intervals)")
        fig.tight_layout()
        _save(fig, out / "robustness_map.png")
        plt.close(fig)
        figures.append("robustness_map.png")

    rms = results.columns(table.column_names, results.RMS)
    torque = results.columns(table.column_names, results.RATIO)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for name in rms:
        v = np.array(table[name].to_pylist(), float)
        v = v[np.isfinite(v) & (v > 0)]
        if len(v):
            axes[0].hist(np.log10(v), bins=30, histtype="step", label=results.label(name))
    axes[0].set_xlabel("log10 final RMS error [rad or m]")
    axes[0].set_ylabel("samples")
    axes[0].legend(fontsize=7)
    for name in torque:
        v = np.array(table[name].to_pylist(), float)
        axes[1].hist(v[np.isfinite(v)], bins=30, histtype="step",
                     label=results.label(name))
    axes[1].set_xlabel("peak |effort| / limit")
    axes[1].legend(fontsize=7)
    fig.suptitle("Distributions over the samples")
    fig.tight_layout()
    _save(fig, out / "distributions.png")
    plt.close(fig)
    figures.append("distributions.png")
    lines += ["## Distributions", "", "Final RMS error per coordinate (last 20 % of the run) "
              "and peak effort per joint over its limit (![distributions](distributions.png)).",
              "", "| column | median | 95th percentile | max |", "| --- | --- | --- | --- |"]
    for name in rms + torque:
        v = np.array(table[name].to_pylist(), float)
        v = v[np.isfinite(v)]
        if len(v):
            lines.append(f"| {name} | {np.median(v):.3g} | {np.percentile(v, 95):.3g} | "
                         f"{v.max():.3g} |")
    lines.append("")

    order = np.argsort(-_badness(table), kind="stable")[:WORST]
    lines += ["## Worst samples", "", "Failures first, then the largest convergence ratio "
              "(final RMS over the threshold of the convergence rule; above 1: not converged).",
              "", "| sample | success | convergence ratio | stop rule | replay |",
              "| --- | --- | --- | --- | --- |"]
    samples = table["sample"].to_pylist()
    ratio = table["convergence_ratio"].to_pylist()
    for j in order:
        command = replay_command(out, samples[j], manifest.robot, manifest.space)
        lines.append(f"| {samples[j]} | {'yes' if success[j] else 'no'} | {ratio[j]:.3g} | "
                     f"{rules[j]} | `{command}` |")
    path = out / "summary.md"
    results.write_atomic(path, ("\n".join(lines) + "\n").encode("utf-8"))
    return path
