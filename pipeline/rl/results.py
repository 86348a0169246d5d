"""Training results as tables and figures: per seed and update, per evaluation, per episode.

Every table is written with its units and the producing config (:func:`write_results`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.infra.parquet import table_metadata, write_parquet

RETURN_UNIT = "sum over the episode of the reward (env=learned/sim: -distance in mm per period)"
RETURN_LABEL = "episodic return [−mm, summed over periods]"
UNITS = {
    "timesteps": "environment steps per seed",
    "mean_return": RETURN_UNIT,
    "warmup": "true while no episode could yet have lasted max_steps: only early-ending ones "
              "are counted in that update's episode statistics",
    "final_distance_m": "m",
    "median_final_distance_m": "m",
    "episode_final_distance_m": "m",
}



def write_results(frame: pd.DataFrame, path: Path, config: dict[str, Any], stage: str) -> Path:
    """``frame`` as Parquet with the units of its columns and the producing config."""
    units = {k: v for k, v in UNITS.items() if k in frame}
    return write_parquet(frame, path, table_metadata(frame, path.stem, config, {"stage": stage},
                                                     units))


def warmup_updates(max_episode_steps: int, rollout_steps: int) -> int:
    """Updates before any episode can have run its full ``max_episode_steps``.

    All environments start together, so in update u (steps ``u * rollout_steps`` to
    ``(u + 1) * rollout_steps - 1`` of every environment) an episode can only have ended by
    truncation once ``(u + 1) * rollout_steps >= max_episode_steps``. Before that the episodes
    that end are only those that terminated early (goal reached): their mean return is that of
    the lucky few, not of the policy, and the curve would start with a spike.
    """
    return max(0, -(-int(max_episode_steps) // int(rollout_steps)) - 1)


def metrics_table(metrics: dict[str, np.ndarray], max_episode_steps: int | None = None,
                  rollout_steps: int | None = None) -> pd.DataFrame:
    """Per seed and update: the [num_seeds, num_updates] arrays of ``TrainOutput.metrics``.

    With ``max_episode_steps`` and ``rollout_steps`` (``agent.num_steps``), the column
    ``warmup`` marks the updates of :func:`warmup_updates` (kept in the table, left out of the
    return curves).
    """
    num_seeds, num_updates = np.asarray(metrics["timesteps"]).shape
    frame = pd.DataFrame({
        "seed": np.repeat(np.arange(num_seeds), num_updates),
        "update": np.tile(np.arange(num_updates), num_seeds),
    })
    for name, values in metrics.items():
        frame[name] = np.asarray(values).reshape(-1)
    if max_episode_steps is not None and rollout_steps is not None:
        frame["warmup"] = frame["update"] < warmup_updates(max_episode_steps, rollout_steps)
    return frame


def return_curves(metrics: pd.DataFrame) -> pd.DataFrame:
    """Columns timesteps, seed, return: each seed's mean return of the episodes that ended in
    each update, the warm-up updates left out, an update where none ended carrying the seed's
    previous value forward."""
    if "warmup" in metrics:
        metrics = metrics[~metrics["warmup"].astype(bool)]
    frame = metrics[["timesteps", "seed", "mean_return"]].rename(columns={"mean_return": "return"})
    return frame.assign(**{"return": frame.groupby("seed")["return"].ffill()})


def evaluation_tables(evaluation: dict[str, np.ndarray]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(per seed and evaluation, the last evaluation's episodes per seed)."""
    summary_names = ["timesteps", "mean_return", "median_final_distance_m", "success_rate"]
    num_seeds, num_evals = np.asarray(evaluation["timesteps"]).shape
    summary = pd.DataFrame({"seed": np.repeat(np.arange(num_seeds), num_evals),
                            "evaluation": np.tile(np.arange(num_evals), num_seeds)})
    for name in summary_names:
        summary[name] = np.asarray(evaluation[name]).reshape(-1)
    last = {name: np.asarray(values)[:, -1] for name, values in evaluation.items()
            if name.startswith("episode_")}
    num_episodes = last["episode_return"].shape[-1]
    episodes = pd.DataFrame({"seed": np.repeat(np.arange(num_seeds), num_episodes),
                             "episode": np.tile(np.arange(num_episodes), num_seeds)})
    for name, values in last.items():
        episodes[name.removeprefix("episode_")] = values.reshape(-1)
    return summary, episodes


def plot_returns(path: Path, metrics: pd.DataFrame, evaluation: pd.DataFrame, title: str
                 ) -> Path:
    """Training return (mean ± std over seeds) and held-out final distance per evaluation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import ticker

    path.parent.mkdir(parents=True, exist_ok=True)
    has_distance = evaluation["median_final_distance_m"].notna().any()
    fig, axes = plt.subplots(1, 2 if has_distance else 1, figsize=(11 if has_distance else 6, 4),
                             squeeze=False)
    stats = return_curves(metrics).groupby("timesteps")["return"].agg(["mean", "std"])
    stats = stats.reset_index()
    ax = axes[0, 0]
    ax.plot(stats["timesteps"], stats["mean"], color="C0",
            label=f"training episodes, mean ± std over {metrics['seed'].nunique()} seeds")
    ax.fill_between(stats["timesteps"], stats["mean"] - stats["std"].fillna(0),
                    stats["mean"] + stats["std"].fillna(0), color="C0", alpha=0.25)
    held_out = evaluation.groupby("timesteps")["mean_return"].mean()
    ax.plot(held_out.index, held_out.to_numpy(), "o-", color="C1",
            label="held-out goals, deterministic policy (mean over seeds)")
    xlabel = "environment steps per seed"
    if "warmup" in metrics and metrics["warmup"].any():
        xlabel += (f"\n(first {int(metrics.loc[metrics['warmup'], 'update'].nunique())} "
                   "update(s) left out: no episode could have run to max_steps yet)")
    ax.set(xlabel=xlabel, ylabel=RETURN_LABEL, title=title)
    ax.legend(fontsize=8)
    if has_distance:
        ax = axes[0, 1]
        many = evaluation["seed"].nunique() > 6  # then one thin grey line per seed, no legend
        style = {"color": "0.6", "lw": 0.8} if many else {"marker": "o"}
        for seed, rows in evaluation.groupby("seed"):
            ax.plot(rows["timesteps"], 1000 * rows["median_final_distance_m"], alpha=0.7,
                    label=None if many else f"seed {seed}", **style)
        if many:
            across = evaluation.groupby("timesteps")["median_final_distance_m"].median()
            ax.plot(across.index, 1000 * across.to_numpy(), "o-", color="C3",
                    label=f"median over {evaluation['seed'].nunique()} seeds")
        ax.axhline(1.0, color="k", ls="--", lw=1, label="1 mm")
        distances = 1000 * evaluation["median_final_distance_m"].dropna()
        if distances.max() > 10 * max(distances.min(), 1e-6):  # a log axis only where needed
            ax.set_yscale("log")
            ax.yaxis.set_major_formatter(ticker.FormatStrFormatter("%g"))
        ax.set(xlabel="environment steps per seed", ylabel="median final distance [mm]",
               title="held-out goals (deterministic policy)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


