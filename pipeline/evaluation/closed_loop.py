"""Closed-loop rollouts of every controller on the learned environment and on the plant.

For every policy type (all seeds) and every baseline (``preload``: do nothing; ``random``: random
safe actions; ``mpc``: sampling-based MPC on the learned model, :mod:`pipeline.evaluation.mpc`), on
the same held-out goals and start states: on the **learned environment**, on the **plant** (the
simulated arm for ``robot=sim``, observed through the same normalization the policies were
trained with) and on a **consecutive-goals** task (several targets in a row, no reset). The
policies act as deployed: within ``env.deadband_m`` of the goal the hold acts.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from pipeline.arm.twins import twin_sim_params
from pipeline.evaluation import mpc, rollouts
from pipeline.evaluation.metrics import MM_PER_M, episode_metrics, plant_gap, summarize
from pipeline.infra.devices import batch_split
from pipeline.rl.envs.factory import observation_options, sim_rest_pose
from pipeline.rl.envs.learned import EnvParams, SoftArmReachEnv, make_env_params, with_hold_map
from pipeline.rl.envs.plants import SimPlantParams, learned_plant, sim_plant
from pipeline.rl.networks import initial_hidden
from pipeline.schemas import ConfigError, EnvConfig, EvaluationConfig


class SimArm(NamedTuple):
    """The simulated arm as the ground-truth plant (``robot=sim``)."""

    plant: SimPlantParams  # its physics, resting at the preload
    mocap_hz: float  # Hz: the frame rate it integrates at
    rest_pose_std_m: Sequence[float]  # m, per axis: the spread of its rest pose between sessions


@dataclass(frozen=True)
class ClosedLoopSettings:
    """What the closed-loop evaluation takes besides the learned environment and the policies.

    ``evaluation``: episodes, baselines, MPC and consecutive-goals settings; ``max_steps``:
    control periods an episode (and each consecutive goal) lasts; ``model_hz``: Hz of a model
    step (a plant's frames per model step follow from it); ``limits``: the arm's pressure
    limits (kPa) the commands are checked against; ``env``: the training env's settings (every
    plant is observed and rewarded as the learned env);
    ``sim``: the ground-truth plant, None where the robot has none or ``evaluation.plant`` is
    off; ``mpc``: the MPC baseline's settings, None: ``evaluation``'s ``mpc_*`` (one command
    held over the horizon).
    """

    evaluation: EvaluationConfig
    max_steps: int
    model_hz: float
    limits: Any
    env: EnvConfig
    sim: SimArm | None = None
    mpc: mpc.CEMSettings | None = None

    def only_in_models(self) -> ClosedLoopSettings:
        """These settings with the preload as the only baseline and no plant, twin or
        consecutive goals: the controllers in fitted models only."""
        return dataclasses.replace(self, sim=None, evaluation=dataclasses.replace(
            self.evaluation, baselines=["preload"], plant=False, num_consecutive_goals=0,
            models=[]))


class Policy(NamedTuple):
    """A trained policy type: its network and its variables, stacked over seeds (leaves
    ``[S, ...]``)."""

    network: Any
    params: Any


def _sim_env(settings: ClosedLoopSettings, learned_env: SoftArmReachEnv, mocap_hz: float,
             built: dict[float, SoftArmReachEnv] | None = None) -> SoftArmReachEnv:
    """The simulated arm at ``mocap_hz`` frames, stepped a model step at a time, observed exactly
    like the learned env (which make_learned_env built from the same options). ``built``: the
    environments already built by frame rate, taken from and added to, so that plants of one
    frame rate (the arm, its twins) share one environment and with it their compiled
    programs."""
    if built is not None and mocap_hz in built:
        return built[mocap_hz]
    frames = round(mocap_hz / float(settings.model_hz))
    if frames < 1 or not math.isclose(mocap_hz / frames, float(settings.model_hz),
                                      rel_tol=1e-6):
        raise ConfigError(f"the simulated arm integrates at {mocap_hz:g} Hz, which "
                          f"dataset.model_hz={settings.model_hz} does not divide")
    env = SoftArmReachEnv(sim_plant(mocap_hz, frames), learned_env.control_hz,
                          **observation_options(settings.env))
    if built is not None:
        built[mocap_hz] = env
    return env


def _plant_env(settings: ClosedLoopSettings, learned_env: SoftArmReachEnv,
               learned_params: EnvParams, key: jax.Array,
               built: dict[float, SoftArmReachEnv] | None = None
               ) -> tuple[SoftArmReachEnv, EnvParams] | None:
    """The ground-truth plant as an environment observed like the learned one (same goals and
    normalization), or None when there is none."""
    sim = settings.sim
    if sim is None:
        return None
    env = _sim_env(settings, learned_env, float(sim.mocap_hz), built)
    plant = sim.plant
    params = make_env_params(
        env, plant, key=key, safe_set=learned_params.safe_set, preload=plant.preload,
        rest_pose=sim_rest_pose(plant),
        rest_pose_std=jnp.asarray(sim.rest_pose_std_m, jnp.float32),
        goal_set=learned_params.goal_set, obs_mean=learned_params.obs_mean,
        obs_scale=learned_params.obs_scale, settings=settings.env,
        hold_map=learned_params.hold_map)
    return env, params


def _starts(params: EnvParams, count: int) -> tuple[Any, jax.Array]:
    index = jnp.arange(count) % params.reset_positions.shape[0]
    return (jax.tree.map(lambda leaf: leaf[index], params.reset_carries),
            params.reset_positions[index])


class Controllers(NamedTuple):
    """One kind of controller for every seed: ``make(params, env_params)`` builds it from its
    parameters, ``params`` (leaves ``[S, ...]``, ``S = 1`` for a baseline) and ``carries``
    (leaves ``[S, E, ...]``, one per episode) are passed to the compiled program as arguments."""

    make: Callable[[Any, EnvParams], rollouts.Controller]
    params: Any
    carries: Any


def rollout_program(env: SoftArmReachEnv, kinds: tuple[rollouts.Kind, ...]
                    ) -> Callable[..., list[tuple[jax.Array, jax.Array]]]:
    """One compiled program for ``kinds`` of controllers on ``env``, every kind, seed and
    episode at once (:func:`pipeline.evaluation.rollouts.rollout_together`, the plant stepped
    once a period for all): ``(env_params, params (per kind, [S_k]), carries (per kind,
    [S_k, E]), keys [E], start_carries [E], start_positions [E, 3], goals [E, T, 3],
    references [E] or None) -> per kind (positions [S_k, E, T + 1, 3], commands [S_k, E, T,
    3])``. Seeds and kinds see the same keys, starts, goals and references (a tracking env's;
    None: the goals)."""

    def program(env_params, params, carries, keys, start_carries, start_positions, goals,
                reference):
        return rollouts.rollout_together(env, env_params, kinds, params, carries, keys,
                                         start_carries, start_positions, goals, reference)

    return jax.jit(program)


def _controllers(settings: ClosedLoopSettings, env, params, learned_params, policies_loaded,
                 num_episodes) -> dict[str, Controllers]:
    """Every policy type (all its seeds) and every baseline on ``env`` with ``params``, by name.

    ``learned_params`` are the learned environment's: the MPC's model starts from its settled
    states (the same ones the learned environment starts from).
    """
    out = {}
    for name, (network, stacked, num_seeds) in policies_loaded.items():
        hidden = initial_hidden(network, 1)
        carries = (jnp.broadcast_to(hidden, (num_seeds, num_episodes, *hidden.shape)),
                   jnp.ones((num_seeds, num_episodes), bool))
        out[name] = Controllers(
            lambda params, env_params, n=network: rollouts.policy_controller(n, params),
            stacked, carries)
    none, dummy = jnp.zeros((1,)), jnp.zeros((1, num_episodes))
    evaluation = settings.evaluation
    for baseline in evaluation.baselines:
        if baseline == "preload":
            out[baseline] = Controllers(
                lambda params, env_params: rollouts.preload_controller(env, env_params),
                none, dummy)
        elif baseline == "random":
            out[baseline] = Controllers(lambda params, env_params: rollouts.random_controller(),
                                        none, dummy)
        elif baseline == "mpc":
            cem = settings.mpc or mpc.CEMSettings(horizon=int(evaluation.mpc_horizon),
                                                  num_samples=int(evaluation.mpc_samples),
                                                  num_iterations=int(evaluation.mpc_iterations))
            model = learned_plant(float(settings.model_hz))
            model_carries, model_starts = _starts(learned_params, num_episodes)
            carries = jax.vmap(lambda carry, start, preload, s=cem: mpc.initial_carry(
                carry, start, preload, s), in_axes=(0, 0, None))(
                model_carries, model_starts, params.preload)
            out[baseline] = Controllers(
                lambda params, env_params, m=model, s=cem: mpc.mpc_controller(
                    env, env_params, m, params, s),
                jax.tree.map(lambda x: x[None], learned_params.plant),
                jax.tree.map(lambda x: x[None], carries))
        else:
            raise ValueError(f"evaluation.baselines: unknown baseline {baseline!r}; "
                             "known: preload, random, mpc")
    return out


class _Programs:
    """The compiled rollout program of each (environment, controller kinds), built on first
    use: plants that differ only in their parameters (the learned model, other fitted models,
    twins of one frame rate) run the same program."""

    def __init__(self):
        self._programs: dict[tuple[Any, ...], Callable[..., Any]] = {}

    def run(self, env: SoftArmReachEnv, env_params: EnvParams,
            controllers: Mapping[str, Controllers], keys, starts, goals, references=None,
            deadband: Collection[str] = ()) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Every controller of ``controllers`` (by name; a name stands for one structure of
        controller) on ``env`` with ``env_params``: ``(positions [S, E, T + 1, 3], commands
        [S, E, T, 3])`` by name; those named in ``deadband`` act as deployed."""
        names = tuple(controllers)
        program = (env, names, tuple(name in deadband for name in names))  # envs by identity
        if program not in self._programs:
            self._programs[program] = rollout_program(env, tuple(
                rollouts.Kind(controllers[name].make, name in deadband) for name in names))
        params = [controllers[name].params for name in names]
        carries = [controllers[name].carries for name in names]
        # the episodes split over the devices (the CPU's cores), each part in parallel
        split = batch_split(int(np.shape(keys)[0]))
        if split is not None:
            env_params, params = split.put((env_params, params), axis=None)
            carries = split.put(carries, axis=1)  # [S, E, ...]
            keys, starts, goals, references = split.put((keys, starts, goals, references))
        runs = self._programs[program](env_params, params, carries, keys, *starts, goals,
                                       references)
        return {name: (np.asarray(positions), np.asarray(commands))
                for name, (positions, commands) in zip(names, runs, strict=True)}


