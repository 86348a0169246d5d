"""Calibrating a fitted forward model to a session from the session's first seconds.

A *context* is the start of a run of the current session: its first ``n`` model steps of
commands ``p[0:n]`` [n, 3] kPa and measured positions ``x[0:n]`` [n, 3] m. A mechanism turns the
context into a :class:`SessionCorrection`, and :func:`predict_adapted` then predicts the whole
run open loop from the commands and the observed initial pose, as
:func:`pipeline.dynamics.model.predict_sequence` does, through the correction::

    p'_t = (1 + g) * p_t + o                             per chamber: gain g, offset o [kPa]
    y_t  = predict_sequence(params, p'[0:t+1], x_0)[t]   the model (its carry runs over the
                                                         context: the prediction after it is
                                                         the warm-started continuation)
    x̂_t  = c + (I + M) (y_t - c) + b                     per axis: M [3, 3], b [m], about the
                                                         context's mean prediction c [m]

The identity correction (all zero) gives the plain prediction exactly. Mechanisms
(``AdaptationSettings.mechanism``):

* ``none``: the identity (the model without context);
* ``offset``: ``b`` is the mean residual ``x_t - y_t`` over the last ``offset_window_s`` of the
  context (all of it by default): the prediction re-referenced to the session's measured poses;
* ``fine_tune``: starting from ``offset``, a few hundred Adam steps (one jitted scan, a fixed
  number of steps, the step size decaying to 0 on a cosine) on the mean squared error over the context of the parameters that
  ``output`` (``bias``: ``b``; ``diagonal``: ``b`` and ``diag(M)``; ``full``: ``b`` and ``M``)
  and ``input_affine`` (``g``, ``o``) free, with a quadratic prior pulling ``g``, ``o / σ_p``
  and ``M`` to zero (``prior_mm2``: the squared error in mm² one unit of them is worth);
* ``latent`` (a model trained with session latents, :mod:`pipeline.dynamics.session_latent`):
  the session latent inferred from the context, the weights fixed.

The baseline given the same context: the linear lagged-pressure model
(:mod:`pipeline.dynamics.scoring`) refitted on it (:func:`refit_linear_on_context`), its
training-runs coefficients the prior.

Settings are typed (:class:`AdaptationSettings`); arrays in, arrays and parameters out.
:func:`context_curve` scores leave-one-run-out fold models so, per context length.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pandas as pd
from flax import struct

from pipeline.data.runs import Run
from pipeline.dynamics import model as dynamics
from pipeline.dynamics.model import NUM_CHAMBERS, POSITION_DIM, DynamicsParams
from pipeline.dynamics.scoring import (
    LEARNED,
    LINEAR_LAGS,
    fit_linear_lagged,
    lagged_features,
    position_errors_mm,
)
from pipeline.dynamics.session_latent import DEFAULT_PRIOR, infer_latent, training_latents

MECHANISMS = ("none", "offset", "fine_tune", "latent")
OUTPUTS = ("bias", "diagonal", "full")
LATENT_CENTERS = ("zero", "training_mean")
_MM = 1000.0  # metres -> millimetres in the fine-tune's loss


@dataclass(frozen=True)
class AdaptationSettings:
    """How a model is calibrated to a session's context (hashable: static under ``jit``).

    mechanism: one of :data:`MECHANISMS` (module docstring).
    offset_window_s: ``offset`` (and the fine-tune's start): the mean residual over the last
        this many seconds of the context; ``None``: the whole context.
    output: the output correction the fine-tune fits, one of :data:`OUTPUTS`.
    input_affine: the fine-tune also fits a gain and an offset per chamber.
    steps: Adam steps of the fine-tune (a fixed number: bounded time).
    learning_rate: Adam's step size (the parameters are O(0.1) unitless, ``b`` in mm).
    prior_mm2: weight of the prior on ``g``, ``o / σ_p``, ``M`` and the readout's change (mm²
        per unit squared).
    readout: the fine-tune also changes the network's readout layer (its kernel [hidden, 3]
        and bias [3], in standardized units), added to what ``output`` and ``input_affine`` fit.
    latent_prior: ``latent`` (a model trained with session latents): the weight of ``|z|²`` in
        the inference of ``z`` (``session_latent.infer_latent``, ``steps`` Adam steps of
        ``learning_rate``).
    latent_center: ``latent``: the prior's mean, the start of the inference and the latent
        without context: ``zero`` or ``training_mean`` (the mean of the latents the model
        learned for its training runs).
    """

    # offset: leave-one-run-out on the recorded runs the best of the mechanisms given a context,
    # none of them below the model without it (docs/results/session-context.md)
    mechanism: str = "offset"
    offset_window_s: float | None = None
    output: str = "diagonal"
    input_affine: bool = True
    steps: int = 300
    learning_rate: float = 1.0e-2
    prior_mm2: float = 1.0
    readout: bool = False
    latent_prior: float = DEFAULT_PRIOR
    latent_center: str = "zero"

    def __post_init__(self):
        if self.mechanism not in MECHANISMS:
            raise ValueError(f"adaptation mechanism must be one of {MECHANISMS}, got "
                             f"{self.mechanism!r}")
        if self.output not in OUTPUTS:
            raise ValueError(f"adaptation output must be one of {OUTPUTS}, got {self.output!r}")
        if self.offset_window_s is not None and not self.offset_window_s > 0:
            raise ValueError(f"adaptation offset_window_s must be > 0 s or None, got "
                             f"{self.offset_window_s}")
        if isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 0:
            raise ValueError(f"adaptation steps must be an integer >= 0, got {self.steps!r}")
        if not self.learning_rate > 0:
            raise ValueError(f"adaptation learning_rate must be > 0, got {self.learning_rate}")
        if not self.prior_mm2 >= 0:
            raise ValueError(f"adaptation prior_mm2 must be >= 0, got {self.prior_mm2}")
        if self.latent_center not in LATENT_CENTERS:
            raise ValueError(f"adaptation latent_center must be one of {LATENT_CENTERS}, got "
                             f"{self.latent_center!r}")
        if not self.latent_prior >= 0:
            raise ValueError(f"adaptation latent_prior must be >= 0, got {self.latent_prior}")


@struct.dataclass
class SessionCorrection:
    """The calibration of a model to a session (module docstring); all zero: no correction.

    input_gain: [3] unitless, ``p' = (1 + g) p + o``.
    input_offset_kpa: [3] kPa.
    output_matrix: [3, 3] unitless, ``x̂ = c + (I + M)(y - c) + b``.
    output_offset_m: [3] m.
    center_m: [3] m, the mean prediction over the context (what ``M`` turns about).
    readout_delta: ``None`` or the change of the network's readout layer, ``{"kernel": [hidden,
        3], "bias": [3]}`` (added to ``params.network["params"]["readout"]``).
    latent: ``None`` or the session latent [d] the model runs with (a model trained with
        session latents, :mod:`pipeline.dynamics.session_latent`).
    """

    input_gain: jax.Array
    input_offset_kpa: jax.Array
    output_matrix: jax.Array
    output_offset_m: jax.Array
    center_m: jax.Array
    readout_delta: Any = None
    latent: Any = None

    @classmethod
    def identity(cls) -> SessionCorrection:
        zeros = jnp.zeros((POSITION_DIM,), jnp.float32)
        return cls(jnp.zeros((NUM_CHAMBERS,), jnp.float32), jnp.zeros((NUM_CHAMBERS,),
                   jnp.float32), jnp.zeros((POSITION_DIM, POSITION_DIM), jnp.float32), zeros,
                   zeros)


def context_steps(context_s: float, model_hz: float) -> int:
    """Model steps in ``context_s`` seconds at ``model_hz`` (rounded); ``ValueError`` if < 0."""
    if not context_s >= 0:
        raise ValueError(f"context length must be >= 0 s, got {context_s}")
    if not model_hz > 0:
        raise ValueError(f"model rate must be > 0 Hz, got {model_hz}")
    return round(float(context_s) * float(model_hz))


def predict_adapted(params: DynamicsParams, correction: SessionCorrection, pressures: jax.Array,
                    initial_pose: jax.Array) -> jax.Array:
    """Open-loop positions [T, 3] m from pressures [T, 3] kPa and x_0 [3] m, corrected."""
    chex.assert_shape(pressures, (None, NUM_CHAMBERS))
    chex.assert_shape(initial_pose, (POSITION_DIM,))
    corrected = (1.0 + correction.input_gain) * pressures + correction.input_offset_kpa
    if correction.readout_delta is not None:
        network = params.network["params"]
        readout = jax.tree.map(jnp.add, network["readout"], correction.readout_delta)
        params = params.replace(network={**params.network,
                                         "params": {**network, "readout": readout}})
    raw = dynamics.predict_sequence(params, corrected, initial_pose, latent=correction.latent)
    turned = (raw - correction.center_m) @ (jnp.eye(POSITION_DIM) + correction.output_matrix).T
    return correction.center_m + turned + correction.output_offset_m


def adapt(params: DynamicsParams, pressures: np.ndarray, positions: np.ndarray,
          settings: AdaptationSettings, model_hz: float) -> SessionCorrection:
    """The correction of ``settings.mechanism`` from a context: the first ``n`` steps of a run,
    pressures [n, 3] kPa and measured positions [n, 3] m (``n = 0``: the identity)."""
    pressures = jnp.asarray(pressures, jnp.float32)
    positions = jnp.asarray(positions, jnp.float32)
    chex.assert_shape(pressures, (None, NUM_CHAMBERS))
    chex.assert_equal_shape_prefix((pressures, positions), 1)
    chex.assert_shape(positions, (None, POSITION_DIM))
    if settings.mechanism == "latent":
        return _latent(params, pressures, positions, settings)
    if len(pressures) == 0 or settings.mechanism == "none":
        return SessionCorrection.identity()
    window = (len(pressures) if settings.offset_window_s is None
              else max(1, min(len(pressures), context_steps(settings.offset_window_s, model_hz))))
    if settings.mechanism == "offset":
        return _offset(params, pressures, positions, window)
    return _fine_tune(params, pressures, positions, settings, window)


def _latent(params: DynamicsParams, pressures: jax.Array, positions: jax.Array,
            settings: AdaptationSettings) -> SessionCorrection:
    """The session latent inferred from the context (``latent_center``: the prior's mean and
    the latent without context, 0 or the mean of the latents the model learned)."""
    if dynamics.session_latent_dim(params) == 0:
        raise ValueError("adaptation mechanism 'latent' needs a model trained with session "
                         "latents (cv.fit_members with a SessionLatentSettings)")
    center = None
    if settings.latent_center == "training_mean":
        center = jnp.mean(training_latents(params, trained_only=True), axis=0)
    if len(pressures) == 0:
        return SessionCorrection.identity().replace(latent=center)
    latent = infer_latent(params, pressures, positions, settings.steps, settings.learning_rate,
                          settings.latent_prior, center)
    return SessionCorrection.identity().replace(latent=latent)


@functools.partial(jax.jit, static_argnames="window")
def _offset(params: DynamicsParams, pressures: jax.Array, positions: jax.Array, window: int
            ) -> SessionCorrection:
    predicted = dynamics.predict_sequence(params, pressures, positions[0])
    residual = jnp.mean(positions[-window:] - predicted[-window:], axis=0)
    return SessionCorrection.identity().replace(output_offset_m=residual,
                                                center_m=jnp.mean(predicted, axis=0))


def _correction(theta: dict, start: SessionCorrection, settings: AdaptationSettings
                ) -> SessionCorrection:
    """The correction of the free parameters ``theta`` (``bias_mm``, ``gain``, ``offset_kpa``,
    ``matrix`` [3, 3] or its diagonal [3])."""
    correction = start.replace(output_offset_m=start.output_offset_m + theta["bias_mm"] / _MM)
    if settings.input_affine:
        correction = correction.replace(input_gain=theta["gain"],
                                        input_offset_kpa=theta["offset_kpa"])
    if settings.output == "diagonal":
        correction = correction.replace(output_matrix=jnp.diag(theta["matrix"]))
    elif settings.output == "full":
        correction = correction.replace(output_matrix=theta["matrix"])
    if settings.readout:
        correction = correction.replace(readout_delta=theta["readout"])
    return correction


def _initial_theta(params: DynamicsParams, settings: AdaptationSettings) -> dict:
    theta = {"bias_mm": jnp.zeros((POSITION_DIM,), jnp.float32)}
    if settings.input_affine:
        theta["gain"] = jnp.zeros((NUM_CHAMBERS,), jnp.float32)
        theta["offset_kpa"] = jnp.zeros((NUM_CHAMBERS,), jnp.float32)
    if settings.output == "diagonal":
        theta["matrix"] = jnp.zeros((POSITION_DIM,), jnp.float32)
    elif settings.output == "full":
        theta["matrix"] = jnp.zeros((POSITION_DIM, POSITION_DIM), jnp.float32)
    if settings.readout:
        theta["readout"] = jax.tree.map(jnp.zeros_like, params.network["params"]["readout"])
    return theta


@functools.partial(jax.jit, static_argnames=("settings", "window"))
def _fine_tune(params: DynamicsParams, pressures: jax.Array, positions: jax.Array,
               settings: AdaptationSettings, window: int) -> SessionCorrection:
    start = _offset(params, pressures, positions, window)
    pressure_std = params.normalizer.pressure_std

    def loss(theta):
        correction = _correction(theta, start, settings)
        predicted = predict_adapted(params, correction, pressures, positions[0])
        error = jnp.mean(jnp.sum(jnp.square(_MM * (predicted - positions)), axis=-1))
        prior = sum(jnp.sum(jnp.square(leaf)) for name in ("gain", "matrix", "readout")
                    if name in theta for leaf in jax.tree.leaves(theta[name]))
        if "offset_kpa" in theta:
            prior = prior + jnp.sum(jnp.square(theta["offset_kpa"] / pressure_std))
        return error + settings.prior_mm2 * prior

    optimizer = optax.adam(optax.cosine_decay_schedule(settings.learning_rate,
                                                       max(settings.steps, 1)))

    def one_step(state, _):
        theta, opt_state = state
        grads = jax.grad(loss)(theta)
        updates, opt_state = optimizer.update(grads, opt_state, theta)
        return (optax.apply_updates(theta, updates), opt_state), None

    theta = _initial_theta(params, settings)
    (theta, _), _ = jax.lax.scan(one_step, (theta, optimizer.init(theta)), None,
                                 length=settings.steps)
    return _correction(theta, start, settings)


# ---------------------------------------------------------------------------------------------
# the baselines given the same context
# ---------------------------------------------------------------------------------------------
def offset_on_context(predicted: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """[T, 3] predictions re-referenced by the mean residual over the context ``positions``
    [n, 3] (its first ``n`` rows; ``n = 0``: unchanged), metres."""
    predicted = np.asarray(predicted, np.float64)
    count = len(positions)
    if count == 0:
        return predicted
    return predicted + np.mean(np.asarray(positions, np.float64) - predicted[:count], axis=0)


def refit_linear_on_context(coefficients: np.ndarray, features: np.ndarray,
                            positions: np.ndarray, ridge: float) -> np.ndarray:
    """The linear model's coefficients [F, 3] refitted on a context: features [n, F] (the
    lagged features of its pressures), positions [n, 3] m, pulled to the training-runs
    ``coefficients`` [F, 3]: ``argmin |A b - x|² + w |b - b_train|²`` with
    ``w = ridge * trace(AᵀA) / F`` (``ridge`` 1: the prior weighs as much as the context's
    average feature)."""
    features = np.asarray(features, np.float64)
    count, width = features.shape
    chex.assert_shape(coefficients, (width, POSITION_DIM))
    if not ridge > 0:
        raise ValueError(f"the linear refit's ridge must be > 0, got {ridge}")
    if count == 0:
        return np.asarray(coefficients, np.float64)
    weight = ridge * np.trace(features.T @ features) / width
    gram = features.T @ features + weight * np.eye(width)
    rhs = features.T @ np.asarray(positions, np.float64) + weight * coefficients
    return np.linalg.solve(gram, rhs)


# ---------------------------------------------------------------------------------------------
# the context curve of leave-one-run-out fold models
# ---------------------------------------------------------------------------------------------
CONTEXTS_S = (0.0, 10.0, 30.0, 60.0)  # context lengths the curve is measured at [s]
SCORED_FROM_S = 60.0  # the common rest: every context length scored on the same samples [s]
LINEAR_RIDGE = 1.0  # the linear baseline's refit on the context (refit_linear_on_context)


def context_curve(held_out: Sequence[Run], train_runs: Sequence[Sequence[Run]],
                  params: Sequence[DynamicsParams], settings: AdaptationSettings,
                  model_hz: float, contexts_s: Sequence[float] = CONTEXTS_S,
                  scored_from_s: float = SCORED_FROM_S) -> pd.DataFrame:
    """Per fold (its held-out run, training runs and model) and context length ``T``: the
    open-loop error of the model calibrated on the first ``T`` s of the held-out run
    (``learned``) and of the linear lagged baseline fitted on the training runs and refitted
    on the same context (``linear_lagged``), over the run from ``max(T, scored_from_s)`` on.

    Rows: ``run_id``, ``context_s``, ``from_s`` [s], ``model``, ``mean_mm``, ``p95_mm``; a
    context that leaves no step to score is skipped.
    """
    if not len(held_out) == len(train_runs) == len(params):
        raise ValueError(f"one held-out run, training runs and model per fold: got "
                         f"{len(held_out)}, {len(train_runs)}, {len(params)}")
    predict = jax.jit(predict_adapted)
    rows = []
    for run, fold_runs, fold_params in zip(held_out, train_runs, params):
        coefficients = fit_linear_lagged(fold_runs, LINEAR_LAGS)
        features = lagged_features(run.pressures_kpa, LINEAR_LAGS)
        for context_s in contexts_s:
            steps = context_steps(context_s, model_hz)
            start = max(steps, context_steps(scored_from_s, model_hz))
            if start >= len(run):
                continue
            correction = adapt(fold_params, run.pressures_kpa[:steps], run.positions_m[:steps],
                               settings, model_hz)
            learned = np.asarray(predict(fold_params, correction, jnp.asarray(run.pressures_kpa),
                                         jnp.asarray(run.positions_m[0])))
            linear = features @ refit_linear_on_context(
                coefficients, features[:steps], run.positions_m[:steps], LINEAR_RIDGE)
            for model, predicted in ((LEARNED, learned), ("linear_lagged", linear)):
                rows.append({"run_id": run.run_id, "context_s": float(context_s),
                             "from_s": start / float(model_hz), "model": model,
                             **position_errors_mm(predicted[start:], run.positions_m[start:])})
    return pd.DataFrame(rows, columns=["run_id", "context_s", "from_s", "model", "mean_mm",
                                       "p95_mm"])


def context_metrics(runs: Sequence[Run], members: Sequence[Any],
                    params: Sequence[DynamicsParams], settings: AdaptationSettings,
                    model_hz: float) -> pd.DataFrame:
    """The ``model_metrics`` rows (``split="cv_context"``) of :func:`context_curve` for the fold
    members (``pipeline.dynamics.cv.Member``: those with a held-out run) and their models."""
    by_id = {run.run_id: run for run in runs}
    folds = [(member, member_params) for member, member_params in zip(members, params)
             if member.held_out]
    curve = context_curve([by_id[m.held_out] for m, _ in folds],
                          [[by_id[i] for i in m.train_ids] for m, _ in folds],
                          [p for _, p in folds], settings, model_hz)
    fold_of = {m.held_out: (index, m.seed) for index, (m, _) in enumerate(folds)}
    curve.insert(1, "split", "cv_context")
    curve["fold"] = [fold_of[run_id][0] for run_id in curve["run_id"]]
    curve["held_out"] = curve["run_id"]
    curve["seed"] = [fold_of[run_id][1] for run_id in curve["run_id"]]
    curve["steps"] = [len(by_id[run_id]) for run_id in curve["run_id"]]
    curve["loses_to_linear"] = False
    return curve


def context_summary(metrics: pd.DataFrame) -> pd.DataFrame:
    """Mean / p95 mm per context length and scored rest (rows) of the calibrated model and the refitted linear
    baseline, averaged over the held-out runs (the ``cv_context`` rows of ``metrics``)."""
    rows = metrics[metrics["split"] == "cv_context"]
    index = ["context_s", "from_s"]
    table = rows.pivot_table(index=index, columns="model", values=["mean_mm", "p95_mm"],
                             aggfunc="mean")
    table.columns = [f"{model}_{stat}" for stat, model in table.columns]
    table["runs"] = rows[rows["model"] == LEARNED].groupby(index)["run_id"].nunique()
    columns = [f"{m}_{s}" for m in (LEARNED, "linear_lagged") for s in ("mean_mm", "p95_mm")]
    return table.reindex(columns=[*columns, "runs"]).reset_index()
