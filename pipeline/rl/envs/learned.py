"""Goal-reaching with a soft arm: what is computed on the plant to build the environment's
parameters.

The environment is :class:`~pipeline.rl.envs.reach.SoftArmReachEnv` (:mod:`pipeline.rl.envs.reach`:
its action, observation, reward, reset and step), its pytrees are in
:mod:`pipeline.rl.envs.params`; all of them are importable from here as well. Here:

- :func:`make_env_params`: :class:`EnvParams` from the env settings, what the plant and the data
  supply, and the bank of start states settled on the plant (gymnax computes a reset on every
  step, so the settling happens once, here);
- the hold of deployment: :func:`with_hold_map`, the damped inverse (:func:`damped_inverse`) of
  the plant's static map (:func:`static_gain`).
"""

from __future__ import annotations

from typing import Any

import chex
import jax
import jax.numpy as jnp

from pipeline.arm.safety import SafeSet, project
from pipeline.rl.envs.params import (
    EnvParams,
    EnvState,
    HoldState,
    Perturbation,
    Randomization,
    randomization,
    setting_values,
)
from pipeline.rl.envs.plants import NUM_VALVES, POSITION_DIM, hold
from pipeline.rl.envs.reach import SoftArmReachEnv
from pipeline.schemas import ConfigError, EnvConfig

__all__ = [
    "GOAL_MODES",
    "HOLD_MAP_COMMANDS",
    "HOLD_MAP_DAMPING",
    "HOLD_MAP_SECONDS",
    "HOLD_MAP_SEED",
    "EnvParams",
    "EnvState",
    "HoldState",
    "Perturbation",
    "Randomization",
    "SoftArmReachEnv",
    "damped_inverse",
    "make_env_params",
    "randomization",
    "setting_values",
    "static_gain",
    "with_hold_map",
]

GOAL_MODES = ("data", "perturb")


def make_env_params(
    env: SoftArmReachEnv,
    plant_params: Any,
    settings: EnvConfig,
    *,
    key: jax.Array,
    safe_set: SafeSet,
    preload: float | jax.Array,
    rest_pose: jax.Array | None = None,
    rest_pose_std: float | jax.Array = 0.0,
    goal_set: jax.Array | None = None,
    obs_mean: jax.Array | None = None,
    obs_scale: jax.Array | None = None,
    randomization_params: Randomization | None = None,
    initial_poses: jax.Array | None = None,
    reset_bank_size: int | None = None,
    hold_map: jax.Array | None = None,
) -> EnvParams:
    """Build :class:`EnvParams`: the settings of ``settings`` (:func:`setting_values`), what the
    plant and the data supply, and ``reset_bank_size`` start states settled on the plant.

    Args:
      settings: the env settings (``goal_mode``, tolerances, noise, costs, ``max_steps``...).
      rest_pose: [3] m, the pose observed at rest at the preload (e.g. the mean first pose of the
        recorded runs); each bank entry starts from ``rest_pose + rest_pose_std * N(0, 1)``.
        Required unless ``initial_poses`` is given.
      goal_set: [G, 3] m goals of ``goal_mode=data``; required there, optional for ``perturb``.
      obs_mean, obs_scale: [3] m; default: the goal set's mean and per-axis std (at least 1 mm).
      randomization_params: per-episode randomization around the plant (:func:`randomization`);
        default: none.
      initial_poses: [N, 3] m, the poses the bank settles from (``N`` replaces the bank size);
        default: drawn around ``rest_pose``.
      reset_bank_size: start states in the bank; default: ``settings.reset_bank_size``.
      hold_map: [3, 3] kPa/m, the hold's map (``EnvParams.hold_map``): another plant deployed
        with the policies of a model passes the model's (:func:`with_hold_map`); default: zeros
        (training never meets the hold).
    """
    goal_mode = str(settings.goal_mode)
    if goal_mode not in GOAL_MODES:
        raise ValueError(f"goal_mode must be one of {GOAL_MODES}, got {goal_mode!r}")
    if goal_mode == "data" and goal_set is None:
        raise ValueError("goal_mode=data needs a goal_set [G, 3] (positions from the data)")
    if rest_pose is None and initial_poses is None:
        raise ValueError("make_env_params needs a rest_pose [3] or initial_poses [N, 3]")
    if int(settings.goal_redraw_periods) < 0:
        raise ConfigError(f"env.goal_redraw_periods={settings.goal_redraw_periods} must be >= 0 "
                          f"(0: the goal stays for the episode)")
    if int(settings.hold_periods) < 1:
        raise ValueError(f"hold_periods must be >= 1 (1: terminate at the first arrival), got "
                         f"{settings.hold_periods}")
    preload = jnp.broadcast_to(jnp.asarray(preload, jnp.float32), (NUM_VALVES,))
    if initial_poses is None:
        rest_pose = jnp.asarray(rest_pose, jnp.float32)
        chex.assert_shape(rest_pose, (POSITION_DIM,))
        size = int(settings.reset_bank_size if reset_bank_size is None else reset_bank_size)
        poses = rest_pose + jnp.asarray(rest_pose_std, jnp.float32) * jax.random.normal(
            key, (size, POSITION_DIM))
    else:
        poses = jnp.asarray(initial_poses, jnp.float32)
        chex.assert_shape(poses, (None, POSITION_DIM))
    bank_params, bank_axes = plant_params, None
    if env.plant.bank_params is not None:  # e.g. an ensemble: entry i settles in member i % K
        bank_params, bank_axes = env.plant.bank_params(plant_params, poses.shape[0])
    carries, positions = jax.jit(jax.vmap(env.settle, in_axes=(bank_axes, 0, None)))(
        bank_params, poses, preload)
    goal_set = jnp.asarray(positions if goal_set is None else goal_set, jnp.float32)
    chex.assert_shape(goal_set, (None, POSITION_DIM))
    if obs_mean is None:
        obs_mean = goal_set.mean(axis=0)
    if obs_scale is None:
        spread = goal_set.std(axis=0) if goal_set.shape[0] > 1 else jnp.zeros(POSITION_DIM)
        obs_scale = jnp.maximum(spread, 1e-3)
    if hold_map is None:
        hold_map = jnp.zeros((NUM_VALVES, POSITION_DIM), jnp.float32)
    chex.assert_shape(hold_map, (NUM_VALVES, POSITION_DIM))
    return EnvParams(
        hold_map=jnp.asarray(hold_map, jnp.float32),
        plant=plant_params, safe_set=safe_set, preload=preload, reset_carries=carries,
        reset_positions=positions, reset_initial_poses=poses, goal_set=goal_set,
        goal_from_data=jnp.asarray(goal_mode == "data"),
        obs_mean=jnp.asarray(obs_mean, jnp.float32), obs_scale=jnp.asarray(obs_scale, jnp.float32),
        randomization=randomization() if randomization_params is None else randomization_params,
        **setting_values(settings))


