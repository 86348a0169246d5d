"""The sections of the evaluation report (:mod:`pipeline.evaluation.report` renders them).

Where the words come from: ``plant`` in the tables is the simulated arm (``robot=sim``: its own
hysteresis, creep and rest-pose spread, equations the model never saw), ``learned`` the fitted
model the policies were trained in; the report says so in words.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import pandas as pd

from pipeline.dynamics.adaptation import context_summary
from pipeline.dynamics.cv import cv_summary
from pipeline.dynamics.scoring import LEARNED
from pipeline.evaluation.metrics import seed_spread
from pipeline.evaluation.report import Figure, Section, Table, format_number
from pipeline.evaluation.summary import evaluation_table
from pipeline.evaluation.tracking_report import tracking_section
from pipeline.infra.records import ArtifactRecord

PLANT_NAMES = {"learned": "learned model", "plant": "simulated arm"}
# the hold after the first arrival within 1 mm (metrics.summarize), as the report shows it
HOLD_COLUMNS = {
    "arrived_1mm": "ever ≤ 1 mm", "held_arrivals": "of those: final ≤ 1.5 mm",
    "within_1mm_after_arrival": "of those: time ≤ 1 mm after arrival",
    "median_max_after_arrival_mm": "of those: median max after arrival [mm]"}
# the summary's columns as the report shows them (units in the name)
SUMMARY_COLUMNS = {
    "controller": "controller", "plant": "evaluated on", "episodes": "episodes",
    "median_final_mm": "median final [mm]", "mean_final_mm": "mean final [mm]",
    "p90_final_mm": "p90 final [mm]", "success_1mm": "final ≤ 1 mm", "success_3mm": "final ≤ 3 mm",
    "reached_3mm": "ever ≤ 3 mm", "median_steps_to_3mm": "median steps to 3 mm",
    **HOLD_COLUMNS,
    "smoothness_kpa": "smoothness [kPa/step]", "time_above_limits": "time above limits",
    "reachable_goals": "goals the plant holds", "success_reachable": "of those: final ≤ 1 mm",
}
STEPS_NOTE = ("'ever ≤ 3 mm' is the fraction of episodes that came within 3 mm of the goal at "
              "any time; 'median steps to 3 mm' the median over all episodes of when they first "
              "did, those that never did counted as never (∞ when fewer than half did). "
              "Smoothness: mean |change| of the command between consecutive control periods, "
              "per valve. Fractions are of episodes; 'time above limits' the largest fraction "
              "of an episode's steps outside the safe set (0 is required). The hold: of the "
              "episodes that were ever within 1 mm ('ever ≤ 1 mm'), the share that ended within "
              "1.5 mm (held to the end), the mean share of the times from the first arrival to "
              "the end spent within 1 mm, and the median of the largest distance after it. 'Goals the "
              "plant holds': the share of the goals some constant command inside the limits "
              "holds the plant within 1 mm of (a lower bound: the search is local); 'of those: "
              "final ≤ 1 mm' the controller's success on them, so that a goal the plant cannot "
              "hold is not its miss.")


@dataclass(frozen=True)
class ReportFacts:
    """The run's settings the report states, as the config gives them (printed as they are).

    ``robot_name``: the robot config; ``exploration_alpha``, ``exploration_beta``,
    ``p_max_kpa`` (kPa): the exploration walk's; ``model_hidden`` units of the model at
    ``model_hz`` (Hz); ``policies`` and ``baselines``: the evaluated policy types and baselines;
    ``max_steps``: control periods an episode (and each consecutive goal) lasts;
    ``num_consecutive_goals``: goals in a row of the consecutive-goals task; ``config_yaml``:
    the whole config, resolved, as YAML.
    """

    robot_name: str
    exploration_alpha: Any
    exploration_beta: Any
    p_max_kpa: Any
    model_hidden: Any
    model_hz: Any
    policies: tuple[str, ...]
    baselines: tuple[str, ...]
    max_steps: int
    num_consecutive_goals: int
    config_yaml: str


# the collect stage's figures the report shows, with their captions
COLLECT_FIGURES = {
    "exploration_alphas.png": "exploration walk for several alpha (the same random draws for each)",
    "runs.png": "recorded commands and positions"}
# the fit_model stage's figures the report shows (captions in the model section)
MODEL_FIGURES = ("loss.png", "reconstruction.png")


def _plant_label(name: str) -> str:
    return PLANT_NAMES.get(name, name)


def _ordered(frame: pd.DataFrame, order: list[str]) -> pd.DataFrame:
    rank = {name: i for i, name in enumerate(order)}
    return frame.sort_values("controller", key=lambda c: c.map(rank), kind="stable")


def _summary_table(summary: pd.DataFrame) -> pd.DataFrame:
    shown = summary.assign(plant=summary["plant"].map(_plant_label))
    return shown[[c for c in SUMMARY_COLUMNS if c in shown]].rename(columns=SUMMARY_COLUMNS)


def _model_sentence(model: ArtifactRecord) -> str:
    held = model.summary
    tested = list(held.get("test_runs", []))
    if held.get("protocol") == "cv":
        folds = list(held.get("folds", []))
        runs = (f"each of the {len(folds)} runs held out once (leave-one-run-out, each predicted "
                "by the model fitted to the other runs)")
    elif tested:
        runs = (f"the {len(tested)} held-out run{'s' if len(tested) != 1 else ''} "
                f"({', '.join(tested)})")
    else:
        runs = "the training runs (no run was held out)"
    return (f"Dynamics model: **{format_number(held[f'{LEARNED}_mean_mm'])} mm** mean and "
            f"{format_number(held[f'{LEARNED}_p95_mm'])} mm 95th-percentile open-loop error over "
            f"{runs}, each predicted over its entire length from its commands alone "
            f"(mean-position baseline {format_number(held['mean_position_mean_mm'])} mm, linear "
            f"lagged-pressure baseline {format_number(held['linear_lagged_mean_mm'])} mm).")


def _summary_section(facts: ReportFacts, model: ArtifactRecord | None,
                     tables: Mapping[str, pd.DataFrame], order: list[str]) -> Section:
    """The report's one summary, its first section: the table the run printed at its end
    (:func:`headline_section`), then the model's accuracy, what the plants are, and each
    controller's median final distance on each plant."""
    summary = tables["summary"]
    section = headline_section(tables)
    if model is not None:
        section.add(_model_sentence(model))
        for warning in model.summary.get("warnings", []):
            section.add(f"**Warning:** {warning}.")
    if "plant" in set(summary["plant"]):
        section.add("Every controller is run on the **learned model** (the fitted recurrent "
                    "model the policies were trained in) and on the **simulated arm** (the plant: "
                    "`robot=sim`'s own physics, with hysteresis, creep and a rest pose that "
                    "differs between sessions, which the model only saw through recorded data).")
    twins = sorted(p for p in set(summary["plant"]) if str(p).startswith("twin "))
    if twins:
        section.add(f"**Calibrated twins** ({', '.join(t.removeprefix('twin ') for t in twins)}): "
                    "the simulated arm with physics fitted to the arm (`evaluation.twins`), "
                    "observed like the learned model, every episode started where its physics "
                    "rest it at the preload: a plant built from other equations than the learned "
                    "model, so it does not share the model's errors.")
    wide = summary.pivot_table(index="controller", columns="plant",
                               values="median_final_mm").reset_index()
    wide.columns.name = None
    wide = _ordered(wide, order).rename(
        columns={p: f"on the {_plant_label(p)} [mm]" for p in PLANT_NAMES})
    section.add(Table(wide, f"median final distance to held-out goals after {facts.max_steps} "
                            "control periods, every seed's episodes pooled"))
    return section


