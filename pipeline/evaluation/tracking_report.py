"""The tracking evaluation's figures and report section (:mod:`pipeline.evaluation.tracking`).

Both figures are drawn from the paths table (``tracking_paths``,
:func:`pipeline.evaluation.tracking.path_table`), the one the evaluate artifact keeps: the
report's (every plant, each its line style) and the paper-style one of ``make figures`` (one
plant, the error's spread over episodes and seeds) are the same drawing.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.evaluation.report import Figure, Section, Table

PLANT_STYLES = {"learned": "-", "plant": "--"}  # others: dotted
PLANT_LABELS = {"learned": "learned model", "plant": "simulated arm", "own": "own model",
                "cross": "other model"}
HIDDEN = ("preload",)  # controllers left out of the figures: the error is the reference's size
TRACKING_COLUMNS = {
    "plant": "plant", "controller": "controller", "reference": "reference",
    "episodes": "episodes", "median_rmse_mm": "RMSE [mm]",
    "seed_rmse_min_mm": "seeds' RMSE min [mm]", "seed_rmse_max_mm": "seeds' RMSE max [mm]",
    "median_p95_mm": "p95 [mm]", "median_max_mm": "max error [mm]",
    "within_1mm": "time within 1 mm", "median_lag_s": "lag [s]",
    "median_offset_mm": "steady offset [mm]", "at_limits": "time at the limits",
}


def draw_tracking(paths: pd.DataFrame, plants: Sequence[str] | None = None, episode: int = 0,
                  seed: int = 0, spread: bool = False, since_s: float = 0.0):
    """A figure, one row per reference of ``paths`` (the paths table): the reference against
    the path of each controller but the preload in x–z from ``since_s`` s on (``episode`` of
    ``seed``; a baseline's only seed where it has no ``seed``) and the distance to the reference
    over time, the median over the table's episodes and seeds (with ``spread``, the band between
    the quartiles); on ``plants`` (None: every plant of the table, each its line style; one:
    solid lines)."""
    import matplotlib.pyplot as plt

    if plants is not None:
        paths = paths[paths["plant"].isin(list(plants))]
    paths = paths[~paths["controller"].isin(HIDDEN)]
    names = list(dict.fromkeys(paths["reference"]))
    colours = {name: f"C{number}" for number, name in
               enumerate(dict.fromkeys(paths["controller"]))}
    fig, axes = plt.subplots(len(names), 2, figsize=(11, 4.2 * len(names)), squeeze=False)
    for (plane, error), name in zip(axes, names, strict=True):
        shown = paths[paths["reference"] == name]
        first = shown[shown["episode"] == episode]
        reference = first[first["seed"] == first["seed"].min()].drop_duplicates("period")
        plane.plot(reference["reference_x_mm"], reference["reference_z_mm"], color="black",
                   lw=2.5, alpha=0.35, label="reference")
        single = plants is not None and len(plants) == 1
        for (plant, controller), group in shown.groupby(["plant", "controller"], sort=False):
            style, colour = "-" if single else PLANT_STYLES.get(plant, ":"), colours[controller]
            label = controller if single else f"{controller} · {PLANT_LABELS.get(plant, plant)}"
            own = group[(group["episode"] == episode) & (group["time_s"] >= since_s - 1e-9)]
            own = own[own["seed"] == (seed if seed in set(own["seed"]) else own["seed"].min())]
            plane.plot(own["x_mm"], own["z_mm"], style, color=colour, lw=1.2, label=label)
            over_time = group.groupby("time_s")["error_mm"]
            median = over_time.median()
            error.plot(median.index, median.to_numpy(), style, color=colour, lw=1.3, label=label)
            if spread:
                error.fill_between(median.index, over_time.quantile(0.25).to_numpy(),
                                   over_time.quantile(0.75).to_numpy(), color=colour, alpha=0.15)
        after = f" from {since_s:g} s" if since_s else ""
        plane.set(title=f"{name}: x–z{after}", xlabel="x [mm]", ylabel="z [mm]", aspect="equal")
        error.set(title=f"{name}: distance to the reference", xlabel="time [s]",
                  ylabel="distance [mm]")
        error.set_ylim(bottom=0)
        error.axhline(1.0, color="grey", lw=0.8, ls=":")
        plane.legend(fontsize=7)
    fig.tight_layout()
    return fig


def tracking_figure(path: Path, results: dict[str, Any], control_hz: float,
                    episode: int = 0, seed: int = 0) -> Figure | None:
    """The report's figure (:func:`draw_tracking` on every plant) into ``path``; None without
    tracking results. ``control_hz``: Hz of the control periods (the table's times carry it)."""
    import matplotlib.pyplot as plt

    paths = results.get("tables", {}).get("tracking_paths")
    if paths is None or not len(paths):
        return None
    since = float(results.get("settle_seconds", 0.0))
    fig = draw_tracking(paths, episode=episode, seed=seed, since_s=since)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    episodes = int(paths["episode"].nunique())
    return Figure(path, (
        f"tracking: the reference (grey) and the paths of each controller's seed {seed}, episode "
        f"{episode}, from {since:g} s on (scored from there), on each plant (line style: solid "
        f"the learned model, dashed the simulated "
        f"arm, dotted the others), and the median over its first {episodes} episodes and its "
        f"seeds of the distance to the reference over time (1 mm dotted); at "
        f"{control_hz:g} Hz, the preload left out."))


def _ordered(frame: pd.DataFrame, order: Sequence[str], by: Sequence[str]) -> pd.DataFrame:
    """``frame`` sorted by ``by``, then by controller: ``order`` first, the rest as they came."""
    rank = {name: number for number, name in enumerate(order)}
    ranked = frame.assign(rank=[rank.get(c, len(rank)) for c in frame["controller"]])
    return ranked.sort_values([*by, "rank"], kind="stable").drop(columns="rank")


def tracking_section(summary: pd.DataFrame, figure: Figure | None, order: Sequence[str],
                     settle_seconds: float | None = None,
                     cross_model: pd.DataFrame | None = None) -> Section:
    """The report's "Tracking" section: the summary per plant, controller and reference
    (:func:`pipeline.evaluation.tracking.summarize_tracking`), the cross-model protocol's
    (``cross_model``, per direction too, where it ran) and the figure."""
    after = "" if settle_seconds is None else f" after the first {settle_seconds:g} s"
    # the policies (in ``order``), the reaching baseline, the MPC, the preload
    reaching = [c for c in dict.fromkeys(summary["controller"]) if str(c).endswith("(reaching)")]
    order = [c for c in order if c not in ("mpc", "preload")] + reaching + ["mpc", "preload"]
    frame = _ordered(summary, order, ["reference", "plant"])
    frame = frame.assign(plant=frame["plant"].map(lambda p: PLANT_LABELS.get(p, p)))
    section = Section("Tracking", [
        "Every controller follows the same references from the same starts (each episode's "
        f"phase its own), scored{after}: the median over seeds and episodes of each episode's "
        "RMSE, 95th percentile and largest error, the share of the time within 1 mm and the lag "
        "(the time shift that best aligns the path with the reference; positive: behind it), "
        "and the share of the periods whose command lay on the limits of the safe set (a valve "
        "at its least or greatest pressure or the sum at its greatest: there the reference asks "
        "for all the rating allows); the seeds' RMSE: the least and largest of the seeds' "
        "medians. Baselines: the preload "
        "(do nothing), sampling MPC (mpc) on the learned model scored against the reference "
        "over its horizon, and the reaching policies fed the moving goal (reaching).",
        Table(frame[list(TRACKING_COLUMNS)].rename(columns=TRACKING_COLUMNS))])
    if cross_model is not None and len(cross_model):
        shown = _ordered(cross_model, order, ["reference", "direction", "plant"])
        shown = shown.assign(plant=shown["plant"].map(lambda p: PLANT_LABELS.get(p, p)))
        columns = {"direction": "direction", **TRACKING_COLUMNS}
        section.add("Across models: each group's policies and baselines (the MPC on the "
                    "group's own model) follow the references in their own model and in the "
                    "model of the other group of runs, fitted to runs they never saw.")
        section.add(Table(shown[list(columns)].rename(columns=columns)))
    if figure is not None:
        section.add(figure)
    return section

