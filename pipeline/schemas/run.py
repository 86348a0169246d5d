"""The schemas of a run: evaluation, control, logging, paths, and the root config that
holds every group.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from pipeline.schemas.adapt import AdaptConfig
from pipeline.schemas.agent import AgentConfig
from pipeline.schemas.choices import Stage
from pipeline.schemas.data import CalibrationConfig, DatasetConfig, ExplorationConfig
from pipeline.schemas.env import EnvConfig
from pipeline.schemas.improve import ImproveConfig
from pipeline.schemas.model import ModelConfig
from pipeline.schemas.values import MISSING


@dataclass
class ReferenceConfig:
    """A reference to follow, in mm and s: a closed shape
    (``pipeline.arm.references.ShapeSettings``) or a replayed measured path
    (``kind: replay``, ``pipeline.arm.references.ReplaySettings``)."""

    # circle | ellipse | figure_eight, or replay: a stretch of the path the arm itself went
    # through, played slow_down times slower: the measured positions of the recordings the
    # evaluation's goals come from (run: one of them by name; null: episodes spread over all),
    # or of a CSV t,x,y,z (s, mm; file), from start_s s on
    kind: str = "circle"
    centre_mm: list[float] | None = None  # [x, y, z] mm; null: the held-out goals' median
    size_mm: float = 5.0  # radius, or semi-axis along the plane's first axis
    size_b_mm: float | None = None  # semi-axis along the second axis; null: size_mm
    period_s: float = 20.0  # s a lap
    phase_deg: float = 0.0  # where the first episode starts (episodes spread over a lap)
    direction: int = 1  # 1: counter-clockwise from the plane's first axis to its second; -1
    plane: str = "xz"  # xz | xy | yz
    run: str | None = None  # replay: the recording (null: every one)
    file: str | None = None  # replay: a CSV t,x,y,z (s, mm) of a measured path instead
    slow_down: float = 4.0  # replay: times slower than recorded
    start_s: float = 0.0  # replay: s into each recording (the CSV) where its stretches begin


def _default_references() -> dict[str, Any]:
    return {"circle": {"kind": "circle"}, "figure_eight": {"kind": "figure_eight"}}


# the settings of the tracking evaluation (left out of the artifact keys of env.task=reach)
TRACK_EVALUATION_SETTINGS = ("references", "tracking_seconds", "tracking_settle_seconds",
                             "reachable_tolerance_mm", "reaching", "tracking_baselines",
                             "tracking_mpc_horizon", "tracking_mpc_per_period",
                             "tracking_mpc_std_kpa")


@dataclass
class EvaluationConfig:
    """The evaluate stage: which policies, how many episodes, which baselines."""

    policies: list[str] = field(default_factory=lambda: ["apg", "apg_rnn"])  # agent configs
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
    # calibrate artifact (key or folder); observed like the training env, same goals, started
    # where its physics rest it at the preload (one arm, one rest pose)
    twins: list[str] = field(default_factory=list)
    # the goals each plant can hold at all (pipeline/evaluation/reachability.py), and each
    # controller's success on those: null on the twins only (where the physics differ from the
    # model's), true on every plant, false on none (the search takes minutes per plant on CPU)
    reach: bool | None = None
    # The cross-model protocol, for recorded data: the recordings split into two disjoint groups
    # (A: cross_model_group_a, by name; empty: every other of the sorted names; B: the rest),
    # each with its own fit_model; every policy type trained in each group's model (this
    # config's env and agent) and rolled out on its held-out goals in its own model and in the
    # other group's (A->B, B->A). null: on for recorded data of at least two runs a group.
    cross_model: bool | None = None
    cross_model_group_a: list[str] = field(default_factory=list)
    # the groups' policies' budget: seeds (null: agent.num_seeds) and the share of the agent's
    # env steps (total_timesteps, recurrent_total_timesteps) they train for
    cross_model_seeds: int | None = None
    cross_model_budget: float = 1.0
    mpc_horizon: int = 2  # control periods a candidate command is held
    mpc_samples: int = 64
    mpc_iterations: int = 3
    seed: int = 0
    # env.task=track: every controller also follows these references, by name, num_episodes
    # episodes each of tracking_seconds, scored after the first tracking_settle_seconds; each is
    # refused where it passes farther than reachable_tolerance_mm from every held-out goal. Each
    # holds the settings of ReferenceConfig that differ from its defaults (a 5 mm circle, 20 s
    # a lap, in the xz plane around the held-out goals' median), e.g.
    # evaluation.references={fast:{kind:figure_eight,period_s:10}}
    references: dict[str, Any] = field(default_factory=_default_references)
    tracking_seconds: float = 30.0
    tracking_settle_seconds: float = 10.0
    reachable_tolerance_mm: float = 1.5
    # env.task=track: also follow the references with the reaching policies of this config
    # (env.task=reach, no preview; trained upstream) fed the moving goal, as a baseline
    reaching: bool = False
    # env.task=track: the baselines that follow the references: preload (do nothing) and mpc
    # (sampling MPC on the learned model, mpc_samples and mpc_iterations, scoring candidates
    # against the reference over tracking_mpc_horizon control periods, 1: the period's goal, the
    # most precise on the default chain; null: env.preview + 1, the points the policies see;
    # tracking_mpc_per_period: a command per period of the horizon, the first sent, else one
    # held over it; tracking_mpc_std_kpa: the spread of the first samples around the last
    # command, kPa)
    tracking_baselines: list[str] = field(default_factory=lambda: ["preload", "mpc"])
    tracking_mpc_horizon: int | None = 1
    tracking_mpc_per_period: bool = True
    tracking_mpc_std_kpa: float = 0.25


@dataclass
class ControlConfig:
    """``stage=control``: a trained policy drives the arm (``pipeline/control``).

    Goals in mm in the mocap frame: ``goals`` (each held ``hold_s``), or ``goals_csv`` (waypoints
    ``t,x,y,z``, t in s from the start, each in force until the next; the last for ``hold_s``), or
    live on ``goal_topic`` (``geometry_msgs/msg/PointStamped`` in metres, robot=ros2 only); or a
    reference followed in real time, ``trajectory`` (``pipeline/control/trajectory.py``): a name
    of ``evaluation.references``, a shape (the fields of ReferenceConfig; no centre: the held-out
    goals' median) or a CSV file ``t,x,y,z`` (s, mm), followed for ``duration_s`` (null: a
    shape for ``evaluation.tracking_seconds``, a CSV to its last time) and scored after
    ``settle_s`` (null: ``evaluation.tracking_settle_seconds``). Or a reference that arrives
    while it is followed, ``trajectory_topic`` (robot=ros2 only): ``geometry_msgs/msg/PointStamped``
    points in metres, each due at its header stamp (ROS time; zero: on arrival), joined by
    straight segments, followed for ``duration_s`` (null: until stopped) and scored like a
    ``trajectory`` from its first point on.
    """

    policy: str = "apg"  # agent option (conf/agent/<policy>.yaml) of the train_ppo artifact
    policy_file: str | None = None  # a policy.msgpack inside a train_ppo artifact, instead
    seed: int | None = None  # seed of the stacked policy; None: best held-out median in training
    goals: list[Any] = field(default_factory=list)  # [[x, y, z], ...] mm (checked by control)
    goals_csv: str | None = None
    goal_topic: str | None = None
    # live goals, a trajectory: arm s to run (None: until Ctrl-C; a trajectory: see above)
    duration_s: float | None = None
    trajectory: Any = None  # a reference to follow: a name, a shape {kind: ...} or a CSV path
    trajectory_topic: str | None = None  # a reference to follow, its points live on this topic
    settle_s: float | None = None  # trajectory: s left out of its metrics (None: evaluation's)
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
    adapt: AdaptConfig = MISSING
    improve: ImproveConfig = MISSING
    logger: LoggerConfig = MISSING
    paths: PathsConfig = MISSING