def _model_section(model: ArtifactRecord | None) -> Section:
    """The model's open-loop error per run next to its baselines (``model``'s ``metrics``
    table), and its figures."""
    accuracy = Section("Model accuracy")
    if model is None:
        accuracy.add("No dynamics model in this run.")
        return accuracy
    metrics = model.tables["metrics"]
    held = model.summary
    if "cv" in set(metrics["split"]):
        accuracy.add("Leave-one-run-out cross-validation: each run predicted over its entire "
                     "length by the model fitted to the other runs, next to the baselines fitted "
                     "to the same runs and that fold model's error on its own training runs; the "
                     "model the policies use is fitted to all runs.")
        accuracy.add(Table(cv_summary(metrics), "held-out open-loop error per run [mm]"))
        if "cv_context" in set(metrics["split"]):
            accuracy.add(Table(context_summary(metrics), "session context: each fold model "
                               "calibrated on the first context_s of its held-out run, mean "
                               "error over the rest from from_s [mm], averaged over the runs; "
                               "linear_lagged refitted on the same context"))
        for warning in held.get("warnings", []):
            accuracy.add(f"**Warning:** {warning}.")
        for name, caption in (("loss.png", "training loss of the model fitted to all runs"),
                              ("reconstruction.png", "open-loop reconstruction of a training "
                               "run (model on all runs) and a held-out run (its fold model)")):
            if name in model.figures:
                accuracy.add(Figure(model.figures[name], caption))
        return accuracy
    trained, tested = list(held.get("train_runs", [])), list(held.get("test_runs", []))
    accuracy.add(f"{len(trained)} training run{'s' if len(trained) != 1 else ''} and "
                 f"{len(tested)} held-out run{'s' if len(tested) != 1 else ''}. Open-loop error "
                 "over each entire run, predicted from its commands alone: the mean and the "
                 "95th percentile over time of the distance between predicted and measured "
                 "position, next to two baselines.")
    per_run = metrics.pivot_table(index=["split", "run_id"], columns="model",
                                  values=["mean_mm", "p95_mm"]).reset_index()
    names = {"mean_mm": "mean [mm]", "p95_mm": "p95 [mm]"}
    per_run.columns = [f"{model_name} {names[stat]}" if model_name else stat
                       for stat, model_name in per_run.columns]
    models = [m for m in (LEARNED, "linear_lagged", "mean_position") if m in set(metrics["model"])]
    columns = ["split", "run_id"] + [f"{m} {s}" for m in models for s in names.values()]
    per_run = per_run.sort_values("split", key=lambda c: c.map({"train": 0, "test": 1}))
    accuracy.add(Table(per_run[columns], "open-loop error per run (split test: held out)"))
    for name, caption in (
            ("loss.png", "loss curves: training loss (raw and EMA-smoothed) and the held-out "
                         "runs' loss and open-loop error"),
            ("reconstruction.png", "open-loop reconstruction of a training and an unseen run: "
                                   "measured and predicted x, y, z, the error over time, and a "
                                   "zoom (right of each run) into the shaded window")):
        if name in model.figures:
            accuracy.add(Figure(model.figures[name], caption))
    return accuracy


