"""Training, checkpointing and open-loop evaluation of the learned dynamics (``dynamics.py``).

Runs are dicts on a regular grid at the model rate::

    {"run_id": str, "t": float64 [T] s, "p": float32 [T, 3] kPa, "pos": float32 [T, 3] m}

Training minimizes the mean squared standardized error over sliding windows (``windows.py``).
Each window starts from the zero/conditioned carry and is given as initial pose the pose its run
started from (the rest pose an environment observes at reset), so a window in the middle of a
run is trained to predict its positions from that run's rest pose and the pressures. The
jitted train step runs ``lax.scan`` over a chunk of steps between evaluations/checkpoints, so the
Python loop only sees chunk boundaries.

Checkpoints are ``flax.serialization`` msgpack files written atomically (temporary file, fsync,
``os.replace``): the network, the optimizer state, the step, the loss history, the normalizer and
the configuration. Batches are a pure function of ``(seed, step)``, so resuming from the last
checkpoint reproduces the uninterrupted training.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pandas as pd
from flax import serialization
from tqdm.auto import tqdm

from pipeline.config import ModelConfig, ModelLoss, dataclass_values, frozen_twin
from pipeline.data.windows import gather_windows, make_windows, sample_batch
from pipeline.dynamics import model as dynamics
from pipeline.dynamics.model import DynamicsConfig, DynamicsParams, Normalizer
from pipeline.infra.parquet import atomic_write

log = logging.getLogger(__name__)

CHECKPOINT_PREFIX = "step_"
CHECKPOINT_SUFFIX = ".msgpack"
LOSS_TABLE_COLUMNS = ["step", "train_loss", "val_loss", "val_mean_mm", "val_p95_mm"]
# the ``model`` column of the model_metrics table: the learned model (whatever its cell) and the
# two baselines fitted on the same training runs
LEARNED = "learned"
MODELS = (LEARNED, "mean_position", "linear_lagged")


# ---------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ModelTrainConfig(frozen_twin(ModelConfig, "ModelSettings")):
    """The ``model`` config group (``pipeline.config.ModelConfig``, its only declaration) as a
    frozen dataclass: model and optimizer settings. Defaults: the CPU recipe.

    The paper's configuration is ``hidden=1024, batch_size=64, learning_rate=1e-3,
    lr_schedule="constant", num_steps=200_000, condition_on_initial_pose=False,
    predict_displacement=False`` with windows of 512 at 100 Hz (dataset settings).
    """

    def __post_init__(self):
        object.__setattr__(self, "head", tuple(int(width) for width in self.head))
        object.__setattr__(self, "step_decays", tuple(float(v) for v in self.step_decays))
        object.__setattr__(self, "play_widths_kpa",
                           tuple(float(v) for v in self.play_widths_kpa))
        if not 0.0 <= self.recurrent_dropout < 1.0:
            raise ValueError(f"recurrent_dropout must lie in [0, 1), got {self.recurrent_dropout}")
        if self.input_noise_std < 0 or self.weight_decay < 0:
            raise ValueError("input_noise_std and weight_decay must be >= 0, got "
                             f"{self.input_noise_std}, {self.weight_decay}")
        if self.loss not in {loss.value for loss in ModelLoss}:
            raise ValueError(f"loss must be mse or distance, got {self.loss!r}")
        if self.lr_schedule not in ("constant", "cosine"):
            raise ValueError(f"lr_schedule must be constant or cosine, got {self.lr_schedule!r}")
        if self.reference_pose not in ("run_start", "window_start"):
            raise ValueError(
                f"reference_pose must be run_start or window_start, got {self.reference_pose!r}"
            )

    @classmethod
    def from_any(cls, config: Any) -> ModelTrainConfig:
        """From this class, another dataclass, a mapping or an OmegaConf node; unknown keys fail."""
        if isinstance(config, cls):
            return config
        values = dataclass_values(cls, config, "model")
        for name in ("head", "step_decays", "play_widths_kpa"):
            if name in values:
                values[name] = tuple(values[name])
        return cls(**values)

    def architecture(self) -> DynamicsConfig:
        return DynamicsConfig(
            hidden=self.hidden,
            layers=self.layers,
            head=self.head,
            condition_on_initial_pose=self.condition_on_initial_pose,
            predict_displacement=self.predict_displacement,
            cell=self.cell,
            pressure_delta=self.pressure_delta,
            step_size=self.step_size,
            step_decays=self.step_decays,
            play_widths_kpa=self.play_widths_kpa,
            step_threshold_kpa=self.step_threshold_kpa,
        )


def make_optimizer(config: ModelTrainConfig) -> optax.GradientTransformation:
    if config.lr_schedule == "cosine":
        learning_rate = optax.warmup_cosine_decay_schedule(
            init_value=0.0,
            peak_value=config.learning_rate,
            warmup_steps=config.warmup_steps,
            decay_steps=max(config.num_steps, config.warmup_steps + 1),
            end_value=config.learning_rate * config.final_lr_fraction,
        )
    else:
        learning_rate = config.learning_rate
    if config.weight_decay > 0:
        adam = optax.adamw(learning_rate, weight_decay=config.weight_decay)
    else:
        adam = optax.adam(learning_rate)
    if config.max_grad_norm > 0:
        return optax.chain(optax.clip_by_global_norm(config.max_grad_norm), adam)
    return adam


# ---------------------------------------------------------------------------------------------
# training step
# ---------------------------------------------------------------------------------------------
class TrainState(NamedTuple):
    network: Any  # flax variables
    opt_state: optax.OptState
    step: jax.Array  # int32 scalar: steps taken so far


class TrainData(NamedTuple):
    """Concatenated training runs and their windows (device arrays).

    inputs: [N, D] standardized network inputs (pressures and features, computed over each
        whole run from its start: ``dynamics.network_inputs``) of all runs, back to back.
    position: [N, 3] positions (m), same rows.
    reference_pose: [N, 3] the pose (m) the model is given as initial pose for a window starting
        at this row: the first pose of the row's run (``reference_pose="run_start"``) or the
        row's own pose (``"window_start"``).
    window_starts: [M] first row of each window in the concatenation; only the first
        ``num_windows`` are real (the rest pad the list to a common length across folds).
    num_windows: [] int32, the number of real windows.
    """

    inputs: jax.Array
    position: jax.Array
    reference_pose: jax.Array
    window_starts: jax.Array
    num_windows: jax.Array


DISTANCE_EPS = 1e-3  # [target std]: keeps the distance loss's gradient finite at zero error


def window_loss(
    params: DynamicsParams,
    inputs: jax.Array,
    position: jax.Array,
    initial_pose: jax.Array,
    hidden_mask: jax.Array | None = None,
    loss: str = "mse",
) -> jax.Array:
    """Error of the open-loop rollout over a batch of windows, a scalar.

    inputs: [B, W, D] standardized network inputs; position: [B, W, 3] m; initial_pose: [B, 3]
    m, the pose each rollout is conditioned on (and displacements are measured from);
    hidden_mask: optional [B, layers, hidden] recurrent-dropout masks. ``loss``: ``mse``, the
    mean over windows, steps and axes of the squared standardized error; ``distance``, the mean
    over windows and steps of the Euclidean distance to the measured position, in units of the
    mean target standard deviation (so both losses are of order one), smoothed by
    :data:`DISTANCE_EPS` at zero.
    """
    targets = jax.vmap(dynamics.normalize_target, in_axes=(None, 0, 0))(
        params, position, initial_pose
    )
    pose_normalized = dynamics.normalize_pose(params.normalizer, initial_pose)
    outputs = jax.vmap(dynamics.predict_normalized, in_axes=(None, 0, 0, 0))(
        params, inputs, pose_normalized, hidden_mask
    )
    chex.assert_equal_shape((outputs, targets))
    if loss == "mse":
        return jnp.mean(jnp.square(outputs - targets))
    if loss == "distance":
        target_std = params.normalizer.target_std
        error = (outputs - targets) * target_std / jnp.mean(target_std)  # [B, W, 3]
        return jnp.mean(jnp.sqrt(jnp.sum(jnp.square(error), axis=-1) + DISTANCE_EPS**2))
    raise ValueError(f"model.loss must be mse or distance, got {loss!r}")


def make_train_step(
    model_template: DynamicsParams,
    optimizer: optax.GradientTransformation,
    window: int,
    batch_size: int,
    order: str,
    input_noise_std: float = 0.0,
    recurrent_dropout: float = 0.0,
    loss: str = "mse",
) -> Callable[[TrainState, TrainData, jax.Array], tuple[TrainState, jax.Array]]:
    """``train_step(state, data, sample_key) -> (state, loss)``: one Adam step on one batch.

    ``model_template`` supplies the normalizer and architecture; its network is replaced by the
    trained one. The batch of step ``k`` depends only on ``(sample_key, k)``, and so do the
    input noise and dropout masks (drawn from a key split off ``sample_key`` and folded with
    ``k``). The data is an argument (not a closure) so a jitted program does not embed the
    dataset as constants.
    """
    config = model_template.config

    def loss_fn(network, inputs, position, initial_pose, hidden_mask):
        params = model_template.replace(network=network)
        return window_loss(params, inputs, position, initial_pose, hidden_mask, loss)

    def train_step(state: TrainState, data: TrainData, sample_key: jax.Array):
        batch_key, regularizer_key = jax.random.split(sample_key)
        window_index = sample_batch(batch_key, state.step, data.num_windows, batch_size, order,
                                    capacity=data.window_starts.shape[0])
        starts = data.window_starts[window_index]
        inputs = gather_windows(data.inputs, starts, window)
        position = gather_windows(data.position, starts, window)
        initial_pose = data.reference_pose[starts]
        noise_key, dropout_key = jax.random.split(jax.random.fold_in(regularizer_key, state.step))
        if input_noise_std > 0:
            inputs = inputs + input_noise_std * jax.random.normal(noise_key, inputs.shape)
        hidden_mask = None
        if recurrent_dropout > 0:
            keep = jax.random.bernoulli(dropout_key, 1.0 - recurrent_dropout,
                                        (batch_size, config.layers, config.hidden))
            hidden_mask = keep.astype(inputs.dtype) / (1.0 - recurrent_dropout)
        loss, grads = jax.value_and_grad(loss_fn)(state.network, inputs, position, initial_pose,
                                                  hidden_mask)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.network)
        network = optax.apply_updates(state.network, updates)
        return TrainState(network, opt_state, state.step + 1), loss

    return train_step


def train_chunk_unjitted(
    state: TrainState,
    data: TrainData,
    normalizer: Normalizer,
    sample_key: jax.Array,
    config: ModelTrainConfig,
    window: int,
    order: str,
    num_steps: int,
) -> tuple[TrainState, jax.Array]:
    """``num_steps`` training steps in one ``lax.scan``: ``-> (state, losses [num_steps])``.

    :func:`train_chunk` is this jitted, once per (config, window, order, num_steps) and data
    shapes, so fits that share them (resumed runs) reuse the compiled program;
    ``pipeline.dynamics.cv`` vmaps it over folds and seeds.
    """
    template = DynamicsParams(network=state.network, normalizer=normalizer,
                              config=config.architecture())
    train_step = make_train_step(
        template, make_optimizer(config), window, config.batch_size, order,
        input_noise_std=config.input_noise_std, recurrent_dropout=config.recurrent_dropout,
        loss=str(config.loss),
    )
    return jax.lax.scan(
        lambda s, _: train_step(s, data, sample_key), state, None, length=num_steps
    )


train_chunk = jax.jit(train_chunk_unjitted,
                      static_argnames=("config", "window", "order", "num_steps"))


# ---------------------------------------------------------------------------------------------
# evaluation and baselines
# ---------------------------------------------------------------------------------------------
_predict_sequence = jax.jit(dynamics.predict_sequence)


def position_errors_mm(predicted: np.ndarray, observed: np.ndarray) -> dict:
    """Mean and 95th percentile of the Euclidean error (mm) between [T, 3] position arrays (m)."""
    error_mm = 1000.0 * np.linalg.norm(np.asarray(predicted) - np.asarray(observed), axis=-1)
    return {"mean_mm": float(error_mm.mean()), "p95_mm": float(np.percentile(error_mm, 95))}


def predict_run(params: DynamicsParams, run: dict) -> np.ndarray:
    """Open-loop [T, 3] positions (m) over the whole run, from its first observed pose."""
    pressure = jnp.asarray(run["p"], jnp.float32)
    initial_pose = jnp.asarray(run["pos"][0], jnp.float32)
    return np.asarray(_predict_sequence(params, pressure, initial_pose))


def evaluate_open_loop(params: DynamicsParams, run: dict) -> dict:
    """Open-loop error over the ENTIRE run: ``{"mean_mm", "p95_mm"}``.

    The model is fed the run's whole pressure sequence from ``t = 0`` and conditioned only on the
    observed pose at ``t = 0``.
    """
    return position_errors_mm(predict_run(params, run), run["pos"])


def baseline_mean_position(train_runs: Sequence[dict], run: dict) -> dict:
    """Errors of the constant prediction "mean training position" over ``run``."""
    mean_position = np.concatenate([r["pos"] for r in train_runs]).astype(np.float64).mean(0)
    return position_errors_mm(np.broadcast_to(mean_position, run["pos"].shape), run["pos"])


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


def fit_linear_lagged(train_runs: Sequence[dict], num_lags: int) -> np.ndarray:
    """Least-squares coefficients [1 + 6 * num_lags, 3] from lagged pressures to position (m)."""
    features = np.concatenate([lagged_features(r["p"], num_lags) for r in train_runs])
    targets = np.concatenate([np.asarray(r["pos"], np.float64) for r in train_runs])
    coefficients, *_ = np.linalg.lstsq(features, targets, rcond=None)
    return coefficients


def predict_linear_lagged(train_runs: Sequence[dict], run: dict, num_lags: int = 30
                          ) -> np.ndarray:
    """[T, 3] positions (m) over ``run`` of the linear model fitted on ``train_runs``."""
    return lagged_features(run["p"], num_lags) @ fit_linear_lagged(train_runs, num_lags)


def baseline_linear_lagged(train_runs: Sequence[dict], run: dict, num_lags: int = 30) -> dict:
    """Errors over ``run`` of the linear model on lagged pressures and their squares."""
    return position_errors_mm(predict_linear_lagged(train_runs, run, num_lags), run["pos"])


# ---------------------------------------------------------------------------------------------
# checkpoints
# ---------------------------------------------------------------------------------------------
def _model_state_dict(params: DynamicsParams) -> dict:
    return {
        "config": json.dumps(dataclasses.asdict(params.config)),
        "normalizer": serialization.to_state_dict(jax.device_get(params.normalizer)),
        "network": serialization.to_state_dict(jax.device_get(params.network)),
    }


def _model_from_state_dict(state: dict) -> DynamicsParams:
    config = DynamicsConfig(**json.loads(state["config"]))
    template_network = jax.eval_shape(
        lambda key: dynamics.init_network(key, config), jax.random.PRNGKey(0)
    )
    template_normalizer = Normalizer(*(jnp.zeros(3) for _ in range(6)))
    to_device = lambda tree: jax.tree.map(jnp.asarray, tree)  # noqa: E731
    return DynamicsParams(
        network=to_device(serialization.from_state_dict(template_network, state["network"])),
        normalizer=to_device(
            serialization.from_state_dict(template_normalizer, state["normalizer"])
        ),
        config=config,
    )


def _write_atomically(path: Path, payload: bytes) -> None:
    with atomic_write(path) as tmp:
        tmp.write_bytes(payload)


def save_dynamics(path: str | Path, params: DynamicsParams) -> None:
    """Writes the model (network, normalizer, architecture) to one msgpack file, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _write_atomically(path, serialization.msgpack_serialize({"model": _model_state_dict(params)}))


