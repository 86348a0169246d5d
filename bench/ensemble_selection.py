"""Ensemble environments: how the episode's member is selected, side by side.

    python -m bench.ensemble_selection [--members 2 4] [--envs 64] [--steps 64]

A vmapped rollout (``--envs`` environments, ``--steps`` control periods, random actions) on an
ensemble of ``--members`` models of the default architecture (``model.*``, ``dataset.model_hz``,
five model steps per 2 Hz action), with each selection of
:func:`pipeline.rl.envs.plants.ensemble_plant`:

- ``gather``: the member's weights taken per environment (a copy of the weights per environment,
  batched matrix-vector products);
- ``all``: every member stepped with its own weights shared by all environments, the carry's
  member kept (K times the arithmetic, in matrix-matrix products).

The single model (no ensemble) is the reference row. Throughput: environment steps per second of
the compiled rollout (compilation excluded, best of three).
"""

from __future__ import annotations

import argparse
import time

import jax

from bench.ppo_throughput import DEFAULT_MODEL, LIMITS, REST_POSE, random_model
from pipeline.arm.safety import SafeSet
from pipeline.rl.envs import SoftArmReachEnv, ensemble_plant, learned_plant, make_env_params
from pipeline.rl.envs.plants import stack_members
from pipeline.schemas import DatasetConfig, EnvConfig, GoalMode


def rollout_program(env: SoftArmReachEnv, num_envs: int, num_steps: int):
    """``(key, params) -> final positions [num_envs, 3]``: reset, then ``num_steps`` steps."""

    def run(key, params):
        reset_key, step_key = jax.random.split(key)
        _, state = jax.vmap(env.reset, in_axes=(0, None))(
            jax.random.split(reset_key, num_envs), params)

        def period(state, key):
            action_key, env_key = jax.random.split(key)
            actions = jax.random.uniform(action_key, (num_envs, 3), minval=-1.0, maxval=1.0)
            _, state, *_ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(env_key, num_envs), state, actions, params)
            return state, None

        state, _ = jax.lax.scan(period, state, jax.random.split(step_key, num_steps))
        return state.position

    return jax.jit(run)


def measure(selection: str | None, members: int, num_envs: int, num_steps: int) -> float:
    """Environment steps per second (``selection`` None: one model, no ensemble)."""
    model_hz = DatasetConfig().model_hz
    plant = learned_plant(model_hz)
    models = [random_model(DEFAULT_MODEL) for _ in range(members)]
    if selection is None:
        plant_params = models[0]
    else:
        plant, plant_params = ensemble_plant(plant, selection), stack_members(models)
    env = SoftArmReachEnv(plant, 2.0, settle_seconds=5.0, include_last_action=True)
    params = make_env_params(env, plant_params,
                             EnvConfig(goal_mode=GoalMode.perturb, reset_bank_size=16),
                             key=jax.random.PRNGKey(0), safe_set=SafeSet.from_limits(LIMITS),
                             preload=2.0, rest_pose=REST_POSE)
    program = rollout_program(env, num_envs, num_steps)
    key = jax.random.PRNGKey(1)
    jax.block_until_ready(program(key, params))  # compile
    best = float("inf")
    for _ in range(3):
        started = time.perf_counter()
        jax.block_until_ready(program(key, params))
        best = min(best, time.perf_counter() - started)
    return num_envs * num_steps / best


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--members", type=int, nargs="+", default=[2, 4])
    parser.add_argument("--envs", type=int, default=64)
    parser.add_argument("--steps", type=int, default=64)
    args = parser.parse_args(argv)
    single = measure(None, 1, args.envs, args.steps)
    print(f"ensemble member selection, {args.envs} envs x {args.steps} steps, "
          f"{jax.devices()[0].platform}; one model: {single:.0f} env steps/s")
    header = (f"{'members':>8}{'gather steps/s':>16}{'all steps/s':>13}{'all / gather':>14}"
              f"{'all / one model':>17}")
    print(header)
    print("-" * len(header))
    for members in args.members:
        gather = measure("gather", members, args.envs, args.steps)
        every = measure("all", members, args.envs, args.steps)
        print(f"{members:>8}{gather:>16.0f}{every:>13.0f}{every / gather:>14.2f}"
              f"{every / single:>17.2f}")


if __name__ == "__main__":
    main()
