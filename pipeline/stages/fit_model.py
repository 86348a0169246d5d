"""Stage ``fit_model``: the LSTM forward-dynamics model on the aligned runs.

The aligned rows (~100 Hz) are resampled to ``dataset.model_hz`` (positions interpolated,
pressures held), split by run into train and test (``dataset.train_fraction``, seeded, recorded in
the artifact) and cut into sliding windows (``dataset.window``, ``dataset.stride``, ``dataset.order``).
Training (:func:`pipeline.dynamics.training.fit`) checkpoints into a work folder beside the artifact,
so an interrupted ``fit_model`` resumes where it stopped when run again with the same config.

Artifact: ``model.msgpack`` (weights, normalization and architecture), ``split.json``,
``losses.parquet`` (per step), ``metrics.parquet`` (per held-out run: mean and p95 open-loop error
in mm over the entire run, next to the mean-position and linear lagged-pressure baselines), and
figures: the EMA-smoothed loss curve and reconstructions of a training and an unseen run.
"""

from __future__ import annotations

import json
import logging
import shutil
from typing import Any

from pipeline import keys
from pipeline.data.alignment import runs_at_model_rate
from pipeline.data.schemas import ALIGNED, read_table
from pipeline.data.windows import split_runs
from pipeline.dynamics.figures import plot_losses, plot_reconstruction
from pipeline.dynamics.training import evaluation_table, fit, save_dynamics
from pipeline.infra.artifacts import Artifact, ArtifactStore, artifact_key, produce
from pipeline.infra.parquet import table_metadata, write_parquet
from pipeline.infra.tracking import tracking

log = logging.getLogger(__name__)
STAGE = "fit_model"


def fit_model(cfg: Any) -> Artifact:
    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = keys.fit_model_spec(cfg)
    aligned_artifact = store.require("align", inputs["align"])
    data = cfg.dataset
    key = artifact_key(spec, inputs)
    work_dir = store.root / STAGE / f".work-{key}"  # checkpoints survive an interrupted run

    def build(writer):
        if cfg.force and work_dir.exists():
            log.info("fit_model: force=true: training afresh (removing the checkpoints in %s)",
                     work_dir)
            shutil.rmtree(work_dir)
        aligned, _ = read_table(aligned_artifact.file("aligned.parquet"), ALIGNED)
        runs = runs_at_model_rate(aligned, float(data.model_hz), str(data.model_grid))
        by_id = {run["run_id"]: run for run in runs}
        train_ids, test_ids = split_runs(list(by_id), float(data.train_fraction),
                                         int(data.split_seed))
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

        params, _, losses = fit(
            train_runs, cfg.model, window=int(data.window), stride=int(data.stride),
            order=str(data.order), val_runs=test_runs, checkpoint_dir=work_dir,
            resume=not cfg.force)
        save_dynamics(writer.file("model.msgpack"), params)
        config = {"model": spec["model"], "dataset": spec["dataset"]}
        provenance = {"stage": STAGE, "inputs": inputs}
        write_parquet(losses, writer.file("losses.parquet"), table_metadata(
            losses, "losses", config, provenance,
            {"train_loss": "normalized MSE", "val_loss": "normalized MSE", "step": "step"}))
        with tracking(cfg, STAGE) as tracker:
            tracker.log_table(losses)

        metrics = evaluation_table(params, train_runs, test_runs)
        write_parquet(metrics, writer.file("metrics.parquet"), table_metadata(
            metrics, "model_metrics", config, provenance, {"steps": "model steps"}))
        plot_losses(writer.file("figures/loss.png"), losses)
        shown = [train_runs[0]] + ([test_runs[0]] if test_runs else [])
        plot_reconstruction(writer.file("figures/reconstruction.png"), params, shown,
                            ["training run", "unseen run"])
        held_out = metrics[metrics["split"] == "test"]
        summary_of = held_out if len(held_out) else metrics
        writer.summary = {
            "train_runs": train_ids, "test_runs": test_ids,
            "steps": int(losses["step"].max()) if len(losses) else 0,
            **{f"{m}_{k}": float(summary_of.loc[summary_of["model"] == m, k].mean())
               for m in ("lstm", "mean_position", "linear_lagged") for k in ("mean_mm", "p95_mm")},
        }
        which = ("held-out" if len(held_out) else
                 "training-run (no test run: dataset.train_fraction keeps every run)")
        writer.summary["error_on"] = "test" if len(held_out) else "train"
        log.info("fit_model: %s open-loop error %.2f mm mean, %.2f mm p95 (baselines: mean "
                 "position %.2f mm, linear lagged %.2f mm)", which, writer.summary["lstm_mean_mm"],
                 writer.summary["lstm_p95_mm"], writer.summary["mean_position_mean_mm"],
                 writer.summary["linear_lagged_mean_mm"])

    artifact = produce(store, STAGE, spec, inputs, build, force=cfg.force)
    shutil.rmtree(work_dir, ignore_errors=True)
    return artifact