def load_dynamics(path: str | Path) -> DynamicsParams:
    """Reads a model written by :func:`save_dynamics` or a training checkpoint."""
    state = serialization.msgpack_restore(Path(path).read_bytes())
    return _model_from_state_dict(state["model"])


def checkpoint_path(checkpoint_dir: Path, step: int) -> Path:
    return checkpoint_dir / f"{CHECKPOINT_PREFIX}{step:08d}{CHECKPOINT_SUFFIX}"


def latest_checkpoint(checkpoint_dir: str | Path) -> Path | None:
    """The complete checkpoint with the highest step (temporary files are ignored)."""
    paths = sorted(Path(checkpoint_dir).glob(f"{CHECKPOINT_PREFIX}*{CHECKPOINT_SUFFIX}"))
    return paths[-1] if paths else None


def _save_checkpoint(checkpoint_dir, params, state, history, spec, keep=2) -> None:
    step = int(state.step)
    payload = {
        "model": _model_state_dict(params.replace(network=state.network)),
        "opt_state": serialization.to_state_dict(jax.device_get(state.opt_state)),
        "step": step,
        "train_loss": np.asarray(history["train_loss"], np.float32),
        "val_rows": np.asarray(history["val_rows"], np.float64).reshape(-1, 4),
        "spec": json.dumps(spec, sort_keys=True),
    }
    _write_atomically(
        checkpoint_path(checkpoint_dir, step), serialization.msgpack_serialize(payload)
    )
    for old in sorted(checkpoint_dir.glob(f"{CHECKPOINT_PREFIX}*{CHECKPOINT_SUFFIX}"))[:-keep]:
        old.unlink()


