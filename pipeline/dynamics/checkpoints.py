"""Files of the learned dynamics: the saved model and the training checkpoints.

A model file (:func:`save_dynamics`) is one ``flax.serialization`` msgpack holding the network,
the normalizer and the architecture (``DynamicsConfig`` as JSON). A training checkpoint holds
the same model entry plus the optimizer state, the step, the loss history and the training spec
(the setup it belongs to); a checkpoint of a vmapped training (``cv.fit_members``) holds the
stacked networks and optimizer states of all its members instead. Every file is written
atomically (temporary file, fsync, ``os.replace``), named ``step_<8 digits>.msgpack`` in its
checkpoint folder, and only the newest ``keep`` are kept.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization

from pipeline.dynamics import model as dynamics
from pipeline.dynamics.model import DynamicsConfig, DynamicsParams, Normalizer
from pipeline.infra.parquet import atomic_write

log = logging.getLogger(__name__)

CHECKPOINT_PREFIX = "step_"
CHECKPOINT_SUFFIX = ".msgpack"


class TrainState(NamedTuple):
    network: Any  # flax variables
    opt_state: optax.OptState
    step: jax.Array  # int32 scalar: steps taken so far ([M] for stacked members)


class CorruptCheckpointError(ValueError):
    """A checkpoint file that cannot be read back (cut off, overwritten, not a checkpoint)."""


# ---------------------------------------------------------------------------------------------
# the model file
# ---------------------------------------------------------------------------------------------
def model_state_dict(params: DynamicsParams) -> dict:
    return {
        "config": json.dumps(dataclasses.asdict(params.config)),
        "normalizer": serialization.to_state_dict(jax.device_get(params.normalizer)),
        "network": serialization.to_state_dict(jax.device_get(params.network)),
    }


def model_from_state_dict(state: dict) -> DynamicsParams:
    values = json.loads(state["config"])
    values.setdefault("pressure_transients", [])  # a model saved before that input existed
    config = DynamicsConfig(**values)
    template_network = jax.eval_shape(
        lambda key: dynamics.init_network(key, config), jax.random.PRNGKey(0)
    )
    template_normalizer = Normalizer(*(jnp.zeros(3) for _ in range(6)))
    to_device = lambda tree: jax.tree.map(jnp.asarray, tree)  # noqa: E731
    network = serialization.from_state_dict(
        template_network, {k: v for k, v in state["network"].items() if k != dynamics.SESSION})
    if dynamics.SESSION in state["network"]:  # a model trained with session latents
        network = {**network, dynamics.SESSION: dict(state["network"][dynamics.SESSION])}
    return DynamicsParams(
        network=to_device(network),
        normalizer=to_device(
            serialization.from_state_dict(template_normalizer, state["normalizer"])
        ),
        config=config,
    )


def params_digest(params: DynamicsParams) -> str:
    """sha256 of the model as :func:`save_dynamics` writes it: what a fit started from it
    checks its checkpoints against."""
    payload = serialization.msgpack_serialize({"model": model_state_dict(params)})
    return hashlib.sha256(payload).hexdigest()


def write_atomically(path: Path, payload: bytes) -> None:
    with atomic_write(path) as tmp:
        tmp.write_bytes(payload)


def save_dynamics(path: str | Path, params: DynamicsParams) -> None:
    """Writes the model (network, normalizer, architecture) to one msgpack file, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, serialization.msgpack_serialize({"model": model_state_dict(params)}))


def load_dynamics(path: str | Path) -> DynamicsParams:
    """Reads a model written by :func:`save_dynamics` or a training checkpoint."""
    state = serialization.msgpack_restore(Path(path).read_bytes())
    return model_from_state_dict(state["model"])


# ---------------------------------------------------------------------------------------------
# checkpoint files
# ---------------------------------------------------------------------------------------------
def checkpoint_path(checkpoint_dir: Path, step: int) -> Path:
    return checkpoint_dir / f"{CHECKPOINT_PREFIX}{step:08d}{CHECKPOINT_SUFFIX}"


def checkpoint_paths(checkpoint_dir: str | Path) -> list[Path]:
    """The complete checkpoints in ``checkpoint_dir``, oldest first (temporary files ignored)."""
    return sorted(Path(checkpoint_dir).glob(f"{CHECKPOINT_PREFIX}*{CHECKPOINT_SUFFIX}"))


def latest_checkpoint(checkpoint_dir: str | Path) -> Path | None:
    """The complete checkpoint with the highest step (temporary files are ignored)."""
    paths = checkpoint_paths(checkpoint_dir)
    return paths[-1] if paths else None


