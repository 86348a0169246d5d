"""The agent's schema: the trainer (PPO, or analytic policy gradients through the learned
model), its policy network and budget, and when training may stop early.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from pipeline.schemas.choices import Activation, Choice
from pipeline.schemas.values import ConfigError, dataclass_values


def budget_overrides(steps: int) -> list[str]:
    """Overrides that train every policy type for ``steps`` environment steps per seed (also the
    recurrent one, which an experiment may give a budget of its own)."""
    return [f"agent.total_timesteps={int(steps)}", "agent.recurrent_total_timesteps=null"]




class Trainer(Choice):
    """How the policy learns: ``ppo`` (``pipeline/rl/ppo.py``, the environment a black box) or
    ``apg`` (``pipeline/rl/apg.py``, analytic policy gradients through the differentiable
    environment, the learned model)."""

    ppo = "ppo"
    apg = "apg"


@dataclass
class StopAt:
    """Stop training once the held-out evaluations during training (``agent.num_evals`` of them)
    are good enough in ``consecutive`` evaluations in a row: the median final distance of all
    seeds' episodes at most ``median_distance_mm`` and the share of them within the goal tolerance
    at least ``success_rate``. A threshold left None is not asked for; both None (the default):
    training runs its whole budget."""

    median_distance_mm: float | None = None  # [mm]
    success_rate: float | None = None  # [0, 1]
    consecutive: int = 1  # evaluations in a row

    @property
    def active(self) -> bool:
        return self.median_distance_mm is not None or self.success_rate is not None

    def reached(self, median_distance_mm: float, success_rate: float) -> bool:
        """Whether one evaluation's figures (pooled over seeds) meet the thresholds set."""
        return ((self.median_distance_mm is None
                 or median_distance_mm <= self.median_distance_mm)
                and (self.success_rate is None or success_rate >= self.success_rate))


@dataclass
class HoldTune:
    """A phase after the trainer's: every seed's policy fine-tuned by analytic policy gradients
    through the training environment (``pipeline/rl/apg.py``) on episodes that never end at the
    goal, so that the distance of every control period of the horizon is the loss, the periods
    after the goal is reached included (training that ends at the first arrival never trains
    them). ``steps`` 0 (the default): none. Measured in docs/results/PPO_RESULTS.md ("Holding
    what was reached")."""

    steps: int = 0  # environment steps per seed
    # the recurrent policy's where it needs another (None: steps; 0: no such phase for it)
    recurrent_steps: int | None = None
    lr: float = 3.0e-5  # Adam step size (decayed to 0 with agent.anneal_lr)
    window: int = 10  # control periods per gradient window (the state detached between them)
    max_grad_norm: float = 1.0  # the gradient's global norm is clipped to this


@dataclass
class AgentConfig:
    """The trainer (``trainer``: PPO or APG) and its policy; ``recurrent`` selects the GRU
    actor-critic. APG (``pipeline/rl/apg.py``) reads the same fields where they mean the same
    (``num_envs`` episodes, ``num_steps`` control periods per gradient window, budget, ``lr``,
    ``max_grad_norm``, network) and ignores PPO's own (epochs, minibatches, GAE, clipping)."""

    name: str = "ppo_ff"
    trainer: Trainer = Trainer.ppo
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
    # stop when the held-out evaluations are good enough (StopAt; default: the whole budget)
    stop_at: StopAt = field(default_factory=StopAt)
    # then fine-tune to hold what is reached (HoldTune; default: no such phase)
    hold_tune: HoldTune = field(default_factory=HoldTune)

    def __post_init__(self) -> None:
        if self.trainer not in {t.value for t in Trainer}:
            raise ConfigError(f"agent.trainer={self.trainer!r}: one of "
                              f"{[t.value for t in Trainer]} expected")
        self.trainer = Trainer(self.trainer)
        if isinstance(self.stop_at, Mapping) or hasattr(self.stop_at, "items"):
            self.stop_at = StopAt(**dataclass_values(StopAt, self.stop_at, "agent.stop_at"))
        if isinstance(self.hold_tune, Mapping) or hasattr(self.hold_tune, "items"):
            self.hold_tune = HoldTune(**dataclass_values(HoldTune, self.hold_tune,
                                                         "agent.hold_tune"))

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

    @property
    def hold_tune_timesteps(self) -> int:
        """This policy type's :class:`HoldTune` budget per seed (0: no such phase):
        ``hold_tune.recurrent_steps`` for a recurrent policy where it is set, else
        ``hold_tune.steps``."""
        tune = self.hold_tune
        if self.recurrent and tune.recurrent_steps is not None:
            return int(tune.recurrent_steps)
        return int(tune.steps)

    def hold_tuning(self) -> AgentConfig:
        """The agent of the :class:`HoldTune` phase: analytic policy gradients with its step
        size, window, clip and budget; the same network, seeds, environments and evaluations;
        no early stop and no warm start of its own (it starts from the trained policies)."""
        tune = self.hold_tune
        return dataclasses.replace(
            self, trainer=Trainer.apg, num_steps=int(tune.window), lr=float(tune.lr),
            max_grad_norm=float(tune.max_grad_norm), total_timesteps=self.hold_tune_timesteps,
            recurrent_total_timesteps=None, stop_at=StopAt(), init_policy=None,
            init_policy_seed=None, init_policy_log_std=None, hold_tune=HoldTune())

    def check(self) -> None:
        stop = self.stop_at
        if stop.median_distance_mm is not None and not stop.median_distance_mm > 0:
            raise ConfigError(f"agent.stop_at.median_distance_mm={stop.median_distance_mm} must "
                              f"be > 0 mm (null: not asked for)")
        if stop.success_rate is not None and not 0 <= stop.success_rate <= 1:
            raise ConfigError(f"agent.stop_at.success_rate={stop.success_rate} must lie in [0, 1] "
                              f"(null: not asked for)")
        if int(stop.consecutive) < 1:
            raise ConfigError(f"agent.stop_at.consecutive={stop.consecutive} must be >= 1")
        if stop.active:
            if int(stop.consecutive) > self.num_evals:
                raise ConfigError(f"agent.stop_at.consecutive={stop.consecutive} exceeds "
                                  f"agent.num_evals={self.num_evals}: it could never be reached")
            if self.eval_envs < 1:
                raise ConfigError(f"agent.eval_envs={self.eval_envs} must be >= 1: "
                                  f"agent.stop_at reads the held-out evaluations")
        tune = self.hold_tune
        if not (int(tune.steps) >= 0 and int(tune.recurrent_steps or 0) >= 0
                and float(tune.lr) > 0 and int(tune.window) >= 1
                and float(tune.max_grad_norm) > 0):
            raise ConfigError(f"agent.hold_tune={dataclasses.asdict(tune)}: steps and "
                              f"recurrent_steps must be >= 0 (0: no such phase), lr and "
                              f"max_grad_norm > 0, window >= 1 control period")
        if self.trainer is not Trainer.ppo:  # the minibatches are PPO's
            return
        if self.recurrent and self.num_envs % self.num_minibatches:
            raise ConfigError(f"recurrent PPO minibatches over environments: num_envs="
                              f"{self.num_envs} must be divisible by num_minibatches="
                              f"{self.num_minibatches}")
        if self.steps_per_update % self.num_minibatches:
            raise ConfigError(f"num_envs * num_steps = {self.steps_per_update} must be divisible "
                              f"by num_minibatches={self.num_minibatches}")
