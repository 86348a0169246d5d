"""Shared fixtures: compose the real configs into a temporary output folder."""

from __future__ import annotations

import os
from pathlib import Path

# Before JAX starts, for this process and every pipeline process a test starts:
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")  # as the entry point (pipeline/__main__.py)
# XLA's lowest backend optimization. The suite's programs run a few steps on tiny inputs, so
# compiling them is most of its time, and at this level it takes about half as long (the same
# programs and results to float rounding; the pipeline itself compiles at XLA's default). A
# caller's own XLA_FLAGS are kept as they are.
os.environ.setdefault("XLA_FLAGS", "--xla_backend_optimization_level=0")
# One CPU device per test worker and pipeline process (the workers already use every core); the
# split over several devices has its own tests (test_devices.py), in processes of their own.
os.environ.setdefault("JAX_NUM_CPU_DEVICES", "1")

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from pipeline.config import PROJECT_ROOT, register_configs
from pipeline.infra.compile_cache import use_compilation_cache

CONF_DIR = PROJECT_ROOT / "conf"
SOROLEX_DIR = Path(os.environ.get("SOROLEX_DIR", PROJECT_ROOT.parent / "shared/data/sorolex"))

register_configs()
# One compilation cache for every test worker and every pipeline process a test starts.
os.environ.setdefault("SOROLEARN_COMPILE_CACHE", str(PROJECT_ROOT / "outputs" / "jax_cache"))
use_compilation_cache(os.environ["SOROLEARN_COMPILE_CACHE"])


def compose_config(output_dir: Path | str, *overrides: str) -> DictConfig:
    """The pipeline's composed config, writing under ``output_dir``."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=[f"paths.output_dir={output_dir}", *overrides])


@pytest.fixture
def make_cfg(tmp_path):
    def make(*overrides: str) -> DictConfig:
        return compose_config(tmp_path / "outputs", *overrides)

    return make


@pytest.fixture(scope="session")
def sorolex_dir() -> Path:
    if not sorted(SOROLEX_DIR.glob("Step_control_*.csv")):
        pytest.skip(f"real-arm data not found at {SOROLEX_DIR} (set SOROLEX_DIR)")
    return SOROLEX_DIR


_domains = iter(range(100))


@pytest.fixture
def ros_domain() -> int:
    """A ROS_DOMAIN_ID no other test of this session uses (per xdist worker: 20 ids); without
    xdist the caller's ROS_DOMAIN_ID where set (tests then run one after another)."""
    if "ROS_DOMAIN_ID" in os.environ and "PYTEST_XDIST_WORKER" not in os.environ:
        return int(os.environ["ROS_DOMAIN_ID"])
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
    return 20 + (20 * worker) % 80 + next(_domains) % 20
