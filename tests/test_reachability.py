"""The reach of a plant: the nearest any admissible constant command holds it to a goal, on a
toy plant whose steady state is worked out by hand, and its split of a controller's misses."""

from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from pipeline.arm.safety import SafeSet
from pipeline.evaluation.closed_loop import ClosedLoopSettings, run_evaluation
from pipeline.evaluation.reachability import (
    ReachSettings,
    evaluation_episodes,
    evaluation_reach,
    held_positions,
    nearest_hold,
    preload_mismatch_mm,
    split_misses,
)
from pipeline.rl.envs.learned import make_env_params
from pipeline.rl.envs.plants import LinearLagParams, default_linear_lag_params, linear_lag_plant
from pipeline.rl.envs.reach import SoftArmReachEnv
from pipeline.schemas import EnvConfig, EvaluationConfig

SAFE = SafeSet.from_limits(SimpleNamespace(p_min=0.0, p_max=7.0, sum_max=13.0))
PLANT = linear_lag_plant(model_hz=10.0)


def toy(lag_factor: float = 1.0) -> LinearLagParams:
    """Position = offset + 1 mm/kPa x the lagged pressure of each valve along its own axis;
    resting at 2 kPa."""
    return LinearLagParams(jnp.eye(3, dtype=jnp.float32) * 1e-3,
                           jnp.asarray(lag_factor, jnp.float32), jnp.full((3,), 2.0))


def carries(params: LinearLagParams, count: int):
    """``count`` carries of the toy resting at the origin (offset -2 mm on every axis)."""
    one = PLANT.init_carry(params, jnp.zeros(3))
    return jax.tree.map(lambda leaf: jnp.broadcast_to(leaf, (count, *leaf.shape)), one)


def test_held_positions_follow_the_lag_by_hand():
    params = toy(lag_factor=0.5)
    pressures = jnp.array([[[4.0, 2.0, 0.0], [2.0, 2.0, 2.0]]])  # [E=1, P=2, 3] kPa
    positions = held_positions(PLANT, params, carries(params, 1), pressures, num_steps=2)
    # the lag halves the gap each step: 2 -> 3 -> 3.5 kPa (4 kPa), 2 -> 1 -> 0.5 kPa (0 kPa);
    # the position is offset -2 mm plus 1 mm/kPa times it
    np.testing.assert_allclose(np.asarray(positions[0]) * 1e3,
                               [[1.5, 0.0, -1.5], [0.0, 0.0, 0.0]], atol=1e-5)


def test_nearest_hold_on_the_toy_by_hand():
    params = toy()
    goals = jnp.array([[1.0, 2.0, 0.0],  # 3, 4, 2 kPa: inside the limits, held exactly
                       [3.0, 3.0, 3.0],  # 5 kPa each sums to 15 > 13: 13/3 kPa each
                       [9.0, -2.0, -2.0],  # 11, 0, 0 kPa: the first valve stops at 7 kPa
                       [-4.0, 0.0, 0.0]]) * 1e-3  # -2, 2, 2 kPa: the first stops at 0 kPa
    reach = nearest_hold(PLANT, params, carries(params, 4), goals, SAFE, num_steps=1,
                         preload=jnp.full((3,), 2.0))
    np.testing.assert_allclose(reach.distance_mm, [0.0, np.sqrt(3) * 2 / 3, 4.0, 2.0],
                               atol=2e-3)
    np.testing.assert_allclose(reach.pressure[0], [3.0, 4.0, 2.0], atol=5e-3)
    np.testing.assert_allclose(reach.pressure[1], [13 / 3] * 3, atol=5e-3)
    np.testing.assert_allclose(reach.pressure[2], [7.0, 0.0, 0.0], atol=5e-3)
    assert (reach.pressure >= 0).all() and (reach.pressure <= 7).all()
    assert (reach.pressure.sum(-1) <= 13 + 1e-5).all()
    # the preload leaves the toy at the origin
    np.testing.assert_allclose(reach.preload_mm, np.linalg.norm(goals, axis=-1) * 1e3,
                               rtol=1e-5)
    # 1 kPa beyond each valve's limits (3 kPa beyond the sum's): the first valve stops at 8 kPa
    wider = nearest_hold(PLANT, params, carries(params, 4), goals, SAFE, num_steps=1,
                         settings=ReachSettings(margin_kpa=1.0))
    np.testing.assert_allclose(wider.distance_mm[2:], [3.0, 1.0], atol=2e-3)
    np.testing.assert_allclose(wider.distance_mm[1], 0.0, atol=2e-3)  # 15 kPa <= 16 kPa
    # the grid alone (no Gauss-Newton, no local search) is coarser: 0.875 kPa spacing
    coarse = nearest_hold(PLANT, params, carries(params, 4), goals, SAFE, num_steps=1,
                          settings=ReachSettings(grid_points=9, refine_rounds=0,
                                                 newton_rounds=0))
    assert coarse.distance_mm[0] > 0.1 and coarse.distance_mm[0] >= reach.distance_mm[0]


