"""Environments: goal reaching with a soft arm on a learned model, the simulated arm or a toy."""

from pipeline.rl.envs.factory import (
    data_goals_and_rest_pose,
    make_gymnax_env,
    make_learned_env,
    make_sim_env,
    sim_plant_params,
    sim_reachable_positions,
    sim_rest_pose,
    split_goals,
)
from pipeline.rl.envs.learned import make_env_params
from pipeline.rl.envs.params import (
    EnvParams,
    EnvState,
    Perturbation,
    Randomization,
    randomization,
)
from pipeline.rl.envs.plants import (
    EnsembleCarry,
    EnsembleParams,
    LinearLagParams,
    Plant,
    SimPlantParams,
    default_linear_lag_params,
    ensemble_plant,
    hold,
    learned_plant,
    linear_lag_plant,
    sim_plant,
    stack_members,
)
from pipeline.rl.envs.reach import SoftArmReachEnv

__all__ = [
    "EnsembleCarry",
    "EnsembleParams",
    "EnvParams",
    "EnvState",
    "LinearLagParams",
    "Perturbation",
    "Plant",
    "Randomization",
    "SimPlantParams",
    "SoftArmReachEnv",
    "data_goals_and_rest_pose",
    "default_linear_lag_params",
    "ensemble_plant",
    "hold",
    "learned_plant",
    "linear_lag_plant",
    "make_env_params",
    "make_gymnax_env",
    "make_learned_env",
    "make_sim_env",
    "randomization",
    "sim_plant",
    "sim_plant_params",
    "sim_reachable_positions",
    "sim_rest_pose",
    "split_goals",
    "stack_members",
]