class CorruptCheckpointError(ValueError):
    """A checkpoint file that cannot be read back (cut off, overwritten, not a checkpoint)."""


def _restore_checkpoint(path: Path, template: TrainState, spec: dict):
    try:
        raw = serialization.msgpack_restore(path.read_bytes())
        stored_spec = json.loads(raw["spec"])
        model = _model_from_state_dict(raw["model"])
        opt_state = serialization.from_state_dict(template.opt_state, raw["opt_state"])
        step, train_loss, val_rows = raw["step"], raw["train_loss"], raw["val_rows"]
    except Exception as err:  # msgpack, KeyError, shape errors: all mean "not a checkpoint"
        raise CorruptCheckpointError(f"checkpoint {path} cannot be read "
                                     f"({type(err).__name__}: {err})") from err
    if stored_spec != spec:
        differing = sorted(k for k in set(spec) | set(stored_spec)
                           if spec.get(k) != stored_spec.get(k))
        raise ValueError(
            f"checkpoint {path} was written by a different training setup (differs in "
            f"{differing}); use another checkpoint_dir or resume=False"
        )
    state = TrainState(
        network=model.network,
        opt_state=jax.tree.map(jnp.asarray, opt_state),
        step=jnp.asarray(step, jnp.int32),
    )
    history = {
        "train_loss": list(np.asarray(train_loss, np.float32)),
        "val_rows": [tuple(row) for row in np.asarray(val_rows).reshape(-1, 4)],
    }
    return state, history


