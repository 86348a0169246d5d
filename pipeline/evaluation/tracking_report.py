"""The tracking evaluation's figure and report section (:mod:`pipeline.evaluation.tracking`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.evaluation.metrics import MM_PER_M
from pipeline.evaluation.report import Figure, Section, Table

PLANT_STYLES = {"learned": "-", "plant": "--"}  # others: dotted
TRACKING_COLUMNS = {
    "plant": "plant", "controller": "controller", "reference": "reference",
    "episodes": "episodes", "median_rmse_mm": "RMSE [mm]",
    "seed_rmse_min_mm": "seeds' RMSE min [mm]", "seed_rmse_max_mm": "seeds' RMSE max [mm]",
    "median_p95_mm": "p95 [mm]", "median_max_mm": "max error [mm]",
    "within_1mm": "time within 1 mm", "median_lag_s": "lag [s]",
}


def tracking_figure(path: Path, results: dict[str, Any], control_hz: float,
                    episode: int = 0, seed: int = 0) -> Figure | None:
    """For each reference (a row): the reference against the paths of every controller but the
    preload in x–z (one episode, one seed, each plant its line style), and their error over
    time; None without tracking results."""
    import matplotlib.pyplot as plt

    targets = results.get("reference_paths") or {}
    if not targets:
        return None
    paths = results["paths"]
    fig, axes = plt.subplots(len(targets), 2, figsize=(10, 4 * len(targets)), squeeze=False)
    for row, (name, target) in enumerate(targets.items()):
        plane, error = axes[row]
        reference = target[episode] * MM_PER_M
        plane.plot(reference[:, 0], reference[:, 2], color="black", lw=2.5, alpha=0.4,
                   label="reference")
        for (plant, controller, reference_name, path_seed), positions in paths.items():
            if reference_name != name or path_seed != seed or controller == "preload":
                continue
            style = PLANT_STYLES.get(plant, ":")
            drawn = positions[episode] * MM_PER_M
            label = f"{controller} · {plant}"
            plane.plot(drawn[:, 0], drawn[:, 2], style, lw=1.2, label=label)
            times = np.arange(len(drawn)) / control_hz
            error.plot(times, np.linalg.norm(drawn - reference, axis=-1), style, lw=1.2,
                       label=label)
        plane.set(title=f"{name}: x–z", xlabel="x [mm]", ylabel="z [mm]", aspect="equal")
        error.set(title=f"{name}: error", xlabel="time [s]", ylabel="distance [mm]")
        error.axhline(1.0, color="grey", lw=0.8, ls=":")
        plane.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return Figure(path, (f"tracking: the reference (grey) and the paths of each policy's seed "
                         f"{seed}, episode {episode}, on each plant (line style), and the "
                         f"distance to the reference over time (1 mm dotted)."))


def tracking_section(summary: pd.DataFrame, figure: Figure | None, order: Sequence[str],
                     settle_seconds: float | None = None) -> Section:
    """The report's "Tracking" section: the summary per plant, controller and reference
    (:func:`pipeline.evaluation.tracking.summarize_tracking`) and the figure."""
    rank = {name: number for number, name in enumerate(order)}
    frame = summary.assign(rank=[rank.get(c, len(rank)) for c in summary["controller"]])
    frame = frame.sort_values(["reference", "plant", "rank"], kind="stable")
    after = "" if settle_seconds is None else f" after the first {settle_seconds:g} s"
    section = Section("Tracking", [
        "Every controller follows the same references from the same starts (each episode's "
        f"phase its own), scored{after}: the median over seeds and episodes of each episode's "
        "RMSE, 95th percentile and largest error, the share of the time within 1 mm and the lag "
        "(the time shift that best aligns the path with the reference; positive: behind it); "
        "the seeds' RMSE: the least and largest of the seeds' medians.",
        Table(frame[list(TRACKING_COLUMNS)].rename(columns=TRACKING_COLUMNS))])
    if figure is not None:
        section.add(figure)
    return section