def _model_env(env: SoftArmReachEnv, eval_params: EnvParams, dynamics_params: Any,
               key: jax.Array, settings: ClosedLoopSettings) -> EnvParams:
    """Another fitted model as a plant of the same environment: its own settled starts, settled
    in it from the poses the learned env's starts settled from (the same rest poses of the
    arm), the same safe set, goals and observation normalization."""
    return make_env_params(
        env, dynamics_params, key=key, safe_set=eval_params.safe_set,
        preload=eval_params.preload, initial_poses=eval_params.reset_initial_poses,
        goal_set=eval_params.goal_set, obs_mean=eval_params.obs_mean,
        obs_scale=eval_params.obs_scale, settings=settings.env, hold_map=eval_params.hold_map)


def _twin_env(settings: ClosedLoopSettings, learned_env: SoftArmReachEnv, eval_params: EnvParams,
              physics: dict[str, Any], key: jax.Array,
              built: dict[float, SoftArmReachEnv] | None = None
              ) -> tuple[SoftArmReachEnv, EnvParams]:
    """A calibrated twin (the simulated arm with ``physics``, SimPhysics values) as a plant
    observed like the learned env: the same goals, safe set and normalization; every start
    settled at the preload where the twin's physics rest it (their base position, which the
    calibration fitted over whole runs): a twin is one arm.

    Not at the learned env's start poses: those are the recordings' first poses, taken before
    the arm has come to rest (over the preload hold that opens each of the paper's runs it
    rises 1.1-1.6 mm and moves up to 2.7 mm sideways, to within 0.6 mm of where the calibrated
    twin rests); a twin put there rests that far from the arm."""
    sim = twin_sim_params(physics)
    env = _sim_env(settings, learned_env, float(sim.mocap_hz), built)
    plant = SimPlantParams(sim, eval_params.preload)
    params = twin_env_params(
        env, plant, key=key, safe_set=eval_params.safe_set, goal_set=eval_params.goal_set,
        obs_mean=eval_params.obs_mean, obs_scale=eval_params.obs_scale,
        settings=settings.env, hold_map=eval_params.hold_map)
    return env, params


