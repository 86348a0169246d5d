"""What a stage or a chain prints when it ends: a short aligned table, the artifact and report
paths, and the next command that makes sense.

Read from the artifacts themselves (their tables and manifests), by column name, so a table that
gains columns keeps its summary:

- ``evaluate``: controller x plant, the median final distance [mm], the share of episodes that
  ended within 1 mm, the seeds and episodes (``summary.parquet``, ``episodes.parquet``), and, on
  recorded data, each policy in the model of runs it never saw (``cross_model.parquet``);
- ``fit_model``: the model's held-out open-loop error next to its baselines (the manifest);
- ``train_ppo``: per policy, the seeds and training's own final evaluation (the manifest: the
  median final distance, the share of episodes that reached the goal within 1 mm);
- ``control``: per goal, the final distance, the time to within 1 mm, the steady-state error
  (``goals.parquet``); following a reference, its RMSE, p95, largest error, lag and share within
  1 mm (``tracking.parquet``).

:func:`evaluation_table` is also the table that heads the evaluation's report
(:func:`pipeline.evaluation.sections.report_sections`).
"""

from __future__ import annotations

import json
import math
import shlex
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import pandas as pd

from pipeline.evaluation.metrics import CROSS
from pipeline.evaluation.report import format_number

WITHIN = "within_1mm_%"  # the share of episodes (or seeds) that ended within 1 mm, in per cent


def read_evaluation_table(artifact_path: Path) -> pd.DataFrame:
    """:func:`evaluation_table` of the evaluate artifact in ``artifact_path`` (its
    ``summary.parquet``, and ``episodes.parquet`` and ``cross_model.parquet`` where there)."""
    folder = Path(artifact_path)
    episodes = cross = None
    if (folder / "episodes.parquet").is_file():
        episodes = pd.read_parquet(folder / "episodes.parquet", columns=["plant", "controller",
                                                                       "seed"])
    if (folder / "cross_model.parquet").is_file():
        cross = pd.read_parquet(folder / "cross_model.parquet")
    return evaluation_table(pd.read_parquet(folder / "summary.parquet"), episodes, cross)


def evaluation_table(summary: pd.DataFrame, episodes: pd.DataFrame | None = None,
                     cross_model: pd.DataFrame | None = None) -> pd.DataFrame:
    """One row per controller and plant of an evaluation's ``summary`` table: ``median_final_mm``
    [mm], ``within_1mm_%`` (episodes that ended within 1 mm) [%], ``seeds`` (counted in
    ``episodes``, 1 without it), ``episodes``; the cross-model protocol's rows (plant ``model of
    runs A->B``, from ``cross_model``) where it ran. Ordered as the evaluation ran them (plant,
    then controller)."""
    seeds = pd.Series(dtype=float)
    if episodes is not None:
        seeds = episodes.groupby(["plant", "controller"], sort=False)["seed"].nunique()
    rows = []
    for row in summary.to_dict("records"):
        rows.append({"controller": row["controller"], "plant": row["plant"],
                     "median_final_mm": float(row["median_final_mm"]),
                     WITHIN: round(100.0 * float(row["success_1mm"])),
                     "seeds": int(seeds.get((row["plant"], row["controller"]), 1)),
                     "episodes": int(row["episodes"])})
    if cross_model is not None:
        for row in cross_model.to_dict("records"):
            if str(row.get("plant")) != CROSS and "direction" in row:
                continue  # its rows in the group's own model: the learned rows say as much
            rows.append({"controller": row["controller"],
                         "plant": f"model of runs {row.get('direction', '?')}",
                         "median_final_mm": float(row["median_final_mm"]),
                         WITHIN: round(100.0 * float(row["success_1mm"])),
                         "seeds": int(row["seeds"]) if "seeds" in row else None,
                         "episodes": int(row["episodes"]) if "episodes" in row else None})
    return pd.DataFrame(rows, columns=["controller", "plant", "median_final_mm", WITHIN, "seeds",
                                       "episodes"])


def model_table(manifest_summary: dict[str, Any]) -> pd.DataFrame:
    """The model's held-out open-loop error next to its baselines, from a fit_model artifact's
    manifest summary: one row per model (``learned``, then the baselines), ``mean_mm`` and
    ``p95_mm`` [mm]."""
    rows = []
    baselines = {key[: -len("_mean_mm")] for key in manifest_summary
                 if key.endswith("_mean_mm")} - {"learned", "train_runs"}
    names = ["learned", *sorted(baselines)]
    for name in names:
        if f"{name}_mean_mm" in manifest_summary:
            rows.append({"model": name, "mean_mm": float(manifest_summary[f"{name}_mean_mm"]),
                         "p95_mm": float(manifest_summary.get(f"{name}_p95_mm", math.nan))})
    return pd.DataFrame(rows, columns=["model", "mean_mm", "p95_mm"])


