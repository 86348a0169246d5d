"""Stage ``fit_model``: the recurrent forward-dynamics model on the aligned runs.

The aligned rows (~100 Hz) are resampled to ``dataset.model_hz`` (positions interpolated,
pressures held) and cut into sliding windows (``dataset.window``, ``dataset.stride``,
``dataset.order``). ``dataset.protocol`` decides how the model is scored:

* ``cv`` (the default for recorded data, ``protocol=auto`` with any robot but ``sim``):
  leave-one-run-out cross-validation, every run held out once, all fold models and the model
  trained on all runs (the one later stages use) in one vmapped program
  (:func:`pipeline.dynamics.cv.fit_members`); each fold model is also calibrated on the first
  seconds of its held-out run (:func:`pipeline.dynamics.adaptation.context_metrics`: the
  session-context curve, ``split="cv_context"`` rows);
* ``split`` (the default for the simulated arm, whose default chain it keeps cheap): one seeded
  split of the runs into train and test (``dataset.train_fraction``, ``dataset.split_seed``).

Training checkpoints into a work folder beside the artifact, so an interrupted ``fit_model``
resumes where it stopped when run again with the same config. Whenever the model does not beat
the linear lagged-pressure baseline on a held-out run, a warning is logged and recorded
(``loses_to_linear`` in the metrics, ``warnings`` in the manifest summary).

Runs joined from control sessions (``dataset.sessions``, :mod:`pipeline.data.sessions`) are
drawn ``dataset.session_weight`` times as often as collected ones, and ``model.init_from`` starts
the fit from a fitted model (a warm start); both with the ``split`` protocol.

Artifact: ``model.msgpack`` (weights, normalization and architecture), ``split.json`` (the runs
the model trained on, the held-out runs or, for cv, the folds), ``losses.parquet`` (per step of
the model later stages use), ``metrics.parquet`` (schema ``model_metrics``: per run, fold and
model the mean and p95 open-loop error in mm over the entire run, the learned model next to the
mean-position and linear lagged-pressure baselines fitted on the same runs) and figures: the
EMA-smoothed loss curve and reconstructions of a training and an unseen run.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from pipeline import keys
from pipeline.data.alignment import load_runs
from pipeline.data.runs import Run
from pipeline.data.schemas import MODEL_METRICS, write_table
from pipeline.data.sessions import SESSION_PREFIX
from pipeline.data.windows import split_runs
from pipeline.dynamics import adaptation
from pipeline.dynamics import cv as model_cv
from pipeline.dynamics.checkpoints import load_dynamics, save_dynamics
from pipeline.dynamics.figures import plot_losses, plot_reconstruction
from pipeline.dynamics.scoring import LEARNED, MODELS, evaluation_table
from pipeline.dynamics.training import fit
from pipeline.infra.artifacts import Artifact, ArtifactStore, artifact_key, produce
from pipeline.infra.parquet import table_metadata, write_parquet
from pipeline.infra.tracking import tracking
from pipeline.schemas import ConfigError

log = logging.getLogger(__name__)
STAGE = "fit_model"


def fit_model(cfg: Any) -> Artifact:
    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = keys.fit_model_spec(cfg)
    aligned_artifact = store.require("align", inputs["align"])
    data = cfg.dataset
    key = artifact_key(spec, inputs)
    work_dir = store.root / STAGE / f".work-{key}"  # checkpoints survive an interrupted run
    start = store.resolve(STAGE, str(cfg.model.init_from[0])) if cfg.model.init_from else None
    if spec["dataset"]["protocol"] == "cv" and (start is not None
                                                or "session_weight" in spec["dataset"]):
        raise ConfigError("model.init_from and dataset.session_weight need dataset.protocol="
                          "split (the cv protocol fits every fold afresh, all runs alike)")

    def build(writer):
        if cfg.force and work_dir.exists():
            log.info("fit_model: force=true: training afresh (removing the checkpoints in %s)",
                     work_dir)
            shutil.rmtree(work_dir)
        runs = load_runs(aligned_artifact.file("aligned.parquet"), float(data.model_hz),
                         str(data.model_grid))
        if spec["dataset"]["protocol"] == "cv":
            return build_cv(cfg, writer, runs, work_dir, spec, inputs)
        by_id = {run.run_id: run for run in runs}
        # the split holds out collected runs only: a session's run always trains the model
        sessions = [i for i in by_id if i.startswith(SESSION_PREFIX)]
        train_ids, test_ids = split_runs([i for i in by_id if i not in sessions],
                                         float(data.train_fraction), int(data.split_seed))
        train_ids = [*train_ids, *sessions]
        if not train_ids:
            raise ValueError(f"no training run: {len(runs)} runs with train_fraction="
                             f"{data.train_fraction}")
        train_runs = [by_id[i] for i in train_ids]
        test_runs = [by_id[i] for i in test_ids]
        log.info("fit_model: %d train runs %s, %d test runs %s at %.3g Hz", len(train_ids),
                 train_ids, len(test_ids), test_ids, float(data.model_hz))
        writer.file("split.json").write_text(json.dumps(
            {"train": train_ids, "test": test_ids, "train_fraction": data.train_fraction,
             "split_seed": data.split_seed, "model_hz": data.model_hz}, indent=2))

        weight = float(data.session_weight)
        weights = ([weight if run.run_id.startswith(SESSION_PREFIX) else 1.0
                    for run in train_runs] if weight != 1.0 else None)
        init = None if start is None else load_dynamics(start.file("model.msgpack"))
        params, _, losses = fit(
            train_runs, cfg.model, window=int(data.window), stride=int(data.stride),
            order=str(data.order), val_runs=test_runs, checkpoint_dir=work_dir,
            resume=not cfg.force, run_weights=weights, init=init)
        save_dynamics(writer.file("model.msgpack"), params)
        config, provenance = write_losses(cfg, writer, losses, spec, inputs)

        metrics = evaluation_table(params, train_runs, test_runs)
        metrics["seed"] = int(cfg.model.seed)
        warnings = model_cv.warn_if_losing(metrics)
        write_metrics(writer.file("metrics.parquet"), metrics, config, provenance)
        plot_losses(writer.file("figures/loss.png"), losses)
        shown = [train_runs[0]] + ([test_runs[0]] if test_runs else [])
        plot_reconstruction(writer.file("figures/reconstruction.png"), params, shown,
                            ["training run", "unseen run"])
        held_out = metrics[metrics["split"] == "test"]
        summary_of = held_out if len(held_out) else metrics
        writer.summary = {
            "protocol": "split", "train_runs": train_ids, "test_runs": test_ids,
            "steps": int(losses["step"].max()) if len(losses) else 0,
            **{f"{m}_{k}": float(summary_of.loc[summary_of["model"] == m, k].mean())
               for m in MODELS for k in ("mean_mm", "p95_mm")},
            "warnings": warnings,
        }
        which = ("held-out" if len(held_out) else
                 "training-run (no test run: dataset.train_fraction keeps every run)")
        writer.summary["error_on"] = "test" if len(held_out) else "train"
        log.info("fit_model: %s open-loop error %.2f mm mean, %.2f mm p95 (baselines: mean "
                 "position %.2f mm, linear lagged %.2f mm)", which,
                 writer.summary[f"{LEARNED}_mean_mm"], writer.summary[f"{LEARNED}_p95_mm"],
                 writer.summary["mean_position_mean_mm"],
                 writer.summary["linear_lagged_mean_mm"])

    artifact = produce(store, STAGE, spec, inputs, build, force=cfg.force)
    shutil.rmtree(work_dir, ignore_errors=True)
    return artifact


def build_cv(cfg: Any, writer, runs: list[Run], work_dir: Path, spec: dict,
             inputs: dict) -> None:
    """The ``cv`` protocol: leave-one-run-out folds and the all-runs model, one program."""
    data = cfg.dataset
    ids = sorted(run.run_id for run in runs)
    members = model_cv.cv_members(ids, (int(cfg.model.seed),), final=True)
    log.info("fit_model: leave-one-run-out over %d runs %s at %.3g Hz (%d fold models and the "
             "model on all runs, one program)", len(ids), ids, float(data.model_hz),
             len(members) - 1)
    writer.file("split.json").write_text(json.dumps(
        {"protocol": "cv", "train": ids, "test": [],
         "folds": [{"held_out": m.held_out, "train": list(m.train_ids)}
                   for m in members if m.held_out],
         "model_hz": data.model_hz}, indent=2))
    params, losses = model_cv.fit_members(
        runs, members, OmegaConf.to_object(cfg.model), window=int(data.window), stride=int(data.stride),
        order=str(data.order), checkpoint_dir=work_dir, resume=not cfg.force)
    final = params[-1]
    save_dynamics(writer.file("model.msgpack"), final)
    loss_table = pd.DataFrame({"step": np.arange(1, losses.shape[1] + 1),
                               "train_loss": losses[-1].astype(np.float64)})
    for column in ("val_loss", "val_mean_mm", "val_p95_mm"):
        loss_table[column] = np.nan
    config, provenance = write_losses(cfg, writer, loss_table, spec, inputs)

    metrics = model_cv.cv_metrics(runs, members, params)
    context = adaptation.context_metrics(runs, members, params, adaptation.AdaptationSettings(),
                                         float(data.model_hz))
    if len(context):  # the held-out runs longer than the context and the common rest
        metrics = pd.concat([metrics, context], ignore_index=True)
    curve = adaptation.context_summary(metrics)
    if len(curve):
        log.info("fit_model: session context: each fold model calibrated on the first seconds "
                 "of its held-out run, error [mm] over the rest (linear: refitted on the same "
                 "context)\n%s", curve.to_string(index=False, float_format="{:.2f}".format))
    warnings = model_cv.warn_if_losing(metrics)
    write_metrics(writer.file("metrics.parquet"), metrics, config, provenance)
    table = model_cv.cv_summary(metrics)
    log.info("fit_model: leave-one-run-out open-loop error [mm] (mean / p95; baselines fitted "
             "on the same folds)\n%s", table.to_string(index=False, float_format="%.2f"))
    plot_losses(writer.file("figures/loss.png"), loss_table)
    by_id = {run.run_id: run for run in runs}
    first_fold = members[0]
    plot_reconstruction(writer.file("figures/reconstruction.png"), [final, params[0]],
                        [by_id[ids[-1]], by_id[first_fold.held_out]],
                        ["training run (model on all runs)", "held-out run (its fold model)"])
    average = table[table["run_id"] == "average"].iloc[0]
    writer.summary = {
        "protocol": "cv", "train_runs": ids, "test_runs": [],
        "folds": [m.held_out for m in members if m.held_out],
        "steps": int(losses.shape[1]),
        **{f"{m}_{k}": float(average[f"{m}_{k}"])
           for m in MODELS for k in ("mean_mm", "p95_mm")},
        "train_runs_mean_mm": float(average["train_runs_mean_mm"]),
        "session_context_mm": {f"{row.context_s:g}": float(row.learned_mean_mm)
                               for row in curve.itertuples()},
        "warnings": warnings,
    }
    log.info("fit_model: leave-one-run-out open-loop error %.2f mm mean, %.2f mm p95 "
             "(baselines: mean position %.2f mm, linear lagged %.2f mm; fold models on their "
             "training runs %.2f mm)", writer.summary[f"{LEARNED}_mean_mm"],
             writer.summary[f"{LEARNED}_p95_mm"], writer.summary["mean_position_mean_mm"],
             writer.summary["linear_lagged_mean_mm"], writer.summary["train_runs_mean_mm"])


def write_losses(cfg: Any, writer, losses: pd.DataFrame, spec: dict, inputs: dict
                 ) -> tuple[dict, dict]:
    """``losses.parquet`` (with units, config, provenance) and the tracker; returns the
    ``(config, provenance)`` every table of this artifact carries."""
    config = {"model": spec["model"], "dataset": spec["dataset"]}
    provenance = {"stage": STAGE, "inputs": inputs}
    write_parquet(losses, writer.file("losses.parquet"), table_metadata(
        losses, "losses", config, provenance,
        {"train_loss": "normalized MSE", "val_loss": "normalized MSE", "step": "step"}))
    with tracking(OmegaConf.to_object(cfg.logger), Path(cfg.paths.output_dir), STAGE,
                  OmegaConf.to_container(cfg, resolve=True)) as tracker:
        tracker.log_table(losses)
    return config, provenance


def write_metrics(path: Path, metrics: pd.DataFrame, config: dict, provenance: dict) -> Path:
    """``metrics.parquet`` through the schema writer (units and config in its metadata)."""
    return write_table(metrics, path, MODEL_METRICS, config=config, provenance=provenance)
