"""What a control session achieved, per goal: tables, figures and the report (following a
reference: :func:`tracking_figures`, the metrics in :mod:`pipeline.control.trajectory`).

Goal ``i`` is in force over periods ``[s_i, e_i)``; the poses at the ticks ``s_i .. e_i`` (the
last one taken before the next goal's first command, or at the end) are its trajectory:

- ``final_distance_mm``: at tick ``e_i``;
- ``time_to_1mm_s`` / ``time_to_3mm_s``: arm seconds from ``s_i`` until the distance is first
  within 1 / 3 mm at a tick (NaN: never);
- ``overshoot_mm``: how far the pose went past the goal along the start-to-goal direction
  (0 when it never passed it);
- ``steady_state_error_mm``: the mean distance over the last quarter of the goal's ticks;
- ``smoothness_kpa``: mean absolute change of the command between consecutive periods, per valve;
- the hold after the first tick within 1 mm (:func:`pipeline.evaluation.metrics.hold_metrics`,
  NaN when it never got there): ``within_1mm_after_arrival`` (the share of the ticks from then on
  within 1 mm), ``max_after_arrival_mm`` and ``held_1.5mm`` (1 when the goal ended within 1.5 mm).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.control.records import GOAL_COLUMNS, REFERENCE_COLUMNS
from pipeline.data.schemas import CMD_COLUMNS, XYZ
from pipeline.evaluation.metrics import hold_metrics
from pipeline.evaluation.report import Figure, Section, Table, write_report

MM_PER_M = 1000.0


def goal_segments(periods: pd.DataFrame) -> list[dict[str, Any]]:
    """Per goal: its index, goal [3] m, positions [n + 1, 3] m at its ticks, commands [n, 3]."""
    table = periods.sort_values("period").reset_index(drop=True)
    commanded = table[table["goal_index"] >= 0]
    segments = []
    for index, rows in commanded.groupby("goal_index", sort=True):
        first, last = int(rows.index.min()), int(rows.index.max())
        through = min(last + 1, len(table) - 1)  # the pose at the goal's end
        segments.append({
            "goal_index": int(index),
            "goal": rows[GOAL_COLUMNS].to_numpy(np.float64)[0],
            "t": table.loc[first:through, "t"].to_numpy(np.float64),
            "positions": table.loc[first:through, XYZ].to_numpy(np.float64),
            "commands": rows[CMD_COLUMNS].to_numpy(np.float64),
            "complete": through == last + 1,
        })
    return segments


def goal_metrics(periods: pd.DataFrame, period_s: float) -> pd.DataFrame:
    """One row per goal (see the module doc)."""
    rows = []
    for segment in goal_segments(periods):
        goal, positions = segment["goal"], segment["positions"]
        distance = np.linalg.norm(positions - goal, axis=1) * MM_PER_M
        direction = goal - positions[0]
        norm = np.linalg.norm(direction)
        past = ((positions - goal) @ (direction / norm) * MM_PER_M) if norm > 0 else np.zeros(1)
        times = {}
        for tol in (1, 3):
            within = np.flatnonzero(distance <= tol)
            times[f"time_to_{tol}mm_s"] = float(within[0] * period_s) if within.size else np.nan
        tail = distance[1:][-max(1, (len(distance) - 1) // 4):] if len(distance) > 1 else distance
        commands = segment["commands"]
        rows.append({
            "goal": segment["goal_index"],
            **{f"goal_{a}_mm": float(v * MM_PER_M) for a, v in zip(XYZ, goal)},
            "start_distance_mm": float(distance[0]),
            "final_distance_mm": float(distance[-1]),
            **times,
            "overshoot_mm": float(max(0.0, past.max())),
            "steady_state_error_mm": float(tail.mean()),
            **{name: float(value[0]) for name, value in hold_metrics(distance[None]).items()},
            "smoothness_kpa": (float(np.abs(np.diff(commands, axis=0)).mean())
                               if len(commands) > 1 else 0.0),
            "periods": len(commands),
            "complete": segment["complete"],
        })
    return pd.DataFrame(rows)


def latency_summary(periods: pd.DataFrame) -> dict[str, float | None]:
    """Compute latency (wall ms), its CPU time (ms) and pose age at command time (arm ms):
    median, p99, max."""
    commanded = periods[periods["goal_index"] >= 0]

    def describe(values: np.ndarray) -> dict[str, float] | None:
        values = values[np.isfinite(values)]
        if not values.size:
            return None
        return {"p50": float(np.median(values)), "p99": float(np.percentile(values, 99)),
                "max": float(values.max())}

    return {"compute_latency_ms": describe(commanded["latency_ms"].to_numpy(np.float64)),
            "compute_cpu_ms": (describe(commanded["cpu_ms"].to_numpy(np.float64))
                               if "cpu_ms" in commanded else None),
            "pose_age_ms": describe(commanded["pose_age_s"].to_numpy(np.float64) * 1e3)}


def _save(fig: Any, ax: Any, path: Path, **legend: Any) -> Path:
    """The figure with ``ax``'s legend (``legend``: its settings, small type) written to
    ``path`` at the control report's resolution, and closed."""
    import matplotlib.pyplot as plt

    ax.legend(**{"fontsize": 8, **legend})
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def make_figures(folder: Path, periods: pd.DataFrame, limits: Any) -> dict[str, Path]:
    """distance.png (with the 1 mm line), path_xz.png (with the goals), pressures.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    segments = goal_segments(periods)
    paths = {}

    fig, ax = plt.subplots(figsize=(9, 3.6))
    for segment in segments:
        distance = np.linalg.norm(segment["positions"] - segment["goal"], axis=1) * MM_PER_M
        ax.plot(segment["t"], distance, label=f"goal {segment['goal_index']}")
    ax.axhline(1.0, color="k", ls="--", lw=1, label="1 mm")
    ax.set(xlabel="arm time [s]", ylabel="distance to goal [mm]", yscale="log")
    paths["distance"] = _save(fig, ax, folder / "distance.png", ncol=4)

    fig, ax = plt.subplots(figsize=(5.5, 5))
    table = periods.sort_values("period")
    ax.plot(table["x"] * MM_PER_M, table["z"] * MM_PER_M, color="0.4", lw=1, label="path")
    for segment in segments:
        ax.plot(*(segment["goal"][[0, 2]] * MM_PER_M), "x", ms=10, mew=2,
                label=f"goal {segment['goal_index']}")
    ax.set(xlabel="x [mm]", ylabel="z [mm]", aspect="equal")
    paths["path"] = _save(fig, ax, folder / "path_xz.png")

    paths["pressures"] = _pressure_figure(folder, table, limits)
    return paths


def _pressure_figure(folder: Path, table: pd.DataFrame, limits: Any) -> Path:
    """pressures.png: the commands sent (after the gate) over arm time, with ``p_max``."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 3.6))
    commanded = table[table["goal_index"] >= 0]
    for j, column in enumerate(CMD_COLUMNS):
        ax.step(commanded["t"], commanded[column], where="post", label=f"valve {j}")
    ax.axhline(float(limits.p_max), color="r", ls=":", lw=1, label="p_max")
    ax.set(xlabel="arm time [s]", ylabel="command [kPa]")
    return _save(fig, ax, folder / "pressures.png", ncol=4)


