"""Training formulations for holding a reached goal: goals re-drawn within an episode from the
recorded goal set (``goal_mode=data``, as ``experiment=real_arm`` trains), training episodes
longer than the evaluation's (``env.train_max_steps``), and what stays the evaluation's.

Known answers on the linear-lag toy of ``tests/test_robust_env.py`` (five plant steps per
period, three recorded goals).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from pipeline import keys
from pipeline.rl.envs.factory import training_only
from pipeline.schemas import ConfigError, EnvConfig
from pipeline.validation import validate_config
from tests.test_robust_env import GOALS, toy


def _goal_index(goal: jax.Array) -> int:
    """Which of the toy's recorded goals ``goal`` is (fails where it is none of them)."""
    (index,) = np.flatnonzero(np.all(np.isclose(np.asarray(GOALS), np.asarray(goal)), axis=1))
    return int(index)


def test_a_redrawn_recorded_goal_is_the_one_observed_and_scored_next():
    """goal_mode=data, a new goal after every period: after period 1 the state's goal is the
    recorded goal of index ``randint(split(fold_in(key, 2))[0], 0, 3)``; the observation that
    period returns holds that goal (standardized, and in the error ``(goal - position) / 5 mm``),
    and period 2's reward is minus its distance in mm, not the first goal's."""
    env, params = toy(goal_redraw_periods=1, hold_periods=5, goal_tolerance_m=1e-6)
    _, state = env.reset(jax.random.PRNGKey(1), params)
    first = state.goal
    step_keys = jax.random.split(jax.random.PRNGKey(7), 2)
    obs, one, _, _, _ = env.step_env(step_keys[0], state, jnp.array([0.5, -0.5, 0.2]), params)
    index_key, _ = jax.random.split(jax.random.fold_in(step_keys[0], 2))
    expected = int(jax.random.randint(index_key, (), 0, 3))
    assert _goal_index(one.goal) == expected
    np.testing.assert_allclose(obs[3:6], (one.goal - params.obs_mean) / params.obs_scale,
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(obs[6:9], (one.goal - one.position) / 0.005, rtol=1e-5,
                               atol=1e-5)
    _, two, reward, terminated, info = env.step_env(step_keys[1], one, jnp.zeros(3), params)
    to_new = 1000.0 * float(jnp.linalg.norm(one.goal - two.position))
    assert float(reward) == pytest.approx(-to_new, rel=1e-5)
    assert float(info["distance_m"]) * 1000.0 == pytest.approx(to_new, rel=1e-5)
    if _goal_index(one.goal) != _goal_index(first):  # the first goal's distance differs
        assert abs(float(reward) + 1000.0 * float(jnp.linalg.norm(first - two.position))) > 0.1
    assert not bool(terminated)


def test_reach_hold_reach_again_with_recorded_goals():
    """Goals every 3 periods, an episode that never ends at a goal (hold_periods 9): a
    controller commanding the pressures whose steady state is the goal in force (the toy's
    ``position = offset + G @ lagged``, solved for the pressure) is within 0.5 mm of each goal
    at the end of its third period, the goals are recorded ones and the episode goes on."""
    env, params = toy(goal_redraw_periods=3, hold_periods=9, max_steps=9, goal_tolerance_m=5e-4)
    gain = np.asarray(params.plant.gain)

    def pressure_for(goal, carry):
        return jnp.asarray(np.linalg.solve(gain, np.asarray(goal - carry.offset)), jnp.float32)

    _, state = env.reset(jax.random.PRNGKey(3), params)
    goals, distances = [], []
    for step_key in jax.random.split(jax.random.PRNGKey(4), 9):
        action = env.action_for(pressure_for(state.goal, state.plant_carry), state.last_pressure,
                                params)
        goals.append(state.goal)
        _, state, _, terminated, info = env.step_env(step_key, state, action, params)
        distances.append(float(info["distance_m"]))
        assert not bool(terminated)
    indices = [_goal_index(goal) for goal in goals]
    assert indices[0:3] == [indices[0]] * 3 and indices[3:6] == [indices[3]] * 3
    assert all(distance < 5e-4 for distance in (distances[2], distances[5], distances[8]))


def test_the_training_horizon_and_redraws_stay_in_training():
    """train_max_steps sets the training parameters' horizon only; the evaluation parameters
    keep max_steps and their goal for the whole episode; unset, nothing changes."""
    env, params = toy(goal_redraw_periods=3, max_steps=5)
    settings = EnvConfig(max_steps=5, goal_redraw_periods=3, train_max_steps=12)
    _, train, evaluation = training_only(settings, env, params, params)
    assert (train.max_steps, evaluation.max_steps) == (12, 5)
    assert (int(train.goal_redraw_periods), int(evaluation.goal_redraw_periods)) == (3, 0)
    _, train, evaluation = training_only(EnvConfig(max_steps=5), env, params, params)
    assert (train.max_steps, evaluation.max_steps) == (5, 5)


def test_training_evaluations_run_the_evaluation_horizon(monkeypatch):
    """The evaluations during training run the evaluation parameters' horizon, not the
    (longer) training episodes'."""
    from pipeline.rl import ppo
    from pipeline.schemas import AgentConfig

    seen = {}
    monkeypatch.setattr(ppo, "_chunk", lambda *args: seen.setdefault("eval_steps", args[5]))
    env, params = toy(max_steps=5)
    program = ppo.make_train_program(AgentConfig(num_envs=4, num_steps=8, total_timesteps=64),
                                     env, params.replace(max_steps=12), params)
    program.chunk(None, 0)
    assert seen["eval_steps"] == 5


def test_the_training_horizon_reaches_the_env_and_the_key_only_where_set(make_cfg):
    from pipeline.stages._environment import config_environment

    base = make_cfg()
    assert "train_max_steps" not in keys.train_ppo_spec(base)[0]["env"]
    assert keys.key("train_ppo", make_cfg("env.train_max_steps=null")) == \
        keys.key("train_ppo", base)
    longer = make_cfg("env=sim", "env.train_max_steps=80", "env.hold_periods=60",
                      "env.num_goals=8", "env.reset_bank_size=2")
    validate_config(longer)
    assert keys.train_ppo_spec(longer)[0]["env"]["train_max_steps"] == 80
    _, train, evaluation = config_environment(longer)
    assert (train.max_steps, evaluation.max_steps) == (80, 40)


@pytest.mark.parametrize("overrides, message", [
    (["env.train_max_steps=0"], r"env.train_max_steps=0 must be an integer >= 1"),
    (["env.train_max_steps=20", "env.hold_periods=21"],
     r"env.hold_periods=21 must be at most env.train_max_steps=20"),
])
def test_unusable_training_horizons_are_refused(make_cfg, overrides, message):
    with pytest.raises(ConfigError, match=message):
        validate_config(make_cfg(*overrides))


# ---- the hold tune: a phase of analytic policy gradients on episodes that never end -------------
class _Folder:
    """What train_into writes into (an ArtifactWriter's ``file``), a plain folder."""

    def __init__(self, path):
        self.path = path

    def file(self, name):
        return self.path / name


def test_the_hold_tune_fine_tunes_the_trained_policies_on_episodes_that_never_end(
        tmp_path, monkeypatch):
    """PPO, then agent.hold_tune: APG from the trained policies (not from scratch) with its own
    step size, window and keys, in the training parameters with hold_periods = the horizon (no
    end at the goal); its evaluations and timesteps follow the trainer's in the tables, marked
    by phase, and its window distance falls."""
    from pipeline.rl.training import seed_keys
    from pipeline.schemas import AgentConfig, HoldTune, Trainer
    from pipeline.stages import _policies
    from tests.test_ppo import toy_reaching

    env, params = toy_reaching()
    agent = AgentConfig(num_seeds=2, num_envs=16, num_steps=10, total_timesteps=16 * 10 * 4,
                        num_evals=2, eval_envs=16, hidden=16, progress=False,
                        hold_tune=HoldTune(steps=16 * 5 * 20, lr=3e-3, window=5))
    calls = []
    train_seeds = _policies.train_seeds

    def spying(agent, env, env_params, eval_params, **kwargs):
        output = train_seeds(agent, env, env_params, eval_params, **kwargs)
        calls.append((agent, env_params, kwargs, output))
        return output

    monkeypatch.setattr(_policies, "train_seeds", spying)
    trained = _policies.train_into(_Folder(tmp_path), "train_ppo", agent, env, params, params,
                                   seed=3, config={}, policy_meta={}, desc="toy",
                                   warm_start=False)
    (first, first_params, first_kwargs, ppo), (tune, holding, kwargs, tuned) = calls
    assert first.trainer is Trainer.ppo and first_kwargs.get("stream", 0) == 0
    assert int(first_params.hold_periods) == 1
    assert (tune.trainer, tune.lr, tune.num_steps, tune.max_grad_norm, tune.timesteps) == (
        Trainer.apg, 3e-3, 5, 1.0, 16 * 5 * 20)
    assert tune.hold_tune == HoldTune() and tune.num_seeds == 2
    assert int(holding.hold_periods) == int(params.max_steps_in_episode) == 10
    assert kwargs["stream"] == 1 and kwargs["seed"] == 3
    assert not np.array_equal(np.asarray(seed_keys(3, 2, 1)), np.asarray(seed_keys(3, 2)))
    jax.tree.map(np.testing.assert_array_equal, kwargs["init_params"], ppo.params)
    window = np.asarray(tuned.metrics["window_distance_m"])  # [seeds, updates]
    assert np.all(window[:, -5:].mean(1) < window[:, :5].mean(1)), window
    evaluation = pd.read_parquet(tmp_path / "evaluation.parquet")
    assert evaluation.groupby("phase")["evaluation"].unique().map(list).to_dict() == {
        "train": [0, 1], "hold_tune": [2, 3]}
    ppo_steps = 16 * 10 * 4
    assert evaluation.loc[evaluation["phase"] == "hold_tune", "timesteps"].min() > ppo_steps
    assert trained.timesteps_per_seed == ppo_steps + 16 * 5 * 20
    metrics = pd.read_parquet(tmp_path / "metrics.parquet")
    assert metrics.groupby("phase")["update"].agg(["min", "max"]).to_dict("index") == {
        "hold_tune": {"min": 4, "max": 4 + 20 - 1}, "train": {"min": 0, "max": 3}}


def test_the_hold_tune_is_in_the_key_only_where_set_and_checked(make_cfg):
    base = keys.train_ppo_spec(make_cfg("experiment=quick"))[0]["agent"]
    assert "hold_tune" not in base  # off: the keys of before
    tuned = keys.train_ppo_spec(make_cfg("experiment=quick", "agent.hold_tune.steps=1000"))
    assert tuned[0]["agent"]["hold_tune"]["steps"] == 1000
    # a policy type with no such phase (the recurrent one here) keeps its key
    rnn = ("experiment=quick", "agent=ppo_rnn")
    assert keys.key("train_ppo", make_cfg(*rnn, "agent.hold_tune.steps=1000",
                                          "agent.hold_tune.recurrent_steps=0")) == \
        keys.key("train_ppo", make_cfg(*rnn))
    assert keys.key("train_ppo", make_cfg(*rnn, "agent.hold_tune.recurrent_steps=1000")) != \
        keys.key("train_ppo", make_cfg(*rnn))
    with pytest.raises(ConfigError, match=r"agent.hold_tune \(analytic policy gradients\) "
                                          r"differentiates through the soft-arm environment"):
        validate_config(make_cfg("experiment=pendulum", "agent.hold_tune.steps=1000"))
    with pytest.raises(ConfigError, match=r"agent.hold_tune=.*window >= 1"):
        validate_config(make_cfg("experiment=quick", "agent.hold_tune.steps=1000",
                                 "agent.hold_tune.window=0"))
