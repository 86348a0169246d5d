"""The cross-model protocol: its variants, composed on top of experiment=real_arm, and its rows."""

import numpy as np
import pytest

from experiments.cross_model import VARIANTS, variant_overrides
from pipeline.chain import policy_configs
from pipeline.schemas import AgentConfig, ConfigError, RandomizationConfig, budget_overrides

RANDOMIZED = {"gain_std": 0.05, "offset_std_kpa": 0.1, "max_delay_s": 0.25,
              "rest_offset_std_m": 0.001, "drift_std_m_per_s": 2.0e-5,
              "saturation_max_per_kpa": 0.0}  # real_arm's chambers do not saturate in training
PRICE = 10.0  # experiment=real_arm's env.command_change_cost_mm_per_kpa


def test_experiment_real_arm_trains_incremental_and_randomized(make_cfg):
    cfg = make_cfg("experiment=real_arm")
    assert cfg.env.action_mode == "incremental"
    assert dict(cfg.env.randomization) == pytest.approx(RANDOMIZED)
    assert list(cfg.evaluation.twins) == ["sim_sorolex"]  # evaluated on the calibrated twin too
    assert cfg.env.ensemble_seeds == 3  # in an ensemble of model seeds


@pytest.mark.parametrize("variant", VARIANTS)
def test_each_variant_sets_what_its_name_says(make_cfg, variant):
    env = make_cfg("experiment=real_arm", *variant_overrides(variant, 3)).env
    incremental = variant.startswith("incremental")
    randomized = variant in ("randomized", "both") or variant.startswith("incremental_random")
    assert env.action_mode == ("incremental" if incremental else "absolute")
    expected = RANDOMIZED if randomized else dict.fromkeys(RANDOMIZED, 0.0)
    assert dict(env.randomization) == pytest.approx(expected)
    assert set(env.randomization) == set(RandomizationConfig.__dataclass_fields__)
    assert env.ensemble_seeds == (3 if "ensemble" in variant or variant == "both" else 1)
    assert env.goal_agreement_mm == (1.0 if variant.endswith("agreed") else None)
    priced = variant.startswith("incremental_randomized")
    assert env.command_change_cost_mm_per_kpa == (PRICE if priced else 0)


def test_experiment_real_arm_trains_the_gru_twice_as_long(make_cfg):
    """One budget per policy type, whichever agent the command names; evaluate's copies of the
    other policy type (chain.policy_configs) get the same budgets as a run naming that agent."""
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


def episodes_table(finals: dict, controller: str = "ppo_ff"):
    """Episode rows as evaluate writes them, from final distances [mm] by (plant, seed)."""
    import pandas as pd

    return pd.DataFrame([
        {"plant": plant, "controller": controller, "seed": seed, "final_distance_mm": d,
         "success_1mm": float(d <= 1.0), "success_3mm": float(d <= 3.0),
         "steps_to_3mm": 1.0 if d <= 3.0 else float("inf"), "smoothness_kpa": 0.0,
         "time_above_limits": 0.0}
        for (plant, seed), distances in finals.items() for d in distances])


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
    episodes_table(finals).to_parquet(evaluated.file("episodes.parquet"))
    answers = iter([{"fit_model": other}, {"evaluate": evaluated, "train_ppo": policy}])
    monkeypatch.setattr(cross_model, "run_stage", lambda *args: next(answers))

    (row,) = cross_model.measure(tmp_path, [], ["a"], ["b"], "plain", 3)
    assert row["deployed_seed"] == 1
    assert row["own_deployed_median_final_mm"] == pytest.approx(0.4)
    assert row["cross_deployed_median_final_mm"] == pytest.approx(0.6)
    assert row["cross_deployed_success_1mm"] == 1.0
    assert row["own_seeds_median_within_1mm"] == 1.0  # medians 0.9 and 0.4 mm
    assert row["cross_seeds_median_within_1mm"] == 0.5  # medians 2.5 and 0.6 mm
    # every seed's episodes pooled: own 0.3, 0.5, 0.8, 1.0; cross 0.5, 0.7, 2, 3
    assert row["own_median_final_mm"] == pytest.approx(0.65)
    assert row["cross_median_final_mm"] == pytest.approx(1.35)
    assert row["cross_success_1mm"] == 0.5 and row["cross_success_3mm"] == 1.0


