"""Which goals a plant can hold at all: the nearest any admissible constant command holds it.

For each episode of an evaluation (a plant, the episode's start state on it and its goal), the
smallest distance to the goal at the end of the episode's horizon that a **constant command
inside the safe set** (the arm's limits, ``p_min <= p_j <= p_max`` per valve and
``sum_j p_j <= sum_max`` kPa, :mod:`pipeline.arm.safety`) leaves the plant at, held from the
episode's start for its whole horizon. Found by a grid over the safe set (``grid_points`` per
valve, projected onto it) and, from each episode's few nearest grid points, damped Gauss-Newton
steps through the plant (its Jacobian in the held pressures), then a local search (the 27
commands ``best + step * {-1, 0, 1}^3``, projected, the best kept; the step doubles after a
move that came nearer and halves after one that did not).

A goal within the tolerance of that distance is **reachable**: the command found holds the
plant there. The search is local, so the distance it finds is an upper bound of the nearest
constant hold, and the share of reachable goals a lower bound. A feedback controller can end
nearer than any constant command only through the plant's memory (hysteresis, creep, a model's
drift under a held command) or by passing the goal at the very end. On the simulated arm the
memory is a play of half-width ``h`` per chamber: any controller holds each chamber's effective
pressure within ``[p_min + h, p_max - h]`` and their sum below ``sum_max + 3 h``, which
constant commands ``2 h`` beyond the limits (``margin_kpa``) cover, so the exact nearest hold
with that margin bounds every controller's hold from below (the search's, only as far as it
finds it). On a learned model a constant command held for the whole horizon is a command
sequence it was never fitted to (its data is a walk at the control rate), so its reach there is
a weaker statement.

The plants are those of the evaluation (:mod:`pipeline.evaluation.closed_loop`): nominal, no
randomization, the position the plant's own (an environment's randomized rest offset is zero
there). :func:`evaluation_episodes` builds them, and the goals, as the evaluation does;
:func:`evaluation_reach` finds the reach of every episode on each, with its start state;
:func:`split_misses` tells which of a controller's misses were on reachable goals.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from pipeline.arm.safety import SafeSet, project
from pipeline.evaluation.closed_loop import ClosedLoopSettings, _plants
from pipeline.evaluation.metrics import MM_PER_M
from pipeline.rl.envs.plants import NUM_VALVES, Plant, hold

# the local search's moves: every valve down, still or up by one step
_STENCIL = np.array(list(itertools.product((-1.0, 0.0, 1.0), repeat=NUM_VALVES)), np.float32)


@dataclass(frozen=True)
class ReachSettings:
    """How finely the safe set is searched.

    grid_points: commands per valve on the grid over ``[p_min, p_max]`` (``grid_points^3``
      before the projection onto the sum limit).
    newton_rounds: damped Gauss-Newton (Levenberg-Marquardt) steps from each of the
      ``starts`` nearest grid points, through the plant's Jacobian in the held pressures
      (forward-mode through the hold), each projected onto the safe set.
    refine_rounds: rounds of the local search after them (where a projected step stalls on
      the limits); its step starts at half the grid's spacing, doubles (up to the spacing)
      after a round that came nearer and halves after one that did not.
    starts: grid points the local search starts from (the nearest ones): the map from the
      pressures to the position is nearly flat along the mean pressure, so the nearest grid
      point can lie in the wrong part of a long valley.
    tolerance_mm: a goal is reachable where the distance is within it.
    margin_kpa: commands this far beyond each valve's limits (and three times it beyond the
      sum limit) are admitted too: 0 for the arm's limits; twice a plant's hysteresis play
      bounds what any controller (not only a constant command) can hold it at.
    """

    grid_points: int = 9
    refine_rounds: int = 24
    starts: int = 4
    newton_rounds: int = 12
    tolerance_mm: float = 1.0
    margin_kpa: float = 0.0

    def check(self) -> None:
        if int(self.grid_points) < 2:
            raise ValueError(f"grid_points must be >= 2, got {self.grid_points}")
        if int(self.newton_rounds) < 0:
            raise ValueError(f"newton_rounds must be >= 0, got {self.newton_rounds}")
        if int(self.refine_rounds) < 0:
            raise ValueError(f"refine_rounds must be >= 0, got {self.refine_rounds}")
        if not 1 <= int(self.starts) <= int(self.grid_points) ** NUM_VALVES:
            raise ValueError(f"starts must be between 1 and the grid's points, got "
                             f"{self.starts}")
        if not float(self.tolerance_mm) > 0:
            raise ValueError(f"tolerance_mm must be > 0, got {self.tolerance_mm}")
        if float(self.margin_kpa) < 0:
            raise ValueError(f"margin_kpa must be >= 0, got {self.margin_kpa}")


class Reach(NamedTuple):
    """The nearest hold per episode: ``distance_mm [E]`` (mm) and the command ``pressure
    [E, 3]`` (kPa, inside the safe set) that holds it; ``preload_mm [E]`` (mm): the distance
    holding the preload instead (what the ``preload`` baseline ends at; NaN where not asked)."""

    distance_mm: np.ndarray
    pressure: np.ndarray
    preload_mm: np.ndarray


def held_positions(plant: Plant, plant_params: Any, carries: Any, pressures: jax.Array,
                   num_steps: int) -> jax.Array:
    """Positions ``[E, P, 3]`` (m) after holding ``pressures [E, P, 3]`` kPa for ``num_steps``
    plant steps from ``carries`` (one per episode, leaves ``[E, ...]``): row ``e, p`` holds
    ``pressures[e, p]`` from ``carries[e]``."""
    chex.assert_rank(pressures, 3)
    chex.assert_axis_dimension(pressures, -1, NUM_VALVES)

    def final(carry, pressure):
        return hold(plant, plant_params, carry, pressure, int(num_steps))[1][-1]

    return jax.vmap(jax.vmap(final, in_axes=(None, 0)), in_axes=(0, 0))(carries, pressures)


@functools.partial(jax.jit, static_argnames=("plant", "num_steps"))
def _linearized(plant: Plant, num_steps: int, plant_params: Any, carries: Any,
                pressures: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Positions ``[E, P, 3]`` (m) of :func:`held_positions` and their Jacobians ``[E, P, 3,
    3]`` (m/kPa) in the held pressures (forward mode, one pass)."""

    def final(carry, pressure):
        position = hold(plant, plant_params, carry, pressure, int(num_steps))[1][-1]
        return position, position

    jacobian = jax.jacfwd(final, argnums=1, has_aux=True)
    jac, positions = jax.vmap(jax.vmap(jacobian, in_axes=(None, 0)), in_axes=(0, 0))(
        carries, pressures)
    return positions, jac