def goals_table(artifact_path: Path) -> pd.DataFrame:
    """Per goal of a control artifact: the goal [mm], ``final_mm``, ``time_to_1mm_s`` (– where it
    never got there), ``steady_state_mm`` [mm]."""
    goals = pd.read_parquet(Path(artifact_path) / "goals.parquet")
    out = pd.DataFrame({"goal": goals["goal"]})
    axes = [c for c in ("goal_x_mm", "goal_y_mm", "goal_z_mm") if c in goals]
    if axes:
        out["goal_mm"] = [", ".join(f"{v:.1f}" for v in values)
                          for values in goals[axes].to_numpy()]
    for name, column in (("final_mm", "final_distance_mm"), ("time_to_1mm_s", "time_to_1mm_s"),
                         ("steady_state_mm", "steady_state_error_mm")):
        if column in goals:
            out[name] = goals[column].astype(float)
    return out


def text_table(frame: pd.DataFrame, significant: int = 3) -> list[str]:
    """``frame`` as aligned text lines: a header, a rule, one line per row; numbers with
    ``significant`` figures (``format_number``), right-aligned; text left-aligned."""
    def cell(value: Any) -> str:
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return "–"
        if isinstance(value, bool):
            return "yes" if value else "no"
        if isinstance(value, int) or (isinstance(value, float) and value.is_integer()
                                      and abs(value) >= 10 ** significant):
            return f"{int(value):,}"
        if isinstance(value, float):
            return format_number(value, significant)
        return str(value)

    columns = [str(c) for c in frame.columns]
    cells = [[cell(v.item() if hasattr(v, "item") else v) for v in row]
             for row in frame.itertuples(index=False)]
    numeric = [pd.api.types.is_numeric_dtype(frame[c]) for c in frame.columns]
    widths = [max([len(name)] + [len(r[i]) for r in cells]) for i, name in enumerate(columns)]

    def line(values: Sequence[str]) -> str:
        return "  ".join(v.rjust(w) if right else v.ljust(w)
                         for v, w, right in zip(values, widths, numeric)).rstrip()

    return [line(columns), "  ".join("-" * w for w in widths), *(line(r) for r in cells)]


def _manifest(path: Path) -> dict[str, Any]:
    file = Path(path) / "artifact.json"
    return json.loads(file.read_text()) if file.is_file() else {}


def _relative(path: Path) -> str:
    """``path`` from the working directory where it lies below it (shorter to read and copy)."""
    path = Path(path)
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def command(stage: str, overrides: Sequence[str], *extra: str) -> str:
    """``python -m pipeline stage=<stage>`` with the run's own ``overrides`` (less ``stage``,
    ``force`` and any key of ``extra``) and ``extra``, quoted for a POSIX shell."""
    replaced = {e.split("=", 1)[0] for e in extra} | {"stage", "force"}
    kept = [o for o in overrides if o.split("=", 1)[0].lstrip("+~") not in replaced]
    return " ".join(["python -m pipeline", f"stage={stage}",
                     *(shlex.quote(o) for o in (*kept, *extra))])


def goals_from_data(align_path: Path, quantiles: Sequence[float] = (0.35, 0.5, 0.65)) -> str | None:
    """Goals [mm] inside the recorded positions of an align artifact (per axis, the given
    quantiles of ``aligned.parquet``'s x, y, z), as a ``control.goals`` value; None where there
    is no such table. Goals of ``stage=control`` must lie inside the training goals' box, which
    is drawn from these positions."""
    table = Path(align_path) / "aligned.parquet"
    if not table.is_file():
        return None
    positions = pd.read_parquet(table, columns=["x", "y", "z"]).dropna()
    if positions.empty:
        return None
    goals = positions.quantile(list(quantiles)).to_numpy() * 1e3
    return "[" + ",".join("[" + ",".join(f"{v:.1f}" for v in goal) + "]" for goal in goals) + "]"


class RunFacts(NamedTuple):
    """What the closing summary needs of a run's config: the robot option and its kind (``sim``,
    ``ros2``, an importer), the run's agent option and env name."""

    robot: str
    robot_kind: str
    agent: str
    env: str


