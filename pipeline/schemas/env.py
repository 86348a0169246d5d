"""The reaching environment's schema and the randomization of its plant.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from pipeline.schemas.choices import ActionMode, EnvName, GoalMode, GoalSource, Task


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
    # the chambers saturate about the preload: each valve's pressure p (after gain and offset)
    # reaches the plant as preload + tanh(a (p - preload)) / a, a ~ U(0, max) per episode [1/kPa]
    saturation_max_per_kpa: float = 0.0


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
    # reach: one goal per episode, the episode ends at it; track: the goal of each control period
    # is a moving reference at the period's end (pipeline/arm/references.py), reward -distance
    # to it in mm, no end on arrival
    task: Task = Task.reach
    # track: also observe the goals of the next `preview` control periods (one period apart),
    # each as (goal - measured) / error_scale_m
    preview: int = 0
    # track, training: each episode follows a circle, ellipse or figure-eight (equal odds, in the
    # xz plane, either direction, uniform phase) around the goal a reaching episode
    # would get, its semi-axis uniform in [reference_size_min_mm, reference_size_max_mm] and its
    # lap rate uniform in [1 / reference_period_max_s, 1 / reference_period_min_s]; or, with
    # probability static_share, stays at that goal
    static_share: float = 0.25
    reference_size_min_mm: float = 1.0
    reference_size_max_mm: float = 6.0
    reference_period_min_s: float = 8.0
    reference_period_max_s: float = 40.0
    # track: integral action on the tracking error; after each control period the reference the
    # policy observes (its goal and preview) moves by this share of the measured error (the
    # reference minus the measured position), in training as on the arm, by at most
    # reference_shift_max_mm in all (a steady offset between path and reference, as a model
    # other than the policy's leaves, is taken out over about 1 / gain periods); 0: off
    reference_integral_gain: float = 0.0
    reference_shift_max_mm: float = 5.0
    max_steps: int = 40  # control periods per episode (truncation); evaluation's horizon too
    # training episodes only: truncated after this many control periods instead (longer than the
    # evaluation's trains the states long after arrival); null: max_steps
    train_max_steps: int | None = None
    goal_tolerance_m: float = 0.001  # a control period ending within this distance is at the goal
    # terminate after this many consecutive control periods at the goal (1: the first arrival);
    # more trains the policy in the states after arrival, where evaluation and the arm keep it
    hold_periods: int = 1
    hold_bonus_mm: float = 0.0  # reward [mm] for every control period that ends at the goal
    # deployment (evaluate's reaching episodes, stage=control's goals): a control period whose
    # measured position is within this distance of the goal [m] does not send the policy's
    # action: with hold_gain > 0 the last command moves by hold_gain times the measured error
    # mapped to kPa through the static map of the model the policy was trained in (integral
    # action: the last millimetres and the hold handed from the policy to a slow, steady
    # correction); with hold_gain 0 the last command stays (a deadband, at most
    # goal_tolerance_m). Training never meets it (its episodes end at the goal); 0: off.
    # Measured across models, on the calibrated twin and the simulated arm:
    # docs/results/PPO_RESULTS.md, "The hold: integral action near the goal"
    deadband_m: float = 0.002
    hold_gain: float = 0.15  # share of the measured error corrected per control period, in [0, 1]
    # after a correction that overshot (the error turned past the goal and grew) the hold's gain
    # is multiplied by this, until the goal changes: it settles where the arm answers a small
    # command change far more steeply than the static map says; in (0, 1], 1: a fixed gain
    hold_backoff: float = 0.5
    goal_mode: GoalMode = GoalMode.data
    goal_perturbation_m: float = 0.01
    # a new goal every this many control periods, drawn as at a reset (goal_mode=perturb: around
    # the position then); 0: the episode's goal stays
    goal_redraw_periods: int = 0
    obs_noise_std_m: float = 0.0  # on the observed position
    action_noise_std_kpa: float = 0.0  # on the commanded pressures (before projection)
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
    # reward: -(distance mm + command_change_cost_mm_per_kpa x summed |change of the command|
    # kPa) [mm/kPa]
    command_change_cost_mm_per_kpa: float = 0.0
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


# the settings of env.task=track (left out of the artifact keys of env.task=reach)
TRACK_SETTINGS = ("task", "preview", "static_share", "reference_size_min_mm",
                  "reference_size_max_mm", "reference_period_min_s", "reference_period_max_s",
                  "reference_integral_gain", "reference_shift_max_mm")


def no_randomization_overrides() -> list[str]:
    """Overrides that turn every ``env.randomization`` off (as ``experiment=real_arm`` sets it)."""
    return [f"env.randomization.{f.name}=0" for f in dataclasses.fields(RandomizationConfig)]




def incremental_actions(env: Any) -> bool:
    """Whether the env settings ``env`` (the schema's object, or a mapping of its fields) act
    incrementally (``env.action_mode``)."""
    mode = env["action_mode"] if isinstance(env, Mapping) else env.action_mode
    return ActionMode(str(mode)) is ActionMode.incremental