def _resume(checkpoint_dir: Path, state: TrainState, history: dict, spec: dict):
    """The newest readable checkpoint's state and history (else the given ones); a corrupt
    checkpoint is logged by name and set aside as ``<name>.corrupt``, and the next one tried."""
    paths = sorted(checkpoint_dir.glob(f"{CHECKPOINT_PREFIX}*{CHECKPOINT_SUFFIX}"))
    for path in reversed(paths):
        try:
            restored = _restore_checkpoint(path, state, spec)
        except CorruptCheckpointError as err:
            aside = path.with_name(path.name + ".corrupt")
            os.replace(path, aside)
            log.warning("%s; moved it to %s and %s", err, aside,
                        "trying the one before" if path != paths[0] else "training afresh")
            continue
        log.info("resuming from checkpoint %s (step %d)", path, int(restored[0].step))
        return restored
    return state, history


# ---------------------------------------------------------------------------------------------
# fit
# ---------------------------------------------------------------------------------------------
def _validate(params: DynamicsParams, val_runs: Sequence[dict]) -> tuple[float, float, float]:
    """(standardized MSE, mean mm, p95 mm) of the open-loop prediction, pooled over val runs."""
    losses, errors = [], []
    for run in val_runs:
        predicted = predict_run(params, run)
        initial_pose = jnp.asarray(run["pos"][0])
        predicted_normalized = dynamics.normalize_target(params, predicted, initial_pose)
        observed_normalized = dynamics.normalize_target(params, run["pos"], initial_pose)
        losses.append(np.square(np.asarray(predicted_normalized - observed_normalized)).ravel())
        errors.append(1000.0 * np.linalg.norm(predicted - run["pos"], axis=-1))
    errors = np.concatenate(errors)
    return (
        float(np.concatenate(losses).mean()),
        float(errors.mean()),
        float(np.percentile(errors, 95)),
    )


