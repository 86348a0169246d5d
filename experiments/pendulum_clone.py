"""Clone the value-iteration optimum of Pendulum-v1 into the PPO actor: a warm start for PPO.

PPO stays at a return of about -144 on Pendulum-v1 where the optimum is about -136
(``pendulum_optimal.py``, :mod:`pipeline.rl.pendulum_optimum`). Is that an optimisation problem (PPO never finds the better swing-up
from scratch) or does PPO's own objective lead away from the optimum? This script answers the
first half of the question: it fits the actor of the ``experiment=pendulum`` network, by
regression, to the stationary greedy policy of value iteration (torque levels over [-2, 2]) on
states visited by that policy with and without action noise, plus uniform states; it then writes
the clone as a ``train_ppo`` policy file, which PPO can start from::

    .venv/bin/python -m experiments.pendulum_clone --out /tmp/clone.msgpack
    .venv/bin/python -m pipeline stage=train_ppo experiment=pendulum \\
        agent.init_policy=/tmp/clone.msgpack agent.init_policy_log_std=-1 agent.lr=5e-5 \\
        agent.ent_coef=0 agent.num_seeds=4

and prints the clone's deterministic return from the 2048 common start states of
``pendulum_optimal.py --policy`` next to the optimum's.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import optax
from gymnax.environments.classic_control.pendulum import EnvState

from pipeline.rl.networks import initial_hidden, make_network
from pipeline.rl.pendulum_optimum import greedy_torque, optimal_returns, policy_returns, solve
from pipeline.rl.policy_io import save_policy
from pipeline.schemas import AgentConfig


def pendulum_agent(overrides: list[str]) -> AgentConfig:
    """The composed ``experiment=pendulum`` agent config (plus Hydra ``overrides``)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from pipeline.config import PROJECT_ROOT, register_configs

    register_configs()
    with initialize_config_dir(config_dir=str(PROJECT_ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["experiment=pendulum", *overrides])
    return AgentConfig.from_any(OmegaConf.to_container(cfg.agent, resolve=True))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, help="policy file to write (.msgpack)")
    parser.add_argument("--angles", type=int, default=512)
    parser.add_argument("--velocities", type=int, default=321)
    parser.add_argument("--torques", type=int, default=81)
    parser.add_argument("--starts", type=int, default=1024, help="rollouts per noise level")
    parser.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.25, 0.5, 1.0],
                        help="action noise std ([-1, 1] units) of the data-collecting rollouts")
    parser.add_argument("--uniform", type=int, default=200_000, help="uniform random states")
    parser.add_argument("--fit-steps", type=int, default=20_000)
    parser.add_argument("--batch", type=int, default=4096)
    parser.add_argument("--episodes", type=int, default=2048)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of the agent (agent.x=y)")
    args = parser.parse_args(argv)

    started = time.perf_counter()
    agent = pendulum_agent(args.overrides)
    optimum = solve(args.angles, args.velocities, args.torques)
    env, params = optimum.env, optimum.params
    max_torque = float(params.max_torque)
    stationary_value = optimum.values[1]  # 199 steps to go: the swing-up is over long before

    def greedy(theta, theta_dot):
        """The stationary greedy policy, [-1, 1] units."""
        return greedy_torque(optimum, stationary_value, theta, theta_dot) / max_torque

    # ------------------------------------------------------------------ states and labels
    rollout_key, uniform_key, init_key, fit_key = jax.random.split(
        jax.random.PRNGKey(args.seed + 1), 4)  # not the evaluation's PRNGKey(seed) starts

    @jax.jit
    def visited(key, noise_std):
        """[starts * 200] angles and velocities visited with noisy greedy actions."""
        def episode(key):
            reset_key, noise_key = jax.random.split(key)
            _, state = env.reset_env(reset_key, params)

            def step(state, noise):
                action = jnp.clip(greedy(state.theta, state.theta_dot) + noise_std * noise, -1, 1)
                _, next_state, _, _, _ = env.step_env(
                    key, state, jnp.array([action * max_torque]), params)
                return next_state, (state.theta, state.theta_dot)
            noises = jax.random.normal(noise_key, (int(params.max_steps_in_episode),))
            return jax.lax.scan(step, state, noises)[1]
        theta, theta_dot = jax.vmap(episode)(jax.random.split(key, args.starts))
        return theta.reshape(-1), theta_dot.reshape(-1)

    thetas, dots = [], []
    for key, noise_std in zip(jax.random.split(rollout_key, len(args.noise)), args.noise):
        theta, theta_dot = visited(key, noise_std)
        thetas.append(theta)
        dots.append(theta_dot)
    angle_key, velocity_key = jax.random.split(uniform_key)
    thetas.append(jax.random.uniform(angle_key, (args.uniform,), minval=-jnp.pi, maxval=jnp.pi))
    dots.append(jax.random.uniform(velocity_key, (args.uniform,), minval=-params.max_speed,
                                   maxval=params.max_speed))
    theta, theta_dot = jnp.concatenate(thetas), jnp.concatenate(dots)
    inputs = jax.vmap(env.get_obs)(EnvState(theta=theta, theta_dot=theta_dot,
                                            last_u=jnp.zeros_like(theta),
                                            time=jnp.zeros(theta.shape, int)))
    labels = jax.jit(greedy)(theta, theta_dot)

    # ------------------------------------------------------------------ regression of the actor mean
    network = make_network(agent, 1)
    hidden = initial_hidden(network, args.batch)
    variables = network.init(init_key, hidden, jnp.zeros((1, args.batch, 3)),
                             jnp.zeros((1, args.batch), bool))
    schedule = optax.cosine_decay_schedule(1e-3, args.fit_steps)
    tx = optax.adam(schedule)

    def loss_fn(variables, obs, target):
        _, pi, _ = network.apply(variables, hidden, obs[None], jnp.zeros((1, args.batch), bool))
        return jnp.mean(jnp.square(pi.mean()[0, :, 0] - target))

    @jax.jit
    def fit(variables, key, inputs, labels):  # data as arguments, not constants in the program
        def step(carry, key):
            variables, opt_state = carry
            index = jax.random.randint(key, (args.batch,), 0, inputs.shape[0])
            loss, grads = jax.value_and_grad(loss_fn)(variables, inputs[index], labels[index])
            updates, opt_state = tx.update(grads, opt_state, variables)
            return (optax.apply_updates(variables, updates), opt_state), loss
        (variables, _), losses = jax.lax.scan(step, (variables, tx.init(variables)),
                                              jax.random.split(key, args.fit_steps))
        return variables, losses

    # the log std stays at agent.log_std_init
    variables, losses = fit(variables, fit_key, inputs, labels)
    print(f"clone: {inputs.shape[0]} states, regression MSE {float(losses[:100].mean()):.4f} "
          f"(first 100 steps) -> {float(losses[-100:].mean()):.4f} (last 100)")

    out = save_policy(args.out, jax.tree.map(lambda x: x[None], variables), {
        "agent": dataclasses.asdict(agent),
        "env": {"name": "gymnax", "gymnax_name": "Pendulum-v1", "scale_observations": False},
        "env_name": "Pendulum-v1", "obs_dim": 3, "action_dim": 1,
        "action_low": [-max_torque], "action_high": [max_torque], "num_seeds": 1,
        "cloned_from": f"value iteration {args.angles} x {args.velocities} x {args.torques}",
    })

    # ------------------------------------------------------------------ returns, common starts
    keys = jax.random.split(jax.random.PRNGKey(args.seed), args.episodes)
    optimal, _ = optimal_returns(optimum, keys)
    cloned = policy_returns(env, params, out, keys)[0]
    stationary, _ = optimal_returns(optimum, keys, stationary=True)
    print(f"{args.episodes} episodes from the common start states: optimum {optimal.mean():.1f}, "
          f"its stationary greedy policy (the label) {stationary.mean():.1f}, clone "
          f"{cloned.mean():.1f} (gap to the optimum {float((cloned - optimal).mean()):.1f}); "
          f"written {out}  [{time.perf_counter() - started:.0f} s]")


if __name__ == "__main__":
    main()
