"""``python -m bench gpu`` where there is no GPU: one line saying so, exit 0, nothing run."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.config import PROJECT_ROOT


def bench_gpu(**env: str) -> tuple[subprocess.CompletedProcess, float]:
    environment = {k: v for k, v in os.environ.items() if k != "JAX_PLATFORMS"}
    environment.update(env)
    started = time.perf_counter()
    result = subprocess.run([sys.executable, "-m", "bench", "gpu"], cwd=PROJECT_ROOT,
                            env=environment, capture_output=True, text=True, timeout=120)
    return result, time.perf_counter() - started


def assert_no_gpu_line(result: subprocess.CompletedProcess, seconds: float) -> str:
    assert result.returncode == 0, result.stderr[-2000:]
    lines = [line for line in result.stdout.splitlines() if line.startswith("no GPU found: ")]
    assert len(lines) == 1, result.stdout
    line = lines[0]
    assert "jax.devices('gpu')" in line and "JAX's backends: cpu (" in line
    assert "---" not in result.stdout  # no part ran
    assert seconds < 60  # one process that imports JAX, nothing more
    return line


def test_where_jax_is_told_cpu_only_it_says_no_gpu_and_runs_nothing():
    line = assert_no_gpu_line(*bench_gpu(JAX_PLATFORMS="cpu"))
    assert "JAX_PLATFORMS=cpu is set" in line


@pytest.mark.skipif(Path("/dev/nvidia0").exists() or Path("/dev/kfd").exists(),
                    reason="a GPU is here: the benchmark would run")
def test_on_a_machine_without_a_gpu_it_says_so_and_runs_nothing():
    line = assert_no_gpu_line(*bench_gpu())
    assert "JAX_PLATFORMS" not in line and "default cpu" in line
