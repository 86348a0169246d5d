"""Sweeps compose: agent x seed x exploration grids, and the launcher configs."""

from __future__ import annotations

import subprocess
import sys

import pytest
from hydra import compose, initialize_config_dir
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser

from pipeline.config import PROJECT_ROOT
from tests.conftest import CONF_DIR, compose_config


def expand_sweep(overrides: list[str]) -> list[list[str]]:
    """The jobs Hydra's basic sweeper makes of command-line overrides (cartesian product)."""
    parsed = OverridesParser.create().parse_overrides(overrides)
    batches = BasicSweeper.split_arguments(parsed, max_batch_size=None)
    return [job for batch in batches for job in batch]


def test_agent_and_seed_sweep_composes(tmp_path):
    jobs = expand_sweep(["stage=train_ppo", "agent=ppo_ff,ppo_rnn", "seed=0,1"])
    assert len(jobs) == 4
    configs = [compose_config(tmp_path, *job) for job in jobs]
    assert sorted((c.agent.name, c.agent.recurrent, c.seed) for c in configs) == [
        ("ppo_ff", False, 0), ("ppo_ff", False, 1), ("ppo_rnn", True, 0), ("ppo_rnn", True, 1)]
    assert {c.stage.value for c in configs} == {"train_ppo"}


def test_exploration_sweep_changes_the_policy_key(tmp_path):
    """An exploration sweep reaches train_ppo through the fit_model input key (env=learned)."""
    from pipeline.keys import key

    jobs = expand_sweep(["stage=train_ppo", "exploration.alpha=0.3,0.8",
                         "exploration.beta=0.05,0.15"])
    assert len(jobs) == 4
    keys = {key("train_ppo", compose_config(tmp_path, *job)) for job in jobs}
    assert len(keys) == 4


def test_policy_key_ignores_display_only_settings(tmp_path):
    from pipeline.keys import key

    base = compose_config(tmp_path, "env=gymnax")
    quiet = compose_config(tmp_path, "env=gymnax", "agent.progress=false")
    other_seed = compose_config(tmp_path, "env=gymnax", "seed=1")
    assert key("train_ppo", base) == key("train_ppo", quiet)
    assert key("train_ppo", base) != key("train_ppo", other_seed)


@pytest.mark.parametrize("launcher,target", [
    ("joblib", "JoblibLauncher"),
    ("submitit_local", "LocalLauncher"),
    ("submitit_slurm", "SlurmLauncher"),
])
def test_launcher_configs_compose(tmp_path, launcher, target):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=[f"paths.output_dir={tmp_path}",
                                           f"hydra/launcher={launcher}"],
                      return_hydra_config=True)
    assert cfg.hydra.launcher._target_.endswith(target)
    if launcher == "joblib":
        assert cfg.hydra.launcher.n_jobs == 2  # ours, not the plugin's default (-1)


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["joblib", "submitit_local"])
def test_sweep_runs_with_launcher(tmp_path, launcher):
    """A real multirun: two tiny PPO jobs on Pendulum through the launcher."""
    command = [
        sys.executable, "-m", "pipeline", "-m", f"hydra/launcher={launcher}",
        "stage=train_ppo", "env=gymnax", "agent=ppo_ff,ppo_rnn", f"paths.output_dir={tmp_path}",
        "agent.num_seeds=1", "agent.num_envs=4", "agent.num_steps=8",
        "agent.total_timesteps=64", "agent.num_evals=1", "agent.eval_envs=2",
        "agent.progress=false",
    ]
    result = subprocess.run(command, cwd=PROJECT_ROOT, capture_output=True, text=True,
                            timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    manifests = sorted((tmp_path / "artifacts" / "train_ppo").glob("*/artifact.json"))
    assert len(manifests) == 2
