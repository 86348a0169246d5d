"""Tracking's baselines and plants: the sampling MPC following a reference over its horizon, the
tracking evaluation on every plant with every baseline, the cross-model protocol and the figures."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from pipeline.arm import references as R
from pipeline.arm.safety import SafeSet
from pipeline.dynamics import model as dynamics
from pipeline.evaluation import mpc, rollouts
from pipeline.evaluation.closed_loop import ClosedLoopSettings, Policy
from pipeline.evaluation.tracking import (
    Reaching,
    TrackingSettings,
    cross_model_tracking,
    path_table,
    run_tracking,
    tracking_metrics,
)
from pipeline.evaluation.tracking_report import draw_tracking, tracking_section
from pipeline.rl.envs import SoftArmReachEnv, default_linear_lag_params, linear_lag_plant, task
from pipeline.rl.envs.factory import observation_options
from pipeline.rl.envs.learned import make_env_params
from pipeline.rl.envs.plants import learned_plant
from pipeline.rl.networks import make_network
from pipeline.schemas import AgentConfig, ConfigError, EnvConfig, EvaluationConfig
from pipeline.validation import validate_config

LIMITS = OmegaConf.create({"p_min": 0.0, "p_max": 7.0, "sum_max": 13.0, "preload": 2.0})
SAFE = SafeSet.from_limits(LIMITS)
REST_POSE = jnp.array([0.032, 0.353, 0.202])
RADIUS_MM = 3.0


def linear_lag_tracking(preview):
    """The linear-lag toy arm (4 mm/kPa sideways, half the way to a command each 0.1 s) as a
    tracking env at 2 Hz, settled at the 2 kPa preload at the rest pose."""
    env = SoftArmReachEnv(linear_lag_plant(10.0), 2.0, settle_seconds=2.0, include_error=True,
                          task="track", preview=preview)
    params = make_env_params(env, default_linear_lag_params(), EnvConfig(
        task="track", preview=preview, reset_bank_size=1), key=jax.random.key(0), safe_set=SAFE,
        preload=2.0, rest_pose=REST_POSE, goal_set=REST_POSE[None])
    return env, params


def circle(period_s=20.0, phase_deg=0.0):
    """A circle of RADIUS_MM in x-z around where the toy arm rests at the preload."""
    centre = tuple(float(v) for v in np.asarray(REST_POSE) * 1000.0)
    return R.shape(R.ShapeSettings("circle", centre, RADIUS_MM, period_s=period_s,
                                   phase_deg=phase_deg))


def follow(env, params, controller, carry, reference, seconds=30.0):
    """``[T + 1, 3]`` m path and ``[T + 1, 3]`` m reference of one episode from the settled
    start."""
    steps = round(seconds * env.control_hz)
    goals = task.goal_path(reference, steps, env.control_hz)
    start_carry = jax.tree.map(lambda x: x[0], params.reset_carries)
    positions, _ = jax.jit(lambda: rollouts.rollout(
        env, params, controller, carry, jax.random.key(1), start_carry,
        params.reset_positions[0], goals, reference))()
    times = jnp.arange(steps + 1, dtype=jnp.float32) / env.control_hz
    return np.asarray(positions), np.asarray(R.positions(reference, times))


def mpc_on_the_toy(env, params, settings):
    model_carry, model_start = env.settle(default_linear_lag_params(), REST_POSE, params.preload)
    controller = mpc.mpc_controller(env, params, env.plant, default_linear_lag_params(), settings)
    return controller, mpc.initial_carry(model_carry, model_start, params.preload, settings)


def test_the_horizon_goals_are_the_current_goal_and_the_reference_after_it():
    env, params = linear_lag_tracking(preview=2)
    reference = circle()
    settings = mpc.CEMSettings(horizon=3)
    state = env.start_state(jax.random.key(0), jax.tree.map(lambda x: x[0], params.reset_carries),
                            params.reset_positions[0], task.period_goal(reference, jnp.asarray(4), 2.0),
                            params, reference).replace(time=jnp.asarray(4, jnp.int32))
    goals = np.asarray(mpc.horizon_goals(env, state, settings)) * 1000.0
    # period 4 of a 2 Hz episode ends at 2.5 s, the next two at 3.0 and 3.5 s: on a 20 s lap of
    # a 3 mm circle starting on the x axis, 45, 54 and 63 degrees on
    angles = np.deg2rad([45.0, 54.0, 63.0])
    centre = np.asarray(REST_POSE) * 1000.0
    expected = centre + RADIUS_MM * np.stack([np.cos(angles), np.zeros(3), np.sin(angles)], -1)
    np.testing.assert_allclose(goals, expected, atol=1e-3)
    # reaching: the one goal throughout
    reach = SoftArmReachEnv(linear_lag_plant(10.0), 2.0, settle_seconds=2.0)
    held = mpc.horizon_goals(reach, state.replace(reference=None), settings)
    np.testing.assert_allclose(held, np.broadcast_to(state.goal, (3, 3)))


def test_mpc_follows_a_circle_within_a_bound_when_the_model_is_the_plant():
    env, params = linear_lag_tracking(preview=3)
    reference = circle()
    still, target = follow(env, params, rollouts.preload_controller(env, params), None, reference)
    preload = tracking_metrics(still[None], target[None], 2.0, settle_seconds=10.0)
    # the preload holds the arm at the circle's centre: always one radius away
    assert preload["rmse_mm"][0] == pytest.approx(RADIUS_MM, abs=0.01)
    assert preload["within_1mm"][0] == 0.0
    followed = {}
    for name, settings in {"tracking": TrackingSettings({}).mpc_settings(EvaluationConfig(), env),
                           "reaching's spread": mpc.CEMSettings(horizon=1)}.items():
        controller, carry = mpc_on_the_toy(env, params, settings)
        path, target = follow(env, params, controller, carry, reference)
        followed[name] = tracking_metrics(path[None], target[None], 2.0, settle_seconds=10.0)
    tracked = followed["tracking"]
    # with the tracking settings it keeps within a tenth of the radius, on time; the reaching
    # MPC's spread (2 kPa around the last command) leaves its samples too coarse for that
    assert tracked["rmse_mm"][0] < 0.3 and tracked["within_1mm"][0] == 1.0
    assert abs(tracked["lag_s"][0]) < 0.25
    assert tracked["rmse_mm"][0] < 0.5 * followed["reaching's spread"]["rmse_mm"][0]


def random_gru(seed):
    config = dynamics.DynamicsConfig(hidden=8)
    ones, zeros = jnp.ones(3), jnp.zeros(3)
    normalizer = dynamics.Normalizer(2.0 * ones, ones, REST_POSE, 0.01 * ones, zeros,
                                     0.001 * ones)
    return dynamics.DynamicsParams(dynamics.init_network(jax.random.PRNGKey(seed), config),
                                   normalizer, config)


def untrained_policy(obs_dim, seeds=2):
    network = make_network(AgentConfig(hidden=8), 3)
    init = jax.vmap(lambda key: network.init(key, jnp.zeros((1, 1)), jnp.zeros((1, 1, obs_dim)),
                                             jnp.zeros((1, 1), bool)))
    return Policy(network, init(jax.random.split(jax.random.key(3), seeds)))


def gru_tracking():
    """A tracking env on a small random GRU (the 'learned model'), its settings and a policy."""
    config = EnvConfig(task="track", preview=1, include_error=True, reset_bank_size=2,
                       num_goals=16)
    env = SoftArmReachEnv(learned_plant(10.0), 2.0, settle_seconds=1.0, include_error=True,
                          task="track", preview=1)
    goals = REST_POSE + jnp.array([[0.004, 0.0, 0.0], [-0.004, 0.0, 0.0], [0.0, 0.0, 0.004],
                                   [0.0, 0.0, -0.004]])
    params = make_env_params(env, random_gru(0), config, key=jax.random.key(0), safe_set=SAFE,
                             preload=2.0, rest_pose=REST_POSE, goal_set=goals)
    settings = ClosedLoopSettings(
        evaluation=EvaluationConfig(num_episodes=2, mpc_samples=8, mpc_iterations=1),
        max_steps=4, model_hz=10.0, limits=LIMITS, env=config)
    reach = EnvConfig(include_error=True, reset_bank_size=2, num_goals=16)
    reach_env = SoftArmReachEnv(learned_plant(10.0), 2.0, **observation_options(reach))
    reaching = Reaching(reach, {"ppo_ff": untrained_policy(reach_env.obs_dim, seeds=1)})
    return env, params, settings, {"ppo_ff": untrained_policy(env.obs_dim)}, reaching


SHAPES = {"circle": R.ShapeSettings("circle", None, 2.0, period_s=10.0),
          "eight": R.ShapeSettings("figure_eight", None, 2.0, period_s=10.0)}


def test_the_tracking_tables_have_a_row_for_every_plant_controller_and_reference():
    env, params, settings, policies, reaching = gru_tracking()
    tracking = TrackingSettings(SHAPES, 3.0, 1.0, 50.0, baselines=("preload", "mpc"))
    results = run_tracking(settings, tracking, policies, env, params,
                           models={"model other": random_gru(1)}, reaching=reaching)
    episodes = results["tables"]["tracking_episodes"]
    plants, references = {"learned", "model other"}, {"circle", "eight"}
    controllers = {"ppo_ff": 2, "preload": 1, "mpc": 1, "ppo_ff (reaching)": 1}  # seeds
    assert set(episodes["plant"]) == plants and set(episodes["reference"]) == references
    counts = episodes.groupby(["plant", "controller", "reference"]).size()
    assert len(counts) == 2 * 4 * 2
    for (plant, controller, name), count in counts.items():
        assert count == controllers[controller] * 2, (plant, controller, name)  # x 2 episodes
    assert np.isfinite(episodes["rmse_mm"]).all()
    summary = results["tables"]["tracking"]
    assert len(summary) == 2 * 4 * 2
    # the paths table: 7 periods (3 s at 2 Hz, and the start) of each path, errors as computed
    paths = results["tables"]["tracking_paths"]
    assert len(paths) == 7 * 2 * (2 + 1 + 1 + 1) * 2 * 2  # periods, episodes, paths, plants, refs
    row = paths[(paths.plant == "learned") & (paths.controller == "mpc")
                & (paths.reference == "eight") & (paths.episode == 1) & (paths.period == 6)]
    path = results["paths"][("learned", "mpc", "eight", 0)][1, 6] * 1000.0
    target = results["reference_paths"]["eight"][1, 6] * 1000.0
    np.testing.assert_allclose(row[["x_mm", "y_mm", "z_mm"]].to_numpy()[0], path, rtol=1e-6)
    assert row["error_mm"].iloc[0] == pytest.approx(np.linalg.norm(path - target), rel=1e-6)
    assert row["time_s"].iloc[0] == 3.0
    # the MPC's settings: the evaluation's samples and iterations, a horizon of one period (null:
    # the preview's, preview 1: 2 periods), a spread of 0.25 kPa
    assert tracking.mpc_settings(settings.evaluation, env) == mpc.CEMSettings(
        horizon=1, num_samples=8, num_iterations=1, initial_std_kpa=0.25, per_period=True)
    preview = TrackingSettings(SHAPES, mpc_horizon=None).mpc_settings(settings.evaluation, env)
    assert preview.horizon == 2


def test_a_replayed_path_is_followed_in_stretches_spread_over_the_recordings(tmp_path):
    env, params, settings, policies, _ = gru_tracking()
    # a recording through the goals: 1 mm/s along x from 4 mm short of the rest pose, 10 Hz
    times = np.arange(81) / 10.0
    points = np.asarray(REST_POSE) + np.outer(times - 4.0, [0.001, 0.0, 0.0])
    replay = {"walk": R.ReplaySettings(slow_down=2.0)}
    tracking = TrackingSettings(replay, 3.0, 1.0, 50.0, recorded={"run_a": (times, points)})
    results = run_tracking(settings, tracking, policies, env, params)
    episodes = results["tables"]["tracking_episodes"]
    assert set(episodes["reference"]) == {"walk"} and np.isfinite(episodes["rmse_mm"]).all()
    # 3 s followed and one period previewed (0.5 s) at half speed: 1.75 s of path a stretch;
    # stretches begin at 0 .. 6.2 s (63 samples), the 2 episodes' at samples 0 and 31 (3.1 s)
    target = results["reference_paths"]["walk"] * 1000.0  # [2, 7, 3] mm at 0, 0.5, .. 3 s
    start = np.asarray(REST_POSE) * 1000.0 + [-4.0, 0.0, 0.0]
    for episode, begin_s in enumerate([0.0, 3.1]):
        expected = start + np.outer(begin_s + np.arange(7) * 0.25, [1.0, 0.0, 0.0])
        np.testing.assert_allclose(target[episode], expected, atol=1e-3)
    # every stretch's points are checked before anything runs: a recording's are what it reached,
    # a CSV's must lie near the goals or the recordings (here 1 mm a second from 4 mm short of
    # the rest pose along z, 0.75 mm past the nearest goal 0.75 s into the path)
    csv = tmp_path / "walk.csv"
    rows = [(t, 32.0, 353.0, 198.0 + t) for t in np.arange(0, 8.01, 0.25)]
    csv.write_text("t,x,y,z\n" + "".join(f"{t},{x},{y},{z}\n" for t, x, y, z in rows))
    replayed_csv = {"walk": R.ReplaySettings(file=str(csv), slow_down=2.0)}
    with pytest.raises(ConfigError, match=r"evaluation.references walk \(episode 0\) refused: "
                                          r"its point at t=1.5 s, \[32.0, 353.0, 198.8\] mm, "
                                          r"lies 0.[78] mm"):  # 0.75 in float32
        run_tracking(settings, TrackingSettings(replayed_csv, 3.0, 1.0, 0.6), policies, env,
                     params)
    with pytest.raises(ConfigError, match=r"evaluation.references walk: a replayed path needs "
                                          r"the recordings the goals come from"):
        run_tracking(settings, TrackingSettings(replay, 3.0, 1.0, 50.0), policies, env, params)


def test_cross_model_tracking_runs_in_the_own_and_the_other_model():
    env, params, settings, policies, reaching = gru_tracking()
    tracking = TrackingSettings({"circle": SHAPES["circle"]}, 3.0, 1.0, 50.0,
                                baselines=("preload", "mpc"))
    table = cross_model_tracking(settings, tracking, policies, env, params, random_gru(1),
                                 reaching)
    assert set(table["plant"]) == {"own", "cross"}
    assert set(table["controller"]) == {"ppo_ff", "preload", "mpc", "ppo_ff (reaching)"}
    own, cross = (table[table.plant == p].sort_values(["controller", "seed", "episode"])
                  for p in ("own", "cross"))
    # the two models differ: so do the errors (the same starts, references and controllers)
    assert not np.allclose(own["rmse_mm"].to_numpy(), cross["rmse_mm"].to_numpy())


def test_path_table_by_hand():
    path = np.zeros((3, 3, 3))
    path[:, :, 0] = 0.001 * np.arange(3)  # x: 0, 1, 2 mm
    target = path + np.array([0.0, 0.0, 0.002])  # 2 mm above, all along
    table = path_table({("learned", "mpc", "line", 0): path}, {"line": target}, 2.0, episodes=2)
    assert len(table) == 2 * 3 and set(table["episode"]) == {0, 1}
    np.testing.assert_allclose(table["x_mm"], [0, 1, 2, 0, 1, 2], atol=1e-12)
    np.testing.assert_allclose(table["error_mm"], 2.0)
    np.testing.assert_allclose(table["time_s"], [0, 0.5, 1.0] * 2)
    np.testing.assert_allclose(table["reference_z_mm"], 2.0)


def summary_rows():
    rows = []
    for plant in ("learned", "plant"):
        for controller, rmse in (("preload", 5.0), ("mpc", 0.6), ("ppo_ff", 0.4)):
            rows.append({"plant": plant, "controller": controller, "reference": "circle",
                         "episodes": 4, "median_rmse_mm": rmse, "median_p95_mm": rmse,
                         "median_max_mm": rmse, "within_1mm": 0.5, "median_lag_s": 0.1,
                         "median_offset_mm": rmse / 2, "seed_rmse_min_mm": rmse,
                         "seed_rmse_max_mm": rmse, "at_limits": rmse / 10})
    return pd.DataFrame(rows)


def test_the_tracking_section_shows_every_plant_baseline_and_the_cross_model_rows():
    summary = summary_rows()
    cross = pd.concat([summary.replace({"learned": "own", "plant": "cross"}).assign(
        direction=direction) for direction in ("A->B", "B->A")], ignore_index=True)
    section = tracking_section(summary, None, ["ppo_ff"], 10.0, cross)
    tables = [block.frame for block in section.blocks if hasattr(block, "frame")]
    assert len(tables) == 2
    main, across = tables
    assert list(main["controller"]) == ["ppo_ff", "mpc", "preload"] * 2
    assert set(main["plant"]) == {"learned model", "simulated arm"}
    assert "RMSE [mm]" in main.columns and "lag [s]" in main.columns
    assert list(main["steady offset [mm]"]) == [0.2, 0.3, 2.5] * 2
    np.testing.assert_allclose(main["time at the limits"], [0.04, 0.06, 0.5] * 2)
    assert len(across) == 12 and set(across["plant"]) == {"own model", "other model"}


def test_the_tracking_drawing_shows_the_policies_and_baselines_but_not_the_preload():
    import matplotlib

    matplotlib.use("Agg")
    path = np.zeros((2, 5, 3))
    path[..., 0] = np.linspace(0, 0.004, 5)
    target = path + 0.001
    paths = path_table({(plant, controller, "circle", 0): path
                        for plant in ("learned", "plant")
                        for controller in ("ppo_ff", "mpc", "preload")}, {"circle": target}, 2.0)
    fig = draw_tracking(paths, plants=["plant"], spread=True)
    plane, error = fig.axes
    assert [line.get_label() for line in plane.lines] == ["reference", "ppo_ff", "mpc"]
    np.testing.assert_allclose(error.lines[0].get_ydata(), np.sqrt(3.0))  # 1 mm on each axis


@pytest.mark.parametrize("overrides, words", [
    (["evaluation.tracking_baselines=[preload,random]"],
     r"evaluation\.tracking_baselines: unknown \['random'\]"),
    (["evaluation.tracking_mpc_horizon=0"], r"evaluation\.tracking_mpc_horizon=0 must be >= 1"),
])
def test_bad_tracking_baselines_are_refused_by_name(make_cfg, overrides, words):
    with pytest.raises(ConfigError, match=words):
        validate_config(make_cfg("experiment=tracking", *overrides))


def test_reaching_keys_ignore_the_tracking_baselines(make_cfg):
    from pipeline import keys

    plain = keys.key("evaluate", make_cfg())
    assert keys.key("evaluate", make_cfg("evaluation.tracking_mpc_horizon=5")) == plain
    tracking = keys.key("evaluate", make_cfg("experiment=tracking"))
    assert keys.key("evaluate", make_cfg("experiment=tracking",
                                         "evaluation.tracking_mpc_horizon=5")) != tracking


TINY = ["experiment=[quick,tracking]", "robot.num_runs=2", "exploration.num_steps=40",
        "agent.num_seeds=1", "agent.total_timesteps=4096", "agent.num_evals=1",
        "evaluation.num_episodes=4", "evaluation.consecutive_episodes=2",
        "model.num_steps=20", "model.eval_every=10", "model.checkpoint_every=10",
        "dataset.window=32", "dataset.train_fraction=0.5", "env.max_steps=8",
        "evaluation.tracking_seconds=8", "evaluation.tracking_settle_seconds=2",
        "evaluation.reachable_tolerance_mm=50", "evaluation.mpc_samples=8",
        "evaluation.mpc_iterations=1", "evaluation.reaching=false"]


@pytest.mark.slow  # trains and evaluates a tiny tracking chain: runs with `make test-all`
def test_the_chain_tracks_with_the_mpc_and_the_figures_command_draws_it(make_cfg, tmp_path):
    from experiments.paper_figures import main
    from pipeline.__main__ import run

    cfg = make_cfg(*TINY, "evaluation.policies=[ppo_ff]")
    artifact = run(cfg)["evaluate"]
    summary = pd.read_parquet(artifact.file("tracking.parquet"))
    assert set(summary["controller"]) == {"ppo_ff", "preload", "mpc"}
    assert set(summary["plant"]) == {"learned", "plant"}
    assert np.isfinite(summary["median_rmse_mm"]).all()
    paths = pd.read_parquet(artifact.file("tracking_paths.parquet"))
    assert len(paths) == 2 * 3 * 2 * 4 * 17  # plants, controllers, references, episodes, periods
    markdown = artifact.file("report.md").read_text()
    assert "## Tracking" in markdown and "| mpc |" in markdown
    assert "tracking/plant/mpc/circle" in artifact.manifest["summary"]

    out = tmp_path / "figures"
    output_dir = str(cfg.paths.output_dir)
    main(["--out", str(out), "--output-dir", output_dir, "--only", "tracking",
          "--tracking-set", *TINY, "evaluation.policies=[ppo_ff]"])
    assert (out / "tracking_paths_and_error.png").stat().st_size > 10_000
    captions = (out / "captions.md").read_text()
    assert "Tracking on the simulated arm" in captions and "mpc" in captions
    # another config's tracking evaluation has not run: skipped, nothing drawn
    main(["--out", str(tmp_path / "none"), "--output-dir", output_dir, "--only", "tracking",
          "--tracking-set", *TINY, "evaluation.policies=[ppo_ff]", "evaluation.seed=1"])
    assert not (tmp_path / "none" / "tracking_paths_and_error.png").exists()


def test_the_cross_model_protocol_reads_each_groups_reaching_policies(make_cfg, tmp_path):
    from pipeline import keys
    from pipeline.chain import reaching_configs

    data = tmp_path / "runs"
    data.mkdir()
    for number in range(4):
        (data / f"Step_control_{number:02d}.csv").write_text(f"t\n{number}\n")
    robot = ["robot=sorolex_csv", f"robot.data_dir={data}"]
    _, inputs = keys.evaluate_spec(make_cfg("experiment=tracking", *robot))
    group_b = make_cfg("experiment=tracking", *robot,
                       "robot.files=[Step_control_01.csv,Step_control_03.csv]")
    assert set(reaching_configs(group_b)) == {"apg", "apg_rnn"}
    for name, variant in reaching_configs(group_b).items():
        assert inputs[f"cross_model/B->A/reaching/train_ppo/{name}"] == keys.key("train_ppo",
                                                                                 variant)
    # reaching has no reaching baseline, in the protocol or outside it
    _, plain = keys.evaluate_spec(make_cfg(*robot))
    assert any(name.startswith("cross_model/") for name in plain)
    assert not any("reaching/" in name for name in plain)