def tracking_figures(folder: Path, periods: pd.DataFrame, limits: Any, settle_s: float
                     ) -> dict[str, Path]:
    """Following a reference: path_xz.png (the reference and the path in x-z), error.png (the
    distance to the reference at each tick, with the settle time and the 1 mm line),
    pressures.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    table = periods.sort_values("period")
    table = table[table["period"] >= 0]
    position = table[XYZ].to_numpy(np.float64) * MM_PER_M
    reference = table[REFERENCE_COLUMNS].to_numpy(np.float64) * MM_PER_M
    paths = {}

    fig, ax = plt.subplots(figsize=(5.5, 5))
    ax.plot(reference[:, 0], reference[:, 2], "k--", lw=1, label="reference")
    ax.plot(position[:, 0], position[:, 2], color="C0", lw=1.2, label="path")
    ax.plot(position[0, 0], position[0, 2], "o", color="C0", label="start")
    ax.set(xlabel="x [mm]", ylabel="z [mm]", aspect="equal")
    paths["tracking_path"] = _save(fig, ax, folder / "path_xz.png")

    fig, ax = plt.subplots(figsize=(9, 3.6))
    ax.plot(table["t"], np.linalg.norm(position - reference, axis=1), color="C0")
    ax.axhline(1.0, color="k", ls="--", lw=1, label="1 mm")
    ax.axvline(settle_s, color="0.5", ls=":", lw=1, label="settled: scored from here")
    ax.set(xlabel="arm time [s]", ylabel="distance to the reference [mm]")
    paths["error"] = _save(fig, ax, folder / "error.png")
    paths["pressures"] = _pressure_figure(folder, table, limits)
    return paths


CAPTIONS = {"distance": "distance to the goal at each control tick",
            "path": "x-z path of the markers and the goals",
            "tracking_path": "x-z path of the markers and the reference",
            "error": "distance to the reference at each control tick",
            "pressures": "pressure commands sent (after the gate)"}


def write_control_report(folder: Path, title: str, header: list[str], metrics: pd.DataFrame,
                         latency: dict[str, Any], figures: dict[str, Path],
                         metrics_section: tuple[str, str] = (
                             "Per goal", "distances in mm, times in arm seconds")) -> None:
    """report.md / report.html: the ``header`` lines, ``metrics`` (a section titled and captioned
    by ``metrics_section``), the ``figures`` (by their :data:`CAPTIONS` name) and the timing."""
    overview = Section("Session")
    for line in header:
        overview.add(line)
    shown = Section("Figures")
    for name, path in figures.items():
        shown.add(Figure(path, CAPTIONS[name]))
    sections = [overview, Section(metrics_section[0]).add(Table(metrics, metrics_section[1])),
                shown]
    rows = [{"quantity": name, **(values or {})} for name, values in latency.items()]
    sections.append(Section("Timing").add(Table(pd.DataFrame(rows),
                                                "compute: wall ms from the pose taken to the "
                                                "command published, cpu: CPU ms of this process "
                                                "in that span; pose age: arm ms")))
    write_report(folder, title, sections)
