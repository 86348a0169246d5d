"""Stage ``evaluate``: closed-loop results on the learned model and on the plant, and the report
(:mod:`pipeline.evaluation`).

For every policy type in ``evaluation.policies`` (all seeds) and every baseline (``preload``: do
nothing; ``random``: random safe actions; ``mpc``: sampling-based MPC on the learned model, see
:mod:`pipeline.evaluation.mpc`), on the same held-out goals and start states:

- on the **learned environment** (the fitted model the policies were trained in);
- on the **plant**: the simulated arm for ``robot=sim`` (its own hysteresis, creep and rest-pose
  spread; the model never saw its equations), with the policies observing it through the same
  normalization they were trained with;
- a **consecutive-goals** task: ``num_consecutive_goals`` targets one after another, no reset.

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

from pipeline import keys
from pipeline.config import EnvName
from pipeline.dynamics.training import load_dynamics
from pipeline.evaluation.closed_loop import run_evaluation
from pipeline.evaluation.figures import make_figures
from pipeline.evaluation.report import write_report
from pipeline.evaluation.sections import report_sections
from pipeline.infra.artifacts import Artifact, ArtifactStore, produce
from pipeline.infra.parquet import table_metadata, write_parquet
from pipeline.rl.envs.factory import environment

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

    def build(writer):
        started = time.perf_counter()
        env, _, eval_params = environment(cfg, upstream["model"], upstream["aligned"])
        models = {name: load_dynamics(artifact.file("model.msgpack"))
                  for name, artifact in other_models.items()}
        results = run_evaluation(cfg, policies, env, eval_params, models)
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
