"""Figures of an evaluation: training curves, distance to goal over time, trajectories.

:func:`make_figures` returns each figure with its caption (:class:`pipeline.evaluation.report.
Figure`); the captions say what is drawn (which seeds, which episodes).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.evaluation.metrics import ARRIVAL_MM, HELD_MM, MM_PER_M, first_step_within
from pipeline.evaluation.report import Figure
from pipeline.evaluation.tracking_report import tracking_figure
from pipeline.rl.results import RETURN_LABEL

PLANT_TITLES = {"learned": "learned model", "plant": "simulated arm (plant)"}
TRAJECTORY_EPISODES = 4  # episodes drawn per panel of the trajectory figure
TAIL_EPISODES = 3  # episodes drawn per plant in the figure after arrival
SEED_STYLES = ["-", "--", ":", "-."]  # line style per seed drawn in the trajectory figure


def tail_episodes(distance_mm: np.ndarray, count: int = TAIL_EPISODES,
                  arrival_mm: float = ARRIVAL_MM) -> np.ndarray:
    """Indices of the ``count`` episodes of ``distance_mm [E, T + 1]`` that came within
    ``arrival_mm`` and ended furthest from the goal, the furthest first (fewer where fewer
    arrived)."""
    arrived = np.flatnonzero(np.isfinite(first_step_within(distance_mm, arrival_mm)))
    order = np.argsort(-distance_mm[arrived, -1], kind="stable")
    return arrived[order[:count]]


@dataclass(frozen=True)
class FigureSettings:
    """What the evaluation's figures say of the run: ``max_steps`` control periods an episode
    lasts, ``control_hz`` (Hz) its control rate, ``goal_tolerance_m`` (m) the training
    tolerance."""

    max_steps: int
    control_hz: float
    goal_tolerance_m: float


def make_figures(folder: Path, settings: FigureSettings, curves: Mapping[str, pd.DataFrame],
                 results) -> dict[str, Figure]:
    """Every figure of an evaluation into ``folder``, by name: the training curves of each policy
    type (``curves``: its :func:`~pipeline.rl.results.return_curves`, columns timesteps, seed,
    return), the distance to the goal over time, the trajectories and, per policy type, what
    happens after the first arrival (where it ever arrived)."""
    import matplotlib

    matplotlib.use("Agg")

    folder.mkdir(parents=True, exist_ok=True)
    figures = {"returns": _returns_figure(folder / "returns.png", settings, curves),
               "distance": _distance_figure(folder / "distance.png", settings, results)}
    trajectories = _trajectories_figure(folder / "trajectories.png", results)
    for name in curves:
        drawn = after_arrival_figure(folder / f"after_arrival_{name}.png",
                                     float(settings.control_hz), results, name)
        if drawn is not None:
            figures[f"after_arrival/{name}"] = drawn
    figures["trajectories"] = trajectories
    if "tracking" in results:
        drawn = tracking_figure(folder / "tracking.png", results["tracking"],
                                float(settings.control_hz))
        if drawn is not None:
            figures["tracking"] = drawn
    return figures


def _returns_figure(path: Path, settings: FigureSettings, curves: Mapping[str, pd.DataFrame]
                    ) -> Figure:
    """Training curves: mean +- std over seeds per policy type (paper Fig. 8)."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4))
    seeds_per_type = {}
    for i, (name, frame) in enumerate(curves.items()):
        seeds_per_type[name] = frame["seed"].nunique()
        stats = frame.groupby("timesteps")["return"].agg(["mean", "std"]).reset_index()
        ax.plot(stats["timesteps"], stats["mean"], color=f"C{i}",
                label=f"{name} ({seeds_per_type[name]} seeds)")
        ax.fill_between(stats["timesteps"], stats["mean"] - stats["std"].fillna(0),
                        stats["mean"] + stats["std"].fillna(0), color=f"C{i}", alpha=0.25)
    ax.set_xlabel("environment steps per seed")
    ax.set_ylabel(RETURN_LABEL)
    ax.set_title("PPO in the learned model (mean ± std over seeds)", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Figure(path, (
        "training return per policy type: the mean return of the training episodes (stochastic "
        "policy) that ended in each update, mean ± std over seeds; the reward is −distance in "
        "mm per control period. The first updates, before any episode could have run its full "
        f"{settings.max_steps} periods, are left out: then only the episodes that reached the "
        "goal early had ended, and their mean made a spike at step 0."))


def _distance_figure(path: Path, settings: FigureSettings, results) -> Figure:
    """Distance to goal over time, and the fraction that has been within 3 mm."""
    import matplotlib.pyplot as plt

    goals = results["goals"]
    plants = sorted({key[0] for key in results["paths"]})
    controllers = list(dict.fromkeys(key[1] for key in results["paths"]))
    fig, axes = plt.subplots(2, len(plants), figsize=(6.5 * len(plants), 6.5), squeeze=False,
                             sharey="row", sharex=True, gridspec_kw={"height_ratios": [3, 2]})
    for col, plant in enumerate(plants):
        ax, ax_reached = axes[0, col], axes[1, col]
        for i, controller in enumerate(controllers):
            seeds = [k for k in results["paths"] if k[0] == plant and k[1] == controller]
            distance = np.concatenate([
                np.linalg.norm(results["paths"][k] - goals[:, None], axis=-1) * MM_PER_M
                for k in seeds])
            t = np.arange(distance.shape[1]) / float(settings.control_hz)
            median = np.median(distance, axis=0)
            low, high = np.percentile(distance, [25, 75], axis=0)
            ax.semilogy(t, median, color=f"C{i}", label=controller)
            ax.fill_between(t, low, high, color=f"C{i}", alpha=0.15)
            first = first_step_within(distance, 3.0)
            reached = (first[:, None] <= np.arange(distance.shape[1])[None]).mean(axis=0)
            ax_reached.step(t, reached, where="post", color=f"C{i}", label=controller)
        ax.axhline(float(settings.goal_tolerance_m) * MM_PER_M, color="k", ls=":", lw=0.8)
        ax.set_title(f"on the {PLANT_TITLES.get(plant, plant)}", fontsize=10)
        ax_reached.set_xlabel("time [s]")
        ax_reached.set_ylim(-0.02, 1.02)
    axes[0, 0].set_ylabel("distance to goal [mm]\n(median, IQR)")
    axes[1, 0].set_ylabel("fraction of episodes\never within 3 mm")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Figure(path, (
        "top: distance to the goal over time, median and interquartile range over every seed's "
        "episodes (dotted: the training tolerance); bottom: the fraction of episodes that have "
        "been within 3 mm by that time (one minus the survival curve of 'not yet within 3 mm')."))


def _trajectories_figure(path: Path, results) -> Figure:
    """Task-space trajectories against goals, every controller but the preload and random."""
    import matplotlib.pyplot as plt

    goals = results["goals"]
    plants = sorted({key[0] for key in results["paths"]})
    controllers = list(dict.fromkeys(key[1] for key in results["paths"]))
    shown = [c for c in controllers if c not in ("preload", "random")]
    fig, axes = plt.subplots(len(plants), len(shown), figsize=(4 * len(shown), 4 * len(plants)),
                             squeeze=False)
    all_seeds = sorted({key[2] for key in results["paths"]})
    drawn_seeds = all_seeds[:len(SEED_STYLES)]
    episodes = min(TRAJECTORY_EPISODES, len(goals))
    for r, plant in enumerate(plants):
        for c, controller in enumerate(shown):
            _trajectory_panel(axes[r, c], results, plant, controller, drawn_seeds, episodes)
    handles = _trajectory_legend(episodes, drawn_seeds)
    fig.legend(handles=handles, loc="upper center", ncol=min(len(handles), 8), fontsize=8,
               frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.5 / (4 * len(plants))))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    seed_words = (f"seeds {', '.join(map(str, drawn_seeds))}" if len(drawn_seeds) > 1
                  else f"seed {drawn_seeds[0]}")
    if len(all_seeds) > len(drawn_seeds):
        seed_words += f" of {len(all_seeds)}"
    return Figure(path, (
        f"task-space trajectories in the x–z plane, episodes 0–{episodes - 1} (one colour "
        f"each, the same goals and starts for every controller), {seed_words} of each policy "
        "(line style); MPC has one."))