def _loss_table(history: dict) -> pd.DataFrame:
    train_loss = np.asarray(history["train_loss"], np.float64)
    table = pd.DataFrame({"step": np.arange(1, len(train_loss) + 1), "train_loss": train_loss})
    val = pd.DataFrame(history["val_rows"], columns=["step", "val_loss", "val_mean_mm",
                                                     "val_p95_mm"])
    val["step"] = val["step"].astype(np.int64)
    return table.merge(val, on="step", how="left")[LOSS_TABLE_COLUMNS]


_batched_network_inputs = jax.jit(jax.vmap(dynamics.network_inputs, in_axes=(None, 0)))


def run_inputs(params: DynamicsParams, runs: Sequence[dict]) -> list[np.ndarray]:
    """Per run, the [T_i, D] float32 standardized network inputs over the whole run.

    The runs are padded (with their last pressure) to a common length and computed in one
    vmapped call; the features are causal, so the padding does not change the real rows.
    """
    lengths = [len(run["p"]) for run in runs]
    longest = max(lengths)
    padded = np.stack([
        np.concatenate([run["p"], np.repeat(run["p"][-1:], longest - len(run["p"]), axis=0)])
        for run in runs
    ]).astype(np.float32)
    inputs = np.asarray(_batched_network_inputs(params, jnp.asarray(padded)))
    return [inputs[i, :length] for i, length in enumerate(lengths)]


