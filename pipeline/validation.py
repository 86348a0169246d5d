"""Validation of a composed config (the router runs :func:`validate_config` before any work).

Values the schemas' types allow but a run cannot use (NaN, a non-finite timeout,
``exploration.alpha`` outside [0, 1], limits outside the arm's rating, a real arm's rating changed
by an override) fail with a :class:`~pipeline.schemas.ConfigError` naming the setting and its
value.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from pipeline.config import PROJECT_ROOT
from pipeline.schemas import (
    AgentConfig,
    ConfigError,
    EnvName,
    PressureRating,
    RobotKind,
    SafetyBounds,
    Task,
    Trainer,
    incremental_actions,
)

# the largest distance from the goal [m] within which the hold may act (env.deadband_m): it is
# for the last millimetres, the policy reaches
MAX_HOLD_RADIUS_M = 0.01
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
    _check_cross_model_budget(cfg)
    _check_tracking_evaluation(cfg)
    _check_agent(cfg)
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


def _check_cross_model_budget(cfg: Any) -> None:
    """The cross-model protocol's own budget: a seed count and a positive share of the steps."""
    evaluation = cfg.get("evaluation")
    if evaluation is None:
        return
    seeds = evaluation.get("cross_model_seeds")
    if seeds is not None and int(seeds) < 1:
        raise ConfigError(f"evaluation.cross_model_seeds={seeds} must be >= 1 (null: "
                          f"agent.num_seeds)")
    budget = float(evaluation.get("cross_model_budget", 1.0))
    if not (math.isfinite(budget) and budget > 0):
        raise ConfigError(f"evaluation.cross_model_budget={budget} must be finite and > 0 (the "
                          f"share of the agent's env steps the cross-model policies train for)")


def _check_tracking_evaluation(cfg: Any) -> None:
    """The tracking evaluation's baselines (preload, mpc) and the MPC's horizon."""
    evaluation = cfg.get("evaluation")
    if evaluation is None:
        return
    baselines = list(evaluation.get("tracking_baselines") or [])
    unknown = [name for name in baselines if name not in ("preload", "mpc")]
    if unknown:
        raise ConfigError(f"evaluation.tracking_baselines: unknown {unknown}; known: preload, mpc "
                          f"(the reaching policies: evaluation.reaching=true)")
    horizon = evaluation.get("tracking_mpc_horizon")
    if horizon is not None and int(horizon) < 1:
        raise ConfigError(f"evaluation.tracking_mpc_horizon={horizon} must be >= 1 (null: "
                          f"env.preview + 1, the reference points the policies see)")
    spread = float(evaluation.get("tracking_mpc_std_kpa", 0.25))
    if not (math.isfinite(spread) and spread > 0):
        raise ConfigError(f"evaluation.tracking_mpc_std_kpa={spread} must be finite and > 0 (kPa, "
                          f"the spread of the MPC's first samples)")


def _check_env(cfg: Any) -> None:
    """The robustness settings of ``env``: counts, magnitudes and the environments they fit; the
    incremental action's step and the price of a command change."""
    env = cfg.get("env")
    if env is None:
        return
    name = EnvName(env.name)
    seeds, models = int(env.ensemble_seeds), list(env.models)
    if seeds < 1:
        raise ConfigError(f"env.ensemble_seeds={seeds} must be >= 1 (1: no ensemble)")
    if (seeds > 1 or models) and name is not EnvName.learned:
        raise ConfigError(f"env.ensemble_seeds={seeds}, env.models={models}: an ensemble of "
                          f"fitted models needs env=learned, not env={name}")
    agreement = env.goal_agreement_mm
    if agreement is not None:
        if not (math.isfinite(float(agreement)) and float(agreement) > 0):
            raise ConfigError(f"env.goal_agreement_mm={agreement} must be finite and > 0 (null: "
                              f"every goal)")
        if seeds == 1 and not models:
            raise ConfigError(f"env.goal_agreement_mm={agreement} keeps the goals an ensemble "
                              f"agrees on: it needs one (env.ensemble_seeds > 1 or env.models)")
    randomization = env.randomization
    for field_name, value in randomization.items():
        if not (math.isfinite(float(value)) and float(value) >= 0):
            raise ConfigError(f"env.randomization.{field_name}={value} must be finite and >= 0")
    if name is EnvName.gymnax and any(float(v) for v in randomization.values()):
        raise ConfigError("env.randomization: env=gymnax has no plant to randomize")
    cost = float(env.command_change_cost_mm_per_kpa)
    if not (math.isfinite(cost) and cost >= 0):
        raise ConfigError(f"env.command_change_cost_mm_per_kpa={cost} must be finite and >= 0 (mm of reward "
                          f"per kPa of command change)")
    step = float(env.action_step_kpa)
    if incremental_actions(env) and not (math.isfinite(step) and step > 0):
        raise ConfigError(f"env.action_step_kpa={step} must be finite and > 0 (the change of a "
                          f"command per control period at action 1, env.action_mode=incremental)")
    hold = env.hold_periods
    if isinstance(hold, bool) or not isinstance(hold, int) or hold < 1:
        raise ConfigError(f"env.hold_periods={hold} must be an integer >= 1 (consecutive control "
                          f"periods at the goal that end an episode; 1: the first arrival)")
    train_steps = env.get("train_max_steps")
    if train_steps is not None and (isinstance(train_steps, bool) or not isinstance(
            train_steps, int) or train_steps < 1):
        raise ConfigError(f"env.train_max_steps={train_steps} must be an integer >= 1 (control "
                          f"periods of a training episode) or null (env.max_steps)")
    horizon, horizon_name = ((int(env.max_steps), "env.max_steps") if train_steps is None
                             else (train_steps, "env.train_max_steps"))
    if hold > horizon:
        raise ConfigError(f"env.hold_periods={hold} must be at most {horizon_name}="
                          f"{horizon} (an episode could never end at the goal)")
    bonus = float(env.hold_bonus_mm)
    if not (math.isfinite(bonus) and bonus >= 0):
        raise ConfigError(f"env.hold_bonus_mm={bonus} must be finite and >= 0 (mm of reward per "
                          f"control period at the goal)")
    gain = _share("env.hold_gain", env.hold_gain,
                  "the share of the measured error the command corrects per control period "
                  "within env.deadband_m; 0: the last command stays")
    backoff = float(env.hold_backoff)
    if not (math.isfinite(backoff) and 0 < backoff <= 1):
        raise ConfigError(f"env.hold_backoff={backoff} must lie in (0, 1] (what the hold's gain "
                          f"is multiplied by after a correction that overshot; 1: a fixed gain)")
    deadband = float(env.deadband_m)
    if gain == 0 and not (math.isfinite(deadband) and
                          0 <= deadband <= float(env.goal_tolerance_m)):
        raise ConfigError(f"env.deadband_m={deadband} must lie in [0, env.goal_tolerance_m="
                          f"{env.goal_tolerance_m}] m where env.hold_gain=0 (where the last "
                          f"command stays; 0: off)")
    if not (math.isfinite(deadband) and 0 <= deadband <= MAX_HOLD_RADIUS_M):
        raise ConfigError(f"env.deadband_m={deadband} must lie in [0, {MAX_HOLD_RADIUS_M}] m "
                          f"(where the hold takes over from the policy; 0: off)")
    decay = float(env.error_integral_decay)
    if not 0.0 <= decay < 1.0:
        raise ConfigError(f"env.error_integral_decay={decay} must lie in [0, 1) (the accumulated "
                          f"error's weight on its past per control period)")
    _check_task(env)
    period = 1.0 / float(cfg.robot.control_hz)
    delay = float(randomization.max_delay_s)
    if delay > period + 1e-9:
        raise ConfigError(f"env.randomization.max_delay_s={delay} s must be at most one control "
                          f"period (1 / robot.control_hz = {period:g} s)")


