"""Figures of an identification (matplotlib, Agg backend: no display needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .estimate import Identification


def _pyplot():
    import matplotlib  # noqa: PLC0415 (loaded only when drawing)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    return plt


def torque_figure(result: Identification, path: Path) -> Path:
    """Measured (filtered) against predicted effort per joint on the held-out data."""
    plt = _pyplot()
    model = result.model
    t = result.validation_time
    measured, predicted = result.measured, result.predict()
    nrms = result.prediction_nrms()
    fig, axes = plt.subplots(model.nq, 1, figsize=(9, 2.2 * model.nq), sharex=True,
                             squeeze=False)
    for j, (ax, joint) in enumerate(zip(axes[:, 0], model.joints)):
        unit = "N m" if joint.type == "revolute" else "N"
        ax.plot(t, measured[:, j], ".", ms=2, label="measured (filtered)")
        ax.plot(t, predicted[:, j], ".", ms=2, label="predicted (WLS)")
        ax.set_ylabel(f"{joint.name} [{unit}]")
        ax.set_title(f"{joint.name}: NRMS {nrms[j]:.2f} % (moving samples)", fontsize=9)
    axes[-1, 0].set_xlabel("time [s]")
    axes[0, 0].legend(loc="upper right", fontsize=8)
    fig.suptitle(f"{model.name}: effort on {result.held_out}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def parameter_figure(result: Identification, path: Path) -> Path:
    """Each base parameter's WLS estimate with its 95 % interval, over its nominal value
    (parameters whose nominal value is zero are shown in their SI unit, marked), then each
    fitted current-to-torque line's slope and offset over the description's values."""
    plt = _pyplot()
    params = result.model.parameters
    nominal = params.nominal
    scale = np.where(nominal != 0, np.abs(nominal), 1.0)
    est = result.wls.beta / scale
    half = 1.96 * result.wls.std_error / scale
    labels = [n if v != 0 else f"{n} (SI, nominal 0)" for n, v in zip(params.names, nominal)]
    # Fitted current-to-torque lines: a and b over the description's values before the fit.
    for k, ln in enumerate(result.lines):
        for i, (was, what) in enumerate(((ln.a0, "a"), (ln.b0, "b"))):
            size = was if was != 0 else 1.0  # signed: 1 is the description's value
            est = np.append(est, result.line_wls[k][i] / size)
            half = np.append(half, 1.96 * result.line_wls_std[k][i] / abs(size))
            labels.append(f"{ln.name} current line {what} (over the description's)")
    fig, ax = plt.subplots(figsize=(9, 0.3 * len(labels) + 1.5))
    y = np.arange(len(labels))
    ax.errorbar(est, y, xerr=half, fmt="o", ms=3, capsize=2)
    ax.axvline(1.0, color="grey", lw=0.8, ls="--")
    ax.set_yticks(y, labels, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("estimate / nominal (95 % interval)")
    if result.lines:
        ax.axhline(len(params.names) - 0.5, color="grey", lw=0.5)
    ax.set_title(f"{result.model.name}: base parameters (WLS)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
