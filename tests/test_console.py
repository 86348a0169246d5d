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


# ---------------------------------------------------------------------------------------------
# the closing summary
# ---------------------------------------------------------------------------------------------
def _evaluate_artifact(folder):
    """An evaluate artifact's two tables, by hand: ppo_ff (2 seeds x 2 episodes) and the
    preload (1 seed x 2 episodes) on the learned model, with a column the summary does not read."""
    import pandas as pd

    folder.mkdir(parents=True)
    pd.DataFrame({
        "plant": ["learned", "learned"], "controller": ["ppo_ff", "preload"],
        "episodes": [4, 2], "median_final_mm": [0.604, 9.3], "success_1mm": [0.75, 0.0],
        "success_3mm": [1.0, 0.0], "hold_new_column": [1.0, 2.0]}).to_parquet(
        folder / "summary.parquet")
    pd.DataFrame({"plant": ["learned"] * 6, "controller": ["ppo_ff"] * 4 + ["preload"] * 2,
                  "seed": [0, 0, 1, 1, 0, 0], "episode": [0, 1, 0, 1, 0, 1]}).to_parquet(
        folder / "episodes.parquet")
    return folder


def test_evaluation_table_reads_columns_by_name(tmp_path):
    from pipeline.evaluation.summary import WITHIN, read_evaluation_table

    table = read_evaluation_table(_evaluate_artifact(tmp_path / "evaluate"))
    assert table["controller"].tolist() == ["ppo_ff", "preload"]
    assert table["median_final_mm"].tolist() == [0.604, 9.3]
    assert table[WITHIN].tolist() == [75, 0]  # 0.75 of the episodes within 1 mm
    assert table["seeds"].tolist() == [2, 1]  # seeds counted in episodes.parquet
    assert table["episodes"].tolist() == [4, 2]


def test_text_table_aligns_numbers_right_and_text_left():
    import pandas as pd

    from pipeline.evaluation.summary import text_table

    lines = text_table(pd.DataFrame({"controller": ["ppo_ff", "mpc"], "median_mm": [0.6038, 12.5],
                                     "seeds": [20, 1]}))
    assert lines == ["controller  median_mm  seeds",
                     "----------  ---------  -----",
                     "ppo_ff          0.604     20",
                     "mpc              12.5      1"]


def test_model_table_puts_the_model_before_its_baselines():
    from pipeline.evaluation.summary import model_table

    table = model_table({"protocol": "cv", "learned_mean_mm": 2.72, "learned_p95_mm": 6.17,
                         "mean_position_mean_mm": 7.8, "mean_position_p95_mm": 13.9,
                         "linear_lagged_mean_mm": 4.0, "linear_lagged_p95_mm": 8.1,
                         "train_runs_mean_mm": 1.2,
                         "session_context_mm": {"0": 2.72, "30": 2.9}})  # not a model
    assert table["model"].tolist() == ["learned", "linear_lagged", "mean_position"]
    assert table["mean_mm"].tolist() == [2.72, 4.0, 7.8]


def test_goals_from_data_are_quantiles_of_the_recorded_positions(tmp_path):
    import pandas as pd

    from pipeline.evaluation.summary import goals_from_data

    (tmp_path / "align").mkdir()
    pd.DataFrame({"x": [0.010, 0.020, 0.030], "y": [0.3, 0.3, 0.3],
                  "z": [0.2, 0.1, None]}).to_parquet(tmp_path / "align" / "aligned.parquet")
    # rows with a missing value are left out: x 10, 20 mm, z 200, 100 mm
    assert goals_from_data(tmp_path / "align", (0.0, 0.5)) == "[[10.0,300.0,100.0],[15.0,300.0,150.0]]"
    assert goals_from_data(tmp_path / "missing") is None


def test_closing_summary_of_the_chain(tmp_path, make_cfg, monkeypatch):
    import json
    from types import SimpleNamespace

    import pandas as pd

    from pipeline.__main__ import run_facts
    from pipeline.evaluation.summary import closing_summary

    monkeypatch.chdir(tmp_path)
    evaluate = _evaluate_artifact(tmp_path / "artifacts" / "evaluate" / "abc")
    (evaluate / "report.html").write_text("<html></html>")
    fit = tmp_path / "artifacts" / "fit_model" / "def"
    fit.mkdir(parents=True)
    (fit / "artifact.json").write_text(json.dumps({"summary": {
        "protocol": "split", "test_runs": ["sim-001"], "learned_mean_mm": 1.75,
        "learned_p95_mm": 4.16, "linear_lagged_mean_mm": 4.84, "linear_lagged_p95_mm": 6.76}}))
    align = tmp_path / "artifacts" / "align" / "ghi"
    align.mkdir(parents=True)
    pd.DataFrame({"x": [0.03], "y": [0.35], "z": [0.2]}).to_parquet(align / "aligned.parquet")
    results = {"align": SimpleNamespace(path=align), "fit_model": SimpleNamespace(path=fit),
               "evaluate": SimpleNamespace(path=evaluate)}
    lines = closing_summary("all", results, run_facts(make_cfg()),
                            ["experiment=quick", "force=true"])
    text = "\n".join(lines)
    assert "held-out runs sim-001" in text
    assert "learned           1.75    4.16" in text
    assert "ppo_ff      learned            0.604            75      2         4" in text
    assert f"artifact: {evaluate.relative_to(tmp_path)}" in text
    assert f"report:   {evaluate.relative_to(tmp_path)}/report.html" in text
    # the next command keeps the run's overrides, not its stage or force
    assert ("next:     python -m pipeline stage=control experiment=quick control.policy=apg "
            "'control.goals=[[30.0,350.0,200.0],[30.0,350.0,200.0],[30.0,350.0,200.0]]'") in text
    assert len(lines) < 25  # read in ten seconds