def twin_env_params(env: SoftArmReachEnv, plant: SimPlantParams, **given: Any) -> EnvParams:
    """The :class:`EnvParams` of a twin plant (:func:`make_env_params` with ``given``): one
    start, settled at the preload where the twin's physics rest it (see :func:`_twin_env`)."""
    return make_env_params(env, plant, preload=plant.preload, rest_pose=sim_rest_pose(plant),
                           reset_bank_size=1, **given)


def _plants(settings: ClosedLoopSettings, env: SoftArmReachEnv, eval_params: EnvParams,
            key: jax.Array, models: Mapping[str, Any], twins: Mapping[str, Mapping[str, Any]]
            ) -> dict[str, tuple[SoftArmReachEnv, EnvParams]]:
    """Every plant by name: the learned env, the ground-truth plant (where there is one), each
    other fitted model and each calibrated twin, observed like the learned env."""
    plants = {"learned": (env, eval_params)}
    built: dict[float, SoftArmReachEnv] = {}  # the simulated arm's environments by frame rate
    plant_env = _plant_env(settings, env, eval_params, key, built)
    if plant_env is not None:
        plants["plant"] = plant_env
    for number, (name, dynamics_params) in enumerate(models.items()):
        plants[name] = (env, _model_env(env, eval_params, dynamics_params,
                                        jax.random.fold_in(key, number + 1), settings))
    for number, (name, physics) in enumerate(twins.items()):
        plants[name] = _twin_env(settings, env, eval_params, physics,
                                 jax.random.fold_in(key, len(models) + number + 1), built)
    return plants


