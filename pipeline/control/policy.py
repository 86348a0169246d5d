"""The policy ``stage=control`` deploys, with the environment it was trained in.

The stage finds the train_ppo artifact and rebuilds its environment exactly as training built it
(:mod:`pipeline.stages.control`); :func:`deploy` makes of them a :class:`Deployment`: the
observation's standardization (``EnvParams``), its preview of the reference (``env.preview``),
the action mapping and the workspace (the box of the training goals), the policy's step
compiled.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from pipeline.evaluation.rollouts import policy_controller
from pipeline.infra.artifacts import Artifact
from pipeline.rl.envs.learned import EnvParams, SoftArmReachEnv, with_hold_map
from pipeline.rl.envs.observation import observe, update_error_integral, update_reference_shift
from pipeline.rl.networks import initial_hidden

log = logging.getLogger(__name__)
MM_PER_M = 1000.0


@dataclass
class Deployment:
    """A policy ready to act: ``step`` is jitted and compiled (see :meth:`act`)."""

    artifact: Artifact
    seed: int
    env: SoftArmReachEnv
    env_params: EnvParams  # the evaluation parameters: the training standardization
    policy_params: Any
    # the initial carry between periods: ([1, H] recurrent state, a placeholder for feed-forward
    # policies; [3] accumulated error, zeros, used with env.include_error_integral; [3] m, where
    # the observed reference is moved, zeros, used to track; the hold's memory, HoldState, whose
    # goal is the last period's, which the accumulated error and the reference's move are
    # updated with)
    hidden: Any
    workspace_m: np.ndarray  # [2, 3] lower and upper corner of the training goals
    train_goals_m: np.ndarray  # [G, 3] the training goals
    control_hz: float
    # (policy_params, env_params, carry, first, measured, goal, preview, last_pressure), jitted
    step: Any
    # the measured paths of the runs the policy's evaluation goals came from, by run: (times [T]
    # s, positions [T, 3] m), what a replayed reference replays (empty: none known)
    recorded: Mapping[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    @property
    def preview(self) -> int:
        """The reference points ahead the policy observes (``env.preview`` it was trained with;
        0: a reaching policy)."""
        return int(self.env.preview)

    def act(self, hidden: Any, first: bool, measured: np.ndarray, goal: np.ndarray,
            preview: np.ndarray, last_pressure: np.ndarray
            ) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray]:
        """One period: ``(carry, observation [obs_dim], action [3] in [-1, 1], pressure [3] kPa
        before the gate)``; ``hidden``: the carry of the previous period (``Deployment.hidden``
        at the first, ``first=True``); ``measured``, ``goal`` in m, ``preview [preview, 3]`` m
        (the goals of the next periods; ignored without a preview), ``last_pressure`` in kPa."""
        preview = np.asarray(preview, np.float32).reshape(self.preview, 3)
        hidden, obs, action, pressure = self.step(
            self.policy_params, self.env_params, hidden, jnp.asarray(first),
            jnp.asarray(measured, jnp.float32), jnp.asarray(goal, jnp.float32),
            jnp.asarray(preview), jnp.asarray(last_pressure, jnp.float32))
        obs, action, pressure = jax.device_get((obs, action, pressure))
        return hidden, np.asarray(obs), np.asarray(action), np.asarray(pressure, np.float64)


def make_step(network: Any, env: SoftArmReachEnv) -> Any:
    """The jitted control step: observation (the environment's :func:`observe`, with the preview
    where the policy was trained with one), the deterministic action (evaluate's policy
    controller), within ``env_params.deadband_m`` of the goal the hold's command instead (the
    environment's :meth:`~SoftArmReachEnv.deadband_action`, as evaluate deploys it), the
    pressures (the environment's action mapping). Its carry is ``(recurrent
    state, accumulated error, reference shift, hold)``; the accumulated error and, tracking, the
    shift of the observed reference are zero at the first period and then updated with each
    measured pose and the goal of the period that led to it (the hold's ``goal``), as the
    environment's step does (:func:`update_error_integral`, :func:`update_reference_shift`); the
    hold's memory (:class:`~pipeline.rl.envs.learned.HoldState`) starts afresh at the first
    period, as evaluate's episodes do."""

    def step(policy_params, env_params, carry, first, measured, goal, preview, last_pressure):
        hidden, integral, shift, hold = carry
        integral = jnp.where(first, jnp.zeros_like(integral),
                             update_error_integral(integral, measured, hold.goal, env_params))
        if env.tracking:  # as the environment's step: a reaching policy's stays at zero
            shift = jnp.where(first, jnp.zeros_like(shift),
                              update_reference_shift(shift, measured, hold.goal, env_params))
        hold = jax.tree.map(lambda fresh, kept: jnp.where(first, fresh, kept),
                            env.initial_hold(goal), hold)
        obs = observe(measured, goal, last_pressure, env_params, include_error=env.include_error,
                      include_last_action=env.include_last_action,
                      error_integral=integral if env.include_error_integral else None,
                      preview=preview if env.preview else None,
                      reference_shift=shift if env.tracking else None)
        act = policy_controller(network, policy_params)
        (hidden, _), action = act(None, obs, None, (hidden, first))
        hold, action = env.deadband_action(hold, action, measured, goal, last_pressure,
                                           env_params)
        return ((hidden, integral, shift, hold), obs, action,
                env.command(action, last_pressure, env_params))

    return jax.jit(step)


def deploy(artifact: Artifact, seed: int, network: Any, stacked: Any, meta: dict[str, Any],
           env: SoftArmReachEnv, train_params: EnvParams, eval_params: EnvParams,
           control_hz: float,
           recorded: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None) -> Deployment:
    """Seed ``seed`` of the policy ``stacked`` (parameters with a leading seed axis, as
    :func:`pipeline.rl.policy_io.load_policy` returns them with ``network`` and ``meta``) in the
    environment it was trained in, its step compiled (one call made), with the hold's map of
    that environment's model where the hold corrects (:func:`with_hold_map`). The workspace is
    the box of ``train_params.goal_set`` [G, 3] m."""
    eval_params = with_hold_map(env, eval_params)
    policy_params = jax.tree.map(lambda x: x[seed], stacked)
    goals = np.asarray(train_params.goal_set, np.float64)
    workspace = np.stack([goals.min(axis=0), goals.max(axis=0)])
    deployment = Deployment(artifact, seed, env, eval_params, policy_params,
                            (initial_hidden(network, 1), jnp.zeros(3, jnp.float32),
                             jnp.zeros(3, jnp.float32), env.initial_hold(jnp.zeros(3))),
                            workspace, goals, control_hz, make_step(network, env),
                            dict(recorded or {}))
    # compile before the first command: the first period must not wait for XLA
    preload = np.asarray(eval_params.preload, np.float64)
    centre = workspace.mean(axis=0)
    deployment.act(deployment.hidden, True, centre, centre,
                   np.broadcast_to(centre, (deployment.preview, 3)), preload)
    log.info("control: policy %s seed %d (%s on %s, preview %d, reference integral gain %g, "
             "hold within %g mm, gain %g, backoff %g), workspace %s mm", artifact.path, seed,
             meta["agent"]["name"], meta.get("env_name"), deployment.preview,
             float(eval_params.reference_integral_gain) if env.tracking else 0.0,
             float(eval_params.deadband_m) * MM_PER_M, float(eval_params.hold_gain),
             float(eval_params.hold_backoff), np.round(workspace * MM_PER_M, 1).tolist())
    return deployment