def _trajectory_panel(ax, results, plant: str, controller: str, seeds: list[int],
                      episodes: int) -> None:
    """``controller``'s first ``episodes`` paths on ``plant`` in the x–z plane (mm), one line
    style per seed of ``seeds``, one colour per episode, with their starts and goals."""
    goals = results["goals"]
    for s, seed in enumerate(seeds):
        path = results["paths"].get((plant, controller, seed))
        if path is None:  # baselines have one "seed"
            continue
        for e in range(episodes):
            ax.plot(path[e, :, 0] * 1e3, path[e, :, 2] * 1e3, SEED_STYLES[s], color=f"C{e}",
                    lw=1.1 if s == 0 else 0.8)
            ax.plot(path[e, 0, 0] * 1e3, path[e, 0, 2] * 1e3, "o", color=f"C{e}", ms=3)
    for e in range(episodes):
        ax.plot(goals[e, 0] * 1e3, goals[e, 2] * 1e3, "x", color=f"C{e}", ms=9, mew=2)
    ax.set_title(f"{controller} on the {PLANT_TITLES.get(plant, plant)}", fontsize=9)
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("z [mm]")
    ax.set_aspect("equal", adjustable="datalim")


def _trajectory_legend(episodes: int, seeds: list[int]) -> list:
    """The trajectory figure's legend: a colour per episode, a line style per seed, start and
    goal markers."""
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=f"C{e}", lw=2, label=f"episode {e}") for e in range(episodes)]
    handles += [Line2D([], [], color="0.3", ls=SEED_STYLES[s], label=f"seed {seed}")
                for s, seed in enumerate(seeds)]
    handles += [Line2D([], [], color="0.3", marker="o", ls="", ms=4, label="start"),
                Line2D([], [], color="0.3", marker="x", ls="", ms=8, mew=2, label="goal")]
    return handles


