"""Safe exploration: the mean-reverting random walk in pressure space (paper section II-A, eq. 1).

For every step i and valve j::

    p*_{i+1,j} = alpha * p_{i,j} + (1 - alpha) * N(p_b, noise_std^2)
    S_{i+1}    = sum_j p*_{i+1,j}
    p_{i+1,j}  = P_max * sigmoid(beta * S_{i+1}) * p*_{i+1,j} / S_{i+1}

The paper's equation mixes the indices i and i+1 inside the sums; we use i+1 throughout, i.e. the
freshly drawn p* is both rescaled and summed, so the rescaled pressures sum exactly to
``P_max * sigmoid(beta * S)`` < P_max. The rescaling is undefined for S near 0 and flips the signs
for S < 0 (possible because the normal draw can go negative); for S <= ``_MIN_SUM`` the step keeps
p* unscaled. Every step then goes through the hard projection onto the robot's safe set
(:func:`pipeline.arm.safety.project` with the sum ceiling ``min(P_max, sum_max)``), so each command is
within its per-valve bounds and the sum within P_max whatever alpha, beta and the draws are.

A run is ``pad_steps`` commands at the preload, the walk starting from the preload, then
``pad_steps`` commands at the preload again (the paper records the preload state before and after).
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np

from pipeline.arm.safety import SafeSet, project

_MIN_SUM = 1e-3  # kPa; below this the sigmoid rescaling is skipped (see module docstring)


@partial(jax.jit, static_argnames=("num_steps",))
def random_walk(
    key: chex.PRNGKey,
    alpha: float,
    beta: float,
    p_max: float,
    preload: float,
    noise_std: float,
    safe: SafeSet,
    num_steps: int,
) -> chex.Array:
    """Pressure commands ``[num_steps, n_valves]`` of the walk, starting from the preload.

    Row i is p_{i+1} (the command sent at step i); p_0 is the preload and is not included.
    """
    n_valves = safe.p_min.shape[-1]
    ceiling = SafeSet(safe.p_min, safe.p_max, jnp.minimum(safe.sum_max, p_max))

    def step(p_prev, step_key):
        draw = preload + noise_std * jax.random.normal(step_key, (n_valves,))
        p_star = alpha * p_prev + (1.0 - alpha) * draw
        total = p_star.sum()
        safe_total = jnp.where(total > _MIN_SUM, total, 1.0)
        rescaled = p_max * jax.nn.sigmoid(beta * total) * p_star / safe_total
        p_next = project(jnp.where(total > _MIN_SUM, rescaled, p_star), ceiling)
        return p_next, p_next

    p0 = jnp.full((n_valves,), preload, jnp.float32)
    _, commands = jax.lax.scan(step, p0, jax.random.split(key, num_steps))
    return commands


def exploration_run(key: chex.PRNGKey, exploration: Any, limits: Any, n_valves: int = 3,
                    alpha: float | None = None) -> np.ndarray:
    """One run's commands ``[pad + num_steps + pad, n_valves]`` in kPa (float64, numpy).

    ``alpha`` overrides ``exploration.alpha`` (for the figure that compares values).
    """
    safe = SafeSet.from_limits(limits, n_valves)
    if n_valves * float(limits.preload) > float(exploration.p_max):
        raise ValueError(
            f"exploration.p_max={exploration.p_max} kPa is below the preload sum "
            f"{n_valves} x {limits.preload} kPa: the runs start and end at the preload"
        )
    walk = random_walk(
        key,
        float(exploration.alpha if alpha is None else alpha),
        float(exploration.beta),
        float(exploration.p_max),
        float(limits.preload),
        float(exploration.noise_std),
        safe,
        int(exploration.num_steps),
    )
    pad = np.full((int(exploration.pad_steps), n_valves), float(limits.preload))
    return np.concatenate([pad, np.asarray(walk, np.float64), pad], axis=0)


class ExplorationPlan(NamedTuple):
    """A session's draws from ``exploration.seed``: one key per purpose, never one for two."""

    commands: np.ndarray  # [runs, pad + num_steps + pad, n_valves] kPa
    session_key: chex.PRNGKey  # the simulated sessions (rest poses, mocap noise)
    figure_key: chex.PRNGKey  # the walks of the several-alpha figure


def plan_keys(exploration: Any) -> tuple[chex.PRNGKey, chex.PRNGKey, chex.PRNGKey]:
    """The walk, session and figure keys of ``exploration.seed``."""
    walk_key, session_key, figure_key = jax.random.split(jax.random.key(int(exploration.seed)), 3)
    return walk_key, session_key, figure_key


def exploration_plan(exploration: Any, limits: Any, n_valves: int, num_runs: int
                     ) -> ExplorationPlan:
    """The walks of ``num_runs`` runs: the same for the simulated arm and a ROS 2 arm."""
    walk_key, session_key, figure_key = plan_keys(exploration)
    commands = np.stack([exploration_run(k, exploration, limits, n_valves)
                         for k in jax.random.split(walk_key, int(num_runs))])
    return ExplorationPlan(commands, session_key, figure_key)


def plot_walks(path: Path, key: chex.PRNGKey, exploration: Any, limits: Any,
               control_hz: float, n_valves: int = 3) -> Path:
    """Figure of the walk for several alpha values (paper Fig. 4), same draws for each alpha."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    alphas = list(exploration.figure_alphas)
    fig, axes = plt.subplots(len(alphas), 1, figsize=(9, 1.9 * len(alphas) + 0.6),
                             sharex=True, squeeze=False)
    for ax, alpha in zip(axes[:, 0], alphas):
        p = exploration_run(key, exploration, limits, n_valves, alpha=alpha)
        t = np.arange(len(p)) / control_hz
        for j in range(n_valves):
            ax.step(t, p[:, j], where="post", lw=1.0, label=f"valve {j}")
        ax.step(t, p.sum(axis=1), where="post", lw=1.0, color="k", alpha=0.5, label="sum")
        ax.axhline(min(float(exploration.p_max), float(limits.sum_max)), color="r", ls="--",
                   lw=0.8, label="sum ceiling")
        ax.set_ylabel("kPa")
        ax.set_title(f"alpha = {alpha:g}, beta = {float(exploration.beta):g}", fontsize=9)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle("Exploration: mean-reverting random walk in pressure space")
    # the legend above the first panel, clear of its traces (alpha = 0 jumps everywhere)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    top = 1 - 0.6 / fig.get_figheight()
    fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, top), ncol=n_valves + 2,
               fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0, 1, top - 0.25 / fig.get_figheight()))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

