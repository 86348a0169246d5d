"""What ``stage=calibrate`` reports of a calibration (``pipeline.arm.calibration``): its folds,
the simulators' open-loop predictions and errors next to the learned model's baselines, the
fitted physics as tables, a Markdown table, a ``conf/robot`` file, and a figure.

Folds are the index of the run held out, or :data:`ALL_RUNS` (last) for the fit on every run.
Predictions are ``[folds, runs, T, 3]`` m at the calibration rate; errors are scored on the
model grid (every ``stride``-th frame), in mm.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import jax
import numpy as np
import pandas as pd

from pipeline.arm import calibration as calib
from pipeline.arm import sim_arm
from pipeline.data.runs import Run
from pipeline.data.schemas import XYZ, Column, TableSchema
from pipeline.dynamics.scoring import (
    baseline_linear_lagged,
    baseline_mean_position,
    position_errors_mm,
)
from pipeline.schemas import CalibrationConfig, SimPhysics

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


def fold_weights(num_runs: int, leave_one_run_out: bool) -> tuple[list[str | int], np.ndarray]:
    """Folds (run index held out, or ALL_RUNS last) and their ``[folds, runs]`` weights."""
    folds: list[str | int] = list(range(num_runs)) if leave_one_run_out and num_runs > 1 else []
    weights = [np.arange(num_runs) != f for f in folds] + [np.ones(num_runs, bool)]
    return [*folds, ALL_RUNS], np.stack(weights).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class Fit:
    """A calibration of some runs: every fold's fitted physics and rest offsets."""

    template: sim_arm.SimParams  # noise free, at the calibration rate
    param: calib.Parameterization
    init: dict[str, Any]  # SimPhysics values the fit started from (no substeps, no spread)
    result: calib.FitResult
    folds: list[str | int]
    weights: np.ndarray  # [folds, R]
    physics_substeps: int  # the integrator steps the fitted physics name (``init``'s, not the
    # fit's, which are ``template.substeps``)

    def physics(self, fold: int = -1) -> dict[str, Any]:
        """SimPhysics values of one fold's fit (:func:`fitted_physics`; by default the fit on
        all runs): a twin of the arm as the runs that fold was trained on show it."""
        return fitted_physics(self.init, self.result, self.physics_substeps, fold, self.weights)


def fit_runs(runs: list[Run], settings: CalibrationConfig) -> Fit:
    """Fit the simulated arm to ``runs`` (a regular grid at ``settings.rate_hz`` each, each
    started settled at its first command) with the calibration ``settings``
    (or the config group composed to it): every leave-one-run-out fold with
    ``settings.leave_one_run_out``, and the fit on all runs (last)."""
    init = calib.sim_physics_values(settings.init)
    substeps = int(init.pop("substeps"))
    init.pop("session_std", None)  # one physics for every run: the spread is not fitted
    template = sim_arm.SimParams.noise_free(init, float(settings.rate_hz), int(settings.substeps))
    param = calib.Parameterization.create(list(settings.fitted), init)
    folds, weights = fold_weights(len(runs), bool(settings.leave_one_run_out))
    result = calib.calibrate(
        template, param, init, calib.RunBatch.from_runs(runs), weights,
        num_steps=int(settings.num_steps), learning_rate=float(settings.learning_rate),
        num_restarts=int(settings.num_restarts), restart_std=float(settings.restart_std),
        key=jax.random.key(int(settings.seed)))
    return Fit(template, param, init, result, folds, weights, substeps)


def scored(fit: Fit, runs: list[Run], model_runs: list[Run], stride: int
           ) -> tuple[dict[str, np.ndarray], pd.DataFrame]:
    """Every fold of ``fit`` driven open loop through ``runs`` (the fitted runs, or others of
    the same ids, e.g. a later stretch of each, started settled at its first command; at the
    fit's rate): :func:`predictions` and their :func:`evaluation_table` on ``model_runs`` (every
    ``stride``-th frame)."""
    batch = calib.RunBatch.from_runs(runs)
    predicted = predictions(fit.template, fit.param, fit.result, batch, fit.weights,
                            fit.template.substeps, fit.template.mocap_hz)
    return predicted, evaluation_table(fit.folds, runs, model_runs, predicted, stride)


def predictions(template: sim_arm.SimParams, param: calib.Parameterization,
                result: calib.FitResult, batch: calib.RunBatch, weights: np.ndarray,
                substeps: int, rate_hz: float) -> dict[str, np.ndarray]:
    """Open-loop ``[folds, runs, T, 3]`` m predictions of the calibrated simulator (at the
    training runs' mean rest offset, and from each run's first pose) and of the hand-set
    simulator (at its own rest pose, and from the first pose), the same for every fold."""
    rest = calib.training_mean_offsets(result.offsets, weights)
    predicted = {
        "sim_calibrated": calib.open_loop(template, param, result.z, batch, rest),
        "sim_calibrated_first_pose": calib.open_loop(template, param, result.z, batch)}
    hand_set = calib.sim_physics_values(SimPhysics())
    hand_set.pop("substeps")
    hand_set.pop("session_std")
    hand_set_template = sim_arm.SimParams.noise_free(hand_set, rate_hz, substeps)
    for name, first_pose in (("sim_default", False), ("sim_default_first_pose", True)):
        predicted[name] = np.broadcast_to(
            calib.open_loop_template(hand_set_template, batch, first_pose),
            predicted["sim_calibrated"].shape)
    return predicted


