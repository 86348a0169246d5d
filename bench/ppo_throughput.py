"""PPO training throughput in the learned environment: our default next to the paper's setting.

    python -m bench ppo_throughput [--updates 20] [--seeds 1] [--trainer ppo|apg]

- ``default``: this project's defaults — the default model architecture (``model.cell``, a GRU,
  of ``model.hidden`` units with the default input features) at ``dataset.model_hz``, stepped
  model_hz / 2 times per 2 Hz action (zero-order hold), ``agent.num_envs`` environments.
- ``default, GRU policy``: the same environment, the recurrent policy of ``agent=ppo_rnn``.
- ``paper``: the paper's environment — a 1024-unit LSTM (pressures in, no further features)
  stepped once per action, 32 environments.

Same PPO (feed-forward unless named, ``agent.num_steps`` = 32, 4 epochs x 4 minibatches), same run, random
model weights (throughput does not depend on them). ``--trainer apg``: analytic policy gradients
instead, with ``conf/agent/apg.yaml``'s window and step (``apg_rnn``'s for the GRU policy). Each
training is :func:`pipeline.rl.ppo.train_seeds`'s, as the pipeline runs it (the seeds split over
the devices where there are several), without evaluations. Compilation is timed apart;
throughput is environment steps per second of the compiled training program (all seeds
together), and the table gives the ratio of each row to the paper's.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
from omegaconf import OmegaConf

from pipeline.arm.safety import SafeSet
from pipeline.chain import agent_option
from pipeline.dynamics import model as dynamics
from pipeline.dynamics.training import ModelTrainConfig
from pipeline.rl.envs import SoftArmReachEnv, learned_plant, make_env_params
from pipeline.rl.ppo import train_seeds
from pipeline.schemas import AgentConfig, DatasetConfig, EnvConfig, GoalMode, ModelConfig

LIMITS = OmegaConf.create({"p_min": 0.0, "p_max": 7.0, "sum_max": 13.0, "preload": 2.0})
REST_POSE = jnp.array([0.032, 0.353, 0.202])
CONTROL_HZ = 2.0
DEFAULT_MODEL = ModelTrainConfig.from_any(ModelConfig()).architecture()
SETTINGS = {
    # name: (model architecture, model Hz, environments, recurrent policy)
    "default": (DEFAULT_MODEL, DatasetConfig().model_hz, AgentConfig().num_envs, False),
    "default, GRU policy": (DEFAULT_MODEL, DatasetConfig().model_hz, AgentConfig().num_envs,
                            True),
    "paper": (dynamics.DynamicsConfig(hidden=1024, cell="lstm", pressure_transients=()),
              2.0, 32, False),
}


def random_model(config: dynamics.DynamicsConfig) -> dynamics.DynamicsParams:
    ones, zeros = jnp.ones(3), jnp.zeros(3)
    normalizer = dynamics.Normalizer(2.0 * ones, ones, REST_POSE, 0.01 * ones, zeros,
                                     0.01 * ones)
    return dynamics.DynamicsParams(dynamics.init_network(jax.random.PRNGKey(0), config),
                                   normalizer, config)


def throughput_agent(trainer: str, recurrent: bool, num_envs: int, updates: int,
                     seeds: int) -> AgentConfig:
    """The agent of one measurement: ``updates`` updates of ``num_envs`` environments, one
    chunk, no evaluation. PPO: 32 steps per update; APG: its option's window and step."""
    if trainer == "ppo":
        base = AgentConfig(num_steps=32, recurrent=recurrent, rnn_skip=recurrent)
    else:
        option = agent_option("apg_rnn" if recurrent else "apg", OmegaConf.structured(AgentConfig))
        base = AgentConfig.from_any(option)
    return AgentConfig.from_any(base, num_seeds=seeds, num_envs=num_envs,
                                total_timesteps=updates * num_envs * base.num_steps,
                                recurrent_total_timesteps=None, num_evals=1, eval_envs=0,
                                progress=False)


def measure(name: str, updates: int, seeds: int, trainer: str = "ppo") -> dict:
    """Train ``seeds`` seeds of ``trainer`` in setting ``name`` for ``updates`` updates; the
    compile and run seconds and the throughput."""
    architecture, model_hz, num_envs, recurrent = SETTINGS[name]
    env = SoftArmReachEnv(learned_plant(model_hz), CONTROL_HZ, settle_seconds=5.0,
                          include_last_action=True)
    params = make_env_params(env, random_model(architecture),
                             EnvConfig(goal_mode=GoalMode.perturb, reset_bank_size=16),
                             key=jax.random.PRNGKey(0), safe_set=SafeSet.from_limits(LIMITS),
                             preload=2.0, rest_pose=REST_POSE)
    agent = throughput_agent(trainer, recurrent, num_envs, updates, seeds)
    timings: dict = {}
    train_seeds(agent, env, params, timings=timings)
    compile_s, run_s = timings["compile_s"], timings["run_s"]
    steps = seeds * agent.num_updates * agent.steps_per_update
    return {"name": name, "trainer": trainer, "cell": architecture.cell,
            "units": architecture.hidden, "model_steps_per_action": env.steps_per_action,
            "envs": num_envs, "seeds": seeds, "devices": timings["devices"],
            "compile_s": compile_s, "run_s": run_s, "steps_per_s": steps / run_s,
            "model_steps_per_s": steps * env.steps_per_action / run_s}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--updates", type=int, default=20, help="PPO updates per setting")
    parser.add_argument("--seeds", type=int, default=1, help="seeds trained at once (vmap)")
    parser.add_argument("--trainer", choices=["ppo", "apg"], default="ppo")
    args = parser.parse_args(argv)
    rows = [measure(name, args.updates, args.seeds, args.trainer) for name in SETTINGS]
    paper = next(r for r in rows if r["name"] == "paper")
    print(f"{args.trainer.upper()} training throughput, {args.updates} updates, {args.seeds} "
          f"seed(s), {jax.devices()[0].platform}")
    header = (f"{'setting':<21}{'model':>11}{'steps/act':>10}{'envs':>6}{'compile s':>11}"
              f"{'run s':>8}{'env steps/s':>13}{'x paper':>9}{'model steps/s':>15}")
    print(header)
    print("-" * len(header))
    for r in rows:
        model = f"{r['cell']} {r['units']}"
        print(f"{r['name']:<21}{model:>11}{r['model_steps_per_action']:>10}{r['envs']:>6}"
              f"{r['compile_s']:>11.1f}{r['run_s']:>8.2f}{r['steps_per_s']:>13.0f}"
              f"{r['steps_per_s'] / paper['steps_per_s']:>9.2f}{r['model_steps_per_s']:>15.0f}")


if __name__ == "__main__":
    main()
