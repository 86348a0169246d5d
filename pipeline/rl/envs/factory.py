"""Build environments and their parameters from the composed config (``env`` group).

``env.name``:

- ``learned``: :class:`SoftArmReachEnv` on the fitted recurrent model (:func:`make_learned_env`;
  the model, the rest pose and the goal sets come from the fit_model / align artifacts).
- ``sim``: the same environment on the simulated arm (:func:`make_sim_env`), the ground-truth
  plant: goals are positions the simulated arm reaches holding random safe pressures.
- ``gymnax``: a standard gymnax environment (``env.gymnax_name``), to check the PPO against
  published results independently of our model.

Every builder returns ``(env, train_params, eval_params)``: the evaluation parameters differ
in their goal set (held-out goals) and are nominal: the training parameters alone carry the
robustness settings, the per-episode randomization (``env.randomization``) and, for
``env=learned`` given further fitted models, the ensemble (member 0: this config's model; the
evaluation parameters hold that member alone, so a policy is always evaluated in its own model).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from typing import Any

import gymnax
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from gymnax.environments import spaces
from gymnax.wrappers.purerl import GymnaxWrapper

from pipeline.arm import sim_arm
from pipeline.arm.limits import validate_limits
from pipeline.arm.safety import SafeSet, project
from pipeline.config import (
    ConfigError,
    EnvConfig,
    EnvName,
    GoalSource,
    RandomizationConfig,
    dataclass_values,
    incremental_actions,
)
from pipeline.data.alignment import runs_at_model_rate
from pipeline.data.schemas import ALIGNED, read_table
from pipeline.dynamics.checkpoints import load_dynamics
from pipeline.dynamics.scoring import predict_run
from pipeline.infra.artifacts import Artifact
from pipeline.rl.envs.learned import (
    Randomization,
    SoftArmReachEnv,
    make_env_params,
    randomization,
    split_goals,
)
from pipeline.rl.envs.plants import (
    NUM_VALVES,
    SimPlantParams,
    ensemble_plant,
    hold,
    learned_plant,
    sim_plant,
    stack_members,
)

# ensembles up to this size step every member and keep the episode's (shared weights); larger
# ones gather the member's weights per environment (bench/ensemble_selection.py)
ALL_MEMBERS_UP_TO = 4

log = logging.getLogger(__name__)


def common_params(cfg: Any) -> dict[str, Any]:
    env_cfg = cfg.env
    return {
        "goal_mode": str(env_cfg.goal_mode),
        "goal_perturbation_m": float(env_cfg.goal_perturbation_m),
        "goal_tolerance_m": float(env_cfg.goal_tolerance_m),
        "hold_periods": int(env_cfg.get("hold_periods", EnvConfig.hold_periods)),
        "hold_bonus_mm": float(env_cfg.get("hold_bonus_mm", EnvConfig.hold_bonus_mm)),
        "obs_noise_std_m": float(env_cfg.obs_noise_std),
        "error_scale_m": float(env_cfg.error_scale_m),
        "error_integral_decay": float(
            env_cfg.get("error_integral_decay", EnvConfig.error_integral_decay)),
        "action_step_kpa": float(env_cfg.get("action_step_kpa", EnvConfig.action_step_kpa)),
        "action_noise_std_kpa": float(env_cfg.action_noise_std),
        "command_change_cost_mm_per_kpa": float(
            env_cfg.get("command_change_cost", EnvConfig.command_change_cost)),
        "max_steps": int(env_cfg.max_steps),
        "reset_bank_size": int(env_cfg.reset_bank_size),
    }


def randomization_config(env_cfg: Any) -> RandomizationConfig:
    """``env.randomization`` (absent in a config rebuilt from an artifact's spec, which keeps
    only settings that differ from the defaults: then none)."""
    node = env_cfg.get("randomization") if hasattr(env_cfg, "get") else None
    return RandomizationConfig(**dataclass_values(RandomizationConfig, node or {},
                                                  "env.randomization"))


def randomization_params(env_cfg: Any, env: SoftArmReachEnv) -> Randomization:
    """The training episodes' randomization of ``env.randomization`` on ``env`` (its delay in
    plant steps: ``round(max_delay_s * plant rate)``, at most one control period)."""
    spread = randomization_config(env_cfg)
    delay = min(round(float(spread.max_delay_s) * env.plant.model_hz), env.steps_per_action)
    return randomization(gain_std=float(spread.gain_std),
                         offset_std_kpa=float(spread.offset_std_kpa), max_delay_steps=delay,
                         rest_offset_std_m=float(spread.rest_offset_std_m),
                         drift_std_m_per_s=float(spread.drift_std_m_per_s))


def observation_options(env_cfg: Any) -> dict[str, Any]:
    """The :class:`SoftArmReachEnv` arguments of the env config besides plant and rate."""
    return {"settle_seconds": float(env_cfg.settle_seconds),
            "include_last_action": bool(env_cfg.include_last_action),
            "include_error": bool(env_cfg.include_error),
            "include_error_integral": bool(
                env_cfg.get("include_error_integral", EnvConfig.include_error_integral)),
            "incremental_actions": incremental_actions(env_cfg)}


def _safe_set(cfg: Any) -> SafeSet:
    validate_limits(cfg.robot.limits, cfg.robot.n_valves)
    return SafeSet.from_limits(cfg.robot.limits, cfg.robot.n_valves)


# ---------------------------------------------------------------------------------------------
# simulated arm
# ---------------------------------------------------------------------------------------------
def sim_plant_params(cfg: Any) -> SimPlantParams:
    """The simulated arm of ``cfg.robot`` (robot=sim physics) resting at the preload."""
    preload = jnp.full((NUM_VALVES,), float(cfg.robot.limits.preload), jnp.float32)
    return SimPlantParams(sim_arm.SimParams.from_config(cfg.robot), preload)


def sim_reachable_positions(env: SoftArmReachEnv, plant_params: SimPlantParams,
                            safe_set: SafeSet, rest_pose: jax.Array, key: jax.Array,
                            num: int, hold_seconds: float = 5.0) -> jax.Array:
    """``[num, 3]`` m: where the arm rests after holding random safe pressures for a while.

    Pressures are drawn uniformly in the valve box and projected onto the safe set; each one is
    held for ``hold_seconds`` starting from the arm settled at the preload.
    """
    pressures = project(
        jax.random.uniform(key, (num, NUM_VALVES), minval=safe_set.p_min,
                           maxval=safe_set.p_max), safe_set)
    hold_steps = max(1, round(hold_seconds * env.plant.model_hz))

    def reach(pressure):
        carry, _ = env.settle(plant_params, rest_pose, plant_params.preload)
        _, positions = hold(env.plant, plant_params, carry, pressure, hold_steps)
        return positions[-1]

    return jax.jit(jax.vmap(reach))(pressures)


def sim_rest_pose(plant_params: SimPlantParams) -> jax.Array:
    """[3] m: the simulated arm's marker at rest at the preload, without a session offset."""
    state = sim_arm.settled_state(plant_params.sim, plant_params.preload, jnp.zeros(3))
    return sim_arm.tip_position(plant_params.sim, state)


