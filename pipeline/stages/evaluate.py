"""Stage ``evaluate``: closed-loop results on the learned model and on the plant, and the report
(:mod:`pipeline.evaluation`).

For every policy type in ``evaluation.policies`` (all seeds) and every baseline (``preload``: do
nothing; ``random``: random safe actions; ``mpc``: sampling-based MPC on the learned model, see
:mod:`pipeline.evaluation.mpc`), on the same held-out goals and start states:

- on the **learned environment** (the fitted model the policies were trained in);
- on the **plant**: the simulated arm for ``robot=sim`` (its own hysteresis, creep and rest-pose
  spread; the model never saw its equations), with the policies observing it through the same
  normalization they were trained with;
- on **calibrated twins** (``evaluation.twins``: the simulated arm with the physics of a simulated
  robot config or of a calibrate artifact, started where its physics rest it at the preload);
- a **consecutive-goals** task: ``num_consecutive_goals`` targets one after another, no reset;
- for ``env.task=track``, **tracking** (:mod:`pipeline.evaluation.tracking`): every policy, the
  baselines of ``evaluation.tracking_baselines`` (the preload; sampling MPC on the learned model
  scored against the reference over its horizon) and (``evaluation.reaching``) the reaching
  policies of the same settings fed the moving goal follow ``evaluation.references`` on every
  plant (``tracking.parquet``, ``tracking_episodes.parquet``, the first episodes' paths in
  ``tracking_paths.parquet``, the report's "Tracking" section);
- on recorded data, the **cross-model protocol** (``evaluation.cross_model``,
  :mod:`pipeline.evaluation.cross_model`): each group of runs' policies in their own model and in
  the model of the other, disjoint group (``cross_model.parquet``, ``cross_model_episodes.parquet``;
  for ``env.task=track`` also following the references, with the baselines of the group,
  ``cross_model_tracking.parquet``, ``cross_model_tracking_episodes.parquet``).

Episodes last ``env.max_steps`` control periods and, unlike in training, do not end when the goal is
first within ``env.goal_tolerance_m``: on an arm the controller has to get there and stay, so the
final distance is the distance after the last period (``steps_to_*`` tells when it first got
within 1 and 3 mm). Passing near a goal by chance, as random actions do, does not count. Tables (Parquet): one row
per episode (``episodes.parquet``), the summary per controller and plant (``summary.parquet``),
the learned-vs-plant gap per episode (``plant_gap.parquet``) and the consecutive-goals results.
Figures and ``report.md`` / ``report.html`` close the run.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd
from omegaconf import OmegaConf

from pipeline import chain, keys
from pipeline.arm.references import reference_settings
from pipeline.dynamics.checkpoints import load_dynamics
from pipeline.evaluation.closed_loop import ClosedLoopSettings, Policy, SimArm, run_evaluation
from pipeline.evaluation.cross_model import CROSS, across_models, cross_model_episodes
from pipeline.evaluation.figures import FigureSettings, make_figures
from pipeline.evaluation.reachability import with_reach
from pipeline.evaluation.report import write_report
from pipeline.evaluation.sections import (
    COLLECT_FIGURES,
    MODEL_FIGURES,
    ReportFacts,
    report_sections,
)
from pipeline.evaluation.tracking import (
    Reaching,
    TrackingSettings,
    cross_model_tracking,
    run_tracking,
    summarize_tracking,
)
from pipeline.infra.artifacts import Artifact, ArtifactStore, produce
from pipeline.infra.parquet import table_metadata, write_parquet
from pipeline.infra.records import ArtifactRecord, artifact_record
from pipeline.rl.envs.factory import sim_plant_params
from pipeline.rl.policy_io import best_seed, load_policy
from pipeline.rl.results import return_curves
from pipeline.schemas import EnvName, RobotKind, Task
from pipeline.stages._environment import (
    config_inputs,
    env_settings,
    environment_of,
    recorded_paths,
)

log = logging.getLogger(__name__)
STAGE = "evaluate"


def evaluate(cfg: Any) -> Artifact:
    """Evaluate the trained policies of this config (every type in ``evaluation.policies``)."""
    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = keys.evaluate_spec(cfg)
    policies = {name: store.require("train_ppo", inputs[f"train_ppo/{name}"],
                                    hint=f" with agent={name}")
                for name in cfg.evaluation.policies}
    upstream = {"collect": None, "aligned": None, "model": None}
    if EnvName(cfg.env.name) is not EnvName.gymnax:
        upstream = {"collect": store.find("collect", keys.key("collect", cfg)),
                    "aligned": store.find("align", keys.key("align", cfg)),
                    "model": store.find("fit_model", keys.key("fit_model", cfg))}

    reaching = {name: store.require("train_ppo", inputs[f"reaching/train_ppo/{name}"],
                                    hint=f" with agent={name} env.task=reach env.preview=0")
                for name in chain.reaching_configs(cfg)}
    other_models = {f"model {Path(str(entry)).name}": store.resolve("fit_model", str(entry))
                    for entry in cfg.evaluation.models}
    folds = _cross_model_inputs(cfg, store, inputs)

    def build(writer):
        started = time.perf_counter()
        inputs = config_inputs(cfg, upstream["model"], upstream["aligned"])
        env, _, eval_params = environment_of(cfg, inputs)
        models = {name: load_dynamics(artifact.file("model.msgpack"))
                  for name, artifact in other_models.items()}
        twins = {f"twin {name}": physics
                 for name, physics in spec["evaluation"].get("twins", {}).items()}
        loaded = _load_policies(policies)
        results = with_reach(run_evaluation(closed_loop_settings(cfg), loaded, env, eval_params,
                                            models, twins), cfg.evaluation.reach)
        if Task(cfg.env.task) is Task.track:
            tracking = tracking_settings(cfg, recorded_paths(inputs))
            tracked = run_tracking(closed_loop_settings(cfg), tracking, loaded, env, eval_params,
                                   models, twins, _reaching(cfg, reaching))
            results["tables"].update(tracked["tables"])
            results["headline"].update(tracked["headline"])
            results["tracking"] = tracked
        if folds:
            _cross_model(folds, results)
        config = {"evaluation": spec["evaluation"], "env": spec["env"]}
        for name, frame in results["tables"].items():
            write_parquet(frame, writer.file(f"{name}.parquet"),
                          table_metadata(frame, name, config, {"stage": STAGE, "inputs": inputs}))
        _report(cfg, writer.path, policies, upstream, results, started)
        writer.summary = results["headline"]
        log.info("evaluate: %s", json.dumps(results["headline"]))

    artifact = produce(store, STAGE, spec, inputs, build, force=cfg.force)
    log.info("evaluate: report at %s", artifact.file("report.html"))
    return artifact


def closed_loop_settings(cfg: Any) -> ClosedLoopSettings:
    """The closed-loop evaluation's settings of ``cfg``: its evaluation, the env's episode
    length, observation and shared parameters as the training env's, the robot's limits, and
    the simulated arm as the plant for ``robot=sim`` with ``evaluation.plant``."""
    evaluation = OmegaConf.to_object(cfg.evaluation)
    sim = None
    if RobotKind(cfg.robot.kind) is RobotKind.sim and evaluation.plant:
        sim = SimArm(sim_plant_params(OmegaConf.to_object(cfg.robot)),
                     float(cfg.robot.mocap.rate_hz),
                     list(cfg.robot.physics.rest_pose_std_m))
    return ClosedLoopSettings(
        evaluation=evaluation, max_steps=int(cfg.env.max_steps),
        model_hz=float(cfg.dataset.model_hz), limits=OmegaConf.to_object(cfg.robot.limits),
        env=env_settings(cfg), sim=sim)


def tracking_settings(cfg: Any, recorded: Mapping[str, tuple[Any, Any]] | None = None
                      ) -> TrackingSettings:
    """The tracking evaluation's settings of ``cfg.evaluation`` (its references as shapes or
    replayed paths); a replayed path without a CSV replays ``recorded``, the measured paths of
    the runs ``cfg``'s goals come from (:func:`~pipeline.stages._environment.recorded_paths`)."""
    evaluation = cfg.evaluation
    shapes = {str(name): reference_settings(
        OmegaConf.to_container(entry, resolve=True) if entry is not None else None,
        f"evaluation.references.{name}") for name, entry in evaluation.references.items()}
    horizon = evaluation.get("tracking_mpc_horizon")
    return TrackingSettings(shapes, float(evaluation.tracking_seconds),
                            float(evaluation.tracking_settle_seconds),
                            float(evaluation.reachable_tolerance_mm),
                            tuple(str(name) for name in evaluation.tracking_baselines),
                            None if horizon is None else int(horizon),
                            bool(evaluation.tracking_mpc_per_period),
                            float(evaluation.tracking_mpc_std_kpa),
                            dict(recorded or {}))


