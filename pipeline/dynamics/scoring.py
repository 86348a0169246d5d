"""Open-loop scoring of the learned dynamics and the baselines it is compared with.

Runs are dicts on a regular grid at the model rate (``training`` module docstring). The model is
fed a run's whole pressure sequence from ``t = 0`` and conditioned only on the pose observed at
``t = 0``; the baselines are the mean training position and a linear model on lagged pressures
and their squares, both fitted on the same training runs. Errors are Euclidean, in mm.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from pipeline.data.runs import Run
from pipeline.dynamics import model as dynamics
from pipeline.dynamics.model import DynamicsParams

# the ``model`` column of the model_metrics table: the learned model (whatever its cell) and the
# two baselines fitted on the same training runs
LEARNED = "learned"
MODELS = (LEARNED, "mean_position", "linear_lagged")
LINEAR_LAGS = 30  # lags of the linear baseline (model steps)

_predict_sequence = jax.jit(dynamics.predict_sequence)


def position_errors_mm(predicted: np.ndarray, observed: np.ndarray) -> dict:
    """Mean and 95th percentile of the Euclidean error (mm) between [T, 3] position arrays (m)."""
    error_mm = 1000.0 * np.linalg.norm(np.asarray(predicted) - np.asarray(observed), axis=-1)
    return {"mean_mm": float(error_mm.mean()), "p95_mm": float(np.percentile(error_mm, 95))}


def predict_run(params: DynamicsParams, run: Run) -> np.ndarray:
    """Open-loop [T, 3] positions (m) over the whole run, from its first observed pose."""
    pressure = jnp.asarray(run.pressures_kpa, jnp.float32)
    initial_pose = jnp.asarray(run.positions_m[0], jnp.float32)
    return np.asarray(_predict_sequence(params, pressure, initial_pose))


def evaluate_open_loop(params: DynamicsParams, run: Run) -> dict:
    """Open-loop error over the ENTIRE run: ``{"mean_mm", "p95_mm"}``."""
    return position_errors_mm(predict_run(params, run), run.positions_m)


def validation_errors(params: DynamicsParams, val_runs: Sequence[Run]
                      ) -> tuple[float, float, float]:
    """(standardized MSE, mean mm, p95 mm) of the open-loop prediction, pooled over val runs."""
    losses, errors = [], []
    for run in val_runs:
        predicted = predict_run(params, run)
        initial_pose = jnp.asarray(run.positions_m[0])
        predicted_normalized = dynamics.normalize_target(params, predicted, initial_pose)
        observed_normalized = dynamics.normalize_target(params, run.positions_m, initial_pose)
        losses.append(np.square(np.asarray(predicted_normalized - observed_normalized)).ravel())
        errors.append(1000.0 * np.linalg.norm(predicted - run.positions_m, axis=-1))
    errors = np.concatenate(errors)
    return (
        float(np.concatenate(losses).mean()),
        float(errors.mean()),
        float(np.percentile(errors, 95)),
    )


def baseline_mean_position(train_runs: Sequence[Run], run: Run) -> dict:
    """Errors of the constant prediction "mean training position" over ``run``."""
    mean_position = np.concatenate([r.positions_m for r in train_runs]).astype(np.float64).mean(0)
    observed = run.positions_m
    return position_errors_mm(np.broadcast_to(mean_position, observed.shape), observed)


def lagged_features(pressure: np.ndarray, num_lags: int) -> np.ndarray:
    """[T, 3] -> [T, 1 + 6 * num_lags]: bias, ``p_{t-k}`` and ``p_{t-k}**2`` for k < num_lags.

    Before the run starts the pressure is taken as its first value (the preload).
    """
    pressure = np.asarray(pressure, np.float64)
    padded = np.concatenate([np.repeat(pressure[:1], num_lags - 1, axis=0), pressure])
    num_steps = pressure.shape[0]
    lags = [padded[num_lags - 1 - k : num_lags - 1 - k + num_steps] for k in range(num_lags)]
    lagged = np.concatenate(lags, axis=1)
    return np.concatenate([np.ones((num_steps, 1)), lagged, lagged**2], axis=1)


def fit_linear_lagged(train_runs: Sequence[Run], num_lags: int) -> np.ndarray:
    """Least-squares coefficients [1 + 6 * num_lags, 3] from lagged pressures to position (m)."""
    features = np.concatenate([lagged_features(r.pressures_kpa, num_lags) for r in train_runs])
    targets = np.concatenate([np.asarray(r.positions_m, np.float64) for r in train_runs])
    coefficients, *_ = np.linalg.lstsq(features, targets, rcond=None)
    return coefficients


def predict_linear_lagged(train_runs: Sequence[Run], run: Run, num_lags: int = LINEAR_LAGS
                          ) -> np.ndarray:
    """[T, 3] positions (m) over ``run`` of the linear model fitted on ``train_runs``."""
    return lagged_features(run.pressures_kpa, num_lags) @ fit_linear_lagged(train_runs, num_lags)


def baseline_linear_lagged(train_runs: Sequence[Run], run: Run, num_lags: int = LINEAR_LAGS
                           ) -> dict:
    """Errors over ``run`` of the linear model on lagged pressures and their squares."""
    return position_errors_mm(predict_linear_lagged(train_runs, run, num_lags), run.positions_m)


def evaluation_table(params, train_runs: list[Run], test_runs: list[Run]) -> pd.DataFrame:
    """Open-loop errors over entire runs for the model and the baselines, per run and split
    (the ``model_metrics`` table of the split protocol: ``fold`` -1, no ``held_out``)."""
    rows = []
    for split, runs in (("train", train_runs), ("test", test_runs)):
        for run in runs:
            errors = {
                LEARNED: evaluate_open_loop(params, run),
                "mean_position": baseline_mean_position(train_runs, run),
                "linear_lagged": baseline_linear_lagged(train_runs, run),
            }
            loses = split == "test" and errors[LEARNED]["mean_mm"] >= errors["linear_lagged"][
                "mean_mm"]
            for model, values in errors.items():
                rows.append({"run_id": run.run_id, "split": split, "fold": -1,
                             "held_out": "", "seed": 0, "model": model,
                             "steps": len(run), "context_s": 0.0, "from_s": 0.0, **values,
                             "loses_to_linear": bool(loses and model == LEARNED)})
    return pd.DataFrame(rows)