def make_sim_env(cfg: Any) -> tuple[SoftArmReachEnv, Any, Any]:
    """The reaching environment on the simulated arm (``env=sim``)."""
    env_cfg = cfg.env
    mocap_hz = float(cfg.robot.mocap.rate_hz)
    frames_per_step = round(mocap_hz / float(cfg.dataset.model_hz))
    env = SoftArmReachEnv(sim_plant(mocap_hz, frames_per_step), float(cfg.robot.control_hz),
                          **observation_options(env_cfg))
    plant_params = sim_plant_params(cfg)
    safe_set = _safe_set(cfg)
    rest_pose = sim_rest_pose(plant_params)
    rest_pose_std = jnp.asarray(cfg.robot.physics.rest_pose_std_m, jnp.float32)
    goal_key, held_out_key, train_bank_key, eval_bank_key = jax.random.split(
        jax.random.PRNGKey(int(env_cfg.env_seed)), 4)
    num_goals = int(env_cfg.num_goals)
    num_held_out = max(1, round(float(env_cfg.held_out_fraction) * num_goals))
    train_goals = sim_reachable_positions(env, plant_params, safe_set, rest_pose, goal_key,
                                          num_goals - num_held_out)
    held_out_goals = sim_reachable_positions(env, plant_params, safe_set, rest_pose,
                                             held_out_key, num_held_out)
    common = common_params(cfg)
    train_params = make_env_params(
        env, plant_params, key=train_bank_key, safe_set=safe_set,
        preload=plant_params.preload, rest_pose=rest_pose, rest_pose_std=rest_pose_std,
        goal_set=train_goals, randomization_params=randomization_params(env_cfg, env), **common)
    eval_params = make_env_params(
        env, plant_params, key=eval_bank_key, safe_set=safe_set,
        preload=plant_params.preload, rest_pose=rest_pose, rest_pose_std=rest_pose_std,
        goal_set=held_out_goals, obs_mean=train_params.obs_mean,
        obs_scale=train_params.obs_scale, **common)
    return env, train_params, eval_params


