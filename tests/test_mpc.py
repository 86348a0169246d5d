"""The sampling-based MPC baseline reaches goals on a toy plant, also with a model mismatch."""

from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np

from pipeline.arm.safety import SafeSet
from pipeline.evaluation import mpc, rollouts
from pipeline.rl.envs.learned import make_env_params
from pipeline.rl.envs.plants import default_linear_lag_params, hold, linear_lag_plant
from pipeline.rl.envs.reach import SoftArmReachEnv
from pipeline.schemas import EnvConfig, GoalMode

SAFE = SafeSet.from_limits(SimpleNamespace(p_min=0.0, p_max=7.0, sum_max=13.0))
PLANT = linear_lag_plant(model_hz=10.0)
REST = jnp.array([0.032, 0.353, 0.2015])
ENV = SoftArmReachEnv(PLANT, control_hz=2.0, settle_seconds=2.0)


def reach(plant_params, model_params, goal, periods=8):
    env_params = make_env_params(ENV, plant_params,
                                 EnvConfig(goal_mode=GoalMode.perturb, reset_bank_size=2),
                                 key=jax.random.key(0), safe_set=SAFE, preload=2.0, rest_pose=REST)
    start_carry = jax.tree.map(lambda x: x[0], env_params.reset_carries)
    start = env_params.reset_positions[0]
    model_carry, model_start = ENV.settle(model_params, REST, env_params.preload)
    controller = mpc.mpc_controller(ENV, env_params, PLANT, model_params)
    carry = mpc.initial_carry(model_carry, model_start, env_params.preload)
    run = jax.jit(lambda: rollouts.rollout(ENV, env_params, controller, carry, jax.random.key(1),
                                           start_carry, start, jnp.broadcast_to(goal, (periods, 3))))
    return run()


def reachable_goal(params):
    carry = PLANT.init_carry(params, REST)
    _, path = hold(PLANT, params, carry, jnp.array([4.5, 1.0, 3.0]), 60)
    return path[-1]


def test_mpc_reaches_a_goal_when_the_model_is_the_plant():
    params = default_linear_lag_params()
    goal = reachable_goal(params)
    positions, commands = reach(params, params, goal)
    distance_mm = np.linalg.norm(np.asarray(positions - goal), axis=-1) * 1e3
    assert distance_mm[0] > 5.0 and distance_mm[-1] < 1.0
    p = np.asarray(commands)
    assert (p >= 0).all() and (p <= 7).all() and (p.sum(-1) <= 13).all()


def test_offset_correction_closes_the_gap_of_a_wrong_model():
    plant_params = default_linear_lag_params()
    model_params = plant_params.replace(gain=plant_params.gain * 0.8)  # the model is 20% off
    goal = reachable_goal(plant_params)
    positions, _ = reach(plant_params, model_params, goal, periods=14)
    distance_mm = np.linalg.norm(np.asarray(positions - goal), axis=-1) * 1e3
    assert distance_mm[0] > 5.0 and distance_mm[-1] < 1.0
