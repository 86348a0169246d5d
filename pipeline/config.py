"""Structured config schemas.

Every YAML file under ``conf/`` extends one of these dataclasses (through its defaults list), so
Hydra type-checks every value and rejects unknown keys at composition: a typo such as
``exploration.alpah=0.5`` or ``stage=fitmodel`` fails before any work starts, with a message that
names the key and, for enums, the valid values.

Units: pressures in kPa, positions in metres, times in seconds, rates in Hz.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING


class Stage(str, Enum):
    collect = "collect"
    align = "align"
    fit_model = "fit_model"
    train_ppo = "train_ppo"
    evaluate = "evaluate"
    all = "all"


class RobotKind(str, Enum):
    sim = "sim"
    ros2 = "ros2"
    sorolex_csv = "sorolex_csv"
    plotjuggler_csv = "plotjuggler_csv"


class GapPolicy(str, Enum):
    error = "error"  # a mocap gap longer than max_gap_s aborts align, naming the run and time
    split = "split"  # the run is split at the gap into runs '<id>#0', '<id>#1', ... (counted)


# --------------------------------------------------------------------------------------------
# robot
# --------------------------------------------------------------------------------------------
@dataclass
class PressureLimits:
    """The safe set of pressure commands: ``p_min <= p_j <= p_max`` and ``sum_j p_j <= sum_max``.

    Every command leaving the process (exploration, policies, hardware) is projected onto it.
    """

    p_min: float = 0.0
    p_max: float = 7.0
    sum_max: float = 13.0
    preload: float = 2.0


@dataclass
class MocapConfig:
    """Motion-capture sampling and its imperfections (used by the simulated arm)."""

    rate_hz: float = 100.0
    noise_std_m: float = 5.0e-5
    jitter_std_s: float = 1.0e-3
    drop_prob: float = 0.005  # probability that a single frame is lost
    burst_prob: float = 0.0005  # probability that a burst of lost frames starts at a frame
    burst_len: int = 8  # frames lost in a burst


@dataclass
class SimPhysics:
    """Parameters of the simulated 3-chamber bellows arm (see ``pipeline/sim_arm.py``).

    Calibrated by hand to the magnitudes of the real arm in ``shared/data/sorolex``.
    """

    segment_length_m: float = 0.09
    tip_offset_m: float = 0.025  # rigid end piece between the bending segment and the markers
    base_position_m: list[float] = field(default_factory=lambda: [0.0320, 0.469, 0.2015])
    chamber_angles_deg: list[float] = field(default_factory=lambda: [90.0, 210.0, 330.0])
    pressure_tau_s: float = 0.10  # first-order lag of each chamber behind its valve command
    bend_gain: float = 0.065  # bending angle per kPa of chamber pressure [rad/kPa]
    elong_gain: float = 0.0005  # elongation per kPa of mean pressure [m/kPa]
    natural_freq_hz: float = 1.5
    damping_ratio: float = 0.3
    gravity_stiffening: float = 0.15  # gravity's restoring torque relative to the elastic one
    hysteresis_kpa: float = 0.2  # half-width of the play (backlash) operator per chamber
    creep_gain: float = 0.1  # fraction of the pressure that acts through the slow creep lag
    creep_tau_s: float = 5.0
    rest_pose_std_m: list[float] = field(default_factory=lambda: [0.002, 0.0003, 0.001])
    substeps: int = 10  # integrator steps per mocap frame


@dataclass
class RobotConfig:
    """Base schema of every robot. ``kind`` selects how ``collect`` obtains raw streams."""

    name: str = MISSING
    kind: RobotKind = MISSING
    n_valves: int = 3
    control_hz: float = 2.0
    limits: PressureLimits = field(default_factory=PressureLimits)


@dataclass
class SimRobotConfig(RobotConfig):
    name: str = "sim"
    kind: RobotKind = RobotKind.sim
    num_runs: int = 4  # exploration runs recorded, each a new session (new rest pose)
    physics: SimPhysics = field(default_factory=SimPhysics)
    mocap: MocapConfig = field(default_factory=MocapConfig)


@dataclass
class ImportRobotConfig(RobotConfig):
    """Recorded real data: ``collect`` imports the files into the raw schemas."""

    data_dir: str = MISSING
    pattern: str = "*.csv"
    files: list[str] = field(default_factory=list)  # explicit names inside data_dir; empty = glob


@dataclass
class Ros2RobotConfig(RobotConfig):
    name: str = "ros2"
    kind: RobotKind = RobotKind.ros2
    command_topic: str = "/control_pressure"
    command_type: str = "std_msgs/msg/Float64MultiArray"
    pose_topic: str = "/mocap_rigid_bodies/rigid_bodies_1/pose"
    pose_type: str = "geometry_msgs/msg/PoseStamped"
    position_field: str = "pose.position"
    qos_depth: int = 10
    watchdog_s: float = 0.5  # no pose for this long: fault, preload, exit
    num_runs: int = 1


# --------------------------------------------------------------------------------------------
# exploration, dataset
# --------------------------------------------------------------------------------------------
@dataclass
class ExplorationConfig:
    """Mean-reverting random walk in pressure space (paper section II-A, equation 1)."""

    seed: int = 0  # draws of the walk and of the simulated sessions (not the training seed)
    alpha: float = 0.5  # memory of the walk: 1 keeps the last pressure, 0 draws afresh
    beta: float = 0.15  # steepness of the sigmoid on the summed pressure
    p_max: float = 13.0  # the paper's P_max: ceiling of the summed pressure [kPa]
    noise_std: float = 1.5  # std of the normal draw around the preload [kPa] (paper: 1)
    num_steps: int = 600  # exploration steps per run (at robot.control_hz)
    pad_steps: int = 4  # preload steps recorded before and after the walk
    figure_alphas: list[float] = field(default_factory=lambda: [0.0, 0.5, 0.8, 0.95])


@dataclass
class AlignConfig:
    max_match_dt_s: float = 0.05  # a command farther than this from every mocap frame is unmatched
    max_gap_s: float = 0.25  # longest mocap gap tolerated inside a run
    gap_policy: GapPolicy = GapPolicy.error
    resample_hz: float | None = None  # None keeps the mocap rows
    accept_incomplete: bool = False  # runs marked incomplete by collect (interrupted)


@dataclass
class DatasetConfig:
    align: AlignConfig = field(default_factory=AlignConfig)
    model_hz: float = 10.0  # rate the dynamics model runs at (downsampled aligned data)
    window: int = 128  # sliding-window length in model steps
    stride: int = 1
    order: str = "permuted"  # permuted | sequential
    train_fraction: float = 0.75
    split_seed: int = 0


# --------------------------------------------------------------------------------------------
# later stages: model, env, agent
# --------------------------------------------------------------------------------------------
@dataclass
class ModelConfig:
    name: str = "lstm"
    seed: int = 0
    hidden: int = 128
    layers: int = 1
    head: list[int] = field(default_factory=list)
    condition_on_initial_pose: bool = True
    batch_size: int = 32
    learning_rate: float = 1.0e-3
    num_steps: int = 3000
    eval_every: int = 100
    checkpoint_every: int = 500


@dataclass
class EnvConfig:
    name: str = "learned"
    max_steps: int = 40
    goal_tolerance_m: float = 0.001
    goal_mode: str = "data"  # data | perturb
    goal_perturbation_m: float = 0.01
    obs_noise_std: float = 0.0
    action_noise_std: float = 0.0
    include_last_action: bool = False
    gymnax_name: str = "Pendulum-v1"


@dataclass
class AgentConfig:
    name: str = "ppo_ff"
    recurrent: bool = False
    num_seeds: int = 4
    num_envs: int = 64
    num_steps: int = 32
    total_timesteps: int = 500_000
    update_epochs: int = 4
    num_minibatches: int = 4
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    lr: float = 3.0e-4
    anneal_lr: bool = True
    hidden: int = 64


@dataclass
class LoggerConfig:
    wandb: bool = False
    project: str = "sorolearn"
    mode: str = "offline"  # offline unless the user configures otherwise


@dataclass
class PathsConfig:
    root_dir: str = "${oc.env:SOROLEARN_ROOT,.}"
    data_dir: str = "${oc.env:SOROLEX_DIR,${paths.root_dir}/../shared/data/sorolex}"
    output_dir: str = "${paths.root_dir}/outputs"
    artifact_dir: str = "${paths.output_dir}/artifacts"


@dataclass
class Config:
    stage: Stage = Stage.all
    seed: int = 0
    force: bool = False  # recompute artifacts even when one with the same key exists
    robot: Any = MISSING  # one of the RobotConfig subclasses, chosen by the robot group
    exploration: ExplorationConfig = MISSING
    dataset: DatasetConfig = MISSING
    model: ModelConfig = MISSING
    env: EnvConfig = MISSING
    agent: AgentConfig = MISSING
    logger: LoggerConfig = MISSING
    paths: PathsConfig = MISSING


def register_configs() -> None:
    """Register the schemas; each YAML names its schema first in its defaults list."""
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(group="robot", name="base_sim", node=SimRobotConfig)
    cs.store(group="robot", name="base_import", node=ImportRobotConfig)
    cs.store(group="robot", name="base_ros2", node=Ros2RobotConfig)
    cs.store(group="exploration", name="base_exploration", node=ExplorationConfig)
    cs.store(group="dataset", name="base_dataset", node=DatasetConfig)
    cs.store(group="model", name="base_model", node=ModelConfig)
    cs.store(group="env", name="base_env", node=EnvConfig)
    cs.store(group="agent", name="base_agent", node=AgentConfig)
    cs.store(group="logger", name="base_logger", node=LoggerConfig)
    cs.store(group="paths", name="base_paths", node=PathsConfig)
