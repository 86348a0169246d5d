"""The data schemas: exploration (the random walk), align, the dataset the model trains on,
and the calibration of the simulated arm to recorded runs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.schemas.choices import GapPolicy, ModelGrid, ModelProtocol, WindowOrder
from pipeline.schemas.robot import SimPhysics


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
    # session artifacts (stage=control sessions, stage=improve walks: keys or folders) whose runs
    # join the collected ones in align (pipeline/data/sessions.py), each with its provenance
    sessions: list[str] = field(default_factory=list)
    # fit_model draws a session run's windows this many times as often as a collected run's
    # (protocol split; 1: every window alike)
    session_weight: float = 1.0


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
    # s into each run where its fit and scores begin, settled at the command in force there
    # (each of the paper's runs opens with its preload held 17 s while the arm still settles)
    start_s: float = 0.0
    fitted: list[str] = field(default_factory=lambda: [
        "chamber_angles_deg", "chamber_gains", "segment_length_m", "tip_offset_m",
        "pressure_tau_s", "bend_gain", "elong_gain", "natural_freq_hz", "damping_ratio",
        "gravity_stiffening", "hysteresis_kpa", "creep_gain", "creep_tau_s",
        "saturation_per_kpa", "saturation_center_kpa", "mean_stiffening_per_kpa"])
    init: SimPhysics = field(default_factory=SimPhysics)  # start; holds the unfitted values
