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
  robot config or of a calibrate artifact, started from the learned env's rest poses);
- a **consecutive-goals** task: ``num_consecutive_goals`` targets one after another, no reset;
- on recorded data, the **cross-model protocol** (``evaluation.cross_model``,
  :mod:`pipeline.evaluation.cross_model`): each group of runs' policies in their own model and in
  the model of the other, disjoint group (``cross_model.parquet``, ``cross_model_episodes.parquet``).

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
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline import chain, keys
from pipeline.dynamics.checkpoints import load_dynamics
from pipeline.evaluation.closed_loop import run_evaluation
from pipeline.evaluation.cross_model import CROSS, across_models, cross_model_episodes
from pipeline.evaluation.figures import make_figures
from pipeline.evaluation.report import write_report
from pipeline.evaluation.sections import report_sections
from pipeline.infra.artifacts import Artifact, ArtifactStore, produce
from pipeline.infra.parquet import table_metadata, write_parquet
from pipeline.rl.policy_io import best_seed
from pipeline.schemas import EnvName
from pipeline.stages._environment import config_environment

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

    other_models = {f"model {Path(str(entry)).name}": store.resolve("fit_model", str(entry))
                    for entry in cfg.evaluation.models}
    folds = _cross_model_inputs(cfg, store, inputs)

    def build(writer):
        started = time.perf_counter()
        env, _, eval_params = config_environment(cfg, upstream["model"], upstream["aligned"])
        models = {name: load_dynamics(artifact.file("model.msgpack"))
                  for name, artifact in other_models.items()}
        twins = {f"twin {name}": physics
                 for name, physics in spec["evaluation"].get("twins", {}).items()}
        results = run_evaluation(cfg, policies, env, eval_params, models, twins)
        if folds:
            _cross_model(folds, results)
        config = {"evaluation": spec["evaluation"], "env": spec["env"]}
        for name, frame in results["tables"].items():
            write_parquet(frame, writer.file(f"{name}.parquet"),
                          table_metadata(frame, name, config, {"stage": STAGE, "inputs": inputs}))
        figures = make_figures(writer.path / "figures", cfg, policies, results)
        sections = report_sections(cfg, policies, results, figures, **upstream,
                                   evaluate_seconds=time.perf_counter() - started)
        write_report(writer.path, f"sorolearn run: robot={cfg.robot.name}", sections)
        writer.summary = results["headline"]
        log.info("evaluate: %s", json.dumps(results["headline"]))

    artifact = produce(store, STAGE, spec, inputs, build, force=cfg.force)
    log.info("evaluate: report at %s", artifact.file("report.html"))
    return artifact


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
            "other": store.require("fit_model", inputs[f"{prefix}/fit_model"], hint=hint)}
    return folds


def _cross_model(folds: dict[str, dict[str, Any]], results: dict[str, Any]) -> None:
    """Both directions of the cross-model protocol into ``results``: the tables
    ``cross_model_episodes`` and ``cross_model`` (per direction, plant and controller) and the
    headline's ``cross_model/<direction>/<controller>`` figures."""
    episodes, summaries = [], []
    for direction, fold in folds.items():
        env, _, eval_params = config_environment(fold["cfg"], fold["model"], fold["aligned"])
        other = load_dynamics(fold["other"].file("model.msgpack"))
        rows = cross_model_episodes(fold["cfg"], fold["policies"], env, eval_params, other)
        labels = {"direction": direction, "train_runs": "+".join(fold["cfg"].robot.files),
                  "test_runs": "+".join(fold["test_runs"])}
        deployed = {name: best_seed(artifact) for name, artifact in fold["policies"].items()}
        episodes.append(rows.assign(**labels))
        summaries.append(across_models(rows, deployed).assign(**labels))
    summary = pd.concat(summaries, ignore_index=True)
    results["tables"]["cross_model_episodes"] = pd.concat(episodes, ignore_index=True)
    results["tables"]["cross_model"] = summary
    for row in summary[summary["plant"] == CROSS].itertuples():
        results["headline"][f"cross_model/{row.direction}/{row.controller}"] = {
            "median_final_mm": float(row.median_final_mm),
            "success_1mm": float(row.success_1mm), "success_3mm": float(row.success_3mm),
            "held_arrivals": float(row.held_arrivals)}
