"""Environments: goal reaching with a soft arm on a learned model, the simulated arm or a toy."""

from pipeline.rl.envs.factory import (
    data_goals_and_rest_pose,
    make_gymnax_env,
    make_learned_env,
    make_sim_env,
    sim_plant_params,
    sim_reachable_positions,
    sim_rest_pose,
)
from pipeline.rl.envs.learned import (
    EnvParams,
    EnvState,
    SoftArmReachEnv,
    make_env_params,
    split_goals,
)
from pipeline.rl.envs.plants import (
    LinearLagParams,
    Plant,
    SimPlantParams,
    default_linear_lag_params,
    hold,
    learned_plant,
    linear_lag_plant,
    sim_plant,
)

__all__ = [
    "EnvParams",
    "EnvState",
    "LinearLagParams",
    "Plant",
    "SimPlantParams",
    "SoftArmReachEnv",
    "data_goals_and_rest_pose",
    "default_linear_lag_params",
    "hold",
    "learned_plant",
    "linear_lag_plant",
    "make_env_params",
    "make_gymnax_env",
    "make_learned_env",
    "make_sim_env",
    "sim_plant",
    "sim_plant_params",
    "sim_reachable_positions",
    "sim_rest_pose",
    "split_goals",
]
