"""Figures of an evaluation: training curves, distance to goal over time, trajectories."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.evaluation.metrics import MM_PER_M
from pipeline.rl.results import training_curves


def make_figures(folder: Path, cfg, policies, results) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    figures = {}

    # ---- training curves: mean +- std over seeds per policy type (paper Fig. 7) ------------

    fig, ax = plt.subplots(figsize=(7.5, 4))
    for i, (name, artifact) in enumerate(policies.items()):
        curves = training_curves(artifact)  # columns: timesteps, seed, return
        stats = curves.groupby("timesteps")["return"].agg(["mean", "std"]).reset_index()
        ax.plot(stats["timesteps"], stats["mean"], color=f"C{i}", label=name)
        ax.fill_between(stats["timesteps"], stats["mean"] - stats["std"].fillna(0),
                        stats["mean"] + stats["std"].fillna(0), color=f"C{i}", alpha=0.25)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episodic return")
    ax.set_title("PPO in the learned environment (mean ± std over seeds)")
    ax.legend()
    fig.tight_layout()
    figures["returns"] = folder / "returns.png"
    fig.savefig(figures["returns"], dpi=100)
    plt.close(fig)

    # ---- distance to goal over time, per controller and plant -------------------------------
    goals = results["goals"]
    plants = sorted({key[0] for key in results["paths"]})
    controllers = list(dict.fromkeys(key[1] for key in results["paths"]))
    fig, axes = plt.subplots(1, len(plants), figsize=(6.5 * len(plants), 4), squeeze=False,
                             sharey=True)
    for ax, plant in zip(axes[0], plants):
        for i, controller in enumerate(controllers):
            seeds = [k for k in results["paths"] if k[0] == plant and k[1] == controller]
            distance = np.concatenate([
                np.linalg.norm(results["paths"][k] - goals[:, None], axis=-1) * MM_PER_M
                for k in seeds])
            t = np.arange(distance.shape[1]) / float(cfg.robot.control_hz)
            median = np.median(distance, axis=0)
            low, high = np.percentile(distance, [25, 75], axis=0)
            ax.semilogy(t, median, color=f"C{i}", label=controller)
            ax.fill_between(t, low, high, color=f"C{i}", alpha=0.15)
        ax.axhline(float(cfg.env.goal_tolerance_m) * MM_PER_M, color="k", ls=":", lw=0.8)
        ax.set_title(f"on the {plant} ({'fitted model' if plant == 'learned' else 'simulated arm'})")
        ax.set_xlabel("time [s]")
    axes[0, 0].set_ylabel("distance to goal [mm] (median, IQR)")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    figures["distance"] = folder / "distance.png"
    fig.savefig(figures["distance"], dpi=100)
    plt.close(fig)

    # ---- task-space trajectories against goals ------------------------------------------------
    shown = [c for c in controllers if c not in ("preload", "random")]
    fig, axes = plt.subplots(len(plants), len(shown), figsize=(4 * len(shown), 4 * len(plants)),
                             squeeze=False)
    for r, plant in enumerate(plants):
        for c, controller in enumerate(shown):
            ax = axes[r, c]
            path = results["paths"][(plant, controller, 0)]
            for e in range(min(6, len(path))):
                ax.plot(path[e, :, 0] * 1e3, path[e, :, 2] * 1e3, "-", color=f"C{e}", lw=1)
                ax.plot(path[e, 0, 0] * 1e3, path[e, 0, 2] * 1e3, "o", color=f"C{e}", ms=3)
                ax.plot(goals[e, 0] * 1e3, goals[e, 2] * 1e3, "x", color=f"C{e}", ms=8, mew=2)
            ax.set_title(f"{controller} on the {plant}", fontsize=9)
            ax.set_xlabel("x [mm]")
            ax.set_ylabel("z [mm]")
            ax.set_aspect("equal", adjustable="datalim")
    fig.suptitle("trajectories (o start, x goal), seed 0")
    fig.tight_layout()
    figures["trajectories"] = folder / "trajectories.png"
    fig.savefig(figures["trajectories"], dpi=100)
    plt.close(fig)
    return figures
