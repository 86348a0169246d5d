"""Figures of a fitted dynamics model: loss curves and open-loop reconstructions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.data.schemas import XYZ
from pipeline.dynamics.training import predict_run


def plot_losses(path: Path, losses: pd.DataFrame, ema: float = 0.98) -> Path:
    """Training loss (raw and EMA-smoothed, as in the paper) and the validation error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_loss, ax_val) = plt.subplots(1, 2, figsize=(11, 3.6))
    train = losses["train_loss"].to_numpy()
    smooth = pd.Series(train).ewm(alpha=1 - ema, adjust=True).mean()
    ax_loss.semilogy(losses["step"], train, lw=0.5, alpha=0.3, color="C0", label="train")
    ax_loss.semilogy(losses["step"], smooth, lw=1.5, color="C0", label=f"train (EMA {ema})")
    val = losses.dropna(subset=["val_loss"])
    if len(val):
        ax_loss.semilogy(val["step"], val["val_loss"], "o-", ms=3, color="C1", label="held out")
        ax_val.plot(val["step"], val["val_mean_mm"], "o-", ms=3, label="mean")
        ax_val.plot(val["step"], val["val_p95_mm"], "s--", ms=3, label="p95")
        ax_val.legend()
    ax_loss.set_xlabel("step")
    ax_loss.set_ylabel("loss (normalized MSE)")
    ax_loss.legend()
    ax_val.set_xlabel("step")
    ax_val.set_ylabel("held-out open-loop error [mm]")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_reconstruction(path: Path, params, runs: list[dict], labels: list[str]) -> Path:
    """Measured vs open-loop predicted x, y, z over time (paper Fig. 6)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, len(runs), figsize=(6.5 * len(runs), 6.5), sharex="col",
                             squeeze=False)
    for col, (run, label) in enumerate(zip(runs, labels)):
        predicted = predict_run(params, run)
        t = run["t"] - run["t"][0]
        error = 1e3 * np.linalg.norm(predicted - run["pos"], axis=1)
        for k, axis in enumerate(XYZ):
            ax = axes[k, col]
            ax.plot(t, run["pos"][:, k] * 1e3, lw=0.8, color="k", label="measured")
            ax.plot(t, predicted[:, k] * 1e3, lw=0.8, color="C3", label="model (open loop)")
            ax.set_ylabel(f"{axis} [mm]")
        axes[0, col].set_title(f"{label} {run['run_id']}: mean error {error.mean():.2f} mm",
                               fontsize=10)
        axes[-1, col].set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