@functools.partial(jax.jit, static_argnames=("plant", "num_steps"))
def _distances(plant: Plant, num_steps: int, plant_params: Any, carries: Any, goals: jax.Array,
               pressures: jax.Array) -> jax.Array:
    """``[E, P]`` m: the distance of :func:`held_positions` to each episode's goal ``[E, 3]``."""
    positions = held_positions(plant, plant_params, carries, pressures, num_steps)
    return jnp.linalg.norm(positions - goals[:, None], axis=-1)


def safe_grid(safe_set: SafeSet, points: int) -> jax.Array:
    """``[points^3, 3]`` kPa: a regular grid over the valves' box, projected onto the safe set
    (grid points beyond the sum limit land on it)."""
    axes = [jnp.linspace(safe_set.p_min[v], safe_set.p_max[v], int(points))
            for v in range(NUM_VALVES)]
    grid = jnp.stack(jnp.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, NUM_VALVES)
    return project(grid, safe_set)


def nearest_hold(plant: Plant, plant_params: Any, carries: Any, goals: jax.Array,
                 safe_set: SafeSet, num_steps: int, settings: ReachSettings = ReachSettings(),
                 preload: jax.Array | None = None) -> Reach:
    """The nearest distance to ``goals [E, 3]`` (m) that a constant admissible command holds
    the plant at after ``num_steps`` plant steps from ``carries`` (leaves ``[E, ...]``); see
    the module docstring for the search. ``preload [3]`` kPa: also the distance holding it."""
    settings.check()
    goals = jnp.asarray(goals, jnp.float32)
    chex.assert_shape(goals, (None, 3))
    count, starts = goals.shape[0], int(settings.starts)
    safe_set = widened(safe_set, settings.margin_kpa)

    def distances(pressures):  # [E, P, 3] kPa -> [E, P] m
        return _distances(plant, int(num_steps), plant_params, carries, goals, pressures)

    grid = safe_grid(safe_set, settings.grid_points)
    to_goal = distances(jnp.broadcast_to(grid, (count, *grid.shape)))
    order = jnp.argsort(to_goal, axis=1)[:, :starts]  # [E, K] the best grid points
    best = grid[order]  # [E, K, 3]
    best_distance = jnp.take_along_axis(to_goal, order, axis=1)  # [E, K]
    best, best_distance = _levenberg_marquardt(
        lambda p: _linearized(plant, int(num_steps), plant_params, carries, p), best,
        best_distance, goals, safe_set, int(settings.newton_rounds))
    spacing = (safe_set.p_max - safe_set.p_min) / (int(settings.grid_points) - 1)  # [3]
    step = jnp.broadcast_to(0.5 * spacing, (count, starts, NUM_VALVES))
    stencil = jnp.asarray(_STENCIL)
    for _ in range(int(settings.refine_rounds)):
        candidates = project(best[:, :, None] + step[:, :, None] * stencil, safe_set)
        to_goal = distances(candidates.reshape(count, -1, NUM_VALVES)).reshape(
            count, starts, -1)  # [E, K, 27]
        pick = jnp.argmin(to_goal, axis=-1)
        nearest = jnp.min(to_goal, axis=-1)
        improved = nearest < best_distance
        chosen = jnp.take_along_axis(candidates, pick[..., None, None], axis=2)[:, :, 0]
        best = jnp.where(improved[..., None], chosen, best)
        best_distance = jnp.minimum(best_distance, nearest)
        # a move that helped is tried again twice as long, one that did not at half the length
        step = jnp.where(improved[..., None], jnp.minimum(2.0 * step, spacing), 0.5 * step)
    winner = jnp.argmin(best_distance, axis=1)
    pressure = best[jnp.arange(count), winner]
    resting = np.full(count, np.nan)
    if preload is not None:
        still = jnp.broadcast_to(jnp.asarray(preload, jnp.float32), (count, 1, NUM_VALVES))
        resting = np.asarray(distances(still)[:, 0], np.float64) * MM_PER_M
    return Reach(np.asarray(best_distance.min(axis=1), np.float64) * MM_PER_M,
                 np.asarray(pressure), resting)


