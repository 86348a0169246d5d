"""Evaluation: rollouts on the simulated plant under vmap, and the report of a tiny run."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from pipeline.__main__ import run
from pipeline.evaluation import closed_loop, rollouts
from pipeline.evaluation.closed_loop import rollout_program
from pipeline.evaluation.metrics import episode_metrics
from pipeline.infra.parquet import read_metadata
from pipeline.stages._environment import config_environment


def test_plant_rollouts_under_vmap_match_single_ones(make_cfg):
    cfg = make_cfg("env=sim", "env.num_goals=16", "env.reset_bank_size=4", "env.max_steps=6")
    env, _, params = config_environment(cfg)
    goals = jnp.broadcast_to(params.goal_set[:3, None], (3, 6, 3))
    starts = (jax.tree.map(lambda x: x[:3], params.reset_carries), params.reset_positions[:3])
    keys = jax.random.split(jax.random.key(0), 3)
    hold_preload = rollouts.preload_controller(env, params)
    random = rollouts.random_controller()

    def one(controller, key, carry, position, goal_path):
        return rollouts.rollout(env, params, controller, jnp.zeros(()), key, carry, position,
                                goal_path)

    batched = jax.jit(jax.vmap(lambda *a: one(random, *a)))(keys, *starts, goals)
    single = jax.jit(lambda *a: one(random, *a))(keys[1], jax.tree.map(lambda x: x[1], starts[0]),
                                                 starts[1][1], goals[1])
    np.testing.assert_allclose(batched[0][1], single[0], atol=1e-6)
    np.testing.assert_allclose(batched[1][1], single[1], atol=1e-6)
    assert batched[0].shape == (3, 7, 3) and batched[1].shape == (3, 6, 3)
    # the random commands reached the plant projected onto the safe set
    p = np.asarray(batched[1])
    assert (p >= 0).all() and (p <= 7).all() and (p.sum(-1) <= 13).all() and p.std() > 0.5

    # holding the preload keeps a settled arm where it rests: its distance to the goal stays put
    positions, commands = jax.jit(jax.vmap(lambda *a: one(hold_preload, *a)))(keys, *starts, goals)
    np.testing.assert_allclose(commands, 2.0, atol=1e-5)
    metrics = episode_metrics(np.asarray(positions), np.asarray(goals[:, 0]), np.asarray(commands),
                              cfg.robot.limits)
    distance = np.linalg.norm(np.asarray(positions - goals[:, :1]), axis=-1)
    np.testing.assert_allclose(distance[:, -1], distance[:, 0], atol=2e-4)
    assert (metrics["steps_above_limits"] == 0).all() and (metrics["smoothness_kpa"] == 0).all()


def test_controllers_rolled_out_together_match_each_rolled_out_alone(make_cfg):
    """Three kinds in one program (two seeds of a gain controller acting as deployed, the
    random one, the preload), the plant stepped once a period for all: each seed and episode
    is what :func:`rollouts.rollout` gives for it alone, keys and deadband included."""
    cfg = make_cfg("env=sim", "env.num_goals=16", "env.reset_bank_size=4", "env.max_steps=6")
    env, _, params = config_environment(cfg)
    params = params.replace(deadband_m=jnp.asarray(0.004, jnp.float32))  # 4 mm: it acts here
    episodes = 3
    starts = (jax.tree.map(lambda x: x[:episodes], params.reset_carries),
              params.reset_positions[:episodes])
    # the first episode's goal is where it starts: within the deadband from the first period
    targets = params.goal_set[:episodes].at[0].set(starts[1][0])
    goals = jnp.broadcast_to(targets[:, None], (episodes, 6, 3))
    keys = jax.random.split(jax.random.key(0), episodes)

    def gain(gains, env_params):  # pushes along its gains, counting its periods in its carry
        return lambda key, obs, state, count: (count + 1, jnp.tanh(gains * obs[:3]))

    kinds = (rollouts.Kind(gain, deadband=True),
             rollouts.Kind(lambda p, e: rollouts.random_controller()),
             rollouts.Kind(lambda p, e: rollouts.preload_controller(env, e)))
    seeds = jnp.asarray([[0.5, -1.0, 2.0], [-3.0, 1.0, 0.2]])
    together = jax.jit(lambda p: rollouts.rollout_together(
        env, p, kinds, [seeds, jnp.zeros(1), jnp.zeros(1)],
        [jnp.zeros((2, episodes), jnp.int32), jnp.zeros((1, episodes)),
         jnp.zeros((1, episodes))], keys, *starts, goals))(params)
    assert [run[0].shape for run in together] == [(2, episodes, 7, 3), (1, episodes, 7, 3),
                                                  (1, episodes, 7, 3)]

    def one(controller, deadband):  # one program per kind, every seed and episode its input
        return jax.jit(lambda p, gains, key, carry, start, goal: rollouts.rollout(
            env, p, controller(gains), jnp.zeros((), jnp.int32), key, carry, start, goal,
            deadband=deadband))

    programs = (one(lambda gains: gain(gains, params), True),
                one(lambda _: rollouts.random_controller(), False),
                one(lambda _: rollouts.preload_controller(env, params), False))

    def alone(number, gains, episode):
        return programs[number](params, gains, keys[episode],
                                jax.tree.map(lambda x: x[episode], starts[0]),
                                starts[1][episode], goals[episode])

    held = 0
    for episode in range(episodes):
        for seed in range(2):
            positions, commands = alone(0, seeds[seed], episode)
            np.testing.assert_allclose(together[0][0][seed, episode], positions, atol=1e-6)
            np.testing.assert_allclose(together[0][1][seed, episode], commands, atol=1e-5)
            held += int((np.abs(np.diff(np.asarray(commands), axis=0)).max(-1) < 1e-6).sum())
        for number in (1, 2):
            positions, commands = alone(number, seeds[0], episode)
            np.testing.assert_allclose(together[number][0][0, episode], positions, atol=1e-6)
            np.testing.assert_allclose(together[number][1][0, episode], commands, atol=1e-5)
    assert held > 0  # the deadband kept some command
    # the random kind's commands differ from the gain seeds': each kind acts on its own
    assert np.abs(np.asarray(together[1][1][0]) - np.asarray(together[0][1][0])).max() > 0.1


TINY = ["experiment=quick", "robot.num_runs=2", "exploration.num_steps=40",
        "agent.num_seeds=1", "agent.total_timesteps=4096", "agent.num_evals=1",
        "evaluation.num_episodes=4", "evaluation.consecutive_episodes=2",
        "evaluation.baselines=[preload,mpc]", "evaluation.mpc_samples=8",
        "evaluation.mpc_iterations=1", "model.num_steps=20", "model.eval_every=10",
        "model.checkpoint_every=10", "dataset.window=32", "dataset.train_fraction=0.5"]


@pytest.mark.slow  # every stage for real, about 85 s cold; each stage has fast tests of its own
def test_the_whole_chain_runs_through_the_real_stages_into_a_report(make_cfg, monkeypatch):
    cfg = make_cfg(*TINY)
    results = run(cfg)  # collect -> align -> fit_model -> train_ppo (both types) -> evaluate
    assert list(results) == ["collect", "align", "fit_model", "train_ppo", "evaluate"]
    tables = sorted(Path(cfg.paths.artifact_dir).glob("*/[!.]*/*.parquet"))
    assert len(tables) >= 12
    for table in tables:  # every table says what it holds, in which units, made by what
        metadata = read_metadata(table)
        assert {"schema", "units", "config", "provenance"} <= set(metadata), table
        assert metadata["units"], table
    artifact = results["evaluate"]
    markdown = artifact.file("report.md").read_text()
    for section in ("Summary", "Configuration", "Data", "Model accuracy", "Policy results",
                    "Baselines",
                    "Plant gap", "Time to a controller", "Consecutive goals"):
        assert f"## {section}" in markdown, section
    # the report opens with its one summary, and that with the table the run printed at its end:
    # one row per controller and plant, the apg row with its one seed's 4 episodes
    first = markdown.split("\n## ")[1]
    assert first.startswith("Summary\n") and markdown.count("## Summary") == 1
    printed = first.split("\n\n")[2]  # after the heading and the table's caption
    assert printed.startswith(
        "| controller | plant | median_final_mm | within_1mm_% | seeds | episodes |")
    assert printed.count("| apg |") == 2 and "| 1 | 4 |" in printed
    # every artifact of the chain says how long it took to build; the policies split theirs
    for stage in ("collect", "align", "fit_model", "train_ppo"):
        built = results[stage].manifest["build_seconds"]
        assert built is not None and built > 0, stage
    assert artifact.manifest["build_seconds"] > 0
    timing = markdown.split("## Time to a controller")[1].split("\n## ")[0]
    for stage in ("collect", "align", "fit_model", "train_ppo (apg)", "train_ppo (apg_rnn)",
                  "evaluate (until this report)"):
        assert f"| {stage} |" in timing, stage
    assert "| devices |" in timing  # the cores the seeds were split over (one in the tests)
    page = artifact.file("report.html").read_text()
    assert page.count("<img") >= 6  # upstream figures linked, and this stage's own
    for image in ("returns.png", "distance.png", "trajectories.png"):
        assert artifact.file(f"figures/{image}").stat().st_size > 10_000

    summary = pd.read_parquet(artifact.file("summary.parquet"))
    assert set(summary["plant"]) == {"learned", "plant"}
    assert set(summary["controller"]) == {"apg", "apg_rnn", "preload", "mpc"}
    assert (summary["time_above_limits"] == 0).all()
    # the hold after the first arrival, in the summary and per episode
    assert {"arrived_1mm", "held_arrivals", "within_1mm_after_arrival",
            "median_max_after_arrival_mm"} <= set(summary.columns)
    assert "| ever ≤ 1 mm | of those: final ≤ 1.5 mm |" in markdown
    episodes = pd.read_parquet(artifact.file("episodes.parquet"))
    assert {"within_1mm_after_arrival", "max_after_arrival_mm", "held_1.5mm"} <= set(episodes)
    assert len(episodes) == 2 * 4 * 4  # plants x controllers (one seed each) x episodes
    gap = pd.read_parquet(artifact.file("plant_gap.parquet"))
    assert len(gap) == 4 * 4 and np.isfinite(gap["final_gap_mm"]).all()

    # the same policies in another fitted model (cross-model): here the fitted model itself,
    # as a separate plant with its own settled starts, same goals and observation
    model = results["fit_model"]
    cfg.stage, cfg.evaluation.models = "evaluate", [str(model.path)]
    built = []  # the environment of every rollout program compiled

    def counting(env, kinds):
        built.append((env, len(kinds)))
        return rollout_program(env, kinds)

    monkeypatch.setattr(closed_loop, "rollout_program", counting)
    crossed = run(cfg)["evaluate"]
    # the other model runs the learned env's program: one per environment, every controller
    # in it
    # (the consecutive goals, without the preload, in another per environment)
    assert len(built) == 4 and len({id(env) for env, _ in built}) == 2
    assert [kinds for _, kinds in built] == [4, 4, 3, 3]
    assert crossed.key != artifact.key
    summary = pd.read_parquet(crossed.file("summary.parquet"))
    other = f"model {model.key}"
    assert set(summary["plant"]) == {"learned", "plant", other}
    in_model = summary.set_index(["plant", "controller"])["median_final_mm"]
    for controller in ("apg", "apg_rnn", "preload", "mpc"):
        assert np.isfinite(in_model[(other, controller)])
        # its own model, settled from the same rest poses: exactly the learned env's figure
        # (before, the other model settled again from the learned env's settled starts, which
        # a model that drifts at the preload had already moved)
        assert in_model[(other, controller)] == pytest.approx(in_model[("learned", controller)],
                                                              rel=1e-4, abs=1e-4)
