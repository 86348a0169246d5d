"""Training of the learned dynamics (``model.py``); its files are ``checkpoints.py``, its
open-loop scores and baselines ``scoring.py``.

Runs are :class:`pipeline.data.runs.Run` records on a regular grid at the model rate
(``times_s`` [T] s, ``pressures_kpa`` [T, 3] kPa, ``positions_m`` [T, 3] m).

Training minimizes the mean squared standardized error over sliding windows (``windows.py``).
Each window starts from the zero/conditioned carry and is given as initial pose the pose its run
started from (the rest pose an environment observes at reset), so a window in the middle of a
run is trained to predict its positions from that run's rest pose and the pressures. The
jitted train step runs ``lax.scan`` over a chunk of steps between evaluations/checkpoints, so the
Python loop only sees chunk boundaries. Batches are a pure function of ``(seed, step)``, so
resuming from the last checkpoint reproduces the uninterrupted training.
"""

from __future__ import annotations

import dataclasses
import json
import math
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
from tqdm.auto import tqdm

from pipeline.data.runs import Run
from pipeline.data.windows import gather_windows, make_windows, sample_batch, weighted_starts
from pipeline.dynamics import checkpoints
from pipeline.dynamics import model as dynamics
from pipeline.dynamics.checkpoints import TrainState
from pipeline.dynamics.model import DynamicsConfig, DynamicsParams, Normalizer
from pipeline.dynamics.scoring import validation_errors
from pipeline.schemas import (
    ModelArchitecture,
    ModelConfig,
    ModelLoss,
    dataclass_values,
    frozen_twin,
)

LOSS_TABLE_COLUMNS = ["step", "train_loss", "val_loss", "val_mean_mm", "val_p95_mm"]


