"""Run-wise cross-validation of the learned dynamics, all fold models in one jitted program.

A *member* is one model to train: the runs it trains on, the run it is scored on (``None`` for
the model trained on all runs) and its seed. :func:`fit_members` trains every member at once:
``train_model.train_chunk_unjitted`` is ``jax.vmap``-ed over members, each with its own
normalizer (statistics of its training runs), initial network and batch key, over one shared
concatenation of all runs in which each member samples only the windows of its training runs
(its window list is padded to the longest one; ``windows.sample_batch`` draws from the first
``num_windows`` entries exactly the batches of the unpadded list). A member therefore trains
exactly as ``train_model.fit`` would on its runs, and K fold models cost one program.

Leave-one-run-out (:func:`loro_folds`): every run is held out once. :func:`cv_metrics` scores
each fold model open loop over its held-out run and its training runs, next to the mean-position
and linear lagged-pressure baselines fitted on the same training runs, and flags every fold on
which the model does not beat the linear baseline.

Checkpoints (stacked states of all members, msgpack, atomic) go to ``checkpoint_dir`` every
``checkpoint_every`` steps; batches are a pure function of ``(seed, step)``, so a resumed run
reproduces the uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from pipeline.data.runs import Run
from pipeline.data.windows import make_windows
from pipeline.dynamics import checkpoints
from pipeline.dynamics import model as dynamics
from pipeline.dynamics.checkpoints import TrainState
from pipeline.dynamics.model import DynamicsParams
from pipeline.dynamics.scoring import (
    LEARNED,
    LINEAR_LAGS,
    MODELS,
    baseline_mean_position,
    fit_linear_lagged,
    lagged_features,
    position_errors_mm,
    predict_run,
)
from pipeline.dynamics.session_latent import SessionLatentSettings
from pipeline.dynamics.training import (
    ModelTrainConfig,
    TrainData,
    make_optimizer,
    reference_poses,
    run_inputs,
    train_chunk_unjitted,
)
from pipeline.infra.devices import batch_split

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Member:
    """One model of a vmapped training: its training runs, held-out run and seed."""

    train_ids: tuple[str, ...]
    held_out: str | None = None  # None: trained on all runs, scored on its training runs
    seed: int = 0


def loro_folds(run_ids: Sequence[str]) -> list[tuple[list[str], str]]:
    """Leave-one-run-out: ``[(train ids, held-out id)]``, one per run, in sorted id order.

    Every run is held out exactly once and trains in every other fold. Needs two runs or more.
    """
    ids = sorted(str(i) for i in run_ids)
    if len(set(ids)) != len(ids):
        raise ValueError(f"duplicate run ids: {ids}")
    if len(ids) < 2:
        raise ValueError(f"cross-validation over runs needs at least 2 runs, got {ids}")
    return [([i for i in ids if i != held_out], held_out) for held_out in ids]


def cv_members(run_ids: Sequence[str], seeds: Sequence[int] = (0,), final: bool = True
               ) -> list[Member]:
    """The LORO fold members for each seed, then (``final``) the all-runs model of seeds[0]."""
    members = [Member(tuple(train), held_out, int(seed))
               for seed in seeds for train, held_out in loro_folds(run_ids)]
    if final:
        members.append(Member(tuple(sorted(str(i) for i in run_ids)), None, int(seeds[0])))
    return members


# ---------------------------------------------------------------------------------------------
# vmapped training
# ---------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=8)
def _members_chunk(config: ModelTrainConfig, window: int, order: str, num_steps: int,
                   latent_prior: float = 0.0):
    """Jitted ``(states, data, normalizers, sample_keys) -> (states, losses [M, num_steps])``."""
    chunk = functools.partial(train_chunk_unjitted, config=config, window=window, order=order,
                              num_steps=num_steps, latent_prior=latent_prior)
    data_axes = TrainData(inputs=0, position=None, reference_pose=None, window_starts=0,
                          num_windows=0, row_run=None)
    return jax.jit(jax.vmap(chunk, in_axes=(0, data_axes, 0, 0)))


def _stack(trees: Sequence[Any]) -> Any:
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *trees)


def _unstack(tree: Any, index: int) -> Any:
    return jax.tree.map(lambda leaf: leaf[index], tree)


def _member_spec(config: ModelTrainConfig, members: Sequence[Member], window: int, stride: int,
                 order: str, latent: SessionLatentSettings | None = None) -> dict:
    spec = {"model": dataclasses.asdict(config), "window": window, "stride": stride,
            "order": order, "members": [dataclasses.asdict(m) for m in members]}
    if latent is not None:
        spec["session_latent"] = dataclasses.asdict(latent)
    return json.loads(json.dumps(spec))  # tuples -> lists, as they come back from the file


def fit_members(
    runs: Sequence[Run],
    members: Sequence[Member],
    model_cfg: Any,
    *,
    window: int,
    stride: int = 1,
    order: str = "permuted",
    checkpoint_dir: str | Path | None = None,
    resume: bool = True,
    progress: bool = True,
    stop_after_steps: int | None = None,
    latent: SessionLatentSettings | None = None,
) -> tuple[list[DynamicsParams], np.ndarray]:
    """Trains every member in one vmapped program; ``(params per member, losses [M, steps])``.

    Args:
        runs: runs at the model rate (``train_model`` docstring); every member's ids among them.
        members: what to train; each member's seed replaces the model settings' ``seed``.
        model_cfg: the model settings (a :class:`pipeline.schemas.ModelConfig` or anything
            ``ModelTrainConfig.from_any`` reads), the same for all members.
        window, stride, order: sliding windows, as for ``train_model.fit``.
        checkpoint_dir, resume: stacked checkpoints every ``checkpoint_every`` steps and at the
            end; resume from the last one (same setup, else ``ValueError``).
        stop_after_steps: stop (after checkpointing) once this many steps are done.
        latent: train each member with a learned session latent per run
            (:mod:`pipeline.dynamics.session_latent`): its model's session collection holds one
            latent per run of ``runs`` sorted by id (a member's held-out run's row stays 0).
    """
    config = ModelTrainConfig.from_any(model_cfg)
    if not members:
        raise ValueError("fit_members needs at least one member")
    runs = sorted(runs, key=lambda run: run.run_id)
    member_starts = _member_windows(runs, members, window, stride)
    templates, state, sample_keys = _initial_members(runs, members, config, latent)
    capacity = max(len(starts) for starts in member_starts)
    data = TrainData(
        inputs=jnp.asarray(np.stack([np.concatenate(run_inputs(t, runs)) for t in templates])),
        position=jnp.asarray(np.concatenate([r.positions_m for r in runs]), jnp.float32),
        reference_pose=jnp.asarray(reference_poses(runs, config.reference_pose)),
        window_starts=jnp.asarray(np.stack(
            [np.pad(s, (0, capacity - len(s))) for s in member_starts]), jnp.int32),
        num_windows=jnp.asarray([len(s) for s in member_starts], jnp.int32),
        row_run=None if latent is None else jnp.asarray(np.concatenate(
            [np.full(len(run), i) for i, run in enumerate(runs)]), jnp.int32),
    )
    normalizers = _stack([t.normalizer for t in templates])

    spec = _member_spec(config, members, window, stride, order, latent)
    prior = 0.0 if latent is None else float(latent.prior)
    losses: list[np.ndarray] = []
    if checkpoint_dir is not None:
        checkpoint_dir = Path(checkpoint_dir)
        checkpoint_dir.mkdir(parents=True, exist_ok=True)
        last = checkpoints.latest_checkpoint(checkpoint_dir) if resume else None
        if last is not None:
            state, losses = checkpoints.restore_members(last, state, spec)
    # the members split over the devices (the CPU's cores: pipeline.infra.devices), each part
    # in parallel; every member trains as it trains in one batch, to float rounding
    split = batch_split(len(members))
    if split is not None:
        state, normalizers, sample_keys = split.put((state, normalizers, sample_keys))
        data = data._replace(**split.put({"inputs": data.inputs,
                                          "window_starts": data.window_starts,
                                          "num_windows": data.num_windows}),
                             **split.put({"position": data.position,
                                          "reference_pose": data.reference_pose,
                                          "row_run": data.row_run}, axis=None))

    last_step = config.num_steps if stop_after_steps is None else min(config.num_steps,
                                                                      stop_after_steps)
    chunk = max(1, math.gcd(config.checkpoint_every, config.num_steps))
    step = int(state.step[0])
    bar = tqdm(total=config.num_steps, initial=step, disable=not progress,
               desc=f"fit {len(members)} models", dynamic_ncols=True)
    while step < last_step:
        num = min(chunk - step % chunk, last_step - step)
        state, chunk_losses = _members_chunk(config, window, order, num, prior)(
            state, data, normalizers, sample_keys)
        losses.append(np.asarray(chunk_losses))
        step = int(state.step[0])
        bar.set_postfix({"loss": f"{float(np.mean(losses[-1][:, -1])):.4f}"})
        bar.update(num)
        if checkpoint_dir is not None and (step % config.checkpoint_every == 0
                                           or step == last_step):
            checkpoints.save_members(checkpoint_dir, state, losses, spec)
    bar.close()
    params = [t.replace(network=_unstack(state.network, m)) for m, t in enumerate(templates)]
    history = (np.concatenate(losses, axis=1) if losses
               else np.zeros((len(members), 0), np.float32))
    return params, history


def _member_windows(runs: Sequence[Run], members: Sequence[Member], window: int, stride: int
                    ) -> list[np.ndarray]:
    """Per member, the starts of its training windows in the concatenation of ``runs`` (sorted
    by id); ``ValueError`` naming the member for unknown ids or no window."""
    index_of = {run.run_id: i for i, run in enumerate(runs)}
    for member in members:
        unknown = [i for i in (*member.train_ids, *([member.held_out] if member.held_out else []))
                   if i not in index_of]
        if unknown or not member.train_ids:
            raise ValueError(f"member {member}: unknown run ids {unknown} (runs: "
                             f"{sorted(index_of)}) or no training run")
    windows = make_windows([len(run) for run in runs], window, stride)
    member_starts = []
    for member in members:
        chosen = np.isin(windows.run_index, [index_of[i] for i in member.train_ids])
        if not chosen.any():
            raise ValueError(f"no training window of length {window} fits in the training runs "
                             f"of {member}")
        member_starts.append(windows.starts[chosen])
    return member_starts


def _initial_members(runs: Sequence[Run], members: Sequence[Member], config: ModelTrainConfig,
                     latent: SessionLatentSettings | None = None
                     ) -> tuple[list[DynamicsParams], TrainState, jax.Array]:
    """Per member its template (normalizer of its training runs, initial network of its seed,
    with ``latent`` its session collection), the stacked initial training state and the
    stacked batch keys [M, 2]."""
    by_id = {run.run_id: run for run in runs}
    optimizer = make_optimizer(config)
    architecture = config.architecture()
    templates, states, sample_keys = [], [], []
    for member in members:
        train_runs = [by_id[i] for i in member.train_ids]
        normalizer = dynamics.fit_normalizer(train_runs, config.predict_displacement)
        init_key, sample_key = jax.random.split(jax.random.PRNGKey(member.seed))
        if latent is not None:
            init_key, session_key = jax.random.split(init_key)
        template = DynamicsParams(network=dynamics.init_network(init_key, architecture),
                                  normalizer=normalizer, config=architecture)
        if latent is not None:
            template = dynamics.init_session(session_key, template, len(runs), latent.dim)
        templates.append(template)
        states.append(TrainState(network=template.network,
                                 opt_state=optimizer.init(template.network),
                                 step=jnp.asarray(0, jnp.int32)))
        sample_keys.append(sample_key)
    return templates, _stack(states), jnp.stack(sample_keys)


# ---------------------------------------------------------------------------------------------
# scoring
# ---------------------------------------------------------------------------------------------
def cv_metrics(runs: Sequence[Run], members: Sequence[Member],
               params: Sequence[DynamicsParams], num_lags: int = LINEAR_LAGS) -> pd.DataFrame:
    """Open-loop errors over entire runs, per member and run (the ``model_metrics`` table).

    Fold members (a held-out run): ``split="cv"`` rows on the held-out run and ``"cv_train"``
    rows on each training run. The all-runs member: ``"train"`` rows. Each row for the model
    (``learned``), the mean training position and the linear lagged-pressure model fitted on the
    member's training runs. ``fold``: the member's index among the fold members (-1: all runs).
    ``loses_to_linear``: on the model's ``cv`` rows, its mean error is not below the linear
    baseline's on that fold.
    """
    by_id = {run.run_id: run for run in runs}
    rows = []
    fold = 0
    for member, member_params in zip(members, params):
        train_runs = [by_id[i] for i in member.train_ids]
        coefficients = fit_linear_lagged(train_runs, num_lags)
        scored = ([("cv", by_id[member.held_out])] if member.held_out else []) + [
            ("cv_train" if member.held_out else "train", run) for run in train_runs]
        for split, run in scored:
            linear = lagged_features(run.pressures_kpa, num_lags) @ coefficients
            errors = {LEARNED: position_errors_mm(predict_run(member_params, run),
                                                  run.positions_m),
                      "mean_position": baseline_mean_position(train_runs, run),
                      "linear_lagged": position_errors_mm(linear, run.positions_m)}
            loses = bool(split == "cv" and errors[LEARNED]["mean_mm"]
                         >= errors["linear_lagged"]["mean_mm"])
            for model in MODELS:
                rows.append({"run_id": run.run_id, "split": split,
                             "fold": fold if member.held_out else -1,
                             "held_out": member.held_out or "", "seed": member.seed,
                             "model": model, "steps": len(run), "context_s": 0.0,
                             "from_s": 0.0, **errors[model],
                             "loses_to_linear": loses and model == LEARNED})
        fold += bool(member.held_out)
    return pd.DataFrame(rows)


def warn_if_losing(metrics: pd.DataFrame) -> list[str]:
    """Logs (WARNING) and returns one message per held-out run where the model does not beat
    the linear lagged baseline."""
    messages = []
    held_out = metrics[metrics["split"].isin(["cv", "test"])]
    for run_id, group in held_out.groupby("run_id", sort=True):
        model = group.loc[group["model"] == LEARNED, "mean_mm"].mean()
        linear = group.loc[group["model"] == "linear_lagged", "mean_mm"].mean()
        if not model < linear:
            messages.append(f"the model does not beat the linear lagged baseline on held-out "
                            f"run {run_id}: {model:.2f} mm mean vs {linear:.2f} mm")
    for message in messages:
        log.warning("fit_model: %s", message)
    return messages


def cv_summary(metrics: pd.DataFrame) -> pd.DataFrame:
    """Per held-out run: mean / p95 mm of the model and both baselines, the fold models' error
    on their training runs, and the average over runs (last row, ``run_id="average"``)."""
    held = metrics[metrics["split"] == "cv"]
    table = held.pivot_table(index="run_id", columns="model", values=["mean_mm", "p95_mm"],
                             aggfunc="mean")
    table.columns = [f"{model}_{stat}" for stat, model in table.columns]
    train = metrics[(metrics["split"] == "cv_train") & (metrics["model"] == LEARNED)]
    train = train.groupby("held_out")[["mean_mm", "p95_mm"]].mean()
    table["train_runs_mean_mm"] = train["mean_mm"]
    table["train_runs_p95_mm"] = train["p95_mm"]
    columns = [f"{m}_{s}" for m in MODELS for s in ("mean_mm", "p95_mm")] + [
        "train_runs_mean_mm", "train_runs_p95_mm"]
    table = table[columns]
    table.loc["average"] = table.mean()
    return table.reset_index()


def ensemble_predictions(members_params: Sequence[DynamicsParams], run: Run
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Mean and per-axis std over members of the open-loop predictions, both [T, 3] m."""
    predictions = np.stack([predict_run(p, run) for p in members_params])
    return predictions.mean(0), predictions.std(0)


def band_coverage(mean: np.ndarray, std: np.ndarray, observed: np.ndarray, width: float = 2.0
                  ) -> float:
    """Fraction of (step, axis) entries with ``|observed - mean| <= width * std``."""
    return float(np.mean(np.abs(np.asarray(observed) - mean) <= width * std))
