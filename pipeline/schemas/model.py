"""The dynamics model's schema: architecture, input features and training.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.schemas.choices import Cell, LrSchedule, ModelLoss, ReferencePose


@dataclass
class ModelArchitecture:
    """The network and its input features: what a saved model stores and needs to run
    (``pipeline.dynamics.model.DynamicsConfig`` is this schema frozen, the only declaration)."""

    hidden: int = 64
    layers: int = 1
    head: list[int] = field(default_factory=list)
    condition_on_initial_pose: bool = False  # initial carry from the observed pose at reset
    # predict the displacement from the run's initial pose (default: robot.settled_start; it
    # helps on settled starts and hurts on the real runs: docs/results/MODEL_RESULTS.md)
    predict_displacement: bool = False
    # gru at 3000 steps with the default dropout: leave-one-run-out on the real runs 2.72 / 6.17
    # mm (mean / p95, 3 seeds) against 2.82 / 6.30 for the LSTM at 1500, at 4/5 of its CPU
    cell: Cell = Cell.gru
    # input features (pipeline/dynamics/features.py); empty / false: off
    pressure_delta: bool = False  # p_t - p_{t-1} per chamber
    # the pressure change at the last command step, held, and exp(-model steps since that step
    # / tau), one input per tau: the former default. Leave-one-run-out on the real runs as
    # accurate (2.72 / 6.17 mm over 3 seeds), but the step is a switch: a model fed them moves
    # about 5 mm for a step of 0.06 kPa and 0.2 mm for one of 0.04 kPa (its threshold, below)
    step_size: bool = False
    step_decays: list[float] = field(default_factory=list)
    play_widths_kpa: list[float] = field(default_factory=list)  # play operators per chamber
    step_threshold_kpa: float = 0.05  # a command step: some chamber changed by more
    # default: per chamber the unsettled part of the pressure, u_t = exp(-1/tau) u_{t-1} +
    # (p_t - p_{t-1}), one input per chamber and tau (model steps): what the transient after a
    # command step depends on, linear and continuous in the commands and zero under a held
    # command (leave-one-run-out 2.74 / 6.36 mm over 3 seeds; docs/results/MODEL_RESULTS.md)
    pressure_transients: list[float] = field(default_factory=lambda: [1.0, 3.0, 10.0])


@dataclass
class ModelConfig(ModelArchitecture):
    """The recurrent forward-dynamics model (``cell``: GRU or LSTM): its architecture and its
    training (see ``pipeline/dynamics/training.py``)."""

    name: str = "recurrent"  # the model family (a recurrent network; which cell: ``cell``)
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
    # regularization (training only)
    input_noise_std: float = 0.0  # on the standardized inputs
    loss: ModelLoss = ModelLoss.mse
    # one mask on h per window; 0.3: leave-one-run-out on the real runs 2.83 / 6.28 mm (mean /
    # p95) against 3.09 / 7.40 without, better on every fold (docs/results/MODEL_RESULTS.md)
    recurrent_dropout: float = 0.3
    weight_decay: float = 0.0  # AdamW, decoupled
    # fit_model artifacts (keys or folders) the fit starts from, their network and normalization
    # (protocol split): entry i for the model of seed model.seed + i (the ensemble's members);
    # empty: a fresh network
    init_from: list[str] = field(default_factory=list)
