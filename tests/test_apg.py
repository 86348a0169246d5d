"""Analytic policy gradients through the environment, and training that stops when good enough."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pipeline import keys
from pipeline.infra.artifacts import artifact_key
from pipeline.rl.apg import differentiable_env, make_train_program, rollout_window
from pipeline.rl.envs import SoftArmReachEnv
from pipeline.rl.networks import initial_hidden, make_network
from pipeline.rl.ppo import make_train_program as make_ppo_program
from pipeline.rl.training import (
    Build,
    RunnerState,
    check_same_variables,
    has_distance,
    held_out_figures,
    train_seeds,
)
from pipeline.schemas import AgentConfig, ConfigError, StopAt, Trainer
from pipeline.validation import validate_config
from tests.test_ppo import toy_reaching


def window_loss(env, params_env, agent, key):
    """The loss of one APG window from fresh resets, as a function of the policy variables."""
    network = make_network(agent, 3)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(
        jax.random.split(key, agent.num_envs), params_env)
    variables = network.init(key, initial_hidden(network, agent.num_envs), obs[None],
                             jnp.zeros((1, agent.num_envs), bool))

    def loss(variables, env_for_steps):
        build = Build(agent, env_for_steps, network, np.full(3, -1.0, np.float32),
                      np.ones(3, np.float32), (obs.shape[-1],),
                      has_distance(env, params_env))
        runner = RunnerState(None, state, obs, jnp.ones(agent.num_envs, bool),
                             initial_hidden(network, agent.num_envs),
                             jnp.zeros(agent.num_envs), jnp.zeros(agent.num_envs, jnp.int32),
                             key)
        _, window = rollout_window(build, variables, runner, key, params_env)
        return -window.reward.mean()

    return variables, loss


def test_the_window_gradient_runs_through_the_environment_and_matches_finite_differences():
    # the loss of a window of 4 control periods on the toy arm: the gradient taken through the
    # environment's step (its copy that keeps transition gradients) is the slope along a random
    # direction of the parameters; the env as PPO steps it detaches its state, so that gradient
    # sees only each step's own action (on the toy's fast lag most of it, not all)
    env, params_env = toy_reaching()
    agent = AgentConfig(num_envs=8, num_steps=4, hidden=16, trainer="apg")
    variables, loss = window_loss(env, params_env, agent, jax.random.PRNGKey(2))
    direction = jax.tree.map(lambda x: jax.random.normal(jax.random.PRNGKey(x.size), x.shape),
                             variables)
    through = differentiable_env(env)
    epsilon = 1e-3
    plus = loss(jax.tree.map(lambda v, d: v + epsilon * d, variables, direction), through)
    minus = loss(jax.tree.map(lambda v, d: v - epsilon * d, variables, direction), through)
    finite = float(plus - minus) / (2 * epsilon)

    def slope(env_for_steps):
        grads = jax.grad(loss)(variables, env_for_steps)
        return float(sum(jnp.vdot(g, d) for g, d in zip(jax.tree.leaves(grads),
                                                       jax.tree.leaves(direction))))

    through_error, detached_error = abs(slope(through) - finite), abs(slope(env) - finite)
    assert abs(finite) > 1e-3
    assert through_error < 0.01 * abs(finite)
    assert detached_error > 5 * through_error


def test_an_environment_without_transition_gradients_is_refused_by_name():
    class Opaque(SoftArmReachEnv):
        _supports_transition_gradients = False

    env, params = toy_reaching()
    opaque = Opaque(env.plant, env.control_hz, settle_seconds=1.0, include_last_action=True)
    agent = AgentConfig(num_seeds=1, num_envs=4, num_steps=2, total_timesteps=16, num_evals=1,
                        eval_envs=0, trainer="apg")
    with pytest.raises(ConfigError, match="SoftArmReach-linear_lag is not"):
        make_train_program(agent, opaque, params)


@pytest.mark.slow  # among the longest of the suite: runs with `make test-all`
def test_tiny_apg_run_reaches_goals_on_the_toy_arm_with_ppo_s_network():
    env, params = toy_reaching()
    agent = AgentConfig(num_seeds=2, num_envs=16, num_steps=5, total_timesteps=16 * 5 * 40,
                        num_evals=2, eval_envs=32, hidden=32, lr=3e-3, max_grad_norm=1.0,
                        trainer="apg", progress=False)
    output = train_seeds(agent, env, params)
    medians = np.asarray(output.evaluation["median_final_distance_m"])  # [seeds, evals]
    window = np.asarray(output.metrics["window_distance_m"])  # [seeds, updates]
    assert medians.shape == (2, 2) and window.shape == (2, agent.num_updates)
    # the goals lie up to 1 cm from the rest pose; the policy brings them within 2 mm
    assert np.all(medians[:, -1] < 0.002), medians
    assert np.all(window[:, -5:].mean(1) < 0.5 * window[:, :5].mean(1))
    # the same variables as PPO's actor-critic: evaluate and control load it unchanged
    ppo = make_ppo_program(AgentConfig(**{**agent.__dict__, "trainer": "ppo"}), env, params)
    expected = ppo.init(jax.random.PRNGKey(0), params).train_state.params
    check_same_variables(expected, jax.tree.map(lambda x: x[0], output.params), "apg params")


@pytest.mark.slow  # among the longest of the suite: runs with `make test-all`
def test_a_recurrent_policy_trains_through_its_hidden_state():
    env, params = toy_reaching()
    agent = AgentConfig(num_seeds=1, num_envs=8, num_steps=5, total_timesteps=8 * 5 * 30,
                        num_evals=1, eval_envs=16, hidden=16, rnn_hidden=16, recurrent=True,
                        lr=3e-3, max_grad_norm=1.0, trainer="apg", progress=False)
    output = train_seeds(agent, env, params)
    window = np.asarray(output.metrics["window_distance_m"])[0]
    assert np.all(np.isfinite(np.asarray(output.metrics["loss"])))
    assert window[-5:].mean() < 0.7 * window[:5].mean()
    gru = output.params["params"]["gru"]["GRUCell_0"]["hr"]["kernel"]
    assert float(jnp.abs(gru).sum()) > 0


@pytest.mark.parametrize("stop, expected_chunks", [
    (StopAt(median_distance_mm=1000.0), 1),  # any policy is within a metre: the first one
    (StopAt(median_distance_mm=1000.0, consecutive=2), 2),
    (StopAt(median_distance_mm=1e-6), 3),  # never: the whole budget
])
def test_stop_at_ends_training_after_the_chunk_that_reaches_it(stop, expected_chunks):
    env, params = toy_reaching()
    agent = AgentConfig(num_seeds=2, num_envs=8, num_steps=5, total_timesteps=8 * 5 * 6,
                        num_evals=3, eval_envs=8, hidden=8, progress=False, stop_at=stop)
    timings = {}
    output = train_seeds(agent, env, params, timings=timings)
    assert np.asarray(output.evaluation["median_final_distance_m"]).shape == (2, expected_chunks)
    assert np.asarray(output.metrics["timesteps"]).shape == (2, 2 * expected_chunks)
    assert len(timings["chunk_seconds"]) == expected_chunks
    stopped = timings["stopped_at"]
    if expected_chunks == 3:
        assert stopped is None
        return
    last = {k: np.asarray(v)[:, -1] for k, v in output.evaluation.items()}
    median_mm, success = held_out_figures(last)
    assert stopped["evaluation"] == expected_chunks - 1
    assert stopped["timesteps_per_seed"] == expected_chunks * 2 * 40
    assert stopped["median_distance_mm"] == pytest.approx(median_mm, abs=1e-3)
    assert stopped["success_rate"] == pytest.approx(success, abs=1e-3)


def test_held_out_figures_pool_the_seeds_episodes():
    evaluation = {"episode_final_distance_m": np.array([[0.001, 0.003], [0.0002, 0.002]]),
                  "episode_success": np.array([[True, False], [True, False]])}
    # median of 0.2, 1, 2, 3 mm: 1.5 mm; half of the four episodes within the tolerance
    assert held_out_figures(evaluation) == pytest.approx((1.5, 0.5))
    assert StopAt(median_distance_mm=1.5, success_rate=0.5).reached(1.5, 0.5)
    assert not StopAt(median_distance_mm=1.4).reached(1.5, 1.0)
    assert not StopAt(success_rate=0.6).reached(0.1, 0.5)
    assert not StopAt().active


def test_new_agent_settings_at_their_defaults_leave_the_train_key_unchanged(make_cfg):
    spec, _ = keys.train_ppo_spec(make_cfg("agent=ppo_ff"))
    assert "trainer" not in spec["agent"] and "stop_at" not in spec["agent"]
    default = artifact_key(*keys.train_ppo_spec(make_cfg()))
    stopping = artifact_key(*keys.train_ppo_spec(make_cfg("agent.stop_at.median_distance_mm=0.6")))
    apg_spec, _ = keys.train_ppo_spec(make_cfg("agent=apg"))
    assert stopping != default
    assert apg_spec["agent"]["trainer"] == Trainer.apg and apg_spec["agent"]["name"] == "apg"


@pytest.mark.parametrize("overrides, message", [
    (("agent=apg", "env=gymnax"), "env=gymnax is a black box"),
    (("agent.stop_at.median_distance_mm=0",), "agent.stop_at.median_distance_mm=0"),
    (("agent.stop_at.success_rate=1.5",), "agent.stop_at.success_rate=1.5"),
    (("agent.stop_at.success_rate=0.8", "agent.stop_at.consecutive=11"),
     "agent.stop_at.consecutive=11 exceeds agent.num_evals=10"),
    (("agent.stop_at.success_rate=0.8", "agent.eval_envs=0"), "agent.eval_envs=0 must be >= 1"),
])
def test_bad_agent_settings_are_refused_naming_them(make_cfg, overrides, message):
    with pytest.raises(ConfigError, match=message):
        validate_config(make_cfg(*overrides))


def test_the_report_says_where_stop_at_stopped_a_training():
    from pipeline.evaluation.sections import _stopped_at

    assert _stopped_at(None) is None
    stopped = {"evaluation": 3, "timesteps_per_seed": 102400, "seconds": 17.6,
               "median_distance_mm": 0.557, "success_rate": 0.852}
    assert _stopped_at(stopped) == "102400 steps/seed, 17.6 s: 0.557 mm, 85 %"


@pytest.mark.parametrize("composed", ["apg", "ppo_ff"])
@pytest.mark.parametrize("option", ["apg", "apg_rnn", "ppo_ff", "ppo_rnn"])
def test_an_option_is_the_same_agent_chosen_or_laid_over_another(make_cfg, option, composed):
    # evaluate lays an option's file over the composed agent (pipeline.chain.agent_option), which
    # drops the file's defaults: the option says everything that makes its policy type itself
    from pipeline.chain import agent_option

    chosen = make_cfg(f"agent={option}").agent
    laid_over = agent_option(option, make_cfg(f"agent={composed}").agent)
    assert dict(laid_over) == dict(chosen)
    expected = Trainer.apg if option.startswith("apg") else Trainer.ppo
    assert AgentConfig.from_any(laid_over).trainer is expected


def test_an_option_keeps_what_an_experiment_or_a_command_line_set(make_cfg):
    # experiment=real_arm sets the seeds, learning rate and budgets of its (PPO) agent: every
    # option laid over it keeps them, as choosing the option with the experiment does
    from pipeline.chain import agent_option

    composed = make_cfg("experiment=real_arm").agent
    rnn = agent_option("ppo_rnn", composed)
    assert (rnn.trainer, rnn.num_seeds, rnn.lr, rnn.recurrent_total_timesteps) == (
        "ppo", 20, 1.0e-3, 4_000_000)
    apg = agent_option("apg", composed)
    assert dict(apg) == dict(make_cfg("experiment=real_arm", "agent=apg").agent)
    assert (apg.trainer, apg.num_seeds, apg.total_timesteps, apg.num_steps) == (
        "apg", 20, 2_000_000, 10)
    # a setting given on the command line reaches every policy type the run trains
    given = make_cfg("agent.total_timesteps=1000", "agent.num_steps=20").agent
    for option in ("apg", "apg_rnn", "ppo_ff"):
        laid = agent_option(option, given)
        assert (laid.total_timesteps, laid.num_steps) == (1000, 20), option