def test_across_models_counts_seeds_and_the_deployed_one_per_plant():
    """Policy seeds 0 and 1 (seed 0 deployed) and the preload, in the own and the other model:
    the policy's seed medians own 0.5 / 1.5 mm, cross 2.5 / 0.75 mm; the preload has no
    deployed seed."""
    import pandas as pd

    from pipeline.evaluation.cross_model import across_models

    policy = {("own", 0): [0.4, 0.6], ("own", 1): [1.0, 2.0],
              ("cross", 0): [2.0, 3.0], ("cross", 1): [0.5, 1.0]}
    preload = {("own", 0): [4.0, 6.0], ("cross", 0): [5.0, 9.0]}
    episodes = pd.concat([episodes_table(policy), episodes_table(preload, "preload")])
    table = across_models(episodes, {"ppo_ff": 0}).set_index(["plant", "controller"])
    own, cross = table.loc[("own", "ppo_ff")], table.loc[("cross", "ppo_ff")]
    assert own["seeds"] == 2 and own["seeds_median_within_1mm"] == 0.5
    assert cross["seeds_median_within_1mm"] == 0.5
    assert own["deployed_seed"] == 0 and own["deployed_median_final_mm"] == pytest.approx(0.5)
    assert cross["deployed_median_final_mm"] == pytest.approx(2.5)
    assert cross["deployed_success_1mm"] == 0.0
    assert cross["median_final_mm"] == pytest.approx(1.5)  # 0.5, 1, 2, 3 pooled
    baseline = table.loc[("cross", "preload")]
    assert pd.isna(baseline["deployed_seed"]) and pd.isna(baseline["deployed_median_final_mm"])
    assert baseline["median_final_mm"] == pytest.approx(7.0)


def _recordings(folder, count):
    folder.mkdir()
    for number in range(count):
        (folder / f"Step_control_{number:02d}.csv").write_text(f"t\n{number}\n")
    return folder


def test_cross_model_groups_alternate_or_follow_group_a(make_cfg, tmp_path):
    from pipeline.chain import cross_model_groups

    data = _recordings(tmp_path / "runs", 5)
    names = [f"Step_control_{n:02d}.csv" for n in range(5)]
    robot = ["robot=sorolex_csv", f"robot.data_dir={data}"]
    assert cross_model_groups(make_cfg(*robot)) == (names[0::2], names[1::2])
    chosen = make_cfg(*robot, f"evaluation.cross_model_group_a=[{names[4]},{names[3]}]")
    assert cross_model_groups(chosen) == ([names[3], names[4]], names[:3])
    assert cross_model_groups(make_cfg(*robot, "evaluation.cross_model=false")) is None
    # the simulated arm has no recordings to split: off unless asked for, then an error
    assert cross_model_groups(make_cfg()) is None
    with pytest.raises(ConfigError, match="needs recorded data"):
        cross_model_groups(make_cfg("evaluation.cross_model=true"))


def test_cross_model_needs_two_recordings_a_group_and_known_names(make_cfg, tmp_path):
    from pipeline.chain import cross_model_groups

    robot = ["robot=sorolex_csv", f"robot.data_dir={_recordings(tmp_path / 'runs', 3)}"]
    assert cross_model_groups(make_cfg(*robot)) is None  # 2 + 1: too few for B, so off
    with pytest.raises(ConfigError, match=r"at least two recordings.*group B \['Step_control_01"):
        cross_model_groups(make_cfg(*robot, "evaluation.cross_model=true"))
    with pytest.raises(ConfigError, match=r"cross_model_group_a: \['nope.csv'\] are not"):
        cross_model_groups(make_cfg(*robot, "evaluation.cross_model_group_a=[nope.csv]"))


def test_evaluate_reads_each_groups_policies_and_the_other_groups_model(make_cfg, tmp_path):
    """The evaluate key's cross-model inputs are the group configs' own train_ppo and
    fit_model keys (so the experiment script's artifacts serve it), and where the protocol does
    not run its settings do not change the key."""
    from pipeline import keys

    data = _recordings(tmp_path / "runs", 4)
    cfg = make_cfg("robot=sorolex_csv", f"robot.data_dir={data}")
    _, inputs = keys.evaluate_spec(cfg)
    group_a = make_cfg("robot=sorolex_csv", f"robot.data_dir={data}",
                       "robot.files=[Step_control_00.csv,Step_control_02.csv]")
    group_b = make_cfg("robot=sorolex_csv", f"robot.data_dir={data}",
                       "robot.files=[Step_control_01.csv,Step_control_03.csv]")
    for name, variant in policy_configs(group_a).items():
        assert inputs[f"cross_model/A->B/train_ppo/{name}"] == keys.key("train_ppo", variant)
    assert inputs["cross_model/A->B/fit_model"] == keys.key("fit_model", group_b)
    assert inputs["cross_model/B->A/fit_model"] == keys.key("fit_model", group_a)
    off = keys.evaluate_spec(make_cfg("robot=sorolex_csv", f"robot.data_dir={data}",
                                      "evaluation.cross_model=false"))
    assert not any(name.startswith("cross_model/") for name in off[1])
    assert keys.key("evaluate", make_cfg()) == keys.key(
        "evaluate", make_cfg("evaluation.cross_model=false"))


