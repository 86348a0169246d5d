"""The robot group's schemas: the arm's rating and limits, its workspace and mocap, the
simulated arm's physics, and the options (sim, recorded files, ROS 2, bags).

Units: pressures in kPa, positions in metres, times in seconds, rates in Hz.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from pipeline.schemas.choices import Choice, RobotKind
from pipeline.schemas.values import MISSING


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
    # the longest the arm may be driven without a rest [arm s]: a budget of stage=improve's
    # (one round's arm time) must lie within it
    max_session_s: float = 600.0


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
