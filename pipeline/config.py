"""Structured config schemas.

Every YAML file under ``conf/`` extends one of these dataclasses (through its defaults list), so
Hydra type-checks every value and rejects unknown keys at composition: a typo such as
``exploration.alpah=0.5`` or ``stage=fitmodel`` fails before any work starts, with a message that
names the key and, for enums, the valid values.

The router then runs :func:`validate_config` before any work: values the types allow but a run
cannot use (NaN, a non-finite timeout, ``exploration.alpha`` outside [0, 1], limits outside the
arm's rating, a real arm's rating changed by an override) fail with a :class:`ConfigError` naming
the setting and its value.

Units: pressures in kPa, positions in metres, times in seconds, rates in Hz.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, OmegaConf


class Choice(str, Enum):
    """A closed set of options: compares equal to, prints and formats as its value."""

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)


class Stage(Choice):
    collect = "collect"
    align = "align"
    fit_model = "fit_model"
    train_ppo = "train_ppo"
    evaluate = "evaluate"
    twin = "twin"  # the simulated arm as a ROS 2 node (not part of `all`)
    guard = "guard"  # the arm-side deadman and rating filter as a ROS 2 node (not part of `all`)
    control = "control"  # a trained policy drives the arm (not part of `all`)
    calibrate = "calibrate"  # fit the simulated arm to recorded runs (not part of `all`)
    all = "all"


class RobotKind(Choice):
    sim = "sim"
    ros2 = "ros2"
    sorolex_csv = "sorolex_csv"
    plotjuggler_csv = "plotjuggler_csv"
    rosbag = "rosbag"


class ModelProtocol(Choice):
    """How fit_model selects and scores the model (``dataset.protocol``)."""

    auto = "auto"  # cv for recorded data (every robot but sim), split for the simulated arm
    cv = "cv"  # leave-one-run-out cross-validation, then the model is trained on all runs
    split = "split"  # one seeded split of the runs (train_fraction, split_seed)


class GapPolicy(Choice):
    error = "error"  # a mocap gap longer than max_gap_s aborts align, naming the run and time
    split = "split"  # the run is split at the gap into runs '<id>#0', '<id>#1', ... (counted)


class EnvName(Choice):
    learned = "learned"  # the fitted model of the fit_model artifact
    sim = "sim"  # the simulated arm itself
    gymnax = "gymnax"  # a standard gymnax environment (env.gymnax_name), to check the PPO


class GoalSource(Choice):
    predicted = "predicted"  # the model's open-loop predictions along the runs: reachable in it
    measured = "measured"  # the runs' recorded positions


class ActionMode(Choice):
    absolute = "absolute"  # the action sets each valve's pressure on its range
    incremental = "incremental"  # the action changes each valve's last command


class GoalMode(Choice):
    data = "data"  # uniform over the positions seen in the data
    perturb = "perturb"  # the paper's: the initial pose plus N(0, 1) * goal_perturbation_m


class ModelGrid(Choice):
    clock = "clock"  # a regular grid at model_hz
    commands = "commands"  # locked to the command times


class WindowOrder(Choice):
    permuted = "permuted"  # windows drawn at random (a fresh permutation per epoch)
    sequential = "sequential"  # windows in time order


class LrSchedule(Choice):
    constant = "constant"
    cosine = "cosine"  # linear warmup, cosine decay to the end


class ReferencePose(Choice):
    run_start = "run_start"  # the pose the window's run started from (as an env sees at reset)
    window_start = "window_start"  # the window's own first pose


class Cell(Choice):
    lstm = "lstm"
    gru = "gru"


class ModelLoss(Choice):
    """What the dynamics model's training minimizes over its open-loop windows."""

    mse = "mse"  # mean squared error of the standardized position, per axis
    distance = "distance"  # mean Euclidean distance to the measured position (the score)


class Activation(Choice):
    tanh = "tanh"
    relu = "relu"


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
class PressureRating:
    """The arm's physical limits (its rating), fixed by its hardware, not by a run.

    ``robot.limits`` (what a run uses) must lie inside it; the hardware gate checks every command
    against both. For a real arm (``robot=ros2``) it is read from the robot's YAML file: a
    command-line, sweep or experiment override of ``robot.rating`` is refused.
    """

    p_min: float = 0.0  # lowest pressure a valve may be commanded [kPa]
    p_max: float = 7.0  # highest pressure of one valve [kPa]
    sum_max: float = 13.0  # the paper's P_max: highest summed pressure of all valves [kPa]
    preload: float = 2.0  # pressure of every valve at rest, where a deadman returns it [kPa]
    n_valves: int = 3  # valves of the arm: a real arm's robot.n_valves must equal it


