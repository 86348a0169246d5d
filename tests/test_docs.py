"""The documentation: the configuration reference covers every option, the README's commands
run or compose, and the site builds with no warning."""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import subprocess
import sys

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

from pipeline.config import PROJECT_ROOT
from tests.conftest import CONF_DIR

README = PROJECT_ROOT / "README.md"
GROUPS = sorted(p.name for p in CONF_DIR.iterdir() if p.is_dir() and p.name != "hydra")


def _reference_module():
    path = PROJECT_ROOT / "docs" / "hooks" / "config_reference.py"
    spec = importlib.util.spec_from_file_location("config_reference", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def reference() -> str:
    return _reference_module().reference_markdown()


def _settings(node: DictConfig, prefix: str = "") -> list[str]:
    """Every setting of a composed config: the leaves of its structured nodes (a plain mapping,
    such as ``robot.physics.session_std``, is one setting)."""
    keys = []
    for key in node:
        child = node._get_node(key)
        name = f"{prefix}{key}"
        structured = isinstance(child, DictConfig) and OmegaConf.get_type(child) not in (dict,
                                                                                        None)
        keys += _settings(child, f"{name}.") if structured else [name]
    return keys


def _compose(tmp_path, *overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=[f"paths.output_dir={tmp_path}", *overrides])


@pytest.mark.parametrize("override", [f"{g}={p.stem}" for g in GROUPS
                                      for p in sorted((CONF_DIR / g).glob("*.yaml"))])
def test_the_reference_lists_every_setting_of_every_option(tmp_path, reference, override):
    cfg = _compose(tmp_path, override)
    missing = [key for key in _settings(cfg) if f"`{key}`" not in reference]
    assert not missing, f"{override}: not in the configuration reference: {missing}"
    group, option = override.split("=")
    assert f"**`{group}={option}`**" in reference  # each option is listed with what it sets


def test_the_reference_gives_defaults_units_and_rules(reference):
    rows = {line.split(" | ")[0].strip("| `"): line.split(" | ")
            for line in reference.splitlines() if line.startswith("| `")}
    assert rows["agent.num_seeds"][2] == "`4`"  # the schema's default
    assert rows["robot.watchdog_s"][3] == "s"  # the unit from the name
    assert rows["robot.rating.p_max"][3] == "kPa"  # the unit from the comment
    assert "must lie in [0, 1]" in rows["exploration.alpha"][5]  # the validation rule
    assert "robot.…=… must be finite and positive" in reference  # a rule over several settings


def _readme_commands() -> list[str]:
    """The commands the README shows (in its code blocks), comments stripped."""
    blocks = re.findall(r"```bash\n(.*?)```", README.read_text(), flags=re.S)
    lines = [line.split("  #")[0].strip() for block in blocks for line in block.splitlines()]
    return [line for line in lines if line]


def test_the_readme_fits_a_screen_and_shows_its_commands():
    assert len(README.read_text().splitlines()) <= 120
    commands = _readme_commands()
    assert "make setup run" in commands and "make test" in commands
    assert all(c.startswith(("make ", "python -m pipeline")) for c in commands), commands


@pytest.mark.parametrize("command", [c for c in _readme_commands() if c.startswith("make ")])
def test_the_readmes_make_commands_exist(command):
    targets = command.split()[1:]
    result = subprocess.run(["make", "-n", *targets], cwd=PROJECT_ROOT, capture_output=True,
                            text=True)
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize("command", [c for c in _readme_commands()
                                     if c.startswith("python -m pipeline")])
def test_the_readmes_pipeline_commands_compose(tmp_path, command):
    from pipeline.cli import dry_run_flag, unknown_key_message

    overrides = dry_run_flag(shlex.split(command)[3:])
    if overrides == ["--help"]:
        result = subprocess.run([sys.executable, "-m", "pipeline", "--help"], cwd=PROJECT_ROOT,
                                capture_output=True, text=True, timeout=120)
        assert result.returncode == 0 and "stage" in result.stdout, result.stderr
        return
    assert unknown_key_message(overrides) is None
    cfg = _compose(tmp_path, *overrides)
    from pipeline.validation import validate_config

    validate_config(cfg)  # the checks the run makes before any work


def test_the_site_builds_with_no_warning(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("material")
    pytest.importorskip("mkdocstrings")
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=PROJECT_ROOT, capture_output=True, text=True, timeout=300,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert result.returncode == 0, result.stderr[-3000:]
    assert "WARNING" not in result.stderr
    page = (tmp_path / "site" / "reference" / "configuration.html").read_text()
    assert "agent.num_seeds" in page
