"""The sections of the evaluation report (:mod:`pipeline.evaluation.report` renders them)."""

from __future__ import annotations

import pandas as pd
from omegaconf import OmegaConf

from pipeline.evaluation.report import Figure, Section, Table
from pipeline.infra.artifacts import Artifact


def _summary_section(cfg, model, summary: pd.DataFrame, policies: list[str]) -> Section:
    """The headline: model accuracy, and each controller's median final distance."""
    section = Section("Summary")
    if model is not None:
        held_out = model.manifest["summary"]
        section.add(f"Dynamics model: **{held_out['lstm_mean_mm']:.2f} mm** mean open-loop error "
                    f"on held-out runs (mean-position baseline {held_out['mean_position_mean_mm']:.2f}"
                    f" mm, linear lagged-pressure baseline {held_out['linear_lagged_mean_mm']:.2f} "
                    "mm).")
    wide = summary.pivot_table(index="controller", columns="plant",
                               values="median_final_mm").reset_index()
    wide.columns.name = None
    order = {name: i for i, name in enumerate(policies + list(cfg.evaluation.baselines))}
    wide = wide.sort_values("controller", key=lambda c: c.map(order))
    section.add(Table(wide.rename(columns={"learned": "learned env [mm]", "plant": "plant [mm]"}),
                      f"median final distance to held-out goals after {cfg.env.max_steps} control "
                      "periods"))
    return section


def report_sections(cfg, policies, results, figures, collect: Artifact | None = None,
                    aligned: Artifact | None = None, model: Artifact | None = None
                    ) -> list[Section]:
    """The report of an evaluation; ``collect``, ``aligned``, ``model``: the upstream artifacts
    where there are any (env=learned)."""
    tables = results["tables"]
    summary = tables["summary"]
    sections = [_summary_section(cfg, model, summary, list(policies))]

    config = Section("Configuration")
    config.add(f"Robot `{cfg.robot.name}`; exploration alpha {cfg.exploration.alpha}, beta "
               f"{cfg.exploration.beta}, P_max {cfg.exploration.p_max} kPa; model "
               f"{cfg.model.hidden} units at {cfg.dataset.model_hz} Hz; policies "
               f"{', '.join(cfg.evaluation.policies)}; baselines "
               f"{', '.join(cfg.evaluation.baselines)}.")
    config.add("```yaml\n" + OmegaConf.to_yaml(cfg, resolve=True) + "```")
    sections.append(config)

    data = Section("Data")
    if collect is not None:
        collected = collect.manifest["summary"]
        data.add(f"{collected.get('runs')} runs, {collected.get('commands')} commands, "
                 f"{collected.get('frames')} motion-capture frames "
                 f"({collected.get('dropped_frames')} dropped). Artifact `{collect.path}`.")
        for name, caption in (("exploration_alphas.png", "exploration walk for several alpha"),
                              ("runs.png", "recorded commands and positions")):
            if collect.file(f"figures/{name}").is_file():
                data.add(Figure(collect.file(f"figures/{name}"), caption))
    if aligned is not None:
        counts = aligned.manifest["summary"]
        data.add(Table(pd.DataFrame([counts]), "alignment counts"))
    sections.append(data)

    accuracy = Section("Model accuracy")
    if model is not None:
        metrics = pd.read_parquet(model.file("metrics.parquet"))
        accuracy.add("Open-loop error over each entire run (mean and 95th percentile, mm).")
        per_run = metrics.pivot_table(index=["split", "run_id"], columns="model",
                                      values="mean_mm").reset_index()
        per_run.columns.name = None
        accuracy.add(Table(per_run, "mean error [mm] per run"))
        for name, caption in (("loss.png", "loss curves (EMA-smoothed)"),
                              ("reconstruction.png", "reconstruction of a training and an "
                                                     "unseen run")):
            accuracy.add(Figure(model.file(f"figures/{name}"), caption))
    sections.append(accuracy)

    is_policy = summary["controller"].isin(list(policies))
    sections.append(Section("Policy results", [
        f"Final distance to held-out goals after {cfg.env.max_steps} control periods (the "
        "controller must reach the goal and stay; steps_to_3mm: when it first got within 3 mm), "
        "all seeds pooled.",
        Table(summary[is_policy]), Figure(figures["returns"], "training return, mean ± std "
                                                              "over seeds"),
        Figure(figures["distance"], "distance to goal over time"),
        Figure(figures["trajectories"], "task-space trajectories against goals")]))
    sections.append(Section("Baselines", [
        "Preload (do nothing), random safe actions, and sampling-based MPC on the learned model "
        "(offset-corrected on the plant), on the same goals and starts.",
        Table(summary[~is_policy])]))
    gap_section = Section("Plant gap")
    if len(tables["plant_gap"]):
        gap = tables["plant_gap"].groupby("controller").agg(
            median_final_gap_mm=("final_gap_mm", "median"),
            median_position_gap_mm=("final_position_gap_mm", "median")).reset_index()
        gap_section.add("Learned environment vs the simulated arm for the same goals: "
                        "plant final distance minus learned final distance, and the distance "
                        "between the two final poses.")
        gap_section.add(Table(gap))
    else:
        gap_section.add(f"No plant for robot `{cfg.robot.name}`: evaluated on the learned "
                        "environment only.")
    sections.append(gap_section)
    consecutive = tables["consecutive"]
    if len(consecutive):
        sections.append(Section("Consecutive goals", [
            f"{cfg.evaluation.num_consecutive_goals} goals in a row, {cfg.env.max_steps} "
            "control periods each, no reset: distance at the end of each goal's time.",
            Table(consecutive.groupby(["plant", "controller", "goal"])
                  ["median_distance_mm"].median().unstack("goal").reset_index())]))
    return sections