# ---------------------------------------------------------------------------------------------
# learned model
# ---------------------------------------------------------------------------------------------
def data_goals_and_rest_pose(aligned: pd.DataFrame, test_run_ids: list[str], every: int = 1
                             ) -> dict[str, np.ndarray]:
    """Goal sets and rest pose from aligned data (columns run_id, x, y, z in metres).

    Returns ``train_goals [G, 3]`` (positions of the training runs, every ``every``-th row),
    ``held_out_goals [H, 3]`` (positions of ``test_run_ids``), ``rest_pose [3]`` and
    ``rest_pose_std [3]`` (mean and spread of the first pose of every run: the runs start at the
    preload).
    """
    xyz = ["x", "y", "z"]
    held_out = aligned["run_id"].isin(test_run_ids)
    first = aligned.groupby("run_id", sort=True)[xyz].first().to_numpy(np.float64)
    return {
        "train_goals": aligned.loc[~held_out, xyz].to_numpy(np.float32)[::every],
        "held_out_goals": aligned.loc[held_out, xyz].to_numpy(np.float32)[::every],
        "rest_pose": first.mean(axis=0).astype(np.float32),
        "rest_pose_std": (first.std(axis=0) if len(first) > 1 else np.zeros(3)).astype(
            np.float32),
    }


def prediction_spread(models: Sequence[Any], run: dict) -> np.ndarray:
    """``[T]`` m: at each step of ``run`` (at the model rate), the largest distance between the
    first model's open-loop prediction along the run's commands and another's (zero for one
    model)."""
    reference = predict_run(models[0], run)
    distances = [np.linalg.norm(predict_run(other, run) - reference, axis=-1)
                 for other in models[1:]]
    return np.max(distances, axis=0) if distances else np.zeros(len(reference))


def conservative_goals(goals: pd.DataFrame, spread_m: np.ndarray, agreement_m: float,
                       held_out: np.ndarray | None = None) -> pd.DataFrame:
    """The rows of ``goals`` (one per step, columns run_id, x, y, z) where the ensemble agrees,
    ``spread_m <= agreement_m`` (``[len(goals)]``, :func:`prediction_spread`), and every row of
    ``held_out`` (a mask: evaluation goals, kept as they are). An error, naming
    ``env.goal_agreement_mm``, when no training goal is left."""
    spread_m = np.asarray(spread_m)
    training = np.ones(len(goals), bool) if held_out is None else ~np.asarray(held_out, bool)
    agreed = spread_m <= agreement_m
    kept, total = int((agreed & training).sum()), int(training.sum())
    if kept == 0:
        raise ConfigError(
            f"env.goal_agreement_mm={agreement_m * 1000:g}: the ensemble agrees on none of the "
            f"{total} training goals (their spread: median "
            f"{np.median(spread_m[training]) * 1000:.2f} mm, smallest "
            f"{np.min(spread_m[training]) * 1000:.2f} mm)")
    log.info("env: %d of %d training goals where the ensemble agrees within %g mm", kept, total,
             agreement_m * 1000)
    return goals[agreed | ~training].reset_index(drop=True)