def _reaching(cfg: Any, policies: dict[str, Artifact]) -> Reaching:
    """The reaching baseline of ``cfg``'s tracking evaluation: the reaching policies
    (``policies``, train_ppo artifacts by policy type; none without ``evaluation.reaching``) with
    the env settings they were trained with."""
    configs = chain.reaching_configs(cfg)
    return Reaching(env_settings(next(iter(configs.values()))) if policies else None,
                    _load_policies(policies))


def _load_policies(policies: dict[str, Artifact]) -> dict[str, Policy]:
    """Each train_ppo artifact's policies (``policy.msgpack``, every seed) by policy type."""
    return {name: Policy(*load_policy(artifact.file("policy.msgpack"))[:2])
            for name, artifact in policies.items()}


def _report(cfg: Any, folder: Path, policies: dict[str, Artifact],
            upstream: dict[str, Artifact | None], results: dict[str, Any],
            started: float) -> None:
    """The figures and ``report.md`` / ``report.html`` into ``folder``, from ``results`` and
    what the upstream artifacts and the policies' training recorded; ``started``: when the
    evaluation began (``time.perf_counter``)."""
    records = {name: artifact_record(artifact, tables=("metrics",))
               for name, artifact in policies.items()}
    curves = {name: return_curves(record.tables["metrics"]) for name, record in records.items()}
    figures = make_figures(folder / "figures", FigureSettings(
        max_steps=int(cfg.env.max_steps), control_hz=float(cfg.robot.control_hz),
        goal_tolerance_m=float(cfg.env.goal_tolerance_m)), curves, results)
    reads = {"collect": {"figures": tuple(COLLECT_FIGURES)}, "aligned": {},
             "model": {"figures": MODEL_FIGURES, "tables": ("metrics",)}}
    loaded: dict[str, ArtifactRecord | None] = {
        name: None if artifact is None else artifact_record(artifact, **reads[name])
        for name, artifact in upstream.items()}
    facts = ReportFacts(
        robot_name=str(cfg.robot.name), exploration_alpha=cfg.exploration.alpha,
        exploration_beta=cfg.exploration.beta, p_max_kpa=cfg.exploration.p_max,
        model_hidden=cfg.model.hidden, model_hz=cfg.dataset.model_hz,
        policies=tuple(cfg.evaluation.policies), baselines=tuple(cfg.evaluation.baselines),
        max_steps=int(cfg.env.max_steps),
        num_consecutive_goals=int(cfg.evaluation.num_consecutive_goals),
        config_yaml=OmegaConf.to_yaml(cfg, resolve=True))
    sections = report_sections(facts, records, results, figures, **loaded,
                               evaluate_seconds=time.perf_counter() - started)
    write_report(folder, f"sorolearn run: robot={cfg.robot.name}", sections)


