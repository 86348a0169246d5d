"""The schema of ``stage=adapt``: a deployed policy calibrated to the session of the day."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class AdaptConfig:
    """``stage=adapt``: record a short calibration walk of the current session, calibrate the
    deployed model to it (``pipeline/dynamics/adaptation.py``) and fine-tune the deployed policy
    (``control.policy`` / ``control.policy_file``, seed ``control.seed``) in the calibrated
    model; ``stage=control control.policy_file=<adapt artifact>/policy.msgpack`` drives with it.

    The walk is the exploration walk (``exploration``: its seed, alpha, noise) cut to ``walk_s``
    seconds at ``robot.control_hz``, padded with the preload as collect pads it.
    """

    walk_s: float = 60.0  # calibration walk [s of arm time]
    # how the model is calibrated (AdaptationSettings): none, offset or fine_tune
    mechanism: str = "fine_tune"
    output: str = "diagonal"  # the fine-tune's output correction: bias, diagonal or full
    input_affine: bool = True  # the fine-tune also fits a gain and an offset per chamber
    steps: int = 300  # Adam steps of the fine-tune
    prior_mm2: float = 1.0  # weight of the fine-tune's prior [mm² per unit²]
    # env steps of the policy's fine-tune in the calibrated model by its own trainer (one seed,
    # warm started; at least num_envs x num_steps x num_evals of the deployed agent)
    policy_timesteps: int = 131072
    # PPO: log std the fine-tune starts from (None: the deployed policy's): explore less than anew
    policy_log_std: float | None = -3.0
    # the folded model may differ from the calibrated prediction (a displacement model turns
    # its output about the walk's first pose) by at most this over the walk [mm]
    max_fold_error_mm: float = 0.1
