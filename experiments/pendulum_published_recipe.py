"""What does the published PPO recipe for Pendulum-v1 score, run again with many seeds?

The gymnax README lists "PPO, ES (R: -130)" for the Pendulum-v1 checkpoints of gymnax-blines;
its PPO (``agents/Pendulum-v1/ppo.yaml``) scores a training run as the mean of 164 rollouts that
sample the policy's Gaussian. One run is one draw. This script re-runs that PPO recipe, written
here from its description, for many seeds at once, and scores every seed three ways:

- the published protocol: the mean return of 164 sampled rollouts from random start states,
  after training and at each of the 31 evaluations during it (every 59 updates, about 32 k
  steps, as every 1000 iterations of 32 environments);
- deterministically (the Gaussian's mean) and sampled, from the 2048 common start states of
  ``pendulum_optimal.py`` (``jax.random.split(PRNGKey(0), 2048)``), the figure that our
  ``train_ppo`` policies are compared on (``pendulum_optimal.py --policy``).

The recipe (``ppo.yaml`` and ``utils/ppo.py``, ``utils/models.py`` of gymnax-blines): 1 M steps,
32 environments, 16-step rollouts (each rollout collects 17 steps; the 17th only bootstraps),
GAE with gamma 0.99 and lambda 0.95, episode ends at the time limit treated as terminal, 4 epochs
of 4 minibatches, advantages normalized per minibatch, clip 0.2 on the ratio and (absolutely) on
the value, value coefficient 0.5, entropy 0.01, Adam (eps 1e-5) at a constant 5e-4, gradient norm
1, rewards unscaled. Separate actor and critic MLPs, 2 x 64 ReLU, flax's default kernels and
biases drawn from U[0, 0.05); the actor outputs the mean and softplus(.) + 0.001 as the std of a
Gaussian in torque units, whose samples the environment clips to [-2, 2]. Two liberties, both
noted: every update draws fresh minibatch permutations (the original reuses one key), and the
last 9 of the original's 1838 updates are not run (1829 updates, 995 k steps), so that the
evaluations fall every 59 updates.

Example (16 seeds, about 2 min on one core)::

    .venv/bin/python experiments/pendulum_published_recipe.py --seeds 16
"""

from __future__ import annotations

import argparse
import time
from typing import NamedTuple

import distrax
import flax.linen as nn
import gymnax
import jax
import jax.numpy as jnp
import numpy as np
import optax

from pipeline.rl.ppo import compute_gae

NUM_ENVS = 32
ROLLOUT = 16  # transitions per environment that train; one more is collected to bootstrap
MINIBATCHES = 4
EPOCHS = 4
GAMMA, LAMBDA = 0.99, 0.95
CLIP_EPS, VF_COEF, ENT_COEF = 0.2, 0.5, 0.01
LR, ADAM_EPS, MAX_GRAD_NORM = 5e-4, 1e-5, 1.0
EVALS, UPDATES_PER_EVAL = 31, 59  # 31 x 59 updates x 17 x 32 steps = 995 k steps
EVAL_ROLLOUTS = 164
MIN_STD = 0.001


class ActorCritic(nn.Module):
    """Separate MLPs: ``obs [..., 3] -> (value [...], Gaussian over the torque [..., 1])``."""

    hidden: int = 64
    layers: int = 2

    @nn.compact
    def __call__(self, obs):
        bias = nn.initializers.uniform(0.05)

        def mlp(x, name):
            for i in range(self.layers):
                x = nn.relu(nn.Dense(self.hidden, bias_init=bias, name=f"{name}_{i}")(x))
            return x
        value = nn.Dense(1, bias_init=bias, name="value")(mlp(obs, "critic"))[..., 0]
        features = mlp(obs, "actor")
        mean = nn.Dense(1, bias_init=bias, name="mean")(features)
        std = jax.nn.softplus(nn.Dense(1, bias_init=bias, name="scale")(features)) + MIN_STD
        return value, distrax.MultivariateNormalDiag(mean, std)


class Rollout(NamedTuple):
    obs: jax.Array  # [T+1, N, 3]
    action: jax.Array  # [T+1, N, 1]
    reward: jax.Array  # [T+1, N]
    done: jax.Array  # [T+1, N] bool, the episode ended with this step (time limit included)
    log_prob: jax.Array  # [T+1, N]
    value: jax.Array  # [T+1, N]