def _chatter_sentence(summary: pd.DataFrame, policies: list[str]) -> str | None:
    """MPC's command smoothness on the simulated arm against the policies', in words."""
    on_plant = summary[summary["plant"] == "plant"].set_index("controller")["smoothness_kpa"]
    if "mpc" not in on_plant or not any(p in on_plant for p in policies):
        return None
    mpc = float(on_plant["mpc"])
    others = {p: float(on_plant[p]) for p in policies if p in on_plant}
    against = ", ".join(f"{format_number(v)} for {p}" for p, v in others.items())
    smoothest = min(others.values())
    sentence = (f"On the simulated arm MPC's commands change by {format_number(mpc)} kPa per "
                f"control period and valve on average, against {against}")
    if smoothest > 0 and mpc > 3 * smoothest:
        sentence += (f": MPC chatters ({format_number(mpc / smoothest)} times the smoothest "
                     "policy's change). It searches a new command every period (cross-entropy "
                     "method on the learned model, from fresh random samples, with the goal "
                     "shifted by the arm-minus-model offset), so consecutive commands jump.")
    else:
        sentence += "."
    return sentence


def _stopped_at(stopped: Mapping[str, Any] | None) -> str | None:
    """Where ``agent.stop_at`` ended a training (its summary's ``stopped_at``), in words."""
    if not stopped:
        return None
    return (f"{stopped['timesteps_per_seed']} steps/seed, {stopped['seconds']} s: "
            f"{stopped['median_distance_mm']} mm, {100 * stopped['success_rate']:.0f} %")