def _reference_poses(runs: Sequence[dict], source: str) -> np.ndarray:
    """[N, 3] float32: per row of the concatenated runs, the initial pose of a window there."""
    if source == "window_start":
        return np.concatenate([r["pos"] for r in runs]).astype(np.float32)
    return np.concatenate(
        [np.broadcast_to(r["pos"][0], r["pos"].shape) for r in runs]
    ).astype(np.float32)


def fit(
    train_runs: Sequence[dict],
    model_cfg: Any,
    *,
    window: int,
    stride: int = 1,
    order: str = "permuted",
    val_runs: Sequence[dict] = (),
    checkpoint_dir: str | Path | None = None,
    resume: bool = True,
    progress: bool = True,
    stop_after_steps: int | None = None,
    time_budget_s: float | None = None,
) -> tuple[DynamicsParams, Normalizer, pd.DataFrame]:
    """Trains the dynamics on ``train_runs``; returns (params, normalizer, loss_table).

    Args:
        train_runs: runs at the model rate (module docstring).
        model_cfg: anything :meth:`ModelTrainConfig.from_any` reads.
        window, stride, order: sliding windows in model steps and their order
            (``permuted`` or ``sequential``, see ``windows.sample_batch``).
        val_runs: held-out runs, evaluated open loop every ``eval_every`` steps and at the end.
        checkpoint_dir: where checkpoints go every ``checkpoint_every`` steps and at the end.
        resume: continue from the last checkpoint in ``checkpoint_dir`` if there is one (it
            must come from the same setup, else ``ValueError``).
        stop_after_steps: stop (after checkpointing) once this many steps are done, as if
            interrupted; for time-sliced jobs and the resume test.
        time_budget_s: also stop after the chunk during which this many seconds (compilation
            included) have passed since the call; for equal wall-clock budgets (bench).

    Returns:
        params: the trained model (``params.normalizer`` is the returned normalizer).
        normalizer: statistics of ``train_runs``.
        loss_table: one row per step (``step``, ``train_loss``) with ``val_loss``,
            ``val_mean_mm``, ``val_p95_mm`` filled on evaluation steps.
    """
    started = time.perf_counter()
    config = ModelTrainConfig.from_any(model_cfg)
    windows = make_windows([len(run["p"]) for run in train_runs], window, stride)
    if len(windows.starts) == 0:
        raise ValueError(f"no training window of length {window} fits in any training run")
    spec = {
        "model": dataclasses.asdict(config),
        "window": window,
        "stride": stride,
        "order": order,
        "train_run_ids": [str(run["run_id"]) for run in train_runs],
    }
    spec = json.loads(json.dumps(spec))  # tuples -> lists, as they come back from the file

    normalizer = dynamics.fit_normalizer(train_runs, config.predict_displacement)
    init_key, sample_key = jax.random.split(jax.random.PRNGKey(config.seed))
    template = DynamicsParams(
        network=dynamics.init_network(init_key, config.architecture()),
        normalizer=normalizer,
        config=config.architecture(),
    )
    optimizer = make_optimizer(config)
    state = TrainState(
        network=template.network,
        opt_state=optimizer.init(template.network),
        step=jnp.asarray(0, jnp.int32),
    )
    history = {"train_loss": [], "val_rows": []}

    if checkpoint_dir is not None:
        checkpoint_dir = Path(checkpoint_dir)
        checkpoint_dir.mkdir(parents=True, exist_ok=True)
        if resume:
            state, history = _resume(checkpoint_dir, state, history, spec)

    data = TrainData(
        inputs=jnp.asarray(np.concatenate(run_inputs(template, train_runs))),
        position=jnp.asarray(np.concatenate([r["pos"] for r in train_runs]), jnp.float32),
        reference_pose=jnp.asarray(_reference_poses(train_runs, config.reference_pose)),
        window_starts=jnp.asarray(windows.starts, jnp.int32),
        num_windows=jnp.asarray(len(windows.starts), jnp.int32),
    )
    chunk = math.gcd(config.eval_every, config.checkpoint_every)
    last_step = config.num_steps
    if stop_after_steps is not None:
        last_step = min(last_step, stop_after_steps)

    step = int(state.step)
    bar = tqdm(total=config.num_steps, initial=step, disable=not progress, desc="fit dynamics",
               dynamic_ncols=True)
    while step < last_step:
        num = min(chunk - step % chunk, last_step - step)
        state, losses = train_chunk(
            state, data, normalizer, sample_key, config=config, window=window, order=order,
            num_steps=num,
        )
        losses = np.asarray(losses)
        history["train_loss"].extend(losses.tolist())
        step = int(state.step)
        postfix = {"loss": f"{losses[-1]:.4f}"}
        if val_runs and (step % config.eval_every == 0 or step == config.num_steps):
            val = _validate(template.replace(network=state.network), val_runs)
            history["val_rows"].append((step, *val))
            postfix["val_mm"] = f"{val[1]:.2f}"
        bar.set_postfix(postfix)
        bar.update(num)
        at_checkpoint = step % config.checkpoint_every == 0 or step == last_step
        out_of_time = (time_budget_s is not None
                       and time.perf_counter() - started >= time_budget_s)
        if checkpoint_dir is not None and (at_checkpoint or out_of_time):
            _save_checkpoint(checkpoint_dir, template, state, history, spec)
        if out_of_time:
            break
    bar.close()
    params = template.replace(network=state.network)
    return params, normalizer, _loss_table(history)


def evaluation_table(params, train_runs: list[dict], test_runs: list[dict]) -> pd.DataFrame:
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
                rows.append({"run_id": run["run_id"], "split": split, "fold": -1,
                             "held_out": "", "seed": 0, "model": model,
                             "steps": len(run["p"]), **values,
                             "loses_to_linear": bool(loses and model == LEARNED)})
    return pd.DataFrame(rows)
