"""The CPU's cores (or the GPUs) as JAX devices: PPO's seeds and the evaluation's episodes split
over them.

JAX fixes its CPU device count when it starts, so each check with several CPU devices runs in a
process of its own.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from pipeline.config import PROJECT_ROOT
from pipeline.infra import devices
from pipeline.infra.devices import configure_cpu_devices, split_count, usable_cores
from pipeline.schemas import ConfigError


def run_python(code: str, **env: str) -> dict:
    """Run ``code`` in a fresh interpreter (tests/ importable); it prints one JSON line."""
    environment = {k: v for k, v in os.environ.items() if k != "JAX_NUM_CPU_DEVICES"}
    environment.update(env, PYTHONPATH=str(PROJECT_ROOT))
    result = subprocess.run([sys.executable, "-c", textwrap.dedent(code)],
                            cwd=PROJECT_ROOT / "tests", env=environment, capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_one_cpu_device_per_core_unless_told_otherwise():
    report = run_python("""
        import json
        from pipeline.infra.devices import configure_cpu_devices
        asked = configure_cpu_devices(None)
        import jax
        started = jax.local_device_count()
        again = configure_cpu_devices(started + 1)  # JAX is running: the count stays
        print(json.dumps({"asked": asked, "started": started, "after": jax.local_device_count()}))
    """)
    assert report["asked"] == report["started"] == report["after"] == usable_cores()
    assert run_python("""
        import json
        from pipeline.infra.devices import configure_cpu_devices
        configure_cpu_devices(None)
        import jax
        print(json.dumps({"devices": jax.local_device_count()}))
    """, JAX_NUM_CPU_DEVICES="3") == {"devices": 3}  # the caller's setting is kept


def test_a_batch_is_split_over_the_most_devices_that_divide_it():
    # 20 seeds (experiment=real_arm): 2 on each of 10 of 16 CPU devices, 4 on each of 5 of 8
    # GPUs, 5 on each of 4 GPUs; 4 seeds (the default) on 3 GPUs: 2 on each of 2; 3 on 2: none
    assert [split_count(20, n) for n in (1, 2, 3, 4, 8, 16)] == [1, 2, 2, 4, 5, 10]
    assert [split_count(4, n) for n in (1, 2, 3, 4, 8)] == [1, 2, 2, 4, 4]
    assert split_count(3, 2) == 1
    assert split_count(7, 8) == 7 and split_count(1, 8) == 1


class FakeGpu:
    """What a Mesh needs of a device to be built: a stand-in for a CUDA device."""

    platform = "gpu"

    def __init__(self, index: int):
        self.id = index

    def __repr__(self) -> str:
        return f"cuda:{self.id}"


def test_the_split_is_over_the_default_backends_devices_so_over_several_gpus(monkeypatch):
    import jax

    gpus = [FakeGpu(i) for i in range(8)]
    monkeypatch.setattr(jax, "local_devices", lambda *args, **kwargs: gpus)
    split = devices.batch_split(20)
    assert list(split.mesh.devices) == gpus[:5]  # 4 seeds on each of the first 5 GPUs
    assert split.mesh.axis_names == (devices.AXIS,)
    assert devices.batch_split(3).mesh.size == 3
    monkeypatch.setattr(jax, "local_devices", lambda *args, **kwargs: gpus[:1])
    assert devices.batch_split(20) is None  # one GPU: nothing to split


def test_eight_cpu_devices_split_as_computed_by_hand():
    assert run_python("""
        import json
        from pipeline.infra.devices import batch_split
        print(json.dumps([batch_split(n) and batch_split(n).mesh.size for n in (20, 12, 9, 1)]))
    """, JAX_NUM_CPU_DEVICES="8") == [5, 6, 3, None]


def test_a_device_count_below_one_is_refused_naming_the_key():
    with pytest.raises(ConfigError, match="cpu_devices"):
        configure_cpu_devices(0)


@pytest.mark.slow  # about 45 s on 2 cores: a subprocess with two CPU devices compiles it all
def test_seeds_and_episodes_split_over_two_devices_give_the_same_results():
    report = run_python("""
        import json
        import jax, jax.numpy as jnp, numpy as np
        import pipeline.evaluation.closed_loop as closed_loop
        import pipeline.rl.training as training
        from pipeline.schemas import AgentConfig
        from pipeline.evaluation import rollouts
        from pipeline.rl.networks import make_network
        from pipeline.infra.devices import batch_split
        from test_ppo import toy_reaching

        env, params = toy_reaching()
        agent = AgentConfig(num_seeds=4, num_envs=8, num_steps=5, total_timesteps=8 * 5 * 4,
                            num_evals=2, eval_envs=0, hidden=8, lr=1e-3, progress=False)
        timings = {}
        split = training.train_seeds(agent, env, params, timings=timings)
        devices = {len(leaf.sharding.device_set) for leaf in jax.tree.leaves(split.params)}

        starts = closed_loop._starts(params, 6)
        goals = jnp.broadcast_to(params.goal_set[:6, None], (6, 10, 3))
        keys = jax.random.split(jax.random.key(0), 6)
        network = make_network(agent, 3)
        controllers = closed_loop.Controllers(
            lambda p, env_params: rollouts.policy_controller(network, p), split.params,
            (jnp.zeros((4, 6, 1, 1)), jnp.ones((4, 6), bool)))
        runs = [closed_loop._Programs().run(env, params, {"ppo_ff": controllers}, keys, starts,
                                            goals)["ppo_ff"]]
        training.batch_split = closed_loop.batch_split = lambda size: None  # one device
        whole = training.train_seeds(agent, env, params)
        runs.append(closed_loop._Programs().run(env, params, {"ppo_ff": controllers}, keys,
                                                starts, goals)["ppo_ff"])
        print(json.dumps({
            "parts": [batch_split(n) and batch_split(n).mesh.size for n in (3, 4, 6)],
            "devices": sorted(devices), "timed_devices": timings["devices"],
            "params": max(float(np.max(np.abs(a - b))) for a, b in zip(
                jax.tree.leaves(split.params), jax.tree.leaves(whole.params))),
            "loss": float(np.max(np.abs(split.metrics["total_loss"]
                                        - whole.metrics["total_loss"]))),
            "positions": float(np.max(np.abs(runs[0][0] - runs[1][0]))),
            "commands": float(np.max(np.abs(runs[0][1] - runs[1][1]))),
            "moved": float(np.max(np.abs(runs[0][0][:, :, -1] - runs[0][0][:, :, 0])))}))
    """, JAX_NUM_CPU_DEVICES="2")
    assert report["parts"] == [None, 2, 2]  # 3 seeds stay on one device
    assert report["devices"] == [2]  # the trained seeds live on both devices
    assert report["timed_devices"] == 2  # and train_ppo's summary says so
    # the same training and rollouts, to float rounding
    assert report["params"] < 1e-5 and report["loss"] < 1e-4
    assert report["positions"] < 1e-7 and report["commands"] < 1e-5
    assert report["moved"] > 1e-4  # the rollouts did move the arm


@pytest.mark.slow  # among the longest of the suite: runs with `make test-all`
def test_model_members_split_over_two_devices_train_as_in_one_batch():
    report = run_python("""
        import json
        import jax, numpy as np
        import pipeline.dynamics.cv as model_cv
        from pipeline.infra.devices import batch_split
        from test_model_cv import TINY, lag_runs

        runs = lag_runs()  # 3 runs: 3 folds and the model on all runs
        members = model_cv.cv_members([r.run_id for r in runs], (0,), final=True)
        parts = []
        model_cv.batch_split = lambda size: parts.append(batch_split(size)) or parts[-1]
        split, split_losses = model_cv.fit_members(runs, members, TINY, window=8, progress=False)
        model_cv.batch_split = lambda size: None  # one device
        whole, whole_losses = model_cv.fit_members(runs, members, TINY, window=8, progress=False)
        print(json.dumps({
            "members": len(members), "parts": parts[0].mesh.size,
            "params": max(float(np.max(np.abs(a - b))) for p, q in zip(split, whole)
                          for a, b in zip(jax.tree.leaves(p.network), jax.tree.leaves(q.network))),
            "losses": float(np.max(np.abs(split_losses - whole_losses))),
            "trained": float(np.min(np.abs(whole_losses[:, -1] - whole_losses[:, 0])))}))
    """, JAX_NUM_CPU_DEVICES="2")
    assert report["members"] == 4 and report["parts"] == 2  # two members on each core
    # the same training, to float rounding
    assert report["params"] < 1e-5 and report["losses"] < 1e-5
    assert report["trained"] > 1e-3  # every member's loss did move