def timing_table(upstream: Mapping[str, ArtifactRecord | None],
                 policies: Mapping[str, ArtifactRecord],
                 evaluate_seconds: float | None = None) -> pd.DataFrame:
    """One row per artifact of the chain: the wall seconds its build took when it was built
    (``build_seconds`` of its manifest; empty for artifacts written before it was recorded), and
    for the policies their compile and training seconds, the devices (cores) their seeds were
    split over, env steps per second and where ``agent.stop_at`` stopped them."""
    rows = []
    for stage, artifact in upstream.items():
        if artifact is not None:
            rows.append({"stage": stage, "artifact": artifact.path.name,
                         "built in [s]": artifact.build_seconds})
    for name, artifact in policies.items():
        summary = artifact.summary
        rows.append({"stage": f"train_ppo ({name})", "artifact": artifact.path.name,
                     "built in [s]": artifact.build_seconds,
                     "compile [s]": summary.get("compile_seconds"),
                     "training [s]": summary.get("train_seconds"),
                     "devices": summary.get("devices"),
                     "env steps/s": summary.get("env_steps_per_second"),
                     "stopped at": _stopped_at(summary.get("stopped_at"))})
    if evaluate_seconds is not None:
        rows.append({"stage": "evaluate (until this report)", "artifact": "this one",
                     "built in [s]": round(float(evaluate_seconds), 2)})
    return pd.DataFrame(rows)


def report_sections(facts: ReportFacts, policies: Mapping[str, ArtifactRecord], results,
                    figures: Mapping[str, Figure], collect: ArtifactRecord | None = None,
                    aligned: ArtifactRecord | None = None, model: ArtifactRecord | None = None,
                    evaluate_seconds: float | None = None) -> list[Section]:
    """The report of an evaluation of ``policies`` (train_ppo records by policy type) with
    ``results`` (:func:`~pipeline.evaluation.closed_loop.run_evaluation`'s) and ``figures``;
    ``collect``, ``aligned``, ``model``: the upstream records where there are any (env=learned;
    ``model`` with its ``metrics`` table and figures); ``evaluate_seconds``: how long this
    evaluation has run."""
    tables = results["tables"]
    summary = tables["summary"]
    names = list(policies)
    order = names + list(facts.baselines)
    sections = [_summary_section(facts, model, tables, order), _configuration_section(facts),
                _data_section(collect, aligned), _model_section(model),
                _policy_section(facts, tables, figures, names, order),
                _baselines_section(summary, names, order),
                _gap_section(facts, tables["plant_gap"], order)]
    if len(tables.get("cross_model", ())):
        sections.append(cross_model_section(tables["cross_model"], order))
    if len(tables.get("tracking", ())):
        sections.append(tracking_section(tables["tracking"], figures.get("tracking"), order,
                                         results.get("tracking", {}).get("settle_seconds"),
                                         tables.get("cross_model_tracking")))
    upstream = {"collect": collect, "align": aligned, "fit_model": model}
    sections.append(Section("Time to a controller", [
        "Wall seconds of each artifact's build, when it was built (a reused artifact keeps the "
        "time of the run that built it); for the policies, the compilation and the training "
        "apart, and the devices (CPU cores or GPUs) their seeds were split over.",
        Table(timing_table(upstream, policies, evaluate_seconds))]))
    consecutive = tables["consecutive"]
    if len(consecutive):
        sections.append(Section("Consecutive goals", [
            f"{facts.num_consecutive_goals} goals in a row, {facts.max_steps} "
            "control periods each, no reset: the distance at the end of each goal's time.",
            Table(consecutive_table(consecutive, order),
                  "median over seeds of each seed's median distance [mm] at the end of goal "
                  "1, 2, ...; the last column: the fraction of all goals (every seed's episodes) ended "
                  "within 3 mm")]))
    return sections


