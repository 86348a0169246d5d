"""The cross-model protocol's variants, composed on top of experiment=real_arm."""

import pytest

from experiments.cross_model import VARIANTS, variant_overrides
from pipeline.config import AgentConfig, RandomizationConfig, budget_overrides
from pipeline.keys import policy_configs

RANDOMIZED = {"gain_std": 0.05, "offset_std_kpa": 0.1, "max_delay_s": 0.25,
              "rest_offset_std_m": 0.001, "drift_std_m_per_s": 2.0e-5}


def test_experiment_real_arm_trains_incremental_and_randomized(make_cfg):
    env = make_cfg("experiment=real_arm").env
    assert env.action_mode == "incremental"
    assert dict(env.randomization) == pytest.approx(RANDOMIZED)


@pytest.mark.parametrize("variant", VARIANTS)
def test_each_variant_sets_what_its_name_says(make_cfg, variant):
    env = make_cfg("experiment=real_arm", *variant_overrides(variant, 3)).env
    incremental = variant.startswith("incremental")
    randomized = variant in ("randomized", "both", "incremental_randomized",
                             "incremental_randomized_ensemble")
    assert env.action_mode == ("incremental" if incremental else "absolute")
    expected = RANDOMIZED if randomized else dict.fromkeys(RANDOMIZED, 0.0)
    assert dict(env.randomization) == pytest.approx(expected)
    assert set(env.randomization) == set(RandomizationConfig.__dataclass_fields__)
    assert env.ensemble_seeds == (3 if variant.endswith("ensemble") or variant == "both" else 1)


def test_experiment_real_arm_trains_the_gru_twice_as_long(make_cfg):
    """One budget per policy type, whichever agent the command names; evaluate's copies of the
    other policy type (keys.policy_configs) get the same budgets as a run naming that agent."""
    for named in ("ppo_ff", "ppo_rnn"):
        cfg = make_cfg("experiment=real_arm", f"agent={named}")
        variants = {named: cfg, **policy_configs(cfg)}
        assert set(variants) == {"ppo_ff", "ppo_rnn"}
        for name, variant in variants.items():
            agent = AgentConfig.from_any(variant.agent)
            assert (agent.name, agent.recurrent) == (name, name == "ppo_rnn")
            assert agent.timesteps == (4_000_000 if agent.recurrent else 2_000_000)
            # 64 envs x 32 steps per update, 10 evaluations: 1950 and 970 updates
            assert agent.num_updates == (1950 if agent.recurrent else 970)
    # a budget given for both (as cross_model --ppo-steps does) reaches the GRU too
    cfg = make_cfg("experiment=real_arm", "agent=ppo_rnn", *budget_overrides(65536))
    assert AgentConfig.from_any(cfg.agent).timesteps == 65536