def run_evaluation(settings: ClosedLoopSettings, policies: Mapping[str, Policy],
                   env: SoftArmReachEnv, eval_params: EnvParams,
                   models: Mapping[str, Any] | None = None,
                   twins: Mapping[str, Mapping[str, Any]] | None = None) -> dict[str, Any]:
    """Roll out every policy type of ``policies`` (all seeds) and every baseline on the learned
    env (``env`` with its evaluation parameters), on the plant, in each of ``models`` (other
    fitted models' ``DynamicsParams`` by plant name) and on each of ``twins`` (calibrated twins'
    SimPhysics values by plant name); return tables and arrays."""
    evaluation = settings.evaluation
    episodes, steps = int(evaluation.num_episodes), int(settings.max_steps)
    eval_params = with_hold_map(env, eval_params)  # the model's map, for every plant
    key = jax.random.key(int(evaluation.seed))
    goal_key, plant_key, rollout_key, consecutive_key = jax.random.split(key, 4)

    goal_index = jax.random.randint(goal_key, (episodes,), 0, eval_params.goal_set.shape[0])
    goals = eval_params.goal_set[goal_index]
    goal_paths = jnp.broadcast_to(goals[:, None], (episodes, steps, 3))
    plants = _plants(settings, env, eval_params, plant_key, models or {}, twins or {})
    loaded = {name: (policy.network, policy.params, jax.tree.leaves(policy.params)[0].shape[0])
              for name, policy in policies.items()}
    programs = _Programs()
    rows, finals, paths, sent = _episodes(settings, plants, loaded, eval_params, programs,
                                          jax.random.split(rollout_key, episodes), goals,
                                          goal_paths)
    episodes_table = pd.concat(rows, ignore_index=True)
    summary = summarize(episodes_table, ["plant", "controller"])
    gaps = _gap_table(episodes_table, finals) if "plant" in plants else pd.DataFrame()
    consecutive = _consecutive(settings, plants, loaded, consecutive_key, eval_params, programs)
    headline = {
        f"{row.plant}/{row.controller}": {"median_final_mm": float(row.median_final_mm),
                                          "success_1mm": float(row.success_1mm),
                                          "success_3mm": float(row.success_3mm),
                                          "held_arrivals": float(row.held_arrivals)}
        for row in summary.itertuples()}
    return {"tables": {"episodes": episodes_table, "summary": summary, "plant_gap": gaps,
                       "consecutive": consecutive},
            "paths": paths, "commands": sent, "goals": np.asarray(goals), "headline": headline,
            "plants": plants}