# ---------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ModelTrainConfig(frozen_twin(ModelConfig, "ModelSettings")):
    """The ``model`` config group (``pipeline.schemas.ModelConfig``, its only declaration) as a
    frozen dataclass: model and optimizer settings. Defaults: the CPU recipe.

    The paper's configuration is ``hidden=1024, batch_size=64, learning_rate=1e-3,
    lr_schedule="constant", num_steps=200_000, condition_on_initial_pose=False,
    predict_displacement=False`` with windows of 512 at 100 Hz (dataset settings).
    """

    def __post_init__(self):
        dynamics.freeze_lists(self)
        object.__setattr__(self, "init_from", tuple(str(entry) for entry in self.init_from))
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
        return cls(**dataclass_values(cls, config, "model"))

    def architecture(self) -> DynamicsConfig:
        """The network part of these settings (the saved model's config)."""
        return DynamicsConfig(**{f.name: getattr(self, f.name)
                                 for f in dataclasses.fields(ModelArchitecture)})


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
    row_run: [N] int32, the index of each row's run (the row of its session latent,
        ``dynamics.init_session``); ``None`` for a model without session latents.
    """

    inputs: jax.Array
    position: jax.Array
    reference_pose: jax.Array
    window_starts: jax.Array
    num_windows: jax.Array
    row_run: jax.Array | None = None


DISTANCE_EPS = 1e-3  # [target std]: keeps the distance loss's gradient finite at zero error


def window_loss(
    params: DynamicsParams,
    inputs: jax.Array,
    position: jax.Array,
    initial_pose: jax.Array,
    hidden_mask: jax.Array | None = None,
    loss: str = "mse",
    latent: jax.Array | None = None,
) -> jax.Array:
    """Error of the open-loop rollout over a batch of windows, a scalar.

    inputs: [B, W, D] standardized network inputs; position: [B, W, 3] m; initial_pose: [B, 3]
    m, the pose each rollout is conditioned on (and displacements are measured from);
    hidden_mask: optional [B, layers, hidden] recurrent-dropout masks. ``loss``: ``mse``, the
    mean over windows, steps and axes of the squared standardized error; ``distance``, the mean
    over windows and steps of the Euclidean distance to the measured position, in units of the
    mean target standard deviation (so both losses are of order one), smoothed by
    :data:`DISTANCE_EPS` at zero. ``latent``: optional [B, d] session latent of each window's
    run (a model with session latents).
    """
    targets = jax.vmap(dynamics.normalize_target, in_axes=(None, 0, 0))(
        params, position, initial_pose
    )
    pose_normalized = dynamics.normalize_pose(params.normalizer, initial_pose)
    if latent is None:
        outputs = jax.vmap(dynamics.predict_normalized, in_axes=(None, 0, 0, 0))(
            params, inputs, pose_normalized, hidden_mask)
    else:
        outputs = jax.vmap(dynamics.predict_normalized, in_axes=(None, 0, 0, 0, 0))(
            params, inputs, pose_normalized, hidden_mask, latent)
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
    latent_prior: float = 0.0,
) -> Callable[[TrainState, TrainData, jax.Array], tuple[TrainState, jax.Array]]:
    """``train_step(state, data, sample_key) -> (state, loss)``: one Adam step on one batch.

    ``model_template`` supplies the normalizer and architecture; its network is replaced by the
    trained one. The batch of step ``k`` depends only on ``(sample_key, k)``, and so do the
    input noise and dropout masks (drawn from a key split off ``sample_key`` and folded with
    ``k``). The data is an argument (not a closure) so a jitted program does not embed the
    dataset as constants.

    A network with a session collection (``dynamics.init_session``) trains its per-run
    latents with the weights: each window reads its run's latent (``data.row_run``), and the
    loss adds ``latent_prior`` times the batch's mean squared latent norm (a Gaussian prior
    that keeps the latents in one shared space around 0).
    """
    config = model_template.config

    def loss_fn(network, inputs, position, initial_pose, hidden_mask, runs):
        params = model_template.replace(network=network)
        if runs is None:
            return window_loss(params, inputs, position, initial_pose, hidden_mask, loss)
        latent = network[dynamics.SESSION]["latents"][runs]  # [B, d]
        prior = latent_prior * jnp.mean(jnp.sum(jnp.square(latent), axis=-1))
        return window_loss(params, inputs, position, initial_pose, hidden_mask, loss,
                           latent) + prior

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
        runs = None
        if isinstance(state.network, dict) and dynamics.SESSION in state.network:
            runs = data.row_run[starts]
        loss, grads = jax.value_and_grad(loss_fn)(state.network, inputs, position, initial_pose,
                                                  hidden_mask, runs)
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
    latent_prior: float = 0.0,
) -> tuple[TrainState, jax.Array]:
    """``num_steps`` training steps in one ``lax.scan``: ``-> (state, losses [num_steps])``.
    ``latent_prior``: the session latents' prior weight (:func:`make_train_step`).

    :func:`train_chunk` is this jitted, once per (config, window, order, num_steps) and data
    shapes, so fits that share them (resumed runs) reuse the compiled program;
    ``pipeline.dynamics.cv`` vmaps it over folds and seeds.
    """
    template = DynamicsParams(network=state.network, normalizer=normalizer,
                              config=config.architecture())
    train_step = make_train_step(
        template, make_optimizer(config), window, config.batch_size, order,
        input_noise_std=config.input_noise_std, recurrent_dropout=config.recurrent_dropout,
        loss=str(config.loss), latent_prior=latent_prior,
    )
    return jax.lax.scan(
        lambda s, _: train_step(s, data, sample_key), state, None, length=num_steps
    )


train_chunk = jax.jit(train_chunk_unjitted,
                      static_argnames=("config", "window", "order", "num_steps", "latent_prior"))


# ---------------------------------------------------------------------------------------------
# fit
# ---------------------------------------------------------------------------------------------
def run_inputs(params: DynamicsParams, runs: Sequence[Run]) -> list[np.ndarray]:
    """Per run, the [T_i, D] float32 standardized network inputs over the whole run.

    The runs are padded (with their last pressure) to a common length and computed in one
    vmapped call; the features are causal, so the padding does not change the real rows.
    """
    lengths = [len(run) for run in runs]
    longest = max(lengths)
    padded = np.stack([
        np.concatenate([run.pressures_kpa,
                        np.repeat(run.pressures_kpa[-1:], longest - len(run), axis=0)])
        for run in runs
    ]).astype(np.float32)
    inputs = np.asarray(_batched_network_inputs(params, jnp.asarray(padded)))
    return [inputs[i, :length] for i, length in enumerate(lengths)]


def reference_poses(runs: Sequence[Run], source: str) -> np.ndarray:
    """[N, 3] float32: per row of the concatenated runs, the initial pose of a window there."""
    if source == "window_start":
        return np.concatenate([r.positions_m for r in runs]).astype(np.float32)
    return np.concatenate(
        [np.broadcast_to(r.positions_m[0], r.positions_m.shape) for r in runs]
    ).astype(np.float32)


def _loss_table(history: dict) -> pd.DataFrame:
    train_loss = np.asarray(history["train_loss"], np.float64)
    table = pd.DataFrame({"step": np.arange(1, len(train_loss) + 1), "train_loss": train_loss})
    val = pd.DataFrame(history["val_rows"], columns=["step", "val_loss", "val_mean_mm",
                                                     "val_p95_mm"])
    val["step"] = val["step"].astype(np.int64)
    return table.merge(val, on="step", how="left")[LOSS_TABLE_COLUMNS]


_batched_network_inputs = jax.jit(jax.vmap(dynamics.network_inputs, in_axes=(None, 0)))


def _fit_spec(config: ModelTrainConfig, window: int, stride: int, order: str,
              train_runs: Sequence[Run]) -> dict:
    """What a checkpoint of this fit must match to be resumed from."""
    spec = {
        "model": dataclasses.asdict(config),
        "window": window,
        "stride": stride,
        "order": order,
        "train_run_ids": [run.run_id for run in train_runs],
    }
    return json.loads(json.dumps(spec))  # tuples -> lists, as they come back from the file


def train_data(template: DynamicsParams, runs: Sequence[Run], window_starts: np.ndarray,
               reference_pose: str) -> TrainData:
    """The :class:`TrainData` of ``runs`` (their inputs standardized by ``template``)."""
    return TrainData(
        inputs=jnp.asarray(np.concatenate(run_inputs(template, runs))),
        position=jnp.asarray(np.concatenate([r.positions_m for r in runs]), jnp.float32),
        reference_pose=jnp.asarray(reference_poses(runs, reference_pose)),
        window_starts=jnp.asarray(window_starts, jnp.int32),
        num_windows=jnp.asarray(len(window_starts), jnp.int32),
    )


def fit(
    train_runs: Sequence[Run],
    model_cfg: Any,
    *,
    window: int,
    stride: int = 1,
    order: str = "permuted",
    val_runs: Sequence[Run] = (),
    checkpoint_dir: str | Path | None = None,
    resume: bool = True,
    progress: bool = True,
    stop_after_steps: int | None = None,
    time_budget_s: float | None = None,
    run_weights: Sequence[float] | None = None,
    init: DynamicsParams | None = None,
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
        run_weights: per training run, how often its windows are drawn relative to a run of
            weight 1 (``pipeline.data.windows.weighted_starts``); None: all alike.
        init: a fitted model to start from (its network and its normalization, kept: a warm
            start); its architecture must be this config's. None: a fresh network.

    Returns:
        params: the trained model (``params.normalizer`` is the returned normalizer).
        normalizer: statistics of ``train_runs``.
        loss_table: one row per step (``step``, ``train_loss``) with ``val_loss``,
            ``val_mean_mm``, ``val_p95_mm`` filled on evaluation steps.
    """
    started = time.perf_counter()
    config = ModelTrainConfig.from_any(model_cfg)
    # where a warm start comes from is the caller's: the program and the checkpoints see the
    # starting network itself
    config = dataclasses.replace(config, init_from=())
    windows = make_windows([len(run) for run in train_runs], window, stride)
    starts = (windows.starts if run_weights is None
              else weighted_starts(windows, run_weights))
    if len(starts) == 0:
        raise ValueError(f"no training window of length {window} fits in any training run")
    spec = _fit_spec(config, window, stride, order, train_runs)
    if run_weights is not None:
        spec["run_weights"] = [float(w) for w in run_weights]

    init_key, sample_key = jax.random.split(jax.random.PRNGKey(config.seed))
    if init is None:
        normalizer = dynamics.fit_normalizer(train_runs, config.predict_displacement)
        network = dynamics.init_network(init_key, config.architecture())
    else:
        if isinstance(init.network, dict) and dynamics.SESSION in init.network:
            raise ValueError("a model with session latents cannot be started from: its latents "
                             "belong to the runs it was fitted on")
        if init.config != config.architecture():
            raise ValueError(f"the model to start from has another architecture ({init.config}) "
                             f"than model ({config.architecture()})")
        normalizer, network = init.normalizer, init.network
        spec["init_sha256"] = checkpoints.params_digest(init)
    template = DynamicsParams(network=network, normalizer=normalizer,
                              config=config.architecture())
    state = TrainState(
        network=template.network,
        opt_state=make_optimizer(config).init(template.network),
        step=jnp.asarray(0, jnp.int32),
    )
    history = {"train_loss": [], "val_rows": []}
    if checkpoint_dir is not None:
        checkpoint_dir = Path(checkpoint_dir)
        checkpoint_dir.mkdir(parents=True, exist_ok=True)
        if resume:
            state, history = checkpoints.resume(checkpoint_dir, state, history, spec)

    data = train_data(template, train_runs, starts, config.reference_pose)
    last_step = config.num_steps
    if stop_after_steps is not None:
        last_step = min(last_step, stop_after_steps)
    run_chunk = lambda state, num: train_chunk(  # noqa: E731
        state, data, normalizer, sample_key, config=config, window=window, order=order,
        num_steps=num)
    deadline = None if time_budget_s is None else started + time_budget_s
    state = _training_loop(run_chunk, state, history, template, config, val_runs, last_step,
                           checkpoint_dir, spec, deadline, progress)
    params = template.replace(network=state.network)
    return params, normalizer, _loss_table(history)


