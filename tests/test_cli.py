"""The command line: a short --help that names the stages, and a mistyped key called unknown."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from pipeline.chain import STAGES
from pipeline.cli import unknown_key_message
from pipeline.config import PROJECT_ROOT


def _python(*args: str) -> subprocess.CompletedProcess:
    """``python *args`` in the project, without the caller's JAX_* settings."""
    env = {key: value for key, value in os.environ.items() if not key.startswith("JAX_")}
    env["PYTHONPATH"] = str(PROJECT_ROOT)
    return subprocess.run([sys.executable, *args], capture_output=True, text=True,
                          cwd=PROJECT_ROOT, env=env, timeout=120)


def _pipeline(*args: str) -> subprocess.CompletedProcess:
    return _python("-m", "pipeline", *args)


def test_help_names_the_stages_and_groups_in_under_40_lines():
    done = _pipeline("--help")
    assert done.returncode == 0, done.stderr
    text = done.stdout
    assert len(text.strip().splitlines()) < 40, text
    for stage in STAGES:
        assert f"  {stage.value} " in text, stage
    for line in ("agent:", "ppo_ff, ppo_rnn", "robot:", "sorolex_csv", "experiment:", "quick"):
        assert line in text, line
    assert "base_" not in text
    assert "make setup run" in text and "make test" in text
    assert "artifacts" in text and "report.html" in text


def test_a_mistyped_key_is_called_unknown_with_close_matches():
    message = unknown_key_message(["agent.lrr=0.1", "robot=sorolex_csv"])
    assert "Unknown config key 'agent.lrr'" in message and "agent.lr" in message
    assert "+agent" not in message
    message = unknown_key_message(["agnet.num_seeds=2"])
    assert "did you mean agent.num_seeds?" in message
    assert unknown_key_message(["agent.lr=0.1", "agent=ppo_rnn", "+foo=1", "seed=3"]) is None
    # a key that only one robot's schema has is known with that robot only
    assert unknown_key_message(["robot.physics.bend_gain=0.1"]) is None
    assert "robot.physics.bend_gain" in unknown_key_message(["robot=sorolex_csv",
                                                              "robot.physics.bend_gain=0.1"])


def test_the_command_line_exits_with_that_message():
    done = _pipeline("stage=collect", "exploration.alpah=0.5")
    assert done.returncode == 1
    assert "Unknown config key 'exploration.alpah'" in done.stderr
    assert "exploration.alpha" in done.stderr and "+exploration" not in done.stderr


def test_the_entry_point_and_the_guard_start_without_jax():
    """Composing, keying and the command checks are NumPy: a run that reuses its artifact, or the
    guard between a controller and the valves, does not load JAX for them."""
    done = _python("-c", "import sys, pipeline.__main__, pipeline.keys, pipeline.stages.guard, "
                   "pipeline.ros2.guard; print(sorted(m for m in sys.modules if m == 'jax' "
                   "or m.startswith(('jax.', 'distrax', 'tensorflow_probability'))))")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


@pytest.mark.slow  # two pipeline processes
def test_stages_that_reuse_the_simulated_arms_collection_start_without_jax(tmp_path):
    """Only simulating the arm needs JAX: align, on a collection already recorded, runs without."""
    script = ("import sys\n"
              "from pipeline.__main__ import run\n"
              "from pipeline.config import compose\n"
              f"run(compose('paths.output_dir={tmp_path}', 'experiment=quick', 'stage=align'))\n"
              "print('jax' in sys.modules)\n")
    first, again = _python("-c", script), _python("-c", script)
    assert first.returncode == 0 and again.returncode == 0, first.stderr + again.stderr
    assert first.stdout.split()[-1] == "True"  # it simulated the arm
    assert again.stdout.split()[-1] == "False"
    assert len(list((tmp_path / "artifacts" / "collect").glob("[!.]*"))) == 1  # reused


def test_the_compilation_cache_reaches_a_jax_imported_before_or_after(tmp_path):
    done = _python(
        "-c",
        "from pipeline.infra.compile_cache import use_compilation_cache\n"
        f"use_compilation_cache({str(tmp_path / 'before')!r}, 0.25)\n"
        "import jax\n"
        "print(jax.config.jax_compilation_cache_dir,\n"
        "      jax.config.jax_persistent_cache_min_compile_time_secs)\n"
        f"use_compilation_cache({str(tmp_path / 'after')!r}, 2.0)\n"
        "print(jax.config.jax_compilation_cache_dir,\n"
        "      jax.config.jax_persistent_cache_min_compile_time_secs)\n")
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [str(tmp_path / "before"), "0.25", str(tmp_path / "after"), "2.0"]
    assert (tmp_path / "before").is_dir() and (tmp_path / "after").is_dir()