def test_settings_are_checked():
    with pytest.raises(ValueError, match="grid_points"):
        ReachSettings(grid_points=1).check()
    with pytest.raises(ValueError, match="tolerance_mm"):
        ReachSettings(tolerance_mm=0.0).check()


def test_split_misses_by_hand():
    episodes = pd.DataFrame({
        "plant": ["twin"] * 6, "controller": ["ppo_ff"] * 6, "seed": [0, 0, 0, 1, 1, 1],
        "episode": [0, 1, 2, 0, 1, 2], "final_distance_mm": [0.5, 2.0, 4.0, 1.5, 0.8, 3.0]})
    reach = pd.DataFrame({"plant": ["twin"] * 3, "episode": [0, 1, 2],
                          "reach_mm": [0.1, 0.4, 2.5], "reachable": [True, True, False]})
    row = split_misses(episodes, reach).iloc[0]
    assert row["episodes"] == 6
    assert row["reachable_goals"] == pytest.approx(4 / 6)
    assert row["misses"] == pytest.approx(4 / 6)  # 2.0, 4.0, 1.5, 3.0
    assert row["misses_reachable"] == pytest.approx(2 / 4)  # 2.0 (episode 1), 1.5 (episode 0)
    assert row["median_final_reachable_mm"] == pytest.approx(np.median([0.5, 2.0, 1.5, 0.8]))
    assert row["success_reachable"] == pytest.approx(2 / 4)
    assert row["median_excess_unreachable_mm"] == pytest.approx(np.median([1.5, 0.5]))
    with pytest.raises(ValueError, match="no reach row"):
        split_misses(episodes.assign(plant="model"), reach)


def test_the_reach_runs_on_the_evaluations_own_plants_goals_and_starts():
    env = SoftArmReachEnv(PLANT, control_hz=2.0, settle_seconds=1.0, incremental_actions=True)
    settings = EnvConfig(max_steps=4, reset_bank_size=3)
    plant = default_linear_lag_params()
    goal_set = jnp.array([[0.03, 0.35, 0.20], [0.04, 0.35, 0.19], [0.02, 0.36, 0.21]])
    params = make_env_params(env, plant, settings, key=jax.random.key(0), safe_set=SAFE,
                             preload=2.0, rest_pose=jnp.array([0.032, 0.353, 0.2015]),
                             rest_pose_std=0.002, goal_set=goal_set)
    other = plant.replace(gain=plant.gain * 0.8)
    closed = ClosedLoopSettings(
        evaluation=EvaluationConfig(num_episodes=5, baselines=["preload"],
                                    num_consecutive_goals=0),
        max_steps=4, model_hz=10.0, limits=SimpleNamespace(p_min=0.0, p_max=7.0, sum_max=13.0),
        env=settings)
    results = run_evaluation(closed, {}, env, params, models={"model other": other})
    plants, goals = evaluation_episodes(closed, env, params, models={"model other": other})
    np.testing.assert_allclose(goals, results["goals"])
    reach = evaluation_reach(plants, goals, ReachSettings(grid_points=5, refine_rounds=4))
    assert set(reach["plant"]) == {"learned", "model other"} and len(reach) == 10
    episodes = results["tables"]["episodes"]
    assert preload_mismatch_mm(reach, episodes) < 1e-3
    # the nearest hold is never further than holding the preload, which is admissible
    assert (reach["reach_mm"] <= reach["preload_mm"] + 1e-6).all()


def test_the_reach_is_found_on_the_twins_unless_asked_for_everywhere():
    from pipeline.evaluation.reachability import reach_plants

    names = ["learned", "plant", "twin sim_sorolex", "model abc"]
    assert reach_plants(names, None) == ["twin sim_sorolex"]
    assert reach_plants(names, True) == names
    assert reach_plants(names, False) == []