def after_arrival_figure(path: Path, control_hz: float, results, controller: str
                         ) -> Figure | None:
    """What happens after the first arrival within 1 mm, for ``controller``'s tail episodes of
    each plant (:func:`tail_episodes` over every seed's episodes): distance to the goal, position
    minus goal per axis and the command per valve over time. None when it never arrived."""
    import matplotlib.pyplot as plt

    goals = results["goals"]
    plants = sorted({key[0] for key in results["paths"] if key[1] == controller})
    picked = {}
    for plant in plants:
        seeds = sorted(k[2] for k in results["paths"] if k[:2] == (plant, controller))
        positions = np.concatenate([results["paths"][(plant, controller, s)] for s in seeds])
        commands = np.concatenate([results["commands"][(plant, controller, s)] for s in seeds])
        episode_goals = np.concatenate([goals] * len(seeds))
        distance = np.linalg.norm(positions - episode_goals[:, None], axis=-1) * MM_PER_M
        chosen = tail_episodes(distance)
        if len(chosen):
            picked[plant] = (chosen, len(goals), distance, positions, commands, episode_goals)
    if not picked:
        return None
    fig, axes = plt.subplots(3, len(picked), figsize=(5.5 * len(picked), 8), squeeze=False,
                             sharex=True)
    axis_styles = ["-", "--", ":"]
    for col, (plant, (chosen, per_seed, distance, positions, commands, episode_goals)) in (
            enumerate(picked.items())):
        t = np.arange(distance.shape[1]) / control_hz
        for i, e in enumerate(chosen):
            colour = f"C{i}"
            first = int(first_step_within(distance[e:e + 1], ARRIVAL_MM)[0])
            label = (f"seed {e // per_seed}, episode {e % per_seed}: "
                     f"{distance[e, -1]:.2f} mm at the end")
            axes[0, col].plot(t, distance[e], color=colour, label=label)
            axes[0, col].plot(t[first], distance[e, first], "o", color=colour, ms=5)
            error = (positions[e] - episode_goals[e]) * MM_PER_M
            for a in range(3):
                axes[1, col].plot(t, error[:, a], axis_styles[a], color=colour, lw=1)
                axes[2, col].step(t[1:], commands[e, :, a], axis_styles[a], where="pre",
                                  color=colour, lw=1)
            for row in range(3):
                axes[row, col].axvline(t[first], color=colour, lw=0.6, alpha=0.5)
        axes[0, col].axhline(ARRIVAL_MM, color="k", ls=":", lw=0.8)
        axes[0, col].axhline(HELD_MM, color="k", ls="--", lw=0.8)
        axes[0, col].set_yscale("log")
        axes[0, col].set_title(f"{controller} on the {PLANT_TITLES.get(plant, plant)}",
                               fontsize=10)
        axes[0, col].legend(fontsize=7)
        axes[1, col].axhline(0.0, color="k", lw=0.6)
        axes[2, col].set_xlabel("time [s]")
    axes[0, 0].set_ylabel("distance to goal [mm]")
    axes[1, 0].set_ylabel("position − goal [mm]\n(x solid, y dashed, z dotted)")
    axes[2, 0].set_ylabel("command [kPa]\n(valve 1 solid, 2 dashed, 3 dotted)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Figure(path, (
        f"after the first arrival within {ARRIVAL_MM:g} mm (dot and vertical line), {controller}'s "
        f"tail episodes on each plant: of every seed's episodes that arrived, the "
        f"{TAIL_EPISODES} that ended furthest from the goal (one colour each). Top: distance to "
        f"the goal (dotted {ARRIVAL_MM:g} mm, dashed {HELD_MM:g} mm: an arrival held to the end "
        "ends below it); middle: position minus goal per axis; bottom: the command sent in each "
        "control period, per valve. A command that stands still while the position moves is "
        "the plant drifting under a held command."))