def _levenberg_marquardt(linearized, pressures: jax.Array, distance: jax.Array,
                         goals: jax.Array, safe_set: SafeSet, rounds: int
                         ) -> tuple[jax.Array, jax.Array]:
    """``rounds`` damped Gauss-Newton steps toward ``goals [E, 3]`` from ``pressures [E, K,
    3]`` (kPa; their distances ``[E, K]`` m), each projected onto ``safe_set``; a step that
    does not come nearer is refused and the damping raised tenfold, one that does lowers it
    threefold. ``linearized(pressures) -> (positions, jacobians)``."""
    damping = jnp.full(distance.shape, 1e-6)  # (m/kPa)^2
    positions, jac = linearized(pressures)
    for _ in range(rounds):
        error = goals[:, None] - positions  # [E, K, 3] m
        normal = jnp.einsum("ekji,ekjl->ekil", jac, jac) + damping[..., None, None] * jnp.eye(3)
        move = jnp.linalg.solve(normal, jnp.einsum("ekji,ekj->eki", jac, error)[..., None])
        trial = project(pressures + move[..., 0], safe_set)
        trial_positions, trial_jac = linearized(trial)
        trial_distance = jnp.linalg.norm(goals[:, None] - trial_positions, axis=-1)
        better = trial_distance < distance
        pressures = jnp.where(better[..., None], trial, pressures)
        positions = jnp.where(better[..., None], trial_positions, positions)
        jac = jnp.where(better[..., None, None], trial_jac, jac)
        distance = jnp.where(better, trial_distance, distance)
        damping = jnp.where(better, damping / 3.0, damping * 10.0)
    return pressures, distance


def widened(safe_set: SafeSet, margin_kpa: float) -> SafeSet:
    """``safe_set`` with every valve's limits ``margin_kpa`` further out and the sum limit
    three times that (the set itself for 0)."""
    if not margin_kpa:
        return safe_set
    margin = jnp.float32(margin_kpa)
    return SafeSet(safe_set.p_min - margin, safe_set.p_max + margin,
                   safe_set.sum_max + NUM_VALVES * margin)