def write_checkpoint(checkpoint_dir: Path, step: int, payload: dict, keep: int = 2) -> None:
    """Writes ``payload`` as the checkpoint of ``step`` and removes all but the newest ``keep``."""
    write_atomically(checkpoint_path(checkpoint_dir, step),
                     serialization.msgpack_serialize(payload))
    for old in checkpoint_paths(checkpoint_dir)[:-keep]:
        old.unlink()


def check_spec(path: Path, stored_spec: dict, spec: dict) -> None:
    """``ValueError`` naming the differing entries unless the checkpoint's spec is ``spec``."""
    if stored_spec != spec:
        differing = sorted(k for k in set(spec) | set(stored_spec)
                           if spec.get(k) != stored_spec.get(k))
        raise ValueError(
            f"checkpoint {path} was written by a different training setup (differs in "
            f"{differing}); use another checkpoint_dir or resume=False"
        )


# ---------------------------------------------------------------------------------------------
# one model's training (``training.fit``)
# ---------------------------------------------------------------------------------------------
def save_checkpoint(checkpoint_dir: Path, params: DynamicsParams, state: TrainState,
                    history: dict, spec: dict, keep: int = 2) -> None:
    """The model (``params`` with the state's network), optimizer state, step, loss history
    (``{"train_loss": [...], "val_rows": [(step, loss, mean_mm, p95_mm), ...]}``) and spec."""
    payload = {
        "model": model_state_dict(params.replace(network=state.network)),
        "opt_state": serialization.to_state_dict(jax.device_get(state.opt_state)),
        "step": int(state.step),
        "train_loss": np.asarray(history["train_loss"], np.float32),
        "val_rows": np.asarray(history["val_rows"], np.float64).reshape(-1, 4),
        "spec": json.dumps(spec, sort_keys=True),
    }
    write_checkpoint(checkpoint_dir, int(state.step), payload, keep)


def restore_checkpoint(path: Path, template: TrainState, spec: dict) -> tuple[TrainState, dict]:
    """The state and history of a :func:`save_checkpoint` file written for ``spec``."""
    try:
        raw = serialization.msgpack_restore(path.read_bytes())
        stored_spec = json.loads(raw["spec"])
        model = model_from_state_dict(raw["model"])
        opt_state = serialization.from_state_dict(template.opt_state, raw["opt_state"])
        step, train_loss, val_rows = raw["step"], raw["train_loss"], raw["val_rows"]
    except Exception as err:  # msgpack, KeyError, shape errors: all mean "not a checkpoint"
        raise CorruptCheckpointError(f"checkpoint {path} cannot be read "
                                     f"({type(err).__name__}: {err})") from err
    check_spec(path, stored_spec, spec)
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


def resume(checkpoint_dir: Path, state: TrainState, history: dict, spec: dict
           ) -> tuple[TrainState, dict]:
    """The newest readable checkpoint's state and history (else the given ones); a corrupt
    checkpoint is logged by name and set aside as ``<name>.corrupt``, and the next one tried."""
    paths = checkpoint_paths(checkpoint_dir)
    for path in reversed(paths):
        try:
            restored = restore_checkpoint(path, state, spec)
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
# stacked members (``cv.fit_members``)
# ---------------------------------------------------------------------------------------------
def save_members(checkpoint_dir: Path, state: TrainState, losses: list[np.ndarray], spec: dict,
                 keep: int = 2) -> None:
    """The stacked networks and optimizer states, steps [M], losses [M, steps] and spec."""
    payload = {
        "network": serialization.to_state_dict(jax.device_get(state.network)),
        "opt_state": serialization.to_state_dict(jax.device_get(state.opt_state)),
        "step": np.asarray(state.step),
        "train_loss": np.concatenate(losses, axis=1).astype(np.float32),
        "spec": json.dumps(spec, sort_keys=True),
    }
    write_checkpoint(checkpoint_dir, int(state.step[0]), payload, keep)


def restore_members(path: Path, template: TrainState, spec: dict
                    ) -> tuple[TrainState, list[np.ndarray]]:
    """The stacked state and ``[losses [M, steps]]`` of a :func:`save_members` file."""
    raw = serialization.msgpack_restore(path.read_bytes())
    check_spec(path, json.loads(raw["spec"]), spec)
    state = TrainState(
        network=jax.tree.map(jnp.asarray,
                             serialization.from_state_dict(template.network, raw["network"])),
        opt_state=jax.tree.map(jnp.asarray, serialization.from_state_dict(
            template.opt_state, raw["opt_state"])),
        step=jnp.asarray(raw["step"], jnp.int32),
    )
    return state, [np.asarray(raw["train_loss"], np.float32)]
