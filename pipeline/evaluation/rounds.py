"""The table of ``stage=improve``'s rounds: per round the arm time, each step's wall time, the
model's error on the round's own sessions before and after the refit, and the closed-loop
figures on the plant and in the model; a figure of them; the report's markdown.

A round's row is read from its steps' artifacts (their manifests' ``build_seconds``, evaluate's
``summary.parquet``, control's ``goals.parquet``, the sessions' runs), so a resumed run reports
the same row as an uninterrupted one.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.data.alignment import load_runs
from pipeline.data.runs import Run
from pipeline.data.sessions import read_session, session_run_id
from pipeline.dynamics.checkpoints import load_dynamics
from pipeline.dynamics.scoring import evaluate_open_loop
from pipeline.infra.artifacts import Artifact
from pipeline.infra.parquet import table_metadata, write_parquet

# the steps of a round whose wall time the table reports, in order (drive: the arm's sessions,
# in simulated time on an in-process arm; the others: computation)
STEPS = ("drive", "align", "fit_model", "train_ppo", "evaluate")
COMPUTE_STEPS = ("align", "fit_model", "train_ppo", "evaluate")
UNITS = {"arm_s": "s", "arm_s_total": "s", **{f"wall_{step}_s": "s" for step in STEPS},
         "wall_compute_s": "s", "model_before_mean_mm": "mm", "model_before_p95_mm": "mm",
         "model_after_mean_mm": "mm", "model_after_p95_mm": "mm", "drive_median_mm": "mm",
         "plant_median_mm": "mm", "plant_p90_mm": "mm", "model_median_mm": "mm",
         "model_p90_mm": "mm"}


def round_runs(aligned: Sequence[Artifact] | None, drives: Sequence[Artifact], model_hz: float,
               grid: str) -> list[Run]:
    """The runs of a round's sessions (``drives``) as the refit saw them: from the round's
    align artifact, at the model's rate."""
    if not aligned or not drives:
        return []
    wanted = {session_run_id(artifact.stage, artifact.key) for artifact in drives}
    runs = load_runs(aligned[0].file("aligned.parquet"), model_hz, grid)
    return [run for run in runs if run.run_id in wanted]


def model_error_mm(model: Artifact, runs: Sequence[Run]) -> tuple[float, float]:
    """The model's open-loop error over ``runs`` (mean over runs of each one's mean and p95)."""
    if not runs:
        return float("nan"), float("nan")
    params = load_dynamics(model.file("model.msgpack"))
    scores = [evaluate_open_loop(params, run) for run in runs]
    return (float(np.mean([s["mean_mm"] for s in scores])),
            float(np.mean([s["p95_mm"] for s in scores])))


def _closed_loop(summary: pd.DataFrame, plant: str, controller: str, prefix: str
                 ) -> dict[str, float]:
    row = summary[(summary["plant"] == plant) & (summary["controller"] == controller)]
    names = {"median_final_mm": "median_mm", "p90_final_mm": "p90_mm",
             "success_1mm": "within_1mm", "held_arrivals": "held_arrivals",
             "reachable_goals": "reachable_goals", "success_reachable": "within_1mm_reachable"}
    return {f"{prefix}_{short}": (float(row[name].iloc[0]) if len(row) and name in row
                                  else float("nan"))
            for name, short in names.items()}


def arm_seconds(drives: Sequence[Artifact]) -> float:
    """Arm seconds the sessions ``drives`` took: each run's first to last frame."""
    total = 0.0
    for artifact in drives:
        times = read_session(artifact.path).mocap["t"].to_numpy(np.float64)
        total += float(times[-1] - times[0]) if len(times) else 0.0
    return total


def drive_figures(drives: Sequence[Artifact]) -> dict[str, float]:
    """The round's own goals on the arm (its control sessions' ``goals.parquet``)."""
    finals = [pd.read_parquet(a.file("goals.parquet"))["final_distance_mm"].to_numpy()
              for a in drives if a.file("goals.parquet").is_file()]
    final = np.concatenate(finals) if finals else np.array([])
    return {"drive_goals": len(final),
            "drive_median_mm": float(np.median(final)) if len(final) else float("nan"),
            "drive_within_1mm": float(np.mean(final <= 1.0)) if len(final) else float("nan")}


