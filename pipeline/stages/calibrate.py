"""Stage ``calibrate``: the simulated arm's physics fitted to the aligned runs.

The aligned runs (any robot: the paper's CSVs, PlotJuggler exports, rosbags, a ROS 2 collection,
or the simulated arm itself) are resampled to ``calibration.rate_hz`` and each is driven open loop
through the simulator with its own pressure commands from the settled preload; the physics
(``calibration.fitted``, bounded, see :mod:`pipeline.arm.calibration`) and one rest offset per
training run are fitted by Adam, from ``calibration.num_restarts`` starts, all in one program.
With ``calibration.leave_one_run_out`` every run is also held out once and its open-loop error is
scored at ``dataset.model_hz``, in fit_model's table format, next to the hand-set simulator and
fit_model's baselines (mean position, linear lagged pressures) trained on the same runs:
``sim_calibrated`` rests where the training runs rest (the mean of their fitted offsets: nothing
of the held-out run is used), ``sim_calibrated_first_pose`` rests on the held-out run's first
recorded pose (the learned model's protocol); ``sim_default`` is the hand-set simulator at its
own rest pose, ``sim_default_first_pose`` on the first pose.

Artifact: ``physics.json`` (the SimPhysics values of the fit on all runs, the base position and
rest-pose spread from its offsets: what ``robot.physics_from`` reads; one physics for every run,
so ``session_std`` is neither fitted nor written and ``physics_from`` leaves it as configured), ``parameters.parquet`` and
``parameters.md`` (value, unit, bounds and start of every fitted parameter, per fold), per-run
``offsets.parquet``, ``robot_sim.yaml`` (a ``conf/robot`` file holding the fitted physics),
``metrics.parquet`` (per run and split: mean and p95 open-loop error in mm),
``losses.parquet`` and ``figures/reconstruction.png``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Any

import jax
import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from pipeline import keys
from pipeline.arm import calibration as calib
from pipeline.arm import sim_arm
from pipeline.arm.twins import load_physics
from pipeline.config import ConfigError, SimPhysics
from pipeline.data.alignment import runs_at_model_rate
from pipeline.data.schemas import ALIGNED, XYZ, Column, TableSchema, read_table, write_table
from pipeline.dynamics.scoring import (
    baseline_linear_lagged,
    baseline_mean_position,
    position_errors_mm,
)
from pipeline.infra.artifacts import Artifact, ArtifactStore, produce
from pipeline.infra.parquet import table_metadata, write_parquet

log = logging.getLogger(__name__)
STAGE = "calibrate"
ALL_RUNS = "all"  # the fold trained on every run

PARAMETERS = TableSchema(
    "calibrated_parameters",
    (Column("fold", "str", "", f"run held out ('{ALL_RUNS}': trained on every run)"),
     Column("name", "str", "", "SimPhysics field"),
     Column("element", "int", "", "index inside a list-valued parameter"),
     Column("value", "float", "", "fitted value, in `unit`"),
     Column("unit", "str", "", "unit of value, lower, upper and initial"),
     Column("lower", "float", "", "bound"),
     Column("upper", "float", "", "bound"),
     Column("initial", "float", "", "start of the first restart")),
    time_column=None, run_column=None,
)
OFFSETS = TableSchema(
    "calibrated_offsets",
    (Column("run_id", "str", "", "run"),
     *(Column(c, "float", "m", f"fitted rest offset along {c}") for c in XYZ)),
    time_column=None,
)


def _template(init: dict[str, Any], rate_hz: float, substeps: int) -> sim_arm.SimParams:
    """Noise-free SimParams at ``rate_hz`` frames of ``substeps`` integrator steps."""
    robot = OmegaConf.create({
        "physics": {**init, "substeps": substeps},
        "mocap": {"rate_hz": rate_hz, "noise_std_m": 0.0, "jitter_std_s": 0.0, "drop_prob": 0.0,
                  "burst_prob": 0.0, "burst_len": 1}})
    return sim_arm.SimParams.from_config(robot)


def fold_weights(num_runs: int, leave_one_run_out: bool) -> tuple[list[str | int], np.ndarray]:
    """Folds (run index held out, or ALL_RUNS last) and their ``[folds, runs]`` weights."""
    folds: list[str | int] = list(range(num_runs)) if leave_one_run_out and num_runs > 1 else []
    weights = [np.arange(num_runs) != f for f in folds] + [np.ones(num_runs, bool)]
    return [*folds, ALL_RUNS], np.stack(weights).astype(np.float32)


def calibrate(cfg: Any) -> Artifact:
    store = ArtifactStore(cfg.paths.artifact_dir)
    spec, inputs = keys.calibrate_spec(cfg)
    aligned_artifact = store.require("align", inputs["align"])
    settings = cfg.calibration
    rate_hz, model_hz = float(settings.rate_hz), float(cfg.dataset.model_hz)
    stride = round(rate_hz / model_hz)
    if stride < 1 or abs(stride * model_hz - rate_hz) > 1e-6:
        raise ValueError(f"calibration.rate_hz={rate_hz} must be a whole multiple of "
                         f"dataset.model_hz={model_hz} (errors are scored at model_hz)")

    def build(writer):
        aligned, _ = read_table(aligned_artifact.file("aligned.parquet"), ALIGNED)
        runs = runs_at_model_rate(aligned, rate_hz, "clock")
        model_runs = runs_at_model_rate(aligned, model_hz, "clock")
        batch = calib.RunBatch.from_runs(runs)
        init = calib.sim_physics_values(settings.init)
        init.pop("substeps", None)
        init.pop("session_std", None)  # one physics for every run: the spread is not fitted
        template = _template(init, rate_hz, int(settings.substeps))
        param = calib.Parameterization.create(list(settings.fitted), init)
        folds, weights = fold_weights(len(runs), bool(settings.leave_one_run_out))
        log.info("calibrate: %d runs at %.3g Hz (%d frames max), %d parameters, %d fits x %d "
                 "restarts x %d steps", len(runs), rate_hz, batch.commands.shape[1], param.size,
                 len(folds), int(settings.num_restarts), int(settings.num_steps))
        result = calib.calibrate(
            template, param, init, batch, weights, num_steps=int(settings.num_steps),
            learning_rate=float(settings.learning_rate),
            num_restarts=int(settings.num_restarts), restart_std=float(settings.restart_std),
            key=jax.random.key(int(settings.seed)))
        rest = calib.training_mean_offsets(result.offsets, weights)
        predicted = {  # [folds, R, T, 3] m
            "sim_calibrated": calib.open_loop(template, param, result.z, batch, rest),
            "sim_calibrated_first_pose": calib.open_loop(template, param, result.z, batch)}
        hand_set = calib.sim_physics_values(SimPhysics())
        hand_set.pop("substeps")
        hand_set.pop("session_std")
        hand_set_template = _template(hand_set, rate_hz, int(settings.substeps))
        for name, first_pose in (("sim_default", False), ("sim_default_first_pose", True)):
            predicted[name] = np.broadcast_to(
                calib.open_loop_template(hand_set_template, batch, first_pose),
                predicted["sim_calibrated"].shape)

        metrics = evaluation_table(folds, runs, model_runs, predicted, stride)
        write_outputs(writer, cfg, spec, inputs, folds, runs, param, init, result, metrics,
                      predicted)

    return produce(store, STAGE, spec, inputs, build, force=cfg.force)


def _scored(prediction: np.ndarray, model_run: dict, stride: int) -> dict:
    """Errors of a rate_hz prediction on the model_hz grid (every ``stride``-th frame)."""
    sub = prediction[::stride]
    n = min(len(sub), len(model_run["pos"]))
    return position_errors_mm(sub[:n], model_run["pos"][:n])


def evaluation_table(folds: list, runs: list[dict], model_runs: list[dict],
                     predicted: dict[str, np.ndarray], stride: int) -> pd.DataFrame:
    """Per run: held-out ("test", leave-one-run-out) and in-sample ("train", the fit on all
    runs) open-loop errors of the simulators in ``predicted`` (name: ``[folds, R, T, 3]`` m)
    and of the baselines."""
    by_id = {r["run_id"]: r for r in model_runs}
    rows = []
    for fold_index, fold in enumerate(folds):
        held_out = [fold] if fold != ALL_RUNS else list(range(len(runs)))
        for i in held_out:
            run = runs[i]
            model_run = by_id[run["run_id"]]
            train = [by_id[r["run_id"]] for j, r in enumerate(runs)
                     if fold == ALL_RUNS or j != fold]
            split = "train" if fold == ALL_RUNS else "test"
            n = len(run["p"])
            scored = {name: _scored(positions[fold_index, i, :n], model_run, stride)
                      for name, positions in predicted.items()}
            for model, errors in (
                *scored.items(),
                ("mean_position", baseline_mean_position(train, model_run)),
                ("linear_lagged", baseline_linear_lagged(train, model_run)),
            ):
                rows.append({"run_id": run["run_id"], "split": split, "model": model,
                             "steps": len(model_run["p"]), **errors})
    return pd.DataFrame(rows)


def parameter_rows(fold: str, param: calib.Parameterization, physics: dict, init: dict
                   ) -> list[dict]:
    rows, start = [], 0
    for name, size in zip(param.names, param.sizes):
        value = np.atleast_1d(physics[name])
        initial = np.atleast_1d(np.asarray(init[name], np.float64))
        for k in range(size):
            rows.append({"fold": fold, "name": name, "element": k, "value": float(value[k]),
                         "unit": calib.UNITS[name], "lower": float(param.lower[start + k]),
                         "upper": float(param.upper[start + k]), "initial": float(initial[k])})
        start += size
    return rows


def write_outputs(writer, cfg, spec, inputs, folds, runs, param, init, result, metrics,
                  predicted) -> None:
    fold_names = [f if f == ALL_RUNS else runs[f]["run_id"] for f in folds]
    last = len(folds) - 1  # the fit on all runs
    config = {"calibration": spec["calibration"], "robot": cfg.robot.name}
    provenance = {"stage": STAGE, "inputs": inputs}

    fitted = calib.physics_dict(init, result.physics[last])
    fitted.update(calib.session_offsets_to_physics(init["base_position_m"], result.offsets[last]))
    fitted["substeps"] = int(calib.sim_physics_values(cfg.calibration.init)["substeps"])
    writer.file("physics.json").write_text(json.dumps(
        {"physics": fitted, "units": {k: calib.UNITS.get(k, "") for k in fitted},
         "runs": [r["run_id"] for r in runs]}, indent=2))

    writer.file("robot_sim.yaml").write_text(robot_yaml(fitted, [r["run_id"] for r in runs]))

    rows = [row for f, name in enumerate(fold_names)
            for row in parameter_rows(name, param, result.physics[f], init)]
    write_table(pd.DataFrame(rows), writer.file("parameters.parquet"), PARAMETERS, config,
                provenance)
    table = pd.DataFrame([r for r in rows if r["fold"] == ALL_RUNS])
    writer.file("parameters.md").write_text(parameter_markdown(table))
    offsets = result.offsets[last]
    write_table(pd.DataFrame({"run_id": [r["run_id"] for r in runs],
                              **{c: offsets[:, k] for k, c in enumerate(XYZ)}}),
                writer.file("offsets.parquet"), OFFSETS, config, provenance)
    write_parquet(metrics, writer.file("metrics.parquet"), table_metadata(
        metrics, "calibration_metrics", config, provenance, {"steps": "model steps"}))
    steps, members, restarts = result.losses.shape
    losses = pd.DataFrame({
        "step": np.repeat(np.arange(steps), members * restarts),
        "fold": np.tile(np.repeat(fold_names, restarts), steps),
        "restart": np.tile(np.arange(restarts), steps * members),
        "loss_mm2": result.losses.reshape(-1),
    })
    write_parquet(losses, writer.file("losses.parquet"), table_metadata(
        losses, "calibration_losses", config, provenance,
        {"loss_mm2": "mm^2", "step": "Adam step"}))
    plot_reconstruction(writer.file("figures/reconstruction.png"), runs, folds,
                        predicted["sim_calibrated"], predicted["sim_default"][0])

    summary = {"runs": [r["run_id"] for r in runs], "parameters": list(param.names),
               "chosen_restarts": result.chosen.tolist(),
               "final_loss_mm2": float(result.losses[-1, last, result.chosen[last]])}
    for split in ("test", "train"):
        part = metrics[metrics["split"] == split]
        for model in metrics["model"].unique():
            for k in ("mean_mm", "p95_mm"):
                values = part.loc[part["model"] == model, k]
                if len(values):
                    summary[f"{split}_{model}_{k}"] = float(values.mean())
    writer.summary = summary
    held = "test" if "test_sim_calibrated_mean_mm" in summary else "train"
    log.info("calibrate: %s open-loop error %.2f mm mean, %.2f mm p95 (from the first pose %.2f "
             "mm; hand-set simulator %.2f mm, mean position %.2f mm, linear lagged %.2f mm)",
             "leave-one-run-out" if held == "test" else "in-sample",
             summary[f"{held}_sim_calibrated_mean_mm"], summary[f"{held}_sim_calibrated_p95_mm"],
             summary[f"{held}_sim_calibrated_first_pose_mean_mm"],
             summary[f"{held}_sim_default_mean_mm"], summary[f"{held}_mean_position_mean_mm"],
             summary[f"{held}_linear_lagged_mean_mm"])


def robot_yaml(physics: dict[str, Any], run_ids: list[str]) -> str:
    """A ``conf/robot`` file of the simulated arm with these physics (no artifact needed): the
    values that differ from the SimPhysics defaults."""
    defaults = dataclasses.asdict(SimPhysics())
    lines = ["# The simulated arm with physics calibrated (stage=calibrate) to the runs",
             f"# {', '.join(run_ids)}.",
             "defaults:", "  - base_sim", "  - _self_", "", "physics:"]
    for name, value in physics.items():
        if name in defaults and value == defaults[name]:
            continue
        text = (f"[{', '.join(f'{v:.6g}' for v in value)}]" if isinstance(value, list)
                else f"{value:.6g}" if isinstance(value, float) else str(value))
        lines.append(f"  {name}: {text}")
    return "\n".join(lines) + "\n"


def parameter_markdown(table: pd.DataFrame) -> str:
    lines = ["| parameter | value | unit | bounds | start |", "| --- | --- | --- | --- | --- |"]
    for name, group in table.groupby("name", sort=False):
        cell = {c: ", ".join(f"{v:.4g}" for v in group[c])
                for c in ("value", "lower", "upper", "initial")}
        lines.append(f"| {name} | {cell['value']} | {group['unit'].iloc[0]} | "
                     f"[{cell['lower']}] .. [{cell['upper']}] | {cell['initial']} |")
    return "\n".join(lines) + "\n"


def plot_reconstruction(path: Path, runs: list[dict], folds: list, predicted: np.ndarray,
                        default_prediction: np.ndarray, max_runs: int = 3) -> Path:
    """Measured vs simulated x, y, z of a few runs: held out where folds allow."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = list(range(min(max_runs, len(runs))))
    if len(runs) > max_runs:  # spread over the runs: first, middle, last
        shown = sorted({0, len(runs) // 2, len(runs) - 1})
    fig, axes = plt.subplots(3, len(shown), figsize=(6.0 * len(shown), 6.5), sharex="col",
                             squeeze=False)
    for col, i in enumerate(shown):
        run = runs[i]
        fold_index = folds.index(i) if i in folds else len(folds) - 1
        label = "held out" if i in folds else "in sample"
        n = len(run["p"])
        t = run["t"] - run["t"][0]
        fitted = predicted[fold_index, i, :n]
        error = 1e3 * np.linalg.norm(fitted - run["pos"], axis=1).mean()
        for k, axis in enumerate(XYZ):
            ax = axes[k, col]
            ax.plot(t, run["pos"][:, k] * 1e3, lw=0.7, color="k", label="measured")
            ax.plot(t, fitted[:, k] * 1e3, lw=0.7, color="C3", label=f"calibrated ({label})")
            ax.plot(t, default_prediction[i, :n, k] * 1e3, lw=0.5, color="C0", alpha=0.6,
                    label="hand-set")
            ax.set_ylabel(f"{axis} [mm]")
        axes[0, col].set_title(f"{run['run_id']}: calibrated {error:.2f} mm mean ({label})",
                               fontsize=9)
        axes[-1, col].set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------------------------
# robot.physics_from
# --------------------------------------------------------------------------------------------
def apply_physics_from(cfg: Any) -> Any:
    """``cfg`` with ``robot.physics`` (robot=sim) or ``robot.twin.physics`` (robot=ros2)
    replaced by the calibrate artifact named in ``robot.physics_from`` (unchanged if unset)."""
    source = cfg.robot.get("physics_from") if hasattr(cfg.robot, "get") else None
    if not source:
        return cfg
    physics = load_physics(str(source), cfg.paths.artifact_dir)
    target = cfg.robot.twin if "twin" in cfg.robot else cfg.robot
    known = set(target.physics.keys())
    unknown = sorted(set(physics) - known)
    if unknown:
        raise ConfigError(f"robot.physics_from={source!r}: parameters {unknown} are not "
                         f"SimPhysics fields of this version")
    for name, value in physics.items():
        target.physics[name] = value
    log.info("robot physics from calibrate artifact %s", source)
    return cfg