def _episodes(settings: ClosedLoopSettings, plants, loaded, eval_params: EnvParams,
              programs: _Programs, keys: jax.Array, goals: jax.Array, goal_paths: jax.Array
              ) -> tuple[list[pd.DataFrame], dict, dict, dict]:
    """Every controller on every plant: the per-episode tables (one per plant, controller and
    seed) and, by ``(plant, controller, seed)``, the final positions ``[E, 3]``, the paths
    ``[E, T + 1, 3]`` (m) and the commands sent ``[E, T, 3]`` (kPa)."""
    episodes = int(np.shape(keys)[0])
    rows, finals, paths, sent = [], {}, {}, {}
    for plant_name, (plant_env_i, plant_params) in plants.items():
        controllers = _controllers(settings, plant_env_i, plant_params, eval_params, loaded,
                                   episodes)
        runs = programs.run(plant_env_i, plant_params, controllers, keys,
                            _starts(plant_params, episodes), goal_paths, deadband=loaded)
        for controller, (positions, commands) in runs.items():
            for seed in range(positions.shape[0]):
                table = episode_metrics(positions[seed], np.asarray(goals), commands[seed],
                                        settings.limits)
                table.insert(0, "episode", np.arange(episodes))
                table.insert(0, "seed", seed)
                table.insert(0, "controller", controller)
                table.insert(0, "plant", plant_name)
                rows.append(table)
                finals[(plant_name, controller, seed)] = positions[seed, :, -1]
                paths[(plant_name, controller, seed)] = positions[seed]
                sent[(plant_name, controller, seed)] = commands[seed]
    return rows, finals, paths, sent


def _gap_table(episodes: pd.DataFrame, finals: dict) -> pd.DataFrame:
    rows = []
    for (plant, controller, seed), final in finals.items():
        if plant != "plant":
            continue
        learned = episodes[(episodes.plant == "learned") & (episodes.controller == controller)
                           & (episodes.seed == seed)]
        on_plant = episodes[(episodes.plant == "plant") & (episodes.controller == controller)
                            & (episodes.seed == seed)]
        gap = plant_gap(learned, on_plant, finals[("learned", controller, seed)], final)
        gap.insert(0, "seed", seed)
        gap.insert(0, "controller", controller)
        rows.append(gap)
    return pd.concat(rows, ignore_index=True)


def _consecutive(settings: ClosedLoopSettings, plants, loaded, key, eval_params,
                 programs: _Programs) -> pd.DataFrame:
    """Reach ``num_consecutive_goals`` goals one after another (``max_steps`` each, no reset);
    the distance at the end of each goal's time is recorded."""
    count = int(settings.evaluation.num_consecutive_goals)
    episodes = int(settings.evaluation.consecutive_episodes)
    per_goal = int(settings.max_steps)
    if count < 1 or episodes < 1:
        return pd.DataFrame()
    goal_key, rollout_key = jax.random.split(key)
    index = jax.random.randint(goal_key, (episodes, count), 0, eval_params.goal_set.shape[0])
    goals = np.repeat(np.asarray(eval_params.goal_set[index]), per_goal, axis=1)
    keys = jax.random.split(rollout_key, episodes)
    rows = []
    for plant_name, (env, params) in plants.items():
        controllers = {name: batch for name, batch in _controllers(
            settings, env, params, eval_params, loaded, episodes).items()
            if name not in ("preload", "random")}
        runs = programs.run(env, params, controllers, keys, _starts(params, episodes),
                            jnp.asarray(goals), deadband=loaded)
        for controller, (positions, _) in runs.items():
            ends = positions[:, :, per_goal::per_goal]  # pose at the end of each goal's time
            targets = goals[:, per_goal - 1::per_goal]
            distance = np.linalg.norm(ends - targets, axis=-1) * MM_PER_M  # [S, E, goals]
            for seed in range(positions.shape[0]):
                for goal_number in range(count):
                    at_goal = distance[seed, :, goal_number]
                    rows.append({"plant": plant_name, "controller": controller, "seed": seed,
                                 "goal": goal_number,
                                 "median_distance_mm": float(np.median(at_goal)),
                                 "success_3mm": float((at_goal <= 3).mean())})
    return pd.DataFrame(rows)