def round_row(index: int, policy: str, plant: str, evaluation: Artifact,
              steps: Mapping[str, Sequence[Artifact]], before: Artifact | None,
              after: Artifact | None, runs: Sequence[Run]) -> dict[str, Any]:
    """One round's row (module doc): ``steps`` the artifacts of each step of :data:`STEPS`
    (only ``evaluate`` in round 0); ``before`` / ``after`` the model before and after the
    refit, scored on ``runs`` (the round's sessions)."""
    wall = {f"wall_{step}_s": float(sum(a.manifest.get("build_seconds") or 0.0
                                        for a in steps.get(step, ())))
            for step in STEPS}
    wall["wall_compute_s"] = float(sum(wall[f"wall_{step}_s"] for step in COMPUTE_STEPS))
    summary = pd.read_parquet(evaluation.file("summary.parquet"))
    drives = steps.get("drive", ())
    row: dict[str, Any] = {"round": int(index), "policy": policy, "plant": plant,
                           "arm_s": arm_seconds(drives), "sessions": len(drives), **wall,
                           **drive_figures(drives)}
    for name, model in (("before", before), ("after", after)):
        mean, p95 = model_error_mm(model, runs) if model is not None else (np.nan, np.nan)
        row[f"model_{name}_mean_mm"], row[f"model_{name}_p95_mm"] = mean, p95
    row.update(_closed_loop(summary, plant, policy, "plant"))
    row.update(_closed_loop(summary, "learned", policy, "model"))
    row["evaluate"] = evaluation.key
    return row


def append(table: pd.DataFrame | None, row: Mapping[str, Any]) -> pd.DataFrame:
    """``table`` (the earlier rounds; None: none) with ``row``, the arm seconds summed."""
    frame = pd.DataFrame([dict(row)])
    table = frame if table is None else pd.concat([table, frame], ignore_index=True)
    table["arm_s_total"] = table["arm_s"].cumsum()
    return table


def one_line(row: Mapping[str, Any]) -> str:
    return (f"{row['arm_s']:.0f} arm s; model on the round's sessions {row['model_before_mean_mm']:.2f}"
            f" -> {row['model_after_mean_mm']:.2f} mm; on {row['plant']}: median "
            f"{row['plant_median_mm']:.2f} mm, within 1 mm {100 * row['plant_within_1mm']:.0f} %, "
            f"p90 {row['plant_p90_mm']:.2f} mm; compute {row['wall_compute_s']:.0f} s")


def write(writer: Any, table: pd.DataFrame, config: Mapping[str, Any]) -> None:
    """``rounds.parquet`` (units and config in its metadata), ``rounds.png`` and ``report.md``
    into the round's artifact."""
    write_parquet(table, writer.file("rounds.parquet"),
                  table_metadata(table, "improve_rounds", dict(config), {"stage": "improve"},
                                 {k: v for k, v in UNITS.items() if k in table}))
    plot(writer.file("rounds.png"), table)
    writer.file("report.md").write_text(markdown(table, config))


def markdown(table: pd.DataFrame, config: Mapping[str, Any]) -> str:
    """The rounds' table as a markdown report."""
    shown = {"round": "round", "arm_s": "arm s", "wall_compute_s": "compute s",
             "model_before_mean_mm": "model before mm", "model_after_mean_mm": "model after mm",
             "drive_median_mm": "drive median mm", "plant_median_mm": "plant median mm",
             "plant_within_1mm": "plant within 1 mm", "plant_p90_mm": "plant p90 mm",
             "plant_held_arrivals": "held arrivals", "model_median_mm": "in model median mm"}
    frame = table[[c for c in shown if c in table]].rename(columns=shown)
    lines = ["# sorolearn improve: rounds on the arm", "",
             f"Policy `{table['policy'].iloc[0]}` on `{table['plant'].iloc[0]}`; round 0 is the "
             "deployed policy. Settings: `" + json.dumps(dict(config)) + "`.", "",
             "| " + " | ".join(frame.columns) + " |",
             "| " + " | ".join("---" for _ in frame.columns) + " |"]
    for values in frame.itertuples(index=False):
        lines.append("| " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v)
                                       for v in values) + " |")
    return "\n".join(lines) + "\n\n![rounds](rounds.png)\n"


def plot(path: Path, table: pd.DataFrame) -> Path:
    """The closed-loop figures and the model's error per round."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    rounds = table["round"].to_numpy()
    for column, label in (("plant_median_mm", "plant median"), ("plant_p90_mm", "plant p90"),
                          ("model_median_mm", "in model median")):
        axes[0].plot(rounds, table[column], marker="o", label=label)
    axes[0].set(xlabel="round", ylabel="final distance [mm]", yscale="log")
    axes[1].plot(rounds, 100 * table["plant_within_1mm"], marker="o", label="within 1 mm")
    axes[1].plot(rounds, 100 * table["plant_held_arrivals"], marker="s", label="arrivals held")
    axes[1].set(xlabel="round", ylabel="% of goals", ylim=(0, 105))
    for column, label in (("model_before_mean_mm", "before refit"),
                          ("model_after_mean_mm", "after refit")):
        axes[2].plot(rounds, table[column], marker="o", label=label)
    axes[2].set(xlabel="round", ylabel="model error on the round's sessions [mm]")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
