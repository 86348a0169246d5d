"""The policy's GRU at PPO's shapes: this project's recurrence next to flax's GRUCell scanned.

    python -m bench gru_kernel [--width 64] [--seeds 4]

Both compute the same GRU (the same variables; ``tests/test_ppo.py`` checks values and
gradients); resets are left out, which flax's cell has no input for. Rows, each vmapped over
``--seeds`` parameter sets as in training (``agent.num_seeds``):

- ``act``: one step of ``agent.num_envs`` environments, 32 times in a scan (a rollout);
- ``train``: loss gradient over a ``[num_steps, num_envs / num_minibatches]`` sequence
  minibatch (one PPO gradient step of the recurrent policy);
- ``bootstrap``: one step of ``num_steps * num_envs`` rows (the rollout's bootstrap values).

Milliseconds per call (best of 3 repeats), and the ratio flax / ours.
"""

from __future__ import annotations

import argparse
import time

import flax.linen as nn
import jax
import jax.numpy as jnp

from pipeline.rl.networks import ResettingGRU
from pipeline.schemas import AgentConfig


class FlaxScannedGRU(nn.Module):
    """flax's GRUCell under ``nn.scan`` (variables under the same name as ResettingGRU's)."""

    features: int

    @nn.compact
    def __call__(self, carry, x):
        scan = nn.scan(nn.GRUCell, variable_broadcast="params", split_rngs={"params": False})
        return scan(self.features, name="GRUCell_0")(carry, x)


def best_ms(fn, *args, repeats: int = 3, calls: int = 20) -> float:
    fn = jax.jit(fn)
    jax.block_until_ready(fn(*args))
    best = float("inf")
    for _ in range(repeats):
        started = time.perf_counter()
        for _ in range(calls):
            out = fn(*args)
        jax.block_until_ready(out)
        best = min(best, (time.perf_counter() - started) / calls * 1e3)
    return best


def measure(width: int, seeds: int) -> list[tuple[str, float, float]]:
    agent = AgentConfig()
    envs, steps = agent.num_envs, agent.num_steps
    ours, flax_gru = ResettingGRU(width), FlaxScannedGRU(width)
    init_key, carry_key, input_key = jax.random.split(jax.random.PRNGKey(0), 3)
    variables = ours.init(init_key, jnp.zeros((1, width)),
                          (jnp.zeros((1, 1, width)), jnp.zeros((1, 1), bool)))
    stacked = jax.tree.map(lambda x: jnp.stack([x] * seeds), variables)

    def ours_apply(v, carry, x):
        return ours.apply(v, carry, (x, jnp.zeros(x.shape[:2], bool)))

    def flax_apply(v, carry, x):
        return flax_gru.apply(v, carry, x)

    def act(apply):
        def rollout(v, carry, x):
            return jax.lax.scan(lambda c, _: (apply(v, c, x)[0], None), carry, None, 32)[0]
        return jax.vmap(rollout)

    def train(apply):
        def loss(v, carry, x):
            final, ys = apply(v, carry, x)
            return (ys ** 2).mean() + (final ** 2).mean()
        return jax.vmap(jax.grad(loss))

    def one_step(apply):
        return jax.vmap(lambda v, carry, x: apply(v, carry, x)[1])

    def inputs(length: int, rows: int):
        return (jax.random.normal(carry_key, (seeds, rows, width)),
                jax.random.normal(input_key, (seeds, length, rows, width)))

    cases = {
        "act": (act, inputs(1, envs)),
        "train": (train, inputs(steps, envs // agent.num_minibatches)),
        "bootstrap": (one_step, inputs(1, steps * envs)),
    }
    return [(name, best_ms(make(flax_apply), stacked, *data), best_ms(make(ours_apply), stacked,
                                                                      *data))
            for name, (make, data) in cases.items()]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=AgentConfig().rnn_hidden)
    parser.add_argument("--seeds", type=int, default=AgentConfig().num_seeds)
    args = parser.parse_args(argv)
    rows = measure(args.width, args.seeds)
    print(f"GRU of {args.width} units, {args.seeds} seeds (vmap), {jax.devices()[0].platform}")
    print(f"{'call':<11}{'flax GRUCell ms':>17}{'ours ms':>10}{'flax / ours':>13}")
    for name, flax_ms, ours_ms in rows:
        print(f"{name:<11}{flax_ms:>17.3f}{ours_ms:>10.3f}{flax_ms / ours_ms:>13.2f}")


if __name__ == "__main__":
    main()
