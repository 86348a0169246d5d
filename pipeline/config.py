"""Structured config schemas.

Every YAML file under ``conf/`` extends one of these dataclasses (through its defaults list), so
Hydra type-checks every value and rejects unknown keys at composition: a typo such as
``exploration.alpah=0.5`` or ``stage=fitmodel`` fails before any work starts, with a message that
names the key and, for enums, the valid values.

Units: pressures in kPa, positions in metres, times in seconds, rates in Hz.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, OmegaConf


class Stage(str, Enum):
    collect = "collect"
    align = "align"
    fit_model = "fit_model"
    train_ppo = "train_ppo"
    evaluate = "evaluate"
    twin = "twin"  # the simulated arm as a ROS 2 node (not part of `all`)
    calibrate = "calibrate"  # fit the simulated arm to recorded runs (not part of `all`)
    all = "all"


class RobotKind(str, Enum):
    sim = "sim"
    ros2 = "ros2"
    sorolex_csv = "sorolex_csv"
    plotjuggler_csv = "plotjuggler_csv"
    rosbag = "rosbag"


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
    chamber_gains: list[float] = field(default_factory=lambda: [1.0, 1.0, 1.0])  # relative
    # each chamber's strain saturates: f(p) = c + tanh(a (p - c)) / a (a in 1/kPa; 0: linear)
    saturation_per_kpa: float = 0.0
    saturation_center_kpa: float = 2.0  # c [kPa]; also the reference of mean_stiffening
    # bending gain times exp(-s (mean pressure - c)): the arm stiffens as its mean pressure rises
    mean_stiffening_per_kpa: float = 0.0
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
    # runs start from a settled rest pose, so the first observed pose is the rest pose and the
    # model predicts the displacement from it (model.predict_displacement follows this). False
    # for the paper's recordings: their first second still settles by about 1 mm.
    settled_start: bool = False


@dataclass
class SimRobotConfig(RobotConfig):
    name: str = "sim"
    kind: RobotKind = RobotKind.sim
    num_runs: int = 4  # exploration runs recorded, each a new session (new rest pose)
    physics: SimPhysics = field(default_factory=SimPhysics)
    mocap: MocapConfig = field(default_factory=MocapConfig)
    # a calibrate artifact (key or folder) whose fitted physics replace `physics`
    physics_from: str | None = None


@dataclass
class ImportRobotConfig(RobotConfig):
    """Recorded real data: ``collect`` imports the files into the raw schemas."""

    data_dir: str = MISSING
    pattern: str = "*.csv"
    files: list[str] = field(default_factory=list)  # explicit names inside data_dir; empty = glob


class QosReliability(str, Enum):
    reliable = "reliable"
    best_effort = "best_effort"


class QosDurability(str, Enum):
    volatile = "volatile"
    transient_local = "transient_local"


@dataclass
class QosConfig:
    """ROS 2 quality of service of one topic (history: keep last ``depth`` messages)."""

    reliability: QosReliability = QosReliability.reliable
    durability: QosDurability = QosDurability.volatile
    depth: int = 10


@dataclass
class RosTopicsConfig:
    """Where the pressure commands and the motion-capture poses travel (ROS 2 and rosbags).

    Field paths are dotted attribute paths into the message: ``command_field`` holds the
    ``n_valves`` pressures [kPa], ``position_field`` an object with x, y, z [m], ``stamp_field``
    a ``builtin_interfaces/Time``; an empty ``stamp_field`` uses the time of receipt (collect) or
    of recording (rosbag) instead.
    """

    command_topic: str = "/control_pressure"
    command_type: str = "std_msgs/msg/Float64MultiArray"
    command_field: str = "data"
    pose_topic: str = "/mocap_rigid_bodies/rigid_bodies_1/pose"
    pose_type: str = "geometry_msgs/msg/PoseStamped"
    position_field: str = "pose.position"
    stamp_field: str = "header.stamp"


@dataclass
class TwinConfig:
    """The digital twin (``stage=twin``): the simulated arm answering on the ROS 2 topics."""

    seed: int = 0  # session draw (rest pose) and mocap noise
    frame_id: str = "sorolearn_twin"  # header.frame_id of its poses (collect records it)
    physics: SimPhysics = field(default_factory=SimPhysics)
    mocap: MocapConfig = field(default_factory=MocapConfig)
    record_path: str | None = None  # JSON lines: every command received, with receipt time
    max_duration_s: float | None = None  # wall seconds until it exits by itself; None: SIGINT


@dataclass
class Ros2RobotConfig(RobotConfig, RosTopicsConfig):
    """A real arm over ROS 2 (rclpy); durations in the arm's seconds unless marked wall.

    ``time_scale`` is arm seconds per wall second: 1 on a real arm; the digital twin and collect
    can both run faster (same value on both sides) so that a rehearsal or a test takes seconds.
    """

    name: str = "ros2"
    kind: RobotKind = RobotKind.ros2
    session: str = "default"  # label in the artifact key: a new label records anew
    node_name: str = "sorolearn_collect"
    domain_id: int | None = None  # None: ROS_DOMAIN_ID from the environment (default 0)
    time_scale: float = 1.0
    command_qos: QosConfig = field(default_factory=QosConfig)
    pose_qos: QosConfig = field(
        default_factory=lambda: QosConfig(QosReliability.best_effort, QosDurability.volatile, 100))
    watchdog_s: float = 0.5  # no pose for this long: fault, preload, exit
    startup_timeout_s: float = 10.0  # wall: wait this long for the first pose and a subscriber
    flush_every_s: float = 5.0  # wall: raw streams are written to Parquet chunks this often
    stop_timeout_s: float = 3.0  # wall: wait up to this for the preload's acknowledgement
    num_runs: int = 1
    reuse_incomplete: bool = False  # reuse an interrupted artifact instead of recollecting
    twin: TwinConfig = field(default_factory=TwinConfig)
    # a calibrate artifact (key or folder) whose fitted physics replace `twin.physics`
    physics_from: str | None = None


@dataclass
class RosbagRobotConfig(ImportRobotConfig, RosTopicsConfig):
    """ROS 2 bags (sqlite3 or MCAP folders) recorded from the ros2 topics, imported."""

    pattern: str = "*"  # matched in data_dir; only bag folders (with metadata.yaml) are read


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
    model_grid: str = "clock"  # clock: regular grid | commands: locked to the command times
    window: int = 128  # sliding-window length in model steps
    stride: int = 1
    order: str = "permuted"  # permuted | sequential
    train_fraction: float = 0.75
    split_seed: int = 0


@dataclass
class CalibrationConfig:
    """``stage=calibrate``: the simulated arm's physics fitted to the aligned runs by gradient
    descent through the simulator (see ``pipeline/calibration.py``)."""

    rate_hz: float = 20.0  # frames simulated and compared per second (a multiple of model_hz)
    substeps: int = 2  # integrator steps per frame
    num_steps: int = 250  # Adam steps (the real runs: the loss stops falling after ~200)
    learning_rate: float = 0.05  # in the unconstrained (logit) coordinates; offsets in mm
    num_restarts: int = 2  # starts per fit (the first at `init`), vmapped
    restart_std: float = 0.5  # logit-space spread of the other starts
    seed: int = 0
    leave_one_run_out: bool = True  # also fit every fold (score the held-out runs)
    fitted: list[str] = field(default_factory=lambda: [
        "chamber_angles_deg", "chamber_gains", "segment_length_m", "tip_offset_m",
        "pressure_tau_s", "bend_gain", "elong_gain", "natural_freq_hz", "damping_ratio",
        "gravity_stiffening", "hysteresis_kpa", "creep_gain", "creep_tau_s",
        "saturation_per_kpa", "saturation_center_kpa", "mean_stiffening_per_kpa"])
    init: SimPhysics = field(default_factory=SimPhysics)  # start; holds the unfitted values


# --------------------------------------------------------------------------------------------
# later stages: model, env, agent
# --------------------------------------------------------------------------------------------
@dataclass
class ModelConfig:
    """The LSTM forward-dynamics model and its training (see ``pipeline/train_model.py``)."""

    name: str = "lstm"
    hidden: int = 64
    layers: int = 1
    head: list[int] = field(default_factory=list)
    condition_on_initial_pose: bool = False  # initial carry from the observed pose at reset
    # predict the displacement from the run's initial pose (default: robot.settled_start; sim
    # held-out 1.03 mm vs 1.96 mm absolute; real runs leave-one-out 4.04 mm vs 3.09 mm)
    predict_displacement: bool = False
    batch_size: int = 32
    learning_rate: float = 3.0e-3
    lr_schedule: str = "cosine"  # constant | cosine
    warmup_steps: int = 100
    final_lr_fraction: float = 0.05
    max_grad_norm: float = 1.0
    num_steps: int = 1500
    eval_every: int = 250
    checkpoint_every: int = 500
    seed: int = 0
    reference_pose: str = "run_start"  # run_start | window_start


@dataclass
class EnvConfig:
    """The reaching environment (``pipeline/envs``). Reward: -distance in mm per control period.

    ``name``: learned (the fitted LSTM) | sim (the simulated arm itself) | gymnax (a standard
    gymnax environment, ``gymnax_name``, to check the PPO against published returns).
    """

    name: str = "learned"
    max_steps: int = 40  # control periods per episode (truncation)
    goal_tolerance_m: float = 0.001  # terminate within this distance of the goal
    goal_mode: str = "data"  # data (uniform over positions seen) | perturb (paper: N(0,1)*pert.)
    goal_perturbation_m: float = 0.01
    obs_noise_std: float = 0.0  # m, on the observed position
    action_noise_std: float = 0.0  # kPa, on the commanded pressures (before projection)
    include_last_action: bool = False
    include_error: bool = False  # also observe (goal - position) / error_scale_m
    error_scale_m: float = 0.005
    gymnax_name: str = "Pendulum-v1"
    scale_observations: bool = False  # gymnax: observations divided by the space's bounds
    settle_seconds: float = 5.0  # preload held before an episode starts
    reset_bank_size: int = 64  # settled start states computed once per EnvParams
    env_seed: int = 0  # draws of the reset bank and (env=sim) of the goal sets
    num_goals: int = 2048  # env=sim: goals drawn from the simulated arm's reachable set
    held_out_fraction: float = 0.25  # env=sim: share of the goals kept for evaluation
    goal_every: int = 1  # env=learned: use every n-th row (at model_hz) as a goal
    goal_source: str = "predicted"  # env=learned: predicted (model along the runs) | measured


@dataclass
class AgentConfig:
    """PPO (``pipeline/ppo.py``); ``recurrent`` selects the GRU actor-critic."""

    name: str = "ppo_ff"
    recurrent: bool = False
    num_seeds: int = 4  # seeds trained at once (vmap); seed i uses fold_in(PRNGKey(seed), i)
    num_envs: int = 64
    num_steps: int = 32  # rollout length per update
    total_timesteps: int = 1_200_000  # per seed (env=sim: held-out median <= 1 mm at ~0.5M)
    update_epochs: int = 4
    num_minibatches: int = 4
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2
    clip_value: bool = True  # PPO value clipping (same clip_eps)
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    lr: float = 3.0e-4
    anneal_lr: bool = True
    hidden: int = 64  # width of the MLP layers
    num_layers: int = 2  # MLP layers of the actor and of the critic (after the GRU if any)
    rnn_hidden: int = 64  # GRU width (recurrent only)
    rnn_skip: bool = False  # heads read the current embedding beside the GRU output
    activation: str = "tanh"  # tanh | relu
    # initial log std of the Gaussian policy ([-1, 1] units): -2 (std 0.14); on the arm, -1
    # ended 0.2 mm less precise (experiments/PPO_RESULTS.md)
    log_std_init: float = -2.0
    state_dependent_std: bool = False  # the actor outputs the log std (else one learned vector)
    reward_scale: float = 0.1  # rewards are multiplied by this for the update only
    num_evals: int = 10  # deterministic evaluations on held-out goals during training
    eval_envs: int = 256  # episodes per evaluation (0: none)
    progress: bool = True  # a progress bar on the host (jax.debug.callback, throttled)
    # warm start: a train_ppo policy.msgpack of the same network; seed i starts from its seed i,
    # or every seed from init_policy_seed; its log std, or init_policy_log_std where given
    init_policy: str | None = None
    init_policy_seed: int | None = None
    init_policy_log_std: float | None = None


@dataclass
class EvaluationConfig:
    """The evaluate stage: which policies, how many episodes, which baselines."""

    policies: list[str] = field(default_factory=lambda: ["ppo_ff", "ppo_rnn"])  # agent configs
    baselines: list[str] = field(default_factory=lambda: ["preload", "random", "mpc"])
    num_episodes: int = 64  # held-out goals, the same for every seed, controller and plant
    num_consecutive_goals: int = 5  # goals reached one after another without reset
    consecutive_episodes: int = 8
    plant: bool = True  # also run on the ground-truth plant (the simulated arm for robot=sim)
    mpc_horizon: int = 2  # control periods a candidate command is held
    mpc_samples: int = 64
    mpc_iterations: int = 3
    seed: int = 0


@dataclass
class LoggerConfig:
    wandb: bool = False
    project: str = "sorolearn"
    mode: str = "offline"  # offline unless the user configures otherwise


@dataclass
class PathsConfig:
    root_dir: str = "${oc.env:SOROLEARN_ROOT,${project_root:}}"
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
    calibration: CalibrationConfig = MISSING
    model: ModelConfig = MISSING
    env: EnvConfig = MISSING
    agent: AgentConfig = MISSING
    evaluation: EvaluationConfig = MISSING
    logger: LoggerConfig = MISSING
    paths: PathsConfig = MISSING


def dataclass_values(cls: type, config: Any, what: str,
                     overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Field values for dataclass ``cls`` read from a dataclass, a mapping or an OmegaConf node
    (plus ``overrides``); unknown keys fail, naming ``what`` ("agent", "model")."""
    if dataclasses.is_dataclass(config):
        values = dataclasses.asdict(config)
    elif isinstance(config, Mapping) or hasattr(config, "items"):
        values = dict(config.items())
    else:
        raise TypeError(f"cannot read a{'n' if what[0] in 'aeiou' else ''} {what} config from "
                        f"{type(config).__name__}")
    values.update(overrides or {})
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"unknown {what} config keys {unknown}; known: {sorted(known)}")
    return values