def headline_section(tables: Mapping[str, pd.DataFrame]) -> Section:
    """The table the run printed at its end (:func:`~pipeline.evaluation.summary.
    evaluation_table` of the evaluation's ``summary``, ``episodes`` and, where it ran,
    ``cross_model`` tables), as the "Summary" section that opens the report (the report goes on
    in it with the model and the plants)."""
    table = evaluation_table(tables["summary"], tables["episodes"], tables.get("cross_model"))
    return Section("Summary").add(Table(table, (
        "Closed loop on held-out goals, per controller and plant: the median final distance "
        "[mm], the share of episodes that ended within 1 mm [%], the seeds and episodes (the "
        "table the run printed at its end).")))


def _configuration_section(facts: ReportFacts) -> Section:
    """The run's main settings in a sentence, and the whole config."""
    config = Section("Configuration")
    config.add(f"Robot `{facts.robot_name}`; exploration alpha {facts.exploration_alpha}, beta "
               f"{facts.exploration_beta}, P_max {facts.p_max_kpa} kPa; model "
               f"{facts.model_hidden} units at {facts.model_hz} Hz; policies "
               f"{', '.join(facts.policies)}; baselines "
               f"{', '.join(facts.baselines)}.")
    config.add("```yaml\n" + facts.config_yaml + "```")
    return config


def _data_section(collect: ArtifactRecord | None, aligned: ArtifactRecord | None) -> Section:
    """The recorded runs (``collect``'s counts and figures) and the alignment's counts."""
    data = Section("Data")
    if collect is not None:
        collected = collect.summary
        data.add(f"{collected.get('runs')} runs, {collected.get('commands')} commands, "
                 f"{collected.get('frames')} motion-capture frames "
                 f"({collected.get('dropped_frames')} dropped). Artifact `{collect.path}`.")
        for name, caption in COLLECT_FIGURES.items():
            if name in collect.figures:
                data.add(Figure(collect.figures[name], caption))
    if aligned is not None:
        counts = aligned.summary
        data.add(Table(pd.DataFrame({"count": list(counts), "value": list(counts.values())}),
                       "alignment counts, summed over runs"))
    return data


def _policy_section(facts: ReportFacts, tables: Mapping[str, pd.DataFrame],
                    figures: Mapping[str, Figure], names: list[str], order: list[str]
                    ) -> Section:
    """Every policy type's results, pooled over seeds and spread over seeds, and the figures."""
    summary, episodes = tables["summary"], tables["episodes"]
    is_policy = summary["controller"].isin(names)
    seeds = sorted(episodes["seed"].unique()) if "seed" in episodes else [0]
    policy_episodes = episodes[episodes["controller"].isin(names)]
    spread = seed_spread(policy_episodes, ["controller", "plant"])
    spread = _ordered(spread.assign(plant=spread["plant"].map(_plant_label)), order).rename(
        columns={"plant": "evaluated on", "median_of_seed_medians": "median [mm]",
                 "q25": "q25 [mm]", "q75": "q75 [mm]", "min": "min [mm]", "max": "max [mm]"})
    return Section("Policy results", [
        f"Final distance to held-out goals after {facts.max_steps} control periods: the "
        "controller must reach the goal and stay there. Below, every seed's episodes pooled; "
        f"then the spread over the {len(seeds)} seeds of each seed's median.",
        Table(_summary_table(_ordered(summary[is_policy], order)), STEPS_NOTE),
        Table(spread, "spread over seeds of each seed's median final distance: median, "
                      "quartiles and extremes over seeds"),
        figures["returns"], figures["distance"], figures["trajectories"],
        *(figures[f"after_arrival/{name}"] for name in names
          if f"after_arrival/{name}" in figures)])


def _baselines_section(summary: pd.DataFrame, names: list[str], order: list[str]) -> Section:
    """The baselines' results, and MPC's chatter against the policies' smoothness."""
    is_policy = summary["controller"].isin(names)
    baselines = Section("Baselines", [
        "Preload (do nothing), random safe actions, and sampling-based MPC on the learned model "
        "(offset-corrected on the simulated arm), on the same goals and starts.",
        Table(_summary_table(_ordered(summary[~is_policy], order)), STEPS_NOTE)])
    chatter = _chatter_sentence(summary, names)
    if chatter:
        baselines.add(chatter)
    return baselines