# ---------------------------------------------------------------------------------------------
# the hold (deployment): integral action through the plant's static map
# ---------------------------------------------------------------------------------------------
# the static map: commands drawn uniformly over the valve box (a fixed draw: every deployment
# of a model gets the same map), each held this long from the arm settled at the preload; the
# damping of its inverse (a share of the largest singular value: the directions the valves
# hardly move the arm in are left alone)
HOLD_MAP_COMMANDS = 256
HOLD_MAP_SEED = 0
HOLD_MAP_SECONDS = 5.0
HOLD_MAP_DAMPING = 0.1


def static_gain(env: SoftArmReachEnv, plant_params: Any, pose: jax.Array, preload: jax.Array,
                safe_set: SafeSet, num: int = HOLD_MAP_COMMANDS,
                hold_seconds: float = HOLD_MAP_SECONDS) -> jax.Array:
    """``[3 axes, 3 valves]`` m/kPa: the plant's static map ``G``, the slopes of the affine
    least-squares fit ``x ≈ c + G p`` of where it rests ``hold_seconds`` after each of ``num``
    commands ``p`` drawn uniformly over the valve box (``HOLD_MAP_SEED``; projected onto the
    safe set), held from the plant settled at ``preload`` from ``pose [3]`` m (an ensemble: its
    ``member``): the slopes of the static response averaged over the box."""
    carry, _ = env.settle(plant_params, pose, preload)
    steps = max(1, round(hold_seconds * env.plant.model_hz))
    pressures = project(jax.random.uniform(jax.random.PRNGKey(HOLD_MAP_SEED), (num, NUM_VALVES),
                                           minval=safe_set.p_min, maxval=safe_set.p_max),
                        safe_set)

    def rest(pressure):
        _, positions = hold(env.plant, plant_params, carry, pressure, steps)
        return positions[-1]

    rests = jax.jit(jax.vmap(rest))(pressures)
    features = jnp.concatenate([pressures, jnp.ones((num, 1), pressures.dtype)], axis=1)
    coefficients, *_ = jnp.linalg.lstsq(features, rests)
    return coefficients[:NUM_VALVES].T


def damped_inverse(gain: jax.Array, damping: float = HOLD_MAP_DAMPING) -> jax.Array:
    """``[3 valves, 3 axes]``: ``(GᵀG + λI)⁻¹ Gᵀ`` of ``gain`` ``G [3 axes, 3 valves]``, with
    ``λ = (damping · σ_max(G))²``."""
    chex.assert_shape(gain, (POSITION_DIM, NUM_VALVES))
    largest = jnp.linalg.norm(gain, ord=2)
    regular = gain.T @ gain + (damping * largest) ** 2 * jnp.eye(NUM_VALVES)
    return jnp.linalg.solve(regular, gain.T)


def with_hold_map(env: SoftArmReachEnv, params: EnvParams) -> EnvParams:
    """``params`` as deployed: where the hold corrects (``deadband_m`` and ``hold_gain`` > 0),
    with ``hold_map`` the damped inverse (:func:`damped_inverse`) of the static map of its plant
    (:func:`static_gain`, from its first start pose), else as they are. Evaluate and the arm
    deploy a policy so, with its model's parameters; every other plant it is evaluated on takes
    the same map (``make_env_params(hold_map=...)``)."""
    if not (float(params.deadband_m) > 0 and float(params.hold_gain) > 0):
        return params
    gain = static_gain(env, params.plant, params.reset_initial_poses[0], params.preload,
                       params.safe_set)
    return params.replace(hold_map=damped_inverse(gain).astype(jnp.float32))
