"""The cross-model protocol: its variants, composed on top of experiment=real_arm, and its rows."""

import pytest

from experiments.cross_model import VARIANTS, variant_overrides
from pipeline.config import AgentConfig, RandomizationConfig, budget_overrides
from pipeline.keys import policy_configs

RANDOMIZED = {"gain_std": 0.05, "offset_std_kpa": 0.1, "max_delay_s": 0.25,
              "rest_offset_std_m": 0.001, "drift_std_m_per_s": 2.0e-5}
PRICE = 10.0  # experiment=real_arm's env.command_change_cost


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
    priced = variant.startswith("incremental_randomized")
    assert env.command_change_cost == (PRICE if priced else 0)


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


class _Folder:
    """An artifact's files in a folder (what measure reads of one)."""

    def __init__(self, path):
        self.path = path
        path.mkdir(parents=True)

    def file(self, name):
        return self.path / name


def test_measure_reports_the_seeds_and_the_one_control_would_deploy(tmp_path, monkeypatch):
    """Two seeds, two episodes each: seed 1 is the training's best (0.4 against 0.9 mm), so it
    is the deployed one; across models its episodes end 0.5 and 0.7 mm from the goal (median
    0.6 mm, both within 1 mm) while seed 0's end 2 and 3 mm away."""
    import pandas as pd

    from experiments import cross_model

    other, evaluated, policy = (_Folder(tmp_path / name) for name in ("other", "ev", "tp"))
    pd.DataFrame({"evaluation": [0, 0, 1, 1], "seed": [0, 1, 0, 1],
                  "median_final_distance_m": [1e-3, 2e-3, 0.9e-3, 0.4e-3]}).to_parquet(
        policy.file("evaluation.parquet"))
    cross = "model other"
    finals = {("learned", 0): [0.8, 1.0], ("learned", 1): [0.3, 0.5],
              (cross, 0): [2.0, 3.0], (cross, 1): [0.5, 0.7]}
    episodes = pd.DataFrame([
        {"plant": plant, "controller": "ppo_ff", "seed": seed, "final_distance_mm": d,
         "success_1mm": float(d <= 1.0)}
        for (plant, seed), distances in finals.items() for d in distances])
    episodes.to_parquet(evaluated.file("episodes.parquet"))
    summary = pd.DataFrame([{"plant": plant, "controller": "ppo_ff",
                             **{metric: 0.0 for metric in cross_model.METRICS}}
                            for plant in ("learned", cross)])
    summary.to_parquet(evaluated.file("summary.parquet"))
    answers = iter([{"fit_model": other}, {"evaluate": evaluated, "train_ppo": policy}])
    monkeypatch.setattr(cross_model, "run_stage", lambda *args: next(answers))

    row = cross_model.measure(tmp_path, [], ["a"], ["b"], "plain", 3)
    assert row["deployed_seed"] == 1
    assert row["own_deployed_median_final_mm"] == pytest.approx(0.4)
    assert row["cross_deployed_median_final_mm"] == pytest.approx(0.6)
    assert row["cross_deployed_success_1mm"] == 1.0
    assert row["own_seeds_median_within_1mm"] == 1.0  # medians 0.9 and 0.4 mm
    assert row["cross_seeds_median_within_1mm"] == 0.5  # medians 2.5 and 0.6 mm
