"""The PPO agent's schema.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pipeline.schemas.choices import Activation
from pipeline.schemas.values import dataclass_values


def budget_overrides(steps: int) -> list[str]:
    """Overrides that train every policy type for ``steps`` environment steps per seed (also the
    recurrent one, which an experiment may give a budget of its own)."""
    return [f"agent.total_timesteps={int(steps)}", "agent.recurrent_total_timesteps=null"]




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
