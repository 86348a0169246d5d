"""The schema of ``stage=improve``: rounds of drive, record, refit and retrain on an arm."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class ImproveConfig:
    """``stage=improve``: the deployed policy (``control.policy``, a train_ppo artifact of this
    config) and the models it was trained in learn from the arm they drive, ``rounds`` times:

    (a) the policy drives the arm for ``arm_s`` arm seconds: goals drawn over its training
    goals, each held ``goal_s``, and (``explore_share`` of the budget) walks chosen where the
    models of the ensemble disagree most; every command through the safe set and the gate (on
    ``robot=ros2`` the guard too);
    (b) the sessions join the data (``dataset.sessions``, weighed ``dataset.session_weight``) and
    the models are fitted anew (``refit``: from the last round's or from scratch);
    (c) the policy is trained on in the refitted models, warm started from the last round's;
    (d) it is evaluated on the arm (``plant``: a simulated arm, with evaluate's protocol; its
    own sessions) and in the models.

    ``plant``: the arm, simulated in process, as ``evaluation.twins`` names one (a simulated
    robot config, e.g. ``sim_sorolex``, or a calibrate artifact); null drives ``robot``
    (``robot=sim``, or the arm over ROS 2).
    """

    rounds: int = 3
    arm_s: float = 300.0  # arm seconds each round drives the arm (within robot.rating.max_session_s)
    explore_share: float = 0.0  # of arm_s: exploration walks instead of goals (1: walks only)
    # how each walk is chosen: disagreement (of explore_candidates exploration walks, the one the
    # ensemble's models disagree on most) or walk (the exploration walk as collect draws it)
    explore: str = "disagreement"
    explore_candidates: int = 32
    explore_walk_s: float = 30.0  # arm seconds of each exploration walk (its preload padding in)
    goal_s: float | None = None  # arm s each goal is held (null: the env's episode)
    plant: str | None = None
    refit: str = "warm"  # warm: each model starts from the last round's; scratch: a fresh one
    model_steps: int | None = None  # Adam steps of a refit (null: model.num_steps)
    # env steps of the policy's training in each round, warm started (null: the agent's budget)
    policy_timesteps: int | None = None
    seed: int = 0  # the goals, the walks and the simulated sessions of the rounds