def make_learned_env(cfg: Any, dynamics_params: Any, train_goals: np.ndarray,
                     held_out_goals: np.ndarray, rest_pose: np.ndarray,
                     rest_pose_std: np.ndarray | float = 0.0, members: Sequence[Any] = ()
                     ) -> tuple[SoftArmReachEnv, Any, Any]:
    """The reaching environment on a fitted model (``env=learned``).

    Args:
      dynamics_params: a ``pipeline.dynamics.model.DynamicsParams`` (the fit_model artifact).
      train_goals, held_out_goals: [G, 3] m goals for training and evaluation (``goal_mode=data``);
        e.g. positions of the training and test runs of the aligned data.
      rest_pose, rest_pose_std: [3] m, the observed pose at rest at the preload and its spread.
      members: further ``DynamicsParams`` of the same architecture: training runs in the
        ensemble ``[dynamics_params, *members]`` (:func:`ensemble_plant`, one member per episode,
        the reset bank rounded up to a multiple of K so that members are drawn uniformly),
        evaluation in ``dynamics_params`` alone. None given: the plain model, no ensemble.
    """
    env_cfg = cfg.env
    plant = learned_plant(float(cfg.dataset.model_hz))
    common = common_params(cfg)
    train_plant, eval_plant = dynamics_params, dynamics_params
    eval_common = dict(common)
    if members:
        count = 1 + len(members)
        plant = ensemble_plant(plant, "all" if count <= ALL_MEMBERS_UP_TO else "gather")
        train_plant = stack_members([dynamics_params, *members])
        eval_plant = stack_members([dynamics_params])
        common["reset_bank_size"] = -(-int(common["reset_bank_size"]) // count) * count
    env = SoftArmReachEnv(plant, float(cfg.robot.control_hz), **observation_options(env_cfg))
    safe_set = _safe_set(cfg)
    preload = float(cfg.robot.limits.preload)
    train_bank_key, eval_bank_key = jax.random.split(jax.random.PRNGKey(int(env_cfg.env_seed)))
    train_params = make_env_params(
        env, train_plant, key=train_bank_key, safe_set=safe_set, preload=preload,
        rest_pose=rest_pose, rest_pose_std=rest_pose_std, goal_set=train_goals,
        randomization_params=randomization_params(env_cfg, env), **common)
    eval_params = make_env_params(
        env, eval_plant, key=eval_bank_key, safe_set=safe_set, preload=preload,
        rest_pose=rest_pose, rest_pose_std=rest_pose_std, goal_set=held_out_goals,
        obs_mean=train_params.obs_mean, obs_scale=train_params.obs_scale, **eval_common)
    return env, train_params, eval_params


# ---------------------------------------------------------------------------------------------
# standard gymnax environments
# ---------------------------------------------------------------------------------------------
class BoundsScaledObservation(GymnaxWrapper):
    """Observations divided elementwise by the bound of the observation space (``max(|low|,
    |high|)`` where finite and nonzero, else 1), also in ``info["final_observation"]``.

    Pendulum-v1's angular velocity spans [-8, 8] next to cos and sin in [-1, 1]; a fixed scale
    (read from the env params at trace time, so nothing varies on ``self``) puts them on one
    footing without the running statistics that a policy would then have to carry."""

    def _scale(self, params) -> jax.Array:
        space = self._env.observation_space(params)
        bound = jnp.maximum(jnp.abs(jnp.asarray(space.low, jnp.float32)),
                            jnp.abs(jnp.asarray(space.high, jnp.float32)))
        return jnp.where(jnp.isfinite(bound) & (bound > 0), bound, 1.0)

    def observation_space(self, params) -> spaces.Box:
        space, scale = self._env.observation_space(params), self._scale(params)
        return spaces.Box(space.low / scale, space.high / scale, space.shape, space.dtype)

    def reset(self, key: jax.Array, params=None):
        params = self._env.default_params if params is None else params
        obs, state = self._env.reset(key, params)
        return obs / self._scale(params), state

    def step(self, key: jax.Array, state, action, params=None):
        params = self._env.default_params if params is None else params
        obs, state, reward, terminated, truncated, info = self._env.step(key, state, action,
                                                                          params)
        scale = self._scale(params)
        if "final_observation" in info:
            info = {**info, "final_observation": info["final_observation"] / scale}
        return obs / scale, state, reward, terminated, truncated, info


def make_gymnax_env(cfg: Any) -> tuple[Any, Any, Any]:
    """``gymnax.make(env.gymnax_name)`` with its default parameters (train = eval); with
    ``env.scale_observations`` the observations are divided by the space's bounds."""
    env, params = gymnax.make(str(cfg.env.gymnax_name))
    if cfg.env.scale_observations:
        env = BoundsScaledObservation(env)
    return env, params, params


__all__ = [
    "BoundsScaledObservation",
    "data_goals_and_rest_pose",
    "make_gymnax_env",
    "make_learned_env",
    "make_sim_env",
    "randomization_config",
    "randomization_params",
    "sim_plant_params",
    "sim_reachable_positions",
    "sim_rest_pose",
    "split_goals",
]


def environment(cfg: Any, model: Artifact | None = None, aligned: Artifact | None = None,
                members: Sequence[Artifact] = ()) -> tuple[Any, Any, Any]:
    """``(env, train_params, eval_params)`` of this config's environment.

    ``env=learned`` reads the ``model`` (a fit_model artifact: the model and its run split) and
    the ``aligned`` data it was fitted to; the other environments need neither. ``members``:
    further fit_model artifacts (``pipeline.keys.ensemble_entries``) to train in as an ensemble
    with ``model`` (goals, rest pose and evaluation stay ``model``'s); none: ``model`` alone.
    """
    env_name = EnvName(cfg.env.name)
    if env_name is EnvName.gymnax:
        return make_gymnax_env(cfg)
    if env_name is EnvName.sim:
        return make_sim_env(cfg)
    if model is None or aligned is None:
        raise ValueError("env=learned needs the fit_model artifact and its aligned data")
    dynamics_params = load_dynamics(model.file("model.msgpack"))
    split = json.loads(model.file("split.json").read_text())
    table, _ = read_table(aligned.file("aligned.parquet"), ALIGNED)
    runs = runs_at_model_rate(table, float(cfg.dataset.model_hz), str(cfg.dataset.model_grid))
    if GoalSource(cfg.env.goal_source) is GoalSource.predicted:
        # the model's open-loop predictions along the recorded commands: reachable in its world
        goal_paths = {run.run_id: predict_run(dynamics_params, run) for run in runs}
    else:
        goal_paths = {run.run_id: run.positions_m for run in runs}
    at_model_rate = pd.concat(
        [pd.DataFrame({"run_id": run.run_id, "x": goal_paths[run.run_id][:, 0],
                       "y": goal_paths[run.run_id][:, 1],
                       "z": goal_paths[run.run_id][:, 2]}) for run in runs],
        ignore_index=True)
    member_params = [load_dynamics(member.file("model.msgpack")) for member in members]
    agreement_mm = cfg.env.get("goal_agreement_mm")
    # without members (evaluation builds the env on the model alone) there is nothing to agree
    # on, and the training goals are not used
    if agreement_mm is not None and member_params:
        spread = np.concatenate([prediction_spread([dynamics_params, *member_params], run)
                                 for run in runs])
        held_out = at_model_rate["run_id"].isin(split.get("test") or [])
        at_model_rate = conservative_goals(at_model_rate, spread, float(agreement_mm) / 1000.0,
                                           held_out.to_numpy())
    first_poses = pd.DataFrame([{"run_id": run.run_id, "x": run.positions_m[0, 0],
                                 "y": run.positions_m[0, 1], "z": run.positions_m[0, 2]}
                                for run in runs])
    every = int(cfg.env.goal_every)
    rest = data_goals_and_rest_pose(first_poses, [])  # rest pose from the measured first poses
    if split.get("protocol") == "cv":
        # training goals along every run (the model trained on all of them); evaluation goals
        # the measured positions of each run as recorded when its fold held it out
        held_out_ids = [fold["held_out"] for fold in split["folds"]]
        measured = pd.concat(
            [pd.DataFrame({"run_id": run.run_id, "x": run.positions_m[:, 0],
                           "y": run.positions_m[:, 1], "z": run.positions_m[:, 2]})
             for run in runs if run.run_id in held_out_ids], ignore_index=True)
        data = {"train_goals": data_goals_and_rest_pose(at_model_rate, [], every)["train_goals"],
                "held_out_goals": data_goals_and_rest_pose(measured, held_out_ids,
                                                           every)["held_out_goals"]}
    else:
        test_ids = list(split["test"]) or list(split["train"])  # one run only: evaluate on it
        data = data_goals_and_rest_pose(at_model_rate, test_ids, every=every)
        if not split["test"]:
            data["train_goals"] = data["held_out_goals"]
    data["rest_pose"], data["rest_pose_std"] = rest["rest_pose"], rest["rest_pose_std"]
    return make_learned_env(cfg, dynamics_params, data["train_goals"], data["held_out_goals"],
                            data["rest_pose"], data["rest_pose_std"], members=member_params)