def _scored(prediction: np.ndarray, model_run: Run, stride: int) -> dict:
    """Errors of a rate_hz prediction on the model_hz grid (every ``stride``-th frame)."""
    sub = prediction[::stride]
    n = min(len(sub), len(model_run.positions_m))
    return position_errors_mm(sub[:n], model_run.positions_m[:n])


def evaluation_table(folds: list, runs: list[Run], model_runs: list[Run],
                     predicted: dict[str, np.ndarray], stride: int) -> pd.DataFrame:
    """Per run: held-out ("test", leave-one-run-out) and in-sample ("train", the fit on all
    runs) open-loop errors of the simulators in ``predicted`` (name: ``[folds, R, T, 3]`` m)
    and of the baselines."""
    by_id = {r.run_id: r for r in model_runs}
    rows = []
    for fold_index, fold in enumerate(folds):
        held_out = [fold] if fold != ALL_RUNS else list(range(len(runs)))
        for i in held_out:
            run = runs[i]
            model_run = by_id[run.run_id]
            train = [by_id[r.run_id] for j, r in enumerate(runs)
                     if fold == ALL_RUNS or j != fold]
            split = "train" if fold == ALL_RUNS else "test"
            n = len(run)
            scored = {name: _scored(positions[fold_index, i, :n], model_run, stride)
                      for name, positions in predicted.items()}
            for model, errors in (
                *scored.items(),
                ("mean_position", baseline_mean_position(train, model_run)),
                ("linear_lagged", baseline_linear_lagged(train, model_run)),
            ):
                rows.append({"run_id": run.run_id, "split": split, "model": model,
                             "steps": len(model_run), **errors})
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


def fitted_physics(init: dict[str, Any], result: calib.FitResult, substeps: int,
                   fold: int = -1, weights: np.ndarray | None = None) -> dict[str, Any]:
    """SimPhysics values of one fold's fit (by default the fit on all runs, the last), with the
    base position and rest-pose spread of the offsets of the runs it was trained on (``weights
    [folds, R]``, 0: held out; None: every run): what ``robot.physics_from`` reads."""
    offsets = result.offsets[fold]
    if weights is not None:
        offsets = offsets[np.asarray(weights)[fold] > 0]
    fitted = calib.physics_dict(init, result.physics[fold])
    fitted.update(calib.session_offsets_to_physics(init["base_position_m"], offsets))
    fitted["substeps"] = int(substeps)
    return fitted


def parameter_table(fold_names: list[str], param: calib.Parameterization,
                    result: calib.FitResult, init: dict) -> pd.DataFrame:
    """The :data:`PARAMETERS` table: every fitted parameter of every fold."""
    return pd.DataFrame([row for f, name in enumerate(fold_names)
                         for row in parameter_rows(name, param, result.physics[f], init)])


def offsets_table(runs: list[Run], result: calib.FitResult) -> pd.DataFrame:
    """The :data:`OFFSETS` table: the fit on all runs' rest offset of each run."""
    offsets = result.offsets[-1]
    return pd.DataFrame({"run_id": [r.run_id for r in runs],
                         **{c: offsets[:, k] for k, c in enumerate(XYZ)}})


def losses_table(result: calib.FitResult, fold_names: list[str]) -> pd.DataFrame:
    """Per Adam step, fold and restart: the loss in mm^2."""
    steps, members, restarts = result.losses.shape
    return pd.DataFrame({
        "step": np.repeat(np.arange(steps), members * restarts),
        "fold": np.tile(np.repeat(fold_names, restarts), steps),
        "restart": np.tile(np.arange(restarts), steps * members),
        "loss_mm2": result.losses.reshape(-1),
    })


def summary(runs: list[Run], param: calib.Parameterization, result: calib.FitResult,
            metrics: pd.DataFrame) -> dict[str, Any]:
    """The artifact's summary: runs, parameters, chosen restarts, the final loss, and the mean
    of each model's ``mean_mm``/``p95_mm`` per split (``<split>_<model>_<stat>``)."""
    values = {"runs": [r.run_id for r in runs], "parameters": list(param.names),
              "chosen_restarts": result.chosen.tolist(),
              "final_loss_mm2": float(result.losses[-1, -1, result.chosen[-1]])}
    for split in ("test", "train"):
        part = metrics[metrics["split"] == split]
        for model in metrics["model"].unique():
            for k in ("mean_mm", "p95_mm"):
                column = part.loc[part["model"] == model, k]
                if len(column):
                    values[f"{split}_{model}_{k}"] = float(column.mean())
    return values


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


def plot_reconstruction(path: Path, runs: list[Run], folds: list, predicted: np.ndarray,
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
        n = len(run)
        t = run.times_s - run.times_s[0]
        fitted = predicted[fold_index, i, :n]
        error = 1e3 * np.linalg.norm(fitted - run.positions_m, axis=1).mean()
        for k, axis in enumerate(XYZ):
            ax = axes[k, col]
            ax.plot(t, run.positions_m[:, k] * 1e3, lw=0.7, color="k", label="measured")
            ax.plot(t, fitted[:, k] * 1e3, lw=0.7, color="C3", label=f"calibrated ({label})")
            ax.plot(t, default_prediction[i, :n, k] * 1e3, lw=0.5, color="C0", alpha=0.6,
                    label="hand-set")
            ax.set_ylabel(f"{axis} [mm]")
        axes[0, col].set_title(f"{run.run_id}: calibrated {error:.2f} mm mean ({label})",
                               fontsize=9)
        axes[-1, col].set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