def episode_reach(env: Any, env_params: Any, goals: jax.Array, num_episodes: int,
                  settings: ReachSettings = ReachSettings()) -> Reach:
    """:func:`nearest_hold` for ``num_episodes`` episodes of an evaluation on the plant of
    ``env`` with ``env_params``: episode ``e`` starts from reset-bank entry ``e`` modulo the
    bank's size (as the evaluation starts it) with goal ``goals[e]``, held for the episode's
    ``max_steps`` control periods. The plant must be nominal: a randomization of the env
    (whose rest offset moves the position) is refused."""
    spread = jax.tree.leaves(env_params.randomization)
    if any(np.any(np.asarray(leaf) != 0) for leaf in spread):
        raise ValueError("episode_reach: the env parameters randomize the plant; the reach is "
                         "defined on a nominal plant (the evaluation's parameters)")
    index = jnp.arange(int(num_episodes)) % env_params.reset_positions.shape[0]
    carries = jax.tree.map(lambda leaf: leaf[index], env_params.reset_carries)
    num_steps = int(env_params.max_steps) * int(env.steps_per_action)
    return nearest_hold(env.plant, env_params.plant, carries, goals, env_params.safe_set,
                        num_steps, settings, env_params.preload)


def evaluation_episodes(settings: ClosedLoopSettings, env: Any, eval_params: Any,
                        models: Mapping[str, Any] | None = None,
                        twins: Mapping[str, Mapping[str, Any]] | None = None
                        ) -> tuple[dict[str, tuple[Any, Any]], jax.Array]:
    """The plants (``{name: (env, env_params)}``) and the goals ``[E, 3]`` (m) that
    :func:`pipeline.evaluation.closed_loop.run_evaluation` rolls every controller out on, for
    the same arguments: its goals drawn with the first of the four keys it splits from
    ``evaluation.seed``, its plants built with the second."""
    episodes = int(settings.evaluation.num_episodes)
    goal_key, plant_key, _, _ = jax.random.split(jax.random.key(int(settings.evaluation.seed)),
                                                 4)
    index = jax.random.randint(goal_key, (episodes,), 0, eval_params.goal_set.shape[0])
    plants = _plants(settings, env, eval_params, plant_key, models or {}, twins or {})
    return plants, eval_params.goal_set[index]


def evaluation_reach(plants: Mapping[str, tuple[Any, Any]], goals: jax.Array,
                     settings: ReachSettings = ReachSettings()) -> pd.DataFrame:
    """One row per plant and episode of an evaluation: ``plant``, ``episode``, ``reach_mm``
    (:func:`episode_reach`), ``reachable`` (within ``settings.tolerance_mm``), the command
    that holds it (``reach_p0_kpa`` ... ``reach_p2_kpa``) and ``preload_mm`` (the distance
    holding the preload: what the ``preload`` baseline ends at). ``plants``: ``{name: (env,
    env_params)}`` as the evaluation builds them; ``goals [E, 3]`` m its goals."""
    rows = []
    count = int(np.shape(goals)[0])
    for name, (env, params) in plants.items():
        reach = episode_reach(env, params, goals, count, settings)
        table = pd.DataFrame({"plant": name, "episode": np.arange(count),
                              "reach_mm": reach.distance_mm,
                              "reachable": reach.distance_mm <= float(settings.tolerance_mm),
                              "preload_mm": reach.preload_mm})
        for valve in range(NUM_VALVES):
            table[f"reach_p{valve}_kpa"] = reach.pressure[:, valve]
        rows.append(table)
    return pd.concat(rows, ignore_index=True)


