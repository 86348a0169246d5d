"""The project's PPO next to Stable-Baselines3's on the same environment, for equal wall time.

    pip install -e ".[peers]"          # torch (CPU) and stable-baselines3, optional
    python -m bench peers [--timesteps 1200000] [--eval-envs 256] [overrides ...]

The environment is the reaching task on the simulated arm (``env=sim`` of the default config,
or the given overrides): the ground-truth plant, so neither learner depends on a fitted model.
Both learners get the same settings: ``agent.num_envs`` environments, rollouts of
``agent.num_steps``, ``agent.update_epochs`` x ``agent.num_minibatches`` minibatches, the same
discount, GAE, clipping, loss weights, gradient clipping, linearly annealed learning rate, 2 x 64
tanh layers for actor and critic, initial log std and reward scale (SB3 sees the rewards
multiplied by ``agent.reward_scale``, as this project's update does).

The project's PPO (one seed) runs ``--timesteps`` environment steps; SB3 then gets the same wall
time (compilation included on our side: what a user waits for) and stops there. Both are scored
by the same deterministic evaluation, ``--eval-envs`` episodes on the held-out goals (the final
distance when the episode ends, as PPO's own evaluation during training reports it). The table
prints env steps/s (environment steps per second of training) and the final distances.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from pipeline.config import compose
from pipeline.rl.evaluation import evaluate_policy
from pipeline.rl.networks import make_network
from pipeline.rl.ppo import make_train, seed_keys
from pipeline.schemas import AgentConfig
from pipeline.stages._environment import config_environment

MM_PER_M = 1000.0


def ours(agent: AgentConfig, env: Any, train_params: Any, eval_params: Any, eval_envs: int
         ) -> dict[str, float]:
    """Train one seed; return wall seconds (compile included), env steps/s and distances."""
    started = time.perf_counter()
    train = jax.jit(jax.vmap(make_train(agent, env, train_params, eval_params),
                             in_axes=(0, None, None)))
    compiled = train.lower(seed_keys(0, 1), train_params, eval_params).compile()
    compiled_at = time.perf_counter()
    output = jax.block_until_ready(compiled(seed_keys(0, 1), train_params, eval_params))
    finished = time.perf_counter()
    params = jax.tree.map(lambda x: x[0], output.params)
    network = make_network(agent, env.num_actions)
    evaluation = jax.jit(lambda p, key: evaluate_policy(
        env, eval_params, network, p, key, eval_envs, eval_params.max_steps_in_episode, True))(
        params, jax.random.PRNGKey(1))
    steps = agent.num_updates * agent.steps_per_update
    return {"wall_s": finished - started, "compile_s": compiled_at - started,
            "steps": steps, "steps_per_s": steps / (finished - compiled_at),
            **distances(np.asarray(evaluation["episode_final_distance_m"]),
                        np.asarray(evaluation["episode_success"]))}


def distances(final_m: np.ndarray, success: np.ndarray) -> dict[str, float]:
    return {"median_mm": float(np.median(final_m) * MM_PER_M),
            "p90_mm": float(np.percentile(final_m, 90) * MM_PER_M),
            "success": float(np.mean(success))}


def vec_env(env: Any, params: Any, num_envs: int, reward_scale: float, seed: int):
    """The gymnax environment as a Stable-Baselines3 ``VecEnv``: one jitted, vmapped step for
    all environments (auto-reset by gymnax), terminal observations and time-limit truncation
    reported the way SB3 bootstraps them."""
    import gymnasium
    from stable_baselines3.common.vec_env import VecEnv

    reset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    obs_dim = env.observation_space(params).shape[0]

    class GymnaxVecEnv(VecEnv):
        def __init__(self):
            super().__init__(
                num_envs,
                gymnasium.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32),
                gymnasium.spaces.Box(-1.0, 1.0, (env.num_actions,), np.float32))
            self.key = jax.random.PRNGKey(seed)
            self.state, self.actions = None, None

        def _split(self):
            self.key, key = jax.random.split(self.key)
            return jax.random.split(key, num_envs)

        def reset(self):
            obs, self.state = reset(self._split(), params)
            return np.array(obs)  # a writable copy (torch refuses read-only buffers)

        def step_async(self, actions):
            self.actions = jnp.asarray(np.clip(actions, -1.0, 1.0), jnp.float32)

        def step_wait(self):
            obs, self.state, reward, terminated, truncated, info = step(
                self._split(), self.state, self.actions, params)
            terminated, truncated = np.asarray(terminated), np.asarray(truncated)
            done = terminated | truncated
            final = np.asarray(info["final_observation"])
            infos = [{} for _ in range(num_envs)]
            for i in np.flatnonzero(done):
                infos[i] = {"terminal_observation": final[i],
                            "TimeLimit.truncated": bool(truncated[i] and not terminated[i])}
            return (np.array(obs), np.asarray(reward) * reward_scale, done, infos)

        def close(self):
            pass

        def get_attr(self, attr_name, indices=None):
            return [getattr(self, attr_name)] * num_envs

        def set_attr(self, attr_name, value, indices=None):
            setattr(self, attr_name, value)

        def env_method(self, method_name, *args, indices=None, **kwargs):
            return [getattr(self, method_name)(*args, **kwargs)]

        def env_is_wrapped(self, wrapper_class, indices=None):
            return [False] * num_envs

    return GymnaxVecEnv()


def stable_baselines(agent: AgentConfig, env: Any, train_params: Any, eval_params: Any,
                     eval_envs: int, seconds: float) -> dict[str, float]:
    """SB3 PPO with the same settings, stopped after ``seconds`` of wall time."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback

    class StopAfter(BaseCallback):
        def _on_step(self) -> bool:
            return time.perf_counter() - started < seconds

    started = time.perf_counter()
    venv = vec_env(env, train_params, agent.num_envs, agent.reward_scale, seed=0)
    batch = agent.steps_per_update // agent.num_minibatches
    model = PPO(
        "MlpPolicy", venv, n_steps=agent.num_steps, batch_size=batch,
        n_epochs=agent.update_epochs, gamma=agent.gamma, gae_lambda=agent.gae_lambda,
        clip_range=agent.clip_eps, clip_range_vf=agent.clip_eps if agent.clip_value else None,
        ent_coef=agent.ent_coef, vf_coef=agent.vf_coef, max_grad_norm=agent.max_grad_norm,
        learning_rate=lambda remaining: agent.lr * (remaining if agent.anneal_lr else 1.0),
        policy_kwargs={"net_arch": {"pi": [agent.hidden] * agent.num_layers,
                                    "vf": [agent.hidden] * agent.num_layers},
                       "activation_fn": torch.nn.Tanh, "log_std_init": agent.log_std_init},
        seed=0, device="cpu", verbose=0)
    learn_started = time.perf_counter()
    model.learn(total_timesteps=agent.num_updates * agent.steps_per_update,
                callback=StopAfter())
    finished = time.perf_counter()
    steps = int(model.num_timesteps)
    final_m, success = sb3_evaluation(model, env, eval_params, eval_envs)
    return {"wall_s": finished - started, "compile_s": learn_started - started,
            "steps": steps, "steps_per_s": steps / (finished - learn_started),
            **distances(final_m, success)}