def closing_summary(stage: str, results: dict[str, Any], run: RunFacts,
                    overrides: Sequence[str] = ()) -> list[str]:
    """The lines a run of ``stage`` (``all`` for the chain) ends with: per stage that ran, its
    table; the last artifact and its report; the next command (``overrides``: the run's own
    command-line overrides, kept in it). ``results``: the router's stage name -> artifact."""
    lines: list[str] = []
    robot = run.robot
    fit = results.get("fit_model")
    if fit is not None and hasattr(fit, "path"):
        summary = _manifest(fit.path).get("summary", {})
        table = model_table(summary)
        if not table.empty:
            protocol = summary.get("protocol", "")
            held = ("every run held out once (leave-one-run-out)" if protocol == "cv"
                    else f"held-out runs {', '.join(summary.get('test_runs', [])) or '–'}")
            lines += ["", f"The model's open-loop error [mm] on {held}, next to its baselines:",
                      *text_table(table)]
    train = results.get("train_ppo")
    if train is not None and hasattr(train, "path") and "evaluate" not in results:
        summary = _manifest(train.path).get("summary", {})
        row = {"policy": summary.get("agent", run.agent),
               "env": summary.get("env", ""), "seeds": summary.get("num_seeds"),
               "steps_per_seed": summary.get("timesteps_per_seed"),
               "median_final_mm": summary.get("final_eval_median_distance_mm"),
               "reached_1mm_%": (None if summary.get("final_eval_success_rate") is None
                                 else round(100.0 * float(summary["final_eval_success_rate"])))}
        lines += ["", "Training's own final evaluation (held-out goals, in its environment):",
                  *text_table(pd.DataFrame([row]))]
    evaluation = results.get("evaluate")
    if evaluation is not None and hasattr(evaluation, "path"):
        lines += ["", f"Closed loop on held-out goals (robot={robot}): median final distance "
                  "[mm], share of episodes within 1 mm [%], seeds:",
                  *text_table(read_evaluation_table(evaluation.path))]
    control = results.get("control")
    if control is not None and hasattr(control, "path") and (control.path /
                                                              "goals.parquet").is_file():
        lines += ["", f"Per goal (robot={robot}):", *text_table(goals_table(control.path))]
    if control is not None and hasattr(control, "path") and (control.path /
                                                              "tracking.parquet").is_file():
        tracking = pd.read_parquet(control.path / "tracking.parquet")
        lines += ["", f"Following the reference (robot={robot}), after the settle time [mm, s]:",
                  *text_table(tracking[[c for c in ("rmse_mm", "p95_mm", "max_mm", "lag_s",
                                                    "within_1mm", "offset_mm", "at_limits")
                                        if c in tracking]])]
    rounds = results.get("improve")
    if rounds is not None and hasattr(rounds, "path") and (rounds.path /
                                                           "rounds.parquet").is_file():
        table = pd.read_parquet(rounds.path / "rounds.parquet")
        shown = {"round": "round", "arm_s": "arm_s", "wall_compute_s": "compute_s",
                 "model_before_mean_mm": "model_before_mm", "model_after_mean_mm":
                 "model_after_mm", "plant_median_mm": "median_mm", "plant_within_1mm":
                 "within_1mm", "plant_p90_mm": "p90_mm", "plant_held_arrivals": "held"}
        lines += ["", f"Rounds on {table['plant'].iloc[0]} (round 0: the deployed policy; the "
                  "model's error on the round's sessions before and after its refit [mm]; the "
                  "policy on the plant [mm, shares]):",
                  *text_table(table[list(shown)].rename(columns=shown).round(3))]
    last = next((results[s] for s in reversed(list(results)) if hasattr(results[s], "path")),
                None)
    if last is not None:
        lines += ["", f"artifact: {_relative(last.path)}"]
        if (last.path / "report.html").is_file():
            lines.append(f"report:   {_relative(last.path / 'report.html')}")
    step = next_step(stage, results, run, overrides)
    if step:
        lines += [f"next:     {step[0]}", *(f"          {s}" for s in step[1:])]
    return lines


def next_step(stage: str, results: dict[str, Any], run: RunFacts, overrides: Sequence[str]
              ) -> list[str]:
    """The command that makes sense after ``stage`` (first line), with what it does."""
    policy, kind = run.agent, run.robot_kind
    if stage == "train_ppo":
        return [command("evaluate", overrides)
                + "    # every policy type and the baselines, on the model and on the plant"]
    if stage in ("all", "evaluate") and run.env != "gymnax":  # a gymnax task drives no arm
        align = results.get("align")
        goals = goals_from_data(align.path) if hasattr(align, "path") else None
        if kind == "sim":
            extra = [f"control.policy={policy}"] + ([f"control.goals={goals}"] if goals else [])
            return [command("control", overrides, *extra),
                    "# the trained policy in closed loop on the simulated arm (the stage that "
                    "drives an arm: robot=ros2 with the twin or the arm)"]
        policy_file = results.get("train_ppo")
        extra = ([f"control.policy_file={_relative(policy_file.path / 'policy.msgpack')}"]
                 if policy_file is not None and hasattr(policy_file, "path") else [])
        return ["python -m pipeline stage=twin robot=ros2    # shell 1: the digital twin",
                command("control", ["robot=ros2", "robot.rehearsal=true"], *extra,
                        *([f"control.goals={goals}"] if goals else []))
                + "    # shell 2: rehearse on the twin before the arm (docs: real-arm workflow)"]
    control = results.get("control")
    if stage == "control" and kind == "sim" and hasattr(control, "path"):
        policy = _manifest(control.path).get("summary", {}).get("policy")
        if policy:
            return ["python -m pipeline stage=twin robot=ros2    # shell 1: the digital twin",
                    command("control", ["robot=ros2", "robot.rehearsal=true"],
                            f"control.policy_file={_relative(Path(policy) / 'policy.msgpack')}",
                            *[o for o in overrides if o.startswith(
                                ("control.goals", "control.trajectory", "control.duration_s",
                                 "control.settle_s"))])
                    + "    # shell 2: the same policy over ROS 2 (docs: real-arm workflow)"]
    follow = {"collect": "align", "align": "fit_model", "fit_model": "train_ppo",
              "calibrate": "evaluate"}
    if stage in follow:
        return [command(follow[stage], overrides)]
    return []