def _cross_model_inputs(cfg: Any, store: ArtifactStore, inputs: dict[str, str]
                        ) -> dict[str, dict[str, Any]]:
    """The cross-model protocol's artifacts by direction (empty where it does not run): the
    training group's config, policies, model and aligned data, and the other group's model."""
    folds = {}
    for direction, (train, test) in chain.cross_model_folds(cfg).items():
        prefix = f"cross_model/{direction}"
        hint = f" (the cross-model group {direction[0]}: robot.files={list(train.robot.files)})"
        folds[direction] = {
            "cfg": train, "test_runs": list(test.robot.files),
            "policies": {name: store.require("train_ppo", inputs[f"{prefix}/train_ppo/{name}"],
                                             hint=f" with agent={name}{hint}")
                         for name in cfg.evaluation.policies},
            "model": store.require("fit_model", keys.key("fit_model", train), hint=hint),
            "aligned": store.require("align", keys.key("align", train), hint=hint),
            "other": store.require("fit_model", inputs[f"{prefix}/fit_model"], hint=hint),
            "reaching": {name: store.require(
                "train_ppo", inputs[f"{prefix}/reaching/train_ppo/{name}"],
                hint=f" with agent={name} env.task=reach env.preview=0{hint}")
                for name in chain.reaching_configs(train)}}
    return folds


