"""Figures of a fitted dynamics model: loss curves and open-loop reconstructions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.data.runs import Run
from pipeline.data.schemas import XYZ
from pipeline.dynamics.scoring import predict_run


def plot_losses(path: Path, losses: pd.DataFrame, ema: float = 0.98) -> Path:
    """Training loss (raw and smoothed with an exponential moving average that keeps ``ema`` of
    its value each step, i.e. weight ``1 - ema`` on the new loss) and the validation error."""
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


def zoom_window(t: np.ndarray, width_s: float) -> tuple[float, float]:
    """The zoom of a reconstruction: ``width_s`` seconds in the middle of the run (all of it if
    shorter)."""
    start, end = float(t[0]), float(t[-1])
    if end - start <= width_s:
        return start, end
    middle = 0.5 * (start + end)
    return middle - 0.5 * width_s, middle + 0.5 * width_s


def plot_reconstruction(path: Path, params, runs: list[Run], labels: list[str],
                        zoom_s: float = 30.0) -> Path:
    """Measured vs open-loop predicted x, y, z over time (paper Fig. 7), the error
    ``|predicted - measured|`` under them, and beside each run a zoom into ``zoom_s`` seconds
    (shaded in the full view), where a millimetre-sized error is visible. ``params``: one
    model for every run, or a list with one model per run."""
    models = list(params) if isinstance(params, (list, tuple)) else [params] * len(runs)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 2 * len(runs), figsize=(8.5 * len(runs), 8), squeeze=False,
                             gridspec_kw={"width_ratios": [2.2, 1] * len(runs),
                                          "height_ratios": [1, 1, 1, 0.9]})
    for col, (model, run, label) in enumerate(zip(models, runs, labels)):
        predicted = predict_run(model, run)
        t = run.times_s - run.times_s[0]
        error = 1e3 * np.linalg.norm(predicted - run.positions_m, axis=1)
        low, high = zoom_window(t, zoom_s)
        inside = (t >= low) & (t <= high)
        full, zoom = axes[:, 2 * col], axes[:, 2 * col + 1]
        for k, axis in enumerate(XYZ):
            for ax, keep in ((full[k], slice(None)), (zoom[k], inside)):
                ax.plot(t[keep], run.positions_m[keep, k] * 1e3, lw=0.8, color="k",
                        label="measured")
                ax.plot(t[keep], predicted[keep, k] * 1e3, lw=0.8, color="C3",
                        label="model (open loop)")
            full[k].axvspan(low, high, color="C0", alpha=0.08)
            full[k].set_ylabel(f"{axis} [mm]")
        for ax, keep in ((full[3], slice(None)), (zoom[3], inside)):
            ax.plot(t[keep], error[keep], lw=0.7, color="C3")
            ax.axhline(error.mean(), color="0.3", ls="--", lw=0.8,
                       label=f"mean {error.mean():.2f} mm")
            ax.set_xlabel("time [s]")
        full[3].axvspan(low, high, color="C0", alpha=0.08)
        full[3].set_ylabel("error [mm]")
        full[3].legend(fontsize=7, loc="upper right")
        for k in range(3):
            full[k].tick_params(labelbottom=False)
            zoom[k].tick_params(labelbottom=False)
        full[0].set_title(f"{label} {run.run_id}: mean error {error.mean():.2f} mm, p95 "
                          f"{np.percentile(error, 95):.2f} mm", fontsize=10)
        zoom[0].set_title(f"zoom: {low:.0f}–{high:.0f} s", fontsize=10)
    axes[0, 0].legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