def _check_agent(cfg: Any) -> None:
    """The agent's trainer and its environment (APG differentiates through the soft-arm
    environment: env=learned or env=sim, not gymnax), and ``agent.stop_at``'s thresholds."""
    agent = cfg.get("agent")
    if agent is None:
        return
    config = AgentConfig.from_any(agent)
    env = cfg.get("env")
    if ((config.trainer is Trainer.apg or config.hold_tune_timesteps) and env is not None
            and EnvName(env.name) is EnvName.gymnax):
        what = ("agent.trainer=apg" if config.trainer is Trainer.apg
                else "agent.hold_tune (analytic policy gradients)")
        raise ConfigError(f"{what} differentiates through the soft-arm environment "
                          f"(env=learned or env=sim); env=gymnax is a black box: train it with "
                          f"agent=ppo_ff and no agent.hold_tune")
    config.check()

def _check_task(env: Any) -> None:
    """``env.task`` and its settings: a preview only to track, the draws' ranges ordered."""
    task = Task(str(env.get("task", Task.reach)))
    preview = env.get("preview", 0)
    if not isinstance(preview, int) or preview < 0:
        raise ConfigError(f"env.preview={preview} must be an integer >= 0 (future reference "
                          f"points observed)")
    if preview and task is not Task.track:
        raise ConfigError(f"env.preview={preview} observes a moving reference: it needs "
                          f"env.task=track, not env.task={task}")
    if task is not Task.track:
        return
    if EnvName(env.name) is EnvName.gymnax:
        raise ConfigError("env.task=track needs an arm (env=learned or env=sim), not env=gymnax")
    share = float(env.static_share)
    if not 0.0 <= share <= 1.0:
        raise ConfigError(f"env.static_share={share} must lie in [0, 1] (the share of training "
                          f"episodes at a static goal)")
    for low, high in (("reference_size_min_mm", "reference_size_max_mm"),
                      ("reference_period_min_s", "reference_period_max_s")):
        lo, hi = float(env[low]), float(env[high])
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
            raise ConfigError(f"env.{low}={lo}, env.{high}={hi}: expected finite 0 < {low} <= "
                              f"{high}")
    _share("env.reference_integral_gain", env.reference_integral_gain,
           "the share of the tracking error the observed reference moves by per control "
           "period; 0: off")
    limit = float(env.reference_shift_max_mm)
    if not (math.isfinite(limit) and limit > 0.0):
        raise ConfigError(f"env.reference_shift_max_mm={limit} must be a finite number of mm "
                          f"> 0 (the most the observed reference moves)")


def _share(name: str, value: Any, meaning: str) -> float:
    """``value`` as a float, refused naming ``name`` unless it lies in [0, 1]."""
    share = float(value)
    if not (math.isfinite(share) and 0.0 <= share <= 1.0):
        raise ConfigError(f"{name}={share} must lie in [0, 1] ({meaning})")
    return share
