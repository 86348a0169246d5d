"""What the evaluation reads of artifacts, loaded by the stage: records, the deployed seed, the
closed-loop settings without plants, the report's opening table."""

from __future__ import annotations

import math

import pandas as pd
import pytest

from pipeline.infra.artifacts import ArtifactStore, produce
from pipeline.infra.records import artifact_record


def test_a_record_holds_the_summary_the_figures_there_and_the_tables(tmp_path):
    store = ArtifactStore(tmp_path / "artifacts")

    def build(writer):
        writer.file("figures").mkdir()
        writer.file("figures/loss.png").write_bytes(b"png")
        pd.DataFrame({"run_id": ["a", "b"], "mean_mm": [0.5, 1.5]}).to_parquet(
            writer.file("metrics.parquet"))
        writer.summary = {"learned_mean_mm": 0.5}

    artifact = produce(store, "fit_model", {"hidden": 8}, {}, build)
    record = artifact_record(artifact, figures=("loss.png", "reconstruction.png"),
                             tables=("metrics",))
    assert (record.stage, record.key, record.path) == ("fit_model", artifact.key, artifact.path)
    assert record.summary == {"learned_mean_mm": 0.5}
    assert record.build_seconds is not None and record.build_seconds >= 0
    # only the figures it holds, by file name
    assert record.figures == {"loss.png": artifact.path / "figures" / "loss.png"}
    assert record.tables["metrics"]["mean_mm"].tolist() == [0.5, 1.5]
    with pytest.raises(FileNotFoundError):  # a table asked for must be there
        artifact_record(artifact, tables=("evaluation",))


def test_the_deployed_seed_is_the_best_in_the_last_evaluation():
    """Seed 0 was best in the first evaluation (1 mm against 2), seed 1 in the last (0.4 mm
    against 0.9): seed 1. Without a finite median the error names the table's source."""
    from pipeline.rl.policy_io import best_seed

    table = pd.DataFrame({"evaluation": [1, 0, 1, 0], "seed": [0, 0, 1, 1],
                          "median_final_distance_m": [0.9e-3, 1e-3, 0.4e-3, 2e-3]})
    assert best_seed(table, "p/evaluation.parquet") == 1
    with pytest.raises(ValueError, match=r"^p/evaluation.parquet: no finite held-out median"):
        best_seed(table.assign(median_final_distance_m=math.nan), "p/evaluation.parquet")


def test_in_models_only_keeps_the_preload_and_drops_plant_and_consecutive_goals():
    from pipeline.evaluation.closed_loop import ClosedLoopSettings, SimArm
    from pipeline.schemas import EnvConfig, EvaluationConfig

    settings = ClosedLoopSettings(
        evaluation=EvaluationConfig(models=["m"], num_episodes=7), max_steps=40, model_hz=10.0,
        limits=None, env=EnvConfig(),
        sim=SimArm(plant=None, mocap_hz=100.0, rest_pose_std_m=[0.002, 0.0, 0.0]))
    only = settings.only_in_models()
    assert only.sim is None and only.evaluation.baselines == ["preload"]
    assert not only.evaluation.plant and only.evaluation.num_consecutive_goals == 0
    assert only.evaluation.models == [] and only.evaluation.num_episodes == 7
    # the settings it came from are left as they were
    assert settings.sim is not None and settings.evaluation.baselines == [
        "preload", "random", "mpc"]


def test_the_opening_table_counts_seeds_and_adds_the_other_models_rows():
    """ppo_ff: 2 seeds of 2 episodes (3 of 4 within 1 mm: 75 %); across models its row in the
    other group's model is added, the one in its own model is not."""
    from pipeline.evaluation.metrics import CROSS, OWN
    from pipeline.evaluation.summary import WITHIN, evaluation_table

    summary = pd.DataFrame({"plant": ["learned"], "controller": ["ppo_ff"], "episodes": [4],
                            "median_final_mm": [0.6], "success_1mm": [0.75]})
    episodes = pd.DataFrame({"plant": ["learned"] * 4, "controller": ["ppo_ff"] * 4,
                             "seed": [0, 0, 1, 1]})
    cross = pd.DataFrame({"direction": ["A->B", "A->B"], "plant": [OWN, CROSS],
                          "controller": ["ppo_ff", "ppo_ff"], "median_final_mm": [0.5, 2.5],
                          "success_1mm": [0.8, 0.25], "seeds": [2, 2], "episodes": [4, 4]})
    table = evaluation_table(summary, episodes, cross)
    assert table["plant"].tolist() == ["learned", "model of runs A->B"]
    assert table[WITHIN].tolist() == [75, 25]
    assert table["seeds"].tolist() == [2, 2]
    assert evaluation_table(summary)["seeds"].tolist() == [1]  # no episodes: one seed
