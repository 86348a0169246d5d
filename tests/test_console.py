"""What a user reads in the terminal: no warning from the project's own configuration, and the
closing summary of every stage and chain."""

from __future__ import annotations

import warnings

import pytest
from hydra import compose, initialize_config_dir

from tests.conftest import CONF_DIR

GROUPS = sorted(p.name for p in CONF_DIR.iterdir() if p.is_dir() and p.name != "hydra")


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


@pytest.mark.parametrize("override", [f"{g}={o}" for g in GROUPS for o in _options(g)]
                         + [f"hydra/launcher={o}" for o in _options("hydra/launcher")])
def test_every_option_composes_without_a_warning(tmp_path, override):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a deprecation of Hydra's, say, fails here
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose("config", overrides=[f"paths.output_dir={tmp_path}", override],
                          return_hydra_config=True)
    group, option = override.split("=")
    assert cfg.hydra.runtime.choices[group] == option