@pytest.mark.slow  # three groups' models and policies, shrunk: runs with `make test-all`
def test_evaluate_runs_the_cross_model_protocol_on_recorded_runs(make_cfg, sorolex_dir):
    """Four recorded runs, everything shrunk: each group gets its own model and policies, and
    evaluate rolls them out in their own model and in the other group's; the policies of all
    runs also run on the calibrated twin."""
    import pandas as pd

    from pipeline.__main__ import run
    from pipeline.data.schemas import ALIGNED, read_table
    from pipeline.infra.artifacts import ArtifactStore
    from pipeline.rl.policy_io import best_seed

    files = sorted(p.name for p in sorolex_dir.glob("Step_control_*.csv"))[:4]
    cfg = make_cfg("experiment=quick", "robot=sorolex_csv", f"robot.data_dir={sorolex_dir}",
                   "robot.num_runs=null", f"robot.files=[{','.join(files)}]", "stage=evaluate",
                   "evaluation.policies=[ppo_ff]", "evaluation.baselines=[preload]",
                   "agent.num_seeds=2", "agent.total_timesteps=2048", "agent.num_envs=16",
                   "agent.num_steps=8", "agent.num_evals=1", "agent.eval_envs=4",
                   "model.num_steps=20", "model.eval_every=10", "model.checkpoint_every=10",
                   "dataset.window=32", "evaluation.num_episodes=4",
                   "evaluation.consecutive_episodes=1", "evaluation.twins=[sim_sorolex]")
    evaluated = run(cfg)["evaluate"]
    summary = pd.read_parquet(evaluated.file("summary.parquet"))
    on_twin = summary[summary["plant"] == "twin sim_sorolex"]
    assert set(on_twin["controller"]) == {"ppo_ff", "preload"}
    assert np.isfinite(on_twin["median_final_mm"]).all()
    assert (on_twin["time_above_limits"] == 0).all()
    # the goals the twin can hold, and each controller's success on those (evaluation.reach:
    # the twins by default, not the learned model)
    assert ((on_twin["reachable_goals"] >= 0) & (on_twin["reachable_goals"] <= 1)).all()
    assert summary.loc[summary["plant"] == "learned", "reachable_goals"].isna().all()
    table = pd.read_parquet(evaluated.file("cross_model.parquet"))
    assert set(table["direction"]) == {"A->B", "B->A"}
    assert set(zip(table["plant"], table["controller"])) == {
        (plant, controller) for plant in ("own", "cross") for controller in ("ppo_ff", "preload")}
    a_to_b = table[table["direction"] == "A->B"]
    assert set(a_to_b["train_runs"]) == {"+".join(files[0::2])}
    assert set(a_to_b["test_runs"]) == {"+".join(files[1::2])}
    assert (table["episodes"] == 4 * table["seeds"]).all()
    assert np.isfinite(table["median_final_mm"]).all()

    store = ArtifactStore(cfg.paths.artifact_dir)
    inputs = evaluated.manifest["inputs"]
    policy = store.require("train_ppo", inputs["cross_model/A->B/train_ppo/ppo_ff"])
    deployed = a_to_b[a_to_b["controller"] == "ppo_ff"]["deployed_seed"]
    evaluation = policy.file("evaluation.parquet")
    assert set(deployed) == {best_seed(pd.read_parquet(evaluation), evaluation)}
    # the model the A policies meet was fitted to B's runs alone
    other = store.require("fit_model", inputs["cross_model/A->B/fit_model"])
    aligned, _ = read_table(store.require("align", other.manifest["inputs"]["align"])
                            .file("aligned.parquet"), ALIGNED)
    assert sorted(aligned["run_id"].unique()) == [name.removesuffix(".csv")
                                                 for name in files[1::2]]
    assert "cross_model/B->A/ppo_ff" in evaluated.manifest["summary"]
    report = evaluated.file("report.md").read_text()
    assert "## Across models" in report and "**Calibrated twins** (sim_sorolex)" in report


def test_the_cross_model_policies_train_with_the_protocols_own_budget(make_cfg, tmp_path):
    from pipeline import keys
    from pipeline.chain import cross_model_folds
    from pipeline.validation import validate_config

    robot = ["robot=sorolex_csv", f"robot.data_dir={_recordings(tmp_path / 'runs', 4)}",
             "agent.num_seeds=20", "agent.total_timesteps=2000000",
             "agent.recurrent_total_timesteps=4000000"]
    same = cross_model_folds(make_cfg(*robot))["A->B"][0]
    assert same.agent.num_seeds == 20 and same.agent.total_timesteps == 2_000_000
    own = cross_model_folds(make_cfg(*robot, "evaluation.cross_model_seeds=4",
                                     "evaluation.cross_model_budget=0.25"))
    for train, _ in own.values():
        assert train.agent.num_seeds == 4
        assert train.agent.total_timesteps == 500_000
        assert train.agent.recurrent_total_timesteps == 1_000_000
        assert keys.key("train_ppo", train) != keys.key("train_ppo", same)
    with pytest.raises(ConfigError, match=r"evaluation\.cross_model_budget=0\.0"):
        validate_config(make_cfg(*robot, "evaluation.cross_model_budget=0"))
    with pytest.raises(ConfigError, match=r"evaluation\.cross_model_seeds=0"):
        validate_config(make_cfg(*robot, "evaluation.cross_model_seeds=0"))