def sb3_evaluation(model: Any, env: Any, params: Any, num_envs: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The deterministic evaluation of :func:`pipeline.rl.evaluation.evaluate_policy` (same
    reset key, so the same goals), with SB3's policy choosing the actions."""
    reset_key, episode_key = jax.random.split(jax.random.PRNGKey(1))
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(
        jax.random.split(reset_key, num_envs), params)
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    active = np.ones(num_envs, bool)
    final = np.full(num_envs, np.nan)
    success = np.zeros(num_envs, bool)
    for step_key in jax.random.split(episode_key, params.max_steps_in_episode):
        action, _ = model.predict(np.array(obs), deterministic=True)
        obs, state, _, terminated, truncated, info = step(
            jax.random.split(step_key, num_envs), state,
            jnp.asarray(np.clip(action, -1.0, 1.0), jnp.float32), params)
        terminated, done = np.asarray(terminated), np.asarray(terminated | truncated)
        final = np.where(active, np.asarray(info["distance_m"]), final)
        success = np.where(active & done, terminated, success)
        active &= ~done
    return final, success


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timesteps", type=int, default=AgentConfig().total_timesteps,
                        help="environment steps of the project's PPO (one seed)")
    parser.add_argument("--eval-envs", type=int, default=256)
    parser.add_argument("overrides", nargs="*", help="config overrides (env=sim is set)")
    args = parser.parse_args(argv)
    try:
        import stable_baselines3  # noqa: F401
        import torch  # noqa: F401
    except ImportError:
        raise SystemExit("bench peers needs torch and stable-baselines3: "
                         "pip install -e \".[peers]\"") from None
    cfg = compose("env=sim", *args.overrides)
    agent = AgentConfig.from_any(cfg.agent, num_seeds=1, total_timesteps=args.timesteps,
                                 progress=False, num_evals=1, eval_envs=0)
    env, train_params, eval_params = config_environment(cfg)
    rows = {"sorolearn PPO (JAX)": ours(agent, env, train_params, eval_params, args.eval_envs)}
    seconds = rows["sorolearn PPO (JAX)"]["wall_s"]
    rows["Stable-Baselines3 PPO (torch)"] = stable_baselines(
        agent, env, train_params, eval_params, args.eval_envs, seconds)
    print(f"Same environment (simulated arm), same PPO settings, {agent.num_envs} envs, equal "
          f"wall time {seconds:.1f} s; {jax.devices()[0].platform}; deterministic evaluation on "
          f"{args.eval_envs} held-out goals")
    header = (f"{'learner':<31}{'setup s':>9}{'env steps':>11}{'steps/s':>10}{'median mm':>11}"
              f"{'p90 mm':>8}{'success':>9}")
    print(header)
    print("-" * len(header))
    for name, r in rows.items():
        print(f"{name:<31}{r['compile_s']:>9.1f}{r['steps']:>11d}{r['steps_per_s']:>10.0f}"
              f"{r['median_mm']:>11.2f}{r['p90_mm']:>8.2f}{r['success']:>9.1%}")
    ours_rate = rows["sorolearn PPO (JAX)"]["steps_per_s"]
    sb3_rate = rows["Stable-Baselines3 PPO (torch)"]["steps_per_s"]
    print(f"throughput ratio (ours / SB3): {ours_rate / sb3_rate:.1f}x")


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
