"""Shared fixtures: compose the real configs into a temporary output folder."""

from __future__ import annotations

import copy
import fcntl
import functools
import os
import shutil
from collections.abc import Callable
from pathlib import Path

# Before JAX starts, for this process and every pipeline process a test starts:
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")  # as the entry point (pipeline/__main__.py)
# XLA's lowest backend optimization, and its CPU backend's older emitters instead of the fusion
# emitters. The suite's programs run a few steps on tiny inputs, so compiling them is most of its
# time: the level halves it, and the older emitters compile the same programs in well under half
# the time again (a PPO training's 35: 11-14 s against 28-32 s), the same results to float
# rounding; the pipeline itself compiles at XLA's defaults. A caller's XLA_FLAGS are kept.
os.environ.setdefault("XLA_FLAGS", "--xla_backend_optimization_level=0 "
                                   "--xla_cpu_use_fusion_emitters=false")
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
    """The pipeline's composed config, writing under ``output_dir``.

    Composing takes a quarter of a second and the suite composes the same overrides hundreds of
    times, so each worker composes them once and hands out copies (``paths.output_dir`` set on
    the copy: everything under it is an interpolation, resolved when read)."""
    if any(o.lstrip("+~").startswith("paths.output_dir=") for o in overrides):
        return _compose((f"paths.output_dir={output_dir}", *overrides))
    cfg = copy.deepcopy(_composed(tuple(overrides)))
    cfg.paths.output_dir = str(output_dir)
    return cfg


def _compose(overrides: tuple[str, ...]) -> DictConfig:
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=list(overrides))


@functools.cache
def _composed(overrides: tuple[str, ...]) -> DictConfig:
    return _compose(("paths.output_dir=unset", *overrides))


def built_once(tmp_path_factory, name: str, build: Callable[[Path], None]) -> Path:
    """A folder ``build`` fills once for the whole test session, whichever worker asks first:
    the others wait for it and share it (a module fixture would build it once per worker, and
    again whenever a worker comes back to the module)."""
    root = tmp_path_factory.getbasetemp()
    if "PYTEST_XDIST_WORKER" in os.environ:
        root = root.parent  # the workers' common folder
    folder = root / f"built-{name}"
    with open(root / f"built-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not (folder / ".done").is_file():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            (folder / ".done").touch()
    return folder


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
