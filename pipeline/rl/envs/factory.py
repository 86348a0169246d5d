"""Build environments and their parameters from typed settings: the env schema's object
(:class:`~pipeline.schemas.EnvConfig`), what they take of the robot and dataset
(:class:`ArmSettings`) and, for ``env=learned``, the loaded fit_model and align artifacts
(:class:`LearnedInputs`, read by the stages with :func:`read_learned_inputs`).

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
from dataclasses import dataclass
from pathlib import Path
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
from pipeline.data.alignment import runs_at_model_rate
from pipeline.data.schemas import ALIGNED, read_table
from pipeline.data.sessions import SESSION_PREFIX
from pipeline.dynamics.checkpoints import load_dynamics
from pipeline.dynamics.scoring import predict_run
from pipeline.rl.envs.learned import make_env_params
from pipeline.rl.envs.params import EnvParams, Randomization, randomization
from pipeline.rl.envs.plants import (
    NUM_VALVES,
    SimPlantParams,
    ensemble_plant,
    hold,
    learned_plant,
    sim_plant,
    stack_members,
)
from pipeline.rl.envs.reach import SoftArmReachEnv
from pipeline.schemas import (
    ConfigError,
    EnvConfig,
    EnvName,
    GoalSource,
    PressureLimits,
    RandomizationConfig,
    incremental_actions,
)

# ensembles up to this size step every member and keep the episode's (shared weights); larger
# ones gather the member's weights per environment (bench/ensemble_selection.py)
ALL_MEMBERS_UP_TO = 4

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ArmSettings:
    """What the environments take of the robot and dataset settings.

    limits: the pressure limits (``robot.limits``: p_min, p_max, sum_max, preload kPa).
    n_valves: valves of the arm.
    control_hz: [Hz] rate of the actions (``robot.control_hz``).
    model_hz: [Hz] rate the plant runs at (``dataset.model_hz``).
    sim: ``env=sim`` only: the simulated arm's robot settings (``physics``, ``mocap``, ``limits``).
    """

    limits: PressureLimits
    n_valves: int
    control_hz: float
    model_hz: float
    sim: Any = None


@dataclass(frozen=True)
class LearnedInputs:
    """What ``env=learned`` is built from (:func:`read_learned_inputs`).

    dynamics: the fit_model artifact's ``DynamicsParams``.
    split: its run split (``split.json``: ``protocol``, ``train``/``test`` or ``folds``).
    runs: the aligned runs at the model rate (``run_id``, ``pos [T, 3]`` m, ...).
    members: further ``DynamicsParams`` of the same architecture, trained in as an ensemble.
    """

    dynamics: Any
    split: dict[str, Any]
    runs: list[dict[str, Any]]
    members: tuple[Any, ...] = ()


def read_learned_inputs(model_file: Path, split_file: Path, aligned_file: Path, model_hz: float,
                        model_grid: str, member_files: Sequence[Path] = ()) -> LearnedInputs:
    """:class:`LearnedInputs` from a fit_model artifact's model and split files, the aligned
    table it was fitted to (resampled at ``model_hz`` on ``model_grid``) and further members'
    model files."""
    table, _ = read_table(aligned_file, ALIGNED)
    return LearnedInputs(load_dynamics(model_file), json.loads(Path(split_file).read_text()),
                         runs_at_model_rate(table, float(model_hz), str(model_grid)),
                         tuple(load_dynamics(path) for path in member_files))


def randomization_params(spread: RandomizationConfig, env: SoftArmReachEnv) -> Randomization:
    """The training episodes' randomization of ``env.randomization`` on ``env`` (its delay in
    plant steps: ``round(max_delay_s * plant rate)``, at most one control period)."""
    delay = min(round(float(spread.max_delay_s) * env.plant.model_hz), env.steps_per_action)
    return randomization(gain_std=float(spread.gain_std),
                         offset_std_kpa=float(spread.offset_std_kpa), max_delay_steps=delay,
                         rest_offset_std_m=float(spread.rest_offset_std_m),
                         drift_std_m_per_s=float(spread.drift_std_m_per_s),
                         saturation_max_per_kpa=float(spread.saturation_max_per_kpa))


def observation_options(settings: EnvConfig) -> dict[str, Any]:
    """The :class:`SoftArmReachEnv` arguments of the env settings besides plant and rate."""
    return {"settle_seconds": float(settings.settle_seconds),
            "include_last_action": bool(settings.include_last_action),
            "include_error": bool(settings.include_error),
            "include_error_integral": bool(settings.include_error_integral),
            "incremental_actions": incremental_actions(settings),
            "task": str(settings.task), "preview": int(settings.preview)}


def _safe_set(arm: ArmSettings) -> SafeSet:
    validate_limits(arm.limits, arm.n_valves)
    return SafeSet.from_limits(arm.limits, arm.n_valves)


# ---------------------------------------------------------------------------------------------
# simulated arm
# ---------------------------------------------------------------------------------------------
def sim_plant_params(robot: Any) -> SimPlantParams:
    """The simulated arm of the robot settings ``robot`` (robot=sim: ``physics``, ``mocap``,
    ``limits``) resting at the preload."""
    preload = jnp.full((NUM_VALVES,), float(robot.limits.preload), jnp.float32)
    return SimPlantParams(sim_arm.SimParams.from_config(robot), preload)


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


def make_sim_env(settings: EnvConfig, arm: ArmSettings) -> tuple[SoftArmReachEnv, Any, Any]:
    """The reaching environment on the simulated arm ``arm.sim`` (``env=sim``)."""
    mocap_hz = float(arm.sim.mocap.rate_hz)
    frames_per_step = round(mocap_hz / float(arm.model_hz))
    env = SoftArmReachEnv(sim_plant(mocap_hz, frames_per_step), float(arm.control_hz),
                          **observation_options(settings))
    plant_params = sim_plant_params(arm.sim)
    safe_set = _safe_set(arm)
    rest_pose = sim_rest_pose(plant_params)
    rest_pose_std = jnp.asarray(arm.sim.physics.rest_pose_std_m, jnp.float32)
    goal_key, held_out_key, train_bank_key, eval_bank_key = jax.random.split(
        jax.random.PRNGKey(int(settings.env_seed)), 4)
    num_goals = int(settings.num_goals)
    num_held_out = max(1, round(float(settings.held_out_fraction) * num_goals))
    train_goals = sim_reachable_positions(env, plant_params, safe_set, rest_pose, goal_key,
                                          num_goals - num_held_out)
    held_out_goals = sim_reachable_positions(env, plant_params, safe_set, rest_pose,
                                             held_out_key, num_held_out)
    train_params = make_env_params(
        env, plant_params, settings, key=train_bank_key, safe_set=safe_set,
        preload=plant_params.preload, rest_pose=rest_pose, rest_pose_std=rest_pose_std,
        goal_set=train_goals,
        randomization_params=randomization_params(settings.randomization, env))
    eval_params = make_env_params(
        env, plant_params, settings, key=eval_bank_key, safe_set=safe_set,
        preload=plant_params.preload, rest_pose=rest_pose, rest_pose_std=rest_pose_std,
        goal_set=held_out_goals, obs_mean=train_params.obs_mean,
        obs_scale=train_params.obs_scale)
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
    preload, the arm not yet at rest: the learned model goes on from there as the arm did).
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


def make_learned_env(settings: EnvConfig, arm: ArmSettings, dynamics_params: Any,
                     train_goals: np.ndarray, held_out_goals: np.ndarray, rest_pose: np.ndarray,
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
    plant = learned_plant(float(arm.model_hz))
    train_plant, eval_plant = dynamics_params, dynamics_params
    bank_size = int(settings.reset_bank_size)
    if members:
        count = 1 + len(members)
        plant = ensemble_plant(plant, "all" if count <= ALL_MEMBERS_UP_TO else "gather")
        train_plant = stack_members([dynamics_params, *members])
        eval_plant = stack_members([dynamics_params])
        bank_size = -(-bank_size // count) * count
    env = SoftArmReachEnv(plant, float(arm.control_hz), **observation_options(settings))
    safe_set = _safe_set(arm)
    preload = float(arm.limits.preload)
    train_bank_key, eval_bank_key = jax.random.split(jax.random.PRNGKey(int(settings.env_seed)))
    train_params = make_env_params(
        env, train_plant, settings, key=train_bank_key, safe_set=safe_set, preload=preload,
        rest_pose=rest_pose, rest_pose_std=rest_pose_std, goal_set=train_goals,
        randomization_params=randomization_params(settings.randomization, env),
        reset_bank_size=bank_size)
    eval_params = make_env_params(
        env, eval_plant, settings, key=eval_bank_key, safe_set=safe_set, preload=preload,
        rest_pose=rest_pose, rest_pose_std=rest_pose_std, goal_set=held_out_goals,
        obs_mean=train_params.obs_mean, obs_scale=train_params.obs_scale)
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


def make_gymnax_env(settings: EnvConfig) -> tuple[Any, Any, Any]:
    """``gymnax.make(env.gymnax_name)`` with its default parameters (train = eval); with
    ``env.scale_observations`` the observations are divided by the space's bounds."""
    env, params = gymnax.make(str(settings.gymnax_name))
    if settings.scale_observations:
        env = BoundsScaledObservation(env)
    return env, params, params