PROJECT_ROOT = Path(__file__).resolve().parent.parent  # the checkout: conf/ lies here


def register_configs() -> None:
    """Register the schemas (each YAML names its schema first in its defaults list) and the
    ``${project_root:}`` resolver."""
    OmegaConf.register_new_resolver("project_root", lambda: str(PROJECT_ROOT), replace=True)
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(group="robot", name="base_sim", node=SimRobotConfig)
    cs.store(group="robot", name="base_import", node=ImportRobotConfig)
    cs.store(group="robot", name="base_ros2", node=Ros2RobotConfig)
    cs.store(group="robot", name="base_rosbag", node=RosbagRobotConfig)
    cs.store(group="exploration", name="base_exploration", node=ExplorationConfig)
    cs.store(group="dataset", name="base_dataset", node=DatasetConfig)
    cs.store(group="calibration", name="base_calibration", node=CalibrationConfig)
    cs.store(group="model", name="base_model", node=ModelConfig)
    cs.store(group="env", name="base_env", node=EnvConfig)
    cs.store(group="agent", name="base_agent", node=AgentConfig)
    cs.store(group="evaluation", name="base_evaluation", node=EvaluationConfig)
    cs.store(group="logger", name="base_logger", node=LoggerConfig)
    cs.store(group="paths", name="base_paths", node=PathsConfig)
