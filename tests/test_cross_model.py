"""The cross-model protocol's variants, composed on top of experiment=real_arm."""

import pytest

from experiments.cross_model import VARIANTS, variant_overrides
from pipeline.config import RandomizationConfig

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
    randomized = variant in ("randomized", "both", "incremental_randomized")
    assert env.action_mode == ("incremental" if incremental else "absolute")
    expected = RANDOMIZED if randomized else dict.fromkeys(RANDOMIZED, 0.0)
    assert dict(env.randomization) == pytest.approx(expected)
    assert set(env.randomization) == set(RandomizationConfig.__dataclass_fields__)
    assert env.ensemble_seeds == (3 if variant in ("ensemble", "both") else 1)