def gae(rollout: Rollout) -> tuple[jax.Array, jax.Array]:
    """Advantages and value targets [T, N] for the first T steps; step T only bootstraps. Every
    episode end, the time limit included, is terminal (no bootstrap), as in the recipe."""
    never = jnp.zeros_like(rollout.done[:-1])
    return compute_gae(rollout.reward[:-1], rollout.value[:-1], rollout.done[:-1], never, never,
                       rollout.value[-1], GAMMA, LAMBDA)


def episode_returns(env, env_params, network, params, keys, sample: bool) -> jax.Array:
    """[episodes] returns of whole episodes from ``env.reset(keys[i])``, with the Gaussian's mean
    as the action or a sample of it."""
    def episode(key):
        obs, state = env.reset(key, env_params)

        def step(carry, noise_key):
            obs, state = carry
            _, pi = network.apply(params, obs)
            action = pi.sample(seed=noise_key) if sample else pi.mode()
            obs, state, reward, *_ = env.step(key, state, action, env_params)
            return (obs, state), reward
        noise = jax.random.split(jax.random.fold_in(key, 1), env_params.max_steps_in_episode)
        return jax.lax.scan(step, (obs, state), noise)[1].sum()
    return jax.vmap(episode)(keys)


def make_train(env, env_params, reward_scale: float = 1.0):
    """``train(key) -> (params, evaluations [EVALS + 1])``, pure, to jit and vmap over seeds.
    ``reward_scale`` multiplies the rewards PPO learns from (1 in the recipe; a diagnostic)."""
    network = ActorCritic()
    optimizer = optax.chain(optax.clip_by_global_norm(MAX_GRAD_NORM),
                            optax.scale_by_adam(eps=ADAM_EPS), optax.scale(-LR))

    def evaluate(params, key):
        """The published protocol: mean return of EVAL_ROLLOUTS sampled episodes."""
        return episode_returns(env, env_params, network, params,
                               jax.random.split(key, EVAL_ROLLOUTS), sample=True).mean()

    def loss_fn(params, obs, action, old_log_prob, old_value, target, advantage):
        value, pi = network.apply(params, obs)
        clipped_value = old_value + jnp.clip(value - old_value, -CLIP_EPS, CLIP_EPS)
        value_loss = 0.5 * jnp.maximum((value - target) ** 2,
                                       (clipped_value - target) ** 2).mean()
        ratio = jnp.exp(pi.log_prob(action) - old_log_prob)
        advantage = (advantage - advantage.mean()) / (advantage.std() + 1e-8)
        actor_loss = -jnp.minimum(ratio * advantage,
                                  jnp.clip(ratio, 1 - CLIP_EPS, 1 + CLIP_EPS) * advantage).mean()
        return actor_loss + VF_COEF * value_loss - ENT_COEF * pi.entropy().mean()

    def train(key):
        init_key, reset_key, key = jax.random.split(key, 3)
        params = network.init(init_key, jnp.zeros(3))
        opt_state = optimizer.init(params)
        obs, state = jax.vmap(env.reset, (0, None))(jax.random.split(reset_key, NUM_ENVS),
                                                     env_params)

        def env_step(carry, key):
            params, obs, state = carry
            noise_key, step_key = jax.random.split(key)
            value, pi = network.apply(params, obs)
            action, action_log_prob = pi.sample_and_log_prob(seed=noise_key)
            next_obs, state, reward, terminated, truncated, _ = jax.vmap(
                env.step, (0, 0, 0, None))(jax.random.split(step_key, NUM_ENVS), state, action,
                                          env_params)
            done = jnp.logical_or(terminated, truncated)
            transition = Rollout(obs, action, reward * reward_scale, done, action_log_prob, value)
            return (params, next_obs, state), transition

        def update(carry, key):
            # ---------------------------------------------------------------- collect
            params, opt_state, obs, state = carry
            rollout_key, shuffle_key = jax.random.split(key)
            (_, obs, state), rollout = jax.lax.scan(
                env_step, (params, obs, state), jax.random.split(rollout_key, ROLLOUT + 1))
            advantages, targets = gae(rollout)
            batch = jax.tree.map(lambda x: x[:ROLLOUT].reshape(ROLLOUT * NUM_ENVS, *x.shape[2:]),
                                 (rollout.obs, rollout.action, rollout.log_prob, rollout.value))
            batch = (*batch, targets.reshape(-1), advantages.reshape(-1))

            # ---------------------------------------------------------------- learn
            def epoch(carry, key):
                order = jax.random.permutation(key, ROLLOUT * NUM_ENVS)
                minibatches = jax.tree.map(
                    lambda x: x[order].reshape(MINIBATCHES, -1, *x.shape[1:]), batch)

                def minibatch(carry, data):
                    params, opt_state = carry
                    grads = jax.grad(loss_fn)(params, *data)
                    updates, opt_state = optimizer.update(grads, opt_state, params)
                    return (optax.apply_updates(params, updates), opt_state), None
                return jax.lax.scan(minibatch, carry, minibatches)[0], None
            (params, opt_state), _ = jax.lax.scan(epoch, (params, opt_state),
                                                  jax.random.split(shuffle_key, EPOCHS))
            return (params, opt_state, obs, state), None

        def block(carry, key):
            update_key, eval_key = jax.random.split(key)
            carry, _ = jax.lax.scan(update, carry, jax.random.split(update_key, UPDATES_PER_EVAL))
            return carry, evaluate(carry[0], eval_key)

        train_key, final_key = jax.random.split(key)
        (params, *_), evaluations = jax.lax.scan(
            block, (params, opt_state, obs, state), jax.random.split(train_key, EVALS))
        return params, jnp.append(evaluations, evaluate(params, final_key))

    return network, train


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0, help="the key the seeds are split from")
    parser.add_argument("--episodes", type=int, default=2048, help="common start states")
    parser.add_argument("--reward-scale", type=float, default=1.0,
                        help="multiplies the rewards PPO learns from; 1 is the recipe")
    args = parser.parse_args(argv)

    env, env_params = gymnax.make("Pendulum-v1")
    network, train = make_train(env, env_params, args.reward_scale)
    started = time.perf_counter()
    params, evaluations = jax.block_until_ready(jax.jit(jax.vmap(train))(
        jax.random.split(jax.random.PRNGKey(args.seed), args.seeds)))
    trained_s = time.perf_counter() - started

    keys = jax.random.split(jax.random.PRNGKey(0), args.episodes)  # pendulum_optimal's starts

    @jax.jit
    def scores(params):
        return (episode_returns(env, env_params, network, params, keys, sample=False),
                episode_returns(env, env_params, network, params, keys, sample=True))
    deterministic, sampled = (np.asarray(x) for x in jax.vmap(scores)(params))
    evaluations = np.asarray(evaluations)
    final, best = evaluations[:, -1], evaluations.max(axis=1)

    updates = EVALS * UPDATES_PER_EVAL
    print(f"gymnax-blines' PPO recipe on Pendulum-v1 (rewards x {args.reward_scale:g}), "
          f"{args.seeds} seeds, {updates} updates ({updates * (ROLLOUT + 1) * NUM_ENVS} steps) "
          f"each  [{trained_s:.0f} s]")
    print(f"{'seed':>4} {'published protocol: final':>26} {'best of 32':>11} "
          f"{'common starts: mean action':>27} {'sampled':>8}")
    for i in range(args.seeds):
        print(f"{i:4d} {final[i]:26.1f} {best[i]:11.1f} {deterministic[i].mean():27.1f} "
              f"{sampled[i].mean():8.1f}")
    print(f"{'mean':>4} {final.mean():26.1f} {best.mean():11.1f} {deterministic.mean():27.1f} "
          f"{sampled.mean():8.1f}")
    print(f"median seed: final {np.median(final):.1f}, common starts (mean action) "
          f"{np.median(deterministic.mean(axis=1)):.1f}")
    print(f"seeds whose final score under the published protocol is >= -130: "
          f"{int((final >= -130).sum())} of {args.seeds}; best of the 32 evaluations >= -130: "
          f"{int((best >= -130).sum())} of {args.seeds}")


if __name__ == "__main__":
    main()