__all__ = [
    "ArmSettings",
    "BoundsScaledObservation",
    "LearnedInputs",
    "data_goals_and_rest_pose",
    "make_gymnax_env",
    "make_learned_env",
    "make_sim_env",
    "measured_paths",
    "randomization_params",
    "read_learned_inputs",
    "sim_plant_params",
    "sim_reachable_positions",
    "sim_rest_pose",
    "split_goals",
]


def split_goals(positions: np.ndarray, held_out_fraction: float, seed: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """Random split of ``positions [N, 3]`` into (training goals, held-out goals)."""
    positions = np.asarray(positions, np.float32)
    order = np.random.default_rng(seed).permutation(len(positions))
    num_held_out = max(1, round(held_out_fraction * len(positions)))
    return positions[order[num_held_out:]], positions[order[:num_held_out]]


def environment(settings: EnvConfig, arm: ArmSettings, inputs: LearnedInputs | None = None
                ) -> tuple[Any, Any, Any]:
    """``(env, train_params, eval_params)`` of the env ``settings``.

    ``env=learned`` is built from ``inputs`` (the fit_model artifact's model and split, the
    aligned runs it was fitted to and, to train in as an ensemble, further members; goals, rest
    pose and evaluation stay the model's); the other environments need none.
    """
    env_name = EnvName(settings.name)
    if env_name is EnvName.gymnax:
        return make_gymnax_env(settings)
    if env_name is EnvName.sim:
        return training_only(settings, *make_sim_env(settings, arm))
    if inputs is None:
        raise ValueError("env=learned needs the fit_model artifact and its aligned data")
    data = learned_goals(settings, inputs)
    return training_only(settings, *make_learned_env(
        settings, arm, inputs.dynamics, data["train_goals"], data["held_out_goals"],
        data["rest_pose"], data["rest_pose_std"], members=inputs.members))


def training_only(settings: EnvConfig, env: SoftArmReachEnv, train_params: EnvParams,
                  eval_params: EnvParams) -> tuple[SoftArmReachEnv, EnvParams, EnvParams]:
    """The settings that shape training episodes only: ``train_max_steps`` (where set) is the
    training parameters' horizon, and the evaluation parameters keep their goal for the whole
    episode (``goal_redraw_periods=0``: an evaluation scores the goal it started with)."""
    if settings.train_max_steps is not None:
        train_params = train_params.replace(max_steps=int(settings.train_max_steps))
    eval_params = eval_params.replace(goal_redraw_periods=jnp.zeros((), jnp.int32))
    return env, train_params, eval_params


def _positions(run_id: str, pos: np.ndarray) -> pd.DataFrame:
    return pd.DataFrame({"run_id": run_id, "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2]})


def evaluation_run_ids(split: dict[str, Any]) -> list[str]:
    """The runs whose positions are ``env=learned``'s evaluation goals, by the model's ``split``:
    each run its fold held out (``cv`` protocol), else the test runs (one run only, none held
    out: the training runs); never a run joined from a session."""
    if split.get("protocol") == "cv":
        return [fold["held_out"] for fold in split["folds"]]
    ids = list(split["test"]) or list(split["train"])
    return [run_id for run_id in ids if not run_id.startswith(SESSION_PREFIX)]


def measured_paths(inputs: LearnedInputs) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The measured paths of the runs the evaluation goals come from (:func:`evaluation_run_ids`),
    by run: ``(times [T] s from the run's start, positions [T, 3] m)`` at the model rate."""
    ids = evaluation_run_ids(inputs.split)
    return {run.run_id: (np.asarray(run.times_s, np.float64) - float(run.times_s[0]),
                         np.asarray(run.positions_m, np.float64))
            for run in inputs.runs if run.run_id in ids}


def learned_goals(settings: EnvConfig, inputs: LearnedInputs) -> dict[str, np.ndarray]:
    """The goal sets and rest pose of ``env=learned`` (:func:`data_goals_and_rest_pose`): goals
    along the runs (``env.goal_source``: the model's open-loop predictions or the measured
    positions; with an ensemble and ``env.goal_agreement_mm`` only where the members agree),
    held out as the model's split held its runs out; the rest pose from the runs' first poses.
    Runs joined from control sessions (:mod:`pipeline.data.sessions`) are the model's data, not
    the workspace: neither goals nor rest pose come from them."""
    split, dynamics = inputs.split, inputs.dynamics
    runs = [run for run in inputs.runs if not run.run_id.startswith(SESSION_PREFIX)]
    if GoalSource(settings.goal_source) is GoalSource.predicted:
        # the model's open-loop predictions along the recorded commands: reachable in its world
        goal_paths = {run.run_id: predict_run(dynamics, run) for run in runs}
    else:
        goal_paths = {run.run_id: run.positions_m for run in runs}
    at_model_rate = pd.concat([_positions(run.run_id, goal_paths[run.run_id])
                               for run in runs], ignore_index=True)
    agreement_mm = settings.goal_agreement_mm
    # without members (evaluation builds the env on the model alone) there is nothing to agree
    # on, and the training goals are not used
    if agreement_mm is not None and inputs.members:
        spread = np.concatenate([prediction_spread([dynamics, *inputs.members], run)
                                 for run in runs])
        held_out = at_model_rate["run_id"].isin(split.get("test") or [])
        at_model_rate = conservative_goals(at_model_rate, spread, float(agreement_mm) / 1000.0,
                                           held_out.to_numpy())
    first_poses = pd.concat([_positions(run.run_id, run.positions_m[:1]) for run in runs],
                            ignore_index=True)
    every = int(settings.goal_every)
    rest = data_goals_and_rest_pose(first_poses, [])  # rest pose from the measured first poses
    held_out_ids = evaluation_run_ids(split)
    if split.get("protocol") == "cv":
        # training goals along every run (the model trained on all of them); evaluation goals
        # the measured positions of each run as recorded when its fold held it out
        measured = pd.concat([_positions(run.run_id, run.positions_m) for run in runs
                              if run.run_id in held_out_ids], ignore_index=True)
        data = {"train_goals": data_goals_and_rest_pose(at_model_rate, [], every)["train_goals"],
                "held_out_goals": data_goals_and_rest_pose(measured, held_out_ids,
                                                           every)["held_out_goals"]}
    else:
        data = data_goals_and_rest_pose(at_model_rate, held_out_ids, every=every)
        if not split["test"]:
            data["train_goals"] = data["held_out_goals"]
    data["rest_pose"], data["rest_pose_std"] = rest["rest_pose"], rest["rest_pose_std"]
    return data
