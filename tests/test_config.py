"""Every config composes; typos and unknown stages fail at composition with a clear message."""

from __future__ import annotations

import shutil

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from tests.conftest import CONF_DIR

GROUPS = ["robot", "exploration", "dataset", "model", "env", "agent", "logger", "paths"]


def group_options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


@pytest.mark.parametrize(
    "override",
    [f"{g}={o}" for g in GROUPS for o in group_options(g)]
    + [f"experiment={o}" for o in group_options("experiment")],
)
def test_every_config_option_composes_and_resolves(make_cfg, override):
    cfg = make_cfg(override)
    if "data_dir" in cfg.robot.keys() and OmegaConf.is_missing(cfg.robot, "data_dir"):
        cfg = make_cfg(override, "robot.data_dir=/recordings")  # import robots name their files
    resolved = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    assert resolved["paths"]["artifact_dir"].endswith("outputs/artifacts")
    assert resolved["robot"]["limits"]["p_min"] < resolved["robot"]["limits"]["p_max"]


def test_default_is_the_simulated_arm_and_whole_chain(make_cfg):
    cfg = make_cfg()
    assert cfg.robot.kind.value == "sim"
    assert cfg.stage.value == "all"


def test_unknown_stage_fails_at_composition_naming_valid_stages(make_cfg):
    with pytest.raises(ConfigCompositionException) as err:
        make_cfg("stage=fitmodel")
    message = str(err.value.__cause__ or err.value)
    assert "fitmodel" in message and "fit_model" in message


@pytest.mark.parametrize("typo", ["exploration.alpah=0.5", "robot.limits.pmax=3", "sed=1"])
def test_typo_in_an_override_fails_at_composition(make_cfg, typo):
    with pytest.raises(ConfigCompositionException) as err:
        make_cfg(typo)
    cause = err.value.__cause__
    assert isinstance(cause, OmegaConfBaseException)
    assert typo.split("=")[0].split(".")[-1] in str(cause)


@pytest.mark.parametrize("body", ["exploration:\n  alpah: 0.5\n", "robot:\n  limits:\n    pmax: 3\n"])
def test_typo_in_a_yaml_file_fails_at_composition(tmp_path, body):
    conf = tmp_path / "conf"
    shutil.copytree(CONF_DIR, conf)
    (conf / "experiment" / "typo.yaml").write_text("# @package _global_\n" + body)
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        with pytest.raises(ConfigCompositionException) as err:
            compose("config", overrides=["experiment=typo"])
    message = str(err.value)
    assert "experiment/typo" in message and body.split(":")[-2].split()[-1] in message


def test_wrong_type_fails_at_composition(make_cfg):
    with pytest.raises(ConfigCompositionException):
        make_cfg("exploration.alpha=high")


def test_experiment_quick_shrinks_the_run(make_cfg):
    default, quick = make_cfg(), make_cfg("experiment=quick")
    assert quick.exploration.num_steps < default.exploration.num_steps


def test_experiment_paper_keeps_the_papers_lstm_while_the_default_is_a_gru(make_cfg):
    default, paper = make_cfg(), make_cfg("experiment=paper")
    assert default.model.cell.value == "gru" and default.model.recurrent_dropout > 0
    assert paper.model.cell.value == "lstm" and paper.model.hidden == 1024
    assert paper.model.recurrent_dropout == 0.0
    assert not paper.model.step_size and list(paper.model.step_decays) == []
    assert list(paper.model.pressure_transients) == []


def test_the_session_spread_of_a_simulated_arm_is_part_of_its_keys(make_cfg):
    from pipeline import keys

    cfg = make_cfg()
    spec, _ = keys.collect_spec(cfg)
    assert spec["spec_version"] == keys.SPEC_VERSIONS["collect"]
    assert not spec["robot"]["physics"]["session_std"] and spec["robot"]["replay"] is None
    spread = make_cfg("+robot.physics.session_std={bend_gain:0.01}")
    assert keys.collect_spec(spread)[0]["robot"]["physics"]["session_std"] == {"bend_gain": 0.01}
    assert keys.key("collect", spread) != keys.key("collect", cfg)


def test_the_evaluate_key_follows_the_plant_the_baselines_act_in(make_cfg):
    """Without a policy the baselines' results still depend on the model (or the simulated arm)
    the environment steps: another model or robot is another evaluation."""
    from pipeline import keys

    alone = ("evaluation.policies=[]",)
    learned = make_cfg(*alone)
    assert keys.evaluate_spec(learned)[1]["fit_model"] == keys.key("fit_model", learned)
    assert keys.key("evaluate", learned) != keys.key("evaluate", make_cfg(*alone, "model.hidden=8"))
    assert keys.key("evaluate", learned) != keys.key(
        "evaluate", make_cfg(*alone, "robot.limits.p_max=6.5"))
    # with policies, the model was already in their keys: it still is, once
    spec, inputs = keys.evaluate_spec(make_cfg())
    assert inputs["fit_model"] == keys.key("fit_model", learned) and "plant" in spec
