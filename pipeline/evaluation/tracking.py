"""Tracking evaluation: every controller follows the same references on every plant.

For ``env.task=track``: each reference of ``evaluation.references`` (a shape in mm and s,
:mod:`pipeline.arm.references`, centred on the held-out goals' median where it names no centre;
or stretches of the measured paths the arm went through, replayed slower; checked against the
held-out goals before anything runs) is followed for ``tracking_seconds`` by
every policy (all seeds) and the baselines (``evaluation.tracking_baselines``: the preload; the
sampling MPC on the learned model, :mod:`pipeline.evaluation.mpc`, scoring its candidates
against the reference over its horizon, :class:`TrackingSettings`; the reaching policies fed the
moving goal, :class:`Reaching`), in ``num_episodes`` episodes from the
learned env's start states, their phases spread evenly over a lap; on the learned model, the
plant, other fitted models and twins (the plants of
:func:`pipeline.evaluation.closed_loop.run_evaluation`), and in the cross-model protocol
(:func:`cross_model_tracking`).

Metrics per episode (:func:`tracking_metrics`), over the times after the first
``tracking_settle_seconds`` (the arm starts at rest, away from the reference): the RMSE, the 95th
percentile and the largest error (mm), the fraction of times within 1 mm and the lag, the time
shift (s) that best aligns the path with the reference (positive: the path runs behind), and
the share of the commands on the limits of the safe set (the reference asks for all the rating
allows there).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from pipeline.arm import references
from pipeline.arm.safety import SafeSet, on_boundary
from pipeline.evaluation import mpc
from pipeline.evaluation.closed_loop import (
    ClosedLoopSettings,
    Policy,
    _controllers,
    _plants,
    _Programs,
    _starts,
)
from pipeline.evaluation.metrics import CROSS, MM_PER_M, OWN
from pipeline.rl.envs import task
from pipeline.rl.envs.factory import observation_options
from pipeline.rl.envs.learned import EnvParams, SoftArmReachEnv

WITHIN_MM = 1.0  # the tolerance of the time-within share
MAX_LAG_S = 5.0  # the lag is searched within +- this many seconds
BASELINES = ("preload", "mpc")  # the tracking evaluation's baselines besides the reaching one
# tracking_metrics' columns, in its order (stage=control's records and summaries name them)
SCORES = ("rmse_mm", "p95_mm", "max_mm", "within_1mm", "lag_s", "offset_mm", "offset_x_mm",
          "offset_y_mm", "offset_z_mm", "at_limits")
PATH_EPISODES = 8  # the episodes of each controller whose paths the paths table keeps


@dataclass(frozen=True)
class TrackingSettings:
    """The references and timing of the tracking evaluation.

    references: the references followed, by name: shapes
      (:class:`~pipeline.arm.references.ShapeSettings`; ``centre_mm`` None: the held-out goals'
      median) or replayed measured paths (:class:`~pipeline.arm.references.ReplaySettings`).
    seconds: s, an episode's length.
    settle_seconds: s, the first part of an episode left out of the metrics.
    reachable_tolerance_mm: mm, how far a reference point may lie from the nearest held-out goal.
    baselines: some of :data:`BASELINES`.
    mpc_horizon: control periods the MPC scores a candidate over; None: the environment's
      ``preview + 1`` (the current goal and the points the policies see ahead). 1: the goal
      of the period only, the most precise on the default chain's model and arm at 2 Hz (the
      arm settles within a period; a longer horizon adds the bias of a held command, or search
      dimensions per period that the samples do not fill).
    mpc_per_period: the MPC plans one command per period of its horizon (False: one held).
    mpc_std_kpa: kPa, the spread of the MPC's first samples around where its search starts (the
      last command: a slow reference moves the command by tenths of a kPa a period).
    """

    references: Mapping[str, Any]
    seconds: float = 30.0
    settle_seconds: float = 10.0
    reachable_tolerance_mm: float = 1.5
    baselines: Sequence[str] = ("preload",)
    mpc_horizon: int | None = 1
    mpc_per_period: bool = True
    mpc_std_kpa: float = 0.25
    # the measured paths a replayed reference without a file replays, by recording: (times [T]
    # s, positions [T, 3] m), the recordings the held-out goals come from
    recorded: Mapping[str, tuple[np.ndarray, np.ndarray]] = dataclasses.field(
        default_factory=dict)

    def mpc_settings(self, evaluation: Any, env: SoftArmReachEnv) -> mpc.CEMSettings:
        """The tracking MPC's settings: ``evaluation``'s samples and iterations, this horizon
        (None: ``env.preview + 1``) and planning."""
        horizon = env.preview + 1 if self.mpc_horizon is None else int(self.mpc_horizon)
        return mpc.CEMSettings(horizon=horizon, num_samples=int(evaluation.mpc_samples),
                               num_iterations=int(evaluation.mpc_iterations),
                               initial_std_kpa=float(self.mpc_std_kpa),
                               per_period=bool(self.mpc_per_period))


def tracking_metrics(positions: np.ndarray, reference: np.ndarray, control_hz: float,
                     settle_seconds: float, max_lag_s: float = MAX_LAG_S,
                     commands: np.ndarray | None = None, safe: SafeSet | None = None
                     ) -> pd.DataFrame:
    """One row per episode: ``rmse_mm``, ``p95_mm``, ``max_mm``, ``within_1mm`` (share of the
    times), ``lag_s`` and the steady offset over the times ``k / control_hz >= settle_seconds``:
    ``offset_x_mm``, ``offset_y_mm``, ``offset_z_mm``, the mean of the path less the reference,
    and ``offset_mm``, its length (the part of the RMSE a constant correction would take out:
    ``rmse_mm**2 = offset_mm**2 +`` the mean squared deviation from it); and ``at_limits``, the
    share of the commands that moved the arm to those times (of the periods ending at them) lying
    on the safe set's boundary (:func:`pipeline.arm.safety.on_boundary`: the reference asks for
    all the arm's rating allows), NaN without ``commands``.

    Args:
      positions: [E, T + 1, 3] m, row k the position after k control periods.
      reference: [E, T + 1, 3] m, the reference at the same times.
      max_lag_s: the lag is the shift ``s`` (whole periods, refined by a parabola through the
        best and its neighbours) within ``+- max_lag_s`` minimizing the RMSE between
        ``positions[k]`` and ``reference[k - s]`` (positive: the path behind the reference).
      commands: [E, T, n_valves] kPa, row k the command of period k (from tick k to k + 1), as
        the plant got it before its own gain or delay; with ``safe``, the limits they lie in.
    """
    positions, reference = np.asarray(positions, np.float64), np.asarray(reference, np.float64)
    if positions.shape != reference.shape or positions.ndim != 3:
        raise ValueError(f"positions and reference must both be [E, T + 1, 3], got "
                         f"{positions.shape} and {reference.shape}")
    first = math.ceil(settle_seconds * control_hz - 1e-9)
    if first >= positions.shape[1]:
        raise ValueError(f"settle_seconds={settle_seconds} leaves no time of the "
                         f"{positions.shape[1] - 1} control periods to score")
    gap = (positions - reference)[:, first:] * MM_PER_M  # [E, T', 3]
    error = np.linalg.norm(gap, axis=-1)  # [E, T']
    offset = gap.mean(axis=1)  # [E, 3]
    table = pd.DataFrame({
        "rmse_mm": np.sqrt(np.mean(error ** 2, axis=1)),
        "p95_mm": np.percentile(error, 95, axis=1),
        "max_mm": error.max(axis=1),
        "within_1mm": (error <= WITHIN_MM).mean(axis=1),
        "lag_s": _lags(positions, reference, first, control_hz, max_lag_s),
        "offset_mm": np.linalg.norm(offset, axis=1),
        **{f"offset_{axis}_mm": offset[:, number] for number, axis in enumerate("xyz")},
        "at_limits": np.nan,
    })
    if commands is not None:
        commands = np.asarray(commands, np.float64)
        if commands.shape[:2] != (positions.shape[0], positions.shape[1] - 1) or safe is None:
            raise ValueError(f"commands must be [E, T, n_valves] beside positions "
                             f"{positions.shape} and come with their safe set, got "
                             f"{commands.shape}")
        table["at_limits"] = on_boundary(commands[:, max(first - 1, 0):], safe).mean(axis=1)
    return table[list(SCORES)]


def _lags(positions: np.ndarray, reference: np.ndarray, first: int, control_hz: float,
          max_lag_s: float) -> np.ndarray:
    """``[E]`` s: the best-aligning shift of each episode (see :func:`tracking_metrics`)."""
    count = positions.shape[1]
    most = max(0, min(round(max_lag_s * control_hz), count - first - 1))
    shifts = np.arange(-most, most + 1)
    rmse = np.full((positions.shape[0], len(shifts)), np.inf)
    for column, shift in enumerate(shifts):
        rows = np.arange(max(first, shift), min(count, count + shift))  # k and k - shift valid
        if len(rows):
            gap = positions[:, rows] - reference[:, rows - shift]
            rmse[:, column] = np.sqrt(np.mean(np.sum(gap ** 2, axis=-1), axis=1))
    best = np.argmin(rmse, axis=1)
    refined = shifts[best].astype(np.float64)
    inner = (best > 0) & (best < len(shifts) - 1)
    for episode in np.flatnonzero(inner):
        left, centre, right = rmse[episode, best[episode] - 1:best[episode] + 2]
        curvature = left - 2.0 * centre + right
        if np.isfinite(curvature) and curvature > 0:
            refined[episode] += 0.5 * (left - right) / curvature
    return refined / control_hz


def episode_references(settings: TrackingSettings, goal_set: np.ndarray, episodes: int,
                       horizon_s: float | None = None) -> dict[str, references.Reference]:
    """Each named reference ``[episodes]`` (stacked), checked over ``horizon_s`` s (None: the
    episode's length; :func:`pipeline.arm.references.check_reachable`): a shape's phase spread
    evenly over a lap, the first episode checked against ``goal_set [G, 3]`` m (the others pass
    the same points); a replayed path's stretches spread over the recordings
    (``settings.recorded``) or its CSV (:func:`pipeline.arm.references.replay_stretches`), the
    points of every one checked against what the recordings reached: the goals and every
    measured position of ``settings.recorded`` (the goals may keep only every n-th,
    ``env.goal_every``). A replay's points, not its chords: where the arm moved fast a straight
    line between two measured positions passes farther from both than the tolerance."""
    horizon = float(settings.seconds if horizon_s is None else horizon_s)
    centre = tuple(float(v) for v in np.median(np.asarray(goal_set), axis=0) * MM_PER_M)
    out = {}
    for name, given in settings.references.items():
        what = f"evaluation.references {name}"
        if isinstance(given, references.ReplaySettings):
            paths = references.measured_paths(given, settings.recorded, what)
            stretches = references.replay_stretches(paths, given, horizon, episodes, what)
            # what the recordings reached: the goals and every measured position of them
            reached = np.concatenate([np.asarray(goal_set, np.float64).reshape(-1, 3), *(
                np.asarray(points, np.float64) for _, points in settings.recorded.values())])
            for number, stretch in enumerate(stretches):
                references.check_points(np.asarray(stretch.times), np.asarray(stretch.points),
                                        reached, settings.reachable_tolerance_mm,
                                        f"{what} (episode {number})")
            out[name] = references.stack(stretches)
            continue
        shape = given if given.centre_mm is not None else dataclasses.replace(
            given, centre_mm=centre)
        first = references.shape(shape)
        references.check_reachable(first, shape.period_s, 64.0 / shape.period_s, goal_set,
                                   settings.reachable_tolerance_mm, what)
        out[name] = references.stack([
            references.shape(dataclasses.replace(
                shape, phase_deg=shape.phase_deg + 360.0 * number / episodes))
            for number in range(episodes)])
    return out


class Reaching(NamedTuple):
    """The reaching baseline: policies trained to reach (``env.task=reach``) fed the moving goal,
    with the env settings they were trained with (``env``); named ``<type> (reaching)``."""

    env: Any
    policies: Mapping[str, Policy]


def _loaded(policies: Mapping[str, Policy]) -> dict[str, tuple[Any, Any, int]]:
    return {name: (policy.network, policy.params, jax.tree.leaves(policy.params)[0].shape[0])
            for name, policy in policies.items()}


def run_tracking(settings: ClosedLoopSettings, tracking: TrackingSettings,
                 policies: Mapping[str, Policy], env: SoftArmReachEnv, eval_params: EnvParams,
                 models: Mapping[str, Any] | None = None,
                 twins: Mapping[str, Mapping[str, Any]] | None = None,
                 reaching: Reaching | None = None) -> dict[str, Any]:
    """Every policy (all seeds), ``tracking``'s baselines and the ``reaching`` baseline
    following each reference of ``tracking`` on every plant (``settings``' plant, ``models``,
    ``twins``: as :func:`~pipeline.evaluation.closed_loop.run_evaluation`); returns ``tables``
    (``tracking_episodes``: one row per plant, controller, reference, seed and episode;
    ``tracking``: the medians per plant, controller and reference; ``tracking_paths``: the paths
    of the first :data:`PATH_EPISODES` episodes, :func:`path_table`), ``paths`` and
    ``reference_paths`` by ``(plant, controller, reference, seed)`` / reference (``[E, T + 1,
    3]`` m) and the ``headline``."""
    if not env.tracking:
        raise ValueError("the tracking evaluation needs a tracking environment (env.task=track)")
    episodes = int(settings.evaluation.num_episodes)
    shapes = episode_references(tracking, np.asarray(eval_params.goal_set), episodes,
                                tracking.seconds + env.preview / env.control_hz)
    key = jax.random.fold_in(jax.random.key(int(settings.evaluation.seed)), 7)
    with_baselines = dataclasses.replace(
        settings, mpc=tracking.mpc_settings(settings.evaluation, env),
        evaluation=dataclasses.replace(settings.evaluation, baselines=list(tracking.baselines)))
    runs = [(with_baselines, env, _loaded(policies))]
    if reaching is not None and reaching.policies:
        reach_env = SoftArmReachEnv(env.plant, env.control_hz, **observation_options(reaching.env))
        no_baselines = dataclasses.replace(settings, env=reaching.env, evaluation=dataclasses.replace(
            settings.evaluation, baselines=[]))
        runs.append((no_baselines, reach_env, _loaded(
            {f"{name} (reaching)": policy for name, policy in reaching.policies.items()})))
    rows, paths, targets, programs = [], {}, {}, _Programs()
    for run_settings, run_env, loaded in runs:
        plants = _plants(run_settings, run_env, eval_params, jax.random.fold_in(key, 1),
                         models or {}, twins or {})
        _follow(run_settings, tracking, plants, loaded, eval_params, shapes,
                jax.random.split(key, episodes), programs, (rows, paths, targets))
    table = pd.concat(rows, ignore_index=True)
    summary = summarize_tracking(table)
    headline = {f"tracking/{row.plant}/{row.controller}/{row.reference}": {
        "median_rmse_mm": float(row.median_rmse_mm), "median_lag_s": float(row.median_lag_s)}
        for row in summary.itertuples()}
    return {"tables": {"tracking_episodes": table, "tracking": summary,
                       "tracking_paths": path_table(paths, targets, env.control_hz)},
            "paths": paths, "reference_paths": targets, "headline": headline,
            "settle_seconds": float(tracking.settle_seconds)}


def cross_model_tracking(settings: ClosedLoopSettings, tracking: TrackingSettings,
                         policies: Mapping[str, Policy], env: SoftArmReachEnv,
                         eval_params: EnvParams, other: Any, reaching: Reaching | None = None
                         ) -> pd.DataFrame:
    """The tracking evaluation in the cross-model protocol: one row per (plant, controller,
    reference, seed, episode) as ``tracking_episodes``, every policy type of ``policies``
    (trained in ``env``'s model, all seeds), ``tracking``'s baselines (the MPC on the policies'
    own model) and the ``reaching`` policies of the same group, under ``settings`` (the training
    group's), in their own model (plant ``own``) and in ``other`` (``cross``: another fitted
    model's ``DynamicsParams``)."""
    results = run_tracking(settings.only_in_models(), tracking, policies, env, eval_params,
                           {CROSS: other}, reaching=reaching)
    episodes = results["tables"]["tracking_episodes"]
    return episodes.assign(plant=episodes["plant"].replace({"learned": OWN}))


def path_table(paths: Mapping[tuple[str, str, str, int], np.ndarray],
               targets: Mapping[str, np.ndarray], control_hz: float,
               episodes: int = PATH_EPISODES) -> pd.DataFrame:
    """One row per (plant, controller, reference, seed, episode, period) of the first
    ``episodes`` episodes of ``paths`` (``[E, T + 1, 3]`` m by ``(plant, controller, reference,
    seed)``): ``time_s`` (s after the start), the position ``x_mm, y_mm, z_mm`` and the
    reference ``reference_{x,y,z}_mm`` (``targets``, ``[E, T + 1, 3]`` m by reference) and the
    distance between them ``error_mm`` (mm)."""
    frames = []
    for (plant, controller, name, seed), positions in paths.items():
        shown = min(episodes, positions.shape[0])
        drawn = np.asarray(positions[:shown], np.float64) * MM_PER_M  # [e, T + 1, 3]
        target = np.asarray(targets[name][:shown], np.float64) * MM_PER_M
        count = drawn.shape[1]
        frame = pd.DataFrame({
            "episode": np.repeat(np.arange(shown), count), "period": np.tile(np.arange(count), shown),
            "time_s": np.tile(np.arange(count) / float(control_hz), shown)})
        for axis, letter in enumerate("xyz"):
            frame[f"{letter}_mm"] = drawn[..., axis].reshape(-1)
            frame[f"reference_{letter}_mm"] = target[..., axis].reshape(-1)
        frame["error_mm"] = np.linalg.norm(drawn - target, axis=-1).reshape(-1)
        frames.append(frame.assign(plant=plant, controller=controller, reference=name, seed=seed))
    columns = ["plant", "controller", "reference", "seed", "episode", "period", "time_s"]
    table = pd.concat(frames, ignore_index=True)
    return table[columns + [c for c in table.columns if c not in columns]]


def _follow(settings: ClosedLoopSettings, tracking: TrackingSettings, plants, loaded,
            eval_params: EnvParams, shapes: Mapping[str, references.Reference], keys: jax.Array,
            programs: _Programs, out: tuple[list, dict, dict]) -> None:
    """Every controller of ``loaded`` and ``settings``' baselines following each of ``shapes``
    on each of ``plants``: the rows, paths and reference paths into ``out``."""
    rows, paths, targets = out
    episodes = int(np.shape(keys)[0])
    control_hz = next(iter(plants.values()))[0].control_hz
    steps = round(float(tracking.seconds) * control_hz)
    times = jnp.arange(steps + 1, dtype=jnp.float32) / control_hz
    for name, stacked in shapes.items():
        target = np.asarray(jax.vmap(references.positions, in_axes=(0, None))(stacked, times))
        goals = jax.vmap(task.goal_path, in_axes=(0, None, None))(stacked, steps, control_hz)
        targets[name] = target
        for plant_name, (plant_env, plant_params) in plants.items():
            controllers = _controllers(settings, plant_env, plant_params, eval_params, loaded,
                                       episodes)
            runs = programs.run(plant_env, plant_params, controllers, keys,
                                _starts(plant_params, episodes), goals, stacked)
            for controller, (positions, commands) in runs.items():
                for seed in range(positions.shape[0]):
                    table = tracking_metrics(positions[seed], target, control_hz,
                                             float(tracking.settle_seconds),
                                             commands=commands[seed],
                                             safe=plant_params.safe_set)
                    rows.append(table.assign(plant=plant_name, controller=controller,
                                             reference=name, seed=seed,
                                             episode=np.arange(episodes)))
                    paths[(plant_name, controller, name, seed)] = positions[seed]


def summarize_tracking(table: pd.DataFrame, by: Sequence[str] = ("plant", "controller",
                                                                   "reference")
                       ) -> pd.DataFrame:
    """Per group: episodes, the median RMSE, p95, max, lag and steady offset over episodes and
    seeds, the mean shares within 1 mm and at the limits, and the spread over seeds of each
    seed's median RMSE (min, max)."""
    by = list(by)
    grouped = table.groupby(by, sort=False)
    out = grouped.agg(episodes=("rmse_mm", "size"), median_rmse_mm=("rmse_mm", "median"),
                      median_p95_mm=("p95_mm", "median"), median_max_mm=("max_mm", "median"),
                      within_1mm=("within_1mm", "mean"), median_lag_s=("lag_s", "median"),
                      median_offset_mm=("offset_mm", "median"),
                      at_limits=("at_limits", "mean"))
    per_seed = table.groupby([*by, "seed"], sort=False)["rmse_mm"].median()
    spread = per_seed.groupby(level=list(range(len(by))), sort=False).agg(
        seed_rmse_min_mm="min", seed_rmse_max_mm="max")
    return out.join(spread).reset_index()