def _gap_section(facts: ReportFacts, plant_gap: pd.DataFrame, order: list[str]) -> Section:
    """The learned model against the simulated arm (``plant_gap`` table), where there is one."""
    gap_section = Section("Plant gap")
    if len(plant_gap):
        gap = plant_gap.groupby("controller").agg(
            median_final_gap_mm=("final_gap_mm", "median"),
            median_position_gap_mm=("final_position_gap_mm", "median")).reset_index()
        gap = _ordered(gap, order).rename(columns={
            "median_final_gap_mm": "median final-distance gap [mm]",
            "median_position_gap_mm": "median final-pose gap [mm]"})
        gap_section.add("The learned model against the simulated arm for the same goals: the "
                        "final distance on the simulated arm minus that on the learned model "
                        "(positive: worse on the arm), and the distance between the two final "
                        "poses.")
        gap_section.add(Table(gap))
    else:
        gap_section.add(f"No plant for robot `{facts.robot_name}`: evaluated on the learned "
                        "model only.")
    return gap_section


def consecutive_table(consecutive: pd.DataFrame, order: list[str] | None = None
                      ) -> pd.DataFrame:
    """One row per (controller, plant), one labelled column per goal (``goal 1 [mm]`` ...)."""
    per_goal = (consecutive.groupby(["controller", "plant", "goal"], sort=False)
                ["median_distance_mm"].median().unstack("goal"))
    per_goal.columns = [f"goal {int(g) + 1} [mm]" for g in per_goal.columns]
    within = consecutive.groupby(["controller", "plant"], sort=False)["success_3mm"].mean()
    table = per_goal.assign(**{"fraction ≤ 3 mm": within}).reset_index()
    table["plant"] = table["plant"].map(_plant_label)
    table = table.rename(columns={"plant": "evaluated on"})
    return _ordered(table, order) if order else table


CROSS_MODEL_COLUMNS = {
    "direction": "direction", "controller": "controller", "plant": "evaluated in",
    "median_final_mm": "median final [mm]", "p90_final_mm": "p90 final [mm]",
    "success_1mm": "final ≤ 1 mm", "success_3mm": "final ≤ 3 mm",
    **HOLD_COLUMNS,
    "seeds_median_within_1mm": "seeds with median ≤ 1 mm", "deployed_seed": "deployed seed",
    "deployed_median_final_mm": "deployed: median [mm]", "deployed_success_1mm": "deployed: ≤ 1 mm",
}


def cross_model_section(summary: pd.DataFrame, order: list[str]) -> Section:
    """The cross-model protocol (``cross_model`` table of evaluate): each direction's policies
    and preload in their own model and in the other group's."""
    groups = summary.drop_duplicates("direction")
    runs = "; ".join(f"{row.direction}: trained in the model of {row.train_runs}, evaluated "
                     f"in that of {row.test_runs}" for row in groups.itertuples())
    shown = pd.concat([_ordered(part, order) for _, part in summary.groupby(
        ["direction", "plant"], sort=False)], ignore_index=True)
    shown = shown.assign(plant=shown["plant"].map({"own": "own model", "cross": "other model"}),
                         deployed_seed=shown["deployed_seed"].astype(object).where(
                             shown["deployed_seed"].notna(), "–"))
    return Section("Across models", [
        "The recordings split into two disjoint groups, each with its own fitted model; every "
        "policy type trained in each group's model, then rolled out on that group's held-out "
        "goals (positions measured on the arm) in its own model and in the model of the other "
        "group, fitted to runs it never saw: the nearest stand-in for the arm here. " + runs
        + ".",
        Table(shown[[c for c in CROSS_MODEL_COLUMNS if c in shown]].rename(
            columns=CROSS_MODEL_COLUMNS),
              "every seed's episodes pooled; 'of those': of the episodes ever within 1 mm "
              "(the hold after the first arrival); 'seeds with median ≤ 1 mm': the share of seeds "
              "whose median final distance is within 1 mm; 'deployed': the seed "
              "stage=control would drive the arm with (the best in its training's last "
              "held-out evaluation)")])