def split_misses(episodes: pd.DataFrame, reach: pd.DataFrame, miss_mm: float = 1.0
                 ) -> pd.DataFrame:
    """Per plant and controller: how many of the goals are reachable and where the misses are.

    ``episodes``: the evaluation's per-episode table (``plant``, ``controller``, ``seed``,
    ``episode``, ``final_distance_mm``); ``reach``: :func:`evaluation_reach`'s (``plant``,
    ``episode``, ``reach_mm``, ``reachable``). Columns: ``episodes`` (all seeds'),
    ``reachable_goals`` (share of the episodes whose goal is reachable), ``misses`` (share
    ending beyond ``miss_mm``), ``misses_reachable`` (of the misses, the share on reachable
    goals), ``median_final_reachable_mm`` / ``success_reachable`` (median final distance and
    share within ``miss_mm`` over the episodes of reachable goals), ``median_reach_mm`` (over
    all episodes) and ``median_excess_unreachable_mm`` (over the misses on unreachable goals:
    final distance minus the reach, how much further than the nearest hold they ended).
    """
    merged = episodes.merge(reach[["plant", "episode", "reach_mm", "reachable"]],
                            on=["plant", "episode"], how="inner", validate="many_to_one")
    if len(merged) != len(episodes):
        raise ValueError(f"split_misses: {len(episodes) - len(merged)} episodes have no reach "
                         f"row (plants {sorted(set(episodes.plant) - set(reach.plant))})")
    rows = []
    for (plant, controller), group in merged.groupby(["plant", "controller"], sort=False):
        final = group["final_distance_mm"].to_numpy()
        reachable = group["reachable"].to_numpy(bool)
        missed = final > miss_mm
        unreachable_misses = missed & ~reachable
        rows.append({
            "plant": plant, "controller": controller, "episodes": len(group),
            "reachable_goals": float(reachable.mean()),
            "misses": float(missed.mean()),
            "misses_reachable": (float((missed & reachable).sum() / missed.sum())
                                 if missed.any() else float("nan")),
            "median_final_reachable_mm": (float(np.median(final[reachable]))
                                          if reachable.any() else float("nan")),
            "success_reachable": (float((final[reachable] <= miss_mm).mean())
                                  if reachable.any() else float("nan")),
            "median_reach_mm": float(np.median(group["reach_mm"])),
            "median_excess_unreachable_mm": (
                float(np.median(final[unreachable_misses]
                                - group["reach_mm"].to_numpy()[unreachable_misses]))
                if unreachable_misses.any() else float("nan")),
        })
    return pd.DataFrame(rows)


REACH_COLUMNS = ("reachable_goals", "success_reachable", "median_final_reachable_mm")


def reach_plants(names: Collection[str], which: bool | None) -> list[str]:
    """The plants whose reach an evaluation finds (``evaluation.reach``): every one for true,
    none for false, the calibrated twins (``twin <name>``) for None."""
    if which is None:
        return [name for name in names if str(name).startswith("twin ")]
    return list(names) if which else []


def with_reach(results: dict[str, Any], which: bool | None = None,
               settings: ReachSettings = ReachSettings()) -> dict[str, Any]:
    """``results`` of :func:`pipeline.evaluation.closed_loop.run_evaluation` with the reach of
    the episodes of the plants :func:`reach_plants` picks (``which``: ``evaluation.reach``):
    the table ``reach`` (:func:`evaluation_reach`) and, in ``summary``
    and the headline, per plant and controller the share of the goals the plant can hold at
    all (``reachable_goals``) and the controller's success and median on those
    (``success_reachable``, ``median_final_reachable_mm``; :func:`split_misses`), so that a
    goal no constant admissible command holds the plant at is not counted as the
    controller's miss."""
    tables = results["tables"]
    chosen = reach_plants(results["plants"], which)
    if not chosen:
        return results
    reach = evaluation_reach({name: results["plants"][name] for name in chosen},
                             results["goals"], settings)
    episodes = tables["episodes"]
    split = split_misses(episodes[episodes["plant"].isin(chosen)], reach,
                         float(settings.tolerance_mm))
    tables["reach"] = reach
    tables["summary"] = tables["summary"].merge(
        split[["plant", "controller", *REACH_COLUMNS]], on=["plant", "controller"], how="left")
    for row in tables["summary"].itertuples():
        entry = results["headline"].get(f"{row.plant}/{row.controller}")
        if entry is not None and row.plant in chosen:
            entry.update({name: float(getattr(row, name)) for name in REACH_COLUMNS[:2]})
    return results


def preload_mismatch_mm(reach: pd.DataFrame, episodes: pd.DataFrame) -> float:
    """The largest difference (mm) between :func:`evaluation_reach`'s ``preload_mm`` and the
    final distance of the evaluation's ``preload`` baseline (``episodes``, every plant of
    ``reach`` the evaluation ran): near 0 where the reach was computed on the evaluation's own
    plants, start states and goals; inf where the evaluation has no preload rows for them."""
    preload = episodes[episodes["controller"] == "preload"]
    merged = reach.merge(preload[["plant", "episode", "final_distance_mm"]],
                         on=["plant", "episode"], how="inner")
    if len(merged) != len(reach):
        return float("inf")
    return float(np.max(np.abs(merged["preload_mm"] - merged["final_distance_mm"])))