@pytest.mark.parametrize("rate, shown", [(0.75, "75"), (None, "–")])
def test_closing_summary_of_a_training_with_or_without_goals(tmp_path, make_cfg, rate, shown):
    """train_ppo alone: its own final evaluation, the share within 1 mm only where the env has
    goals (a gymnax env has none: its summary holds None)."""
    import json
    from types import SimpleNamespace

    from pipeline.__main__ import run_facts
    from pipeline.evaluation.summary import closing_summary

    train = tmp_path / "artifacts" / "train_ppo" / "abc"
    train.mkdir(parents=True)
    (train / "artifact.json").write_text(json.dumps({"summary": {
        "agent": "ppo_ff", "env": "Pendulum-v1", "num_seeds": 2, "timesteps_per_seed": 64,
        "final_eval_median_distance_mm": None, "final_eval_success_rate": rate}}))
    lines = closing_summary("train_ppo", {"train_ppo": SimpleNamespace(path=train)},
                            run_facts(make_cfg()), [])
    row = next(line for line in lines if line.startswith("ppo_ff"))
    assert row.split()[:5] == ["ppo_ff", "Pendulum-v1", "2", "64", "–"]
    assert row.split()[-1] == shown


def test_the_report_opens_with_the_summary_table(tmp_path):
    import pandas as pd

    from pipeline.evaluation.report import Section, write_report
    from pipeline.evaluation.sections import headline_section

    folder = _evaluate_artifact(tmp_path / "evaluate")
    tables = {name: pd.read_parquet(folder / f"{name}.parquet")
              for name in ("summary", "episodes")}
    markdown, page = write_report(folder, "run", [headline_section(tables),
                                                  Section("Results").add("text")])
    text = markdown.read_text()
    assert text.index("## Summary") < text.index("## Results")
    assert "| ppo_ff | learned | 0.604 | 75 | 2 | 4 |" in text
    assert "<h2 id=\"s0\">Summary</h2>" in page.read_text()


# ---------------------------------------------------------------------------------------------
# XLA's C++ log on warm runs
# ---------------------------------------------------------------------------------------------
XLA_NOISE = ("cpu_aot_loader.cc", "pjrt_executable.cc")


@pytest.mark.slow  # three pipeline processes
def test_a_warm_run_prints_no_xla_machine_type_errors(tmp_path):
    """Programs loaded from the compilation cache: no ``E... cpu_aot_loader.cc`` lines (spurious
    on AVX-512 CPUs) under the entry point, although the log level is set by the environment
    (conftest), as for a user's run."""
    import os
    import subprocess
    import sys

    from pipeline.config import PROJECT_ROOT

    command = [sys.executable, "-m", "pipeline", "stage=collect", "experiment=quick",
               "robot.num_runs=1", "exploration.num_steps=10", f"paths.output_dir={tmp_path}",
               f"paths.compile_cache_dir={tmp_path / 'cache'}", "force=true"]

    def stderr(**env: str) -> str:
        result = subprocess.run(command, cwd=PROJECT_ROOT, capture_output=True, text=True,
                                timeout=300, env={**os.environ, **env})
        assert result.returncode == 0, result.stderr[-2000:]
        return result.stderr

    stderr()  # compiles, fills the cache
    warm = stderr()
    assert not [line for line in warm.splitlines() if any(n in line for n in XLA_NOISE)]
    if not any(n in stderr(TF_CPP_MIN_LOG_LEVEL="0") for n in XLA_NOISE):
        pytest.skip("this CPU logs no machine-type error on a cache load: nothing was hidden")


def test_the_next_command_follows_the_stage_and_the_robot(tmp_path, make_cfg):
    from types import SimpleNamespace

    from pipeline.__main__ import run_facts
    from pipeline.evaluation.summary import next_step

    assert next_step("fit_model", {}, run_facts(make_cfg()),
                     ["model.hidden=32", "stage=fit_model"]) == [
        "python -m pipeline stage=train_ppo model.hidden=32"]
    assert next_step("train_ppo", {}, run_facts(make_cfg()), [])[0].startswith(
        "python -m pipeline stage=evaluate    #")
    # a policy for a ROS 2 arm is rehearsed on the twin first, named by its file
    policy = SimpleNamespace(path=tmp_path / "train_ppo" / "abc")
    steps = next_step("evaluate", {"train_ppo": policy}, run_facts(make_cfg("robot=ros2")), [])
    assert steps[0].startswith("python -m pipeline stage=twin robot=ros2")
    assert steps[1].startswith("python -m pipeline stage=control robot=ros2 robot.rehearsal=true "
                               f"control.policy_file={policy.path / 'policy.msgpack'}")
    assert next_step("guard", {}, run_facts(make_cfg("robot=ros2")), []) == []
