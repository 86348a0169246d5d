"""Stage ``fit_model``: the LSTM forward-dynamics model on the aligned runs.

The aligned rows (~100 Hz) are resampled to ``dataset.model_hz`` (positions interpolated,
pressures held) and cut into sliding windows (``dataset.window``, ``dataset.stride``,
``dataset.order``). ``dataset.protocol`` decides how the model is scored:

* ``cv`` (the default for recorded data, ``protocol=auto`` with any robot but ``sim``):
  leave-one-run-out cross-validation, every run held out once, all fold models and the model
  trained on all runs (the one later stages use) in one vmapped program
  (:func:`pipeline.model_cv.fit_members`);
* ``split`` (the default for the simulated arm, whose default chain it keeps cheap): one seeded
  split of the runs into train and test (``dataset.train_fraction``, ``dataset.split_seed``).

Training checkpoints into a work folder beside the artifact, so an interrupted ``fit_model``
resumes where it stopped when run again with the same config. Whenever the model does not beat
the linear lagged-pressure baseline on a held-out run, a warning is logged and recorded
(``loses_to_linear`` in the metrics, ``warnings`` in the manifest summary).

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

from pipeline import align as align_stage
from pipeline import model_cv
from pipeline.artifacts import Artifact, ArtifactStore, artifact_key, produce
from pipeline.config import ModelProtocol, RobotKind
from pipeline.schemas import ALIGNED, MODEL_METRICS, P_COLUMNS, XYZ, read_table, write_table
from pipeline.tracking import tracking
from pipeline.train_model import (
    baseline_linear_lagged,
    baseline_mean_position,
    evaluate_open_loop,
    fit,
    load_dynamics,
    predict_run,
    save_dynamics,
)
from pipeline.windows import split_runs

log = logging.getLogger(__name__)
STAGE = "fit_model"
DATASET_KEYS = ("model_hz", "model_grid", "window", "stride", "order")
SPLIT_KEYS = ("train_fraction", "split_seed")


def protocol(cfg: Any) -> str:
    """``cv`` or ``split``: ``dataset.protocol``, with ``auto`` resolved by the robot (split for
    the simulated arm, cv for recorded data)."""
    value = ModelProtocol(getattr(cfg.dataset.protocol, "value", cfg.dataset.protocol))
    if value is ModelProtocol.auto:
        simulated = RobotKind(getattr(cfg.robot.kind, "value", cfg.robot.kind)) is RobotKind.sim
        value = ModelProtocol.split if simulated else ModelProtocol.cv
    return value.value


def fit_model_spec(cfg: Any) -> tuple[dict[str, Any], dict[str, str]]:
    dataset = OmegaConf.to_container(cfg.dataset, resolve=True)
    chosen = protocol(cfg)
    keys = DATASET_KEYS + (SPLIT_KEYS if chosen == "split" else ())
    spec = {
        "model": OmegaConf.to_container(cfg.model, resolve=True),
        "dataset": {**{k: dataset[k] for k in keys}, "protocol": chosen},
    }
    return spec, {"align": align_stage.align_key(cfg)}


def fit_model_key(cfg: Any) -> str:
    return artifact_key(*fit_model_spec(cfg))


def runs_at_model_rate(aligned: pd.DataFrame, model_hz: float, grid: str = "clock"
                       ) -> list[dict[str, Any]]:
    """Aligned rows as the model's runs: ``{run_id, t [T], p [T, 3] kPa, pos [T, 3] m}``.

    ``grid``: ``clock`` (a regular grid) or ``commands`` (locked to the command times, see
    :func:`pipeline.align.resample_command_locked`).
    """
    if grid == "clock":
        resampled = align_stage.resample(aligned, model_hz)
    elif grid == "commands":
        resampled = align_stage.resample_command_locked(aligned, model_hz)
    else:
        raise ValueError(f"dataset.model_grid must be clock or commands, got {grid!r}")
    return [
        {
            "run_id": str(run_id),
            "t": run["t"].to_numpy(np.float64),
            "p": run[P_COLUMNS].to_numpy(np.float32),
            "pos": run[XYZ].to_numpy(np.float32),
        }
        for run_id, run in resampled.groupby("run_id", sort=True)
    ]


def load_model(artifact: Artifact):
    """The fitted :class:`pipeline.dynamics.DynamicsParams` of a fit_model artifact."""
    return load_dynamics(artifact.file("model.msgpack"))


def fit_model(cfg: Any) -> Artifact:
    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = fit_model_spec(cfg)
    aligned_artifact = store.require("align", inputs["align"])
    data = cfg.dataset
    key = artifact_key(spec, inputs)
    work_dir = store.root / STAGE / f".work-{key}"  # checkpoints survive an interrupted run

    def build(writer):
        aligned, _ = read_table(aligned_artifact.file("aligned.parquet"), ALIGNED)
        runs = runs_at_model_rate(aligned, float(data.model_hz), str(data.model_grid))
        if spec["dataset"]["protocol"] == "cv":
            return build_cv(cfg, writer, runs, work_dir, spec)
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
            order=str(data.order), val_runs=test_runs, checkpoint_dir=work_dir, resume=True)
        save_dynamics(writer.file("model.msgpack"), params)
        losses.to_parquet(writer.file("losses.parquet"), index=False)
        with tracking(cfg, STAGE) as tracker:
            tracker.log_table(losses)

        metrics = evaluation_table(params, train_runs, test_runs)
        metrics["seed"] = int(cfg.model.seed)
        warnings = model_cv.warn_if_losing(metrics)
        write_metrics(writer.file("metrics.parquet"), metrics, spec)
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
               for m in ("lstm", "mean_position", "linear_lagged") for k in ("mean_mm", "p95_mm")},
            "warnings": warnings,
        }
        log.info("fit_model: held-out open-loop error %.2f mm mean, %.2f mm p95 (baselines: mean "
                 "position %.2f mm, linear lagged %.2f mm)", writer.summary["lstm_mean_mm"],
                 writer.summary["lstm_p95_mm"], writer.summary["mean_position_mean_mm"],
                 writer.summary["linear_lagged_mean_mm"])

    artifact = produce(store, STAGE, spec, inputs, build, force=cfg.force)
    shutil.rmtree(work_dir, ignore_errors=True)
    return artifact


def build_cv(cfg: Any, writer, runs: list[dict], work_dir: Path, spec: dict) -> None:
    """The ``cv`` protocol: leave-one-run-out folds and the all-runs model, one program."""
    data = cfg.dataset
    ids = sorted(run["run_id"] for run in runs)
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
        runs, members, cfg.model, window=int(data.window), stride=int(data.stride),
        order=str(data.order), checkpoint_dir=work_dir, resume=True)
    final = params[-1]
    save_dynamics(writer.file("model.msgpack"), final)
    loss_table = pd.DataFrame({"step": np.arange(1, losses.shape[1] + 1),
                               "train_loss": losses[-1].astype(np.float64)})
    for column in ("val_loss", "val_mean_mm", "val_p95_mm"):
        loss_table[column] = np.nan
    loss_table.to_parquet(writer.file("losses.parquet"), index=False)
    with tracking(cfg, STAGE) as tracker:
        tracker.log_table(loss_table)

    metrics = model_cv.cv_metrics(runs, members, params)
    warnings = model_cv.warn_if_losing(metrics)
    write_metrics(writer.file("metrics.parquet"), metrics, spec)
    table = model_cv.cv_summary(metrics)
    log.info("fit_model: leave-one-run-out open-loop error [mm] (mean / p95; baselines fitted "
             "on the same folds)\n%s", table.to_string(index=False, float_format="%.2f"))
    plot_losses(writer.file("figures/loss.png"), loss_table)
    by_id = {run["run_id"]: run for run in runs}
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
           for m in model_cv.MODELS for k in ("mean_mm", "p95_mm")},
        "train_runs_mean_mm": float(average["train_runs_mean_mm"]),
        "warnings": warnings,
    }
    log.info("fit_model: leave-one-run-out open-loop error %.2f mm mean, %.2f mm p95 "
             "(baselines: mean position %.2f mm, linear lagged %.2f mm; fold models on their "
             "training runs %.2f mm)", writer.summary["lstm_mean_mm"],
             writer.summary["lstm_p95_mm"], writer.summary["mean_position_mean_mm"],
             writer.summary["linear_lagged_mean_mm"], writer.summary["train_runs_mean_mm"])


def write_metrics(path: Path, metrics: pd.DataFrame, spec: dict) -> Path:
    """``metrics.parquet`` through the schema writer (units and config in its metadata)."""
    return write_table(metrics, path, MODEL_METRICS, config=spec,
                       provenance={"stage": STAGE})


def evaluation_table(params, train_runs: list[dict], test_runs: list[dict]) -> pd.DataFrame:
    """Open-loop errors over entire runs for the model and the baselines, per run and split
    (the ``model_metrics`` table of the split protocol: ``fold`` -1, no ``held_out``)."""
    rows = []
    for split, runs in (("train", train_runs), ("test", test_runs)):
        for run in runs:
            errors = {
                "lstm": evaluate_open_loop(params, run),
                "mean_position": baseline_mean_position(train_runs, run),
                "linear_lagged": baseline_linear_lagged(train_runs, run),
            }
            loses = split == "test" and errors["lstm"]["mean_mm"] >= errors["linear_lagged"][
                "mean_mm"]
            for model, values in errors.items():
                rows.append({"run_id": run["run_id"], "split": split, "fold": -1,
                             "held_out": "", "seed": 0, "model": model,
                             "steps": len(run["p"]), **values,
                             "loses_to_linear": bool(loses and model == "lstm")})
    return pd.DataFrame(rows)


def plot_losses(path: Path, losses: pd.DataFrame, ema: float = 0.98) -> Path:
    """Training loss (raw and EMA-smoothed, as in the paper) and the validation error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_loss, ax_val) = plt.subplots(1, 2, figsize=(11, 3.6))
    train = losses["train_loss"].to_numpy()
    smooth = pd.Series(train).ewm(alpha=1 - ema, adjust=True).mean()
    ax_loss.semilogy(losses["step"], train, lw=0.5, alpha=0.3, color="C0", label="train")
    ax_loss.semilogy(losses["step"], smooth, lw=1.5, color="C0", label=f"train (EMA {ema})")
    val = losses.dropna(subset=["val_loss"])
    if len(val):
        ax_loss.semilogy(val["step"], val["val_loss"], "o-", ms=3, color="C1", label="held out")
        ax_val.plot(val["step"], val["val_mean_mm"], "o-", ms=3, label="mean")
        ax_val.plot(val["step"], val["val_p95_mm"], "s--", ms=3, label="p95")
        ax_val.legend()
    ax_loss.set_xlabel("step")
    ax_loss.set_ylabel("loss (normalized MSE)")
    ax_loss.legend()
    ax_val.set_xlabel("step")
    ax_val.set_ylabel("held-out open-loop error [mm]")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_reconstruction(path: Path, params, runs: list[dict], labels: list[str]) -> Path:
    """Measured vs open-loop predicted x, y, z over time (paper Fig. 6).

    ``params``: one model for every run, or a list with one model per run.
    """
    models = list(params) if isinstance(params, (list, tuple)) else [params] * len(runs)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, len(runs), figsize=(6.5 * len(runs), 6.5), sharex="col",
                             squeeze=False)
    for col, (model, run, label) in enumerate(zip(models, runs, labels)):
        predicted = predict_run(model, run)
        t = run["t"] - run["t"][0]
        error = 1e3 * np.linalg.norm(predicted - run["pos"], axis=1)
        for k, axis in enumerate(XYZ):
            ax = axes[k, col]
            ax.plot(t, run["pos"][:, k] * 1e3, lw=0.8, color="k", label="measured")
            ax.plot(t, predicted[:, k] * 1e3, lw=0.8, color="C3", label="model (open loop)")
            ax.set_ylabel(f"{axis} [mm]")
        axes[0, col].set_title(f"{label} {run['run_id']}: mean error {error.mean():.2f} mm",
                               fontsize=10)
        axes[-1, col].set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
