"""How good can a Pendulum-v1 return be? Dynamic programming on gymnax's own dynamics.

PPO's returns on Pendulum-v1 are compared with a published figure; this script gives
the reference that no policy can beat by much: the finite-horizon optimum, by backward value
iteration over a grid of (angle, angular velocity) with bilinear interpolation and a set of
torque levels, 200 steps as in an episode. The greedy policy of that value function is then run
on the exact dynamics (``gymnax`` ``Pendulum-v1``) from gymnax's reset distribution (angle uniform
in [-pi, pi], velocity uniform in [-1, 1]): its mean return is what a near-optimal policy scores.

With ``--policy`` a trained policy (a ``train_ppo`` artifact's ``policy.msgpack``, every seed in
it) is run, deterministically, from the same start states, and the gap to the optimum is broken
down by the start angle: where the policy loses return, not only how much.

Example::

    .venv/bin/python -m experiments.pendulum_optimal --episodes 2048
    .venv/bin/python -m experiments.pendulum_optimal --policy outputs/artifacts/train_ppo/<key>/policy.msgpack
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from pipeline.rl.pendulum_optimum import optimal_returns, policy_returns, solve

ANGLE_BINS = 12  # start-angle bins of the breakdown (0 is upright, +-pi hanging down)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--angles", type=int, default=512, help="grid points over [-pi, pi)")
    parser.add_argument("--velocities", type=int, default=321, help="grid points over [-8, 8]")
    parser.add_argument("--torques", type=int, default=41, help="torque levels over [-2, 2]")
    parser.add_argument("--episodes", type=int, default=2048)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--policy", default=None,
                        help="a train_ppo policy.msgpack to compare, from the same start states")
    parser.add_argument("--sampled", action="store_true",
                        help="with --policy, also run it with actions sampled from its Gaussian")
    args = parser.parse_args(argv)

    started = time.perf_counter()
    optimum = solve(args.angles, args.velocities, args.torques)
    keys = jax.random.split(jax.random.PRNGKey(args.seed), args.episodes)
    returns, predicted = optimal_returns(optimum, keys)
    print(f"Pendulum-v1, greedy policy of value iteration ({args.angles} x {args.velocities} "
          f"grid, {args.torques} torques), {args.episodes} episodes on the exact dynamics: mean "
          f"return {returns.mean():.1f} (standard error "
          f"{returns.std() / np.sqrt(len(returns)):.1f}), median {np.median(returns):.1f}, "
          f"p5 {np.percentile(returns, 5):.1f}; the grid's own estimate of the optimum "
          f"{predicted.mean():.1f}  [{time.perf_counter() - started:.0f} s]")
    if args.policy:
        compare_policy(optimum.env, optimum.params, args.policy, keys, returns, args.sampled)


def compare_policy(env, params, policy_path, keys, optimal, sampled: bool = False) -> None:
    """Print the policy's returns next to the optimum's, from the same start states."""
    if sampled:
        noisy = policy_returns(env, params, policy_path, keys, sampled=True)
        # what one published-style figure (the mean of 164 episodes) spreads over
        chunks = noisy[:, : noisy.shape[1] // 164 * 164].reshape(noisy.shape[0], -1, 164)
        print(f"policy {policy_path}, actions sampled: mean return {noisy.mean():.1f}; per seed "
              f"{[round(float(x), 1) for x in noisy.mean(axis=1)]}; means of 164 episodes range "
              f"{chunks.mean(axis=2).min():.1f} .. {chunks.mean(axis=2).max():.1f}")
    returns = policy_returns(env, params, policy_path, keys)
    gap = returns - optimal[None]
    print(f"policy {policy_path}: {returns.shape[0]} seeds x {returns.shape[1]} episodes, mean "
          f"return {returns.mean():.1f}, median {np.median(returns):.1f}; per seed "
          f"{[round(float(x), 1) for x in returns.mean(axis=1)]}")
    print(f"gap to the optimum from the same start states: mean {gap.mean():.1f}, median "
          f"{np.median(gap):.1f}")
    _, start = jax.vmap(env.reset_env, in_axes=(0, None))(keys, params)
    edges = np.linspace(-np.pi, np.pi, ANGLE_BINS + 1)
    which = np.clip(np.digitize(np.asarray(start.theta), edges) - 1, 0, ANGLE_BINS - 1)
    print(f"{'start angle (rad)':>18} {'episodes':>8} {'optimum':>8} {'policy':>8} {'gap':>7}")
    for b in range(ANGLE_BINS):
        chosen = which == b
        print(f"{edges[b]:+8.2f} .. {edges[b + 1]:+5.2f} {chosen.sum():8d} "
              f"{optimal[chosen].mean():8.1f} {returns[:, chosen].mean():8.1f} "
              f"{gap[:, chosen].mean():7.1f}")


if __name__ == "__main__":
    main()