def _training_loop(run_chunk, state: TrainState, history: dict, template: DynamicsParams,
                   config: ModelTrainConfig, val_runs: Sequence[Run], last_step: int,
                   checkpoint_dir: Path | None, spec: dict, deadline: float | None,
                   progress: bool) -> TrainState:
    """Chunks of ``run_chunk(state, num_steps) -> (state, losses)`` up to ``last_step``, with
    validation (appended to ``history``) and checkpoints at their steps; stops early after the
    chunk that passes ``deadline`` (``time.perf_counter`` seconds)."""
    chunk = math.gcd(config.eval_every, config.checkpoint_every)
    step = int(state.step)
    bar = tqdm(total=config.num_steps, initial=step, disable=not progress, desc="fit dynamics",
               dynamic_ncols=True)
    while step < last_step:
        num = min(chunk - step % chunk, last_step - step)
        state, losses = run_chunk(state, num)
        losses = np.asarray(losses)
        history["train_loss"].extend(losses.tolist())
        step = int(state.step)
        postfix = {"loss": f"{losses[-1]:.4f}"}
        if val_runs and (step % config.eval_every == 0 or step == config.num_steps):
            val = validation_errors(template.replace(network=state.network), val_runs)
            history["val_rows"].append((step, *val))
            postfix["val_mm"] = f"{val[1]:.2f}"
        bar.set_postfix(postfix)
        bar.update(num)
        at_checkpoint = step % config.checkpoint_every == 0 or step == last_step
        out_of_time = deadline is not None and time.perf_counter() >= deadline
        if checkpoint_dir is not None and (at_checkpoint or out_of_time):
            checkpoints.save_checkpoint(checkpoint_dir, template, state, history, spec)
        if out_of_time:
            break
    bar.close()
    return state