@dataclass
class WorkspaceConfig:
    """Box the marker positions [m] must lie in (a plausibility check of recorded data)."""

    low_m: list[float] = field(default_factory=lambda: [-3.0, -3.0, -3.0])
    high_m: list[float] = field(default_factory=lambda: [3.0, 3.0, 3.0])


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
    """Parameters of the simulated 3-chamber bellows arm (see ``pipeline/arm/sim_arm.py``).

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
    # session-to-session spread of the physics: each session (a simulated run) adds its own
    # N(0, std^2) draw to every parameter named here, per element of a list, in that
    # parameter's own unit (deg, kPa, s, Hz, rad/kPa, 1, ...). Empty: every session has the
    # same physics. Read off per-run refits of the real runs (experiments/twin_variability.py).
    session_std: dict[str, Any] = field(default_factory=dict)


@dataclass
class RobotConfig:
    """Base schema of every robot. ``kind`` selects how ``collect`` obtains raw streams."""

    name: str = MISSING
    kind: RobotKind = MISSING
    n_valves: int = 3
    control_hz: float = 2.0
    limits: PressureLimits = field(default_factory=PressureLimits)
    rating: PressureRating = field(default_factory=PressureRating)
    workspace: WorkspaceConfig = field(default_factory=WorkspaceConfig)
    # runs start from a settled rest pose, so the first observed pose is the rest pose and the
    # model predicts the displacement from it (model.predict_displacement follows this). False
    # for the paper's recordings, which settle in their first second (docs/results/MODEL_RESULTS.md).
    settled_start: bool = False


@dataclass
class ReplayConfig:
    """Recordings of an import kind (as ``ImportRobotConfig`` reads them) whose commands a
    simulated arm replays; their positions are not used."""

    kind: RobotKind = RobotKind.sorolex_csv
    data_dir: str = MISSING
    pattern: str = "*.csv"
    files: list[str] = field(default_factory=list)  # explicit names inside data_dir; empty = glob
    num_runs: int | None = None  # only the first num_runs recordings (None: all)


@dataclass
class SimRobotConfig(RobotConfig):
    name: str = "sim"
    kind: RobotKind = RobotKind.sim
    num_runs: int = 4  # exploration runs recorded, each a new session (new rest pose)
    physics: SimPhysics = field(default_factory=SimPhysics)
    mocap: MocapConfig = field(default_factory=MocapConfig)
    # a calibrate artifact (key or folder) whose fitted physics replace `physics`
    physics_from: str | None = None
    # recorded runs whose valve commands the sessions replay at their recorded times, one
    # session per recording, instead of the exploration walk (null: the walk, num_runs runs)
    replay: ReplayConfig | None = None


@dataclass
class ImportRobotConfig(RobotConfig):
    """Recorded real data: ``collect`` imports the files into the raw schemas."""

    data_dir: str = MISSING
    pattern: str = "*.csv"
    files: list[str] = field(default_factory=list)  # explicit names inside data_dir; empty = glob
    num_runs: int | None = None  # read only the first num_runs recordings (None: all)


class QosReliability(Choice):
    reliable = "reliable"
    best_effort = "best_effort"


class QosDurability(Choice):
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
    # wall: its poses' header stamps shifted by this, a motion capture clock ahead of (> 0) or
    # behind (< 0) the stages' clock, to rehearse the clock checks
    clock_offset_s: float = 0.0


@dataclass
class GuardConfig:
    """The guard (``stage=guard``): an arm-side node between collect and the valve driver.

    It forwards each command from ``robot.command_topic`` to ``output_topic`` (which the valve
    driver subscribes to instead) if it lies inside ``robot.rating``, and publishes the rating's
    preload instead of a command outside it and, at ``robot.control_hz``, whenever no command
    arrived within ``robot.command_timeout_s``.
    """

    output_topic: str = "/control_pressure/guarded"
    # std_msgs/String (JSON, latched): who answers for the arm (guard or twin) and the rating it
    # enforces; a real-arm stage publishes only after this answer matches its config
    handshake_topic: str = "/sorolearn/arm_handshake"
    node_name: str = "sorolearn_guard"
    max_duration_s: float | None = None  # wall seconds until it exits by itself; None: SIGINT


@dataclass
class SafetyBounds:
    """Upper bounds of a real arm's safety settings, pinned like its rating.

    Read from the robot's YAML file (``robot.safety_bounds``): an override of them is refused,
    and ``robot.watchdog_s``, ``robot.command_timeout_s``, ``robot.max_missed_periods`` and
    ``robot.max_pose_latency_s`` may only be set at or below them. In a rehearsal
    (``robot.rehearsal=true``, the twin running faster than real time) the durations are
    compared in wall seconds (value / ``robot.time_scale``).
    """

    watchdog_s: float = 1.0  # longest mocap silence before the preload [s]
    command_timeout_s: float = 2.0  # longest deadman timeout of the guard and the twin [s]
    max_missed_periods: int = 3  # most control periods a loop may be late in a row
    max_pose_latency_s: float = 0.5  # wall: largest pose latency (receipt - header stamp)


@dataclass
class Ros2RobotConfig(RobotConfig, RosTopicsConfig):
    """A real arm over ROS 2 (rclpy); durations in the arm's seconds unless marked wall.

    ``time_scale`` is arm seconds per wall second: 1 on a real arm; in a rehearsal
    (``rehearsal=true``, on the twin's own domain) the digital twin and the stage can both run
    faster (same value on both sides) so that a rehearsal or a test takes seconds. The rating and
    ``safety_bounds`` are pinned by the robot's YAML file (docs/safety.md).
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
    # arm side (twin, guard): no command for this long: back to the preload (a few periods)
    command_timeout_s: float = 1.5
    startup_timeout_s: float = 10.0  # wall: wait this long for the first pose and a subscriber
    flush_every_s: float = 5.0  # wall: raw streams are written to Parquet chunks this often
    stop_timeout_s: float = 3.0  # wall: wait up to this for the preload's acknowledgement
    # a loop (collect, control) more than one period late holds the last command; late more
    # than this many periods in a row: the preload and a clear error
    max_missed_periods: int = 2
    # wall: a pose whose latency (receipt - header stamp) is negative beyond the clocks'
    # tolerance or above this (at best, over the recent frames) means unsynchronised clocks
    max_pose_latency_s: float = 0.25
    safety_bounds: SafetyBounds = field(default_factory=SafetyBounds)
    # talk to the digital twin: it runs on rehearsal_domain_id (never the arm's domain), the
    # stages follow it there only with rehearsal=true, and its handshake must say it is a twin;
    # only then may time_scale differ from 1
    rehearsal: bool = False
    rehearsal_domain_id: int = 42
    num_runs: int = 1
    reuse_incomplete: bool = False  # reuse an interrupted artifact instead of recollecting
    twin: TwinConfig = field(default_factory=TwinConfig)
    guard: GuardConfig = field(default_factory=GuardConfig)
    # a calibrate artifact (key or folder) whose fitted physics replace `twin.physics`
    physics_from: str | None = None


@dataclass
class RosbagRobotConfig(ImportRobotConfig, RosTopicsConfig):
    """ROS 2 bags (sqlite3 or MCAP folders) recorded from the ros2 topics, imported."""

    pattern: str = "*"  # matched in data_dir; only bag folders (with metadata.yaml) are read
    # largest offset of the poses' log times from their header stamps [s]: beyond it (or
    # stamps after their log times) the clocks disagree and the bag is refused
    max_clock_offset_s: float = 0.25


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
    model_grid: ModelGrid = ModelGrid.clock
    window: int = 128  # sliding-window length in model steps
    stride: int = 1
    order: WindowOrder = WindowOrder.permuted
    protocol: ModelProtocol = ModelProtocol.auto
    train_fraction: float = 0.75  # protocol split only
    split_seed: int = 0  # protocol split only


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
    """The recurrent forward-dynamics model (``cell``: GRU or LSTM) and its training (see
    ``pipeline/dynamics/training.py``)."""

    name: str = "recurrent"  # the model family (a recurrent network; which cell: ``cell``)
    hidden: int = 64
    layers: int = 1
    head: list[int] = field(default_factory=list)
    condition_on_initial_pose: bool = False  # initial carry from the observed pose at reset
    # predict the displacement from the run's initial pose (default: robot.settled_start; it
    # helps on settled starts and hurts on the real runs: docs/results/MODEL_RESULTS.md)
    predict_displacement: bool = False
    batch_size: int = 32
    learning_rate: float = 3.0e-3
    lr_schedule: LrSchedule = LrSchedule.cosine
    warmup_steps: int = 100
    final_lr_fraction: float = 0.05
    max_grad_norm: float = 1.0
    # 3000: leave-one-run-out on the real runs the GRU gains to about 3000 steps and not after
    # (2.71 mm at 3000, 2.67 at 6000, 2.79 at 1500; docs/results/MODEL_RESULTS.md)
    num_steps: int = 3000
    eval_every: int = 250
    checkpoint_every: int = 500
    seed: int = 0
    reference_pose: ReferencePose = ReferencePose.run_start
    # gru at 3000 steps with the default dropout: leave-one-run-out on the real runs 2.72 / 6.17
    # mm (mean / p95, 3 seeds) against 2.82 / 6.30 for the LSTM at 1500, at 4/5 of its CPU
    cell: Cell = Cell.gru
    # input features (pipeline/model_features.py); empty / false: off
    # default: the last command step and the time since it (leave-one-run-out on the real runs
    # 3.08 mm mean over 3 seeds against 3.20 without; docs/results/MODEL_RESULTS.md)
    pressure_delta: bool = False  # p_t - p_{t-1} per chamber
    step_size: bool = True  # the pressure change at the last command step, held
    # exp(-model steps since the last command step / tau), one input per tau
    step_decays: list[float] = field(default_factory=lambda: [1.0, 3.0, 10.0])
    play_widths_kpa: list[float] = field(default_factory=list)  # play operators per chamber
    step_threshold_kpa: float = 0.05  # a command step: some chamber changed by more
    # regularization (training only)
    input_noise_std: float = 0.0  # on the standardized inputs
    loss: ModelLoss = ModelLoss.mse
    # one mask on h per window; 0.3: leave-one-run-out on the real runs 2.83 / 6.28 mm (mean /
    # p95) against 3.09 / 7.40 without, better on every fold (docs/results/MODEL_RESULTS.md)
    recurrent_dropout: float = 0.3
    weight_decay: float = 0.0  # AdamW, decoupled


@dataclass
class RandomizationConfig:
    """Randomization around the plant, drawn per training episode (``env.randomization``).

    Training only: the evaluation parameters (held-out goals, the evaluate stage) are nominal.
    All zero (the default): none, the environment exactly as without randomization. Each draw is
    per valve or per axis (``pipeline.rl.envs.learned.Randomization``).
    """

    gain_std: float = 0.0  # each valve receives (1 + N(0, gain_std)) x the command [unitless]
    offset_std_kpa: float = 0.0  # ... plus N(0, offset_std_kpa), then projected on the safe set
    # the previous command is held for U{0 .. round(max_delay_s * dataset.model_hz)} plant steps
    # at the start of every control period; at most one period (1 / robot.control_hz) [s]
    max_delay_s: float = 0.0
    rest_offset_std_m: float = 0.0  # N(0, std) per axis added to the plant's position [m]
    drift_std_m_per_s: float = 0.0  # that offset grows by N(0, std) per axis and second [m/s]


@dataclass
class EnvConfig:
    """The reaching environment (``pipeline/envs``). Reward: -distance in mm per control period.

    ``name``: learned (the fitted recurrent model) | sim (the simulated arm itself) | gymnax (a
    standard gymnax environment, ``gymnax_name``, to check the PPO against published returns).

    Robustness to model error (training only; evaluation stays in this config's own model):
    ``ensemble_seeds`` and ``models`` train in an ensemble of fitted models, one drawn per episode
    (env=learned); ``randomization`` perturbs the plant per episode (learned and sim).
    """

    name: EnvName = EnvName.learned
    max_steps: int = 40  # control periods per episode (truncation)
    goal_tolerance_m: float = 0.001  # a control period ending within this distance is at the goal
    # terminate after this many consecutive control periods at the goal (1: the first arrival);
    # more trains the policy in the states after arrival, where evaluation and the arm keep it
    hold_periods: int = 1
    hold_bonus_mm: float = 0.0  # reward [mm] for every control period that ends at the goal
    goal_mode: GoalMode = GoalMode.data
    goal_perturbation_m: float = 0.01
    obs_noise_std: float = 0.0  # m, on the observed position
    action_noise_std: float = 0.0  # kPa, on the commanded pressures (before projection)
    include_last_action: bool = False
    include_error: bool = False  # also observe (goal - position) / error_scale_m
    error_scale_m: float = 0.005
    # also observe the accumulated error: I_t = decay I_(t-1) + (1 - decay) (goal - measured_t)
    # / error_scale_m after each control period (0 at the start; a leaky integral of the error)
    include_error_integral: bool = False
    error_integral_decay: float = 0.8  # per control period, in [0, 1)
    # incremental: each action changes the last command by up to action_step_kpa per control
    # period (integral action: the commands rest only where the policy outputs zero)
    action_mode: ActionMode = ActionMode.absolute
    action_step_kpa: float = 1.0
    # reward: -(distance mm + command_change_cost x summed |change of the command| kPa) [mm/kPa]
    command_change_cost: float = 0.0
    gymnax_name: str = "Pendulum-v1"
    scale_observations: bool = False  # gymnax: observations divided by the space's bounds
    settle_seconds: float = 5.0  # preload held before an episode starts
    reset_bank_size: int = 64  # settled start states computed once per EnvParams
    env_seed: int = 0  # draws of the reset bank and (env=sim) of the goal sets
    num_goals: int = 2048  # env=sim: goals drawn from the simulated arm's reachable set
    held_out_fraction: float = 0.25  # env=sim: share of the goals kept for evaluation
    goal_every: int = 1  # env=learned: use every n-th row (at model_hz) as a goal
    goal_source: GoalSource = GoalSource.predicted  # env=learned
    # env=learned: train in an ensemble of the fit_model artifacts of model.seed, model.seed + 1,
    # ..., model.seed + ensemble_seeds - 1 (same data and settings; produced upstream); 1: none
    ensemble_seeds: int = 1
    # env=learned: further ensemble members, fit_model artifact folders or keys of this store
    # (same model architecture); goals, rest pose and evaluation stay those of this config's model
    models: list[str] = field(default_factory=list)
    # env=learned, in an ensemble: conservative goals, train only on the goals where every
    # member's open-loop prediction along the recorded commands lies within this many mm of the
    # model's own (the members agree the commands get there); null: every goal
    goal_agreement_mm: float | None = None
    randomization: RandomizationConfig = field(default_factory=RandomizationConfig)


def no_randomization_overrides() -> list[str]:
    """Overrides that turn every ``env.randomization`` off (as ``experiment=real_arm`` sets it)."""
    return [f"env.randomization.{f.name}=0" for f in dataclasses.fields(RandomizationConfig)]


def budget_overrides(steps: int) -> list[str]:
    """Overrides that train every policy type for ``steps`` environment steps per seed (also the
    recurrent one, which an experiment may give a budget of its own)."""
    return [f"agent.total_timesteps={int(steps)}", "agent.recurrent_total_timesteps=null"]


def incremental_actions(env: Any) -> bool:
    """Whether the env config ``env`` acts incrementally (``env.action_mode``; absent, as in a
    config rebuilt from an artifact's spec where it is the default: absolute)."""
    mode = ActionMode(str(env.get("action_mode", EnvConfig.action_mode)))
    return mode is ActionMode.incremental


@dataclass
class AgentConfig:
    """PPO (``pipeline/rl/ppo.py``); ``recurrent`` selects the GRU actor-critic."""

    name: str = "ppo_ff"
    recurrent: bool = False
    num_seeds: int = 4  # seeds trained at once (vmap); seed i uses fold_in(PRNGKey(seed), i)
    num_envs: int = 64
    num_steps: int = 32  # rollout length per update
    total_timesteps: int = 1_200_000  # per seed (its results: docs/results/PPO_RESULTS.md)
    # the recurrent policy's budget per seed where it needs another (None: total_timesteps)
    recurrent_total_timesteps: int | None = None
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
    activation: Activation = Activation.tanh
    # initial log std of the Gaussian policy ([-1, 1] units): -2 (std 0.14); -1 explores too
    # much on the arm and ends less precise (see docs/results/PPO_RESULTS.md)
    log_std_init: float = -2.0
    state_dependent_std: bool = False  # the actor outputs the log std (else one learned vector)
    reward_scale: float = 0.1  # rewards are multiplied by this for the update only
    num_evals: int = 10  # deterministic evaluations on held-out goals during training
    eval_envs: int = 256  # episodes per evaluation (0: none)
    progress: bool = True  # a progress bar on the host, advanced after each evaluation chunk
    # warm start: a train_ppo policy.msgpack of the same network; seed i starts from its seed i,
    # or every seed from init_policy_seed; its log std, or init_policy_log_std where given
    init_policy: str | None = None
    init_policy_seed: int | None = None
    init_policy_log_std: float | None = None

    @classmethod
    def from_any(cls, config: Any, **overrides: Any) -> AgentConfig:
        """From a mapping, a dataclass or an OmegaConf node (plus ``overrides``); unknown keys
        fail, naming them."""
        return cls(**dataclass_values(cls, config, "agent", overrides))

    @property
    def steps_per_update(self) -> int:
        return self.num_steps * self.num_envs

    @property
    def timesteps(self) -> int:
        """This policy type's budget per seed: ``recurrent_total_timesteps`` for a recurrent
        policy where it is set, else ``total_timesteps``."""
        if self.recurrent and self.recurrent_total_timesteps is not None:
            return self.recurrent_total_timesteps
        return self.total_timesteps

    @property
    def updates_per_eval(self) -> int:
        return max(1, self.timesteps // self.steps_per_update // self.num_evals)

    @property
    def num_updates(self) -> int:
        """Updates actually run: a multiple of ``num_evals`` (:attr:`timesteps` rounded down)."""
        return self.updates_per_eval * self.num_evals

    def check(self) -> None:
        if self.recurrent and self.num_envs % self.num_minibatches:
            raise ValueError(f"recurrent PPO minibatches over environments: num_envs="
                             f"{self.num_envs} must be divisible by num_minibatches="
                             f"{self.num_minibatches}")
        if self.steps_per_update % self.num_minibatches:
            raise ValueError(f"num_envs * num_steps = {self.steps_per_update} must be divisible "
                             f"by num_minibatches={self.num_minibatches}")


@dataclass
class EvaluationConfig:
    """The evaluate stage: which policies, how many episodes, which baselines."""

    policies: list[str] = field(default_factory=lambda: ["ppo_ff", "ppo_rnn"])  # agent configs
    baselines: list[str] = field(default_factory=lambda: ["preload", "random", "mpc"])
    num_episodes: int = 64  # held-out goals, the same for every seed, controller and plant
    num_consecutive_goals: int = 5  # goals reached one after another without reset
    consecutive_episodes: int = 8
    plant: bool = True  # also run on the ground-truth plant (the simulated arm for robot=sim)
    # other fitted models to evaluate every controller in (cross-model): fit_model artifact
    # folders or keys of this artifact store; observed like the training env, same goals
    models: list[str] = field(default_factory=list)
    # calibrated twins to evaluate every controller on: the simulated arm with the physics of a
    # simulated robot config (by name, e.g. sim_sorolex: calibrated to the paper's runs) or of a
    # calibrate artifact (key or folder); observed like the training env, same goals, settled
    # at the preload from the same rest poses
    twins: list[str] = field(default_factory=list)
    # The cross-model protocol, for recorded data: the recordings split into two disjoint groups
    # (A: cross_model_group_a, by name; empty: every other of the sorted names; B: the rest),
    # each with its own fit_model; every policy type trained in each group's model (this
    # config's env and agent) and rolled out on its held-out goals in its own model and in the
    # other group's (A->B, B->A). null: on for recorded data of at least two runs a group.
    cross_model: bool | None = None
    cross_model_group_a: list[str] = field(default_factory=list)
    mpc_horizon: int = 2  # control periods a candidate command is held
    mpc_samples: int = 64
    mpc_iterations: int = 3
    seed: int = 0


@dataclass
class ControlConfig:
    """``stage=control``: a trained policy drives the arm (``pipeline/control``).

    Goals in mm in the mocap frame: ``goals`` (each held ``hold_s``), or ``goals_csv`` (waypoints
    ``t,x,y,z``, t in s from the start, each in force until the next; the last for ``hold_s``), or
    live on ``goal_topic`` (``geometry_msgs/msg/PointStamped`` in metres, robot=ros2 only).
    """

    policy: str = "ppo_ff"  # agent option (conf/agent/<policy>.yaml) of the train_ppo artifact
    policy_file: str | None = None  # a policy.msgpack inside a train_ppo artifact, instead
    seed: int | None = None  # seed of the stacked policy; None: best held-out median in training
    goals: list[Any] = field(default_factory=list)  # [[x, y, z], ...] mm (checked by control)
    goals_csv: str | None = None
    goal_topic: str | None = None
    duration_s: float | None = None  # live goals: stop after this long (None: until Ctrl-C)
    hold_s: float = 20.0  # arm seconds each goal is held (the last waypoint too)
    workspace_margin_mm: float = 2.0  # goals this far outside the training goals' box are allowed
    max_pose_jump_mm: float = 20.0  # between consecutive frames: preload and stop
    arm_seed: int = 0  # robot=sim: the simulated session (rest pose, mocap noise); as twin.seed
    flush_every_s: float = 2.0  # wall: rows written to Parquet chunks this often
    node_name: str = "sorolearn_control"


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
    # JAX's persistent compilation cache, shared by runs, sweep jobs and tests; null: off
    compile_cache_dir: str | None = "${oc.env:SOROLEARN_COMPILE_CACHE,${paths.output_dir}/jax_cache}"


@dataclass
class Config:
    stage: Stage = Stage.all
    seed: int = 0
    force: bool = False  # recompute artifacts even when one with the same key exists
    # print what the run would do (every job, its artifact key, reused or to run) and stop
    dry_run: bool = False
    # policy types the chain trains at once (threads; each training is one compiled program).
    # 1: each training already runs on every core (cpu_devices); 2 was not faster on 2 cores
    train_workers: int = 1
    # JAX's CPU devices (null: JAX_NUM_CPU_DEVICES where set, else one per core this process
    # may use; 1: JAX's own default). PPO's seeds and the evaluation's episodes are split over
    # them and the parts run in parallel (pipeline/infra/devices.py); a GPU machine splits
    # them over its GPUs where it has several
    cpu_devices: int | None = None
    robot: Any = MISSING  # one of the RobotConfig subclasses, chosen by the robot group
    exploration: ExplorationConfig = MISSING
    dataset: DatasetConfig = MISSING
    calibration: CalibrationConfig = MISSING
    model: ModelConfig = MISSING
    env: EnvConfig = MISSING
    agent: AgentConfig = MISSING
    evaluation: EvaluationConfig = MISSING
    control: ControlConfig = MISSING
    logger: LoggerConfig = MISSING
    paths: PathsConfig = MISSING


# --------------------------------------------------------------------------------------------
# validation at composition (the router runs it before any work)
# --------------------------------------------------------------------------------------------
class ConfigError(ValueError):
    """A composed config that cannot run: the message names the setting and its value."""


# robot settings that are durations and must be finite and positive [s]
_ROBOT_DURATIONS = ("watchdog_s", "command_timeout_s", "startup_timeout_s", "flush_every_s",
                    "stop_timeout_s", "time_scale", "control_hz")


def _walk_numbers(node: Any, path: str) -> Iterator[tuple[str, float]]:
    """Every float in ``node`` (an OmegaConf node, mapping or list) with its dotted path."""
    if OmegaConf.is_config(node):
        if OmegaConf.is_list(node):
            items = ((str(i), node[i]) for i in range(len(node)))
        else:
            items = ((str(k), node[k]) for k in node.keys()
                     if not OmegaConf.is_missing(node, k))
    elif isinstance(node, Mapping):
        items = ((str(k), v) for k, v in node.items())
    elif isinstance(node, list | tuple):
        items = ((str(i), v) for i, v in enumerate(node))
    else:
        if isinstance(node, float):
            yield path, node
        return
    for key, value in items:
        yield from _walk_numbers(value, f"{path}.{key}" if path else key)


def _check_inside_rating(robot: Any) -> None:
    limits, rating, n = robot.limits, robot.rating, int(robot.n_valves)
    if not float(rating.p_min) < float(rating.p_max):
        raise ConfigError(f"robot.rating: p_min={rating.p_min} must be below "
                          f"p_max={rating.p_max} kPa")
    if not float(limits.p_min) < float(limits.p_max):
        raise ConfigError(f"robot.limits: p_min={limits.p_min} must be below "
                          f"p_max={limits.p_max} kPa")
    if not n * float(limits.p_min) < float(limits.sum_max):
        raise ConfigError(f"robot.limits: sum_max={limits.sum_max} kPa must exceed {n} x "
                          f"p_min={limits.p_min} kPa")
    for name, inside in (("p_min", float(limits.p_min) >= float(rating.p_min)),
                         ("p_max", float(limits.p_max) <= float(rating.p_max)),
                         ("sum_max", float(limits.sum_max) <= float(rating.sum_max))):
        if not inside:
            raise ConfigError(
                f"robot.limits.{name}={limits[name]} kPa lies outside the arm's rating "
                f"robot.rating.{name}={rating[name]} kPa (the limits may only tighten the rating)")
    for what, values in (("robot.limits", limits), ("robot.rating", rating)):
        preload = float(values.preload)
        if not (float(values.p_min) <= preload <= float(values.p_max)
                and n * preload <= float(values.sum_max)):
            raise ConfigError(f"{what}.preload={preload} kPa is outside {what}: "
                              f"[{values.p_min}, {values.p_max}] per valve, sum <= "
                              f"{values.sum_max}")
    if not (float(rating.p_min) <= float(limits.preload) <= float(rating.p_max)
            and n * float(limits.preload) <= float(rating.sum_max)):
        raise ConfigError(f"robot.limits.preload={limits.preload} kPa lies outside the arm's "
                          f"rating robot.rating: [{rating.p_min}, {rating.p_max}] per valve, "
                          f"sum <= {rating.sum_max}")


def robot_file(choice: str, search_dirs: list[Path] | None = None) -> Path | None:
    """The YAML file of robot group option ``choice`` (``conf/robot/<choice>.yaml``)."""
    for folder in [*(search_dirs or []), PROJECT_ROOT / "conf"]:
        path = Path(folder) / "robot" / f"{choice}.yaml"
        if path.is_file():
            return path
    return None


def _section_from_file(path: Path, section: str, schema: type,
                       search_dirs: list[Path] | None = None) -> dict[str, Any]:
    """The values a robot's YAML file sets for ``section`` over ``schema``'s defaults, following
    the robot options its defaults list extends (``defaults: [ros2, _self_]``)."""
    text = OmegaConf.load(path)
    values = OmegaConf.structured(schema)
    for entry in text.get("defaults") or []:
        parent = robot_file(entry, search_dirs) if isinstance(entry, str) else None
        if parent is not None and parent != path:
            values = OmegaConf.merge(values, _section_from_file(parent, section, schema,
                                                                search_dirs))
    values = OmegaConf.merge(values, text.get(section) or {})
    return dict(OmegaConf.to_container(values))


def rating_from_file(path: Path, search_dirs: list[Path] | None = None) -> dict[str, float]:
    """The pressure rating [kPa] a robot's YAML file sets over the schema's defaults, following
    the robot options its defaults list extends (``defaults: [ros2, _self_]``)."""
    values = _section_from_file(path, "rating", PressureRating, search_dirs)
    return {k: float(v) for k, v in values.items() if k != "n_valves"}


# what a real arm's YAML file pins: an override of these is refused
_PINNED_SECTIONS = {"rating": PressureRating, "safety_bounds": SafetyBounds}


def check_rating_source(robot: Any, choice: str | None,
                        search_dirs: list[Path] | None = None) -> None:
    """A real arm's rating and safety bounds must be those its YAML file sets: an override
    cannot change them."""
    if RobotKind(robot.kind) is not RobotKind.ros2:
        return
    choice = choice or str(robot.name)
    path = robot_file(choice, search_dirs)
    if path is None:
        raise ConfigError(f"robot={choice}: no conf/robot/{choice}.yaml to read the arm's rating "
                          f"from; a real arm's rating comes from its robot config file")
    for section, schema in _PINNED_SECTIONS.items():
        expected = _section_from_file(path, section, schema, search_dirs)
        for name, value in expected.items():
            got = float(robot[section][name])
            if got != float(value) and not (math.isnan(got) and math.isnan(float(value))):
                unit = " kPa" if section == "rating" and name != "n_valves" else ""
                raise ConfigError(
                    f"robot.{section}.{name}={robot[section][name]}{unit} differs from {value}"
                    f"{unit} in {path}: the {section.replace('_', ' ')} of a real arm "
                    f"(robot=ros2) cannot be overridden; edit {path} to change it (an override "
                    f"may tighten robot.limits and the timeouts instead)")


def _check_real_arm(cfg: Any) -> None:
    """A real arm's settings against its pinned rating and safety bounds (``robot=ros2``)."""
    robot = cfg.robot
    if RobotKind(robot.kind) is not RobotKind.ros2:
        return
    rating, bounds = robot.rating, robot.safety_bounds
    rehearsal, scale = bool(robot.rehearsal), float(robot.time_scale)
    if int(robot.n_valves) != int(rating.n_valves):
        raise ConfigError(f"robot.n_valves={robot.n_valves} differs from the arm's rating "
                          f"robot.rating.n_valves={rating.n_valves}: the number of valves comes "
                          f"from the rating")
    if float(robot.limits.preload) != float(rating.preload):
        raise ConfigError(f"robot.limits.preload={robot.limits.preload} kPa differs from the "
                          f"arm's rating robot.rating.preload={rating.preload} kPa: a fault "
                          f"returns the arm to the rating's preload, so the limits must use it")
    if str(robot.command_topic) == str(robot.guard.output_topic):
        raise ConfigError(f"robot.command_topic={robot.command_topic} is the guard's output "
                          f"(robot.guard.output_topic): commands must go through the guard, not "
                          f"around it")
    stage = str(cfg.get("stage", ""))
    if scale != 1.0 and not rehearsal and stage != "twin":
        raise ConfigError(f"robot.time_scale={robot.time_scale}: a real arm runs in real time "
                          f"(time_scale=1); only a rehearsal on the digital twin "
                          f"(robot.rehearsal=true) may run faster")
    wall = scale if rehearsal or stage == "twin" else 1.0
    for name in ("watchdog_s", "command_timeout_s"):
        value, bound = float(robot[name]), float(bounds[name])
        if value / wall > bound:
            where = f" ({value / wall:g} wall s at robot.time_scale={scale:g})" if wall != 1 else ""
            raise ConfigError(f"robot.{name}={robot[name]} s{where} exceeds its bound "
                              f"robot.safety_bounds.{name}={bound} s, set in the arm's robot "
                              f"config file: a real arm's timeouts may only be shortened")
    if not 1 <= int(robot.max_missed_periods) <= int(bounds.max_missed_periods):
        raise ConfigError(f"robot.max_missed_periods={robot.max_missed_periods} must lie in "
                          f"[1, robot.safety_bounds.max_missed_periods="
                          f"{bounds.max_missed_periods}]")
    latency = float(robot.max_pose_latency_s)
    if not 0 < latency <= float(bounds.max_pose_latency_s):
        raise ConfigError(f"robot.max_pose_latency_s={robot.max_pose_latency_s} s must lie in "
                          f"(0, robot.safety_bounds.max_pose_latency_s="
                          f"{bounds.max_pose_latency_s}] s")


def validate_config(cfg: Any, robot_choice: str | None = None,
                    search_dirs: list[Path] | None = None) -> None:
    """Refuse a composed config that cannot run safely or sensibly, naming setting and value.

    NaN anywhere numeric; robot durations that are not finite and positive; limits outside the
    rating (or a real arm's rating differing from its YAML file); exploration settings outside
    their ranges. ``robot_choice`` is the robot group option (default: ``robot.name``).
    """
    for path, value in _walk_numbers(cfg, ""):
        if math.isnan(value):
            raise ConfigError(f"{path}=nan: a number is required")
    robot = cfg.robot
    for name in _ROBOT_DURATIONS:
        if name in robot:
            value = float(robot[name])
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"robot.{name}={robot[name]} must be finite and positive")
    if "command_timeout_s" in robot:
        period = 1.0 / float(robot.control_hz)
        if float(robot.command_timeout_s) <= period:
            raise ConfigError(
                f"robot.command_timeout_s={robot.command_timeout_s} s must exceed one control "
                f"period (1 / robot.control_hz = {period:g} s), or the arm falls back to the "
                f"preload between commands")
    check_rating_source(robot, robot_choice, search_dirs)
    _check_inside_rating(robot)
    _check_real_arm(cfg)
    low, high = list(robot.workspace.low_m), list(robot.workspace.high_m)
    if len(low) != 3 or len(high) != 3 or not all(a < b for a, b in zip(low, high)):
        raise ConfigError(f"robot.workspace: low_m={low} must lie below high_m={high} (x, y, z)")
    _check_env(cfg)
    exploration = cfg.get("exploration")
    if exploration is not None:
        alpha = float(exploration.alpha)
        if not 0.0 <= alpha <= 1.0:
            raise ConfigError(f"exploration.alpha={exploration.alpha} must lie in [0, 1] (1 keeps "
                              f"the last pressure, 0 draws afresh)")
        for name in ("beta", "noise_std", "p_max"):
            if not math.isfinite(float(exploration[name])):
                raise ConfigError(f"exploration.{name}={exploration[name]} must be finite")
        if float(exploration.noise_std) < 0:
            raise ConfigError(f"exploration.noise_std={exploration.noise_std} must be >= 0")
        if float(exploration.p_max) > float(robot.rating.sum_max):
            raise ConfigError(f"exploration.p_max={exploration.p_max} kPa exceeds the arm's "
                              f"rating robot.rating.sum_max={robot.rating.sum_max} kPa")


def _check_env(cfg: Any) -> None:
    """The robustness settings of ``env``: counts, magnitudes and the environments they fit; the
    incremental action's step and the price of a command change."""
    env = cfg.get("env")
    if env is None:
        return
    name = EnvName(env.name)
    seeds, models = int(env.get("ensemble_seeds", 1)), list(env.get("models") or [])
    if seeds < 1:
        raise ConfigError(f"env.ensemble_seeds={seeds} must be >= 1 (1: no ensemble)")
    if (seeds > 1 or models) and name is not EnvName.learned:
        raise ConfigError(f"env.ensemble_seeds={seeds}, env.models={models}: an ensemble of "
                          f"fitted models needs env=learned, not env={name}")
    agreement = env.get("goal_agreement_mm")
    if agreement is not None:
        if not (math.isfinite(float(agreement)) and float(agreement) > 0):
            raise ConfigError(f"env.goal_agreement_mm={agreement} must be finite and > 0 (null: "
                              f"every goal)")
        if seeds == 1 and not models:
            raise ConfigError(f"env.goal_agreement_mm={agreement} keeps the goals an ensemble "
                              f"agrees on: it needs one (env.ensemble_seeds > 1 or env.models)")
    randomization = env.get("randomization") or {}
    for field_name, value in randomization.items():
        if not (math.isfinite(float(value)) and float(value) >= 0):
            raise ConfigError(f"env.randomization.{field_name}={value} must be finite and >= 0")
    if name is EnvName.gymnax and any(float(v) for v in randomization.values()):
        raise ConfigError("env.randomization: env=gymnax has no plant to randomize")
    cost = float(env.get("command_change_cost", EnvConfig.command_change_cost))
    if not (math.isfinite(cost) and cost >= 0):
        raise ConfigError(f"env.command_change_cost={cost} must be finite and >= 0 (mm of reward "
                          f"per kPa of command change)")
    step = float(env.get("action_step_kpa", EnvConfig.action_step_kpa))
    if incremental_actions(env) and not (math.isfinite(step) and step > 0):
        raise ConfigError(f"env.action_step_kpa={step} must be finite and > 0 (the change of a "
                          f"command per control period at action 1, env.action_mode=incremental)")
    hold = env.get("hold_periods", EnvConfig.hold_periods)
    if isinstance(hold, bool) or not isinstance(hold, int) or hold < 1:
        raise ConfigError(f"env.hold_periods={hold} must be an integer >= 1 (consecutive control "
                          f"periods at the goal that end an episode; 1: the first arrival)")
    if hold > int(env.max_steps):
        raise ConfigError(f"env.hold_periods={hold} must be at most env.max_steps="
                          f"{env.max_steps} (an episode could never end at the goal)")
    bonus = float(env.get("hold_bonus_mm", EnvConfig.hold_bonus_mm))
    if not (math.isfinite(bonus) and bonus >= 0):
        raise ConfigError(f"env.hold_bonus_mm={bonus} must be finite and >= 0 (mm of reward per "
                          f"control period at the goal)")
    decay = float(env.get("error_integral_decay", EnvConfig.error_integral_decay))
    if not 0.0 <= decay < 1.0:
        raise ConfigError(f"env.error_integral_decay={decay} must lie in [0, 1) (the accumulated "
                          f"error's weight on its past per control period)")
    period = 1.0 / float(cfg.robot.control_hz)
    delay = float(randomization.get("max_delay_s", 0.0))
    if delay > period + 1e-9:
        raise ConfigError(f"env.randomization.max_delay_s={delay} s must be at most one control "
                          f"period (1 / robot.control_hz = {period:g} s)")


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


def frozen_twin(schema: type, name: str) -> type:
    """A frozen (hashable) dataclass with ``schema``'s fields and defaults, lists as tuples: the
    schema in the form runtime code can pass to ``jax.jit`` as a static argument. Derived, so
    the schema stays the only place a field is declared."""
    fields = []
    for f in dataclasses.fields(schema):
        default = (f.default_factory() if f.default_factory is not dataclasses.MISSING
                   else f.default)
        if isinstance(default, list):
            default = tuple(default)
        fields.append((f.name, Any, dataclasses.field(default=default)))
    return dataclasses.make_dataclass(name, fields, frozen=True)


PROJECT_ROOT = Path(__file__).resolve().parent.parent  # the checkout: conf/ lies here


def sorolex_dir() -> Path:
    """The paper's recorded runs: ``SOROLEX_DIR``, else ``../shared/data/sorolex`` beside the
    checkout (as ``paths.data_dir``)."""
    return Path(os.environ.get("SOROLEX_DIR", PROJECT_ROOT.parent / "shared" / "data" / "sorolex"))


def compose(*overrides: str) -> Any:
    """The pipeline's composed config (``conf/config.yaml``) with Hydra ``overrides``, outside
    a Hydra run (scripts, benchmarks, experiments); the schemas are registered first."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    register_configs()
    with initialize_config_dir(config_dir=str(PROJECT_ROOT / "conf"), version_base="1.3"):
        return hydra_compose("config", overrides=list(overrides))


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
    cs.store(group="control", name="base_control", node=ControlConfig)
    cs.store(group="logger", name="base_logger", node=LoggerConfig)
    cs.store(group="paths", name="base_paths", node=PathsConfig)
    adopt_launcher_schemas()


# Hydra's sweep launchers (hydra/launcher=joblib|submitit_local|submitit_slurm): the plugins
# register their schemas under the options' own names, and a YAML of the same name is then
# matched to its schema automatically, which Hydra deprecated (a warning on every composition).
# Each schema moves to base_<name>, which conf/hydra/launcher/<name>.yaml names first, as the
# other groups name theirs.
LAUNCHER_OPTIONS = ("joblib", "submitit_local", "submitit_slurm")


def adopt_launcher_schemas() -> list[str]:
    """Store each installed launcher plugin's schema as ``hydra/launcher/base_<name>`` in place of
    the entry of the option's own name; returns the options whose schema is there."""
    from hydra.core.plugins import Plugins

    Plugins.instance()  # Hydra's one scan of the plugins, which registers their schemas
    entries = ConfigStore.instance().repo.setdefault("hydra", {}).setdefault("launcher", {})
    for name in LAUNCHER_OPTIONS:
        entry = entries.pop(f"{name}.yaml", None)
        if entry is not None:
            ConfigStore.instance().store(group="hydra/launcher", name=f"base_{name}",
                                         node=entry.node, provider=entry.provider)
    return [name for name in LAUNCHER_OPTIONS if f"base_{name}.yaml" in entries]