def _cross_model(folds: dict[str, dict[str, Any]], results: dict[str, Any]) -> None:
    """Both directions of the cross-model protocol into ``results``: the tables
    ``cross_model_episodes`` and ``cross_model`` (per direction, plant and controller) and the
    headline's ``cross_model/<direction>/<controller>`` figures; for ``env.task=track`` also the
    tracking evaluation's (:func:`_cross_model_tracking`)."""
    episodes, summaries, tracked = [], [], []
    for direction, fold in folds.items():
        train = fold["cfg"]
        inputs = config_inputs(train, fold["model"], fold["aligned"])
        env, _, eval_params = environment_of(train, inputs)
        other = load_dynamics(fold["other"].file("model.msgpack"))
        settings, policies = closed_loop_settings(train), _load_policies(fold["policies"])
        rows = cross_model_episodes(settings, policies, env, eval_params, other)
        labels = {"direction": direction, "train_runs": "+".join(train.robot.files),
                  "test_runs": "+".join(fold["test_runs"])}
        deployed = {name: _deployed_seed(artifact) for name, artifact in fold["policies"].items()}
        episodes.append(rows.assign(**labels))
        summaries.append(across_models(rows, deployed).assign(**labels))
        if Task(train.env.task) is Task.track:
            tracked.append(cross_model_tracking(
                settings, tracking_settings(train, recorded_paths(inputs)), policies, env,
                eval_params, other,
                _reaching(train, fold["reaching"])).assign(**labels))
    summary = pd.concat(summaries, ignore_index=True)
    results["tables"]["cross_model_episodes"] = pd.concat(episodes, ignore_index=True)
    results["tables"]["cross_model"] = summary
    for row in summary[summary["plant"] == CROSS].itertuples():
        results["headline"][f"cross_model/{row.direction}/{row.controller}"] = {
            "median_final_mm": float(row.median_final_mm),
            "success_1mm": float(row.success_1mm), "success_3mm": float(row.success_3mm),
            "held_arrivals": float(row.held_arrivals)}
    if tracked:
        _cross_model_tracking(pd.concat(tracked, ignore_index=True), results)


def _cross_model_tracking(episodes: pd.DataFrame, results: dict[str, Any]) -> None:
    """The cross-model tracking episodes (both directions) into ``results``: the tables
    ``cross_model_tracking_episodes`` and ``cross_model_tracking`` (medians per direction,
    plant, controller and reference) and the headline's
    ``cross_model_tracking/<direction>/<controller>/<reference>`` figures (in the other model)."""
    summary = summarize_tracking(episodes, ("direction", "plant", "controller", "reference"))
    results["tables"]["cross_model_tracking_episodes"] = episodes
    results["tables"]["cross_model_tracking"] = summary
    for row in summary[summary["plant"] == CROSS].itertuples():
        results["headline"][f"cross_model_tracking/{row.direction}/{row.controller}/"
                            f"{row.reference}"] = {"median_rmse_mm": float(row.median_rmse_mm),
                                                   "median_lag_s": float(row.median_lag_s)}


def _deployed_seed(policy: Artifact) -> int:
    """The seed ``stage=control`` drives the arm with: the best in the training's last held-out
    evaluation (``evaluation.parquet``)."""
    path = policy.file("evaluation.parquet")
    return best_seed(pd.read_parquet(path), path)
